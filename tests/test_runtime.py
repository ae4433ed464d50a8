"""The FMUs' native FMI runtime (fmu_src/runtime) in hosts that are not Python, and in fmpy.

Proves (issue 11): a plain C FMI 2.0 host (tests/host/fmi2_host.c, compiled here) runs each FMU in
a child process with no LD_PRELOAD, PYTHONPATH or PYTHONHOME and a PATH whose python3 is not the
build's: the default experiment equals fmpy's outputs, every run exits 0; instances come and go
(100 in one process; mixed free/dlclose orders, a reopened library, exit with instances alive);
two instances step on two threads; a host that loaded libpython itself; the compiled engine
(numba) from C; the closed loop from C equals ``cosimulate``; NaN input is fmi2Error and the
instance steps on; libcosim driven from C (tests/host/libcosim_run.c) agrees with libcosimpy;
``fmpy simulate`` and a plain fmpy script exit 0 in 20 of 20 runs; wrong overrides are reported
by fmi2Instantiate; without a C compiler the build falls back to pythonfmu's binary in one line,
and such a fallback FMU survives repeated errors (its reference-count workaround).
"""
from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from fmpy import extract, read_model_description, simulate_fmu

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
HOST_SRC = HERE / "host" / "fmi2_host.c"
LIBCOSIM_SRC = HERE / "host" / "libcosim_run.c"
SYSTEM = ("Actuator", "Sensor", "Compensator")
RUNS = 20
CC = shutil.which("gcc") or shutil.which("cc")
OTHER_PATH = "/usr/bin:/bin"            # its python3 (if any) is not the build's

pytestmark = pytest.mark.skipif(CC is None, reason="no C compiler: the FMUs carry pythonfmu's binary")


def clean_env(**extra):
    """A child environment without Python variables; PATH's python3 is not the build's."""
    env = {"PATH": OTHER_PATH, "HOME": os.environ.get("HOME", "/tmp"), "LC_ALL": "C"}
    env.update(extra)
    return env


def test_clean_environment_is_really_foreign():
    other = shutil.which("python3", path=OTHER_PATH)
    build = os.path.realpath(sys.executable)
    assert other is None or os.path.realpath(other) != build
    env = clean_env()
    assert not {"LD_PRELOAD", "PYTHONPATH", "PYTHONHOME"} & set(env)


