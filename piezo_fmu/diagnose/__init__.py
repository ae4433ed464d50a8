"""``piezo-fmu diagnose``: find where a model and recordings of a real rig differ, name the missing
physics, model it, and show the fit improve on held-out data.

::

    piezo-fmu diagnose REC.csv [REC2.csv ...] [--model models/paper.toml] --out DIR [--force]

Python API: :func:`diagnose` (read, analyse, write) or :func:`.run.analyse` on recordings in memory.
The heavy modules are imported when the command runs, so registering the command costs nothing.
"""
from __future__ import annotations

import sys
import time

__all__ = ["diagnose", "register"]


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


def _cmd(args):
    from ..recording import parse_mapping

    t0 = time.perf_counter()

    def say(msg):
        if not args.quiet:
            print(msg, file=sys.stderr, flush=True)

    columns = parse_mapping(args.columns, "--columns")
    scale = parse_mapping(args.scale, "--scale", numeric=True)
    diag = diagnose(args.recordings, args.model, args.out, force=args.force, columns=columns or None,
                    scale=scale or None, say=say, figures=not args.no_figures)
    print(summary(diag.result))
    say(f"wrote {args.out}/ (diagnosis.json, fit.csv, model.toml, report.html) in "
        f"{time.perf_counter() - t0:.1f} s")
    return 0


def summary(res):
    """A few lines for the terminal."""
    chans = list(res["baseline"]["rmse"])
    lines = [res["final"]["verdict"]]
    lines.append("held-out rmse: " + ", ".join(
        f"{c} {res['baseline']['rmse'][c]:.4g} -> {res['final']['rmse'][c]:.4g} (noise {res['baseline']['noise'][c]:.3g})"
        for c in chans))
    for f in res["findings"]:
        where = f["where"][0] if f["where"] else None
        lines.append(f"  {f['effect']:<24} confidence {f['confidence']:.2f}  {f['parameters']}"
                     + (f"  e.g. {where['t0']:.3g}-{where['t1']:.3g} s" if where else ""))
        rival = f["evidence"].get("strongest_alternative")
        if rival and rival["passed"]:
            lines.append(f"  {'':<24} (the data nearly as well support {rival['effect']}: explains "
                         + ", ".join(f"{c} {100 * v:.0f} %" for c, v in rival["explained_share"].items()) + ")")
    for u in res["unexplained"]:
        lines.append(f"  unexplained ({u['channel']}): {u['description']}")
    return "\n".join(lines)


def register(subparsers):
    p = subparsers.add_parser(
        "diagnose", help="find what a model misses in recordings of a real rig",
        description="Recalibrate the model to the recordings, locate where they still differ (time, "
                    "frequency, operating range, channel), name the missing physics from a catalogue "
                    "(creep, sensor_leakage, amplifier_current_limit, time_delay, extra_resonance, "
                    "thermal_drift, hysteresis_shape), fit it, and validate on held-out data. Writes "
                    "diagnosis.json, fit.csv, model.toml (loadable by every command; rebuild the FMUs "
                    "from it), report.html and its PNG figures into --out.")
    p.add_argument("recordings", nargs="+", metavar="REC.csv",
                   help="CSV with a header row (# comments allowed): time [s] (uniform), u [V] (amplifier "
                        "command) and x [um] and/or us [V]")
    p.add_argument("--model", metavar="FILE.toml", default=None, help="nominal model (default: models/paper.toml)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument("--columns", action="append", metavar="NAME=COLUMN,...",
                   help="map column names, e.g. --columns time=t,u=V_cmd,x=disp")
    p.add_argument("--scale", action="append", metavar="NAME=FACTOR,...",
                   help="multiply columns after reading, e.g. --scale x=1e6 (m -> um)")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures (report without images)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=_cmd)
    return p
