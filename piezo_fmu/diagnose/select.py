"""Naming the missing physics: forward selection over the catalogue with a backward check.

Each round every candidate is screened cheaply (:func:`.catalogue.propose`), the most promising
ones are fitted with every coupled parameter re-identified (the ordinary physics of the
recalibration included when the candidate acts in the same band), and compared with the current
model by statistics that hold under noise (:func:`.stats.compare`). A candidate passes when

* the likelihood-ratio test and BIC (effective sample size) pass on the training rows;
* it removes at least :data:`ACCEPT` ``explained`` of the structured residual on its best channel;
* the held-out blocks confirm its correction (regression slope and significance);
* no channel gets worse on held-out data;
* its fitted values are physical and show its signature (:func:`.catalogue.plausible`), and none
  of its own parameters sits at a bound of its search range (a value at a bound is the search
  telling that the mechanism is not what the data want: it is reported as such, never accepted).

The best passing candidate is added and every parameter settled; repeat. Afterwards every
accepted mechanism is removed again in turn and must still pass (backward check). The
**confidence** of each finding (:func:`confidence`) decides where it is reported: at 0.5 or more
it is a finding (``final.effects``, model.toml); below, a *candidate* with its rival.
"""
from __future__ import annotations

import math

import numpy as np

from .catalogue import CATALOGUE, plausible, propose, residual_peaks, shape_size
from .fit import Fitter, free_names, get_value, strip
from .residuals import ACCEPT, full_residuals, residual_sets
from .stats import compare, noise_level

__all__ = ["ACCEPT", "CONFIDENT", "confidence", "full_residuals", "noise_levels", "residual_sets", "select"]

CONFIDENT = 0.5              # findings at or above this confidence are named; below: candidates
# a finer loop is missing loop shape when it explains most of what is left (this share of the
# structured residual on its best channel) by at least three times the noise (removed structured
# rms, in noise rms); one that only trims a residual whose larger part stays, or removes less, is
# approximating a loop of another kind (another hysteresis family, other thresholds) or bending to
# another misfit: an ordinary difference, taken into the recalibration, not named. A device's own
# loop of another family lies up to ~1.5 noise rms from the best nine-operator PI (the rig's clean
# devices do), a loop shape worth a name 3 or more (both generators' present shapes). Twice was
# enough for play operators alone; the KP cells bend further: a leakage's, a drift's and a current
# limit's leftovers gave 2.1-2.4 (rig-053, 035, 023), named shapes 3.2-10 (rig-041, 030, 027)
SHAPE_EXPLAINED = 0.7
SHAPE_REMOVED = 3.0
SHAPE_LAST = 0.8           # a physical mechanism explaining this share of what a finer loop does goes first
CREEP_BEFORE_DRIFT = 0.03  # a drift in both channels must explain this much more of the structured
                           # residual (share, mean over channels) than a creep element

# a further mode where the device's first mode would do must beat it by "positive" evidence (a BIC
# difference of 2, Kass & Raftery 1995), not by a tie (rig-179, displacement only: the two are
# the same dynamics, BIC 0.1); less than the naming threshold: a further mode beside a first mode
# above the Nyquist frequency is told apart only by how it reaches the two channels (rig-025: 5.1)
MODE_EVIDENCE = 2.0

ORDINARY_ADOPTIONS = 2     # times a search may hand a better fit of the ordinary physics to the recalibration

SLOW = {"creep", "sensor_leakage", "thermal_drift"}
FAST = {"time_delay", "amplifier_current_limit", "extra_resonance"}


def _physics_before_shape(best, tried, step, rnd):
    """A loop shape wins a round only clearly: a passing physical mechanism that explains at least
    :data:`SHAPE_LAST` as much goes first (the cells of a loop shape bend to the distortion of a
    slew-limited step too, rig-006; a shape still missing is added in the next round, and the
    backward check drops the mechanism if the shape makes it unnecessary)."""
    if best["name"] != "hysteresis_shape":
        return best
    phys = [t for t in tried if t["passed"] and t["name"] != "hysteresis_shape"]
    if not phys:
        return best
    alt = max(phys, key=lambda t: _score(t["cmp"], t["name"]))
    if _score(alt["cmp"], alt["name"]) >= SHAPE_LAST * _score(best["cmp"], best["name"]):
        step(f"round {rnd + 1}: {alt['name']} explains nearly as much as a finer loop: the physical reading first")
        return alt
    return best


