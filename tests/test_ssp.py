"""The SSP package (piezo_fmu.ssp) and the two third-party masters that run it.

How the masters differ from ours (piezo_fmu.cosim), and the tolerances that follow:

* ``fmpy.ssp.simulate_ssp`` is Jacobi, starts every connector at 0.0 (no initialisation pass) and
  stamps row i with the step's start time although it holds the values at its end. Re-stamped, it
  equals our Jacobi master with ``initial="zero"`` to round-off; against our consistent
  initialisation it differs by the effect of one step with a zero command (bounded below).
* libcosim (libcosimpy) is Jacobi with an initialisation that propagates the initial outputs
  (as ours does), with times in integer nanoseconds: it equals our Jacobi master to round-off.
* Gauss-Seidel differs from both Jacobi runs by the two extra steps of loop delay, O(H).
* At the SSP's default step (1e-4 s, the controller's design rate) the Jacobi loop is unstable
  (see test_cosim): every Jacobi master, ours included, ends in the same limit cycle, so
  round-off differences (fmpy's ``time += h``, libcosim's nanoseconds) grow from ~1e-15 um until
  the runs decorrelate. There we check round-off agreement before the growth, and that the limit
  cycles are statistically the same; the tight checks are at a stable step, 2.5e-5 s.

libcosim runs in a subprocess: a crash in its C++ (e.g. a step size in seconds instead of
nanoseconds) must not take pytest down.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

from piezo_fmu.connections import COMPONENTS, CONNECTIONS, ORDER
from piezo_fmu.cosim import cosimulate
from piezo_fmu.errors import UserError
from piezo_fmu.simulate import Signal
from piezo_fmu.ssp import (
    fmpy_parameter_set,
    read_ssp_bindings,
    read_ssp_connections,
    system_ssd,
    write_system_ssp,
)

PAPER_10HZ = Signal("sine", 45.0, 45.0, 10.0, -90.0)
STABLE_STEP = 2.5e-5


@pytest.fixture(scope="module")
def fmus(built_fmus):
    return {n: Path(built_fmus[n]) for n in ORDER}


@pytest.fixture(scope="module")
def ssp(fmus, tmp_path_factory):
    return write_system_ssp(tmp_path_factory.mktemp("ssp") / "PiezoSystem.ssp", fmus)


@pytest.fixture(scope="module")
def stroke():
    from piezo_fmu.model import load_model

    return load_model()["compensator"]["k_ideal"] * 90.0


# -- the package ---------------------------------------------------------------------------------------

def test_archive_layout_and_ssd(ssp, fmus):
    with zipfile.ZipFile(ssp) as zf:
        names = zf.namelist()
        assert names[0] == "SystemStructure.ssd"
        assert sorted(names) == sorted(["SystemStructure.ssd"] + [f"resources/{n}.fmu" for n in ORDER])
        for n in ORDER:
            assert zf.read(f"resources/{n}.fmu") == fmus[n].read_bytes()
        text = zf.read("SystemStructure.ssd").decode("utf-8")
    # libcosim matches literal prefixes (boost::property_tree, not namespace-aware)
    for tag in ("<ssd:SystemStructureDescription", "<ssd:System ", "<ssd:Component ", "<ssc:Real ",
                "<ssd:DefaultExperiment", "<osp:FixedStepAlgorithm", "<ssv:ParameterSet"):
        assert tag in text, tag
    assert 'version="1.0"' in text

    from fmpy.ssp.ssd import read_ssd  # validates against the SSP 1.0 schema

    ssd = read_ssd(str(ssp))
    comps = {c.name: c for c in ssd.system.elements}
    assert list(comps) == list(COMPONENTS)
    for name, comp in comps.items():
        assert comp.source == f"resources/{name}.fmu"
        declared = {(c.name, c.kind) for c in comp.connectors}
        ports = {(p.name, p.causality) for p in COMPONENTS[name]}
        # every port, except the Compensator's x_ref (the built-in generator drives the loop;
        # fmpy.ssp cannot leave a declared input unconnected)
        assert declared == ports - {("x_ref", "input")}
    assert {u.name for u in ssd.units} == {"um", "V", "N"}
    um = next(u for u in ssd.units if u.name == "um")
    assert um.m == 1 and um.factor == 1e-6
    assert read_ssp_connections(ssp) == CONNECTIONS

    from piezo_fmu.ssp import NS, read_ssp

    root = read_ssp(ssp)
    units = {c.get("name"): c.find(f"{{{NS['ssc']}}}Real").get("unit")
             for comp in root.iter(f"{{{NS['ssd']}}}Component") if comp.get("name") == "Actuator"
             for c in comp.iter(f"{{{NS['ssd']}}}Connector")}
    assert units == {"uc": "V", "x": "um", "F": "N", "ua": "V"}
    de = root.find(f"{{{NS['ssd']}}}DefaultExperiment")
    assert float(de.get("startTime")) == 0.0 and float(de.get("stopTime")) == 0.3
    fs = de.find(f".//{{{NS['osp']}}}FixedStepAlgorithm")
    assert float(fs.get("baseStepSize")) == 1e-4
    assert fs.get("numWorkerThreads") == "0"      # libcosim steps the FMUs on its calling thread
    assert read_ssp_bindings(ssp) == {"Compensator": {
        "reference.signal": 1, "reference.amplitude": 45.0, "reference.offset": 45.0,
        "reference.freq": 10.0, "reference.phase": -90.0, "compensator.mode": 3,
        "compensator.inverse": 1}}


def test_write_is_atomic_and_checked(fmus, tmp_path, monkeypatch):
    target = tmp_path / "PiezoSystem.ssp"
    write_system_ssp(target, fmus)
    before = target.read_bytes()
    with pytest.raises(UserError, match="exists"):
        write_system_ssp(target, fmus, force=False)
    with pytest.raises(UserError, match="piezo-fmu build"):
        write_system_ssp(target, {**fmus, "Sensor": tmp_path / "nope.fmu"})
    with pytest.raises(UserError, match="Compensator"):
        write_system_ssp(target, {n: p for n, p in fmus.items() if n != "Compensator"})
    # a failure while writing leaves the old file untouched and no temporary behind

    def boom(self, *a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(zipfile.ZipFile, "write", boom)
    with pytest.raises(OSError, match="disk full"):
        write_system_ssp(target, fmus)
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["PiezoSystem.ssp"]
    with pytest.raises(UserError, match="step"):
        system_ssd(step=0.0)


# -- fmpy.ssp --------------------------------------------------------------------------------------------

def _fmpy_x(ssp, stop, step):
    """fmpy.ssp's displacement re-stamped onto t_k = k h (row i holds the values at t_(i+1))."""
    from fmpy.ssp.simulation import simulate_ssp

    res = simulate_ssp(str(ssp), stop_time=stop, step_size=step, parameter_set=fmpy_parameter_set(ssp))
    n = round(stop / step)
    assert len(res) >= n           # fmpy counts time += h: one extra row when the sum falls short
    np.testing.assert_allclose(res["time"][:n], step * np.arange(n), rtol=0, atol=1e-9 * stop)
    return {c: np.concatenate([[np.nan], res[c][:n]]) for c in res.dtype.names if c != "time"}


