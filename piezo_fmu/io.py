"""File output that never leaves a half-written file where a good one stood.

:func:`atomic_writer` writes to a temporary file beside the target and renames it into place
only when the block finishes without an exception (including ``KeyboardInterrupt``); an existing
target is refused unless ``force`` is given.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from .errors import UserError

__all__ = ["atomic_writer", "check_writable", "write_text"]


def check_writable(path, force=False):
    """Raise :class:`UserError` if ``path`` exists and ``force`` is false, or its folder is missing."""
    path = Path(path)
    if path.exists() and not force:
        raise UserError(f"{path}: exists; not overwritten (use --force to replace it)")
    if path.is_dir():
        raise UserError(f"{path}: is a directory")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.exists():
        raise UserError(f"{parent}: folder does not exist (create it first)")


@contextlib.contextmanager
def atomic_writer(path, mode="w", force=False, newline=None):
    """Context manager yielding a file object; the target appears only on success."""
    path = Path(path)
    check_writable(path, force)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent or ".")
    try:
        os.chmod(tmp, 0o666 & ~_umask())          # mkstemp makes 0600; give the usual permissions
        with os.fdopen(fd, mode, newline=newline) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text(path, text, force=False):
    with atomic_writer(path, "w", force=force) as fh:
        fh.write(text)
