"""Rivals settled for the ordinary or the simpler reading, around the selection of :mod:`.select`.

* a passing physical mechanism goes before a finer loop that explains little more
  (:func:`physics_before_shape`);
* a failed candidate whose fit owes its gain to the ordinary physics re-fitted with it hands that
  fit to the recalibration (:func:`ordinary_found`);
* a drift in both channels must beat one more creep element (:func:`creep_before_drift`, and
  :func:`drift_or_creep` after the backward check); a drift without creep beside it gives way to
  creep that fits better in its place (:func:`creep_for_drift`); creep's drift rival fitting
  clearly worse in its place at the end no longer lowers creep's confidence (:func:`drift_rival_settled`);
* a further mode where the device's first mode would do is that first mode
  (:func:`resonance_or_mode`);
* a delay where the amplifier's second lag stage would do is that stage (:func:`delay_or_lag`);
* a delay screened beside a named further mode is fitted even when its screening gained nothing
  (:func:`beside_named_mode`);
* a finding's confidence counts a rival that is in the model (named, or taken into the
  recalibration after it) as no rival (:func:`confidences`).
"""
from __future__ import annotations

import math

import numpy as np

from .catalogue import MODE_LIGHT, plausible, propose
from .decide import at_bound, confidence, noise_levels, own_parameters, passes, score
from .fit import Structure, free_names, get_value, strip
from .recalibrate import ITEM_K, ITEM_PARAMS, MAX_LAG, adopt_mode, drop, mode_at
from .residuals import ACCEPT, heldout_rmse, residual_sets
from .stats import compare

__all__ = ["ABSORBED_KEPT", "CREEP_BEFORE_DRIFT", "MODE_EVIDENCE", "ORDINARY_ADOPTIONS", "SHAPE_LAST",
           "beside_named_mode", "confidences", "creep_at_floor", "creep_before_drift", "creep_for_drift",
           "delay_or_lag", "drift_both", "drift_or_creep", "drift_rival_settled", "modes_exchanged", "ordinary_found",
           "physics_before_shape", "resonance_or_mode", "sampling_lag_rival", "shape_after_physics"]

SHAPE_LAST = 0.8           # a physical mechanism explaining this share of what a finer loop does goes first

CREEP_BEFORE_DRIFT = 0.03  # a drift in both channels must explain this much more of the structured
                           # residual (share, mean over channels) than a creep element

# a finding whose rival was taken into the recalibration after it is unique when the backward check
# (the others in, the rival as ordinary physics among them) keeps this share of its BIC gain
ABSORBED_KEPT = 0.5

# a further mode where the device's first mode would do must beat it by the evidence every name
# needs (ACCEPT["dbic"]): the first mode there is ordinary physics, the account a name must beat,
# not a tie (rig-179, displacement only: the two are the same dynamics, BIC 0.1). Until 2026-11-28
# "positive" evidence (2, Kass & Raftery 1995) sufficed, kept for rig-025 (5.1: a further mode
# beside a first mode above the Nyquist frequency, told apart only by how it reaches the two
# channels); on fresh devices that named a first mode as a further one: rig-d1-101 (2.8, beside a
# drift) and rig-d2-126 (6.9, a clean device)
MODE_EVIDENCE = ACCEPT["dbic"]

# a delay found with a one-stage amplifier must beat a second lag stage in its place (the same number
# of parameters) by "positive" evidence (a BIC difference of 2, Kass & Raftery 1995): over a drive
# slow against both (rig-010: chirps to 100 Hz, a 0.20 ms stage named as a 3-sample delay at
# 15.1 kHz) the two differ by a fraction of a percent
LAG_EVIDENCE = 2.0

# the drift may be taken by a third creep element (the search's limit is two): the rig's logarithmic
# creep over a 16-18 s record needs an element of a few ms, one of a few hundred, and one slower, which
# a drift in both channels had stood in for (rig-077, 115)
DRIFT_AS_CREEP = 3

ORDINARY_ADOPTIONS = 2     # times a search may hand a better fit of the ordinary physics to the recalibration


