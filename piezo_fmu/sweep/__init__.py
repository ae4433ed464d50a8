"""Sweeps and Monte Carlo studies of the closed loop, on dask.distributed.

A designer's questions need many runs: the tracking error of each control scheme from 0.5 to
200 Hz, the yield of a production batch whose parameters scatter, how much delay the loop
tolerates. :func:`sweep` runs a specification (:mod:`.spec`) of such a study::

    from piezo_fmu.sweep import sweep
    summary = sweep("examples/frequency_sweep.toml", "out/freq")            # a local cluster
    summary = sweep("spec.toml", "out/mc", scheduler="tcp://10.0.0.5:8786")  # an existing one

The parts, one concept each: :mod:`.spec` (the TOML, validated), :mod:`.space` (run index ->
varied values; random values from ``(seed, unit, key)``), :mod:`.runner` (one run -> one row,
never raises), :mod:`.metrics`, :mod:`.store` (streamed, resumable Parquet), :mod:`.report`
(HTML and PNGs). The engine is :mod:`piezo_fmu.parallel`.
"""
from __future__ import annotations

import time
from pathlib import Path

from .report import column_array, passes, write_report, yield_of
from .spec import SpecError, SweepSpec, load_spec, loads_spec
from .store import RESULTS, ResultStore, read_results

__all__ = ["SpecError", "SweepSpec", "build_fmus", "load_spec", "loads_spec", "read_results", "sweep",
           "write_report"]


def build_fmus(spec: SweepSpec, out_dir) -> dict:
    """``{name: bytes}`` of the three FMUs built from the spec's base model into
    ``out_dir/fmus`` (reused while the base model is the same)."""
    import hashlib

    from ..builder import SYSTEM, build_all

    digest = hashlib.sha256(spec.model_text.encode()).hexdigest()[:16]
    folder = Path(out_dir) / "fmus" / digest
    paths = {n: folder / f"{n}.fmu" for n in SYSTEM}
    if not all(p.is_file() for p in paths.values()):
        model_file = folder / "model.toml"
        folder.mkdir(parents=True, exist_ok=True)
        model_file.write_text(spec.model_text)
        built = build_all(model_file, folder, ssp=False, log=lambda *a, **k: None)
        paths = {n: Path(built[n]) for n in SYSTEM}
    return {n: p.read_bytes() for n, p in paths.items()}


def _needs_fmus(spec: SweepSpec) -> bool:
    engines = {spec.experiment["engine"]}
    for axis in spec.grid:
        if "experiment.engine" in axis.keys:
            engines |= {axis.at(k)["experiment.engine"] for k in range(len(axis.values))}
    return "cosim" in engines and spec.experiment["fmu_dir"] is None


def sweep(spec, out, scheduler=None, workers=None, resume=False, force=False, progress=None,
          report=True) -> dict:
    """Run a sweep: every run of ``spec`` into ``out/results.parquet``, then ``out/report.html``.

    Parameters
    ----------
    spec : str, Path or SweepSpec
        The specification file (or a loaded one); see :mod:`piezo_fmu.sweep.spec`.
    out : str or Path
        Output folder: ``results.parquet`` (one row per run, streamed as runs finish),
        ``sweep.json`` (the spec and base model), ``report.html`` and ``figures/``.
    scheduler : str, optional
        Address of a running dask scheduler (``tcp://host:port``) whose workers have piezo-fmu
        installed; default: a local cluster sized to the machine.
    workers : int, optional
        Local cluster size (default: one worker per core); with ``scheduler``, wait for that many
        workers; ``0``: run serially in this process, without dask.
    resume : bool
        Complete an interrupted sweep in ``out``: compute only the runs it lacks.
    force : bool
        Delete an earlier sweep's outputs in ``out`` first.
    progress : callable, optional
        ``progress(fraction, message)``: a stage (fraction ``None``) or the share of the runs to
        compute that are done.
    report : bool
        Write ``report.html`` and its figures at the end (``write_report`` does it later).

    Returns
    -------
    dict
        ``runs`` (in the spec), ``computed`` (by this call), ``ok``, ``error``, ``lost``,
        ``yield`` (with ``yield_low``, ``yield_high``: 95 % interval; with a tolerance),
        ``wall_s`` [s], ``runs_per_s`` (computed / wall time of the runs), ``engine``,
        ``results`` and ``report`` (paths; ``report`` None without one).

    Results are identical (``seconds`` aside) for any number of workers and to a serial run:
    every run depends only on the spec and its index. Ctrl-C keeps every finished row; call again
    with ``resume=True``.
    """
    from ..parallel import Engine, TaskFailed
    from .runner import RunContext, run_task, warm

    say = (lambda msg: progress(None, msg)) if progress is not None else (lambda msg: None)
    t_start = time.perf_counter()
    if not isinstance(spec, SweepSpec):
        spec = load_spec(spec)
    out = Path(out)
    fmu_dir = spec.experiment["fmu_dir"]
    if fmu_dir is not None and scheduler is None and not Path(fmu_dir).is_dir():
        raise SpecError(f"{spec.origin}: experiment.fmu_dir: {fmu_dir}: folder not found")
    store = ResultStore(out, spec, resume=resume, force=force)
    todo = [i for i in range(spec.n_runs) if i not in store.done]
    fmus = None
    if todo and _needs_fmus(spec):
        say("building the FMUs of the base model")
        fmus = build_fmus(spec, out)
    context = RunContext(spec, fmus)
    computed = 0
    wall_runs = 0.0
    described = "none: nothing to compute"
    try:
        if todo:
            say(f"{len(todo)} of {spec.n_runs} runs to compute; starting the engine")
            with Engine(scheduler, workers) as engine:
                described = engine.describe()
                say(f"engine: {described}" + ("; compiling numba on each worker"
                                              if spec.experiment["kernels"] == "numba" else ""))
                engine.warm(warm, context)
                say(f"running {len(todo)} runs")
                t_runs = time.perf_counter()
                fraction = (lambda f, msg="": progress(f)) if progress is not None else None
                for pos, row in engine.map(run_task, todo, context=context, progress=fraction,
                                           errors="return"):
                    if isinstance(row, TaskFailed):
                        row = _lost_row(spec, todo[pos], str(row))
                    store.add(row)
                    computed += 1
                wall_runs = time.perf_counter() - t_runs
    finally:
        store.close()
    table = read_results(out)
    data_status = table.column("status").to_pylist()
    summary = {"runs": spec.n_runs, "computed": computed, "ok": data_status.count("ok"),
               "error": data_status.count("error"), "lost": data_status.count("lost"),
               "wall_s": time.perf_counter() - t_start,
               "runs_per_s": computed / wall_runs if computed and wall_runs > 0 else None,
               "engine": described, "results": str(out / RESULTS)}
    if spec.tolerance is not None:
        data = {n: column_array(table, n) for n in table.column_names}
        y, lo, hi = yield_of(int(passes(spec, data).sum()), len(data["index"]))
        summary.update({"yield": y, "yield_low": lo, "yield_high": hi})
    summary["report"] = None
    if report:
        say("writing the report")
        summary["report"] = str(write_report(out, spec, table, {"computed now": computed,
                                                                "wall time [s]": round(summary["wall_s"], 1)}))
    return summary


def _lost_row(spec, index, message):
    from .space import point, run_values

    row = {"index": index, "status": "lost", "error": message[:500], "seconds": None}
    try:
        row["grid"], row["draw"] = point(spec, index)
        row.update(run_values(spec, index))
    except Exception:  # noqa: BLE001, S110 - the row keeps what is known
        pass
    return row

