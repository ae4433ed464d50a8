"""Recognition studies: run diagnose blind on concealed recordings and count what it names.

``python -m piezo_fmu.diagnose.evaluate [--generator synth|rig|both] [--quick] [--draw K] [--jobs 2]
[--scheduler tcp://HOST:PORT] [--only GROUPS] [--cases NAMES] [--ceiling] [--logs DIR]
[--replay-rate HZ] [--out eval.json]
[--markdown table.md]``

Two generators:

* ``rig`` - :mod:`piezo_fmu.rig`, written independently of diagnose: its own plant (other
  hysteresis families, its own mechanics, pick-offs, amplifier, noise), excitation programmes and
  case set with ground truth (which mechanisms are visible, which hidden). Used as a black box
  through ``cases``, ``generate`` and the truth it returns.
* ``synth`` - :mod:`.synth`, the project's own generator (the core's model plus mechanisms).

The cases run on :mod:`piezo_fmu.parallel` (dask.distributed: a local cluster, or the cluster at
``--scheduler``). Scoring: :mod:`.scoring`.

The synth cases (deterministic, seeded) cover every catalogue mechanism alone at three noise levels and
two parameter draws, every pair of mechanisms, clean recordings (nothing to find), and negative
controls (mechanisms the catalogue does not have: mains hum on the displacement, a drifting sensor
offset). Each case draws its own excitation programme: 2-4 of sine sets (0.5-50 Hz), steps and
holds, decaying triangles and chirps, in random order. diagnose sees only the recording.

Reported:

* **recognition rate** - visible true mechanisms that were named, over all visible ones. Both
  generators use the rig's rule: a mechanism is raised within its physical range until what it
  changes beyond a channel's gain and offset is 3 noise rms over the record (a loop shape: until
  the best nominal-threshold PI misses it by 3 noise rms); one still below that is *hidden*
  (naming it is no false name, missing it no miss; the synth cases report how many);
* on the rig, the true mechanisms with an *ordinary twin* (the rig's own equations draw the same
  record, to within 3 noise rms, with the mechanism out and ordinary physics re-tuned: a further
  mode as the first mode at its frequency, a delay as a slower amplifier or one channel's
  sampling lag) and recognition over the others beside the rate over all;
* **false names** - cases with at least one name that is neither true nor hidden;
* for the controls, how often the structured residual was described as unexplained;
* with ``--ceiling``, for every miss: put into the final model after the diagnosis, does it pass
  the tests (the selection lost it) or not (why the tests refuse it even when told to look)?
"""
from __future__ import annotations

import argparse
import functools
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np

from .scoring import markdown, summarise
from .synth import EFFECTS, PROGRAMMES, VISIBLE

__all__ = ["cases", "main", "rig_cases", "run_case", "run_rig_case"]


def cases(quick=False, draw=0):
    """The list of case specifications (dicts); ``draw`` >= 1: the same composition on fresh seeds
    (``synth-<1000 (draw + 1) + k>``, cases no rule of diagnose was tuned on)."""
    out = []
    seed = 1000 * (draw + 1)
    noises = ("low", "mid", "high")
    rng = np.random.default_rng(7 + draw)

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
    """Per true mechanism: what it changes beyond a channel's gain and offset, in noise rms (the
    generator raised it to at least ``synth.VISIBLE`` within its range; the loop shape: the best
    nominal-threshold PI's misfit)."""
    return dict(case.truth["visibility"])


def _outcome(res):
    named = list(res["final"]["effects"])
    return {"named": named,
            "confidence": {f["effect"]: f["confidence"] for f in res["findings"]},
            "candidates": {c["effect"]: c["confidence"] for c in res.get("candidates", [])},
            "nothing_missing": bool(res["final"]["nothing_missing"]), "verdict": res["final"]["verdict"],
            "rmse_before": res["baseline"]["rmse"], "rmse_after": res["final"]["rmse"],
            "noise_est": res["baseline"]["noise"],
            "recalibrated": res["baseline"]["recalibrated"],
            "parameters": {f["effect"]: f["parameters"] for f in res["findings"]},
            "timing": res.get("timing_s"), "error": None,
            # what each confidence was made of (decide.confidence's factors), to study its calibration
            "evidence": {f["effect"]: {k: f["evidence"][k] for k in _EVIDENCE}
                         for f in res["findings"] + res.get("candidates", [])}}


_EVIDENCE = ("explained_share", "explained_share_heldout", "heldout_beta", "heldout_z", "delta_bic",
             "strongest_alternative")


