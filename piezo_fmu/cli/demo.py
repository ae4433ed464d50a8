"""``piezo-fmu demo``: the main job (reproduce, build, co-simulate, compare)."""
from __future__ import annotations

from .common import add_quiet, progress_for, say

__all__ = ["register"]


def cmd_demo(args):
    from ..demo import format_summary, run_demo
    from ..reproduce import format_table

    bar = progress_for(args, "demo")
    summary = run_demo(args.out, args.fmu_dir, force=args.force, progress=bar)
    bar.close()
    print(format_table(summary["reproduction"]))
    print()
    print(format_summary(summary))
    files = summary["files"]
    say(args, f"wrote {files['out']}/ (demo.json, reproduction/, runs as CSV, cosim_vs_monolithic.png) and "
              f"{len(files['fmus'])} FMUs and {files['ssp']} in {summary['total_s']:.0f} s")
    return 0


def register(sub):
    s = sub.add_parser("demo", help="the main job: reproduce the paper, build the FMUs, co-simulate",
                       description="Reproduce the paper, build the FMUs and the SSP, run the 10 Hz "
                                   "closed loop as a co-simulation and compare it with the monolithic "
                                   "model.")
    s.add_argument("--out", default="demo-out", metavar="DIR", help="output folder (default: demo-out)")
    s.add_argument("--fmu-dir", metavar="DIR", default=None,
                   help="where to build the FMUs and the SSP (default: ./models, where every command "
                        "looks for them)")
    s.add_argument("--force", action="store_true", help="overwrite the results of an earlier run")
    add_quiet(s)
    s.set_defaults(func=cmd_demo)
