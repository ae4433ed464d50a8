"""Linear time-invariant blocks: exact discretisation and a stateful stepping unit (NumPy only).

Continuous systems are given as transfer functions ``num(s)/den(s)`` (coefficients in descending
powers of ``s``) or as state-space matrices. :func:`discretize` returns the exact discrete
equivalent for an input that is held (``"zoh"``), linearly interpolated (``"foh"``) or moved along
a first-order lag (``"lag"``) over the step::

    x[k+1] = Phi x[k] + G0 u[k] + G1 u[k+1]        (G1 = 0 for "zoh")
    y[k]   = C x[k] + D u[k]

The matrix exponential is computed here (balancing, then scaling and squaring of a Taylor series)
so that FMUs need nothing beyond NumPy on the target host; the tests check it against SciPy.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["balance", "expm", "tf2ss", "discretize", "is_hurwitz", "LinearSystem", "lti_advance", "same_step",
           "as_floats", "TINY"]

STEP_RTOL = 1e-9

# A state that decays towards zero (an input back at exactly zero) ends in subnormal doubles,
# where its coarse rounding holds it in a limit cycle for good, and each operation on a subnormal
# costs some hundred cycles on an Intel Xeon (stop 62: the monolithic model 4.3x slower after a
# pulse back to 0 V than with the command held at 1e-200 V). Every state of the core whose
# magnitude falls below TINY is therefore zero (its value is physically nothing: 1e-290 um or V).
TINY = 1e-290


def as_floats(seq):
    """Plain Python floats: unit data are lists, or NumPy views under the compiled engine."""
    return [float(v) for v in seq]


def same_step(h, cached):
    """True when ``h`` equals the cached step to 1e-9 relative: masters that compute steps as
    differences of grid times (fmpy: ``t[n+1] - t[n]``) jitter in the last bits, and re-discretising
    for every jittered step would cost far more than the ~1e-9 relative coefficient change."""
    return cached is not None and abs(h - cached) <= STEP_RTOL * cached


def balance(a):
    """``(b, d)`` with ``b = diag(d)^-1 a diag(d)``: rows and columns of ``a`` brought to comparable
    norms by powers of two (Parlett and Reinsch's iteration, as LAPACK's ``gebal`` without
    permutations), so ``b`` is similar to ``a`` and the scaling is exact in floating point.

    A companion matrix of a stiff chain (the mechanics' first mode at 15 kHz times a further mode
    at 8.6 kHz: coefficients from 1 to 3e19 s^-4) has a norm many orders above its eigenvalues;
    scaling and squaring would then square ~50 times and lose every digit.
    """
    b = np.array(a, dtype=float)
    n = b.shape[0]
    d = np.ones(n)
    for _ in range(64):
        done = True
        for i in range(n):
            c = float(np.sum(np.abs(b[:, i]))) - abs(b[i, i])
            r = float(np.sum(np.abs(b[i, :]))) - abs(b[i, i])
            if c == 0.0 or r == 0.0 or not (math.isfinite(c) and math.isfinite(r)):
                continue            # (a non-finite row or column would never balance)
            total = c + r
            f = 1.0
            while c < r / 2.0:
                f *= 2.0
                c *= 4.0
            while c >= r * 2.0:
                f /= 2.0
                c /= 4.0
            if (c + r) / f < 0.95 * total:
                done = False
                d[i] *= f
                b[i, :] /= f
                b[:, i] *= f
        if done:
            break
    return b, d


def expm(a):
    """Matrix exponential of a small square matrix (balanced by :func:`balance`, then scaling and
    squaring of a Taylor series of order 18)."""
    a = np.asarray(a, dtype=float)
    if a.ndim != 2 or a.shape[0] != a.shape[1]:
        raise ValueError("expm needs a square matrix")
    if not np.all(np.isfinite(a)):
        raise ValueError("expm needs a finite matrix")
    a, d = balance(a)
    # exp(D^-1 A D) = D^-1 exp(A) D, so exp(A) = D exp(B) D^-1 (powers of two: exact)
    return _expm_taylor(a) * d[:, None] / d[None, :]


def _expm_taylor(a):
    norm = np.max(np.sum(np.abs(a), axis=1)) if a.size else 0.0
    squarings = max(0, int(math.ceil(math.log2(norm / 0.25)))) if norm > 0.25 else 0
    scaled = a / (2.0 ** squarings)
    result = np.eye(a.shape[0])
    term = np.eye(a.shape[0])
    for k in range(1, 19):
        term = term @ scaled / k
        result = result + term
    for _ in range(squarings):
        result = result @ result
    return result


def tf2ss(num, den):
    """Controllable canonical state-space ``(A, B, C, D)`` of a proper transfer function."""
    num = np.atleast_1d(np.asarray(num, dtype=float))
    den = np.atleast_1d(np.asarray(den, dtype=float))
    den = np.trim_zeros(den, "f")
    if den.size == 0 or den[0] == 0:
        raise ValueError("transfer function denominator is zero")
    num = np.trim_zeros(num, "f") if np.any(num) else np.zeros(1)
    if num.size > den.size:
        raise ValueError("transfer function is improper (numerator degree > denominator degree)")
    num, den = num / den[0], den / den[0]
    n = den.size - 1
    num = np.concatenate([np.zeros(den.size - num.size), num])
    d = num[0]
    if n == 0:
        return np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), np.array([[d]])
    a = np.zeros((n, n))
    a[0, :] = -den[1:]
    a[1:, :-1] = np.eye(n - 1)
    b = np.zeros((n, 1))
    b[0, 0] = 1.0
    c = (num[1:] - d * den[1:]).reshape(1, n)
    return a, b, c, np.array([[d]])


def is_hurwitz(den) -> bool:
    """True when every root of the polynomial ``den`` has a negative real part."""
    den = np.trim_zeros(np.asarray(den, dtype=float), "f")
    if den.size <= 1:
        return True
    return bool(np.all(np.real(np.roots(den)) < 0))


def discretize(a, b, h, method="foh", tau=0.0):
    """Exact discretisation of ``x' = A x + B u`` over a step ``h`` [s].

    Returns ``(Phi, G0, G1)`` with ``x[k+1] = Phi x[k] + G0 u[k] + G1 u[k+1]``.
    ``method="zoh"`` holds ``u[k]`` over the step (``G1 = 0``); ``"foh"`` interpolates linearly;
    ``"lag"`` moves the input from ``u[k]`` to ``u[k+1]`` along a first-order lag of time constant
    ``tau`` [s], ``u[k] + (u[k+1] - u[k]) (1 - exp(-t / tau)) / (1 - exp(-h / tau))``: the path of
    a stroke behind an amplifier of that lag driven by a held command (``tau`` far below ``h``: the
    new value over the whole step; far above: the straight line of ``"foh"``).
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float).reshape(a.shape[0], -1)
    n, m = b.shape
    if not (h > 0 and math.isfinite(h)):
        raise ValueError(f"step must be positive and finite, got {h!r}")
    if method == "lag" and not (tau >= 0 and math.isfinite(tau)):
        raise ValueError(f"the lag of the input's path must be >= 0 and finite [s], got {tau!r}")
    # Block matrix [[A, B, 0], [0, 0, I/h], [0, 0, 0]] * h: its exponential holds
    # Phi, the integral of e^{As}B, and the first moment needed for the ramp input.
    big = np.zeros((n + 2 * m, n + 2 * m))
    big[:n, :n] = a * h
    big[:n, n:n + m] = b * h
    big[n:n + m, n + m:] = np.eye(m)
    e = expm(big)
    phi = e[:n, :n]
    gam1 = e[:n, n:n + m]          # int_0^h e^{A s} ds B
    gam2 = e[:n, n + m:]           # int_0^h e^{A s} (h - s)/h ds B
    if method == "zoh":
        return phi, gam1, np.zeros_like(gam1)
    if method == "foh" or (method == "lag" and tau > 1e8 * h):
        return phi, gam1 - gam2, gam2
    if method == "lag":
        lam = min(h / tau, 1e5) if tau > 0 else 1e5
        # [[A, B, 0], [0, -I/tau, I/tau], [0, 0, 0]] * h: the middle state v rises as 1 - e^{-t/tau}
        # from 0 towards the held last one; the top right block is int_0^h e^{A (h - t)} B v(t) dt,
        # with no difference of nearly equal terms at any ratio h / tau
        big[:n, n + m:] = 0.0
        big[n:n + m, n:n + m] = -lam * np.eye(m)
        big[n:n + m, n + m:] = lam * np.eye(m)
        rise = expm(big)[:n, n + m:]
        g1 = rise / -math.expm1(-lam)
        return phi, gam1 - g1, g1
    raise ValueError(f"unknown discretisation method {method!r}")


