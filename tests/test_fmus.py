"""The three co-simulation FMUs (and the PassThrough floor) as built by piezo_fmu.builder.

Proves: fmpy validation; the interface contract of piezo_fmu.connections and the model's
parameters; `fmpy simulate` from the defaults and with an input file; bit-exact get/set and
serialized FMU state; several instances of all FMUs side by side; the adapters are thin (an FMU
stepped through fmpy equals the core unit stepped directly, and the Gauss-Seidel loop of the three
equals the monolithic model); bad calls give a non-OK status, a logged message naming the variable,
and the process and the instance survive (risky cases in subprocesses).
"""
from __future__ import annotations

import csv
import json
import math
import shutil
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
from fmpy import extract, read_model_description
from fmpy.fmi1 import FMICallException
from fmpy.fmi2 import (
    FMU2Slave,
)
from fmpy.validation import validate_fmu

from piezo_fmu import fmilog
from piezo_fmu.connections import COMPONENTS
from piezo_fmu.core import compiled, units
from piezo_fmu.model import SCHEMA, load_model

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SYSTEM = ("Actuator", "Sensor", "Compensator")
MODEL = load_model(ROOT / "models" / "paper.toml")
ERROR = 3

# ---------------------------------------------------------------------------------------------
# a small fmpy host that captures the FMU log
# ---------------------------------------------------------------------------------------------
LOG = []      # (instance, status, category, message)


def _logger(instance, status, category, message):
    LOG.append((instance, status, category, message))


# fmpy's native log proxy is process-global: use the one process-wide logger (piezo_fmu.fmilog)
fmilog.listen(_logger)


class Fmu:
    """An extracted FMU with its variables by name."""

    def __init__(self, path):
        self.path = str(path)
        self.md = read_model_description(self.path)
        self.dir = extract(self.path, unzipdir=tempfile.mkdtemp(prefix="fmu_test_"))
        self.var = {v.name: v for v in self.md.modelVariables}
        self.name = self.md.coSimulation.modelIdentifier

    def slave(self, instance="i", init=True, t0=0.0, values=None):
        return Slave(self, instance, init, t0, values)

    def close(self):
        shutil.rmtree(self.dir, ignore_errors=True)


class Slave:
    """One instance, driven through fmpy's FMU2Slave (set/get by variable name)."""

    def __init__(self, fmu, instance, init=True, t0=0.0, values=None):
        self.fmu = fmu
        self.s = FMU2Slave(guid=fmu.md.guid, unzipDirectory=fmu.dir, modelIdentifier=fmu.name,
                           instanceName=instance)
        self.s.instantiate(callbacks=fmilog.callbacks(), loggingOn=True)
        self.t = t0
        if init:
            self.s.setupExperiment(startTime=t0)
            self.s.enterInitializationMode()
            self.set(values or {})
            self.s.exitInitializationMode()

    def set(self, values):
        for name, v in values.items():
            var = self.fmu.var[name]
            if var.type == "Integer":
                self.s.setInteger([var.valueReference], [int(v)])
            else:
                self.s.setReal([var.valueReference], [float(v)])

    def get(self, *names):
        out = []
        for n in names:
            var = self.fmu.var[n]
            f = self.s.getInteger if var.type == "Integer" else self.s.getReal
            out.append(f([var.valueReference])[0])
        return out

    def step(self, h):
        self.s.doStep(self.t, h)
        self.t += h

    def free(self):
        self.s.terminate()
        self.s.freeInstance()


def call(fn, *args):
    """(status, [messages logged during the call])."""
    k = len(LOG)
    try:
        fn(*args)
        status = 0
    except FMICallException as e:
        status = e.status
    return status, [m for m in LOG[k:]]


def bits(values):
    return struct.pack(f"<{len(values)}d", *values)


OUTPUTS = {name: [p.name for p in ports if p.causality == "output"] for name, ports in COMPONENTS.items()}
INPUTS = {name: [p.name for p in ports if p.causality == "input"] for name, ports in COMPONENTS.items()}


def inputs_at(name, t, uc_prev=0.0):
    """Deterministic, varying inputs at time t (the Compensator sees a fake plant driven by uc)."""
    if name == "Actuator":
        return {"uc": 6.0 + 6.0 * math.sin(2 * math.pi * 40.0 * t) + 2.0 * math.sin(2 * math.pi * 230.0 * t)}
    if name == "Sensor":
        return {"F": 300.0 * (1.0 + math.sin(2 * math.pi * 25.0 * t))}
    if name == "Compensator":
        return {"x_ref": 0.0, "us": 0.44 * 0.45 * uc_prev * (1.0 + 0.05 * math.sin(2 * math.pi * 7.0 * t))}
    return {"u": math.sin(t)}


def drive(slave, n, h=1e-4, k0=0):
    """n steps with inputs_at(k h); returns the outputs after every step as bytes."""
    name = slave.fmu.name
    rows = []
    for k in range(k0, k0 + n):
        uc = slave.get("uc")[0] if name == "Compensator" else 0.0
        slave.set(inputs_at(name, k * h, uc))
        slave.step(h)
        rows.append(bits(slave.get(*OUTPUTS[name])))
    return b"".join(rows)


def restore(slave, state, t):
    slave.s.setFMUstate(state)
    slave.t = t


@pytest.fixture(scope="module")
def fmus(built_fmus):
    loaded = {name: Fmu(path) for name, path in built_fmus.items()}
    yield loaded
    for f in loaded.values():
        f.close()


def run_python(code, *args, timeout=300):
    """Run code in a fresh interpreter that can import this module (as T)."""
    prelude = f"import sys; sys.path.insert(0, {str(HERE)!r}); sys.path.insert(0, {str(ROOT)!r})\n"
    return subprocess.run([sys.executable, "-c", prelude + code, *map(str, args)],
                          capture_output=True, text=True, check=False, timeout=timeout)


