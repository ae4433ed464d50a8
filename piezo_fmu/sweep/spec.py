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
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.control import INVERSES, MODES
from ..errors import UserError
from ..model import (
    DEFAULT_MODEL,
    SCHEMA,
    ModelError,
    dump_model,
    key_spec,
    load_model,
    loads_model,
    split_key,
    with_values,
)
from .metrics import METRIC_NAMES
from .metrics import UNITS as METRIC_UNITS

__all__ = ["EXPERIMENT", "METRICS", "METRIC_NAMES", "SWEEP", "Axis", "Draw", "Field", "SpecError", "SweepSpec",
           "Tolerance", "load_spec", "loads_spec"]

MAX_RUNS = 10_000_000


class SpecError(UserError):
    """A sweep specification is invalid; the message names the file and the key."""


@dataclass(frozen=True)
class Field:
    """One field of a spec section: ``kind`` in float|int|bool|str|strs, its unit, a check."""

    unit: str | None
    kind: str = "float"
    check: str = "finite"
    default: object = None
    doc: str = ""
    choices: tuple = ()
    varies: bool = True


def _num(unit, check, default, doc):
    return Field(unit, "float", check, default, doc)



SWEEP = {
    "name": Field(None, "str", default="", doc="short name (default: the spec file's name)", varies=False),
    "description": Field(None, "str", default="", doc="what the study asks", varies=False),
    "model": Field(None, "str", default=None, varies=False,
                   doc="base model file, relative to the spec file (default: the paper's model)"),
    "seed": Field("1", "int", "nonneg", 0, "seed of the random draws", varies=False),
    "count": Field("1", "int", "positive", None, "random draws (units) per grid point; required with "
                   "[random], 1 without", varies=False),
}

EXPERIMENT = {
    "engine": Field(None, "str", default="monolithic", choices=("monolithic", "cosim"),
                    doc="monolithic: the compiled closed loop (piezo_fmu.simulate); cosim: the three "
                        "FMUs co-simulated (piezo_fmu.cosim.cosimulate)"),
    "kernels": Field(None, "str", default="numba", choices=("numba", "python"),
                     doc="compiled or interpreted kernels (same results); for cosim the FMUs' "
                         "simulation.engine"),
    "signal": Field(None, "str", default="sine", choices=("sine", "step", "triangle", "constant"),
                    doc="reference shape: u_ref = offset + amplitude * shape(2 pi freq t + phase)"),
    "amplitude": _num("V", "finite", 45.0, "reference amplitude (a step's height)"),
    "offset": _num("V", "finite", 45.0, "reference offset (0-90 V with the defaults)"),
    "freq": _num("Hz", "positive", 10.0, "reference frequency (sine, triangle)"),
    "phase": _num("deg", "finite", -90.0, "reference phase (-90: starts at the minimum)"),
    "mode": Field(None, "str", default=None, choices=tuple(MODES),
                  doc="compensation: open | ff | fb | ff+fb (default: the model's)"),
    "inverse": Field(None, "str", default=None, choices=tuple(INVERSES),
                     doc="inverse model: static | dynamic (default: the model's)"),
    "periods": _num("1", "positive", None, "run length in reference periods (default 3 for a sine "
                                           "or triangle; not with stop_time)"),
    "stop_time": _num("s", "positive", None, "run length (default 0.05 s for a step or constant)"),
    "step": _num("s", "positive", None, "internal step of the monolithic model (default: the model's "
                                        "simulation.step)"),
    "control_step": _num("s", "positive", None, "monolithic: sample time of the sensor and "
                                                "compensator, a multiple of step (default: step)"),
    "comm_step": _num("s", "positive", 1e-4, "cosim: communication step"),
    "algorithm": Field(None, "str", default="gauss-seidel", choices=("gauss-seidel", "jacobi"),
                       doc="cosim: coupling algorithm"),
    "samples_per_period": Field("1", "int", "positive", 2000, "recorded samples per reference period "
                                "(at most one per step); the metrics use the recorded samples"),
    "record_step": _num("s", "positive", None, "recording interval instead of samples_per_period "
                                               "(default for a step: stop_time / 5000)"),
    "noise": Field(None, "bool", default=True, doc="include the model's sensor noise"),
    "fmu_dir": Field(None, "str", default=None, varies=False,
                     doc="cosim: folder with Actuator.fmu, Sensor.fmu, Compensator.fmu, where the "
                         "runs execute (default: built from the base model and sent to the workers)"),
}

