"""What a slowly sampled recording leaves between its samples: the straight-line path's misfit.

At one replay step per sample (the default) the mechanics see the stroke as a straight line from
sample to sample. Where the amplifier settles within a sample or the first mode rings within a few,
the true path is far from that line, and a recalibrated model of a device with nothing missing
leaves a structured residual of several noise rms right after the command's jumps: of rig draw
23's 27 clean devices, 9 ended "a structured residual remains", 8 of them sampled at 283 Hz-3.2 kHz,
most with a first mode near or above the Nyquist frequency that the recalibration's search (up to
0.8 x the sample rate, on the straight line) did not find. Replaying all the time at a finer step,
or along the amplifier's lag, moves decisions the search was set on (``--replay-rate``, stop 47;
the model's ``simulation.stroke_path``, stops 48 and 76), so this asks only at the
end, when nothing is named and more than the ordinary misfit is left: replayed at
:data:`~.recordings.INTERNAL_RATE` inside, with a first mode searched up to twice the sample rate
when none was found, does the recalibrated model leave no more than the ordinary misfit? If so,
what was left is the path between the samples, not missing physics.

The same replay asks one more question of a slowly sampled recording whose search named no delay
(:func:`delay_between`): at one step per sample a command delay of a sample or two, beside a fast
amplifier and a first mode near or above the Nyquist frequency, is drawn by a slower lag and a
heavily damped mode below it (rig-d24-000, 564 Hz: a one-sample delay, 0.33 ms lag and 1036 Hz mode
replayed to the noise as a 1.07 ms lag and a 120 Hz mode with zeta 0.23; with the true delay the
one-step replay ends at 11 times that cost, replayed at 8 kHz it fits 19 % better than without).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .catalogue import plausible, propose
from .decide import at_bound, confidence, own_parameters, passes
from .engine import predict
from .fit import Fitter, free_names
from .loopshape import nominal_distance
from .recalibrate import mode_at, mode_picks
from .recordings import INTERNAL_RATE, internal_steps
from .residuals import ACCEPT, heldout_rmse, residual_sets
from .rivals import sampling_lag_rival
from .starts import with_params
from .stats import compare

__all__ = ["between_samples", "delay_between", "fine_fitter", "limit_between"]


def fine_fitter(fitter: Fitter):
    """A :class:`.fit.Fitter` like ``fitter`` (its limits, restarts, ordinary items, channel weights
    and effective sample size) on its recordings replayed at :data:`INTERNAL_RATE` inside, or None
    when every recording is sampled at that rate or faster."""
    fine = [replace(r, oversample=internal_steps(r.dt, r.n, INTERNAL_RATE)) for r in fitter.recs]
    if all(r.oversample == 1 for r in fine):
        return None
    fit = Fitter(fine, fitter.dev, fitter.lam)
    fit.limits = dict(fitter.limits)
    fit.restart = dict(fitter.restart)
    fit.ordinary = list(fitter.ordinary)
    fit.n_eff = fitter.n_eff
    fit.noise = dict(fitter.noise)
    return fit


def between_samples(fitter: Fitter, p, struct, noise, step=None):
    """Refit the ordinary parameters of ``p`` (``fitter.ordinary`` and ``struct``'s) with the
    recordings replayed at :data:`INTERNAL_RATE` inside, and return ``{"rate_hz", "steps_per_sample",
    "structured_rms": {channel: value in the channel's unit}, "rmse", "first_mode"}`` over all
    samples (with the ``noise`` levels per channel; ``first_mode.found_here``: searched by
    :func:`_first_mode`, up to twice the sample rate), or None when every recording is sampled at
    that rate or faster."""
    fit = fine_fitter(fitter)
    if fit is None:
        return None
    fine = fit.recs
    if step:
        step(f"refitting the recalibrated model with {max(r.oversample for r in fine)} steps per sample "
             "(the stroke's path between the samples)")
    q, found = p, False
    if "mech_f" not in fit.ordinary:
        q = _first_mode(fit, p, struct)
        found = "mech_f" in fit.ordinary
    q = fit.fit(q, struct, free=free_names(struct, fit.ordinary), max_nfev=10, held=True).params
    structured, rmse = {}, {}
    for c in noise:
        e = [getattr(r, c) - predict(r, fit.dev, q)[c] for r in fine if getattr(r, c) is not None]
        if not e:
            continue
        ms = float(np.mean(np.concatenate(e) ** 2))
        structured[c] = math.sqrt(max(ms - noise[c] ** 2, 0.0))
        rmse[c] = math.sqrt(ms)
    f1, z1 = q.mode(fit.dev)
    return {"rate_hz": INTERNAL_RATE, "steps_per_sample": max(r.oversample for r in fine),
            "structured_rms": structured, "rmse": rmse,
            "first_mode": {"frequency_hz": float(f"{f1:.5g}"), "zeta": float(f"{z1:.4g}"),
                           "found_here": found}}


# where the first mode is searched, in units of the sample rate: a mode above the Nyquist frequency
# that the command's jumps ring (rig-d23-004: 466 Hz, zeta 0.27, sampled at 517 Hz; rig-d23-118:
# 314 Hz at 307 Hz) shows at the samples only through the path between them, which a replay at
# one step per sample does not have, and the recalibration's search stops at 0.8 x the rate
MODE_SPAN = (0.3, 2.0)


def _mode_span(fit: Fitter, keep=None):
    """Where a first mode is searched at the finer replay (:data:`MODE_SPAN` of the sample rate, in
    Hz); sets ``fit``'s search range for it a little wider, and wide enough for a mode of ``keep`` Hz
    (one the one-step recalibration found below that span: rig-d31-073, 2.14 kHz, a 260 Hz mode
    recalibrated to 201 Hz, which the range from 321 Hz put at its bound and the delay fell with it)."""
    lo, hi = (MODE_SPAN[0] * fit.fs, MODE_SPAN[1] * fit.fs)
    f_lo = 0.5 * lo if keep is None else min(0.5 * lo, keep / 1.5)
    fit.limits["mech_f"] = (max(100.0, f_lo), min(25000.0, 1.5 * hi))
    return lo, hi


def _first_mode(fit: Fitter, p, struct):
    """``p`` with the first mode that fits the finely replayed recordings best (screened over
    :data:`MODE_SPAN` with the weights held, the best two starts fitted with every pick-off the
    channels allow), or ``p`` itself when none fits better; ``fit.ordinary`` gains the mode's
    parameters when one is taken."""
    lo, hi = _mode_span(fit)
    picks = mode_picks(fit)
    starts, qs = [], []
    for pick in picks:
        for f in np.exp(np.linspace(math.log(lo), math.log(hi), 12)):
            for z in (0.05, 0.25):
                q = p.copy()
                q.pick = pick
                q.set_mode(fit.dev, f=float(f), zeta=z)
                starts.append((float(f), z))
                qs.append(q)
    best, cost0 = None, fit.cost(p)
    for _, (f, z) in sorted(zip(fit.quick_many(qs), starts))[:2]:
        fr = mode_at(fit, p, struct, f, z)
        if fr is not None and fr.cost < cost0 and (best is None or fr.cost < best.cost):
            best = fr
    if best is None:
        return p
    fit.ordinary = fit.ordinary + ["mech_f", "mech_zeta"]
    return best.params



# a delay the replay between the samples is searched at: whole samples (a one-step replay cannot
# draw one beside a fast lag), each with the first mode started at these multiples of the sample
# rate (the one-step search had put its mode where the delay's phase lag asked, far below the
# device's: rig-d24-000's 120 Hz for 1036 Hz, fitted beside the delay at 470 Hz; rig-d24-100's 315;
# or above it: rig-d25-050's 723 Hz for 470, at 1.2 kHz, which starts at 0.3 and 0.8 x the rate
# did not reach, 0.4 does)
DELAY_SAMPLES = (1, 2, 3)
DELAY_MODE_SPAN = (0.25, 0.4, 0.6, 0.8, 1.1, 1.6)
DELAY_FITTED = 2          # the best starts (weights held, gains and offsets re-solved) fitted
# not asked when the search's final loop lies this far (noise rms) from every classical loop of the
# nominal operators: a loop shape's misfit is left, and a delay's phase lag widens the loop on a slow
# drive (rig-d25-137, a missed KP loop shape at 660 Hz, 4.97: a false two-sample delay at confidence
# 1.00; rig-045's current limit, 8.47). The delays it names lie at 0.00-2.52 (rig draws 24 and 25);
# rig draw 10's final loops: shapes 4.1-55, none 0.01-1.7, 2.3 and 3.4 where a mechanism was missed
DELAY_LOOP_FAR = 4.0
# ... and beat a second amplifier stage in its place by this BIC (the search's LAG_EVIDENCE asks 2 of
# a delay found at one step per sample; found afterwards at another replay, a delay meets the
# evidence a mechanism needs: rig-d25-160, a clean device at 5.04 kHz with a 1.08 + 0.38 ms
# amplifier, named a two-sample delay at 0.61 that beat that stage by 5.8)
DELAY_LAG_EVIDENCE = ACCEPT["dbic"]


def delay_between(fitter: Fitter, p, struct, noise, cctx, thresholds, step=None):
    """A command delay searched with the recordings replayed at :data:`INTERNAL_RATE` inside.

    ``p`` (the search's final model, no delay in ``struct``) is refitted at the finer replay (its
    ordinary parameters; a first mode searched when none was found), then with a delay of
    :data:`DELAY_SAMPLES` beside the refitted first mode or one started from
    :data:`DELAY_MODE_SPAN`; the better fit is
    tested on the held-out data as a round of the search tests a candidate.

    Returns
    -------
    dict or None
        None when every recording is sampled at :data:`INTERNAL_RATE` or faster; else ``fitter``
        (the finer replay's), ``base`` (``p`` refitted there), ``fit`` (with the delay), ``struct``,
        ``cmp``, ``passed``, ``why``, ``note``, ``bounds``, ``confidence`` and ``mode_added`` (the
        first mode was not an ordinary item before); without ``fit`` when the final loop lies
        :data:`DELAY_LOOP_FAR` or further from the classical loops on ``thresholds`` (the nominal
        operators') and nothing was searched.
    """
    fit = fine_fitter(fitter)
    if fit is None:
        return None
    far = nominal_distance(fitter, p, noise, thresholds)[0]
    if far >= DELAY_LOOP_FAR:
        return {"passed": False, "bounds": [], "why": f"not searched: the final loop lies {far:.2f} x the noise "
                                                      "from every classical loop (a loop shape's misfit is left)"}
    fs, dt = fit.fs, fitter.dt
    if step:
        step(f"searching a command delay with the recording replayed at {max(r.oversample for r in fit.recs)} "
             "steps per sample (a delay of whole samples beside a fast lag is not drawn at one step)")
    had_mode = "mech_f" in fit.ordinary
    q = p if had_mode else _first_mode(fit, p, struct)
    base = fit.fit(q, struct, free=free_names(struct, fit.ordinary), max_nfev=10, held=True).params
    _mode_span(fit, base.mode(fit.dev)[0] if had_mode else None)
    f_lo, f_hi = fit.bounds("mech_f")
    z_lo = 1.2 * fit.bounds("mech_zeta")[0]
    s_new = struct.with_effect("time_delay", 0, len(p.creep))
    free = [n for n in fit.ordinary if n not in ("mech_f", "mech_zeta")] + ["mech_f", "mech_zeta"]
    total = base.tau + base.tau2
    tau_lo = 1.5 * fit.bounds("tau")[0]
    # the first mode where the refit left it (with its pick-off), and started afresh
    modes = [(base.pick, None)] + [(pick, span) for span in DELAY_MODE_SPAN for pick in mode_picks(fit)]
    starts = []
    for k in DELAY_SAMPLES:
        for pick, span in modes:
            r = base.copy()
            r.delay = k * dt
            # the total lag roughly conserved: the delay takes its share from the first stage
            r.tau = max(base.tau - k * dt, 0.25 * total, tau_lo)
            r.pick = pick
            if span is not None:
                r.set_mode(fit.dev, f=float(np.clip(span * fs, 1.02 * f_lo, f_hi / 1.02)),
                           zeta=float(max(0.05, z_lo)))
            starts.append(r)
    order = np.argsort(fit.quick_many(starts), kind="stable")[:DELAY_FITTED]
    best = min((fit.fit(starts[i], s_new, free=free, max_nfev=10, held=True) for i in order),
               key=lambda fr: fr.cost)
    sets0, _ = residual_sets(fit, base)
    sets1, _ = residual_sets(fit, best.params)
    # the delay, and the first mode's three parameters when it was not an ordinary item before
    cmp = compare(sets0, sets1, 1 + (0 if had_mode else 3), noise)
    ok = plausible("time_delay", fit, base, best.params, cmp, cctx, s_new)
    bounds = at_bound(fit, best.params, own_parameters("time_delay", struct, s_new) + ["mech_f", "mech_zeta"])
    passed, why = passes(cmp, "time_delay", ok, bounds)
    if passed:
        lag, worth = _second_stage(fit, best, struct, free)
        if lag is not None:
            passed, why = False, lag
        else:
            ok = (ok[0], "; ".join(n for n in (ok[1], f"beats a second amplifier stage in its place by BIC "
                                                       f"{worth:.1f}") if n))
    lagged = sampling_lag_rival(fit, best.params)
    return {"fitter": fit, "base": base, "fit": best, "struct": s_new, "cmp": cmp, "passed": passed,
            "why": why, "note": ok[1], "bounds": bounds, "mode_added": not had_mode,
            # (with one channel a delay of whole samples is that channel's sampling lag as well: a coin
            # toss, as in the search)
            "confidence": confidence(cmp, "time_delay", 1.0 if lagged else 0.0) if passed else 0.0,
            "rival": {"effect": "sampling_lag", "passed": True, "explained_share": {
                c: round(v["explained"], 4) for c, v in cmp["channels"].items()},
                "why": "one recorded channel: a lag of whole samples of that channel gives the same model"}
            if lagged else None, "sets": sets1,
            "rmse_after": heldout_rmse(sets1)}


def _second_stage(fit: Fitter, best, struct, free, name="time_delay", base=None):
    """``(why, worth)``: why the mechanism ``name`` of ``best`` (a fit; a delay or a current limit)
    is the amplifier's lag, or None, and the BIC by which it beats a second lag stage fitted in its
    place with ``free`` (for a delay, a stage of its length added to the one there; for a current
    limit, the better of two fits: from ``best`` without the limit and from ``base``, the model it
    was tested against, each with the best of :data:`LIMIT_STAGE_SHARES` of the first stage moved
    to the second); it must beat it by :data:`DELAY_LAG_EVIDENCE`, as the search asks
    :data:`.rivals.LAG_EVIDENCE` of a delay it finds."""
    free = [n for n in free if n not in ("tau2", "slew")] + ["tau2"]
    q = best.params.copy()
    if name == "time_delay":
        q.tau2 = q.tau2 + q.delay
        q.delay = 0.0
        fr = fit.fit(q, struct, free=free, max_nfev=10, held=True)
    else:
        q.slew = math.inf
        fits = []
        for p in (q,) if base is None else (q, base):
            qs = [with_params(p, tau=p.tau * (1.0 - k), tau2=p.tau2 + p.tau * k) for k in LIMIT_STAGE_SHARES]
            start = qs[int(np.argmin(fit.quick_many(qs)))]
            fits.append(fit.fit(start, struct, free=free, max_nfev=10, held=True))
        fr = min(fits, key=lambda f: f.cost)
    worth = fit.n_eff * math.log(max(fr.cost, 1e-300) / max(best.cost, 1e-300))
    lo, hi = fit.bounds("tau2")
    if worth >= DELAY_LAG_EVIDENCE or not lo * 1.05 < fr.params.tau2 < hi / 1.05:
        return None, worth
    what = "delay" if name == "time_delay" else "current limit"
    return (f"a second amplifier lag stage in its place ({1e3 * fr.params.tau:.3g} + {1e3 * fr.params.tau2:.3g} ms) "
            f"explains the data as well (the {what} would gain BIC {worth:.1f} < {DELAY_LAG_EVIDENCE:g})",
            worth)


# the lag alone, faster by these factors, is what a current limit found between the samples must beat:
# a current limit slows the command's jumps, and the one-step search's lag had been fitted to them
# (rig-d28-100, 210 Hz: from the limit's grid the lag went from 6.6 to 2.6 ms and the held-out
# displacement error halved, the limit itself binding nowhere)
LIMIT_LAGS = (0.4, 0.15)
# ... and a second lag stage in its place, started with these shares of the first stage moved to it:
# at the finer replay the amplifier's second stage shapes how a step excites a lightly damped first
# mode, which a limit ramping the step over a fifth of a sample also does (rig-d29-158, 751 Hz, a
# 0.82 + 0.39 ms amplifier and a 283 Hz mode at zeta 0.020: a limit binding on one sample took the
# training cost from 9186 to 1705 and was named at confidence 1.00; the second stage in its place
# reached 267, at 0.80 + 0.38 ms beside 282.8 Hz, zeta 0.020)
LIMIT_STAGE_SHARES = (0.1, 0.3)
# ... and leave no recorded channel worse on the held-out data by more than this share of what the
# channel it helps most gains (both in noise rms)
LIMIT_WORSE_SHARE = 0.1


def limit_between(late, p, struct, noise, cctx, step=None):
    """An amplifier current limit searched with the recordings replayed at :data:`INTERNAL_RATE`
    inside, after :func:`delay_between` (``late``: its result, whose finer replay and refitted
    ``base`` are used) found no delay.

    At one step per sample the stroke runs a straight line from sample to sample; a current limit
    that turns the command's jumps into ramps of a sample or two is drawn there by a slower lag
    (rig-d28-025, 1.24 kHz: a current limit and sensor leakage, the leakage alone named). The base
    is refitted from the lag made faster (:data:`LIMIT_LAGS`) when that fits better; the limit is
    screened over the slew rates and faster lags :func:`.catalogue.propose` gives, fitted, and
    tested on the held-out data as a round of the search tests a candidate; it must also leave no
    recorded channel worse on the held-out data (the limit shapes the stroke they all follow).

    Returns
    -------
    dict or None
        As :func:`delay_between` (``fit`` with the current limit), or None when ``late`` searched
        nothing.
    """
    if late is None or "fitter" not in late:
        return None
    fit, base, name = late["fitter"], late["base"], "amplifier_current_limit"
    mode_added = late["mode_added"] and "mech_f" in fit.ordinary      # (found by the delay's refit)
    if step:
        step(f"searching a current limit with the recording replayed at {max(r.oversample for r in fit.recs)} "
             "steps per sample (a limit that ramps the command's jumps over a sample or two is drawn by a "
             "slower lag at one step)")
    free0 = free_names(struct, fit.ordinary)
    tau_lo = fit.bounds("tau")[0]
    faster = [with_params(base, tau=max(base.tau * k, tau_lo), tau2=base.tau2 * k) for k in LIMIT_LAGS]
    alt = fit.fit(faster[int(np.argmin(fit.quick_many(faster)))], struct, free=free0, max_nfev=10, held=True)
    if alt.cost < fit.cost(base):
        base = alt.params
    s_new = struct.with_effect(name)
    start = propose(name, fit, base, struct, cctx)
    if start is None:
        return None
    best = fit.fit(start, s_new, free=free_names(s_new, fit.ordinary), max_nfev=15, held=True)
    sets0, _ = residual_sets(fit, base)
    sets1, _ = residual_sets(fit, best.params)
    # the limit, and the first mode's three parameters when the finer replay found it
    cmp = compare(sets0, sets1, 1 + (3 if mode_added else 0), noise)
    ok = plausible(name, fit, base, best.params, cmp, cctx, s_new)
    bounds = at_bound(fit, best.params, own_parameters(name, struct, s_new))
    passed, why = passes(cmp, name, ok, bounds)
    # the limit shapes the stroke, which every recorded channel follows: found this late, it must
    # help each of them (rig-103, a drift alone at 5.63 kHz: a limit binding on 14 samples took the
    # sensor voltage's 0.6 noise rms of structure, held-out rmse -9 %, and made x 1.9 % worse: by 0.25
    # of what the sensor gained, both in noise rms); a channel the stroke's ramps hardly touch may end
    # within :data:`LIMIT_WORSE_SHARE` of the best channel's gain (rig-d29-039, 292 Hz, a true limit: the
    # sensor voltage gained 0.46 noise rms, x lost 0.014, held-out z -0.4)
    gain = {c: (v["rmse_before"] - v["rmse_after"]) / v["noise"] for c, v in cmp["channels"].items()}
    worse = [c for c, g in gain.items() if g < -LIMIT_WORSE_SHARE * max(max(gain.values()), 0.0)]
    if passed and worse:
        passed, why = False, "; ".join(
            f"it shapes the stroke every channel follows, yet makes {c} {100 * -cmp['channels'][c]['rel_improvement']:.1f} % "
            "worse on held-out data" for c in worse)
    if passed:
        lag, worth = _second_stage(fit, best, struct, free0, name, base)
        if lag is not None:
            passed, why = False, lag
        else:
            ok = (ok[0], "; ".join(n for n in (ok[1], f"beats a second amplifier stage in its place by BIC "
                                                       f"{worth:.1f}") if n))
    return {"fitter": fit, "base": base, "fit": best, "struct": s_new, "cmp": cmp, "passed": passed,
            "why": why, "note": ok[1], "bounds": bounds, "mode_added": mode_added,
            "confidence": confidence(cmp, name) if passed else 0.0, "rival": None, "sets": sets1,
            "rmse_after": heldout_rmse(sets1)}
