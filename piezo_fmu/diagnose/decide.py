"""Deciding on a candidate: the statistics every finding must pass, its confidence, and how
candidates are ranked against each other (used by :mod:`.select` and :mod:`.rivals`).

A candidate passes (:func:`passes`) when the likelihood-ratio test and BIC (effective sample size)
pass on the training rows, it removes at least ``ACCEPT["explained"]`` of the structured residual
on its best channel, the held-out blocks confirm its correction, no channel gets worse on held-out
data, and its fitted values are physical (:func:`.catalogue.plausible`) and none of its own
parameters sits at a bound of its search range. Its **confidence** (:func:`confidence`) decides
where it is reported: at :data:`CONFIDENT` or more a finding, below a candidate.
"""
from __future__ import annotations

import math

import numpy as np

from .catalogue import CATALOGUE
from .fit import Fitter, free_names, get_value
from .residuals import ACCEPT, full_residuals
from .stats import noise_level

__all__ = ["CONFIDENT", "at_bound", "closeness", "confidence", "noise_levels", "own_parameters",
           "passes", "removed_rms", "score", "told_apart"]

CONFIDENT = 0.5              # findings at or above this confidence are named; below: candidates
RIVAL_BIC = 30.0             # a rival beaten head to head by this many BIC units keeps exp(-1) = 0.37 of its closeness


def noise_levels(fitter: Fitter, p):
    """Noise level (standard deviation) and AR(1) coefficient of every channel's residual."""
    fulls = full_residuals(fitter, p)
    noise, ar = {}, {}
    for c in sorted({c for r in fitter.recs for c in r.channels()}):
        lv = [noise_level(f[c], 1 / r.dt) for f, r in zip(fulls, fitter.recs) if c in f]
        noise[c] = float(np.sqrt(np.mean([v[0] ** 2 for v in lv])))
        ar[c] = float(np.mean([v[1] for v in lv]))
    return noise, ar


def at_bound(fitter: Fitter, p, names):
    """The parameters among ``names`` whose fitted value sits at a bound of its search range."""
    out = []
    for n in names:
        lo, hi = fitter.bounds(n, p)
        v = get_value(p, n, fitter.dev)
        span = math.log(hi / lo)
        x = math.log(max(v, 1e-300) / lo) / span if span > 0 else 0.5
        # (a drift's warm-up at its slow end is the quadratic drift: a model, not a search that ran out)
        if x <= ACCEPT["bound"] or (x >= 1.0 - ACCEPT["bound"] and n != "drift_tau"):
            out.append({"parameter": n, "value": float(f"{v:.5g}"),
                        "range": [float(f"{lo:.5g}"), float(f"{hi:.5g}")]})
    return out


def own_parameters(name, struct_before, struct_after):
    """Nonlinear parameters a mechanism brings (what the bound check looks at)."""
    before = set(free_names(struct_before))
    return [n for n in free_names(struct_after) if n not in before]


def passes(cmp, name, ok, bounds=()):
    mech = CATALOGUE[name]
    chans = [c for c in mech.channels if c in cmp["channels"]]
    if not chans:
        return False, "no recorded channel shows this mechanism"
    best_c = max(chans, key=lambda c: cmp["channels"][c]["explained"])
    explained = cmp["channels"][best_c]["explained"]
    # a channel is made worse when its held-out RMSE grows by more than 2 % and its structured
    # residual by more than a quarter of its noise (shared parameters may shift a little)
    worse = [c for c, v in cmp["channels"].items()
             if v["rel_improvement"] < -ACCEPT["worse"]
             and math.sqrt(max(v["rmse_after"] ** 2 - v["noise"] ** 2, 0.0)) - v["structured_before"] > 0.25 * v["noise"]]
    reasons = []
    if not ok[0]:
        reasons.append(ok[1])
    for b in bounds:
        reasons.append(f"{b['parameter']} = {b['value']:g} is at a bound of its search range "
                       f"[{b['range'][0]:g}, {b['range'][1]:g}]")
    if cmp["p_lr"] > ACCEPT["p_lr"]:
        reasons.append(f"likelihood-ratio p = {cmp['p_lr']:.2g}")
    if cmp["dbic"] < ACCEPT["dbic"]:
        reasons.append(f"BIC gain {cmp['dbic']:.1f} < {ACCEPT['dbic']:g}")
    if cmp["beta_heldout"] < ACCEPT["beta_heldout"] or cmp["z_heldout"] < ACCEPT["z_heldout"]:
        reasons.append(f"held-out data take {cmp['beta_heldout']:.2f} of its correction (z = {cmp['z_heldout']:.1f})")
    if explained < ACCEPT["explained"]:
        reasons.append(f"explains {100 * explained:.0f} % of the structured residual")
    for c in worse:
        reasons.append(f"makes {c} {100 * -cmp['channels'][c]['rel_improvement']:.1f} % worse on held-out data")
    return (not reasons), "; ".join(reasons)


