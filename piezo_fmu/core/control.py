"""The compensator: reference generator, inverse-model feedforward and discrete PID feedback.

Structure (paper Figure 8), with the PID acting on the linearised plant::

    x_ref [um] --+-------------------------------> (+) x_d --> inverse --> u_d [V] --> G_inv --> /k_amp --> uc [V]
                 |                                  ^            (PI^-1 or 1/k_ideal)  (dynamic only)   (limited)
                 +--> (+) e --> PID --> u_fb [um] --+
    us [V] --> (us - offset) / sensor_gain = x_meas [um] --(-)--^

Modes (integer codes used by the FMU):

* ``0`` open-loop: ``uc = x_ref / (k_ideal k_amp)`` (the uncompensated device; Figure 5, Table 2)
* ``1`` ff: inverse-model feedforward only (Table 3)
* ``2`` fb: PID feedback only, mapped through the linear gain ``1 / k_ideal``
* ``3`` ff+fb: the PID output is added to the reference before the inverse model (Table 4), so
  the loop sees the hysteresis-linearised plant and its gain does not swing with the local slope
  of the hysteresis loop.

``inverse`` = ``0`` static (``PI^-1``), ``1`` dynamic (``PI^-1`` followed by ``G_inv(s)``, the
inverse of the identified linear dynamics made proper by a fast filter).

The PID (``Kp`` [1], ``Ki`` [1/s], ``Kd`` [s] with derivative filter ``Tf`` [s]) is discretised at
the compensator's own step (backward Euler) and uses conditional integration as anti-windup:
the integrator holds while the command sits on a limit and the error pushes further into it.
"""
from __future__ import annotations

import math

from .buffers import pack
from .hysteresis import PrandtlIshlinskii, pi_load, pi_save, pi_state, pi_step, pi_table
from .linear import TINY, LinearSystem, as_floats, lti_advance, same_step

__all__ = ["MODES", "INVERSES", "SIGNALS", "reference_value", "pid_step", "compensator_step",
           "Compensator", "inverse_filter_tf"]

MODES = {"open": 0, "ff": 1, "fb": 2, "ff+fb": 3}
INVERSES = {"static": 0, "dynamic": 1}
SIGNALS = {"external": 0, "sine": 1, "step": 2, "triangle": 3, "constant": 4}

TWO_PI = 2.0 * math.pi


def reference_value(kind, t, amplitude, offset, freq, phase):
    """Reference voltage [V] at time ``t`` [s].

    ``kind``: 1 sine ``offset + A sin(2 pi f t + phase)``; 2 step ``offset + A`` for ``t >= 0``;
    3 triangle with the zero crossings and peaks of the sine; 4 constant ``offset``.
    ``phase`` in radians (the default -pi/2 starts a sine or triangle at its minimum).
    """
    if kind == 1:
        return offset + amplitude * math.sin(TWO_PI * freq * t + phase)
    if kind == 2:
        return offset + amplitude if t >= 0.0 else offset
    if kind == 3:
        p = (freq * t + phase / TWO_PI) % 1.0
        if p < 0.25:
            tri = 4.0 * p
        elif p < 0.75:
            tri = 2.0 - 4.0 * p
        else:
            tri = 4.0 * p - 4.0
        return offset + amplitude * tri
    return offset


def pid_step(e, h, gains, st, sat):
    """Discrete PID on error ``e`` over a step ``h`` [s]; returns the output.

    ``gains`` = [Kp, Ki, Kd, Tf]; ``st`` = [integral, derivative, e_prev, started];
    ``sat`` = +1/-1 when the last command sat on the upper/lower limit, else 0.
    """
    if st[3] == 0.0:
        st[2] = e
        st[3] = 1.0
    if not ((sat > 0 and e > 0) or (sat < 0 and e < 0)):
        st[0] += gains[1] * h * e
    if gains[2] != 0.0:
        d = (gains[3] * st[1] + gains[2] * (e - st[2])) / (gains[3] + h)
        st[1] = d if abs(d) >= TINY else 0.0      # no subnormal state (see linear.TINY)
    st[2] = e
    return gains[0] * e + st[0] + st[1]