# ---------------------------------------------------------------------------------------------
# 1. validation and the modelDescription contract
# ---------------------------------------------------------------------------------------------
def test_fmpy_validation_finds_no_problem(built_fmus, passthrough_fmu):
    for path in [*built_fmus.values(), passthrough_fmu]:
        assert validate_fmu(str(path)) == [], path


def test_interface_matches_connections_and_model(built_fmus):
    expected_sections = {
        "Actuator": {"amplifier": None, "hysteresis": None, "creep": None, "mechanics": None,
                     "resonance": None, "drift": None, "simulation": ("actuator_max_step", "stroke_path")},
        "Sensor": {"sensor": None},
        "Compensator": {"compensator": None, "compensator.hysteresis": None, "compensator.dynamics": None},
    }
    for name, path in built_fmus.items():
        md = read_model_description(str(path), validate=True)
        var = {v.name: v for v in md.modelVariables}
        units_defined = {u.name for u in md.unitDefinitions}
        assert md.coSimulation.canGetAndSetFMUstate and md.coSimulation.canSerializeFMUstate
        assert md.defaultExperiment is not None and md.defaultExperiment.stepSize is not None
        # interface: exactly the ports of piezo_fmu.connections
        io = {v.name for v in md.modelVariables if v.causality in ("input", "output")}
        assert io == {p.name for p in COMPONENTS[name]}
        for p in COMPONENTS[name]:
            v = var[p.name]
            assert (v.causality, v.unit, v.type, v.description) == (p.causality, p.unit, "Real", p.description)
        # every variable: description, explicit variability; every Real: a defined unit
        for v in md.modelVariables:
            assert v.description and v.variability in ("fixed", "tunable", "continuous")
            if v.type == "Real":
                assert v.unit in units_defined, v.name
        # outputs: no direct feedthrough, and exactly the InitialUnknowns
        assert [u.variable.name for u in md.outputs] == OUTPUTS[name]
        assert all(u.dependencies == [] for u in md.outputs)
        assert [u.variable.name for u in md.initialUnknowns] == OUTPUTS[name]
        # parameters: every key of the sections, start = the model value exactly, unit from SCHEMA
        params = set()
        for sec, keys in expected_sections[name].items():
            for key in (keys or SCHEMA[sec]):
                spec, value = SCHEMA[sec][key], MODEL.sections[sec][key]
                if isinstance(value, list):
                    names = [f"{sec}.{key}[{i}]" for i in range(1, len(value) + 1)]
                    values = value
                else:
                    names, values = [f"{sec}.{key}"], [value]
                for n, x in zip(names, values):
                    v = var[n]
                    params.add(n)
                    assert v.causality == "parameter"
                    if spec.kind == "str":
                        assert v.type == "Integer" and int(v.start) == {
                            "mode": {"open": 0, "ff": 1, "fb": 2, "ff+fb": 3},
                            "inverse": {"static": 0, "dynamic": 1},
                            "pickoff": {"stack": 0, "load": 1, "contact": 2},
                            "position": {"output": 0, "drive": 1},
                            "stroke_path": {"linear": 0, "amplifier_lag": 1}}[key][x]
                    elif spec.kind == "int":
                        assert v.type == "Integer" and int(v.start) == x
                    else:
                        assert v.type == "Real" and v.unit == spec.unit
                        assert float(v.start) == x and str(float(v.start)) == str(x), n   # exact
                        assert spec.doc in v.description
        if name == "Compensator":
            ref = {n: var[n] for n in var if n.startswith("reference.")}
            params |= set(ref)
            assert {n: v.start for n, v in ref.items()} == {
                "reference.signal": "1", "reference.amplitude": "45.0", "reference.offset": "45.0",
                "reference.freq": "10.0", "reference.phase": "-90.0"}
            assert ref["reference.phase"].unit == "deg" and ref["reference.amplitude"].unit == "V"
        if name in ("Actuator", "Compensator"):           # the kernel engine, python by default
            eng = var["simulation.engine"]
            assert (eng.type, eng.start, eng.variability) == ("Integer", "0", "fixed")
            assert "0 python, 1 numba" in eng.description
            params.add("simulation.engine")
        assert params == {v.name for v in md.modelVariables if v.causality == "parameter"}


def test_runtime_defaults_equal_start_values(fmus):
    for f in fmus.values():
        s = f.slave("defaults", init=False)
        try:
            for v in f.md.modelVariables:
                if v.start is None:
                    continue
                got = s.get(v.name)[0]
                want = int(v.start) if v.type == "Integer" else float(v.start)
                assert got == want and type(got) is type(want), v.name
        finally:
            s.s.freeInstance()


def test_variabilities_are_the_documented_choice(fmus):
    tunable = {n for f in fmus.values() for n, v in f.var.items() if v.variability == "tunable"}
    assert {"amplifier.k_amp", "amplifier.u_max", "hysteresis.weights[3]", "simulation.actuator_max_step",
            "sensor.offset", "sensor.noise_std", "compensator.Kp", "compensator.uc_max",
            "reference.signal", "reference.freq"} <= tunable
    fixed = {n for f in fmus.values() for n, v in f.var.items() if v.variability == "fixed"}
    assert {"amplifier.delay", "hysteresis.thresholds[2]", "hysteresis.u_norm", "mechanics.m",
            "resonance.f_n", "sensor.d11", "sensor.seed", "compensator.mode", "compensator.inverse",
            "compensator.filter_hz", "compensator.hysteresis.weights[1]", "compensator.dynamics.den[1]",
            "simulation.engine"} <= fixed


# ---------------------------------------------------------------------------------------------
# 2. the fmpy command line
# ---------------------------------------------------------------------------------------------
def fmpy_cli(*args):
    exe = Path(sys.executable).with_name("fmpy")
    exe = str(exe) if exe.exists() else shutil.which("fmpy")
    return subprocess.run([exe, *map(str, args)], capture_output=True, text=True, check=False, timeout=300)


