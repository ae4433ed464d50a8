"""Fast open-loop replay of the device on a recording, for fitting.

:func:`predict` computes what ``simulate(model, Signal("table", t, u, column="u"), mode="open",
step=dt, noise=False)`` computes for a recorded command ``u`` sampled at ``dt`` (the command held
over each sample, the device relaxed at zero command before the first sample; with
``rec.oversample`` internal steps per sample, ``step=dt / oversample`` read at the samples, see
:func:`at_samples`), plus the channels' sampling lags, but splits the device at its only
nonlinearity that is not linear in its parameters:

* ``ua`` (delay, the amplifier's optional input stage, its output stage with current limit and
  rails) by the core's own :func:`~piezo_fmu.core.plant.amp_step` compiled with numba;
* the play-operator outputs ``z_i[ua / u_norm]`` (``N x n``, numba), and the KP cells' states
  when the model has cells (:mod:`piezo_fmu.core.preisach`: linear in their weights too);
* everything after the hysteresis is linear in the PI weights: creep, the mechanics (first mode,
  optional further mode) for ``x``; creep, then the stack force (pick-off ``stack``) or the load
  spring's force (``load``: through the mechanics), then leakage for ``us``. These are the core's
  continuous blocks discretised exactly as the core does (the stroke moving linearly between
  steps, or along the amplifier's lag under the model's ``simulation.stroke_path``,
  :func:`~piezo_fmu.core.linear.discretize`), applied as IIR filters to every operator column at
  once; a channel's sampling lag shifts its samples.

So for given dynamics the displacement and sensor voltage are linear in the PI weights, the
channel offsets, the drift polynomial and (bilinearly) the sensor sensitivity:
:func:`.varpro.solve_linear` finds them by bounded linear least squares (variable projection),
which keeps the nonlinear searches of :mod:`.fit` small.

The physics stays in :mod:`piezo_fmu.core`; this module re-arranges it for speed and is checked
against ``simulate`` sample by sample (tests/test_diagnose.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.signal import lfilter, ss2tf, tf2sos

from ..core.linear import discretize, tf2ss
from ..core.plant import drift_curvature, mechanics_tf, mode_tf, series_tf
from ..core.preisach import kp_relax, kp_step, kp_table
from .kernels import kernels
from .model_io import Device, Params, Recording, device_from_model, model_from_params, params_from_model

__all__ = [
    "Device",
    "Params",
    "Recording",
    "amplifier_output",
    "at_samples",
    "cell_states",
    "chain",
    "device_from_model",
    "limited_samples",
    "model_from_params",
    "operators",
    "params_from_model",
    "predict",
    "shift",
    "sos_filter",
]


# -- pieces of the replay -------------------------------------------------------------------------

def at_samples(rec: Recording, a: np.ndarray) -> np.ndarray:
    """``a``, computed on ``rec``'s internal grid (``rec.oversample`` steps per sample), at the
    recording's samples (the last axis).

    The replay runs ``rec.oversample`` internal steps per sample, the command held over each
    sample: what ``simulate`` computes with ``step = dt / oversample``, read at the samples. Between
    the samples the stack voltage moves along its lag and the mechanics follow that path; at one
    step per sample the path is taken as a straight line between the samples' strokes, which a lag
    or a mode comparable to the sample interval is not (see :mod:`.recordings`)."""
    m = rec.oversample
    return a if m == 1 else a[..., ::m]


def amplifier_output(rec: Recording, dev: Device, p: Params) -> np.ndarray:
    """Stack voltage ``ua`` at every internal step (step 0: the device at rest, ua = 0)."""
    amp_run = kernels()[0]
    u = rec.u if rec.oversample == 1 else np.repeat(rec.u, rec.oversample)
    nd = int(round(p.delay / rec.h)) if p.delay > 0 else 0
    out = np.empty(u.size)
    return amp_run(u, nd, dev.k_amp, p.tau, p.slew, dev.u_min, dev.u_max, rec.h, float(p.tau2), out)


def limited_samples(rec: Recording, dev: Device, p: Params):
    """How long the amplifier slews at its current limit ``p.slew``: ``(whole, ramps)``, the internal
    steps it slews from end to end, counted in whole samples, and the time of every ramp, in samples.

    Within an internal step the output ramps while the error to the step's target exceeds
    ``slew * tau`` (:func:`~piezo_fmu.core.plant.amp_step`): at one step per sample a limit whose
    ramps last less than a sample never slews for a whole step, yet shapes every jump it meets
    (rig-d35-014, 423 Hz: 2 whole steps at the limit, 105.6 samples' worth of ramps on a chirp)."""
    if not p.slew < math.inf:
        return 0, 0.0
    ua = amplifier_output(rec, dev, p)
    whole = int(np.count_nonzero(np.abs(np.diff(ua)) >= 0.999 * p.slew * rec.h)) // rec.oversample
    u = rec.u if rec.oversample == 1 else np.repeat(rec.u, rec.oversample)
    nd = int(round(p.delay / rec.h)) if p.delay > 0 else 0
    # each step's target: the same stages with an output stage that follows at once
    target = kernels()[0](u, nd, dev.k_amp, 1e-9 * rec.h, math.inf, dev.u_min, dev.u_max, rec.h,
                          float(p.tau2), np.empty(u.size))
    ramp = np.clip((np.abs(target[1:] - ua[:-1]) - p.slew * p.tau) / p.slew, 0.0, rec.h)
    return whole, float(ramp.sum()) / (rec.h * rec.oversample)


def initial_state(ua0: float, p: Params) -> np.ndarray:
    """The operators' state at the first sample: relaxed (0) or, with ``p.prep`` > 0, after a
    preparation sweep from rest up to ``p.prep`` volts and back down to the first sample's ``ua0``
    (a rig exercised before the record starts leaves that memory in the stack)."""
    r = np.asarray(p.thresholds, dtype=float)
    if p.prep <= 0.0:
        return np.zeros(r.size)
    top, v0 = p.prep / p.u_norm, ua0 / p.u_norm
    return np.minimum(v0 + r, np.maximum(top - r, 0.0))


def cell_states(ua0: float, p: Params):
    """The KP cells' states ``(relaxed, start)``: relaxed at rest (the core's
    :func:`~piezo_fmu.core.preisach.kp_relax`) and at the first sample (after the preparation sweep
    of :func:`initial_state`, when there is one)."""
    up, down, width = p.cells
    c = kp_table(up, down, width, np.zeros(up.size))
    s = [0.0] * up.size
    kp_relax(c, s)
    relaxed = np.array(s)
    if p.prep > 0.0:
        kp_step(p.prep / p.u_norm, c, s)
        kp_step(ua0 / p.u_norm, c, s)
    return relaxed, np.array(s)


def operators(ua: np.ndarray, p: Params) -> np.ndarray:
    """Play-operator outputs ``(n, N)`` for the stack voltage ``ua``, from :func:`initial_state`,
    followed by the KP cells' states counted from their relaxed state (``(n + m, N)``, or with the
    cells held their weighted sum, ``(n + 1, N)``: the columns of :meth:`Params.all_weights`)."""
    kern = kernels()
    r = np.asarray(p.thresholds, dtype=float)
    z = np.empty((r.size + p.n_cell_cols, ua.size))
    v = ua / p.u_norm
    kern[1](v, r, z[:r.size], initial_state(float(ua[0]), p))
    if p.n_cells:
        relaxed, start = cell_states(float(ua[0]), p)
        cells = [np.ascontiguousarray(c) for c in p.cells]
        if p.cells_held:          # one column: the cells' weighted sum
            z[r.size] = 0.0
            kern[3](v, *cells, start, relaxed, np.asarray(p.cell_w, float), z[r.size:])
        else:
            kern[3](v, *cells, start, relaxed, np.empty(0), z[r.size:])
    return z


@lru_cache(maxsize=8192)
def foh_filter(num, den, h, hold=None):
    """``(b, a)`` of the exact discretisation of ``num/den`` at step ``h``: the input interpolated
    linearly over the step, or with ``hold`` [s] moving along a first-order lag of that time
    constant (the stroke behind the amplifier, as the core's actuator discretises its blocks).

    The same discretisation the core's ``LinearSystem`` uses: ``x[k+1] = Phi x[k] + G0 u[k] +
    G1 u[k+1]``, ``y[k] = C x[k] + D u[k]``, rewritten as an ordinary difference equation for
    ``lfilter``.
    """
    a, b, c, d = tf2ss(np.array(num), np.array(den))
    n = a.shape[0]
    if n == 0:
        return np.array([float(d[0, 0])]), np.array([1.0])
    phi, g0, g1 = discretize(a, b, h, "foh") if hold is None else discretize(a, b, h, "lag", hold)
    bd = phi @ g1 + g0
    dd = c @ g1 + d
    bz, az = ss2tf(phi, bd, c, dd)
    return np.asarray(bz[0], dtype=float), np.asarray(az, dtype=float)


def _filt(num, den, h, cols):
    b, a = foh_filter(tuple(float(v) for v in num), tuple(float(v) for v in den), float(h))
    if a.size == 1:
        return cols * (b[0] / a[0])
    return lfilter(b, a, cols, axis=-1)


def lowpass(cols, tau, h):
    """``1 / (tau s + 1)``, the input interpolated linearly (a screening's regressor)."""
    return _filt([1.0], [tau, 1.0], h, cols)


def _padd(a, b):
    n = max(a.size, b.size)
    return np.pad(a, (0, n - a.size)) + np.pad(b, (0, n - b.size))


@lru_cache(maxsize=8192)
def _chain_sos(channel, creep, res, tau_leak, mech, pick, h, res_at="output", hold=None):
    """Second-order sections of the whole linear chain after the hysteresis for one channel:
    ``(front, sos, gain, dc)``, ``dc`` its static gain before the sensor's leakage (from the
    continuous blocks, exact). ``hold`` [s]: the amplifier's lag, along which the stroke moves
    between samples into the creep and the mechanics (the sensor's leakage sees the force at the
    samples, linearly interpolated, as the core's sensor).

    The core's blocks, each discretised on its own as the core steps them (creep, then mechanics
    with the optional mode for ``x``; creep, then the force (through the mechanics for the load
    pick-off) and the leakage for ``us``): composing discrete systems is exact, and one cascaded
    pass replaces one pass per block. Each block keeps its own sections, so slow poles near
    z = 1 are never multiplied into ill-conditioned polynomials.
    """
    num, den = np.array([1.0]), np.array([1.0])
    front = None
    dc = 1.0                 # static gain before the leakage, from the continuous blocks (exact)
    if res is not None and res_at == "drive":
        # the core discretises creep and the drive's mode as one block, (1 + sum g/(tau s + 1)) M(s);
        # its discretisation is the sum of those of the parallel terms M and g M / (tau s + 1), each
        # well conditioned on its own (the product's polynomial is not, with slow creep poles)
        mn, md = mode_tf(*res)
        terms = [(mn, md)] + [series_tf((np.array([g]), np.array([tau, 1.0])), (mn, md)) for g, tau in creep]
        front = []
        dc = sum(float(tn[-1]) / float(td[-1]) for tn, td in terms)
        for tn, td in terms:
            b, a = foh_filter(tuple(float(v) for v in tn), tuple(float(v) for v in td), h, hold)
            front.append(_sos(b, a))
        blocks = []
        res = None
    else:
        for g, tau in creep:
            b, a = foh_filter((1.0,), (tau, 1.0), h, hold)
            # num/den + g b/a = (num a + g b den) / (den a)
            num = _padd(np.convolve(num, a), g * np.convolve(b, den))
            den = np.convolve(den, a)
        blocks = [(num, den)] if creep else []
        dc = 1.0 + sum(g for g, _ in creep)
    m, c, k_a, k_f = mech
    gain = k_a * 1e-6
    if channel == "x" or pick in ("load", "contact"):
        # the core discretises the mechanics and the optional mode as one block: so do we
        mn, md = mechanics_tf(m, c, k_a, k_f, res)
        if channel == "us" and pick == "contact":
            # F_c / F_out = 1 - k_a 1e-6 x / F_out (the core subtracts k_a x from F_out: the same map)
            mn = _padd(np.asarray(md, float)[::-1], -k_a * 1e-6 * np.asarray(mn, float)[::-1])[::-1]
        blocks.append(foh_filter(tuple(float(v) for v in mn), tuple(float(v) for v in md), h, hold))
        dc *= float(np.asarray(mn, float)[-1]) / float(np.asarray(md, float)[-1])
        if channel == "us" and pick == "load":
            gain *= k_f * 1e-6
    if channel == "us" and math.isfinite(tau_leak):
        blocks.append(foh_filter((tau_leak, 0.0), (tau_leak, 1.0), h))
    sos = [_sos(b, a) for b, a in blocks]
    if not sos:
        return front, None, gain, dc
    return front, np.vstack(sos), gain, dc


def _sos(b, a):
    """Second-order sections of ``b/a``: written directly up to order 2 (most blocks), else by
    :func:`scipy.signal.tf2sos` (which pairs poles and zeros, at a thousand times the cost), kept
    for the next chain with the same block (read only).

    A chain is built afresh whenever one of its blocks changes (a Jacobian column, a grid point),
    but the blocks it leaves alone give the same sections: on a short creep record (rig-d8-025,
    profiled) ``tf2sos`` took 3.8 of 18.6 s in 3 508 calls, kept 2.3 s in 2 018 (the same numbers).
    A copy is returned: the compiled filter is specialised for writable arrays."""
    b = np.asarray(b, float)
    a = np.asarray(a, float)
    b = np.pad(b, (max(0, a.size - b.size), 0))
    if a.size <= 3:
        row = np.zeros(6)            # [b0 b1 b2 1 a1 a2] in powers of 1/z
        row[:b.size] = b / a[0]
        row[3:3 + a.size] = a / a[0]
        return row[None, :]
    return _sections(b.tobytes(), a.tobytes()).copy()


@lru_cache(maxsize=8192)
def _sections(b, a):
    """:func:`scipy.signal.tf2sos` of the coefficients ``b``, ``a`` (float64 bytes), read only."""
    sos = tf2sos(np.frombuffer(b), np.frombuffer(a))
    sos.flags.writeable = False
    return sos


def chain(cols, channel, dev: Device, p: Params, h):
    """``x`` [um] (channel "x") or the sensor's force [N] (channel "us") from the hysteretic stroke
    (before the channel's sampling lag)."""
    front, sos, gain, dc = _chain_sos(channel, tuple((float(g), float(t)) for g, t in p.creep),
                           None if p.res is None else (float(p.res[0]), float(p.res[1])),
                           float(p.tau_leak) if channel == "us" else math.inf,
                           (float(p.m), float(p.c), dev.k_a, dev.k_f), p.pick, float(h), p.res_at,
                           float(p.tau + p.tau2) if p.path_lag else None)
    # the chain starts settled at the first sample's stroke (a prepared start has one; a relaxed
    # start is at zero): its steady response to that level, plus the filtered change from it
    c0 = cols[..., :1] * gain
    settled = bool(np.any(c0))
    if settled and channel == "us" and math.isfinite(p.tau_leak) and not p.leak_settled:
        # a sensor charged with the first force leaks from there, as the core's sensor does from
        # Sensor.reset(F): the step response of the leakage block. A sensor that held that force
        # long before the record has leaked it: it reads the changes from there (``leak_settled``;
        # the start's level a constant, which the sensor offset takes)
        dc = _leak_start(cols.shape[-1], dc, float(h), float(p.tau_leak))
    if front is None and sos is not None:
        # the gain, the settled start and the filter in one compiled pass
        return sos_filter(sos, cols, gain, c0 if settled else None, dc)
    cols = cols * gain
    if settled:
        cols = cols - c0
    if front is not None:
        acc = sos_filter(front[0], cols)
        for f in front[1:]:
            acc += sos_filter(f, cols)
        cols = acc
    if sos is not None:
        cols = sos_filter(sos, cols)
    if settled:
        cols = cols + dc * c0
    return cols


@lru_cache(maxsize=16)
def _leak_start(n, dc, h, tau_leak):
    """``dc`` decaying through the sensor's leakage over ``n`` steps of ``h`` [s] (read only)."""
    out = dc * np.exp(-np.arange(n) * (h / tau_leak))
    out.flags.writeable = False
    return out


def sos_filter(sos, cols, gain=1.0, c0=None, dc=1.0):
    """``scipy.signal.sosfilt(sos, cols, axis=-1)`` (from rest; ``sos`` normalised, a0 = 1), the
    same numbers except that states below :data:`TINY` are zero at the end of every :data:`BLOCK`
    samples (no subnormal limit cycles), with all rows of ``cols`` filtered in one compiled pass
    (a row alone gives the numbers it gives in a design). With ``c0`` (one value
    per row, shaped as ``cols[..., :1]``) the filter runs from a settled start, as
    ``sosfilt(sos, cols * gain - c0) + dc * c0`` (``dc``: the static gain, one value or one per
    sample)."""
    x = np.ascontiguousarray(cols, dtype=float)
    rows = x.reshape(-1, x.shape[-1])
    out = np.empty_like(rows)
    start = np.empty(0) if c0 is None else np.ascontiguousarray(c0, dtype=float).reshape(-1)
    kernels()[4](np.ascontiguousarray(sos, dtype=float), rows, float(gain), start,
                  np.atleast_1d(np.asarray(dc, dtype=float)), out)
    return out.reshape(x.shape)


def shift(a, n):
    """``a`` delayed by ``n`` samples along its last axis, the first value held before it (a
    channel sampled ``n`` samples late; the device is at rest before the record)."""
    if n <= 0:
        return a
    out = np.empty_like(a)
    out[..., n:] = a[..., :-n]
    out[..., :n] = a[..., :1]
    return out


def drift(t, p: Params):
    """The displacement reading's drift [um]: offset plus :func:`trend` (the offset alone, a number,
    when there is no trend: the same sums, without the curvature's exponentials at every sample)."""
    if not p.rate and not p.curv:
        return p.off_x
    return p.off_x + trend(t, p)


def load_trend(t, dev: Device, p: Params, h):
    """The load spring's force from the drift's change [N] (through the sensor's leakage)."""
    return leak(dev.k_load * trend(t, p), p.tau_leak, h)


def leak(f, tau_leak, h):
    """``f`` through the sensor's charge leakage ``tau s / (tau s + 1)`` (from rest; none when inf)."""
    if math.isfinite(tau_leak):
        return _filt([tau_leak, 0.0], [tau_leak, 1.0], h, f)
    return f


def trend(t, p: Params):
    """The drift's change since the start [um] (a load pick-off's force follows it: k_load trend)."""
    return p.rate * t + p.curv * drift_curvature(t, p.drift_tau)


def saturate(hx, y_sat):
    if not math.isfinite(y_sat):
        return hx
    return hx / (1.0 + np.abs(hx) / y_sat)


@dataclass
class Replay:
    """Intermediate signals of one recording for given dynamics (cached across linear solves)."""

    z: np.ndarray                   # (N, n * oversample) operator outputs, at every internal step
    ua: np.ndarray                  # stack voltage [V] at every internal step


def replay(rec: Recording, dev: Device, p: Params) -> Replay:
    ua = amplifier_output(rec, dev, p)
    return Replay(operators(ua, p), ua)


def stroke(rec: Recording, dev: Device, p: Params, rp: Replay | None = None):
    """Hysteretic free stroke ``x_h`` [um] (saturated), from the stored operators or computed directly."""
    if rp is not None:
        hx = p.all_weights() @ rp.z
        return saturate(hx, p.y_sat)
    ua = amplifier_output(rec, dev, p)
    kern = kernels()
    y_inv = 1.0 / p.y_sat if math.isfinite(p.y_sat) else 0.0
    v = ua / p.u_norm
    if not p.n_cells:
        return kern[2](v, np.asarray(p.thresholds, float), np.asarray(p.weights, float), y_inv,
                       np.empty(ua.size), initial_state(float(ua[0]), p))
    hx = kern[2](v, np.asarray(p.thresholds, float), np.asarray(p.weights, float), 0.0,
                 np.empty(ua.size), initial_state(float(ua[0]), p))
    relaxed, start = cell_states(float(ua[0]), p)
    kern[3](v, *(np.ascontiguousarray(c) for c in p.cells), start, relaxed, p.cell_weights(), hx[None, :])
    return saturate(hx, p.y_sat)


def predict(rec: Recording, dev: Device, p: Params, rp: Replay | None = None, direct=False,
            hx: np.ndarray | None = None) -> dict:
    """Noise-free ``x`` [um] and ``us`` [V] of the model at every sample of ``rec``.

    ``direct``: compute the weighted operator sum in one compiled pass (no operator matrix),
    for evaluations that do not need the operators themselves. ``hx``: the hysteretic stroke
    [um] of ``p`` already computed (:func:`stroke`, at every internal step), only the linear chain
    after it is run. ``ua`` and ``x_h`` are returned at the samples too.
    """
    if hx is None and direct and rp is None:
        hx = stroke(rec, dev, p)
    elif hx is None:
        rp = rp or replay(rec, dev, p)
        hx = stroke(rec, dev, p, rp)
    force = at_samples(rec, chain(hx, "us", dev, p, rec.h))
    if p.pick == "load" and (p.rate or p.curv):
        force = force + load_trend(rec.t, dev, p, rec.dt)
    out = {"x": shift(at_samples(rec, chain(hx, "x", dev, p, rec.h)) + drift(rec.t, p), p.lag_x),
           "us": shift(p.S * force + p.off_s, p.lag_us),
           "ua": at_samples(rec, rp.ua) if rp is not None else None, "x_h": at_samples(rec, hx)}
    return out
