"""One float64 buffer for a unit's data: what the compiled engine passes as a single argument.

Kept apart from :mod:`.compiled` so that the units (which lay their data out here when they are
handed a runner) never import the module that compiles them.
"""
from __future__ import annotations

import numpy as np

__all__ = ["pack"]


def pack(regions):
    """Lay ``regions`` (sequences of floats) out back to back in one float64 buffer.

    Returns ``(buf, offsets, views)``: region ``i`` is ``buf[offsets[i]:offsets[i + 1]]``
    (``offsets`` int64, one longer than ``regions``), ``views`` those slices, filled with the
    regions' current values.
    """
    offsets = np.zeros(len(regions) + 1, dtype=np.int64)
    np.cumsum([len(r) for r in regions], out=offsets[1:])
    buf = np.empty(int(offsets[-1]))
    views = []
    for i, r in enumerate(regions):
        v = buf[offsets[i]:offsets[i + 1]]
        v[:] = r
        views.append(v)
    return buf, offsets, views
