"""Command line interface: ``piezo-fmu <command> [options]`` (try ``piezo-fmu --help``).

The command line is one layer over the library (as fmpy's ``cli.py`` is over ``fmpy``): each
module here parses one command's options, calls the library, prints, and maps errors to exit
codes. No library module imports this package. Bad input exits with status 2 and one line saying
what is wrong and where (``--debug`` shows the traceback); Ctrl-C exits with 130.

Each module of :data:`COMMANDS` has ``register(subparsers)``.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from .. import __version__
from ..errors import UserError

__all__ = ["COMMANDS", "build_parser", "main"]

EXAMPLES = """examples:
  piezo-fmu demo                            the main job: reproduce, build the FMUs, co-simulate
  piezo-fmu simulate --freq 10 --out run.csv    monolithic closed loop, 10 Hz, 0-90 V reference
  piezo-fmu build                           build the FMUs and the SSP into ./models
  piezo-fmu cosim --freq 10 --out cosim.csv     the same loop with the three FMUs
  piezo-fmu reproduce --out out/            the paper's experiments: tables and figures
  piezo-fmu identify --out my.toml          re-identify the compensator from simulated measurements
  piezo-fmu validate my.toml models/Actuator.fmu   check model files and FMUs
  piezo-fmu diagnose rec.csv --out diag/    find what a model misses in a recording
  piezo-fmu sweep examples/frequency_sweep.toml --out sweep/   many runs on dask
  piezo-fmu bench                           speed figures
"""

# the command modules, in the order of `piezo-fmu --help`
COMMANDS = ("demo", "run", "build", "reproduce", "identify", "validate", "diagnose",
            "sweep", "bench")


def build_parser():
    p = argparse.ArgumentParser(
        prog="piezo-fmu",
        description="Piezoelectric stack actuator with Prandtl-Ishlinskii hysteresis and a quartz "
                    "force sensor (Shan et al., Sensors 2021): monolithic model, FMI 2.0 "
                    "co-simulation FMUs, the paper's experiments, diagnosis of recordings, sweeps.",
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"piezo-fmu {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"{__name__}.{name}":      # a command not written yet
                continue
            raise
        module.register(sub)
    return p


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return args.func(args) or 0
    except UserError as exc:
        if args.debug:
            raise
        print(f"piezo-fmu {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader of the output went away (`piezo-fmu diagnose ... | head`): stop quietly, with
        # the shell's status for SIGPIPE; stdout goes to /dev/null so the exit flush cannot fail
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except KeyboardInterrupt:
        print(f"piezo-fmu {args.command}: interrupted; no partial output was left behind",
              file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