def read_result(path):
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    head = rows[0]
    data = np.array([[float(x) for x in r] for r in rows[1:]])
    return {h: data[:, i] for i, h in enumerate(head)}


@pytest.mark.parametrize("name", SYSTEM)
def test_cli_simulate_defaults(built_fmus, tmp_path, name):
    out = tmp_path / "out.csv"
    r = fmpy_cli("simulate", built_fmus[name], "--output-file", out)
    assert r.returncode == 0, r.stderr
    res = read_result(out)
    t = res["time"]
    if name == "Actuator":     # uc = 3 V (start value): the exact 30 V step response of the amplifier
        a = MODEL["amplifier"]
        assert len(t) == 201 and t[-1] == pytest.approx(0.02)
        ua = 3.0 * a["k_amp"] * (1.0 - np.exp(-t / (a["R"] * a["C_a"])))
        np.testing.assert_allclose(res["ua"], ua, rtol=1e-9, atol=1e-12)
        assert res["x"][0] == 0.0 and 1.0 < res["x"][-1] < 5.0 and np.all(np.diff(res["x"][50:]) >= 0)
        assert res["F"][-1] > 100.0
    elif name == "Sensor":     # at rest: the 1 mV noise of the model, seed 1
        assert len(t) == 1001
        assert 0.8e-3 < np.std(res["us"]) < 1.2e-3 and abs(np.mean(res["us"])) < 2e-4
    else:                      # the built-in 10 Hz, 0-90 V reference; no plant, so the PID winds up
        c = MODEL["compensator"]
        assert len(t) == 1001
        x_ref = c["k_ideal"] * (45.0 + 45.0 * np.sin(2 * np.pi * 10.0 * t - np.pi / 2))
        np.testing.assert_allclose(res["x_target"], x_ref, rtol=0, atol=1e-12)
        assert np.all(res["uc"] >= c["uc_min"]) and np.all(res["uc"] <= c["uc_max"])
        assert res["uc"][-1] == c["uc_max"]


def replay_core(name, res, sections=None, **kw):
    """Outputs of the core unit driven with the inputs fmpy applied (recorded row k+1 = input of step k)."""
    sections = sections or MODEL.sections
    t = res["time"]
    outs = {n: [] for n in OUTPUTS[name]}
    if name == "Actuator":
        u = units.actuator_from(sections)
        u.reset(t[0])
        for k in range(len(t) - 1):
            u.advance(res["uc"][k + 1], t[k + 1] - t[k])
            for n, v in zip(("x", "F", "ua"), u.out[:3]):
                outs[n].append(v)
    elif name == "Sensor":
        u = units.sensor_from(sections)
        u.reset(res["F"][0])
        for k in range(len(t) - 1):
            outs["us"].append(u.step(res["F"][k + 1], t[k + 1] - t[k]))
    else:
        u = units.compensator_from(sections, **kw)
        u.reset()
        u.initialize(t[0], res["x_ref"][0], res["us"][0])
        for k in range(len(t) - 1):
            h = t[k + 1] - t[k]
            outs["uc"].append(u.step(t[k] + h, res["x_ref"][k + 1], res["us"][k + 1], h))
            outs["x_target"].append(u.out[1])
    return {n: np.array(v) for n, v in outs.items()}


@pytest.mark.parametrize("name", SYSTEM)
def test_cli_simulate_input_file(built_fmus, tmp_path, name):
    inp = tmp_path / "in.csv"
    extra = []
    if name == "Actuator":       # a ramp, then a step down (a discontinuity between grid points)
        inp.write_text('"time","uc"\n0.0,0.0\n0.01,8.0\n0.01234,8.0\n0.01234,1.0\n0.02,1.0\n')
    elif name == "Sensor":
        inp.write_text('"time","F"\n0.0,0.0\n0.05,600.0\n0.1,-100.0\n')
    else:                        # external reference (reference.signal = 0) and a sensor signal
        inp.write_text('"time","x_ref","us"\n0.0,0.0,0.0\n0.05,2.0,0.5\n0.1,0.5,0.1\n')
        extra = ["--start-values", "reference.signal", "0"]
    out = tmp_path / "out.csv"
    names = INPUTS[name] + OUTPUTS[name]
    r = fmpy_cli("simulate", built_fmus[name], "--input-file", inp, "--output-file", out,
                 "--output-variables", *names, *extra)
    assert r.returncode == 0, r.stderr
    res = read_result(out)
    t = res["time"]
    # the inputs arrived as given (linear interpolation of the table at the communication points)
    table = np.genfromtxt(inp, delimiter=",", names=True)
    for n in INPUTS[name]:
        cont = t < 0.01234 if name == "Actuator" else np.ones_like(t, bool)
        np.testing.assert_allclose(res[n][1:][cont[:-1]], np.interp(t[:-1][cont[:-1]], table["time"], table[n]),
                                   rtol=1e-12, atol=1e-12)
    if name == "Actuator":
        assert 0.01234 in t                     # fmpy split the step at the input discontinuity
    # the outputs are exactly those of the core unit fed with the same inputs
    want = replay_core(name, res, signal="external") if name == "Compensator" else replay_core(name, res)
    for n in OUTPUTS[name]:
        assert bits(res[n][1:]) == bits(want[n]), n
    if name == "Compensator":
        assert bits(res["x_target"][1:]) == bits(res["x_ref"][1:])     # x_target = the x_ref input


