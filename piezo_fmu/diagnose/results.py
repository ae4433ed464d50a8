"""The results of a diagnosis: diagnosis.json's content, the model files, the predictions.

:func:`assemble` turns the recalibration, the localisation and the selection into the
``diagnosis.json`` dictionary (every number a plain number with its unit in its key or beside
it); :func:`to_model` writes a parameter set back into a model file with provenance;
:func:`localise` says where a residual lives (time windows, input segments, bands, operating
range); the rest describes what is left unexplained.
"""
from __future__ import annotations

import math

import numpy as np

from . import locate
from .catalogue import CATALOGUE
from .decide import at_bound, removed_rms
from .engine import model_from_params, predict
from .recordings import HELDOUT_EVERY, JUMP, RESPONSE_S
from .select import ACCEPT, CONFIDENT
from .stats import improvement_band, input_xcorr, tau_int, whiteness
from .unexplained import bandpass, describe_band, dominant_freq, range_sentence, trend as slow_trend

__all__ = ["assemble", "below_noise", "describe_parameters", "file_predictions", "localise", "nrmse",
           "rmse_as_given", "to_model"]


def rmse_as_given(recs, dev, p):
    out = {}
    for c in ("x", "us"):
        e = [getattr(r, c)[r.heldout] - predict(r, dev, p)[c][r.heldout] for r in recs if getattr(r, c) is not None]
        if e:
            out[c] = float(np.sqrt(np.mean(np.concatenate(e) ** 2)))
    return out


def localise(recs, fulls, ctxs, noise):
    out = {}
    for c in ("x", "us"):
        per = [(r, f[c], ctx) for r, f, ctx in zip(recs, fulls, ctxs) if c in f]
        if not per:
            continue
        e_all = np.concatenate([e for _, e, _ in per])
        struct_rms = math.sqrt(max(float(np.mean(e_all ** 2)) - noise[c] ** 2, 0.0))
        wins, seg, opr, bands = [], {}, None, []
        for r, e, ctx in per:
            score = np.clip(e * e - noise[c] ** 2, 0.0, None)
            level = max(3.0 * noise[c] ** 2, 0.25 * float(np.mean(score)) + 1e-300)
            for w in locate.windows(score, ctx, level, min_len_s=max(0.02, 0.002 * r.t[-1])):
                sl = slice(w["k0"], w["k1"] + 1)
                wins.append({"recording": r.name, "t0_s": round(r.t0 + w["t0"], 6), "t1_s": round(r.t0 + w["t1"], 6),
                             "rms": float(np.sqrt(np.mean(e[sl] ** 2))),
                             "why": locate.describe_window(ctx, w["k0"], w["k1"])})
            for k, v in locate.segment_rms(e, ctx).items():
                seg.setdefault(k, []).append(v)
            bands += locate.bands(e, r.u, 1 / r.dt, noise[c])
        seg = {k: {"rms": float(np.sqrt(np.mean([x["rms"] ** 2 for x in v]))),
                   "share_of_samples": float(np.mean([x["share_of_samples"] for x in v]))} for k, v in seg.items()}
        r0, e0, ctx0 = per[0]
        opr = locate.operating_range(e0, r0.u, ctx0["rate"])
        wins.sort(key=lambda w: -w["rms"])
        out[c] = {"rms_all_samples": float(np.sqrt(np.mean(e_all ** 2))), "noise": noise[c],
                  "structured_rms": struct_rms, "windows": wins[:6], "segments": seg,
                  "bands": bands[:4], "operating_range": opr}
    return out


def file_predictions(recs, dev, p):
    out = []
    for r in recs:
        pr = predict(r, dev, p)
        out.append({c: r.sign.get(c, 1) * pr[c] for c in ("x", "us")})
    return out


