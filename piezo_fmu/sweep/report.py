"""The report of a sweep: ``DIR/report.html`` with PNG figures in ``DIR/figures/`` (matplotlib, Agg).

What a designer looks at first:

* **curves** (``curves.png``): when a grid has a numeric axis of five or more values (a frequency
  sweep), each metric against it, one line per combination of the other grid axes (with random
  draws: the median and the 5-95 % band over the units);
* **distributions** (``distributions.png``): a histogram of each metric over the finished runs;
* **each metric against each varied parameter** (``<metric>_vs_parameters.png``): scatter, lines
  for grid axes, strips for categories;
* **yield** (``yield.png``, with a tolerance): the histogram of the tolerance metric with its
  limit, the share of runs that pass with a 95 % (Wilson) interval, and how much of the metric
  each varied parameter explains (:func:`sensitivity`): which tolerances matter;
* **the worst runs** with their values, and the errors grouped by message.
"""
from __future__ import annotations

import html
import math
from collections import Counter
from pathlib import Path

import numpy as np

from .metrics import UNITS
from .space import columns
from .spec import SweepSpec

__all__ = ["FIGURES", "column_array", "passes", "sensitivity", "write_report", "yield_of"]

FIGURES = "figures"
MAX_PANELS = 16
MAX_LINES = 12
DPI = 80


def column_array(table, name) -> np.ndarray:
    """A column as a NumPy array: numbers as float (NaN for missing), others as objects."""
    import pyarrow as pa

    c = table.column(name)
    if pa.types.is_floating(c.type) or pa.types.is_integer(c.type):
        return np.array([math.nan if v is None else v for v in c.to_pylist()], dtype=float)
    return np.array(c.to_pylist(), dtype=object)


def passes(spec: SweepSpec, data: dict) -> np.ndarray:
    """Per run: finished, stable (when computed) and within the tolerance."""
    ok = data["status"] == "ok"
    if "stable" in data:
        ok &= np.array([v is True for v in data["stable"]])
    t = spec.tolerance
    if t is not None and t.metric != "stable":
        v = data[t.metric]
        with np.errstate(invalid="ignore"):
            if t.max is not None:
                ok &= v <= t.max
            if t.min is not None:
                ok &= v >= t.min
    return ok


def yield_of(n_pass, n) -> tuple:
    """``(yield, low, high)``: the share and its 95 % Wilson score interval."""
    if n == 0:
        return math.nan, math.nan, math.nan
    z = 1.959964
    p = n_pass / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return p, max(0.0, centre - half), min(1.0, centre + half)


def _ranks(v):
    order = np.argsort(v, kind="stable")
    r = np.empty(v.size)
    r[order] = np.arange(v.size)
    return r


def sensitivity(x, y, bins=10) -> float:
    """How much of ``y`` a parameter ``x`` explains: the correlation ratio (eta squared) of the
    ranks of ``y`` over ``bins`` quantile bins of ``x``, in 0..1 (NaN if under 3 finite pairs or
    flat). Unlike a rank correlation it also sees a V-shaped dependence (an error that grows with
    the distance from the nominal value either way). With ``n`` runs, chance alone gives about
    ``(bins - 1) / n``."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    m = np.isfinite(x) & np.isfinite(y)
    if m.sum() < 3:
        return math.nan
    rx, ry = _ranks(x[m]), _ranks(y[m])
    if np.std(rx) == 0 or np.std(ry) == 0:
        return math.nan
    group = np.minimum((rx * bins / rx.size).astype(int), bins - 1)
    total = np.sum((ry - ry.mean()) ** 2)
    between = sum(np.sum(group == g) * (ry[group == g].mean() - ry.mean()) ** 2
                  for g in np.unique(group))
    return float(between / total)


def _label(name):
    unit = UNITS.get(name)
    return f"{name} [{unit}]" if unit else name


def _param_label(spec, key):
    from ..model import key_spec

    if key.startswith("experiment."):
        from .spec import EXPERIMENT

        unit = EXPERIMENT[key.split(".", 1)[1]].unit
    else:
        unit = key_spec(key).unit
    return f"{key} [{unit}]" if unit and unit != "1" else key


def _is_log(spec, key, values):
    axis = next((a for a in spec.grid if key in a.keys), None)
    if axis is not None:
        return axis.log
    v = values[np.isfinite(values)] if values.dtype != object else np.array([])
    return v.size > 0 and v.min() > 0 and v.max() / v.min() > 100


def _grid_groups(spec, data, key):
    """Labels of the other grid axes' combinations, per run (None if too many or none)."""
    others = [k for a in spec.grid if key not in a.keys for k in a.keys]
    if not others:
        return None

    def text(k, v):
        return f"{k.split('.')[-1]}={v:g}" if isinstance(v, float) else f"{k.split('.')[-1]}={v}"

    labels = np.array([", ".join(text(k, data[k][i]) for k in others) for i in range(len(data["index"]))],
                      dtype=object)
    return labels if len(set(labels)) <= MAX_LINES else None


