"""The uncertainty of recalibrated and fitted parameters: Gauss-Newton covariances of the training
residual, its variance inflated by the residual's integrated autocorrelation time."""
from __future__ import annotations

import math

import numpy as np

from .fit import Fitter, get_value, set_value
from .stats import tau_int

__all__ = ["channel_uncertainty", "sensitive", "uncertainty"]


def uncertainty(fitter: Fitter, p, struct, names):
    """Relative standard uncertainty of each nonlinear parameter: Gauss-Newton covariance in log
    coordinates, the residual's variance inflated by its integrated autocorrelation time; ``inf``
    for one no sample responds to (:func:`sensitive`), None when the rest cannot be separated.

    With both lag stages in, also ``"tau+tau2"``: the relative uncertainty of the amplifier's total
    lag, which a record of slow steps determines although it cannot split it between the stages
    (rig-d3-012: 0.27 and 0.41 ms at 89 and 49 x their values, anti-correlated)."""
    if not names:
        return {}
    r0 = fitter.varpro(p.copy(), struct)
    cols = []
    for n in names:
        q, h = _nudged(fitter, p, n)
        cols.append((fitter.varpro(q, struct) - r0) / h)
    J = np.column_stack(cols)
    s2 = float(r0 @ r0) / max(r0.size - len(names), 1) * tau_int(r0)
    moves = sensitive(J, r0)
    out = {n: math.inf for n, m in zip(names, moves) if not m}
    keep = [i for i, m in enumerate(moves) if m]
    if not keep:
        return out
    J = J[:, keep]
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        return {**out, **{names[i]: None for i in keep}}
    out.update({names[i]: float(f"{math.sqrt(max(cov[j, j], 0.0)):.3g}") for j, i in enumerate(keep)})
    names = [names[i] for i in keep]
    if "tau" in names and "tau2" in names and p.tau2 > 0:
        # d log(tau + tau2) = (tau d log tau + tau2 d log tau2) / (tau + tau2)
        w = np.zeros(len(names))
        w[names.index("tau")], w[names.index("tau2")] = p.tau, p.tau2
        w /= p.tau + p.tau2
        out["tau+tau2"] = float(f"{math.sqrt(max(float(w @ cov @ w), 0.0)):.3g}")
    return out


def sensitive(J, r0, rel=1e-9):
    """Which columns of the Jacobian ``J`` (per unit of a log parameter) move the residual ``r0``
    at all: False for a column below ``rel`` x the residual's norm, a parameter no sample responds
    to (changing it e-fold changes the cost by a part in 1e18). An amplifier lag of 0.1 ms sampled
    every 3.8 ms decays by exp(-38) between samples, below round-off (rig-d3-165: its column zero
    on one CPU, 3e-12 against a residual of 2e2 on another). Its uncertainty is unbounded and its
    correlation with the others nil, so theirs is the covariance without it."""
    norms = np.linalg.norm(J, axis=0)
    floor = rel * float(np.linalg.norm(r0))
    return [bool(v > floor and v > 0.0) for v in norms]


def _nudged(fitter: Fitter, p, name, h=1e-3):
    """``(q, step)``: ``p`` with the nonlinear parameter ``name`` moved by ``step`` in log
    coordinates (``h``, or ``-h`` where that would pass its upper bound)."""
    q = p.copy()
    v = get_value(q, name, fitter.dev)
    step = h if v * math.exp(h) <= fitter.bounds(name, p)[1] else -h
    set_value(q, name, v * math.exp(step), fitter.dev)
    return q, step


def channel_uncertainty(fitter: Fitter, p, names):
    """Standard uncertainty of the linear calibration of ``p``: the loop's scale and the sensor's
    sensitivity (relative) and the channels' offsets (absolute: um and V). The Gauss-Newton
    covariance of the residual in these and the nonlinear parameters ``names`` (so that their
    correlations count; the weights' shape is held, their common scale free), its variance
    inflated by the residual's integrated autocorrelation time. ``None`` for what the data cannot
    separate (the loop's scale from the sensitivity with the sensor voltage alone)."""
    from .varpro import residuals

    def res(q):
        return residuals(fitter.recs, fitter.dev, q, fitter.lam, fitter.replays(q))

    r0 = res(p)
    chans = {c for r in fitter.recs for c in r.channels()}
    cols, keys = [], []

    def column(key, q, step):
        cols.append((res(q) - r0) / step)
        keys.append(key)

    for n in names:                     # the linear parameters held
        column(n, *_nudged(fitter, p, n))
    if cols:                            # a nonlinear parameter no sample responds to: left out
        moves = sensitive(np.column_stack(cols), r0)
        cols = [c for c, m in zip(cols, moves) if m]
        keys = [k for k, m in zip(keys, moves) if m]
    h = 1e-3
    q = p.copy()
    q.weights = np.asarray(p.weights, float) * (1.0 + h)
    if q.cell_w is not None:
        q.cell_w = np.asarray(p.cell_w, float) * (1.0 + h)
    column("pi_scale", q, h)
    if "us" in chans:
        q = p.copy()
        q.S = p.S * (1.0 + h)
        column("S", q, h)
        q = p.copy()
        q.off_s = p.off_s + 1.0
        column("off_s", q, 1.0)
    if "x" in chans:
        q = p.copy()
        q.off_x = p.off_x + 1.0
        column("off_x", q, 1.0)
    J = np.column_stack(cols)
    s2 = float(r0 @ r0) / max(r0.size - len(keys), 1) * tau_int(r0)
    gram = J.T @ J
    if np.linalg.cond(gram) > 1e12 and "x" not in chans:
        # the inseparable pair gets no figure; the rest from the covariance without it
        idx = [i for i, k in enumerate(keys) if k not in ("pi_scale", "S")]
        keys, gram = [keys[i] for i in idx], gram[np.ix_(idx, idx)]
    if np.linalg.cond(gram) > 1e12:
        return {}                       # no figures rather than wrong ones
    cov = np.linalg.inv(gram) * s2
    return {k: float(f"{math.sqrt(max(cov[i, i], 0.0)):.3g}") for i, k in enumerate(keys)
            if k in ("pi_scale", "S", "off_s", "off_x")}