def shape_after_physics(screened):
    """The round's screening (``(gain, name, ...)``, best first) with a loop shape moved behind the
    physical mechanisms that screened at least :data:`SHAPE_LAST` of its gain: fitted first, they are
    what a round whose budget ends after one fit still tries (rig-d29-061, a delay and a drift at
    10.5 kHz: round 2 screened the shape 0.215 and the delay 0.209, fitted the shape, which went into
    the recalibration, and ran out of budget; given the time the delay passed and was named at 0.61).
    With time for both, both are fitted and :func:`physics_before_shape` decides as before (the
    caller takes the first four of the screening before reordering them: the same ones are fitted)."""
    shape = [s for s in screened if s[1] == "hysteresis_shape"]
    if not shape:
        return list(screened)
    ahead = [s for s in screened if s[1] != "hysteresis_shape" and s[0] >= SHAPE_LAST * shape[0][0] > 0]
    return ahead + [s for s in screened if all(s is not a for a in ahead)]


def physics_before_shape(best, tried, step, rnd):
    """A loop shape wins a round only clearly: a passing physical mechanism that explains at least
    :data:`SHAPE_LAST` as much goes first (the cells of a loop shape bend to the distortion of a
    slew-limited step too, rig-006; a shape still missing is added in the next round, and the
    backward check drops the mechanism if the shape makes it unnecessary)."""
    if best["name"] != "hysteresis_shape":
        return best
    phys = [t for t in tried if t["passed"] and t["name"] != "hysteresis_shape"]
    if not phys:
        return best
    alt = max(phys, key=lambda t: score(t["cmp"], t["name"]))
    if score(alt["cmp"], alt["name"]) >= SHAPE_LAST * score(best["cmp"], best["name"]):
        step(f"round {rnd + 1}: {alt['name']} explains nearly as much as a finer loop: the physical reading first")
        return alt
    return best


def ordinary_found(fitter, tried, current, struct, p_base, sets_cur, noise):
    """A failed candidate's fit that owes its gain to the ordinary physics re-fitted with it (the
    lag, the first mode, the weights moved to a better optimum while the candidate's own parameter
    stayed inert: a current limit that never binds, a negligible creep gain): that fit with the
    candidate switched off, re-fitted, when it beats the current model by BIC (> 10, effective
    sample size, no added parameter) with no channel worse on held-out data. Returns
    ``(params, name, dbic)`` or None (also when nothing was tried, or when the candidate's fit
    changed the ordinary structure itself, e.g. took the amplifier's second order)."""
    if not tried:
        return None
    t = max(tried, key=lambda t: score(t["cmp"], t["name"]))
    if not (t["fit"].cost < fitter.cost(current) and score(t["cmp"], t["name"]) > ACCEPT["explained"]):
        return None
    q0 = strip(t["fit"].params.hold_cells(False), struct, p_base.thresholds)
    if any(get_value(q0, n, fitter.dev) <= 0.0 for n in free_names(struct, fitter.ordinary)):
        return None     # the candidate changed the ordinary structure (a mode took the amplifier's 2nd order: rig-128)
    q = fitter.fit(q0, struct, max_nfev=8).params
    cmp = compare(sets_cur, residual_sets(fitter, q)[0], 0, noise)
    worse = any(v["rel_improvement"] < -ACCEPT["worse"] for v in cmp["channels"].values())
    if cmp["dbic"] > ACCEPT["dbic"] and cmp["p_lr"] < ACCEPT["p_lr"] and not worse:
        return q, t["name"], cmp["dbic"]
    return None


def drift_both(tried):
    """The passing thermal drift among ``tried`` that reaches both channels (a sensor on the push
    rod: a pick-off the data did not identify), or ``None``."""
    return next((t for t in tried if t["name"] == "thermal_drift" and t["passed"]
                 and t["fit"].params.pick == "load" and "us" in t["cmp"]["channels"]), None)


