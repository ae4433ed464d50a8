"""The device: drive amplifier, hysteretic stack, mechanics, and the quartz force sensor.

Signal chain of the actuator (paper eqs. 1-5, with the stack's free stroke made hysteretic)::

    uc [V] -> delay -> (input stage) -> amplifier -> ua [V] -> PI -> x_h [um] -> creep -> x_free [um]
           F_out = k_a x_free [N] -> mechanics -> x [um] (+ drift)
           sensed force F = F_out (pick-off "stack"), k_a (x_free - x) ("contact") or k_f x ("load")

* Amplifier (eq. 2): ``R C_a dua/dt + ua = k_amp uc``, output held between the rails
  ``[u_min, u_max]``, and (beyond the paper) an optional current limit ``|C_a dua/dt| <= I_max``,
  i.e. a slew-rate limit. With the command held over a step the response is monotone, so the
  rate-independent PI evaluated at the step's end point is exact. Optionally (beyond the paper) a
  second lag stage ``tau_2 dy/dt + y = uc`` before it makes the amplifier second order; the output
  stage sees ``y``'s mean over the step held (exact for ``y``, second order in ``h`` for ``ua``).
* Stack (eq. 1 with hysteresis): the free stroke ``x_h = scale * Pi[ua / u_norm]`` (beyond the
  paper, optionally plus a Preisach term of KP cells, ``scale * K[ua / u_norm]``
  (:mod:`.preisach`: loop features tied to absolute voltages), and saturating at high field:
  ``x_h / (1 + |x_h| / y_sat)``); the force on the push rod is ``F_out = k_a x_h`` (eq. 5).
* Mechanics (eq. 4): ``m x'' + c x' + (k_a + k_f) x = F_out``, optionally followed by a further
  mechanical mode (``extra_resonance``; or that mode on the drive, before the mechanics, where
  every pick-off of the sensor sees it: ``resonance_at = "drive"``); solved exactly for a stroke
  moving over the step linearly or along the amplifier's lag (``stroke_path``).
* Creep (beyond the paper): ``x_free = (1 + sum_j g_j / (tau_j s + 1)) x_h``.
* Sensor (eq. 3): the quartz charge ``q = d11 F`` on ``C_s + C_load`` gives
  ``us = q / (C_s + C_load)``; with a finite leakage time constant the charge decays
  (a first-order high-pass); plus offset and white measurement noise. ``F`` is the force the
  wafer carries: the stack's blocked force ``F_out`` (the paper's eq. 5, pick-off ``"stack"``), the
  contact force between stack and push rod ``k_a (x_free - x) = m x'' + c x' + k_f x`` (``"contact"``:
  the mechanics' modes show in it), or the preload spring's ``k_f x`` (``"load"``: it follows the
  push-rod displacement). Optionally sampled late by whole steps (``lag``: a sampling lag).

All units keep explicit state with ``get_state``/``set_state``. Everything needs only NumPy; the
optional compiled engine (:func:`.compiled.compile_unit`) needs numba.
"""
from __future__ import annotations

import math

import numpy as np

from .buffers import pack
from .hysteresis import PrandtlIshlinskii, pi_load, pi_save, pi_state, pi_step, pi_table
from .preisach import KPCells, kp_relax, kp_step
from .linear import TINY, LinearSystem, as_floats, lti_advance, same_step

EPS0 = 8.8541878128e-12  # vacuum permittivity [F/m]

__all__ = ["amp_step", "actuator_step", "drift_at", "drift_curvature", "Actuator", "Sensor",
           "sensor_step", "EPS0", "PICKOFFS", "RESONANCE_AT", "STROKE_PATHS"]

# what the quartz wafer's force is (mechanics.pickoff), as the FMUs' Integer codes
PICKOFFS = {"stack": 0, "load": 1, "contact": 2}
# where the further mode acts (resonance.position), as the FMUs' Integer codes
RESONANCE_AT = {"output": 0, "drive": 1}
STROKE_PATHS = {"linear": 0, "amplifier_lag": 1}    # simulation.stroke_path (Actuator), as Integer codes


