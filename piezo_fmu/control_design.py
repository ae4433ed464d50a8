"""PID design for the inverse-compensated loop, with python-control.

With the PID acting before the inverse model (see :mod:`piezo_fmu.core.control`), the loop the
PID sees is, linearised, ``P(s) = G_inv(s) G(s) s_ratio``: the identified linear dynamics times
their proper inverse, i.e. the filter ``1 / (tau_f s + 1)``, times the ratio ``s_ratio`` of the
device's local hysteresis slope to the model's (1 when the model is exact). The design works on
the sampled loop at the slowest rate the controller runs (the co-simulation step, 1e-4 s; ZOH):

* PID gains (with a filtered derivative) are searched on a grid for the largest attenuation of the
  tracking error at 50 Hz (the paper's highest test frequency), subject to
  - phase margin >= 55 deg and gain margin >= 10 dB with Gauss-Seidel coupling (our master and the
    monolithic model: no delay beyond the sample and hold), and
  - phase margin >= 45 deg and gain margin >= 6 dB with **Jacobi** coupling, which adds two
    communication steps of delay around the loop (fmpy.ssp, libcosim and most system-level tools
    step FMUs in parallel): the FMUs and the SSP must work in any master;
* stability is re-checked for ``s_ratio`` in [0.5, 2] (model error) and the margins are reported.

Dropping the Jacobi requirement allows a 1.5 kHz crossover (|S(50 Hz)| = 0.033) that is unstable
with a Jacobi master at 1e-4 s (phase margin -48 deg); with it the crossover is about 530 Hz.
"""
from __future__ import annotations

import math

import control as ct
import numpy as np

from .core.control import inverse_filter_tf
from .model import Model

__all__ = ["loop", "margins", "design_pid", "DESIGN_STEP", "PM_MIN_DEG", "GM_MIN_DB"]

DESIGN_STEP = 1e-4      # s: the co-simulation communication step (slowest controller rate)
PM_MIN_DEG = 55.0       # Gauss-Seidel
GM_MIN_DB = 10.0
PM_MIN_JACOBI_DEG = 45.0
GM_MIN_JACOBI_DB = 6.0
JACOBI_DELAY_STEPS = 2


def _pid_discrete(kp, ki, kd, tf, dt):
    """The backward-Euler PID of :func:`piezo_fmu.core.control.pid_step` as a z-domain TF."""
    z = ct.tf([1.0, 0.0], [1.0], dt)
    c = kp + ki * dt * z / (z - 1)
    if kd:
        c = c + kd * (z - 1) / ((tf + dt) * z - tf)
    return c


def loop(model: Model, kp, ki, kd=0.0, tf=1e-4, filter_hz=None, dt=DESIGN_STEP, s_ratio=1.0,
         delay_steps=0):
    """Sampled open loop ``L(z)`` of the PID around the inverse-compensated device model.

    ``delay_steps`` adds whole steps of delay (2 for a Jacobi co-simulation master).
    """
    d = model["compensator.dynamics"]
    fh = filter_hz if filter_hz is not None else model["compensator"]["filter_hz"]
    gi_num, gi_den = inverse_filter_tf(d["num"], d["den"], fh)
    plant = ct.tf(gi_num, gi_den) * ct.tf(d["num"], d["den"]) * s_ratio
    pd = ct.c2d(ct.minreal(plant, verbose=False), dt, "zoh")
    lz = _pid_discrete(kp, ki, kd, tf, dt) * pd
    if delay_steps:
        lz = lz * ct.tf([1.0], [1.0] + [0.0] * delay_steps, dt)
    return lz