def lti_advance(phi, g, cd, xs, u, tmp):
    """Advance an LTI block whose input moves linearly from its previous value to ``u``.

    Flat, row-major data (no row views: cheap in CPython, no reference counting in numba):
    ``phi``: n*n; ``g``: 2n (G0 then G1); ``cd``: n + 1 (C then D); ``xs``: n + 1 (state then
    previous input), updated in place; ``tmp``: scratch of length n. Returns ``C x + D u``.
    Orders 0-2 (gains, first-order filters, the mechanics) have unrolled paths with the generic
    summation order. A state below :data:`TINY` in magnitude is set to zero.
    """
    n = len(tmp)
    u0 = xs[n]
    if n == 0:
        xs[0] = u
        return cd[0] * u
    if n == 1:
        a = g[0] * u0 + g[1] * u + phi[0] * xs[0]
        if abs(a) < TINY:
            a = 0.0
        xs[0] = a
        xs[1] = u
        return cd[1] * u + cd[0] * a
    if n == 2:
        x0 = xs[0]
        x1 = xs[1]
        a = g[0] * u0 + g[2] * u + phi[0] * x0 + phi[1] * x1
        b = g[1] * u0 + g[3] * u + phi[2] * x0 + phi[3] * x1
        if abs(a) < TINY:
            a = 0.0
        if abs(b) < TINY:
            b = 0.0
        xs[0] = a
        xs[1] = b
        xs[2] = u
        return cd[2] * u + cd[0] * a + cd[1] * b
    for i in range(n):
        acc = g[i] * u0 + g[n + i] * u
        base = i * n
        for j in range(n):
            acc += phi[base + j] * xs[j]
        tmp[i] = acc if abs(acc) >= TINY else 0.0
    y = cd[n] * u
    for i in range(n):
        xs[i] = tmp[i]
        y += cd[i] * tmp[i]
    xs[n] = u
    return y


