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


class ParameterError(InputError, ValueError):
    """A parameter value a method refuses (NaN, infinite, out of range).

    Also a ``ValueError``, so callers that caught the ``ValueError`` the core
    dataclasses used to raise keep working.
    """


class OutputError(SylvaError):
    """An output cannot be written where asked (it would overwrite an input, wrong extension,
    read-only or full disk, a folder another run holds); the message names the path."""


class DamagedInputError(InputError):
    """An input file is damaged: truncated, zeroed, a header that disagrees with its points."""


def disk_error(path, err: OSError) -> "OutputError":
    """One line for an OSError met while writing ``path`` (full disk, read-only, permissions)."""
    import errno

    reason = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is exceeded",
              errno.EROFS: "the file system is read-only", errno.EACCES: "permission denied",
              errno.EPERM: "permission denied"}.get(err.errno, err.strerror or str(err))
    return OutputError(f"{path}: cannot write ({reason}); nothing was left half-written")