METRICS = {
    "names": Field(None, "strs", default=METRIC_NAMES, choices=METRIC_NAMES, varies=False,
                   doc="metrics to report (default: all)"),
    "settle_band_pct": _num("%", "positive", 2.0, "settling band, % of the reference span"),
    "skip_periods": _num("1", "nonneg", 0.0, "periods left out of the error metrics at the start"),
    "skip_time": _num("s", "nonneg", 0.0, "time left out of the error metrics at the start"),
    "worst": Field("1", "int", "positive", 10, "worst runs listed in the report", varies=False),
    "tolerance": Field(None, "table", default=None, varies=False,
                       doc="{ metric = NAME, max = LIMIT, min = LIMIT }: a run passes when it "
                           "finished, is stable and the metric is within the limits; the yield is "
                           "the share of runs that pass"),
}

GRID_FIELDS = {"start", "stop", "step", "num", "log", "unit"}
DRAWS = {"uniform": "[low, high]", "normal": "[mean, std]", "integers": "[low, high] (inclusive)",
         "tolerance_pct": "+-x % of the base value"}


@dataclass(frozen=True)
class Axis:
    """One grid axis: ``key`` and its ``values`` (``log``: spaced logarithmically)."""

    key: str
    values: tuple
    log: bool = False


@dataclass(frozen=True)
class Draw:
    """One random draw: ``key``, ``kind`` (uniform | normal | integers | tolerance), parameters
    ``a``, ``b`` (low/high, mean/std; for tolerance: the fraction and 0 uniform / 1 normal),
    the base value(s) ``nominal`` and ``size`` (elements of a whole list, or ``None``)."""

    key: str
    kind: str
    a: float
    b: float
    nominal: object = None
    size: int | None = None


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


# -- values ---------------------------------------------------------------------------------------

def _where(section, key):
    return f"{section}.{key}" if section else key


def _unwrap(where, value, unit):
    """A bare value, or ``{ value = ..., unit = "..." }`` with the unit checked."""
    if isinstance(value, dict) and "value" in value:
        extra = set(value) - {"value", "unit"}
        if extra:
            raise SpecError(f"{where}: unknown field(s) {', '.join(sorted(extra))} (expected value, unit)")
        if "unit" in value and unit is not None and value["unit"] != unit:
            raise SpecError(f"{where}: unit {value['unit']!r} given, expected {unit!r}")
        return value["value"]
    return value


def _check(where, f: Field, value):
    """The normalised value of a field, or :class:`SpecError` naming it."""
    kinds = {"float": "a number", "int": "a whole number", "bool": "true or false", "str": "a string",
             "strs": "a list of strings", "table": "a table { ... }"}
    bad = SpecError(f"{where}: expected {kinds[f.kind]}, got {type(value).__name__} {value!r}")
    if f.kind in ("bool", "str", "table") and not isinstance(value, {"bool": bool, "str": str, "table": dict}[f.kind]):
        raise bad
    if f.kind in ("bool", "table"):
        return value
    if f.kind == "str":
        if f.choices and value not in f.choices:
            raise SpecError(f"{where}: {value!r} is not one of {', '.join(f.choices)}")
        return value
    if f.kind == "strs":
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value) or not value:
            raise bad
        for v in value:
            if f.choices and v not in f.choices:
                raise SpecError(f"{where}: {v!r} is not one of {', '.join(f.choices)}")
        return tuple(dict.fromkeys(value))
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise bad
    if f.kind == "int":
        if isinstance(value, float):
            if not value.is_integer():
                raise bad
            value = int(value)
    else:
        value = float(value)
    if isinstance(value, float) and not math.isfinite(value):
        raise SpecError(f"{where}: must be finite, got {value}")
    if f.check == "positive" and not value > 0:
        raise SpecError(f"{where}: must be > 0, got {value}")
    if f.check == "nonneg" and not value >= 0:
        raise SpecError(f"{where}: must be >= 0, got {value}")
    return value


def _section(raw, name, fields, origin):
    table = raw.get(name, {})
    if not isinstance(table, dict):
        raise SpecError(f"{origin}: {name}: expected a table [{name}], got a value")
    out = {}
    for key in table:
        if key not in fields:
            raise SpecError(f"{origin}: {name}.{key}: unknown field (known: {', '.join(fields)})")
    for key, f in fields.items():
        where = f"{origin}: {name}.{key}"
        if key in table:
            out[key] = _check(where, f, _unwrap(where, table[key], f.unit))
        else:
            out[key] = f.default
    return out


# -- varied keys ----------------------------------------------------------------------------------

