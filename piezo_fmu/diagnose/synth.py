"""Synthetic recordings from a richer plant, for testing diagnose blind.

A *case* is: an excitation programme (sine sets at 0.5-50 Hz, steps and holds, decaying triangles,
chirps, in random order), a plant (the nominal model with its ordinary parameters perturbed, as any
real specimen differs from the data sheet, plus zero or more mechanisms of the catalogue switched
on with random parameter values; ``hysteresis_shape`` adds play operators between the nominal
ones, their weights raised until the best PI on the nominal thresholds misses the finer loop by
``VISIBLE`` noise rms: a shape a recalibration absorbs is no shape; every other mechanism raised
within its range until it changes the outputs by ``VISIBLE`` noise rms beyond a channel gain and
offset, the rule of the independent rig), and measurement noise on the displacement and the sensor
voltage. The plant is run by the core (``simulate``, open loop, command held over each sample),
exactly the physics the FMUs run. The truth (which mechanisms, which values, how visible) is
returned separately and never written into the recording.

Mechanisms the catalogue does not know can be added as negative controls: ``hum`` (a mains-like
sinusoidal interference on the displacement channel) and ``sensor_drift`` (a slow wander of the
sensor's offset). diagnose must not give them a catalogue name.

``python -m piezo_fmu.diagnose.synth --effects creep,time_delay --out rec.csv`` writes one case.
"""
from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass, field

import numpy as np

from ..model import Model, load_model
from ..simulate import Signal, simulate

__all__ = [
    "CONTROLS",
    "EFFECTS",
    "NOISE",
    "PROGRAMMES",
    "Case",
    "make_case",
    "make_plant",
    "programme",
    "write_recording",
]

EFFECTS = ("creep", "sensor_leakage", "amplifier_current_limit", "time_delay", "extra_resonance",
           "thermal_drift", "hysteresis_shape")
CONTROLS = ("hum", "sensor_drift")
PROGRAMMES = ("sines", "steps", "triangles", "chirp")
# measurement noise (x [um], us [V]) by level
NOISE = {"low": (0.002, 0.0005), "mid": (0.01, 0.002), "high": (0.03, 0.006)}

SRC = "synthetic plant (piezo_fmu.diagnose.synth)"
# a mechanism is raised (within its physical range) until what it changes beyond a channel's gain
# and offset is this many noise rms over the record; a hysteresis_shape until the best PI on the
# nominal thresholds misses the finer loop by as much (the rig's VISIBLE, both)
VISIBLE = 3.0
SHAPE_MAX_FACTOR = 20.0   # the added operators' weights raised by up to this factor


# -- excitation ------------------------------------------------------------------------------------

def _seg_sines(rng, fs, mean, amp_max):
    freqs = rng.choice([0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0], size=rng.integers(2, 4), replace=False)
    parts = []
    for f in sorted(freqs, key=lambda _: rng.random()):
        dur = max(1.0 / f, min(1.5, 8.0 / f))
        n = int(round(dur * fs))
        tt = np.arange(n) / fs
        a = amp_max * rng.uniform(0.5, 1.0)
        parts.append(mean + a * np.sin(2 * np.pi * f * tt - np.pi / 2))
    return np.concatenate(parts), f"sines at {', '.join(f'{f:g}' for f in freqs)} Hz"


def _seg_steps(rng, fs, lo, hi):
    parts = []
    n_steps = int(rng.integers(3, 6))
    levels = rng.uniform(lo, hi, size=n_steps)
    for lev in levels:
        parts.append(np.full(int(round(rng.uniform(0.5, 1.3) * fs)), lev))
    return np.concatenate(parts), f"{n_steps} steps and holds"


def _seg_triangles(rng, fs, mean, amp_max):
    f = rng.uniform(1.0, 5.0)
    dur = rng.uniform(1.5, 2.5)
    tt = np.arange(int(round(dur * fs))) / fs
    ph = (f * tt) % 1.0
    tri = np.where(ph < 0.5, 4 * ph - 1, 3 - 4 * ph)            # -1..1..-1
    env = amp_max * np.exp(-tt / (dur / 2.5))
    return mean + env * tri, f"decaying triangle at {f:.1f} Hz"


