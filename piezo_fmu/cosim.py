"""The co-simulation master: Actuator.fmu, Sensor.fmu and Compensator.fmu coupled by fmpy.

The wiring comes from :mod:`piezo_fmu.connections`. Every communication step ``t_k -> t_k + H``
(``t_k = t0 + k H``, computed from the step counter so the time does not drift):

* **Gauss-Seidel** (default), in the order of :data:`~piezo_fmu.connections.ORDER`: each
  component's inputs are set from the outputs just computed, then it steps::

      Actuator:    uc(t_k)                        -> x, F, ua at t_k+1
      Sensor:      F(t_k+1)                       -> us at t_k+1
      Compensator: us(t_k+1), x_ref(t_k+1)        -> uc, x_target for the next interval

  This is exactly the orchestration of the monolithic model (:mod:`piezo_fmu.simulate`), so at a
  communication step equal to the monolithic step the two agree to round-off.
* **Jacobi**: all inputs are set from the outputs at ``t_k``, then all components step. Each
  connection adds one step of delay, so the feedback path (Actuator -> Sensor -> Compensator)
  sees the measurement two steps late; the difference to Gauss-Seidel is O(H). The PID is
  designed to keep a 45 deg phase margin with those two delays at H = 1e-4 s (see
  :mod:`piezo_fmu.control_design`), so Jacobi runs (and Jacobi masters such as fmpy.ssp and
  libcosim) stay stable; at 1e-4 s they differ from Gauss-Seidel by about 0.7 % of the stroke.

Initialisation (both algorithms): all FMUs enter initialisation mode with the start values
applied, then, in Gauss-Seidel order, each gets its inputs from the outputs already known, leaves
initialisation mode and reports its initial outputs (the actuator at rest, the sensor's voltage,
the compensator's initial command). The initial values are therefore consistent, as in libcosim.

The reference: with a generator signal (sine, step, triangle, constant) the Compensator's own
generator is configured (``reference.*`` parameters) and its ``x_ref`` input is not used; with a
table (``Signal("table", ...)``) ``reference.signal = 0`` and the master feeds ``x_ref`` [um],
interpolated at the instant the Compensator samples it: the start time at initialisation and
``t_k+1`` in the step ``t_k -> t_k+1`` (the Compensator computes the command for the next interval
from its inputs at the end of the step).

Failures: a missing or unreadable FMU, a failing FMI call (with the messages the FMU logged)
and a model whose list parameters do not fit the FMUs raise :class:`~piezo_fmu.errors.UserError`
(:class:`~piezo_fmu.fmi.FmuError`); after an fmi2Fatal no further call is made on any instance.
The FMI binding itself (loading, ctypes calls, the FMUs' log) is :mod:`piezo_fmu.fmi`. Ctrl-C is taken
between FMI calls (inside an FMU it would fail the call with fmi2Error).

Speed: value references are batched per FMU and the FMI functions are called through ctypes on
preallocated arrays (one ``fmi2SetReal``, one ``fmi2DoStep`` and one ``fmi2GetReal`` per FMU
and step, without ``argtypes`` conversions; nothing is allocated per step but the step's time as
a ``c_double``). Results stream in chunks to ``sink``.
"""
from __future__ import annotations

import ctypes
import math
import time

import numpy as np

from .connections import COMPONENTS, CONNECTIONS, EXTERNAL_INPUTS, ORDER, RECORDED
from .core.compiled import ENGINES
from .core.control import INVERSES, MODES, SIGNALS
from .errors import UserError
from .fmi import BUILD_HINT, DEFAULT_FMU_DIR, DeferredInterrupt, FmuError, fmu_paths, load_slaves
from .simulate import COLUMNS, UNITS, Signal, SimResult

__all__ = ["ALGORITHMS", "CHUNK", "DEFAULT_FMU_DIR", "FmuError", "Plan", "cosimulate", "fmu_paths",
           "model_start_values", "run_component"]

ALGORITHMS = ("gauss-seidel", "jacobi")

