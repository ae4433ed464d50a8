"""Writing a diagnosis: model.toml, fit.csv, diagnosis.json, figures and a self-contained report.html.

The final model is written first and then *re-run through the monolithic model* (``simulate``,
open loop, the recorded command, noise off): the columns ``x_final``/``us_final`` of fit.csv are
that run, so anyone can rebuild the FMUs from model.toml and expect the same signals. The
recalibrated nominal model is written beside it (model_nominal.toml) and gives ``x_nominal``.
"""
from __future__ import annotations

import base64
import html
import io
import itertools
import json
import math
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..io import atomic_writer, check_writable, write_text
from ..model import dump_model, load_model
from ..simulate import Signal, simulate
from .catalogue import CATALOGUE
from .stats import psd

__all__ = ["FIGURES", "OUTPUTS", "check_outputs", "replay_model", "write_outputs"]

FIGURES = ("residual_time.png", "residual_spectrum.png", "fit_before_after.png", "operating_range.png")
OUTPUTS = ("diagnosis.json", "fit.csv", "model.toml", "model_nominal.toml", "report.html") + FIGURES


def check_outputs(out, force=False):
    """Create ``out`` and refuse (before any work) to overwrite existing outputs without ``force``."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    for name in OUTPUTS:
        check_writable(out / name, force)
    return out


def replay_model(model, rec):
    """Run ``model`` open loop on the recorded command of ``rec`` (noise off; held over each sample,
    stepped ``rec.oversample`` times per sample as the fit replayed it): dict x, us at the samples.

    On the fit's grid (``rec.n`` samples ``rec.dt`` apart), not the file's times: written with 8
    digits, the times of 13.8 s at 13.2 kHz give a median step 7.5758e-05 s for 7.57576e-05, whose
    181728.98 steps to the last time replayed one sample short (rig-d32-033: the report failed
    after the diagnosis)."""
    m, n = rec.oversample, rec.n
    t = np.arange(n * m) * rec.h
    sig = Signal("table", t=t, values=rec.u if m == 1 else np.repeat(rec.u, m), column="u")
    res = simulate(model, sig, float(t[-1]), step=rec.h, mode="open", noise=False, t0=0.0)
    return {"x": np.asarray(res["x"])[:n * m:m], "us": np.asarray(res["us"])[:n * m:m]}


def _fmt(v):
    return f"{v:.6g}"


def write_outputs(diag, out, force=False, say=None, figures=True):
    say = say or (lambda msg: None)
    out = check_outputs(out, force)
    res = diag.result
    recs = diag.recs
    header = ("Written by piezo-fmu diagnose from " + ", ".join(r.name for r in recs) + ".\n"
              f"Base model: {diag.model.path}. Mechanisms added: "
              + (", ".join(res["final"]["effects"]) or "none") + ".\n"
              "Displacement units are the recording's (drift and PI scale carry them); the drift polynomial "
              "runs in time since the start of the recording.")
    write_text(out / "model.toml", dump_model(diag.final_model, header), force=force)
    write_text(out / "model_nominal.toml", dump_model(diag.nominal_model, header.replace(
        "Mechanisms added", "Recalibrated nominal model (no mechanism added); the final model adds")), force=force)
    # re-run both written models through the monolithic simulation
    say("re-running model.toml and model_nominal.toml through the monolithic model")
    final = load_model(out / "model.toml")
    nominal = load_model(out / "model_nominal.toml")
    sim_fin, sim_nom, dev = [], [], 0.0
    for i, r in enumerate(recs):
        f = replay_model(final, r)
        nm = replay_model(nominal, r)
        for c in r.channels():
            s = r.sign.get(c, 1)
            f[c] = s * f[c]
            nm[c] = s * nm[c]
            dev = max(dev, float(np.max(np.abs(f[c] - diag.pred_final[i][c]))))
        sim_fin.append(f)
        sim_nom.append(nm)
    res["check"] = {"simulate_vs_fit_max_abs": dev,
                    "note": "x_final/us_final are model.toml re-run by piezo_fmu.simulate (open loop, "
                            "recorded command, noise off); this is their largest difference from the "
                            "fitting engine"}
    # fit.csv
    _write_fit_csv(out / "fit.csv", recs, sim_nom, sim_fin, force)
    # figures and report
    figs = {}
    if figures:
        say("drawing figures")
        figs = _figures(diag, sim_nom, sim_fin, out, force)
    res["files"] = sorted(["diagnosis.json", "fit.csv", "model.toml", "model_nominal.toml", "report.html"]
                          + list(figs))
    write_text(out / "diagnosis.json", json.dumps(_jsonable(res), indent=2), force=force)
    write_text(out / "report.html", _html(diag, figs), force=force)
    return out


def _write_fit_csv(path, recs, sim_nom, sim_fin, force):
    chans = [c for c in ("x", "us") if any(getattr(r, c) is not None for r in recs)]
    cols = ["time"] + chans + [f"{c}_nominal" for c in chans] + [f"{c}_final" for c in chans] + ["heldout"]
    multi = len(recs) > 1
    if multi:
        cols.append("recording")
    with atomic_writer(path, "w", force=force) as fh:
        fh.write("# piezo-fmu diagnose: measured channels, the recalibrated nominal model and the final model "
                 "(both re-run by the monolithic model), held-out flag (1 = not used for fitting)\n")
        fh.write(",".join(cols) + "\n")
        for i, (r, nm, fi) in enumerate(zip(recs, sim_nom, sim_fin)):
            nan = np.full(r.n, np.nan)
            data = [r.t0 + r.t]
            data += [r.sign.get(c, 1) * getattr(r, c) if getattr(r, c) is not None else nan for c in chans]
            data += [nm[c] if getattr(r, c) is not None else nan for c in chans]
            data += [fi[c] if getattr(r, c) is not None else nan for c in chans]
            data.append(r.heldout.astype(float))
            if multi:
                data.append(np.full(r.n, float(i)))
            arr = np.column_stack(data)
            fmt = ["%.9g"] * (len(cols) - (2 if multi else 1)) + ["%d"] * (2 if multi else 1)
            np.savetxt(fh, arr, delimiter=",", fmt=fmt)


def _jsonable(o):
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, (np.floating, float)):
        v = float(o)
        return v if math.isfinite(v) else (None if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return _jsonable(o.tolist())
    return o


# -- figures -------------------------------------------------------------------------------------------

def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _decimate(t, *ys, n_max=3000):
    """At most ``n_max`` points per line, for a figure about a thousand pixels wide: each of
    ``n_max // 2`` bins of samples is drawn as its extremes (the earlier one at the bin's first
    time, the later at its last), so the noise band and a spike look as in the full record,
    where a plain stride would alias them."""
    bins = n_max // 2
    if t.size <= n_max:
        return (t,) + tuple(ys)
    size = t.size // bins
    m = bins * size
    tb = t[:m].reshape(bins, size)
    out = [np.column_stack([tb[:, 0], tb[:, -1]]).ravel()]
    rows = np.arange(bins)
    for y in ys:
        yb = y[:m].reshape(bins, size)
        i_lo, i_hi = np.argmin(yb, axis=1), np.argmax(yb, axis=1)
        out.append(np.column_stack([yb[rows, np.minimum(i_lo, i_hi)], yb[rows, np.maximum(i_lo, i_hi)]]).ravel())
    return tuple(out)


def _layout(fig, left=0.85, right=0.15, bottom=0.45, top=0.45, hspace=0.2, wspace=0.2):
    """Fixed margins in inches (labels, suptitle), in place of ``tight_layout``, which draws the
    whole figure once more to measure it (half of the figures' time on a long recording)."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h,
                        hspace=hspace, wspace=wspace)


