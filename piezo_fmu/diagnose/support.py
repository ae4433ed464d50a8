"""Which of a loop's states the training rows see move, against the held-out rows.

A loop state (a play operator, a KP cell) that the command moves in a handful of training rows
and through a whole held-out block has a weight the training rows hardly determine: fitted to
those few rows (often as one of a set whose weights cancel there), it draws a stroke of its own
where the held-out rows alone move it, and the validation then sees a misfit the model was never
shown. Only the command, the thresholds and the split into training and held-out blocks decide
this, never the measured channels. :func:`seen_in_training` counts, per state, the share of each
set of rows where it moves; the finer loop (:func:`.catalogue.finer_loop`) leaves out the states
the training rows do not support.
"""
from __future__ import annotations

import numpy as np

from .engine import at_samples

__all__ = ["CELL_FLOOR", "CELL_SUPPORT", "PLAY_FLOOR", "cell_switched", "play_moves", "seen_in_training"]

# a state the held-out rows see move more than CELL_SUPPORT times as often as the training rows
# (each as a share of its rows) is not supported. Cells: rig-072's were out at 3.5-4.9, the true
# shapes' cells reach 1.2-3.05 (rig-028, 052, 088, 108). Play operators: rig-d40-095, a Bouc-Wen
# loop: the finer loop's operators at 0.5-0.8 of the voltage scale moved in 0-7 training rows and
# 42-57 held-out rows, the first rise of a sine after a 38 V step; their weights -15.2, +13.7,
# -12.3 um cancelled on the training rows and took that held-out block from 0.098 to 0.317 um (the
# finer loop failed, x 186 % worse; without them x 0.028 -> 0.005 um, and the loop shape is named).
# At least PLAY_FLOOR held-out rows count as moving for an operator (a cell: CELL_FLOOR)
CELL_SUPPORT = 3.3
PLAY_FLOOR = 1.0
CELL_FLOOR = 20.0


def play_moves(z, rec):
    """Where each play operator's state (rows of ``z``, at ``rec``'s samples) changes between samples."""
    return np.abs(np.diff(z, axis=1, prepend=z[:, :1])) > 1e-9 * max(float(np.abs(z).max()), 1e-12)


def cell_switched(z, rec):
    """Where each KP cell's state differs from its median over ``rec``'s training rows."""
    return np.abs(z - np.median(z[:, rec.train], axis=1)[:, None]) > 0.5


def seen_in_training(recs, replays, states, floor, moved):
    """Whether each loop state ``states`` (a slice of the replays' states) is ``moved`` (``moved(z,
    rec)``: a boolean per state and sample) on a share of the held-out rows at most
    :data:`CELL_SUPPORT` x its share of the training rows (at least ``floor`` held-out rows counted)."""
    on_tr = on_ho = 0.0
    for rp, r in zip(replays, recs):
        m = moved(at_samples(r, rp.z[states]), r)
        on_tr = on_tr + m[:, r.train].sum(axis=1)
        on_ho = on_ho + m[:, r.heldout].sum(axis=1)
    n_tr = max(sum(int(r.train.sum()) for r in recs), 1)
    n_ho = max(sum(int(r.heldout.sum()) for r in recs), 1)
    return on_ho / n_ho <= CELL_SUPPORT * np.maximum(on_tr / n_tr, floor / n_ho)