def _ordinary_found(fitter, tried, current, struct, p_base, sets_cur, noise):
    """A failed candidate's fit that owes its gain to the ordinary physics re-fitted with it (the
    lag, the first mode, the weights moved to a better optimum while the candidate's own parameter
    stayed inert: a current limit that never binds, a negligible creep gain): that fit with the
    candidate switched off, re-fitted, when it beats the current model by BIC (> 10, effective
    sample size, no added parameter) with no channel worse on held-out data. Returns
    ``(params, name, dbic)`` or None."""
    t = max(tried, key=lambda t: _score(t["cmp"], t["name"]))
    if not (t["fit"].cost < fitter.cost(current) and _score(t["cmp"], t["name"]) > ACCEPT["explained"]):
        return None
    q = fitter.fit(strip(t["fit"].params.hold_cells(False), struct, p_base.thresholds), struct, max_nfev=8).params
    cmp = compare(sets_cur, residual_sets(fitter, q)[0], 0, noise)
    worse = any(v["rel_improvement"] < -ACCEPT["worse"] for v in cmp["channels"].values())
    if cmp["dbic"] > ACCEPT["dbic"] and cmp["p_lr"] < ACCEPT["p_lr"] and not worse:
        return q, t["name"], cmp["dbic"]
    return None


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
        lo, hi = fitter.bounds(n)
        v = get_value(p, n, fitter.dev)
        span = math.log(hi / lo)
        x = math.log(max(v, 1e-300) / lo) / span if span > 0 else 0.5
        if x <= ACCEPT["bound"] or x >= 1.0 - ACCEPT["bound"]:
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
    structured residual unexplained: see :func:`_closeness`)."""
    mech = CATALOGUE[name]
    chans = [c for c in mech.channels if c in cmp["channels"]]
    explained = max(cmp["channels"][c]["explained"] for c in chans)
    s_evidence = 1.0 - math.exp(-max(cmp["dbic"], 0.0) / 30.0)
    s_size = min(1.0, max(explained, 0.0) / 0.5)
    s_heldout = float(np.clip(cmp["beta_heldout"], 0.0, 1.0)) * (1.0 - math.exp(-max(cmp["z_heldout"], 0.0) / 3.0))
    s_unique = 1.0 - 0.7 * float(np.clip(alt_share, 0.0, 1.0))
    return float(np.clip(s_evidence * s_size * s_heldout * s_unique, 0.0, 1.0))


def _removed(v):
    """Structured rms a candidate removes from one channel, in multiples of its noise."""
    after = math.sqrt(max(v["rmse_after"] ** 2 - v["noise"] ** 2, 0.0))
    return math.sqrt(max(v["structured_before"] ** 2 - after ** 2, 0.0)) / max(v["noise"], 1e-300)


def _closeness(best, other):
    """How close a rival comes to the best candidate, 0..1, by what each leaves unexplained (its
    structured residual share): a rival that leaves thirty times more (explaining 0.84 where the best
    explains 0.995) is no real alternative; one that leaves as much is."""
    left_best = 1.0 - float(np.clip(best, 0.0, 1.0))
    left_other = 1.0 - float(np.clip(other, 0.0, 1.0))
    return float(np.clip(left_best / max(left_other, 1e-9), 0.0, 1.0))


def _score(cmp, name):
    """Rank passing candidates: structured residual removed, averaged over every recorded channel
    (a mechanism that explains both channels beats one that explains one), BIC as tie-break."""
    ex = [max(v["explained"], 0.0) for v in cmp["channels"].values()]
    return float(np.mean(ex)) + 1e-3 * cmp["dbic"] / max(1.0, abs(cmp["dbic"]))


def at_noise(sets, noise, level=0.3):
    """True when every channel's held-out residual is within ``level`` x noise of pure noise."""
    for c, v in sets.items():
        mse = float(np.mean(v["heldout"] ** 2))
        if math.sqrt(max(mse - noise[c] ** 2, 0.0)) > level * noise[c]:
            return False
    return True


