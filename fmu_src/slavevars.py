"""Variables of the piezo-fmu slaves: registration, value checks and the build's metadata.

:class:`VariableRegistry` is a mixin of :class:`slavebase.SlaveBase`: Real/Integer inputs, outputs
and parameters with unit, description and variability, every parameter of a model section
(``<section>.<key>``, list elements ``<section>.<key>[i]``, 1-based) from the bundled model, the
parameters back as model ``sections``, and :meth:`~VariableRegistry.fmu_meta` for
:mod:`piezo_fmu.builder`. A variable lives in the slave's ``__dict__`` under its name and is
registered with pythonfmu (which numbers the value references and writes the modelDescription).
Bundled into every FMU next to ``slavebase``.
"""
from __future__ import annotations

import functools
import math

from pythonfmu import Fmi2Causality, Fmi2Variability, Integer, Real

__all__ = ["INT_MAX", "FmuUsageError", "Var", "VariableRegistry", "value_problem", "xml_number"]

INT_MAX = 2 ** 31 - 1
_INF = math.inf


class FmuUsageError(RuntimeError):
    """Illegal FMI usage or value; logged with status error before it is raised."""


class Var:
    """One registered variable: its FMI attributes and, for a model parameter, where it lives in
    the model (``section``, ``key``, 1-based list ``index``) and its check."""

    __slots__ = (
        "causality",
        "check",
        "codes",
        "description",
        "hi",
        "index",
        "key",
        "lo",
        "name",
        "section",
        "start",
        "type",
        "unit",
        "variability",
        "vr",
    )

    def __init__(self, **kw):
        for k in self.__slots__:
            setattr(self, k, kw.get(k))

    def label(self):
        return f"'{self.name}' (vr={self.vr})"


def value_problem(var, v):
    """Why ``v`` is not acceptable for ``var`` (``""`` if it is)."""
    if var.type == "Integer":
        if var.lo is not None and v < var.lo or var.hi is not None and v > var.hi:
            codes = ""
            if var.codes:
                codes = " (" + ", ".join(f"{c} {n}" for n, c in var.codes.items()) + ")"
            return f"must be an integer in [{var.lo}, {var.hi}]{codes}, got {v}"
        return ""
    if math.isnan(v):
        return "is NaN"
    check = var.check or "finite"
    if check == "positive_or_inf":
        return "" if v > 0 else f"must be > 0 (or inf), got {v!r}"
    if v - v != 0.0:
        return f"must be finite, got {v!r}"
    if check == "positive" and not v > 0:
        return f"must be > 0, got {v!r}"
    if check == "nonneg" and not v >= 0:
        return f"must be >= 0, got {v!r}"
    return ""