# ---------------------------------------------------------------------------------------------
# 3. FMU state: save -> step -> restore -> step is bit-exact; serialization too
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", SYSTEM)
def test_state_restore_and_serialization_bit_exact(fmus, name):
    f = fmus[name]
    s = f.slave("state")
    warm = 4050 if name == "Sensor" else 300      # the Sensor crosses a 4096-sample noise block below
    drive(s, warm)
    t = s.t
    st = s.s.getFMUstate()
    a = drive(s, 200, k0=warm)
    restore(s, st, t)
    b = drive(s, 200, k0=warm)
    restore(s, st, t)                             # the same state object, restored a second time
    c = drive(s, 200, k0=warm)
    blob = s.s.serializeFMUstate(st)
    st2 = s.s.deSerializeFMUstate(blob)
    assert s.s.serializeFMUstate(st2) == blob     # deterministic, exact
    restore(s, st2, t)
    d = drive(s, 200, k0=warm)
    fresh = f.slave("fresh", init=False)          # a new instance takes the deserialized state
    st3 = fresh.s.deSerializeFMUstate(blob)
    restore(fresh, st3, t)
    e = drive(fresh, 200, k0=warm)
    assert a == b == c == d == e
    # the state matters (hysteresis memory, filters, PID, noise position): a fresh run differs
    other = f.slave("other")
    other.t = t
    assert drive(other, 200, k0=warm) != a
    state = json.loads(blob)
    assert state["identity"].startswith(name + ":") and state["mode"] == "stepMode"
    if name == "Sensor":
        assert state["unit"]["noise"]["pos"] > 0 and state["unit"]["noise"]["filled"]
    if name == "Actuator":
        assert any(z != 0.0 for z in state["unit"]["z"])
    if name == "Compensator":
        assert state["unit"]["pid"][0] != 0.0 and any(z != 0.0 for z in state["unit"]["inv_z"])
    for x in (st, st2, st3):
        (s if x is not st3 else fresh).s.freeFMUstate(x)
    for x in (s, fresh, other):
        x.free()


def test_state_restores_tunable_parameters(fmus):
    """A state saved before a tunable change brings the old value (and the unit built from it) back."""
    f = fmus["Actuator"]
    s = f.slave("tune")
    drive(s, 100)
    t = s.t
    st = s.s.getFMUstate()
    ref = drive(s, 100, k0=100)
    restore(s, st, t)
    s.set({"amplifier.k_amp": 12.0, "hysteresis.weights[2]": 0.3})
    changed = drive(s, 100, k0=100)
    assert changed != ref
    restore(s, st, t)
    assert s.get("amplifier.k_amp", "hysteresis.weights[2]") == [10.0, MODEL["hysteresis"]["weights"][1]]
    assert drive(s, 100, k0=100) == ref
    s.s.freeFMUstate(st)
    s.free()


# ---------------------------------------------------------------------------------------------
# 4. side by side; the adapters are thin
# ---------------------------------------------------------------------------------------------
def test_all_fmus_side_by_side_several_instances(fmus):
    configs = {  # instance -> (FMU, parameters set at initialization)
        "act1": ("Actuator", {}), "act2": ("Actuator", {"amplifier.k_amp": 8.0}),
        "act3": ("Actuator", {"mechanics.m": 0.03}),
        "sen1": ("Sensor", {}), "sen2": ("Sensor", {"sensor.seed": 7}),
        "com1": ("Compensator", {}), "com2": ("Compensator", {"compensator.mode": 1, "reference.freq": 20.0}),
    }
    alone = {}
    for inst, (name, values) in configs.items():      # each alone, one after the other
        s = fmus[name].slave(inst + "_alone", values=values)
        alone[inst] = drive(s, 150)
        s.free()
    live = {inst: fmus[name].slave(inst, values=values) for inst, (name, values) in configs.items()}
    together = {inst: [] for inst in live}
    for k in range(150):                              # all interleaved, step by step
        for inst, s in live.items():
            together[inst].append(drive(s, 1, k0=k))
    for inst in live:
        assert b"".join(together[inst]) == alone[inst], inst
    assert alone["act1"] != alone["act2"] != alone["act3"] and alone["sen1"] != alone["sen2"]
    assert alone["com1"] != alone["com2"]
    bundles = sorted(m for m in sys.modules if m.startswith("_pz_") and m.count(".") == 0)
    assert len([b for b in bundles if b.startswith(("_pz_actuator_", "_pz_sensor_", "_pz_compensator_"))]) == 3, bundles
    for s in live.values():
        s.free()


REFERENCE_DEFAULT = {"signal": "sine", "amplitude": 45.0, "offset": 45.0, "freq": 10.0, "phase_deg": -90.0}
LABELS = {"compensator.mode": {0: "open", 1: "ff", 2: "fb", 3: "ff+fb"},
          "compensator.inverse": {0: "static", 1: "dynamic"},
          "reference.signal": {0: "external", 1: "sine", 2: "step", 3: "triangle", 4: "constant"},
          "simulation.stroke_path": {0: "linear", 1: "amplifier_lag"}}


def sections_with(values):
    """The model's sections and the reference with FMU parameter values applied."""
    sections = json.loads(json.dumps(MODEL.sections, allow_nan=True))
    ref = dict(REFERENCE_DEFAULT)
    for name, v in values.items():
        if name == "simulation.engine":       # how the unit runs, not what it computes
            continue
        v = LABELS.get(name, {}).get(v, v)
        base, _, idx = name.partition("[")
        sec, key = base.rsplit(".", 1)
        if sec == "reference":
            ref[{"phase": "phase_deg"}.get(key, key)] = v
        elif idx:
            sections[sec][key][int(idx[:-1]) - 1] = v
        else:
            sections[sec][key] = v
    return sections, ref


def fmu_and_core(fmu, values, hs, instance="both"):
    """Drive the FMU (through fmpy) and the core unit built from the same parameters with the same
    inputs and step sizes; returns both output sequences as bytes."""
    name = fmu.name
    s = fmu.slave(instance, values=values)
    sections, ref = sections_with(values)
    if name == "Actuator":
        u = units.actuator_from(sections)
        u.reset(0.0)
    elif name == "Sensor":
        u = units.sensor_from(sections)
        u.reset(0.0)
    else:
        u = units.compensator_from(sections, **ref)
        u.reset()
        u.initialize(0.0, 0.0, 0.0)
    got, want = [], []
    t = 0.0
    uc = s.get("uc")[0] if name == "Compensator" else 0.0
    for h in hs:
        inp = inputs_at(name, t, uc)
        s.set(inp)
        s.s.doStep(t, h)
        got += s.get(*OUTPUTS[name])
        if name == "Actuator":
            u.advance(inp["uc"], h)
            want += u.out[:3]
        elif name == "Sensor":
            want.append(u.step(inp["F"], h))
        else:
            want += [u.step(t + h, inp["x_ref"], inp["us"], h), u.out[1]]
            uc = got[-2]
        t += h
    s.free()
    return bits(got), bits(want)


