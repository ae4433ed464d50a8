"""The two worker threads diagnose spreads its independent evaluations over.

The machine issue 12 names has two cores. Jacobian columns, the points of a screening grid, the
starts of a search and the two channels of a design are independent evaluations whose heavy parts
(the compiled kernels, NumPy's products) release the GIL: :func:`each` runs them on two threads and
returns their results in order, the same numbers as one after another. Work started on one of the
threads stays on it (a worker waiting for the pool's other tasks could wait for itself), so nested
calls are safe and run in order.
"""
from __future__ import annotations

import threading

__all__ = ["each", "pool"]

_NAME = "diagnose-pool"
_POOL = None


def pool():
    """The two worker threads (created on first use)."""
    global _POOL
    if _POOL is None:
        from concurrent.futures import ThreadPoolExecutor

        _POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix=_NAME)
    return _POOL


def each(f, items):
    """``[f(x) for x in items]``, on the two worker threads: on the calling thread for a single
    item, or when it is one of the workers."""
    items = list(items)
    if len(items) < 2 or threading.current_thread().name.startswith(_NAME):
        return [f(x) for x in items]
    return list(pool().map(f, items))
