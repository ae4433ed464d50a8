"""The fields of a sweep specification: names, kinds, units, defaults and their checks.

Each section of the spec (``[sweep]``, ``[experiment]``, ``[metrics]``) is a table of
:class:`Field`; :func:`read_section` reads one, :func:`check_field` checks one value. A number
is given bare (in the field's unit) or as ``{ value = ..., unit = "..." }`` with the unit checked,
like the model files. Errors are :class:`SpecError` naming the file and key.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from ..core.control import INVERSES, MODES
from ..errors import UserError
from .metrics import METRIC_NAMES

__all__ = ["EXPERIMENT", "MAX_RUNS", "METRICS", "SWEEP", "Field", "SpecError", "check_field", "read_section",
           "unwrap"]

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
                         "runs execute, relative to the spec file (default: built from the base model "
                         "and sent to the workers)"),
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

def unwrap(where, value, unit):
    """A bare value, or ``{ value = ..., unit = "..." }`` with the unit checked."""
    if isinstance(value, dict) and "value" in value:
        extra = set(value) - {"value", "unit"}
        if extra:
            raise SpecError(f"{where}: unknown field(s) {', '.join(sorted(extra))} (expected value, unit)")
        if "unit" in value and unit is not None and value["unit"] != unit:
            raise SpecError(f"{where}: unit {value['unit']!r} given, expected {unit!r}")
        return value["value"]
    return value


def check_field(where, f: Field, value):
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


def read_section(raw, name, fields, origin):
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
            out[key] = check_field(where, f, unwrap(where, table[key], f.unit))
        else:
            out[key] = f.default
    return out
