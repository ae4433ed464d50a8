"""The recalibration's record and yardsticks: what :mod:`.recalibrate` and :mod:`.loopstate` share.

:class:`Recalibration` carries the ordinary parameters found so far and their report; an item is
fitted by :func:`fit_ordinary` and kept when :func:`gain` (the BIC gain with the effective sample
size, against the noise of the better model) beats ``ACCEPT['dbic']``; a cheap screening must first
promise :data:`SCREEN` (:func:`promise`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .engine import predict
from .fit import free_names
from .residuals import residual_sets
from .stats import compare, noise_level

__all__ = ["SCREEN", "Recalibration", "fit_ordinary", "gain", "noise_of", "promise"]


@dataclass
class Recalibration:
    params: object
    report: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    nominal_mode: tuple = (0.0, 0.0)          # the nominal (m, c)
    k_total: float = math.inf                 # the mechanics' stiffness k_a + k_f [N/m] (c / k [s]: a mode's lag)
    scale_tried_with: tuple | None = None     # the mechanisms in when the thresholds' scale was last tried


def noise_of(fitter, p):
    """Noise level per channel of the current residual (all samples)."""
    out = {}
    for r, pr in zip(fitter.recs, [predict(r, fitter.dev, p, rp) for r, rp in zip(fitter.recs, fitter.replays(p))]):
        for c in r.channels():
            out.setdefault(c, []).append(noise_level(getattr(r, c) - pr[c], 1 / r.dt)[0] ** 2)
    return {c: math.sqrt(float(np.mean(v))) for c, v in out.items()}


def gain(fitter, p0, p1, k):
    """BIC gain (effective sample size) of ``p1`` over ``p0`` with ``k`` more parameters."""
    noise = noise_of(fitter, p1)
    cmp = compare(residual_sets(fitter, p0)[0], residual_sets(fitter, p1)[0], k, noise)
    return cmp["dbic"], cmp


def fit_ordinary(fitter, p, struct, ordinary, nfev=10, held=True):
    """Fit the ordinary parameters ``ordinary`` with every parameter of ``struct``'s mechanisms."""
    return fitter.fit(p, struct, free=free_names(struct, ordinary), max_nfev=nfev, held=held)


SCREEN = 5.0     # a screening (weights held) must promise this BIC gain before a full fit is tried


def promise(fitter, q0, q1):
    """BIC gain a screening cost ``q1`` promises over ``q0`` (effective sample size)."""
    return fitter.n_eff * math.log(max(q0, 1e-300) / max(q1, 1e-300))