def _agrees_with_our_jacobi(who, x, t, early, x_jac, fmus, stroke):
    """Another master's displacement ``x`` against our Jacobi run ``x_jac`` (same initialisation):
    round-off over the first 10 ms; after 50 ms both sit in the same limit cycle around our
    Gauss-Seidel run (the Jacobi delay at 1e-4 s), of the same size within 25 %."""
    gs = cosimulate(fmus, PAPER_10HZ, 0.3, 1e-4)["x"]
    d_early = np.max(np.abs(x[early] - x_jac[early]))
    late = t >= 0.05
    rms = [math.sqrt(np.mean((y[late] - gs[late]) ** 2)) for y in (x, x_jac)]
    print(f"\n  {who}: vs our Jacobi {d_early:.1e} um over the first 10 ms; "
          f"limit cycle rms(x - x_GS) after 50 ms {rms[0] * 1e3:.1f} nm (ours {rms[1] * 1e3:.1f} nm)")
    assert d_early <= 1e-9 * stroke
    assert abs(rms[0] - rms[1]) <= 0.25 * rms[1]


def test_fmpy_ssp_runs_the_package(ssp, fmus, stroke):
    # the default experiment (fmpy ignores the SSD's DefaultExperiment: pass it)
    fx = _fmpy_x(ssp, 0.3, 1e-4)
    x = fx["Actuator.x"]
    t = 1e-4 * np.arange(x.size)
    zero = cosimulate(fmus, PAPER_10HZ, 0.3, 1e-4, algorithm="jacobi", initial="zero")
    _agrees_with_our_jacobi("fmpy.ssp at 1e-4 s", x, t, (t > 0) & (t < 0.01), zero["x"], fmus, stroke)
    # the SSP's parameter bindings reached the Compensator: it tracks the 10 Hz 0-90 V sine
    assert abs(np.nanmax(fx["Compensator.x_target"]) - stroke) < 1e-3 * stroke

    # a stable step: tight agreement
    h, stop = STABLE_STEP, 0.1
    fx = _fmpy_x(ssp, stop, h)
    x = fx["Actuator.x"]
    zero = cosimulate(fmus, PAPER_10HZ, stop, h, algorithm="jacobi", initial="zero")
    jac = cosimulate(fmus, PAPER_10HZ, stop, h, algorithm="jacobi")
    gs = cosimulate(fmus, PAPER_10HZ, stop, h)
    d = {k: float(np.max(np.abs(x[1:] - r["x"][1:]))) for k, r in
         (("jacobi zero init", zero), ("jacobi", jac), ("gauss-seidel", gs))}
    print(f"  fmpy.ssp at {h:g} s: max |dx| vs our " + ", ".join(f"{k} {v:.2e} um" for k, v in d.items()))
    # same algorithm and initialisation: round-off (fmpy's time += h moves the reference by ulps)
    assert d["jacobi zero init"] <= 1e-9 * stroke
    # zero instead of consistent initial connectors: the first step runs with uc = 0 instead of the
    # initial command uc0; its effect on x is bounded by the amplifier's response to uc0 over a step
    uc0 = jac["uc"][0]
    bound = abs(uc0) * 10.0 * 0.05 * 2.0          # k_amp * ~k_ideal [um/V], factor 2 for the loop
    assert d["jacobi"] <= max(bound, 1e-9), (d["jacobi"], bound)
    # Gauss-Seidel: the Jacobi delay, well below 1 % of the stroke at this step
    assert d["gauss-seidel"] <= 0.005 * stroke


