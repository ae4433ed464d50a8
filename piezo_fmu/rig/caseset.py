"""The concealed evaluation set: case specifications, generation, and the ground truth.

A ``CaseSpec`` says only what a case must contain (group, mechanisms visible and hidden, control,
channels, limits) and a seed; ``generate`` draws everything else from that seed: rate,
duration, programme, the plant, the effects' magnitudes. Present effects are raised until they
are visible, hidden ones lowered until they are not, by simulating the case with and without
each effect:

* ``visibility[e][ch] = rms(d - mean d) / sigma_ch`` with ``d = y_ch(all) - y_ch(all but e)``,
  noise-free channels (offsets are recalibrated by anyone, so the mean is removed);
* ``visibility_beyond_affine[e][ch]``: the same after removing the best fit ``a + b y_ch(all but
  e)`` from ``d``: the part a channel gain and offset cannot absorb.

An effect counts as present when ``max_ch visibility_beyond_affine >= 3`` (for
``hysteresis_shape`` also its misfit by a 9-operator PI with a fitted output sag, see
``pi9_misfit``), as hidden when ``max_ch visibility < 1``. If a present effect is still too small
at the top of its physical range, the channel noise is lowered (within its range); if that is
not enough the case is redrawn (``truth["attempt"]``).

The device's own loop must not be a ``hysteresis_shape`` in disguise: every case keeps its base
hysteresis within ``BASE_MISFIT`` (1.5) noise rms of the best 9-operator PI with sag (smoother
redraws of the same family, then a noisier rig, then a new draw), and a case with
``hysteresis_shape`` needs the shaped loop >= 3 noise rms from it. Both figures are in
``truth["pi9_misfit"]``. The noise of a channel, expressed as hysteresis stroke, is
``sigma_x / (g_x kappa)`` for the probe, ``sigma_us / (g_F k_a (1 - kappa))`` for a force
pick-off and ``sigma_us / (g_x' kappa)`` for a displacement pick-off (``kappa = k_a / (k_a +
k_f)``); "best channel" is the smallest.
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
from scipy.optimize import nnls

from . import mechanisms as mech
from .excitation import MIN_DURATION as SEG_MIN
from .excitation import choose_kinds, programme
from .hysteresis import draw_hysteresis, plays
from .plant import CATALOGUE, CONTROLS, Effects, Plant, Simulator, lag_one, noise, quantise
from .recording import RigRecording
from .twins import ordinary_twins

GROUPS = ("clean", "single", "pair", "control", "one_channel")
VISIBLE = 3.0        # present: max over channels of visibility_beyond_affine >= VISIBLE
HIDDEN = 1.0         # hidden: max over channels of visibility < HIDDEN
_AIM_VISIBLE = 3.4   # margins used while calibrating
_AIM_HIDDEN = 0.8
BASE_MISFIT = 1.5    # the device's own loop: pi9_misfit at most this many noise rms
SIGMA_X = (0.002, 0.03)      # probe noise range [um]
SIGMA_US = (0.2e-3, 3e-3)    # sensor noise range [V]


@dataclass(frozen=True)
class CaseSpec:
    """What one case must contain; everything else is drawn from ``seed`` by ``generate``.

    Attributes
    ----------
    case_id : str
        Neutral name (reveals nothing of the truth).
    seed : int
    group : str
        One of ``GROUPS``.
    mechanisms : tuple of str
        Catalogue mechanisms injected visibly.
    hidden : tuple of str
        Catalogue mechanisms injected below visibility.
    control : str or None
        Off-catalogue effect (see ``plant.CONTROLS``).
    channels : str
        ``"both"``, ``"x"`` or ``"us"``.
    max_duration : float
        Longest record [s].
    max_rate : float
        Highest sample rate [Hz].
    max_samples : int
        Most samples per channel.
    """

    case_id: str
    seed: int
    group: str
    mechanisms: tuple = ()
    hidden: tuple = ()
    control: str | None = None
    channels: str = "both"
    max_duration: float = 20.0
    max_rate: float = 20000.0
    max_samples: int = 400_000


# ----------------------------------------------------------------------------------------------
# the set


def compatible(names, channels: str = "both") -> bool:
    """Whether effects can share one case: leakage needs the force channel ``us``; a drift
    needs the probe ``x`` or a displacement pick-off (impossible together with leakage on us
    alone); controls on ``us`` need ``us``, the backlash needs both channels to be told apart."""
    names = set(names)
    if "sensor_leakage" in names and channels == "x":
        return False
    if {"sensor_leakage", "thermal_drift"} <= names and channels == "us":
        return False
    if names & {"us_offset_drift"} and channels == "x":
        return False
    if names & {"push_rod_backlash"} and channels != "both":
        return False
    return not (names & {"probe_quantisation", "probe_gain_modulation"} and channels == "us")


def _assemble(rows, seed0: int, prefix: str, **limits) -> list[CaseSpec]:
    order = np.random.default_rng(seed0).permutation(len(rows))
    out = []
    for idx, i in enumerate(order):
        group, mechs, hidden, control, channels = rows[i]
        out.append(CaseSpec(f"{prefix}{idx:03d}", seed0 + 1000 + int(i), group, tuple(mechs),
                            tuple(hidden), control, channels, **limits))
    return out


DRAW_SEED_STEP = 10_000   # draw k's seed0 is the set's + k * DRAW_SEED_STEP (a set's seeds: seed0 + 1000 + index)


def cases(quick: bool = False, draw: int = 0) -> list[CaseSpec]:
    """The concealed evaluation set (deterministic).

    Parameters
    ----------
    quick : bool
        False: the full set (185 cases): 27 clean (9 with a hidden mechanism), 13 per
        mechanism alone (91; 14 with a hidden second one), every pair of mechanisms twice (42),
        15 controls (3 of each), 10 one-channel cases. True: 16 short cases (<= 4 s,
        <= 5 kHz): every mechanism alone, two pairs, three clean (one with a hidden
        mechanism), three controls, one one-channel case.
    draw : int
        0: the established set (``rig-000`` ...). ``k >= 1``: the same composition drawn afresh
        from other seeds (``rig-d<k>-000`` ...): cases no rule of diagnose was tuned on.

    Returns
    -------
    list of CaseSpec
    """
    cat = list(CATALOGUE)
    rows = []
    if quick:
        rows += [("clean", (), (), None, "both"), ("clean", (), (), None, "both"),
                 ("clean", (), ("creep",), None, "both")]
        rows += [("single", (m,), (), None, "both") for m in cat]
        rows += [("pair", ("creep", "time_delay"), (), None, "both"),
                 ("pair", ("sensor_leakage", "extra_resonance"), (), None, "both")]
        rows += [("control", (), (), c, "both")
                 for c in ("mains_hum", "push_rod_backlash", "us_offset_drift")]
        rows += [("one_channel", ("time_delay",), (), None, "x")]
        return _assemble(rows, 4_100_000 + draw * DRAW_SEED_STEP, f"quick-d{draw}-" if draw else "quick-",
                         max_duration=4.0, max_rate=5000.0)
    for i in range(27):
        hidden = (cat[i % 7],) if i < 9 else ()
        rows.append(("clean", (), hidden, None, "both"))
    for k, m in enumerate(cat):
        partners = [p for p in cat if p != m]
        for j in range(13):
            hidden = ()
            if j < 2:
                hidden = (partners[(2 * k + j * 3) % len(partners)],)
            rows.append(("single", (m,), hidden, None, "both"))
    for a, b in combinations(cat, 2):
        rows += [("pair", (a, b), (), None, "both")] * 2
    for c in CONTROLS:
        rows += [("control", (), (), c, "both")] * 3
    for m, ch in [("creep", "x"), ("time_delay", "x"), ("thermal_drift", "x"),
                  ("hysteresis_shape", "x"), (None, "x"), ("sensor_leakage", "us"),
                  ("extra_resonance", "us"), ("amplifier_current_limit", "us"), ("creep", "us"),
                  (None, "us")]:
        rows.append(("one_channel", (m,) if m else (), (), None, ch))
    return _assemble(rows, 7_300_000 + draw * DRAW_SEED_STEP, f"rig-d{draw}-" if draw else "rig-")


# ----------------------------------------------------------------------------------------------
# checks


def pi9_misfit(ua_int: np.ndarray, x_h: np.ndarray, M: int, u_top: float | None = None) -> float:
    """How far a stroke is from anything a 9-operator PI with an output sag can draw [um rms].

    The fit: thresholds 0, 3, ..., 24 V (the paper's ``r = 0 ... 0.8`` in units of 30 V),
    non-negative weights, a free offset, and the sag ``y / (1 + |y| / s)`` for ``s`` on a grid
    (infinite, 400 ... 12.5 um), least squares on the recording samples.

    Parameters
    ----------
    ua_int : ndarray
        Stack voltage on the internal grid [V].
    x_h : ndarray
        The hysteresis' stroke at the recording samples [um].
    M : int
        Internal steps per recording sample.
    u_top : float, optional
        Top of the preparation sweep (rest -> top -> start) both the device and the fitted
        operators went through [V]; default the largest voltage.
    """
    top = u_top if u_top is not None else float(ua_int.max())
    pre = np.concatenate([np.linspace(0.0, top, 400), np.linspace(top, ua_int[0], 400)])
    cols = plays(np.concatenate([pre, ua_int]), np.arange(9) * 3.0, np.zeros(9))[pre.size:]
    cols = cols[::M][: x_h.size]
    # free offset: centre everything; then nnls on a square root B of the 9 x 9 Gram matrix,
    # |A w - y|^2 = |B w - c|^2 + const (the same minimiser, at a fraction of the cost; columns
    # that coincide, e.g. operators never reached, make G singular, which B tolerates)
    A = cols - cols.mean(axis=0)
    norms = np.sqrt((A * A).sum(axis=0))
    A = A[:, norms > 1e-9 * max(norms.max(), 1e-300)]        # operators never moved
    if A.shape[1] == 0:
        return float(np.std(x_h))
    lam, V = np.linalg.eigh(A.T @ A)
    lam = lam + 1e-10 * max(lam.max(), 1e-300)                 # a whisper of ridge: bounded w
    root = np.sqrt(lam)
    B = root[:, None] * V.T
    inv_root = 1.0 / root
    tgt = x_h
    best = np.inf
    for s in (np.inf, 400.0, 200.0, 100.0, 50.0, 25.0, 12.5):
        if np.isfinite(s):
            if np.abs(tgt).max() >= 0.95 * s:
                continue
            y = tgt / (1.0 - np.abs(tgt) / s)           # the sag's inverse
        else:
            y = tgt
        w, _ = nnls(B, inv_root * (V.T @ (A.T @ (y - y.mean()))))
        pred = A @ w + y.mean()
        if np.isfinite(s):
            pred = pred / (1.0 + np.abs(pred) / s)
        best = min(best, float(np.sqrt(np.mean((pred - tgt) ** 2))))
    return best


def _vis(full: np.ndarray, wo: np.ndarray, sigma: float) -> tuple[float, float]:
    d = full - wo
    d0 = d - d.mean()
    plain = float(np.sqrt(np.mean(d0 ** 2)) / sigma)
    w0 = wo - wo.mean()
    ww = float(w0 @ w0)
    beta = float(w0 @ d0) / ww if ww > 0 else 0.0
    aff = float(np.sqrt(np.mean((d0 - beta * w0) ** 2)) / sigma)
    return plain, aff


def visibility(full: dict, without: dict, plant: Plant, channels) -> tuple[dict, dict]:
    """``({ch: visibility}, {ch: visibility_beyond_affine})`` of one effect (module docstring)."""
    plain, aff = {}, {}
    for ch in channels:
        sig = plant.sigma_x if ch == "x" else plant.sigma_us
        plain[ch], aff[ch] = _vis(full[ch], without[ch], sig)
    return plain, aff


def _xh_noise(plant: Plant, channels) -> float:
    """Noise of the best channel expressed as hysteresis stroke [um]."""
    kappa = plant.k_a / (plant.k_a + plant.k_f)
    out = []
    if "x" in channels:
        out.append(plant.sigma_x / (plant.g_x * kappa))
    if "us" in channels:
        gain = plant.g_us * (plant.k_a * (1 - kappa) if plant.pickoff == "force" else kappa)
        out.append(plant.sigma_us / gain)
    return min(out)


def _base_fit(plant: Plant, run: dict, channels) -> float:
    """``pi9_misfit`` of the device's own loop, in noise units of the best channel."""
    return pi9_misfit(run["ua_int"], run["x_h"], plant.oversample, plant.u_hi) / _xh_noise(plant, channels)


# ----------------------------------------------------------------------------------------------
# drawing a case


def _loguniform(rng, lo, hi):
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _draw_plant(rng, spec: CaseSpec, fs: float, names) -> Plant:
    bipolar = rng.random() < 0.2
    u_lo = float(rng.uniform(-20.0, -5.0)) if bipolar else 0.0
    u_hi = float(rng.uniform(30.0, 100.0))
    if "sensor_leakage" in names:
        pickoff = "force"
    elif "thermal_drift" in names and spec.channels == "us":
        pickoff = "displacement"
    else:
        pickoff = "force" if rng.random() < 0.6 else "displacement"
    tau = _loguniform(rng, 0.2e-3, 3e-3)
    tau2 = tau * float(rng.uniform(0.15, 0.6)) if rng.random() < 0.4 else 0.0
    chans = ["x", "us"] if spec.channels == "both" else [spec.channels]
    lag = chans[rng.integers(len(chans))] if rng.random() < 0.1 and fs >= 1000.0 else None
    u = lambda: float(rng.uniform(0.7, 1.3))
    plant = Plant(
        fs=fs, oversample=max(1, int(np.ceil(40000.0 / fs))),
        hysteresis=draw_hysteresis(rng, 0.0, u_lo, u_hi),
        amp_gain=u(), amp_tau=tau, amp_tau2=tau2, C_a=3.98e-6 * u(), d_eff=0.11 * u(),
        k_a=176.6 * u(), k_f=17.66 * u(),
        f1=_loguniform(rng, 200.0, 20000.0), zeta1=_loguniform(rng, 0.01, 0.3),
        pickoff=pickoff,
        g_us=(2.3e-3 if pickoff == "force" else 0.05) * u(),
        g_x=float(rng.uniform(0.9, 1.1)), off_x=float(rng.uniform(-0.5, 0.5)),
        off_us=float(rng.uniform(-0.02, 0.02)),
        sigma_x=_loguniform(rng, *SIGMA_X), sigma_us=_loguniform(rng, *SIGMA_US),
        noise_colour=float(rng.uniform(0.2, 0.5)) if rng.random() < 0.3 else 0.0,
        lag_channel=lag, u_lo=u_lo, u_hi=u_hi)
    return plant


def _rate_and_duration(rng, spec: CaseSpec, kinds, names):
    fs = _loguniform(rng, 200.0, spec.max_rate)
    fs = float(np.round(fs, -int(np.floor(np.log10(fs))) + 2))
    t_min = max([sum(SEG_MIN[k] for k in kinds), 2.0]
                + [min(mech.MIN_DURATION.get(e, 0.0), spec.max_duration) for e in names])
    t_min = min(t_min, spec.max_duration)
    if t_min * fs > spec.max_samples:
        fs = float(np.floor(spec.max_samples / t_min))
    t_max = min(spec.max_duration, spec.max_samples / fs)
    duration = float(rng.uniform(t_min, max(t_min, t_max)))
    return fs, duration


def _unit_noise(spec: CaseSpec, attempt: int, n: int, ar: float, noise_draw: int = 0) -> dict:
    """The case's noise sequences at unit rms (scaled by each channel's sigma when used);
    ``noise_draw`` k >= 1: another realisation of the same noise process."""
    rng = np.random.default_rng([spec.seed, attempt, 99] + ([noise_draw] if noise_draw else []))
    return {ch: noise(rng, n, 1.0, ar) for ch in ("x", "us")}


def _quantisation_visibility(x: np.ndarray, nz: np.ndarray, step: float, sigma: float) -> float:
    """rms of (quantised - unquantised) noisy probe signal, mean removed, over the noise rms."""
    y = x + nz
    d = quantise(y, step) - y
    return float(np.std(d) / sigma)


def _fail(why: list | None, reason: str) -> None:
    if why is not None:
        why.append(reason)


def _attempt(spec: CaseSpec, attempt: int, why: list | None = None, twins: bool = False,
             noise_draw: int = 0) -> RigRecording | None:
    rng = np.random.default_rng([spec.seed, attempt])
    channels = ["x", "us"] if spec.channels == "both" else [spec.channels]
    present = list(spec.mechanisms) + ([spec.control] if spec.control else [])
    hidden = list(spec.hidden)
    names = present + hidden
    required = [r for e in present for r in mech.NEEDS_SEGMENT[e]]
    kinds = choose_kinds(rng, required, spec.max_duration)
    fs, duration = _rate_and_duration(rng, spec, kinds, names)
    plant = _draw_plant(rng, spec, fs, names)
    u, segments = programme(rng, fs, duration, kinds, 0.0, plant.u_lo, plant.u_hi)
    unit_noise = _unit_noise(spec, attempt, u.size, plant.noise_colour)
    sim = Simulator(plant, u)
    nominal = sim.run(Effects())
    base_fit = _base_fit(plant, nominal, channels)
    for k in range(1, 4):
        if base_fit <= BASE_MISFIT:
            break
        plant.hysteresis = draw_hysteresis(rng, 0.0, plant.u_lo, plant.u_hi,
                                           family=plant.hysteresis.family, calm=k / 3)
        sim = Simulator(plant, u)
        nominal = sim.run(Effects())
        base_fit = _base_fit(plant, nominal, channels)
    if base_fit > BASE_MISFIT:
        # still more shape than a clean device may have at this noise: a noisier rig (raise
        # every channel quieter than needed, within its range)
        need = _xh_noise(plant, channels) * base_fit / (0.95 * BASE_MISFIT)
        for ch in channels:
            gain = _xh_noise(plant, [ch]) / (plant.sigma_x if ch == "x" else plant.sigma_us)
            attr, top = ("sigma_x", SIGMA_X[1]) if ch == "x" else ("sigma_us", SIGMA_US[1])
            setattr(plant, attr, min(top, max(getattr(plant, attr), need / gain)))
        base_fit = _base_fit(plant, nominal, channels)
        if base_fit > BASE_MISFIT:
            return _fail(why, 'base loop: too much shape even at the highest noise')
    stroke = float(np.ptp((nominal["x"] - plant.off_x) / plant.g_x))
    ctx = {"plant": plant, "duration": duration, "stroke": stroke,
           "slew": nominal["slew_peak"], "channels": channels}
    fx = {e: mech.fixed(e, rng, ctx) for e in names}
    level = {e: float(rng.uniform(0.55, 0.95)) for e in present}
    level.update({e: float(rng.uniform(0.1, 0.35)) for e in hidden})
    sig_floor = {"x": SIGMA_X[0], "us": SIGMA_US[0]}
    dropped = []
    for _ in range(14):
        eff = Effects({e: mech.realise(e, level[e], fx[e], ctx) for e in names if e not in dropped})
        full = sim.run(eff)
        vis, aff, shape_fit = {}, {}, None
        for e in eff.items:
            if e == "probe_quantisation":     # acts on the noisy samples
                q = _quantisation_visibility(full["x"], plant.sigma_x * unit_noise["x"],
                                             eff.items[e]["step"], plant.sigma_x)
                vis[e], aff[e] = {"x": q}, {"x": q}
                continue
            vis[e], aff[e] = visibility(full, sim.run(eff.without(e)), plant, channels)
        if "hysteresis_shape" in present:
            shape_fit = (pi9_misfit(full["ua_int"], full["x_h"], plant.oversample, plant.u_hi)
                         / _xh_noise(plant, channels))
        changed = False
        for e in present:
            score = max(aff[e].values())
            if e == "hysteresis_shape":
                score = min(score, shape_fit)
            if score >= _AIM_VISIBLE:
                continue
            changed = True
            if level[e] < 0.999:
                level[e] = min(1.0, level[e] + max(0.1, 0.5 * (1.0 - level[e])))
                continue
            # at the top of its range: lower the noise of the channel where it shows most
            # (the shape's pi9 misfit is measured against the best channel: lower both)
            chans = channels if e == "hysteresis_shape" else [max(aff[e], key=aff[e].get)]
            factor = max(score, 1e-3) / (_AIM_VISIBLE * 1.1)
            for ch in chans:
                attr = "sigma_x" if ch == "x" else "sigma_us"
                new = getattr(plant, attr) * factor
                if new < sig_floor[ch]:
                    return _fail(why, f"{e} stays invisible at the lowest noise")
                setattr(plant, attr, new)
        for e in hidden:
            if e in dropped:
                continue
            if max(vis[e].values()) >= _AIM_HIDDEN:
                changed = True
                level[e] *= 0.35
                if level[e] < 1e-3:
                    dropped.append(e)
        if not changed:
            break
    else:
        return _fail(why, 'calibration did not settle')
    base_fit = _base_fit(plant, nominal, channels)
    if base_fit > BASE_MISFIT:           # the noise was lowered too far for the base loop
        return _fail(why, 'base loop: noise lowered too far')
    return _finish(spec, attempt, sim, segments, eff, full, vis, aff, channels, shape_fit,
                   base_fit, dropped, twins, noise_draw)


def _finish(spec, attempt, sim, segments, eff, full, vis, aff, channels, shape_fit,
            base_fit, dropped, twins=False, noise_draw=0) -> RigRecording:
    plant, u = sim.plant, sim.u
    n = u.size
    # the calibration above used draw 0's noise (the probe's quantisation only): a redraw changes
    # the noise the recording carries, nothing the truth says
    unit_noise = _unit_noise(spec, attempt, n, plant.noise_colour, noise_draw)
    rec = {}
    sig = {"x": plant.sigma_x, "us": plant.sigma_us}
    for ch in ("x", "us"):
        y = full[ch] + sig[ch] * unit_noise[ch]
        if ch == "x" and "probe_quantisation" in eff.items:
            y = quantise(y, eff.items["probe_quantisation"]["step"])
        rec[ch] = y
    nuisance = {"first_mode": {}, "sampling_lag": {}}
    static = sim.run(eff, first_mode=False)
    for ch in channels:
        nuisance["first_mode"][ch] = _vis(full[ch], static[ch], sig[ch])[0]
        nuisance["sampling_lag"][ch] = (_vis(lag_one(full[ch]), full[ch], sig[ch])[0]
                                        if plant.lag_channel == ch else 0.0)
    if plant.lag_channel is not None:
        rec[plant.lag_channel] = lag_one(rec[plant.lag_channel])
    params = plant.describe()
    for e, p in eff.items.items():
        params.update(mech.describe(e, p))
    present_mechs = [m for m in CATALOGUE if m in spec.mechanisms]
    hidden_mechs = [m for m in CATALOGUE if m in spec.hidden and m not in dropped]
    truth = {
        "case_id": spec.case_id, "seed": spec.seed, "attempt": attempt, "noise_draw": noise_draw,
        "group": spec.group,
        "mechanisms": present_mechs, "hidden": hidden_mechs, "control": spec.control,
        "channels": list(channels), "fs": plant.fs, "duration": n / plant.fs, "n_samples": n,
        "visibility": {e: {c: round(v, 4) for c, v in d.items()} for e, d in vis.items()},
        "visibility_beyond_affine": {e: {c: round(v, 4) for c, v in d.items()} for e, d in aff.items()},
        "nuisance_visibility": {k: {c: round(v, 4) for c, v in d.items()} for k, d in nuisance.items()},
        "pi9_misfit": {"base": round(base_fit, 4),
                       "with_shape": None if shape_fit is None else round(shape_fit, 4),
                       "unit": "noise rms of the best channel, as hysteresis stroke"},
        "segments": segments,
        "params": params,
    }
    if twins:
        truth["ordinary_twins"] = ordinary_twins(sim, eff, full, channels)
    t = np.arange(n) / plant.fs
    return RigRecording(time=t, u=np.asarray(u, dtype=float),
                        x=rec["x"] if "x" in channels else None,
                        us=rec["us"] if "us" in channels else None, truth=truth)


def generate(spec: CaseSpec, twins: bool = False, noise_draw: int = 0) -> RigRecording:
    """Simulate one case (deterministic: the same spec gives identical arrays).

    Parameters
    ----------
    spec : CaseSpec
    twins : bool
        Also measure each present delay's and further mode's closest ordinary twin
        (``truth["ordinary_twins"]``, see :func:`.twins.ordinary_twins`; seconds per case).
    noise_draw : int
        0: the case's own noise; k >= 1: another realisation of the same noise process (same
        rms, colour and everything else: the same device and truth), to measure how much a
        diagnosis depends on the noise it happened to get.

    Returns
    -------
    RigRecording
        ``time`` [s], ``u`` [V], ``x`` [um] and/or ``us`` [V], and ``truth``.
    """
    for attempt in range(12):
        rec = _attempt(spec, attempt, twins=twins, noise_draw=noise_draw)
        if rec is not None:
            return rec
    raise RuntimeError(f"case {spec.case_id}: no draw met the visibility requirements")
