"""Recognition study: run diagnose blind on synthetic recordings and count what it names.

``python -m piezo_fmu.diagnose.evaluate [--jobs 2] [--out eval.json] [--markdown table.md]``

The cases (deterministic, seeded) cover every catalogue mechanism alone at three noise levels and
two parameter draws, every pair of mechanisms, clean recordings (nothing to find), and negative
controls (mechanisms the catalogue does not have: mains hum on the displacement, a drifting sensor
offset). Each case draws its own excitation programme: 2-4 of sine sets (0.5-50 Hz), steps and
holds, decaying triangles and chirps, in random order. diagnose sees only the recording.

Reported:

* **recognition rate** - true mechanisms that were named, over all true mechanisms; also over the
  *visible* ones, whose effect on the clean outputs exceeds twice the noise rms over some 50 ms
  window (a mechanism the excitation does not excite cannot be recognised by anyone);
* **false-positive rate** - cases with at least one name that is not in the truth; and false names
  per opportunity (catalogue entries not in the truth, over all cases);
* for the controls, how often the structured residual was described as unexplained.
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from .synth import EFFECTS, NOISE, PROGRAMMES

__all__ = ["cases", "markdown", "run_case", "summarise"]


def cases(quick=False):
    """The list of case specifications (dicts)."""
    out = []
    seed = 1000
    noises = ("low", "mid", "high")
    rng = np.random.default_rng(7)

    def kinds():
        k = int(rng.integers(2, 5))
        return [str(v) for v in rng.choice(PROGRAMMES, size=k, replace=False)]

    reps = 1 if quick else 2
    for noise in noises:
        for rep in range(reps + 1):
            seed += 1
            out.append({"group": "clean", "effects": [], "noise": noise, "seed": seed, "kinds": kinds()})
    for eff in EFFECTS:
        for noise in noises:
            for rep in range(reps):
                seed += 1
                out.append({"group": "single", "effects": [eff], "noise": noise, "seed": seed, "kinds": kinds()})
    for a, b in itertools.combinations(EFFECTS, 2):
        seed += 1
        out.append({"group": "pair", "effects": [a, b], "noise": "mid", "seed": seed, "kinds": kinds()})
    for ctrl in ("hum", "sensor_drift"):
        for noise in ("low", "mid"):
            seed += 1
            out.append({"group": "control", "effects": [ctrl], "noise": noise, "seed": seed, "kinds": kinds()})
    # one channel only
    for eff, chans in (("creep", ("x",)), ("time_delay", ("us",)), ("sensor_leakage", ("us",)),
                       ("extra_resonance", ("x",))):
        seed += 1
        out.append({"group": "one channel", "effects": [eff], "noise": "mid", "seed": seed, "kinds": kinds(),
                    "channels": list(chans)})
    if quick:
        out = out[::3]
    return out


def _visibility(spec, case):
    """Per true mechanism: rms change of the clean outputs it causes, over the noise (max over channels)."""
    from scipy.ndimage import uniform_filter1d

    from ..model import load_model
    from ..simulate import Signal, simulate

    vis = {}
    ref = load_model()
    plant = case.truth["plant"]
    for eff in spec["effects"]:
        if eff not in EFFECTS:
            continue
        off = plant.copy()
        if eff == "hysteresis_shape":       # the added operators sit between the nominal ones
            h = plant["hysteresis"]
            off.set("hysteresis", "thresholds", h["thresholds"][::2], "off")
            off.set("hysteresis", "weights", h["weights"][::2], "off")
        for key in {"creep": [("creep", "gains"), ("creep", "time_constants")],
                    "sensor_leakage": [("sensor", "tau_leak")],
                    "amplifier_current_limit": [("amplifier", "I_max")],
                    "time_delay": [("amplifier", "delay")],
                    "extra_resonance": [("resonance", "f_n")],
                    "thermal_drift": [("drift", "rate"), ("drift", "curvature")],
                    "hysteresis_shape": []}[eff]:
            off.set(key[0], key[1], ref[key[0]][key[1]], "off")
        sig = Signal("table", t=case.t, values=case.u, column="u")
        a = simulate(plant, sig, float(case.t[-1]), step=1 / case.truth["fs"], mode="open", noise=False)
        b = simulate(off, sig, float(case.t[-1]), step=1 / case.truth["fs"], mode="open", noise=False)
        v = 0.0
        fs = case.truth["fs"]
        w = max(3, round(0.05 * fs))
        for c in spec.get("channels", ["x", "us"]):
            d = a[c] - b[c]
            d = d - np.mean(d)
            local = np.sqrt(uniform_filter1d(d * d, w))          # rms over 50 ms windows
            v = max(v, float(np.max(local)) / case.truth["noise"][c])
        vis[eff] = v
    return vis


def run_case(spec):
    import warnings

    from .run import analyse
    from .synth import make_case

    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    case = make_case(spec["seed"], spec["effects"], spec["noise"], spec["kinds"],
                     channels=tuple(spec.get("channels", ("x", "us"))))
    raw = [{"name": f"case{spec['seed']}", "time": case.t, "u": case.u, "x": case.x, "us": case.us}]
    try:
        diag = analyse(raw)
        res = diag.result
        named = [f["effect"] for f in res["findings"]]
        out = {"named": named, "confidence": {f["effect"]: f["confidence"] for f in res["findings"]},
               "unexplained": len(res["unexplained"]), "verdict": res["final"]["verdict"],
               "rmse_before": res["baseline"]["rmse"], "rmse_after": res["final"]["rmse"],
               "noise_est": res["baseline"]["noise"], "error": None}
    except Exception as exc:  # noqa: BLE001 - a crash is a result too, counted and reported
        out = {"named": [], "confidence": {}, "unexplained": 0, "verdict": "", "error": repr(exc)}
    out["seconds"] = time.perf_counter() - t0
    out["visibility"] = _visibility(spec, case)
    out["truth_params"] = case.truth["parameters"]
    out["programme"] = case.truth["programme"]
    return {**spec, **out}


def summarise(results):
    catalogue = list(EFFECTS)
    s = {"cases": len(results), "by_effect": {}, "by_noise": {}, "by_group": {}}
    tp = fn = tp_vis = n_vis = 0
    fp_cases = 0
    fp_names = 0
    opportunities = 0
    for r in results:
        truth = [e for e in r["effects"] if e in EFFECTS]
        wrong = [n for n in r["named"] if n not in truth]
        fp_cases += bool(wrong)
        fp_names += len(set(wrong))
        opportunities += len([c for c in catalogue if c not in truth])
        g = s["by_group"].setdefault(r["group"], {"cases": 0, "all_right": 0, "false_positive_cases": 0,
                                                  "true": 0, "recognised": 0, "described_unexplained": 0})
        g["cases"] += 1
        g["false_positive_cases"] += bool(wrong)
        g["all_right"] += (sorted(set(r["named"])) == sorted(truth))
        g["described_unexplained"] += bool(r.get("unexplained"))
        nz = s["by_noise"].setdefault(r["noise"], {"true": 0, "recognised": 0, "cases": 0, "fp_cases": 0})
        nz["cases"] += 1
        nz["fp_cases"] += bool(wrong)
        for e in truth:
            hit = e in r["named"]
            vis = r["visibility"].get(e, 0.0) >= 2.0
            tp += hit
            fn += not hit
            n_vis += vis
            tp_vis += hit and vis
            g["true"] += 1
            g["recognised"] += hit
            nz["true"] += 1
            nz["recognised"] += hit
            be = s["by_effect"].setdefault(e, {"true": 0, "recognised": 0, "visible": 0, "visible_recognised": 0,
                                               "named_wrongly": 0})
            be["true"] += 1
            be["recognised"] += hit
            be["visible"] += vis
            be["visible_recognised"] += hit and vis
        for n in set(wrong):
            be = s["by_effect"].setdefault(n, {"true": 0, "recognised": 0, "visible": 0, "visible_recognised": 0,
                                               "named_wrongly": 0})
            be["named_wrongly"] += 1
    conf_true = [r["confidence"][n] for r in results for n in set(r["named"]) if n in r["effects"]]
    conf_false = [r["confidence"][n] for r in results for n in set(r["named"]) if n not in r["effects"]]
    s["confidence_true_names"] = float(np.mean(conf_true)) if conf_true else None
    s["confidence_false_names"] = float(np.mean(conf_false)) if conf_false else None
    s["recognition_rate"] = tp / max(tp + fn, 1)
    s["recognition_rate_visible"] = tp_vis / max(n_vis, 1)
    s["false_positive_case_rate"] = fp_cases / max(len(results), 1)
    s["false_names_per_opportunity"] = fp_names / max(opportunities, 1)
    s["errors"] = sum(1 for r in results if r.get("error"))
    s["median_seconds"] = float(np.median([r["seconds"] for r in results])) if results else 0.0
    return s


def _pct(a, b):
    return f"{100 * a / b:.0f} % ({a}/{b})" if b else "-"


def markdown(s, results):
    lines = ["| mechanism | recognised | recognised when visible (effect > 2 x noise over 50 ms somewhere) | named where absent (cases) |",
             "|---|---|---|---|"]
    for e in EFFECTS:
        b = s["by_effect"].get(e)
        if not b:
            continue
        lines.append(f"| {e} | {_pct(b['recognised'], b['true'])} | {_pct(b['visible_recognised'], b['visible'])} | "
                     f"{b['named_wrongly']} |")
    lines += ["", "| case group | cases | exactly right | recognised (true mechanisms) | cases with a false name |",
              "|---|---|---|---|---|"]
    for g, b in s["by_group"].items():
        lines.append(f"| {g} | {b['cases']} | {_pct(b['all_right'], b['cases'])} | {_pct(b['recognised'], b['true'])} | "
                     f"{_pct(b['false_positive_cases'], b['cases'])} |")
    lines += ["", "| noise (x [um], us [V]) | recognised | cases with a false name |", "|---|---|---|"]
    for nz, b in s["by_noise"].items():
        sx, su = NOISE[nz]
        lines.append(f"| {nz} ({sx:g}, {su:g}) | {_pct(b['recognised'], b['true'])} | {_pct(b['fp_cases'], b['cases'])} |")
    lines += ["", (f"Overall: recognition rate {100 * s['recognition_rate']:.0f} % "
                   f"({100 * s['recognition_rate_visible']:.0f} % of the visible mechanisms); "
                   f"false-positive rate {100 * s['false_positive_case_rate']:.0f} % of cases "
                   f"({100 * s['false_names_per_opportunity']:.1f} % of the chances to name a wrong mechanism); "
                   f"{s['cases']} cases, median {s['median_seconds']:.1f} s per case, {s['errors']} errors. "
                   + (f"Mean confidence of the right names {s['confidence_true_names']:.2f}"
                      if s["confidence_true_names"] is not None else "")
                   + (f", of the wrong ones {s['confidence_false_names']:.2f}."
                      if s["confidence_false_names"] is not None else "."))]
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m piezo_fmu.diagnose.evaluate", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--quick", action="store_true", help="a third of the cases")
    ap.add_argument("--only", default="", help="comma-separated case groups to run")
    ap.add_argument("--out", help="write all results as JSON")
    ap.add_argument("--markdown", help="write the tables as markdown")
    a = ap.parse_args(argv)
    specs = cases(a.quick)
    if a.only:
        keep = set(a.only.split(","))
        specs = [c for c in specs if c["group"] in keep]
    t0 = time.perf_counter()
    results = []
    if a.jobs > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(a.jobs) as pool:
            for i, r in enumerate(pool.imap_unordered(run_case, specs)):
                results.append(r)
                _progress(i, len(specs), r, t0)
    else:
        for i, spec in enumerate(specs):
            r = run_case(spec)
            results.append(r)
            _progress(i, len(specs), r, t0)
    results.sort(key=lambda r: r["seed"])
    s = summarise(results)
    table = markdown(s, results)
    print(table)
    if a.out:
        Path(a.out).write_text(json.dumps({"summary": s, "results": results}, indent=1, default=_default))
    if a.markdown:
        Path(a.markdown).write_text(table + "\n")
    return 0


def _default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _progress(i, n, r, t0):
    truth = "+".join(r["effects"]) or "clean"
    named = "+".join(r["named"]) or "-"
    mark = "ok" if sorted(set(r["named"])) == sorted(e for e in r["effects"] if e in EFFECTS) else "XX"
    vis = ",".join(f"{k}:{v:.1f}" for k, v in r["visibility"].items())
    print(f"[{i + 1}/{n} {time.perf_counter() - t0:6.0f} s] {mark} {r['group']:<11} {r['noise']:<4} truth {truth:<45} "
          f"named {named:<40} vis {vis} ({r['seconds']:.0f} s){' ERROR ' + r['error'] if r.get('error') else ''}",
          file=sys.stderr, flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