def amp_step(ua, target, tau, slew, h, decay):
    """Exact amplifier response over ``h`` [s] to a constant ``target`` = k_amp*uc [V].

    ``tau`` = R C_a [s], ``slew`` = I_max / C_a [V/s] (``inf`` = no current limit),
    ``decay`` = exp(-h/tau) (precomputed). Returns the amplifier voltage at the end of the step.
    """
    e = target - ua
    if abs(e) > slew * tau:
        sgn = 1.0 if e > 0 else -1.0
        t_ramp = (abs(e) - slew * tau) / slew
        if t_ramp >= h:
            return ua + sgn * slew * h
        return target - sgn * slew * tau * math.exp(-(h - t_ramp) / tau)
    return target if abs(e * decay) < TINY else target - e * decay     # no subnormal remainder (TINY)


def drift_curvature(t, tau):
    """The drift's curvature term [s^2] at ``t`` [s] (float or array): ``t^2`` for ``tau`` = inf, else
    a warm-up ``2 tau^2 (exp(-t/tau) - 1 + t/tau)`` [tau in s]: the same start (``t^2 - t^3/(3 tau)``),
    then a line of slope ``2 tau``; with the rate's ``t``, a ramp and a settling ``1 - exp(-t/tau)``."""
    if tau == math.inf:
        return t * t
    return 2.0 * tau * tau * (np.expm1(-t / tau) + t / tau)


def drift_at(t, drift):
    """The additive displacement drift [um] at time ``t`` [s]: ``drift`` = [offset [um], rate
    [um/s], curvature [um/s^2], warm-up time constant [s] (inf: quadratic)] or empty (none)."""
    if len(drift) == 0:
        return 0.0
    return drift[0] + drift[1] * t + drift[2] * drift_curvature(t, drift[3])


def actuator_step(uc, h, t_end, amp, amp_s, dly, dly_buf, pi_r, pi_w, pi_z, pi_k, kp_c, kp_s,
                  cr_phi, cr_g, cr_cd, cr_xs, cr_tmp, frc,
                  me_phi, me_g, me_cd, me_xs, me_tmp, drift, out):
    """One internal step of the actuator with the command ``uc`` [V] held over ``h`` [s].

    ``amp`` = [k_amp, tau, slew, u_min, u_max, decay, tau_2, decay_2, mean_2] (``tau_2`` > 0: a
    first-order input stage before the output stage, ``decay_2`` = exp(-h/tau_2), ``mean_2`` =
    (tau_2/h)(1 - decay_2)); ``amp_s`` = [ua, y] (``y`` the input stage's output);
    ``dly`` = [n_delay_steps, head] (delay line of the command, ``dly_buf`` its ring buffer);
    ``pi_k`` = [1/u_norm, scale, 1/saturation] (strain saturation ``x_h / (1 + |x_h| / y_sat)``,
    0 = none); ``kp_c``, ``kp_s`` = the KP cells' table and states (:mod:`.preisach`; empty: none),
    added to the PI's output before the scale; ``frc`` = [k_a * 1e-6 [N/um], pick-off code (0 stack, 1 load, 2 contact), k_f * 1e-6 [N/um]];
    ``drift`` = an additive displacement drift, [offset, rate, curvature, warm-up time constant]
    (:func:`drift_at`; empty: none; with the load pick-off the force follows the drift's change
    too: it moves the push rod).
    Writes ``out`` = [x [um], F [N] (the sensed force), ua [V], x_h [um]].
    """
    nd = int(dly[0])
    if nd > 0:
        head = int(dly[1])
        size = len(dly_buf)
        dly_buf[head] = uc
        uc = dly_buf[(head - nd) % size]
        dly[1] = (head + 1) % size
    if amp[6] > 0.0:
        # input stage, exact for the held command; the output stage sees its mean over the step
        e2 = amp_s[1] - uc
        e2 = e2 if abs(e2) >= TINY else 0.0
        amp_s[1] = uc + e2 * amp[7]
        uc = uc + e2 * amp[8]
    target = amp[0] * uc
    if target < amp[3]:
        target = amp[3]
    elif target > amp[4]:
        target = amp[4]
    ua = amp_step(amp_s[0], target, amp[1], amp[2], h, amp[5])
    amp_s[0] = ua
    v = ua * pi_k[0]
    x_h = pi_k[1] * (pi_step(v, pi_r, pi_w, pi_z) + kp_step(v, kp_c, kp_s))
    if pi_k[2] != 0.0:
        x_h = x_h / (1.0 + abs(x_h) * pi_k[2])
    x_free = lti_advance(cr_phi, cr_g, cr_cd, cr_xs, x_h, cr_tmp)
    force = frc[0] * x_free
    x = lti_advance(me_phi, me_g, me_cd, me_xs, force, me_tmp)
    nd2 = len(drift)
    acc = drift_at(t_end, drift)
    if frc[1] == 1.0:
        # the load spring follows the push rod, and a thermal drift moves the push rod: the force
        # sees the drift's change (not the constant offset of the displacement reading)
        force = frc[2] * (x + (acc - drift[0] if nd2 else 0.0))
    elif frc[1] == 2.0:
        force = force - frc[0] * x
    x += acc
    out[0] = x
    out[1] = force
    out[2] = ua
    out[3] = x_h


