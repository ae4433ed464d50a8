"""Where the search for a thermal drift starts: its form and the sensor's pick-off.

The drift is ``rate t + curvature 2 T^2 (exp(-t/T) - 1 + t/T)`` (the core's ``drift_curvature``): a
ramp and a warm-up settling with time constant ``T``; as ``T`` grows, the quadratic drift
``rate t + curvature t^2``. Its linear terms are solved exactly with the weights; ``T`` is a
fitted parameter (:data:`.fit.DRIFT_TAU` record lengths), started from the screening's best of a
grid (:func:`drift_start`), and the quadratic itself (one parameter fewer) is fitted beside it
with every pick-off of the sensor (:func:`drift_alternatives`); :func:`.select.select` keeps the
better by BIC. Used by :func:`.catalogue.propose` (``thermal_drift``) and :mod:`.select`.
"""
from __future__ import annotations

import math

import numpy as np

from .fit import DRIFT_TAU, Fitter

__all__ = ["DRIFT_TAU_GRID", "drift_alternatives", "drift_start"]

# the drift's warm-up time constants the screening tries [record durations] (the slowest, the top
# of the fit's range, is the quadratic drift; rig warm-ups settle with 0.1-0.6 of the record)
DRIFT_TAU_GRID = (0.1, 0.25, 0.6, DRIFT_TAU[1])


def drift_start(fitter: Fitter, p):
    """The drift's start: of the warm-ups in :data:`DRIFT_TAU_GRID`, the one the screening (the
    weights held, gains, offsets and the drift's linear terms solved: :meth:`.Fitter.quick`) fits
    best. A quadratic alone cannot follow a warm-up that settles within the record: it bends back
    at the end, where the command's last hold then sees the opposite trend (rig-d9-145). A drift
    the sensor follows (a load pick-off) starts so too: see :func:`drift_alternatives`."""
    qs = []
    for k in DRIFT_TAU_GRID:
        q = p.copy()
        q.drift_tau = k * fitter.duration
        qs.append(q)
    return qs[int(np.argmin(fitter.quick_many(qs, drift=True)))]


def drift_alternatives(fitter: Fitter, start, cctx):
    """Further starts of a drift (each fitted; the better by BIC is kept): the quadratic drift
    beside the screening's warm-up (one parameter fewer; a warm-up fitted to the record's first
    twentieth is a start transient, rig-083, and a quadratic was the drift), and each with every
    other pick-off of the sensor. The pick-off decides whether the drift reaches the sensor (a
    sensor on the load spring follows the push rod, one on the stack or its contact does not), and
    the recalibration chose it without the drift (rig-d9-109: a load pick-off beside a first mode of
    534 Hz, the drift then pulled the sensor along and made it 46 % worse on held-out data; on the
    stack it explains all of the displacement's structured residual). Without a visible first mode
    the contact force is the load's (k_a (x_free - x) = k_f x at rest): stack and load only.

    A drift that the sensor follows may be a warm-up too (until 2026-12-07 it was a quadratic only,
    lest a warm-up in both channels take the place of a slow creep element, synth-1055). A quadratic
    on the load spring cannot follow a warm-up that settles before the record's last rest: there it
    keeps bending, the data do not, and the drift failed the hold test while creep took its place
    beside the drift found later (rig-d38-144 and 170: a displacement pick-off, warm-ups of 1.8 s
    and 3.4 s, creep named falsely beside the drift; with the warm-up on the load spring the drift
    alone). On draw 38's 78 cases with creep, a drift or nothing, only those two changed."""
    out = []
    if math.isfinite(start.drift_tau):
        out.append(start.copy())
        out[-1].drift_tau = math.inf
    if "us" in cctx["channels"]:
        picks = ("stack", "load", "contact") if "mech_f" in fitter.ordinary else ("stack", "load")
        for a in [start] + out:
            for pick in picks:
                if pick != a.pick:
                    out.append(a.copy())
                    out[-1].pick = pick
    return out
