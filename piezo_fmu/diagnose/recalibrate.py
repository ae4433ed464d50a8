"""Recalibration: the ordinary physics of this specimen, fitted before anything is named.

Any real device differs from its data sheet, and an independently built rig differs from the
paper's structure in ordinary ways. None of that is missing physics, so all of it is fitted first:

1. the PI weights (bounded least squares, every partial sum positive), the displacement gain and
   offset, the sensor gain and offset, the strain saturation, the amplifier's lag ``R C_a``;
2. the operators' **state at the first sample** (relaxed, or the memory of a preparation sweep up
   to the record's top voltage) and the **voltage scale of the PI thresholds** (``u_norm``: the
   nominal pattern of thresholds at the device's voltages), each kept when it beats the start
   clearly;
3. the mechanics' **first mode** (frequency 100 Hz - 20 kHz via the moving mass, damping via
   ``c``: up to 0.35, or 0.9 with the contact force, see :meth:`.fit.Fitter.bounds`) together
   with **what the sensor channel follows** (:data:`PICKOFFS`: the stack's blocked force, the
   contact force between stack and push rod, or the load spring's force, i.e. the push-rod
   displacement): a grid, then a joint fit of the best points. Kept only when the data
   see it (the fit beats the nominal mode clearly); otherwise the nominal mode stays and the
   report says it was not visible;
4. the amplifier's **order**: a second lag stage ``tau_2`` kept when it beats a first-order
   amplifier clearly;
5. the channels' **sampling lags** (whole samples, 0-2; with both channels recorded only their
   difference is ordinary: a lag common to both is the catalogue's ``time_delay``);
6. a joint fit of everything kept, and the uncertainty of each value (:mod:`.uncertainty`).

"Clearly" is the selection's own yardstick: a BIC gain of more than ``ACCEPT['dbic']`` with the
effective sample size (:mod:`.recalbase`). Step 2 is :mod:`.loopstate`.
"""
from __future__ import annotations

import math

import numpy as np

from .fit import Fitter, Structure
from .loopstate import initial_state as _history, threshold_scale as _threshold_scale
from .recalbase import SCREEN, Recalibration, fit_ordinary as _fit, gain as _gain, promise as _promise
from .residuals import ACCEPT, full_residuals, residual_sets, spectral_peaks
from .starts import with_params
from .stats import near_range_end, tau_int
from .uncertainty import uncertainty

__all__ = ["PICKOFFS", "Recalibration", "adopt_mode", "mode_at", "mode_picks", "ordinary_names", "recalibrate"]

PICKOFFS = ("stack", "contact", "load")
MODE_RANGE = (100.0, 20000.0)        # [Hz] the first mode's search range
# the first mode fitted beside a further mode from this many frequencies up to this share of fs (of the 8
# found without that bound in draws 34-35, 5 sat at fs / 2 or above, 1 at 100 Hz: 3.6-49 x below the truth)
MODE_BESIDE_STARTS, MODE_BESIDE_NYQUIST = 4, 0.4
BESIDE_FURTHER = "the further mode"
MAX_LAG = 2                          # [samples]
# a lag searched again once the mode moved: refitted when it moved by this factor, kept below this cost ratio
LAG_AGAIN_MOVED, LAG_AGAIN_RATIO = 2.0, 0.5


def recalibrate(fitter: Fitter, p_start, struct: Structure, step) -> Recalibration:
    """Fit the ordinary physics (see the module docstring); ``fitter.ordinary`` ends up naming the
    nonlinear ordinary parameters every later fit frees."""
    sat = ["y_sat"] if struct.saturation else []
    rc = Recalibration(p_start, nominal_mode=(p_start.m, p_start.c), k_total=fitter.dev.k_total)
    p = p_start
    # -- 1. the amplifier lag with the nominal mechanics -----------------------------------------------
    p, _ = fitter.fit_scalar(p, struct, "tau")
    rc.params = _fit(fitter, p, struct, ["tau"], 8).params
    # -- 2. the hysteresis' memory at the first sample, and the voltage scale of its thresholds -----------
    step("recalibrating the hysteresis' state at the start of the recording")
    _history(fitter, rc, struct, sat)
    step("recalibrating the voltage scale of the hysteresis thresholds")
    _threshold_scale(fitter, rc, struct, sat)
    revisit(fitter, rc, struct, step)
    rc.report["uncertainty"] = uncertainty(fitter, rc.params, struct, ordinary_names(fitter, rc, struct))
    return rc


