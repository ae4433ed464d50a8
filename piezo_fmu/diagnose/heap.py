"""Freed memory kept for reuse while diagnose runs.

diagnose's fits allocate and free arrays of a recording's length (and Jacobians of several of
them) tens of thousands of times. With glibc's defaults a block above the mmap threshold (dynamic,
at most 32 MiB) is mapped for each allocation and unmapped when freed, and the heap is trimmed
whenever 128 KiB lie free at its top: every new array then faults its pages in again. rig-136
(125 000 samples, two channels) took 2.0 million page faults and 13 s of system time in a 56 s
diagnosis (2026-11-28, 2-core VM); with the thresholds below 0.11 million and 3 s, 40 s in all, at
1.9 GB peak resident memory instead of 1.1.

:func:`kept` raises glibc's mmap threshold, trim threshold and top pad (``mallopt``) for the
duration; afterwards it gives the free memory back (``malloc_trim``) and sets the three to glibc's
documented defaults (which leaves the dynamic mmap threshold off: the process keeps fixed
thresholds). Nested and concurrent uses count: the defaults come back when the last one ends.
Without glibc's ``mallopt`` (musl, macOS, Windows) it does nothing.
"""
from __future__ import annotations

import ctypes
import threading
from contextlib import contextmanager

__all__ = ["KEPT", "kept"]

_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
# [bytes] while diagnose runs: blocks up to 256 MiB from the heap, up to 1 GiB free at its top
# kept, the heap grown 256 MiB at a time
KEPT = {_M_MMAP_THRESHOLD: 256 << 20, _M_TRIM_THRESHOLD: 1 << 30, _M_TOP_PAD: 256 << 20}
# glibc's documented defaults (mallopt(3)): what the three are set back to
_DEFAULTS = {_M_MMAP_THRESHOLD: 128 << 10, _M_TRIM_THRESHOLD: 128 << 10, _M_TOP_PAD: 128 << 10}

_lock = threading.Lock()
_depth = 0


def _libc():
    try:
        lib = ctypes.CDLL(None)
    except OSError:
        return None
    if not (hasattr(lib, "mallopt") and hasattr(lib, "malloc_trim")):
        return None
    lib.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    lib.malloc_trim.argtypes = [ctypes.c_size_t]
    return lib


def _set(lib, values):
    for param, value in values.items():
        lib.mallopt(param, value)


@contextmanager
def kept():
    """Run the block with freed memory kept for reuse (see the module docstring)."""
    global _depth
    lib = _libc()
    if lib is None:
        yield
        return
    with _lock:
        if _depth == 0:
            _set(lib, KEPT)
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                _set(lib, _DEFAULTS)
                lib.malloc_trim(0)
