"""Reading recordings and cutting them into validation blocks.

A recording is a CSV with ``time`` [s] (uniform), ``u`` [V] (the amplifier command) and ``x`` [um]
and/or ``us`` [V]. Each one is cut into :data:`N_BLOCKS` consecutive blocks; every
:data:`HELDOUT_EVERY`-th block (starting with block ``HELDOUT_EVERY // 2``) is held out: no
parameter is fitted on its measured outputs, and every RMSE diagnose reports is over them.
"""
from __future__ import annotations

import numpy as np

from ..errors import UserError
from ..recording import read_csv_table
from .model_io import Recording

__all__ = ["HELDOUT_EVERY", "N_BLOCKS", "load_recordings", "make_recordings"]

N_BLOCKS = 64
HELDOUT_EVERY = 4


def load_recordings(paths, columns=None, scale=None):
    """Read recordings: columns time [s], u [V] and x [um] and/or us [V] (after --columns/--scale)."""
    if not paths:
        raise UserError("give at least one recording (CSV with time, u and x and/or us)")
    out = []
    for path in paths:
        tab = read_csv_table(path, required=("time", "u"), one_of=("x", "us"), columns=columns,
                             scale=scale, uniform=True, min_rows=50)
        out.append({"name": str(path), "time": tab["time"], "u": tab["u"],
                    "x": tab.columns.get("x"), "us": tab.columns.get("us")})
    return out


def blocks(n, n_blocks=N_BLOCKS):
    """Validation block of every sample and the held-out mask."""
    nb = n_blocks if n >= 20 * n_blocks else max(4, n // 20)
    block = np.minimum((np.arange(n) * nb) // n, nb - 1)
    return block, (block % HELDOUT_EVERY) == HELDOUT_EVERY // 2


def make_recordings(raw):
    """:class:`.model_io.Recording` objects from read (or in-memory) recordings."""
    recs = []
    for r in raw:
        t = np.asarray(r["time"], float)
        dt = float(np.median(np.diff(t)))
        block, held = blocks(t.size)
        recs.append(Recording(r["name"], t - t[0], dt, np.asarray(r["u"], float),
                              None if r.get("x") is None else np.asarray(r["x"], float),
                              None if r.get("us") is None else np.asarray(r["us"], float),
                              held, float(t[0]), block, {}))
    return recs