def coupled(fitter, name, struct, s_new):
    """Nonlinear parameters fitted with candidate ``name``: the amplifier lag, the candidate's own,
    and those of accepted mechanisms acting in the same band (slow: creep, leakage, drift; fast:
    delay, current limit, mode) and, for a fast candidate, the ordinary fast physics (second lag
    stage, first mode), which it may trade off against. The final fit frees them all."""
    if name == "hysteresis_shape":
        return ["tau"]
    group = SLOW if name in SLOW else FAST
    owner = {"creep": "creep", "tau_leak": "sensor_leakage", "slew": "amplifier_current_limit",
             "res_": "extra_resonance"}
    old = set(free_names(struct, fitter.ordinary))
    keep = []
    for n in free_names(s_new, fitter.ordinary):
        mech = next((m for k, m in owner.items() if n.startswith(k)), None)
        if n in ("tau", "y_sat") or n not in old or mech in group or (n in fitter.ordinary and name in FAST):
            keep.append(n)
    return keep


def refine_delay(fitter, p, struct, reach=3):
    """Step the integer delay while the training cost, with the lag re-searched and the weights
    re-solved (the loop's width trades off against lag, so they must move with it), falls."""
    dt = fitter.dt
    nd = int(round(p.delay / dt))

    def at(k, tau):
        q = p.copy()
        q.delay = k * dt
        lo = max(fitter.bounds("tau")[0], tau / 4)
        return fitter.fit_scalar(q, struct, "tau", quick=False, bounds=(lo, tau * 4), xatol=0.02)

    best, best_c = at(nd, p.tau)
    for direction in (1, -1):
        moved = False
        for k in range(1, reach + 1):
            if nd + direction * k < 1:
                break
            q, c = at(nd + direction * k, max(best.tau - direction * dt, p.tau / 10))
            if c < best_c:
                best, best_c, moved = q, c, True
            else:
                break
        if moved:
            break
    return best


def _free(fitter, name, struct, s_new, dropped):
    from .recalibrate import ITEM_PARAMS
    gone = {n for it in dropped for n in ITEM_PARAMS[it]}
    return [n for n in coupled(fitter, name, struct, s_new) if n not in gone]


def _bic_worth(fitter, fr, dropped):
    """-BIC (up to a constant) of a fitted candidate that does without the ordinary items ``dropped``."""
    from .recalibrate import ITEM_K
    k = -sum(ITEM_K[i] for i in dropped)
    return -fitter.n_eff * math.log(max(fr.cost, 1e-300)) - k * math.log(max(fitter.n_eff, 2.0))


def _simpler(fitter, name, struct, s_new, fr, recal, step, dropped=()):
    """A fast candidate may explain what a fast ordinary item (the first mode, a second lag stage,
    a sampling lag) had absorbed: try it without each of them; keep the simpler model when the
    fit is as good as the extra parameters are worth (BIC, effective sample size). Returns the
    fit and the items it does without."""
    from .recalibrate import ITEM_K, present, without

    dropped = list(dropped)
    if recal is None or name not in FAST:
        return fr, dropped
    for item in present(fitter, recal):
        if item in dropped:
            continue
        q = without(fr.params, item, recal)
        free = _free(fitter, name, struct, s_new, dropped + [item])
        alt = fitter.fit(q, s_new, free=free, max_nfev=10, held=True)
        worth = fitter.n_eff * math.log(max(fr.cost, 1e-300) / max(alt.cost, 1e-300)) + ITEM_K[item] * math.log(
            max(fitter.n_eff, 2.0))
        if worth > 0:
            step(f"{name} explains what the ordinary {item} had taken (BIC {worth:.1f} for the simpler model)")
            fr, dropped = alt, dropped + [item]
    return fr, dropped


