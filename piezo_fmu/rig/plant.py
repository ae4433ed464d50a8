"""The rig's plant: amplifier, stack, mechanics, sensors, and every effect that can be injected.

Signal chain, simulated on an internal grid ``M`` times finer than the recording (``dt_int``,
at least ~40 kHz) with the command held between its samples (the DAQ's zero-order hold):

::

    u [V]  --latency-->  internal lag(s)  -->  RC output stage, |C_a dua/dt| <= I_max  --> ua [V]
    ua     --hysteresis H[.] (volts of stroke-equivalent) x d_eff [um/V]-->  x_h [um]
    x_h    --log creep: x_h + g sum_k dx_h[k] log10(1 + (t - t_k)/t0)-->  x_c
    x_c    --extra series mode w2^2/(s^2 + 2 z2 w2 s + w2^2)-->  x_f (free stroke) [um]
    x_f    --m x'' + c x' + (k_a + k_f) x = k_a x_f-->  x (push rod) [um]
    force in the stack F = k_a (x_f - x) [N]
    probe   x_meas = g_p (x + drift(t)) + offset_x                [um]
    sensor  force pick-off  us = g_F * leak(F - F(0)) + offset_us  [V]
            displacement    us = g_x * (x + drift(t)) + offset_us  [V]

``leak`` is the quartz charge leakage, a first-order high-pass ``tau s / (tau s + 1)``; the
thermal drift moves the whole stack and push rod against the probe's frame, so it reaches the
probe and a displacement pick-off but not the force. Recording samples are the internal
states at ``t_k = k / fs`` (point sampling; ``x[k]`` depends on ``u`` up to ``u[k-1]``).

None of these equations is the project's model: the hysteresis families, the creep law, the
force definition, the discretisation and the sampling are the rig's own.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np
from numba import njit
from scipy import fft as sp_fft
from scipy import signal

from .hysteresis import Hysteresis

CATALOGUE = ("creep", "sensor_leakage", "amplifier_current_limit", "time_delay",
             "extra_resonance", "thermal_drift", "hysteresis_shape")
CONTROLS = ("mains_hum", "us_offset_drift", "push_rod_backlash", "probe_quantisation",
            "probe_gain_modulation")


@dataclass
class Plant:
    """Nominal plant of one case (every value in the unit its name says).

    Attributes
    ----------
    fs : float
        Recording sample rate [Hz].
    oversample : int
        Internal steps per recording sample.
    amp_gain : float
        Amplifier gain error [V/V] (command in stack volts).
    amp_tau : float
        RC output-stage time constant R C_a [s].
    amp_tau2 : float
        Internal stage time constant [s], 0 for a first-order amplifier.
    C_a : float
        Stack capacitance [F].
    d_eff : float
        Stack sensitivity [um/V].
    k_a, k_f : float
        Stack and preload stiffness [N/um].
    f1, zeta1 : float
        First mode of the push rod [Hz], its damping ratio [1].
    pickoff : str
        ``"force"`` (quartz, ``us = g_us F``) or ``"displacement"`` (``us = g_us x``).
    g_us : float
        Sensor gain [V/N] (quartz, ~2.3 mV/N) or [V/um] (a strain-gauge type pick-off,
        ~0.05 V/um).
    g_x : float
        Probe gain [1].
    off_x, off_us : float
        Channel offsets [um], [V].
    sigma_x, sigma_us : float
        Noise rms [um], [V].
    noise_colour : float
        AR(1) coefficient of the noise (0 = white).
    lag_channel : str or None
        Channel sampled one sample late (``"x"`` or ``"us"``), or None.
    """

    fs: float
    oversample: int
    hysteresis: Hysteresis
    amp_gain: float
    amp_tau: float
    amp_tau2: float
    C_a: float
    d_eff: float
    k_a: float
    k_f: float
    f1: float
    zeta1: float
    pickoff: str
    g_us: float
    g_x: float
    off_x: float
    off_us: float
    sigma_x: float
    sigma_us: float
    noise_colour: float = 0.0
    lag_channel: str | None = None
    u_lo: float = 0.0
    u_hi: float = 90.0

    @property
    def dt_int(self) -> float:
        return 1.0 / (self.fs * self.oversample)

    @property
    def mass(self) -> float:
        """Moving mass [kg] implied by the first mode."""
        return (self.k_a + self.k_f) * 1e6 / (2 * np.pi * self.f1) ** 2

    def describe(self) -> dict:
        rows = {
            "rate.fs": (self.fs, "Hz"), "rate.internal_oversample": (self.oversample, "1"),
            "amplifier.gain": (self.amp_gain, "V/V"), "amplifier.tau_output": (self.amp_tau, "s"),
            "amplifier.tau_internal": (self.amp_tau2, "s"),
            "amplifier.order": (1 if self.amp_tau2 == 0 else 2, "1"),
            "amplifier.C_a": (self.C_a, "F"), "amplifier.u_lo": (self.u_lo, "V"),
            "amplifier.u_hi": (self.u_hi, "V"),
            "stack.d_eff": (self.d_eff, "um/V"), "stack.k_a": (self.k_a, "N/um"),
            "mechanics.k_f": (self.k_f, "N/um"), "mechanics.f1": (self.f1, "Hz"),
            "mechanics.zeta1": (self.zeta1, "1"), "mechanics.mass": (self.mass, "kg"),
            "sensor.pickoff": (self.pickoff, ""),
            "sensor.gain": (self.g_us, "V/N" if self.pickoff == "force" else "V/um"),
            "sensor.offset": (self.off_us, "V"), "sensor.noise_rms": (self.sigma_us, "V"),
            "probe.gain": (self.g_x, "1"), "probe.offset": (self.off_x, "um"),
            "probe.noise_rms": (self.sigma_x, "um"), "noise.ar1": (self.noise_colour, "1"),
            "sampling.lag_channel": (self.lag_channel, ""),
        }
        out = {k: {"value": v, "unit": unit} for k, (v, unit) in rows.items()}
        out.update(self.hysteresis.describe())
        return out


@dataclass
class Effects:
    """Injected effects: ``{name: parameter dict}`` for catalogue mechanisms and controls."""

    items: dict = field(default_factory=dict)

    def without(self, name: str) -> Effects:
        return Effects({k: v for k, v in self.items.items() if k != name})

    def get(self, name: str):
        return self.items.get(name)


# ----------------------------------------------------------------------------------------------
# linear pieces


@lru_cache(maxsize=64)
def _zoh(num: tuple, den: tuple, dt: float):
    b, a, _ = signal.cont2discrete((list(num), list(den)), dt, method="zoh")
    b = np.atleast_1d(np.squeeze(b))
    return b, a


def _filter_rest(b, a, x):
    """``lfilter`` started at the steady state for the constant input ``x[0]``."""
    zi = signal.lfilter_zi(b, a) * x[0]
    return signal.lfilter(b, a, x, zi=zi)[0]


def first_order(x: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """``1 / (tau s + 1)`` on a held input; ``y[k]`` sees ``x`` up to ``x[k-1]``."""
    p = np.exp(-dt / tau)
    return _filter_rest(np.array([0.0, 1.0 - p]), np.array([1.0, -p]), x)


def second_order(x: np.ndarray, f: float, zeta: float, dt: float, gain: float = 1.0) -> np.ndarray:
    """``gain w^2 / (s^2 + 2 zeta w s + w^2)``, zero-order-hold exact, from rest at ``x[0]``."""
    w = 2 * np.pi * f
    b, a = _zoh((gain * w * w,), (1.0, 2 * zeta * w, w * w), dt)
    return _filter_rest(b, a, x)


@njit(cache=True)
def _rc_slew(v, tau, dt, smax, y0):  # pragma: no cover - compiled
    n = v.size
    y = np.empty(n)
    yc = y0
    p = np.exp(-dt / tau)
    band = smax * tau
    for k in range(n):
        y[k] = yc
        e = v[k] - yc
        if abs(e) <= band:
            yc = v[k] - e * p
        else:
            sg = 1.0 if e > 0 else -1.0
            t1 = (abs(e) - band) / smax          # time spent at the current limit
            if t1 >= dt:
                yc += sg * smax * dt
            else:
                yc = v[k] - sg * band * np.exp(-(dt - t1) / tau)
    return y


def amplifier(u_int: np.ndarray, plant: Plant, slew: float | None) -> np.ndarray:
    """Stack voltage ``ua`` [V] from the held command [V].

    ``R C_a dua/dt + ua = v`` with ``|dua/dt| <= slew`` (``slew = I_max / C_a`` [V/s]) solved
    exactly for a held ``v``: at the limit the voltage ramps, then relaxes exponentially.
    """
    v = plant.amp_gain * u_int
    if plant.amp_tau2 > 0:
        v = first_order(v, plant.amp_tau2, plant.dt_int)
    if slew is None or not np.isfinite(slew):
        return first_order(v, plant.amp_tau, plant.dt_int)
    return _rc_slew(np.ascontiguousarray(v), plant.amp_tau, plant.dt_int, float(slew), float(v[0]))


def log_creep(x_h: np.ndarray, gamma: float, t0: float, dt: float) -> np.ndarray:
    """Logarithmic creep ``x_h + gamma sum_k dx_h[k] log10(1 + (t - t_k) / t0)``.

    A step ``X`` held from ``t = 0`` reads ``X (1 + gamma log10(1 + t / t0))``: ``gamma``
    per decade of time, with no finite set of time constants.
    """
    n = x_h.size
    dx = np.diff(x_h, prepend=x_h[0])
    nfft, spec = _creep_kernel(n, dt, t0)
    conv = sp_fft.irfft(sp_fft.rfft(dx, nfft) * spec, nfft)[:n]
    return x_h + gamma * conv


@lru_cache(maxsize=4)
def _creep_kernel(n: int, dt: float, t0: float):
    nfft = sp_fft.next_fast_len(2 * n, real=True)
    return nfft, sp_fft.rfft(np.log10(1.0 + np.arange(n) * dt / t0), nfft)


def drift_curve(t: np.ndarray, p: dict) -> np.ndarray:
    """Thermal drift of the displacement zero [um]: warm-up, ramp, or both."""
    T = t[-1] if t[-1] > 0 else 1.0
    warm = 1.0 - np.exp(-t / p["tau"])
    ramp = t / T
    shape = {"warmup": warm / warm[-1], "ramp": ramp,
             "mixed": 0.5 * warm / warm[-1] + 0.5 * ramp}[p["form"]]
    return p["amplitude"] * shape


@njit(cache=True)
def _backlash(x, half):  # pragma: no cover - compiled
    y = np.empty_like(x)
    yc = x[0]
    for k in range(x.size):
        if yc < x[k] - half:
            yc = x[k] - half
        elif yc > x[k] + half:
            yc = x[k] + half
        y[k] = yc
    return y


# ----------------------------------------------------------------------------------------------
# the whole chain


def _key(*parts) -> tuple:
    """A hashable key of effect parameter dicts (arrays by value)."""
    out = []
    for p in parts:
        if p is None:
            out.append(None)
            continue
        out.append(tuple(sorted((k, tuple(np.ravel(v).tolist()) if isinstance(v, (list, np.ndarray))
                                 else v) for k, v in p.items())))
    return tuple(out)


class Simulator:
    """Runs one case's plant on one command, again and again with different effects.

    The chain is split into stages (amplifier, hysteresis, creep, extra mode, mechanics); each
    stage's output is kept for the effects upstream of it, so re-running a case without one
    effect recomputes only what that effect changes.

    Parameters
    ----------
    plant : Plant
    u : ndarray
        Command [V] at the recording rate (held between samples).
    """

    _KEEP = 4

    def __init__(self, plant: Plant, u: np.ndarray):
        self.plant = plant
        self.u = np.asarray(u, dtype=float)
        self._stages: dict[str, dict] = {}

    def _memo(self, stage: str, key: tuple, fn):
        store = self._stages.setdefault(stage, {})
        if key not in store:
            if len(store) >= self._KEEP:
                store.pop(next(iter(store)))
            store[key] = fn()
        return store[key]

    def _ua(self, cl):
        u_int = np.repeat(self.u, self.plant.oversample)
        return amplifier(u_int, self.plant, None if cl is None else cl["I_max"] / self.plant.C_a)

    def run(self, effects: Effects, first_mode: bool = True) -> dict:
        """Noise-free channels at the recording rate.

        Parameters
        ----------
        effects : Effects
            Mechanisms and controls to inject (parameter dicts, see ``mechanisms``).
        first_mode : bool
            False replaces the first mode by its static gain (to measure how visible it is).

        Returns
        -------
        dict
            ``x`` [um], ``us`` [V] (noise-free, gains and offsets included, before the
            sampling lag and quantisation), ``ua`` [V] and ``x_h`` [um] (hysteresis output) at
            the recording samples, ``ua_int`` [V] on the internal grid, ``slew_peak`` [V/s]
            (largest |dua/dt|).

        Notes
        -----
        Everything from the amplifier to the mechanics is time-invariant and starts at rest on
        a constant command, so the command latency is applied as a shift of that chain's
        outputs: the same numbers as delaying the command, without recomputing the chain.
        The shape feature and the creep are linear in their size, so they are kept per unit
        size.
        """
        plant = self.plant
        M = plant.oversample
        dt = plant.dt_int
        n = self.u.size
        g = effects.get
        cl = g("amplifier_current_limit")
        k_ua = _key(cl)
        ua = self._memo("ua", k_ua, lambda: self._ua(cl))
        hyst = plant.hysteresis
        H = self._memo("H", k_ua, lambda: hyst.base(ua))
        hs = g("hysteresis_shape")
        x_h = plant.d_eff * H
        if hs is not None:
            unit = self._memo("feature", k_ua + (hyst.shape,),
                              lambda: replace(hyst, shape_amplitude=1.0).feature(ua, H))
            x_h = x_h + plant.d_eff * hs["amplitude"] * unit
        k_xh = k_ua + _key(hs)
        cr = g("creep")
        x_c = x_h
        if cr is not None:
            crept = self._memo("creep", k_xh + (cr["t0"],),
                               lambda: log_creep(x_h, 1.0, cr["t0"], dt) - x_h)
            x_c = x_h + cr["gamma"] * crept
        k_xf = k_xh + _key(cr, g("extra_resonance"))
        er = g("extra_resonance")
        x_f = x_c if er is None else self._memo(
            "xf", k_xf, lambda: second_order(x_c, er["f"], er["zeta"], dt))
        kappa = plant.k_a / (plant.k_a + plant.k_f)
        if first_mode:
            x = self._memo("x", k_xf, lambda: second_order(x_f, plant.f1, plant.zeta1, dt, gain=kappa))
        else:
            x = kappa * x_f
        td = g("time_delay")
        d = int(td["steps_internal"]) if td is not None else 0
        if d > 0:
            shift = lambda y: np.concatenate([np.full(d, y[0]), y[:-d]])
            ua, x_h, x_f, x = shift(ua), shift(x_h), shift(x_f), shift(x)
        sl = slice(0, n * M, M)
        t = np.arange(n) / plant.fs
        td_ = g("thermal_drift")
        drift = drift_curve(t, td_) if td_ is not None else 0.0
        x_moved = x[sl] + drift
        bl = g("push_rod_backlash")
        x_probe = x_moved
        if bl is not None:
            # the push rod's play acts on the continuous motion: run it on the internal grid
            t_int = np.arange(x.size) * dt
            fine = x + (drift_curve(t_int, td_) if td_ is not None else 0.0)
            x_probe = _backlash(np.ascontiguousarray(fine), float(bl["half_width"]))[sl]
        if plant.pickoff == "force":
            force = plant.k_a * (x_f - x)                           # [N]
            f_rel = force - force[0]
            lk = g("sensor_leakage")
            if lk is not None:
                p = np.exp(-dt / lk["tau"])
                f_rel = signal.lfilter([1.0, -1.0], [1.0, -p], f_rel)
            us_rec = plant.g_us * f_rel[sl]
        else:
            us_rec = plant.g_us * x_moved
        x_rec = plant.g_x * x_probe + plant.off_x
        us_rec = us_rec + plant.off_us
        gm = g("probe_gain_modulation")
        if gm is not None:
            x_rec = plant.off_x + (x_rec - plant.off_x) * (
                1.0 + gm["depth"] * np.sin(2 * np.pi * gm["freq"] * t + gm["phase"]))
        hum = g("mains_hum")
        if hum is not None:
            wave = sum(a * np.sin(2 * np.pi * h * hum["freq"] * t + ph)
                       for h, a, ph in zip(hum["harmonics"], hum["weights"], hum["phases"]))
            if "x" in hum["channels"]:
                x_rec = x_rec + hum["amplitude_x"] * wave
            if "us" in hum["channels"]:
                us_rec = us_rec + hum["amplitude_us"] * wave
        od = g("us_offset_drift")
        if od is not None:
            us_rec = us_rec + od["amplitude"] * np.interp(t, od["knots_t"], od["knots_v"])
        slew_peak = float(np.abs(np.diff(ua)).max() / dt) if ua.size > 1 else 0.0
        return {"x": x_rec, "us": us_rec, "ua": ua[sl], "x_h": x_h[sl], "slew_peak": slew_peak,
                "ua_int": ua}


def simulate(plant: Plant, u: np.ndarray, effects: Effects, first_mode: bool = True) -> dict:
    """One run of ``Simulator(plant, u).run(effects, first_mode)`` (see there)."""
    return Simulator(plant, u).run(effects, first_mode)


def noise(rng: np.random.Generator, n: int, sigma: float, ar: float) -> np.ndarray:
    """Zero-mean noise of rms ``sigma``, white or AR(1) coloured with coefficient ``ar``."""
    w = rng.standard_normal(n)
    if ar > 0:
        w = signal.lfilter([np.sqrt(1 - ar * ar)], [1.0, -ar], w)
    return sigma * w


def lag_one(y: np.ndarray) -> np.ndarray:
    """The channel sampled one sample late: ``y[k-1]`` (``y[0]`` repeated)."""
    return np.concatenate([y[:1], y[:-1]])


def quantise(y: np.ndarray, step: float) -> np.ndarray:
    """Round to a multiple of ``step`` (a probe's converter)."""
    return step * np.round(y / step)