class VariableRegistry:
    """Mixin: registration of variables and parameters (see the module docstring). Expects the
    slave's ``_vars`` (vr -> Var), ``_by_name``, ``_list_keys``, ``_params`` and ``_model``."""

    def _register(self, var, *, pyvar_cls):
        if var.name in self._by_name:
            raise ValueError(f"variable {var.name!r} registered twice")
        if var.name.startswith("_") or var.name in self.__dict__:
            raise ValueError(f"variable name {var.name!r} clashes with an attribute")
        caus = getattr(Fmi2Causality, var.causality)
        vari = getattr(Fmi2Variability, var.variability)
        name = var.name
        d = self.__dict__
        d[name] = var.start if var.causality != "output" else (0 if var.type == "Integer" else 0.0)
        pv = pyvar_cls(name, causality=caus, variability=vari, description=var.description,
                       getter=functools.partial(d.__getitem__, name),
                       setter=functools.partial(d.__setitem__, name))
        self.register_variable(pv, nested=False)
        var.vr = pv.value_reference
        self._vars[var.vr] = var
        self._by_name[name] = var
        return var

    def add_input(self, name, start, unit, description):
        return self._register(Var(name=name, type="Real", causality="input", variability="continuous",
                                  unit=unit, description=description, start=float(start)),
                              pyvar_cls=Real)

    def add_output(self, name, unit, description):
        return self._register(Var(name=name, type="Real", causality="output", variability="continuous",
                                  unit=unit, description=description), pyvar_cls=Real)

    def add_parameter(self, name, start, unit, description, *, tunable, check="finite",
                      integer=False, lo=None, hi=None, codes=None, section=None, key=None, index=None):
        """A Real (or Integer) parameter. ``check`` is a SCHEMA constraint; ``codes`` maps labels to
        the Integer codes (the model value is the label)."""
        if section is None:
            section, _, key = name.rpartition(".")
        var = Var(name=name, type="Integer" if integer else "Real", causality="parameter",
                  variability="tunable" if tunable else "fixed", unit=None if integer else unit,
                  description=description, check=check, lo=lo, hi=hi, codes=codes,
                  start=int(start) if integer else float(start), section=section, key=key, index=index)
        problem = value_problem(var, var.start)
        if problem:
            raise FmuUsageError(f"start value of parameter '{name}' {problem}")
        return self._register(var, pyvar_cls=Integer if integer else Real)

    def add_model_parameters(self, sections, tunable=(), codes=None):
        """Register every key of the given model sections as parameters.

        ``sections``: ``{section: None | (key, ...)}`` (None: all keys of the section);
        ``tunable``: names (a list key covers all its elements) that may change in step mode;
        ``codes``: ``{"section.key": {label: code}}`` for string-valued keys (Integer parameters).
        """
        schema, values = self._model["schema"], self._model["sections"]
        codes = codes or {}
        tunable = frozenset(tunable)
        for sec, keys in sections.items():
            for key in (keys if keys is not None else schema[sec]):
                spec = schema[sec][key]
                name = f"{sec}.{key}"
                value = values[sec][key]
                doc = spec["doc"]
                tun = name in tunable
                kind = spec["kind"]
                if kind == "float":
                    self.add_parameter(name, value, spec["unit"], doc, tunable=tun, check=spec["check"],
                                       section=sec, key=key)
                elif kind == "floats":
                    n = len(value)
                    self._list_keys[(sec, key)] = n
                    check = "finite" if spec["check"] == "thresholds" else spec["check"]
                    for i, x in enumerate(value, 1):
                        self.add_parameter(f"{name}[{i}]", x, spec["unit"], f"{doc} (element {i} of {n})",
                                           tunable=tun, check=check, section=sec, key=key, index=i)
                elif kind == "int":
                    lo = 0 if spec["check"] == "nonneg" else -INT_MAX - 1
                    self.add_parameter(name, value, None, doc, tunable=tun, integer=True, lo=lo,
                                       hi=INT_MAX, section=sec, key=key)
                elif kind == "str":
                    cmap = codes[name]
                    text = ", ".join(f"{c} {lab}" for lab, c in sorted(cmap.items(), key=lambda i: i[1]))
                    self.add_parameter(name, cmap[value], None, f"{key} as an Integer code: {text}", tunable=tun,
                                       integer=True, lo=min(cmap.values()), hi=max(cmap.values()),
                                       codes=cmap, section=sec, key=key)
                else:
                    raise ValueError(f"{name}: unsupported schema kind {kind!r}")

    def add_engine_parameter(self, engines):
        """``simulation.engine``: run the unit's kernel interpreted (``python``, NumPy only) or
        compiled by numba (``numba``: the slave's ``COMPILE(unit)``); ``engines`` maps the labels to
        their Integer codes (``piezo_fmu.core.compiled.ENGINES``). A fixed parameter; the results
        are the same bit for bit."""
        codes = ", ".join(f"{c} {n}" for n, c in engines.items())
        self.add_parameter("simulation.engine", engines["python"], None,
                           f"kernel engine: {codes} (compiled: numba must be installed in the host's "
                           "Python; the first instance in a process compiles for a few seconds; "
                           "identical results, less time per step)", tunable=False, integer=True,
                           lo=min(engines.values()), hi=max(engines.values()), codes=engines)

    def model_sections(self):
        """The parameters as a model ``sections`` dict (lists for list keys, labels for coded ints)."""
        d = self.__dict__
        out = {}
        for (sec, key), n in self._list_keys.items():
            out.setdefault(sec, {})[key] = [None] * n
        for v in self._params:
            value = d[v.name]
            if v.codes:
                value = next(lab for lab, c in v.codes.items() if c == value)
            sec = out.setdefault(v.section, {})
            if v.index is None:
                sec[v.key] = value
            else:
                sec[v.key][v.index - 1] = value
        return out

    def fmu_meta(self):
        """Everything piezo_fmu.builder needs to post-process the modelDescription."""
        variables = {}
        for v in self._vars.values():
            start = None
            if v.causality != "output":
                start = xml_number(v.start)
            lo = v.lo
            if v.type == "Real" and v.causality == "parameter" and v.check in (
                    "positive", "nonneg", "positive_or_inf"):
                lo = 0.0
            variables[v.name] = {
                "type": v.type, "causality": v.causality, "variability": v.variability,
                "unit": v.unit, "description": v.description, "start": start,
                "min": None if lo is None else xml_number(lo),
                "max": None if v.hi is None else xml_number(v.hi),
                # outputs are computed in do_step / at initialization only: no direct feedthrough
                "depends_on": [] if v.causality == "output" else None,
                "init_depends_on": None,
            }
        return {
            "model_name": type(self).__name__,
            "description": type(self).description,
            "default_experiment": self.DEFAULT_EXPERIMENT,
            "can_get_set_state": True,
            "can_serialize_state": True,
            "variables": variables,
        }


def xml_number(v):
    """Exact xs:double / xs:int text (repr round-trips; XML spells infinity INF)."""
    if isinstance(v, bool):
        raise TypeError("bool is not a number here")
    if isinstance(v, int):
        return str(v)
    v = float(v)
    if v == _INF:
        return "INF"
    if v == -_INF:
        return "-INF"
    return repr(v)
