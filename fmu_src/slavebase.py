"""Shared base class of the piezo-fmu co-simulation slaves (FMI 2.0 CS, authored with pythonfmu).

``piezo-fmu build`` (:mod:`piezo_fmu.builder`) bundles this module, the modules it is split into
(``slavevars``, ``statecodec``, ``nativeslave``, ``pythonfmu_compat``) and a copy of
:mod:`piezo_fmu.core` into every FMU, under a package name that is unique per FMU and
content-hashed, and rewrites the imports. A slave script therefore imports it by its plain name and
keeps the literal class line pythonfmu's builder searches for (regex
``^class (\\w+)\\(\\s*Fmi2Slave\\s*\\)\\s*:``)::

    from slavebase import SlaveBase as Fmi2Slave
    class Actuator(Fmi2Slave):
        def define(self): ...            # register variables
        def make_unit(self, sections): ...   # build the core unit from the parameter sections
        def initialize(self, t0): ...    # initial outputs from inputs/parameters
        def step(self, t, h): ...        # one communication step; False = non-finite result

What the base provides:

* Registration of variables and model parameters (:mod:`slavevars`), from the model bundled as
  ``resources/piezo_model.json`` (values, units, docs and constraints of
  ``piezo_fmu.model.SCHEMA``, written by the build).
* Two ways in: the FMUs' native runtime (``fmu_src/runtime``, the C binary the build bundles)
  calls the ``_rt_*`` entry points of :mod:`nativeslave`, which serve inputs and outputs from a
  shared buffer; pythonfmu's binary (the build's fallback without a C compiler) calls the
  ``get_real``/``set_real``/``do_step``/... methods below directly, with the workarounds of
  :mod:`pythonfmu_compat`.
* Fast ``get_real``/``set_real``/``get_integer``: per-mode tables ``{vr: attribute}``, explicit
  loops, no allocation beyond the returned list. Anything unusual (unknown vr, non-float, NaN,
  a parameter, a variable that may not be set in this mode) falls through to a fully checked
  slow path that names the variable.
* The FMI mode state machine (instantiated, initializationMode, stepMode, terminated, plus
  ``broken`` after a step produced a non-finite value) with clear errors for out-of-order calls.
* Value checks: finite inputs; parameter constraints (positive, nonneg, positive_or_inf, ...)
  and ``min <= max`` pairs; fixed parameters refused after initialization; a tunable parameter
  set in step mode rebuilds the core unit and carries its state over (the new value acts from the
  next step); a combination the core rejects is rolled back with an error naming the parameters.
* Complete FMU state (registered variables + the unit's ``get_state()`` + bookkeeping), deep-copied
  in and out, and an exact, deterministic serialization (:mod:`statecodec`).

Every error is logged through ``self.log`` with status error, naming the variable, and then
raised as :class:`FmuUsageError`; the native runtime returns fmi2Error (pythonfmu's binary can
only say fmi2Fatal). The instance stays usable after such an error.
"""
from __future__ import annotations

import copy
import functools
import json
import math
import os
import sys
import traceback
import weakref

import pythonfmu
from nativeslave import NativeSlave
from pythonfmu import Fmi2Slave
from pythonfmu.enums import Fmi2Status  # not re-exported by pythonfmu 0.7.0
from slavevars import FmuUsageError, VariableRegistry, value_problem
from statecodec import InvalidState, State, state_dumps, state_loads

__all__ = ["MODEL_JSON", "FmuUsageError", "SlaveBase", "state_dumps", "state_loads"]

MODEL_JSON = "piezo_model.json"     # written into resources/ by piezo_fmu.builder
STATE_FORMAT = 1

INSTANTIATED = "instantiated"
INIT = "initializationMode"
STEP = "stepMode"
TERMINATED = "terminated"
BROKEN = "broken"                   # a step produced a non-finite value; restore a state or reset
_MODES = (INSTANTIATED, INIT, STEP, TERMINATED, BROKEN)
_CANONICAL = {m: m for m in _MODES}   # do_step compares modes by identity: restored states use these
# what the native runtime may serve from its buffer in each mode: (fmi2GetReal, fmi2SetReal) of
# inputs/outputs; initialization mode computes outputs lazily, sets outside step mode mark the
# initial values dirty or are refused with a message: those go through Python
_RT_FAST = {INSTANTIATED: (1, 0), INIT: (0, 0), STEP: (1, 1), BROKEN: (1, 1), TERMINATED: (1, 0)}