@pytest.mark.parametrize("name", SYSTEM)
def test_fmu_equals_core_unit(fmus, name):
    """The same inputs through fmpy and straight into the core unit: identical to the last bit."""
    hs = [1e-4] * 200 + [3.7e-4] * 100 + [2.5e-5] * 100     # step size changes re-discretise
    got, want = fmu_and_core(fmus[name], {}, hs)
    assert got == want


@pytest.mark.skipif(not compiled.available(), reason="numba is not installed")
@pytest.mark.parametrize("name", ("Actuator", "Compensator"))
def test_compiled_engine_equals_the_interpreted_core_unit_and_saves_its_state(fmus, name):
    """simulation.engine = 1 (numba): the FMU still equals the interpreted core unit to the last
    bit (step-size changes included), and its state (the packed buffer's hysteresis memory,
    filters, PID) saves, serializes and restores bit for bit, also into a fresh instance."""
    hs = [1e-4] * 200 + [3.7e-4] * 100 + [2.5e-5] * 100
    got, want = fmu_and_core(fmus[name], {"simulation.engine": 1}, hs)
    assert got == want
    f = fmus[name]
    s = f.slave("compiled", values={"simulation.engine": 1})
    assert s.get("simulation.engine") == [1]
    drive(s, 300)
    t = s.t
    st = s.s.getFMUstate()
    a = drive(s, 200, k0=300)
    blob = s.s.serializeFMUstate(st)
    fresh = f.slave("fresh", init=False)
    st2 = fresh.s.deSerializeFMUstate(blob)
    restore(fresh, st2, t)
    assert fresh.get("simulation.engine") == [1]
    assert drive(fresh, 200, k0=300) == a
    restore(s, st, t)
    assert drive(s, 200, k0=300) == a
    other = f.slave("other")                       # the interpreted engine from the start
    drive(other, 300)
    assert drive(other, 200, k0=300) == a
    # a fixed parameter: refused once initialized
    status, msgs = call(s.s.setInteger, [f.var["simulation.engine"].valueReference], [0])
    assert status != 0 and any("simulation.engine" in m[3] for m in msgs)
    for x, y in ((s, st), (fresh, st2)):
        x.s.freeFMUstate(y)
    for x in (s, fresh, other):
        x.free()


def test_parameters_set_before_initialization_take_effect(fmus):
    cases = {"Actuator": {"mechanics.m": 0.05, "amplifier.delay": 3e-4, "hysteresis.thresholds[9]": 0.85},
             "Sensor": {"sensor.seed": 5, "sensor.C_load": 2e-9},
             "Compensator": {"compensator.mode": 1, "compensator.inverse": 0, "reference.signal": 3,
                             "reference.freq": 20.0, "compensator.dynamics.den[1]": 0.002}}
    hs = [1e-4] * 150
    for name, values in cases.items():
        got, want = fmu_and_core(fmus[name], values, hs, "set_" + name)
        default, _ = fmu_and_core(fmus[name], {}, hs, "default_" + name)
        assert got == want and got != default, name


def test_the_actuator_fmu_moves_the_stroke_along_the_amplifiers_lag_when_asked(fmus):
    # simulation.stroke_path = 1 (amplifier_lag): the core's numbers, and not those of the line; at
    # 1 ms per step against the 1.6 ms lag the two paths differ well beyond round-off
    hs = [1e-3] * 60
    values = {"simulation.stroke_path": 1, "simulation.actuator_max_step": 1e-3}
    got, want = fmu_and_core(fmus["Actuator"], values, hs, "lag_path")
    line, _ = fmu_and_core(fmus["Actuator"], {"simulation.actuator_max_step": 1e-3}, hs, "line_path")
    assert got == want and got != line


def test_initial_values_follow_the_inputs_in_initialization_mode(fmus):
    """A master may read outputs during initialization (libcosim iterates get/set there): they are
    recomputed from the inputs as set, idempotently, and exit_initialization_mode keeps the last."""
    f = fmus["Compensator"]
    s = f.slave("init", init=False)
    s.s.setupExperiment(startTime=0.25)
    s.s.enterInitializationMode()
    core = units.compensator_from(MODEL.sections, **REFERENCE_DEFAULT)
    for us in (0.3, 0.9, 0.3):
        s.set({"us": us})
        core.reset()
        assert s.get("uc", "x_target") == [core.initialize(0.25, 0.0, us), core.out[1]]
    s.s.exitInitializationMode()
    assert s.get("uc")[0] == core.out[0]
    k = MODEL["compensator"]["k_ideal"]
    assert s.get("x_target")[0] == k * (45.0 + 45.0 * math.sin(2 * math.pi * 10.0 * 0.25 - math.pi / 2))
    s.t = 0.25
    s.step(1e-4)
    assert s.get("x_target")[0] == k * (45.0 + 45.0 * math.sin(2 * math.pi * 10.0 * (0.25 + 1e-4) - math.pi / 2))
    s.free()


def test_reset_returns_to_the_defaults(fmus):
    f = fmus["Actuator"]
    s = f.slave("reset", values={"amplifier.k_amp": 7.0})
    drive(s, 30)
    s.s.terminate()
    s.s.reset()                                   # pythonfmu re-creates the Python object
    assert s.get("amplifier.k_amp", "uc") == [10.0, 3.0]
    s.s.setupExperiment(startTime=0.0)
    s.s.enterInitializationMode()
    s.s.exitInitializationMode()
    s.t = 0.0
    ref = f.slave("reset_ref")
    assert drive(s, 30) == drive(ref, 30)
    s.free()
    ref.free()