def _save(fig, path, force):
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    _plt().close(fig)
    data = buf.getvalue()
    with atomic_writer(path, "wb", force=force) as fh:
        fh.write(data)
    return data


UNITS = {"x": "x", "us": "us [V]"}


def _figures(diag, sim_nom, sim_fin, out, force):
    plt = _plt()
    res = diag.result
    recs = diag.recs
    chans = [c for c in ("x", "us") if any(getattr(r, c) is not None for r in recs)]
    r0, nm0, fi0 = recs[0], sim_nom[0], sim_fin[0]
    t = r0.t0 + r0.t
    figs = {}
    colours = {}
    palette = ["C3", "C2", "C4", "C1", "C5", "C6", "C8", "C9"]
    for i, f in enumerate(res["findings"]):
        colours[f["effect"]] = palette[i % len(palette)]

    # 1. residual over time with the located windows
    fig, axes = plt.subplots(len(chans) + 1, 1, figsize=(11, 2.6 * (len(chans) + 1)), sharex=True)
    axes[0].plot(*_decimate(t, r0.u), color="k", lw=0.7)
    axes[0].set_ylabel("command u [V]")
    for ax, c in zip(axes[1:], chans):
        y = r0.sign.get(c, 1) * getattr(r0, c)
        tt, e0, e1 = _decimate(t, y - nm0[c], y - fi0[c])
        ax.plot(tt, e0, color="0.6", lw=0.6, label="recalibrated nominal")
        ax.plot(tt, e1, color="C0", lw=0.6, label="final model")
        noise = res["baseline"]["noise"].get(c, 0)
        ax.axhspan(-2 * noise, 2 * noise, color="C2", alpha=0.12, lw=0, label="noise +/-2 sigma")
        ax.set_ylabel(f"residual {UNITS[c]}")
        for f in res["findings"]:
            for w in f["where"]:
                if w.get("channel", c) == c and w.get("recording", r0.name) == r0.name:
                    ax.axvspan(w["t0_s"], max(w["t1_s"], w["t0_s"] + 2 * r0.dt), color=colours[f["effect"]], alpha=0.2, lw=0)
        for u in res["unexplained"]:
            if u["channel"] == c:
                for w in u["where"]:
                    ax.axvspan(w["t0_s"], w["t1_s"], color="k", alpha=0.08, hatch="//", lw=0)
        handles, labels = ax.get_legend_handles_labels()
        from matplotlib.patches import Patch

        for f in res["findings"]:
            handles.append(Patch(color=colours[f["effect"]], alpha=0.3))
            labels.append(f"where {f['effect']} acts")
        if res["unexplained"]:
            handles.append(Patch(facecolor="none", hatch="//", edgecolor="0.4"))
            labels.append("unexplained")
        ax.legend(handles, labels, loc="upper right", fontsize=7, ncol=2)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"Residual (measured - model) over time: {Path(r0.name).name}")
    _layout(fig, hspace=0.12)
    figs["residual_time.png"] = _save(fig, out / "residual_time.png", force)

    # 2. residual spectrum before/after
    fig, axes = plt.subplots(1, len(chans), figsize=(5.5 * len(chans), 3.8), squeeze=False)
    for ax, c in zip(axes[0], chans):
        y = r0.sign.get(c, 1) * getattr(r0, c)
        nper = int(2 ** int(math.log2(max(r0.n // 4, 64))))     # resolves the slow mechanisms too
        f, p0 = psd(y - nm0[c], 1 / r0.dt, nper)
        _, p1 = psd(y - fi0[c], 1 / r0.dt, nper)
        noise = res["baseline"]["noise"].get(c, 0)
        ax.loglog(f[1:], p0[1:], color="0.5", lw=1, label="recalibrated nominal")
        ax.loglog(f[1:], p1[1:], color="C0", lw=1, label="final model")
        ax.axhline(noise ** 2 / (0.5 / r0.dt), color="C2", ls="--", lw=1, label="white-noise floor")
        for fd in res["findings"]:
            if fd["band_hz"] and c in fd["channels"]:
                lo, hi = fd["band_hz"]
                ax.axvspan(max(lo, f[1]), max(hi, f[1] * 1.1), color=colours[fd["effect"]], alpha=0.15,
                           label=f"{fd['effect']} band")
        for u in res["unexplained"]:
            if u["channel"] == c:
                lo, hi = u["band_hz"]
                ax.axvspan(max(lo, f[1]), max(hi, f[1] * 1.1), facecolor="none", hatch="//", edgecolor="0.4",
                           label="unexplained")
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel(f"PSD of {c} residual [{'V' if c == 'us' else 'x'}^2/Hz]")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3, which="both")
    fig.suptitle("Residual spectrum before / after")
    _layout(fig, bottom=0.55, wspace=0.32)
    figs["residual_spectrum.png"] = _save(fig, out / "residual_spectrum.png", force)

    # 3. measured vs simulated in the located windows: signals on top, residuals below
    zooms = []
    for fd in res["findings"]:
        if fd["where"]:
            zooms.append((fd["effect"], fd["where"][0]))
    for u in res["unexplained"][:1]:
        if u["where"]:
            zooms.append(("unexplained", u["where"][0]))
    zooms = zooms[:3] or [("whole recording", {"t0_s": float(t[0]), "t1_s": float(t[-1])})]
    ncol = len(zooms)
    fig, axes = plt.subplots(2 * len(chans), ncol, figsize=(4.6 * ncol + 1.5, 2.4 * 2 * len(chans)),
                             squeeze=False, gridspec_kw={"height_ratios": [1.4, 1] * len(chans)})
    for i, c in enumerate(chans):
        y = r0.sign.get(c, 1) * getattr(r0, c)
        for j, (name, w) in enumerate(zooms):
            span = w["t1_s"] - w["t0_s"]
            pad = max(0.25 * span, 30 * r0.dt)
            sl = (t >= w["t0_s"] - pad) & (t <= w["t1_s"] + pad)
            tt, yy, a, b = _decimate(t[sl], y[sl], nm0[c][sl], fi0[c][sl])
            ax = axes[2 * i][j]
            ax.plot(tt, yy, color="k", lw=1.0, label="measured")
            ax.plot(tt, a, color="0.55", lw=0.9, ls="--", label="nominal (recalibrated)")
            ax.plot(tt, b, color="C0", lw=0.9, label="final")
            ax.set_title(f"{name}: {w['t0_s']:.4g}-{w['t1_s']:.4g} s", fontsize=9)
            ax.grid(alpha=0.3)
            ax2 = axes[2 * i + 1][j]
            ax2.plot(tt, yy - a, color="0.55", lw=0.8, label="measured - nominal")
            ax2.plot(tt, yy - b, color="C0", lw=0.8, label="measured - final")
            noise = res["baseline"]["noise"].get(c, 0)
            ax2.axhspan(-2 * noise, 2 * noise, color="C2", alpha=0.12, lw=0)
            ax2.grid(alpha=0.3)
            if j == 0:
                ax.set_ylabel(UNITS[c])
                ax2.set_ylabel(f"residual {c}")
                ax.legend(fontsize=7)
                ax2.legend(fontsize=7)
            if i == len(chans) - 1:
                ax2.set_xlabel("time [s]")
    fig.suptitle("Measured vs simulated where it matters,\nbefore (nominal) and after (final)", fontsize=11)
    _layout(fig, left=0.95, bottom=0.55, top=0.8, hspace=0.45, wspace=0.28)
    figs["fit_before_after.png"] = _save(fig, out / "fit_before_after.png", force)

    # 4. residual over the operating range (command level and rate)
    fig, axes = plt.subplots(len(chans), 2, figsize=(10, 2.8 * len(chans)), squeeze=False)

    ctx = diag.ctx[0]
    for i, c in enumerate(chans):
        y = r0.sign.get(c, 1) * getattr(r0, c)
        for j, (v, lab) in enumerate(((r0.u, "command u [V]"), (ctx["rate"], "command rate [V/s]"))):
            ax = axes[i][j]
            qs = np.unique(np.quantile(v, np.linspace(0, 1, 11)))
            mids, r_nom, r_fin = [], [], []
            for lo, hi in itertools.pairwise(qs):
                m = (v >= lo) & (v <= hi)
                if np.count_nonzero(m) < 5:
                    continue
                mids.append(0.5 * (lo + hi))
                r_nom.append(np.sqrt(np.mean((y - nm0[c])[m] ** 2)))
                r_fin.append(np.sqrt(np.mean((y - fi0[c])[m] ** 2)))
            ax.plot(mids, r_nom, "o-", color="0.5", label="recalibrated nominal")
            ax.plot(mids, r_fin, "o-", color="C0", label="final")
            ax.axhline(res["baseline"]["noise"].get(c, 0), color="C2", ls="--", label="noise")
            ax.set_xlabel(lab)
            ax.set_ylabel(f"rms residual {UNITS[c]}")
            ax.grid(alpha=0.3)
            if j == 0:
                ax.legend(fontsize=7)
    fig.suptitle("Where in the operating range the residual lives (10 quantile bins)")
    _layout(fig, bottom=0.55, hspace=0.55, wspace=0.28)
    figs["operating_range.png"] = _save(fig, out / "operating_range.png", force)
    return figs


# -- html -------------------------------------------------------------------------------------------------

# units of the parameter keys (suffix -> unit) for the findings table
_SUFFIX = (("_Hz", "Hz"), ("_V_per_s", "V/s"), ("_per_s2", "x/s^2"), ("_per_s", "x/s"), ("_s", "s"),
           ("_A", "A"), ("_um", "um"), ("_V", "V"))
_PLAIN = {"zeta": "1", "gains": "1", "samples": "samples", "operators": "operators", "thresholds": "1 (of u_norm)"}


def _num(v):
    return f"{v:.4g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)


def _param_text(params):
    """``{"f_n_Hz": 65.4, "zeta": 0.005}`` -> ``f_n 65.4 Hz, zeta 0.005 (1)``: plain numbers, units."""
    out = []
    for k, v in params.items():
        unit, name = None, k
        for suf, u in _SUFFIX:
            if k.endswith(suf):
                name, unit = k[: -len(suf)], u
                break
        unit = unit or _PLAIN.get(k, "")
        if isinstance(v, (list, tuple)):
            val = "[" + ", ".join(_num(x) for x in v) + "]"
        else:
            val = _num(v)
        out.append(f"{name} {val}" + (f" {unit}" if unit and unit != "1" else (" (1)" if unit == "1" else "")))
    return ", ".join(out)


def _band(b):
    """``[lo, hi]`` [Hz] -> ``lo-hi Hz`` (plain numbers); ``-`` when there is none."""
    if not b:
        return "-"
    return f"{float(b[0]):.4g}-{float(b[1]):.4g} Hz"


def _where_text(w):
    return f"{w['t0_s']:.4g}-{w['t1_s']:.4g} s: {w['why']}"


UNIT = {"x": "um", "us": "V"}


def _table(rows, head):
    h = "".join(f"<th>{html.escape(str(x))}</th>" for x in head)
    b = "".join("<tr>" + "".join(f"<td>{x}</td>" for x in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{b}</table>"


def _html(diag, figs):
    res = diag.result
    e = html.escape
    parts = [f"""<!DOCTYPE html><html><head><meta charset="utf-8"><title>piezo-fmu diagnose</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto;color:#222}}
table{{border-collapse:collapse;margin:0.6em 0}}td,th{{border:1px solid #ccc;padding:3px 8px;font-size:0.9em;vertical-align:top}}
th{{background:#f2f2f2}}img{{max-width:100%;border:1px solid #eee;margin:0.5em 0}}.v{{font-size:1.15em;padding:0.6em;background:#eef5ff}}
code{{background:#f6f6f6}}</style></head><body>
<h1>Diagnosis of {e(", ".join(Path(r.name).name for r in diag.recs))}</h1>
<p class="v"><b>Verdict:</b> {e(res["final"]["verdict"])}</p>"""]
    chans = list(res["baseline"]["rmse"])
    rows = [["recalibrated nominal"] + [_fmt(res["baseline"]["rmse"][c]) for c in chans]
            + [_fmt(res["baseline"]["nrmse"])]]
    for f in res["findings"]:
        rows.append([f"+ {e(f['effect'])}"] + [_fmt(f["rmse_after"].get(c, float("nan"))) for c in chans] + [""])
    rows.append(["<b>final</b>"] + [f"<b>{_fmt(res['final']['rmse'][c])}</b>" for c in chans]
                + [f"<b>{_fmt(res['final']['nrmse'])}</b>"])
    rows.append(["noise level"] + [_fmt(res["baseline"]["noise"][c]) for c in chans] + [""])
    parts.append("<h2>Held-out RMSE</h2>" + _table(rows, ["model"] + [f"rmse {c} [{UNIT[c]}]" for c in chans]
                                                       + ["nrmse [1]"]))
    away_b, away_f = res["baseline"].get("rmse_away_from_jumps", {}), res["final"].get("rmse_away_from_jumps", {})
    if away_b and any(away_b[c] != res["baseline"]["rmse"][c] for c in away_b):
        parts.append("<p>Away from the command's jumps (where creep, leakage and drift are judged; the "
                     "transients after the steps left out): recalibrated nominal "
                     + ", ".join(f"{c} {_fmt(away_b[c])} {UNIT[c]}" for c in away_b) + "; final "
                     + ", ".join(f"{c} {_fmt(away_f[c])} {UNIT[c]}" for c in away_f) + ".</p>")
    parts.append("<p>Nominal model as given (before recalibration): "
                 + ", ".join(f"{c} {_fmt(v)} {UNIT[c]}" for c, v in res["baseline"]["nominal_as_given_rmse"].items())
                 + ". " + e(res["validation"]["method"]) + f" ({100 * res['validation']['heldout_fraction']:.0f} % held out).</p>")
    if res["findings"]:
        rows = []
        for f in res["findings"]:
            ev = f["evidence"]
            where = "<br>".join(e(_where_text(w)) for w in f["where"][:3])
            rows.append([f"<b>{e(f['effect'])}</b><br>{e(CATALOGUE[f['effect']].title)}", e(", ".join(f["channels"])),
                         f"{f['confidence']:.2f}", e(_param_text(f["parameters"])),
                         e(_band(f["band_hz"])), where,
                         e(f"explains {', '.join(f'{c} {100 * v:.0f} %' for c, v in ev['explained_share'].items())} "
                           f"of the structured held-out residual; LR {ev['likelihood_ratio']:.1f} (df {ev['df']}, "
                           f"p {ev['p_lr']:.2g}); dBIC {ev['delta_bic']:.1f}; held-out blocks better "
                           f"{ev['heldout_blocks_better']} (p {ev['p_heldout_blocks']:.2g})")])
        parts.append("<h2>Findings</h2>" + _table(rows, ["mechanism", "channel", "confidence [0-1]", "parameters",
                                                          "band", "where", "evidence"]))
    if res.get("candidates"):
        rows = [[f"<b>{e(c['effect'])}</b>", f"{c['confidence']:.2f}", e(_param_text(c["parameters"])),
                 e(_band(c["band_hz"])), e(c["why_not_named"]),
                 e((c["evidence"].get("strongest_alternative") or {}).get("effect", "-"))] for c in res["candidates"]]
        parts.append("<h2>Candidates (supported, but below confidence 0.5: not in the model)</h2>"
                     + _table(rows, ["mechanism", "confidence [0-1]", "parameters", "band", "why not named", "rival"]))
    rc = res["baseline"].get("recalibrated", {})
    if rc:
        rows = []
        for k, v in rc.items():
            if isinstance(v, dict) and "value" in v:
                unc, absolute = v.get("relative_uncertainty"), v.get("uncertainty")
                extra = " (not identified" + (f": {v['why']}" if v.get("why") else "") + ")" \
                    if v.get("identified") is False else ""
                if v.get("determined") is False:
                    extra += f" (not determined: {v['why_undetermined']})"
                # an offset's uncertainty is in its own unit (the key's suffix: x_offset_um)
                rows.append([e(k), e(_param_text({k: v["value"]})) + e(extra),
                             f"{100 * unc:.2g} %" if unc is not None else
                             e(f"{_fmt(absolute)} {k.rsplit('_', 1)[-1]}") if absolute is not None else "-"])
            else:
                rows.append([e(k), e(_param_text({k: v})), "-"])
        parts.append("<h2>Recalibrated ordinary physics</h2>" + _table(rows, ["quantity", "value", "standard uncertainty"]))
    rows = []
    for c, t in res["final"]["tests"].items():
        xc = t["input_xcorr"]
        rows.append([e(c), f"{_fmt(t['noise'])} {UNIT[c]}", f"{_fmt(t['structured_rms'])} {UNIT[c]}",
                     f"{t['whiteness_decimated']['p']:.2g} (Q {t['whiteness_decimated']['Q']:.3g})",
                     f"{xc['max_abs']:.3g} (99 % bound {xc['bound']:.3g}, lag {xc['lag']})"])
    parts.append("<h2>Residual tests of the final model (held-out and training samples)</h2>"
                 + _table(rows, ["channel", "noise floor", "structured rms",
                                 "Ljung-Box p (decimated by the correlation time)",
                                 "max |corr| with the command's increments"]))
    if res["unexplained"]:
        rows = [[e(u["channel"]), e(_band(u["band_hz"])), e(u["description"]),
                 "<br>".join(e(_where_text(w)) for w in u["where"])]
                for u in res["unexplained"]]
        parts.append("<h2>Structured residual no mechanism explains</h2>" + _table(rows, ["channel", "band", "what", "where"]))
    for name, title in (("residual_time.png", "Residual over time (located windows shaded)"),
                        ("residual_spectrum.png", "Residual spectrum before / after"),
                        ("fit_before_after.png", "Measured vs simulated before / after"),
                        ("operating_range.png", "Residual over the operating range")):
        if name in figs:
            b64 = base64.b64encode(figs[name]).decode("ascii")
            parts.append(f"<h2>{e(title)}</h2><img alt='{e(name)}' src='data:image/png;base64,{b64}'>")
    loc = res["localisation"]
    for c, L in loc.items():
        rows = [[e(k), f"{_fmt(v['rms'])} {UNIT[c]}", f"{100 * v['share_of_samples']:.0f} %"] for k, v in L["segments"].items()]
        parts.append(f"<h2>Where the recalibrated nominal model misses ({e(c)})</h2>"
                     f"<p>rms over all samples (for locating; the RMSEs above are held-out) "
                     f"{_fmt(L['rms_all_samples'])} {UNIT[c]}, noise {_fmt(L['noise'])} {UNIT[c]}, "
                     f"structured {_fmt(L['structured_rms'])} {UNIT[c]}</p>"
                     + _table(rows, ["input segment", "rms residual", "share of samples"])
                     + _table([[e(_band(b["band_hz"])), f"{_fmt(b['rms'])} {UNIT[c]}", f"{100 * b['share']:.0f} %",
                                f"{b['coherence']:.2f}"]
                               for b in L["bands"]], ["band above noise", "rms", "share", "coherence with u [0-1]"]))
    if res["rejected"]:
        parts.append("<h2>Candidates tested and not accepted</h2>"
                     + _table([[e(r["effect"]), e(r["why"])] for r in res["rejected"]], ["mechanism", "why not"]))
    rows = [[e(m.name), e(m.model), e(m.signature), e(m.parameters)] for m in CATALOGUE.values()]
    parts.append("<h2>Catalogue</h2>" + _table(rows, ["mechanism", "model", "residual signature", "parameters"]))
    if res.get("notes"):
        parts.append("<h2>Notes</h2><ul>" + "".join(f"<li>{e(n)}</li>" for n in res["notes"]) + "</ul>")
    parts.append(f"<p>Files: {e(', '.join(res.get('files', [])))}. Timing: {e(json.dumps(res.get('timing_s', {})))}.</p>")
    parts.append("</body></html>")
    return "\n".join(parts)
