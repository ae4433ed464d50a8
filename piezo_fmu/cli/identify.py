"""``piezo-fmu identify``: identify the compensator's models the way the paper did."""
from __future__ import annotations

import warnings

from .common import add_quiet, progress_for, say

__all__ = ["register"]


def cmd_identify(args):
    from ..identify import identify_compensator
    from ..io import check_writable, write_text
    from ..model import dump_model, load_model

    model = load_model(args.model)
    check_writable(args.out, args.force)
    bar = progress_for(args, "identify")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        new, report = identify_compensator(model, design=not args.no_design, progress=bar)
    bar.close()
    header = (f"Compensator re-identified by piezo-fmu identify from {model.path}.\n"
              "The device sections are copied unchanged.")
    write_text(args.out, dump_model(new, header), force=args.force)
    for line in report["summary"]:
        say(args, line)
    if "pid" in report:
        say(args, report["pid"]["source"])
    say(args, f"wrote {args.out}")
    return 0


def register(sub):
    s = sub.add_parser("identify", help="identify the compensator's models from simulated measurements",
                       description="Measure the model's device (simulated, with probe noise) as the "
                                   "paper did, identify the compensator's PI model, linear dynamics "
                                   "and sensor calibration, design the PID, and write a model file.")
    s.add_argument("--model", metavar="FILE.toml", default=None,
                   help="model file (default: the paper's, shipped with piezo-fmu)")
    s.add_argument("--out", required=True, metavar="FILE.toml", help="model file to write")
    s.add_argument("--no-design", action="store_true", help="keep the PID gains of the input model")
    s.add_argument("--force", action="store_true", help="overwrite --out")
    add_quiet(s)
    s.set_defaults(func=cmd_identify)