class Actuator:
    """Drive amplifier + hysteretic stack + mechanics, stepped with a held command.

    Parameters (SI unless stated)
    ----------
    k_amp : amplifier gain [V/V]; R : series resistance [ohm]; C_a : stack capacitance [F];
    u_min, u_max : amplifier rails [V]; I_max : current limit [A] (``inf``: none);
    tau_2 : time constant of a first-order input stage before the output stage [s] (0: none);
    delay : command latency [s] (resolved to the internal step);
    hysteresis : :class:`PrandtlIshlinskii` from ua [V] to free stroke [um];
    cells : :class:`~.preisach.KPCells` added to the PI (same normalised input, same scale), or None;
    saturation : strain saturation ``y_sat`` [um]: ``x_h -> x_h / (1 + |x_h| / y_sat)`` (``inf``: none);
    prepared : stack voltage [V] of a sweep before ``t0`` whose memory the device starts with (0: relaxed);
    creep_gains, creep_taus : creep elements (dimensionless gains, time constants [s]);
    m [kg], c [N s/m], k_a [N/m] (stack), k_f [N/m] (preload spring);
    pickoff : the force output ``F``: ``"stack"`` (F_out = k_a x_free), ``"contact"`` (k_a (x_free - x))
    or ``"load"`` (k_f x);
    resonance : optional ``(f_n [Hz], zeta [1])`` of a further mode in series (unity DC gain);
    resonance_at : where that mode acts: ``"output"`` (after the mechanics, on x) or ``"drive"``
    (on the free stroke, before the mechanics: in x and in every sensed force);
    drift : an additive displacement drift's offset [um], rate [um/s] and curvature [um/s^2]
    (up to three; :func:`drift_at`);
    drift_tau : the curvature term's warm-up time constant [s] (inf: a quadratic drift).
    max_step : largest internal step [s]; a communication step is split into equal sub-steps.
    stroke_path : the free stroke's path between steps: ``"linear"`` or ``"amplifier_lag"`` (along the
    lag ``R C_a + tau_2`` towards the new value: exact for a stroke proportional to ``ua``).

    Outputs after :meth:`advance`: ``x`` [um], ``F`` [N], ``ua`` [V], ``x_h`` [um].
    """

    def __init__(self, *, k_amp, R, C_a, u_min, u_max, hysteresis: PrandtlIshlinskii,
                 m, c, k_a, k_f, saturation=math.inf, I_max=math.inf, delay=0.0, creep_gains=(), creep_taus=(),
                 resonance=None, drift=(), drift_tau=math.inf, max_step=1e-4, tau_2=0.0, pickoff="stack", resonance_at="output",
                 prepared=0.0, cells: KPCells | None = None, stroke_path="linear"):
        self.k_amp, self.R, self.C_a = float(k_amp), float(R), float(C_a)
        self.u_min, self.u_max, self.I_max = float(u_min), float(u_max), float(I_max)
        self.delay = float(delay)
        self.tau_2 = float(tau_2)
        if pickoff not in PICKOFFS:
            raise ValueError(f"pickoff {pickoff!r}: expected one of {', '.join(PICKOFFS)}")
        self.pickoff = pickoff
        self.hysteresis = hysteresis
        self.saturation = float(saturation)
        self.prepared = float(prepared)
        self.m, self.c, self.k_a, self.k_f = float(m), float(c), float(k_a), float(k_f)
        self.creep_gains = [float(v) for v in creep_gains]
        self.creep_taus = [float(v) for v in creep_taus]
        self.resonance = None if resonance is None else (float(resonance[0]), float(resonance[1]))
        if len(drift) > 3:
            raise ValueError(f"drift: offset, rate and curvature at most, got {len(drift)} coefficients")
        coef = [float(v) for v in drift] + [0.0] * (3 - len(drift))
        if not float(drift_tau) > 0.0:
            raise ValueError(f"drift_tau = {drift_tau!r}: a warm-up time constant is positive [s] (inf: none)")
        self.drift = coef + [float(drift_tau)] if any(coef) else []
        self.max_step = float(max_step)
        tau = self.R * self.C_a
        self.amp = [self.k_amp, tau, self.I_max / self.C_a, self.u_min, self.u_max, 0.0, self.tau_2, 0.0, 0.0]
        self.amp_s = [0.0, 0.0]
        self.dly = [0.0, 0.0]
        self.dly_buf = [0.0]
        self.pi_r = list(hysteresis.thresholds)
        self.pi_w = pi_table(hysteresis.thresholds, hysteresis.weights)
        self.pi_z = pi_state(hysteresis.n)
        self.pi_k = [1.0 / hysteresis.in_scale, hysteresis.out_scale, 1.0 / self.saturation]
        self.cells = cells if cells is not None else KPCells()
        self.kp_c = self.cells.table()
        self.kp_s = [0.0] * self.cells.m
        path = ("lag", self.R * self.C_a + self.tau_2) if STROKE_PATHS[stroke_path] else ("foh",)
        self.creep = LinearSystem(*creep_tf(self.creep_gains, self.creep_taus), *path)
        self.k_force = self.k_a * 1e-6
        self.frc = [self.k_force, float(PICKOFFS[pickoff]), self.k_f * 1e-6]
        if resonance_at not in RESONANCE_AT:
            raise ValueError(f"resonance_at {resonance_at!r}: expected one of {', '.join(RESONANCE_AT)}")
        self.resonance_at = resonance_at
        drive = self.resonance is not None and resonance_at == "drive"
        if drive:          # the mode shapes the free stroke: it joins the creep block
            self.creep = LinearSystem(*series_tf(creep_tf(self.creep_gains, self.creep_taus), mode_tf(*self.resonance)), *path)
        self.mech = LinearSystem(*mechanics_tf(self.m, self.c, self.k_a, self.k_f, None if drive else self.resonance), *path)
        self.out = [0.0, 0.0, 0.0, 0.0]
        self._h = None
        self._adv_step = None
        self._adv_n = 1
        self.time = 0.0
        self._run = None            # a runner handed over by use_runner(), else None
        self._bind()

    def _bind(self):
        """The kernel's arguments after ``(uc, h, t_end)``, bound once (one attribute lookup per
        step instead of twenty); rebuilt whenever a list is replaced rather than updated in place.
        Under the compiled engine the data are first re-packed into one buffer (views)."""
        cr, me = self.creep, self.mech
        if self._run is not None:
            buf, o, v = pack([self.amp, self.amp_s, self.dly, self.dly_buf, self.pi_r, self.pi_w,
                              self.pi_z, self.pi_k, self.kp_c, self.kp_s, cr.phi, cr.g, cr.cd, cr.xs,
                              cr.tmp, self.frc, me.phi, me.g, me.cd, me.xs, me.tmp, self.drift, self.out])
            (self.amp, self.amp_s, self.dly, self.dly_buf, self.pi_r, self.pi_w, self.pi_z,
             self.pi_k, self.kp_c, self.kp_s, cr.phi, cr.g, cr.cd, cr.xs, cr.tmp, self.frc, me.phi, me.g,
             me.cd, me.xs, me.tmp, self.drift, self.out) = v
            self._packed = (buf, o)
        self._args = (self.amp, self.amp_s, self.dly, self.dly_buf, self.pi_r, self.pi_w, self.pi_z,
                      self.pi_k, self.kp_c, self.kp_s, cr.phi, cr.g, cr.cd, cr.xs, cr.tmp, self.frc,
                      me.phi, me.g, me.cd, me.xs, me.tmp, self.drift, self.out)

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

    # -- configuration ---------------------------------------------------------------------
    def prepare(self, h):
        """Discretise for internal step ``h`` [s] (cached; see :func:`~.linear.same_step`)."""
        if same_step(h, self._h):
            return
        self.amp[5] = math.exp(-h / self.amp[1])
        if self.tau_2 > 0.0:
            d2 = math.exp(-h / self.tau_2)
            self.amp[7] = d2
            self.amp[8] = (self.tau_2 / h) * (1.0 - d2)
        self.creep.prepare(h)
        self.mech.prepare(h)
        nd = int(round(self.delay / h)) if self.delay > 0 else 0
        if nd != int(self.dly[0]):
            fill = self.dly_buf[int(self.dly[1]) - 1] if len(self.dly_buf) > 1 else 0.0
            self.dly_buf = [fill] * (nd + 1)
            self.dly[0], self.dly[1] = float(nd), 0.0
            self._bind()
        self._h = h

    def substeps(self, step):
        """Number of equal internal steps used for a communication step ``step`` [s]."""
        return max(1, int(math.ceil(step / self.max_step - 1e-9)))

    # -- stepping --------------------------------------------------------------------------
    def step(self, uc, h):
        """One internal step of ``h`` [s] with the command ``uc`` [V] held; returns ``x`` [um]."""
        if h != self._h:
            self.prepare(h)
        if self._run is not None:
            self.time = self._run(uc, h, 1, self.time, *self._packed)
        else:
            self.time += h
            actuator_step(uc, h, self.time, *self._args)
        return self.out[0]

    def advance(self, uc, step):
        """Advance a communication step ``step`` [s] (split by ``max_step``); returns ``x`` [um]."""
        if step != self._adv_step:
            self._adv_step = step
            self._adv_n = self.substeps(step)
        n = self._adv_n
        if n == 1:
            self.step(uc, step)
        elif self._run is not None:          # all sub-steps in one compiled call
            h = step / n
            if h != self._h:
                self.prepare(h)
            self.time = self._run(uc, h, n, self.time, *self._packed)
        else:
            h = step / n
            for _ in range(n):
                self.step(uc, h)
        return self.out[0]

    @property
    def x(self):
        return self.out[0]

    @property
    def F(self):
        return self.out[1]

    @property
    def ua(self):
        return self.out[2]

    # -- state -----------------------------------------------------------------------------
    def reset(self, t0=0.0):
        """Device at rest at time ``t0`` (zero command): relaxed memory, or with ``prepared`` > 0
        the memory of a sweep up to ``prepared`` volts and back to 0 V, everything after the
        hysteresis settled at the stroke that leaves."""
        self.time = float(t0)
        self.amp_s[0] = 0.0
        self.amp_s[1] = 0.0
        for i in range(len(self.pi_z)):
            self.pi_z[i] = 0.0
        x_h = self.pi_k[1] * kp_relax(self.kp_c, self.kp_s)
        if self.prepared > 0.0:
            top = self.prepared * self.pi_k[0]
            pi_step(top, self.pi_r, self.pi_w, self.pi_z)
            kp_step(top, self.kp_c, self.kp_s)
            x_h = self.pi_k[1] * (pi_step(0.0, self.pi_r, self.pi_w, self.pi_z)
                                  + kp_step(0.0, self.kp_c, self.kp_s))
        if self.pi_k[2] != 0.0:
            x_h = x_h / (1.0 + abs(x_h) * self.pi_k[2])
        self.creep.settle(x_h)
        f_out = self.frc[0] * self.creep.dc_gain() * x_h
        self.mech.settle(f_out)
        x = self.mech.dc_gain() * f_out
        trend = self._drift_at(self.time) - (self.drift[0] if len(self.drift) else 0.0)
        force = {0.0: f_out, 1.0: self.frc[2] * (x + trend), 2.0: f_out - self.frc[0] * x}[self.frc[1]]
        self.dly_buf[:] = [0.0] * len(self.dly_buf)
        self.dly[1] = 0.0
        self.out[:] = [x + self._drift_at(self.time), force, 0.0, x_h]

    def _drift_at(self, t):
        return drift_at(t, self.drift)

    def get_state(self):
        """Complete state as plain Python data (JSON-serialisable)."""
        return {"time": self.time, "ua": float(self.amp_s[0]), "y2": float(self.amp_s[1]), "z": as_floats(pi_save(self.pi_r, self.pi_z)),
                "kp": as_floats(self.kp_s),
                "creep": as_floats(self.creep.xs), "mech": as_floats(self.mech.xs),
                "dly": as_floats(self.dly), "dly_buf": as_floats(self.dly_buf), "out": as_floats(self.out),
                "h": self._h}

    def set_state(self, s):
        self.time = float(s["time"])
        self.amp_s[0] = float(s["ua"])
        self.amp_s[1] = float(s.get("y2", 0.0))
        pi_load(self.pi_r, self.pi_w, self.pi_z, s["z"])
        kp = [float(v) for v in s.get("kp", [])]
        if len(kp) != len(self.kp_s):
            raise ValueError(f"actuator state has {len(kp)} KP cell states, the unit has {len(self.kp_s)} cells")
        self.kp_s[:] = kp
        self.creep.xs[:] = [float(v) for v in s["creep"]]
        self.mech.xs[:] = [float(v) for v in s["mech"]]
        if s["h"] is not None:
            self.prepare(float(s["h"]))
        self.dly[:] = [float(v) for v in s["dly"]]
        self.dly_buf = [float(v) for v in s["dly_buf"]]
        self._bind()
        self.out[:] = [float(v) for v in s["out"]]

    # -- analysis helpers --------------------------------------------------------------------
    def static_gain(self):
        """Displacement per free stroke at DC: k_a / (k_a + k_f) times the creep DC gain."""
        return self.mech.dc_gain() * self.k_force * self.creep.dc_gain()


