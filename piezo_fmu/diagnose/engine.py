"""Fast open-loop replay of the device on a recording, for fitting.

:func:`predict` computes what ``simulate(model, Signal("table", t, u, column="u"), mode="open",
step=dt, noise=False)`` computes for a recorded command ``u`` sampled at ``dt`` (the command held
over each sample, the device relaxed at zero command before the first sample), but splits the
device at its only nonlinearity that is not linear in its parameters:

* ``ua`` (delay, amplifier lag, current limit, rails) by the core's own :func:`~piezo_fmu.core.plant.amp_step`
  compiled with numba;
* the play-operator outputs ``z_i[ua / u_norm]`` (``N x n``, numba);
* everything after the hysteresis is linear in the PI weights: creep, mechanics (with the optional
  further mode) for ``x``, leakage for ``us``. These are the core's continuous blocks discretised
  exactly as the core does (first-order hold, :func:`~piezo_fmu.core.linear.discretize`), applied as
  IIR filters to every operator column at once.

So for given dynamics the displacement and sensor voltage are linear in the PI weights, the
channel offsets, the drift polynomial and (bilinearly) the sensor sensitivity: :func:`solve_linear`
finds them by bounded linear least squares (variable projection), which keeps the nonlinear
searches of :mod:`.fit` one- to four-dimensional.

The physics stays in :mod:`piezo_fmu.core`; this module re-arranges it for speed and is checked
against ``simulate`` sample by sample (tests/test_diagnose.py).
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular
from scipy.optimize import lsq_linear
from scipy.signal import lfilter, sosfilt, ss2tf, tf2sos

from ..core import plant
from ..core.linear import discretize, tf2ss
from ..core.plant import EPS0, mechanics_tf

__all__ = [
    "Device",
    "Params",
    "Recording",
    "amplifier_output",
    "device_from_model",
    "model_from_params",
    "operators",
    "params_from_model",
    "predict",
    "solve_linear",
]


# -- compiled kernels ---------------------------------------------------------------------------

@lru_cache(maxsize=1)
def _kernels():
    import numba

    amp_step = numba.njit(cache=True, nogil=True)(plant.amp_step)

    @numba.njit(cache=True, nogil=True)
    def amp_run(uc, nd, k_amp, tau, slew, u_min, u_max, h, out):
        decay = math.exp(-h / tau)
        ua = 0.0
        out[0] = 0.0
        for k in range(uc.size - 1):
            c = uc[k - nd] if k >= nd else 0.0
            target = k_amp * c
            if target < u_min:
                target = u_min
            elif target > u_max:
                target = u_max
            ua = amp_step(ua, target, tau, slew, h, decay)
            out[k + 1] = ua
        return out

    @numba.njit(cache=True, nogil=True, inline="always")
    def play(z, v, r):
        # one play operator (threshold r) moved by the input v: the rule of core.hysteresis.pi_step
        lo = v - r
        if z < lo:
            return lo
        return min(z, v + r)

    @numba.njit(cache=True, nogil=True)
    def play_run(v, r, z):
        # the operators are independent: one pass per operator keeps the writes contiguous
        for i in range(r.size):
            ri = r[i]
            zi = 0.0
            row = z[i]
            for k in range(v.size):
                zi = play(zi, v[k], ri)
                row[k] = zi
        return z

    @numba.njit(cache=True, nogil=True)
    def pi_run(v, r, w, y_inv, out):
        # the weighted sum of the operators (and the strain saturation) without storing them
        out[:] = 0.0
        for i in range(r.size):
            ri = r[i]
            wi = w[i]
            zi = 0.0
            for k in range(v.size):
                zi = play(zi, v[k], ri)
                out[k] += wi * zi
        if y_inv > 0.0:
            for k in range(v.size):
                out[k] = out[k] / (1.0 + abs(out[k]) * y_inv)
        return out

    return amp_run, play_run, pi_run


# -- the device -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Device:
    """Constants of the model that diagnose never changes (taken from the nominal model)."""

    k_amp: float
    C_a: float
    u_min: float
    u_max: float
    m: float
    c: float
    k_a: float
    k_f: float
    C_sensor: float        # C_s + C_load [F]

    @property
    def k_force(self):
        return self.k_a * 1e-6

    @property
    def mech_gain(self):
        """Static displacement per free stroke (k_a / (k_a + k_f))."""
        return self.k_a / (self.k_a + self.k_f)


@dataclass
class Params:
    """Everything diagnose may fit (SI units; displacements in the recording's x units)."""

    tau: float                       # amplifier R C_a [s]
    u_norm: float                    # PI input normalisation [V]
    thresholds: np.ndarray           # normalised
    weights: np.ndarray              # free stroke per operator output [um]
    y_sat: float = math.inf          # strain saturation [um]
    slew: float = math.inf           # I_max / C_a [V/s]
    delay: float = 0.0               # [s]
    creep: list = field(default_factory=list)     # [(gain, tau [s]), ...]
    res: tuple | None = None         # (f_n [Hz], zeta)
    off_x: float = 0.0               # drift.offset [um]
    rate: float = 0.0                # drift.rate [um/s]
    curv: float = 0.0                # drift.curvature [um/s^2]
    S: float = 1.0                   # sensor sensitivity [V/N]
    off_s: float = 0.0               # sensor offset [V]
    tau_leak: float = math.inf       # [s]

    def copy(self):
        return copy.deepcopy(self)


@dataclass
class Recording:
    """One recording in model orientation: ``x`` and ``us`` already multiplied by their sign."""

    name: str
    t: np.ndarray            # time since the first sample [s]
    dt: float
    u: np.ndarray            # amplifier command [V]
    x: np.ndarray | None
    us: np.ndarray | None
    heldout: np.ndarray      # bool per sample
    t0: float = 0.0          # time of the first sample in the file [s]
    block: np.ndarray | None = None   # validation block of every sample
    sign: dict = field(default_factory=dict)   # channel -> +1/-1 (file = sign * model)

    @property
    def n(self):
        return self.u.size

    @property
    def train(self):
        return ~self.heldout

    def channels(self):
        return [c for c in ("x", "us") if getattr(self, c) is not None]


# -- pieces of the replay -------------------------------------------------------------------------

def amplifier_output(rec: Recording, dev: Device, p: Params) -> np.ndarray:
    """Stack voltage ``ua`` at every sample (sample 0: the device at rest, ua = 0)."""
    amp_run = _kernels()[0]
    nd = int(round(p.delay / rec.dt)) if p.delay > 0 else 0
    out = np.empty(rec.n)
    return amp_run(rec.u, nd, dev.k_amp, p.tau, p.slew, dev.u_min, dev.u_max, rec.dt, out)


def operators(ua: np.ndarray, p: Params) -> np.ndarray:
    """Play-operator outputs ``(n, N)`` for the stack voltage ``ua``, from the relaxed state."""
    play_run = _kernels()[1]
    r = np.asarray(p.thresholds, dtype=float)
    z = np.empty((r.size, ua.size))
    return play_run(ua / p.u_norm, r, z)


@lru_cache(maxsize=256)
def foh_filter(num, den, h):
    """``(b, a)`` of the exact first-order-hold discretisation of ``num/den`` at step ``h``.

    The same discretisation the core's ``LTIData`` uses: ``x[k+1] = Phi x[k] + G0 u[k] + G1 u[k+1]``,
    ``y[k] = C x[k] + D u[k]``, rewritten as an ordinary difference equation for ``lfilter``.
    """
    a, b, c, d = tf2ss(np.array(num), np.array(den))
    n = a.shape[0]
    if n == 0:
        return np.array([float(d[0, 0])]), np.array([1.0])
    phi, g0, g1 = discretize(a, b, h, "foh")
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
    """``1 / (tau s + 1)`` (first-order hold, as the core's creep elements)."""
    return _filt([1.0], [tau, 1.0], h, cols)


def _padd(a, b):
    n = max(a.size, b.size)
    return np.pad(a, (0, n - a.size)) + np.pad(b, (0, n - b.size))


@lru_cache(maxsize=512)
def _chain_sos(channel, creep, res, tau_leak, mech, h):
    """Second-order sections of the whole linear chain after the hysteresis for one channel.

    The core's blocks, each discretised on its own as the core steps them (creep, then mechanics
    with the optional mode for ``x``; creep, then the force and the leakage for ``us``): composing
    discrete systems is exact, and one cascaded pass replaces one pass per block. Each block keeps
    its own sections, so slow poles near z = 1 are never multiplied into ill-conditioned polynomials.
    """
    num, den = np.array([1.0]), np.array([1.0])
    for g, tau in creep:
        b, a = foh_filter((1.0,), (tau, 1.0), h)
        # num/den + g b/a = (num a + g b den) / (den a)
        num = _padd(np.convolve(num, a), g * np.convolve(b, den))
        den = np.convolve(den, a)
    blocks = [(num, den)] if creep else []
    m, c, k_a, k_f = mech
    if channel == "x":
        # the core discretises the mechanics and the optional mode as one block: so do we
        mn, md = mechanics_tf(m, c, k_a, k_f, res)
        blocks.append(foh_filter(tuple(float(v) for v in mn), tuple(float(v) for v in md), h))
    elif math.isfinite(tau_leak):
        blocks.append(foh_filter((tau_leak, 0.0), (tau_leak, 1.0), h))
    sos = []
    gain = k_a * 1e-6
    for b, a in blocks:
        b = np.asarray(b, float)
        a = np.asarray(a, float)
        b = np.pad(b, (max(0, a.size - b.size), 0))
        sos.append(tf2sos(b, a))
    if not sos:
        return None, gain
    return np.vstack(sos), gain


def chain(cols, channel, dev: Device, p: Params, h):
    """``x`` [um] (channel "x") or the sensor's force [N] (channel "us") from the hysteretic stroke."""
    sos, gain = _chain_sos(channel, tuple((float(g), float(t)) for g, t in p.creep),
                           None if p.res is None else (float(p.res[0]), float(p.res[1])),
                           float(p.tau_leak) if channel == "us" else math.inf,
                           (dev.m, dev.c, dev.k_a, dev.k_f), float(h))
    if sos is None:
        return cols * gain
    return sosfilt(sos, cols * gain, axis=-1)


def drift(t, p: Params):
    return p.off_x + p.rate * t + p.curv * t * t


def _saturate(hx, y_sat):
    if not math.isfinite(y_sat):
        return hx
    return hx / (1.0 + np.abs(hx) / y_sat)


@dataclass
class Replay:
    """Intermediate signals of one recording for given dynamics (cached across linear solves)."""

    z: np.ndarray                   # (n, N) operator outputs
    ua: np.ndarray


def replay(rec: Recording, dev: Device, p: Params) -> Replay:
    ua = amplifier_output(rec, dev, p)
    return Replay(operators(ua, p), ua)


def stroke(rec: Recording, dev: Device, p: Params, rp: Replay | None = None):
    """Hysteretic free stroke ``x_h`` [um] (saturated), from the stored operators or computed directly."""
    if rp is not None:
        hx = np.zeros(rec.n)
        for wi, zi in zip(np.asarray(p.weights, float), rp.z):
            hx += wi * zi
        return _saturate(hx, p.y_sat)
    ua = amplifier_output(rec, dev, p)
    pi_run = _kernels()[2]
    y_inv = 1.0 / p.y_sat if math.isfinite(p.y_sat) else 0.0
    return pi_run(ua / p.u_norm, np.asarray(p.thresholds, float), np.asarray(p.weights, float), y_inv,
                  np.empty(rec.n))


def predict(rec: Recording, dev: Device, p: Params, rp: Replay | None = None, direct=False) -> dict:
    """Noise-free ``x`` [um] and ``us`` [V] of the model at every sample of ``rec``.

    ``direct``: compute the weighted operator sum in one compiled pass (no operator matrix),
    for evaluations that do not need the operators themselves.
    """
    if direct and rp is None:
        hx = stroke(rec, dev, p)
        rp = None
    else:
        rp = rp or replay(rec, dev, p)
        hx = stroke(rec, dev, p, rp)
    out = {"x": chain(hx, "x", dev, p, rec.dt) + drift(rec.t, p),
           "us": p.S * chain(hx, "us", dev, p, rec.dt) + p.off_s,
           "ua": rp.ua if rp is not None else None, "x_h": hx}
    return out


# -- variable projection: the linear parameters ---------------------------------------------------

def _design(rec, dev, p, rp, lin_w):
    """Columns (per weight) of x and of the sensor force, plus the known part from saturation."""
    z = rp.z
    if math.isfinite(p.y_sat) and lin_w is not None:
        h0 = lin_w @ z
        gp = 1.0 / (1.0 + np.abs(h0) / p.y_sat) ** 2
        c0 = _saturate(h0, p.y_sat) - gp * h0
        cols = np.vstack([z * gp, c0[None, :]])
    else:
        cols = np.vstack([z, np.zeros((1, z.shape[1]))])
    ax = chain(cols, "x", dev, p, rec.dt) if rec.x is not None else None
    asf = chain(cols, "us", dev, p, rec.dt) if rec.us is not None else None
    return ax, asf


def solve_linear(recs, dev: Device, p: Params, lam: dict, *, drift_terms=0, fit_sensor_gain=True,
                 replays=None, gn_iter=2, rows="train", want_residuals=True):
    """Fit the PI weights, offsets, drift and sensor gain for fixed dynamics; update ``p`` in place.

    Minimises ``sum_c lam[c] * ||y_c - model_c||^2`` over the training rows with every partial sum
    of the weights >= a small positive bound (the model stays invertible; concave loading curves
    allowed). ``drift_terms``: 0 (offset only), 1 (+ rate) or 2 (+ curvature). The sensor gain
    (bilinear with the weights) is alternated with them; strain saturation is handled by
    Gauss-Newton steps from the current weights. Everything after the design matrices works on
    their small Gram matrices. Returns the weighted residual vector (training rows).
    """
    replays = replays or [replay(r, dev, p) for r in recs]
    n = len(p.thresholds)
    has_x = any(r.x is not None for r in recs)
    has_us = any(r.us is not None for r in recs)
    nd = 1 + drift_terms if has_x else 0
    n_par = n + nd + (1 if has_us else 0)       # W (partial sums) | x offset, rate, curv | us offset
    diff = np.eye(n) - np.eye(n, k=-1)          # w = diff @ W
    lin_w = np.asarray(p.weights, float) if np.any(p.weights) else None
    iters = 1
    if math.isfinite(p.y_sat):
        iters = gn_iter + (1 if lin_w is None else 0)
    for _ in range(iters):
        kx, ks = n + 1 + nd, n + 2              # rows of the x and us designs
        Mx, cx, Ms, cs = np.zeros((kx, kx)), np.zeros(kx), np.zeros((ks, ks)), np.zeros(ks)
        for r, rp in zip(recs, replays):
            ax, asf = _design(r, dev, p, rp, lin_w)
            if r.x is not None:
                cmat = np.empty((kx, r.n))
                cmat[:n + 1] = ax
                if nd >= 1:
                    cmat[n + 1] = 1.0
                if nd >= 2:
                    cmat[n + 2] = r.t
                if nd >= 3:
                    cmat[n + 3] = r.t * r.t
                Mx += _gram(cmat, r, rows)
                cx += _gram_vec(cmat, r.x, r, rows)
            if r.us is not None:
                cmat = np.empty((ks, r.n))
                cmat[:n + 1] = asf
                cmat[n + 1] = 1.0
                Ms += _gram(cmat, r, rows)
                cs += _gram_vec(cmat, r.us, r, rows)
        # coefficient maps: c_x = Px theta + qx, c_s = Ps theta + qs
        Px = np.zeros((kx, n_par))
        Px[:n, :n] = diff
        Px[n + 1:, n:n + nd] = np.eye(nd)
        qx = np.zeros(kx)
        qx[n] = 1.0
        S = p.S
        for _ in range(3 if (has_x and has_us and fit_sensor_gain) else 1):
            G = np.zeros((n_par, n_par))
            rhs = np.zeros(n_par)
            if has_x:
                G += lam["x"] * (Px.T @ Mx @ Px)
                rhs += lam["x"] * (Px.T @ (cx - Mx @ qx))
            if has_us:
                Ps = np.zeros((ks, n_par))
                Ps[:n, :n] = S * diff
                Ps[n + 1, n_par - 1] = 1.0
                qs = np.zeros(ks)
                qs[n] = S
                G += lam["us"] * (Ps.T @ Ms @ Ps)
                rhs += lam["us"] * (Ps.T @ (cs - Ms @ qs))
            sol = _bounded_normal_solve(G, rhs, n, scale_hint=_scale_hint(recs, dev, p))
            w = diff @ sol[:n]
            if has_x and has_us and fit_sensor_gain:
                # us = S * (force columns @ w + known) + offset: regression on (prediction, 1)
                v = np.concatenate([w, [1.0]])
                pp = v @ Ms[:n + 1, :n + 1] @ v
                p1 = v @ Ms[:n + 1, n + 1]
                py = v @ cs[:n + 1]
                a = np.array([[pp, p1], [p1, Ms[n + 1, n + 1]]])
                try:
                    s_new = np.linalg.solve(a, [py, cs[n + 1]])[0]
                except np.linalg.LinAlgError:
                    s_new = S
                if s_new > 0 and np.isfinite(s_new):
                    S = float(s_new)
        p.weights = w
        p.S = S
        if has_x:
            p.off_x = float(sol[n])
            p.rate = float(sol[n + 1]) if drift_terms >= 1 else 0.0
            p.curv = float(sol[n + 2]) if drift_terms >= 2 else 0.0
        if has_us:
            p.off_s = float(sol[n_par - 1])
        lin_w = w
    if not want_residuals:
        return None
    return residuals(recs, dev, p, lam, replays)


def _heldout_runs(r):
    runs = r.__dict__.get("_ho_runs")
    if runs is None:
        ho = np.concatenate([[False], r.heldout, [False]]).astype(np.int8)
        d = np.diff(ho)
        runs = list(zip(np.nonzero(d == 1)[0].tolist(), np.nonzero(d == -1)[0].tolist()))
        r.__dict__["_ho_runs"] = runs
    return runs


def _gram(cmat, r, rows):
    """``C C^T`` over the training samples: over all samples minus the held-out runs."""
    g = cmat @ cmat.T
    if rows == "train":
        for a, b in _heldout_runs(r):
            blk = cmat[:, a:b]
            g -= blk @ blk.T
    return g


def _gram_vec(cmat, y, r, rows):
    v = cmat @ y
    if rows == "train":
        for a, b in _heldout_runs(r):
            v -= cmat[:, a:b] @ y[a:b]
    return v


def _scale_hint(recs, dev, p):
    """Rough size of the free stroke [x units] the weights must produce (sets their lower bound)."""
    spans = [np.ptp(r.x) / dev.mech_gain for r in recs if r.x is not None]
    spans += [np.ptp(r.us) / max(abs(p.S) * dev.k_force, 1e-300) for r in recs if r.us is not None]
    return max(max(spans or [1.0]), 1e-12)


def _bounded_normal_solve(G, rhs, n_bounded, scale_hint=1.0):
    """min ||M theta - y|| given ``G = M^T M`` and ``rhs = M^T y``; theta[:n_bounded] >= eps."""
    d = np.sqrt(np.maximum(np.diag(G), 1e-300))
    Gs = G / np.outer(d, d)
    rs = rhs / d
    jitter = 1e-12
    for _ in range(6):
        try:
            c, low = cho_factor(Gs + jitter * np.eye(len(d)))
            break
        except np.linalg.LinAlgError:
            jitter *= 100
    R = np.triu(c) if not low else np.tril(c).T
    q = solve_triangular(R, rs, trans="T")
    unc = cho_solve((c, low), rs)
    eps = 1e-6 * scale_hint       # partial sums stay positive after rounding to 8 digits
    lb = np.full(len(d), -np.inf)
    lb[:n_bounded] = eps * d[:n_bounded]
    if np.all(unc[:n_bounded] >= lb[:n_bounded]):
        return unc / d
    res = lsq_linear(R, q, bounds=(lb, np.full(len(d), np.inf)), method="bvls", lsmr_tol=None)
    return res.x / d


def residuals(recs, dev, p, lam, replays=None, rows="train"):
    """Weighted residual vector (measured - model) over the chosen rows of every recording."""
    out = []
    for i, r in enumerate(recs):
        pred = predict(r, dev, p, replays[i] if replays else None)
        m = r.train if rows == "train" else (r.heldout if rows == "heldout" else np.ones(r.n, bool))
        for c in r.channels():
            out.append(math.sqrt(lam[c]) * (getattr(r, c)[m] - pred[c][m]))
    return np.concatenate(out)


# -- model <-> parameters ------------------------------------------------------------------------

def device_from_model(model) -> Device:
    a, me, s = model["amplifier"], model["mechanics"], model["sensor"]
    c_s = EPS0 * s["eps_r"] * s["area"] / s["thickness"]
    return Device(k_amp=a["k_amp"], C_a=a["C_a"], u_min=a["u_min"], u_max=a["u_max"], m=me["m"],
                  c=me["c"], k_a=me["k_a"], k_f=me["k_f"], C_sensor=c_s + s["C_load"])


def params_from_model(model) -> Params:
    a, h, s = model["amplifier"], model["hysteresis"], model["sensor"]
    dev = device_from_model(model)
    cr, res, dr = model["creep"], model["resonance"], model["drift"]
    return Params(
        tau=a["R"] * a["C_a"], u_norm=h["u_norm"], thresholds=np.array(h["thresholds"], float),
        weights=h["scale"] * np.array(h["weights"], float), y_sat=h.get("saturation", math.inf),
        slew=a.get("I_max", math.inf) / a["C_a"], delay=a.get("delay", 0.0),
        creep=list(zip(cr.get("gains", []), cr.get("time_constants", []))),
        res=(res["f_n"], res["zeta"]) if res.get("f_n", 0.0) > 0 else None,
        off_x=dr.get("offset", 0.0), rate=dr.get("rate", 0.0), curv=dr.get("curvature", 0.0),
        S=s["d11"] / dev.C_sensor, off_s=s.get("offset", 0.0), tau_leak=s.get("tau_leak", math.inf))


def _num(v, digits=8):
    return float(f"{float(v):.{digits}g}")


def model_from_params(base, p: Params, sources: dict, dt=None):
    """A copy of ``base`` carrying ``p``; ``sources`` maps (section, key) -> provenance text.

    Keys not in ``sources`` get a generic 'fitted by piezo-fmu diagnose' provenance.
    """
    m = base.copy()
    C_a = m["amplifier"]["C_a"]

    def put(sec, key, value, default_src):
        m.set(sec, key, value, sources.get((sec, key), default_src))

    fitted = "fitted by piezo-fmu diagnose to the recording(s)"
    put("amplifier", "R", _num(p.tau / C_a), fitted + " (R = tau / C_a, tau the amplifier lag)")
    put("amplifier", "I_max", _num(p.slew * C_a) if math.isfinite(p.slew) else math.inf,
        fitted if math.isfinite(p.slew) else "diagnose: no current limit found")
    delay = p.delay
    if dt and delay > 0:
        delay = round(delay / dt) * dt
    put("amplifier", "delay", _num(delay, 10), fitted if delay > 0 else "diagnose: no latency found")
    w = np.asarray(p.weights, float)
    total = float(np.sum(w))
    put("hysteresis", "u_norm", _num(p.u_norm), "diagnose: input normalisation, the recording's stack-voltage span")
    put("hysteresis", "thresholds", [_num(v) for v in p.thresholds], "diagnose: the nominal thresholds on the recording's span")
    put("hysteresis", "scale", _num(total), fitted + " (sum of the weights: stroke per PI unit)")
    ws = [_num(v) for v in (w / total)]
    put("hysteresis", "weights", ws, fitted + " (bounded least squares, every partial sum > 0)")
    put("hysteresis", "saturation", _num(p.y_sat) if math.isfinite(p.y_sat) else math.inf,
        "diagnose: nominal saturation, scaled with the recalibrated stroke")
    put("creep", "gains", [_num(g) for g, _ in p.creep], fitted if p.creep else "diagnose: no creep found")
    put("creep", "time_constants", [_num(t) for _, t in p.creep], fitted if p.creep else "diagnose: no creep found")
    put("resonance", "f_n", _num(p.res[0]) if p.res else 0.0, fitted if p.res else "diagnose: no further mode found")
    put("resonance", "zeta", _num(p.res[1]) if p.res else 0.05, fitted if p.res else "default")
    put("drift", "offset", _num(p.off_x), fitted + " (offset of the displacement channel)")
    put("drift", "rate", _num(p.rate), fitted if p.rate else "diagnose: no drift found")
    put("drift", "curvature", _num(p.curv), fitted if p.curv else "diagnose: no drift found")
    dev = device_from_model(m)
    put("sensor", "d11", _num(p.S * dev.C_sensor), fitted + " (effective: absorbs the sensor chain's gain)")
    put("sensor", "offset", _num(p.off_s), fitted)
    put("sensor", "tau_leak", _num(p.tau_leak) if math.isfinite(p.tau_leak) else math.inf,
        fitted if math.isfinite(p.tau_leak) else "diagnose: no charge leakage found")
    return m