def _seg_chirp(rng, fs, mean, amp_max):
    dur = rng.uniform(2.0, 3.0)
    f0, f1 = 0.5, 50.0
    tt = np.arange(int(round(dur * fs))) / fs
    k = math.log(f1 / f0) / dur
    phase = 2 * np.pi * f0 * (np.exp(k * tt) - 1) / k
    return mean + amp_max * rng.uniform(0.5, 0.9) * np.sin(phase - np.pi / 2), "chirp 0.5-50 Hz"


def programme(rng, fs=5000.0, kinds=None, u_lo=0.3, u_hi=5.7, rest=0.2, duration=None):
    """Command [V] (amplifier input) at ``fs`` [Hz]: a rest at 0 V, then the segments in random order
    (repeated in new random orders until ``duration`` [s] is reached, then cut, when given).

    Returns ``(t, u, description)``.
    """
    kinds = list(kinds) if kinds is not None else list(PROGRAMMES)
    rng.shuffle(kinds)
    if duration:
        total = list(kinds)
        while len(total) < 64:
            more = list(kinds)
            rng.shuffle(more)
            total += more
        kinds = total
    mean = 0.5 * (u_lo + u_hi)
    amp = 0.5 * (u_hi - u_lo)
    parts = [np.zeros(int(round(rest * fs)))]
    desc = []
    for kind in kinds:
        if kind == "sines":
            seg, d = _seg_sines(rng, fs, mean, amp)
        elif kind == "steps":
            seg, d = _seg_steps(rng, fs, u_lo, u_hi)
        elif kind == "triangles":
            seg, d = _seg_triangles(rng, fs, mean, amp)
        elif kind == "chirp":
            seg, d = _seg_chirp(rng, fs, mean, amp)
        else:
            raise ValueError(f"unknown programme segment {kind!r} (one of {', '.join(PROGRAMMES)})")
        parts.append(seg)
        desc.append(d)
        if duration and sum(p.size for p in parts) / fs > duration:
            break
    u = np.concatenate(parts)
    if duration:
        u = u[:int(round(duration * fs)) + 1]
    t = np.arange(u.size) / fs
    return t, u, "; ".join(desc)


# -- the plant -------------------------------------------------------------------------------------

def default_effect(name, rng, fs, duration):
    """Random parameters of one mechanism, in ranges where it is visible but not dominant."""
    if name == "creep":
        if rng.random() < 0.5:
            return {"gains": [float(rng.uniform(0.04, 0.15))], "time_constants": [float(rng.uniform(0.3, 2.5))]}
        return {"gains": [float(rng.uniform(0.03, 0.08)), float(rng.uniform(0.03, 0.1))],
                "time_constants": [float(rng.uniform(0.1, 0.5)), float(rng.uniform(1.5, 5.0))]}
    if name == "sensor_leakage":
        return {"tau_leak": float(rng.uniform(0.5, 5.0))}
    if name == "amplifier_current_limit":
        return {"I_max": float(rng.uniform(0.006, 0.02))}          # 1.5-5 kV/s on 4 uF
    if name == "time_delay":
        return {"delay": float(rng.integers(1, 11)) / fs}           # 1-10 samples
    if name == "extra_resonance":
        # the amplifier's 100 Hz lag filters the excitation: modes up to ~700 Hz ring visibly
        return {"f_n": float(rng.uniform(150.0, min(700.0, 0.3 * fs))), "zeta": float(rng.uniform(0.01, 0.05))}
    if name == "thermal_drift":
        s = rng.choice([-1.0, 1.0])
        return {"rate": float(s * rng.uniform(0.01, 0.04)),
                "curvature": float(rng.choice([-1.0, 1.0]) * rng.uniform(0.0, 0.003))}
    if name == "hysteresis_shape":
        # further play operators between the nominal ones: a loop with more shape than nine draw
        return {"extra_weight": float(rng.uniform(0.3, 0.8))}
    if name == "hum":
        return {"freq": float(rng.choice([50.0, 60.0])), "amplitude_rel": float(rng.uniform(3.0, 8.0))}
    if name == "sensor_drift":
        return {"rate": float(rng.choice([-1.0, 1.0]) * rng.uniform(0.002, 0.006))}
    raise ValueError(f"unknown effect {name!r}")