def creep_tf(gains, taus):
    """Transfer function ``1 + sum_j g_j / (tau_j s + 1)`` as ``(num, den)``."""
    num, den = np.array([1.0]), np.array([1.0])
    for g, tau in zip(gains, taus):
        # (num/den) + g/(tau s + 1) = (num (tau s + 1) + g den) / (den (tau s + 1))
        num = np.polyadd(np.polymul(num, [tau, 1.0]), g * den)
        den = np.polymul(den, [tau, 1.0])
    return num, den


def mode_tf(f_n, zeta):
    """A mode of unity DC gain: ``wn^2 / (s^2 + 2 zeta wn s + wn^2)``."""
    wn = 2.0 * math.pi * f_n
    return np.array([wn * wn]), np.array([1.0, 2.0 * zeta * wn, wn * wn])


def series_tf(a, b):
    """Two transfer functions ``(num, den)`` in series."""
    return np.polymul(a[0], b[0]), np.polymul(a[1], b[1])


def mechanics_tf(m, c, k_a, k_f, resonance=None):
    """Force [N] to displacement [um]: ``1e6 / (m s^2 + c s + k_a + k_f)``, times an optional mode."""
    num, den = np.array([1e6]), np.array([m, c, k_a + k_f])
    if resonance is not None:
        wn = 2.0 * math.pi * resonance[0]
        num = np.polymul(num, [wn * wn])
        den = np.polymul(den, [1.0, 2.0 * resonance[1] * wn, wn * wn])
    return num, den


