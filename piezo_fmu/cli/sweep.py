"""``piezo-fmu sweep SPEC.toml --out DIR``: many closed-loop runs on dask.distributed (see
:mod:`piezo_fmu.sweep`)."""
from __future__ import annotations

import argparse
import sys

from .common import count, progress_for, say

__all__ = ["register"]

DESCRIPTION = """\
Run a sweep or Monte Carlo study of the closed loop: a grid (lists, ranges, log ranges) times
random draws (uniform, normal, +-x % tolerance; seed, count) over any model-file parameter
(amplifier.R, hysteresis.weights[3], ...) or experiment field (experiment.freq, .amplitude,
.mode, ...). Each run's metrics (tracking error max/avg/rms, stroke, overshoot, settling time,
stable) go to DIR/results.parquet as runs finish (one row per run, failed runs with their error);
DIR/report.html shows the curves, distributions, each metric against each parameter, the worst
runs and, with a tolerance, the yield.

Runs on dask.distributed: a local cluster of one worker per core, or an existing cluster
(--scheduler). Results do not depend on the number of workers. Ctrl-C keeps every finished run;
--resume computes only the missing ones. The spec format is in the README ("Sweeps") and in
`python -c "import piezo_fmu.sweep.spec as s; help(s)"`."""

EXAMPLES = """\
examples:
  piezo-fmu sweep examples/frequency_sweep.toml --out freq/
        ff and ff+PID from 0.5 to 200 Hz at three amplitudes, on this machine
  piezo-fmu sweep examples/tolerance_sweep.toml --out batch/ --workers 2
        1000 production units, two worker processes
  dask scheduler --port 8786 &  dask worker tcp://HOST:8786 --nthreads 1 &   (on each machine)
  piezo-fmu sweep examples/tolerance_sweep.toml --out batch/ --scheduler tcp://HOST:8786
        the same on an existing cluster (its workers need piezo-fmu installed)
  piezo-fmu sweep examples/tolerance_sweep.toml --out batch/ --resume
        complete an interrupted sweep
  piezo-fmu sweep spec.toml --out dbg/ --workers 0
        serially in this process, without dask (debugging)
"""


def cmd_sweep(args):
    from ..sweep import sweep

    bar = progress_for(args, "sweep")

    def progress(fraction, message=""):       # "done" only after the report, not with the last run
        bar(None if fraction is None else min(fraction, 0.999), message)

    try:
        summary = sweep(args.spec, args.out, scheduler=args.scheduler, workers=args.workers,
                        resume=args.resume, force=args.force, progress=progress)
    except KeyboardInterrupt:
        bar.close()
        print(f"piezo-fmu sweep: interrupted; the finished runs are in {args.out}/results.parquet "
              f"(continue with --resume)", file=sys.stderr)
        return 130
    bar(1.0)
    bar.close()
    line = (f"{summary['runs']} runs ({summary['computed']} computed now): {summary['ok']} ok, "
            f"{summary['error']} failed" + (f", {summary['lost']} lost with their workers" if summary["lost"] else ""))
    if summary.get("runs_per_s"):
        line += f"; {summary['runs_per_s']:.1f} runs/s"
    if "yield" in summary:
        line += (f"; yield {100 * summary['yield']:.1f} % (95 %: {100 * summary['yield_low']:.1f}-"
                 f"{100 * summary['yield_high']:.1f} %)")
    print(line)
    say(args, f"wrote {summary['results']} and {summary['report']}")
    return 0


def register(sub):
    p = sub.add_parser("sweep", help="sweeps and Monte Carlo studies on dask.distributed",
                       description=DESCRIPTION, epilog=EXAMPLES,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("spec", metavar="SPEC.toml", help="the sweep specification")
    p.add_argument("--out", metavar="DIR", required=True,
                   help="output folder: results.parquet, sweep.json, report.html, figures/")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="a running dask scheduler, tcp://HOST:PORT (default: a local cluster)")
    p.add_argument("--workers", metavar="N", type=count("--workers", least=0), default=None,
                   help="local cluster size (default: one per core); with --scheduler: wait for N "
                        "workers; 0: serially in this process, without dask")
    p.add_argument("--resume", action="store_true", help="complete an interrupted sweep in DIR")
    p.add_argument("--force", action="store_true", help="delete an earlier sweep in DIR and start over")
    p.add_argument("--quiet", action="store_true", help="no progress or messages on stderr")
    p.set_defaults(func=cmd_sweep)