def test_instantiation_without_the_bundled_model_fails_clearly():
    r = run_python("sys.path.insert(0, sys.argv[1])\n"
                   "import Actuator\n"
                   "try:\n"
                   "    Actuator.Actuator(instance_name='x', resources=None)\n"
                   "except Exception as e:\n"
                   "    print('@@', type(e).__name__, e)\n", ROOT / "fmu_src")
    assert r.returncode == 0, r.stderr
    assert "@@ FmuUsageError" in r.stdout and "piezo_model.json not found" in r.stdout


def test_gauss_seidel_loop_equals_monolithic_model(fmus):
    """Actuator -> Sensor -> Compensator each step, as piezo_fmu.simulate orders the monolithic loop."""
    from piezo_fmu.simulate import Signal, simulate

    h, n = 1e-4, 300
    mono = simulate(MODEL, Signal("sine", 45.0, 45.0, 10.0, -90.0), n * h, step=h, engine="python")
    a, s, c = (fmus[k].slave("gs_" + k, init=False) for k in SYSTEM)
    for x in (a, s, c):
        x.s.setupExperiment(startTime=0.0)
        x.s.enterInitializationMode()
    a.s.exitInitializationMode()
    s.set({"F": a.get("F")[0]})
    s.s.exitInitializationMode()
    c.set({"us": s.get("us")[0]})
    c.s.exitInitializationMode()
    rec = {k: [] for k in ("x_ref", "x", "us", "uc", "ua", "F")}

    def sample():
        for key, (x, var) in {"x_ref": (c, "x_target"), "x": (a, "x"), "us": (s, "us"), "uc": (c, "uc"),
                              "ua": (a, "ua"), "F": (a, "F")}.items():
            rec[key].append(x.get(var)[0])

    sample()
    for k in range(n):
        t = k * h
        a.set({"uc": c.get("uc")[0]})
        a.s.doStep(t, h)
        s.set({"F": a.get("F")[0]})
        s.s.doStep(t, h)
        c.set({"us": s.get("us")[0]})
        c.s.doStep(t, h)
        sample()
    for key, v in rec.items():
        # the only difference: the compensator evaluates the reference at t_k + h, the monolithic
        # loop at (k + 1) h, which can differ in the last bit
        np.testing.assert_allclose(v, mono[key], rtol=1e-9, atol=1e-9, err_msg=key)
    assert max(rec["x"]) > 2.5                # the loop tracks the 0-4.4 um sine
    for x in (a, s, c):
        x.free()


def test_tunable_change_acts_from_the_next_step(fmus):
    s = fmus["Actuator"].slave("tune2")
    s.set({"uc": 2.0})
    for _ in range(100):
        s.step(1e-4)
    ua_before = s.get("ua")[0]
    s.set({"amplifier.k_amp": 20.0})
    assert s.get("ua")[0] == ua_before                # outputs change only with the next step
    for _ in range(300):
        s.step(1e-4)
    assert s.get("ua")[0] == pytest.approx(40.0, rel=1e-6)
    s.free()


