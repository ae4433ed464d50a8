"""Model parameter files: one TOML format, with a unit and a provenance for every value.

A model file holds the device (amplifier, hysteresis, mechanics, sensor, optional beyond-paper
effects) and the compensator's own, separately identified models. Every parameter is an inline
table::

    [amplifier]
    R = { value = 400.0, unit = "ohm", source = "chosen: amplifier corner 100 Hz, see README" }

:func:`load_model` validates on load: unknown or missing keys, wrong types, wrong units and
non-physical values (negative mass, an unstable or non-invertible filter, a non-invertible
hysteresis model) raise :class:`ModelError` naming the key. :func:`validate_model` returns the list
of problems instead (like ``fmpy.validation``). :func:`dump_model` writes the format back.
"""
from __future__ import annotations

import copy
import math
import tomllib
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path

import numpy as np

from .core.hysteresis import PrandtlIshlinskii
from .core.units import check_sections
from .errors import UserError

__all__ = ["Spec", "SCHEMA", "ModelError", "Model", "load_model", "loads_model", "validate_model",
           "dump_model", "DEFAULT_MODEL", "split_key", "key_spec", "with_values"]

# the model file of the paper, shipped inside the package (the repository's models/paper.toml)
DEFAULT_MODEL = Path(str(files("piezo_fmu.model_files").joinpath("paper.toml")))

UNIT_ALIASES = {"µm": "um", "μm": "um", "Ohm": "ohm", "Ω": "ohm", "-": "1", "": "1"}


class ModelError(UserError):
    """A model file is missing, unreadable or invalid; the message names the file and key."""


@dataclass(frozen=True)
class Spec:
    """Expected form of one parameter: ``kind`` in float|int|floats|str, ``check`` a constraint."""

    unit: str | None
    kind: str = "float"
    check: str = "finite"
    doc: str = ""
    default: object = None
    choices: tuple = ()


def _f(unit, check="finite", doc="", default=None):
    return Spec(unit, "float", check, doc, default)


def _hyst(doc):
    return {
        "u_norm": _f("V", "positive", f"input normalisation of the {doc} PI model"),
        "scale": _f("um", "positive", f"output scale of the {doc} PI model (um per PI unit)"),
        "thresholds": Spec("1", "floats", "thresholds", f"play-operator thresholds of the {doc} PI model"),
        "weights": Spec("1", "floats", "finite", f"PI weights of the {doc} model (w_0 = the paper's q)"),
    }