# Which FMU carries the parameters of a model section (used when an FMU has no variable of a
# section at all, e.g. an actuator built without creep elements, to still detect a mismatch).
SECTION_OWNER = {
    "amplifier": "Actuator", "hysteresis": "Actuator", "creep": "Actuator",
    "mechanics": "Actuator", "resonance": "Actuator", "drift": "Actuator",
    "sensor": "Sensor",
    "compensator": "Compensator", "compensator.hysteresis": "Compensator",
    "compensator.dynamics": "Compensator",
}
# The FMUs whose kernels can run compiled (their simulation.engine parameter).
ENGINE_FMUS = ("Actuator", "Compensator")
# Model-file values that are strings and the Integer parameters that encode them.
ENUM_PARAMETERS = {"compensator.mode": MODES, "compensator.inverse": INVERSES}

CHUNK = 2000  # communication steps between progress reports / sink calls


# -- start values from a model file ---------------------------------------------------------------

def _same(a, b):
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


def model_start_values(model, slaves) -> dict:
    """``{component: {variable: value}}``: the model's parameters where they differ from the FMUs'.

    Parameters are named ``<section>.<key>`` (lists ``<section>.<key>[i]``, 1-based); the model's
    mode/inverse strings map to the Integer codes. A list whose length differs from what the FMU
    was built with cannot be applied (the FMU's structure is fixed) and raises :class:`UserError`.
    """
    out = {n: {} for n in slaves}
    for section, values in model.sections.items():
        if section == "model":
            continue
        for key, value in values.items():
            name = f"{section}.{key}"
            if isinstance(value, list):
                owner = next((n for n, s in slaves.items() if f"{name}[1]" in s.variables), None)
                if owner is None:
                    owner = SECTION_OWNER.get(section)
                    if owner not in slaves:
                        continue
                have = 0
                while f"{name}[{have + 1}]" in slaves[owner].variables:
                    have += 1
                if have != len(value):
                    raise UserError(
                        f"{name}: the model has {len(value)} values but {slaves[owner].path.name} "
                        f"was built with {have} (list lengths are fixed when an FMU is built); "
                        f"rebuild the FMUs from this model: piezo-fmu build --model "
                        f"{model.path or 'FILE.toml'} --out-dir {slaves[owner].path.parent}")
                for i, v in enumerate(value, 1):
                    out[owner][f"{name}[{i}]"] = float(v)
                continue
            owner = next((n for n, s in slaves.items() if name in s.variables), None)
            if owner is None:
                if SECTION_OWNER.get(section) in slaves:
                    raise UserError(f"{name}: {slaves[SECTION_OWNER[section]].path.name} has no such "
                                    f"parameter; rebuild the FMUs ({BUILD_HINT})")
                continue
            if isinstance(value, str):
                codes = ENUM_PARAMETERS.get(name)
                if codes is None or value not in codes:
                    continue
                value = codes[value]
            out[owner][name] = value
    # keep only what differs from the FMUs' start values
    for comp, values in out.items():
        s = slaves[comp]
        for name in list(values):
            start = s.start_value(name)
            v = values[name]
            if start is not None and _same(float(start), float(v)):
                del values[name]
    return out


def _reference_values(signal: Signal) -> dict:
    if signal.kind == "table":
        return {"reference.signal": SIGNALS["external"]}
    return {"reference.signal": SIGNALS[signal.kind], "reference.amplitude": signal.amplitude,
            "reference.offset": signal.offset, "reference.freq": signal.freq,
            "reference.phase": signal.phase_deg}


def _compensator_constant(model, slave, key):
    if model is not None:
        return float(model["compensator"][key])
    v = slave.start_value(f"compensator.{key}")
    if v is None:
        raise FmuError(f"{slave.path}: no start value for compensator.{key}")
    return float(v)


# -- the master -----------------------------------------------------------------------------------

