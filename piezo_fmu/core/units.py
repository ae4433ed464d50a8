"""Build the units from a model's parameter sections (a plain nested dict, NumPy-only).

``sections`` is ``Model.sections`` (section -> key -> value): the same mapping serves the
monolithic model and, inside an FMU, the slaves, which carry the model's values bundled as JSON.
"""
from __future__ import annotations

from .control import Compensator
from .hysteresis import PrandtlIshlinskii
from .plant import Actuator, Sensor

__all__ = ["hysteresis_from", "actuator_from", "sensor_from", "compensator_from"]


def hysteresis_from(sections, name="hysteresis") -> PrandtlIshlinskii:
    s = sections[name]
    return PrandtlIshlinskii(s["thresholds"], s["weights"], s["u_norm"], s["scale"])


def actuator_from(sections) -> Actuator:
    a, me = sections["amplifier"], sections["mechanics"]
    cr = sections.get("creep", {})
    dr = sections.get("drift", {})
    res = sections.get("resonance", {})
    drift = [dr.get("offset", 0.0), dr.get("rate", 0.0), dr.get("curvature", 0.0)]
    while drift and drift[-1] == 0.0:
        drift.pop()
    f_n = res.get("f_n", 0.0)
    act = Actuator(
        k_amp=a["k_amp"], R=a["R"], C_a=a["C_a"], u_min=a["u_min"], u_max=a["u_max"],
        I_max=a.get("I_max", float("inf")), delay=a.get("delay", 0.0),
        hysteresis=hysteresis_from(sections),
        saturation=sections["hysteresis"].get("saturation", float("inf")),
        m=me["m"], c=me["c"], k_a=me["k_a"], k_f=me["k_f"],
        creep_gains=cr.get("gains", []), creep_taus=cr.get("time_constants", []),
        resonance=(f_n, res.get("zeta", 0.05)) if f_n > 0 else None,
        drift=drift, max_step=sections.get("simulation", {}).get("actuator_max_step", 1e-4),
    )
    act.reset()
    return act


def sensor_from(sections, noise=True) -> Sensor:
    kw = dict(sections["sensor"])
    if not noise:
        kw["noise_std"] = 0.0
    sen = Sensor(**kw)
    sen.reset()
    return sen


def compensator_from(sections, mode=None, inverse=None, signal="external", amplitude=0.0,
                     offset=0.0, freq=1.0, phase_deg=-90.0) -> Compensator:
    c = sections["compensator"]
    d = sections["compensator.dynamics"]
    comp = Compensator(
        model=hysteresis_from(sections, "compensator.hysteresis"), g_num=d["num"], g_den=d["den"],
        filter_hz=c["filter_hz"], k_ideal=c["k_ideal"], k_amp=c["k_amp"],
        sensor_gain=c["sensor_gain"], sensor_offset=c.get("sensor_offset", 0.0),
        Kp=c["Kp"], Ki=c["Ki"], Kd=c.get("Kd", 0.0), Tf=c.get("Tf", 1e-4),
        uc_min=c["uc_min"], uc_max=c["uc_max"], mode=mode or c["mode"],
        inverse=inverse or c["inverse"], signal=signal, amplitude=amplitude, offset=offset,
        freq=freq, phase_deg=phase_deg,
    )
    comp.reset()
    return comp
