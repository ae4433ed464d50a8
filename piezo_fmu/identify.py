"""Identification of the compensator's models from measurements, as in the paper.

The compensator never sees the device's parameters. It gets what an experimenter would measure:

1. **Static PI model** (paper Sec. 3.1): a 0.5 Hz, 0-30 V sine from the relaxed state, the
   displacement measured with probe noise; weights by constrained linear least squares
   (``w_0 > 0``, ``w_i >= 0``, so the model is invertible) on the matrix of play-operator outputs.
2. **Sensor calibration**: sensor voltage against measured displacement on the same record.
3. **Linear dynamics** ``G(s)`` of the dynamic model (Figure 6: linear part, then the 0.5 Hz
   quasi-static PI): first-order lag with unity DC gain fitted by output-error least squares to
   sine records at higher frequencies (the PI model held fixed).
4. **Ideal gain** ``k_ideal``: slope of the line through the ends of the steady 0-30 V loop of
   the identified model, the "ideal linear relationship between input voltage and output
   displacement" that the references follow.

The PID is designed in :mod:`piezo_fmu.control_design`. :func:`identify_compensator` runs all of
it and returns a new :class:`Model` whose compensator sections carry the results and provenance.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, lsq_linear

from .core.hysteresis import PrandtlIshlinskii
from .core.linear import LinearSystem
from .model import Model
from .simulate import Signal, simulate

__all__ = ["Measurement", "measure", "fit_pi", "fit_first_order", "apply_linear", "ideal_gain",
           "identify_compensator", "IDENT_THRESHOLDS", "IDENT_FREQS"]

IDENT_THRESHOLDS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)
IDENT_FREQS = (10.0, 20.0, 50.0)


@dataclass
class Measurement:
    """An open-loop record: time [s], nominal stack voltage ``u = k_amp uc`` [V], measured
    displacement ``x`` [um] (with probe noise), sensor voltage ``us`` [V], and the noise-free
    displacement ``x_true`` [um] (available in simulation only, for reference)."""

    t: np.ndarray
    u: np.ndarray
    x: np.ndarray
    us: np.ndarray
    x_true: np.ndarray


def measure(model: Model, signal: Signal, stop_time, record_step=1e-3, seed_offset=0,
            engine="auto") -> Measurement:
    """Drive the device open-loop with ``signal`` and 'measure' it as an experimenter would."""
    res = simulate(model, signal, stop_time, mode="open", record_step=record_step, engine=engine)
    meas = model["measurement"]
    rng = np.random.default_rng(meas["seed"] + seed_offset)
    x = res["x"] + meas["x_noise_std"] * rng.standard_normal(res["x"].size)
    u = model["compensator"]["k_amp"] * res["uc"]
    return Measurement(res["time"], u, x, res["us"], res["x"].copy())


def fit_pi(u, x, thresholds=IDENT_THRESHOLDS, u_norm=30.0, scale=1.0, w0_min=1e-6):
    """PI model from input ``u`` [V] and output ``x`` [um] by bounded linear least squares.

    Returns ``(model, rms_residual)``. The model's weights are in units of ``scale`` [um].
    """
    z = PrandtlIshlinskii(thresholds, [1.0] * len(thresholds), u_norm, 1.0).operators(u)
    lb = np.zeros(z.shape[1])
    lb[0] = w0_min
    sol = lsq_linear(z * scale, np.asarray(x, dtype=float), bounds=(lb, np.inf), method="bvls")
    model = PrandtlIshlinskii(tuple(thresholds), tuple(sol.x), u_norm, scale)
    resid = model.apply(u) - x
    return model, float(np.sqrt(np.mean(resid ** 2)))


def apply_linear(num, den, t, u):
    """Response of ``num/den`` to the sampled input ``u`` (linear interpolation), from rest at u[0]."""
    sys = LinearSystem(num, den, "foh")
    sys.reset(u[0])
    y = np.empty_like(u)
    y[0] = sys.output()
    dt = np.diff(t)
    for k in range(1, u.size):
        y[k] = sys.step(u[k], dt[k - 1])
    return y


def fit_first_order(records, pi: PrandtlIshlinskii, tau0=1e-3):
    """Fit ``G(s) = 1 / (tau s + 1)`` so that ``PI[G u]`` matches the records; returns (num, den, rms)."""

    def resid(p):
        tau = math.exp(p[0])
        out = []
        for rec in records:
            v = apply_linear([1.0], [tau, 1.0], rec.t, rec.u)
            out.append(pi.apply(v) - rec.x)
        return np.concatenate(out)

    sol = least_squares(resid, [math.log(tau0)], x_scale=[1.0])
    tau = math.exp(sol.x[0])
    rms = float(np.sqrt(np.mean(sol.fun ** 2)))
    return [1.0], [tau, 1.0], rms


def ideal_gain(pi: PrandtlIshlinskii, u_lo=0.0, u_hi=30.0, periods=3, n=3000):
    """Slope [um/V] of the line through the ends of the steady ``u_lo..u_hi`` loop of ``pi``."""
    ph = np.linspace(0.0, periods, periods * n + 1)
    u = u_lo + (u_hi - u_lo) * 0.5 * (1.0 - np.cos(2.0 * np.pi * ph))
    x = pi.apply(u)
    last = ph >= periods - 1
    lo = x[last][np.argmin(u[last])]
    hi = x[last][np.argmax(u[last])]
    return float((hi - lo) / (u_hi - u_lo))


def identify_compensator(model: Model, *, design=True, engine="auto", progress=None) -> tuple:
    """Identify the compensator's models from simulated noisy measurements of ``model``'s device.

    Returns ``(new_model, report)`` where ``report`` is a dict of the figures (residuals, fitted
    time constant, PID design margins). ``progress(fraction, message)`` is called at each stage (see
    :mod:`piezo_fmu.progress`).
    """
    from .control_design import design_pid

    n_steps = 2 + len(IDENT_FREQS) + (1 if design else 0)
    done = [0]

    def say(message):
        if progress is not None:
            progress(done[0] / n_steps, message)
        done[0] += 1
    new = model.copy()

    u_norm = 30.0
    say("measuring a 0.5 Hz, 0-30 V sine (3 periods, probe noise on)")
    static_rec = measure(model, Signal("sine", 15.0, 15.0, 0.5), 6.0, 1e-3, 0, engine)
    # sensor calibration: us = gain * x + offset on the same record
    a = np.vstack([static_rec.x, np.ones_like(static_rec.x)]).T
    (s_gain, s_off), *_ = np.linalg.lstsq(a, static_rec.us, rcond=None)
    report_lines = [f"sensor calibration: {s_gain:.5f} V/um, offset {s_off * 1e3:.2f} mV"]
    dyn_recs = []
    for i, f in enumerate(IDENT_FREQS):
        say(f"measuring a {f:g} Hz, 0-30 V sine (5 periods)")
        rec = measure(model, Signal("sine", 15.0, 15.0, f), 5.0 / f, 1.0 / (f * 400), 10 + i, engine)
        dyn_recs.append(rec)
    # Joint identification: the PI is the *quasi-static* part, so it is fitted to the input
    # filtered by G (otherwise its weights absorb the 0.5 Hz lag and the dynamic inverse would
    # compensate that lag twice); G is fitted with the PI held. Three rounds converge (tau
    # changes < 0.1 %).
    num, den = [1.0], [1e-9, 1.0]
    say("fitting the quasi-static PI jointly with the linear dynamics")
    for _ in range(3):
        u_f = apply_linear(num, den, static_rec.t, static_rec.u)
        pi, rms_pi = fit_pi(u_f, static_rec.x, IDENT_THRESHOLDS, u_norm)
        num, den, rms_dyn = fit_first_order(dyn_recs, pi, tau0=max(den[0], 1e-4))
    report_lines.append(f"quasi-static PI: rms residual {rms_pi * 1e3:.1f} nm; linear dynamics: tau = "
                        f"{den[0] * 1e3:.4f} ms (corner {1 / (2 * math.pi * den[0]):.1f} Hz), rms residual "
                        f"{rms_dyn * 1e3:.1f} nm")
    k_ideal = ideal_gain(pi)
    src = ("identified by piezo-fmu identify from noisy simulated measurements of the device "
           "(0.5 Hz 0-30 V sine, probe noise {:.3g} um)".format(model["measurement"]["x_noise_std"]))
    h = "compensator.hysteresis"
    new.set(h, "u_norm", u_norm, "paper Sec. 3.1: thresholds in units of the 30 V identification range")
    new.set(h, "scale", 1.0, "chosen: weights carry um")
    new.set(h, "thresholds", list(IDENT_THRESHOLDS), "paper Sec. 3.1: r = [0, 0.1, ..., 0.8]")
    new.set(h, "weights", [round(float(w), 8) for w in pi.weights], src)
    new.set("compensator.dynamics", "num", num, "first-order lag with unity DC gain (model structure)")
    new.set("compensator.dynamics", "den", [float(f"{den[0]:.8g}"), 1.0],
            "identified by piezo-fmu identify: output-error fit of PI[G u] to 10, 20, 50 Hz sines, "
            "jointly with the quasi-static PI")
    new.set("compensator", "k_ideal", round(k_ideal, 8),
            "derived: slope of the line through the ends of the identified model's 0-30 V loop")
    new.set("compensator", "sensor_gain", float(f"{s_gain:.8g}"),
            "identified: regression of sensor voltage on measured displacement (0.5 Hz record)")
    new.set("compensator", "sensor_offset", float(f"{s_off:.6g}"), "identified with sensor_gain")
    report = {"pi_rms_um": rms_pi, "dyn_rms_um": rms_dyn, "tau_s": den[0], "k_ideal": k_ideal,
              "sensor_gain": s_gain, "sensor_offset": s_off, "weights": list(pi.weights)}
    if design:
        say("designing the PID (python-control)")
        pid = design_pid(new)
        for key in ("Kp", "Ki", "Kd", "Tf"):
            new.set("compensator", key, float(f"{pid[key]:.6g}"), pid["source"])
        new.set("compensator", "filter_hz", pid["filter_hz"],
                "chosen: 20x the identified amplifier corner, so the dynamic inverse's own lag at "
                "50 Hz is 1.4 deg while its high-frequency gain stays 20")
        report["pid"] = pid
    report["summary"] = report_lines
    if progress is not None:
        progress(1.0)
    return new.check(), report
