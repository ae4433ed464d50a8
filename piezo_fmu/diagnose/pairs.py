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

import copy
import math
from dataclasses import replace

from .catalogue import plausible
from .decide import at_bound, own_parameters, passes
from .residuals import residual_sets
from .stats import compare

__all__ = ["OWN_FIELDS", "PARTNERS", "SLOW_PAIR", "cross_miss", "cross_pair", "near_miss", "slow_pair"]

SLOW_PAIR = ("creep", "thermal_drift")
PARTNERS = 2    # a cross miss is fitted beside at most this many other candidates of its round
# the fields of :class:`.model_io.Params` each mechanism brings (a pair's start takes them from its own fit)
OWN_FIELDS = {"creep": ("creep",), "sensor_leakage": ("tau_leak", "leak_settled"),
              "amplifier_current_limit": ("slew",), "time_delay": ("delay",),
              "extra_resonance": ("res", "res_at"), "thermal_drift": ("off_x", "rate", "curv", "drift_tau", "pick")}


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
    cmp, why = _fitted(fitter, starts, s, SLOW_PAIR, current, struct, sets_cur, noise, cctx, True)
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
    return _added(first, other, note)


def _fitted(fitter, starts, s, names, current, struct, sets_cur, noise, cctx, slow):
    """A pair ``names`` of structure ``s`` fitted from ``starts`` (the best fit kept), compared with
    ``current`` and tested as each of its members would be: ``(cmp, why)``, ``why`` the failures."""
    fr = min((fitter.fit(q, s, max_nfev=10) for q in starts), key=lambda f: f.cost)
    sets_new, _ = residual_sets(fitter, fr.params)
    cmp = compare(sets_cur, sets_new, s.n_params() - struct.n_params(), noise, slow=slow)
    why = []
    for name in names:
        ok = plausible(name, fitter, current, fr.params, cmp, cctx, s)
        bounds = at_bound(fitter, fr.params, own_parameters(name, struct, struct.with_effect(name)))
        passed, w = passes(cmp, name, ok, bounds)
        if not passed:
            why.append(f"{name}: {w}")
    return cmp, why


def _added(first, other, note):
    """The round's entry of ``first``, passed for the pair (``note`` added), and ``other``'s name."""
    return {**first, "passed": True, "why": "", "note": "; ".join(n for n in (first["note"], note) if n),
            "pair": other["name"]}, other["name"]


def cross_miss(cmp, name, ok, bounds) -> bool:
    """Whether a candidate that failed failed only because a channel got worse on held-out data."""
    if name not in OWN_FIELDS:
        return False
    spared = {c: {**v, "rel_improvement": max(v["rel_improvement"], 0.0)} for c, v in cmp["channels"].items()}
    return passes({**cmp, "channels": spared}, name, ok, bounds)[0]


def cross_pair(fitter, tried, current, struct, sets_cur, noise, cctx, step, rnd, slow=()):
    """Fit two mechanisms together when one of ``tried`` (a round's entries) failed only because it
    made a channel worse (:func:`cross_miss`): alone it pulls the shared parameters towards its own
    channel's misfit and spoils the other channel's, which another mechanism explains (rig-d39-038,
    a current limit in x and a leaking sensor in us: leakage alone took us's held-out error from
    0.031 to 0.0075 V and made x 9 % worse, the limit alone made x 5 % worse). Its partners: the
    :data:`PARTNERS` other candidates of the round that lowered the training cost most, whatever
    their own verdict (beside the misfit the first leaves, the partner's own evidence is not
    measurable). The pair must pass every test as each of its members would; the one that failed only
    on a channel made worse goes in first (of two such, the one with the larger BIC gain alone) and
    the other must then pass on its own in a later round, or the first is taken back. ``slow``: the
    mechanisms compared away from the command's jumps (both must be). Returns ``(entry, other)``
    as :func:`slow_pair` does, or None."""
    cross = sorted((t for t in tried if t.get("cross") and not t["dropped"]), key=lambda t: t["fit"].cost)
    if not cross or fitter.out_of_time():
        return None
    a, cost_now = cross[0], fitter.cost(current)
    partners = sorted((t for t in tried if t["name"] not in (a["name"], "hysteresis_shape") and not t["dropped"]
                       and t["name"] in OWN_FIELDS and t["fit"].cost < cost_now), key=lambda t: t["fit"].cost)
    for b in partners[:PARTNERS]:
        if fitter.out_of_time():
            break
        out = _together(fitter, a, b, current, struct, sets_cur, noise, cctx, step, rnd, slow)
        if out is not None:
            return out
    return None


def _together(fitter, a, b, current, struct, sets_cur, noise, cctx, step, rnd, slow):
    """The pair of :func:`cross_pair`: ``a`` (a cross miss) and ``b`` fitted together from both
    fits' values; ``(entry, other)`` when the pair passes, else None."""
    s = a["struct"].with_effect(b["name"])
    starts = []
    for one, two in ((a, b), (b, a)):
        q = one["fit"].params.copy()
        for f in OWN_FIELDS[two["name"]]:
            setattr(q, f, copy.deepcopy(getattr(two["fit"].params, f)))
        starts.append(q)
    cmp, why = _fitted(fitter, starts, s, (a["name"], b["name"]), current, struct, sets_cur, noise, cctx,
                       a["name"] in slow and b["name"] in slow)
    names = f"{a['name']} (a channel made worse alone) and {b['name']}"
    if why:
        step(f"round {rnd + 1}: {names} fitted together fail too ({'; '.join(why)})")
        return None
    first, other = (b, a) if b.get("cross") and b["cmp"]["dbic"] > a["cmp"]["dbic"] else (a, b)
    note = (f"passes with {other['name']} beside it: together BIC gain {cmp['dbic']:.1f}, no channel worse; "
            f"{other['name']} must pass on its own next")
    step(f"round {rnd + 1}: {names} fitted together pass (BIC gain {cmp['dbic']:.1f}, held-out rmse "
         + ", ".join(f"{c} {v['rmse_before']:.4g} -> {v['rmse_after']:.4g}" for c, v in cmp["channels"].items())
         + f"): {first['name']} added first")
    return _added(first, other, note)
