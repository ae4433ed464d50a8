"""Command line interface: ``piezo-fmu <command> [options]`` (try ``piezo-fmu --help``).

Every command is a thin layer over the Python API. Bad input exits with status 2 and one line
saying what is wrong and where (``--debug`` shows the traceback).
"""
from __future__ import annotations

import argparse
import importlib
import math
import sys
import time
import warnings
from pathlib import Path

from . import __version__
from .errors import UserError

EXAMPLES = """examples:
  piezo-fmu reproduce --out out/            run the paper's experiments, write tables and figures
  piezo-fmu simulate --freq 10 --out run.csv    monolithic closed loop, 10 Hz, 0-90 V reference
  piezo-fmu cosim --freq 10 --out cosim.csv     the same with the three FMUs (build them first)
  piezo-fmu identify --out my.toml          re-identify the compensator from simulated measurements
  piezo-fmu validate models/paper.toml      check a model file
  piezo-fmu diagnose rec.csv --out diag/    find what a model misses in a recording
"""

# Commands implemented in their own modules register themselves here (module.register(sub)).
PLUGINS = ("piezo_fmu.diagnose", "piezo_fmu.bench")


class Progress:
    """A progress line on stderr for long runs (silent when ``quiet`` or not a terminal)."""

    def __init__(self, label, quiet=False):
        self.label = label
        self.enabled = not quiet and sys.stderr.isatty()
        self.last = -1.0
        self.t0 = time.perf_counter()

    def __call__(self, fraction):
        if not self.enabled or fraction - self.last < 0.01 and fraction < 1.0:
            return
        self.last = fraction
        n = int(30 * fraction)
        sys.stderr.write(f"\r{self.label} [{'#' * n}{' ' * (30 - n)}] {100 * fraction:5.1f}% "
                         f"{time.perf_counter() - self.t0:6.1f} s")
        if fraction >= 1.0:
            sys.stderr.write("\n")
        sys.stderr.flush()


def say(args, msg):
    if not getattr(args, "quiet", False):
        print(msg, file=sys.stderr)


def _positive(name):
    def parse(text):
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {text!r}") from None
        if not (math.isfinite(v) and v > 0):
            raise argparse.ArgumentTypeError(f"{name} must be a positive number, got {text}")
        return v
    return parse


def _finite(name):
    def parse(text):
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {text!r}") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"{name} must be finite, got {text}")
        return v
    return parse


def add_run_options(p, cosim=False):
    """The options ``simulate`` and ``cosim`` share."""
    g = p.add_argument_group("reference (x_ref = k_ideal * u_ref)")
    g.add_argument("--signal", choices=("sine", "step", "triangle", "csv"), default="sine",
                   help="reference shape (default: sine); csv reads --input")
    g.add_argument("--freq", type=_positive("--freq"), default=10.0, metavar="HZ",
                   help="frequency of sine/triangle [Hz] (default: 10)")
    g.add_argument("--amplitude", type=_finite("--amplitude"), default=45.0, metavar="V",
                   help="amplitude of the reference voltage [V] (default: 45, the paper's)")
    g.add_argument("--offset", type=_finite("--offset"), default=45.0, metavar="V",
                   help="offset of the reference voltage [V] (default: 45: a 0-90 V sine)")
    g.add_argument("--phase", type=_finite("--phase"), default=-90.0, metavar="DEG",
                   help="phase of sine/triangle [deg] (default: -90, starts at the minimum, so a "
                        "device at rest is not kicked)")
    g.add_argument("--input", metavar="FILE.csv",
                   help="reference table for --signal csv: columns time [s] and one of x_ref [um], "
                        "u_ref [V, nominal stack voltage] or u [V, amplifier command]")
    g = p.add_argument_group("run")
    g.add_argument("--stop-time", type=_positive("--stop-time"), default=0.3, metavar="S",
                   help="end of the run [s] (default: 0.3, three periods at 10 Hz)")
    if cosim:
        g.add_argument("--step", type=_positive("--step"), default=1e-4, metavar="H",
                       help="communication step [s] (default: 1e-4)")
        g.add_argument("--algorithm", choices=("gauss-seidel", "jacobi"), default="gauss-seidel",
                       help="coupling: sequential actuator->sensor->compensator (default) or parallel")
        g.add_argument("--fmu-dir", metavar="DIR", default=None,
                       help="folder with Actuator.fmu, Sensor.fmu, Compensator.fmu (default: models/)")
        g.add_argument("--engine", choices=("python", "numba"), default=None,
                       help="kernels of the Actuator and Compensator FMUs (their simulation.engine): "
                            "interpreted or compiled by numba; same results, numba ~1/5 of the "
                            "physics' time per step after a few seconds' compile "
                            "(default: the FMUs' setting, python)")
    else:
        g.add_argument("--step", type=_positive("--step"), default=None, metavar="H",
                       help="internal step [s] (default: the model's simulation.step, 1e-5)")
        g.add_argument("--engine", choices=("auto", "numba", "python"), default="auto",
                       help="compiled (numba) or interpreted loop; same results (default: auto)")
        g.add_argument("--control-step", type=_positive("--control-step"), default=None, metavar="S",
                       help="sample time [s] of the sensor and compensator, a multiple of --step "
                            "(default: every internal step); with 1e-4 the loop is the one "
                            "`piezo-fmu cosim --step 1e-4` computes")
    g.add_argument("--mode", choices=("open", "ff", "fb", "ff+fb"), default=None,
                   help="compensation: open loop, inverse feedforward, PID feedback, or both "
                        "(default: the model's, ff+fb)")
    g.add_argument("--inverse", choices=("static", "dynamic"), default=None,
                   help="inverse model for feedforward (default: the model's, dynamic)")
    g.add_argument("--model", metavar="FILE.toml", default=None,
                   help="model parameter file (default: models/paper.toml)")
    g.add_argument("--record-step", type=_positive("--record-step"), default=None, metavar="S",
                   help="output interval [s] (default: every step)")
    g = p.add_argument_group("output")
    g.add_argument("--out", metavar="FILE.csv", help="write time,x_ref,x,us,uc,ua,F (units in a # line)")
    g.add_argument("--plot", metavar="FILE.png", help="plot reference, displacement, error and command")
    g.add_argument("--force", action="store_true", help="overwrite existing output files")
    g.add_argument("--quiet", action="store_true", help="no progress or summary on stderr")


