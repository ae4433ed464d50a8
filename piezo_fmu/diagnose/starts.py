"""Where the search for a further mode starts: the screening's grid, the device's first mode searched
again under it, and the swap (the further mode where the recalibration put the first mode).

A lightly damped mode is narrow, and the recalibrated first mode may have bent to a further mode it
did not have (rig-d5-000: a 205 Hz mode pulled the first mode from 484 to 997 Hz) or be that further
mode (rig-119, rig-d5-168): a start at the right frequency screens worse than no mode at all until
the first mode and the lag it had absorbed are searched again. Used by :func:`.catalogue.propose`
(``extra_resonance``) and :mod:`.select` (the swapped start); :func:`swap_lag_account` is the rival
:func:`.catalogue.plausible` weighs a swap against (the device's own mode with lags beside it).
The grid helpers (:func:`log_grid`, :func:`with_params`) live here, below the catalogue, which
screens its other mechanisms with them.
"""
from __future__ import annotations

import math

import numpy as np

from . import workers
from .delays import delay_search, refine_delay
from .fit import Fitter, Structure, free_names, strip

__all__ = ["MODE_RESEARCH", "MODE_RESEARCH_PEAKS", "MODE_RESEARCH_ZETA", "MODE_START_GN", "MODE_SWAP_STARTS",
           "PEAK_SOLVED_ZETA", "distinct", "first_mode_searched", "further_mode_start", "lag_searched", "log_grid",
           "solved_starts", "swap_lag_account", "swapped_mode", "with_params"]

PEAK_SOLVED_ZETA = (0.015,)   # damping of the residual-peak starts scored with the weights re-solved
# Gauss-Newton steps of the strain saturation when a further mode's starts get their weights re-solved:
# one step from weights fitted without the mode can land far off under a deep saturation (rig-d33-120,
# a 74.6 Hz mode on the drive beside a 1.7 um saturation: with the weights held 0.44 x the cost of the
# model without it, after one step 1.4 x, after three 0.16 x). The work counted is one solve's, as for
# every other solve with more steps (the search's budget is a measure of its calls, not of their steps)
MODE_START_GN = 3
# the first mode restarted at these x the old one (up to 16 x: rig-d23-090, a 283 Hz further mode
# taken for the first mode, its own 3.1 kHz first mode 11 x above; from 6.3 x at most the swap's
# first mode went to the range's end, 10.5 kHz, and explained 78 %, from 10 x 97 %)
MODE_SWAP_STARTS = (0.4, 0.63, 1.6, 2.5, 4.0, 6.3, 10.0, 16.0)
# the first mode re-searched under a further mode's start: at these multiples of where it was and
# at the residual's peaks (light and moderate damping), the best by the screening's cost
MODE_RESEARCH = (0.25, 0.4, 0.5, 0.63, 0.8, 1.25, 1.6, 2.5, 4.0)
MODE_RESEARCH_ZETA = (0.03, 0.1)
MODE_RESEARCH_PEAKS = 2     # residual peaks (with a place) whose start gets the first mode re-searched


def log_grid(lo, hi, n):
    """``n`` values from ``lo`` to ``hi``, evenly spaced in log."""
    return list(np.exp(np.linspace(math.log(lo), math.log(hi), n)))


def with_params(p, **kw):
    """A copy of the parameters ``p`` with the attributes ``kw`` set."""
    q = p.copy()
    for k, v in kw.items():
        setattr(q, k, v)
    return q