SECTION_OF = {"creep": "creep", "sensor_leakage": "sensor", "amplifier_current_limit": "amplifier",
              "time_delay": "amplifier", "extra_resonance": "resonance", "thermal_drift": "drift"}


def make_plant(base: Model, rng, effects: dict, perturb=True) -> Model:
    """The nominal model with ordinary parameter mismatch and the given mechanisms switched on."""
    m = base.copy()
    if perturb:
        h = m["hysteresis"]
        w = np.array(h["weights"]) * rng.uniform(0.8, 1.2, size=len(h["weights"]))
        m.set("hysteresis", "weights", [float(v) for v in w], SRC)
        m.set("hysteresis", "scale", float(h["scale"] * rng.uniform(0.85, 1.2)), SRC)
        m.set("amplifier", "R", float(m["amplifier"]["R"] * rng.uniform(0.7, 1.4)), SRC)
        m.set("sensor", "d11", float(m["sensor"]["d11"] * rng.uniform(0.85, 1.15)), SRC)
        m.set("sensor", "offset", float(rng.uniform(-0.05, 0.05)), SRC)
        m.set("drift", "offset", float(rng.uniform(-0.5, 0.5)), SRC)
    if "hysteresis_shape" in effects:
        h = m["hysteresis"]
        r = np.array(h["thresholds"])
        w = np.array(h["weights"])
        mids = 0.5 * (r[1:] + r[:-1])
        w_mid = effects["hysteresis_shape"]["extra_weight"] * np.mean(w) * rng.uniform(0.3, 1.7, size=mids.size)
        order = np.argsort(np.concatenate([r, mids]), kind="stable")
        m.set("hysteresis", "thresholds", [float(v) for v in np.concatenate([r, mids])[order]], SRC)
        m.set("hysteresis", "weights", [float(v) for v in np.concatenate([w, w_mid])[order]], SRC)
    for name, par in effects.items():
        if name not in SECTION_OF:
            continue
        for key, value in par.items():
            m.set(SECTION_OF[name], key, value, SRC)
    return m.check()


@dataclass
class Case:
    t: np.ndarray
    u: np.ndarray
    x: np.ndarray | None
    us: np.ndarray | None
    truth: dict = field(default_factory=dict)

    def columns(self):
        cols = {"time": self.t, "u": self.u}
        if self.x is not None:
            cols["x"] = self.x
        if self.us is not None:
            cols["us"] = self.us
        return cols


def make_case(seed, effects=(), noise="mid", kinds=None, fs=5000.0, channels=("x", "us"),
              params=None, base=None, perturb=True, duration=None) -> Case:
    """One synthetic recording. ``effects``: names from :data:`EFFECTS` and :data:`CONTROLS`;
    ``params`` optionally fixes their parameters (name -> dict)."""
    rng = np.random.default_rng(seed)
    base = base or load_model()
    t, u, desc = programme(rng, fs, kinds, duration=duration)
    duration = float(t[-1])
    chosen = {}
    for name in effects:
        chosen[name] = (params or {}).get(name) or default_effect(name, rng, fs, duration)
    plant = make_plant(base, rng, chosen, perturb)
    sig = Signal("table", t=t, values=u, column="u")
    res = simulate(plant, sig, duration, step=1.0 / fs, mode="open", noise=False)
    sx, ss = NOISE[noise] if isinstance(noise, str) else noise
    sigma = {"x": sx, "us": ss}
    visibility = {}
    if "hysteresis_shape" in chosen:
        plant, visibility["hysteresis_shape"], factor = _visible_shape(plant, base, res, sigma, channels)
        chosen["hysteresis_shape"] = {**chosen["hysteresis_shape"],
                                      "extra_weight": chosen["hysteresis_shape"]["extra_weight"] * factor}
        res = simulate(plant, sig, duration, step=1.0 / fs, mode="open", noise=False)
    for name in [e for e in EFFECTS if e in chosen and e in SECTION_OF]:
        plant, res, chosen[name], visibility[name] = _visible(name, plant, base, res, chosen[name], sig,
                                                              duration, fs, sigma, channels)
    x = res["x"] + sx * rng.standard_normal(t.size)
    us = res["us"] + ss * rng.standard_normal(t.size)
    if "hum" in chosen:
        hp = chosen["hum"]
        x = x + hp["amplitude_rel"] * sx * np.sin(2 * np.pi * hp["freq"] * t + rng.uniform(0, 2 * np.pi))
    if "sensor_drift" in chosen:
        us = us + chosen["sensor_drift"]["rate"] * t
    truth = {"effects": sorted(chosen), "parameters": chosen, "noise": {"x": sx, "us": ss},
             "programme": desc, "seed": seed, "fs": fs, "duration_s": duration,
             "x_clean": res["x"], "us_clean": res["us"], "plant": plant, "visibility": visibility}
    return Case(t, u, x if "x" in channels else None, us if "us" in channels else None, truth)


