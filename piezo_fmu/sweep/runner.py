"""One run of a sweep: its values -> the model and experiment -> a simulation -> one results row.

:func:`run_one` never raises: a model the overrides make invalid, a simulation that fails or
produces NaN, a missing FMU, all become a row with ``status = "error"`` and the message, so one bad
unit never ends a sweep of thousands. It is pure: the row depends only on the spec and the index
(the wall time ``seconds`` aside), which is what lets dask run it again on another worker after a
worker died, and what makes a sweep's results independent of the number of workers.

Workers keep the base model parsed and the FMUs unpacked per process (keyed by content), and
:func:`warm` compiles the numba kernels once per worker before the runs are timed.
"""
from __future__ import annotations

import hashlib
import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from .metrics import compute
from .space import point, run_values
from .spec import SweepSpec

__all__ = ["ROW_FIELDS", "RunContext", "experiment_for", "run_one", "run_task", "warm"]

# columns of every row besides the varied values and the metrics
ROW_FIELDS = (("index", "int"), ("grid", "int"), ("draw", "int"), ("status", "str"), ("error", "str"),
              ("seconds", "float"))
MAX_MESSAGE = 500

_MODELS = {}          # spec hash -> base Model (per worker process)
_FMU_DIRS = {}        # content hash -> folder with the unpacked FMUs (per worker process)


@dataclass(frozen=True)
class RunContext:
    """What every run needs: the spec and, for a co-simulation without ``fmu_dir``, the FMUs'
    bytes (``{name: bytes}``; written to a temporary folder once per worker process)."""

    spec: SweepSpec
    fmus: dict | None = None


def _base(spec: SweepSpec):
    model = _MODELS.get(spec.hash)
    if model is None:
        if len(_MODELS) > 8:
            _MODELS.clear()
        model = _MODELS[spec.hash] = spec.base_model()
    return model


def _fmu_dir(fmus: dict) -> Path:
    digest = hashlib.sha256(b"".join(fmus[k] for k in sorted(fmus))).hexdigest()[:16]
    folder = _FMU_DIRS.get(digest)
    if folder is None or not folder.is_dir():
        folder = Path(tempfile.mkdtemp(prefix=f"piezo-fmu-sweep-{digest}-"))
        for name, data in fmus.items():
            (folder / f"{name}.fmu").write_bytes(data)
        _FMU_DIRS[digest] = folder
    return folder


def experiment_for(spec: SweepSpec, values: dict) -> dict:
    """The experiment of a run: ``spec.experiment`` with the ``experiment.*`` values applied, and
    derived ``stop_time`` [s], ``record_step`` [s], ``skip`` [s] and ``ref_freq`` [Hz]."""
    e = dict(spec.experiment)
    for key, v in values.items():
        if key.startswith("experiment."):
            e[key.split(".", 1)[1]] = v
    periodic = e["signal"] in ("sine", "triangle")
    period = 1.0 / e["freq"] if periodic else math.nan
    if e["stop_time"] is None:
        e["stop_time"] = (e["periods"] or 3.0) * period if periodic else 0.05
    if e["record_step"] is None:
        e["record_step"] = (period / e["samples_per_period"] if periodic
                            else e["stop_time"] / 5000.0)
    m = spec.metrics
    e["skip"] = m["skip_time"] or (m["skip_periods"] * period if periodic and m["skip_periods"] else 0.0)
    e["ref_freq"] = e["freq"] if periodic else 0.0
    return e


def _record_step(wanted, h):
    """A whole multiple of ``h`` [s] near ``wanted`` (at least one step)."""
    return max(1, round(wanted / h)) * h


