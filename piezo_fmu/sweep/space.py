"""The runs of a sweep: grid points times random draws, each computable from its index alone.

Run ``i`` of a :class:`~piezo_fmu.sweep.spec.SweepSpec` is grid point ``g = i // count`` and
draw ``j = i % count``. The grid point is the Cartesian product of the axes in file order, the last
axis fastest. Each random key gets its own generator,
``numpy.random.SeedSequence(seed, spawn_key=(j, crc32(key)))``, so a run's values depend only on
``(seed, j, key)``: not on which worker computes it, in which order, how many runs there are, or
which other keys are drawn. Draw ``j`` is one production unit, the same at every grid point
(common random numbers: differences between grid points are not drowned in unit-to-unit scatter).
"""
from __future__ import annotations

import zlib

import numpy as np

from .spec import EXPERIMENT, Draw, SweepSpec

__all__ = ["columns", "draw_values", "point", "run_values"]


def point(spec: SweepSpec, index: int) -> tuple:
    """``(grid_index, draw_index)`` of run ``index``."""
    if not 0 <= index < spec.n_runs:
        raise IndexError(f"run {index} is not in 0..{spec.n_runs - 1}")
    return divmod(int(index), spec.count)


def _rng(seed, draw, key):
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(draw, zlib.crc32(key.encode()))))


def _sample(d: Draw, rng, n):
    """``n`` values of draw ``d``."""
    if d.kind == "uniform":
        return rng.uniform(d.a, d.b, n)
    if d.kind == "normal":
        return rng.normal(d.a, d.b, n)
    if d.kind == "integers":
        return rng.integers(int(d.a), int(d.b), n, endpoint=True)
    # tolerance: nominal * (1 + u), u uniform in +-x, or normal with 3 sigma = x
    u = rng.normal(0.0, d.a / 3.0, n) if d.b else rng.uniform(-d.a, d.a, n)
    return np.asarray(d.nominal, dtype=float).reshape(-1) * (1.0 + u)


def draw_values(spec: SweepSpec, draw: int) -> dict:
    """The random values of unit ``draw``: ``{key: value}``, whole lists as elements ``key[i]``."""
    out = {}
    for d in spec.draws:
        rng = _rng(spec.seed, draw, d.key)
        if d.size is None:
            v = _sample(d, rng, 1)[0]
            out[d.key] = int(v) if d.kind == "integers" else float(v)
        else:
            vs = _sample(d, rng, d.size)
            for i, v in enumerate(vs, 1):
                out[f"{d.key}[{i}]"] = float(v)
    return out


def run_values(spec: SweepSpec, index: int) -> dict:
    """Every varied value of run ``index``: grid keys (file order), then the random ones."""
    g, j = point(spec, index)
    out = {}
    for axis, k in zip(spec.grid, np.unravel_index(g, [len(a.values) for a in spec.grid]) if spec.grid else ()):
        out.update(axis.at(int(k)))
    out.update(draw_values(spec, j))
    return out


def columns(spec: SweepSpec) -> list:
    """``[(name, kind)]`` of the varied values (kind: float, int, str or bool), as in
    :func:`run_values`; the results table has one column each."""
    from ..model import key_spec

    out = []
    for key in [k for a in spec.grid for k in a.keys] + [d.key for d in spec.draws]:
        d = next((d for d in spec.draws if d.key == key), None)
        if d is not None and d.size is not None:
            out += [(f"{key}[{i}]", "float") for i in range(1, d.size + 1)]
            continue
        if key.startswith("experiment."):
            kind = EXPERIMENT[key.split(".", 1)[1]].kind
        else:
            kind = key_spec(key).kind
        if d is not None:
            kind = "int" if d.kind == "integers" else "float"
        out.append((key, kind))
    return out