def creep_before_drift(fitter, best, tried, struct, step, rnd):
    """A drift that moves both channels competes with a slow creep element (both move both
    channels; a creep element slower than the record grows with the stroke's integral, a trend
    under a unipolar drive). When creep is already in the model, or passed beside the drift, and
    explains within ``CREEP_BEFORE_DRIFT`` of the drift's share, or fits the training data better
    (BIC, effective sample size, each with its own parameters), creep is kept: it needs no
    assumption about the pick-off, which the data did not identify. (The training fit decides
    since a drift on the load spring may settle, stop 94: synth-1055's creep, a 1.3 s warm-up in
    its place explaining 0.035 more of the held-out residual at a training cost of 12 591 against
    creep's 10 708, which then hid the 306 Hz mode beside it.)"""
    drift = drift_both(tried)
    creep = next((t for t in tried if t["name"] == "creep" and t["passed"]), None)
    if best is not drift or creep is None:
        return best
    gap = score(drift["cmp"], drift["name"]) - score(creep["cmp"], creep["name"])
    worth = _bic_behind(fitter, creep["fit"].cost, drift["fit"].cost,
                        creep["struct"].n_params() - drift["struct"].n_params())
    if gap > CREEP_BEFORE_DRIFT and worth >= 0.0:
        return best
    what = "a further creep element" if "creep" in struct.effects else "creep"
    why = (f"explains within {gap:.3f} of" if gap <= CREEP_BEFORE_DRIFT
           else f"fits the training data better (BIC {-worth:.1f}) than")
    step(f"round {rnd + 1}: {what} {why} a drift that would need the sensor on the push rod (a pick-off the data "
         "did not identify): creep kept")
    return creep


def drift_or_creep(fitter, current, struct, findings, rejected, p_base, noise, cctx, step, try_in=None):
    """With a drift and no creep accepted: :func:`creep_for_drift`. With creep and a drift that
    reaches both channels accepted, try the drift as one more creep element (a slow element grows
    with the stroke's integral: a trend under a unipolar drive). When that model is within the BIC
    threshold of the one with the drift (the same number of parameters, or fewer), the drift is not
    needed: creep takes its place. Returns ``(p, struct, findings)``.

    A drift of the displacement alone is not tried so: tried (2026-11-28), it dropped rig-d2-169's
    false drift (BIC -0.8) but on draw 3, the test, two true drifts beside creep (rig-d3-009 and
    063, BIC 7.5 and 9.6 < 10).

    With creep accepted beside no drift, a drift that was creep's rival is fitted in its place
    (``try_in``: the search's fit and tests of a candidate, :func:`.select.put_in`):
    :func:`drift_rival_settled`."""
    names = {f["name"] for f in findings}
    if "thermal_drift" in names and "creep" not in names:
        return creep_for_drift(fitter, current, struct, findings, rejected, p_base, noise, cctx, step)
    if "creep" in names and "thermal_drift" not in names and try_in is not None:
        drift_rival_settled(fitter, current, struct, findings, p_base, noise, cctx, step, try_in)
        return current, struct, findings
    if not {"creep", "thermal_drift"} <= names or current.pick != "load" or struct.creep_order >= DRIFT_AS_CREEP:
        return current, struct, findings
    step("checking whether a further creep element explains the drift in both channels")
    swap = _creep_in_drift_place(fitter, current, struct, p_base, cctx)
    if swap is None:
        return current, struct, findings
    fr, s_sw, worth, _ = swap
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
            f["rmse_after"] = heldout_rmse(sets_new)
            if f.get("rival", {}) and f["rival"].get("effect") == "thermal_drift":
                f["alt_share"] = 0.0
    findings = [f for f in findings if f["name"] != "thermal_drift"]
    noise.update(noise_levels(fitter, fr.params)[0])
    return fr.params, s_sw, findings