def _numeric(v):
    return v.dtype != object


def _plot_against(ax, spec, data, key, metric, fin):
    x = data[key]
    y = data[metric] if metric != "stable" else np.array([1.0 if v is True else 0.0 for v in data["stable"]])
    if not _numeric(x):       # categories: a strip per value
        cats = list(dict.fromkeys(x[fin]))
        for j, c in enumerate(cats):
            sel = fin & (x == c)
            jitter = (np.random.default_rng(j).random(sel.sum()) - 0.5) * 0.3
            ax.plot(j + jitter, y[sel], ".", ms=3, alpha=0.6)
        ax.set_xticks(range(len(cats)), [str(c) for c in cats])
    else:
        groups = _grid_groups(spec, data, key) if any(key in a.keys for a in spec.grid) else None
        if groups is not None:
            for g in dict.fromkeys(groups[fin]):
                sel = fin & (groups == g)
                xs, ys = _median_curve(x[sel], y[sel])
                ax.plot(xs, ys, "-o", ms=2.5, lw=1.2, label=g)
            if len(set(groups[fin])) > 1:
                ax.legend(fontsize=6)
        else:
            ax.plot(x[fin], y[fin], ".", ms=2.5, alpha=0.5)
        if _is_log(spec, key, x):
            _log_x(ax)
        else:
            from matplotlib.ticker import MaxNLocator

            ax.xaxis.set_major_locator(MaxNLocator(4))
    ax.set_xlabel(_param_label(spec, key), fontsize=8)
    ax.set_ylabel(_label(metric), fontsize=8)
    ax.tick_params(labelsize=7)
    _maybe_log_y(ax, y[fin])


def _log_x(ax):
    from matplotlib.ticker import NullFormatter

    ax.set_xscale("log")
    ax.xaxis.set_minor_formatter(NullFormatter())


def _median_curve(x, y):
    xs = np.unique(x)
    return xs, np.array([np.nanmedian(y[x == v]) if np.any(np.isfinite(y[x == v])) else np.nan for v in xs])


def _maybe_log_y(ax, y):
    y = y[np.isfinite(y)]
    if y.size and y.min() > 0 and y.max() / y.min() > 100:
        ax.set_yscale("log")


def _grid_of(n):
    cols = min(4, n)
    rows = math.ceil(n / cols)
    return rows, cols


def _save(fig, path, bottom_in=0.0, tight=False):
    """Fixed margins in inches (tight_layout draws the figure once more: a second per figure)."""
    if tight:
        fig.tight_layout()
        fig.savefig(path, dpi=DPI)
        import matplotlib.pyplot as plt

        plt.close(fig)
        return
    w, h = fig.get_size_inches()
    rows, cols = fig.axes[0].get_subplotspec().get_gridspec().get_geometry() if fig.axes else (1, 1)
    fig.subplots_adjust(left=0.75 / w, right=1 - 0.15 / w, top=1 - 0.45 / h, bottom=(0.5 + bottom_in) / h,
                        wspace=0.8 * cols / w if cols > 1 else 0.2, hspace=0.75 * rows / h if rows > 1 else 0.2)
    fig.savefig(path, dpi=DPI)
    import matplotlib.pyplot as plt

    plt.close(fig)