def to_model(base, p, dev, recs, noise, what, sources):
    src = dict(sources)
    if len(p.thresholds) != len(base["hysteresis"]["thresholds"]):
        src[("hysteresis", "thresholds")] = ("diagnose: the nominal thresholds plus their midpoints (a finer loop: "
                                             "hysteresis_shape when named, else refined in the recalibration)")
    if p.n_cells:
        what_cells = ("fitted by piezo-fmu diagnose: KP cells on a Preisach grid over the recorded stack voltages "
                      "(a finer loop: hysteresis_shape when named, else refined in the recalibration)")
        for key in ("cells_up", "cells_down", "cells_width", "cells_weights"):
            src[("hysteresis", key)] = what_cells
    m = model_from_params(base, p, src, dt=min(r.dt for r in recs))
    if dev.u_min < base["amplifier"]["u_min"] or dev.u_max > base["amplifier"]["u_max"]:
        m.set("amplifier", "u_min", float(f"{dev.u_min:.6g}"), "widened by diagnose: the recording's command exceeds the nominal rails")
        m.set("amplifier", "u_max", float(f"{dev.u_max:.6g}"), "widened by diagnose: the recording's command exceeds the nominal rails")
    u_lo = min(float(np.min(r.u)) for r in recs)
    u_hi = max(float(np.max(r.u)) for r in recs)
    c = m["compensator"]
    if u_lo < c["uc_min"] or u_hi > c["uc_max"]:
        m.set("compensator", "uc_min", float(f"{min(c['uc_min'], u_lo - 0.05 * abs(u_lo) - 1e-6):.6g}"),
              "widened by diagnose: the recording's command range")
        m.set("compensator", "uc_max", float(f"{max(c['uc_max'], u_hi + 0.05 * abs(u_hi) + 1e-6):.6g}"),
              "widened by diagnose: the recording's command range")
    if "us" in noise:
        m.set("sensor", "noise_std", float(f"{noise['us']:.4g}"), "estimated by diagnose: white-noise floor of the sensor residual")
    if "x" in noise:
        m.set("measurement", "x_noise_std", float(f"{noise['x']:.4g}"), "estimated by diagnose: white-noise floor of the displacement residual")
    m.set("model", "name", f"{base.name}-diagnosed", "")
    m.set("model", "description", f"{base['model']['description']} ({what}, piezo-fmu diagnose)", "")
    return m.check()


def _heldout_rmse(recs, preds, away=False):
    """Held-out rmse per channel; ``away``: over the held-out samples away from the command's jumps
    (where slow mechanisms are judged, :func:`.recordings.after_jumps`)."""
    out = {}
    for c in ("x", "us"):
        e = []
        for r, pr in zip(recs, preds):
            if getattr(r, c) is None:
                continue
            m = r.heldout & ~r.transient if away and r.transient is not None else r.heldout
            e.append(r.sign.get(c, 1) * getattr(r, c)[m] - pr[c][m])
        if e:
            out[c] = float(np.sqrt(np.mean(np.concatenate(e) ** 2)))
    return out


def nrmse(recs, rmse):
    vals = []
    for c, v in rmse.items():
        y = np.concatenate([getattr(r, c)[r.heldout] for r in recs if getattr(r, c) is not None])
        vals.append(v / max(float(np.std(y)), 1e-300))
    return float(np.sqrt(np.mean(np.square(vals)))) if vals else None


def _where(f, recs, ctxs, dev, noise):
    """Where a finding helped most (windows of the largest reduction of the squared residual),
    and the band of the residual spectrum it removed."""
    mech = CATALOGUE[f["name"]]
    where, band = [], None
    for r, ctx in zip(recs, ctxs):
        pb, pa = predict(r, dev, f["before"]), predict(r, dev, f["after"])
        for c in mech.channels:
            y = getattr(r, c)
            if y is None:
                continue
            e0, e1 = y - pb[c], y - pa[c]
            gain = np.clip(e0 * e0 - e1 * e1, 0.0, None)
            level = max(2.0 * noise[c] ** 2, 0.1 * float(np.max(
                np.convolve(gain, np.ones(max(3, int(0.02 / r.dt))) / max(3, int(0.02 / r.dt)), "same"))))
            for w in locate.windows(gain, ctx, level, min_len_s=max(0.02, 0.002 * r.t[-1]), max_windows=4):
                sl = slice(w["k0"], w["k1"] + 1)
                unit = UNITS[c]
                where.append({"t0_s": round(r.t0 + w["t0"], 6), "t1_s": round(r.t0 + w["t1"], 6),
                              "channel": c, "energy": w["energy"],
                              "why": f"{locate.describe_window(ctx, w['k0'], w['k1'])}; {c} residual rms "
                                     f"{np.sqrt(np.mean(e0[sl] ** 2)):.3g} -> {np.sqrt(np.mean(e1[sl] ** 2)):.3g} {unit}",
                              **({"recording": r.name} if len(recs) > 1 else {})})
            if band is None:
                band = improvement_band(e0, e1, 1 / r.dt)
    where.sort(key=lambda w: -w.pop("energy"))
    return where[:5], band


