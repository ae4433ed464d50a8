"""Linear time-invariant blocks: exact discretisation and a stateful stepping unit (NumPy only).

Continuous systems are given as transfer functions ``num(s)/den(s)`` (coefficients in descending
powers of ``s``) or as state-space matrices. :func:`discretize` returns the exact discrete
equivalent for an input that is held (``"zoh"``) or linearly interpolated (``"foh"``) over the
step::

    x[k+1] = Phi x[k] + G0 u[k] + G1 u[k+1]        (G1 = 0 for "zoh")
    y[k]   = C x[k] + D u[k]

The matrix exponential is computed here (scaling and squaring of a Taylor series) so that FMUs
need nothing beyond NumPy on the target host; the tests check it against SciPy.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["expm", "tf2ss", "discretize", "is_hurwitz", "LinearSystem", "lti_step", "same_step"]

STEP_RTOL = 1e-9


def same_step(h, cached):
    """True when ``h`` equals the cached step to 1e-9 relative: masters that compute steps as
    differences of grid times (fmpy: ``t[n+1] - t[n]``) jitter in the last bits, and re-discretising
    for every jittered step would cost far more than the ~1e-9 relative coefficient change."""
    return cached is not None and abs(h - cached) <= STEP_RTOL * cached


def expm(a):
    """Matrix exponential of a small square matrix (scaling and squaring, Taylor order 18)."""
    a = np.asarray(a, dtype=float)
    if a.ndim != 2 or a.shape[0] != a.shape[1]:
        raise ValueError("expm needs a square matrix")
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


def discretize(a, b, h, method="foh"):
    """Exact discretisation of ``x' = A x + B u`` over a step ``h`` [s].

    Returns ``(Phi, G0, G1)`` with ``x[k+1] = Phi x[k] + G0 u[k] + G1 u[k+1]``.
    ``method="zoh"`` holds ``u[k]`` over the step (``G1 = 0``); ``"foh"`` interpolates linearly.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float).reshape(a.shape[0], -1)
    n, m = b.shape
    if not (h > 0 and math.isfinite(h)):
        raise ValueError(f"step must be positive and finite, got {h!r}")
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
    if method == "foh":
        return phi, gam1 - gam2, gam2
    raise ValueError(f"unknown discretisation method {method!r}")


def lti_step(phi, g0, g1, x, u0, u1, tmp):
    """Advance a single-input discrete system one step in place (no allocation).

    ``phi`` is ``n x n`` (nested lists or a 2-D array), ``g0``/``g1`` length ``n``; ``tmp`` is a
    scratch buffer of length ``n``.
    """
    n = len(x)
    for i in range(n):
        acc = g0[i] * u0 + g1[i] * u1
        row = phi[i]
        for j in range(n):
            acc += row[j] * x[j]
        tmp[i] = acc
    for i in range(n):
        x[i] = tmp[i]


class LinearSystem:
    """A stateful single-input single-output LTI block stepped at a (cached) step size.

    Parameters
    ----------
    num, den : sequence of float
        Transfer function coefficients, descending powers of ``s`` (proper).
    method : {"foh", "zoh"}
        How the input is interpolated within a step.

    ``step(u, h)`` advances ``h`` seconds and returns the output at the end of the step: with
    ``"foh"`` the input moves linearly from the previous value to ``u``, with ``"zoh"`` ``u`` is
    held over the step. The state (``x`` and the previous input) is explicit.
    """

    __slots__ = ("num", "den", "method", "_a", "_b", "_c", "_d", "_x", "_tmp", "_u", "_h",
                 "_phi", "_g0", "_g1", "_cl", "_dd")

    def __init__(self, num, den, method="foh"):
        self.num = tuple(float(v) for v in np.atleast_1d(num))
        self.den = tuple(float(v) for v in np.atleast_1d(den))
        self.method = method
        a, b, c, d = tf2ss(self.num, self.den)
        self._a, self._b = a, b
        self._cl = [float(v) for v in c.ravel()]
        self._dd = float(d[0, 0])
        n = a.shape[0]
        self._x = [0.0] * n
        self._tmp = [0.0] * n
        self._u = 0.0
        self._h = None

    @property
    def order(self) -> int:
        return len(self._x)

    def dc_gain(self) -> float:
        return self.num[-1] / self.den[-1] if self.den[-1] != 0 else math.inf

    def prepare(self, h):
        """Compute (and cache) the discrete matrices for step ``h``."""
        if not same_step(h, self._h):
            phi, g0, g1 = discretize(self._a, self._b, h, self.method)
            self._phi = [[float(v) for v in row] for row in phi]
            self._g0 = [float(v) for v in g0.ravel()]
            self._g1 = [float(v) for v in g1.ravel()]
            self._h = h

    def reset(self, u=0.0):
        """Put the block at rest in the steady state for a constant input ``u``."""
        n = len(self._x)
        if n:
            xs = np.linalg.solve(self._a, -self._b[:, 0] * u) if u else np.zeros(n)
            self._x[:] = [float(v) for v in xs]
        self._u = float(u)

    def step(self, u, h):
        if h != self._h:
            self.prepare(h)
        u0 = u if self.method == "zoh" else self._u
        lti_step(self._phi, self._g0, self._g1, self._x, u0, u, self._tmp)
        self._u = u
        y = self._dd * u
        c = self._cl
        x = self._x
        for i in range(len(x)):
            y += c[i] * x[i]
        return y

    def output(self):
        y = self._dd * self._u
        for ci, xi in zip(self._cl, self._x):
            y += ci * xi
        return y

    def get_state(self):
        return [*self._x, self._u]

    def set_state(self, s):
        if len(s) != len(self._x) + 1:
            raise ValueError(f"linear block state needs {len(self._x) + 1} values, got {len(s)}")
        self._x[:] = [float(v) for v in s[:-1]]
        self._u = float(s[-1])