def _curves(spec, data, fin, metrics, folder):
    import matplotlib.pyplot as plt

    axes = [a for a in spec.grid if len(a.values) >= 5 and len(a.keys) == 1 and not isinstance(a.values[0], str)]
    if not axes:
        return None
    axis = max(axes, key=lambda a: len(a.values))
    ms = [m for m in metrics if m != "stable"]
    rows, cols = _grid_of(len(ms))
    fig, axs = plt.subplots(rows, cols, figsize=(3.3 * cols, 2.6 * rows), squeeze=False)
    groups = _grid_groups(spec, data, axis.key)
    if groups is None:
        groups = np.array([""] * len(data["index"]), dtype=object)
    x = data[axis.key]
    for ax, m in zip(axs.flat, ms):
        y = data[m]
        for g in dict.fromkeys(groups):
            sel = fin & (groups == g)
            if not sel.any():
                continue
            xs = np.unique(x[sel])
            q = np.array([np.nanpercentile(y[sel & (x == v)], [5, 50, 95]) if np.any(np.isfinite(y[sel & (x == v)]))
                          else [np.nan] * 3 for v in xs])
            line, = ax.plot(xs, q[:, 1], "-o", ms=2.5, lw=1.2, label=g or None)
            if spec.count > 1:
                ax.fill_between(xs, q[:, 0], q[:, 2], color=line.get_color(), alpha=0.2, lw=0)
        if axis.log:
            _log_x(ax)
        _maybe_log_y(ax, y[fin])
        ax.set_xlabel(_param_label(spec, axis.key), fontsize=8)
        ax.set_ylabel(_label(m), fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, which="both", alpha=0.3)
    for ax in list(axs.flat)[len(ms):]:
        ax.axis("off")
    handles, labels = axs.flat[0].get_legend_handles_labels()
    if labels:
        fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 4), fontsize=7, frameon=False)
        _save(fig, folder / "curves.png", bottom_in=0.15 + 0.17 * math.ceil(len(labels) / 4))
    else:
        _save(fig, folder / "curves.png")
    return "curves.png"