def _finding(f, recs, ctxs, dev, noise, p_final, struct_final, dt):
    name = f["name"]
    mech = CATALOGUE[name]
    cmp = f["cmp"]
    where, band = _where(f, recs, ctxs, dev, noise)
    return {
        # the channel where it shows most; "channels": every recorded channel it acts on
        "effect": name, "channel": max((c for c in mech.channels if c in cmp["channels"]),
                                       key=lambda c: cmp["channels"][c]["explained"]),
        "channels": [c for c in mech.channels if c in cmp["channels"]],
        "confidence": round(f["confidence"], 3), "where": where, "band_hz": band,
        "parameters": describe_parameters(name, p_final if name in struct_final.effects else f["after"], dev, dt,
                                          max(float(r.t[-1]) for r in recs)),
        "rmse_after": f["rmse_after"],
        "evidence": {
            "explained_share": {c: round(v["explained"], 4) for c, v in cmp["channels"].items()},
            "explained_share_heldout": {c: round(v["explained_heldout"], 4) for c, v in cmp["channels"].items()},
            # structured rms its correction removes on held-out data, in multiples of each channel's noise
            "removed_noise_multiples": {c: round(removed_rms(v), 3) for c, v in cmp["channels"].items()},
            "heldout_beta": round(cmp["beta_heldout"], 3), "heldout_z": round(cmp["z_heldout"], 1),
            "likelihood_ratio": round(cmp["lr"], 2), "df": cmp["df"], "p_lr": cmp["p_lr"],
            "delta_bic": round(cmp["dbic"], 2), "p_heldout_blocks": cmp["p_block"],
            "heldout_blocks_better": f"{cmp['blocks_better']}/{cmp['blocks']}",
            "effective_n": {c: round(v["n_eff"], 1) for c, v in cmp["channels"].items()},
            "alternatives_tried": f["alternatives"], "note": f["note"],
            "strongest_alternative": f.get("rival"),
            **({"further_elements": [{"explained_share": {c: round(v["explained"], 4)
                                                          for c, v in m["channels"].items()},
                                      "delta_bic": round(m["dbic"], 2)} for m in f["more"]]}
               if f.get("more") else {}),
        },
        "model": mech.model, "signature": mech.signature,
    }