SCHEMA = {
    "model": {
        "name": Spec(None, "str", doc="short model name"),
        "description": Spec(None, "str", doc="what this model describes"),
        "format": Spec(None, "int", "format", doc="model file format version (1)"),
    },
    "amplifier": {
        "k_amp": _f("V/V", "positive", "amplifier voltage gain"),
        "R": _f("ohm", "positive", "series resistance of the amplifier output (eq. 2)"),
        "C_a": _f("F", "positive", "stack capacitance (eq. 2)"),
        "u_min": _f("V", "finite", "lower output rail"),
        "u_max": _f("V", "finite", "upper output rail"),
        "I_max": _f("A", "positive_or_inf", "output current limit (inf: none)", math.inf),
        "delay": _f("s", "nonneg", "command latency (transport or sampling delay)", 0.0),
        "tau_2": _f("s", "nonneg", "time constant of a first-order input stage before the output "
                                   "stage R C_a: a second-order amplifier (0: none, eq. 2)", 0.0),
    },
    "hysteresis": {**_hyst("device's"),
                   "saturation": _f("um", "positive_or_inf",
                                    "strain saturation y_sat: x_h / (1 + |x_h| / y_sat) (inf: none)",
                                    math.inf),
                   "prepared": _f("V", "nonneg", "the stack's memory at the start: 0 relaxed; > 0 the memory "
                                                 "of a sweep up to this stack voltage and back to rest before "
                                                 "t0 (a device exercised before the run)", 0.0),
                   "cells_up": Spec("1", "floats", "finite", "Preisach term (beyond the paper): input at which each "
                                    "Krasnosel'skii-Pokrovskii cell has switched up, in units of u_norm", []),
                   "cells_down": Spec("1", "floats", "finite", "input at which each KP cell has switched down "
                                      "(cells_up - cells_down >= cells_width), in units of u_norm", []),
                   "cells_width": Spec("1", "floats", "positive", "ramp width of each KP cell's switching, in "
                                       "units of u_norm", []),
                   "cells_weights": Spec("1", "floats", "finite", "weight of each KP cell (output in units of "
                                         "scale, added to the PI's; any sign)", [])},
    "creep": {
        "gains": Spec("1", "floats", "nonneg", "creep element gains relative to the hysteretic stroke", []),
        "time_constants": Spec("s", "floats", "positive", "creep element time constants", []),
    },
    "mechanics": {
        "m": _f("kg", "positive", "equivalent moving mass (eq. 4)"),
        "c": _f("N*s/m", "nonneg", "equivalent viscous damping (eq. 4)"),
        "k_a": _f("N/m", "positive", "stack stiffness; F_out = k_a x_free (eq. 5)"),
        "k_f": _f("N/m", "nonneg", "preload spring and housing stiffness (eq. 4)"),
        "pickoff": Spec("1", "str", doc="the force the quartz wafer carries: stack (the stack's blocked "
                                         "force F_out, paper eq. 5) | contact (between stack and push rod, "
                                         "k_a (x_free - x): the modes show in it) | load (the preload "
                                         "spring's k_f x: it follows the push-rod displacement)",
                        default="stack", choices=("stack", "contact", "load")),
    },
    "resonance": {
        "f_n": _f("Hz", "nonneg", "natural frequency of a further mode in series (0: none)", 0.0),
        "zeta": _f("1", "positive", "damping ratio of that mode", 0.05),
        "position": Spec("1", "str", doc="where that mode acts: output (after the mechanics, on the "
                                          "displacement) | drive (on the free stroke before the mechanics: "
                                          "in the displacement and in every sensed force)",
                         default="output", choices=("output", "drive")),
    },
    "drift": {
        "offset": _f("um", "finite", "displacement offset at t = 0", 0.0),
        "rate": _f("um/s", "finite", "linear displacement drift", 0.0),
        "curvature": _f("um/s^2", "finite", "curvature of the displacement drift: half its acceleration "
                        "at t = 0 (the coefficient of t^2, or of its warm-up form)", 0.0),
        "time_constant": _f("s", "positive_or_inf", "warm-up time constant of the drift's curvature "
                            "term 2 T^2 (exp(-t/T) - 1 + t/T) (inf: t^2, a quadratic drift)", math.inf),
    },
    "sensor": {
        "d11": _f("C/N", "positive", "piezoelectric coefficient of x-cut quartz (eq. 3)"),
        "thickness": _f("m", "positive", "quartz wafer thickness (eq. 3)"),
        "eps_r": _f("1", "positive", "relative permittivity of quartz (eq. 3)"),
        "area": _f("m^2", "positive", "electrode area of the annular wafer (eq. 3)"),
        "C_load": _f("F", "nonneg", "cable and input capacitance in parallel", 0.0),
        "tau_leak": _f("s", "positive_or_inf", "charge leakage time constant (inf: none)", math.inf),
        "offset": _f("V", "finite", "output offset", 0.0),
        "noise_std": _f("V", "nonneg", "white measurement noise, standard deviation", 0.0),
        "seed": Spec("1", "int", "nonneg", "noise seed", 0),
        "lag": _f("s", "nonneg", "sampling lag of the sensor voltage (whole steps; 0: none)", 0.0),
    },
    "measurement": {
        "x_noise_std": _f("um", "nonneg", "noise of the displacement measurement (capacitive probe)", 0.0),
        "seed": Spec("1", "int", "nonneg", "seed of the displacement noise", 0),
        "lag": _f("s", "nonneg", "sampling lag of the displacement probe's reading (acquisition, "
                                 "not the device: the x of simulate and the FMUs is the push-rod "
                                 "itself; diagnose aligns recordings by it)", 0.0),
    },
    "compensator": {
        "mode": Spec(None, "str", doc="open | ff | fb | ff+fb", choices=("open", "ff", "fb", "ff+fb")),
        "inverse": Spec(None, "str", doc="static | dynamic", choices=("static", "dynamic")),
        "k_ideal": _f("um/V", "positive", "ideal linear gain: x_ref = k_ideal u_ref"),
        "k_amp": _f("V/V", "positive", "amplifier gain assumed by the compensator"),
        "sensor_gain": _f("V/um", "positive", "sensor calibration: us per um of displacement"),
        "sensor_offset": _f("V", "finite", "sensor calibration offset", 0.0),
        "filter_hz": _f("Hz", "positive", "corner of the filter that makes G_inv proper"),
        "Kp": _f("1", "nonneg", "PID proportional gain (um per um)"),
        "Ki": _f("1/s", "nonneg", "PID integral gain"),
        "Kd": _f("s", "nonneg", "PID derivative gain", 0.0),
        "Tf": _f("s", "positive", "PID derivative filter time constant", 1e-4),
        "uc_min": _f("V", "finite", "lower command limit (amplifier input range)"),
        "uc_max": _f("V", "finite", "upper command limit (amplifier input range)"),
    },
    "compensator.hysteresis": _hyst("compensator's"),
    "compensator.dynamics": {
        "num": Spec("1", "floats", "finite", "numerator of G(s), descending powers of s"),
        "den": Spec("1", "floats", "finite", "denominator of G(s), descending powers of s (Hurwitz)"),
    },
    "simulation": {
        "step": _f("s", "positive", "internal step of the monolithic model", 1e-5),
        "actuator_max_step": _f("s", "positive", "largest internal step of the actuator unit", 1e-4),
        "stroke_path": Spec("1", "str", doc="how the free stroke moves between the actuator's steps: linear "
                                             "(a straight line) | amplifier_lag (along the amplifier's lag "
                                             "R C_a + tau_2; exact for a stroke proportional to ua)",
                            default="linear", choices=("linear", "amplifier_lag")),
    },
}