def confidence(cmp, name, alt_share=0.0):
    """0..1 from four factors: strength of evidence (BIC with effective sample size), size (share
    of the structured residual removed), held-out confirmation (how much of its correction the
    held-out data take, and how significantly), uniqueness (no other candidate left as little of the
    structured residual unexplained: see :func:`closeness`).

    Size is the share over every sample, counted in full from half, or the share of the held-out
    samples' structured residual, counted as it is: the training blocks may hold misfit no mechanism
    explains (a fast transient, a loop difference) that dilutes the share over every sample while
    the held-out data, which the fit never saw, lose most of theirs (rig-d8-136, a thermal drift:
    19 % of every sample's, 79 % of the held-out samples'; the false candidates of draws 0 and 8
    take at most 61 % of the held-out samples' and stay below 0.5)."""
    mech = CATALOGUE[name]
    chans = [c for c in mech.channels if c in cmp["channels"]]
    explained = max(cmp["channels"][c]["explained"] for c in chans)
    explained_heldout = max(cmp["channels"][c]["explained_heldout"] for c in chans)
    s_evidence = 1.0 - math.exp(-max(cmp["dbic"], 0.0) / 30.0)
    s_size = min(1.0, max(explained / 0.5, explained_heldout, 0.0))
    s_heldout = float(np.clip(cmp["beta_heldout"], 0.0, 1.0)) * (1.0 - math.exp(-max(cmp["z_heldout"], 0.0) / 3.0))
    s_unique = 1.0 - 0.7 * float(np.clip(alt_share, 0.0, 1.0))
    return float(np.clip(s_evidence * s_size * s_heldout * s_unique, 0.0, 1.0))


def removed_rms(v):
    """Structured rms a candidate removes from one channel, in multiples of its noise."""
    after = math.sqrt(max(v["rmse_after"] ** 2 - v["noise"] ** 2, 0.0))
    return math.sqrt(max(v["structured_before"] ** 2 - after ** 2, 0.0)) / max(v["noise"], 1e-300)


def closeness(best, other):
    """How close a rival comes to the best candidate, 0..1, by what each leaves unexplained (its
    structured residual share): a rival that leaves thirty times more (explaining 0.84 where the best
    explains 0.995) is no real alternative; one that leaves as much is."""
    left_best = 1.0 - float(np.clip(best, 0.0, 1.0))
    left_other = 1.0 - float(np.clip(other, 0.0, 1.0))
    return float(np.clip(left_best / max(left_other, 1e-9), 0.0, 1.0))


def told_apart(best_cmp, rival_cmp, k_more):
    """How far the data leave a rival open, 0..1: ``exp(-dBIC / RIVAL_BIC)``, ``dBIC`` the BIC by
    which the best candidate beats the rival head to head on the training rows: per channel the log
    ratio of the two training sums of squares (each :func:`.stats.compare` result holds its own
    against the same model) at the smaller of the two residuals' effective sample sizes, less
    ``k_more`` (the parameters the best one has beyond the rival's) x log n.

    :func:`closeness` compares what each leaves unexplained; on a large, clean record a rival
    leaving 1.3x the best one's leftover is beaten by far (synth-1054: creep against a drift). A
    rival that fits the training rows better stays fully open, whatever its held-out blocks say
    (rig-179: a drift against a mode that fitted better and failed on held-out data: the mode was
    the device's own, found in the next round)."""
    d, n_tot = 0.0, 0.0
    for c, b in best_cmp["channels"].items():
        r = rival_cmp["channels"][c]
        n = min(b["n_eff"], r["n_eff"])
        d += n * (b["lr"] / b["n_eff"] - r["lr"] / r["n_eff"])
        n_tot += n
    d -= k_more * math.log(max(n_tot, 2.0))
    return float(math.exp(-max(d, 0.0) / RIVAL_BIC))


def score(cmp, name):
    """Rank passing candidates: structured residual removed, averaged over every recorded channel
    (a mechanism that explains both channels beats one that explains one), BIC as tie-break."""
    ex = [max(v["explained"], 0.0) for v in cmp["channels"].values()]
    return float(np.mean(ex)) + 1e-3 * cmp["dbic"] / max(1.0, abs(cmp["dbic"]))

