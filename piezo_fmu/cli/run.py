"""``piezo-fmu simulate`` (the monolithic closed loop) and ``piezo-fmu cosim`` (the three FMUs)."""
from __future__ import annotations

import argparse

from ..errors import UserError
from .common import finite, positive, progress_for, say

__all__ = ["DEFAULT_RECORD_STEP", "add_run_options", "register", "signal_from_args"]

# a row every 1e-4 s: 100 rows per period of the fastest reference the paper runs (100 Hz),
# 1e6 rows (~130 MB as CSV, ~70 MB as Parquet, about 1 s to write) for a 100 s run
DEFAULT_RECORD_STEP = 1e-4


def add_run_options(p, cosim=False):
    """The options ``simulate`` and ``cosim`` share."""
    g = p.add_argument_group("reference (x_ref = k_ideal * u_ref)")
    g.add_argument("--signal", choices=("sine", "step", "triangle", "csv"), default="sine",
                   help="reference shape (default: sine); csv reads --input")
    g.add_argument("--freq", type=positive("--freq"), default=10.0, metavar="HZ",
                   help="frequency of sine/triangle [Hz] (default: 10)")
    g.add_argument("--amplitude", type=finite("--amplitude"), default=45.0, metavar="V",
                   help="amplitude of the reference voltage [V] (default: 45, the paper's)")
    g.add_argument("--offset", type=finite("--offset"), default=45.0, metavar="V",
                   help="offset of the reference voltage [V] (default: 45: a 0-90 V sine)")
    g.add_argument("--phase", type=finite("--phase"), default=-90.0, metavar="DEG",
                   help="phase of sine/triangle [deg] (default: -90, starts at the minimum, so a "
                        "device at rest is not kicked)")
    g.add_argument("--input", metavar="FILE.csv",
                   help="reference table for --signal csv: columns time [s] and one of x_ref [um], "
                        "u_ref [V, nominal stack voltage] or u [V, amplifier command] (another unit in the "
                        "header, 'x_ref [nm]', is converted)")
    g = p.add_argument_group("run")
    g.add_argument("--stop-time", type=positive("--stop-time"), default=0.3, metavar="S",
                   help="end of the run [s] (default: 0.3, three periods at 10 Hz)")
    if cosim:
        g.add_argument("--step", type=positive("--step"), default=1e-4, metavar="H",
                       help="communication step [s] (default: 1e-4)")
        g.add_argument("--algorithm", choices=("gauss-seidel", "jacobi"), default="gauss-seidel",
                       help="coupling: sequential actuator->sensor->compensator (default) or parallel")
        g.add_argument("--fmu-dir", metavar="DIR", default=None,
                       help="folder with Actuator.fmu, Sensor.fmu, Compensator.fmu (default: ./models, "
                            "where `piezo-fmu build` puts them)")
        g.add_argument("--engine", choices=("python", "numba"), default=None,
                       help="kernels of the Actuator and Compensator FMUs (their simulation.engine): "
                            "interpreted or compiled by numba; same results, numba ~1/5 of the "
                            "physics' time per step after a few seconds' compile "
                            "(default: the FMUs' setting, python)")
        record_help = "output interval [s], a multiple of --step (default: every communication step)"
    else:
        g.add_argument("--step", type=positive("--step"), default=None, metavar="H",
                       help="internal step [s] (default: the model's simulation.step, 1e-5)")
        g.add_argument("--engine", choices=("auto", "numba", "python"), default="auto",
                       help="compiled (numba) or interpreted loop; same results (default: auto)")
        g.add_argument("--control-step", type=positive("--control-step"), default=None, metavar="S",
                       help="sample time [s] of the sensor and compensator, a multiple of --step "
                            "(default: every internal step); with 1e-4 the loop is the one "
                            "`piezo-fmu cosim --step 1e-4` computes")
        record_help = (f"output interval [s], a multiple of --step (default: {DEFAULT_RECORD_STEP:g} s, "
                       "100 rows per period at 100 Hz, or --step if that is longer)")
    g.add_argument("--mode", choices=("open", "ff", "fb", "ff+fb"), default=None,
                   help="compensation: open loop, inverse feedforward, PID feedback, or both "
                        "(default: the model's, ff+fb)")
    g.add_argument("--inverse", choices=("static", "dynamic"), default=None,
                   help="inverse model for feedforward (default: the model's, dynamic)")
    g.add_argument("--model", metavar="FILE.toml", default=None,
                   help="model parameter file (default: the paper's, shipped with piezo-fmu)")
    g.add_argument("--record-step", type=positive("--record-step"), default=None, metavar="S", help=record_help)
    g = p.add_argument_group("output")
    g.add_argument("--out", metavar="FILE",
                   help="write time,x_ref,x,us,uc,ua,F: FILE.csv (units in a # line) or FILE.parquet "
                        "(units in the schema); streamed, so long runs keep memory flat")
    g.add_argument("--plot", metavar="FILE.png", help="plot reference, displacement, error and command")
    g.add_argument("--force", action="store_true", help="overwrite existing output files")
    g.add_argument("--quiet", action="store_true", help="no progress or summary on stderr")