OPTIONAL_SECTIONS = {"creep", "resonance", "drift", "measurement", "simulation"}


def _norm_unit(u):
    return UNIT_ALIASES.get(u, u)


class Model:
    """A validated model: ``model["amplifier"]["R"]`` is the value; units and sources alongside.

    ``sections`` maps section -> key -> value; ``units`` and ``sources`` mirror it.
    ``path`` is the file it came from (or ``None``).
    """

    def __init__(self, sections, units, sources, path=None):
        self.sections = sections
        self.units = units
        self.sources = sources
        self.path = path

    def __getitem__(self, section):
        return self.sections[section]

    @property
    def name(self):
        return self.sections["model"]["name"]

    def copy(self):
        return Model(copy.deepcopy(self.sections), copy.deepcopy(self.units),
                     copy.deepcopy(self.sources), self.path)

    def set(self, section, key, value, source):
        """Set a parameter (unit from the schema) with its provenance; re-validate with :meth:`check`."""
        spec = SCHEMA[section][key]
        self.sections.setdefault(section, {})[key] = value
        self.units.setdefault(section, {})[key] = spec.unit
        self.sources.setdefault(section, {})[key] = source

    def check(self):
        problems = validate_model(self)
        if problems:
            raise ModelError(f"{self.path or 'model'}: " + "; ".join(problems))
        return self

    # convenient derived objects ----------------------------------------------------------
    def hysteresis(self, section="hysteresis") -> PrandtlIshlinskii:
        s = self.sections[section]
        return PrandtlIshlinskii(s["thresholds"], s["weights"], s["u_norm"], s["scale"])

    def describe(self, section, key):
        """``value unit (source)`` for reports."""
        return (f"{self.sections[section][key]} {self.units[section].get(key) or ''}".strip()
                + f"  ({self.sources[section].get(key, '')})")