def ordinary_names(fitter: Fitter, rc: Recalibration, struct: Structure):
    """The recalibrated nonlinear parameters (those :func:`uncertainty` reports)."""
    sat = ["y_sat"] if struct.saturation else []
    scale = ["u_norm"] if rc.report["threshold_scale"].get("identified") else []
    return fitter.ordinary + sat + scale


def revisit(fitter: Fitter, rc: Recalibration, struct: Structure, step):
    """Try every ordinary item not identified yet (first mode and pick-off, amplifier order,
    sampling lags; the thresholds' voltage scale also when identified with other mechanisms in) on
    ``rc.params`` with the mechanisms of ``struct`` in; update ``rc`` in place and return whether
    anything changed. The selection calls it again after each finding: a mechanism
    that dominated the residual may have hidden an ordinary item."""
    sat = ["y_sat"] if struct.saturation else []
    changed = False
    # effective sample size of the current residual: how much a screening gain is worth
    sets = residual_sets(fitter, rc.params)[0]
    fitter.n_eff = sum(v["train"].size / tau_int(v["train"]) for v in sets.values())
    step("recalibrating the amplifier's order")
    changed |= _order(fitter, rc, struct, sat)
    if not rc.report.get("first_mode", {}).get("identified") and (
            not fitter.out_of_time() or "first_mode" not in rc.report):
        step("recalibrating the first mode of the mechanics and what the sensor channel follows")
        if _mode(fitter, rc, struct, sat):
            changed = True
            _lag_again(fitter, rc, struct)
    if not rc.report.get("sampling_lags", {}).get("identified") and (
            not fitter.out_of_time() or "sampling_lags" not in rc.report):
        step("recalibrating the channels' sampling lags")
        changed |= _lags(fitter, rc, struct, sat)
    scale = rc.report.get("threshold_scale", {})
    if (scale.get("identified") or scale.get("bic_gain", 0.0) > 0.0) and not fitter.out_of_time() \
            and rc.scale_tried_with != struct.effects:
        # another scale fitted better but not clearly: a mechanism that dominated the residual (a
        # drift: few effective samples) may have hidden it (rig-161: BIC gain 2.7 before the drift
        # was in, a finer loop named after it); or the scale identified then was pulled by what was
        # still missing (synth-1055: creep and a 306 Hz mode took it from 30 to 41.5 V; with both
        # in, 30 V fits to the noise and 41.5 V leaves 5 x the noise)
        step("recalibrating the voltage scale of the hysteresis thresholds")
        changed |= _threshold_scale(fitter, rc, struct, sat)
    if changed:
        rc.params = _fit(fitter, rc.params, struct, fitter.ordinary, 20, held=False).params
        f, z = rc.params.mode(fitter.dev)
        beside = rc.report.get("first_mode", {}).get("fitted_with") == BESIDE_FURTHER
        top = MODE_BESIDE_NYQUIST * fitter.fs if beside else math.inf
        if "mech_f" in fitter.ordinary and (near_range_end(f, *fitter.bounds("mech_f"))
                                            or near_range_end(z, *fitter.bounds("mech_zeta", rc.params)) or f > top):
            # settled at the end of its range: not a mode the data see (a lag or a delay passing for one)
            drop(fitter, rc, "mode", why=f"settled at the end of its search range ({f:.4g} Hz, zeta {z:.3g})"
                 if f <= top else f"found beside the further mode, settled above {top:.4g} Hz ({f:.4g} Hz): a lag")
            rc.params = _fit(fitter, rc.params, struct, fitter.ordinary, 12).params
    return changed