def _simulate(model, e, fmu_dir):
    from ..simulate import Signal

    signal = Signal(e["signal"], e["amplitude"], e["offset"], e["freq"], e["phase"])
    if e["engine"] == "monolithic":
        from ..simulate import simulate

        h = e["step"] or model["simulation"]["step"]
        res = simulate(model, signal, e["stop_time"], step=h, mode=e["mode"], inverse=e["inverse"],
                       record_step=_record_step(e["record_step"], h), control_step=e["control_step"],
                       engine=e["kernels"], noise=e["noise"])
    else:
        from ..cosim import cosimulate
        from ..model import with_values

        if not e["noise"]:
            model = with_values(model, {"sensor.noise_std": 0.0}, "sweep: experiment.noise = false")
        H = e["comm_step"]
        res = cosimulate(fmu_dir, signal, e["stop_time"], step=H, algorithm=e["algorithm"],
                         mode=e["mode"], inverse=e["inverse"], model=model,
                         record_step=_record_step(e["record_step"], H), engine=e["kernels"])
    return res.data


def run_one(spec: SweepSpec, index: int, fmus: dict | None = None) -> dict:
    """The results row of run ``index``: ``index, grid, draw``, the varied values, the metrics,
    ``status`` (``"ok"`` or ``"error"``), ``error`` (the message, or ``""``) and ``seconds`` (wall
    time of the run in the worker [s]). Never raises."""
    from ..model import with_values

    t0 = time.perf_counter()
    row = {"index": int(index)}
    names = spec.metric_names
    metrics = {n: (None if n == "stable" else math.nan) for n in names}
    try:
        row["grid"], row["draw"] = point(spec, index)
        values = run_values(spec, index)
        row.update(values)
        e = experiment_for(spec, values)
        overrides = {k: v for k, v in values.items() if not k.startswith("experiment.")}
        base = _base(spec)
        model = with_values(base, overrides, "sweep") if overrides else base
        if e["engine"] == "cosim":
            fmu_dir = e["fmu_dir"] or (_fmu_dir(fmus) if fmus else None)
            if fmu_dir is None:
                raise RuntimeError("no FMUs for the co-simulation (give experiment.fmu_dir)")
        else:
            fmu_dir = None
        data = _simulate(model, e, fmu_dir)
        c = model["compensator"]
        metrics = compute(data["time"], data["x_ref"], data["x"], data["uc"], (c["uc_min"], c["uc_max"]),
                          skip=e["skip"], settle_band=spec.metrics["settle_band_pct"] / 100.0,
                          ref_freq=e["ref_freq"], names=names)
        row.update(metrics)
        row["status"], row["error"] = "ok", ""
    except Exception as exc:  # noqa: BLE001 - a failing run is a row, never the end of the sweep
        row.update(metrics)
        row["status"] = "error"
        text = str(exc) if _is_user_error(exc) else f"{type(exc).__name__}: {exc}"
        row["error"] = text[:MAX_MESSAGE]
    row["seconds"] = time.perf_counter() - t0
    return row


def _is_user_error(exc):
    from ..errors import UserError

    return isinstance(exc, UserError)


def run_task(context: RunContext, index: int) -> dict:
    """:func:`run_one` in the form :meth:`piezo_fmu.parallel.Engine.map` calls it."""
    return run_one(context.spec, index, context.fmus)


def warm(context: RunContext):
    """Compile what the runs will use (numba kernels; the FMUs' compiled engine) with a run of a
    few steps of the base experiment; errors are left for the real runs to report."""
    spec = context.spec
    e = experiment_for(spec, {})
    if e["kernels"] != "numba":
        return
    short = dict(e)
    h = e["comm_step"] if e["engine"] == "cosim" else (e["step"] or _base(spec)["simulation"]["step"])
    short["stop_time"] = 20 * h
    short["record_step"] = h
    try:
        fmu_dir = (e["fmu_dir"] or (_fmu_dir(context.fmus) if context.fmus else None)) if e["engine"] == "cosim" else None
        if e["engine"] == "monolithic" or fmu_dir is not None:
            _simulate(_base(spec), short, fmu_dir)
    except Exception:  # noqa: BLE001, S110 - the runs report their own errors
        pass