def _type_error(where, spec, value):
    kinds = {"float": "a number", "int": "an integer", "floats": "a list of numbers", "str": "a string"}
    return f"{where}: expected {kinds[spec.kind]}, got {type(value).__name__} {value!r}"


def _check_value(where, spec, value):
    """Return (normalised value, problem or '')."""
    if spec.kind == "str":
        if not isinstance(value, str):
            return value, _type_error(where, spec, value)
        if spec.choices and value not in spec.choices:
            return value, f"{where}: {value!r} is not one of {', '.join(spec.choices)}"
        return value, ""
    if spec.kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            return value, _type_error(where, spec, value)
        if spec.check == "nonneg" and value < 0:
            return value, f"{where}: must be >= 0, got {value}"
        if spec.check == "format" and value != 1:
            return value, f"{where}: unsupported format {value} (this version reads format 1)"
        return value, ""
    if spec.kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return value, _type_error(where, spec, value)
        value = float(value)
        return value, _check_number(where, spec.check, value)
    # floats
    if not isinstance(value, list) or any(isinstance(v, bool) or not isinstance(v, (int, float))
                                          for v in value):
        return value, _type_error(where, spec, value)
    value = [float(v) for v in value]
    for i, v in enumerate(value):
        problem = _check_number(f"{where}[{i}]", "finite" if spec.check == "thresholds" else spec.check, v)
        if problem:
            return value, problem
    return value, ""


def _check_number(where, check, v):
    if math.isnan(v):
        return f"{where}: is NaN"
    if check == "positive_or_inf":
        return "" if v > 0 else f"{where}: must be > 0 (or inf), got {v}"
    if math.isinf(v):
        return f"{where}: must be finite, got {v}"
    if check == "positive" and not v > 0:
        return f"{where}: must be > 0, got {v}"
    if check == "nonneg" and not v >= 0:
        return f"{where}: must be >= 0, got {v}"
    return ""


def _parse(raw, origin):
    """Turn the raw TOML dict into (sections, units, sources, problems)."""
    sections, units, sources, problems = {}, {}, {}, []
    flat = {}
    for name, table in raw.items():
        if not isinstance(table, dict):
            problems.append(f"{name}: expected a table [{name}], got a value")
            continue
        sub = {k: v for k, v in table.items()
               if isinstance(v, dict) and "value" not in v and k not in SCHEMA.get(name, {})}
        flat[name] = {k: v for k, v in table.items() if k not in sub}
        for k, v in sub.items():
            flat[f"{name}.{k}"] = v
    for name in flat:
        if name not in SCHEMA:
            problems.append(f"[{name}]: unknown section (known: {', '.join(SCHEMA)})")
    for name, specs in SCHEMA.items():
        table = flat.get(name)
        if table is None:
            if name in OPTIONAL_SECTIONS:
                table = {}
            else:
                problems.append(f"[{name}]: missing section")
                continue
        sections[name], units[name], sources[name] = {}, {}, {}
        for key in table:
            if key not in specs:
                problems.append(f"{name}.{key}: unknown key (known: {', '.join(specs)})")
        for key, spec in specs.items():
            where = f"{name}.{key}"
            if key not in table:
                if spec.default is not None:
                    sections[name][key] = copy.deepcopy(spec.default)
                    units[name][key] = spec.unit
                    sources[name][key] = "default"
                else:
                    problems.append(f"{where}: missing")
                continue
            entry = table[key]
            if spec.unit is None:
                value, unit, source = entry, None, ""
            else:
                if not isinstance(entry, dict) or "value" not in entry:
                    problems.append(f"{where}: expected {{ value = ..., unit = \"{spec.unit}\", "
                                    f"source = \"...\" }}, got {entry!r}")
                    continue
                extra = set(entry) - {"value", "unit", "source"}
                if extra:
                    problems.append(f"{where}: unknown field(s) {', '.join(sorted(extra))}")
                value = entry["value"]
                unit = _norm_unit(entry.get("unit", "<missing>"))
                source = entry.get("source")
                if unit != spec.unit:
                    problems.append(f"{where}: unit {entry.get('unit', '<missing>')!r} given, "
                                    f"expected {spec.unit!r}")
                if not isinstance(source, str) or not source.strip():
                    problems.append(f"{where}: missing source (say where the value comes from)")
            value, problem = _check_value(where, spec, value)
            if problem:
                problems.append(problem)
            sections[name][key] = value
            units[name][key] = spec.unit
            sources[name][key] = source
    if not problems:
        problems.extend(_cross_checks(sections))
    return sections, units, sources, problems