def further_mode_start(fitter: Fitter, p, struct: Structure, ctx):
    """The screening's start for a further mode (``extra_resonance``) on ``p`` (which has none):
    a log grid and a fine comb at the residual's peaks (``ctx["peaks"]``), each place, three
    dampings; the best three and the best :data:`MODE_RESEARCH_PEAKS` peak starts with the first
    mode searched again (:func:`first_mode_searched`), each with its lag re-searched; then the
    residual's peaks (:data:`PEAK_SOLVED_ZETA`, each place) and the best of those, each with the
    weights re-solved (:meth:`.Fitter.varpro`) and then scored with them held, the best returned."""
    dt = fitter.dt
    chans = ctx["channels"]
    fmax = 0.45 / dt
    fs = log_grid(10.0, fmax, 12)
    in_band = [pk for pk in ctx.get("peaks", []) if 5.0 < pk < fmax]
    for pk in in_band:
        # a fine comb around each peak of the residual: a lightly damped mode is narrow
        fs += [pk * (1 + 0.004 * k) for k in range(-3, 4)]
    # the mode adds phase lag below f_n that the amplifier lag had absorbed: the best grid
    # points get their lag re-searched
    # where it acts: after the mechanics (displacement) or on the drive (every channel)
    places = ("output", "drive") if "us" in chans else ("output",)
    grid = [(f, z, at) for f in fs for z in (0.005, 0.015, 0.06) for at in places]
    costs = fitter.quick_many(with_params(p, res=(f, z), res_at=at) for f, z, at in grid)
    scored = sorted((c, f, z, at) for c, (f, z, at) in zip(costs, grid))
    starts = [(c, with_params(p, res=(f, z), res_at=at)) for c, f, z, at in scored[:3]]
    # a further mode the recalibrated first mode had bent to: the first mode is no longer
    # where it settled (rig-d5-000: a 205 Hz mode left the first mode at 997 Hz, zeta 0.13,
    # for a true 484 Hz, 0.035; from the peak alone the screening was 3.8 x worse than
    # without the mode, with the first mode re-searched 0.13 x): each residual peak is
    # screened with the first mode re-searched (the best MODE_RESEARCH_PEAKS of them: the search
    # is the screening's largest cost on long records)
    peak_qs = [with_params(p, res=(f, 0.015), res_at=at) for f in distinct(in_band) for at in places]
    at_peaks = sorted((c, i, q) for i, (c, q) in enumerate(zip(fitter.quick_many(peak_qs), peak_qs)))
    starts += [first_mode_searched(fitter, q, ctx) for _, _, q in at_peaks[:MODE_RESEARCH_PEAKS]]
    best, best_c = None, math.inf
    for _, _, q0 in sorted((c, i, q) for i, (c, q) in enumerate(starts))[:3]:
        q, c = lag_searched(fitter, q0, struct, p.tau)
        if c < best_c:
            best, best_c = q, c
    # a lightly damped mode the recalibrated weights and lag had bent to: the held screening cannot
    # see it (rig-d8-001: a 61.6 Hz mode, zeta 0.005, at its true place cost 3.3-5.5 x the model
    # without it with the weights held and 0.11 x with them re-solved; the grid's best, a 3.2 kHz
    # mode, changed nothing): the residual's peaks and the chosen start, each with the weights
    # re-solved as the screening re-solves them (:data:`MODE_START_GN` steps), scored as it scores them.
    # (Not by the solve's own residual: one Gauss-Newton step of the saturation from weights fitted
    # to other dynamics is far from settled; on rig-015 it ranked a false 65 Hz peak start over the
    # true 154 Hz mode, 1.6e5 against 1.3e6, whose second step reached 8.0e3)
    peak_starts = [with_params(p, res=(f, z), res_at=at)
                   for f in distinct(in_band) for z in PEAK_SOLVED_ZETA for at in places]
    if not peak_starts:
        return best
    peak_starts.append(best.copy())
    s_mode = struct.with_effect("extra_resonance")
    solved_starts(fitter, peak_starts, lambda q: s_mode)
    costs = fitter.quick_many(peak_starts)
    i = int(np.argmin(costs))
    # the chosen start also as it was (its screening cost), should the solve move the weights the
    # wrong way from every start
    return best if (i == len(peak_starts) - 1 or costs[i] >= best_c) else peak_starts[i]


def swapped_mode(fitter: Fitter, p, struct: Structure, ctx):
    """A further mode where the recalibrated first mode is (rig-119: a 148 Hz mode in series taken for
    it), the first mode restarted at ``MODE_SWAP_STARTS`` times it and at the residual's peaks, each
    pick-off and place: of the best three by the screening's cost and the best at a residual peak,
    the best with its lag re-searched; ``None`` without a first mode or with a further one."""
    if "mech_f" not in fitter.ordinary or p.res is not None:
        return None
    f1, z1 = p.mode(fitter.dev)
    lo, hi = fitter.bounds("mech_f")
    # the first mode restarted at multiples of the old one, and at each residual peak away from it
    # with a light damping (rig-d5-168: the first mode taken at a 292 Hz further mode, its own
    # 499 Hz ringing left in the residual, 1.7 x: between the multiples)
    restarts = [(f1 * k, 0.05, False) for k in MODE_SWAP_STARTS] + [
        (pk, 0.015, True) for pk in distinct(ctx.get("peaks", [])) if abs(math.log(pk / f1)) > math.log(1.1)
        and lo < pk < hi]
    qs, at_peak = [], []
    for f, z, peak in restarts:
        for pick in (("contact", "load") if "us" in ctx["channels"] else ("stack",)):
            for at in (("output", "drive") if "us" in ctx["channels"] else ("output",)):
                q = with_params(p, res=(f1, z1), res_at=at, pick=pick)
                q.set_mode(fitter.dev, f=float(np.clip(f, lo * 1.02, hi / 1.02)), zeta=z)
                qs.append(q)
                at_peak.append(peak)
    starts = sorted((c, i, q) for i, (c, q) in enumerate(zip(fitter.quick_many(qs), qs)))
    # the lag the old first mode had absorbed decides between them: the best three re-searched
    # (rig-d5-168: the true pair screened 0.98 x the old model's cost before and 0.09 x after), and
    # the best at a residual peak with them (rig-d5-168's 499 Hz peak screened behind the restarts
    # at 10 and 16 x; with its lag searched again it costs 4732 against their 49165)
    best = starts[:3] + [s for s in starts[3:] if at_peak[s[1]]][:1]
    return min((lag_searched(fitter, q, struct, p.tau) for _, _, q in best), key=lambda qc: qc[1])[0]


