"""``piezo-fmu bench``: speed figures, measured side by side in one run.

1. ``floor_us_per_step``: three instances of a trivial pass-through FMU built the same way
   (pythonfmu, the same slave base) in a ring, stepped by the co-simulation master's own
   Gauss-Seidel loop at H = 1e-4 s: the cost of the FMI machinery alone.
2. ``cosim_us_per_step``: the closed loop of the three real FMUs through the same loop
   (the paper's 10 Hz experiment, H = 1e-4 s), with the Actuator and Compensator FMUs' kernels
   compiled (``simulation.engine = numba``, when numba is installed; ``cosim_engine`` says which);
   ``cosim_to_floor`` (target <= 1.5) and ``cosim_realtime_factor`` = simulated / wall time
   (target >= 3). The same with the interpreted kernels (the FMUs' default, NumPy only):
   ``cosim_python_*``. Wall time of the stepping loop (``cosimulate``'s ``us_per_step``; loading
   and initialising the FMUs excluded).
3. ``monolithic_samples_per_s``: the monolithic model of the same closed loop, the actuator
   integrated at an internal step of 1e-5 s and the sensor and compensator sampled at H = 1e-4 s
   as in the co-simulation (``simulate(control_step=H)``), numba engine (the interpreted one as
   ``monolithic_python_samples_per_s``); like the co-simulation figure, the wall time of the
   stepping loop (``SimResult.samples_per_s``); ``monolithic_end_to_end_samples_per_s`` includes
   building the model and the recording table. ``monolithic_speedup_vs_cosim``: wall time per
   simulated second, loop against loop (target >= 100); ``monolithic_end_to_end_speedup_vs_cosim``
   the same with the monolithic model end to end. Also the single-rate model, the compensator
   acting every 1e-5 s (``monolithic_single_rate_*``): ten times the controller work of the
   co-simulated loop.
4. ``pi_ns_per_sample_operator``: the PI step kernel (compiled), forward and inverse (mean of the
   two; each also reported), plus the interpreted kernel and the vectorised scan. The step kernel
   is O(1) per sample away from reversals (see ``core.hysteresis.pi_step``), so the figure per
   sample (``pi_*_ns_per_sample``) is the more telling one; "per operator" divides it by n = 9.
5. ``diagnose_s``: ``diagnose`` (outputs included) on a fixed set of hard cases, each a synthetic
   recording of 20 s at 10 kHz with two channels: a resonant plant (first mode at 900 Hz, the
   sensor between stack and push rod, and a further mode to find), two mechanisms (creep and a
   delay) and a long record with creep, and (full size) recordings of the independent rig as drawn
   (:data:`DIAGNOSE_RIG_CASES`); ``diagnose_s`` is the slowest (target < 60 s),
   ``diagnose_median_s`` the median, ``diagnose_cases`` each case's seconds and what it named,
   ``diagnose_threads`` the worker threads each used (:mod:`piezo_fmu.diagnose.workers`).
6. ``write_csv_s``, ``write_parquet_s``: writing the 1e6 rows of a 100 s run recorded every 1e-4 s
   (the command line's default) through :class:`piezo_fmu.results.RunWriter` (target < 5 s).
7. The FMUs' native runtime (:func:`piezo_fmu.bench_runtime.runtime_figures`), in one run:

   * one FMI call on the pass-through FMU: ``call_master_dostep_us`` / ``call_master_setget_us``
     (``fmi2DoStep``; one ``fmi2SetReal`` or ``fmi2GetReal``) from our master's binding on the main
     thread, ``call_master_thread_*`` from another Python thread; ``call_c_*`` and
     ``call_c_thread_*`` the same from the C host ``tests/host/fmi2_host.c`` on its main thread
     and on a thread Python has never seen;
   * the 3-FMU closed loop per communication step from the C host: ``loop_c_us_per_step`` (engine
     ``cosim_engine``) and ``loop_c_python_us_per_step``, with ``loop_c_to_master`` and
     ``loop_c_python_to_master`` against ``cosim_us_per_step`` / ``cosim_python_us_per_step``
     (target <= 1: the C host no slower than our master);
   * libcosim driven from C (``tests/host/libcosim_run.c`` on libcosimpy's ``libcosimc.so``):
     ``loop_libcosim_us_per_step`` for ``PiezoSystem.ssp`` (the FMUs' default engine, so against
     ``cosim_python_us_per_step``: ``loop_libcosim_to_master``, target <= 3) and
     ``loop_libcosim_floor_us_per_step``, three pass-through FMUs in a ring: libcosim's own cost
     per step, both with the SSD's ``numWorkerThreads="0"`` (the FMUs stepped on libcosim's
     calling thread), and ``loop_libcosim_pool_us_per_step`` / ``loop_libcosim_floor_pool_us_per_step``
     the same with libcosim's default worker pool (its hand-offs; see :mod:`.bench_runtime`);
   * ``cosim_command_us_per_step``: the ``cosim`` command as a user runs it (a fresh process,
     ``--out run.csv``, recording every 1e-4 s, the FMUs' default engine, its progress, CSV and
     error summary), per communication step: the difference between a long and a short run
     (``cosim_command_steps`` apart) over the difference in steps, so the fixed costs (imports,
     loading the FMUs) are excluded and everything a step costs is in; ``cosim_command_to_loop``
     against ``cosim_python_us_per_step`` (target <= 1.3); ``cosim_command_fixed_s`` the fixed
     part (from the command's imports to its summary, interpreter start excluded). Runs too
     short to tell apart (``--size tiny``) give the whole command per step instead.

   The C figures need a C compiler and the repository's ``tests/host`` (a source checkout), the
   libcosim ones libcosimpy; without them those keys are ``None``.

Every figure is the best of a few repetitions (the machine's other load only slows runs down).
``--size tiny`` runs each part briefly so the test suite can check the benchmark keeps working.
"""
from __future__ import annotations

