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

__all__ = ["diagnose"]


def diagnose(recordings, model=None, out=None, *, force=False, columns=None, scale=None, say=None,
             figures=True):
    """Diagnose recording files against a model; write the results into ``out`` when given.

    Returns the :class:`~piezo_fmu.diagnose.run.Diagnosis` (``.result`` is diagnosis.json).
    """
    from ..model import load_model
    from .report import check_outputs, write_outputs
    from .run import analyse, load_recordings

    say = say or (lambda msg: None)
    if out is not None:
        check_outputs(out, force)
    raw = load_recordings(recordings, columns, scale)
    base = load_model(model)
    diag = analyse(raw, base, say=say)
    if out is not None:
        t0 = time.perf_counter()
        write_outputs(diag, out, force=force, say=say, figures=figures)
        diag.timing["outputs_s"] = time.perf_counter() - t0
    return diag