def signal_from_args(args):
    from .recording import read_csv_table
    from .simulate import Signal

    if args.signal == "csv":
        if not args.input:
            raise UserError("--signal csv needs --input FILE.csv")
        tab = read_csv_table(args.input, required=("time",), one_of=("x_ref", "u_ref", "u"))
        col = next(c for c in ("x_ref", "u_ref", "u") if c in tab)
        return Signal("table", t=tab["time"], values=tab[col], column=col)
    if args.input:
        raise UserError("--input is only used with --signal csv")
    return Signal(args.signal, args.amplitude, args.offset, args.freq, args.phase)


def _csv_sink(fh):
    import numpy as np

    def sink(rows):
        np.savetxt(fh, rows, delimiter=",", fmt="%.10g")
    return sink


CSV_HEADER = "# units: time [s], x_ref [um], x [um], us [V], uc [V], ua [V], F [N]\ntime,x_ref,x,us,uc,ua,F\n"


def summarize(data):
    import numpy as np

    e = np.asarray(data["x"]) - np.asarray(data["x_ref"])
    return {"max_um": float(np.max(np.abs(e))), "avg_um": float(np.mean(np.abs(e))),
            "rms_um": float(np.sqrt(np.mean(e * e)))}


def run_to_outputs(args, run, plot_title):
    """Run ``run(sink=None)`` (``simulate`` or ``cosimulate``) and write ``args.out``/``args.plot``.

    With ``--out`` and no plot the rows stream to the CSV as they are computed (memory stays flat
    on long runs) and the tracking-error summary is accumulated on the way; otherwise the run is
    kept in memory. Returns ``(result, summary)``, the summary in um (see :func:`summarize`).
    """
    import numpy as np

    from .io import atomic_writer, check_writable
    from .simulate import COLUMNS

    for path in (args.out, args.plot):        # before any work: never overwrite without --force
        if path:
            check_writable(path, args.force)
    if args.out and not args.plot:
        acc = {"n": 0, "sum_abs": 0.0, "sum_sq": 0.0, "max": 0.0}
        with atomic_writer(args.out, "w", force=args.force) as fh:
            fh.write(CSV_HEADER)
            write = _csv_sink(fh)

            def sink(rows):
                write(rows)
                e = rows[:, 2] - rows[:, 1]
                if e.size:
                    acc["n"] += e.size
                    acc["sum_abs"] += float(np.sum(np.abs(e)))
                    acc["sum_sq"] += float(np.sum(e * e))
                    acc["max"] = max(acc["max"], float(np.max(np.abs(e))))

            res = run(sink=sink)
        n = max(acc["n"], 1)
        return res, {"max_um": acc["max"], "avg_um": acc["sum_abs"] / n, "rms_um": math.sqrt(acc["sum_sq"] / n)}
    res = run()
    if args.out:
        with atomic_writer(args.out, "w", force=args.force) as fh:
            fh.write(CSV_HEADER)
            _csv_sink(fh)(np.column_stack([res.data[c] for c in COLUMNS]))
    if args.plot:
        plot_run(res.data, args.plot, plot_title(res), args.force)
    return res, summarize(res.data)


