"""The worker threads diagnose spreads its independent evaluations over.

The machine issue 12 names has two cores. Jacobian columns, the points of a screening grid, the
starts of a search and the two channels of a design are independent evaluations whose heavy parts
(the compiled kernels, NumPy's products) release the GIL: :func:`each` runs them on the worker
threads and returns their results in order, the same numbers as one after another. Work started
on one of the threads stays on it (a worker waiting for the pool's other tasks could wait for
itself), so nested calls are safe and run in order.

How many threads: :data:`THREADS` (two) unless the environment variable :data:`THREADS_ENV` or
:func:`limit` says otherwise; one runs everything on the calling thread. Where the cores are busy
anyway (several diagnoses side by side, the test suite on two processes) one thread costs less:
on the two-core Intel Xeon the benchmark's recording (20 s at 10 kHz) took 165 s of CPU on two
threads (124 s wall) and 145 s on one.
"""
from __future__ import annotations

import os
import threading
from contextlib import contextmanager

from ..errors import UserError

__all__ = ["THREADS", "THREADS_ENV", "each", "limit", "pool", "thread_count"]

THREADS = 2
THREADS_ENV = "PIEZO_FMU_DIAGNOSE_THREADS"
_NAME = "diagnose-pool"
_POOLS = {}
_LIMIT = [None]


def thread_count() -> int:
    """The number of threads :func:`each` uses: :func:`limit`'s, else :data:`THREADS_ENV`'s, else
    :data:`THREADS`. Raises UserError for an environment value that is not a whole number >= 1."""
    if _LIMIT[0] is not None:
        return _LIMIT[0]
    text = os.environ.get(THREADS_ENV, "").strip()
    if not text:
        return THREADS
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise UserError(f"{THREADS_ENV} must be a whole number >= 1, got {text!r}")
    return n


@contextmanager
def limit(n):
    """Run the block with ``n`` worker threads (``None``: the default, :func:`thread_count`)."""
    if n is not None and (int(n) != n or n < 1):
        raise UserError(f"threads must be a whole number >= 1, got {n!r}")
    saved = _LIMIT[0]
    _LIMIT[0] = None if n is None else int(n)
    try:
        yield
    finally:
        _LIMIT[0] = saved


def pool(n=None):
    """``n`` worker threads (default :func:`thread_count`; created on first use)."""
    n = n or thread_count()
    if n not in _POOLS:
        from concurrent.futures import ThreadPoolExecutor

        _POOLS[n] = ThreadPoolExecutor(max_workers=n, thread_name_prefix=_NAME)
    return _POOLS[n]


def each(f, items):
    """``[f(x) for x in items]``, on the worker threads: on the calling thread for a single item,
    with one thread, or when it is one of the workers."""
    items = list(items)
    if len(items) < 2 or threading.current_thread().name.startswith(_NAME):
        return [f(x) for x in items]
    n = thread_count()
    if n == 1:
        return [f(x) for x in items]
    return list(pool(n).map(f, items))
