"""How fast sweeps run on dask: runs per second on 1 and 2 workers, scaling, per-task overhead.

:func:`measure_throughput` runs the same batch of closed-loop runs (the paper's 10 Hz experiment,
ff + PID, three periods, the hysteresis weights drawn +-20 %: a tolerance study) through
:class:`piezo_fmu.parallel.Engine` on a local cluster of 1, then 2 workers, each warmed (numba
compiled) before the clock starts, results collected as in :func:`piezo_fmu.sweep.sweep` but not
written (the store and the report are not the engine). Figures:

* ``sweep_runs_per_s_1``, ``sweep_runs_per_s_2``: runs over wall time from the first submission
  to the last result;
* ``sweep_scaling_efficiency = runs_per_s_2 / (2 runs_per_s_1)`` (goal >= 0.8);
* ``sweep_run_ms``: a run's own time inside its worker (mean);
* ``sweep_overhead_per_task_ms``: on 1 worker, the wall time not spent in runs, per dask task
  (a task carries a batch of runs, sized to take about half a second), and
  ``sweep_overhead_fraction``: that time over the wall time;
* ``sweep_machine_scaling_efficiency``: the same runs split over 1, then 2 plain processes
  (``concurrent.futures``, no dask, no scheduler): what the machine itself gives a second
  process. On a shared machine it is below 1 whatever the engine does, and
  ``sweep_engine_efficiency = sweep_scaling_efficiency / sweep_machine_scaling_efficiency`` is
  the engine's own share.
"""
from __future__ import annotations

import time

__all__ = ["SPEC", "SWEEP_KEYS", "measure_throughput"]

SWEEP_KEYS = ("sweep_runs_per_s_1", "sweep_runs_per_s_2", "sweep_scaling_efficiency", "sweep_run_ms",
              "sweep_overhead_per_task_ms", "sweep_overhead_fraction", "sweep_machine_scaling_efficiency",
              "sweep_engine_efficiency")

SPEC = """
[sweep]
name = "throughput"
seed = 1
count = {count}

[experiment]
freq = 10.0
periods = {periods}
mode = "ff+fb"
kernels = "{kernels}"

[random]
"hysteresis.weights" = {{ tolerance_pct = 20 }}
"""

SIZES = {"full": {"runs": 400, "periods": 3, "kernels": "numba", "reps": 2},
         "tiny": {"runs": 8, "periods": 0.2, "kernels": "python", "reps": 1}}


def measure_throughput(size="full", workers=(1, 2), say=None) -> dict:
    """The figures of the module docstring (``size``: full or tiny; ``workers``: the two cluster
    sizes compared). The best of ``reps`` passes per cluster size."""
    from ..parallel import Engine
    from .runner import RunContext, run_task, warm
    from .spec import loads_spec

    say = say or (lambda msg: None)
    cfg = SIZES[size]
    spec = loads_spec(SPEC.format(count=cfg["runs"], periods=cfg["periods"], kernels=cfg["kernels"]))
    context = RunContext(spec)
    out = {"sweep_runs": cfg["runs"], "sweep_kernels": cfg["kernels"], "sweep_workers": list(workers)}
    rates = {}
    for n in workers:
        say(f"sweep throughput: {cfg['runs']} runs on a local cluster of {n} worker(s)")
        best = None
        with Engine(workers=n) as engine:
            engine.warm(warm, context)
            for _ in range(cfg["reps"]):
                tasks0 = engine.tasks
                t0 = time.perf_counter()
                rows = [row for _, row in engine.map(run_task, range(spec.n_runs), context=context)]
                wall = time.perf_counter() - t0
                busy = sum(r["seconds"] for r in rows)
                bad = [r for r in rows if r["status"] != "ok"]
                if bad:
                    raise RuntimeError(f"sweep throughput: a run failed: {bad[0]['error']}")
                if best is None or wall < best[0]:
                    best = (wall, busy, engine.tasks - tasks0)
        wall, busy, tasks = best
        rates[n] = spec.n_runs / wall
        out[f"sweep_runs_per_s_{n}"] = rates[n]
        if n == workers[0]:
            out["sweep_run_ms"] = 1e3 * busy / spec.n_runs
            out["sweep_overhead_per_task_ms"] = 1e3 * max(wall * n - busy, 0.0) / max(tasks, 1)
            out["sweep_overhead_fraction"] = max(wall * n - busy, 0.0) / (wall * n)
            out["sweep_tasks_1"] = tasks
    a, b = workers[0], workers[-1]
    out["sweep_scaling_efficiency"] = (rates[b] / rates[a]) / (b / a)
    plain = {n: _plain_processes(context, spec.n_runs, n, cfg["reps"], say) for n in (a, b)}
    out["sweep_machine_scaling_efficiency"] = (plain[b] / plain[a]) / (b / a)
    out["sweep_engine_efficiency"] = out["sweep_scaling_efficiency"] / out["sweep_machine_scaling_efficiency"]
    return out


def _runs(context, indices):
    from .runner import run_task

    return [run_task(context, i)["status"] for i in indices]


def _plain_processes(context, n_runs, n, reps, say):
    """Runs per second of ``n`` warmed plain processes, each running an equal share in order."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from .runner import warm

    say(f"sweep throughput: the same runs on {n} plain process(es), no dask")
    shares = [list(range(k, n_runs, n)) for k in range(n)]
    with ProcessPoolExecutor(n, mp_context=mp.get_context("spawn"), initializer=warm,
                             initargs=(context,)) as pool:
        list(pool.map(_runs, [context] * n, [[0]] * n))          # every process started and warm
        best = 0.0
        for _ in range(reps):
            t0 = time.perf_counter()
            list(pool.map(_runs, [context] * n, shares))
            best = max(best, n_runs / (time.perf_counter() - t0))
    return best