def drop(fitter: Fitter, rc: Recalibration, item, why=""):
    """Take an ordinary item back out (``mode``, ``order`` or ``lags``): a candidate explains its
    share better, or it settled where it is no longer what it stands for."""
    p = rc.params
    if item == "mode":
        p.m, p.c = rc.nominal_mode
        fitter.ordinary = [n for n in fitter.ordinary if n not in ("mech_f", "mech_zeta")]
        rc.report["first_mode"] = {"identified": False, "why": why or "not needed"}
        rc.report["pickoff"] = {"value": p.pick, "identified": False, "why": "without a visible mode every "
                                                                           "pick-off gives the same signals"}
    elif item == "order":
        p.tau, p.tau2 = p.tau + p.tau2, 0.0
        fitter.ordinary = [n for n in fitter.ordinary if n != "tau2"]
        rc.report["amplifier_order"] = {"value": 1, "why_not_2": why or "not needed"}
    elif item == "lags":
        p.lag_x = p.lag_us = 0
        rc.report["sampling_lags"] = {"identified": False, "x_samples": 0, "us_samples": 0}
    return p


ITEM_PARAMS = {"mode": ("mech_f", "mech_zeta"), "order": ("tau2",), "lags": ()}
ITEM_K = {"mode": 3, "order": 1, "lags": 1}     # parameters each item adds (the mode: f, zeta, pick-off)


def _mode_not_identified(rc: Recalibration, p, why, f_nom, z_nom):
    """Report that the first mode stays nominal (and so does the pick-off); returns False."""
    rc.report["first_mode"] = {"identified": False, "why": why}
    rc.report["pickoff"] = {"value": p.pick, "identified": False,
                            "why": "without a visible mode every pick-off gives the same signals"}
    rc.notes = [n for n in rc.notes if "first mode" not in n]
    rc.notes.append(f"the mechanics' first mode was {why}; the nominal {f_nom:.4g} Hz (zeta {z_nom:.3g}) is kept")
    return False


def without(p, item, rc: Recalibration):
    """A copy of ``p`` without the ordinary ``item``; the low-frequency lag the item gave goes to the
    first lag stage (nothing else changed)."""
    q = p.copy()
    if item == "mode":
        # the mode's group delay at low frequencies (c / k = 2 zeta / w_n) goes to the first stage,
        # as a second stage's does below: a heavily damped mode above the drive's band is mostly
        # lag (rig-040: 115 Hz, zeta 0.33, 0.9 ms, standing in for a one-sample delay)
        q.m, q.c = rc.nominal_mode
        q.tau += max((p.c - q.c) / rc.k_total, 0.0)
    elif item == "order":
        q.tau, q.tau2 = q.tau + q.tau2, 0.0
    elif item == "lags":
        q.lag_x = q.lag_us = 0
    return q


def present(fitter: Fitter, rc: Recalibration):
    """The fast ordinary items currently in (what a fast candidate may replace)."""
    p = rc.params
    out = []
    if "mech_f" in fitter.ordinary:
        out.append("mode")
    if p.tau2 > 0:
        out.append("order")
    if p.lag_x or p.lag_us:
        out.append("lags")
    return out