def sensor_step(force, h, sen, sen_s, noise):
    """Quartz sensor output [V] at the end of a step whose force moved linearly to ``force`` [N].

    ``sen`` = [S_q [V/N], leak_decay = exp(-h/tau_leak) (0 < .. <= 1), tau_leak/h, offset [V],
    n_lag]; ``sen_s`` = [w, F_prev, us, head, v_0 .. v_n_lag] where ``us = S_q F + w`` (+ offset and
    noise) and ``w`` is the leaked part (``tau dw/dt = -(w + S_q F)``, solved exactly for the linear
    force ramp); ``us`` is the last output. With ``n_lag`` > 0 the output is the noise-free voltage
    of ``n_lag`` steps before (ring buffer ``v`` at ``head``) plus this step's noise: a sampling lag.
    ``noise`` is the additive noise sample [V] for this output.
    """
    sq = sen[0]
    a = sen[1]
    if a < 1.0:
        f0 = sen_s[1]
        # exact solution of tau w' = -w - S_q F with F linear from f0 to force over h:
        # w1 = a w0 - S_q [ (1 - a) f0 + (force - f0) (1 - (1 - a) * tau/h) ]
        r = sen[2]
        w = a * sen_s[0] - sq * ((1.0 - a) * f0 + (force - f0) * (1.0 - (1.0 - a) * r))
        sen_s[0] = w if abs(w) >= TINY else 0.0     # leaked away: no subnormal state (linear.TINY)
    sen_s[1] = force
    nl = int(sen[4])
    if nl > 0:
        v = sq * force + sen_s[0] + sen[3]
        head = int(sen_s[3])
        size = nl + 1
        sen_s[4 + head] = v
        head = (head + 1) % size
        sen_s[3] = head
        us = sen_s[4 + head] + noise          # the oldest entry: n_lag steps ago
    else:
        us = sq * force + sen_s[0] + sen[3] + noise
    sen_s[2] = us
    return us