def assemble(recs, fitter, dev, model, p_base, p_final, struct_nom, struct_final, findings, candidates,
             rejected, noise, noise_ar, loc_base, ctxs, nominal_as_given, notes, base_struct_rms, recal,
             between=None):
    dt = min(r.dt for r in recs)
    base_preds = [predict(r, dev, p_base) for r in recs]
    base_oriented = [{c: r.sign.get(c, 1) * pr[c] for c in ("x", "us")} for r, pr in zip(recs, base_preds)]
    base_rmse, base_away = _heldout_rmse(recs, base_oriented), _heldout_rmse(recs, base_oriented, away=True)
    out_findings = [_finding(f, recs, ctxs, dev, noise, p_final, struct_final, dt) for f in findings]
    out_candidates = []
    for f in candidates:
        c = _finding(f, recs, ctxs, dev, noise, p_final, struct_final, dt)
        same = (f.get("rival") or {}).get("why")
        c["why_not_named"] = (f"confidence {f['confidence']:.2f} is below {CONFIDENT}: "
                              + (f"{same}, an ordinary item (rival {f['rival']['effect']})" if same else
                                 "the data support it, but not clearly enough to put it into the model"))
        out_candidates.append(c)
    # final residual tests and what is still unexplained
    final_preds = [predict(r, dev, p_final) for r in recs]
    final_oriented = [{c: r.sign.get(c, 1) * pr[c] for c in ("x", "us")} for r, pr in zip(recs, final_preds)]
    final_rmse, final_away = _heldout_rmse(recs, final_oriented), _heldout_rmse(recs, final_oriented, away=True)
    tests, unexplained = {}, []
    for c in noise:
        e_all = []
        for r, pr in zip(recs, final_preds):
            y = getattr(r, c)
            if y is None:
                continue
            e = y - pr[c]
            e_all.append((r, e))
        e_cat = np.concatenate([e for _, e in e_all])
        r0, e0 = e_all[0]
        ti = tau_int(e0)
        tests[c] = {"whiteness": whiteness(e0, 20), "whiteness_decimated": whiteness(e0, 20, ti),
                    "input_xcorr": input_xcorr(e0, r0.u, max(1, int(0.05 / r0.dt))),
                    "noise": noise[c], "tau_int_samples": round(ti, 1),
                    "structured_rms": math.sqrt(max(float(np.mean(e_cat ** 2)) - noise[c] ** 2, 0.0))}
        struct_rms = tests[c]["structured_rms"]
        where_range = range_sentence(e0, r0.u, ctxs[0]["rate"], noise[c])
        trend = slow_trend(e0, r0.t, noise[c])
        if trend and struct_rms > 0.5 * noise[c]:
            unexplained.append({
                "channel": c, "band_hz": [0.0, round(2.0 / max(float(r0.t[-1]), 1e-9), 4)], "peak_hz": 0.0,
                "rms": trend["rms"], "unit": UNITS[c], "coherence_with_input": None,
                "description": (f"a slow trend of {c} over the recording ({trend['change']:+.3g} from start to end, "
                                f"{100 * trend['share']:.0f} % of the structured residual), not tied to the "
                                "input's changes: a drifting offset of the channel, not in the catalogue"
                                + (" (a displacement drift would be thermal_drift, but it was not supported)"
                                   if c == "x" else "")),
                "where": [{"t0_s": round(r0.t0, 6), "t1_s": round(r0.t0 + float(r0.t[-1]), 6),
                           "why": "the whole recording"}],
            })
        if struct_rms > 0.5 * noise[c] and struct_rms > 0.002 * float(np.std(np.concatenate(
                [getattr(r, c) for r in recs if getattr(r, c) is not None]))):
            for r, e in e_all:
                ctx = ctxs[recs.index(r)]
                for b in locate.bands(e, r.u, 1 / r.dt, noise[c], min_share=0.1):
                    if b["rms"] < 0.3 * noise[c]:
                        continue
                    score = np.clip(bandpass(e, b["band_hz"], 1 / r.dt) ** 2, 0, None)
                    wins = locate.windows(score, ctx, 2.0 * float(np.mean(score)), max_windows=3,
                                          min_len_s=max(0.02, 0.002 * r.t[-1]))
                    unexplained.append({
                        "channel": c, "band_hz": b["band_hz"], "peak_hz": b["peak_hz"], "rms": b["rms"],
                        "unit": UNITS[c],
                        "coherence_with_input": round(b["coherence"], 3),
                        "description": describe_band(b, noise[c], dominant_freq(r.u, r.dt))
                                       + (f"; {where_range}" if where_range else ""),
                        "where": [{"t0_s": round(r.t0 + w["t0"], 6), "t1_s": round(r.t0 + w["t1"], 6),
                                   "why": locate.describe_window(ctx, w["k0"], w["k1"])} for w in wins],
                    })
    unexplained.sort(key=lambda u: -u["rms"])
    final_struct_rms = {c: tests[c]["structured_rms"] for c in tests}
    if out_candidates:
        unexplained.insert(0, {
            "channel": out_candidates[0]["channel"], "band_hz": out_candidates[0]["band_hz"], "peak_hz": None,
            "rms": None, "unit": UNITS[out_candidates[0]["channel"]], "coherence_with_input": None,
            "description": "weakly supported: " + ", ".join(
                f"{c['effect']} (confidence {c['confidence']:.2f})" for c in out_candidates)
            + " would explain part of it (see 'candidates')",
            "where": out_candidates[0]["where"][:3]})
    # nothing is missing when no mechanism is named or supported as a candidate from WEAK up (whose
    # correction reaches FAINT_REMOVED x the noise on a channel: see below_noise) and what
    # is left is below ORDINARY x the noise on every channel: the ordinary misfit of a recalibrated
    # model (a device's own loop of another family lies up to ~1.5 noise rms from the best
    # nine-operator PI), not missing physics, which both evaluations count from 3 noise rms; the bands
    # it has are listed under 'unexplained' all the same, weaker candidates under 'candidates'
    faint = [c for c, f in zip(out_candidates, candidates) if c["confidence"] < WEAK or below_noise(f["cmp"])]
    nothing_missing = not out_findings and len(faint) == len(out_candidates) and all(
        final_struct_rms[c] <= ORDINARY * noise[c] for c in final_struct_rms)
    # with nothing named and more than the ordinary misfit left, a slowly sampled recording is refitted
    # with its path between the samples (``between``: :func:`.between.between_samples`)
    path = None
    if (between is not None and not nothing_missing and not out_findings
            and len(faint) == len(out_candidates)):
        path = between()
        if path is not None and all(path["structured_rms"][c] <= ORDINARY * noise[c] for c in final_struct_rms):
            nothing_missing = True
    struct_txt = ", ".join(f"{c} {final_struct_rms[c] / max(noise[c], 1e-300):.2g}" for c in final_struct_rms)
    listed = (f"; weaker candidates (confidence below {WEAK:g}, or a correction below {FAINT_REMOVED:g} x the "
              "noise rms on held-out data) are listed, not counted: "
              + ", ".join(f"{c['effect']} ({c['confidence']:.2f})" for c in faint)) if faint else ""
    if nothing_missing and all(final_struct_rms[c] <= 0.5 * noise[c] for c in final_struct_rms):
        verdict = ("nothing is missing: the recalibrated nominal model explains the recording down to the "
                   "noise (structured residual below half the noise level on every channel)" + listed)
    elif nothing_missing and path is not None:
        fine_txt = ", ".join(f"{c} {path['structured_rms'][c] / max(noise[c], 1e-300):.2g}" for c in final_struct_rms)
        verdict = ("nothing is missing: no catalogue mechanism is supported; what is left at one step per sample "
                   f"(structured residual {struct_txt} x the noise rms) is the stroke's path between the "
                   f"samples: refitted with {path['steps_per_sample']} steps per sample, the recalibrated model "
                   f"leaves {fine_txt} x the noise, below {ORDINARY:g} x" + listed)
    elif nothing_missing:
        verdict = ("nothing is missing: no catalogue mechanism is supported"
                   + (f" at confidence {WEAK:g} or more" if faint else "") + ", and what is left (structured "
                   f"residual {struct_txt} x the noise rms) is below {ORDINARY:g} x the noise: the ordinary "
                   "misfit of the recalibrated model" + (" (its bands: see 'unexplained')" if unexplained else "")
                   + listed)
    elif out_findings:
        verdict = "missing physics: " + ", ".join(f["effect"] for f in out_findings)
        if unexplained:
            verdict += "; some structured residual remains unexplained (see 'unexplained')"
    elif unexplained:
        verdict = ("a structured residual remains that no catalogue mechanism explains (see 'unexplained'); "
                   "no mechanism is named")
    else:
        verdict = (f"a structured residual of {struct_txt} x the noise rms remains with no band or trend of "
                   "its own; no catalogue mechanism explains it and none is named")
    first = recs[0]
    block_s = float(first.t[-1] / (np.max(first.block) + 1))
    return {
        "units": {"x": UNITS["x"], "us": UNITS["us"],
                  "note": "values per channel (rmse, noise, rms, residuals) are in that channel's unit; every "
                          "other key names its unit (_s seconds, _hz hertz, _V volts, ...) or is dimensionless"},
        "recordings": [{"file": r.name, "samples": int(r.n), "dt_s": r.dt, "duration_s": float(r.t[-1]),
                        "channels": r.channels(), "sign": r.sign,
                        "replay_step_s": float(f"{r.h:.6g}"), "replay_steps_per_sample": r.oversample}
                       for r in recs],
        "baseline": {"rmse": base_rmse, "nrmse": nrmse(recs, base_rmse), "rmse_away_from_jumps": base_away,
                     "nominal_as_given_rmse": nominal_as_given,
                     "structured_rms": base_struct_rms, "noise": noise,
                     "noise_ar1": noise_ar,
                     "recalibrated": recal_summary(p_base, dev, dt, recal, fitter),
                     "structure": list(struct_nom.effects)},
        "localisation": loc_base,
        "findings": out_findings,
        "candidates": out_candidates,
        "rejected": rejected,
        "unexplained": unexplained[:5],
        "final": {"effects": list(struct_final.effects), "rmse": final_rmse, "nrmse": nrmse(recs, final_rmse),
                  "rmse_away_from_jumps": final_away,
                  "structured_rms": final_struct_rms, "tests": tests, "verdict": verdict,
                  **({"refitted_between_samples": {
                      **path, "meaning": "the recalibrated model refitted with that many replay steps per sample "
                                 "(units as the channels'); asked when nothing is named and more than the "
                                 "ordinary misfit is left at one step per sample"}} if path else {}),
                  "nothing_missing": nothing_missing},
        "validation": {
            "method": "interleaved blocks: each recording is cut into equal consecutive blocks; "
                      + "; ".join(f"{r.name}: held out {r.split or f'every {HELDOUT_EVERY}th block'}" for r in recs),
            "blocks_per_recording": int(np.max(first.block) + 1), "block_s": block_s,
            "heldout_fraction": float(np.mean(np.concatenate([r.heldout for r in recs]))),
            "fitted_on": "the other blocks only (every parameter, every candidate)",
            "simulation": "the model is driven by the recorded command through the whole recording "
                          "(held-out blocks included); only the measured outputs of held-out blocks are "
                          "withheld from fitting",
            "selection": "candidates are accepted on training-row statistics (likelihood ratio, BIC with "
                         "effective sample size) and on held-out improvement (share of the structured "
                         "residual removed, one-sided test over held-out blocks); every rmse reported is "
                         "over held-out samples. Slow mechanisms (creep, sensor leakage, thermal drift) are "
                         f"judged on the held-out samples away from the command's jumps (the {RESPONSE_S:g} s "
                         f"after each change of {100 * JUMP:g} % of its span within a sample: the fast "
                         "dynamics' transient); rmse_away_from_jumps is over those",
            "thresholds": ACCEPT,
        },
        "notes": notes,
    }


