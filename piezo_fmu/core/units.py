"""Build the units from a model's parameter sections (a plain nested dict, NumPy-only).

``sections`` is ``Model.sections`` (section -> key -> value): the same mapping serves the
monolithic model and, inside an FMU, the slaves, which carry the model's values bundled as JSON.
"""
from __future__ import annotations

import math

import numpy as np

from .control import Compensator
from .hysteresis import PrandtlIshlinskii
from .linear import is_hurwitz
from .plant import Actuator, Sensor
from .preisach import KPCells, cells_problem

__all__ = ["hysteresis_from", "cells_from", "actuator_from", "sensor_from", "compensator_from", "check_sections"]


def check_sections(sections) -> list:
    """Consistency problems across parameters (each names the key), empty when consistent.

    Checks what single values cannot: rails in order, invertible hysteresis models, creep lists
    of equal length, and a compensator ``G(s)`` that is proper, stable, minimum-phase (so
    ``G_inv`` is stable) and of unity DC gain. Used by model files and by the FMUs.
    """
    problems = []
    a = sections.get("amplifier")
    if a is not None and not a["u_max"] > a["u_min"]:
        problems.append(f"amplifier.u_max: must exceed amplifier.u_min ({a['u_max']} <= {a['u_min']})")
    me = sections.get("mechanics")
    if me is not None and me.get("pickoff", "stack") == "load" and not me["k_f"] > 0:
        problems.append("mechanics.pickoff: 'load' needs a load spring (mechanics.k_f > 0)")
    c = sections.get("compensator")
    if c is not None and not c["uc_max"] > c["uc_min"]:
        problems.append(f"compensator.uc_max: must exceed compensator.uc_min "
                        f"({c['uc_max']} <= {c['uc_min']})")
    for sec in ("hysteresis", "compensator.hysteresis"):
        h = sections.get(sec)
        if h is None:
            continue
        pi = PrandtlIshlinskii.__new__(PrandtlIshlinskii)
        for attr, key in (("thresholds", "thresholds"), ("weights", "weights"),
                          ("in_scale", "u_norm"), ("out_scale", "scale")):
            object.__setattr__(pi, attr, tuple(h[key]) if attr in ("thresholds", "weights") else h[key])
        problem = pi.problem()
        if problem:
            key = "weights" if "weight" in problem else "thresholds"
            problems.append(f"{sec}.{key}: {problem}")
    h = sections.get("hysteresis")
    if h is not None:
        problem = cells_problem(*(h.get(f"cells_{k}", []) for k in ("up", "down", "width", "weights")))
        if problem:
            key = problem.split(":")[0] if problem.startswith("cells_") else "cells_up"
            problems.append(f"hysteresis.{key}: {problem}")
    cr = sections.get("creep")
    if cr is not None and len(cr["gains"]) != len(cr["time_constants"]):
        problems.append(f"creep.time_constants: has {len(cr['time_constants'])} entries but creep.gains "
                        f"has {len(cr['gains'])}")
    d = sections.get("compensator.dynamics")
    if d is not None:
        num = np.trim_zeros(np.array(d["num"], dtype=float), "f")
        den = np.trim_zeros(np.array(d["den"], dtype=float), "f")
        if den.size == 0:
            problems.append("compensator.dynamics.den: is zero")
        elif num.size > den.size:
            problems.append("compensator.dynamics.num: G(s) is improper "
                            "(numerator degree > denominator degree)")
        elif not is_hurwitz(den):
            problems.append(f"compensator.dynamics.den: G(s) is unstable (poles {np.roots(den)})")
        elif num.size == 0 or not is_hurwitz(num):
            problems.append("compensator.dynamics.num: G(s) has right-half-plane or zero numerator "
                            "roots, so G_inv(s) would be unstable")
        elif abs(num[-1] / den[-1] - 1.0) > 1e-6:
            problems.append(f"compensator.dynamics: G(s) must have unity DC gain, has {num[-1] / den[-1]:.6g}")
    return problems


def hysteresis_from(sections, name="hysteresis") -> PrandtlIshlinskii:
    s = sections[name]
    return PrandtlIshlinskii(s["thresholds"], s["weights"], s["u_norm"], s["scale"])


def cells_from(sections, name="hysteresis") -> KPCells:
    """The device's KP cells (:mod:`.preisach`; none when the model file lists none)."""
    s = sections[name]
    return KPCells(*(s.get(f"cells_{k}", ()) for k in ("up", "down", "width", "weights")))


def actuator_from(sections) -> Actuator:
    a, me = sections["amplifier"], sections["mechanics"]
    cr = sections.get("creep", {})
    dr = sections.get("drift", {})
    res = sections.get("resonance", {})
    drift = [dr.get("offset", 0.0), dr.get("rate", 0.0), dr.get("curvature", 0.0)]
    f_n = res.get("f_n", 0.0)
    act = Actuator(
        k_amp=a["k_amp"], R=a["R"], C_a=a["C_a"], u_min=a["u_min"], u_max=a["u_max"],
        I_max=a.get("I_max", float("inf")), delay=a.get("delay", 0.0), tau_2=a.get("tau_2", 0.0),
        pickoff=me.get("pickoff", "stack"), resonance_at=res.get("position", "output"),
        hysteresis=hysteresis_from(sections),
        saturation=sections["hysteresis"].get("saturation", float("inf")),
        prepared=sections["hysteresis"].get("prepared", 0.0), cells=cells_from(sections),
        m=me["m"], c=me["c"], k_a=me["k_a"], k_f=me["k_f"],
        creep_gains=cr.get("gains", []), creep_taus=cr.get("time_constants", []),
        resonance=(f_n, res.get("zeta", 0.05)) if f_n > 0 else None,
        drift=drift, drift_tau=dr.get("time_constant", math.inf), max_step=sections.get("simulation", {}).get("actuator_max_step", 1e-4),
        stroke_path=sections.get("simulation", {}).get("stroke_path", "linear"),
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