def _distributions(spec, data, fin, metrics, folder):
    import matplotlib.pyplot as plt

    rows, cols = _grid_of(len(metrics))
    fig, axs = plt.subplots(rows, cols, figsize=(3.0 * cols, 2.3 * rows), squeeze=False)
    for ax, m in zip(axs.flat, metrics):
        if m == "stable":
            v = data["stable"][fin]
            ax.bar(["stable", "not stable"], [sum(x is True for x in v), sum(x is False for x in v)])
        else:
            v = data[m][fin]
            v = v[np.isfinite(v)]
            if v.size:
                log = v.min() > 0 and v.max() / v.min() > 100
                bins = np.geomspace(v.min(), v.max(), 30) if log else 30
                ax.hist(v, bins=bins)
                if log:
                    ax.set_xscale("log")
            ax.set_xlabel(_label(m), fontsize=8)
        ax.set_ylabel("runs", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in list(axs.flat)[len(metrics):]:
        ax.axis("off")
    _save(fig, folder / "distributions.png")
    return "distributions.png"


def _against(spec, data, fin, metric, params, folder):
    import matplotlib.pyplot as plt

    shown = params[:MAX_PANELS]
    rows, cols = _grid_of(len(shown))
    fig, axs = plt.subplots(rows, cols, figsize=(2.6 * cols, 2.2 * rows), squeeze=False, sharey=True)
    for ax, key in zip(axs.flat, shown):
        _plot_against(ax, spec, data, key, metric, fin)
    for k, ax in enumerate(axs.flat):       # one y axis per row: the same metric throughout
        if k >= len(shown):
            ax.axis("off")
        elif k % cols:
            ax.set_ylabel("")
            ax.tick_params(labelleft=False)
    name = f"{metric}_vs_parameters.png"
    _save(fig, folder / name)
    return name


def _yield_figure(spec, data, fin, params, ok, folder):
    import matplotlib.pyplot as plt

    t = spec.tolerance
    numeric = [k for k in params if _numeric(data[k])]
    fig, axs = plt.subplots(1, 2, figsize=(8.4, 3.2), gridspec_kw={"width_ratios": [1, 1.1]})
    n = len(data["index"])
    y, lo, hi = yield_of(int(ok.sum()), n)
    ax = axs[0]
    if t.metric == "stable":
        v = data["stable"]
        ax.bar(["stable", "not stable", "failed"], [sum(x is True for x in v), sum(x is False for x in v),
                                                    int((~fin).sum())])
    else:
        v = data[t.metric][fin]
        v = v[np.isfinite(v)]
        if v.size:
            log = v.min() > 0 and v.max() / v.min() > 100
            bins = np.geomspace(v.min(), v.max(), 40) if log else 40
            ax.hist(v, bins=bins, color="0.6")
            if log:
                ax.set_xscale("log")
        for limit in (t.min, t.max):
            if limit is not None:
                ax.axvline(limit, color="C3", lw=1.5)
        ax.set_xlabel(_label(t.metric), fontsize=8)
    ax.set_ylabel("runs", fontsize=8)
    ax.set_title(f"yield {100 * y:.1f} % (95 %: {100 * lo:.1f}-{100 * hi:.1f} %), {n} runs\n"
                 f"pass: {t.describe()}, stable", fontsize=8)
    ax.tick_params(labelsize=7)
    ax = axs[1]
    metric = t.metric if t.metric != "stable" else "rms_um"
    if numeric and metric in data:
        eta = [sensitivity(data[k][fin], data[metric][fin]) for k in numeric]
        order = np.argsort([-r if np.isfinite(r) else 0 for r in eta])[:MAX_PANELS]
        keys = [numeric[i] for i in order][::-1]
        vals = [eta[i] for i in order][::-1]
        ax.barh(range(len(keys)), vals, color="C0")
        ax.set_yticks(range(len(keys)), keys, fontsize=7)
        ax.axvline(9 / max(int(fin.sum()), 1), color="0.5", lw=0.8, ls="--")      # chance level
        ax.set_xlim(0, 1)
        ax.set_xlabel(f"share of the variance of {metric} (ranks) explained", fontsize=8)
        ax.set_title("which parameters matter (dashed: chance)", fontsize=8)
        ax.tick_params(labelsize=7)
    else:
        ax.axis("off")
    _save(fig, folder / "yield.png", tight=True)
    return "yield.png", (y, lo, hi)


def _fmt(v):
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.4g}"
    if v is None:
        return ""
    return html.escape(str(v))


