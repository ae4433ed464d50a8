"""How far a fitted loop lies from every classical Prandtl-Ishlinskii loop.

A PI with non-negative weights, on any thresholds, draws the classical loops: every branch the
same curve from its reversal point, only scaled (Masing's rules). What no such PI draws - a loop
width that depends on the absolute level, a band of domains switching at fixed voltages, a knee
part-way up the stroke - is a loop shape, the catalogue's ``hysteresis_shape``, however fine the
grid that fits it.

The recalibrated PI keeps only the partial sums of its weights positive (an invertible model that
may load concavely), so a weight may go negative and the recalibration itself can bend part of a
shape in; the improvement a finer loop then adds (``select.SHAPE_REMOVED``) counts only the rest
(rig-078: a band of switching domains 4.0 noise rms from the best classical loop of the device's
true stroke, a finer loop removing 1.05 beyond the recalibrated one). :func:`beyond_classical`
measures the shape itself: the stroke of a fitted loop, refitted by ``CLASSICAL_OPERATORS`` play operators with non-negative
weights on threshold grids of several spacings and voltage scales, and what is left, at each
channel's static gain, in multiples of that channel's noise. What the stack remembers from before
the record is not known (the fitted loop's KP cells may draw any start): the classical operators
start from the fitted model's memory, relaxed, or after a sweep from rest to the record's top
voltage, whichever fits best (rig-029, a fitted loop with relaxed operators: 16.8 noise rms from
relaxed classical operators, 1.1 from swept ones). The saturation is ordinary: the classical
loops are tried without a sag and with the fitted model's.

A loop of the classical kind is still more than the model's own nine operators draw when it needs
other thresholds: :func:`further_from_nominal` measures how much further a finer loop lies from
every PI on the nominal thresholds (non-negative weights) than the recalibrated loop did - the
catalogue's own definition of a loop shape ("a loop the nominal play-operator grid cannot draw"),
taken as an increase so that what the recalibration's free-signed weights already bent in counts
as ordinary.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import nnls

from .engine import operators, predict, stroke
from .fit import Fitter
from .model_io import Params

__all__ = ["CLASSICAL_OPERATORS", "CLASSICAL_ROWS", "CLASSICAL_SCALES", "CLASSICAL_SPACINGS",
           "beyond_classical", "further_from_nominal"]

CLASSICAL_OPERATORS = 20                            # play operators of the classical loops tried
CLASSICAL_SPACINGS = (1.0, 2.0)                     # thresholds U (k / (n - 1))^s, k = 0 .. n - 1
CLASSICAL_SCALES = tuple(np.geomspace(0.05, 1.2, 12))   # U [the recorded stack-voltage span]
CLASSICAL_ROWS = 40000                              # at most this many samples in the least squares


def _nonneg_lsq(cols, y):
    """Weights ``w >= 0`` minimising ``|cols.T w - y|`` (``cols`` ``(n, N)``, centred), solved on the
    small Gram matrix."""
    gram = cols @ cols.T
    lam, vec = np.linalg.eigh(gram)
    lam = np.maximum(lam, 0.0) + 1e-12 * max(float(lam.max()), 1e-300)   # columns never moved: singular
    root = np.sqrt(lam)
    w, _ = nnls(root[:, None] * vec.T, (vec.T @ (cols @ y)) / root)
    return w


def beyond_classical(fitter: Fitter, p: Params, noise: dict, thresholds=None) -> dict:
    """What of the loop of ``p`` no classical PI draws, per channel [multiples of its noise rms].

    Parameters
    ----------
    fitter : Fitter
        The recordings and device (the stroke is replayed with ``p``'s dynamics and memory).
    p : Params
        A fitted model (its operators and KP cells make the loop).
    noise : dict
        Channel -> noise rms [um for x, V for us].
    thresholds : array_like, optional
        One set of thresholds [normalised like ``p.thresholds``] in the place of the grids: how
        far the loop lies from every PI on those thresholds with non-negative weights (the
        nominal model's nine: the loop the model's own operators cannot draw).

    Returns
    -------
    dict
        Channel -> rms of the stroke beyond the best classical loop, times the channel's static
        gain from the stroke [um/um or V/um], over the channel's noise rms.
    """
    hs, uas, gains = [], [], {c: [] for c in noise}
    for r, rp in zip(fitter.recs, fitter.replays(p)):
        h = stroke(r, fitter.dev, p, rp)
        pred = predict(r, fitter.dev, p, rp)
        hc = h - h.mean()
        for c in noise:
            if pred.get(c) is not None and getattr(r, c) is not None and float(hc @ hc) > 0:
                gains[c].append(abs(float((pred[c] - pred[c].mean()) @ hc) / float(hc @ hc)))
        hs.append(h)
        uas.append(rp.ua)
    span = max(float(ua.max()) for ua in uas) - min(min(float(ua.min()) for ua in uas), 0.0)
    if span <= 0 or not max(float(np.ptp(h)) for h in hs) > 0:
        return {c: 0.0 for c in noise}
    # rows for the least squares (the operators run over every sample)
    every = max(1, -(-sum(h.size for h in hs) // CLASSICAL_ROWS))
    h = np.concatenate(hs)[::every]
    # the targets before a sag (none, or the fitted model's own), each recording's mean apart
    targets = []
    for sag in [np.inf] + ([p.y_sat] if math.isfinite(p.y_sat) else []):
        ys = [x if sag == np.inf else x / (1.0 - np.abs(x) / sag) for x in hs]
        mean = np.concatenate([np.full(y.size, y.mean()) for y in ys])[::every]
        targets.append((sag, np.concatenate(ys)[::every] - mean, mean))
    top = max(float(ua.max()) for ua in uas)
    best = np.inf
    k = np.arange(CLASSICAL_OPERATORS) / (CLASSICAL_OPERATORS - 1)
    grids = ([scale * span * k ** s / p.u_norm for s in CLASSICAL_SPACINGS for scale in CLASSICAL_SCALES]
             if thresholds is None else [np.asarray(thresholds, float)])
    for prep in sorted({p.prep, 0.0, top}):
        for grid in grids:
            q = p.copy()
            q.thresholds = grid
            q.weights = np.zeros(grid.size)
            q.cells = q.cell_w = None
            q.cells_held = False
            q.prep = prep
            cols = []
            for ua in uas:           # each recording's operators, their mean removed
                z = operators(ua, q)
                cols.append(z - z.mean(axis=1, keepdims=True))
            cols = np.hstack(cols)[:, ::every]
            for sag, y, mean in targets:
                fit = _nonneg_lsq(cols, y) @ cols + mean
                if sag != np.inf:
                    fit = fit / (1.0 + np.abs(fit) / sag)
                best = min(best, float(np.sum((fit - h) ** 2)))
    left = np.sqrt(best / h.size)
    return {c: float(left * np.mean(g) / noise[c]) if g else 0.0 for c, g in gains.items()}


def further_from_nominal(fitter: Fitter, p_new: Params, p_old: Params, noise: dict, thresholds) -> float:
    """How much further the loop of ``p_new`` lies from every PI on ``thresholds`` (non-negative
    weights) than that of ``p_old`` [noise rms, best channel of each].

    Parameters
    ----------
    fitter : Fitter
        The recordings and device.
    p_new, p_old : Params
        The finer loop's model and the recalibrated one it would replace.
    noise : dict
        Channel -> noise rms [um for x, V for us].
    thresholds : array_like
        The nominal thresholds [normalised like ``p_old.thresholds``].

    Returns
    -------
    float
        ``max_ch beyond(p_new) - max_ch beyond(p_old)`` with :func:`beyond_classical` on
        ``thresholds``; negative when the finer loop is nearer the nominal operators' loops.
    """
    new = beyond_classical(fitter, p_new, noise, thresholds)
    old = beyond_classical(fitter, p_old, noise, thresholds)
    return max(new.values(), default=0.0) - max(old.values(), default=0.0)