def creep_for_drift(fitter, current, struct, findings, rejected, p_base, noise, cctx, step):
    """With a drift accepted and no creep, fit creep in the drift's place (up to
    :data:`DRIFT_AS_CREEP` elements, the pick-off the recalibration chose). When it passes every
    test a name needs against the model without either, and beats the drift by the evidence a name
    needs (BIC, :data:`.residuals.ACCEPT`), creep takes the drift's place. A drift can pass first
    while creep, measured against a residual another mechanism still fills, makes that channel
    worse (rig-d30-068: creep beside a 96-noise-rms sensor leakage not yet in; with the leakage in,
    creep in the drift's place took the training cost from 8423 to 2128, BIC 52 better); a true
    warm-up can be drawn nearly as well by one creep element slower than the record (rig-d30-023:
    BIC 5 better, within the threshold). Returns ``(p, struct, findings)``."""
    step("checking whether creep explains the drift as well")
    swap = _creep_in_drift_place(fitter, current, struct, p_base, cctx, refit=True)
    if swap is None:
        return current, struct, findings
    fr, s_cr, worth, without = swap
    s_wo = struct.without("thermal_drift")
    sets_wo, _ = residual_sets(fitter, without.params)
    sets_new, _ = residual_sets(fitter, fr.params)
    cmp = compare(sets_wo, sets_new, s_cr.n_params() - s_wo.n_params(), noise, slow=True)
    ok = plausible("creep", fitter, without.params, fr.params, cmp, cctx, s_cr)
    passed, why = passes(cmp, "creep", ok, at_bound(fitter, fr.params, own_parameters("creep", s_wo, s_cr)))
    if not passed or worth > -ACCEPT["dbic"]:
        step("the drift stays: creep in its place " + (
            f"fails ({why})" if not passed else f"leaves a BIC {worth:.1f} worse" if worth >= 0
            else f"is better by BIC {-worth:.1f} only (< {ACCEPT['dbic']:g})"))
        return current, struct, findings
    step(f"creep with {len(fr.params.creep)} element(s) in the drift's place fits better (BIC {-worth:.1f} "
         f">= {ACCEPT['dbic']:g}): creep named, the drift dropped")
    rejected.append({"effect": "thermal_drift",
                     "why": f"creep in its place fits better (BIC difference {-worth:.1f} >= {ACCEPT['dbic']:g})"})
    drift = next(f for f in findings if f["name"] == "thermal_drift")
    findings = [f for f in findings if f["name"] != "thermal_drift"] + [{
        **drift, "name": "creep", "cmp": cmp, "before": without.params, "after": fr.params, "note": ok[1],
        "alt_share": 0.0, "rival": {
            "effect": "thermal_drift", "passed": True, "bic_behind": round(-worth, 1),
            "explained_share": {c: round(v["explained"], 4) for c, v in drift["cmp"]["channels"].items()}},
        "alternatives": ["thermal_drift"], "rmse_after": heldout_rmse(sets_new)}]
    findings[-1].pop("backward", None)
    noise.update(noise_levels(fitter, fr.params)[0])
    return fr.params, s_cr, findings


def drift_rival_settled(fitter, current, struct, findings, p_base, noise, cctx, step, try_in):
    """Creep whose rival when it went in was a drift (it explained nearly as much then): with the
    search ended, the drift is fitted and tested in creep's place (creep stripped, the rest in,
    the model re-fitted; ``try_in``, as a round fits a candidate). When that model is worse than
    the final one by the evidence a name needs (BIC, :data:`.residuals.ACCEPT`), the rival is
    settled: it no longer lowers creep's confidence. A slow creep element and a warm-up on the load
    spring can explain the same share when creep goes in; a further creep element then explains
    what the drift cannot (synth case 34, creep and a delay: round 2's creep 0.88 against a drift's
    0.88, round 3's element 1.00; creep named at 0.43, a candidate, until the rival was settled)."""
    mine = [f for f in findings if f["name"] == "creep" and (f.get("rival") or {}).get("effect") == "thermal_drift"
            and f["alt_share"] > 0.0]
    if not mine:
        return
    step("fitting the drift that was creep's rival in creep's place, the others in")
    s_wo = struct.without("creep")
    without = fitter.fit(strip(current, s_wo, p_base.thresholds), s_wo, max_nfev=5)
    t = try_in(fitter, "thermal_drift", without.params, s_wo, p_base, noise, cctx)
    if t is None:
        return
    worth = _bic_behind(fitter, t["fit"].cost, fitter.cost(current), t["struct"].n_params() - struct.n_params())
    if worth < ACCEPT["dbic"]:
        step(f"the drift in creep's place is within BIC {worth:.1f} of creep: the rival stands")
        return
    step(f"the drift in creep's place fits worse by BIC {worth:.1f}: creep's rival settled")
    for f in mine:
        f["alt_share"] = 0.0
        f["rival"] = {**f["rival"], "settled_bic": round(worth, 1)}


