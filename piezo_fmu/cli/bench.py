"""``piezo-fmu bench``: speed figures, measured side by side in one run (see :mod:`piezo_fmu.bench`)."""
from __future__ import annotations

import json

from .common import add_quiet, progress_for, say

__all__ = ["register"]


def cmd_bench(args):
    from ..bench import format_figures, run_bench
    from ..io import check_writable, write_text

    if args.json:
        check_writable(args.json, args.force)
    bar = progress_for(args, "bench")
    result = run_bench(args.size, args.model, lambda msg: bar(None, msg))
    bar.close()
    print(format_figures(result))
    if args.json:
        write_text(args.json, json.dumps(result, indent=2), force=args.force)
        say(args, f"wrote {args.json}")
    return 0


def register(sub):
    from ..bench import SIZES

    p = sub.add_parser(
        "bench", help="measure co-simulation, monolithic, PI and diagnose speed",
        description="Measure, in one run: the FMI floor (3 pass-through FMUs), the co-simulation of "
                    "the three FMUs at H = 1e-4 s, the monolithic model at 1e-5 s, PI operator "
                    "throughput, writing a 100 s run as CSV and Parquet, diagnose on three hard 20 s, 10 kHz "
                    "recordings and sweep throughput on dask. Figures, not pass/fail.")
    p.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    p.add_argument("--size", choices=tuple(SIZES), default="full",
                   help="full (default, about 3-5 minutes on 2 cores) or tiny (seconds; for tests)")
    p.add_argument("--model", metavar="FILE.toml", default=None,
                   help="model file (default: the paper's, shipped with piezo-fmu)")
    p.add_argument("--force", action="store_true", help="overwrite --json")
    add_quiet(p)
    p.set_defaults(func=cmd_bench)
