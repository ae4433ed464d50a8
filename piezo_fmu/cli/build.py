"""``piezo-fmu build``: the FMUs and the SSP from a model file (``build_fmu.py`` calls this too)."""
from __future__ import annotations

import argparse

from ..errors import UserError
from .common import add_quiet, progress_for

__all__ = ["register"]


def cmd_build(args):
    from ..builder import FLOOR, SYSTEM, BuildError, build_all
    from ..io import check_out_dir

    out = check_out_dir(args.out_dir, force=True)
    bar = progress_for(args, "build")
    names = SYSTEM + (FLOOR if args.floor else ())
    done = [0]

    def log(msg):
        if msg.endswith(" s)") and ": ok (" in msg:       # one FMU finished
            done[0] += 1
        bar(min(done[0] / (len(names) + 1), 0.99), msg)

    try:
        result = build_all(args.model, out, floor=args.floor, log=log)
    except BuildError as exc:
        bar.close()
        raise UserError(str(exc)) from None
    bar(1.0)
    for path in [*result.values(), result.ssp]:
        if path is not None:
            print(path)
    return 0


def register(sub):
    s = sub.add_parser(
        "build", help="build the FMUs and the SSP from a model file",
        description="Build Actuator.fmu, Sensor.fmu and Compensator.fmu (FMI 2.0 co-simulation, "
                    "authored with pythonfmu) and PiezoSystem.ssp from a model file. Every FMU is "
                    "validated (fmpy validate: no problems) and run once in a process that cannot "
                    "import piezo_fmu before it reaches the output folder; the paths are printed.",
        epilog="examples:\n  piezo-fmu build                          the paper's model into ./models\n"
               "  piezo-fmu build --model diag/model.toml --out-dir fmus\n"
               "  fmpy simulate models/Actuator.fmu --show-plot",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("--model", metavar="FILE.toml", default=None,
                   help="model file (default: the paper's, shipped with piezo-fmu)")
    s.add_argument("--out-dir", metavar="DIR", default="models",
                   help="where the FMUs and the SSP go (default: ./models, created)")
    s.add_argument("--floor", action="store_true",
                   help="also build PassThrough.fmu (y = u on the same base: the benchmark's floor)")
    add_quiet(s)
    s.set_defaults(func=cmd_build)