def _drift_both(tried):
    """The passing thermal drift among ``tried`` that reaches both channels (a sensor on the push
    rod: a pick-off the data did not identify), or ``None``."""
    return next((t for t in tried if t["name"] == "thermal_drift" and t["passed"]
                 and t["fit"].params.pick == "load" and "us" in t["cmp"]["channels"]), None)


def _creep_before_drift(best, tried, struct, step, rnd):
    """A drift that moves both channels competes with a slow creep element (both move both
    channels; a creep element slower than the record grows with the stroke's integral, a trend
    under a unipolar drive). When creep is already in the model, or passed beside the drift, and
    explains within ``CREEP_BEFORE_DRIFT`` of the drift's share, creep is kept: it needs no
    assumption about the pick-off, which the data did not identify."""
    drift = _drift_both(tried)
    creep = next((t for t in tried if t["name"] == "creep" and t["passed"]), None)
    if best is not drift or creep is None:
        return best
    gap = _score(drift["cmp"], drift["name"]) - _score(creep["cmp"], creep["name"])
    if gap > CREEP_BEFORE_DRIFT:
        return best
    what = "a further creep element" if "creep" in struct.effects else "creep"
    step(f"round {rnd + 1}: {what} explains within {gap:.3f} of a drift that would need the sensor on the "
         "push rod (a pick-off the data did not identify): creep kept")
    return creep


def _drift_or_creep(fitter, current, struct, findings, rejected, p_base, noise, cctx, step):
    """With creep and a drift that reaches both channels accepted, try the drift as one more creep
    element (a slow element grows with the stroke's integral: a trend under a unipolar drive).
    When that model is within the BIC threshold of the one with the drift (the same number of
    parameters, or fewer), the drift is not needed: creep takes its place. Returns ``(p, struct,
    findings)``."""
    names = {f["name"] for f in findings}
    if not {"creep", "thermal_drift"} <= names or current.pick != "load" or struct.creep_order >= 2:
        return current, struct, findings
    step("checking whether a further creep element explains the drift in both channels")
    s_wo = struct.without("thermal_drift")
    base = strip(current, s_wo, p_base.thresholds)
    base.pick = p_base.pick
    start = propose("creep", fitter, base, s_wo, cctx)
    if start is None:
        return current, struct, findings
    s_sw = s_wo.with_effect("creep", 0, len(start.creep))
    fr = fitter.fit(start, s_sw, max_nfev=10)
    full = fitter.cost(current)
    k = struct.n_params() - s_sw.n_params()
    worth = fitter.n_eff * math.log(max(fr.cost, 1e-300) / max(full, 1e-300)) - k * math.log(max(fitter.n_eff, 2.0))
    need = ACCEPT["dbic"]
    if worth >= need:
        step(f"the drift stays: creep in its place leaves a BIC {worth:.1f} worse")
        return current, struct, findings
    step(f"creep with {len(fr.params.creep)} elements explains the drift in both channels as well (BIC "
         f"{worth:.1f} < {need:g} for the drift): creep kept, the drift dropped")
    rejected.append({"effect": "thermal_drift",
                     "why": f"a further creep element explains it as well (BIC difference {worth:.1f} < {need:g}); "
                            "a drift in both channels would also need the sensor on the push rod"})
    sets_new, _ = residual_sets(fitter, fr.params)
    for f in findings:
        if f["name"] == "creep":
            f["after"] = fr.params
            f["rmse_after"] = {c: float(np.sqrt(np.mean(v["heldout"] ** 2))) for c, v in sets_new.items()}
            if f.get("rival", {}) and f["rival"].get("effect") == "thermal_drift":
                f["alt_share"] = 0.0
    findings = [f for f in findings if f["name"] != "thermal_drift"]
    noise.update(noise_levels(fitter, fr.params)[0])
    return fr.params, s_sw, findings