def _cross_checks(s):
    return check_sections(s)


def loads_model(text, origin="<string>") -> Model:
    """Parse and validate model text; raise :class:`ModelError` naming the first problems."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ModelError(f"{origin}: not valid TOML: {exc}") from None
    sections, units, sources, problems = _parse(raw, origin)
    if problems:
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        raise ModelError(f"{origin}: " + "; ".join(problems[:3]) + more)
    return Model(sections, units, sources, origin)


def load_model(path=None) -> Model:
    """Load and validate a model file.

    Parameters
    ----------
    path : str or Path, optional
        A TOML model file (format: ``models/paper.toml``: every value as
        ``{ value = ..., unit = "...", source = "..." }``). Default: the paper's model, shipped
        inside the package (:data:`DEFAULT_MODEL`).

    Returns
    -------
    Model
        The validated parameters; ``model["amplifier"]["R"]`` is the value in the file's unit
        (every unit is checked against the schema, e.g. ohm, F, um, V/V), ``model.path`` the file.

    Raises
    ------
    ModelError
        (a :class:`~piezo_fmu.errors.UserError`) naming the file and the first problems: a missing
        file, invalid TOML, an unknown or missing key, a wrong unit or type, a non-physical value,
        an unstable filter or a non-invertible hysteresis.

    Examples
    --------
    >>> from piezo_fmu import load_model
    >>> model = load_model()
    >>> model["amplifier"]["R"]          # ohm
    400.0
    """
    path = Path(path) if path is not None else DEFAULT_MODEL
    if not path.exists():
        raise ModelError(f"{path}: model file not found")
    if path.is_dir():
        raise ModelError(f"{path}: is a directory, expected a .toml model file")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise ModelError(f"{path}: not a text file (expected a TOML model file)") from None
    model = loads_model(text, str(path))
    model.path = str(path)
    return model


def validate_model(model) -> list:
    """Problems of a model (a :class:`Model`, a path or TOML text); empty when valid."""
    if isinstance(model, Model):
        text = dump_model(model)
    elif isinstance(model, Path) or (isinstance(model, str) and "\n" not in model
                                     and model.strip().endswith(".toml")):
        try:
            text = Path(model).read_bytes().decode("utf-8")
        except FileNotFoundError:
            return [f"{model}: model file not found"]
        except (OSError, UnicodeDecodeError) as exc:
            return [f"{model}: cannot be read as text ({exc.__class__.__name__})"]
    else:
        text = str(model)
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        return [f"not valid TOML: {exc}"]
    return _parse(raw, "<model>")[3]


def split_key(name) -> tuple:
    """``"section.key"`` or ``"section.key[i]"`` -> ``(section, key, i)`` (``i`` 1-based or ``None``).

    The names of the FMU parameters: ``amplifier.R``, ``hysteresis.weights[3]`` (the third
    weight), ``compensator.hysteresis.scale``. Raises :class:`ModelError` naming ``name`` when the
    section or key is not in :data:`SCHEMA`, or an index is given for a single value (or is not a
    whole number >= 1).
    """
    text = str(name).strip()
    index = None
    if text.endswith("]") and "[" in text:
        text, _, tail = text[:-1].partition("[")
        try:
            index = int(tail)
        except ValueError:
            raise ModelError(f"{name}: the index in [...] must be a whole number >= 1") from None
        if index < 1:
            raise ModelError(f"{name}: indices are 1-based, like the FMU parameters (got [{index}])")
    section, _, key = text.rpartition(".")
    if not section or section not in SCHEMA:
        known = ", ".join(s for s in SCHEMA if s != "model")
        raise ModelError(f"{name}: unknown section {section or text!r} (known: {known})")
    if key not in SCHEMA[section]:
        raise ModelError(f"{name}: unknown key {key!r} of [{section}] (known: {', '.join(SCHEMA[section])})")
    if index is not None and SCHEMA[section][key].kind != "floats":
        raise ModelError(f"{name}: {section}.{key} is a single value, not a list; drop the [{index}]")
    return section, key, index


def key_spec(name) -> Spec:
    """The :class:`Spec` of a parameter name (``section.key`` or ``section.key[i]``): unit, kind.

    For an element ``[i]`` of a list the kind is ``float``."""
    section, key, index = split_key(name)
    spec = SCHEMA[section][key]
    if index is not None:
        return Spec(spec.unit, "float", "finite" if spec.check == "thresholds" else spec.check, spec.doc)
    return spec


def with_values(model: Model, values: dict, source: str = "override") -> Model:
    """A copy of ``model`` with some parameters replaced, validated again.

    Parameters
    ----------
    model : Model
        The base model (not changed).
    values : dict
        ``{name: value}`` with names as the FMU parameters: ``"amplifier.R"`` (a value in the
        model file's unit, here ohm), ``"hysteresis.weights[3]"`` (one element of a list,
        1-based), ``"creep.gains"`` (a whole list), ``"compensator.mode"`` (a string).
    source : str
        The provenance recorded for the replaced values.

    Returns
    -------
    Model
        The new model. Raises :class:`ModelError` naming the parameter when a name is unknown, an
        index is out of range, a value has the wrong type or is non-physical, or the changed model
        fails a cross-check (rails in order, invertible hysteresis, stable ``G(s)``, ...).

    Examples
    --------
    >>> m = with_values(load_model(), {"hysteresis.weights[3]": 0.5, "amplifier.R": 410.0})
    >>> m["amplifier"]["R"], m["hysteresis"]["weights"][2]
    (410.0, 0.5)
    """
    new = model.copy()
    new.path = None
    problems = []
    for name, value in values.items():
        section, key, index = split_key(name)
        spec = SCHEMA[section][key]
        current = new.sections.setdefault(section, {}).get(key)
        if isinstance(value, np.generic):
            value = value.item()
        if index is not None:
            length = len(current or [])
            if index > length:
                problems.append(f"{name}: index out of range ({section}.{key} has {length} values in "
                                f"this model; indices are 1-based)")
                continue
            value, problem = _check_value(name, key_spec(name), value)
            if not problem:
                current = list(current)
                current[index - 1] = value
                value = current
        else:
            value, problem = _check_value(name, spec, value)
        if problem:
            problems.append(problem)
            continue
        new.set(section, key, value, source)
    if not problems:
        problems = _cross_checks(new.sections)
    if problems:
        more = f" (and {len(problems) - 3} more)" if len(problems) > 3 else ""
        raise ModelError("; ".join(problems[:3]) + more)
    return new


def _toml_value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        if math.isnan(v):
            return "nan"
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_model(model: Model, header: str = "") -> str:
    """The model as TOML text in the project's format (round-trips through :func:`loads_model`)."""
    lines = []
    if header:
        lines += ["# " + line for line in header.splitlines()] + [""]
    for name, specs in SCHEMA.items():
        values = model.sections.get(name)
        if not values:
            continue
        lines.append(f"[{name}]")
        for key, spec in specs.items():
            if key not in values:
                continue
            v = values[key]
            if spec.unit is None:
                lines.append(f"{key} = {_toml_value(v)}")
            else:
                src = model.sources.get(name, {}).get(key) or "default"
                lines.append(f"{key} = {{ value = {_toml_value(v)}, unit = {_toml_value(spec.unit)}, "
                             f"source = {_toml_value(src)} }}")
        lines.append("")
    return "\n".join(lines)
