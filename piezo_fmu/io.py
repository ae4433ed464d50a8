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

__all__ = ["atomic_writer", "check_out_dir", "check_writable", "write_text"]


def _probe(folder: Path, what: Path):
    """Raise :class:`UserError` naming ``what`` unless a file can be created in ``folder``."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=".piezo-fmu-probe-", dir=folder)
    except OSError as exc:
        raise UserError(f"{what}: cannot write there ({exc.strerror or exc})") from None
    os.close(fd)
    os.unlink(tmp)


def check_writable(path, force=False):
    """Raise :class:`UserError` (one line naming ``path``) unless ``path`` can be written: it
    exists and ``force`` is false, it is a folder, its folder is missing, or nothing can be created
    there. Call it before any work, so a long run never ends in an error it could have foreseen."""
    path = Path(path)
    if path.exists() and not force:
        raise UserError(f"{path}: exists; not overwritten (use --force to replace it)")
    if path.is_dir():
        raise UserError(f"{path}: is a directory")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.exists():
        raise UserError(f"{parent}: folder does not exist (create it first)")
    if not parent.is_dir():
        raise UserError(f"{parent}: is not a folder")
    _probe(parent, path)


def check_out_dir(path, force=False, outputs=()) -> Path:
    """Create the output folder ``path`` if needed and make sure files can be written in it.

    ``outputs``: names of files the command will write there; one that exists is refused unless
    ``force``. Raises :class:`UserError` with one line naming the folder or file. Returns the path.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UserError(f"{path}: exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{path}: cannot create the output folder ({exc.strerror or exc})") from None
    _probe(path, path)
    if not force:
        for name in outputs:
            if (path / name).exists():
                raise UserError(f"{path / name}: exists; not overwritten (use --force to replace it)")
    return path


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