def _varied_kind(key, base):
    """``(kind, unit, list_length or None)`` of a varied key, or :class:`SpecError`."""
    if key.startswith("experiment."):
        name = key.split(".", 1)[1]
        f = EXPERIMENT.get(name)
        if f is None:
            raise SpecError(f"{key}: unknown experiment field (known: {', '.join(EXPERIMENT)})")
        if not f.varies:
            raise SpecError(f"{key}: cannot vary; set it in [experiment]")
        return f.kind, f.unit, None
    section, k, index = split_key(key)
    spec = SCHEMA[section][k]
    if section == "model":
        raise SpecError(f"{key}: the model's name and format cannot vary")
    if spec.kind == "floats" and index is None:
        return "floats", spec.unit, len(base[section][k])
    if index is not None:
        have = len(base[section][k])
        if index > have:
            raise SpecError(f"{key}: index out of range ({section}.{k} has {have} values in the base "
                            f"model; indices are 1-based; to add elements, put them in the base model)")
        return "float", spec.unit, None
    return key_spec(key).kind, spec.unit, None


def _check_varied_value(key, kind, value, base):
    """Normalise one grid value for ``key`` and check it against the model (or the field)."""
    if isinstance(value, bool) and kind != "bool":
        raise SpecError(f"{key}: expected {kind}, got {value!r}")
    if key.startswith("experiment."):
        name = key.split(".", 1)[1]
        return _check(key, EXPERIMENT[name], value)
    if kind == "float" and isinstance(value, int):
        value = float(value)
    try:
        with_values(base, {key: value})
    except ModelError as exc:
        raise SpecError(str(exc)) from None
    return value


def _grid_axis(key, entry, base, origin):
    where = f"{origin}: [grid] {key}"
    try:
        kind, unit, _ = _varied_kind(key, base)
    except (SpecError, ModelError) as exc:
        raise SpecError(f"{origin}: [grid] {exc}") from None
    if kind == "floats":
        raise SpecError(f"{where}: a grid varies one value; name an element, e.g. {key}[1] "
                        "(whole lists can be drawn in [random])")
    log = False
    if isinstance(entry, list):
        if not entry:
            raise SpecError(f"{where}: empty list")
        values = list(entry)
    elif isinstance(entry, dict):
        extra = set(entry) - GRID_FIELDS
        if extra:
            raise SpecError(f"{where}: unknown field(s) {', '.join(sorted(extra))} (a list of values, "
                            "{ start, stop, num [, log = true] } or { start, stop, step })")
        if kind not in ("float", "int"):
            raise SpecError(f"{where}: a range needs a numeric key; list the values instead")
        if "unit" in entry and entry["unit"] != unit:
            raise SpecError(f"{where}: unit {entry['unit']!r} given, expected {unit!r}")
        if "start" not in entry or "stop" not in entry:
            raise SpecError(f"{where}: missing start or stop")
        start = _check(f"{where}.start", Field(unit), entry["start"])
        stop = _check(f"{where}.stop", Field(unit), entry["stop"])
        if ("num" in entry) == ("step" in entry):
            raise SpecError(f"{where}: give exactly one of num (number of values) or step (spacing)")
        log = _check(f"{where}.log", Field(None, "bool"), entry.get("log", False))
        if "num" in entry:
            num = _check(f"{where}.num", Field("1", "int", "positive"), entry["num"])
            if num > MAX_RUNS:
                raise SpecError(f"{where}.num: at most {MAX_RUNS}")
            if log:
                if not (start > 0 and stop > 0):
                    raise SpecError(f"{where}: a log range needs start > 0 and stop > 0")
                values = np.geomspace(start, stop, num).tolist()
            else:
                values = np.linspace(start, stop, num).tolist()
        else:
            if log:
                raise SpecError(f"{where}: log = true needs num, not step")
            step = _check(f"{where}.step", Field(unit, check="positive"), entry["step"])
            if stop < start:
                raise SpecError(f"{where}: stop {stop} is before start {start}")
            n = math.floor((stop - start) / step + 1e-9) + 1
            if n > MAX_RUNS:
                raise SpecError(f"{where}: {n} values; at most {MAX_RUNS}")
            values = [start + k * step for k in range(n)]
        if kind == "int":
            values = [round(v) for v in values]
    else:
        raise SpecError(f"{where}: expected a list of values or a range table, got {entry!r}")
    out = []
    for i, v in enumerate(values, 1):
        try:
            out.append(_check_varied_value(key, kind, v, base))
        except SpecError as exc:
            raise SpecError(f"{origin}: [grid] value {i} of {key}: {exc}") from None
    if len(set(map(repr, out))) != len(out):
        raise SpecError(f"{where}: repeated values")
    return Axis(key, tuple(out), bool(log))