def signal_from_args(args):
    from ..recording import read_csv_table
    from ..simulate import Signal

    if args.signal == "csv":
        if not args.input:
            raise UserError("--signal csv needs --input FILE.csv")
        tab = read_csv_table(args.input, required=("time",), one_of=("x_ref", "u_ref", "u"))
        col = next(c for c in ("x_ref", "u_ref", "u") if c in tab)
        return Signal("table", t=tab["time"], values=tab[col], column=col)
    if args.input:
        raise UserError("--input is only used with --signal csv")
    return Signal(args.signal, args.amplitude, args.offset, args.freq, args.phase)


def run_to_outputs(args, run, plot_title):
    """Run ``run(sink=None)`` (``simulate`` or ``cosimulate``) and write ``--out``/``--plot``.

    Every output path is checked before the run. With ``--out`` and no plot the rows stream to the
    file as they are computed (memory stays flat on long runs); with a plot the run is kept in
    memory. Returns ``(result, tracking error summary [um])``.
    """
    from ..io import check_writable
    from ..results import RunWriter, output_format, plot_run, summarize, write_run

    if args.out:
        output_format(args.out)
    for path in (args.out, args.plot):
        if path:
            check_writable(path, args.force)
    if args.out and not args.plot:
        with RunWriter(args.out, force=args.force) as out:
            res = run(sink=out)
        return res, out.summary
    res = run()
    if args.out:
        write_run(args.out, res.data, force=args.force)
    if args.plot:
        plot_run(res.data, args.plot, plot_title(res), args.force)
    return res, summarize(res.data)


def _report(args, res, summary, what):
    say(args, f"{what}; tracking error max {summary['max_um']:.4f} um, avg {summary['avg_um']:.4f} um, "
              f"rms {summary['rms_um']:.4f} um")
    for path in (args.out, args.plot):
        if path:
            say(args, f"wrote {path}")


def cmd_simulate(args):
    from ..model import load_model
    from ..simulate import simulate

    model = load_model(args.model)
    signal = signal_from_args(args)
    bar = progress_for(args, "simulate")
    h = args.step if args.step is not None else model["simulation"]["step"]
    record_step = args.record_step if args.record_step is not None else max(DEFAULT_RECORD_STEP, h)

    def run(sink=None):
        return simulate(model, signal, args.stop_time, step=args.step, mode=args.mode,
                        inverse=args.inverse, record_step=record_step,
                        control_step=args.control_step, engine=args.engine, progress=bar, sink=sink)

    res, summary = run_to_outputs(args, run, lambda r: f"monolithic, {r.info['mode']}, {r.info['signal']}")
    bar.close()
    ctrl = res.info["control_step"]
    sampled = f", compensator every {ctrl:g} s" if ctrl != res.step else ""
    _report(args, res, summary, f"simulated {res.n_steps} steps of {res.step:g} s ({res.engine} engine, "
                                f"{res.samples_per_s:,.0f} steps/s{sampled}), recorded every {record_step:g} s")
    return 0


def cmd_cosim(args):
    from ..cosim import cosimulate
    from ..fmi import fmu_paths
    from ..model import load_model

    model = load_model(args.model)
    signal = signal_from_args(args)
    fmus = fmu_paths(args.fmu_dir)
    bar = progress_for(args, "cosim")
    kw = {"step": args.step, "algorithm": args.algorithm, "mode": args.mode, "inverse": args.inverse,
          "model": model, "record_step": args.record_step, "progress": bar, "engine": args.engine}

    def run(sink=None):
        return cosimulate(fmus, signal, args.stop_time, sink=sink, **kw)

    res, summary = run_to_outputs(args, run, lambda r: f"co-simulation ({r.info['algorithm']}), "
                                                       f"{r.info['mode']}, {r.info['signal']}")
    bar.close()
    _report(args, res, summary, f"co-simulated {res.n_steps} steps of {res.step:g} s ({res.info['algorithm']}, "
                                f"3 FMUs, {res.info['us_per_step']:.0f} us per step)")
    return 0


def register(sub):
    s = sub.add_parser("simulate", help="run the monolithic (FMU-free) closed loop",
                       description="Run the monolithic closed loop (actuator -> sensor -> compensator) "
                                   "on a fixed internal step.",
                       epilog="examples:\n  piezo-fmu simulate --freq 10 --out run.csv\n"
                              "  piezo-fmu simulate --stop-time 100 --out long.parquet\n"
                              "  piezo-fmu simulate --signal step --amplitude 30 --offset 30 --plot step.png",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    add_run_options(s)
    s.set_defaults(func=cmd_simulate)

    s = sub.add_parser("cosim", help="co-simulate the three FMUs with fmpy",
                       description="Co-simulate Actuator.fmu, Sensor.fmu and Compensator.fmu with "
                                   "fmpy at a fixed communication step (build them first: "
                                   "piezo-fmu build).",
                       epilog="examples:\n  piezo-fmu build && piezo-fmu cosim --freq 10 --out cosim.csv\n"
                              "  piezo-fmu cosim --algorithm jacobi --engine numba --fmu-dir fmus",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    add_run_options(s, cosim=True)
    s.set_defaults(func=cmd_cosim)
