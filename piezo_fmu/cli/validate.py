"""``piezo-fmu validate``: check model files and FMUs."""
from __future__ import annotations

from pathlib import Path

from ..errors import UserError

__all__ = ["register"]


def cmd_validate(args):
    from ..model import load_model, validate_model

    status = 0
    for path in args.files:
        p = Path(path)
        if not p.exists():
            raise UserError(f"{p}: file not found")
        if p.suffix.lower() == ".fmu":
            from fmpy.validation import validate_fmu

            problems = validate_fmu(str(p))
        else:
            problems = validate_model(p)
            if not problems:
                load_model(p)
        if problems:
            status = 2
            print(f"{p}: {len(problems)} problem(s)")
            for prob in problems:
                print(f"  - {prob}")
        else:
            print(f"{p}: no problems")
    return status


def register(sub):
    s = sub.add_parser("validate", help="check model files (.toml) or FMUs (.fmu)",
                       description="Validate model parameter files (keys, units, types, physical "
                                   "values) and FMUs (fmpy's validation); exit status 2 if any has "
                                   "problems.")
    s.add_argument("files", nargs="+", metavar="FILE")
    s.set_defaults(func=cmd_validate)
