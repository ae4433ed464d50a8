"""The FMI runtime's figures of ``piezo-fmu bench`` (see :mod:`piezo_fmu.bench`, item 7): the cost
of one FMI call from our master and from a C host (main thread and a foreign thread), the closed
loop stepped from C and by libcosim driven from C, and the ``cosim`` command as a user sees it.
The C hosts are the repository's (``tests/host``), compiled here; without a compiler, a source
checkout or libcosimpy those keys are ``None``.

libcosim: where the time goes
-----------------------------
``loop_libcosim_us_per_step`` / ``loop_libcosim_floor_us_per_step`` run ``libcosim_run`` on the
SSD's fixed-step algorithm with ``numWorkerThreads="0"`` (as :mod:`.ssp` writes it); the
``*_pool_*`` keys the same systems with libcosim's default worker pool (``--fixed-step``, what
``cosim_ssp_fixed_step_execution_create`` and libcosimpy's ``from_ssp_file(step_size=..)`` give).
Measured 2026-11-22 on the 2-core VM while three CPU-bound processes of other jobs ran (load 5-6),
5000 steps of 1e-4 s, best of 3 (median), wall us per communication step, taken in turns::

                                        3 pass-through FMUs    PiezoSystem (python engine)
    default pool (1 worker on 2 cores)    16.5 (26)  cpu 16.4     42 (105)  cpu 28
    numWorkerThreads="0"                   3.7 (5.4) cpu 3.3      10.7 (25) cpu 9.6
    our master, same run                  11.7 (13)               15.2 (17)

(the bench's own run a minute later: 4.4 / 13.7 us at zero workers, 98 / 45 us with the pool,
our master 7.8 / 13.4 us: x1.0 our master, was x3.4; last session's 68 us floor was the pool.)

Why. libcosim 0.11.2 (the ``libcosimc.so`` of libcosimpy 0.0.6) steps in
``fixed_step_algorithm::impl::do_step`` (``src/cosim/algorithm/fixed_step_algorithm.cpp``): each
FMU's step (set inputs, ``fmi2DoStep``, get outputs: ``slave_simulator::do_step``) is submitted as
a ``std::function`` task to ``utility::thread_pool`` (``src/cosim/utility/thread_pool.hpp``: one
mutex, a queue, two condition variables), the calling thread blocks in
``wait_for_tasks_to_finish`` and then transfers the connections itself. The pool has
``min(numWorkerThreads, hardware_concurrency() - 1)`` workers (the ``impl`` constructor,
``max_threads_``): one on this machine, so no parallelism at all, only a wake-up of the worker
and of the caller every step (futex calls and context switches, in a VM whose cores are shared,
plus the scheduler's latency): ~13 us of CPU and 13-95 us of wall time per step, independent of
the FMUs (pinning the process to one CPU with ``taskset`` does not help: 19 against 16.5 us).
More cores would not help these FMUs either: the three share the process's one embedded Python
and its GIL (``fmu_src/runtime/fmi2_bridge.c``), so their steps cannot overlap. With zero workers
``thread_pool::submit`` runs the task on the calling thread (``threads_.empty()``) and a step is
a plain loop.

libcosimc offers no worker count: ``cosim_fixed_step_algorithm_create(stepSize)``,
``cosim_execution_create`` and ``cosim_ssp_fixed_step_execution_create`` all build
``fixed_step_algorithm(step)`` with the default pool (libcosimc ``src/cosim.cpp``). The one way from
C is the SSD's OSP annotation ``<osp:FixedStepAlgorithm baseStepSize=".." numWorkerThreads="0"/>``
(``src/cosim/ssp/ssp_parser.cpp``; declared in libcosim's ``OSPAnnotations.xsd``), which
``cosim_ssp_execution_create`` uses - the configuration a libcosim user sets for this system.
The results do not change: ``tests/test_runtime.py`` checks the zero-worker run from C against
libcosimpy's run with the default pool.

The rest is small (same measurements):
``cosim_execution_step(exec, N)`` against ``simulate_until``: the same within the noise (real time
is off by default; ``real_time_timer::sleep`` then hashes the config and reads the clock,
``src/cosim/timer.cpp``); the time-series observer of 3-4 variables ~0.9 us of CPU per step (a
mutex and a ``std::map`` insert per variable, ``time_series_observer.cpp`` ``observe``; no
observer saves that, a last-value observer costs about as much); the FMUs loaded with
``cosim_local_slave_create`` and connected from C instead of through the SSP: the same algorithm,
the same cost per step. At zero workers the ring's ~3.3 us of CPU are ~1-1.7 us for the three
``fmi2DoStep`` calls into Python (``call_c_dostep_us``), ~0.9 us the observer and ~1 us libcosim's
bookkeeping (a ``std::function`` per FMU, a ``std::stringstream`` and an ``unordered_set`` built in
every ``do_step``, ``unordered_map`` look-ups per connection).
"""
from __future__ import annotations