def _ceiling(diag, missed):
    """Each missed mechanism put into the final model and searched, fitted and tested as a round
    would (:func:`.select.put_in`): ``passes`` says the recording shows it to the tool's tests (the
    miss is the selection's: its order, a rival, the confidence, the budget); a failure says why the
    tests refuse it even when told to look. Run after the diagnosis: the truth never reaches it."""
    from .decide import confidence
    from .select import put_in

    sr = diag.search
    loop = sr["recal"].report.get("loop", {})
    out = {}
    for name in missed:
        if name == "hysteresis_shape" and diag.struct_final.refined and loop.get("refined"):
            # the finer loop was tried and taken into the recalibration: that was its test
            out[name] = {"passes": False, "explained": loop.get("explained_share"),
                         "why": f"taken into the recalibration as an ordinary loop difference (it removed "
                                f"{loop.get('removed_noise_multiples')} noise rms, explaining "
                                f"{100 * loop.get('explained_share', 0):.0f} % of the structured residual)"}
            continue
        t = put_in(sr["fitter"], name, diag.p_final, diag.struct_final, diag.p_nominal, sr["noise"], sr["cctx"],
                   sr["recal"])
        if t is None:
            out[name] = {"passes": False, "why": "no start proposed for it in this recording"}
            continue
        ch = t["cmp"]["channels"].values()
        out[name] = {"passes": bool(t["passed"]), "why": t["why"] or "",
                     "explained": max(v["explained"] for v in ch), "dbic": t["cmp"].get("dbic"),
                     "confidence": confidence(t["cmp"], name) if t["passed"] else 0.0}
    return out


def _diagnose(raw, truth=None, log=None, replay_rate=None):
    """Diagnose ``raw`` blind; with ``truth`` (the visible true mechanisms, given only for the
    post-mortem, after the diagnosis is complete) also the ``ceiling`` of each miss. ``log``: a
    file the diagnosis's progress lines (every screening, fit and decision) are written to."""
    import warnings

    from .run import analyse

    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    seconds = None
    lines = []
    try:
        diag = analyse(raw, say=lines.append if log else None, replay_rate=replay_rate)
        seconds = time.perf_counter() - t0            # the diagnosis alone
        out = _outcome(diag.result)
        if truth is not None:
            missed = [e for e in truth if e not in out["named"]]
            out["ceiling"] = _ceiling(diag, missed) if missed else {}
            out["ceiling_seconds"] = time.perf_counter() - t0 - seconds
    except Exception as exc:  # noqa: BLE001 - a crash is a result too, counted and reported
        out = {"named": [], "confidence": {}, "candidates": {}, "nothing_missing": False, "verdict": "",
               "error": repr(exc)}
        lines.append(f"ERROR {exc!r}")
    out["seconds"] = seconds if seconds is not None else time.perf_counter() - t0
    if log:
        Path(log).write_text("\n".join(lines) + "\n")
    return out


def _log_file(logs, name):
    return None if logs is None else str(Path(logs) / f"{name}.log")


def run_case(spec, ceiling=False, logs=None, replay_rate=None, noise_draw=0):
    """One synth case: generate, diagnose blind, score against the truth (``ceiling``: and put each
    miss in afterwards, see :func:`_ceiling`; ``logs``: a folder for the diagnosis's progress log;
    ``noise_draw``: the rig's only, 0 here: :func:`study` refuses another)."""
    from .synth import make_case

    case = make_case(spec["seed"], spec["effects"], spec["noise"], spec["kinds"],
                     channels=tuple(spec.get("channels", ("x", "us"))))
    raw = [{"name": f"case{spec['seed']}", "time": case.t, "u": case.u, "x": case.x, "us": case.us}]
    visible = [e for e in spec["effects"] if e in EFFECTS and case.truth["visibility"][e] >= VISIBLE]
    out = _diagnose(raw, visible if ceiling else None, _log_file(logs, f"synth-{spec['seed']}"), replay_rate)
    out["visibility"] = _visibility(spec, case)
    # a mechanism still below visibility at the end of its range is hidden, as in the rig: naming it
    # is no false name, missing it no miss
    present = [e for e in spec["effects"] if e in EFFECTS]
    out["truth"] = [e for e in present if out["visibility"][e] >= VISIBLE]
    out["hidden"] = [e for e in present if out["visibility"][e] < VISIBLE]
    out["control"] = next((e for e in spec["effects"] if e not in EFFECTS), None)
    out["case"] = f"synth-{spec['seed']}"
    out["n_samples"] = int(case.t.size)
    out["truth_params"] = case.truth["parameters"]
    out["programme"] = case.truth["programme"]
    return {**spec, **out}


