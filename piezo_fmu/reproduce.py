"""Reproduce the paper's experiments (Figure 5, Tables 2-4, Figures 7 and 9) on the monolithic model.

Every table cell is one run whose samples are written to a CSV (``time, ideal, output``) and whose
errors are computed from exactly those samples, with ``error = output - ideal``:

* ``max`` = max |error|, ``avg`` = mean |error|, ``rms`` = sqrt(mean(error^2)), in um, over all
  recorded samples of the run (the first period included, as in the paper; 2000 samples per period).
* Table 2 (forward models): a 0-30 V sine drives the device open-loop for 3 periods from rest;
  ``ideal`` = the measured displacement (device + probe noise), ``output`` = the compensator's
  static model ``PI[u]`` or dynamic model ``PI[G u]`` fed with the same command.
* Table 3 (inverse feedforward): the reference ``x_ref = k_ideal u_ref`` follows a 0-90 V sine
  (amplitude 45 V about 45 V, starting at its minimum) for 3 periods; ``ideal`` = x_ref,
  ``output`` = the device's displacement with static- or dynamic-inverse feedforward only.
* Table 4: the same with dynamic-inverse feedforward + PID feedback on the quartz sensor.
* Figure 5: the 0-30 V, 0.5 Hz loop of the device; the widest distance between its branches
  (noise-free displacement, last period) and the voltage at the centre of the region within 1 % of
  that width; the repeatability is the largest difference between two consecutive measured
  periods at the same voltage and branch.
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from .errors import UserError
from .identify import apply_linear, measure
from .io import atomic_writer, write_text
from .model import Model
from .simulate import Signal, simulate

__all__ = ["PAPER", "FREQS", "error_stats", "loop_width", "run_reproduction", "format_table"]

FREQS = (0.5, 10.0, 20.0, 50.0)
PERIODS = 3
SAMPLES_PER_PERIOD = 2000
SINE_30 = (15.0, 15.0)   # offset, amplitude [V]: 0-30 V
SINE_90 = (45.0, 45.0)   # 0-90 V, "amplitude 45 V"

# The paper's values (um), Tables 2-4 and Figure 5.
PAPER = {
    "figure5": {"max_width_um": 0.26, "at_voltage_V": 15.0, "repeatability_um": 0.06},
    "table2": {
        "static": {"0.5": (0.06529, 0.02707, 0.03394), "10": (0.24479, 0.07615, 0.08634),
                   "20": (0.27672, 0.09984, 0.11256), "50": (0.29893, 0.18748, 0.20978)},
        "dynamic": {"0.5": (0.12678, 0.04434, 0.05940), "10": (0.17687, 0.04614, 0.05288),
                    "20": (0.15577, 0.04096, 0.04746), "50": (0.78268, 0.05255, 0.08927)},
    },
    "table3": {
        "static_inverse": {"0.5": (0.90116, 0.31638, 0.40279), "10": (2.08209, 0.28382, 0.63755),
                           "20": (2.24139, 0.30930, 0.70053), "50": (4.76271, 1.24777, 1.99596)},
        "dynamic_inverse": {"0.5": (1.23827, 0.27003, 0.33745), "10": (1.68336, 0.08209, 0.25077),
                            "20": (2.73286, 0.08725, 0.33672), "50": (4.13814, 0.46418, 1.05211)},
    },
    "table4": {
        "ff_pid": {"0.5": (0.20094, 0.07136, 0.07998), "10": (1.68336, 0.07545, 0.17840),
                   "20": (3.92499, 0.05028, 0.22415), "50": (2.28057, 0.13326, 0.24960)},
    },
}


def fkey(f):
    return f"{f:g}"


def error_stats(ideal, output):
    """max / avg / rms of ``output - ideal`` [same unit]."""
    e = np.asarray(output, dtype=float) - np.asarray(ideal, dtype=float)
    return {"max": float(np.max(np.abs(e))), "avg": float(np.mean(np.abs(e))),
            "rms": float(np.sqrt(np.mean(e * e)))}


def _branches(u, x):
    """Split one period into rising and falling branches, each sorted by voltage."""
    rising = np.gradient(u) > 0
    out = []
    for sel in (rising, ~rising):
        order = np.argsort(u[sel])
        out.append((u[sel][order], x[sel][order]))
    return out


def loop_width(u, x, grid):
    """Distance between the falling and rising branch [x units] at the voltages ``grid``."""
    (ua, xa), (ud, xd) = _branches(u, x)
    return np.interp(grid, ud, xd) - np.interp(grid, ua, xa)


def _figure5(model, engine, say):
    say("Figure 5: 0-30 V, 0.5 Hz loop")
    f = 0.5
    rec = measure(model, Signal("sine", SINE_30[1], SINE_30[0], f), PERIODS / f,
                  1.0 / (f * SAMPLES_PER_PERIOD), seed_offset=0, engine=engine)
    period = 1.0 / f
    last = rec.t >= (PERIODS - 1) * period - 1e-12
    grid = np.linspace(0.5, 29.5, 291)
    w = loop_width(rec.u[last], rec.x_true[last], grid)
    wmax = float(np.max(w))
    at = float(np.mean(grid[w >= 0.99 * wmax]))
    # repeatability: same voltage, same branch, periods 2 and 3 (measured, with probe noise)
    p2 = (rec.t >= period - 1e-12) & (rec.t < 2 * period - 1e-12)
    p3 = last
    rep = 0.0
    for (u2, x2), (u3, x3) in zip(_branches(rec.u[p2], rec.x[p2]), _branches(rec.u[p3], rec.x[p3])):
        g = np.linspace(max(u2[0], u3[0]), min(u2[-1], u3[-1]), 400)
        rep = max(rep, float(np.max(np.abs(np.interp(g, u2, x2) - np.interp(g, u3, x3)))))
    return {"max_width_um": wmax, "at_voltage_V": at, "repeatability_um": rep}, rec, (grid, w)


def _write_cell(out_dir, name, t, ideal, output, force):
    path = out_dir / name
    with atomic_writer(path, "w", force=force) as fh:
        fh.write("time,ideal,output\n")
        np.savetxt(fh, np.column_stack([t, ideal, output]), delimiter=",", fmt="%.10g")
    return name


def run_reproduction(model: Model, out_dir, *, force=False, engine="auto", figures=True,
                     progress=None) -> dict:
    """Run all experiments, write ``reproduction.json``, the cell CSVs and the figures into ``out_dir``.

    ``progress(fraction, message)`` is called before each experiment (see :mod:`piezo_fmu.progress`).
    """
    n_steps = 1 + 4 * len(FREQS) + (1 if figures else 0)
    done = [0]

    def say(message):
        if progress is not None:
            progress(done[0] / n_steps, message)
        done[0] += 1
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"{out_dir}: exists and is not a folder")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "csv").mkdir(exist_ok=True)
    result = {"figure5": None, "table2": {"static": {}, "dynamic": {}},
              "table3": {"static_inverse": {}, "dynamic_inverse": {}}, "table4": {"ff_pid": {}},
              "csv": {}, "model": model.path, "paper": PAPER}
    fig5, rec5, width5 = _figure5(model, engine, say)
    result["figure5"] = fig5
    pi = model.hysteresis("compensator.hysteresis")
    dyn = model["compensator.dynamics"]
    runs = {}
    for i, f in enumerate(FREQS):
        k = fkey(f)
        dt = 1.0 / (f * SAMPLES_PER_PERIOD)
        stop = PERIODS / f
        say(f"Table 2: forward models at {k} Hz")
        rec = measure(model, Signal("sine", SINE_30[1], SINE_30[0], f), stop, dt, seed_offset=100 + i,
                      engine=engine)
        outputs = {"static": pi.apply(rec.u),
                   "dynamic": pi.apply(apply_linear(dyn["num"], dyn["den"], rec.t, rec.u))}
        for name, x_model in outputs.items():
            cell = f"table2/{name}/{k}"
            result["table2"][name][k] = error_stats(rec.x, x_model)
            result["csv"][cell] = _write_cell(out_dir, f"csv/table2_{name}_{k}Hz.csv", rec.t, rec.x,
                                              x_model, force)
        for table, name, mode, inv in (("table3", "static_inverse", "ff", "static"),
                                       ("table3", "dynamic_inverse", "ff", "dynamic"),
                                       ("table4", "ff_pid", "ff+fb", "dynamic")):
            say(f"{table.capitalize()}: {name.replace('_', ' ')} at {k} Hz")
            res = simulate(model, Signal("sine", SINE_90[1], SINE_90[0], f), stop, mode=mode,
                           inverse=inv, record_step=dt, engine=engine)
            cell = f"{table}/{name}/{k}"
            result[table][name][k] = error_stats(res["x_ref"], res["x"])
            result["csv"][cell] = _write_cell(out_dir, f"csv/{table}_{name}_{k}Hz.csv", res["time"],
                                              res["x_ref"], res["x"], force)
            runs[(name, k)] = res
    result["checks"] = trend_checks(result)
    if figures:
        say("figures")
        result["figures"] = _figures(out_dir, model, rec5, width5, fig5, runs, force)
    write_text(out_dir / "reproduction.json", json.dumps(result, indent=2), force=force)
    if progress is not None:
        progress(1.0)
    return result


def trend_checks(r) -> dict:
    """The paper's headline claims evaluated on our numbers (the issue's acceptance trends)."""
    t2, t3, t4 = r["table2"], r["table3"], r["table4"]
    ks = [fkey(f) for f in FREQS]
    static_growth = t2["static"]["50"]["avg"] / t2["static"]["0.5"]["avg"]
    dyn_spread = max(t2["dynamic"][k]["avg"] for k in ks) / t2["dynamic"]["0.5"]["avg"]
    cut = {k: t3["dynamic_inverse"][k]["rms"] / t4["ff_pid"][k]["rms"] for k in ks}
    return {
        "table2_static_avg_growth_0.5_to_50": static_growth,
        "table2_dynamic_avg_max_over_0.5": dyn_spread,
        "table2_dynamic_beats_static_at_20_50": all(t2["dynamic"][k]["avg"] < t2["static"][k]["avg"]
                                                    for k in ("20", "50")),
        "table3_dynamic_beats_static": {k: t3["dynamic_inverse"][k]["avg"] < t3["static_inverse"][k]["avg"]
                                        for k in ks},
        "table4_rms_cut_by_pid": cut,
    }


def format_table(r) -> str:
    """Our values beside the paper's, as a plain-text table."""
    lines = [f"Figure 5: widest loop {r['figure5']['max_width_um']:.3f} um at "
             f"{r['figure5']['at_voltage_V']:.1f} V (paper 0.26 um at 15 V); repeatability "
             f"{r['figure5']['repeatability_um']:.3f} um (paper 0.06 um)", ""]
    head = f"{'table / cell':34s}" + "".join(f"{fkey(f) + ' Hz':>22s}" for f in FREQS)
    for table, cells in (("table2", ("static", "dynamic")),
                         ("table3", ("static_inverse", "dynamic_inverse")), ("table4", ("ff_pid",))):
        lines += [head, f"{'':34s}" + "".join(f"{'ours / paper':>22s}" for _ in FREQS)]
        for cell in cells:
            for j, stat in enumerate(("max", "avg", "rms")):
                row = f"{table + ' ' + cell + ' ' + stat:34s}"
                for f in FREQS:
                    k = fkey(f)
                    row += f"{r[table][cell][k][stat]:>12.4f} / {PAPER[table][cell][k][j]:<7.4f}"
                lines.append(row)
        lines.append("")
    c = r["checks"]
    lines.append(f"static model avg error 0.5 -> 50 Hz: x{c['table2_static_avg_growth_0.5_to_50']:.1f}; "
                 f"dynamic model worst / 0.5 Hz: x{c['table2_dynamic_avg_max_over_0.5']:.2f}")
    lines.append("dynamic inverse beats static (avg): " + ", ".join(
        f"{k} Hz {'yes' if v else 'NO'}" for k, v in c["table3_dynamic_beats_static"].items()))
    lines.append("PID cuts the dynamic-inverse RMS error by: " + ", ".join(
        f"{k} Hz x{v:.1f}" for k, v in c["table4_rms_cut_by_pid"].items()))
    return "\n".join(lines)


