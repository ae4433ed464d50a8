"""PID design for the inverse-compensated loop, with python-control.

With the PID acting before the inverse model (see :mod:`piezo_fmu.core.control`), the loop the
PID sees is, linearised, ``P(s) = G_inv(s) G(s) s_ratio``: the identified linear dynamics times
their proper inverse, i.e. the filter ``1 / (tau_f s + 1)``, times the ratio ``s_ratio`` of the
device's local hysteresis slope to the model's (1 when the model is exact). The design works on
the sampled loop at the slowest rate the controller runs (the co-simulation step, 1e-4 s; ZOH):

* PI (+ optional filtered D) gains are searched on a grid for the largest attenuation of the
  tracking error at 50 Hz (the paper's highest test frequency), subject to a phase margin
  >= 55 deg and a gain margin >= 10 dB;
* the margins are then re-checked for ``s_ratio`` in [0.5, 2] (model error) and reported.
"""
from __future__ import annotations

import math

import control as ct
import numpy as np

from .core.control import inverse_filter_tf
from .model import Model

__all__ = ["loop", "margins", "design_pid", "DESIGN_STEP", "PM_MIN_DEG", "GM_MIN_DB"]

DESIGN_STEP = 1e-4      # s: the co-simulation communication step (slowest controller rate)
PM_MIN_DEG = 55.0
GM_MIN_DB = 10.0


def _pid_discrete(kp, ki, kd, tf, dt):
    """The backward-Euler PID of :func:`piezo_fmu.core.control.pid_step` as a z-domain TF."""
    z = ct.tf([1.0, 0.0], [1.0], dt)
    c = kp + ki * dt * z / (z - 1)
    if kd:
        c = c + kd * (z - 1) / ((tf + dt) * z - tf)
    return c


def loop(model: Model, kp, ki, kd=0.0, tf=1e-4, filter_hz=None, dt=DESIGN_STEP, s_ratio=1.0):
    """Sampled open loop ``L(z)`` of the PID around the inverse-compensated device model."""
    d = model["compensator.dynamics"]
    fh = filter_hz if filter_hz is not None else model["compensator"]["filter_hz"]
    gi_num, gi_den = inverse_filter_tf(d["num"], d["den"], fh)
    plant = ct.tf(gi_num, gi_den) * ct.tf(d["num"], d["den"]) * s_ratio
    pd = ct.c2d(ct.minreal(plant, verbose=False), dt, "zoh")
    return _pid_discrete(kp, ki, kd, tf, dt) * pd


def margins(lz, f_eval=50.0):
    """Gain margin [dB], phase margin [deg], crossover [Hz] and |S| at ``f_eval`` [Hz] of ``L(z)``."""
    gm, pm, wcg, wcp = ct.margin(lz)
    gm_db = 20 * math.log10(gm) if gm and np.isfinite(gm) else math.inf
    s = 1.0 / (1.0 + lz(np.exp(1j * 2 * math.pi * f_eval * lz.dt)))
    closed = ct.feedback(lz, 1)
    return {"gm_db": gm_db, "pm_deg": float(pm), "crossover_hz": float(wcp) / (2 * math.pi),
            "S_at_hz": float(abs(s)), "f_eval_hz": f_eval,
            "stable": bool(np.all(np.abs(ct.poles(closed)) < 1.0))}


def design_pid(model: Model, filter_hz=2000.0, dt=DESIGN_STEP) -> dict:
    """Choose Kp, Ki (and Kd if it helps) by grid search; returns gains, margins and provenance."""
    best = None
    for ki in np.geomspace(300.0, 30000.0, 25):
        for kp in (0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0):
            for kd in (0.0, 2e-5, 5e-5):
                lz = loop(model, kp, ki, kd, 1e-4, filter_hz, dt)
                m = margins(lz)
                if not m["stable"] or m["pm_deg"] < PM_MIN_DEG or m["gm_db"] < GM_MIN_DB:
                    continue
                # robustness: the loop must stay stable with the slope ratio in [0.5, 2]
                if any(not margins(loop(model, kp, ki, kd, 1e-4, filter_hz, dt, r))["stable"]
                       for r in (0.5, 2.0)):
                    continue
                if best is None or m["S_at_hz"] < best[0]["S_at_hz"] - 1e-12:
                    best = (m, kp, ki, kd)
    if best is None:
        raise RuntimeError("no PID met the margin requirements")
    m, kp, ki, kd = best
    robust = {str(r): margins(loop(model, kp, ki, kd, 1e-4, filter_hz, dt, r))
              for r in (0.5, 1.0, 2.0)}
    source = (f"designed by piezo_fmu.control_design: grid search at dt = {dt:g} s for the smallest "
              f"|S(50 Hz)| with PM >= {PM_MIN_DEG:g} deg and GM >= {GM_MIN_DB:g} dB; "
              f"got PM {m['pm_deg']:.1f} deg, GM {m['gm_db']:.1f} dB, crossover "
              f"{m['crossover_hz']:.0f} Hz, |S(50 Hz)| = {m['S_at_hz']:.3f}")
    return {"Kp": kp, "Ki": float(ki), "Kd": kd, "Tf": 1e-4, "filter_hz": filter_hz,
            "margins": m, "robust": robust, "source": source}