# -- libcosim --------------------------------------------------------------------------------------------

LIBCOSIM_RUNNER = textwrap.dedent(r"""
    import ctypes, json, sys
    import numpy as np
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimObserver import CosimObserver
    from libcosimpy.CosimEnums import CosimVariableType
    from libcosimpy.CosimLogging import log_output_level, CosimLogLevel
    from libcosimpy._internal import libcosimc

    ssp, step_ns, stop_ns, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
    log_output_level(CosimLogLevel.WARNING)
    # libcosim times are int64 NANOSECONDS (a float in seconds crashes or silently misleads)
    if step_ns > 0:
        ex = CosimExecution.from_ssp_file(ssp, step_size=step_ns)
    else:
        ex = CosimExecution.from_ssp_file(ssp)      # the step from the osp:FixedStepAlgorithm annotation
    names = ("Actuator", "Sensor", "Compensator")
    idx = {n: ex.slave_index_from_instance_name(n) for n in names}     # not SSD order
    vr = {n: {v.name.decode(): v.reference for v in ex.slave_variables(i)} for n, i in idx.items()}
    cols = [("Actuator", "x"), ("Sensor", "us"), ("Compensator", "uc"), ("Compensator", "x_target")]
    obs = CosimObserver.create_time_series()
    ex.add_observer(obs)
    for n, v in cols:
        obs.start_time_series(idx[n], vr[n][v], CosimVariableType.REAL)
    ok = ex.simulate_until(target_time=stop_ns)
    # libcosimpy 0.0.6's time_series_real_samples drops the last sample: call the C function
    get = libcosimc().cosim_observer_slave_get_real_samples
    get.restype = ctypes.c_int64
    res = {}
    for n, v in cols:
        m = 10 ** 6
        val, stp, tim = (ctypes.c_double * m)(), (ctypes.c_int64 * m)(), (ctypes.c_int64 * m)()
        cnt = get(obs.ptr(), idx[n], ctypes.c_uint32(vr[n][v]), ctypes.c_int64(0), ctypes.c_size_t(m),
                  val, stp, tim)
        res[f"{n}.{v}"] = np.array(val[:cnt])
        res["time_ns"] = np.array(tim[:cnt])
    np.savez(out, **res)
    print(json.dumps({"ok": bool(ok), "samples": int(cnt), "now_ns": int(ex.status().current_time)}))
    del ex, obs                  # free the instances before the interpreter shuts down
""")


