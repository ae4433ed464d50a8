"""``piezo-fmu demo``: the main job in one command.

1. reproduce the paper (``DIR/reproduction/``: tables, CSVs, figures);
2. build the three FMUs and the SSP from the paper's model into ``./models`` (the folder every
   command looks in by default; these are build artefacts, rebuilt each time);
3. co-simulate the paper's 10 Hz closed loop (0-90 V reference, dynamic inverse + PID) with fmpy
   at H = 1e-4 s, Gauss-Seidel and Jacobi, and run the monolithic model on the same experiment;
4. compare them (``DIR/cosim_vs_monolithic.png``, ``DIR/demo.json``, the runs as CSVs).

:func:`run_demo` does it and returns the summary; ``piezo-fmu demo`` (:mod:`piezo_fmu.cli.demo`)
prints it.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np


__all__ = ["OUTPUTS", "format_summary", "run_demo"]

STEP = 1e-4
STOP = 0.3


OUTPUTS = ("demo.json", "cosim_gauss_seidel_10Hz.csv", "cosim_jacobi_10Hz.csv", "monolithic_10Hz.csv",
           "cosim_vs_monolithic.png")


def run_demo(out, fmu_dir=None, force=False, progress=None) -> dict:
    """Reproduce the paper into ``out/reproduction``, build the FMUs and the SSP into ``fmu_dir``
    (default ``./models``), co-simulate the paper's 10 Hz closed loop and compare it with the
    monolithic model. Returns the summary written to ``out/demo.json`` (``reproduction``: the
    reproduction's result; every difference in um, times in s).

    ``progress(fraction, message)`` reports the stages (see :mod:`piezo_fmu.progress`).
    """
    from .builder import build_all
    from .cosim import DEFAULT_FMU_DIR, cosimulate
    from .io import check_out_dir
    from .model import DEFAULT_MODEL, load_model
    from .io import write_text
    from .reproduce import run_reproduction
    from .results import write_run
    from .simulate import Signal, simulate

    report = progress or (lambda fraction=None, message="": None)
    out = check_out_dir(out, force, OUTPUTS)
    models_dir = check_out_dir(Path(fmu_dir) if fmu_dir else DEFAULT_FMU_DIR, force=True)
    t_start = time.perf_counter()
    model = load_model(DEFAULT_MODEL)

    report(0.0, "1/4 reproducing the paper (Figure 5, Tables 2-4, Figures 7 and 9)")
    repro = run_reproduction(model, out / "reproduction", force=force,
                             progress=lambda f, m="": report(0.6 * f, m and f"1/4 {m}"))

    report(0.6, "2/4 building Actuator.fmu, Sensor.fmu, Compensator.fmu and PiezoSystem.ssp")
    fmus = build_all(DEFAULT_MODEL, models_dir, log=lambda *a, **k: None)

    report(0.85, f"3/4 co-simulating the paper's 10 Hz closed loop at H = {STEP:g} s (fmpy), and the monolithic model")
    sig = Signal("sine", 45.0, 45.0, 10.0)
    system = {n: fmus[n] for n in ("Actuator", "Sensor", "Compensator")}
    gs = cosimulate(system, sig, STOP, STEP)
    jac = cosimulate(system, sig, STOP, STEP, algorithm="jacobi")
    mono = simulate(model, sig, STOP, record_step=STEP)
    # the same loop with the compensator sampled at H, as in the co-simulation (actuator at 1e-5 s)
    sampled = simulate(model, sig, STOP, record_step=STEP, control_step=STEP)

    report(0.97, "4/4 comparing")
    t = gs["time"]
    stroke = float(np.ptp(mono["x_ref"]))

    def diff(a, ref=mono):
        d = np.interp(ref["time"], a["time"], a["x"]) - ref["x"]
        return {"max_um": float(np.max(np.abs(d))), "max_percent_of_stroke": 100 * float(np.max(np.abs(d))) / stroke,
                "rms_um": float(np.sqrt(np.mean(d * d)))}

    def tracking(a):
        e = a["x"] - a["x_ref"]
        return {"max_um": float(np.max(np.abs(e))), "avg_um": float(np.mean(np.abs(e))),
                "rms_um": float(np.sqrt(np.mean(e * e)))}

    summary = {
        "experiment": "paper 10 Hz closed loop: 0-90 V reference, dynamic inverse + PID",
        "step_s": STEP, "stop_time_s": STOP, "stroke_um": stroke,
        "cosim_vs_monolithic": {"gauss-seidel": diff(gs), "jacobi": diff(jac)},
        "cosim_vs_monolithic_sampled_at_step": {"gauss-seidel": diff(gs, sampled)},
        "tracking_error": {"monolithic": tracking(mono), "gauss-seidel": tracking(gs), "jacobi": tracking(jac)},
        "cosim_us_per_step": {"gauss-seidel": gs.info["us_per_step"], "jacobi": jac.info["us_per_step"]},
        "files": {"fmus": {k: str(v) for k, v in fmus.items()}, "ssp": str(fmus.ssp),
                  "reproduction": str(out / "reproduction"), "out": str(out)},
    }
    for name, res in (("cosim_gauss_seidel_10Hz.csv", gs), ("cosim_jacobi_10Hz.csv", jac),
                      ("monolithic_10Hz.csv", mono)):
        write_run(out / name, res.data, force=force)
    _figure(out / "cosim_vs_monolithic.png", t, gs, jac, mono, force)

    summary["total_s"] = time.perf_counter() - t_start
    write_text(out / "demo.json", json.dumps(summary, indent=2), force=force)
    report(1.0)
    summary["reproduction"] = repro
    return summary


def format_summary(summary) -> str:
    """The comparison as a few lines of text (``summary`` from :func:`run_demo`)."""
    c = summary["cosim_vs_monolithic"]
    stroke = summary["stroke_um"]
    return (f"co-simulation (3 FMUs, fmpy, H = {STEP:g} s) vs monolithic model, 10 Hz closed loop:\n"
          f"  Gauss-Seidel: max |dx| {c['gauss-seidel']['max_um'] * 1e3:.2f} nm "
          f"({c['gauss-seidel']['max_percent_of_stroke']:.2f} % of the {stroke:.2f} um stroke)\n"
          f"  Jacobi:       max |dx| {c['jacobi']['max_um'] * 1e3:.2f} nm "
          f"({c['jacobi']['max_percent_of_stroke']:.2f} %)\n"
          f"  Gauss-Seidel vs the monolithic model with the compensator sampled at H (the same loop, "
          f"actuator at 1e-5 s): max |dx| "
          f"{summary['cosim_vs_monolithic_sampled_at_step']['gauss-seidel']['max_um'] * 1e3:.2f} nm\n"
          f"  tracking error rms: monolithic {summary['tracking_error']['monolithic']['rms_um'] * 1e3:.2f} nm, "
          f"co-simulation {summary['tracking_error']['gauss-seidel']['rms_um'] * 1e3:.2f} nm\n"
          f"  {summary['cosim_us_per_step']['gauss-seidel']:.1f} us per communication step")


def _figure(path, t, gs, jac, mono, force):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .io import atomic_writer

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    a1.plot(mono["time"], mono["x_ref"], "k--", lw=1, label="reference x_ref")
    a1.plot(mono["time"], mono["x"], lw=2.5, alpha=0.5, label="monolithic model")
    a1.plot(gs["time"], gs["x"], lw=1, label="co-simulation, Gauss-Seidel")
    a1.plot(jac["time"], jac["x"], lw=1, ls=":", label="co-simulation, Jacobi")
    a1.set_ylabel("displacement x [um]")
    a1.legend(loc="upper right")
    a1.set_title("Paper 10 Hz closed loop: three FMUs co-simulated with fmpy (H = 1e-4 s) vs the monolithic model")
    for res, label in ((gs, "Gauss-Seidel"), (jac, "Jacobi")):
        d = np.interp(mono["time"], res["time"], res["x"]) - mono["x"]
        a2.plot(mono["time"], d * 1e3, lw=1, label=label)
    a2.set_ylabel("co-simulation - monolithic [nm]")
    a2.set_xlabel("time [s]")
    a2.legend()
    for ax in (a1, a2):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_writer(path, "wb", force=force) as fh:
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)