import ctypes
import functools
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

__all__ = ["HOST_SRC", "RUNTIME_KEYS", "runtime_figures"]

# the runtime's figures (item 7); the C and libcosim ones are None without a compiler, the
# repository's tests/host or libcosimpy
RUNTIME_KEYS = ("call_master_dostep_us", "call_master_setget_us", "call_master_thread_dostep_us",
                "call_master_thread_setget_us", "call_c_dostep_us", "call_c_setget_us",
                "call_c_thread_dostep_us", "call_c_thread_setget_us", "loop_c_us_per_step",
                "loop_c_python_us_per_step", "loop_c_to_master", "loop_c_python_to_master",
                "loop_libcosim_us_per_step", "loop_libcosim_to_master", "loop_libcosim_floor_us_per_step",
                "loop_libcosim_pool_us_per_step", "loop_libcosim_floor_pool_us_per_step",
                "cosim_command_us_per_step", "cosim_command_to_loop")
HOST_SRC = Path(__file__).resolve().parents[1] / "tests" / "host"    # the C hosts (a source checkout)
H = 1e-4


def _best(fn, reps):
    return min(fn() for _ in range(reps))


def _master_calls(passthrough, n, reps):
    """us per fmi2DoStep and per fmi2SetReal/fmi2GetReal through our master's binding
    (:attr:`piezo_fmu.fmi.Slave.hot`), on this thread and on another Python thread."""
    import threading

    from .fmi import load_slaves

    with load_slaves({"P": passthrough}) as slaves:
        s = slaves["P"]
        s.setup(0.0)
        s.enter_initialization(0.0)
        s.exit_initialization(0.0)
        setr, dostep, getr = s.hot
        in_vr, inp, _ = s.bind(["u"])
        out_vr, out, _ = s.bind(["y"])
        c, one, h, no_prior = s.c, ctypes.c_size_t(1), ctypes.c_double(H), ctypes.c_int(1)
        res = {}

        def measure(key):
            t = ctypes.c_double(0.0)

            def steps():
                t0 = time.perf_counter()
                for _ in range(n):
                    dostep(c, t, h, no_prior)
                return (time.perf_counter() - t0) / n * 1e6

            def setget():
                t0 = time.perf_counter()
                for _ in range(n):
                    setr(c, in_vr, one, inp)
                    getr(c, out_vr, one, out)
                return (time.perf_counter() - t0) / (2 * n) * 1e6
            res[f"call_master{key}_dostep_us"] = _best(steps, reps)
            res[f"call_master{key}_setget_us"] = _best(setget, reps)

        measure("")
        worker = threading.Thread(target=measure, args=("_thread",))
        worker.start()
        worker.join()
    return res


def _compile(src, exe, *flags):
    from .builder.runtime import find_compiler

    argv, _ = find_compiler()
    if argv is None or not Path(src).is_file():
        return None
    proc = subprocess.run([*argv, "-O2", "-o", str(exe), str(src), *flags], capture_output=True, text=True,
                          check=False, timeout=300)
    return exe if proc.returncode == 0 else None


def _numbers(stdout):
    return {ln.split()[0]: float(ln.split()[1]) for ln in stdout.splitlines()
            if len(ln.split()) == 2 and not ln.startswith(("row", "status", "errors"))}