def compensator_step(t, x_ref_in, us, h, cfg, ref, gains, pid_s, inv_r, inv_w, inv_z, inv_k,
                     gi_phi, gi_g, gi_cd, gi_xs, gi_tmp, out):
    """Compute the command for the next interval from the inputs sampled at time ``t`` [s].

    ``cfg`` = [mode, inverse, k_ideal [um/V], k_amp [V/V], sensor_gain [V/um],
    sensor_offset [V], uc_min [V], uc_max [V], sat];
    ``ref`` = [kind, amplitude [V], offset [V], freq [Hz], phase [rad]] (kind 0: use ``x_ref_in``);
    ``inv_k`` = [1 / out_scale, in_scale] of the inverse PI (x [um] -> u [V]).
    ``h`` = 0 evaluates the initial command (no integration, the inverse filter not advanced).
    Writes ``out`` = [uc [V], x_ref [um], x_meas [um], u_fb [um]].
    """
    mode = int(cfg[0])
    kind = int(ref[0])
    if kind == 0:
        x_ref = x_ref_in
    else:
        x_ref = cfg[2] * reference_value(kind, t, ref[1], ref[2], ref[3], ref[4])
    x_meas = (us - cfg[5]) / cfg[4]
    u_fb = 0.0
    if mode >= 2:
        e = x_ref - x_meas
        if h > 0.0:
            u_fb = pid_step(e, h, gains, pid_s, cfg[8])
        else:
            u_fb = gains[0] * e + pid_s[0] + pid_s[1]
    if mode == 0:
        u_d = x_ref / cfg[2]
    elif mode == 2:
        u_d = u_fb / cfg[2]
    else:
        x_d = x_ref + u_fb if mode == 3 else x_ref
        u_d = inv_k[1] * pi_step(x_d * inv_k[0], inv_r, inv_w, inv_z)
    if mode != 0 and cfg[1] == 1.0:
        if h > 0.0:
            u_d = lti_advance(gi_phi, gi_g, gi_cd, gi_xs, u_d, gi_tmp)
        else:
            n = len(gi_tmp)
            y = gi_cd[n] * u_d
            for i in range(n):
                y += gi_cd[i] * gi_xs[i]
            gi_xs[n] = u_d
            u_d = y
    uc = u_d / cfg[3]
    sat = 0.0
    if uc > cfg[7]:
        uc = cfg[7]
        sat = 1.0
    elif uc < cfg[6]:
        uc = cfg[6]
        sat = -1.0
    cfg[8] = sat
    out[0] = uc
    out[1] = x_ref
    out[2] = x_meas
    out[3] = u_fb


def inverse_filter_tf(num, den, filter_hz):
    """``G_inv = den / (num (tau_f s + 1)^r)``: the inverse of ``G = num/den`` made proper.

    ``r`` is the relative degree of ``G``; ``tau_f = 1 / (2 pi filter_hz)``.
    """
    import numpy as np

    num = np.trim_zeros(np.asarray(num, dtype=float), "f")
    den = np.trim_zeros(np.asarray(den, dtype=float), "f")
    rel = den.size - num.size
    tau_f = 1.0 / (TWO_PI * filter_hz)
    filt = np.array([1.0])
    for _ in range(rel):
        filt = np.polymul(filt, [tau_f, 1.0])
    return den.tolist(), np.polymul(num, filt).tolist()


