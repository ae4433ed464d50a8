"""The catalogue of candidate mechanisms: model, residual signature, parameters, and how to search.

Every mechanism is physics the core already runs (so the FMUs run it too), switched on by
parameters of the model file. For each one this module knows

* where it lives in the model file (``keys``) and which channels it touches;
* its residual signature (what the recalibrated nominal model leaves behind without it);
* :func:`propose` - a coarse screening from which the full fit starts (weights held, the
  candidate's parameters on a grid, the best grid point kept);
* :func:`plausible` - physical checks on the fitted values (a mode must be lightly damped and
  below Nyquist, a current limit must actually bind somewhere, ...).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from ..core.preisach import grid_cells
from .engine import amplifier_output, chain, limited_samples, lowpass, predict, trend
from .delays import delay_search
from .drifts import drift_start
from .fit import Fitter, Structure
from .offsets import OFFSET_PARTS, offset_drift_rival
from .residuals import MODE_BAND_WIDTH, band_share, holds_still, taken_in_holds
from .starts import further_mode_start, log_grid, swap_lag_account, with_params
from .stats import near_range_end
from .support import CELL_FLOOR, PLAY_FLOOR, cell_switched, play_moves, seen_in_training

__all__ = ["CATALOGUE", "Mechanism", "other_charge", "plausible", "propose"]


@dataclass(frozen=True)
class Mechanism:
    name: str
    title: str
    model: str
    signature: str
    parameters: str
    keys: tuple
    channels: tuple          # channels the mechanism changes


CATALOGUE = {m.name: m for m in (
    Mechanism(
        "creep", "Creep (slow viscoelastic drift after input changes)",
        "x_free = (1 + sum_j g_j / (tau_j s + 1)) x_h: Kelvin elements after the hysteresis",
        "after every step the output keeps moving in the step's direction for tau_j; in both "
        "channels (the sensor measures the creeping force); residual below about 1/(2 pi tau) Hz, "
        "largest in holds after steps, coherent with the input history",
        "gains g_j [1] (relative to the hysteretic stroke), time_constants tau_j [s]",
        ("creep.gains", "creep.time_constants"), ("x", "us")),
    Mechanism(
        "sensor_leakage", "Charge leakage of the quartz sensor",
        "tau dw/dt = -(w + S_q F), us = S_q F + w: a first-order high-pass tau s / (tau s + 1) on the force",
        "the sensor voltage decays towards its offset during holds while the displacement does "
        "not; only in us; residual at frequencies below 1/(2 pi tau)",
        "tau_leak [s]", ("sensor.tau_leak",), ("us",)),
    Mechanism(
        "amplifier_current_limit", "Amplifier current limit (slew-rate limit)",
        "|C_a dua/dt| <= I_max: the stack voltage ramps at I_max / C_a instead of following the lag",
        "distortion where amplitude x frequency is high and after large steps (linear ramps instead "
        "of exponentials); grows with the command rate; odd harmonics in fast sines",
        "I_max [A] (slew rate I_max / C_a [V/s])", ("amplifier.I_max",), ("x", "us")),
    Mechanism(
        "time_delay", "Transport or sampling latency",
        "uc(t) -> uc(t - T) before the amplifier",
        "phase lag growing linearly with frequency, no change of magnitude: residual in quadrature "
        "with the fast parts of the input, largest at the highest frequencies and right after steps",
        "delay T [s]", ("amplifier.delay",), ("x", "us")),
    Mechanism(
        "extra_resonance", "A further lightly damped mechanical mode",
        "x -> wn^2 / (s^2 + 2 zeta wn s + wn^2) x (unity DC gain, in series with the mechanics' "
        "first mode, which the recalibration fits)",
        "ringing at f_n after steps and a peak of the residual spectrum at f_n, coherent with the "
        "input, at a frequency other than the first mode's; in the displacement, and in the sensor "
        "voltage when the sensor follows the push rod (contact or load pick-off)",
        "f_n [Hz], zeta [1]", ("resonance.f_n", "resonance.zeta"), ("x", "us")),
    Mechanism(
        "thermal_drift", "Slow offset drift (thermal)",
        "x += rate t + curvature 2 T^2 (exp(-t/T) - 1 + t/T) (t since the start of the recording): "
        "a ramp and a warm-up settling with time constant T (T -> inf: curvature t^2)",
        "a slow trend of the displacement that the input history does not explain: not tied to "
        "steps, same in holds and in motion, the lowest frequencies of the residual spectrum",
        "rate [um/s], curvature [um/s^2], warm-up time constant T [s]",
        ("drift.rate", "drift.curvature", "drift.time_constant"), ("x",)),
    Mechanism(
        "hysteresis_shape", "A loop shape the nominal play-operator grid cannot draw",
        "the same Prandtl-Ishlinskii model with twice the operators (midpoints added to the "
        "nominal thresholds): finer, rate-independent loop shape",
        "at harmonics of a periodic command, locked to its phase; depends on amplitude and reversal "
        "history, not on rate; present in both channels",
        "thresholds and weights of the finer grid", ("hysteresis.thresholds", "hysteresis.weights"),
        ("x", "us")),
)}


def propose(name, fitter: Fitter, p, struct: Structure, ctx):
    """Screen candidate ``name`` on a coarse grid (weights held); return the best start or ``None``."""
    dt, T = fitter.dt, fitter.duration
    chans = ctx["channels"]
    if name == "creep":
        # two elements at most, three where a rival asks for one more (``ctx["creep_max"]``)
        if struct.creep_order >= ctx.get("creep_max", 2):
            return None
        # one element more than now (or, from none, one or two at once: creep that spans decades,
        # logarithmic in time, needs both); every element re-screened (taus on a grid, gains solved)
        taus = log_grid(max(0.005, 10 * dt), 2.0 * T, 13)
        more = [c for c in itertools.combinations(taus, max(struct.creep_order + 1, 2))
                if all(b / a >= 2.5 for a, b in zip(c, c[1:]))]
        sets = ([(t,) for t in taus] + more) if struct.creep_order == 0 else more
        best = {}
        for cost, gains, tset in _quick_creep_sets(fitter, p, sets):
            if all(g > 0 for g in gains) and cost < best.get(len(tset), (math.inf,))[0]:
                best[len(tset)] = (cost, list(zip(gains, tset)))
        if not best:
            return None
        # two elements at once only when they beat one clearly (BIC, effective sample size)
        if 1 in best and 2 in best and fitter.n_eff * math.log(best[1][0] / max(best[2][0], 1e-300)) \
                < 2 * math.log(max(fitter.n_eff, 2.0)) + 10.0:
            best.pop(2)
        q = p.copy()
        q.creep = best[max(best)][1]
        return q
    if name == "sensor_leakage":
        if "us" not in chans or math.isfinite(p.tau_leak):
            return None
        # a record that starts under a force: how much of its charge the sensor still holds is not
        # known (charged now, or leaked over a rest before the record); both ends screened
        return _leak_grid(fitter, p, (False, True) if _under_force(fitter, p) else (False,))
    if name == "amplifier_current_limit":
        if math.isfinite(p.slew):
            return None
        # a current limit slows the steps the lag had been fitted to: faster lags with it too
        grid = []
        for k in (1.0, 0.4, 0.15, 0.06):
            q = with_params(p, tau=max(p.tau * k, fitter.bounds("tau")[0]), tau2=p.tau2 * k)
            rmax = max(float(np.max(np.abs(np.diff(amplifier_output(r, fitter.dev, q))))) / r.h
                       for r in fitter.recs)
            grid += [{"slew": s, "tau": q.tau, "tau2": q.tau2} for s in log_grid(0.02 * rmax, 0.9 * rmax, 10)]
        # the weights re-solved at every point: a lag fitted to slew-limited steps bends the loop
        best, _ = fitter.grid(p, grid, solve=struct.with_effect(name))
        return best
    if name == "time_delay":
        if p.delay > 0:
            return None
        # a delay the recalibration took for lag may sit in the second stage too (rig-151: 1.5 + 2.2
        # ms for a 3.4 ms delay): with two stages, both scaled together is searched as well
        searches = [delay_search(fitter, p, struct, dt, both) for both in ((False, True) if p.tau2 > 0 else (False,))]
        return min(searches, key=lambda qc: qc[1])[0]
    if name == "extra_resonance":
        return None if p.res is not None else further_mode_start(fitter, p, struct, ctx)
    if name == "thermal_drift":
        if "x" not in chans or "thermal_drift" in struct.effects:
            return None
        return drift_start(fitter, p)
    if name == "hysteresis_shape":
        if struct.refined:
            return None
        if "hysteresis_shape" in struct.effects:
            # a named shape may ask for a finer grid of cells (as creep for a further element)
            if 0 < p.n_cells < SHAPE_GRID_FINE * (SHAPE_GRID_FINE + 1) // 2:
                return finer_loop(fitter, p, struct, SHAPE_GRID_FINE)
            return None
        return finer_loop(fitter, p, struct)
    return None


# creep is the slow motion after input changes: its slowest Kelvin element is at least this slow [s]
# (rig creep is logarithmic from t0 = 5-200 ms: fits to it pair an element of 8-600 ms with a
# slower one; a lone element of 3 ms on a clean Bouc-Wen device, rig-140, was the loop's
# different gain for the fast and slow parts of a multisine)
CREEP_SLOWEST_S = 0.05
# a further mode rings at its own frequency: at least this share of what it changes lies within
# f_n / 1.25 .. 1.25 f_n (rig survey, 2026-11-25: true modes 0.38-0.99, the further "modes" named
# on rig-004, rig-040 and the clean rig-125, each reshaping the first mode's response, 0.001-0.010),
# or, damped at most MODE_OWN_BELOW[2], MODE_OWN_BELOW[1] within f_n / MODE_OWN_BELOW[0] .. 1.25 f_n:
# below f_n such a mode amplifies the drive by 1 / (1 - (f / f_n)^2) (rig-d26-069: 79 Hz, zeta 0.005,
# 224 noise rms, sines of 20 and 50 Hz: 0.06 near it, 0.99 from f_n / 2; the refused ones of draws 0,
# 23, 26 at most 0.14 there, but rig-040's 164 Hz at zeta 0.12, a delay's stand-in, more: its phase lag)
MODE_OWN_BAND, MODE_OWN_BELOW = 0.1, (2.0, 0.5, 0.05)
# a current limit binds on at least 3 samples, or on 1-2 when it explains at least this share of
# the structured residual on every channel and the held-out data take its correction within
# LIMIT_BRIEF_BETA at z >= 3: a slowly sampled record sees a limit only at its largest steps
# (rig-d8-069, 884 Hz: 2 samples at the limit, 100 % explained on both channels, held-out beta
# 0.99 and 1.00 at z 72 and 43). Of the 33 limits refused as never binding in draws 0 and 8 and
# synth, the false ones explain at most 0.62 of a channel's, or take 0.67 of it on held-out data
# (rig-131)
LIMIT_BRIEF_EXPLAINED = 0.9
LIMIT_BRIEF_BETA = (0.8, 1.25)
# a limit whose ramps last less than a step (at one step per sample) never slews a whole step yet
# shapes every jump it meets; their time counts as binding only when it explains at least this share
# of the structured residual on every channel: between the samples a lag or a delay draws such ramps
# as well (rig-d35-014, 423 Hz: 2 whole steps, 105 samples' worth of ramps, 1.00 and 0.87 explained;
# rig-d35-064, 317 Hz, a one-sample delay beside a further mode: 150 samples' worth, 0.25 and 0.16)
LIMIT_RAMPS_EXPLAINED = 0.8
MODE_SWAP_EXPLAINED = 0.8   # the share of the structured residual such a further mode must explain
# ... unless this share of what the swap changes lies near the moved mode (f1 / 1.25 .. 1.25 f1, below
# Nyquist): it rings there, a second mode (swaps refused in rig draws 0, 23-25, 2026-12-05: true second
# modes 0.28 (rig-d25-010: 958 Hz beside a 582 Hz further mode), 0.44 (rig-d25-015); a device's own
# mode drawn another way 0.00-0.08 (rig-004, 149, d23-084, d23-180, d24-169, d25-026: 42-67 % explained))
MODE_MOVED_RINGS = 0.2
MODE_LIGHT = 0.15           # a mode's damping ratio up to which it rings (above: it may only add phase lag)
MODE_LAG_KEPT = 0.5         # the share of a swap's gain that lags in its moved mode's place may keep
                            # (swaps' moved modes past MODE_LIGHT, 2026-11-29: rig-004 0.95, rig-d8-112
                            # 1.12, rig-017 0.67 and rig-d8-115's first round 0.95, each with a delay
                            # the lags drew; no swap of draws 0 and 8 kept less, so no passing case set it)
# a thermal drift goes on while the command holds still: there the residual must take at least
# this share of its correction when the holds can tell (strength: the z a full share would have).
# Rig survey, 2026-11-26: named true drifts 0.57-1.5 (rig-004, 012, 035, 059, 085, 089, 090, 098,
# 103, 124, 155, 161-182), false drift candidates -0.06-0.10 (clean rig-050's Bouc-Wen loop over
# a slow multisine; rig-105, 144); synth drifts 1.00-1.06. From strength 2: rig-050's trend beside
# its refined loop, -0.01 taken at 2.7 (no other of 72 rig drift or clean cases lies at 1.5-3)
DRIFT_HOLD_TAKEN = 0.3
DRIFT_HOLD_STRENGTH = 2.0
# a displacement drift fitted to the displacement alone explains at least this share of that
# channel's structured residual, or removes at least DRIFT_OWN_REMOVED x its noise variance: beside
# another mechanism the drift is a small part of what is left (2026-12-05: the first own-channel
# fits of true drifts refused so beside a delay, a mode, a loop shape or creep, rig-d23-019, 047,
# 087, 149 and rig-d22-056, took 0.04-0.15 of the residual but 1.2-2.5 x the noise variance; the
# trends from the sensor channel surveyed, 11 cases, 0.00-0.14 and at most 0.54 x. Run again with
# the rule, the 108 cases of the established set and draws 22-23 where the check had refused a
# drift changed in one: rig-d23-149 names its creep and drift, and a loop shape found at the
# search's end beside them)
DRIFT_OWN_SHARE = 0.15
DRIFT_OWN_REMOVED = 1.0
SHAPE_GRID = 6        # steps of the KP cells' Preisach grid over the recorded stack voltages (21 cells)
SHAPE_GRID_FINE = 8   # the finer grid a named shape may ask for next (36 cells)


def finer_loop(fitter: Fitter, p, struct, steps=SHAPE_GRID):
    """``p`` with a loop that can draw more: the play operators' thresholds plus their midpoints
    (more shape of the same kind; once) and KP cells on a ``steps``-step Preisach grid over the
    normalised stack voltages the recordings reach (features tied to absolute voltages: a loop
    width that changes with the level, a band of switching domains, a high-field knee), every
    weight solved exactly. Play operators the training rows barely see move are left out
    (:func:`_plays_supported`), the narrowest always stays."""
    r = np.asarray(p.thresholds, float)
    q = p.copy()
    if not p.n_cells:
        q.thresholds = np.sort(np.concatenate([r, 0.5 * (r[1:] + r[:-1])]))
        q.weights = np.zeros(q.thresholds.size)
        keep = _plays_supported(fitter, q) | (q.thresholds == q.thresholds[0])
        q.thresholds, q.weights = q.thresholds[keep], q.weights[keep]
    q.cells = q.cell_w = None
    q.cells_held, q.cell_scale = False, 1.0
    v = np.concatenate([rp.ua for rp in fitter.replays(q)]) / q.u_norm
    lo, hi = min(float(v.min()), 0.0), float(v.max())
    if hi - lo > 1e-9:
        pad = 1e-6 * (hi - lo)
        q.cells = np.array(grid_cells(lo - pad, hi + pad, steps))
        q.cell_w = np.zeros(q.n_cells)
        # a cell the recordings barely move is a constant (the offset's) or nearly so, and a
        # weight on it only shifts the stroke the saturation sees: the Gauss-Newton steps of the
        # saturation then overshoot (rig-052). Only cells that switch by a tenth or more stay
        n = len(q.thresholds)
        swing = np.max([np.ptp(rp.z[n:], axis=1) for rp in fitter.replays(q)], axis=0)
        keep = swing >= 0.2
        keep &= _supported(fitter, q, n)
        q.cells = q.cells[:, keep] if keep.any() else None
        q.cell_w = np.zeros(int(keep.sum())) if keep.any() else None
    fitter.varpro(q, struct, gn_iter=2)          # the weights are linear: solve them exactly
    return q


def _supported(fitter: Fitter, q, n):
    """Which of ``q``'s KP cells (after the ``n`` play operators) the training rows see switched
    (:func:`.support.seen_in_training`; a cell switched on fewer than ``CELL_FLOOR x CELL_SUPPORT``
    held-out rows stays).

    A cell switched on at the record's one peak and off at thresholds crossed only inside the
    held-out block after it is a few rows to the fit and a whole block to the validation: its
    weight, fitted to those few, draws a step there (rig-072: 0.94 um off in that block, 0.01-0.05
    elsewhere, and the finer loop that would have taken in an ordinary loop difference failed)."""
    return seen_in_training(fitter.recs, fitter.replays(q), slice(n, None), CELL_FLOOR, cell_switched)


def _plays_supported(fitter: Fitter, q):
    """Which of ``q``'s play operators the training rows see move (as :func:`_supported` for
    cells; an operator moving in fewer than ``PLAY_FLOOR x CELL_SUPPORT`` held-out rows stays)."""
    return seen_in_training(fitter.recs, fitter.replays(q), slice(None, len(q.thresholds)), PLAY_FLOOR,
                            play_moves)


def shape_size(p, nominal_thresholds):
    """Linear parameters a finer loop adds to the nominal one: operators and KP cells."""
    return len(p.thresholds) - len(nominal_thresholds) + p.n_cells


def _quick_creep_sets(fitter: Fitter, p, sets):
    """Screening costs of creep with the time constants of each set in ``sets``, gains solved.

    With the weights held, creep adds ``sum_j g_j LP_tau_j(x_h)`` to the free stroke, so each channel
    is ``a * (prediction without creep) + sum_j c_j * (element j's contribution) + offset``: linear,
    ``g_j = c_j / a`` (from the displacement when recorded: the sensor voltage mixes creep with any
    leakage). Yields ``(cost, gains, set)``.
    """
    p0 = p.copy()
    p0.creep = []
    taus = sorted({t for s in sets for t in s})
    per_ch = {}
    for ch in ("x", "us"):
        ys, base, cols = [], [], {t: [] for t in taus}
        for r in fitter.recs:
            y = getattr(r, ch)
            if y is None:
                continue
            pr = predict(r, fitter.dev, p0, direct=True)
            m = r.train
            ys.append(y[m])
            base.append(pr[ch][m])
            for t in taus:
                add = chain(lowpass(pr["x_h"], t, r.dt), ch, fitter.dev, p0, r.dt) * (1.0 if ch == "x" else p0.S)
                cols[t].append(add[m])
        if ys:
            names = ["base", "one"] + taus
            mat = np.vstack([np.concatenate(base), np.ones(sum(v.size for v in ys))]
                            + [np.concatenate(cols[t]) for t in taus])
            y = np.concatenate(ys)
            per_ch[ch] = (names, mat @ mat.T, mat @ y, float(y @ y))
    for tset in sets:
        cost, gains = 0.0, {}
        for ch, (names, G, gy, yy) in per_ch.items():
            idx = [0, 1] + [names.index(t) for t in tset]
            g = G[np.ix_(idx, idx)]
            r = gy[idx]
            try:
                c = np.linalg.solve(g, r)
            except np.linalg.LinAlgError:
                c = np.linalg.lstsq(g, r, rcond=None)[0]
            cost += fitter.lam[ch] * max(yy - float(c @ r), 0.0)
            if c[0] > 0:
                gains[ch] = [float(v / c[0]) for v in c[2:]]
        gs = gains.get("x", gains.get("us"))
        if gs is not None:
            yield cost, gs, tset


def _under_force(fitter: Fitter, p):
    """Whether the recording starts under a force: operators prepared before it, or a command away
    from 0 V at its first sample."""
    return p.prep > 0 or any(r.u[0] != 0 for r in fitter.recs)


def _leak_grid(fitter: Fitter, p, charges):
    """The best leakage start on a grid of time constants [s] for each of ``charges`` (the sensor's
    charge at the first sample leaked already: ``leak_settled``), weights held."""
    taus = log_grid(max(0.02, 20 * fitter.dt), 50 * fitter.duration, 12)
    return fitter.grid(p, [{"tau_leak": tau, "leak_settled": s} for s in charges for tau in taus])[0]


def other_charge(fitter: Fitter, start):
    """The leakage's start with the sensor's charge at the first sample the other way from
    ``start``'s (``None`` when the record starts at no force: then both are the same). The screening
    with the weights held decides that charge; fitted with them free, the other may fit better
    (rig-d8-006: the leaked charge screened 0.44 against 0.22 and fitted to training cost 2922,
    the charged one to 1532): both are fitted."""
    return _leak_grid(fitter, start, (not start.leak_settled,)) if _under_force(fitter, start) else None


def _own_channel_share(fitter: Fitter, p0, p1, ch):
    """``(share, removed)``: the share of channel ``ch``'s structured residual that ``p1`` removes
    over ``p0`` when both are re-solved on that channel alone (the other channel weighted out; each
    kept as fitted where that fits the channel better than the re-solve), and that removed mean
    square in units of the channel's noise variance. A mechanism acting on one channel must pass
    this: otherwise its gain came from the other channel via shared parameters. ``None`` when only
    ``ch`` is recorded (then the joint fit already is the own-channel fit)."""
    from .varpro import solve_linear

    if not all(getattr(r, c) is not None for r in fitter.recs for c in ("x", "us")):
        return None
    lam = {c: (v if c == ch else v * 1e-9) for c, v in fitter.lam.items()}

    def channel_mse(q):
        e = np.concatenate([(getattr(r, ch) - predict(r, fitter.dev, q, direct=True)[ch])[r.train]
                            for r in fitter.recs])
        return float(np.mean(e * e))

    mse = []
    for p in (p0, p1):
        q = p.copy()
        solve_linear(fitter.recs, fitter.dev, q, lam, drift_terms=2 if (p.rate or p.curv) else 0,
                     replays=fitter.replays(q), gn_iter=2)
        # the re-solve's few saturation steps can land worse than the joint fit on this channel:
        # the values as fitted are then the better own-channel fit
        mse.append(min(channel_mse(q), channel_mse(p)))
    var = fitter.noise.get(ch, 0.0) ** 2
    removed = (mse[0] - mse[1]) / var if var > 0 else math.inf
    structured = mse[0] - var
    if structured <= 0:
        return 0.0, removed
    return (mse[0] - mse[1]) / structured, removed


def _drift_in_sensor(fitter: Fitter, p):
    """How much of the fitted displacement drift also shows in the sensor residual, relative to a
    trend of the force itself (1: all of it, 0: none); ``None`` without a sensor channel."""
    dev = fitter.dev
    us_per_x = p.S * (dev.k_force / dev.mech_gain if p.pick == "stack" else dev.k_load)
    es, ds = [], []
    for r in fitter.recs:
        if r.us is None or r.x is None:
            continue
        m = r.train
        pr = predict(r, fitter.dev, p, direct=True)
        es.append((r.us - pr["us"])[m])
        t = r.t[m]
        ds.append(us_per_x * trend(t, p))
    if not es:
        return None
    e, d = np.concatenate(es), np.concatenate(ds)
    d = d - np.mean(d)
    dd = float(d @ d)
    if dd <= 0:
        return None
    return float((e - np.mean(e)) @ d / dd)


def plausible(name, fitter: Fitter, p_before, p_after, cmp, ctx, struct: Structure):
    """``(ok, reason)``: physical checks of a fitted candidate and of where it helped (``struct``:
    the structure of ``p_after``; a further mode's swap is weighed against a re-fit without it)."""
    dt, T = fitter.dt, fitter.duration
    ch = cmp["channels"]
    if name == "creep":
        g, tau = p_after.creep[-1]
        if g < 0.003:
            return False, f"creep gain {g:.3g} is negligible"
        if not any(holds_still(r.u, r.dt) for r in fitter.recs):
            # (rig-d30-151, d31-082, 101: creep named beside a drift, a delay, on a control, each on
            # chirps or a triangle; every true creep of the rig's draws 0 and 28-31 run had a hold)
            return False, ("the command never holds still: creep, the slow motion after input changes, "
                           "cannot be told there from a rate-dependent loop")
        if "x" in ch and "us" in ch and ch["us"]["explained"] > 0.3 and ch["x"]["explained"] < 0.05 \
                and ch["x"]["structured_before"] > 2 * ch["x"]["noise"]:
            return False, "helps the sensor voltage only, which creep cannot do (creep moves both)"
        slowest = max(t for _, t in p_after.creep)
        if slowest < CREEP_SLOWEST_S:
            return False, (f"its slowest element ({1e3 * slowest:.3g} ms) is faster than "
                           f"{1e3 * CREEP_SLOWEST_S:.0f} ms: a rate-dependent gain of the loop (how fast and "
                           "slow parts of the command move it), not the slow motion after input changes")
        if tau > 4.5 * T:
            return True, f"time constant {tau:.3g} s is longer than the recording: creep or drift"
        return True, ""
    if name == "sensor_leakage":
        if p_after.tau_leak > 100 * T:
            return False, "leakage time constant far beyond the recording: no visible decay"
        quad, parts, own = offset_drift_rival(fitter, p_after)
        noise = ch["us"]["noise"]
        # (the offset straight in parts only against a leakage slower than the record: one that
        # completes no decay there draws a smooth wander of the sensor voltage, as an offset drift)
        rivals = [(quad, "quadratic in time", own + 0.5 * noise)] + (
            [(parts, f"straight in {OFFSET_PARTS} parts", own)] if p_after.tau_leak > T else [])
        as_well = [(alt, what) for alt, what, bar in rivals if alt <= bar]
        if as_well:
            alt, what = as_well[0]
            return False, (f"a slow drift of the sensor offset ({what}; not in the catalogue) "
                           f"explains the sensor voltage as well (structured residual {alt:.3g} against "
                           f"{own:.3g} V): the level-dependent decays that would single out leakage are not "
                           "in the data")
        return True, ""
    if name == "amplifier_current_limit":
        # internal steps at the limit, counted in samples, and the time of its ramps
        counts = [limited_samples(r, fitter.dev, p_after) for r in fitter.recs]
        limited, within = sum(w for w, _ in counts), int(sum(t for _, t in counts))
        ramps = ""
        if limited < 3 <= within and all(v["explained"] >= LIMIT_RAMPS_EXPLAINED for v in ch.values()):
            # ramps shorter than a step, counted by their time (LIMIT_RAMPS_EXPLAINED)
            limited, ramps = within, " (its ramps within the steps, in samples' worth)"
        if limited < 3 and not (limited >= 1 and all(
                v["explained"] >= LIMIT_BRIEF_EXPLAINED and v["z_heldout"] >= 3.0
                and LIMIT_BRIEF_BETA[0] <= v["beta_heldout"] <= LIMIT_BRIEF_BETA[1] for v in ch.values())):
            return False, "the fitted current limit never binds"
        return True, (f"binds on {limited} samples" + ramps + (" only, and explains nearly all the misfit there is"
                                                               if limited < 3 else ""))
    if name == "time_delay":
        if p_after.delay < 0.5 * dt:
            return False, "delay below one sample"
        return True, ""
    if name == "extra_resonance":
        f, z = p_after.res
        if z > MODE_LIGHT:
            return False, f"damping ratio {z:.2f}: not a lightly damped mode (it only adds phase lag)"
        if f > 0.45 / dt:
            return False, "above the Nyquist frequency"
        share = band_share(fitter, p_after, f)
        below = (1.0 if share >= MODE_OWN_BAND else 0.0 if z > MODE_OWN_BELOW[2]
                 else band_share(fitter, p_after, f, below=MODE_OWN_BELOW[0]))
        if below < MODE_OWN_BELOW[1]:
            return False, (f"only {100 * share:.1f} % of what it changes lies within "
                           f"{f / MODE_BAND_WIDTH:.4g}-{f * MODE_BAND_WIDTH:.4g} Hz: it does not ring at its "
                           "own frequency, it reshapes the response elsewhere (near the first mode, or "
                           "the lag)")
        f1 = p_after.mode(fitter.dev)[0]
        if "mech_f" in fitter.ordinary and abs(math.log(f / f1)) < math.log(1.2):
            return False, (f"at the first mode ({f1:.4g} Hz, recalibrated): it re-fits that mode, it is "
                           "not a further one")
        f0 = p_before.mode(fitter.dev)[0]
        if "mech_f" in fitter.ordinary and abs(math.log(f / f0)) < math.log(1.2):
            # it took the recalibrated first mode's place, the first mode moved elsewhere: another
            # account of the main resonance, taken only when it explains nearly all the one-mode
            # model left (rig-119: a 148 Hz mode in series taken as the first mode, the true one
            # found at 487 Hz, explains 100 %, rig-089 86 %; a device's own mode drawn the other way: 25-44 %)
            explained = max(v["explained"] for v in ch.values())
            low = explained < MODE_SWAP_EXPLAINED and f1 < 0.45 / dt    # ... or the moved mode rings there
            rings = band_share(fitter, p_after, f1, q=p_before) if low else 0.0
            if explained < MODE_SWAP_EXPLAINED and rings < MODE_MOVED_RINGS:
                where = f"only {100 * rings:.0f} % of what it changes is near it" if low else "past Nyquist"
                return False, (f"it takes the place of the recalibrated first mode ({f0:.4g} Hz) and moves "
                               f"that to {f1:.4g} Hz, but explains only {100 * explained:.0f} % of the "
                               f"structured residual, and {where}: the device's own mode drawn another way, "
                               "not a further one")
            # two modes only when both ring: a moved "mode" damped beyond MODE_LIGHT may only add lag
            # (rig-004: 710 Hz at zeta 0.35 for a delay fitted a sample short), but a device's own
            # mode is damped up to 0.3 (rig-d8-115: 259 Hz at 0.23 beside a 161 Hz further mode)
            # - the lags it would stand for are re-fitted in its place, and it must beat them
            z1 = p_after.mode(fitter.dev)[1]
            if z1 > MODE_LIGHT:
                # a moved mode at the end of its search range is not one the data place: the further
                # mode is the device's own first mode found again (rig-d19-074, a clean device: its
                # 2.69 kHz mode named as a further one at 2.64 kHz, the first mode moved to 10.2 kHz,
                # zeta 0.26 - 0.85 x the sample rate - and dropped there by the recalibration after)
                if (near_range_end(f1, *fitter.bounds("mech_f"))
                        or near_range_end(z1, *fitter.bounds("mech_zeta", p_after))):
                    return False, (f"it takes the place of the recalibrated first mode ({f0:.4g} Hz) and "
                                   f"moves that to the end of its search range ({f1:.4g} Hz, damping ratio "
                                   f"{z1:.2f}): the device's own mode found again, not a further one")
                alt = swap_lag_account(fitter, p_before, p_after, struct)
                c0, c2 = fitter.cost(p_before), fitter.cost(p_after)
                kept = (c0 - alt.cost) / max(c0 - c2, 1e-300)
                if kept >= MODE_LAG_KEPT:
                    q = alt.params
                    lags = f"{1e3 * q.tau:.3g} + {1e3 * q.tau2:.3g} ms" if q.tau2 > 0 else f"{1e3 * q.tau:.3g} ms"
                    return False, (f"it takes the place of the recalibrated first mode ({f0:.4g} Hz) and "
                                   f"moves that to {f1:.4g} Hz at damping ratio {z1:.2f}, where it only "
                                   f"adds lag: the device's own mode with lags beside it ({lags}, a delay "
                                   f"of {round(q.delay / dt)} samples) keeps {100 * kept:.0f} % of what it "
                                   "gains, not two modes")
                return True, (f"two modes: lags in the place of the moved one ({f1:.4g} Hz, damping ratio "
                              f"{z1:.2f}) keep only {100 * kept:.0f} % of what it gains")
        return True, ""
    if name == "thermal_drift":
        tt = np.linspace(0.0, T, 200)
        drift = float(np.ptp(trend(tt, p_after)))
        if "x" in ch and drift < 0.5 * ch["x"]["noise"]:
            return False, "drift over the recording below the noise"
        # with the sensor on the stack's own force a displacement drift cannot reach it; a sensor
        # that follows the push rod (contact, load) sees a drift of the push rod's position too
        share = _drift_in_sensor(fitter, p_after) if p_after.pick == "stack" else None
        if share is not None and share > 0.3:
            return False, (f"the same slow trend is in the sensor voltage ({100 * share:.0f} % of what a "
                           "trend of the force would give): it moves the force, so it is not a drift of "
                           "the displacement reading")
        held = taken_in_holds(fitter, p_before, p_after, "x", own=lambda r, q: trend(r.t, q))
        if held is not None and held[1] >= DRIFT_HOLD_STRENGTH and held[0] < DRIFT_HOLD_TAKEN:
            return False, (f"where the command holds still (a drift goes on there as in motion) the data "
                           f"take {held[0]:.2f} of its correction (test strength {held[1]:.0f}): a trend "
                           "of the moving part, not a drift of the device")
        own = _own_channel_share(fitter, p_before, p_after, "x")
        if own is not None and own[0] < DRIFT_OWN_SHARE and own[1] < DRIFT_OWN_REMOVED:
            return False, (f"fitted to the displacement alone it explains {100 * max(own[0], 0):.0f} % of "
                           f"its structured residual and removes {max(own[1], 0):.2f} x its noise variance: "
                           "the trend came from the sensor channel through the shared parameters")
        return True, ""
    return True, ""