def _creep_in_drift_place(fitter, current, struct, p_base, cctx, refit=False):
    """Creep (up to :data:`DRIFT_AS_CREEP` elements) proposed and fitted in the place of the drift of
    ``current``, the sensor's pick-off the recalibration's; ``refit``: proposed from the model without
    the drift refitted (5 evaluations), not from the drift merely stripped. Returns ``(fit, struct,
    worth, without)``: ``worth`` the BIC by which that model is worse than ``current`` (below zero:
    better), ``without`` the refit (or ``None``); ``None`` when no creep start is proposed."""
    s_wo = struct.without("thermal_drift")
    base = strip(current, s_wo, p_base.thresholds)
    base.pick = p_base.pick
    without = fitter.fit(base, s_wo, max_nfev=5) if refit else None
    start = propose("creep", fitter, base if without is None else without.params, s_wo,
                    {**cctx, "creep_max": DRIFT_AS_CREEP})
    if start is None:
        return None
    s_cr = s_wo.with_effect("creep", 0, len(start.creep))
    # converged, not a first descent: after 10 evaluations rig-077's creep in the drift's place
    # stood at BIC 1.0 or 11.1 from starts differing in the last digits (the threshold is 10); after
    # 20 at 0.0 from both (-0.1 after 30)
    fr = fitter.fit(start, s_cr, max_nfev=20)
    return fr, s_cr, _bic_behind(fitter, fr.cost, fitter.cost(current), s_cr.n_params() - struct.n_params()), without


def _bic_behind(fitter, cost, cost_ref, extra):
    """The BIC (effective sample size) by which a model of training cost ``cost`` with ``extra``
    parameters more than the reference (fewer: negative) is worse than the reference of ``cost_ref``
    (below zero: better)."""
    return (fitter.n_eff * math.log(max(cost, 1e-300) / max(cost_ref, 1e-300))
            + extra * math.log(max(fitter.n_eff, 2.0)))


def resonance_or_mode(fitter, best, struct, p_base, recal, cctx, step, rnd):
    """A further mode found while the device's own first mode was not identified (the residual
    that hid it was another's, or the sample rate left it to the mechanism's search), or one that
    takes the identified first mode's place, may be that first mode: ordinary physics, not a
    missing mechanism (rig-098, 179: a "further mode" at the device's first mode, 232 and 441 Hz).
    The first mode is fitted from the found frequency and damping, with the pick-offs the channels
    allow; when it explains the data as well as the further mode (BIC with the effective sample
    size, the further mode's parameters against the first mode's and its pick-off's, within
    ``MODE_EVIDENCE``), the first mode is recalibrated and nothing is named. Returns the new
    parameters or ``None``."""

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


def delay_or_lag(fitter, best, struct, p_base, recal, step, rnd):
    """A delay found with a first-order amplifier may be the amplifier's second lag stage, ordinary
    physics. The delay's fit is re-fitted with a second stage of the delay's length in its place
    (the lags and the ordinary items the delay left in free); when that explains the data within
    :data:`LAG_EVIDENCE` of the delay (BIC, effective sample size), the second stage is taken into
    the recalibration and nothing is named (once per diagnosis: the delay searched again beside the
    second stage then stands on its own). Returns the new parameters or ``None``."""

    fp = best["fit"].params
    if best["name"] != "time_delay" or recal is None or fp.tau2 > 0.0 \
            or "from_delay" in recal.report.get("amplifier_order", {}):
        return None
    q = strip(fp, struct, p_base.thresholds)
    q.tau2 = fp.delay
    gone = {n for it in best["dropped"] for n in ITEM_PARAMS[it]}
    free = [n for n in fitter.ordinary if n not in gone and n != "tau2"] + ["tau2"]
    fr = fitter.fit(q, struct, free=free, max_nfev=10, held=True)
    worth = fitter.n_eff * math.log(max(fr.cost, 1e-300) / max(best["fit"].cost, 1e-300))
    lo, hi = fitter.bounds("tau2")
    if worth >= LAG_EVIDENCE or not lo * 1.05 < fr.params.tau2 < hi / 1.05:
        step(f"round {rnd + 1}: the delay of {1e3 * fp.delay:.3g} ms beats a second amplifier stage in its "
             f"place (BIC {worth:.1f})")
        return None
    step(f"round {rnd + 1}: the delay of {1e3 * fp.delay:.3g} ms is the amplifier's second lag stage "
         f"({1e3 * fr.params.tau:.3g} + {1e3 * fr.params.tau2:.3g} ms; the delay would gain BIC {worth:.1f}): "
         "recalibrated, not named")
    recal.params = fr.params
    fitter.ordinary = [n for n in fitter.ordinary if n != "tau2"] + ["tau2"]
    recal.report["amplifier_order"] = {"value": 2, "from_delay": round(worth, 1),
                                       "why": f"found in round {rnd + 1} where a delay was searched"}
    for item in best["dropped"]:
        drop(fitter, recal, item, why="the second lag stage explains it")
    return recal.params