def _mode(fitter, rc, struct, sat):
    """The first mode (grid over frequency and damping for each pick-off, joint fit of the best
    three) and what the sensor follows; kept when the data see them."""
    p = rc.params
    chans = sorted({c for r in fitter.recs for c in r.channels()})
    picks = mode_picks(fitter)
    # a further mode found already may sit elsewhere once the first mode is in: both places
    places = ("output", "drive") if (p.res is not None and "us" in chans) else (p.res_at,)
    f_nom, z_nom = p.mode(fitter.dev)
    free = [n for n in fitter.ordinary if n not in ("mech_f", "mech_zeta")]
    # frequencies: a coarse grid and the peaks of the residual's spectrum (a lightly damped mode
    # falls between grid points)
    # up to 0.8 fs: a mode a little above the Nyquist frequency still shows (aliased); far above
    # it, the samples cannot tell its frequency
    hi = min(MODE_RANGE[1], 0.8 * fitter.fs)
    if hi <= MODE_RANGE[0]:
        rc.report["first_mode"] = {"identified": False, "why": "the sample rate cannot see the mode range"}
        return False
    freqs = list(np.exp(np.linspace(math.log(MODE_RANGE[0]), math.log(hi), 15)))
    for r, e in zip(fitter.recs, full_residuals(fitter, p)):
        for res in e.values():
            freqs += [f for f in spectral_peaks(res, 1 / r.dt, 4) if MODE_RANGE[0] <= f <= hi]
    # screened with the weights held (gains and offsets re-solved): cheap, and the mode's effect
    # is far larger than the weights' re-adjustment
    points, qs = [], []
    for pick in picks:
        for at in places:
            for f in freqs:
                for z in (0.03, 0.15):
                    q = p.copy()
                    q.pick, q.res_at = pick, at
                    q.set_mode(fitter.dev, f=float(f), zeta=z)
                    points.append((pick, at, float(f), z))
                    qs.append(q)
            if (pick, at) != (p.pick, p.res_at):
                q = p.copy()
                q.pick, q.res_at = pick, at
                points.append((pick, at, f_nom, z_nom))
                qs.append(q)
    grid = sorted((c, *pt) for c, pt in zip(fitter.quick_many(qs), points))
    q_now = fitter.quick(p)
    if _promise(fitter, q_now, grid[0][0]) < SCREEN:
        if _beside_further(fitter, rc, struct, free, picks, hi):
            return True
        why = "not visible in this recording (no mode frequency improves the fit)"
        return _mode_not_identified(rc, p, why, f_nom, z_nom)
    tried, seen = [], set()
    for _, pick, at, f, z in grid:
        key = (pick, at, round(math.log(f), 1))
        if key in seen:
            continue
        seen.add(key)
        q = p.copy()
        q.pick, q.res_at = pick, at
        q.set_mode(fitter.dev, f=f, zeta=z)
        # the mode's own parameters and the lags it trades off against (everything else follows in
        # the settling fit once it is in)
        tried.append(fitter.fit(q, struct, free=free + ["mech_f", "mech_zeta"], max_nfev=10, held=True))
        if len(tried) >= 2:
            break
    best = min(tried, key=lambda fr: fr.cost)
    gain, _ = _gain(fitter, p, best.params, 2 + (best.params.pick != p.pick))
    edge = _mode_at_range_end(fitter, best.params)
    if (edge and p.tau2 == 0.0 and "tau2" not in fitter.ordinary
            and best.params.mode(fitter.dev)[1] > 0.9 * fitter.bounds("mech_zeta", best.params)[1]):
        # a mode at its damping bound stands in for a second lag stage: both together
        two = _mode_with_order(fitter, p, struct, free, tried)
        gain2, _ = _gain(fitter, p, two.params, 3 + (two.params.pick != p.pick))
        if gain2 > ACCEPT["dbic"] and not (_mode_at_range_end(fitter, two.params)
                                          or near_range_end(two.params.tau2, *fitter.bounds("tau2"))):
            fitter.ordinary = fitter.ordinary + ["tau2"]
            rc.report["amplifier_order"] = {"value": 2, "bic_gain": round(gain2, 1),
                                            "with": "the first mode (each alone settles at a bound)"}
            best, gain, edge = two, gain2, False
        elif _mode_after_order(fitter, rc, struct, sat):
            return True
    if gain > ACCEPT["dbic"] and not edge:
        adopt_mode(fitter, rc, best.params, bic_gain=round(gain, 1))
        return True
    if _beside_further(fitter, rc, struct, free, picks, hi):
        return True
    why = ("at the end of its search range" if edge else f"not visible in this recording (BIC gain {gain:.1f})")
    return _mode_not_identified(rc, p, why, f_nom, z_nom)