def margins(lz, f_eval=50.0, n=4000):
    """Gain margin [dB], phase margin [deg], crossover [Hz] and |S| at ``f_eval`` [Hz] of ``L(z)``.

    Margins come from a dense sweep of ``L(e^{j w dt})`` up to the Nyquist frequency (all gain and
    phase crossovers, the worst one reported); stability from the closed-loop poles.
    (``control.margin`` falls back to a numerically fragile method on these loops.)
    """
    dt = lz.dt
    w = np.geomspace(2 * math.pi * 0.01, math.pi / dt, n)
    resp = np.asarray(lz(np.exp(1j * w * dt))).ravel()
    mag = np.abs(resp)
    phase = np.degrees(np.unwrap(np.angle(resp)))
    pm, wc = math.inf, math.nan
    for i in np.nonzero(np.diff(np.sign(mag - 1.0)) != 0)[0]:
        f = (0.0 - math.log(mag[i])) / (math.log(mag[i + 1]) - math.log(mag[i]))
        ph = phase[i] + f * (phase[i + 1] - phase[i])
        margin = (ph + 360.0) % 360.0 - 180.0
        if margin < pm:
            pm, wc = margin, w[i] + f * (w[i + 1] - w[i])
    gm_db = math.inf
    turns = np.floor((phase + 180.0) / 360.0)
    for i in np.nonzero(np.diff(turns) != 0)[0]:
        target = 360.0 * max(turns[i], turns[i + 1]) - 180.0
        f = (target - phase[i]) / (phase[i + 1] - phase[i])
        g = math.exp(math.log(mag[i]) + f * (math.log(mag[i + 1]) - math.log(mag[i])))
        gm_db = min(gm_db, -20.0 * math.log10(g))
    s = 1.0 / (1.0 + lz(np.exp(1j * 2 * math.pi * f_eval * dt)))
    closed = ct.feedback(lz, 1)
    return {"gm_db": gm_db, "pm_deg": float(pm), "crossover_hz": float(wc) / (2 * math.pi),
            "S_at_hz": float(abs(s)), "f_eval_hz": f_eval,
            "stable": bool(np.all(np.abs(ct.poles(closed)) < 1.0))}


def design_pid(model: Model, filter_hz=2000.0, dt=DESIGN_STEP) -> dict:
    """Choose Kp, Ki, Kd, Tf by grid search (see the module docstring); returns gains, margins and
    provenance."""
    import itertools
    import warnings

    best = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for ki, kp, kd, tf in itertools.product(np.geomspace(1500.0, 15000.0, 17),
                                                (0.0, 0.1, 0.2, 0.3, 0.4, 0.6),
                                                (0.0, 2e-5, 5e-5, 1e-4), (2e-5, 5e-5, 1e-4)):
            if kd == 0.0 and tf != 1e-4:
                continue
            m = margins(loop(model, kp, ki, kd, tf, filter_hz, dt))
            if not m["stable"] or m["pm_deg"] < PM_MIN_DEG or m["gm_db"] < GM_MIN_DB:
                continue
            if best is not None and m["S_at_hz"] >= best[0]["S_at_hz"] - 1e-12:
                continue
            mj = margins(loop(model, kp, ki, kd, tf, filter_hz, dt, delay_steps=JACOBI_DELAY_STEPS))
            if not mj["stable"] or mj["pm_deg"] < PM_MIN_JACOBI_DEG or mj["gm_db"] < GM_MIN_JACOBI_DB:
                continue
            if any(not margins(loop(model, kp, ki, kd, tf, filter_hz, dt, r))["stable"]
                   for r in (0.5, 2.0)):
                continue
            best = (m, kp, float(ki), kd, tf, mj)
        if best is None:
            raise RuntimeError("no PID met the margin requirements")
        m, kp, ki, kd, tf, mj = best
        ki = float(f"{ki:.4g}")
        robust = {str(r): margins(loop(model, kp, ki, kd, tf, filter_hz, dt, r)) for r in (0.5, 1.0, 2.0)}
        jacobi = margins(loop(model, kp, ki, kd, tf, filter_hz, dt, delay_steps=JACOBI_DELAY_STEPS))
    source = (f"designed by piezo_fmu.control_design at dt = {dt:g} s: smallest |S(50 Hz)| with "
              f"PM >= {PM_MIN_DEG:g} deg, GM >= {GM_MIN_DB:g} dB (Gauss-Seidel) and PM >= "
              f"{PM_MIN_JACOBI_DEG:g} deg, GM >= {GM_MIN_JACOBI_DB:g} dB (Jacobi, 2 steps delay); got "
              f"PM {m['pm_deg']:.1f} deg, GM {m['gm_db']:.1f} dB, crossover {m['crossover_hz']:.0f} Hz, "
              f"|S(50 Hz)| = {m['S_at_hz']:.3f}; Jacobi PM {jacobi['pm_deg']:.1f} deg, "
              f"GM {jacobi['gm_db']:.1f} dB")
    return {"Kp": kp, "Ki": ki, "Kd": kd, "Tf": tf, "filter_hz": filter_hz,
            "margins": m, "jacobi": jacobi, "robust": robust, "source": source}