def cmd_simulate(args):
    from .model import load_model
    from .simulate import simulate

    model = load_model(args.model)
    signal = signal_from_args(args)
    bar = Progress("simulate", args.quiet)

    def run(sink=None):
        return simulate(model, signal, args.stop_time, step=args.step, mode=args.mode,
                        inverse=args.inverse, record_step=args.record_step,
                        control_step=args.control_step, engine=args.engine, progress=bar, sink=sink)

    res, summary = run_to_outputs(args, run, lambda r: f"monolithic, {r.info['mode']}, {r.info['signal']}")
    ctrl = res.info["control_step"]
    sampled = f", compensator every {ctrl:g} s" if ctrl != res.step else ""
    say(args, f"simulated {res.n_steps} steps of {res.step:g} s ({res.engine} engine, "
              f"{res.samples_per_s:,.0f} steps/s{sampled}); tracking error max {summary['max_um']:.4f} um, "
              f"avg {summary['avg_um']:.4f} um, rms {summary['rms_um']:.4f} um")
    if args.out:
        say(args, f"wrote {args.out}")
    return 0


def plot_run(data, path, title, force=False):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from .io import atomic_writer

    t = np.asarray(data["time"])
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    axes[0].plot(t, data["x_ref"], "k--", lw=1, label="x_ref")
    axes[0].plot(t, data["x"], lw=1, label="x")
    axes[0].set_ylabel("displacement [um]")
    axes[0].legend()
    axes[1].plot(t, np.asarray(data["x"]) - np.asarray(data["x_ref"]), color="C3", lw=1)
    axes[1].set_ylabel("x - x_ref [um]")
    axes[2].plot(t, data["uc"], color="C2", lw=1)
    axes[2].set_ylabel("command uc [V]")
    axes[2].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_writer(path, "wb", force=force) as fh:
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)


def cmd_cosim(args):
    from .cosim import run_cli

    return run_cli(args)


def cmd_reproduce(args):
    from .model import load_model
    from .reproduce import format_table, run_reproduction

    model = load_model(args.model)
    out = Path(args.out)
    if (out / "reproduction.json").exists() and not args.force:
        raise UserError(f"{out / 'reproduction.json'}: exists; not overwritten (use --force)")
    t0 = time.perf_counter()
    result = run_reproduction(model, out, force=args.force, engine=args.engine,
                              figures=not args.no_figures, progress=lambda m: say(args, m))
    print(format_table(result))
    say(args, f"wrote {out / 'reproduction.json'}, {len(result['csv'])} CSV files"
              + (f" and {len(result.get('figures', {}))} figures" if not args.no_figures else "")
              + f" in {time.perf_counter() - t0:.1f} s")
    return 0


def cmd_identify(args):
    from .identify import identify_compensator
    from .io import check_writable, write_text
    from .model import dump_model, load_model

    model = load_model(args.model)
    check_writable(args.out, args.force)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        new, report = identify_compensator(model, design=not args.no_design,
                                           progress=lambda m: say(args, m))
    header = (f"Compensator re-identified by piezo-fmu identify from {model.path}.\n"
              "The device sections are copied unchanged.")
    write_text(args.out, dump_model(new, header), force=args.force)
    if "pid" in report:
        say(args, report["pid"]["source"])
    say(args, f"wrote {args.out}")
    return 0


def cmd_validate(args):
    from .model import load_model, validate_model

    status = 0
    for path in args.files:
        p = Path(path)
        if p.suffix.lower() == ".fmu":
            from fmpy.validation import validate_fmu

            problems = validate_fmu(str(p))
        else:
            if not p.exists():
                raise UserError(f"{p}: file not found")
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