class LinearSystem:
    """A stateful single-input single-output LTI block with explicit, flat state.

    Parameters
    ----------
    num, den : sequence of float
        Transfer function coefficients, descending powers of ``s`` (proper).
    method : {"foh", "zoh", "lag"}
        How the input moves within a step: linearly from the previous value (``"foh"``), held
        at the new value (``"zoh"``) or along a first-order lag from the previous value to the new
        one (``"lag"``, see :func:`discretize`).
    tau : float
        The time constant of that lag [s] (``"lag"`` only).

    ``step(u, h)`` advances ``h`` seconds and returns the output at the end of the step. The
    discrete data (``phi`` n*n row-major, ``g`` = G0 then G1, ``cd`` = C then D) and the state
    (``xs`` = x then the previous input; ``tmp`` scratch) are plain lists, used directly by the
    :func:`lti_advance` kernel (also compiled by numba for the monolithic model).
    """

    __slots__ = ("num", "den", "method", "tau", "a", "b", "phi", "g", "cd", "xs", "tmp", "h")

    def __init__(self, num, den, method="foh", tau=0.0):
        if method not in ("foh", "zoh", "lag"):
            raise ValueError(f"unknown discretisation method {method!r}")
        self.tau = float(tau)
        self.num = [float(v) for v in np.atleast_1d(num)]
        self.den = [float(v) for v in np.atleast_1d(den)]
        self.method = method
        a, b, c, d = tf2ss(self.num, self.den)
        self.a, self.b = a, b
        n = a.shape[0]
        self.cd = [float(v) for v in c.ravel()] + [float(d[0, 0])]
        self.xs = [0.0] * (n + 1)
        self.tmp = [0.0] * n
        self.phi = [0.0] * (n * n)
        self.g = [0.0] * (2 * n)
        self.h = None

    @property
    def order(self):
        return len(self.tmp)

    def dc_gain(self):
        return self.num[-1] / self.den[-1] if self.den[-1] != 0 else math.inf

    def prepare(self, h):
        """Compute (and cache, see :func:`same_step`) the discrete data for step ``h`` [s]."""
        if same_step(h, self.h):
            return
        n = self.order
        if n:
            phi, g0, g1 = discretize(self.a, self.b, h, self.method, self.tau)
            self.phi[:] = [float(v) for v in phi.ravel()]
            self.g[:] = [float(v) for v in g0.ravel()] + [float(v) for v in g1.ravel()]
        self.h = h

    def settle(self, u):
        """Set the state to the steady state for a constant input ``u``."""
        n = self.order
        if n:
            xs = np.linalg.solve(self.a, -self.b[:, 0] * u)
            self.xs[:n] = [float(v) for v in xs]
        self.xs[n] = float(u)

    reset = settle

    def step(self, u, h):
        if h != self.h:
            self.prepare(h)
        if self.method == "zoh":
            self.xs[self.order] = u        # G1 = 0: the input held over the step is the new one
        return lti_advance(self.phi, self.g, self.cd, self.xs, u, self.tmp)

    def output(self):
        n = self.order
        return sum(self.cd[i] * self.xs[i] for i in range(n)) + self.cd[n] * self.xs[n]

    def get_state(self):
        return list(self.xs)

    def set_state(self, s):
        if len(s) != len(self.xs):
            raise ValueError(f"linear block state needs {len(self.xs)} values, got {len(s)}")
        self.xs[:] = [float(v) for v in s]
