"""``piezo-fmu reproduce``: the paper's experiments (Figure 5, Tables 2-4) into a folder."""
from __future__ import annotations

import time

from .common import add_quiet, progress_for, say

__all__ = ["register"]


def cmd_reproduce(args):
    from ..io import check_out_dir
    from ..model import load_model
    from ..reproduce import format_table, run_reproduction

    model = load_model(args.model)
    out = check_out_dir(args.out, args.force, ("reproduction.json",))
    bar = progress_for(args, "reproduce")
    t0 = time.perf_counter()
    result = run_reproduction(model, out, force=args.force, engine=args.engine,
                              figures=not args.no_figures, progress=bar)
    bar.close()
    print(format_table(result))
    say(args, f"wrote {out / 'reproduction.json'}, {len(result['csv'])} CSV files"
              + (f" and {len(result.get('figures', {}))} figures" if not args.no_figures else "")
              + f" in {time.perf_counter() - t0:.1f} s")
    return 0


def register(sub):
    s = sub.add_parser("reproduce", help="reproduce the paper's Figure 5 and Tables 2-4",
                       description="Run the paper's experiments on the monolithic model and write "
                                   "reproduction.json, one CSV per table cell and the figures.")
    s.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    s.add_argument("--model", metavar="FILE.toml", default=None,
                   help="model file (default: the paper's, shipped with piezo-fmu)")
    s.add_argument("--engine", choices=("auto", "numba", "python"), default="auto",
                   help="compiled (numba) or interpreted monolithic model (default: auto)")
    s.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    s.add_argument("--force", action="store_true", help="overwrite existing results")
    add_quiet(s)
    s.set_defaults(func=cmd_reproduce)