def _c_host_figures(fmus, cfg, workdir, engine):
    """The C host's figures (None each without a compiler or tests/host)."""
    from fmpy import extract, read_model_description

    res = dict.fromkeys(("call_c_dostep_us", "call_c_setget_us", "call_c_thread_dostep_us",
                         "call_c_thread_setget_us", "loop_c_us_per_step", "loop_c_python_us_per_step"))
    host = _compile(HOST_SRC / "fmi2_host.c", Path(workdir) / "fmi2_host", "-ldl", "-lpthread", "-lm")
    if host is None:
        return res
    info = {}
    for name in ("Actuator", "Sensor", "Compensator", "PassThrough"):
        md = read_model_description(str(fmus[name]))
        info[name] = (f"{extract(str(fmus[name]), unzipdir=str(Path(workdir) / name))}:{name}:{md.guid}",
                      {v.name: v.valueReference for v in md.modelVariables})
    env = {"PATH": "/usr/bin:/bin"}       # nothing of this process's Python
    run = functools.partial(subprocess.run, capture_output=True, text=True, check=False, timeout=600, env=env)
    calls = _numbers(run([str(host), "bench", info["PassThrough"][0], str(cfg["calls"])]).stdout)
    for src, key in (("main_dostep_us", "call_c_dostep_us"), ("main_setget_us", "call_c_setget_us"),
                     ("thread_dostep_us", "call_c_thread_dostep_us"), ("thread_setget_us", "call_c_thread_setget_us")):
        res[key] = calls.get(src)
    a, s, c = (info[n][1] for n in ("Actuator", "Sensor", "Compensator"))
    env["HOST_LOOP_VRS"] = ",".join(str(v) for v in (a["uc"], a["x"], a["F"], a["ua"], s["F"], s["us"], c["us"],
                                                       c["uc"], c["x_target"]))
    specs = [info[n][0] for n in ("Actuator", "Sensor", "Compensator")]
    compiled = [arg for n, vrs in (("Actuator", a), ("Compensator", c))
                for arg in ("--int", f"{n}:{vrs['simulation.engine']}=1")]
    for key, flags in (("loop_c_python_us_per_step", []),
                       ("loop_c_us_per_step", compiled if engine == "numba" else [])):
        best = [_numbers(run([str(host), *flags, "bench-loop", *specs, str(cfg["steps"]), str(H)]).stdout)
                .get("loop_us_per_step") for _ in range(max(1, min(cfg["reps"], 3)))]
        best = [b for b in best if b]
        res[key] = min(best) if best else None
    return res


RING_SSD = """<?xml version="1.0" encoding="UTF-8"?>
<ssd:SystemStructureDescription xmlns:ssc="http://ssp-standard.org/SSP1/SystemStructureCommon"
    xmlns:ssd="http://ssp-standard.org/SSP1/SystemStructureDescription"
    xmlns:osp="http://opensimulationplatform.com/SSP/OSPAnnotations" version="1.0" name="Ring">
  <ssd:System name="Ring"><ssd:Elements>{components}</ssd:Elements><ssd:Connections>{connections}
  </ssd:Connections></ssd:System>
  <ssd:DefaultExperiment startTime="0.0"><ssd:Annotations>
    <ssc:Annotation type="com.opensimulationplatform"><osp:Algorithm>
      <osp:FixedStepAlgorithm baseStepSize="{step}" numWorkerThreads="{workers}"/>
    </osp:Algorithm></ssc:Annotation>
  </ssd:Annotations></ssd:DefaultExperiment>
</ssd:SystemStructureDescription>
"""


def _libcosim_figures(fmus, cfg, workdir):
    """libcosim driven from C: PiezoSystem.ssp and a ring of three pass-through FMUs, each with
    the SSD's algorithm at ``numWorkerThreads="0"`` and (``*_pool_*``) with libcosim's default
    worker pool (``--fixed-step``), the runs taken in turns."""
    keys = ("loop_libcosim_us_per_step", "loop_libcosim_floor_us_per_step", "loop_libcosim_pool_us_per_step",
            "loop_libcosim_floor_pool_us_per_step")
    res = dict.fromkeys(keys)
    try:
        import libcosimpy
    except ImportError:
        return res
    from .ssp import write_system_ssp

    libdir = Path(libcosimpy.__file__).parent / "libcosimc"
    exe = _compile(HOST_SRC / "libcosim_run.c", Path(workdir) / "libcosim_run", f"-L{libdir}", "-l:libcosimc.so",
                   f"-Wl,-rpath,{libdir}")
    if exe is None:
        return res
    # the SSD asks for numWorkerThreads="0"; --fixed-step below runs the default pool
    ssp = write_system_ssp(Path(workdir) / "PiezoSystem.ssp",
                           {n: fmus[n] for n in ("Actuator", "Sensor", "Compensator")}, step=H)
    ring = Path(workdir) / "ring"
    (ring / "resources").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(fmus["PassThrough"], ring / "resources" / "PassThrough.fmu")
    names = ("P1", "P2", "P3")
    components = "".join(f'<ssd:Component name="{n}" source="resources/PassThrough.fmu"><ssd:Connectors>'
                         '<ssd:Connector name="u" kind="input"><ssc:Real/></ssd:Connector>'
                         '<ssd:Connector name="y" kind="output"><ssc:Real/></ssd:Connector>'
                         '</ssd:Connectors></ssd:Component>' for n in names)
    connections = "".join(f'<ssd:Connection startElement="{a}" startConnector="y" endElement="{b}" '
                          'endConnector="u"/>' for a, b in zip(names, names[1:] + names[:1]))
    (ring / "SystemStructure.ssd").write_text(RING_SSD.format(components=components, connections=connections,
                                                              step=repr(H), workers=0))
    step_ns = round(H * 1e9)
    stop_ns = cfg["steps"] * step_ns
    runs = {"loop_libcosim_us_per_step": ([], ssp, []),
            "loop_libcosim_floor_us_per_step": ([], ring, ["P1.y", "P2.y", "P3.y"]),
            "loop_libcosim_pool_us_per_step": (["--fixed-step"], ssp, []),
            "loop_libcosim_floor_pool_us_per_step": (["--fixed-step"], ring, ["P1.y", "P2.y", "P3.y"])}
    best = {k: [] for k in keys}
    for _ in range(max(1, min(cfg["reps"], 3))):
        for key, (flags, target, cols) in runs.items():
            proc = subprocess.run([str(exe), *flags, str(target), str(step_ns), str(stop_ns), *cols],
                                  capture_output=True, text=True, check=False, timeout=600, env={})
            best[key].append(_numbers(proc.stdout).get("us_per_step"))
    for key in keys:
        got = [b for b in best[key] if b]
        res[key] = min(got) if got else None
    return res


