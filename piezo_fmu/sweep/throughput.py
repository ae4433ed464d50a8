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
* ``sweep_machine_scaling_efficiency``: the same runs in chunks of 10 over 1, then 2 plain
  processes (``concurrent.futures``, no dask, no scheduler): what the machine itself gives a
  second process. On a shared machine it is below 1 whatever the engine does, and
  ``sweep_engine_efficiency = sweep_scaling_efficiency / sweep_machine_scaling_efficiency`` is
  the engine's own share.

Each set-up is measured alone: started, warmed, timed ``reps`` times (the best counts), closed,
before the next one starts (local cluster of 1 worker, 1 plain process, cluster of 2, 2
processes). An idle local cluster is not free: its scheduler and nannies live in this process
and, like its workers, wake up periodically (with dask's defaults about 50 ms of CPU per second
in this process and 35-40 ms per worker), which a user's sweep, running one cluster, does not
pay. Measuring in turns with all set-ups alive would charge that to whichever set-up is timed,
most to the one that uses every core. The price: the two sizes are timed some seconds apart,
so the machine's drift enters their ratio; the best of ``reps`` passes is kept against it.
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

SIZES = {"full": {"runs": 400, "periods": 3, "kernels": "numba", "reps": 3},
         "tiny": {"runs": 8, "periods": 0.2, "kernels": "python", "reps": 1}}


def measure_throughput(size="full", workers=(1, 2), say=None) -> dict:
    """The figures of the module docstring (``size``: full or tiny; ``workers``: the two sizes
    compared). Each set-up runs alone (module docstring): a local cluster of ``workers[0]``
    worker(s), as many plain processes, then the same with ``workers[-1]``; each is warmed (numba
    compiled) before the clock starts and timed ``reps`` times, the best pass kept."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from ..parallel import Engine
    from .runner import RunContext, warm
    from .spec import loads_spec

    say = say or (lambda msg: None)
    cfg = SIZES[size]
    spec = loads_spec(SPEC.format(count=cfg["runs"], periods=cfg["periods"], kernels=cfg["kernels"]))
    context = RunContext(spec)
    n_runs = spec.n_runs
    reps = cfg["reps"]
    out = {"sweep_runs": n_runs, "sweep_kernels": cfg["kernels"], "sweep_workers": list(workers)}
    best = {}
    for n in workers:
        say(f"sweep throughput: local cluster of {n} worker(s) alone, warming, then {reps} pass(es) "
            f"of {n_runs} runs")
        with Engine(workers=n) as engine:
            engine.warm(warm, context)
            best[("dask", n)] = min(_on_engine(engine, context) for _ in range(reps))
        say(f"sweep throughput: {n} plain process(es) alone, warming, then {reps} pass(es)")
        with ProcessPoolExecutor(n, mp_context=mp.get_context("spawn"), initializer=warm,
                                 initargs=(context,)) as pool:
            list(pool.map(_runs, [context] * n, [[0]] * n))      # every process started, warm
            best[("plain", n)] = min(_on_pool(pool, context, n_runs, n) for _ in range(reps))
    a, b = workers[0], workers[-1]
    for n in workers:
        out[f"sweep_runs_per_s_{n}"] = n_runs / best[("dask", n)][0]
    wall, busy, tasks = best[("dask", a)]
    out["sweep_run_ms"] = 1e3 * busy / n_runs
    out["sweep_overhead_per_task_ms"] = 1e3 * max(wall * a - busy, 0.0) / max(tasks, 1)
    out["sweep_overhead_fraction"] = max(wall * a - busy, 0.0) / (wall * a)
    out["sweep_tasks_1"] = tasks
    out["sweep_scaling_efficiency"] = (best[("dask", a)][0] / best[("dask", b)][0]) / (b / a)
    out["sweep_plain_runs_per_s_1"] = n_runs / best[("plain", a)]
    out["sweep_machine_scaling_efficiency"] = (best[("plain", a)] / best[("plain", b)]) / (b / a)
    out["sweep_engine_efficiency"] = out["sweep_scaling_efficiency"] / out["sweep_machine_scaling_efficiency"]
    return out


def _on_engine(engine, context):
    """``(wall [s], seconds inside the runs [s], tasks)`` of one pass over all runs."""
    from ..parallel import TaskFailed
    from .runner import run_task

    tasks0 = engine.tasks
    t0 = time.perf_counter()
    rows = [row for _, row in engine.map(run_task, range(context.spec.n_runs), context=context,
                                         errors="return")]       # as piezo_fmu.sweep.sweep
    wall = time.perf_counter() - t0
    bad = [str(r) if isinstance(r, TaskFailed) else r["error"] for r in rows
           if isinstance(r, TaskFailed) or r["status"] != "ok"]
    if bad:
        raise RuntimeError(f"sweep throughput: a run failed: {bad[0]}")
    return wall, sum(r["seconds"] for r in rows), engine.tasks - tasks0


def _runs(context, indices):
    from .runner import run_task

    return [run_task(context, i)["status"] for i in indices]


def _on_pool(pool, context, n_runs, n, chunk=10):
    """Wall time [s] of ``n`` warmed plain processes taking chunks of ``chunk`` runs as they
    finish (dynamic, like dask's batches, so a process the machine starves does not hold up
    the others)."""
    chunks = [list(range(k, min(k + chunk, n_runs))) for k in range(0, n_runs, chunk)]
    t0 = time.perf_counter()
    list(pool.map(_runs, [context] * len(chunks), chunks))
    return time.perf_counter() - t0