def _draw(key, entry, base, origin):
    where = f"{origin}: [random] {key}"
    try:
        kind, unit, size = _varied_kind(key, base)
    except (SpecError, ModelError) as exc:
        raise SpecError(f"{origin}: [random] {exc}") from None
    if not isinstance(entry, dict):
        raise SpecError(f"{where}: expected a table, one of " +
                        ", ".join(f"{{ {k} = {v} }}" for k, v in DRAWS.items()))
    extra = set(entry) - set(DRAWS) - {"unit", "distribution"}
    if extra:
        raise SpecError(f"{where}: unknown field(s) {', '.join(sorted(extra))} (one of {', '.join(DRAWS)}; "
                        "unit; distribution with tolerance_pct)")
    given = [k for k in DRAWS if k in entry]
    if len(given) != 1:
        raise SpecError(f"{where}: give exactly one of {', '.join(DRAWS)}")
    how = given[0]
    if "unit" in entry and entry["unit"] != unit:
        raise SpecError(f"{where}: unit {entry['unit']!r} given, expected {unit!r}")
    if "distribution" in entry and how != "tolerance_pct":
        raise SpecError(f"{where}: distribution goes with tolerance_pct")
    if kind in ("str", "bool"):
        raise SpecError(f"{where}: {key} is not a number; vary it in [grid]")
    if (kind == "int") != (how == "integers"):
        raise SpecError(f"{where}: " + ("an integer parameter takes { integers = [low, high] }" if kind == "int"
                                         else "integers only for integer parameters (e.g. sensor.seed)"))
    nominal = None
    if how == "tolerance_pct":
        pct = _check(f"{where}.tolerance_pct", Field("%", check="positive"), entry[how])
        dist = _check(f"{where}.distribution", Field(None, "str", choices=("uniform", "normal")),
                      entry.get("distribution", "uniform"))
        if key.startswith("experiment."):
            nominal = None      # filled from the experiment by load_spec
        else:
            section, k, index = split_key(key)
            v = base[section][k]
            nominal = tuple(v) if index is None and isinstance(v, list) else (v[index - 1] if index else v)
        return Draw(key, "tolerance", pct / 100.0, 1.0 if dist == "normal" else 0.0, nominal, size)
    pair = entry[how]
    if (not isinstance(pair, list) or len(pair) != 2
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in pair)):
        raise SpecError(f"{where}.{how}: expected {DRAWS[how]}, got {pair!r}")
    a, b = (float(v) for v in pair)
    if not (math.isfinite(a) and math.isfinite(b)):
        raise SpecError(f"{where}.{how}: must be finite, got {pair}")
    if how == "normal" and not b > 0:
        raise SpecError(f"{where}.normal: the standard deviation must be > 0, got {b}")
    if how in ("uniform", "integers") and not b >= a:
        raise SpecError(f"{where}.{how}: high {b} is below low {a}")
    if how == "integers" and not (a.is_integer() and b.is_integer()):
        raise SpecError(f"{where}.integers: expected whole numbers, got {pair}")
    return Draw(key, how, a, b, None, size)


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
    sweep = _section(raw, "sweep", SWEEP, origin)
    experiment = _section(raw, "experiment", EXPERIMENT, origin)
    metrics = _section(raw, "metrics", METRICS, origin)

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
        name = _check(f"{where}.metric", Field(None, "str", choices=METRIC_NAMES), t["metric"])
        lo = _check(f"{where}.min", Field(None), t["min"]) if "min" in t else None
        hi = _check(f"{where}.max", Field(None), t["max"]) if "max" in t else None
        if name != "stable" and lo is None and hi is None:
            raise SpecError(f"{where}: give max and/or min for {name}")
        if lo is not None and hi is not None and not hi >= lo:
            raise SpecError(f"{where}: max {hi} is below min {lo}")
        if name not in metrics["names"]:
            raise SpecError(f"{where}.metric: {name} is not among metrics.names")
        tolerance = Tolerance(name, lo, hi)

    # what varies
    grid = tuple(_grid_axis(k, v, base, origin) for k, v in raw.get("grid", {}).items())
    draws = []
    for k, v in raw.get("random", {}).items():
        d = _draw(k, v, base, origin)
        if d.kind == "tolerance" and k.startswith("experiment."):
            nominal = experiment[k.split(".", 1)[1]]
            if nominal is None:
                raise SpecError(f"{origin}: [random] {k}: tolerance_pct needs a base value in [experiment]")
            d = Draw(d.key, d.kind, d.a, d.b, nominal, None)
        draws.append(d)
    draws = tuple(draws)
    keys = [a.key for a in grid] + [d.key for d in draws]
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
    if periodic is False and any(a.key == "experiment.periods" for a in grid):
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