class Compensator:
    """Inverse-model feedforward + PID feedback (see module docstring).

    Parameters
    ----------
    model : :class:`PrandtlIshlinskii`
        The identified forward hysteresis model, u [V] -> x [um]; its exact inverse is used.
    g_num, g_den : sequence of float
        Identified linear dynamics ``G(s)`` (unity DC gain) of the dynamic model.
    filter_hz : float
        Corner [Hz] of the filter that makes ``G_inv`` proper.
    k_ideal : float
        Ideal linear gain [um/V] that defines the reference ``x_ref = k_ideal u_ref``.
    k_amp : float
        The amplifier gain the compensator assumes [V/V].
    sensor_gain, sensor_offset : float
        Calibration of the sensor signal, ``x_meas = (us - offset) / gain`` [V/um], [V].
    Kp, Ki, Kd, Tf : float
        PID gains [1], [1/s], [s] and derivative filter time constant [s].
    uc_min, uc_max : float
        Command limits [V].
    mode, inverse : str
        See :data:`MODES` and :data:`INVERSES`.
    signal, amplitude, offset, freq, phase_deg : reference generator ("external" = input x_ref).
    """

    def __init__(self, *, model: PrandtlIshlinskii, g_num, g_den, filter_hz, k_ideal, k_amp,
                 sensor_gain, sensor_offset=0.0, Kp=0.0, Ki=0.0, Kd=0.0, Tf=1e-4,
                 uc_min=-math.inf, uc_max=math.inf, mode="ff+fb", inverse="dynamic",
                 signal="external", amplitude=0.0, offset=0.0, freq=1.0, phase_deg=-90.0):
        self.model = model
        inv = model.inverse()
        self.inv_r = list(inv.thresholds)
        self.inv_w = pi_table(inv.thresholds, inv.weights)
        self.inv_z = pi_state(inv.n)
        self.inv_k = [1.0 / inv.in_scale, inv.out_scale]
        self.g_num, self.g_den = list(g_num), list(g_den)
        self.filter_hz = float(filter_hz)
        self.ginv = LinearSystem(*inverse_filter_tf(self.g_num, self.g_den, self.filter_hz))
        self.cfg = [float(MODES[mode]), float(INVERSES[inverse]), float(k_ideal), float(k_amp),
                    float(sensor_gain), float(sensor_offset), float(uc_min), float(uc_max), 0.0]
        self.ref = [float(SIGNALS[signal]), float(amplitude), float(offset), float(freq),
                    math.radians(phase_deg)]
        self.gains = [float(Kp), float(Ki), float(Kd), float(Tf)]
        self.pid_s = [0.0, 0.0, 0.0, 0.0]
        self.out = [0.0, 0.0, 0.0, 0.0]
        self._h = None
        self._run = None            # a runner handed over by use_runner(), else None
        self._bind()

    def _bind(self):
        """The kernel's arguments after ``(t, x_ref, us, h)``, bound once (every list is updated
        in place); under the compiled engine the data are first packed into one buffer (views)."""
        g = self.ginv
        if self._run is not None:
            buf, o, v = pack([self.cfg, self.ref, self.gains, self.pid_s, self.inv_r, self.inv_w,
                              self.inv_z, self.inv_k, g.phi, g.g, g.cd, g.xs, g.tmp, self.out])
            (self.cfg, self.ref, self.gains, self.pid_s, self.inv_r, self.inv_w, self.inv_z,
             self.inv_k, g.phi, g.g, g.cd, g.xs, g.tmp, self.out) = v
            self._packed = (buf, o)
        self._args = (self.cfg, self.ref, self.gains, self.pid_s, self.inv_r, self.inv_w, self.inv_z,
                      self.inv_k, g.phi, g.g, g.cd, g.xs, g.tmp, self.out)

    def use_runner(self, run):
        """Step through ``run`` (a runner of :mod:`.compiled` taking the unit's data packed in one
        buffer, :attr:`packed`) instead of the interpreted kernel; the data become views of that
        buffer. :func:`.compiled.compile_unit` is the way to call this. Returns ``self``."""
        self._run = run
        self._bind()
        return self

    @property
    def packed(self):
        """``(buffer, offsets)`` of the unit's data under a runner (see :func:`.buffers.pack`)."""
        return self._packed

    @property
    def uc(self):
        return self.out[0]

    def set_mode(self, mode=None, inverse=None):
        if mode is not None:
            self.cfg[0] = float(MODES[mode])
        if inverse is not None:
            self.cfg[1] = float(INVERSES[inverse])

    def prepare(self, h):
        if not same_step(h, self._h):
            self.ginv.prepare(h)
            self._h = h

    def initialize(self, t, x_ref_in, us):
        """Initial command from the inputs at the start time ``t`` (no integration)."""
        if self._run is not None:
            return self._run(t, x_ref_in, us, 0.0, *self._packed)
        compensator_step(t, x_ref_in, us, 0.0, *self._args)
        return self.out[0]

    def step(self, t, x_ref_in, us, h):
        """Command for the next interval from inputs sampled at ``t`` [s], after a step ``h`` [s]."""
        if h != self._h:
            self.prepare(h)
        if self._run is not None:
            return self._run(t, x_ref_in, us, h, *self._packed)
        compensator_step(t, x_ref_in, us, h, *self._args)
        return self.out[0]

    def reset(self):
        for i in range(len(self.inv_z)):
            self.inv_z[i] = 0.0
        self.ginv.xs[:] = [0.0] * len(self.ginv.xs)
        self.pid_s[:] = [0.0, 0.0, 0.0, 0.0]
        self.cfg[8] = 0.0
        self.out[:] = [0.0, 0.0, 0.0, 0.0]

    def get_state(self):
        return {"inv_z": as_floats(pi_save(self.inv_r, self.inv_z)), "ginv": as_floats(self.ginv.xs),
                "pid": as_floats(self.pid_s), "sat": float(self.cfg[8]), "out": as_floats(self.out),
                "h": self._h}

    def set_state(self, s):
        pi_load(self.inv_r, self.inv_w, self.inv_z, s["inv_z"])
        self.ginv.xs[:] = [float(v) for v in s["ginv"]]
        self.pid_s[:] = [float(v) for v in s["pid"]]
        self.cfg[8] = float(s["sat"])
        self.out[:] = [float(v) for v in s["out"]]
        if s["h"] is not None:
            self.prepare(float(s["h"]))