def cosimulate(fmus, signal: Signal, stop_time: float, step: float = 1e-4, algorithm="gauss-seidel",
               mode=None, inverse=None, model=None, record_step=None, sink=None, progress=None,
               t0: float = 0.0, initial="consistent", chunk: int = CHUNK, engine=None) -> SimResult:
    """Co-simulate the three FMUs at a fixed communication step.

    Parameters
    ----------
    fmus : folder or dict
        A folder holding ``Actuator.fmu``, ``Sensor.fmu`` and ``Compensator.fmu`` (``None``: the
        folder ``./models`` where ``piezo-fmu build`` puts them), or ``{name: path}``.
    signal : Signal
        The reference (a generator configures the Compensator's; a table is fed to ``x_ref``).
    stop_time : float
        End time [s].
    step : float
        Communication step ``H`` [s].
    algorithm : {"gauss-seidel", "jacobi"}
    mode, inverse : str, optional
        Compensator mode (open, ff, fb, ff+fb) and inverse (static, dynamic); default: the
        model's, or the FMU's start value without a model.
    model : Model, optional
        Its parameters are applied as start values (as ``--model`` in ``simulate``); ``None``
        keeps the values the FMUs were built with.
    record_step : float, optional
        Recording interval [s], a multiple of ``step`` (default: every step).
    sink : callable, optional
        Called with each recorded chunk (an ``(n, 7)`` array in :data:`COLUMNS` order); nothing is
        kept in memory and the result holds only the last chunk.
    progress : callable, optional
        ``progress(fraction)`` after each chunk.
    t0 : float
        Start time [s].
    initial : {"consistent", "zero"}
        ``consistent`` (default) propagates the initial outputs in Gauss-Seidel order (as
        libcosim's initialisation does); ``zero`` starts every coupling from 0.0 and ignores
        the FMUs' initial outputs, as ``fmpy.ssp.simulate_ssp`` does (for comparisons).
    engine : {None, "python", "numba"}
        Kernel engine of the Actuator and Compensator FMUs (their ``simulation.engine``):
        ``numba`` runs the same kernels compiled (same results bit for bit, ~1/5 of the physics'
        time per step; compiling takes a few seconds once per process); ``None`` keeps the FMUs'
        setting (as built: ``python``).

    Returns a :class:`~piezo_fmu.simulate.SimResult` with the columns of ``simulate``;
    ``info["us_per_step"]`` is the wall time per communication step [us].
    """
    if algorithm not in ALGORITHMS:
        raise UserError(f"--algorithm: unknown {algorithm!r} ({', '.join(ALGORITHMS)})")
    if initial not in ("consistent", "zero"):
        raise UserError(f"initial: unknown {initial!r} (consistent, zero)")
    H = float(step)
    if not (H > 0 and math.isfinite(H)):
        raise UserError(f"--step: must be a positive number of seconds, got {step}")
    if not (math.isfinite(stop_time) and stop_time > t0):
        raise UserError(f"--stop-time: must be after the start time {t0} s, got {stop_time}")
    n_total = round((stop_time - t0) / H)
    if n_total < 1:
        raise UserError(f"--stop-time: {stop_time} s is shorter than one step of {H} s")
    rec_every = 1 if record_step is None else max(1, round(record_step / H))
    if mode is not None and mode not in MODES:
        raise UserError(f"--mode: unknown {mode!r} ({', '.join(MODES)})")
    if inverse is not None and inverse not in INVERSES:
        raise UserError(f"--inverse: unknown {inverse!r} ({', '.join(INVERSES)})")
    if engine is not None and engine not in ENGINES:
        raise UserError(f"--engine: unknown {engine!r} ({', '.join(ENGINES)})")
    paths = fmu_paths(fmus)
    t_end = t0 + n_total * H
    w_start = time.perf_counter()

    with DeferredInterrupt() as interrupt, load_slaves({n: paths[n] for n in ORDER}) as slaves:
        comp = slaves["Compensator"]
        # start values: model, then mode/inverse/reference
        values = model_start_values(model, slaves) if model is not None else {n: {} for n in slaves}
        cmode = mode or (model["compensator"]["mode"] if model is not None else None)
        cinv = inverse or (model["compensator"]["inverse"] if model is not None else None)
        if cmode is not None:
            values["Compensator"]["compensator.mode"] = MODES[cmode]
        if cinv is not None:
            values["Compensator"]["compensator.inverse"] = INVERSES[cinv]
        values["Compensator"].update(_reference_values(signal))
        if engine is not None:
            for name in ENGINE_FMUS:
                values[name]["simulation.engine"] = ENGINES[engine]
        use_ext = signal.kind == "table"
        if use_ext:
            k_ideal = _compensator_constant(model, comp, "k_ideal")
            k_amp = _compensator_constant(model, comp, "k_amp")
        for name, s in slaves.items():
            if values[name]:
                s.set_values(values[name])
            s.setup(t0, t_end)
        for s in slaves.values():
            s.enter_initialization(t0)
        if cmode is None:   # the FMU's own setting (its start value)
            cmode = {v: k for k, v in MODES.items()}.get(comp.start_value("compensator.mode"), "?")
        if cinv is None:
            cinv = {v: k for k, v in INVERSES.items()}.get(comp.start_value("compensator.inverse"), "?")

        plan = Plan.system(slaves)
        ext = plan.external  # (input array, index) of Compensator.x_ref, or None
        # initialisation in Gauss-Seidel order: inputs from the outputs already known
        x0 = float(signal.x_ref_at(t0, k_ideal, k_amp)) if use_ext else None
        for p in plan.steps:
            if initial == "zero":  # every coupling starts from 0.0 (fmpy.ssp)
                p.slave.exit_initialization(t0)
                for j in range(p.n_out):
                    p.out[j] = 0.0
                continue
            forward = [(i, src, j) for i, src, j, back in p.copies if not back]
            for i, src, j in forward:
                p.inp[i] = src[j]
            if use_ext and p.slave is comp:
                ext[0][ext[1]] = x0
            if forward or (use_ext and p.slave is comp):
                p.slave.check(p.slave.set_real(p.slave.c, p.in_vr, p.n_in, p.inp),
                              "fmi2SetReal (initial inputs)", t0)
            p.slave.exit_initialization(t0)
            p.slave.check(p.slave.get_real(p.slave.c, p.out_vr, p.n_out, p.out),
                          "fmi2GetReal (initial outputs)", t0)
        init_s = time.perf_counter() - w_start

        keep = [] if sink is None else None
        first = plan.record_row(t0)
        if keep is not None:
            keep.append(first)
        else:
            sink(first)
        last = first
        chunk = max(rec_every, (max(1, int(chunk)) // rec_every) * rec_every)
        loop = plan.gauss_seidel if algorithm == "gauss-seidel" else plan.jacobi
        done = 0
        wall = 0.0
        while done < n_total:
            n = min(chunk, n_total - done)
            xr = (signal.x_ref_at(t0 + H * np.arange(done + 1, done + n + 1), k_ideal, k_amp).tolist()
                  if use_ext else None)
            rows = n // rec_every
            buf = (ctypes.c_double * (plan.width * max(rows, 1)))()
            w0 = time.perf_counter()
            loop(done, n, t0, H, rec_every, xr, buf)
            wall += time.perf_counter() - w0
            done += n
            last = plan.table(buf, rows)
            if keep is not None:
                keep.append(last)
            else:
                sink(last)
            if progress is not None:
                progress(done / n_total)
            interrupt.check()

    table = np.vstack(keep) if keep is not None else last
    data = {name: table[:, i] for i, name in enumerate(COLUMNS)}
    info = {"mode": cmode, "inverse": cinv, "signal": signal.describe(), "units": dict(UNITS),
            "algorithm": algorithm, "initial": initial, "us_per_step": 1e6 * wall / n_total, "init_s": init_s,
            "total_s": time.perf_counter() - w_start, "fmus": {k: str(v) for k, v in paths.items()}}
    return SimResult(data, f"fmpy {algorithm}", H, wall, n_total, info)


class _Step:
    """The per-component data of the loop: slave, bound arrays and where its inputs come from."""

    __slots__ = (
        "copies",
        "in_names",
        "in_vr",
        "inp",
        "n_in",
        "n_out",
        "out",
        "out_names",
        "out_vr",
        "slave",
    )


class Plan:
    """Bound arrays for a set of components and the two loop bodies.

    Generic over the components (``order``: names in Gauss-Seidel order; ``ports``: name ->
    (input names, output names)), the ``connections`` (from component, variable, to component,
    variable), one optional ``external`` input (component, variable) fed from a table, and the
    ``recorded`` outputs ((component, variable), ...). :meth:`system` builds the piezo system from
    :mod:`piezo_fmu.connections`; the benchmark steps its pass-through floor with the same loops.

    Every component's outputs are a view into one frame (``fmi2GetReal`` writes there), so a
    recorded row of the loops' buffer is the time and the frame, copied with one ``memmove``
    (0.2 us per row against ~0.9 us for the columns one by one); :attr:`width` doubles per row,
    and :meth:`table` gives the rows with the ``recorded`` columns in their order.
    """

    def __init__(self, slaves, order, ports, connections, external, recorded):
        self.steps = []
        by_name = {}
        for name in order:
            s = slaves[name]
            p = _Step()
            p.slave = s
            p.in_names, p.out_names = (list(x) for x in ports[name])
            p.in_vr, p.inp, p.n_in = s.bind(p.in_names)
            p.out_vr, p.out, p.n_out = s.bind(p.out_names)
            p.copies = []
            by_name[name] = p
            self.steps.append(p)
        n_frame = sum(p.n_out for p in self.steps)
        self.frame = (ctypes.c_double * (n_frame + 1))()     # (+1: a view for a component without outputs)
        offset = {}
        at = 0
        for name, p in by_name.items():
            view = (ctypes.c_double * max(p.n_out, 1)).from_buffer(self.frame, 8 * at)
            view[:p.n_out] = p.out[:p.n_out]        # the start values
            p.out = view
            offset[name] = at
            at += p.n_out
        position = {n: i for i, n in enumerate(order)}
        for a, av, b, bv in connections:
            src, dst = by_name[a], by_name[b]
            # back: the source comes later in the Gauss-Seidel order (its value is from t_k)
            dst.copies.append((dst.in_names.index(bv), src.out, src.out_names.index(av),
                               position[a] >= position[b]))
        self.external = None
        self.ext_index, self.ext_step = 0, -1
        if external is not None:
            p = by_name[external[0]]
            self.external = (p.inp, p.in_names.index(external[1]))
            self.ext_index = self.external[1]
            self.ext_step = self.steps.index(p)
        self.rec = [offset[c] + by_name[c].out_names.index(v) for c, v in recorded]   # frame index
        self.n_frame = n_frame
        self.width = 1 + n_frame
        self._columns = [0] + [1 + i for i in self.rec]

    @classmethod
    def system(cls, slaves):
        """The actuator -> sensor -> compensator system of :mod:`piezo_fmu.connections`."""
        if len(EXTERNAL_INPUTS) != 1:
            raise NotImplementedError("the master feeds exactly one external input")
        ports = {n: ([p.name for p in COMPONENTS[n] if p.causality == "input"],
                     [p.name for p in COMPONENTS[n] if p.causality == "output"]) for n in ORDER}
        recorded = [next((c, v) for col2, c, v in RECORDED if col2 == col) for col in COLUMNS[1:]]
        return cls(slaves, ORDER, ports, CONNECTIONS, EXTERNAL_INPUTS[0], recorded)

    def record_row(self, t):
        """The time and the ``recorded`` outputs now, as a ``(1, 1 + len(recorded))`` array."""
        return np.array([[t] + [self.frame[i] for i in self.rec]])

    def table(self, buf, rows):
        """The first ``rows`` rows of a loop buffer as ``(rows, 1 + len(recorded))`` (a copy)."""
        return np.frombuffer(buf, dtype=float, count=self.width * rows).reshape(rows, self.width)[:, self._columns]

    def _bodies(self):
        # the raw calls (Slave.hot) take ctypes objects of the exact C types: the counts as c_size_t
        return [(p.slave, p.slave.c, *p.slave.hot,
                 p.in_vr, ctypes.c_size_t(p.n_in) if p.n_in else None, p.inp, p.out_vr,
                 ctypes.c_size_t(p.n_out), p.out,
                 tuple((i, src, j) for i, src, j, _ in p.copies), k == self.ext_step)
                for k, p in enumerate(self.steps)]

    def _recorder(self, buf):
        """``record(row, t)`` into ``buf``: the time, then the frame in one copy."""
        width, size, memmove = self.width, 8 * self.n_frame, ctypes.memmove
        base, frame = ctypes.addressof(buf), ctypes.addressof(self.frame)

        def record(row, t):
            b = width * row
            buf[b] = t
            memmove(base + 8 * (b + 1), frame, size)
        return record

    def gauss_seidel(self, k0, n, t0, H, rec_every, xr, buf):
        """Each component in turn: inputs from the outputs just computed, step, outputs."""
        bodies = self._bodies()
        ei = self.ext_index
        use_ext = xr is not None
        record = self._recorder(buf)
        row = 0
        double, h, no_prior = ctypes.c_double, ctypes.c_double(H), ctypes.c_int(1)
        for k in range(n):
            t = t0 + (k0 + k) * H
            tc = double(t)
            for s, c, setr, dostep, getr, in_vr, n_in, inp, out_vr, n_out, out, copies, ext in bodies:
                for i, src, j in copies:
                    inp[i] = src[j]
                if ext and use_ext:
                    inp[ei] = xr[k]
                if n_in:
                    st = setr(c, in_vr, n_in, inp)
                    if st:
                        s.check(st, "fmi2SetReal", t)
                st = dostep(c, tc, h, no_prior)
                if st:
                    s.check(st, "fmi2DoStep", t)
                st = getr(c, out_vr, n_out, out)
                if st:
                    s.check(st, "fmi2GetReal", t)
            if (k + 1) % rec_every == 0:
                record(row, t0 + (k0 + k + 1) * H)
                row += 1

    def jacobi(self, k0, n, t0, H, rec_every, xr, buf):
        """All inputs from the outputs at t_k, then every component steps."""
        bodies = self._bodies()
        ei = self.ext_index
        use_ext = xr is not None
        record = self._recorder(buf)
        row = 0
        double, h, no_prior = ctypes.c_double, ctypes.c_double(H), ctypes.c_int(1)
        for k in range(n):
            t = t0 + (k0 + k) * H
            tc = double(t)
            for s, c, setr, dostep, getr, in_vr, n_in, inp, out_vr, n_out, out, copies, ext in bodies:
                for i, src, j in copies:
                    inp[i] = src[j]
                if ext and use_ext:
                    inp[ei] = xr[k]
                if n_in:
                    st = setr(c, in_vr, n_in, inp)
                    if st:
                        s.check(st, "fmi2SetReal", t)
            for s, c, setr, dostep, getr, in_vr, n_in, inp, out_vr, n_out, out, copies, ext in bodies:
                st = dostep(c, tc, h, no_prior)
                if st:
                    s.check(st, "fmi2DoStep", t)
                st = getr(c, out_vr, n_out, out)
                if st:
                    s.check(st, "fmi2GetReal", t)
            if (k + 1) % rec_every == 0:
                record(row, t0 + (k0 + k + 1) * H)
                row += 1


# -- one component driven by input sequences --------------------------------------------------------

def run_component(fmu, name, inputs: dict, outputs, step, t0=0.0, model=None, start_values=None):
    """Co-simulate one FMU alone with its inputs held over each communication step.

    ``inputs`` maps input names to sequences ``u[k]`` applied over ``t0 + k step -> t0 + (k+1) step``
    (all of one length ``n``). Returns ``{output: array of n + 1 values}`` (the initial outputs,
    then after each step). Uses the master's FMU binding (batched raw ctypes calls).
    """
    paths = fmu_paths({name: fmu}, names=(name,))
    H = float(step)
    names = list(inputs)
    seqs = [np.asarray(inputs[k], dtype=float).tolist() for k in names]
    n = len(seqs[0]) if seqs else 0
    if any(len(s) != n for s in seqs):
        raise UserError("run_component: all input sequences must have the same length")
    with load_slaves(paths) as slaves:
        s = slaves[name]
        values = model_start_values(model, slaves)[name] if model is not None else {}
        values.update(start_values or {})
        if values:
            s.set_values(values)
        s.setup(t0, t0 + n * H)
        s.enter_initialization(t0)
        in_vr, inp, n_in = s.bind(names)
        out_vr, out, n_out = s.bind(list(outputs))
        if n_in:
            for j, seq in enumerate(seqs):
                inp[j] = seq[0] if n else 0.0
            s.check(s.set_real(s.c, in_vr, n_in, inp), "fmi2SetReal (initial inputs)", t0)
        s.exit_initialization(t0)
        res = np.empty((n + 1, n_out))
        s.check(s.get_real(s.c, out_vr, n_out, out), "fmi2GetReal", t0)
        res[0] = out[:n_out]
        setr, dostep, getr, c = s.set_real, s.do_step, s.get_real, s.c
        for k in range(n):
            t = t0 + k * H
            for j in range(n_in):
                inp[j] = seqs[j][k]
            if n_in:
                st = setr(c, in_vr, n_in, inp)
                if st:
                    s.check(st, "fmi2SetReal", t)
            st = dostep(c, t, H, 1)
            if st:
                s.check(st, "fmi2DoStep", t)
            st = getr(c, out_vr, n_out, out)
            if st:
                s.check(st, "fmi2GetReal", t)
            res[k + 1] = out[:n_out]
    return {o: res[:, i] for i, o in enumerate(outputs)}