UNITS = {"x": "um", "us": "V"}
ORDINARY = 2.0     # a structured residual up to this many noise rms, with nothing named, is ordinary misfit
# a candidate below this confidence does not keep a small residual from "nothing is missing" (it is
# listed as a candidate all the same). Set 2026-11-28 on rig draws 0-4: the cases with candidates only
# and a residual below ORDINARY were 5 clean devices (candidates 0.10, 0.11, 0.20, 0.34, 0.45) and 6
# others, candidates 0.31-0.48 (three true: two delays, a drift; creep beside a true drift, beside a
# true loop shape, and on a control)
WEAK = 0.25
# ... nor does one whose correction removes less than this many noise rms of structured residual
# from each of its channels on held-out data (:func:`.decide.removed_rms`): below half the noise,
# where a residual counts as "down to the noise". Set 2026-12-05 on rig draw 22 and the
# established set (stop 73's logs): the candidates removing less were a creep on two clean
# devices (0.14 and 0.15 x, confidence 0.26 and 0.39: rig-d22-018, 157) and a drift beside a
# named creep (0.28 x); every true candidate removed 0.69 x or more on a channel (rig-d22-057's
# drift), the control rig-135's creep 1.6 x (it stays counted)
FAINT_REMOVED = 0.5


def below_noise(cmp):
    """Whether a candidate's correction (its :func:`.stats.compare` result ``cmp``) removes less
    than ``FAINT_REMOVED`` x the noise rms of structured residual from every channel on held-out data."""
    return all(removed_rms(v) < FAINT_REMOVED for v in cmp["channels"].values())


