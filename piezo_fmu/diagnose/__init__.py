"""``piezo-fmu diagnose``: find where a model and recordings of a real rig differ, name the missing
physics, model it, and show the fit improve on held-out data.

::

    piezo-fmu diagnose REC.csv [REC2.csv ...] [--model models/paper.toml] --out DIR [--force]

Python API: :func:`diagnose` (read, analyse, write) or :func:`.run.analyse` on recordings in memory.
The command line over it is :mod:`piezo_fmu.cli.diagnose`. The heavy modules are imported when
:func:`diagnose` runs, so importing this package costs nothing.
"""
from __future__ import annotations

import time

from .budget import TIME_BUDGET_S

__all__ = ["diagnose"]


def diagnose(recordings, model=None, out=None, *, force=False, columns=None, scale=None, say=None,
             figures=True, time_budget_s=TIME_BUDGET_S, replay_rate=None, threads=None):
    """Diagnose recording files against a model; write the results into ``out`` when given.

    Parameters
    ----------
    recordings : list of str or Path
        CSV files with a header row: ``time`` [s] (uniform), ``u`` [V] (the amplifier command) and
        ``x`` [um] (displacement) and/or ``us`` [V] (sensor voltage). Several are fitted together.
    model : str or Path, optional
        The nominal model file (default: the paper's).
    out : str or Path, optional
        Folder for diagnosis.json, fit.csv, model.toml, report.html and figures (created; files
        there are not overwritten without ``force``).
    columns, scale : dict, optional
        ``{"time": "t", "x": "disp"}`` maps column names; ``{"x": 1e6}`` multiplies a column after
        reading (m -> um).
    say : callable, optional
        ``say(message)`` for progress messages.
    figures : bool
        Write the PNG figures (report.html embeds them).
    time_budget_s : float or None
        Search budget [s of the reference machine per 200 k samples, the budget growing in
        proportion for a longer record]: after that much work no further candidate
        search is started (what was found stays; diagnosis.json says so); ``None``: no limit.
        Counted as work (samples simulated), not time, so the result does not depend on the
        machine or its load.
    replay_rate : float, optional
        Replay rate [Hz]: a recording sampled slower is replayed with several internal steps per
        sample (the amplifier's and the mechanics' path between the samples); 8000 is the rate
        measured on the rig (see :mod:`.recordings`). Default: one step per sample.
    threads : int, optional
        Worker threads for the independent evaluations (default 2, or the environment variable
        ``PIEZO_FMU_DIAGNOSE_THREADS``); one costs less CPU where the cores are busy anyway. The
        result does not depend on it.

    Returns
    -------
    Diagnosis
        ``.result`` is the content of diagnosis.json (held-out RMSE per channel in the channel's
        unit, um or V; findings with confidence 0..1; parameters with units).
    """
    from ..model import load_model
    from .report import check_outputs, write_outputs
    from .run import analyse, load_recordings

    say = say or (lambda msg: None)
    if out is not None:
        check_outputs(out, force)
    raw = load_recordings(recordings, columns, scale)
    base = load_model(model)
    diag = analyse(raw, base, say=say, time_budget_s=time_budget_s, replay_rate=replay_rate, threads=threads)
    if out is not None:
        t0 = time.perf_counter()
        write_outputs(diag, out, force=force, say=say, figures=figures)
        diag.timing["outputs_s"] = time.perf_counter() - t0
    return diag
