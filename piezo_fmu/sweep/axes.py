"""What varies in a sweep: grid axes and random draws, parsed and checked against the base model.

A key is an experiment field (``experiment.freq``) or a model parameter named like the FMU
parameters (``amplifier.R``, ``hysteresis.weights[3]``; a whole list, ``hysteresis.weights``,
only in random draws). Grid values are checked one by one against the base model
(:func:`piezo_fmu.model.with_values`), so a value the model rejects is an error of the spec, not
a thousand failed runs. Keys joined by commas vary together (one linked axis):
``"experiment.amplitude, experiment.offset" = [[15.0, 15.0], [45.0, 45.0]]``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..model import SCHEMA, ModelError, key_spec, split_key, with_values
from .fields import EXPERIMENT, MAX_RUNS, Field, SpecError, check_field

__all__ = ["DRAWS", "GRID_FIELDS", "Axis", "Draw", "check_varied_value", "grid_axis", "random_draw",
           "varied_kind"]

GRID_FIELDS = {"start", "stop", "step", "num", "log", "unit"}
DRAWS = {"uniform": "[low, high]", "normal": "[mean, std]", "integers": "[low, high] (inclusive)",
         "tolerance_pct": "+-x % of the base value"}


@dataclass(frozen=True)
class Axis:
    """One grid axis: ``key`` and its ``values`` (``log``: spaced logarithmically).

    A linked axis varies several ``keys`` together: ``key`` is them joined by ``", "`` and each
    value is a tuple with one value per key."""

    key: str
    values: tuple
    log: bool = False
    keys: tuple = ()

    def __post_init__(self):
        if not self.keys:
            object.__setattr__(self, "keys", (self.key,))

    def at(self, k) -> dict:
        """``{key: value}`` of the ``k``-th value."""
        v = self.values[k]
        return dict(zip(self.keys, v)) if len(self.keys) > 1 else {self.key: v}


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


def varied_kind(key, base):
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


def check_varied_value(key, kind, value, base):
    """Normalise one grid value for ``key`` and check it against the model (or the field)."""
    if isinstance(value, bool) and kind != "bool":
        raise SpecError(f"{key}: expected {kind}, got {value!r}")
    if key.startswith("experiment."):
        name = key.split(".", 1)[1]
        return check_field(key, EXPERIMENT[name], value)
    if kind == "float" and isinstance(value, int):
        value = float(value)
    try:
        with_values(base, {key: value})
    except ModelError as exc:
        raise SpecError(str(exc)) from None
    return value


def _linked_axis(key, entry, base, origin):
    keys = tuple(k.strip() for k in key.split(","))
    where = f"{origin}: [grid] {key}"
    kinds = []
    for k in keys:
        try:
            kind, _, _ = varied_kind(k, base)
        except (SpecError, ModelError) as exc:
            raise SpecError(f"{origin}: [grid] {exc}") from None
        if kind == "floats":
            raise SpecError(f"{where}: {k}: a grid varies one value; name an element, e.g. {k}[1]")
        kinds.append(kind)
    if len(set(keys)) != len(keys) or not all(keys):
        raise SpecError(f"{where}: name each key once, separated by commas")
    if not isinstance(entry, list) or not entry or not all(isinstance(r, list) and len(r) == len(keys)
                                                           for r in entry):
        raise SpecError(f"{where}: expected a list of [{', '.join(keys)}] lists, one value per key")
    rows = []
    for i, row in enumerate(entry, 1):
        try:
            rows.append(tuple(check_varied_value(k, kind, v, base) for k, kind, v in zip(keys, kinds, row)))
        except SpecError as exc:
            raise SpecError(f"{origin}: [grid] value {i} of {key}: {exc}") from None
    if len(set(map(repr, rows))) != len(rows):
        raise SpecError(f"{where}: repeated values")
    return Axis(", ".join(keys), tuple(rows), False, keys)


def grid_axis(key, entry, base, origin):
    """The :class:`Axis` of a ``[grid]`` entry: a list of values, a range ``{ start, stop, num
    [, log] }`` or ``{ start, stop, step }``, or for keys joined by commas a list of rows."""
    if "," in key:
        return _linked_axis(key, entry, base, origin)
    where = f"{origin}: [grid] {key}"
    try:
        kind, unit, _ = varied_kind(key, base)
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
        start = check_field(f"{where}.start", Field(unit), entry["start"])
        stop = check_field(f"{where}.stop", Field(unit), entry["stop"])
        if ("num" in entry) == ("step" in entry):
            raise SpecError(f"{where}: give exactly one of num (number of values) or step (spacing)")
        log = check_field(f"{where}.log", Field(None, "bool"), entry.get("log", False))
        if "num" in entry:
            num = check_field(f"{where}.num", Field("1", "int", "positive"), entry["num"])
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
            step = check_field(f"{where}.step", Field(unit, check="positive"), entry["step"])
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
            out.append(check_varied_value(key, kind, v, base))
        except SpecError as exc:
            raise SpecError(f"{origin}: [grid] value {i} of {key}: {exc}") from None
    if len(set(map(repr, out))) != len(out):
        raise SpecError(f"{where}: repeated values")
    return Axis(key, tuple(out), bool(log))


def random_draw(key, entry, base, origin):
    where = f"{origin}: [random] {key}"
    try:
        kind, unit, size = varied_kind(key, base)
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
        pct = check_field(f"{where}.tolerance_pct", Field("%", check="positive"), entry[how])
        dist = check_field(f"{where}.distribution", Field(None, "str", choices=("uniform", "normal")),
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