def visibility_beyond_affine(with_e, without_e, sigma, channels) -> float:
    """What a mechanism changes that a channel's gain and offset cannot absorb: per recorded
    channel, the rms of ``d = y(with) - y(without)`` after the best fit ``a + b y(without)`` is
    removed from it, over the channel's noise rms; the largest over the channels (the rig's
    ``visibility_beyond_affine``)."""
    best = 0.0
    for c in channels:
        y0 = np.asarray(without_e[c], float)
        d = np.asarray(with_e[c], float) - y0
        a = np.column_stack([np.ones_like(y0), y0])
        coef, *_ = np.linalg.lstsq(a, d, rcond=None)
        best = max(best, float(np.sqrt(np.mean((d - a @ coef) ** 2))) / sigma[c])
    return best


def _stronger(name, par, fs):
    """One step up in size for a mechanism that is not visible yet; ``None`` at the end of its
    physical range."""
    q = dict(par)
    if name == "creep":
        q["gains"] = [g * 1.5 for g in par["gains"]]
        return q if sum(q["gains"]) <= 0.5 else None
    if name == "sensor_leakage":
        q["tau_leak"] = par["tau_leak"] / 1.5
        return q if q["tau_leak"] >= 0.1 else None
    if name == "amplifier_current_limit":
        q["I_max"] = par["I_max"] / 1.5
        return q if q["I_max"] >= 0.001 else None
    if name == "time_delay":
        n = round(par["delay"] * fs)
        q["delay"] = float(max(n + 1, round(1.5 * n))) / fs
        return q if q["delay"] * fs <= 30 else None
    if name == "extra_resonance":
        # lighter damping down to the range's 0.01, then lower (the amplifier's lag passes more)
        if par["zeta"] > 0.0101:
            q["zeta"] = max(par["zeta"] / 1.5, 0.01)
            return q
        q["f_n"] = par["f_n"] / 1.25
        return q if q["f_n"] >= 150.0 else None
    if name == "thermal_drift":
        q["rate"], q["curvature"] = 1.5 * par["rate"], 1.5 * par["curvature"]
        return q if abs(q["rate"]) <= 0.3 else None
    raise ValueError(name)


def _visible(name, plant, base, res, par, sig, duration, fs, sigma, channels):
    """Raise mechanism ``name`` until it is visible beyond a channel's gain and offset by
    :data:`VISIBLE` noise rms (the rig's rule), within its physical range. Returns the plant, its
    run, the mechanism's parameters and its visibility."""
    off = plant.copy()
    for key in par:
        off.set(SECTION_OF[name], key, base[SECTION_OF[name]][key], "off")
    res_off = simulate(off, sig, duration, step=1.0 / fs, mode="open", noise=False)
    while True:
        vis = visibility_beyond_affine(res, res_off, sigma, channels)
        q = _stronger(name, par, fs) if vis < VISIBLE else None
        if q is None:
            return plant, res, par, round(vis, 3)
        par = q
        plant = plant.copy()
        for key, value in par.items():
            plant.set(SECTION_OF[name], key, value, SRC)
        plant = plant.check()
        res = simulate(plant, sig, duration, step=1.0 / fs, mode="open", noise=False)


