"""Recalibration of the hysteresis' ordinary items: its state at the first sample and the voltage
scale of its thresholds (step 2 of :mod:`.recalibrate`).

A rig exercised before each record starts with the memory of that exercise, and the nominal
thresholds come from another stack and amplifier: both are ordinary, not a missing loop shape.
"""
from __future__ import annotations

import numpy as np

from .recalbase import fit_ordinary, gain
from .residuals import ACCEPT
from .stats import near_range_end

__all__ = ["SCALE_NOTE", "THRESHOLD_FITTED", "THRESHOLD_SCALES", "initial_state", "threshold_scale"]


def initial_state(fitter, rc, struct, sat):
    """The operators' state at the first sample: relaxed, or left by a preparation sweep up to the
    recording's highest stack voltage and back (a rig exercised before each record). The record's
    first excursions differ until the voltage passes that top; kept when it beats relaxed
    operators clearly."""
    p = rc.params
    top = max(min(float(np.max(r.u)) * fitter.dev.k_amp, fitter.dev.u_max) for r in fitter.recs)
    if top <= 0.0:
        rc.report["initial_state"] = {"value": "relaxed", "why": "the command never rises above zero"}
        return False
    q = p.copy()
    q.prep = top
    # (known fault, kept for now: with ``sat`` in the ordinary list ``free_names`` frees y_sat twice,
    # two identical Jacobian columns; deduplicating re-routes cases: docs/diagnose-history.md, stop 72)
    fr = fit_ordinary(fitter, q, struct, ["tau"] + sat, 6)
    bic, _ = gain(fitter, p, fr.params, 1)
    if bic > ACCEPT["dbic"]:
        rc.params = fr.params
        rc.report["initial_state"] = {"value": "prepared", "top_V": float(f"{top:.6g}"), "bic_gain": round(bic, 1)}
        rc.notes.append(f"the recording starts with the hysteresis' memory of a sweep up to {top:.4g} V of "
                        "stack voltage (the device was exercised before the record)")
        return True
    rc.report["initial_state"] = {"value": "relaxed", "bic_gain_of_prepared": round(bic, 1)}
    return False


THRESHOLD_SCALES = (0.3, 0.45, 0.7, 1.4)     # starting points of the threshold scale's fit (x the start)
THRESHOLD_FITTED = 2                          # of them, the best screened are fitted
SCALE_NOTE = "the hysteresis thresholds sit at"   # the note a scale found writes (one at a time)


def threshold_scale(fitter, rc, struct, sat):
    """The voltage scale of the PI thresholds (``u_norm``): the thresholds keep their nominal
    pattern, the voltage they sit at is the device's. The nominal scale comes from another stack
    and amplifier (or from the recording's span): a loop that bends at other voltages is ordinary,
    not a missing loop shape. A short fit from a few starting scales (weights, saturation and lag
    re-fitted at each, after a screening with the weights re-solved), then a joint fit from the
    best; kept when it beats the start clearly and does not settle at the end of its range."""
    rc.scale_tried_with = struct.effects
    before = rc.report.get("threshold_scale", {})
    if not before.get("identified"):
        return _threshold_scalefit_ordinary(fitter, rc, struct, sat, rc.params.u_norm)
    # asked again with mechanisms in: measured from the first start; a scale no better keeps the
    # one identified before
    if not _threshold_scalefit_ordinary(fitter, rc, struct, sat, before["start_V"]):
        rc.report["threshold_scale"] = before
        return False
    return True


def _threshold_scalefit_ordinary(fitter, rc, struct, sat, start):
    """One search of the scale from ``rc.params`` (see :func:`threshold_scale`); ``start`` [V] is
    the scale the report and the note measure from."""
    p = rc.params
    if "u_norm" not in fitter.limits:
        rc.report["threshold_scale"] = {"identified": False, "why": "no range given"}
        return False
    lo, hi = fitter.limits["u_norm"]
    # screened with the weights re-solved at each scale (lag held); the two best are fitted
    screen = []
    for k in THRESHOLD_SCALES:
        q = p.copy()
        q.u_norm = float(np.clip(p.u_norm * k, lo * 1.01, hi / 1.01))
        r = fitter.varpro(q, struct)
        screen.append((float(r @ r), k, q))
    screen.sort(key=lambda s: s[0])
    trials = [fit_ordinary(fitter, q, struct, ["tau"] + sat, 4) for _, _, q in screen[:THRESHOLD_FITTED]]
    best = min(trials, key=lambda fr: fr.cost)
    if best.cost >= fitter.cost(p):
        rc.report["threshold_scale"] = {"identified": False, "why": "no other scale fits better"}
        return False
    fr = fit_ordinary(fitter, best.params, struct, ["u_norm", "tau"] + sat, 8)
    bic, _ = gain(fitter, p, fr.params, 1)
    edge = near_range_end(fr.params.u_norm, *fitter.bounds("u_norm"))
    if bic > ACCEPT["dbic"] and not edge:
        rc.report["threshold_scale"] = {"identified": True, "bic_gain": round(bic, 1),
                                        "u_norm_V": float(f"{fr.params.u_norm:.6g}"),
                                        "start_V": float(f"{start:.6g}")}
        rc.params = fr.params
        rc.notes = [n for n in rc.notes if not n.startswith(SCALE_NOTE)]
        rc.notes.append(f"{SCALE_NOTE} {fr.params.u_norm / start:.3g} x the starting voltage scale "
                        f"(u_norm {fr.params.u_norm:.4g} V instead of {start:.4g} V)")
        return True
    rc.report["threshold_scale"] = {"identified": False, "why": "at the end of its search range" if edge
                                    else f"not clearly better (BIC gain {bic:.1f})",
                                    "bic_gain": 0.0 if edge else round(bic, 1)}
    return False
