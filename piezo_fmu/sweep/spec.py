"""The sweep specification: a TOML file naming a base model, an experiment, metrics and what varies.

::

    [sweep]
    model = "../models/paper.toml"    # base model file, relative to this file (default: the paper's)
    seed = 2021                        # seed of the random draws
    count = 1000                       # random draws (production units) per grid point

    [experiment]                       # one closed-loop run (fields: EXPERIMENT)
    signal = "sine"
    freq = 10.0                        # Hz; a bare number is in the field's unit, or
    amplitude = { value = 45.0, unit = "V" }    # with its unit, which is checked
    mode = "ff+fb"

    [metrics]                          # what is computed from each run (fields: METRICS)
    tolerance = { metric = "rms_um", max = 0.05 }

    [grid]                             # the Cartesian product of these axes
    "experiment.freq" = { start = 0.5, stop = 200.0, num = 12, log = true }
    "experiment.mode" = ["ff", "ff+fb"]

    [random]                           # drawn per unit from (seed, unit index)
    "hysteresis.weights" = { tolerance_pct = 20 }          # every element, +-20 %
    "amplifier.R" = { normal = [400.0, 20.0], unit = "ohm" }

A varied key is an experiment field (``experiment.freq``) or a model-file parameter named like the
FMU parameters: ``amplifier.R``, ``hysteresis.weights[3]`` (1-based), or a whole list
(``hysteresis.weights``, random draws only: each element drawn on its own). Values are in the
model file's unit of that parameter.

:func:`load_spec` validates like a model file: an unknown section, field or key, a wrong type,
unit or value, a list index out of range, a grid value the model rejects, raise
:class:`SpecError` (a :class:`~piezo_fmu.errors.UserError`: the command exits 2) naming the file
and the key.
"""
from __future__ import annotations

import hashlib
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..model import DEFAULT_MODEL, ModelError, dump_model, load_model, loads_model
from .axes import Axis, Draw, grid_axis, random_draw
from .fields import EXPERIMENT, MAX_RUNS, METRICS, SWEEP, Field, SpecError, check_field, read_section
from .metrics import METRIC_NAMES
from .metrics import UNITS as METRIC_UNITS

__all__ = ["EXPERIMENT", "METRICS", "METRIC_NAMES", "SWEEP", "Axis", "Draw", "Field", "SpecError", "SweepSpec",
           "Tolerance", "load_spec", "loads_spec"]


@dataclass(frozen=True)
class Tolerance:
    """A pass/fail limit on one metric (``min`` and/or ``max``; ``stable``: must be true)."""

    metric: str
    min: float | None = None
    max: float | None = None

    def describe(self) -> str:
        unit = METRIC_UNITS.get(self.metric) or ""
        if self.metric == "stable":
            return "stable"
        parts = []
        if self.min is not None:
            parts.append(f"{self.metric} >= {self.min:g} {unit}".strip())
        if self.max is not None:
            parts.append(f"{self.metric} <= {self.max:g} {unit}".strip())
        return " and ".join(parts)