# a recalibrated value whose standard uncertainty exceeds this many times the value is not
# determined by the recording (rig draw 3, stop 44's code: 123 of 185 recordings had such a value,
# 57 besides the saturation; the amplifier lag of rig-d3-165 at 1.7e12 x its 0.1 ms, sampled at 264 Hz)
UNDETERMINED = 1.0
# the nonlinear ordinary parameters behind the report's keys
# (the total lag of two stages is derived: it has no search range of its own)
_REPORTED = {"amplifier_tau_s": "tau", "amplifier_tau2_s": "tau2", "amplifier_total_lag_s": None,
             "first_mode_hz": "mech_f", "first_mode_zeta": "mech_zeta", "threshold_scale_V": "u_norm",
             "saturation_um": "y_sat"}


def _judge(out, fitter, p):
    """Mark each recalibrated nonlinear value the recording does not determine (``determined``
    false, with ``why_undetermined``): one at a bound of its search range (a mechanism's parameter
    there is never accepted; an ordinary one there is reported as such) or one whose standard
    uncertainty exceeds ``UNDETERMINED`` x the value, or one no sample responds to (uncertainty
    ``inf``, reported as None). Values not fitted (no uncertainty) are left as they are."""
    for key, name in _REPORTED.items():
        v = out.get(key)
        if not isinstance(v, dict) or v.get("relative_uncertainty") is None or v["value"] <= 0:
            continue
        edge = at_bound(fitter, p, [name]) if fitter is not None and name is not None else []
        u = v["relative_uncertainty"]
        if not math.isfinite(u):        # no sample responds to it: no figure (JSON has no infinity)
            v["relative_uncertainty"] = None
        if edge:
            lo, hi = edge[0]["range"]
            end = "lower" if math.log(v["value"] / lo) < math.log(hi / v["value"]) else "upper"
            unit = {"s": " s", "hz": " Hz", "V": " V", "um": " um"}.get(key.rsplit("_", 1)[-1], "")
            v.update(determined=False, search_range=[lo, hi],
                     why_undetermined=f"at the {end} end of its search range {lo:.4g}-{hi:.4g}{unit}: the "
                                      "recording does not place it inside")
        elif not math.isfinite(u):
            v.update(determined=False,
                     why_undetermined="moving it by 0.1 % changes no sample: the recording does not "
                                      "determine it")
        elif u > UNDETERMINED:
            v.update(determined=False,
                     why_undetermined=f"its standard uncertainty is {u:.2g} x the value: the recording "
                                      "does not determine it")
        else:
            v["determined"] = True
    return out


