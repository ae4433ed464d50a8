"""Scoring a recognition study: what diagnose named against what the generator put in.

Every case result carries ``truth`` (the catalogue mechanisms present and visible), ``hidden``
(present but too small to see: naming one is not a false name, missing one is no miss), the
case ``group`` (clean, single, pair, control, one channel), ``named`` (``final.effects``), the
``candidates`` (weaker findings, with confidence) and the verdict. Reported:

* **recognised**: visible true mechanisms named, over all visible true mechanisms;
* **false names**: cases with a name that is neither true nor hidden (a control's name never is);
* **nothing is missing**: clean cases with that verdict;
* **how a miss ends**: a visible true mechanism not named is reported as a candidate (below the
  naming confidence), or its case ends with a structured residual flagged as unexplained, or the
  case says "nothing is missing" (a *silent* miss: the recalibrated ordinary physics, or another
  mechanism, absorbed it down to the noise, so the recording gave no sign of it to a user);
* **confidence calibration**: every reported mechanism (findings and candidates) by confidence
  band, and how often it was right (true or hidden);
* per mechanism and per group;
* with ``ceiling`` results (the evaluation's ``--ceiling``): per mechanism, how many misses pass
  the tests when put into the final model afterwards, and the first test that refused the others;
* **ordinary twins**, where the generator measures them (the rig's ``ordinary_twins``: a present
  mechanism whose record the device's ordinary physics, re-tuned, draws to within 3 noise rms - a
  further mode as the first mode at its frequency, a delay as a slower amplifier or one channel's
  sampling lag): how many true mechanisms have one, how many of those were named, and recognition
  over the others (the share a diagnosis can be held to; the headline rate stays over all);
* per kind of a mechanism, where the generator says which kind it put in (the rig's loop-shape
  features: a width that depends on the level, a cluster of KP cells, a high-field knee; a result's
  ``variants`` maps a mechanism to its kind). The kinds matter because the catalogue's
  ``hysteresis_shape`` draws its loop with KP cells: the rig's cell cluster is of the same family,
  the other two are not.
"""
from __future__ import annotations

import re

import numpy as np

__all__ = ["BANDS", "markdown", "summarise"]

BANDS = ((0.0, 0.25), (0.25, 0.5), (0.5, 0.75), (0.75, 0.9), (0.9, 1.0001))
GROUPS = ("clean", "single", "pair", "control", "one channel")


def _pct(a, b):
    return f"{100 * a / b:.0f} % ({a}/{b})" if b else "-"


def _effect_row():
    # a miss not counted as a candidate or silent ends in a flagged residual
    return {"true": 0, "recognised": 0, "named_wrongly": 0, "candidate": 0, "silent": 0, "twin": 0}


def _reason(why):
    """The first test a refused candidate failed, without its figures (for counting)."""
    head = (why or "no reason given").split(";")[0].split("(")[0].split("[")[0]
    head = re.sub(r"(?<![\w.])[-+]?\d[\d.]*(e[-+]?\d+)?( ?(Hz|%|ms|s|um|V)(?!\w))?", "", head)
    head = re.sub(r"\s+", " ", head).replace(" :", ":").replace(" =", "").strip(" :=<>,.")
    return head[:70]


def summarise(results, catalogue):
    s = {"cases": len(results), "by_effect": {}, "by_group": {}, "by_variant": {}, "calibration": []}
    tp = fn = fp_cases = silent_cases = 0
    twin_true = twin_hit = 0
    measured = any("twins" in r for r in results)
    reported = []
    for r in results:
        truth, hidden = set(r["truth"]), set(r.get("hidden", []))
        named = set(r["named"])
        wrong = named - truth - hidden
        fp_cases += bool(wrong)
        g = s["by_group"].setdefault(r["group"], {"cases": 0, "all_right": 0, "false_name_cases": 0, "true": 0,
                                                 "recognised": 0, "nothing_missing": 0, "errors": 0})
        g["cases"] += 1
        g["false_name_cases"] += bool(wrong)
        g["all_right"] += (named - hidden == truth)
        g["nothing_missing"] += bool(r.get("nothing_missing"))
        g["errors"] += bool(r.get("error"))
        cands = r.get("candidates", {})
        # missed, not even a candidate, under a "nothing is missing" verdict
        silent = {e for e in truth - named if e not in cands} if r.get("nothing_missing") else set()
        silent_cases += bool(silent)
        for e in truth:
            hit = e in named
            tp += hit
            fn += not hit
            twin = ((r.get("twins") or {}).get(e) or {}).get("same", False)
            twin_true += twin
            twin_hit += twin and hit
            g["true"] += 1
            g["recognised"] += hit
            be = s["by_effect"].setdefault(e, _effect_row())
            be["true"] += 1
            be["recognised"] += hit
            be["candidate"] += (not hit) and e in cands
            be["silent"] += e in silent
            be["twin"] += twin
            kind = (r.get("variants") or {}).get(e)
            if kind:
                bv = s["by_variant"].setdefault(f"{e}: {kind}", {"true": 0, "recognised": 0})
                bv["true"] += 1
                bv["recognised"] += hit
        for e in wrong:
            s["by_effect"].setdefault(e, _effect_row())["named_wrongly"] += 1
        for e, c in (r.get("ceiling") or {}).items():
            bc = s.setdefault("ceiling", {}).setdefault(e, {"missed": 0, "passes": 0, "why": {}})
            bc["missed"] += 1
            bc["passes"] += bool(c["passes"])
            if not c["passes"]:
                reason = _reason(c["why"])
                bc["why"][reason] = bc["why"].get(reason, 0) + 1
        for e, c in list(r.get("confidence", {}).items()) + list(r.get("candidates", {}).items()):
            reported.append((c, e in truth or e in hidden, e in named))
    for lo, hi in BANDS:
        rows = [(c, right) for c, right, _ in reported if lo <= c < hi]
        s["calibration"].append({"band": [lo, min(hi, 1.0)], "reported": len(rows),
                                 "right": sum(1 for _, ok in rows if ok),
                                 "mean_confidence": float(np.mean([c for c, _ in rows])) if rows else None})
    named_rows = [(c, right) for c, right, is_named in reported if is_named]
    s["named_right"] = sum(1 for _, ok in named_rows if ok)
    s["named_total"] = len(named_rows)
    s["recognition_rate"] = tp / max(tp + fn, 1)
    if measured:
        s["twins"] = {"true": twin_true, "recognised": twin_hit,
                      "others_true": tp + fn - twin_true, "others_recognised": tp - twin_hit}
        s["recognition_rate_beyond_twins"] = (tp - twin_hit) / max(tp + fn - twin_true, 1)
    s["false_name_case_rate"] = fp_cases / max(len(results), 1)
    s["silent_miss_case_rate"] = silent_cases / max(len(results), 1)
    clean = s["by_group"].get("clean", {})
    s["clean_nothing_missing_rate"] = clean.get("nothing_missing", 0) / max(clean.get("cases", 0), 1)
    ctrl = s["by_group"].get("control", {})
    s["controls_named"] = ctrl.get("false_name_cases", 0)
    s["errors"] = sum(1 for r in results if r.get("error"))
    secs = [r["seconds"] for r in results]
    s["median_seconds"] = float(np.median(secs)) if secs else 0.0
    s["max_seconds"] = float(np.max(secs)) if secs else 0.0
    s["catalogue"] = list(catalogue)
    return s