def write_report(out_dir, spec: SweepSpec, table=None, summary=None) -> Path:
    """Write ``out_dir/report.html`` and its figures from the results (read from ``out_dir``
    unless ``table`` is given); returns the HTML's path. ``summary``: extra facts shown on top
    (e.g. wall time, engine)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from .store import read_results

    out_dir = Path(out_dir)
    if table is None:
        table = read_results(out_dir)
    folder = out_dir / FIGURES
    folder.mkdir(exist_ok=True)
    for old in folder.glob("*.png"):
        old.unlink()
    data = {name: column_array(table, name) for name in table.column_names}
    n = len(data["index"])
    status = data["status"]
    fin = status == "ok"
    metrics = [m for m in spec.metric_names if m in data]
    params = [name for name, kind in columns(spec)]
    ok = passes(spec, data)
    figures = []
    if n and fin.any():
        c = _curves(spec, data, fin, metrics, folder)
        if c:
            figures.append(("Curves over the grid", c))
        figures.append(("Distribution of each metric (finished runs)", _distributions(spec, data, fin, metrics,
                                                                                       folder)))
        for m in metrics:
            if params:
                figures.append((f"{m} against each varied parameter", _against(spec, data, fin, m, params, folder)))
    yield_line = ""
    if spec.tolerance is not None and n:
        name, (y, lo, hi) = _yield_figure(spec, data, fin, params, ok, folder) if fin.any() else (None, yield_of(0, n))
        if name:
            figures.insert(0, ("Yield and sensitivity", name))
        yield_line = (f"<p><b>Yield: {100 * y:.1f} %</b> (95 % interval {100 * lo:.1f}-{100 * hi:.1f} %) of {n} "
                      f"runs pass: finished, stable and {html.escape(spec.tolerance.describe())}.</p>")
    counts = Counter(status.tolist())
    parts = [f"<!doctype html><meta charset='utf-8'><title>sweep {html.escape(spec.name)}</title>",
             ("<style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
              "table{border-collapse:collapse;font-size:12px}td,th{border:1px solid #ccc;padding:2px 6px}"
              "img{max-width:100%}</style>"),
             f"<h1>Sweep {html.escape(spec.name)}</h1>",
             f"<p>{html.escape(spec.description)}</p>" if spec.description else "",
             f"<p>{n} of {spec.n_runs} runs in the results: " +
             ", ".join(f"{v} {html.escape(k)}" for k, v in counts.items()) +
             f". Base model <code>{html.escape(spec.model_origin)}</code>; engine "
             f"{html.escape(spec.experiment['engine'])} ({html.escape(spec.experiment['kernels'])}).</p>",
             yield_line]
    if summary:
        parts.append("<p>" + "; ".join(f"{html.escape(str(k))}: {_fmt(v)}" for k, v in summary.items()) + "</p>")
    for title, name in figures:
        parts.append(f"<h2>{html.escape(title)}</h2><img src='{FIGURES}/{name}' alt='{html.escape(title)}'>")
    # the worst runs
    rank = spec.tolerance.metric if spec.tolerance is not None and spec.tolerance.metric != "stable" else (
        "rms_um" if "rms_um" in data else (metrics[0] if metrics and metrics[0] != "stable" else None))
    if rank is not None and fin.any():
        v = np.where(fin, data[rank], np.nan)
        if spec.tolerance is not None and spec.tolerance.min is not None and spec.tolerance.max is None:
            order = np.argsort(np.where(np.isfinite(v), v, np.inf), kind="stable")
        else:
            order = np.argsort(np.where(np.isfinite(v), -v, np.inf), kind="stable")
        order = [i for i in order if fin[i]][: spec.metrics["worst"]]
        cols = ["index"] + params + metrics
        parts.append(f"<h2>The {len(order)} worst runs by {html.escape(rank)}</h2><table><tr>" +
                     "".join(f"<th>{html.escape(c)}</th>" for c in cols) + "</tr>")
        for i in order:
            parts.append("<tr>" + "".join(f"<td>{_fmt(data[c][i] if c != 'index' else int(data[c][i]))}</td>"
                                          for c in cols) + "</tr>")
        parts.append("</table>")
    errors = Counter(m for m, s in zip(data["error"].tolist(), status.tolist()) if s != "ok")
    if errors:
        parts.append("<h2>Runs without a result</h2><table><tr><th>runs</th><th>message</th></tr>")
        for msg, k in errors.most_common(20):
            parts.append(f"<tr><td>{k}</td><td>{html.escape(msg or '')}</td></tr>")
        parts.append("</table>")
    path = out_dir / "report.html"
    tmp = path.with_name(".report.html.tmp")
    tmp.write_text("\n".join(p for p in parts if p))
    tmp.replace(path)
    return path