def solved_starts(fitter: Fitter, starts, struct_of):
    """Re-solve the weights of each of a further mode's ``starts`` in place (on the two threads) with
    :data:`MODE_START_GN` Gauss-Newton steps; ``struct_of(q)`` is the structure of start ``q``."""
    workers.each(lambda q: fitter.varpro(q, struct_of(q), gn_iter=MODE_START_GN), starts)


def distinct(freqs, rel=0.01):
    """The frequencies [Hz] ``freqs``, sorted, those within ``rel`` of a kept one left out."""
    out = []
    for f in sorted(freqs):
        if not out or f > out[-1] * (1 + rel):
            out.append(float(f))
    return out


def first_mode_searched(fitter: Fitter, q, ctx):
    """``(cost, q)``: ``q`` (a further mode's start) with the recalibrated first mode moved to where
    the screening's cost is least (:data:`MODE_RESEARCH`), and that cost; ``q`` itself without a
    first mode."""
    if "mech_f" not in fitter.ordinary:
        return fitter.quick(q), q
    f1, z1 = q.mode(fitter.dev)
    lo, hi = fitter.bounds("mech_f")
    fres = q.res[0]
    fs = [f1 * k for k in MODE_RESEARCH] + [pk for pk in distinct(ctx.get("peaks", []))
                                            if abs(math.log(pk / fres)) > math.log(1.1)]
    moved = []
    for f in fs:
        if not lo < f < hi:
            continue
        for z in MODE_RESEARCH_ZETA:
            r = q.copy()
            r.set_mode(fitter.dev, f=f, zeta=z)
            moved.append(r)
    costs = fitter.quick_many([q] + moved)
    best, best_c = q, costs[0]
    for r, c in zip(moved, costs[1:]):
        if c < best_c:
            best, best_c = r, c
    return best_c, best


def lag_searched(fitter: Fitter, q, struct: Structure, tau):
    """``(q, cost)``: a mode's start, the lag it had absorbed re-searched in ``tau`` / 5 .. 2 ``tau``."""
    return fitter.fit_scalar(q, struct, "tau", quick=True,
                             bounds=(max(fitter.bounds("tau")[0], tau / 5), tau * 2), xatol=0.03)


def swap_lag_account(fitter: Fitter, p_before, p_after, struct: Structure):
    """The lags' account of a swap (``p_after``: a further mode in the recalibrated first mode's
    place, the first mode moved elsewhere): the model without the further mode, its mode as the
    device's first, with the lags a moved, damped "mode" may stand for re-fitted - a second
    amplifier stage and a whole-sample delay (stepped when ``struct`` has one, searched when not).
    Started from ``p_before`` and from the further mode's values in each pick-off the channels
    allow; the best :class:`.fit.FitResult` (its structure has the delay when one was searched).
    """
    f_res, z_res = p_after.res
    s_alt = struct.without("extra_resonance")
    free = free_names(s_alt, list(dict.fromkeys(fitter.ordinary + ["tau2", "mech_f", "mech_zeta"])))
    starts = [strip(p_before, s_alt)]
    for pick in (("contact", "load") if any("us" in r.channels() for r in fitter.recs) else ("stack",)):
        q = with_params(p_after, res=None, pick=pick)
        q.set_mode(fitter.dev, f=f_res, zeta=max(z_res, 1.2 * fitter.bounds("mech_zeta")[0]))
        starts.append(q)
    best = None
    for q in starts:
        if q.tau2 <= 0:        # a second stage: the recalibration's shares of the lag, the best screened
            split = [with_params(q, tau=q.tau * (1 - sh), tau2=q.tau * sh) for sh in (0.1, 0.25, 0.5)]
            q = split[int(np.argmin(fitter.quick_many(split)))]
        fr = fitter.fit(q, s_alt, free=free, max_nfev=10, held=True)
        if best is None or fr.cost < best.cost:
            best = fr
    s_d = s_alt if "time_delay" in struct.effects else s_alt.with_effect("time_delay")
    q = best.params
    if "time_delay" not in struct.effects:
        q, _ = delay_search(fitter, q, s_d, fitter.dt, q.tau2 > 0)
    q = refine_delay(fitter, q, s_d)
    if q.delay != best.params.delay:
        fr = fitter.fit(q, s_d, free=free, max_nfev=8, held=True)
        if fr.cost < best.cost:
            best = fr
    return best
