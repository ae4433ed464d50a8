"""The monolithic (FMU-free) closed-loop model: actuator -> sensor -> compensator on a fixed step.

The loop is orchestrated exactly like the Gauss-Seidel co-simulation (actuator, then sensor,
then compensator, each step), so the two can be compared sample by sample::

    uc[0] = compensator(x_ref(t0), us(t0))
    for k:  actuator.step(uc[k], h) -> x, F    (t_k -> t_k+1)
            us[k+1] = sensor.step(F, h)
            uc[k+1] = compensator.step(t_k+1, x_ref(t_k+1), us[k+1], h)

With ``control_step`` (a multiple of the step) the sensor is sampled and the compensator acts only
every ``control_step``, the command held in between, while the actuator keeps the fine step: a
digital controller on a continuous plant, and exactly the loop a Gauss-Seidel co-simulation with
the communication step ``control_step`` computes when the actuator FMU sub-steps at the same
fine step (tested to round-off).

:func:`closed_loop` is the loop body. It calls the kernels of :mod:`piezo_fmu.core` and runs
either interpreted (the pure Python/NumPy engine) or compiled by numba (``engine="numba"``):
:func:`compiled_kernels` re-binds the same kernel functions to their compiled callees, so there is
one copy of the physics and of the orchestration.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from .core import compiled
from .core.control import compensator_step
from .core.plant import actuator_step, sensor_step
from .errors import UserError
from .model import Model
from .system import make_actuator, make_compensator, make_sensor

__all__ = ["Signal", "SimResult", "simulate", "closed_loop", "compiled_kernels", "numba_available",
           "COLUMNS"]

COLUMNS = ("time", "x_ref", "x", "us", "uc", "ua", "F")
UNITS = {"time": "s", "x_ref": "um", "x": "um", "us": "V", "uc": "V", "ua": "V", "F": "N"}


@dataclass
class Signal:
    """The reference of a run.

    ``kind`` = sine | step | triangle | constant | table. For the generators the reference
    voltage is ``offset + amplitude * shape(2 pi freq t + phase)`` [V] and the displacement
    reference is ``x_ref = k_ideal * u_ref``. A ``table`` gives samples ``(t, values)`` of one
    ``column``: ``x_ref`` [um], ``u_ref`` [V, nominal stack voltage] or ``u`` [V, amplifier
    command as in recordings]; it is interpolated linearly (held constant past its ends).
    """

    kind: str = "sine"
    amplitude: float = 0.0
    offset: float = 0.0
    freq: float = 1.0
    phase_deg: float = -90.0
    t: np.ndarray | None = None
    values: np.ndarray | None = None
    column: str = "u_ref"

    def __post_init__(self):
        if self.kind not in ("sine", "step", "triangle", "constant", "table"):
            raise UserError(f"unknown signal kind {self.kind!r} (sine, step, triangle, csv)")
        for name in ("amplitude", "offset", "freq", "phase_deg"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise UserError(f"--{name.replace('_deg', '')}: must be a finite number, got {v}")
        if self.kind in ("sine", "triangle") and not self.freq > 0:
            raise UserError(f"--freq: must be > 0 Hz for a {self.kind}, got {self.freq}")
        if self.kind == "table":
            if self.column not in ("x_ref", "u_ref", "u"):
                raise UserError(f"reference column {self.column!r}: expected x_ref, u_ref or u")
            self.t = np.asarray(self.t, dtype=float)
            self.values = np.asarray(self.values, dtype=float)

    def x_ref_at(self, t, k_ideal, k_amp):
        """Displacement reference [um] at times ``t`` (tables only)."""
        v = np.interp(t, self.t, self.values)
        if self.column == "x_ref":
            return v
        if self.column == "u_ref":
            return k_ideal * v
        return k_ideal * k_amp * v

    def describe(self):
        if self.kind == "table":
            return f"table of {self.column} ({self.t.size} samples, {self.t[0]:g}-{self.t[-1]:g} s)"
        if self.kind == "step":
            return f"step {self.offset:g} V -> {self.offset + self.amplitude:g} V"
        if self.kind == "constant":
            return f"constant {self.offset:g} V"
        return (f"{self.kind} {self.offset:g} +/- {self.amplitude:g} V at {self.freq:g} Hz, "
                f"phase {self.phase_deg:g} deg")


@dataclass
class SimResult:
    """Recorded signals (columns of :data:`COLUMNS`, units in :data:`UNITS`) and run facts."""

    data: dict
    engine: str
    step: float
    wall_s: float
    n_steps: int
    info: dict = field(default_factory=dict)

    def __getitem__(self, key):
        return self.data[key]

    @property
    def samples_per_s(self):
        return self.n_steps / self.wall_s if self.wall_s > 0 else math.inf


def closed_loop(n, h, t0, k0, rec_every, ctrl_every, xref, use_ext, noise,
                amp, amp_s, dly, dly_buf, pi_r, pi_w, pi_z, pi_k, kp_c, kp_s,
                cr_phi, cr_g, cr_cd, cr_xs, cr_tmp, frc,
                me_phi, me_g, me_cd, me_xs, me_tmp, drift, act_out, act_time,
                sen, sen_s, cfg, ref, gains, pid_s, inv_r, inv_w, inv_z, inv_k,
                gi_phi, gi_g, gi_cd, gi_xs, gi_tmp, comp_out, rec):
    """Run steps ``k0 + 1 .. k0 + n`` of ``h`` [s] after the start time ``t0``; record every
    ``rec_every``-th step into ``rec``. Times are ``t0 + k h`` (no accumulated round-off, so the
    result does not depend on how a run is split into chunks).

    The actuator advances every step; the sensor is sampled and the compensator computes a new
    command every ``ctrl_every``-th step (its step ``ctrl_every * h``; ``k0`` and, except for the
    last chunk, ``n`` are multiples of it), the command is held in between.
    ``xref[k]`` is the external reference at ``t0 + (k0 + k) h`` (used when ``use_ext``); ``noise[m]``
    the sensor noise of the chunk's ``m + 1``-th sample. Returns the number of rows written to ``rec``
    (columns: t, x_ref, x, us, uc, ua, F; us and uc as last sampled). All state arrays are updated
    in place.
    """
    uc = comp_out[0]
    us = sen_s[2]
    ta = act_time[0]
    hc = ctrl_every * h
    row = 0
    m = 0
    count = ctrl_every
    rcount = rec_every
    for k in range(n):
        ta += h
        actuator_step(uc, h, ta, amp, amp_s, dly, dly_buf, pi_r, pi_w, pi_z, pi_k, kp_c, kp_s,
                      cr_phi, cr_g, cr_cd, cr_xs, cr_tmp, frc,
                      me_phi, me_g, me_cd, me_xs, me_tmp, drift, act_out)
        count -= 1
        rcount -= 1
        if count == 0:
            count = ctrl_every
            t = t0 + (k0 + k + 1) * h
            us = sensor_step(act_out[1], hc, sen, sen_s, noise[m])
            m += 1
            xr = xref[k + 1] if use_ext else 0.0
            compensator_step(t, xr, us, hc, cfg, ref, gains, pid_s, inv_r, inv_w, inv_z, inv_k,
                             gi_phi, gi_g, gi_cd, gi_xs, gi_tmp, comp_out)
            uc = comp_out[0]
        if rcount == 0:
            rcount = rec_every
            rec[row, 0] = t0 + (k0 + k + 1) * h
            rec[row, 1] = comp_out[1]
            rec[row, 2] = act_out[0]
            rec[row, 3] = us
            rec[row, 4] = uc
            rec[row, 5] = act_out[2]
            rec[row, 6] = act_out[1]
            row += 1
    act_time[0] = ta
    return row


# -- the compiled engine ------------------------------------------------------------------------

def numba_available() -> bool:
    return compiled.available()


@lru_cache(maxsize=1)
def compiled_kernels():
    """The compiled kernels of :func:`piezo_fmu.core.compiled.kernels` plus :func:`closed_loop`,
    compiled the same way (its kernel calls re-bound to the compiled, inlined kernels)."""
    k = dict(compiled.kernels())
    k["closed_loop"] = compiled.compile_function(closed_loop, k)
    return k


# -- running ------------------------------------------------------------------------------------

_COMPILED_LOOP_RAN = []          # non-empty once the compiled loop has run in this process


def _unit_args(act, sen, comp, as_arrays):
    """Argument lists (state shared with the units, or NumPy copies for the compiled engine)."""
    cr, me, gi = act.creep, act.mech, comp.ginv

    def arr(x):
        return np.asarray(x, dtype=float) if as_arrays else x

    act_time = [act.time]
    a = [arr(act.amp), arr(act.amp_s), arr(act.dly), arr(act.dly_buf), arr(act.pi_r), arr(act.pi_w),
         arr(act.pi_z), arr(act.pi_k), arr(act.kp_c), arr(act.kp_s), arr(cr.phi), arr(cr.g),
         arr(cr.cd), arr(cr.xs), arr(cr.tmp), arr(act.frc),
         arr(me.phi), arr(me.g), arr(me.cd), arr(me.xs), arr(me.tmp),
         arr(act.drift), arr(act.out), arr(act_time)]
    s = [arr(sen.sen), arr(sen.sen_s)]
    c = [arr(comp.cfg), arr(comp.ref), arr(comp.gains), arr(comp.pid_s), arr(comp.inv_r),
         arr(comp.inv_w), arr(comp.inv_z), arr(comp.inv_k), arr(gi.phi),
         arr(gi.g), arr(gi.cd), arr(gi.xs), arr(gi.tmp), arr(comp.out)]
    return a, s, c


def _write_back(act, sen, comp, a, s, c):
    """Copy final states from NumPy arrays back into the units (compiled engine)."""
    cr, me, gi = act.creep, act.mech, comp.ginv
    act.amp_s[:] = a[1].tolist()
    act.dly[:] = a[2].tolist()
    act.dly_buf[:] = a[3].tolist()
    act.pi_z[:] = a[6].tolist()
    act.kp_s[:] = a[9].tolist()
    cr.xs[:] = a[13].tolist()
    me.xs[:] = a[19].tolist()
    act.out[:] = a[22].tolist()
    act.time = float(a[23][0])
    sen.sen_s[:] = s[1].tolist()
    comp.cfg[:] = c[0].tolist()
    comp.pid_s[:] = c[3].tolist()
    comp.inv_z[:] = c[6].tolist()
    gi.xs[:] = c[11].tolist()
    comp.out[:] = c[13].tolist()


def _multiple(option, value, h):
    """``value`` [s] as a whole number of steps ``h`` (None: 1)."""
    if value is None:
        return 1
    if not (value > 0 and math.isfinite(value)):
        raise UserError(f"{option}: must be a positive number of seconds, got {value}")
    k = max(1, int(round(value / h)))
    if abs(k * h - value) > 1e-9 * value:
        raise UserError(f"{option}: {value} s is not a whole number of steps of {h} s")
    return k


def _pick_engine(engine):
    if engine == "auto":
        return "numba" if numba_available() else "python"
    if engine not in ("numba", "python"):
        raise UserError(f"unknown engine {engine!r} (auto, numba, python)")
    if engine == "numba" and not numba_available():
        raise UserError("engine 'numba' requested but numba is not installed (pip install numba)")
    return engine


def simulate(model: Model, signal: Signal, stop_time: float, *, step=None, mode=None, inverse=None,
             record_step=None, control_step=None, engine="auto", noise=True, t0=0.0, progress=None,
             sink=None, chunk=50_000) -> SimResult:
    """Run the monolithic closed loop.

    Parameters
    ----------
    model : Model
        Device and compensator parameters.
    signal : Signal
        The reference.
    stop_time : float
        End time [s] (the run starts at ``t0``).
    step : float, optional
        Internal step [s] (default: the model's ``simulation.step``).
    mode, inverse : str, optional
        Compensator mode (open, ff, fb, ff+fb) and inverse (static, dynamic); default: the model's.
    record_step : float, optional
        Recording interval [s], a multiple of ``step`` (default: every step).
    control_step : float, optional
        Sample time [s] of the sensor and the compensator, a multiple of ``step`` (default:
        ``step``, i.e. the controller acts every internal step). A digital controller sampling
        at ``control_step`` while the actuator is integrated at ``step``: the closed loop the
        Gauss-Seidel co-simulation computes with the communication step ``control_step``.
    engine : {"auto", "numba", "python"}
        Compiled or interpreted loop; results agree to round-off.
    noise : bool
        Include the sensor noise of the model.
    progress : callable, optional
        Called as ``progress(fraction)`` after each chunk (and ``progress(0.0, message)`` before
        the compiled loop is compiled, the first time in a process; see :mod:`piezo_fmu.progress`).
    sink : callable, optional
        Called with each recorded chunk (an ``(n, 7)`` array); when given, nothing is kept in
        memory and the result holds only the last chunk, so long runs stream to disk.
    """
    h = float(step if step is not None else model["simulation"]["step"])
    if not (h > 0 and math.isfinite(h)):
        raise UserError(f"--step: must be a positive number of seconds, got {step}")
    if not (math.isfinite(stop_time) and stop_time > t0):
        raise UserError(f"--stop-time: must be after the start time {t0} s, got {stop_time}")
    n_total = int(round((stop_time - t0) / h))
    if n_total < 1:
        raise UserError(f"--stop-time: {stop_time} s is shorter than one step of {h} s")
    rec_every = 1 if record_step is None else max(1, int(round(record_step / h)))
    ctrl_every = _multiple("--control-step", control_step, h)
    engine = _pick_engine(engine)

    act = make_actuator(model)
    act.reset(t0)
    sen = make_sensor(model, noise=noise)
    sen.reset(act.F)
    cmode = mode or model["compensator"]["mode"]
    cinv = inverse or model["compensator"]["inverse"]
    if signal.kind == "table":
        comp = make_compensator(model, mode=cmode, inverse=cinv, signal="external")
    else:
        comp = make_compensator(model, mode=cmode, inverse=cinv, signal=signal.kind,
                                amplitude=signal.amplitude, offset=signal.offset, freq=signal.freq,
                                phase_deg=signal.phase_deg)
    k_ideal, k_amp = model["compensator"]["k_ideal"], model["compensator"]["k_amp"]
    use_ext = signal.kind == "table"
    x0 = float(signal.x_ref_at(t0, k_ideal, k_amp)) if use_ext else 0.0
    act.prepare(h)
    sen.prepare(h * ctrl_every)
    comp.prepare(h * ctrl_every)
    comp.initialize(t0, x0, sen.us)

    a, s, c = _unit_args(act, sen, comp, engine == "numba")
    runner = compiled_kernels()["closed_loop"] if engine == "numba" else closed_loop
    compile_s = 0.0
    if engine == "numba":      # compile (first call in the process) outside the timed loop
        announce = progress is not None and not _COMPILED_LOOP_RAN
        if announce:
            progress(0.0, "compiling the model with numba (the first time: a few seconds; then loaded from the cache)")
        w0 = time.perf_counter()
        runner(0, h, t0, 0, rec_every, ctrl_every, np.zeros(1), use_ext, np.zeros(1), *a, *s, *c,
               np.empty((1, 7)))
        compile_s = time.perf_counter() - w0
        _COMPILED_LOOP_RAN.append(True)
        if announce:
            progress(0.0, "simulating")

    first = np.array([[t0, comp.out[1], act.x, sen.us, comp.uc, act.ua, act.F]])
    period = rec_every * ctrl_every // math.gcd(rec_every, ctrl_every)
    chunk = max(period, (chunk // period) * period)
    # kept in memory: one table, each chunk recorded straight into its rows (no copies)
    table = np.empty((1 + n_total // rec_every + 1, 7)) if sink is None else None
    if table is not None:
        table[0] = first[0]
    else:
        sink(first)
    row = 1
    done = 0
    wall = 0.0
    last = first
    while done < n_total:
        n = min(chunk, n_total - done)
        xref = (signal.x_ref_at(t0 + h * np.arange(done, done + n + 1), k_ideal, k_amp) if use_ext
                else np.zeros(1))
        noise_arr = sen.noise.take(n // ctrl_every)
        rec = table[row:row + n // rec_every + 1] if table is not None else np.empty((n // rec_every + 1, 7))
        # the recording phase continues across chunks because chunks are multiples of rec_every
        w0 = time.perf_counter()
        rows = runner(n, h, t0, done, rec_every, ctrl_every, xref, use_ext, noise_arr, *a, *s, *c, rec)
        wall += time.perf_counter() - w0
        done += n
        last = rec[:rows]
        if table is not None:
            row += rows
        else:
            sink(last)
        if progress is not None:
            progress(done / n_total)
    if engine == "numba":
        _write_back(act, sen, comp, a, s, c)
    if table is not None:
        table = table[:row]
    else:
        table = last
    data = {name: table[:, i] for i, name in enumerate(COLUMNS)}
    info = {"mode": cmode, "inverse": cinv, "signal": signal.describe(), "units": dict(UNITS),
            "control_step": h * ctrl_every, "compile_s": compile_s}
    return SimResult(data, engine, h, wall, n_total, info)
