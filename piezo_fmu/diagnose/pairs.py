"""Two slow mechanisms that pass only together, in a round of :mod:`.select`.

Creep and a thermal drift in one recording each take part of one slow residual. The BIC gain of
either alone is counted over the residual's effective sample size (:func:`.stats.tau_int`), which
that slow residual keeps small: each fails on the BIC gain alone while the held-out data take it
(rig-d29-055, creep and a drift at 3.99 kHz: the drift alone took the training cost from 89169 to
48676 and x's held-out error from 0.079 to 0.047 um, BIC gain 8.5; creep alone to 42211, BIC gain
2.8; rig-d29-059 the same at 1.54 kHz, 7.0 and 7.5; nothing was named in either). When both fail on
the BIC gain alone (every other test passed, the gain above zero), they are fitted together
(:func:`slow_pair`): when the pair passes every test as each of them would, the one with the larger
gain alone is added now, and the other must pass on its own in a later round (the selection takes
the first back when it does not).
"""
from __future__ import annotations

import math
from dataclasses import replace

from .catalogue import plausible
from .decide import at_bound, own_parameters, passes
from .residuals import residual_sets
from .stats import compare

__all__ = ["SLOW_PAIR", "near_miss", "slow_pair"]

SLOW_PAIR = ("creep", "thermal_drift")


def near_miss(cmp, name, ok, bounds) -> bool:
    """Whether a candidate that failed (``cmp``, its plausibility ``ok`` and ``bounds`` as
    :func:`.decide.passes` takes them) failed only on the BIC gain and the likelihood ratio, with
    a gain above zero."""
    if cmp["dbic"] <= 0.0:
        return False
    return passes({**cmp, "dbic": math.inf, "p_lr": 0.0}, name, ok, bounds)[0]


def slow_pair(fitter, tried, current, struct, sets_cur, noise, cctx, step, rnd):
    """Fit creep and a drift together when both of ``tried`` (a round's entries) were near misses
    (:func:`near_miss`); returns ``(entry, other)``: the entry of the one with the larger BIC gain
    alone, passed, with the pair's note, and the other's name; or None."""
    near = {t["name"]: t for t in tried if t.get("near")}
    if not set(SLOW_PAIR) <= set(near) or fitter.out_of_time():
        return None
    creep, drift = near["creep"], near["thermal_drift"]
    dp = drift["fit"].params
    s = replace(creep["struct"].with_effect("thermal_drift"), drift_warmup=drift["struct"].drift_warmup)
    starts = []
    for pick in dict.fromkeys((creep["fit"].params.pick, dp.pick)):
        q = creep["fit"].params.copy()
        q.off_x, q.rate, q.curv, q.drift_tau, q.pick = dp.off_x, dp.rate, dp.curv, dp.drift_tau, pick
        starts.append(q)
    fr = min((fitter.fit(q, s, max_nfev=10) for q in starts), key=lambda f: f.cost)
    sets_new, _ = residual_sets(fitter, fr.params)
    cmp = compare(sets_cur, sets_new, s.n_params() - struct.n_params(), noise, slow=True)
    why = []
    for name in SLOW_PAIR:
        ok = plausible(name, fitter, current, fr.params, cmp, cctx, s)
        bounds = at_bound(fitter, fr.params, own_parameters(name, struct, struct.with_effect(name)))
        passed, w = passes(cmp, name, ok, bounds)
        if not passed:
            why.append(f"{name}: {w}")
    gains = f"BIC gains alone: creep {creep['cmp']['dbic']:.1f}, thermal_drift {drift['cmp']['dbic']:.1f}"
    if why:
        step(f"round {rnd + 1}: creep and thermal_drift fail alone on the BIC gain only ({gains}); together "
             f"they fail too ({'; '.join(why)})")
        return None
    first, other = (creep, drift) if creep["cmp"]["dbic"] >= drift["cmp"]["dbic"] else (drift, creep)
    note = (f"passes with {other['name']} beside it: together BIC gain {cmp['dbic']:.1f} ({gains}); "
            f"{other['name']} must pass on its own next")
    step(f"round {rnd + 1}: creep and thermal_drift fail alone on the BIC gain only; together they pass "
         f"(BIC gain {cmp['dbic']:.1f}, {gains}): {first['name']} added first")
    return {**first, "passed": True, "why": "", "note": "; ".join(n for n in (first["note"], note) if n),
            "pair": other["name"]}, other["name"]
