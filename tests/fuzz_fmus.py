"""Drive the FMUs with random FMI call sequences (hypothesis); run as a script in a child process.

Usage: python fuzz_fmus.py PATHS_JSON N_EXAMPLES SEED

Every example instantiates one FMU and applies 20-120 random operations: real/integer sets on
inputs and parameters with wild values (NaN, +-inf, +-1e308, negatives, zero), steps with good,
zero, negative and odd step sizes, out-of-order mode calls, state save/restore, reset. The
invariants: every call returns (no crash of this process), statuses are OK or error (a refused
call leaves the instance usable: never fatal), outputs read after an OK step are finite, and after the abuse a reset + re-initialisation gives
an instance that steps normally with finite outputs. Prints one JSON summary line (prefix @@).
"""
import json
import math
import sys

from fmpy import read_model_description
from fmpy.fmi1 import FMICallException
from fmpy.fmi2 import FMU2Slave
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

WILD = [math.nan, math.inf, -math.inf, 1e308, -1e308, 0.0, -1.0, 1e-300]
STEPS = [1e-4, 1e-4, 1e-4, 5e-5, 1e-5, 3.3e-4, 0.0, -1e-4, 1e-3, math.nan]


class Target:
    def __init__(self, name, path):
        self.name = name
        self.md = read_model_description(path)
        from fmpy import extract

        self.dir = extract(path)
        self.reals = [v for v in self.md.modelVariables if v.type == "Real"
                      and v.causality in ("input", "parameter")]
        self.ints = [v for v in self.md.modelVariables if v.type == "Integer" and v.causality == "parameter"]
        self.outs = [v.valueReference for v in self.md.modelVariables if v.causality == "output"]

    def slave(self, label):
        return FMU2Slave(guid=self.md.guid, unzipDirectory=self.dir,
                         modelIdentifier=self.md.coSimulation.modelIdentifier, instanceName=label)


def op_strategy(target):
    real = st.tuples(st.just("real"), st.integers(0, len(target.reals) - 1),
                     st.one_of(st.sampled_from(WILD), st.floats(-1e3, 1e3),
                               st.floats(allow_nan=True, allow_infinity=True)))
    integer = st.tuples(st.just("int"), st.integers(0, max(0, len(target.ints) - 1)),
                        st.integers(-(2 ** 31), 2 ** 31 - 1) | st.integers(-2, 6))
    step = st.tuples(st.just("step"), st.sampled_from(STEPS), st.integers(1, 40))
    other = st.tuples(st.sampled_from(["get", "save", "restore", "enter_init", "exit_init",
                                       "terminate", "reset", "setup"]), st.just(0), st.just(0))
    ops = [real, step, step, other]
    if target.ints:
        ops.append(integer)
    return st.lists(st.one_of(*ops), min_size=20, max_size=120)


def call(stats, fn, *args):
    try:
        out = fn(*args)
        stats["ok"] += 1
        return True, out
    except FMICallException as exc:
        text = str(exc)
        code = "discard" if "discard" in text else "fatal" if "fatal" in text else "error" if "error" in text else "other"
        stats[code] = stats.get(code, 0) + 1
        return False, None


def run(target, ops, stats, label):
    s = target.slave(label)
    s.instantiate(loggingOn=False)
    t = 0.0
    saved = None
    call(stats, s.setupExperiment, None, 0.0)
    call(stats, s.enterInitializationMode)
    call(stats, s.exitInitializationMode)
    for kind, a, b in ops:
        if kind == "real":
            var = target.reals[a]
            call(stats, s.setReal, [var.valueReference], [b])
        elif kind == "int":
            var = target.ints[a]
            call(stats, s.setInteger, [var.valueReference], [b])
        elif kind == "step":
            for _ in range(b):
                ok, _ = call(stats, s.doStep, t, a)
                stats["steps"] += 1
                if not ok:
                    break
                t += a
                ok, vals = call(stats, s.getReal, target.outs)
                if ok and not all(math.isfinite(v) for v in vals):
                    stats["nonfinite_after_ok"] += 1
        elif kind == "get":
            call(stats, s.getReal, target.outs)
        elif kind == "save":
            ok, st_ = call(stats, s.getFMUstate)
            if ok:
                if saved is not None:
                    call(stats, s.freeFMUstate, saved)
                saved = st_
        elif kind == "restore" and saved is not None:
            call(stats, s.setFMUstate, saved)
        elif kind == "enter_init":
            call(stats, s.enterInitializationMode)
        elif kind == "exit_init":
            call(stats, s.exitInitializationMode)
        elif kind == "terminate":
            call(stats, s.terminate)
        elif kind == "reset":
            call(stats, s.reset)
        elif kind == "setup":
            call(stats, s.setupExperiment, None, t)
    # recovery: a reset instance re-initialised with its defaults steps normally
    ok = all(call(stats, f)[0] for f in (s.reset,))
    ok = ok and call(stats, s.setupExperiment, None, 0.0)[0]
    ok = ok and call(stats, s.enterInitializationMode)[0] and call(stats, s.exitInitializationMode)[0]
    for k in range(20):
        ok = ok and call(stats, s.doStep, k * 1e-4, 1e-4)[0]
    got, vals = call(stats, s.getReal, target.outs)
    if not (ok and got and all(math.isfinite(v) for v in vals)):
        stats["not_recovered"] += 1
    if saved is not None:
        call(stats, s.freeFMUstate, saved)
    call(stats, s.terminate)
    s.freeInstance()


def main():
    paths = json.loads(sys.argv[1])
    n = int(sys.argv[2])
    summary = {}
    for name, path in paths.items():
        target = Target(name, path)
        stats = {"ok": 0, "steps": 0, "nonfinite_after_ok": 0, "not_recovered": 0, "examples": 0}
        counter = {"i": 0}

        @settings(max_examples=n, deadline=None, derandomize=True, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(op_strategy(target))
        def fuzz(ops):
            counter["i"] += 1
            stats["examples"] += 1
            run(target, ops, stats, f"{name}{counter['i']}")

        fuzz()
        summary[name] = stats
    print("@@" + json.dumps(summary), flush=True)


if __name__ == "__main__":
    main()
