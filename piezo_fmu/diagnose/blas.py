"""One BLAS thread while diagnose runs.

diagnose's linear algebra is many small products over long vectors, and it already runs its
Jacobian columns on two threads. OpenBLAS's own threads on top of that spin and wait for each
other, and on a shared two-core machine that costs more than it gives: a screening evaluation of
a 264 000-sample recording took 237 ms with OpenBLAS's default threads and 18 ms with one (while
other jobs ran). :func:`single_thread` sets every loaded OpenBLAS (NumPy's and SciPy's) to one
thread for the duration and restores the previous counts; without OpenBLAS it does nothing.
"""
from __future__ import annotations

import ctypes
import re
from contextlib import contextmanager

__all__ = ["single_thread"]

_NAMES = (("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
          ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
          ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
          ("openblas_set_num_threads", "openblas_get_num_threads"))


def _controls():
    out = []
    try:
        with open("/proc/self/maps") as fh:
            paths = {m.group(1) for line in fh if (m := re.search(r"(/\S*openblas\S*\.so\S*)", line))}
    except OSError:
        return out
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for set_name, get_name in _NAMES:
            if hasattr(lib, set_name) and hasattr(lib, get_name):
                out.append((getattr(lib, set_name), getattr(lib, get_name)))
                break
    return out


@contextmanager
def single_thread():
    """Run the block with one OpenBLAS thread (the previous counts come back afterwards)."""
    ctl = _controls()
    before = []
    for set_n, get_n in ctl:
        try:
            before.append(int(get_n()))
            set_n(1)
        except Exception:  # noqa: BLE001 - an OpenBLAS without these entry points: leave it
            before.append(None)
    try:
        yield
    finally:
        for (set_n, _), n in zip(ctl, before):
            if n is not None:
                set_n(n)