@pytest.fixture(scope="module")
def libcosim(tmp_path_factory):
    pytest.importorskip("libcosimpy", reason="libcosimpy (test dependency) is not installed")
    d = tmp_path_factory.mktemp("libcosim")
    script = d / "run_libcosim.py"
    script.write_text(LIBCOSIM_RUNNER)

    def run(ssp, step_s, stop_s):
        out = d / f"run_{len(list(d.glob('*.npz')))}.npz"
        step_ns = 0 if step_s is None else round(step_s * 1e9)
        proc = subprocess.run([sys.executable, str(script), str(ssp), str(step_ns),
                               str(round(stop_s * 1e9)), str(out)],
                              capture_output=True, text=True, timeout=300, cwd=d, check=False)
        assert proc.returncode == 0, f"libcosim run failed ({proc.returncode}): {proc.stderr[-2000:]}"
        facts = json.loads(proc.stdout.strip().splitlines()[-1])
        return facts, dict(np.load(out))
    return run


def test_libcosim_runs_the_package(ssp, fmus, libcosim, stroke):
    # the default experiment: step from the OSP annotation, stop time 0.3 s (libcosim ignores stopTime)
    facts, lc = libcosim(ssp, None, 0.3)
    assert facts["ok"] and facts["now_ns"] == 300_000_000
    np.testing.assert_array_equal(lc["time_ns"], 100_000 * np.arange(3001))
    x = lc["Actuator.x"]
    t = 1e-4 * np.arange(x.size)
    jac = cosimulate(fmus, PAPER_10HZ, 0.3, 1e-4, algorithm="jacobi")
    # same initialisation (consistent initial values): identical first samples
    assert lc["Compensator.uc"][0] == jac["uc"][0] and x[0] == jac["x"][0]
    _agrees_with_our_jacobi("libcosim at 1e-4 s (annotation)", x, t, t < 0.01, jac["x"], fmus, stroke)
    assert abs(np.max(lc["Compensator.x_target"]) - stroke) < 1e-3 * stroke   # bindings applied

    # a stable step (the step size argument overrides the annotation): round-off agreement
    h, stop = STABLE_STEP, 0.1
    facts, lc = libcosim(ssp, h, stop)
    assert facts["samples"] == 4001
    jac = cosimulate(fmus, PAPER_10HZ, stop, h, algorithm="jacobi")
    gs = cosimulate(fmus, PAPER_10HZ, stop, h)
    d_jac = float(np.max(np.abs(lc["Actuator.x"] - jac["x"])))
    d_gs = float(np.max(np.abs(lc["Actuator.x"] - gs["x"])))
    d_uc = float(np.max(np.abs(lc["Compensator.uc"] - jac["uc"])))
    print(f"  libcosim at {h:g} s: max |dx| vs our Jacobi {d_jac:.2e} um (|duc| {d_uc:.1e} V), "
          f"vs our Gauss-Seidel {d_gs:.2e} um")
    assert d_jac <= 1e-9 * stroke
    assert d_gs <= 0.005 * stroke