COMMAND = """
import contextlib, io, sys, time
t0 = time.perf_counter()
from piezo_fmu.cli import main
with contextlib.redirect_stderr(io.StringIO()):
    rc = main(["cosim", "--fmu-dir", sys.argv[1], "--stop-time", sys.argv[2], "--out", sys.argv[3], "--force",
               "--quiet"])
print("@@", rc, time.perf_counter() - t0)
"""


def _command_s(fmu_dir, seconds, workdir):
    """Seconds of one ``cosim`` command in a fresh process (imports to summary), None on failure."""
    import sys

    proc = subprocess.run([sys.executable, "-c", COMMAND, str(fmu_dir), repr(seconds),
                           str(Path(workdir) / "command.csv")], capture_output=True, text=True,
                          check=False, timeout=600)
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("@@")), None)
    return float(line.split()[2]) if line and line.split()[1] == "0" else None


def _command_us(fmu_dir, seconds, reps, workdir):
    """``(us per step, fixed s)`` of the ``cosim`` command: a run of ``seconds`` against one a
    tenth as long, the best of ``reps`` each (module docstring, item 7)."""
    short, long = seconds / 10, seconds
    t_short = [t for t in (_command_s(fmu_dir, short, workdir) for _ in range(reps)) if t]
    t_long = [t for t in (_command_s(fmu_dir, long, workdir) for _ in range(reps)) if t]
    if not t_short or not t_long:
        return None, None
    steps = round(long / H) - round(short / H)
    per_step = (min(t_long) - min(t_short)) / steps
    if per_step <= 0:     # runs too short to tell apart (the tiny size): the whole command per step
        return min(t_long) / round(long / H) * 1e6, min(t_short)
    return per_step * 1e6, min(t_short) - per_step * round(short / H)


def runtime_figures(fmus, cfg, master=None, workdir=None, engine="python") -> dict:
    """The native runtime's figures (module docstring). ``fmus``: ``build_all`` output with the
    pass-through FMU; ``cfg``: the size's settings (:data:`piezo_fmu.bench.SIZES`: ``calls``,
    ``reps``, ``steps``, ``command_s``); ``master``: the run's ``cosim_us_per_step`` and
    ``cosim_python_us_per_step`` [us] for the ratios."""
    master = master or {}
    out = {}
    with tempfile.TemporaryDirectory(prefix="piezo-fmu-bench-rt-") as tmp:
        work = Path(workdir or tmp)
        out.update(_master_calls(fmus["PassThrough"], cfg["calls"], cfg["reps"]))
        out.update(_c_host_figures(fmus, cfg, work, engine))
        out.update(_libcosim_figures(fmus, cfg, work))
        out["cosim_command_us_per_step"], out["cosim_command_fixed_s"] = _command_us(
            Path(fmus["Actuator"]).parent, cfg["command_s"], max(1, min(cfg["reps"], 2)), work)
    loop, loop_py = master.get("cosim_us_per_step"), master.get("cosim_python_us_per_step")

    def ratio(a, b):
        return a / b if a and b else None
    out["loop_c_to_master"] = ratio(out["loop_c_us_per_step"], loop)
    out["loop_c_python_to_master"] = ratio(out["loop_c_python_us_per_step"], loop_py)
    out["loop_libcosim_to_master"] = ratio(out["loop_libcosim_us_per_step"], loop_py)
    out["cosim_command_to_loop"] = ratio(out["cosim_command_us_per_step"], loop_py)
    out["cosim_command_steps"] = round(cfg["command_s"] / H) - round(cfg["command_s"] / 10 / H)
    return out
