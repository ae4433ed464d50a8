"""The residuals of a parameter set (training and held-out rows per channel) and the acceptance
thresholds every decision of the diagnosis uses (see docs/diagnose.md, "How a finding is decided").

Kept apart from :mod:`.select` and :mod:`.recalibrate`, which both need them, so that neither
imports the other at module level.
"""
from __future__ import annotations

import numpy as np

from .engine import predict
from .fit import Fitter

__all__ = ["ACCEPT", "full_residuals", "residual_sets"]

ACCEPT = {
    "p_lr": 1e-3,            # likelihood-ratio test on training rows (effective sample size)
    "dbic": 10.0,            # BIC difference (effective sample size), > 10 = very strong
    "explained": 0.15,       # share of the structured residual removed (its best channel)
    "beta_heldout": 0.5,     # held-out residual regressed on the candidate's change there (1 = all of it)
    "z_heldout": 3.0,        # ... and that regression's significance
    "worse": 0.02,           # no channel's held-out RMSE may grow by more than this
    "bound": 0.01,           # a fitted value within 1 % (log scale) of its search range's ends is at a bound
}


def residual_sets(fitter: Fitter, p):
    """channel -> train/heldout residuals, held-out blocks, weight (model orientation)."""
    out = {}
    rps = fitter.replays(p)
    preds = [predict(r, fitter.dev, p, rp) for r, rp in zip(fitter.recs, rps)]
    for ch in ("x", "us"):
        tr, ho, blocks = [], [], []
        for r, pr in zip(fitter.recs, preds):
            y = getattr(r, ch)
            if y is None:
                continue
            e = y - pr[ch]
            tr.append(e[r.train])
            ho.append(e[r.heldout])
            for b in np.unique(r.block[r.heldout]):
                blocks.append(e[r.block == b])
        if tr:
            out[ch] = {"train": np.concatenate(tr), "heldout": np.concatenate(ho), "blocks": blocks,
                       "lam": fitter.lam[ch]}
    return out, preds


def full_residuals(fitter, p):
    rps = fitter.replays(p)
    out = []
    for r, rp in zip(fitter.recs, rps):
        pr = predict(r, fitter.dev, p, rp)
        out.append({ch: getattr(r, ch) - pr[ch] for ch in r.channels()})
    return out