def _figures(out_dir, model, rec5, width5, fig5, runs, force):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # Figure 5: the loop
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.5))
        a1.plot(rec5.u, rec5.x, ".", ms=1.5, color="0.6", label="measured (probe noise)")
        a1.plot(rec5.u, rec5.x_true, lw=1.2, color="C0", label="device displacement")
        a1.set_xlabel("input voltage u [V]")
        a1.set_ylabel("displacement x [um]")
        a1.set_title("Figure 5: hysteresis loop, 0-30 V, 0.5 Hz")
        a1.legend(loc="upper left")
        grid, w = width5
        a2.plot(grid, w, color="C1")
        a2.axhline(0.26, ls="--", color="0.4", label="paper: 0.26 um at 15 V")
        a2.axvline(fig5["at_voltage_V"], ls=":", color="C1",
                   label=f"ours: {fig5['max_width_um']:.3f} um at {fig5['at_voltage_V']:.1f} V")
        a2.set_xlabel("input voltage u [V]")
        a2.set_ylabel("loop width [um]")
        a2.set_title("distance between the branches (last period)")
        a2.legend()
        fig.tight_layout()
        names["figure5"] = _save(fig, out_dir / "figure5_hysteresis.png", force)
        plt.close(fig)
        # Figure 7: errors of inverse feedforward
        fig, axes = plt.subplots(2, 2, figsize=(12, 7))
        for ax, f in zip(axes.ravel(), FREQS):
            k = fkey(f)
            for name, color in (("static_inverse", "C3"), ("dynamic_inverse", "C0")):
                res = runs[(name, k)]
                ax.plot(res["time"], res["x"] - res["x_ref"], color=color, lw=0.9,
                        label=name.replace("_", " "))
            ax.set_title(f"{k} Hz")
            ax.set_xlabel("time [s]")
            ax.set_ylabel("x - x_ref [um]")
            ax.grid(alpha=0.3)
        axes[0, 0].legend()
        fig.suptitle("Figure 7: error of inverse-model feedforward (0-90 V reference)")
        fig.tight_layout()
        names["figure7"] = _save(fig, out_dir / "figure7_inverse_errors.png", force)
        plt.close(fig)
        # Figure 9: displacement against input voltage for the three schemes
        fig, axes = plt.subplots(2, 2, figsize=(12, 8))
        k_ideal = model["compensator"]["k_ideal"]
        for ax, f in zip(axes.ravel(), FREQS):
            k = fkey(f)
            u_ref = runs[("ff_pid", k)]["x_ref"] / k_ideal
            ax.plot(u_ref, runs[("ff_pid", k)]["x_ref"], color="k", lw=1, ls="--", label="ideal")
            for name, color in (("static_inverse", "C3"), ("dynamic_inverse", "C0"), ("ff_pid", "C2")):
                res = runs[(name, k)]
                ax.plot(res["x_ref"] / k_ideal, res["x"], color=color, lw=0.9,
                        label={"ff_pid": "dynamic inverse + PID"}.get(name, name.replace("_", " ")))
            ax.set_title(f"{k} Hz")
            ax.set_xlabel("input voltage u_ref [V]")
            ax.set_ylabel("displacement x [um]")
            ax.grid(alpha=0.3)
        axes[0, 0].legend()
        fig.suptitle("Figure 9: displacement of the three control schemes")
        fig.tight_layout()
        names["figure9"] = _save(fig, out_dir / "figure9_control.png", force)
        plt.close(fig)
    return names


def _save(fig, path, force):
    with atomic_writer(path, "wb", force=force) as fh:
        fig.savefig(fh, format="png", dpi=110)
    return path.name
