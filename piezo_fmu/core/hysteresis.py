"""Play operators and the Prandtl-Ishlinskii (PI) hysteresis model, with its analytic inverse.

Conventions (Shan et al. 2021, eqs. 8-17):

* A play operator with threshold ``r >= 0`` maps an input ``v(t)`` to
  ``z(t) = max(v(t) - r, min(v(t) + r, z(t-)))``, i.e. the previous output clamped to
  ``[v - r, v + r]``. The initial state is ``z = 0`` ("initially relaxed").
* The PI model is ``Pi[v] = sum_i w_i F_{r_i}[v]`` with ascending thresholds and ``r_0 = 0``;
  the ``r_0 = 0`` operator is the identity, so ``w_0`` is the paper's ``q``.
* Physical scaling: the model input ``u`` [V] is normalised by ``in_scale`` [V] and the output is
  multiplied by ``out_scale`` [um]: ``x = out_scale * Pi[u / in_scale]``.

The inverse of a PI model is again a PI model (paper eqs. 13-17, sign restored):
``r^_j = sum_{i<j} w_i (r_j - r_i)`` (the initial loading curve at ``r_j``),
``w^_0 = 1 / w_0`` and ``w^_j = -w_j / (W_j W_{j-1})`` with ``W_j = sum_{i<=j} w_i``.
It is exact (to round-off) for any input that starts from the relaxed state, provided every
``W_j > 0``.

Everything here needs only NumPy, so the module can be bundled into an FMU.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "pi_step",
    "pi_table",
    "pi_state",
    "pi_tail",
    "pi_memory",
    "pi_save",
    "pi_load",
    "play_scan",
    "PrandtlIshlinskii",
    "Hysteresis",
]


def pi_table(r, w):
    """The weights table of :func:`pi_step`: ``w_0..w_{n-1}``, then the prefix sums
    ``W_m = sum_{i<m} w_i`` and ``S_m = sum_{i<m} w_i r_i`` for ``m = 0..n`` (length ``3n + 2``)."""
    n = len(r)
    table = [float(x) for x in w]
    wsum, ssum = [0.0], [0.0]
    for i in range(n):
        wsum.append(wsum[-1] + table[i])
        ssum.append(ssum[-1] + table[i] * float(r[i]))
    return table + wsum + ssum


def pi_state(n):
    """The relaxed memory of :func:`pi_step` for ``n`` operators (every output 0, never moved)."""
    return [0.0] * (n + 4)


def pi_tail(w, z, m, n):
    """``sum_{i>=m} w_i z_i``: the part of the output held by the operators that do not follow
    the input (always summed in this order, so the value is a function of the memory)."""
    t = 0.0
    for i in range(m, n):
        t += w[i] * z[i]
    return t


def pi_step(v, r, w, z):
    """Advance every play operator to input ``v`` and return ``sum_i w_i z_i``.

    ``r``: the ``n`` thresholds, ascending with ``r_0 = 0``; ``w``: the weights table of
    :func:`pi_table`; ``z``: the memory, ``n + 4`` values ``[z_0 .. z_{n-1}, v, m, d, T]``
    (:func:`pi_state`), updated in place. Python lists in CPython, NumPy arrays under numba.

    The operators that move form a prefix: the memory of a PI model is 1-Lipschitz in the
    threshold (``|z_i - z_j| <= r_j - r_i``; true of the relaxed state and kept by every step), so
    ``z_i + r_i`` (and ``z_i - r_i``) is non-decreasing in ``i`` and a rising input ``v`` catches
    the operators ``z_i < v - r_i`` from ``i = 0`` up to the first that it does not catch (falling:
    ``z_i > v + r_i``). The ``m`` caught operators then *follow* the input, ``z_i = v - d r_i``
    (``d`` = +1 rising, -1 falling), until the input turns; only then are their outputs written
    back ("materialised"). The output is ``v W_m - d S_m + T`` with ``T = sum_{i>=m} w_i z_i``
    (recomputed by :func:`pi_tail` when ``m`` changes). A step therefore costs O(1) unless the
    input turns or catches another operator (O(n), a few times per half cycle), and the result is
    that of clamping every operator to ``[v - r_i, v + r_i]`` (to round-off in the sum).
    No allocation: this is the per-step kernel.
    """
    n = len(r)
    vl = z[n]
    m = int(z[n + 1])
    d = z[n + 2]
    if v != vl:
        s = 1.0 if v > vl else -1.0
        moved = False
        if s != d:                               # the input turns: materialise the followers
            for i in range(m):
                z[i] = vl - d * r[i]
            m = 0
            d = s
            z[n + 2] = s
            moved = True
        while m < n and s * (v - s * r[m] - z[m]) > 0.0:
            m += 1
            moved = True
        if moved:
            z[n + 1] = float(m)
            z[n + 3] = pi_tail(w, z, m, n)
        z[n] = v
    return v * w[n + m] - d * w[2 * n + 1 + m] + z[n + 3]


def pi_memory(r, z):
    """The operator outputs ``[z_0 .. z_{n-1}]`` of a :func:`pi_step` memory (followers written out)."""
    n = len(r)
    vl, m, d = z[n], int(z[n + 1]), z[n + 2]
    return [vl - d * r[i] if i < m else z[i] for i in range(n)]


def pi_save(r, z):
    """The memory as plain data: the operator outputs, then ``[v, m, d]`` (``T`` is derived)."""
    n = len(r)
    return pi_memory(r, z) + [z[n], z[n + 1], z[n + 2]]


def pi_load(r, w, z, saved):
    """Restore :func:`pi_save` data into ``z`` (in place) for the weights table ``w``.

    Also accepts the ``n`` operator outputs alone (no follower information: ``v = z_0``).
    ``T`` is recomputed with :func:`pi_tail`, so a restored memory continues bit for bit, and
    continues correctly when the weights have changed since it was saved.
    """
    n = len(r)
    saved = [float(x) for x in saved]
    if len(saved) == n:
        saved = saved + [saved[0], 0.0, 0.0]
    if len(saved) != n + 3:
        raise ValueError(f"hysteresis state needs {n} or {n + 3} values, got {len(saved)}")
    m = int(saved[n + 1])
    if not (0 <= m <= n and saved[n + 1] == m and saved[n + 2] in (-1.0, 0.0, 1.0)):
        raise ValueError(f"hysteresis state: invalid follower count {saved[n + 1]!r} or direction "
                         f"{saved[n + 2]!r}")
    z[:n + 3] = saved
    z[n + 3] = pi_tail(w, z, m, n)


def play_scan(v, r, z0=None):
    """Outputs of all play operators for a whole input sequence, vectorised over time and operators.

    Parameters
    ----------
    v : array_like, shape (N,)
        Normalised input sequence.
    r : array_like, shape (n,)
        Thresholds (>= 0).
    z0 : array_like, shape (n,), optional
        Operator state before the first sample (default: relaxed, zeros).

    Returns
    -------
    ndarray, shape (N, n)
        ``z[k, i]`` = output of operator ``i`` after sample ``k``.

    Notes
    -----
    One play step is the clamp ``z -> clamp(z, v_k - r, v_k + r)``. Clamps compose into clamps:
    applying ``[a, b]`` then ``[c, d]`` equals the clamp ``[clamp(a, c, d), clamp(b, c, d)]``.
    The composition is associative, so the whole sequence is an inclusive prefix scan, computed
    here by recursive doubling in ``ceil(log2 N)`` vectorised passes.
    """
    v = np.asarray(v, dtype=float)
    r = np.asarray(r, dtype=float)
    if v.ndim != 1:
        raise ValueError("play_scan: input must be one-dimensional")
    lo = v[:, None] - r[None, :]
    hi = v[:, None] + r[None, :]
    n_t = v.shape[0]
    d = 1
    while d < n_t:
        # combine earlier composite (k - d) with later composite (k): earlier first, then later.
        new_lo = np.clip(lo[:-d], lo[d:], hi[d:])
        new_hi = np.clip(hi[:-d], lo[d:], hi[d:])
        lo[d:] = new_lo
        hi[d:] = new_hi
        d *= 2
    start = np.zeros(r.shape) if z0 is None else np.asarray(z0, dtype=float)
    return np.clip(start[None, :], lo, hi)


@dataclass(frozen=True)
class PrandtlIshlinskii:
    """A classical Prandtl-Ishlinskii model ``x = out_scale * sum_i w_i F_{r_i}[u / in_scale]``.

    Parameters
    ----------
    thresholds : sequence of float
        Ascending thresholds ``r_i`` in normalised input units; the first must be 0.
    weights : sequence of float
        Weights ``w_i`` (dimensionless); ``w_0 > 0`` and every partial sum ``W_j > 0``
        (the model is then strictly increasing on its loading curve, hence invertible).
    in_scale : float
        Input normalisation [input unit, e.g. V].
    out_scale : float
        Output scale [output unit, e.g. um per PI unit].
    """

    thresholds: tuple
    weights: tuple
    in_scale: float = 1.0
    out_scale: float = 1.0
    _r: np.ndarray = field(init=False, repr=False, compare=False)
    _w: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        r = np.asarray(self.thresholds, dtype=float)
        w = np.asarray(self.weights, dtype=float)
        object.__setattr__(self, "thresholds", tuple(float(x) for x in r))
        object.__setattr__(self, "weights", tuple(float(x) for x in w))
        problem = self.problem()
        if problem:
            raise ValueError(problem)
        object.__setattr__(self, "_r", r)
        object.__setattr__(self, "_w", w)

    def problem(self):
        """Return a sentence describing why the parameters are invalid, or ``""``."""
        r, w = np.asarray(self.thresholds), np.asarray(self.weights)
        if r.ndim != 1 or r.size == 0:
            return "thresholds must be a non-empty list"
        if w.shape != r.shape:
            return f"weights has {w.size} entries but thresholds has {r.size}"
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(w))):
            return "thresholds and weights must be finite"
        if r[0] != 0.0:
            return "the first threshold must be 0 (the identity operator carries the paper's q)"
        if np.any(np.diff(r) <= 0):
            return "thresholds must be strictly increasing"
        partial = np.cumsum(w)
        if np.any(partial <= 0):
            j = int(np.argmax(partial <= 0))
            return (f"partial weight sum W_{j} = {partial[j]:.6g} <= 0: the loading curve is not "
                    "increasing, so the model is not invertible")
        for name, s in (("in_scale", self.in_scale), ("out_scale", self.out_scale)):
            if not (math.isfinite(s) and s > 0):
                return f"{name} must be a positive finite number"
        return ""

    @property
    def n(self) -> int:
        """Number of play operators."""
        return len(self.thresholds)

    def loading_curve(self, v):
        """Initial loading curve ``phi(v) = sum_i w_i max(v - r_i, 0)`` (normalised units, v >= 0)."""
        v = np.asarray(v, dtype=float)
        return np.maximum(v[..., None] - self._r, 0.0) @ self._w

    def operators(self, u, z0=None):
        """Operator outputs ``(N, n)`` for input ``u`` [in units], vectorised (see :func:`play_scan`)."""
        return play_scan(np.asarray(u, dtype=float) / self.in_scale, self._r, z0)

    def apply(self, u, z0=None):
        """Model output for the input sequence ``u`` [in units], starting relaxed (or from ``z0``)."""
        return self.out_scale * (self.operators(u, z0) @ self._w)

    def inverse(self) -> "PrandtlIshlinskii":
        """The exact inverse PI model (paper eqs. 13-17), mapping output units back to input units."""
        r, w = self._r, self._w
        partial = np.cumsum(w)
        r_hat = np.array([np.sum(w[:j] * (r[j] - r[:j])) for j in range(r.size)])
        w_hat = np.empty_like(w)
        w_hat[0] = 1.0 / w[0]
        w_hat[1:] = -w[1:] / (partial[1:] * partial[:-1])
        return PrandtlIshlinskii(tuple(r_hat), tuple(w_hat), in_scale=self.out_scale,
                                 out_scale=self.in_scale)

    def unit(self) -> "Hysteresis":
        """A stateful stepping unit for this model, starting relaxed."""
        return Hysteresis(self)


class Hysteresis:
    """Stateful PI unit: ``step(u)`` advances the operators to input ``u`` and returns the output.

    The state (the play-operator memory, see :func:`pi_step`) is explicit:
    :meth:`get_state` / :meth:`set_state` copy it in and out, :meth:`reset` relaxes it.
    """

    __slots__ = ("model", "_r", "_w", "_z", "_inv_in", "_out")

    def __init__(self, model: PrandtlIshlinskii):
        self.model = model
        self._r = list(model.thresholds)
        self._w = pi_table(model.thresholds, model.weights)
        self._z = pi_state(model.n)
        self._inv_in = 1.0 / model.in_scale
        self._out = model.out_scale

    def reset(self):
        for i in range(len(self._z)):
            self._z[i] = 0.0

    def step(self, u):
        """Advance to input ``u`` [in units]; return the output [out units]."""
        return self._out * pi_step(u * self._inv_in, self._r, self._w, self._z)

    def output(self):
        """Current output without advancing."""
        return self._out * sum(w * z for w, z in zip(self._w, pi_memory(self._r, self._z)))

    def operators(self):
        """The play-operator outputs [normalised input units]."""
        return pi_memory(self._r, self._z)

    def get_state(self):
        return pi_save(self._r, self._z)

    def set_state(self, z):
        pi_load(self._r, self._w, self._z, z)