def recal_summary(p, dev, dt, recal, fitter=None):
    """The recalibrated ordinary physics, each value with its unit and its standard uncertainty:
    relative for the nonlinear ones fitted, the loop's scale and the sensor's sensitivity; in the
    value's unit for the offsets. With ``fitter``, each nonlinear value also says whether the
    recording determines it (:func:`_judge`); with two lag stages the total lag is reported too."""
    unc = recal.report.get("uncertainty", {}) if recal else {}
    lin = recal.report.get("uncertainty_linear", {}) if recal else {}
    rep = recal.report if recal else {}
    loop = rep.get("loop", {})
    f1, z1 = p.mode(dev)

    def val(v, digits=5):
        return float(f"{v:.{digits}g}")

    out = {
        "amplifier_tau_s": {"value": val(p.tau), "relative_uncertainty": unc.get("tau")},
        "amplifier_order": rep.get("amplifier_order", {}).get("value", 2 if p.tau2 > 0 else 1),
        "amplifier_tau2_s": {"value": val(p.tau2), "relative_uncertainty": unc.get("tau2")},
        **({"amplifier_total_lag_s": {"value": val(p.tau + p.tau2), "relative_uncertainty": unc.get("tau+tau2"),
                                      "meaning": "tau + tau2: the two stages' lag together"}}
           if p.tau2 > 0 else {}),
        "first_mode_hz": {"value": val(f1), "relative_uncertainty": unc.get("mech_f"),
                          "identified": rep.get("first_mode", {}).get("identified", False),
                          **{k: v for k, v in rep.get("first_mode", {}).items() if k in ("why", "fitted_with")}},
        "first_mode_zeta": {"value": val(z1, 4), "relative_uncertainty": unc.get("mech_zeta")},
        "sensor_follows": {"value": p.pick, "meaning": {
            "stack": "the stack's blocked force (paper eq. 5)",
            "contact": "the contact force between stack and push rod (the modes show in it)",
            "load": "the load spring's force: the push-rod displacement"}[p.pick],
            "identified": rep.get("pickoff", {}).get("identified", False)},
        "stroke_path": "amplifier_lag" if p.path_lag else "linear",
        "sampling_lag_x_samples": p.lag_x, "sampling_lag_us_samples": p.lag_us,
        "sampling_lag_x_s": val(p.lag_x * dt), "sampling_lag_us_s": val(p.lag_us * dt),
        "u_norm_V": p.u_norm,
        "initial_state": {"value": "prepared" if p.prep > 0 else "relaxed",
                          "meaning": ("the operators start with the memory of a sweep up to "
                                      f"{p.prep:.4g} V of stack voltage and back" if p.prep > 0 else
                                      "the operators start relaxed (no memory before the record)")},
        "threshold_scale_V": {"value": val(p.u_norm), "relative_uncertainty": unc.get("u_norm"),
                              "identified": rep.get("threshold_scale", {}).get("identified", False),
                              "meaning": "u_norm: the voltage the normalised PI thresholds are in units of"},
        "pi_scale_um": {"value": val(np.sum(p.weights), 6), "relative_uncertainty": lin.get("pi_scale")},
        "x_offset_um": {"value": val(p.off_x, 6), "uncertainty": lin.get("off_x")},
        "sensor_sensitivity_V_per_N": {"value": val(p.S, 6), "relative_uncertainty": lin.get("S")},
        "sensor_offset_V": {"value": val(p.off_s, 6), "uncertainty": lin.get("off_s")},
        "saturation_um": ({"value": val(p.y_sat, 6), "relative_uncertainty": unc.get("y_sat")}
                          if math.isfinite(p.y_sat) else None),
        "loop": {"value": f"{len(p.thresholds)} play operators"
                          + (f", {p.n_cells} KP cells" if p.n_cells else "")
                          + (" (refined: an ordinary loop difference, not named)"
                             if loop.get("refined") else "")
                          + (" with the finer loop's own fit: refitted, it was worse on held-out data"
                             if loop.get("refit_undone") else ""),
                 "refined": False, **loop},
    }
    return _judge(out, fitter, p)