_INF = math.inf


def _no_debt(slave):
    return None


def _guard(where):
    """Route any unexpected exception of a wrapper-called method through :meth:`SlaveBase._fail`."""
    def deco(fn):
        @functools.wraps(fn)
        def wrapper(self, *args):
            try:
                return fn(self, *args)
            except FmuUsageError:
                raise
            except Exception as e:  # noqa: BLE001 - everything must become a logged, compensated error
                self._fail(f"{where}: unexpected {type(e).__name__}: {e}\n"
                           + "".join(traceback.format_exception(e)[-3:]).rstrip())
        return wrapper
    return deco


# ---------------------------------------------------------------------------------------------
# the base class
# ---------------------------------------------------------------------------------------------
class SlaveBase(NativeSlave, VariableRegistry, Fmi2Slave):
    """Base of the piezo-fmu slaves. Subclasses implement :meth:`define`, :meth:`make_unit`,
    :meth:`initialize`, :meth:`step` and :meth:`describe_outputs`; see the module docstring."""

    description = "piezo-fmu slave"
    DEFAULT_EXPERIMENT = None        # dict(startTime=..., stopTime=..., stepSize=...)
    CHECK = None                     # f(sections) -> list of problems naming the keys (the core's check)
    STATE_ATTRS = ()                 # further instance attributes that belong to the FMU state
    NEEDS_MODEL = True               # the slave builds a unit from the bundled model
    COMPILE = None                   # f(unit): switch a unit to the compiled engine (core.compiled.compile_unit)
    RT_FAST = _RT_FAST

    # -- construction ------------------------------------------------------------------------
    def __init__(self, **kwargs):
        try:
            super().__init__(**kwargs)
            self._model = self._load_model(kwargs.get("resources"))
            self._error_hook = _no_debt
            if "logger" in kwargs:     # pythonfmu's binary passes logger=; the native runtime does not
                from pythonfmu_compat import install
                self._error_hook = install(self, self._model.get("pythonfmu", pythonfmu.__version__))
            self._rt_init()
            self._identity = f"{type(self).__name__}:{self._model.get('hash', '-')}"
            self._vars = {}            # vr -> slavevars.Var
            self._by_name = {}         # name -> slavevars.Var
            self._params = ()          # parameters in vr order
            self._list_keys = {}       # (section, key) -> number of elements (also 0)
            self._mode = INSTANTIATED
            self._start_time = 0.0
            self._stop_time = None
            self._time = 0.0
            self._init_dirty = True
            self._broken = ""
            self._unit_key = None
            self.unit = None
            self._tables = {}
            self._rget = self._rset = self._iget = self._iset = None
            self._base_attrs = frozenset(self.__dict__) | {"_base_attrs", "_out_names"}
            self.define()
            self._finish()
        except FmuUsageError:
            raise
        except Exception as e:
            # no instance exists for the wrapper yet: the message can only go to stderr
            msg = (f"[{kwargs.get('instance_name')}] instantiating {type(self).__name__} failed: "
                   f"{type(e).__name__}: {e}")
            sys.stderr.write(msg + "\n")
            raise FmuUsageError(msg) from e

    def _load_model(self, resources):
        path = os.path.join(resources, MODEL_JSON) if resources else None
        if path is None or not os.path.exists(path):
            if self.NEEDS_MODEL:
                raise FmuUsageError(f"{type(self).__name__}: model file {MODEL_JSON} not found in "
                                    f"the resources folder {resources!r} (rebuild with piezo-fmu build)")
            return {}
        with open(path, encoding="utf-8") as f:
            return json.load(f)

    def define(self):
        """Register the variables (subclass hook)."""
        raise NotImplementedError

    def _finish(self):
        """Freeze the registry, build the per-mode access tables and the unit from the defaults."""
        self._params = tuple(v for v in self._vars.values() if v.causality == "parameter")
        self._out_names = tuple(v.name for v in self._vars.values() if v.causality == "output")
        rget = {vr: v.name for vr, v in self._vars.items() if v.type == "Real"}
        iget = {vr: v.name for vr, v in self._vars.items() if v.type == "Integer"}
        rin = {vr: v.name for vr, v in self._vars.items() if v.type == "Real" and v.causality == "input"}
        iin = {vr: v.name for vr, v in self._vars.items()
               if v.type == "Integer" and v.causality == "input"}
        # None -> every call takes the checked slow path (initialization: sets mark the initial
        # values dirty, gets compute them); {} -> every set is refused with a message
        self._tables = {
            INSTANTIATED: (rget, None, iget, None),
            INIT: (None, None, None, None),
            STEP: (rget, rin, iget, iin),
            BROKEN: (rget, rin, iget, iin),
            TERMINATED: (rget, {}, iget, {}),
        }
        self._set_mode(INSTANTIATED)
        if self.NEEDS_MODEL:
            problem = self._ensure_unit(transfer=False)
            if problem:
                raise FmuUsageError(f"the bundled model is invalid: {problem}")

    # -- registration ------------------------------------------------------------------------
    # -- subclass hooks ----------------------------------------------------------------------
    def make_unit(self, sections):
        """Build the core unit from ``sections`` (raise ValueError for an invalid combination)."""
        raise NotImplementedError

    def initialize(self, t0):
        """Compute the initial outputs at the start time ``t0`` from the inputs and parameters."""

    def step(self, t, h):
        """Advance one communication step; return False if an output came out non-finite."""
        raise NotImplementedError

    def describe_outputs(self):
        """Text naming the current unit outputs and inputs (for the non-finite-step error)."""
        d = self.__dict__
        return ", ".join(f"{v.name}={d[v.name]!r}" for v in self._vars.values()
                         if v.causality in ("input", "output"))

    # -- errors -----------------------------------------------------------------------------
    def _fail(self, msg):
        """Log ``msg`` with status error, then raise :class:`FmuUsageError` (the native runtime
        returns fmi2Error; under pythonfmu's binary the error hook of :mod:`pythonfmu_compat`
        first pays the references that binary drops for an exception)."""
        msg = f"[{self.instance_name}] {msg}"
        self.log(msg, Fmi2Status.error)
        self._error_hook(self)
        raise FmuUsageError(msg)

    def _where(self):
        return f"in {self._mode} at t={self._time!r}"

    # -- modes -------------------------------------------------------------------------------
    def _set_mode(self, mode):
        mode = _CANONICAL[mode]
        self._mode = mode
        self._rget, self._rset, self._iget, self._iset = self._tables[mode]
        self._rt_publish()

    @_guard("setup_experiment")
    def setup_experiment(self, start_time, stop_time=None, tolerance=None):
        if self._mode is not INSTANTIATED:
            self._fail(f"setup_experiment called {self._where()}; it is only allowed after instantiation")
        if not isinstance(start_time, (int, float)) or start_time - start_time != 0.0:
            self._fail(f"setup_experiment: start time {start_time!r} is not a finite number")
        self._start_time = float(start_time)
        self._time = self._start_time
        self._stop_time = stop_time if isinstance(stop_time, (int, float)) else None
        self._init_dirty = True

    @_guard("enter_initialization_mode")
    def enter_initialization_mode(self):
        if self._mode is not INSTANTIATED:
            self._fail(f"enter_initialization_mode called {self._where()}; it is only allowed once, "
                       "after instantiation (and setup_experiment)")
        self._init_dirty = True
        self._set_mode(INIT)

    @_guard("exit_initialization_mode")
    def exit_initialization_mode(self):
        if self._mode is not INIT:
            self._fail(f"exit_initialization_mode called {self._where()}; enter_initialization_mode "
                       "must come first")
        self._initial_values("exit_initialization_mode")
        self._set_mode(STEP)

    @_guard("terminate")
    def terminate(self):
        if self._mode not in (INIT, STEP, BROKEN):
            self._fail(f"terminate called {self._where()}")
        self._set_mode(TERMINATED)

    def _initial_values(self, where):
        """(Re)compute the initial outputs from the current inputs and parameters (idempotent)."""
        if self.NEEDS_MODEL:
            problem = self._ensure_unit(transfer=False)
            if problem:
                self._fail(f"{where}: invalid parameters: {problem}")
        self.initialize(self._start_time)
        bad = self._nonfinite_outputs()
        if bad:
            self._fail(f"{where}: initial output(s) not finite: {bad} ({self.describe_outputs()})")
        self._init_dirty = False

    def _nonfinite_outputs(self):
        d = self.__dict__
        bad = []
        for name in self._out_names:
            v = d[name]
            if type(v) is not float:
                v = d[name] = float(v)
            if v - v != 0.0:
                bad.append(f"{name}={v!r}")
        return ", ".join(bad)

    # -- stepping (hot path) -------------------------------------------------------------------
    def do_step(self, current_time, step_size):
        if self._mode is STEP and 0.0 < step_size < _INF and current_time - current_time == 0.0:
            try:
                ok = self.step(current_time, step_size)
            except FmuUsageError:
                raise
            except Exception as e:  # noqa: BLE001
                self._step_raised(current_time, step_size, e)
            if ok:
                self._time = current_time + step_size
                return True
            self._step_nonfinite(current_time, step_size)
        self._step_refused(current_time, step_size)

    @_guard("do_step")
    def _step_refused(self, t, h):
        if self._mode is BROKEN:
            self._fail(f"do_step(t={t!r}, h={h!r}) refused: {self._broken}; restore a saved FMU state "
                       "(fmi2SetFMUstate) or reset the instance")
        if self._mode is not STEP:
            why = {INSTANTIATED: "enter_initialization_mode and exit_initialization_mode have not "
                                 "been called",
                   INIT: "exit_initialization_mode has not been called",
                   TERMINATED: "the instance was terminated"}[self._mode]
            self._fail(f"do_step(t={t!r}, h={h!r}) called in {self._mode}: {why}")
        if not (isinstance(h, float) and 0.0 < h < _INF):
            self._fail(f"do_step: invalid communication step size h={h!r} at t={t!r} "
                       "(must be finite and > 0)")
        self._fail(f"do_step: current communication point t={t!r} is not finite")

    @_guard("do_step")
    def _step_nonfinite(self, t, h):
        self._broken = (f"the step from t={t!r} with h={h!r} produced a non-finite value "
                        f"({self.describe_outputs()})")
        self._set_mode(BROKEN)
        self._fail(f"do_step: {self._broken}; outputs keep their last finite values and the "
                   "instance refuses further steps until a saved FMU state is restored")

    @_guard("do_step")
    def _step_raised(self, t, h, e):
        self._broken = f"the step from t={t!r} with h={h!r} raised {type(e).__name__}: {e}"
        self._set_mode(BROKEN)
        self._fail(f"do_step: {self._broken}\n" + "".join(traceback.format_exception(e)[-3:]).rstrip())

    # -- Real / Integer access: fast paths --------------------------------------------------
    # explicit loops (a comprehension costs a function object per call in CPython 3.11);
    # dict tables: an unknown or negative vr misses (a list would wrap around)
    def get_real(self, vrs):
        d = self.__dict__
        g = self._rget
        out = []                       # must be a list of floats: the C++ side uses PyList_GetItem
        try:
            for vr in vrs:
                out.append(d[g[vr]])
        except Exception:  # noqa: BLE001 - unknown vr / initialization mode -> checked path
            return self._get_slow("Real", vrs)
        return out

    def set_real(self, vrs, values):
        d = self.__dict__
        s = self._rset
        i = 0
        try:
            for vr in vrs:
                v = values[i]
                i += 1
                if type(v) is not float or v - v != 0.0:    # v - v != 0 <=> NaN or inf
                    raise ValueError
                d[s[vr]] = v
        except Exception:  # noqa: BLE001 - anything unusual -> checked path with messages
            self._set_slow("Real", vrs, values)

    def get_integer(self, vrs):
        d = self.__dict__
        g = self._iget
        out = []
        try:
            for vr in vrs:
                out.append(d[g[vr]])
        except Exception:  # noqa: BLE001
            return self._get_slow("Integer", vrs)
        return out

    def set_integer(self, vrs, values):
        d = self.__dict__
        s = self._iset
        i = 0
        try:
            for vr in vrs:
                v = values[i]
                i += 1
                if type(v) is not int:
                    raise ValueError
                d[s[vr]] = v
        except Exception:  # noqa: BLE001
            self._set_slow("Integer", vrs, values)

    @_guard("get_boolean")
    def get_boolean(self, vrs):
        self._fail(f"get_boolean: this FMU has no Boolean variables (vr={list(vrs)})")

    @_guard("set_boolean")
    def set_boolean(self, vrs, values):
        self._fail(f"set_boolean: this FMU has no Boolean variables (vr={list(vrs)})")

    @_guard("get_string")
    def get_string(self, vrs):
        self._fail(f"get_string: this FMU has no String variables (vr={list(vrs)})")

    @_guard("set_string")
    def set_string(self, vrs, values):
        self._fail(f"set_string: this FMU has no String variables (vr={list(vrs)})")

    # -- checked slow paths ------------------------------------------------------------------
    def _lookup(self, where, type_name, vr):
        var = self._vars.get(vr)
        if var is None:
            self._fail(f"{where}: unknown value reference {vr!r}")
        if var.type != type_name:
            self._fail(f"{where}: variable {var.label()} is a {var.type}, not a {type_name}")
        return var

    @_guard("get")
    def _get_slow(self, type_name, vrs):
        where = f"get_{type_name.lower()}"
        if self._mode is INIT and self._init_dirty:
            self._initial_values(where)
        d = self.__dict__
        out = []
        for vr in vrs:
            var = self._lookup(where, type_name, vr)
            v = d[var.name]
            out.append(float(v) if type_name == "Real" else int(v))
        return out

    @_guard("set")
    def _set_slow(self, type_name, vrs, values):
        where = f"set_{type_name.lower()}"
        mode = self._mode
        if len(values) < len(vrs):
            self._fail(f"{where}: {len(vrs)} value references but {len(values)} values")
        staged = []
        for vr, v in zip(vrs, values):
            var = self._lookup(where, type_name, vr)
            if type_name == "Real":
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    self._fail(f"{where}: value {v!r} for variable {var.label()} is not a number")
                v = float(v)
            elif isinstance(v, bool) or not isinstance(v, int):
                self._fail(f"{where}: value {v!r} for variable {var.label()} is not an integer")
            if var.causality == "output":
                self._fail(f"{where}: variable {var.label()} is an output and cannot be set")
            if mode is TERMINATED:
                self._fail(f"{where}: variable {var.label()} cannot be set after terminate")
            if var.causality == "parameter" and mode in (STEP, BROKEN) and var.variability != "tunable":
                self._fail(f"{where}: parameter {var.label()} is fixed and cannot be set after "
                           f"initialization ({self._where()}); set it before exit_initialization_mode")
            if var.causality == "input":
                if v - v != 0.0:
                    self._fail(f"{where}: non-finite value {v!r} for input {var.label()} {self._where()}")
            else:
                problem = value_problem(var, v)
                if problem:
                    self._fail(f"{where}: parameter {var.label()} {problem}")
            staged.append((var, v))
        d = self.__dict__
        old = [(var, d[var.name]) for var, _ in staged]
        for var, v in staged:
            d[var.name] = v
        if mode is INSTANTIATED or mode is INIT:
            self._init_dirty = True
            return
        changed = [var.name for var, v in staged if var.causality == "parameter"]
        if changed:
            problem = self._ensure_unit(transfer=True)
            if problem:
                for var, v in old:
                    d[var.name] = v
                self._fail(f"{where}: rejected {', '.join(changed)} {self._where()}: {problem}; "
                           "the previous values were kept")
            self.log(f"[{self.instance_name}] tunable parameter(s) {', '.join(changed)} changed "
                     f"{self._where()}; effective from the next step", Fmi2Status.ok)

    # -- the unit --------------------------------------------------------------------------
    def _param_key(self):
        d = self.__dict__
        return tuple(repr(d[v.name]) for v in self._params)   # repr: exact, tells -0.0 from 0.0

    def _changed_since_build(self, key):
        if self._unit_key is None:
            return "the parameters"
        names = [v.name for v, a, b in zip(self._params, key, self._unit_key) if a != b]
        return ", ".join(names) or "the parameters"

    def _ensure_unit(self, transfer):
        """Rebuild the unit if the parameters changed since it was built; ``transfer`` carries the
        dynamic state over. Returns a problem description (``""`` on success), changes nothing on
        failure."""
        key = self._param_key()
        if key == self._unit_key:
            return ""
        sections = self.model_sections()
        if self.CHECK is not None:
            problems = self.CHECK(sections)
            if problems:
                return f"{self._changed_since_build(key)}: " + "; ".join(problems)
        try:
            unit = self.make_unit(sections)
            if sections.get("simulation", {}).get("engine") == "numba":
                self.COMPILE(unit)
        except Exception as e:  # noqa: BLE001 - the core says why
            return f"{self._changed_since_build(key)}: {e}"
        if transfer and self.unit is not None:
            try:
                unit.set_state(copy.deepcopy(self.unit.get_state()))
            except Exception as e:  # noqa: BLE001
                return f"{self._changed_since_build(key)}: the state cannot be carried over ({e})"
        self.unit = unit
        self._unit_key = key
        return ""

    # -- FMU state --------------------------------------------------------------------------
    def _coverage_problem(self):
        known = (self._base_attrs | set(self._by_name) | set(self.STATE_ATTRS)
                 | {"unit"} | {v.name for v in self.vars.values()})
        extra = sorted(set(self.__dict__) - known)
        if extra:
            return (f"instance attribute(s) {extra} are neither registered variables nor STATE_ATTRS: "
                    "the FMU state would be incomplete")
        return ""

    @_guard("get_fmu_state")
    def _get_fmu_state(self):
        problem = self._coverage_problem()
        if problem:
            self._fail(f"get_fmu_state: {problem}")
        d = self.__dict__
        st = State(format=STATE_FORMAT, identity=self._identity, mode=self._mode, time=self._time,
                    start_time=self._start_time, stop_time=self._stop_time,
                    init_dirty=self._init_dirty, broken=self._broken,
                    vars={v.name: d[v.name] for v in self._vars.values()},
                    unit=copy.deepcopy(self.unit.get_state()) if self.unit is not None else None,
                    hidden={a: copy.deepcopy(d[a]) for a in self.STATE_ATTRS})
        st.owner = weakref.ref(self)
        return st

    @_guard("set_fmu_state")
    def _set_fmu_state(self, state):
        if isinstance(state, InvalidState):
            self._fail(f"set_fmu_state: the serialized state could not be decoded: {state.get('error')}")
        if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
            self._fail("set_fmu_state: not an FMU state of this FMU (unknown format)")
        if state.get("identity") != self._identity:
            self._fail(f"set_fmu_state: the state belongs to {state.get('identity')!r}, this instance is "
                       f"{self._identity!r} (another FMU or another model)")
        values = state["vars"]
        if set(values) != set(self._by_name):
            self._fail("set_fmu_state: the state's variables do not match this FMU's")
        for name, v in values.items():
            var = self._by_name[name]
            ok = (type(v) is float) if var.type == "Real" else (type(v) is int)
            if not ok:
                self._fail(f"set_fmu_state: value {v!r} of variable {var.label()} has the wrong type")
        mode = state["mode"]
        if mode not in _MODES:
            self._fail(f"set_fmu_state: unknown mode {mode!r}")
        d = self.__dict__
        saved = {name: d[name] for name in values}
        d.update(values)
        if self.NEEDS_MODEL and mode not in (INSTANTIATED, INIT):
            problem = self._ensure_unit(transfer=False)
            if problem:
                d.update(saved)
                self._fail(f"set_fmu_state: the state's parameters are invalid: {problem}")
            self.unit.set_state(copy.deepcopy(state["unit"]))
        # in instantiated/initializationMode the dynamic state is recomputed at
        # exit_initialization_mode (the unit is rebuilt there if the parameters differ)
        for a, v in state["hidden"].items():
            d[a] = copy.deepcopy(v)
        self._time = state["time"]
        self._start_time = state["start_time"]
        self._stop_time = state["stop_time"]
        self._init_dirty = state["init_dirty"] or mode in (INSTANTIATED, INIT)
        self._broken = state["broken"]
        self._set_mode(mode)

    @staticmethod
    def _fmu_state_to_bytes(state):
        """Serialization as pythonfmu's binary calls it (static; an error is reported on the
        state's owner). The native runtime calls ``_rt_serialize`` on the instance instead."""
        try:
            return state_dumps(dict(state))
        except Exception as e:
            ref = getattr(state, "owner", None)
            owner = ref() if ref is not None else None
            if owner is None:
                raise
            owner._fail(f"serialize_fmu_state: {type(e).__name__}: {e}")

    @staticmethod
    def _fmu_state_from_bytes(data):
        try:
            return state_loads(data)
        except Exception as e:  # noqa: BLE001 - never raise here (no instance to report to)
            bad = InvalidState()
            bad["error"] = f"{type(e).__name__}: {e}"
            return bad