def _beside_further(fitter, rc, struct, free, picks, hi):
    """The first mode fitted together with a further mode already named, from
    :data:`MODE_BESIDE_STARTS` frequencies over its range; kept (``rc`` updated, True) when it pays.

    Held, beside a lightly damped further mode every first mode fits worse: it changes how much the
    drive rings there, which the lags had taken up (rig-d35-019: 144 Hz at zeta 0.005 beside the
    device's 330 Hz, 0.028: 7158 against 2180 held; fitted with the further mode and the lags, 1632 at
    319 Hz; without it a 0.85 ms delay was named for its phase lag). Only below
    :data:`MODE_BESIDE_NYQUIST` x the sample rate."""
    p = rc.params
    top = min(hi, MODE_BESIDE_NYQUIST * fitter.fs)
    if p.res is None or "extra_resonance" not in struct.effects or fitter.out_of_time() \
            or top < 2.0 * MODE_RANGE[0]:
        return False
    f_res = p.res[0]
    tried = []
    for f in np.exp(np.linspace(math.log(MODE_RANGE[0] * 1.2), math.log(top / 1.2), MODE_BESIDE_STARTS)):
        if abs(math.log(f / f_res)) < math.log(1.25):
            continue
        for pick in picks:
            q = p.copy()
            q.pick = pick
            q.set_mode(fitter.dev, f=float(f), zeta=0.1)
            tried.append(fitter.fit(q, struct, free=free + ["mech_f", "mech_zeta", "res_f", "res_zeta"],
                                    max_nfev=10, held=True))
    if not tried:
        return False
    best = min(tried, key=lambda fr: fr.cost)
    gain, _ = _gain(fitter, p, best.params, 2 + (best.params.pick != p.pick))
    if gain <= ACCEPT["dbic"] or _mode_at_range_end(fitter, best.params) \
            or best.params.mode(fitter.dev)[0] > top:
        return False
    adopt_mode(fitter, rc, best.params, bic_gain=round(gain, 1), fitted_with=BESIDE_FURTHER)
    return True


def _mode_at_range_end(fitter, q):
    """Whether the first mode of ``q`` (frequency or damping) ended at its search range's end."""
    f, z = q.mode(fitter.dev)
    return near_range_end(f, *fitter.bounds("mech_f")) or near_range_end(z, *fitter.bounds("mech_zeta", q))


def _mode_after_order(fitter, rc, struct, sat):
    """The first mode searched afresh (:func:`_mode`) on a two-stage amplifier: where the mode rings
    in one channel only, a second stage alone helps the other and spoils it, and the search beside
    one stage ends at a bound far from the mode (rig-d39-092, clean, 2.25 kHz: stages 1.28 + 0.62 ms,
    a 715 Hz mode at zeta 0.016 in the sensor's contact force; two stages alone: x 0.030 -> 0.021 um,
    us 0.0013 -> 0.0014 V, BIC -968; a mode beside one stage settled at zeta 0.35; both together:
    710.7 Hz, 1.33 + 0.57 ms, the residual at the noise). Kept (``rc`` updated, True) when the two
    beat ``rc.params`` by the BIC (three parameters, four with a new pick-off)."""
    p, ordinary = rc.params, fitter.ordinary
    start = _stage_splits(fitter, p)[0][2]
    fitter.ordinary = ordinary + ["tau2"]
    trial = Recalibration(_fit(fitter, start, struct, fitter.ordinary, 20).params,
                          nominal_mode=rc.nominal_mode, k_total=rc.k_total)
    if _mode(fitter, trial, struct, sat) and trial.report["first_mode"].get("identified") \
            and not near_range_end(trial.params.tau2, *fitter.bounds("tau2")):
        gain, _ = _gain(fitter, p, trial.params, 3 + (trial.params.pick != p.pick))
        if gain > ACCEPT["dbic"]:
            rc.params = trial.params
            rc.report.update({k: trial.report[k] for k in ("first_mode", "pickoff")})
            rc.report["amplifier_order"] = {"value": 2, "bic_gain": round(gain, 1),
                                            "with": "the first mode, searched again beside two stages"}
            rc.notes = [n for n in rc.notes if "first mode" not in n]
            return True
    fitter.ordinary = ordinary
    return False


def _mode_with_order(fitter, p, struct, free, tried):
    """The first mode fitted together with a second lag stage of the amplifier, from the modes
    ``tried``: each alone may not pay (a second stage beside the nominal mechanics; a mode beside a
    one-stage lag settles heavily damped at its bound, standing in for the stage)."""
    out = None
    for fr in tried:
        q = fr.params.copy()
        f, z = q.mode(fitter.dev)
        q.tau, q.tau2 = 0.75 * p.tau, 0.25 * p.tau
        q.set_mode(fitter.dev, f=float(np.clip(f, *fitter.bounds("mech_f"))), zeta=float(min(z, 0.3)))
        got = fitter.fit(q, struct, free=free + ["tau2", "mech_f", "mech_zeta"], max_nfev=20, held=True)
        if out is None or got.cost < out.cost:
            out = got
    return out