def cmd_build(args):
    from .builder import BuildError, build_all

    log = (lambda msg: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    try:
        build_all(args.model, args.out_dir, floor=args.floor, log=log)
    except BuildError as exc:
        raise UserError(str(exc)) from None
    return 0


def cmd_demo(args):
    from .demo import run_demo

    return run_demo(args)


def build_parser():
    p = argparse.ArgumentParser(
        prog="piezo-fmu",
        description="Piezoelectric stack actuator with Prandtl-Ishlinskii hysteresis and a quartz "
                    "force sensor (Shan et al., Sensors 2021): monolithic model, FMI 2.0 "
                    "co-simulation FMUs, the paper's experiments, and diagnosis of recordings.",
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"piezo-fmu {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    s = sub.add_parser("simulate", help="run the monolithic (FMU-free) closed loop",
                       description="Run the monolithic closed loop (actuator -> sensor -> compensator) "
                                   "on a fixed internal step.")
    add_run_options(s)
    s.set_defaults(func=cmd_simulate)

    s = sub.add_parser("cosim", help="co-simulate the three FMUs with fmpy",
                       description="Co-simulate Actuator.fmu, Sensor.fmu and Compensator.fmu with "
                                   "fmpy at a fixed communication step.")
    add_run_options(s, cosim=True)
    s.set_defaults(func=cmd_cosim)

    s = sub.add_parser("reproduce", help="reproduce the paper's Figure 5 and Tables 2-4",
                       description="Run the paper's experiments on the monolithic model and write "
                                   "reproduction.json, one CSV per table cell and the figures.")
    s.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    s.add_argument("--model", metavar="FILE.toml", default=None, help="model file (default: models/paper.toml)")
    s.add_argument("--engine", choices=("auto", "numba", "python"), default="auto")
    s.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    s.add_argument("--force", action="store_true", help="overwrite existing results")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=cmd_reproduce)

    s = sub.add_parser("identify", help="identify the compensator's models from simulated measurements",
                       description="Measure the model's device (simulated, with probe noise) as the "
                                   "paper did, identify the compensator's PI model, linear dynamics "
                                   "and sensor calibration, design the PID, and write a model file.")
    s.add_argument("--model", metavar="FILE.toml", default=None, help="model file (default: models/paper.toml)")
    s.add_argument("--out", required=True, metavar="FILE.toml", help="model file to write")
    s.add_argument("--no-design", action="store_true", help="keep the PID gains of the input model")
    s.add_argument("--force", action="store_true")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=cmd_identify)

    s = sub.add_parser("build", help="build the FMUs and the SSP from a model file",
                       description="Build Actuator.fmu, Sensor.fmu, Compensator.fmu (FMI 2.0 co-simulation, "
                                   "authored with pythonfmu) and PiezoSystem.ssp from a model file; every FMU "
                                   "is validated and run once before it reaches the output folder.")
    s.add_argument("--model", metavar="FILE.toml", default=None, help="model file (default: the paper's)")
    s.add_argument("--out-dir", metavar="DIR", default="models",
                   help="where the FMUs and the SSP go (default: ./models, created)")
    s.add_argument("--floor", action="store_true",
                   help="also build PassThrough.fmu (y = u on the same base: the benchmark's floor)")
    s.add_argument("--quiet", action="store_true", help="no progress on stderr")
    s.set_defaults(func=cmd_build)

    s = sub.add_parser("validate", help="check model files (.toml) or FMUs (.fmu)",
                       description="Validate model parameter files and FMUs; exit status 2 if any "
                                   "has problems.")
    s.add_argument("files", nargs="+", metavar="FILE")
    s.set_defaults(func=cmd_validate)

    s = sub.add_parser("demo", help="the main job: reproduce the paper, build the FMUs, co-simulate",
                       description="Reproduce the paper, build the FMUs and the SSP, run the 10 Hz "
                                   "closed loop as a co-simulation and compare it with the monolithic "
                                   "model.")
    s.add_argument("--out", default="demo-out", metavar="DIR", help="output folder (default: demo-out)")
    s.add_argument("--fmu-dir", metavar="DIR", default=None,
                   help="where to build the FMUs and the SSP (default: models/, where every command "
                        "looks for them)")
    s.add_argument("--force", action="store_true")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=cmd_demo)

    for name in PLUGINS:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name and name.startswith(exc.name):
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
    except KeyboardInterrupt:
        print(f"piezo-fmu {args.command}: interrupted; no partial output was left behind",
              file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