def _visible_shape(plant, base, res, noise, channels):
    """Raise the added operators' weights until the finer loop is visible beyond what a
    recalibration absorbs (the rig's rule, :mod:`piezo_fmu.rig.caseset`): the best PI on the
    nominal thresholds (non-negative weights and an offset, NNLS on the same stack voltage) misses
    it by :data:`VISIBLE` noise rms, the noise of the best recorded channel expressed as hysteresis
    stroke (channel noise over the channel's gain from stroke). Returns the plant, the misfit and
    the factor the added weights were raised by; the stack voltage does not depend on the loop
    (open loop), so one simulation and one pair of operator scans serve every factor."""
    from scipy.optimize import nnls

    from ..core.hysteresis import play_scan

    h = plant["hysteresis"]
    r, w = np.asarray(h["thresholds"], float), np.asarray(h["weights"], float)
    r_nom = np.asarray(base["hysteresis"]["thresholds"], float)
    extra = ~np.isin(r, r_nom)
    v = np.asarray(res["ua"], float) / h["u_norm"]
    plays = h["scale"] * play_scan(v, r)                        # [um] per unit weight
    basis = np.column_stack([play_scan(v, r_nom), np.ones_like(v), -np.ones_like(v)])
    x_h = plays @ w
    x_h = x_h - np.mean(x_h)
    stroke_noise = []
    for c in channels:
        y = res[c] - np.mean(res[c])
        gain = abs(float(y @ x_h) / max(float(x_h @ x_h), 1e-300))
        if gain > 0:
            stroke_noise.append(noise[c] / gain)
    sigma = min(stroke_noise)
    factor = 1.0
    while True:
        ww = np.where(extra, w * factor, w)
        x_h = plays @ ww
        coef, _ = nnls(basis, x_h)
        misfit = float(np.sqrt(np.mean((x_h - basis @ coef) ** 2))) / sigma
        if misfit >= VISIBLE or factor >= SHAPE_MAX_FACTOR:
            break
        factor = min(factor * 1.5, SHAPE_MAX_FACTOR)
    out = plant.copy()
    out.set("hysteresis", "weights", [float(v) for v in ww], SRC)
    return out.check(), round(misfit, 3), factor


def write_recording(path, case: Case, force=False):
    from ..io import atomic_writer

    cols = case.columns()
    names = list(cols)
    with atomic_writer(path, "w", force=force) as fh:
        fh.write("# synthetic recording (piezo_fmu.diagnose.synth); time [s], u [V], x [um], us [V]\n")
        fh.write(",".join(names) + "\n")
        np.savetxt(fh, np.column_stack([cols[c] for c in names]), delimiter=",", fmt="%.9g")


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m piezo_fmu.diagnose.synth", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--effects", default="", help=f"comma-separated, from {', '.join(EFFECTS + CONTROLS)}")
    ap.add_argument("--noise", choices=tuple(NOISE), default="mid")
    ap.add_argument("--programme", default="", help=f"comma-separated segments from {', '.join(PROGRAMMES)}")
    ap.add_argument("--fs", type=float, default=5000.0)
    ap.add_argument("--duration", type=float, default=None, help="length [s] (default: one pass of the segments)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", required=True)
    ap.add_argument("--truth", help="also write the hidden truth as JSON here")
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args(argv)
    effects = [e for e in a.effects.split(",") if e]
    kinds = [k for k in a.programme.split(",") if k] or None
    case = make_case(a.seed, effects, a.noise, kinds, a.fs, duration=a.duration)
    write_recording(a.out, case, a.force)
    if a.truth:
        from ..io import write_text

        t = {k: v for k, v in case.truth.items() if not k.endswith("_clean") and k != "plant"}
        write_text(a.truth, json.dumps(t, indent=2), a.force)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