def mode_picks(fitter):
    """The pick-offs a first mode is tried with. A stack's first mode moves the push rod against
    the sensor: a sensor in the load path (the contact force, or the load spring's) sees it. A mode
    in the displacement alone, with a sensor channel recorded, sits after the sensor: a further
    mode (extra_resonance), not this one."""
    return ("contact", "load") if any("us" in r.channels() for r in fitter.recs) else ("stack",)


def mode_at(fitter: Fitter, p, struct: Structure, f, zeta, without_items=()):
    """The first mode started at ``f`` [Hz] and ``zeta`` (a further mode a candidate found), for each
    pick-off the recorded channels allow, fitted with the ordinary parameters (but those of the
    ordinary items ``without_items``, switched off in ``p``); the best fit, or ``None`` when it
    settles at the end of its search range."""
    picks = mode_picks(fitter)
    gone = {n for it in without_items for n in ITEM_PARAMS[it]} | {"mech_f", "mech_zeta"}
    free = [n for n in fitter.ordinary if n not in gone] + ["mech_f", "mech_zeta"]
    lo, hi = fitter.bounds("mech_f")
    z_lo = 1.2 * fitter.bounds("mech_zeta")[0]
    best = None
    for pick in picks:
        q = p.copy()
        q.pick = pick
        q.set_mode(fitter.dev, f=float(np.clip(f, lo * 1.02, hi / 1.02)), zeta=float(np.clip(zeta, z_lo, 0.3)))
        fr = fitter.fit(q, struct, free=free, max_nfev=10, held=True)
        if best is None or fr.cost < best.cost:
            best = fr
    if _mode_at_range_end(fitter, best.params):
        return None
    return best


def adopt_mode(fitter: Fitter, rc: Recalibration, p, why=None, **report):
    """Take the first mode of ``p`` into the recalibration (found after a finding: ``why``); ``report``
    goes into its entry of ``rc.report``."""
    if "mech_f" not in fitter.ordinary:
        fitter.ordinary = fitter.ordinary + ["mech_f", "mech_zeta"]
    rc.params = p
    rc.report["first_mode"] = {"identified": True, **({"why": why} if why else {}), **report}
    rc.report["pickoff"] = {"value": p.pick, "identified": p.pick != "stack"}
    rc.notes = [n for n in rc.notes if "first mode" not in n]


def _lag_again(fitter, rc, struct):
    """The amplifier lag searched again over its whole range once the first mode has moved: fitted
    with the nominal mechanics (step 1) it may stand in for them, and the fits after start from
    there. When the lag found is ``LAG_AGAIN_MOVED`` times off, the ordinary parameters are refitted
    from it, and the result kept only when its cost is below ``LAG_AGAIN_RATIO`` of what it was: a
    lag that had stood in for the mechanics is far off (rig-d26-094, clean: 1.65 ms beside a 741 Hz
    mode at zeta 0.14; searched again 0.29 ms, refitted 0.39 ms beside 744 Hz at zeta 0.013, 0.08 of
    the cost; the device 0.27 + 0.10 ms, 746 Hz, zeta 0.011), while a lag moved for a few per cent
    trades against what the search names next (a one-sample delay of rig-d24-000: 0.40 to 0.36 ms;
    rig-d28-042, a delay beside a further mode: 0.55 to 0.50 ms, and the refit took the further mode
    for the first one) and a fixture's mode of rig-177 keeps 0.85 of the cost."""
    q, _ = fitter.fit_scalar(rc.params, struct, "tau")
    if abs(math.log(q.tau / rc.params.tau)) < math.log(LAG_AGAIN_MOVED):
        return
    fr = _fit(fitter, q, struct, fitter.ordinary, 20)
    if fr.cost < LAG_AGAIN_RATIO * fitter.cost(rc.params):
        rc.params = fr.params