def _resonance_or_mode(fitter, best, struct, p_base, recal, cctx, step, rnd):
    """A further mode found while the device's own first mode was not identified (the residual
    that hid it was another's, or the sample rate left it to the mechanism's search), or one that
    takes the identified first mode's place, may be that first mode: ordinary physics, not a
    missing mechanism (rig-098, 179: a "further mode" at the device's first mode, 232 and 441 Hz).
    The first mode is fitted from the found frequency and damping, with the pick-offs the channels
    allow; when it explains the data as well as the further mode (BIC with the effective sample
    size, the further mode's parameters against the first mode's and its pick-off's, within
    ``MODE_EVIDENCE``), the first mode is recalibrated and nothing is named. Returns the new
    parameters or ``None``."""
    from .recalibrate import ITEM_K, adopt_mode, drop, mode_at

    if best["name"] != "extra_resonance" or recal is None or (
            "mech_f" in fitter.ordinary and "mode" not in best["dropped"]):
        return None
    f, z = best["fit"].params.res
    base = strip(best["fit"].params, struct, p_base.thresholds)
    fr = mode_at(fitter, base, struct, f, z, without_items=best["dropped"])
    if fr is None:
        step(f"round {rnd + 1}: the first mode started at {f:.4g} Hz settles at the end of its range: "
             "the further mode stays")
        return None
    # both without the ordinary items the further mode explained (``dropped``)
    # (the pick-off counts only where there is a choice: with the displacement alone it is the stack)
    k_mode = ITEM_K["mode"] - (0 if "us" in cctx["channels"] else 1)
    k = (best["struct"].n_params() - struct.n_params()) - k_mode
    worth = fitter.n_eff * math.log(max(fr.cost, 1e-300) / max(best["fit"].cost, 1e-300)) \
        - k * math.log(max(fitter.n_eff, 2.0))
    f1, z1 = fr.params.mode(fitter.dev)
    if worth >= MODE_EVIDENCE:
        step(f"round {rnd + 1}: the further mode at {f:.4g} Hz beats the first mode there (BIC {worth:.1f})")
        return None
    step(f"round {rnd + 1}: the mode at {f:.4g} Hz is the device's first mode ({f1:.4g} Hz, zeta {z1:.3g}, "
         f"sensor on {fr.params.pick}; the further mode would gain BIC {worth:.1f}): recalibrated, not named")
    adopt_mode(fitter, recal, fr.params, why=f"found in round {rnd + 1} where a further mode was searched "
                                             f"(it explains the mode as well: BIC difference {worth:.1f})")
    for item in best["dropped"]:
        if item != "mode":
            drop(fitter, recal, item, why="the first mode explains it")
    return recal.params