@dataclass(frozen=True)
class SweepSpec:
    """A validated sweep: everything a worker needs to compute any run, with the base model as
    TOML text (``model_text``) so that workers need no files.

    ``n_runs = n_grid * count`` runs; run ``i`` is grid point ``i // count`` (axes in file order,
    the last fastest) with the random draw ``i % count`` (the same unit at every grid point).
    """

    name: str
    description: str
    origin: str
    model_origin: str
    model_text: str
    seed: int
    count: int
    experiment: dict
    metrics: dict
    grid: tuple
    draws: tuple
    tolerance: Tolerance | None
    raw: dict = field(compare=False, repr=False)

    @property
    def n_grid(self) -> int:
        return int(np.prod([len(a.values) for a in self.grid])) if self.grid else 1

    @property
    def n_runs(self) -> int:
        return self.n_grid * self.count

    @property
    def metric_names(self) -> tuple:
        return tuple(self.metrics["names"])

    @property
    def hash(self) -> str:
        """Changes whenever a run's result could: the spec's content and the base model."""
        text = json.dumps({"raw": self.raw, "model": self.model_text}, sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def base_model(self):
        """The base :class:`~piezo_fmu.model.Model` (parsed from ``model_text``)."""
        return loads_model(self.model_text, self.model_origin)


# -- the file ---------------------------------------------------------------------------------------

def loads_spec(text, origin="<spec>", base_dir=None) -> SweepSpec:
    """Parse and validate spec text; ``base_dir`` resolves ``[sweep] model`` (default: cwd)."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{origin}: not valid TOML: {exc}") from None
    known = ("sweep", "experiment", "metrics", "grid", "random")
    for name, value in raw.items():
        if name not in known:
            raise SpecError(f"{origin}: [{name}]: unknown section (known: {', '.join(known)})")
        if not isinstance(value, dict):
            raise SpecError(f"{origin}: {name}: expected a table [{name}], got a value")
    sweep = read_section(raw, "sweep", SWEEP, origin)
    experiment = read_section(raw, "experiment", EXPERIMENT, origin)
    metrics = read_section(raw, "metrics", METRICS, origin)

    # the base model
    if sweep["model"]:
        path = Path(sweep["model"]).expanduser()
        if not path.is_absolute():
            path = Path(base_dir or ".") / path
        try:
            base = load_model(path)
        except ModelError as exc:
            raise SpecError(f"{origin}: sweep.model: {exc}") from None
        model_origin = str(path)
    else:
        base = load_model(DEFAULT_MODEL)
        model_origin = str(DEFAULT_MODEL)
    model_text = dump_model(base)

    # the experiment, checked as far as it can be without a run
    e = experiment
    periodic = e["signal"] in ("sine", "triangle")
    if e["periods"] is not None and e["stop_time"] is not None:
        raise SpecError(f"{origin}: experiment.periods and experiment.stop_time: give one, not both")
    if e["periods"] is not None and not periodic:
        raise SpecError(f"{origin}: experiment.periods: a {e['signal']} has no period; give stop_time")
    if e["fmu_dir"] is not None and e["engine"] != "cosim":
        raise SpecError(f"{origin}: experiment.fmu_dir: only with engine = \"cosim\"")
    if e["fmu_dir"] is not None and not Path(e["fmu_dir"]).expanduser().is_absolute():
        e["fmu_dir"] = str(Path(base_dir or ".") / Path(e["fmu_dir"]).expanduser())

    # metrics
    if metrics["skip_periods"] and metrics["skip_time"]:
        raise SpecError(f"{origin}: metrics.skip_periods and metrics.skip_time: give one, not both")
    tolerance = None
    if metrics["tolerance"] is not None:
        t = metrics["tolerance"]
        where = f"{origin}: metrics.tolerance"
        extra = set(t) - {"metric", "min", "max"}
        if extra:
            raise SpecError(f"{where}: unknown field(s) {', '.join(sorted(extra))} (metric, min, max)")
        if "metric" not in t:
            raise SpecError(f"{where}: missing metric (one of {', '.join(METRIC_NAMES)})")
        name = check_field(f"{where}.metric", Field(None, "str", choices=METRIC_NAMES), t["metric"])
        lo = check_field(f"{where}.min", Field(None), t["min"]) if "min" in t else None
        hi = check_field(f"{where}.max", Field(None), t["max"]) if "max" in t else None
        if name != "stable" and lo is None and hi is None:
            raise SpecError(f"{where}: give max and/or min for {name}")
        if lo is not None and hi is not None and not hi >= lo:
            raise SpecError(f"{where}: max {hi} is below min {lo}")
        if name not in metrics["names"]:
            raise SpecError(f"{where}.metric: {name} is not among metrics.names")
        tolerance = Tolerance(name, lo, hi)

    # what varies
    grid = tuple(grid_axis(k, v, base, origin) for k, v in raw.get("grid", {}).items())
    draws = []
    for k, v in raw.get("random", {}).items():
        d = random_draw(k, v, base, origin)
        if d.kind == "tolerance" and k.startswith("experiment."):
            nominal = experiment[k.split(".", 1)[1]]
            if nominal is None:
                raise SpecError(f"{origin}: [random] {k}: tolerance_pct needs a base value in [experiment]")
            d = Draw(d.key, d.kind, d.a, d.b, nominal, None)
        draws.append(d)
    draws = tuple(draws)
    keys = [k for a in grid for k in a.keys] + [d.key for d in draws]
    seen = {}
    for k in keys:
        whole = k.split("[", 1)[0]
        for other in seen:
            if other == k or (whole == other.split("[", 1)[0] and ("[" not in k or "[" not in other)):
                raise SpecError(f"{origin}: {k}: varied twice (also as {other})")
        seen[k] = True
    if draws and sweep["count"] is None:
        raise SpecError(f"{origin}: sweep.count: missing: the number of random draws (units) per grid point")
    count = sweep["count"] if sweep["count"] is not None else 1
    if count > 1 and not draws:
        raise SpecError(f"{origin}: sweep.count: {count} draws but [random] is empty (the runs would "
                        "be identical)")
    if periodic is False and any("experiment.periods" in a.keys for a in grid):
        raise SpecError(f"{origin}: experiment.periods: a {e['signal']} has no period")
    spec = SweepSpec(name=sweep["name"] or Path(origin).stem, description=sweep["description"],
                     origin=origin, model_origin=model_origin, model_text=model_text, seed=sweep["seed"],
                     count=count, experiment=experiment, metrics=metrics, grid=grid, draws=draws,
                     tolerance=tolerance, raw=raw)
    if spec.n_runs > MAX_RUNS:
        raise SpecError(f"{origin}: {spec.n_runs} runs; at most {MAX_RUNS}")
    return spec


def load_spec(path) -> SweepSpec:
    """Load and validate a sweep specification file (see the module docstring)."""
    path = Path(path)
    if not path.exists():
        raise SpecError(f"{path}: sweep specification not found")
    if path.is_dir():
        raise SpecError(f"{path}: is a directory, expected a .toml sweep specification")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise SpecError(f"{path}: not a text file (expected a TOML sweep specification)") from None
    return loads_spec(text, str(path), base_dir=path.parent)
