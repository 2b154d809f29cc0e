"""One family of exceptions, with messages a forester understands.

Every error a user can cause (a missing file, a tile without CRS, a tile in
feet where metres were expected, an empty tile, a cancelled run) is a
:class:`SylvaError`.  The front ends (CLI, Processing) print its message and
never a traceback; anything that is *not* a SylvaError is a bug.
"""


class SylvaError(Exception):
    """Base class of every error Sylva raises on purpose."""


class InputError(SylvaError):
    """An input file or parameter is unusable; the message names it and says why."""


class CRSError(InputError):
    """A coordinate reference system is missing, unknown or unsuitable."""


class EmptyInputError(InputError):
    """An input holds no usable points (or no points of a needed class)."""


class Cancelled(SylvaError):
    """The user cancelled the run; nothing half-written is left behind."""

    def __init__(self, message: str = "cancelled by the user"):
        super().__init__(message)
