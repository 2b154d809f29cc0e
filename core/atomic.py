"""Write files so that a failure or a cancel never leaves a half-written output behind.

Everything is written under a temporary name in the destination folder and
moved into place with ``os.replace`` (atomic on one file system) only when
complete; on any exception the temporary file is removed.  New files get
the usual permissions (0666 minus the umask), not mkstemp's 0600.
"""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

from .errors import InputError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def temporary_beside(path: Path) -> Path:
    """A new empty temporary file in ``path``'s folder, named after it (for :func:`move_into_place`)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=str(path.parent))
    os.close(fd)
    return Path(tmp)


def move_into_place(tmp: Path, path: Path) -> None:
    """Give the complete temporary file ``tmp`` the usual permissions and move it to ``path``."""
    os.chmod(tmp, 0o666 & ~_umask())
    os.replace(tmp, path)


@contextmanager
def atomic_path(path):
    """``with atomic_path(out) as tmp:`` write ``tmp`` (a Path); it becomes ``out`` on success."""
    path = Path(path)
    if not path.parent.is_dir():
        raise InputError(f"{path}: the output folder {path.parent} does not exist")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a file name")
    tmp = temporary_beside(path)
    try:
        yield tmp
        move_into_place(tmp, path)
    except BaseException:
        if tmp.exists():
            tmp.unlink()
        raise


@contextmanager
def atomic_open(path, mode: str = "wb"):
    """``with atomic_open(out) as fh:`` write a stream; it becomes ``out`` on success."""
    with atomic_path(path) as tmp:
        with open(tmp, mode) as fh:
            yield fh


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_open(path) as fh:
        fh.write(data)
    return Path(path)


def atomic_save_npz(path, **arrays) -> Path:
    """``np.savez`` to ``path`` atomically.  The archive is built in memory first: numpy's zip writer,
    failing half-way (a full disk), would leave a zip object whose clean-up prints a traceback."""
    import io

    import numpy as np

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return atomic_write_bytes(path, buf.getvalue())