def describe_parameters(name, p, dev, dt, duration=math.inf):
    """The fitted parameters of a mechanism in model-file units (``duration`` [s]: the longest record)."""
    if name == "creep":
        return {"gains": [float(f"{g:.5g}") for g, _ in p.creep],
                "time_constants_s": [float(f"{t:.5g}") for _, t in p.creep]}
    if name == "sensor_leakage":
        return {"tau_leak_s": float(f"{p.tau_leak:.5g}"),
                "charge_at_start": "leaked before the record" if p.leak_settled else "charged at the first sample"}
    if name == "amplifier_current_limit":
        return {"I_max_A": float(f"{p.slew * dev.C_a:.5g}"), "slew_V_per_s": float(f"{p.slew:.5g}")}
    if name == "time_delay":
        return {"delay_s": float(f"{round(p.delay / dt) * dt:.6g}"), "samples": int(round(p.delay / dt))}
    if name == "extra_resonance":
        return {"f_n_Hz": float(f"{p.res[0]:.5g}"), "zeta": float(f"{p.res[1]:.4g}"), "position": p.res_at}
    if name == "thermal_drift":
        out = {"rate_per_s": float(f"{p.rate:.5g}"), "curvature_per_s2": float(f"{p.curv:.5g}")}
        if math.isfinite(p.drift_tau):
            out["time_constant_s"] = float(f"{p.drift_tau:.5g}")
        if math.isfinite(p.drift_tau) and p.drift_tau <= duration:
            # rate t + curvature 2 T^2 (exp(-t/T) - 1 + t/T): a ramp and a warm-up settling within the record
            out.update(ramp_um_per_s=float(f"{p.rate + 2 * p.drift_tau * p.curv:.5g}"),
                       warm_up_um=float(f"{-2 * p.drift_tau ** 2 * p.curv:.5g}"))
        return out
    if name == "hysteresis_shape":
        out = {"operators": len(p.thresholds), "thresholds": [float(f"{v:.5g}") for v in p.thresholds]}
        if p.n_cells:
            out["kp_cells"] = p.n_cells
            out["kp_grid_V"] = [float(f"{float(p.cells[1].min()) * p.u_norm:.4g}"),
                                float(f"{float(p.cells[0].max()) * p.u_norm:.4g}")]
        return out
    return {}