class Sensor:
    """The quartz force sensor (paper eq. 3) with optional leakage, offset and noise.

    Parameters
    ----------
    d11 : piezoelectric coefficient of quartz [C/N]
    thickness : wafer thickness [m]; eps_r : relative permittivity [1]; area : electrode area [m^2]
    C_load : cable and input capacitance in parallel [F] (0: the paper's eq. 3)
    tau_leak : charge leakage time constant [s] (``inf``: no leakage, as in the paper)
    offset : output offset [V]; noise_std : white noise standard deviation [V]; seed : noise seed
    lag : sampling lag of the output [s], resolved to whole steps (0: none)
    """

    def __init__(self, *, d11, thickness, eps_r, area, C_load=0.0, tau_leak=math.inf,
                 offset=0.0, noise_std=0.0, seed=0, lag=0.0):
        self.d11, self.thickness, self.eps_r, self.area = (float(d11), float(thickness),
                                                           float(eps_r), float(area))
        self.C_load, self.tau_leak = float(C_load), float(tau_leak)
        self.offset, self.noise_std, self.seed = float(offset), float(noise_std), int(seed)
        self.C_s = EPS0 * self.eps_r * self.area / self.thickness
        self.sensitivity = self.d11 / (self.C_s + self.C_load)       # [V/N]
        self.lag = float(lag)
        self.sen = [self.sensitivity, 1.0, 0.0, self.offset, 0.0]
        self.sen_s = [0.0, 0.0, self.offset, 0.0]
        self.noise = NoiseSource(self.noise_std, self.seed)
        self._h = None

    @property
    def us(self):
        """The last output [V]."""
        return self.sen_s[2]

    def prepare(self, h):
        if same_step(h, self._h):
            return
        if math.isfinite(self.tau_leak):
            self.sen[1] = math.exp(-h / self.tau_leak)
            self.sen[2] = self.tau_leak / h
        nl = int(round(self.lag / h)) if self.lag > 0 else 0
        if nl != int(self.sen[4]):
            # the delay line holds the last noise-free value for every lagged step
            fill = self.sen_s[2] if len(self.sen_s) == 4 else self.sen_s[4 + int(self.sen_s[3])]
            self.sen[4] = float(nl)
            self.sen_s[3:] = [0.0] + [fill] * (nl + 1 if nl else 0)
        self._h = h

    def step(self, force, h):
        """Advance ``h`` [s] with the force moving linearly to ``force`` [N]; returns us [V]."""
        if h != self._h:
            self.prepare(h)
        return sensor_step(force, h, self.sen, self.sen_s, self.noise.next())

    def reset(self, force=0.0):
        self.sen_s[0] = 0.0
        self.sen_s[1] = float(force)
        self.noise.reset()
        self.sen_s[2] = self.sensitivity * force + self.offset
        self.sen_s[3] = 0.0
        for i in range(4, len(self.sen_s)):
            self.sen_s[i] = self.sen_s[2]

    def get_state(self):
        return {"w": self.sen_s[0], "F": self.sen_s[1], "us": self.us, "noise": self.noise.get_state(),
                "h": self._h, "lag_line": as_floats(self.sen_s[3:])}

    def set_state(self, s):
        self.sen_s[0], self.sen_s[1] = float(s["w"]), float(s["F"])
        self.sen_s[2] = float(s["us"])
        self.noise.set_state(s["noise"])
        if s["h"] is not None:
            self.prepare(float(s["h"]))
        line = s.get("lag_line")
        if line is not None and len(line) == len(self.sen_s) - 3:
            self.sen_s[3:] = [float(v) for v in line]