def beside_named_mode(struct, screened, tried):
    """The screened entries ``(gain, name, start, alts)`` a round fits although their screening
    gained nothing: when nothing it tried passed and a further mode is named, the delay. Its
    screening holds that mode, whose phase a delay moves (and the held mode's phase had taken part
    of the delay): synth-1067, a 0.2 ms delay beside the named 248 Hz mode, screened 31 % worse than
    the model without it; fitted, it explained 97 % and 95 % of what was left on the two channels
    (BIC gain 17357), the residual at the noise after it."""
    if "extra_resonance" not in struct.effects \
            or any(t["passed"] or t["name"] == "time_delay" for t in tried):
        return []
    return [s for s in screened if s[1] == "time_delay" and s[0] <= 0]


def sampling_lag_rival(fitter, p):
    """True when the delay of ``p`` is also a sampling lag of the one recorded channel: every
    recording has one channel and the delay is 1..``MAX_LAG`` whole samples (the recalibration looks
    for sampling lags only with two channels, where they are told from a latency by their
    difference)."""
    if len({c for r in fitter.recs for c in r.channels()}) != 1 or p.delay <= 0:
        return False
    n = p.delay / fitter.dt
    return abs(n - round(n)) < 1e-6 and 1 <= round(n) <= MAX_LAG


def confidences(fitter, findings, absorbed, last_round):
    """Set every finding's ``confidence`` (:func:`.decide.confidence`) with its uniqueness against
    its rival settled: a rival accepted itself, or taken into the recalibration after the finding
    (``absorbed``: effect -> round; findings carry the ``round`` they were made in, else
    ``last_round``) while the backward check keeps the finding's evidence, does not count; a
    delay that is also the one recorded channel's sampling lag is a coin toss."""
    accepted = {f["name"] for f in findings}
    for f in findings:
        # a rival that is itself accepted explained another part of the residual (two mechanisms),
        # not the same part another way: it does not make this finding less unique
        rival = (f.get("rival") or {}).get("effect")
        alt = 0.0 if rival in accepted else f["alt_share"]
        bw = f.get("backward")
        if (rival in absorbed and absorbed[rival] > f.get("round", last_round) and bw is not None
                and bw["dbic"] >= ABSORBED_KEPT * f["cmp"]["dbic"]):
            # a rival taken into the recalibration after this finding (a delay that was the amplifier's
            # second lag stage, a further mode that was the first mode) is in the model as ordinary
            # physics: where the finding keeps its evidence beside it (the backward check), the rival
            # explained another part of the residual, as an accepted one does (rig-d28-073: a drift
            # beside a delay rival, later the second stage, BIC gain 4774 forward and 4331 beside it;
            # rig-179's false drift fell from 4393 to 107 beside the first mode its rival became)
            alt = 0.0
            f["rival"] = {**f["rival"], "taken_into_recalibration": True}
        if f["name"] == "time_delay" and sampling_lag_rival(fitter, f["after"]):
            # with one channel a delay of a whole sample or two is that channel's sampling lag as
            # well (the same model: an ordinary item, recalibrated on two channels): a coin toss
            # between the two, never confident
            alt = 1.0
            f["rival"] = {"effect": "sampling_lag", "passed": True, "explained_share": {
                c: round(v["explained"], 4) for c, v in f["cmp"]["channels"].items()},
                "why": "one recorded channel: a lag of whole samples of that channel gives the same model"}
        f["confidence"] = confidence(f["cmp"], f["name"], alt)
        if bw is not None and bw["dbic"] >= f["cmp"]["dbic"]:
            # a finding made before a larger one was measured against a residual that larger one
            # still filled (rig-141: a delay explained 26 % beside a loop shape named after it; with
            # the shape in, the delay explains 73 % at a BIC gain of 447 against 55). When the
            # backward check's evidence is at least the forward one's, the others did not take what
            # it explains: its confidence is the better of the two. (When the evidence falls with
            # the others in, they explain part of the same residual: the forward measure stands;
            # rig-179's false drift beside a creep: BIC 4393 forward, 107 backward.)
            f["confidence"] = max(f["confidence"], confidence(bw, f["name"], alt))