def compile_c(src: Path, out: Path, *flags):
    proc = subprocess.run([CC, "-O2", "-Wall", "-o", str(out), str(src), *flags], capture_output=True,
                          text=True, check=False, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.fixture(scope="module")
def host(tmp_path_factory):
    return compile_c(HOST_SRC, tmp_path_factory.mktemp("host") / "fmi2_host", "-ldl", "-lpthread", "-lm")


class Unpacked:
    """An extracted FMU: its folder, the host's FMU argument, value references by name."""

    def __init__(self, path, where):
        self.path = Path(path)
        self.md = read_model_description(str(path))
        self.dir = extract(str(path), unzipdir=str(where))
        self.id = self.md.coSimulation.modelIdentifier
        self.spec = f"{self.dir}:{self.id}:{self.md.guid}"
        self.vr = {v.name: v.valueReference for v in self.md.modelVariables}
        self.outputs = [v.name for v in self.md.modelVariables if v.causality == "output"]
        self.de = self.md.defaultExperiment

    def vrs(self, names):
        return ",".join(str(self.vr[n]) for n in names)


@pytest.fixture(scope="module")
def unpacked(fmu_build, tmp_path_factory):
    base = tmp_path_factory.mktemp("unpacked")
    return {name: Unpacked(fmu_build[name], base / name) for name in (*SYSTEM, "PassThrough")}


def run_host(host, *args, env=None, timeout=300, check=True):
    proc = subprocess.run([str(host), *map(str, args)], capture_output=True, text=True, check=False,
                          timeout=timeout, env=env if env is not None else clean_env())
    if check:
        assert proc.returncode == 0 and "status ok" in proc.stdout, (proc.returncode, proc.stdout[-2000:],
                                                                      proc.stderr[-3000:])
    return proc


def rows(stdout, key="row"):
    return np.array([[float.fromhex(x) for x in line.split()[1:]] for line in stdout.splitlines()
                     if line.split(" ", 1)[0] == key])


def parallel(fn, jobs):
    with ThreadPoolExecutor(max_workers=2) as pool:
        return list(pool.map(fn, jobs))


# ---------------------------------------------------------------------------------------------
# what the build put into the FMUs
# ---------------------------------------------------------------------------------------------
def test_fmus_carry_the_native_runtime(fmu_build, tmp_path):
    for name in (*SYSTEM, "PassThrough"):
        with zipfile.ZipFile(fmu_build[name]) as z:
            names = set(z.namelist())
            assert {f"binaries/linux64/{name}.so", "binaries/linux64/piezo_fmu_bridge.so",
                    "resources/piezo_runtime.cfg"} <= names
            cfg = z.read("resources/piezo_runtime.cfg").decode()
            fmi = z.read(f"binaries/linux64/{name}.so")
        assert f"class={name}\n" in cfg and "libpython=/" in cfg and "protocol=1\n" in cfg
        assert b"piezo_fmu_bridge_1" in fmi and b"_Py_NoneStruct" not in fmi   # no Python symbol
    readelf = shutil.which("readelf")
    if readelf:
        probe = tmp_path / "Sensor.so"
        with zipfile.ZipFile(fmu_build["Sensor"]) as z:
            probe.write_bytes(z.read("binaries/linux64/Sensor.so"))
        dyn = subprocess.run([readelf, "-d", str(probe)], capture_output=True, text=True, check=True).stdout
        needed = [ln.split("[")[1].rstrip("]") for ln in dyn.splitlines() if "(NEEDED)" in ln]
        assert needed and not [n for n in needed if "python" in n], needed


# ---------------------------------------------------------------------------------------------
# a plain C host
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", SYSTEM)
def test_default_experiment_from_c_equals_fmpy(host, unpacked, name):
    u = unpacked[name]
    de = u.de
    args = ("run", u.spec, de.startTime, de.stopTime, de.stepSize, u.vrs(u.outputs))
    procs = parallel(lambda _: run_host(host, *args, check=False), range(RUNS))
    codes = [p.returncode for p in procs]
    assert codes == [0] * RUNS, [(p.returncode, p.stderr[-500:]) for p in procs if p.returncode][:2]
    assert all(p.stdout == procs[0].stdout for p in procs)          # deterministic
    got = rows(procs[0].stdout)
    ref = simulate_fmu(str(u.path), output_interval=float(de.stepSize), output=u.outputs)
    assert got.shape == (len(ref), 1 + len(u.outputs))
    np.testing.assert_allclose(got[:, 0], ref["time"], rtol=0, atol=1e-12)
    for j, out in enumerate(u.outputs, 1):
        scale = max(1.0, float(np.max(np.abs(ref[out]))))
        np.testing.assert_allclose(got[:, j], ref[out], rtol=1e-12, atol=1e-12 * scale, err_msg=out)


def test_instantiate_and_free_100_times_in_one_process(host, unpacked):
    p = run_host(host, "churn", unpacked["Sensor"].spec, 100)
    assert "churned 100" in p.stdout and "errors 0" in p.stdout


def test_free_dlclose_and_exit_in_any_order(host, unpacked):
    """Several instances of three FMUs; the library that started Python closed while the others
    run; a library reopened; the process exits with instances alive and libraries open."""
    for _ in range(3):
        p = run_host(host, "orders", *(unpacked[n].spec for n in SYSTEM))
        assert "orders ok" in p.stdout and "errors 0" in p.stdout


def test_two_instances_step_on_two_threads(host, unpacked):
    u = unpacked["Actuator"]
    out = u.vrs(["x", "F", "ua"])
    p = run_host(host, "threads", u.spec, 1e-4, 400, out, u.vr["uc"], 1)
    alone = rows(run_host(host, "run", u.spec, 0.0, 0.04, 1e-4, out, u.vr["uc"], 1).stdout)[1:]
    a, b = rows(p.stdout, "row0"), rows(p.stdout, "row1")
    assert a.shape == alone.shape == (400, 4)
    assert a.tobytes() == b.tobytes() == alone.tobytes()       # bit for bit, whatever the interleaving


@pytest.mark.parametrize("name", ["Sensor", "Compensator"])
def test_host_that_loaded_libpython_itself(host, unpacked, name):
    """The host's own (not started) libpython is used; exit is clean (pythonfmu aborted 8 of 8)."""
    u = unpacked[name]
    with zipfile.ZipFile(u.path) as z:
        cfg = dict(ln.split("=", 1) for ln in z.read("resources/piezo_runtime.cfg").decode().splitlines()
                   if "=" in ln and not ln.startswith("#"))
    de = u.de
    args = ("run", u.spec, de.startTime, de.stopTime, de.stepSize, u.vrs(u.outputs))
    plain = run_host(host, *args).stdout
    procs = parallel(lambda _: run_host(host, "--preload", cfg["libpython"], *args, check=False), range(8))
    assert [p.returncode for p in procs] == [0] * 8, procs[0].stderr[-2000:]
    assert all(p.stdout == plain for p in procs)


def test_compiled_engine_from_c(host, unpacked):
    """numba found through the recorded module path; the same bits as the interpreted kernels."""
    u = unpacked["Actuator"]
    args = ("run", u.spec, 0.0, 0.01, 1e-4, u.vrs(["x", "F", "ua"]), u.vr["uc"], 1)
    python = run_host(host, *args).stdout
    numba = run_host(host, "--int", f"Actuator:{u.vr['simulation.engine']}=1", *args).stdout
    assert numba == python


def test_closed_loop_from_c_equals_cosimulate(host, unpacked, built_fmus):
    from piezo_fmu.cosim import cosimulate
    from piezo_fmu.simulate import Signal

    a, s, c = (unpacked[n] for n in SYSTEM)
    vrs = [a.vr["uc"], a.vr["x"], a.vr["F"], a.vr["ua"], s.vr["F"], s.vr["us"], c.vr["us"], c.vr["uc"],
           c.vr["x_target"]]
    stop, h = 0.05, 1e-4
    p = run_host(host, "loop", a.spec, s.spec, c.spec, stop, h,
                 env=clean_env(HOST_LOOP_VRS=",".join(map(str, vrs))))
    got = rows(p.stdout)                                  # t x F ua us uc x_target
    co = cosimulate(built_fmus, Signal("sine", 45.0, 45.0, 10.0, -90.0), stop, h)
    assert got.shape == (co["time"].size, 7)
    for j, col in enumerate(("time", "x", "F", "ua", "us", "uc", "x_ref")):
        scale = max(1.0, float(np.max(np.abs(co[col]))))
        assert float(np.max(np.abs(got[:, j] - co[col]))) <= 1e-13 * scale, col


def test_nan_input_is_an_error_and_the_instance_steps_on(host, unpacked):
    u = unpacked["Actuator"]
    p = run_host(host, "nan", u.spec, u.vr["uc"], u.vrs(["x", "F", "ua"]))
    line = next(ln for ln in p.stdout.splitlines() if ln.startswith("nan "))
    assert line == "nan 3 logged 1 good 0 step 0 get 0"      # fmi2Error, one message; then all OK
    assert "non-finite value nan for input 'uc'" in p.stderr and "status 3 logStatusError" in p.stderr
    assert np.all(np.isfinite(rows(p.stdout)))


# ---------------------------------------------------------------------------------------------
# what the build recorded, and its overrides
# ---------------------------------------------------------------------------------------------
def test_missing_libpython_is_reported_by_instantiate(host, unpacked):
    u = unpacked["Sensor"]
    p = run_host(host, "run", u.spec, 0.0, 0.001, 1e-4, u.vr["us"], check=False,
                 env=clean_env(PIEZO_FMU_LIBPYTHON="/nonexistent/libpython3.so"))
    assert p.returncode == 3 and "fail fmi2Instantiate NULL" in p.stdout
    assert "cannot load the Python library /nonexistent/libpython3.so (PIEZO_FMU_LIBPYTHON)" in p.stderr


def test_bad_python_home_is_reported_by_instantiate(host, unpacked):
    u = unpacked["Sensor"]
    p = run_host(host, "run", u.spec, 0.0, 0.001, 1e-4, u.vr["us"], check=False,
                 env=clean_env(PIEZO_FMU_PYTHONHOME="/nonexistent"))
    assert p.returncode == 3 and "fail fmi2Instantiate NULL" in p.stdout, p.stdout + p.stderr
    assert "starting Python (home /nonexistent) failed" in p.stderr


def test_module_path_override_is_used(host, unpacked):
    """PIEZO_FMU_PYTHONPATH replaces the recorded path: without site-packages numpy is missing,
    and fmi2Instantiate says so with the module path it used."""
    u = unpacked["Sensor"]
    with zipfile.ZipFile(u.path) as z:
        paths = [ln[5:] for ln in z.read("resources/piezo_runtime.cfg").decode().splitlines()
                 if ln.startswith("path=")]
    stdlib_only = [p for p in paths if "site-packages" not in p]
    p = run_host(host, "run", u.spec, 0.0, 0.001, 1e-4, u.vr["us"], check=False,
                 env=clean_env(PIEZO_FMU_PYTHONPATH=":".join(stdlib_only)))
    assert p.returncode == 3 and "No module named" in p.stderr, p.stderr[-2000:]


# ---------------------------------------------------------------------------------------------
# libcosim from C
# ---------------------------------------------------------------------------------------------
LIBCOSIMPY_RUN = r"""
import ctypes, json, sys
from libcosimpy.CosimExecution import CosimExecution
from libcosimpy.CosimObserver import CosimObserver
from libcosimpy.CosimEnums import CosimVariableType
from libcosimpy._internal import libcosimc
ssp, step, stop = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
ex = CosimExecution.from_ssp_file(ssp, step_size=step)
idx = {n: ex.slave_index_from_instance_name(n) for n in ("Actuator", "Sensor", "Compensator")}
vr = {n: {v.name.decode(): v.reference for v in ex.slave_variables(i)} for n, i in idx.items()}
cols = [("Actuator", "x"), ("Sensor", "us"), ("Compensator", "uc"), ("Compensator", "x_target")]
obs = CosimObserver.create_time_series()
ex.add_observer(obs)
for n, v in cols:
    obs.start_time_series(idx[n], vr[n][v], CosimVariableType.REAL)
assert ex.simulate_until(target_time=stop)
get = libcosimc().cosim_observer_slave_get_real_samples
get.restype = ctypes.c_int64
out = {}
for n, v in cols:
    m = stop // step + 2
    val, stp, tim = (ctypes.c_double * m)(), (ctypes.c_int64 * m)(), (ctypes.c_int64 * m)()
    cnt = get(obs.ptr(), idx[n], ctypes.c_uint32(vr[n][v]), ctypes.c_int64(0), ctypes.c_size_t(m), val, stp, tim)
    out[f"{n}.{v}"] = [x.hex() for x in val[:cnt]]
    out["time"] = [(t * 1e-9).hex() for t in tim[:cnt]]
print("@@" + json.dumps(out))
del ex, obs
"""


def test_libcosim_driven_from_c_agrees_with_libcosimpy(unpacked, built_fmus, tmp_path):
    libcosimpy = pytest.importorskip("libcosimpy", reason="libcosimpy (test dependency) is not installed")
    from piezo_fmu.ssp import write_system_ssp

    libdir = Path(libcosimpy.__file__).parent / "libcosimc"
    exe = compile_c(LIBCOSIM_SRC, tmp_path / "libcosim_run", f"-L{libdir}", "-l:libcosimc.so",
                    f"-Wl,-rpath,{libdir}")
    step_ns, stop_ns = 25_000, 100_000_000            # a stable Jacobi step (see test_ssp)
    ssp = write_system_ssp(tmp_path / "PiezoSystem.ssp", built_fmus, step=step_ns * 1e-9)
    # the C run takes the SSD's algorithm with numWorkerThreads="0" (the FMUs stepped on its own
    # thread, as the bench runs it); libcosimpy below libcosim's default worker pool
    proc = subprocess.run([str(exe), str(ssp), str(step_ns), str(stop_ns)], capture_output=True, text=True,
                          check=False, timeout=300, env={})
    assert proc.returncode == 0 and "status ok" in proc.stdout, proc.stdout[-1000:] + proc.stderr[-2000:]
    # a STEP_NS other than the SSD's step is refused, not run at the SSD's
    wrong = subprocess.run([str(exe), str(ssp), str(2 * step_ns), str(20 * step_ns)], capture_output=True,
                           text=True, check=False, timeout=300, env={})
    assert wrong.returncode == 3 and "fail step" in wrong.stdout, wrong.stdout[-1000:]
    got = rows(proc.stdout)
    py = subprocess.run([sys.executable, "-c", LIBCOSIMPY_RUN, str(ssp), str(step_ns), str(stop_ns)],
                        capture_output=True, text=True, check=False, timeout=300)
    assert py.returncode == 0, py.stderr[-2000:]
    ref = json.loads(next(ln for ln in py.stdout.splitlines() if ln.startswith("@@"))[2:])
    assert got.shape == (len(ref["time"]), 5) and got.shape[0] == stop_ns // step_ns + 1
    for j, key in enumerate(("time", "Actuator.x", "Sensor.us", "Compensator.uc", "Compensator.x_target")):
        want = np.array([float.fromhex(x) for x in ref[key]])
        scale = max(1.0, float(np.max(np.abs(want))))
        assert float(np.max(np.abs(got[:, j] - want))) <= 1e-12 * scale, key


# ---------------------------------------------------------------------------------------------
# fmpy: the command line and a plain script exit cleanly, every time
# ---------------------------------------------------------------------------------------------
SCRIPT = """
import sys, fmpy, numpy
res = fmpy.simulate_fmu(sys.argv[1])
numpy.savetxt(sys.argv[2], numpy.column_stack([res[n] for n in res.dtype.names]), delimiter=",")
print(numpy.genfromtxt(sys.argv[2], delimiter=",").shape)
"""


@pytest.mark.parametrize("name", SYSTEM)
def test_fmpy_cli_and_script_exit_0_every_time(built_fmus, tmp_path, name):
    fmpy_exe = Path(sys.executable).with_name("fmpy")
    fmpy_cmd = [str(fmpy_exe)] if fmpy_exe.exists() else [sys.executable, "-m", "fmpy.command_line"]
    path = built_fmus[name]

    def cli(i):
        return subprocess.run([*fmpy_cmd, "simulate", str(path), "--output-file", str(tmp_path / f"c{i}.csv")],
                              capture_output=True, text=True, check=False, timeout=300)

    def script(i):
        return subprocess.run([sys.executable, "-c", SCRIPT, str(path), str(tmp_path / f"s{i}.csv")],
                              capture_output=True, text=True, check=False, timeout=300)

    for kind, fn in (("fmpy simulate", cli), ("script", script)):
        procs = parallel(fn, range(RUNS))
        bad = [(p.returncode, p.stderr[-800:]) for p in procs if p.returncode != 0]
        assert not bad, (kind, len(bad), bad[0])
    v = subprocess.run([*fmpy_cmd, "validate", str(path)], capture_output=True, text=True, check=False,
                       timeout=300)
    assert v.returncode == 0 and "problem" not in v.stdout.lower().replace("no problems", ""), v.stdout


# ---------------------------------------------------------------------------------------------
# the fallback: no C compiler
# ---------------------------------------------------------------------------------------------
def test_without_a_compiler_the_build_says_so_in_one_line(tmp_path, monkeypatch):
    from piezo_fmu.builder import runtime

    monkeypatch.setenv("CC", "/nonexistent/cc")
    lines = []
    assert runtime.compile_runtime(tmp_path, log=lines.append) is None
    assert len(lines) == 1 and "\n" not in lines[0]
    assert "/nonexistent/cc" in lines[0] and "pythonfmu's binary" in lines[0] and "README" in lines[0]


def fallback_main(path):
    """Run in a subprocess: a pythonfmu-binary FMU; its wrapper drops references on every error
    unless the slave's compat hook pays them (fmu_src/pythonfmu_compat.py)."""
    import ctypes
    import gc

    from fmpy.fmi1 import FMICallException
    from fmpy.fmi2 import FMU2Slave

    md = read_model_description(path)
    d = extract(path)
    s = FMU2Slave(guid=md.guid, unzipDirectory=d, modelIdentifier=md.coSimulation.modelIdentifier,
                  instanceName="rc")
    s.instantiate(loggingOn=True)
    s.setupExperiment(startTime=0.0)
    s.enterInitializationMode()
    s.exitInitializationMode()
    (obj,) = [o for o in gc.get_objects() if type(o).__name__ == "PassThrough" and hasattr(o, "_error_hook")]
    hook = obj._error_hook

    def counts():
        return [sys.getrefcount(type(obj)), sys.getrefcount(obj), sys.getrefcount(obj.log_queue)]

    def fail(fn, *args):
        try:
            fn(*args)
        except FMICallException as e:
            return e.status
        return 0

    start = counts()
    obj._error_hook = lambda slave: None          # one error without the hook ...
    statuses = [fail(s.setReal, [0], [math.nan])]
    unpaid = counts()
    for o in (type(obj), obj, obj.log_queue):     # ... (pay that debt back by hand) ...
        ctypes.pythonapi.Py_IncRef(ctypes.py_object(o))
    del o
    obj._error_hook = hook
    for _ in range(12):                           # ... and 24 with it
        statuses.append(fail(s.setReal, [0], [math.inf]))
        statuses.append(fail(s.doStep, 0.0, 0.0))
    paid = counts()
    s.setReal([0], [4.5])
    s.doStep(0.0, 0.1)
    y = s.getReal([1])[0]
    s.terminate()
    s.freeInstance()
    print("@@" + json.dumps({"start": start, "unpaid": unpaid, "paid": paid, "y": y, "statuses": statuses}))


def test_fallback_fmu_has_pythonfmus_binary_and_survives_errors(tmp_path):
    from piezo_fmu.builder import build_one, model_payload
    from piezo_fmu.model import load_model

    payload = model_payload(load_model(ROOT / "models" / "paper.toml"))
    fmu = build_one("PassThrough", payload, tmp_path, log=lambda *a: None, runtime=None)
    with zipfile.ZipFile(fmu) as z:
        names = set(z.namelist())
        assert "resources/piezo_runtime.cfg" not in names and "binaries/linux64/piezo_fmu_bridge.so" not in names
        assert b"finalizePythonInterpreter" in z.read("binaries/linux64/PassThrough.so")   # pythonfmu's
    code = (f"import sys; sys.path.insert(0, {str(HERE)!r}); import test_runtime as T; "
            f"T.fallback_main({str(fmu)!r})")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]      # also: no abort at exit
    res = json.loads(next(ln for ln in r.stdout.splitlines() if ln.startswith("@@"))[2:])
    assert set(res["statuses"]) == {4}                # pythonfmu's binary can only say fmi2Fatal
    assert [a - b for a, b in zip(res["start"], res["unpaid"])] == [1, 1, 1]
    assert res["paid"] == res["start"] and res["y"] == 4.5