class NoiseSource:
    """Reproducible white Gaussian noise drawn in blocks (NumPy PCG64), with explicit state.

    The sequence depends only on ``seed`` and the number of samples drawn, so a monolithic run
    and an FMU draw identical samples; the state (generator state + position) is saveable.
    """

    BLOCK = 4096

    def __init__(self, std, seed):
        self.std = float(std)
        self.seed = int(seed)
        self.reset()

    def reset(self):
        self._gen = np.random.Generator(np.random.PCG64(self.seed))
        self._arr = np.empty(0)
        self._buf = None
        self._pos = 0
        self._block_state = None

    def _refill(self):
        self._block_state = self._gen.bit_generator.state
        self._arr = self.std * self._gen.standard_normal(self.BLOCK)
        self._buf = None            # the list view for next() is made when needed
        self._pos = 0

    def next(self):
        if self.std == 0.0:
            return 0.0
        if self._pos >= len(self._arr):
            self._refill()
        if self._buf is None:
            self._buf = self._arr.tolist()     # floats from a list: fast per-sample access
        v = self._buf[self._pos]
        self._pos += 1
        return v

    def take(self, n):
        """The next ``n`` samples as an array (same sequence as ``n`` calls to :meth:`next`)."""
        if self.std == 0.0:
            return np.zeros(n)
        out = np.empty(n)
        done = 0
        while done < n:
            if self._pos >= len(self._arr):
                self._refill()
            m = min(n - done, len(self._arr) - self._pos)
            out[done:done + m] = self._arr[self._pos:self._pos + m]
            self._pos += m
            done += m
        return out

    def get_state(self):
        return {"block_state": self._block_state, "pos": self._pos, "filled": len(self._arr) > 0}

    def set_state(self, s):
        self.reset()
        if s["filled"]:
            self._gen.bit_generator.state = s["block_state"]
            self._refill()
            self._pos = int(s["pos"])