# ---------------------------------------------------------------------------------------------
# 5. bad calls: non-OK status, a logged message naming the variable, nothing dies
# ---------------------------------------------------------------------------------------------
def bad_calls_main(paths_json):
    """Run in a subprocess: every kind of bad call; prints one JSON line and 'SURVIVED'."""
    import gc

    paths = json.loads(paths_json)
    F = {n: Fmu(p) for n, p in paths.items()}
    out = []

    def rec(case, expect, fn, *args):
        status, msgs = call(fn, *args)
        errors = [m[3] for m in msgs if m[1] == ERROR]
        out.append({"case": case, "status": status, "errors": errors, "expect": expect})

    a = F["Actuator"].slave("A")
    vr = {n: v.valueReference for n, v in F["Actuator"].var.items()}
    clean = F["Actuator"].slave("A_clean")
    rec("NaN input", ["'uc'", "nan"], a.s.setReal, [vr["uc"]], [math.nan])
    rec("inf input", ["'uc'", "inf"], a.s.setReal, [vr["uc"]], [math.inf])
    rec("fixed parameter after init", ["'mechanics.m'", "fixed"], a.s.setReal, [vr["mechanics.m"]], [0.03])
    rec("tunable out of range", ["'amplifier.R'", "> 0"], a.s.setReal, [vr["amplifier.R"]], [-5.0])
    rec("tunable NaN", ["'amplifier.k_amp'", "NaN"], a.s.setReal, [vr["amplifier.k_amp"]], [math.nan])
    rec("tunable pair inconsistent", ["amplifier.u_min", "amplifier.u_max", "previous values were kept"],
        a.s.setReal, [vr["amplifier.u_min"]], [500.0])
    rec("zero step", ["h=0.0"], a.s.doStep, 0.0, 0.0)
    rec("negative step", ["h=-0.0001"], a.s.doStep, 0.0, -1e-4)
    rec("NaN step", ["h=nan"], a.s.doStep, 0.0, math.nan)
    rec("set an output", ["'x'", "output"], a.s.setReal, [vr["x"]], [1.0])
    rec("unknown vr", ["9999"], a.s.getReal, [9999])
    rec("Integer access to a Real", ["'uc'", "is a Real"], a.s.setInteger, [vr["uc"]], [1])
    rec("Boolean access", ["Boolean"], a.s.getBoolean, [0])
    after = {"u_min": a.get("amplifier.u_min")[0], "R": a.get("amplifier.R")[0]}
    same_after_errors = drive(a, 100) == drive(clean, 100)

    b = F["Actuator"].slave("B", init=False)
    vb = vr
    rec("do_step before initialization", ["instantiated", "exit_initialization_mode"], b.s.doStep, 0.0, 1e-4)
    rec("parameter out of range before init", ["'amplifier.C_a'", "> 0"], b.s.setReal, [vb["amplifier.C_a"]], [0.0])
    rec("exit init before enter", ["exit_initialization_mode", "instantiated"], b.s.exitInitializationMode)
    b.s.setupExperiment(startTime=0.0)
    b.s.enterInitializationMode()
    rec("do_step in initialization mode", ["initializationMode"], b.s.doStep, 0.0, 1e-4)
    b.s.setReal([vb["hysteresis.weights[1]"]], [-5.0])
    rec("invalid combination at exit init", ["hysteresis.weights[1]", "partial weight sum"],
        b.s.exitInitializationMode)
    b.s.setReal([vb["hysteresis.weights[1]"]], [MODEL["hysteresis"]["weights"][0]])
    b.s.exitInitializationMode()
    b_ok = drive(b, 50) == drive(F["Actuator"].slave("B_clean"), 50)

    s = F["Sensor"].slave("S", init=False)
    vs = {n: v.valueReference for n, v in F["Sensor"].var.items()}
    s.s.setupExperiment(startTime=0.0)
    s.s.enterInitializationMode()
    rec("negative Integer parameter", ["'sensor.seed'", "[0, 2147483647]"], s.s.setInteger, [vs["sensor.seed"]], [-1])
    rec("NaN parameter", ["'sensor.noise_std'", "NaN"], s.s.setReal, [vs["sensor.noise_std"]], [math.nan])
    rec("-inf input", ["'F'", "-inf"], s.s.setReal, [vs["F"]], [-math.inf])
    s.s.exitInitializationMode()

    c = F["Compensator"].slave("C", init=False)
    vc = {n: v.valueReference for n, v in F["Compensator"].var.items()}
    c.s.setupExperiment(startTime=0.0)
    c.s.enterInitializationMode()
    rec("Integer parameter out of range", ["'compensator.mode'", "3 ff+fb"], c.s.setInteger,
        [vc["compensator.mode"]], [7])
    den1 = MODEL["compensator.dynamics"]["den"][1]
    c.s.setReal([vc["compensator.dynamics.den[2]"]], [-1.0])     # G(s) = 1/(tau s - 1): unstable
    rec("unstable G(s) at exit init", ["compensator.dynamics.den[2]", "unstable"],
        c.s.exitInitializationMode)
    c.s.setReal([vc["compensator.dynamics.den[2]"]], [den1])
    c.s.exitInitializationMode()
    drive(c, 20)
    rec("tunable Integer out of range", ["'reference.signal'"], c.s.setInteger, [vc["reference.signal"]], [9])
    rec("tunable limits crossed", ["compensator.uc_max", "compensator.uc_min"], c.s.setReal,
        [vc["compensator.uc_max"]], [-10.0])
    good, t_good = c.s.getFMUstate(), c.t
    before = drive(c, 10, k0=20)
    restore(c, good, t_good)
    c.set({"reference.signal": 0, "x_ref": 1e308})
    rec("non-finite result", ["non-finite", "uc=nan", "x_ref=1e+308"], c.s.doStep, c.t, 1e-4)
    rec("step after a non-finite result", ["refused", "restore"], c.s.doStep, c.t, 1e-4)
    restore(c, good, t_good)                    # restoring a good state makes it usable again
    recovered = drive(c, 10, k0=20) == before
    bad_state = c.s.deSerializeFMUstate(b"\x00 not json")
    rec("undecodable serialized state", ["could not be decoded"], c.s.setFMUstate, bad_state)
    other_state = a.s.getFMUstate()
    rec("state of another FMU", ["belongs to", "Actuator"], c.s.setFMUstate, other_state)
    recovered = recovered and drive(c, 10, k0=30) != b""

    n_errors = len(out)
    for x in (a, clean, b, s, c):
        x.free()
    gc.collect()
    again = F["Compensator"].slave("again")     # the FMUs still instantiate and run
    drive(again, 10)
    again.free()
    for f in F.values():
        f.close()
    print("@@" + json.dumps({"cases": out, "after": after, "same_after_errors": same_after_errors,
                             "b_ok": b_ok, "recovered": recovered, "n_errors": n_errors}))
    print("SURVIVED", flush=True)


def test_bad_calls_are_reported_and_survived(built_fmus):
    r = run_python("import test_fmus as T; T.bad_calls_main(sys.argv[1])",
                   json.dumps({k: str(v) for k, v in built_fmus.items()}))
    assert r.returncode == 0 and "SURVIVED" in r.stdout, r.stdout[-2000:] + r.stderr[-3000:]
    res = json.loads(next(ln for ln in r.stdout.splitlines() if ln.startswith("@@"))[2:])
    for case in res["cases"]:
        assert case["status"] == ERROR, case            # the instance stays usable: not fmi2Fatal
        assert len(case["errors"]) == 1, case           # our message, logged with status error
        for word in case["expect"]:
            assert word in case["errors"][0], (case["case"], word, case["errors"][0])
    assert res["n_errors"] >= 25
    assert res["after"] == {"u_min": MODEL["amplifier"]["u_min"], "R": MODEL["amplifier"]["R"]}
    assert res["same_after_errors"] and res["b_ok"] and res["recovered"]


def test_fmus_run_without_the_project_package(built_fmus, passthrough_fmu):
    code = ("sys.modules['piezo_fmu'] = None\n"
            "from fmpy import simulate_fmu\n"
            "for p in sys.argv[1:]:\n"
            "    r = simulate_fmu(p, stop_time=0.005)\n"
            "    print(p, len(r))\n")
    r = run_python(code, *built_fmus.values(), passthrough_fmu)
    assert r.returncode == 0, r.stderr[-3000:]
    assert len(r.stdout.strip().splitlines()) == 4


