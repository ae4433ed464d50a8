"""``piezo-fmu diagnose``: what a model misses in recordings of a real rig."""
from __future__ import annotations

import argparse
import time

from .common import add_quiet, count, positive, progress_for, say

__all__ = ["register", "summary"]


def summary(res):
    """A few lines for the terminal from ``diagnosis.json``'s content."""
    chans = list(res["baseline"]["rmse"])
    lines = [res["final"]["verdict"]]
    lines.append("held-out rmse: " + ", ".join(
        f"{c} {res['baseline']['rmse'][c]:.4g} -> {res['final']['rmse'][c]:.4g} (noise {res['baseline']['noise'][c]:.3g})"
        for c in chans))
    away_b, away_f = res["baseline"].get("rmse_away_from_jumps", {}), res["final"].get("rmse_away_from_jumps", {})
    if away_b and any(away_b[c] != res["baseline"]["rmse"][c] for c in away_b):
        lines.append("  away from the command's jumps (where creep, leakage and drift are judged): "
                     + ", ".join(f"{c} {away_b[c]:.4g} -> {away_f[c]:.4g}" for c in away_b))
    for f in res["findings"]:
        where = f["where"][0] if f["where"] else None
        lines.append(f"  {f['effect']:<24} confidence {f['confidence']:.2f}  {f['parameters']}"
                     + (f"  e.g. {where['t0_s']:.3g}-{where['t1_s']:.3g} s" if where else ""))
        rival = f["evidence"].get("strongest_alternative")
        if rival and rival["passed"]:
            how = (f"also support {rival['effect']}, BIC {rival['bic_behind']:g} behind" if "bic_behind" in rival
                   else f"nearly as well support {rival['effect']}")
            lines.append(f"  {'':<24} (the data {how}: explains "
                         + ", ".join(f"{c} {100 * v:.0f} %" for c, v in rival["explained_share"].items()) + ")")
    for c in res.get("candidates", []):
        lines.append(f"  candidate {c['effect']:<14} confidence {c['confidence']:.2f} (below 0.5: not in the model)")
    for u in res["unexplained"]:
        lines.append(f"  unexplained ({u['channel']}): {u['description']}")
    return "\n".join(lines)


def cmd_diagnose(args):
    from ..diagnose import diagnose
    from ..io import check_out_dir
    from ..recording import parse_mapping

    t0 = time.perf_counter()
    check_out_dir(args.out, force=True)        # creatable and writable, before any work
    bar = progress_for(args, "diagnose")
    columns = parse_mapping(args.columns, "--columns")
    scale = parse_mapping(args.scale, "--scale", numeric=True)
    diag = diagnose(args.recordings, args.model, args.out, force=args.force, columns=columns or None,
                    scale=scale or None, say=lambda msg: bar(None, msg), figures=not args.no_figures,
                    replay_rate=args.replay_rate, threads=args.threads)
    bar.close()
    print(summary(diag.result))
    say(args, f"wrote {args.out}/ (diagnosis.json, fit.csv, model.toml, report.html) in "
              f"{time.perf_counter() - t0:.1f} s")
    return 0


def register(sub):
    p = sub.add_parser(
        "diagnose", help="find what a model misses in recordings of a real rig",
        description="Recalibrate the model to the recordings, locate where they still differ (time, "
                    "frequency, operating range, channel), name the missing physics from a catalogue "
                    "(creep, sensor_leakage, amplifier_current_limit, time_delay, extra_resonance, "
                    "thermal_drift, hysteresis_shape), fit it, and validate on held-out data. Writes "
                    "diagnosis.json, fit.csv, model.toml (loadable by every command; rebuild the FMUs "
                    "from it), report.html and its PNG figures into --out.",
        epilog="examples:\n  piezo-fmu diagnose rec.csv --out diag/\n"
               "  piezo-fmu diagnose a.csv b.csv --columns time=t,u=V_cmd,x=disp --scale x=1e6 --out diag/\n"
               "  piezo-fmu build --model diag/model.toml --out-dir fmus",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recordings", nargs="+", metavar="REC.csv",
                   help="CSV with a header row (# comments allowed): time [s] (uniform), u [V] (amplifier "
                        "command) and x [um] and/or us [V]; a header may name another unit, converted on "
                        "reading: 'time [ms]', 'x (nm)', 'u [mV]'")
    p.add_argument("--model", metavar="FILE.toml", default=None,
                   help="nominal model (default: the paper's, shipped with piezo-fmu)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument("--columns", action="append", metavar="NAME=COLUMN,...",
                   help="map column names, e.g. --columns time=t,u=V_cmd,x=disp")
    p.add_argument("--scale", action="append", metavar="NAME=FACTOR,...",
                   help="multiply columns after reading, e.g. --scale x=1e6 (m -> um)")
    p.add_argument("--replay-rate", type=positive("--replay-rate"), default=None, metavar="HZ",
                   help="replay a recording sampled slower than HZ with several internal steps per sample "
                        "(the amplifier's and the push rod's motion between the samples; e.g. 8000 for a "
                        "recording at 1 kHz of a device with a sub-ms amplifier lag or a mode of a few "
                        "hundred Hz). Default: one step per sample (faster)")
    p.add_argument("--threads", type=count("--threads"), default=None, metavar="N",
                   help="worker threads for the independent evaluations (default 2, or the environment "
                        "variable PIEZO_FMU_DIAGNOSE_THREADS); 1 costs less CPU where the cores are busy "
                        "anyway (diagnoses side by side). The result does not depend on it")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures (report without images)")
    add_quiet(p)
    p.set_defaults(func=cmd_diagnose)
    return p