def markdown(s, title=""):
    lines = []
    if title:
        lines += [f"**{title}**", ""]
    lines += ["| mechanism | recognised | named where absent (cases) | missed: a candidate | missed: residual "
              "flagged | missed silently |", "|---|---|---|---|---|---|"]
    for e in s["catalogue"]:
        b = s["by_effect"].get(e)
        if not b:
            continue
        missed = b["true"] - b["recognised"]
        lines.append(f"| {e} | {_pct(b['recognised'], b['true'])} | {b['named_wrongly']} | {b['candidate']} | "
                     f"{missed - b['candidate'] - b['silent']} | {b['silent']} |")
    if s.get("by_variant"):
        lines += ["", "| mechanism: kind put in | recognised |", "|---|---|"]
        lines += [f"| {k} | {_pct(b['recognised'], b['true'])} |" for k, b in sorted(s["by_variant"].items())]
    if s.get("ceiling"):
        lines += ["", "| mechanism | missed | put in afterwards: passes the tests | refused: first failed test (cases) |",
                  "|---|---|---|---|"]
        for e in s["catalogue"]:
            b = s["ceiling"].get(e)
            if b:
                why = "; ".join(f"{k} ({v})" for k, v in sorted(b["why"].items(), key=lambda kv: -kv[1]))
                lines.append(f"| {e} | {b['missed']} | {_pct(b['passes'], b['missed'])} | {why or '-'} |")
    lines += ["", "| case group | cases | exactly right | recognised | cases with a false name | \"nothing is missing\" |",
              "|---|---|---|---|---|---|"]
    for g in GROUPS:
        b = s["by_group"].get(g)
        if not b:
            continue
        nm = _pct(b["nothing_missing"], b["cases"]) if g in ("clean", "control") else "-"
        lines.append(f"| {g} | {b['cases']} | {_pct(b['all_right'], b['cases'])} | {_pct(b['recognised'], b['true'])} | "
                     f"{_pct(b['false_name_cases'], b['cases'])} | {nm} |")
    lines += ["", "| confidence | reported (findings and candidates) | right | mean confidence |", "|---|---|---|---|"]
    for row in s["calibration"]:
        lo, hi = row["band"]
        mc = f"{row['mean_confidence']:.2f}" if row["mean_confidence"] is not None else "-"
        lines.append(f"| {lo:.2f}-{hi:.2f} | {row['reported']} | {_pct(row['right'], row['reported'])} | {mc} |")
    tw = s.get("twins")
    if tw:
        per = ", ".join(f"{e} {b['twin']}" for e in s["catalogue"] if (b := s["by_effect"].get(e)) and b["twin"])
        lines += ["", (f"Ordinary twins (the generator's own equations: the mechanism out, an ordinary parameter "
                       f"re-tuned in its place, within 3 noise rms of the record): {tw['true']} of the "
                       f"{tw['true'] + tw['others_true']} true mechanisms ({per or 'none'}), "
                       f"{tw['recognised']} of them named; recognised among the others "
                       f"{_pct(tw['others_recognised'], tw['others_true'])}.")]
    lines += ["", (f"Overall: recognised {100 * s['recognition_rate']:.0f} %; cases with a false name "
                   f"{100 * s['false_name_case_rate']:.1f} %; clean cases \"nothing is missing\" "
                   f"{100 * s['clean_nothing_missing_rate']:.0f} %; cases with a silent miss (a true "
                   f"mechanism missed where the verdict is \"nothing is missing\") "
                   f"{100 * s['silent_miss_case_rate']:.1f} %; controls named {s['controls_named']}; named "
                   f"mechanisms right {_pct(s['named_right'], s['named_total'])}; {s['cases']} cases, "
                   f"{s['errors']} errors; seconds per case median {s['median_seconds']:.1f}, "
                   f"max {s['max_seconds']:.1f}.")]
    return "\n".join(lines)
