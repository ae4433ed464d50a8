"""Krasnosel'skii-Pokrovskii (KP) cells: a Preisach term beside the Prandtl-Ishlinskii model.

A PI model can only draw loops whose shape depends on the distance from the last reversal
(Masing's rule: every minor loop congruent with the initial loading curve, whatever its level).
Real stacks also have loop features tied to absolute voltages: a loop width that changes with
the level, domains that switch in a band of field, a high-field knee. The classical Preisach
model draws them with relays that switch up at ``alpha`` and down at ``beta <= alpha``; the KP
cell is such a relay with both switchings spread over a ramp of width ``w`` (continuous in the
input, so a weighted sum of cells is a smooth rate-independent operator that is linear in its
weights). A cell is exactly the mean of the relays ``(alpha - w + t w, beta + t w)``, ``t``
uniform in (0, 1): those that are up always form the prefix ``t < T``, and ``s = 2 T - 1``:

* cell state ``s`` in [-1, 1]; after every input ``v``
  ``s <- clip(s, lo(v), hi(v))`` with ``lo(v) = clip(2 (v - alpha) / w + 1, -1, 1)`` (the rising
  ramp ends at ``alpha``: above it the cell is up) and ``hi(v) = clip(2 (v - beta) / w - 1, -1, 1)``
  (the falling ramp ends at ``beta``: below it the cell is down); ``alpha - beta >= w`` keeps
  ``lo <= hi``;
* output ``sum_i mu_i s_i``; inputs and ``alpha, beta, w`` in the PI's normalised units
  (``v = ua / u_norm``), weights ``mu_i`` dimensionless like the PI weights (the actuator
  multiplies the sum of both by ``hysteresis.scale``).

The relaxed (demagnetised) state at ``v = 0`` is the Preisach staircase ``alpha + beta = 0``:
each of a cell's relays is up when ``alpha' + beta' <= 0`` (``s = clip(-(alpha + beta) / w, -1,
1)``: a cell centred above zero is down, one centred below is up), then every cell is moved to
``v = 0``.
That is the state of a PI model's relaxed operators (``z = 0``): both start from the same virgin
curve, and the output is counted from there (a constant in the table makes it 0 at rest). Monotone input paths may be jumped in one step (the clip of a monotone ramp): a preparation
sweep up to ``v_top`` and back is two steps.

Everything here needs only NumPy (the kernel only lists or arrays), so it is bundled into the FMUs
and compiled by :mod:`.compiled` like the other kernels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["kp_step", "kp_relax", "kp_table", "KPCells", "cells_problem", "grid_cells"]


def kp_table(up, down, width, weights):
    """The cell table of :func:`kp_step`: ``[alpha..., beta..., w..., mu..., c0]`` (length
    ``4 m + 1``), ``c0`` the offset that makes the relaxed output 0 (as a relaxed PI's)."""
    c = [float(x) for x in up] + [float(x) for x in down] + [float(x) for x in width] \
        + [float(x) for x in weights] + [0.0]
    c[-1] = -kp_relax(c, [0.0] * len(up))
    return c


def kp_step(v, c, s):
    """Move every cell to input ``v`` and return ``sum_i mu_i s_i``.

    ``c``: the cell table of :func:`kp_table` (``4 m + 1`` values); ``s``: the ``m`` cell states,
    updated in place. Python lists in CPython, NumPy arrays under numba. No allocation: this is a
    per-step kernel (``O(m)``; no cells: returns 0).
    """
    m = len(s)
    acc = c[4 * m]
    for i in range(m):
        w = c[2 * m + i]
        lo = 2.0 * (v - c[i]) / w + 1.0
        if lo > 1.0:
            lo = 1.0
        elif lo < -1.0:
            lo = -1.0
        hi = 2.0 * (v - c[m + i]) / w - 1.0
        if hi > 1.0:
            hi = 1.0
        elif hi < -1.0:
            hi = -1.0
        si = s[i]
        if si < lo:
            si = lo
        elif si > hi:
            si = hi
        s[i] = si
        acc += c[3 * m + i] * si
    return acc


def kp_relax(c, s):
    """Put the cells into the relaxed state at ``v = 0`` (in place) and return the output there."""
    m = len(s)
    for i in range(m):
        x = -(c[i] + c[m + i]) / c[2 * m + i]
        s[i] = 1.0 if x > 1.0 else (-1.0 if x < -1.0 else x)
    return kp_step(0.0, c, s)


def grid_cells(lo, hi, n):
    """Cells on a regular Preisach grid over the input range ``[lo, hi]`` (normalised units).

    ``n`` steps of width ``w = (hi - lo) / n``; every corner pair ``alpha > beta`` of the grid with
    ``alpha - beta >= w``, ramps of width ``w``: ``n (n + 1) / 2`` cells that tile the Preisach
    triangle of the range. Returns ``(up, down, width)`` arrays.
    """
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo and n >= 1):
        raise ValueError(f"grid_cells: need lo < hi and n >= 1, got [{lo}, {hi}], n = {n}")
    w = (hi - lo) / n
    g = lo + w * np.arange(n + 1)
    a, b = np.meshgrid(g, g, indexing="ij")
    keep = (a - b) >= w * (1.0 - 1e-9)
    return a[keep], b[keep], np.full(int(keep.sum()), w)