def rig_cases(quick=False, draw=0):
    """The rig's concealed cases (its own specs; ``draw`` >= 1: the same composition on fresh seeds)."""
    from .. import rig

    return list(rig.cases(quick=quick, draw=draw))


def run_rig_case(spec, ceiling=False, logs=None, replay_rate=None, noise_draw=0):
    """One rig case: the rig generates it (its truth stays here), diagnose sees the recording only
    (``ceiling``: each miss is put in afterwards, see :func:`_ceiling`; ``logs``: a folder for the
    diagnosis's progress log; ``noise_draw`` k >= 1: the same device and truth with another
    realisation of its noise, see :func:`piezo_fmu.rig.generate`)."""
    from .. import rig

    rec = rig.generate(spec, twins=True, noise_draw=noise_draw)
    raw = [{"name": str(rec.truth.get("case_id", "case")), "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}]
    out = _diagnose(raw, list(rec.truth.get("mechanisms", [])) if ceiling else None, _log_file(logs, spec.case_id),
                    replay_rate)
    t = rec.truth
    params = t.get("params", {})                 # the device's own loop family and its shape feature
    shape = params.get("hysteresis_shape.variant", {}).get("value")
    group = str(t.get("group", "")).replace("_", " ")
    out.update({"case": t.get("case_id"), "group": group, "truth": list(t.get("mechanisms", [])),
                "hidden": list(t.get("hidden", [])), "control": t.get("control"),
                "n_samples": int(np.size(rec.time)), "fs": t.get("fs"),
                "visibility": t.get("visibility"), "channels": t.get("channels"),
                "family": params.get("hysteresis.family", {}).get("value"),
                "twins": t.get("ordinary_twins", {}),
                "variants": {"hysteresis_shape": shape} if shape else {}})
    return out


GENERATORS = {"synth": (cases, run_case), "rig": (rig_cases, run_rig_case)}


def _case_line(r, done, n, t0):
    truth = "+".join(r["truth"]) or ("clean" if not r.get("control") else f"control {r['control']}")
    named = "+".join(r["named"]) or "-"
    ok = set(r["named"]) - set(r.get("hidden", [])) == set(r["truth"])
    cand = ",".join(f"{k}:{v:.2f}" for k, v in r.get("candidates", {}).items())
    return (f"[{done}/{n} {time.perf_counter() - t0:6.0f} s] {'ok' if ok else 'XX'} {r['case']:<12} {r['group']:<11} "
            f"truth {truth:<40} named {named:<36} {('cand ' + cand) if cand else ''} "
            f"({r['seconds']:.0f} s, {r.get('n_samples', 0)} samples)"
            + "".join(f" | put in afterwards: {e} {'passes' if c['passes'] else 'refused (' + c['why'][:80] + ')'}"
                      for e, c in (r.get("ceiling") or {}).items())
            + (f" ERROR {r['error']}" if r.get("error") else ""))


def study(generator, quick=False, jobs=None, scheduler=None, only=None, log=None, ceiling=False, cases_=None,
          draw=0, logs=None, replay_rate=None, noise_draw=0):
    """Run one generator's cases; returns ``(summary, results)``. ``only``: case groups to run;
    ``cases_``: case names to run; ``ceiling``: put each miss in afterwards (:func:`_ceiling`);
    ``draw``: 0 the established set, k >= 1 the same composition on fresh seeds; ``logs``: a folder
    each case's progress log is written to (``<case>.log``); ``replay_rate`` [Hz]: see
    :func:`.run.analyse`; ``noise_draw`` k >= 1 (the rig only): each case with another realisation of
    its noise (what a repeated measurement of the same device would give)."""
    from ..parallel import map_as_completed

    make, run = GENERATORS[generator]
    if logs:
        logs = Path(logs).resolve()
        logs.mkdir(parents=True, exist_ok=True)
    if noise_draw and generator != "rig":
        raise ValueError(f"a noise redraw is the rig's: the {generator} cases have one noise realisation each")
    run = functools.partial(run, ceiling=ceiling, logs=None if logs is None else str(logs), replay_rate=replay_rate,
                            noise_draw=noise_draw)
    specs = make(quick, draw)
    if only:
        keep = set(only)
        specs = [c for c in specs if (c["group"] if isinstance(c, dict) else c.group) in keep]
    if cases_:
        keep = set(cases_)
        specs = [c for c in specs if (f"synth-{c['seed']}" if isinstance(c, dict) else c.case_id) in keep]
        unknown = keep - {f"synth-{c['seed']}" if isinstance(c, dict) else c.case_id for c in specs}
        if unknown:
            raise ValueError(f"no {generator} case named {', '.join(sorted(unknown))}")
    t0 = time.perf_counter()
    results = []
    for i, (_, r) in enumerate(map_as_completed(run, specs, scheduler=scheduler, workers=jobs,
                                                 errors="raise", target_task_s=60.0, max_batch=1)):
        results.append(r)
        if log:
            log(_case_line(r, i + 1, len(specs), t0))
    results.sort(key=lambda r: str(r["case"]))
    catalogue = EFFECTS
    return summarise(results, catalogue), results


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m piezo_fmu.diagnose.evaluate", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--generator", choices=("synth", "rig", "both"), default="both")
    ap.add_argument("--jobs", type=int, default=None, help="local worker processes (default: one per core; "
                                                           "0 runs in this process)")
    ap.add_argument("--scheduler", default=None, metavar="ADDRESS",
                    help="run on an existing dask.distributed cluster (tcp://HOST:PORT)")
    ap.add_argument("--quick", action="store_true", help="the generators' smaller case sets")
    ap.add_argument("--draw", type=int, default=0, metavar="K",
                    help="0 (default): the established sets; K >= 1: the same composition drawn afresh from "
                         "other seeds - cases no rule of diagnose was tuned on")
    ap.add_argument("--only", default="", help="comma-separated case groups to run")
    ap.add_argument("--cases", default="", help="comma-separated case names to run (rig-017, synth-1046, ...)")
    ap.add_argument("--ceiling", action="store_true",
                    help="after each diagnosis, put every missed mechanism into the final model and run the "
                         "tests on it: does the recording show it when the tool is told to look?")
    ap.add_argument("--logs", metavar="DIR", help="write each case's diagnosis log (every screening, fit and "
                                                 "decision) to DIR/<case>.log (on the machine that runs the case)")
    ap.add_argument("--replay-rate", type=float, default=None, metavar="HZ",
                    help="replay recordings sampled slower with internal steps up to HZ (diagnose --replay-rate)")
    ap.add_argument("--noise-draw", type=int, default=0, metavar="K",
                    help="the rig only: 0 (default) each case's own noise; K >= 1 the same devices and truth "
                         "with another realisation of their noise (how much the outcome of a case depends "
                         "on the noise it happened to get)")
    ap.add_argument("--out", help="write all results as JSON")
    ap.add_argument("--markdown", help="write the tables as markdown")
    a = ap.parse_args(argv)
    if a.replay_rate is not None and not 0 < a.replay_rate < float("inf"):
        ap.error(f"--replay-rate {a.replay_rate}: a positive rate in Hz")
    if a.draw < 0:
        ap.error(f"--draw {a.draw}: a draw is 0 (the established sets) or a positive number")
    if a.noise_draw < 0:
        ap.error(f"--noise-draw {a.noise_draw}: 0 (each case's own noise) or a positive number")
    if a.noise_draw and a.generator != "rig":
        ap.error("--noise-draw is the rig's (the synth cases have one noise realisation each): "
                 "add --generator rig")
    gens = ("rig", "synth") if a.generator == "both" else (a.generator,)
    only = [g for g in a.only.split(",") if g] or None
    names = [c for c in a.cases.split(",") if c] or None
    report, tables = {}, []
    if names:
        # a case name says its generator (rig-017, synth-1046)
        stray = [n for n in names if not n.startswith(tuple(f"{g}-" for g in gens))]
        if stray:
            ap.error(f"--cases: {', '.join(stray)} is no case of {' or '.join(gens)}")
        gens = tuple(g for g in gens if any(n.startswith(f"{g}-") for n in names))
    for gen in gens:
        try:
            s, results = study(gen, a.quick, a.jobs, a.scheduler, only,
                               log=lambda line: print(line, file=sys.stderr, flush=True), ceiling=a.ceiling,
                               cases_=[n for n in names if n.startswith(f"{gen}-")] if names else None,
                               draw=a.draw, logs=a.logs, replay_rate=a.replay_rate,
                               noise_draw=a.noise_draw)
        except ValueError as exc:
            ap.error(str(exc))
        report[gen] = {"summary": s, "results": results}
        tables.append(markdown(s, f"{gen}: {s['cases']} cases"))
    text = "\n\n".join(tables)
    print(text)
    if a.out:
        Path(a.out).write_text(json.dumps(report, indent=1, default=_default))
    if a.markdown:
        Path(a.markdown).write_text(text + "\n")
    return 0


def _default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


if __name__ == "__main__":
    raise SystemExit(main())
