"""Magnitudes of the injected effects: catalogue mechanisms and off-catalogue controls.

Each effect has a one-number size knob, the *level* ``l`` in (0, 1]. Levels 0.5-1 cover the
physically plausible range of a present effect (for instance creep 1-5 % of a step per
decade, leakage time constants 20-0.2 s); below 0.5 the effect weakens continuously towards
nothing (for effects injected below visibility). ``caseset`` raises the level of a present
effect until it is visible and lowers that of a hidden one until it is not.

``fixed(name, rng, ctx)`` draws what does not set the size (creep's t0, the drift's form, the
resonance's frequency, the shape variant, the hum's harmonics ...); ``realise(name, level,
fixed, ctx)`` returns the parameter dict that ``plant.simulate`` reads.

``ctx`` holds the case's nominal numbers: ``plant``, ``duration`` [s], ``stroke`` (peak-to-peak
push-rod displacement of the nominal run) [um], ``slew`` (largest |dua/dt| of the nominal
run) [V/s], ``channels`` (present channels).
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import PchipInterpolator

from .hysteresis import draw_shape
from .plant import CATALOGUE, CONTROLS

# requirements on the case for each effect
NEEDS_SEGMENT = {
    "creep": ["steps"], "sensor_leakage": ["steps"], "amplifier_current_limit": ["steps"],
    "extra_resonance": ["steps"], "hysteresis_shape": ["triangle|sine_set"],
    "time_delay": ["multisine|chirp"], "thermal_drift": [],
    "mains_hum": [], "us_offset_drift": [], "push_rod_backlash": ["triangle|sine_set"],
    "probe_quantisation": [], "probe_gain_modulation": ["steps|sine_set"],
}
MIN_DURATION = {"thermal_drift": 6.0, "us_offset_drift": 4.0, "probe_gain_modulation": 4.0}


def _piece(level: float, at0: float, at_half: float, at1: float, log: bool = False) -> float:
    """Piecewise interpolation: level 0 -> ``at0``, 0.5 -> ``at_half``, 1 -> ``at1``."""
    f = (lambda v: np.log(v)) if log else (lambda v: v)
    g = (lambda v: np.exp(v)) if log else (lambda v: v)
    if level <= 0.5:
        return float(g(f(at0) + (f(at_half) - f(at0)) * level / 0.5))
    return float(g(f(at_half) + (f(at1) - f(at_half)) * (level - 0.5) / 0.5))


def fixed(name: str, rng: np.random.Generator, ctx: dict) -> dict:
    """Draw the parts of an effect that do not set its size."""
    plant = ctx["plant"]
    T = ctx["duration"]
    if name == "creep":
        return {"t0": float(np.exp(rng.uniform(np.log(0.005), np.log(0.2))))}
    if name == "thermal_drift":
        return {"form": ["warmup", "ramp", "mixed"][rng.integers(3)],
                "tau": float(rng.uniform(0.1, 0.6) * T), "sign": float(rng.choice([-1.0, 1.0]))}
    if name in ("sensor_leakage", "amplifier_current_limit", "time_delay"):
        return {}
    if name == "extra_resonance":
        hi = 0.4 * plant.fs
        for _ in range(50):
            f = float(np.exp(rng.uniform(np.log(50.0), np.log(hi))))
            if abs(np.log(f / plant.f1)) > np.log(1.5):
                break
        return {"f": f}
    if name == "hysteresis_shape":
        draw_shape(rng, plant.hysteresis, plant.u_lo)
        return {"variant": plant.hysteresis.shape}
    if name == "mains_hum":
        base = float(rng.choice([50.0, 60.0]))
        harm = [1, 2, 3] if rng.random() < 0.5 else [1, 3, 5]
        keep = [h for h in harm if h * base < 0.45 * plant.fs] or [1]
        chans = list(ctx["channels"])
        if len(chans) == 2:
            chans = [["x"], ["us"], ["x", "us"]][rng.integers(3)]
        return {"freq": base, "harmonics": keep,
                "weights": [1.0] + [float(rng.uniform(0.1, 0.5)) for _ in keep[1:]],
                "phases": [float(rng.uniform(0, 2 * np.pi)) for _ in keep],
                "channels": chans, "rel": float(rng.uniform(4.0, 12.0))}
    if name == "us_offset_drift":
        k = int(rng.integers(5, 10))
        knots_t = np.linspace(0.0, T, k)
        walk = np.cumsum(rng.standard_normal(k))
        walk -= walk[0]
        dense_t = np.linspace(0.0, T, 200)
        dense = PchipInterpolator(knots_t, walk)(dense_t)
        dense /= max(np.abs(dense).max(), 1e-12)
        return {"knots_t": dense_t, "knots_v": dense, "rel": float(rng.uniform(6.0, 20.0))}
    if name == "push_rod_backlash":
        return {"rel": float(rng.uniform(0.01, 0.03))}
    if name == "probe_quantisation":
        return {"rel": float(rng.uniform(12.0, 25.0))}
    if name == "probe_gain_modulation":
        return {"depth": float(rng.uniform(0.01, 0.03)),
                "freq": float(rng.uniform(2.0, 6.0) / T), "phase": float(rng.uniform(0, 2 * np.pi))}
    raise ValueError(f"unknown effect {name!r}")


def realise(name: str, level: float, fx: dict, ctx: dict) -> dict:
    """Parameters of an effect at ``level`` (see the module docstring), with their units.

    Returns a dict read by ``plant.simulate``; keys ending in a unit are for the record.
    """
    plant = ctx["plant"]
    if name == "creep":
        g = _piece(level, 0.0, 0.01, 0.05)
        return {"gamma": g, "t0": fx["t0"]}
    if name == "thermal_drift":
        rel = _piece(level, 0.0, 0.005, 0.05)
        return {"form": fx["form"], "tau": fx["tau"], "relative": rel,
                "amplitude": fx["sign"] * rel * ctx["stroke"]}
    if name == "sensor_leakage":
        return {"tau": _piece(level, 2e4, 20.0, 0.2, log=True)}
    if name == "amplifier_current_limit":
        ratio = _piece(level, 1.0, 0.7, 0.03, log=True)
        slew = ratio * ctx["slew"]
        return {"I_max": slew * plant.C_a, "slew": slew, "slew_ratio": ratio}
    if name == "time_delay":
        M = plant.oversample
        if level >= 0.5:
            n_max = int(np.clip(np.floor(2e-3 * plant.fs), 1, 20))
            n_rec = round(n_max ** ((level - 0.5) / 0.5))
            steps = n_rec * M
        else:
            steps = int(np.floor(level / 0.5 * M))
        return {"steps_internal": steps, "delay": steps * plant.dt_int,
                "samples": steps / M}
    if name == "extra_resonance":
        f = fx["f"]
        if level >= 0.5:
            s = (level - 0.5) / 0.5
            zeta = 0.05 * 0.1 ** min(1.0, s / 0.6)
            if s > 0.6:
                f = f * (50.0 / f) ** ((s - 0.6) / 0.4)
        else:
            zeta = 0.05 * (1.0 + 10.0 * (0.5 - level))
        if abs(np.log(f / plant.f1)) < np.log(1.5):
            f = plant.f1 / 1.5 if plant.f1 / 1.5 >= 50.0 else min(plant.f1 * 1.5, 0.4 * plant.fs)
        return {"f": float(f), "zeta": float(zeta)}
    if name == "hysteresis_shape":
        span = plant.u_hi - plant.u_lo
        return {"variant": fx["variant"], "amplitude": _piece(level, 0.0, 0.02, 0.12) * span}
    if name == "mains_hum":
        a = fx["rel"] * level / 0.75
        out = dict(fx)
        out["amplitude_x"] = a * plant.sigma_x
        out["amplitude_us"] = a * plant.sigma_us
        return out
    if name == "us_offset_drift":
        return {"knots_t": fx["knots_t"], "knots_v": fx["knots_v"],
                "amplitude": fx["rel"] * level / 0.75 * plant.sigma_us}
    if name == "push_rod_backlash":
        return {"half_width": fx["rel"] * level / 0.75 * ctx["stroke"]}
    if name == "probe_quantisation":
        return {"step": fx["rel"] * level / 0.75 * plant.sigma_x}
    if name == "probe_gain_modulation":
        return {"depth": fx["depth"] * level / 0.75, "freq": fx["freq"], "phase": fx["phase"]}
    raise ValueError(f"unknown effect {name!r}")


UNITS = {
    "gamma": "1/decade", "t0": "s", "form": "", "tau": "s", "relative": "1", "amplitude": "um",
    "I_max": "A", "slew": "V/s", "slew_ratio": "1", "steps_internal": "1", "delay": "s",
    "samples": "samples", "f": "Hz", "zeta": "1", "variant": "", "freq": "Hz", "harmonics": "1",
    "weights": "1", "phases": "rad", "channels": "", "rel": "1", "amplitude_x": "um",
    "amplitude_us": "V", "half_width": "um", "step": "um", "depth": "1", "phase": "rad",
}


def describe(name: str, p: dict) -> dict:
    """The effect's parameters for the truth record, ``{name.key: {value, unit}}``."""
    out = {}
    for k, v in p.items():
        if k in ("knots_t", "knots_v"):
            continue
        unit = UNITS.get(k, "")
        if name == "hysteresis_shape" and k == "amplitude":
            unit = "V"
        if name == "us_offset_drift" and k == "amplitude":
            unit = "V"
        if isinstance(v, np.ndarray):
            v = v.tolist()
        out[f"{name}.{k}"] = {"value": v, "unit": unit}
    return out


assert set(NEEDS_SEGMENT) == set(CATALOGUE) | set(CONTROLS)