def _order(fitter, rc, struct, sat):
    """A second lag stage of the amplifier, kept when it beats a first-order amplifier clearly
    (asked again when it is in: what it absorbed may have been explained since)."""
    p = rc.params
    if p.tau2 > 0:
        one = p.copy()
        one.tau, one.tau2 = p.tau + p.tau2, 0.0
        fitter.ordinary = [n for n in fitter.ordinary if n != "tau2"]
        one = _fit(fitter, one, struct, fitter.ordinary, 20).params
        gain, _ = _gain(fitter, one, p, 1)
        if gain > ACCEPT["dbic"]:
            fitter.ordinary = fitter.ordinary + ["tau2"]
            rc.report["amplifier_order"] = {"value": 2, "bic_gain": round(gain, 1)}
            return False
        rc.params = one
        rc.report["amplifier_order"] = {"value": 1, "bic_gain_of_order_2": round(gain, 1)}
        return True
    trials = []
    q_now = fitter.quick(p)
    screen = _stage_splits(fitter, p)
    if _promise(fitter, q_now, screen[0][0]) < SCREEN:
        rc.report["amplifier_order"] = {"value": 1, "why_not_2": "a second lag stage does not improve the fit"}
        return False
    for _, _, q in screen[:2]:
        trials.append(_fit(fitter, q, struct, fitter.ordinary + ["tau2"], 20))
    two = min(trials, key=lambda fr: fr.cost)
    gain, _ = _gain(fitter, p, two.params, 1)
    if gain > ACCEPT["dbic"] and not near_range_end(two.params.tau2, *fitter.bounds("tau2")):
        rc.params = two.params
        fitter.ordinary = fitter.ordinary + ["tau2"]
        rc.report["amplifier_order"] = {"value": 2, "bic_gain": round(gain, 1)}
        return True
    rc.report["amplifier_order"] = {"value": 1, "bic_gain_of_order_2": round(gain, 1)}
    return False


def _stage_splits(fitter, p):
    """``p``'s lag split into two stages (a tenth, a quarter, half of it in the second), screened with
    the weights held: ``[(cost, share, params), ...]``, best first."""
    shares = (0.1, 0.25, 0.5)
    qs = [with_params(p, tau=p.tau * (1 - share), tau2=p.tau * share) for share in shares]
    return sorted(zip(fitter.quick_many(qs), shares, qs), key=lambda t: t[0])


def _lags(fitter, rc, struct, sat):
    """Sampling lags of the channels (whole samples, 0..MAX_LAG; with two channels only their
    difference), kept when they beat no lag clearly."""
    p = rc.params
    chans = sorted({c for r in fitter.recs for c in r.channels()})
    if len(chans) < 2:
        # with one channel a sampling lag cannot be told from a command latency (time_delay)
        rc.report["sampling_lags"] = {"identified": False, "x_samples": 0, "us_samples": 0,
                                      "why": "one channel: a lag is the catalogue's time_delay"}
        return False
    combos = [(lx, 0) for lx in range(MAX_LAG + 1)] + [(0, lu) for lu in range(1, MAX_LAG + 1)]
    q_now = fitter.quick(p)
    screen = []
    for lx, lu in combos:
        if (lx, lu) == (p.lag_x, p.lag_us):
            continue
        q = p.copy()
        q.lag_x, q.lag_us = lx, lu
        # a lag trades off against the amplifier's lag: screened at three lags
        best = min(zip(fitter.quick_many(_scaled(q, k) for k in (0.7, 1.0, 1.4)), (0.7, 1.0, 1.4)))
        screen.append((best[0], _scaled(q, best[1])))
    screen.sort(key=lambda t: t[0])
    changed = False
    if screen and _promise(fitter, q_now, screen[0][0]) >= SCREEN:
        q, _ = fitter.fit_scalar(screen[0][1], struct, "tau", bounds=(p.tau / 3, p.tau * 3), xatol=0.02)
        q = _fit(fitter, q, struct, fitter.ordinary, 10).params
        gain, _ = _gain(fitter, p, q, 1)
        if gain > ACCEPT["dbic"]:
            rc.params = p = q
            changed = True
            rc.report["sampling_lags"] = {"identified": True, "bic_gain": round(gain, 1)}
    rc.report.setdefault("sampling_lags", {"identified": False})
    rc.report["sampling_lags"].update({"x_samples": p.lag_x, "us_samples": p.lag_us})
    return changed


def _scaled(p, k):
    q = p.copy()
    q.tau *= k
    return q