import ctypes
import math
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from .bench_runtime import RUNTIME_KEYS, runtime_figures
from .builder import build_all
from .sweep.throughput import SWEEP_KEYS, measure_throughput

__all__ = ["KEYS", "RUNTIME_KEYS", "SIZES", "SWEEP_KEYS", "format_figures", "run_bench", "runtime_figures"]

KEYS = ("floor_us_per_step", "cosim_us_per_step", "cosim_to_floor", "cosim_realtime_factor",
        "monolithic_samples_per_s", "monolithic_speedup_vs_cosim", "pi_ns_per_sample_operator",
        "diagnose_s")
H = 1e-4

SIZES = {  # steps per co-simulation run, repetitions, monolithic seconds, PI samples, diagnose recording
    "full": dict(steps=5000, reps=10, mono_s=10.0, mono_py_s=0.2, pi_n=200_000, diag=(20.0, 10_000.0),
                 write_rows=1_000_000, calls=100_000, command_s=10.0),
    "tiny": dict(steps=300, reps=1, mono_s=0.02, mono_py_s=0.01, pi_n=2_000, diag=(0.6, 2_000.0),
                 write_rows=2_000, calls=2_000, command_s=0.05),
}


def _best(fn, reps):
    return min(fn() for _ in range(reps))


def _floor_and_cosim_us(passthrough, fmus, steps, reps, engines):
    """``(floor, {engine: cosim})`` in us per step: the best of ``reps`` runs of each, taken in
    turns (floor, co-simulation with each engine, floor, ...) so that all see the same machine;
    the ratio of two measurements taken minutes apart would carry the machine's drift."""
    from .cosim import Plan, cosimulate
    from .fmi import load_slaves
    from .simulate import Signal

    names = ("P1", "P2", "P3")
    slaves = load_slaves({n: passthrough for n in names})
    with slaves:
        for s in slaves.values():
            s.setup(0.0)
            s.enter_initialization(0.0)
        for s in slaves.values():
            s.exit_initialization(0.0)
        ring = [(a, "y", b, "u") for a, b in zip(names, names[1:] + names[:1])]
        plan = Plan(slaves, names, {n: (["u"], ["y"]) for n in names}, ring, None,
                           [(n, "y") for n in names])
        rec_every = 10
        buf = (ctypes.c_double * (plan.width * (steps // rec_every + 1)))()
        done = [0]

        def floor():
            t0 = time.perf_counter()
            plan.gauss_seidel(done[0], steps, 0.0, H, rec_every, None, buf)
            done[0] += steps
            return (time.perf_counter() - t0) / steps * 1e6

        def system(engine):
            res = cosimulate(fmus, Signal("sine", 45.0, 45.0, 10.0), steps * H, H,
                                   record_step=rec_every * H, engine=engine)
            return res.info["us_per_step"]

        for e in engines:       # compile (the numba engine: once per process) outside the timing
            cosimulate(fmus, Signal("sine", 45.0, 45.0, 10.0), 10 * H, H, engine=e)
        runs = [(floor(), {e: system(e) for e in engines}) for _ in range(reps)]
    return min(f for f, _ in runs), {e: min(c[e] for _, c in runs) for e in engines}


def _monolithic(model, seconds, engine, reps, control_step):
    from .simulate import Signal, simulate

    sig = Signal("sine", 45.0, 45.0, 10.0)
    simulate(model, sig, 0.002, step=1e-5, engine=engine)        # compile / warm up

    def once():
        t0 = time.perf_counter()
        res = simulate(model, sig, seconds, step=1e-5, record_step=H, control_step=control_step,
                       engine=engine)
        return res.samples_per_s, res.n_steps / (time.perf_counter() - t0)

    runs = [once() for _ in range(reps)]
    return max(r[0] for r in runs), max(r[1] for r in runs)


def _speedup(cosim_us_per_step, mono_samples_per_s):
    """Wall time per simulated second: co-simulation (steps of H) over monolithic (1e-5 s steps)."""
    return (cosim_us_per_step * 1e-6 / H) * (mono_samples_per_s * 1e-5)


def _pi_figures(model, n, reps):
    """ns per sample and operator: compiled kernel, interpreted kernel, vectorised scan."""
    from .core.hysteresis import pi_state, pi_step, pi_table, play_scan
    from .simulate import compiled_kernels, numba_available

    fwd = model.hysteresis("hysteresis")
    inv = fwd.inverse()
    rng = np.random.default_rng(0)
    u = 45.0 + 40.0 * np.sin(np.cumsum(rng.uniform(0.0, 0.02, n)))
    out = {}
    for label, m, x in (("forward", fwd, u / fwd.in_scale), ("inverse", inv, fwd.apply(u) / inv.in_scale)):
        r, w = np.array(m.thresholds), np.array(m.weights)
        wt = np.array(pi_table(m.thresholds, m.weights))
        ops = n * m.n
        if numba_available():
            import numba

            kern = compiled_kernels()["pi_step"]

            @numba.njit(cache=False)
            def run(v, r, w, z, y):
                for k in range(v.size):
                    y[k] = kern(v[k], r, w, z)

            y = np.empty_like(x)
            run(x[:10], r, wt, np.array(pi_state(m.n)), y)          # compile

            def compiled():
                z = np.array(pi_state(m.n))
                t0 = time.perf_counter()
                run(x, r, wt, z, y)
                return (time.perf_counter() - t0) / ops * 1e9

            out[f"pi_{label}_ns_per_sample_operator"] = _best(compiled, reps)
            out[f"pi_{label}_ns_per_sample"] = out[f"pi_{label}_ns_per_sample_operator"] * m.n
        rl, wl, xl = list(r), list(wt), x[: max(1, n // 20)].tolist()

        def interpreted():
            z = pi_state(len(rl))
            t0 = time.perf_counter()
            for v in xl:
                pi_step(v, rl, wl, z)
            return (time.perf_counter() - t0) / (len(xl) * len(rl)) * 1e9

        def scan():
            t0 = time.perf_counter()
            play_scan(x, r) @ w
            return (time.perf_counter() - t0) / ops * 1e9

        out[f"pi_{label}_interpreted_ns_per_sample_operator"] = _best(interpreted, reps)
        out[f"pi_{label}_interpreted_ns_per_sample"] = (
            out[f"pi_{label}_interpreted_ns_per_sample_operator"] * m.n)
        out[f"pi_{label}_scan_ns_per_sample_operator"] = _best(scan, reps)
    key = "pi_{}_ns_per_sample_operator" if numba_available() else "pi_{}_interpreted_ns_per_sample_operator"
    out["pi_ns_per_sample_operator"] = 0.5 * (out[key.format("forward")] + out[key.format("inverse")])
    return out


# the hard cases of the diagnose figure: (name, synth seed, mechanisms, plant changes)
DIAGNOSE_CASES = (
    ("resonant plant", 3, ("extra_resonance",), {"mechanics.m": 5.9, "mechanics.pickoff": "contact"}),
    ("two mechanisms", 5, ("creep", "time_delay"), {}),
    ("long record", 7, ("creep",), {}),
)


# and recordings of the independent rig (``piezo_fmu.rig``, its own plant and hysteresis), as drawn:
# (name, draw, case id). rig-d14-095 was the slowest case of fresh draw 14 (74.7 s two at a time):
# a 1.1 kHz first mode, creep and a loop shape, 14.3 s at 5.08 kHz
DIAGNOSE_RIG_CASES = (
    ("independent rig device", 14, "rig-d14-095"),
)


def _diagnose_figures(model_path, seconds, fs, workdir, rig_cases=True):
    """``diagnose`` (outputs included) on each hard case (``rig_cases``: with the rig's): median and
    slowest seconds."""
    from . import rig
    from .diagnose import diagnose
    from .diagnose.synth import make_case, write_recording
    from .model import load_model, with_values

    cases = {}
    for name, draw, case_id in (DIAGNOSE_RIG_CASES if rig_cases else ()):
        rec = rig.generate(next(s for s in rig.cases(draw=draw) if s.case_id == case_id), twins=True)
        path = Path(workdir) / f"{case_id}.csv"
        rig.write_csv(rec, path)
        t0 = time.perf_counter()
        diag = diagnose([str(path)], model_path, Path(workdir) / "diagnosis", force=True)
        cases[f"{name} ({case_id})"] = {"seconds": time.perf_counter() - t0, "truth": list(rec.truth["mechanisms"]),
                                        "named": list(diag.result["final"]["effects"]),
                                        "samples": int(rec.u.size)}
    for name, seed, effects, changes in DIAGNOSE_CASES:
        base = with_values(load_model(model_path), changes, "bench: a resonant plant") if changes else None
        case = make_case(seed, effects=effects, fs=fs, duration=seconds, channels=("x", "us"), base=base)
        rec = Path(workdir) / "bench_recording.csv"
        write_recording(rec, case, force=True)
        t0 = time.perf_counter()
        diag = diagnose([str(rec)], model_path, Path(workdir) / "diagnosis", force=True)
        cases[name] = {"seconds": time.perf_counter() - t0, "truth": list(effects),
                       "named": list(diag.result["final"]["effects"]), "samples": int(case.t.size)}
    from .diagnose.workers import thread_count

    secs = sorted(c["seconds"] for c in cases.values())
    return {"diagnose_s": secs[-1], "diagnose_median_s": secs[len(secs) // 2], "diagnose_cases": cases,
            "diagnose_threads": thread_count()}


def _write_figures(rows, reps, workdir):
    """Seconds to write ``rows`` recorded rows (a 100 s run at the CLI's default recording step of
    1e-4 s is 1e6 rows) through :class:`~piezo_fmu.results.RunWriter`, as CSV and as Parquet, in
    the chunks ``simulate`` streams (50 000 rows)."""
    from .results import RunWriter

    t = np.arange(rows) * 1e-4
    table = np.column_stack([t, 2.2 + 2.2 * np.sin(2 * np.pi * 10 * t), 2.2 + 2.1 * np.sin(2 * np.pi * 10 * t - 0.1),
                             1e-3 * np.cos(t), 4.5 + np.sin(t), 45 + 45 * np.sin(t), 400 * np.sin(t)])
    out = {"write_rows": rows}
    for fmt in ("csv", "parquet"):
        path = Path(workdir) / f"bench.{fmt}"

        def once():
            t0 = time.perf_counter()
            with RunWriter(path, force=True) as w:
                for k in range(0, rows, 50_000):
                    w(table[k:k + 50_000])
            return time.perf_counter() - t0
        out[f"write_{fmt}_s"] = _best(once, max(1, min(reps, 3)))
        out[f"write_{fmt}_MB"] = path.stat().st_size / 1e6
        path.unlink()
    return out


def _machine():
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import fmpy
    import numpy
    import pythonfmu

    info = {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "numpy": numpy.__version__, "fmpy": fmpy.__version__, "pythonfmu": pythonfmu.__version__,
            "platform": platform.platform()}
    try:
        import numba

        info["numba"] = numba.__version__
    except ImportError:
        info["numba"] = None
    return info


def run_bench(size="full", model=None, say=None) -> dict:
    """Run every measurement; returns the figures (see the module docstring)."""
    from .model import DEFAULT_MODEL, load_model

    say = say or (lambda msg: None)
    cfg = SIZES[size]
    model_path = Path(model) if model else DEFAULT_MODEL
    m = load_model(model_path)
    out = {"size": size, "machine": _machine(), "step_s": H}
    with tempfile.TemporaryDirectory(prefix="piezo-fmu-bench-") as tmp:
        say("building the FMUs and the pass-through floor FMU")
        fmus = build_all(model_path, tmp, floor=True, ssp=False, log=lambda *a, **k: None)
        from .simulate import numba_available

        engine = "numba" if numba_available() else "python"
        engines = (engine, "python") if engine != "python" else ("python",)
        say(f"FMI floor (3 pass-through instances) and co-simulation (3 FMUs; engine "
            f"{' and '.join(engines)}), in turns: {cfg['steps']} steps x {cfg['reps']} each")
        system = {n: fmus[n] for n in ("Actuator", "Sensor", "Compensator")}
        out["floor_us_per_step"], per_engine = _floor_and_cosim_us(
            fmus["PassThrough"], system, cfg["steps"], cfg["reps"], engines)
        out["cosim_engine"] = engine
        for key, e in (("", engine), ("_python", "python")):
            out[f"cosim{key}_us_per_step"] = per_engine[e]
            out[f"cosim{key}_to_floor"] = per_engine[e] / out["floor_us_per_step"]
            out[f"cosim{key}_realtime_factor"] = H / (per_engine[e] * 1e-6)

        say("monolithic model at 1e-5 s")
        out["monolithic_engine"] = engine
        out["monolithic_control_step_s"] = H
        for key, seconds, eng, control in (("", cfg["mono_s"], engine, H),
                                           ("_single_rate", cfg["mono_s"] / 5, engine, None),
                                           ("_python", cfg["mono_py_s"], "python", H)):
            out[f"monolithic{key}_samples_per_s"], out[f"monolithic{key}_end_to_end_samples_per_s"] = (
                _monolithic(m, seconds, eng, cfg["reps"], control))
        for key in ("", "_end_to_end", "_single_rate", "_python"):
            out[f"monolithic{key}_speedup_vs_cosim"] = _speedup(out["cosim_us_per_step"],
                                                               out[f"monolithic{key}_samples_per_s"])
        # the interpreted model against the interpreted FMUs (NumPy only on both sides)
        out["monolithic_python_speedup_vs_cosim_python"] = _speedup(
            out["cosim_python_us_per_step"], out["monolithic_python_samples_per_s"])
        say("native FMI runtime: calls, closed loop from C and in libcosim, the cosim command")
        out.update(runtime_figures(fmus, cfg, out, engine=engine))
        say(f"writing {cfg['write_rows']:,} recorded rows as CSV and Parquet")
        out.update(_write_figures(cfg["write_rows"], cfg["reps"], tmp))
        say("PI operator throughput")
        out.update(_pi_figures(m, cfg["pi_n"], cfg["reps"]))
        seconds, fs = cfg["diag"]
        rig_cases = size == "full"
        say(f"diagnose on {len(DIAGNOSE_CASES)} hard cases, each {seconds:g} s at {fs:g} Hz with two channels"
            + (f", and {len(DIAGNOSE_RIG_CASES)} of the independent rig" if rig_cases else ""))
        out.update(_diagnose_figures(model_path, seconds, fs, tmp, rig_cases=rig_cases))
        out["diagnose_recording"] = {"seconds": seconds, "rate_hz": fs, "channels": ["x", "us"]}
    say("sweeps on dask (piezo_fmu.sweep.throughput): 1 and 2 workers, 1 and 2 plain processes")
    out.update(measure_throughput(size, say=say))
    out["targets"] = {"loop_c_to_master": "<= 1", "loop_libcosim_to_master": "<= 3", "sweep_scaling_efficiency": ">= 0.8",
                      "cosim_command_to_loop": "<= 1.3", "cosim_us_per_step": "<= 10 (compiled)",
                      "cosim_to_floor": "<= 1.5", "cosim_realtime_factor": ">= 3",
                      "monolithic_samples_per_s": ">= 1e6", "monolithic_speedup_vs_cosim": ">= 100",
                      "diagnose_s": "< 60 (20 s at 10 kHz)"}
    return out


def _us(r, key, digits):
    v = r.get(key)
    return "n/a" if v is None else f"{v:.{digits}f}"


def _diagnose_cases_text(r):
    return ", ".join(f"{k} {v['seconds']:.0f} s" for k, v in r.get("diagnose_cases", {}).items())


def format_figures(r) -> str:
    rows = [("FMI floor (3 pass-through FMUs)", f"{r['floor_us_per_step']:.1f} us/step"),
            (f"co-simulation (3 FMUs, H = 1e-4 s, {r['cosim_engine']})", f"{r['cosim_us_per_step']:.1f} us/step"),
            ("co-simulation / floor", f"{r['cosim_to_floor']:.2f} (target <= 1.5)"),
            ("co-simulation real-time factor", f"{r['cosim_realtime_factor']:.2f} (target >= 3)"),
            ("co-simulation, interpreted FMUs", f"{r['cosim_python_us_per_step']:.1f} us/step, "
                                                f"{r['cosim_python_to_floor']:.2f} x floor, real time "
                                                f"x{r['cosim_python_realtime_factor']:.2f}"),
            (f"monolithic, 1e-5 s, control 1e-4 s ({r['monolithic_engine']})",
             f"{r['monolithic_samples_per_s']:.3g} samples/s (target >= 1e6)"),
            ("monolithic, end to end (incl. model build)",
             f"{r['monolithic_end_to_end_samples_per_s']:.3g} samples/s, "
             f"x{r['monolithic_end_to_end_speedup_vs_cosim']:.0f} vs co-simulation"),
            ("monolithic, interpreted", f"{r['monolithic_python_samples_per_s']:.3g} samples/s, "
                                        f"x{r['monolithic_python_speedup_vs_cosim_python']:.2f} vs "
                                        "the interpreted FMUs"),
            ("monolithic speed-up vs co-simulation", f"x{r['monolithic_speedup_vs_cosim']:.0f} (target >= 100)"),
            ("monolithic, single rate (control 1e-5 s)",
             f"{r['monolithic_single_rate_samples_per_s']:.3g} samples/s, "
             f"x{r['monolithic_single_rate_speedup_vs_cosim']:.0f} vs co-simulation"),
            ("PI step, forward / inverse", f"{r.get('pi_forward_ns_per_sample_operator', math.nan):.2f} / "
                                           f"{r.get('pi_inverse_ns_per_sample_operator', math.nan):.2f} "
                                           "ns per sample and operator (compiled; "
                                           f"{r.get('pi_forward_ns_per_sample', math.nan):.0f} ns "
                                           "per sample)"),
            ("PI step, interpreted", f"{r['pi_forward_interpreted_ns_per_sample_operator']:.0f} ns per "
                                     f"sample and operator ({r['pi_forward_interpreted_ns_per_sample']:.0f} "
                                     "ns per sample)"),
            ("PI scan, vectorised", f"{r['pi_forward_scan_ns_per_sample_operator']:.1f} ns per sample and "
                                    "operator"),
            ("one FMI call from our master: fmi2DoStep / Set-GetReal",
             f"{_us(r, 'call_master_dostep_us', 2)} / {_us(r, 'call_master_setget_us', 3)} us "
             f"(another Python thread {_us(r, 'call_master_thread_dostep_us', 2)} / "
             f"{_us(r, 'call_master_thread_setget_us', 3)} us)"),
            ("one FMI call from C: fmi2DoStep / Set-GetReal",
             f"{_us(r, 'call_c_dostep_us', 2)} / {_us(r, 'call_c_setget_us', 3)} us (a thread Python never saw "
             f"{_us(r, 'call_c_thread_dostep_us', 2)} / {_us(r, 'call_c_thread_setget_us', 3)} us)"),
            (f"closed loop from the C host ({r['cosim_engine']} / python)",
             f"{_us(r, 'loop_c_us_per_step', 1)} / {_us(r, 'loop_c_python_us_per_step', 1)} us/step, "
             f"x{_us(r, 'loop_c_to_master', 2)} / x{_us(r, 'loop_c_python_to_master', 2)} our master (target <= 1)"),
            ("closed loop in libcosim (python engine)",
             f"{_us(r, 'loop_libcosim_us_per_step', 1)} us/step, x{_us(r, 'loop_libcosim_to_master', 1)} our "
             f"master (target <= 3); 3 pass-through FMUs {_us(r, 'loop_libcosim_floor_us_per_step', 1)} us/step"),
            ("the cosim command, recording every step",
             f"{_us(r, 'cosim_command_us_per_step', 1)} us/step ({r.get('cosim_command_steps', 0)} steps "
             f"apart), x{_us(r, 'cosim_command_to_loop', 2)} the stepping loop (target <= 1.3); fixed "
             f"{_us(r, 'cosim_command_fixed_s', 2)} s"),
            ("writing a 100 s run (1e6 rows at 1e-4 s)" if r["write_rows"] == 1_000_000
             else f"writing {r['write_rows']} rows",
             f"CSV {r['write_csv_s']:.2f} s ({r['write_csv_MB']:.0f} MB), Parquet {r['write_parquet_s']:.2f} s "
             f"({r['write_parquet_MB']:.0f} MB) (target < 5 s)"),
            ("diagnose, hard cases", f"slowest {r['diagnose_s']:.1f} s, median {r['diagnose_median_s']:.1f} s "
                                     f"({_diagnose_cases_text(r)}) "
                                     f"for {r['diagnose_recording']['seconds']:g} s at "
                                     f"{r['diagnose_recording']['rate_hz']:g} Hz, 2 channels, "
                                     f"{r.get('diagnose_threads', 2)} threads (target < 60 s)"),
            ("sweep on dask, 1 / 2 workers", f"{r['sweep_runs_per_s_1']:.0f} / {r['sweep_runs_per_s_2']:.0f} runs/s "
             f"({r['sweep_run_ms']:.1f} ms a run), scaling {100 * r['sweep_scaling_efficiency']:.0f} % (goal >= 80 "
             f"%; 2 plain processes: {100 * r['sweep_machine_scaling_efficiency']:.0f} %), overhead "
             f"{r['sweep_overhead_per_task_ms']:.0f} ms per task, {100 * r['sweep_overhead_fraction']:.0f} % of 1 worker")]
    width = max(len(a) for a, _ in rows)
    return "\n".join(f"{a:<{width}}  {b}" for a, b in rows)