# ---------------------------------------------------------------------------------------------
# 6. the build's own machinery
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("src,expected", [
    ("from slavebase import SlaveBase as Fmi2Slave\n", "from _b.slavebase import SlaveBase as Fmi2Slave\n"),
    ("import slavebase\n", "import _b.slavebase as slavebase\n"),
    ("from slavebase import (\n    a,\n    b,\n)\nz = 1\n", "from _b.slavebase import a, b\nz = 1\n"),
    ("s = 'é'; import slavebase as sb\n", "s = 'é'; import _b.slavebase as sb\n"),     # byte offsets
    ("import slavebasex\nfrom .slavebase import b\n", "import slavebasex\nfrom .slavebase import b\n"),
])
def test_rewrite_imports(src, expected):
    from piezo_fmu.builder import rewrite_imports
    assert rewrite_imports(src, "slavebase", "_b.slavebase") == expected


@pytest.mark.parametrize("src,expected", [
    ("from piezo_fmu.core import units\n", "from _b.core import units\n"),
    ("from piezo_fmu.core.control import MODES as M\n", "from _b.core.control import MODES as M\n"),
    ("import piezo_fmu.core.plant as p\n", "import _b.core.plant as p\n"),
    ("from piezo_fmu import model\n", "from piezo_fmu import model\n"),    # left alone: the stage check fails it
])
def test_rewrite_core_imports(src, expected):
    from piezo_fmu.builder import rewrite_imports
    assert rewrite_imports(src, "piezo_fmu.core", "_b.core") == expected


@pytest.mark.parametrize("src", ["import piezo_fmu.core\n", "import piezo_fmu.core.units\n",
                                 "import importlib\nm = importlib.import_module('piezo_fmu.core.units')\n"])
def test_rewrite_imports_rejects_ambiguous(src):
    from piezo_fmu.builder import StageError, rewrite_imports
    with pytest.raises(StageError):
        rewrite_imports(src, "piezo_fmu.core", "_b.core")


def test_stage_rejects_an_unbundled_import(tmp_path, monkeypatch):
    from piezo_fmu.builder import staging as build_stage
    src = tmp_path / "fmu_src"
    src.mkdir()
    (src / "Bad.py").write_text("from slavebase import SlaveBase as Fmi2Slave\nfrom piezo_fmu import model\n\n\n"
                                "class Bad(Fmi2Slave):\n    pass\n")
    monkeypatch.setattr(build_stage, "FMU_SRC", src)
    with pytest.raises(build_stage.StageError, match="piezo_fmu"):
        build_stage.stage("Bad", {}, tmp_path / "stage")


def test_zip_rewrite_replaces_one_member_or_nothing(tmp_path, monkeypatch):
    import zipfile

    from piezo_fmu.builder import rewrite_zip_member
    p = tmp_path / "X.fmu"
    with zipfile.ZipFile(p, "w") as z:
        z.writestr("modelDescription.xml", b"<old/>")
        z.writestr("binaries/linux64/X.so", bytes(range(256)) * 10)
        z.writestr("resources/a.py", b"print(1)\n")
    before = {i.filename: zipfile.ZipFile(p).read(i.filename) for i in zipfile.ZipFile(p).infolist()}
    rewrite_zip_member(p, "modelDescription.xml", b"<new/>")
    with zipfile.ZipFile(p) as z:
        assert z.testzip() is None and z.namelist() == list(before)
        for n, data in before.items():
            assert z.read(n) == (b"<new/>" if n == "modelDescription.xml" else data)
    assert list(tmp_path.iterdir()) == [p]
    orig = p.read_bytes()
    real = zipfile.ZipFile.writestr
    calls = []

    def flaky(self, *a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise OSError("disk full")
        return real(self, *a, **k)
    monkeypatch.setattr(zipfile.ZipFile, "writestr", flaky)
    with pytest.raises(OSError):
        rewrite_zip_member(p, "modelDescription.xml", b"<newer/>")
    assert p.read_bytes() == orig and list(tmp_path.iterdir()) == [p]


def test_state_codec_is_exact():
    sys.path.insert(0, str(ROOT / "fmu_src"))
    try:
        import statecodec
    finally:
        sys.path.remove(str(ROOT / "fmu_src"))
    v = {"f": [0.1 + 0.2, -0.0, 5e-324, math.inf, -math.inf, 1.7976931348623157e308], "t": (1, "a"),
         "i": 2 ** 127 + 1, "d": {1: "x", "__t": None}, "n": None, "b": True,
         "a": np.arange(3, dtype=np.int32), "s": np.float64(0.1)}
    data = statecodec.state_dumps(v)
    back = statecodec.state_loads(data)
    assert statecodec.state_dumps(back) == data
    assert bits(back["f"]) == bits(v["f"]) and back["t"] == (1, "a") and back["i"] == v["i"]
    assert back["d"] == {1: "x", "__t": None} and back["a"].dtype == np.int32 and type(back["s"]) is np.float64


def test_random_call_sequences_never_take_the_host_down(built_fmus):
    """Hypothesis drives each FMU with random FMI call sequences and wild values (issue 6); it runs
    in a child process so that a crash would show as a failed exit code, not a dead pytest."""
    import subprocess
    import sys
    from pathlib import Path

    paths = {name: str(p) for name, p in built_fmus.items() if name in ("Actuator", "Sensor", "Compensator")}
    script = Path(__file__).with_name("fuzz_fmus.py")
    r = subprocess.run([sys.executable, str(script), json.dumps(paths), "40", "0"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    summary = json.loads(next(ln for ln in r.stdout.splitlines() if ln.startswith("@@"))[2:])
    for name, s in summary.items():
        assert s["examples"] == 40, (name, s)
        assert s["steps"] >= 1000, (name, s)             # thousands of steps over all FMUs
        assert s["error"] > 0, (name, s)                 # the abuse was rejected with fmi2Error
        assert s["nonfinite_after_ok"] == 0, (name, s)   # an OK step never hands out NaN/inf
        assert s["not_recovered"] == 0, (name, s)        # reset + init always recovers
        assert s.get("other", 0) == 0 and s.get("fatal", 0) == 0, (name, s)   # nothing is fatal