def select(fitter: Fitter, p_base, struct_nom, noise, cctx, step, max_rounds=5, revisit=None, recal=None):
    """Forward selection with a backward check. Returns ``(p, struct, findings, candidates,
    rejected)``; findings and candidates carry their comparison statistics and ``confidence``.
    ``revisit(p, struct)``, called after each finding, may return better ordinary parameters
    (an ordinary item the finding's residual had hidden) or ``None``."""
    current, struct = p_base, struct_nom
    findings, rejected = [], []
    adopted = 0
    sets_cur, _ = residual_sets(fitter, current)
    budget_note = None
    for rnd in range(max_rounds):
        if fitter.out_of_time():
            budget_note = f"time budget reached after {rnd} round(s): no further candidates searched"
            step(budget_note)
            break
        if rnd > 0 and at_noise(sets_cur, noise, level=0.1):
            # (the first round always looks: a mechanism acting in a few short segments, steps for
            # instance, hardly moves the residual's overall level)
            step("the residual is at the noise floor: nothing more to explain")
            break
        # creep may add an element and a named loop shape a finer grid of cells (propose says when)
        names = [n for n in CATALOGUE if n not in struct.effects or n in ("creep", "hysteresis_shape")]
        q0 = fitter.quick(current)
        if rnd > 0:
            # peaks of what is left now (the first round's residual may be dominated by something else)
            cctx["peaks"] = residual_peaks(fitter, current)
        screened = []
        # while other mechanisms are searched a loop shape found before keeps its form (its cells'
        # weights held in their ratios, one scale free): one column instead of tens; the final fit
        # frees them again
        held = current.hold_cells()
        for i, name in enumerate(names):
            step(f"round {rnd + 1}: screening {name} ({i + 1}/{len(names)})")
            start = propose(name, fitter, current if name == "hysteresis_shape" else held, struct, cctx)
            alt = None
            if name in FAST and recal is not None:
                # a fast mechanism may be what the fast ordinary items stand in for: screen it also
                # from the model without them (both are fitted; the better by BIC is kept)
                from .recalibrate import present, without
                items = present(fitter, recal)
                if items:
                    base = held
                    for it in items:
                        base = without(base, it, recal)
                    a = propose(name, fitter, base, struct, cctx)
                    alt = None if a is None else (a, items)
            if (name == "thermal_drift" and start is not None and start.pick == "stack"
                    and "us" in cctx["channels"] and "mech_f" not in fitter.ordinary):
                # without a visible first mode the pick-off is open: a sensor on the load spring
                # follows the push rod, and the drift reaches it too (both are fitted, the better
                # by BIC is kept)
                a = start.copy()
                a.pick = "load"
                alt = (a, [])
            if start is None and alt is None:
                continue
            # the screening's cost with the weights re-solved for the proposed dynamics (held
            # weights fitted to other dynamics would make a good proposal look bad)
            for x in (start, alt and alt[0]):
                if x is not None and name != "hysteresis_shape":
                    fitter.varpro(x, struct.with_effect(name, 0, len(x.creep)))
            q = min(fitter.quick(x, drift=name == "thermal_drift") for x in (start, alt and alt[0]) if x is not None)
            screened.append((q0 - q, name, start, alt))
        screened.sort(key=lambda s: -s[0])
        step(f"round {rnd + 1}: screening gains " + ", ".join(f"{n} {g / max(q0, 1e-300):.3g}" for g, n, _, _ in screened))
        tried = []
        # the loop shape's cells can bend to much that is not a loop shape: the physical candidates
        # are measured against the best of them, not against the shape
        top = max([g for g, n, _, _ in screened if n != "hysteresis_shape"] + [0.0])
        for i, (gain, name, start, alt) in enumerate(screened[:4]):
            # the best screened candidate, the next ones when they come close to it, and further ones
            # (down the screening order) as long as nothing tried so far passed
            if gain <= 0 or (i >= 1 and gain < 0.4 * top and any(t["passed"] for t in tried)
                             and not (name == "creep" and _drift_both(tried))):
                continue
            if i >= 1 and fitter.out_of_time():
                budget_note = "time budget reached: the weaker screened candidates were not fitted"
                break
            step(f"round {rnd + 1}: fitting {name} (with the lag and every coupled parameter)")
            s_new = struct.with_effect(name, shape_size(start, p_base.thresholds), len(start.creep))
            fits = []
            for st, dropped0 in ((start, []), alt or (None, None)):
                if st is None:
                    continue
                free = _free(fitter, name, struct, s_new, dropped0)
                fr = fitter.fit(st, s_new, free=free, max_nfev=10, held=name in FAST)
                if name == "time_delay":
                    # the screening's integer delay trades off against the lag: step it, then re-fit
                    q = refine_delay(fitter, fr.params, s_new)
                    if q.delay != fr.params.delay:
                        fr = fitter.fit(q, s_new, free=free, max_nfev=6, held=True)
                fits.append(_simpler(fitter, name, struct, s_new, fr, recal, step, dropped0))
            fr, dropped = max(fits, key=lambda f: _bic_worth(fitter, f[0], f[1]))
            sets_new, _ = residual_sets(fitter, fr.params)
            from .recalibrate import ITEM_K
            k = s_new.n_params() - struct.n_params() - sum(ITEM_K[i] for i in dropped)
            cmp = compare(sets_cur, sets_new, k, noise)
            ok = plausible(name, fitter, current, fr.params, cmp, cctx)
            bounds = at_bound(fitter, fr.params, own_parameters(name, struct, s_new))
            passed, why = passes(cmp, name, ok, bounds)
            step(f"round {rnd + 1}: {name}: " + ("passes" if passed else f"fails ({why})") + "; held-out rmse "
                 + ", ".join(f"{c} {v['rmse_before']:.4g} -> {v['rmse_after']:.4g} (explains {v['explained']:.2f}, "
                             f"held-out beta {v['beta_heldout']:.2f}, z {v['z_heldout']:.1f})"
                             for c, v in cmp["channels"].items())
                 + f"; training cost {fitter.cost(current):.5g} -> {fr.cost:.5g}")
            tried.append({"name": name, "fit": fr, "cmp": cmp, "passed": passed, "why": why,
                          "note": ok[1], "struct": s_new, "sets": sets_new, "bounds": bounds, "dropped": dropped})
        if not any(t["passed"] for t in tried):
            better = None if adopted >= ORDINARY_ADOPTIONS else _ordinary_found(fitter, tried, current, struct,
                                                                                  p_base, sets_cur, noise)
            if better is not None:
                adopted += 1
                step(f"round {rnd + 1}: the search for {better[1]} found a better fit of the ordinary physics "
                     f"(dBIC {better[2]:.0f} with {better[1]} switched off): taken into the recalibration")
                current = better[0]
                if recal is not None:
                    recal.params = current
                noise.update(noise_levels(fitter, current)[0])
                sets_cur, _ = residual_sets(fitter, current)
                continue
            rejected += [{"effect": t["name"], "why": t["why"], **({"at_bound": t["bounds"]} if t["bounds"] else {})}
                         for t in tried]
            break
        best = max((t for t in tried if t["passed"]), key=lambda t: _score(t["cmp"], t["name"]))
        best = _physics_before_shape(best, tried, step, rnd)
        best = _creep_before_drift(best, tried, struct, step, rnd)
        as_mode = _resonance_or_mode(fitter, best, struct, p_base, recal, cctx, step, rnd)
        if as_mode is not None:
            rejected.append({"effect": "extra_resonance", "why": "the device's own first mode: refitted as "
                             "that mode from where the search found it, taken into the recalibration"})
            current = fitter.fit(as_mode, struct, max_nfev=10).params
            recal.params = current
            noise.update(noise_levels(fitter, current)[0])
            sets_cur, _ = residual_sets(fitter, current)
            continue
        if best["name"] == "hysteresis_shape" and "hysteresis_shape" not in struct.effects:
            removed = max(_removed(v) for v in best["cmp"]["channels"].values())
            explained = max(v["explained"] for v in best["cmp"]["channels"].values())
            if removed < SHAPE_REMOVED or explained < SHAPE_EXPLAINED:
                step(f"round {rnd + 1}: the finer loop explains {100 * explained:.0f} % ({removed:.2f} x the "
                     "noise): an ordinary loop difference, taken into the recalibration (not named)")
                struct = struct.refine(shape_size(best["fit"].params, p_base.thresholds))
                current = fitter.fit(best["fit"].params, struct, max_nfev=10).params
                if recal is not None:
                    recal.report["loop"] = {"operators": len(current.thresholds), "kp_cells": current.n_cells,
                                            "refined": True,
                                            "removed_noise_multiples": round(removed, 2),
                                            "explained_share": round(explained, 3)}
                sets_cur, _ = residual_sets(fitter, current)
                continue
        # the strongest competitor on the same residual (a failed one counts half)
        b_score = _score(best["cmp"], best["name"])
        # (a finer loop's cells bend to much of any residual: they rival a loop shape, not physics
        # the loop cannot have, which _physics_before_shape already put first)
        others = [(_closeness(b_score, _score(t["cmp"], t["name"])) * (1.0 if t["passed"] else 0.5), t)
                  for t in tried if t is not best
                  and (t["name"] != "hysteresis_shape" or best["name"] == "hysteresis_shape")]
        alt = max([a for a, _ in others] + [0.0])
        rival = max(others, key=lambda o: o[0])[1] if others else None
        step(f"round {rnd + 1}: added {best['name']}")
        prev = next((f for f in findings if f["name"] == best["name"]), None)
        if prev is not None:
            # a further creep element refines the same finding
            prev["after"] = best["fit"].params
            prev["rmse_after"] = {c: v["rmse_after"] for c, v in best["cmp"]["channels"].items()}
            prev.setdefault("more", []).append(best["cmp"])
        else:
            findings.append({"name": best["name"], "cmp": best["cmp"], "before": current,
                             "after": best["fit"].params, "note": best["note"],
                             "alt_share": alt,
                             "alternatives": [t["name"] for t in tried if t is not best],
                             "rival": None if rival is None else {
                                 "effect": rival["name"], "passed": rival["passed"],
                                 "explained_share": {c: round(v["explained"], 4)
                                                     for c, v in rival["cmp"]["channels"].items()}},
                             "rmse_after": {c: v["rmse_after"] for c, v in best["cmp"]["channels"].items()}})
        rejected += [{"effect": t["name"], "why": t["why"] or "another candidate explained more",
                      **({"at_bound": t["bounds"]} if t["bounds"] else {})}
                     for t in tried if t is not best and not t["passed"]]
        current, struct = best["fit"].params, best["struct"]
        if best["dropped"]:
            from .recalibrate import drop
            recal.params = current
            for item in best["dropped"]:
                drop(fitter, recal, item, why=f"{best['name']} explains it")
            current = recal.params
        # settle every parameter with the new mechanism in before the next round compares against it
        current = fitter.fit(current, struct, max_nfev=15).params
        if revisit is not None and (best["name"] in FAST or len(findings) == 1) \
                and not fitter.out_of_time():
            # a dominant residual may have hidden an ordinary item: after the first finding and
            # after fast ones (slow mechanisms do not hide lags or modes once a finding is in)
            again = revisit(current, struct)
            if again is not None:
                current = again
        # the noise level from the better model's residual (less misfit passing for noise)
        noise.update(noise_levels(fitter, current)[0])
        sets_cur, _ = residual_sets(fitter, current)

    if current.cells_held:
        current = fitter.fit(current.hold_cells(False), struct, max_nfev=6).params
    # -- backward check: every accepted mechanism must still be needed ---------------------------------
    added = list(dict.fromkeys(f["name"] for f in findings))
    if len(added) >= 2:
        sets_full, _ = residual_sets(fitter, current)
        for name in added:
            step(f"checking that {name} is still needed with the others in the model")
            s_wo = struct.without(name)
            fr = fitter.fit(strip(current, s_wo, p_base.thresholds), s_wo, max_nfev=5)
            cmp = compare(residual_sets(fitter, fr.params)[0], sets_full,
                          struct.n_params() - s_wo.n_params(), noise)
            ok = plausible(name, fitter, fr.params, current, cmp, cctx)
            passed, why = passes(cmp, name, ok)
            if not passed:
                step(f"dropped {name}: {why}")
                findings = [f for f in findings if f["name"] != name]
                rejected.append({"effect": name, "why": f"not needed once the others are in: {why}"})
                current, struct = fr.params, s_wo
                sets_full, _ = residual_sets(fitter, current)
            else:
                for f in findings:
                    if f["name"] == name:
                        f["backward"] = cmp
    if not fitter.out_of_time():
        current, struct, findings = _drift_or_creep(fitter, current, struct, findings, rejected, p_base, noise,
                                                    cctx, step)
    accepted = {f["name"] for f in findings}
    for f in findings:
        # a rival that is itself accepted explained another part of the residual (two mechanisms),
        # not the same part another way: it does not make this finding less unique
        rival = (f.get("rival") or {}).get("effect")
        alt = 0.0 if rival in accepted else f["alt_share"]
        f["confidence"] = confidence(f["cmp"], f["name"], alt)

    # -- weak findings become candidates: the model keeps only the confident ones -----------------------
    weak = [f for f in findings if f["confidence"] < CONFIDENT]
    if weak:
        for f in weak:
            step(f"{f['name']}: confidence {f['confidence']:.2f} < {CONFIDENT}: a candidate, not named")
            struct = struct.without(f["name"])
        current = fitter.fit(strip(current, struct, p_base.thresholds), struct, max_nfev=6).params
    strong = [f for f in findings if f["confidence"] >= CONFIDENT]
    if budget_note:
        rejected.append({"effect": "-", "why": budget_note})
    return current, struct, strong, weak, rejected