@dataclass(frozen=True)
class KPCells:
    """A weighted set of KP cells (see the module docstring), in normalised input units.

    Parameters
    ----------
    up, down : sequence of float
        Switch-up input ``alpha_i`` and switch-down input ``beta_i`` of each cell [1, units of
        ``u_norm``].
    width : sequence of float
        Ramp width ``w_i > 0`` of each cell [1], with ``alpha_i - beta_i >= w_i``.
    weights : sequence of float
        Weight ``mu_i`` of each cell [1] (any sign: a cell adds to or takes from the loop).
    """

    up: tuple = ()
    down: tuple = ()
    width: tuple = ()
    weights: tuple = ()

    def __post_init__(self):
        for name in ("up", "down", "width", "weights"):
            object.__setattr__(self, name, tuple(float(x) for x in getattr(self, name)))
        problem = self.problem()
        if problem:
            raise ValueError(problem)

    def problem(self):
        """A sentence naming the key that is wrong (``cells_up`` ...), or ``""``."""
        return cells_problem(self.up, self.down, self.width, self.weights)

    @property
    def m(self) -> int:
        """Number of cells."""
        return len(self.up)

    def table(self):
        return kp_table(self.up, self.down, self.width, self.weights)

    def apply(self, v):
        """Output for the normalised input sequence ``v`` from the relaxed state (array)."""
        c = self.table()
        s = [0.0] * self.m
        kp_relax(c, s)
        return np.array([kp_step(float(x), c, s) for x in np.asarray(v, dtype=float)])


def cells_problem(up, down, width, weights):
    """Why a cell set is invalid (naming the model-file key), or ``""``."""
    lens = {len(up), len(down), len(width), len(weights)}
    if len(lens) != 1:
        return (f"cells_up, cells_down, cells_width and cells_weights must have equal lengths "
                f"(got {len(up)}, {len(down)}, {len(width)}, {len(weights)})")
    for name, vals in (("cells_up", up), ("cells_down", down), ("cells_width", width),
                       ("cells_weights", weights)):
        if not all(math.isfinite(float(x)) for x in vals):
            return f"{name}: must be finite"
    for i, (a, b, w) in enumerate(zip(up, down, width)):
        if not w > 0.0:
            return f"cells_width: cell {i} has width {w} <= 0"
        if a - b < w * (1.0 - 1e-9):
            return (f"cells_up: cell {i} switches up at {a} and down at {b}: alpha - beta must be at "
                    f"least its width {w}")
    return ""