def creep_at_floor(name, bounds, p, struct: Structure):
    """Index of a new creep element whose time constant sits at the lower end of its range when
    another new element stays (else ``None``): an element that fast draws a lag, a mode or the
    loop's rate dependence, and the slower ones may be the creep (rig-d8-025: log creep from
    t0 = 19 ms fitted as 2.6 ms at the floor with gain 0.15 beside 0.50 s with 0.058; one element
    alone settles at 0.21 s and passes)."""
    if name != "creep" or len(p.creep) - 1 <= struct.creep_order:
        return None
    for b in bounds:
        n = b["parameter"]
        if n.startswith("creep_tau") and b["value"] <= b["range"][0] * 1.5:
            return int(n[9:])
    return None


def modes_exchanged(fitter, fr, dropped, step, rnd):
    """A further mode fitted heavily damped (beyond ``MODE_LIGHT``) beside a lightly damped first
    mode may be the same two modes the other way round: the device's own mode damped, the further
    one ringing (rig-d33-129, displacement pick-off: the device's 278 Hz mode at zeta 0.19 and a
    548 Hz further mode at 0.007 fitted as a further mode at 279 Hz, 0.19, beside a first mode
    moved to 548 Hz, and refused as one that only adds phase lag). The fit ``fr`` with the two
    exchanged and re-fitted is returned when it fits as well (BIC within ``ACCEPT["dbic"]``, the
    same parameters), else ``fr`` (also when the fit does without the first mode: ``dropped``)."""
    p = fr.params
    if p.res is None or "mech_f" not in fitter.ordinary or "mode" in dropped:
        return fr
    (f2, z2), (f1, z1) = p.res, p.mode(fitter.dev)
    lo, hi = fitter.bounds("mech_f")
    if z2 <= MODE_LIGHT or z1 > MODE_LIGHT or not lo < f2 < hi or f1 > fitter.bounds("res_f")[1]:
        return fr
    q = p.copy()
    q.res = (f1, max(z1, fitter.bounds("res_zeta")[0] * 1.2))
    q.set_mode(fitter.dev, f=f2, zeta=float(np.clip(z2, *fitter.bounds("mech_zeta", q))))
    gone = {n for it in dropped for n in ITEM_PARAMS[it]}      # (the ordinary items the fit does without)
    free = [n for n in free_names(fr.struct, fitter.ordinary) if n not in gone]
    got = fitter.fit(q, fr.struct, free=free, max_nfev=10, held=True)
    worse = fitter.n_eff * math.log(max(got.cost, 1e-300) / max(fr.cost, 1e-300))
    if worse >= ACCEPT["dbic"]:
        return fr
    step(f"round {rnd + 1}: the further mode at {f2:.4g} Hz (zeta {z2:.2g}) beside the first mode at {f1:.4g} Hz "
         f"(zeta {z1:.2g}) fits the other way round as well (BIC {-worse:.1f}): exchanged")
    return got
