"""The diagnosis: recalibrate, locate, name, model, validate.

1. **Recalibrate** the nominal model to the recordings (PI weights, amplifier lag, channel gains
   and offsets, the input normalisation, the sign of each channel) so that ordinary parameter
   mismatch is never mistaken for missing physics. Mechanisms the nominal model already has are
   re-fitted too.
2. **Locate** the mismatch of the recalibrated model: in time (input segments), frequency
   (residual spectrum above the noise floor, coherence with the input), operating range
   (command level and rate), per channel.
3. **Name** it: forward selection over the catalogue (:mod:`.catalogue`). Every candidate is
   screened, the promising ones are fitted (linear parameters and coupled nonlinear ones
   re-identified) and compared with the current model by statistics that hold under noise
   (:func:`.stats.compare`): a likelihood-ratio test and BIC with effective sample sizes on the
   training rows, the share of the structured residual removed, the held-out confirmation (how
   much of the candidate's correction the held-out residual takes, and how significantly), and
   physical checks. The best candidate that passes is added and every parameter settled; repeat.
   Then every accepted mechanism is removed again in turn (backward check) and must still be
   needed. What is left structured is described, not named.
4. **Model and validate**: the final model is the nominal one plus the accepted mechanisms; all
   RMSEs are on held-out samples.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import UserError
from ..model import Model, load_model
from ..recording import read_csv_table
from . import locate
from .catalogue import CATALOGUE, describe_parameters, plausible, propose, spectral_peaks
from .engine import (
    Device,
    Params,
    Recording,
    device_from_model,
    model_from_params,
    params_from_model,
    predict,
    solve_linear,
)
from .fit import Fitter, Structure, free_names, strip
from .stats import compare, improvement_band, input_xcorr, noise_std, tau_int, whiteness

__all__ = ["ACCEPT", "Diagnosis", "analyse", "load_recordings"]

# Acceptance thresholds (see docs/diagnose.md, "How a finding is decided").
ACCEPT = {
    "p_lr": 1e-3,            # likelihood-ratio test on training rows (effective sample size)
    "dbic": 10.0,            # BIC difference (effective sample size), > 10 = very strong
    "explained": 0.15,       # share of the structured residual removed (its best channel)
    "beta_heldout": 0.5,     # held-out residual regressed on the candidate's change there (1 = all of it)
    "z_heldout": 3.0,        # ... and that regression's significance
    "worse": 0.02,           # no channel's held-out RMSE may grow by more than this
}
N_BLOCKS = 64
HELDOUT_EVERY = 4


@dataclass
class Diagnosis:
    recs: list
    model: Model
    nominal_model: Model           # recalibrated nominal
    final_model: Model
    p_nominal: Params
    p_final: Params
    struct_nominal: Structure
    struct_final: Structure
    result: dict                   # diagnosis.json content
    pred_nominal: list             # per recording: dict channel -> prediction (file orientation)
    pred_final: list
    ctx: list                      # per recording input context
    timing: dict = field(default_factory=dict)


# -- recordings --------------------------------------------------------------------------------------

def load_recordings(paths, columns=None, scale=None):
    """Read recordings: columns time [s], u [V] and x [um] and/or us [V] (after --columns/--scale)."""
    if not paths:
        raise UserError("give at least one recording (CSV with time, u and x and/or us)")
    out = []
    for path in paths:
        tab = read_csv_table(path, required=("time", "u"), one_of=("x", "us"), columns=columns,
                             scale=scale, uniform=True, min_rows=50)
        out.append({"name": str(path), "time": tab["time"], "u": tab["u"],
                    "x": tab.columns.get("x"), "us": tab.columns.get("us")})
    return out


def _blocks(n, n_blocks=N_BLOCKS):
    nb = n_blocks if n >= 20 * n_blocks else max(4, n // 20)
    block = np.minimum((np.arange(n) * nb) // n, nb - 1)
    return block, (block % HELDOUT_EVERY) == HELDOUT_EVERY // 2


def make_recordings(raw):
    recs = []
    for r in raw:
        t = np.asarray(r["time"], float)
        dt = float(np.median(np.diff(t)))
        block, held = _blocks(t.size)
        recs.append(Recording(r["name"], t - t[0], dt, np.asarray(r["u"], float),
                              None if r.get("x") is None else np.asarray(r["x"], float),
                              None if r.get("us") is None else np.asarray(r["us"], float),
                              held, float(t[0]), block, {}))
    return recs


# -- helpers --------------------------------------------------------------------------------------------

def _residual_sets(fitter: Fitter, p: Params):
    """channel -> train/heldout residuals, held-out blocks, weight (model orientation)."""
    out = {}
    rps = fitter.replays(p)
    preds = [predict(r, fitter.dev, p, rp) for r, rp in zip(fitter.recs, rps)]
    for ch in ("x", "us"):
        tr, ho, blocks = [], [], []
        for r, pr in zip(fitter.recs, preds):
            y = getattr(r, ch)
            if y is None:
                continue
            e = y - pr[ch]
            tr.append(e[r.train])
            ho.append(e[r.heldout])
            for b in np.unique(r.block[r.heldout]):
                blocks.append(e[r.block == b])
        if tr:
            out[ch] = {"train": np.concatenate(tr), "heldout": np.concatenate(ho), "blocks": blocks,
                       "lam": fitter.lam[ch]}
    return out, preds


def _full_residuals(fitter, p):
    rps = fitter.replays(p)
    out = []
    for r, rp in zip(fitter.recs, rps):
        pr = predict(r, fitter.dev, p, rp)
        out.append({ch: getattr(r, ch) - pr[ch] for ch in r.channels()})
    return out


def _passes(cmp, name, ok):
    mech = CATALOGUE[name]
    chans = [c for c in mech.channels if c in cmp["channels"]]
    if not chans:
        return False, "no recorded channel shows this mechanism"
    best_c = max(chans, key=lambda c: cmp["channels"][c]["explained"])
    explained = cmp["channels"][best_c]["explained"]
    # a channel is made worse when its held-out RMSE grows by more than 2 % and its structured
    # residual by more than a quarter of its noise (shared parameters may shift a little)
    worse = [c for c, v in cmp["channels"].items()
             if v["rel_improvement"] < -ACCEPT["worse"]
             and math.sqrt(max(v["rmse_after"] ** 2 - v["noise"] ** 2, 0.0)) - v["structured_before"] > 0.25 * v["noise"]]
    reasons = []
    if not ok[0]:
        reasons.append(ok[1])
    if cmp["p_lr"] > ACCEPT["p_lr"]:
        reasons.append(f"likelihood-ratio p = {cmp['p_lr']:.2g}")
    if cmp["dbic"] < ACCEPT["dbic"]:
        reasons.append(f"BIC gain {cmp['dbic']:.1f} < {ACCEPT['dbic']:g}")
    if cmp["beta_heldout"] < ACCEPT["beta_heldout"] or cmp["z_heldout"] < ACCEPT["z_heldout"]:
        reasons.append(f"held-out data take {cmp['beta_heldout']:.2f} of its correction (z = {cmp['z_heldout']:.1f})")
    if explained < ACCEPT["explained"]:
        reasons.append(f"explains {100 * explained:.0f} % of the structured residual")
    for c in worse:
        reasons.append(f"makes {c} {100 * -cmp['channels'][c]['rel_improvement']:.1f} % worse on held-out data")
    return (not reasons), "; ".join(reasons)


def _confidence(cmp, name, alt_share=0.0):
    """0..1 from four factors: strength of evidence (BIC with effective sample size), size (share
    of the structured residual removed), held-out confirmation (how much of its correction the
    held-out data take, and how significantly), uniqueness (no other candidate explained as much)."""
    mech = CATALOGUE[name]
    chans = [c for c in mech.channels if c in cmp["channels"]]
    explained = max(cmp["channels"][c]["explained"] for c in chans)
    s_evidence = 1.0 - math.exp(-max(cmp["dbic"], 0.0) / 30.0)
    s_size = min(1.0, max(explained, 0.0) / 0.5)
    s_heldout = float(np.clip(cmp["beta_heldout"], 0.0, 1.0)) * (1.0 - math.exp(-max(cmp["z_heldout"], 0.0) / 3.0))
    s_unique = 1.0 - 0.7 * float(np.clip(alt_share, 0.0, 1.0))
    return float(np.clip(s_evidence * s_size * s_heldout * s_unique, 0.0, 1.0))


# -- the analysis ----------------------------------------------------------------------------------------

def analyse(raw, model: Model | None = None, say=None, max_rounds=5) -> Diagnosis:
    say = say or (lambda msg: None)
    t_start = time.perf_counter()
    timing = {}

    def step(msg):
        say(f"[{time.perf_counter() - t_start:6.1f} s] {msg}")

    model = model or load_model()
    recs = make_recordings(raw)
    chans = sorted({c for r in recs for c in r.channels()})
    dev = device_from_model(model)
    p_nom = params_from_model(model)
    struct_nom = _nominal_structure(p_nom)
    notes = []

    # input normalisation and rails: the recording's stack-voltage span
    ua_hi = max(float(np.max(r.u)) for r in recs) * dev.k_amp
    ua_lo = min(float(np.min(r.u)) for r in recs) * dev.k_amp
    span = ua_hi - min(ua_lo, 0.0)
    if span <= 0:
        raise UserError("the command u never leaves zero: nothing to diagnose")
    sources = {("hysteresis", "u_norm"): f"nominal ({model.path}): kept, the recording's stack-voltage span "
                                         f"{span:.4g} V is within a factor 3 of it",
               ("hysteresis", "thresholds"): f"nominal ({model.path})"}
    if not (1 / 3 <= span / p_nom.u_norm <= 3):
        notes.append(f"input normalisation: the recording spans {span:.4g} V of stack voltage, the model's "
                     f"PI is normalised to {p_nom.u_norm:.4g} V; re-normalised to {span:.4g} V")
        p_nom.u_norm = span
        sources[("hysteresis", "u_norm")] = ("diagnose: re-normalised to the recording's stack-voltage span "
                                             "(k_amp times the command range)")
        sources[("hysteresis", "thresholds")] = f"nominal ({model.path}) in units of the new u_norm"
    if struct_nom.saturation:
        sources[("hysteresis", "saturation")] = "re-fitted by piezo-fmu diagnose with the recalibration"
    if ua_hi > dev.u_max or ua_lo < dev.u_min:
        notes.append(f"the command asks for {ua_lo:.4g}..{ua_hi:.4g} V of stack voltage, beyond the model's "
                     f"rails {dev.u_min:g}..{dev.u_max:g} V; rails widened so the recording is not clipped")
        dev = Device(**{**dev.__dict__, "u_min": min(dev.u_min, ua_lo * 1.05 - 1e-9),
                        "u_max": max(dev.u_max, ua_hi * 1.05 + 1e-9)})

    # signs of the channels: regression of each channel on the nominal model's prediction
    for r in recs:
        pr = predict(r, dev, p_nom)
        for c in r.channels():
            y = getattr(r, c)
            a = np.vstack([pr[c], np.ones_like(y)]).T
            slope = np.linalg.lstsq(a, y, rcond=None)[0][0]
            r.sign[c] = -1 if slope < 0 else 1
            if r.sign[c] < 0:
                setattr(r, c, -y)
                notes.append(f"{r.name}: {c} falls when the command rises; diagnose works on -{c} "
                             f"(the model's orientation) and reports in the file's orientation")
    nominal_as_given = _rmse_as_given(recs, dev, p_nom)

    # -- 1. recalibration ---------------------------------------------------------------------------
    step("recalibrating the nominal model (PI weights, amplifier lag, gains and offsets)")
    lam = {c: 1.0 / max(np.var(np.concatenate([getattr(r, c) for r in recs if getattr(r, c) is not None])), 1e-300)
           for c in chans}
    fitter = Fitter(recs, dev, lam, say)
    p = p_nom.copy()
    y_sat_nom = p.y_sat
    p.y_sat = math.inf
    p.weights = np.zeros_like(p.weights)
    stroke_nom = _stroke(recs, dev, p_nom)
    solve_linear(recs, dev, p, lam, drift_terms=struct_nom.drift_terms, replays=fitter.replays(p))
    stroke = _stroke(recs, dev, p)
    if math.isfinite(y_sat_nom) and stroke_nom > 0:
        p.y_sat = y_sat_nom * stroke / stroke_nom
    # nuisance parameters stay physical: a lag within a factor 50 of the nominal one, a saturation
    # level no lower than 0.3 x the stroke; a fit that starts at one of these limits restarts from here
    fitter.limits["tau"] = (max(1e-7, p.tau / 50), max(fitter.bounds("tau")[1], 20 * p.tau))
    if math.isfinite(p.y_sat):
        fitter.limits["y_sat"] = (0.3 * stroke, max(1000 * stroke, 10 * p.y_sat))
    fitter.restart = {"tau": p.tau, "y_sat": p.y_sat}
    # amplifier lag first (1-D), then everything of the nominal structure
    p, _ = fitter.fit_scalar(p, struct_nom, "tau")
    fr = fitter.fit(p, struct_nom, max_nfev=15)
    p = fr.params
    # channel weights from the recalibrated residuals, then once more
    sets, _ = _residual_sets(fitter, p)
    fitter.lam = {c: 1.0 / max(float(np.mean(sets[c]["train"] ** 2)), 1e-300) for c in sets}
    fr = fitter.fit(p, struct_nom, max_nfev=10)
    p_base = fr.params
    timing["recalibration_s"] = time.perf_counter() - t_start

    # noise floor of every channel from the recalibrated residual
    fulls = _full_residuals(fitter, p_base)
    noise = {c: float(np.sqrt(np.mean([noise_std(f[c], 1 / r.dt) ** 2 for f, r in zip(fulls, recs) if c in f])))
             for c in chans}
    sets_base, _ = _residual_sets(fitter, p_base)
    fitter.noise = noise

    # -- 2. where the recalibrated model misses ------------------------------------------------------
    step("locating the mismatch (time, frequency, operating range, channels)")
    ctxs = [locate.input_context(r.t, r.u, r.dt) for r in recs]
    loc_base = _localise(recs, fulls, ctxs, noise)
    x_peaks = []
    if "x" in chans:
        x_peaks = spectral_peaks(np.concatenate([f["x"] for f in fulls if "x" in f]), 1 / recs[0].dt)
    cctx = {"channels": chans, "x_peaks": x_peaks}
    structured = {c: sets_base[c]["heldout"] for c in sets_base}
    base_struct_rms = {c: math.sqrt(max(float(np.mean(structured[c] ** 2)) - noise[c] ** 2, 0.0)) for c in structured}

    # -- 3. forward selection --------------------------------------------------------------------------
    current, struct = p_base, struct_nom
    findings, rejected = [], []
    sets_cur, _ = _residual_sets(fitter, current)
    for rnd in range(max_rounds):
        if _at_noise(sets_cur, noise):
            step("the residual is at the noise floor: nothing more to explain")
            break
        names = [n for n in CATALOGUE if n not in struct.effects or n == "creep"]
        q0 = fitter.quick(current)
        if "x" in chans and rnd > 0:
            # peaks of what is left now (the first round's residual may be dominated by something else)
            cctx["x_peaks"] = spectral_peaks(np.concatenate([sets_cur["x"]["train"]]), 1 / recs[0].dt)
        screened = []
        for i, name in enumerate(names):
            step(f"round {rnd + 1}: screening {name} ({i + 1}/{len(names)})")
            start = propose(name, fitter, current, struct, cctx)
            if start is None:
                continue
            q = fitter.quick(start, drift=name == "thermal_drift")
            screened.append((q0 - q, name, start))
        screened.sort(key=lambda s: -s[0])
        step(f"round {rnd + 1}: screening gains " + ", ".join(f"{n} {g / max(q0, 1e-300):.3g}" for g, n, _ in screened))
        tried = []
        top = screened[0][0] if screened else 0.0
        for i, (gain, name, start) in enumerate(screened[:4]):
            # the best screened candidate, the next ones when they come close to it, and further ones
            # (down the screening order) as long as nothing tried so far passed
            if gain <= 0 or (i >= 1 and gain < 0.4 * top and any(t["passed"] for t in tried)):
                continue
            step(f"round {rnd + 1}: fitting {name} (with the lag and every coupled parameter)")
            s_new = struct.with_effect(name, len(start.thresholds) - len(current.thresholds))
            fr = fitter.fit(start, s_new, free=_coupled(name, struct, s_new), max_nfev=10)
            if name == "time_delay":
                # the screening's integer delay trades off against the lag: step it, then re-fit
                q = _refine_delay(fitter, fr.params, s_new)
                if q.delay != fr.params.delay:
                    fr = fitter.fit(q, s_new, free=_coupled(name, struct, s_new), max_nfev=6)
            sets_new, _ = _residual_sets(fitter, fr.params)
            k = s_new.n_params() - struct.n_params()
            cmp = compare(sets_cur, sets_new, k, noise)
            ok = plausible(name, fitter, current, fr.params, cmp, cctx)
            passed, why = _passes(cmp, name, ok)
            step(f"round {rnd + 1}: {name}: " + ("passes" if passed else f"fails ({why})") + "; held-out rmse "
                 + ", ".join(f"{c} {v['rmse_before']:.4g} -> {v['rmse_after']:.4g} (explains {v['explained']:.2f}, "
                             f"held-out beta {v['beta_heldout']:.2f}, z {v['z_heldout']:.1f})"
                             for c, v in cmp["channels"].items())
                 + f"; training cost {fitter.cost(current):.5g} -> {fr.cost:.5g}")
            tried.append({"name": name, "fit": fr, "cmp": cmp, "passed": passed, "why": why,
                          "note": ok[1], "struct": s_new, "sets": sets_new})
        if not any(t["passed"] for t in tried):
            rejected += [{"effect": t["name"], "why": t["why"]} for t in tried]
            break
        best = max((t for t in tried if t["passed"]), key=lambda t: _score(t["cmp"], t["name"]))
        # the strongest competitor on the same residual (a failed one counts half)
        others = [(_score(t["cmp"], t["name"]) * (1.0 if t["passed"] else 0.5), t) for t in tried if t is not best]
        alt = max([a for a, _ in others] + [0.0])
        rival = max(others, key=lambda o: o[0])[1] if others else None
        step(f"round {rnd + 1}: added {best['name']}")
        prev = next((f for f in findings if f["name"] == best["name"]), None)
        if prev is not None:
            # a further creep element refines the same finding
            prev["after"] = best["fit"].params
            prev["rmse_after"] = {c: v["rmse_after"] for c, v in best["cmp"]["channels"].items()}
            prev.setdefault("more", []).append(best["cmp"])
        else:
            findings.append({"name": best["name"], "cmp": best["cmp"], "before": current,
                             "after": best["fit"].params, "note": best["note"],
                             "alt_share": alt / max(_score(best["cmp"], best["name"]), 1e-9),
                             "alternatives": [t["name"] for t in tried if t is not best],
                             "rival": None if rival is None else {
                                 "effect": rival["name"], "passed": rival["passed"],
                                 "explained_share": {c: round(v["explained"], 4)
                                                     for c, v in rival["cmp"]["channels"].items()}},
                             "rmse_after": {c: v["rmse_after"] for c, v in best["cmp"]["channels"].items()}})
        rejected += [{"effect": t["name"], "why": t["why"] or "another candidate explained more"}
                     for t in tried if t is not best and not t["passed"]]
        current, struct = best["fit"].params, best["struct"]
        # settle every parameter with the new mechanism in before the next round compares against it
        current = fitter.fit(current, struct, max_nfev=6).params
        sets_cur, _ = _residual_sets(fitter, current)

    # every accepted mechanism was settled with all parameters free when it came in; without any,
    # the recalibrated nominal model is the final one

    # -- backward check: every accepted mechanism must still be needed ---------------------------------
    added = list(dict.fromkeys(f["name"] for f in findings))
    if len(added) >= 2:
        sets_full, _ = _residual_sets(fitter, current)
        for name in added:
            step(f"checking that {name} is still needed with the others in the model")
            s_wo = struct.without(name)
            fr = fitter.fit(strip(current, s_wo, p_base.thresholds), s_wo, max_nfev=5)
            cmp = compare(_residual_sets(fitter, fr.params)[0], sets_full,
                          struct.n_params() - s_wo.n_params(), noise)
            ok = plausible(name, fitter, fr.params, current, cmp, cctx)
            passed, why = _passes(cmp, name, ok)
            if not passed:
                step(f"dropped {name}: {why}")
                findings = [f for f in findings if f["name"] != name]
                rejected.append({"effect": name, "why": f"not needed once the others are in: {why}"})
                current, struct = fr.params, s_wo
                sets_full, _ = _residual_sets(fitter, current)
            else:
                for f in findings:
                    if f["name"] == name:
                        f["backward"] = cmp
    p_final, struct_final = current, struct
    timing["selection_s"] = time.perf_counter() - t_start - timing["recalibration_s"]

    # -- results ----------------------------------------------------------------------------------------
    step("validating on held-out data")
    result = _assemble(recs, fitter, dev, model, p_base, p_final, struct_nom, struct_final, findings,
                       rejected, noise, loc_base, ctxs, nominal_as_given, notes, base_struct_rms)
    nominal_model = _to_model(model, p_base, dev, recs, noise, "recalibrated nominal", sources)
    final_model = _to_model(model, p_final, dev, recs, noise, "final", sources)
    preds_nom = _file_predictions(recs, dev, p_base)
    preds_fin = _file_predictions(recs, dev, p_final)
    timing["total_s"] = time.perf_counter() - t_start
    result["timing_s"] = {k: round(v, 2) for k, v in timing.items()}
    return Diagnosis(recs, model, nominal_model, final_model, p_base, p_final, struct_nom, struct_final,
                     result, preds_nom, preds_fin, ctxs, timing)


SLOW = {"creep", "sensor_leakage", "thermal_drift"}
FAST = {"time_delay", "amplifier_current_limit", "extra_resonance"}


def _coupled(name, struct, s_new):
    """Nonlinear parameters fitted with candidate ``name``: the amplifier lag, the candidate's own,
    and those of accepted mechanisms acting in the same band (slow: creep, leakage, drift; fast:
    delay, current limit, mode), which it may trade off against. The final fit frees them all."""
    if name == "hysteresis_shape":
        return ["tau"]
    group = SLOW if name in SLOW else FAST
    owner = {"creep": "creep", "tau_leak": "sensor_leakage", "slew": "amplifier_current_limit",
             "res_": "extra_resonance"}
    old = set(free_names(struct))
    keep = []
    for n in free_names(s_new):
        mech = next((m for k, m in owner.items() if n.startswith(k)), None)
        if n in ("tau", "y_sat") or n not in old or mech in group:
            keep.append(n)
    return keep


def _refine_delay(fitter, p, struct, reach=3):
    """Step the integer delay while the training cost, with the lag re-searched and the weights
    re-solved (the loop's width trades off against lag, so they must move with it), falls."""
    dt = fitter.dt
    nd = int(round(p.delay / dt))

    def at(k, tau):
        q = p.copy()
        q.delay = k * dt
        lo = max(fitter.bounds("tau")[0], tau / 4)
        return fitter.fit_scalar(q, struct, "tau", quick=False, bounds=(lo, tau * 4), xatol=0.02)

    best, best_c = at(nd, p.tau)
    for direction in (1, -1):
        moved = False
        for k in range(1, reach + 1):
            if nd + direction * k < 1:
                break
            q, c = at(nd + direction * k, max(best.tau - direction * dt, p.tau / 10))
            if c < best_c:
                best, best_c, moved = q, c, True
            else:
                break
        if moved:
            break
    return best


def _at_noise(sets, noise, level=0.3):
    """True when every channel's held-out residual is within ``level`` x noise of pure noise."""
    for c, v in sets.items():
        mse = float(np.mean(v["heldout"] ** 2))
        if math.sqrt(max(mse - noise[c] ** 2, 0.0)) > level * noise[c]:
            return False
    return True


def _score(cmp, name):
    """Rank passing candidates: structured residual removed, averaged over every recorded channel
    (a mechanism that explains both channels beats one that explains one), BIC as tie-break."""
    ex = [max(v["explained"], 0.0) for v in cmp["channels"].values()]
    return float(np.mean(ex)) + 1e-3 * cmp["dbic"] / max(1.0, abs(cmp["dbic"]))


def _nominal_structure(p: Params) -> Structure:
    eff = []
    if p.creep:
        eff.append("creep")
    if math.isfinite(p.tau_leak):
        eff.append("sensor_leakage")
    if math.isfinite(p.slew):
        eff.append("amplifier_current_limit")
    if p.delay > 0:
        eff.append("time_delay")
    if p.res is not None:
        eff.append("extra_resonance")
    if p.rate or p.curv:
        eff.append("thermal_drift")
    return Structure(tuple(sorted(eff)), len(p.creep), math.isfinite(p.y_sat))


def _stroke(recs, dev, p):
    return max(float(np.ptp(predict(r, dev, p)["x_h"])) for r in recs)


def _rmse_as_given(recs, dev, p):
    out = {}
    for c in ("x", "us"):
        e = [getattr(r, c)[r.heldout] - predict(r, dev, p)[c][r.heldout] for r in recs if getattr(r, c) is not None]
        if e:
            out[c] = float(np.sqrt(np.mean(np.concatenate(e) ** 2)))
    return out


def _localise(recs, fulls, ctxs, noise):
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
                wins.append({"recording": r.name, "t0": round(r.t0 + w["t0"], 6), "t1": round(r.t0 + w["t1"], 6),
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


def _file_predictions(recs, dev, p):
    out = []
    for r in recs:
        pr = predict(r, dev, p)
        out.append({c: r.sign.get(c, 1) * pr[c] for c in ("x", "us")})
    return out


def _to_model(base, p, dev, recs, noise, what, sources):
    src = dict(sources)
    if len(p.thresholds) != len(base["hysteresis"]["thresholds"]):
        src[("hysteresis", "thresholds")] = "diagnose (hysteresis_shape): nominal thresholds plus their midpoints"
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


def _heldout_rmse(recs, preds):
    out = {}
    for c in ("x", "us"):
        e = [r.sign.get(c, 1) * getattr(r, c)[r.heldout] - pr[c][r.heldout]
             for r, pr in zip(recs, preds) if getattr(r, c) is not None]
        if e:
            out[c] = float(np.sqrt(np.mean(np.concatenate(e) ** 2)))
    return out


def nrmse(recs, rmse):
    vals = []
    for c, v in rmse.items():
        y = np.concatenate([getattr(r, c)[r.heldout] for r in recs if getattr(r, c) is not None])
        vals.append(v / max(float(np.std(y)), 1e-300))
    return float(np.sqrt(np.mean(np.square(vals)))) if vals else None


def _assemble(recs, fitter, dev, model, p_base, p_final, struct_nom, struct_final, findings, rejected,
              noise, loc_base, ctxs, nominal_as_given, notes, base_struct_rms):
    dt = min(r.dt for r in recs)
    base_preds = [predict(r, dev, p_base) for r in recs]
    base_rmse = _heldout_rmse(recs, [{c: r.sign.get(c, 1) * pr[c] for c in ("x", "us")}
                                     for r, pr in zip(recs, base_preds)])
    out_findings = []
    for f in findings:
        name = f["name"]
        mech = CATALOGUE[name]
        after = f["after"]
        # where it helped: windows of the largest reduction of the squared residual
        where, band = [], None
        for r, ctx in zip(recs, ctxs):
            pb, pa = predict(r, dev, f["before"]), predict(r, dev, after)
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
                    where.append({"t0": round(r.t0 + w["t0"], 6), "t1": round(r.t0 + w["t1"], 6),
                                  "channel": c, "energy": w["energy"],
                                  "why": f"{locate.describe_window(ctx, w['k0'], w['k1'])}; {c} residual rms "
                                         f"{np.sqrt(np.mean(e0[sl] ** 2)):.3g} -> {np.sqrt(np.mean(e1[sl] ** 2)):.3g}",
                                  **({"recording": r.name} if len(recs) > 1 else {})})
                if band is None:
                    band = improvement_band(e0, e1, 1 / r.dt)
        where.sort(key=lambda w: -w.pop("energy"))
        cmp = f["cmp"]
        rmse_after = f["rmse_after"]
        conf = _confidence(cmp, name, f["alt_share"])
        out_findings.append({
            # the channel where it shows most; "channels": every recorded channel it acts on
            "effect": name, "channel": max((c for c in mech.channels if c in cmp["channels"]),
                                           key=lambda c: cmp["channels"][c]["explained"]),
            "channels": [c for c in mech.channels if c in cmp["channels"]],
            "confidence": round(conf, 3), "where": where[:5], "band_hz": band,
            "parameters": describe_parameters(name, p_final if name in struct_final.effects else after, dev, dt),
            "rmse_after": rmse_after,
            "evidence": {
                "explained_share": {c: round(v["explained"], 4) for c, v in cmp["channels"].items()},
                "explained_share_heldout": {c: round(v["explained_heldout"], 4) for c, v in cmp["channels"].items()},
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
        })
    # final residual tests and what is still unexplained
    final_preds = [predict(r, dev, p_final) for r in recs]
    final_rmse = _heldout_rmse(recs, [{c: r.sign.get(c, 1) * pr[c] for c in ("x", "us")}
                                      for r, pr in zip(recs, final_preds)])
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
        where_range = _range_sentence(e0, r0.u, ctxs[0]["rate"], noise[c])
        trend = _trend(e0, r0.t, noise[c])
        if trend and struct_rms > 0.5 * noise[c]:
            unexplained.append({
                "channel": c, "band_hz": [0.0, round(2.0 / max(float(r0.t[-1]), 1e-9), 4)], "peak_hz": 0.0,
                "rms": trend["rms"], "coherence_with_input": None,
                "description": (f"a slow trend of {c} over the recording ({trend['change']:+.3g} from start to end, "
                                f"{100 * trend['share']:.0f} % of the structured residual), not tied to the "
                                "input's changes: a drifting offset of the channel, not in the catalogue"
                                + (" (a displacement drift would be thermal_drift, but it was not supported)"
                                   if c == "x" else "")),
                "where": [{"t0": round(r0.t0, 6), "t1": round(r0.t0 + float(r0.t[-1]), 6),
                           "why": "the whole recording"}],
            })
        if struct_rms > 0.5 * noise[c] and struct_rms > 0.002 * float(np.std(np.concatenate(
                [getattr(r, c) for r in recs if getattr(r, c) is not None]))):
            for r, e in e_all:
                ctx = ctxs[recs.index(r)]
                for b in locate.bands(e, r.u, 1 / r.dt, noise[c], min_share=0.1):
                    if b["rms"] < 0.3 * noise[c]:
                        continue
                    score = np.clip(_bandpass(e, b["band_hz"], 1 / r.dt) ** 2, 0, None)
                    wins = locate.windows(score, ctx, 2.0 * float(np.mean(score)), max_windows=3,
                                          min_len_s=max(0.02, 0.002 * r.t[-1]))
                    unexplained.append({
                        "channel": c, "band_hz": b["band_hz"], "peak_hz": b["peak_hz"], "rms": b["rms"],
                        "coherence_with_input": round(b["coherence"], 3),
                        "description": _describe_band(b, noise[c], _dominant_freq(r.u, r.dt))
                                       + (f"; {where_range}" if where_range else ""),
                        "where": [{"t0": round(r.t0 + w["t0"], 6), "t1": round(r.t0 + w["t1"], 6),
                                   "why": locate.describe_window(ctx, w["k0"], w["k1"])} for w in wins],
                    })
    unexplained.sort(key=lambda u: -u["rms"])
    final_struct_rms = {c: tests[c]["structured_rms"] for c in tests}
    nothing_missing = not out_findings and all(final_struct_rms[c] <= 0.5 * noise[c] for c in final_struct_rms)
    if nothing_missing:
        verdict = ("nothing is missing: the recalibrated nominal model explains the recording down to the "
                   "noise (structured residual below half the noise level on every channel)")
    elif out_findings:
        verdict = "missing physics: " + ", ".join(f["effect"] for f in out_findings)
        if unexplained:
            verdict += "; some structured residual remains unexplained (see 'unexplained')"
    elif unexplained:
        verdict = ("a structured residual remains that no catalogue mechanism explains (see 'unexplained'); "
                   "no mechanism is named")
    else:
        verdict = "no catalogue mechanism is supported by the data; the remaining residual is close to the noise"
    first = recs[0]
    block_s = float(first.t[-1] / (np.max(first.block) + 1))
    return {
        "recordings": [{"file": r.name, "samples": int(r.n), "dt_s": r.dt, "duration_s": float(r.t[-1]),
                        "channels": r.channels(), "sign": r.sign} for r in recs],
        "baseline": {"rmse": base_rmse, "nrmse": nrmse(recs, base_rmse),
                     "nominal_as_given_rmse": nominal_as_given,
                     "structured_rms": base_struct_rms, "noise": noise,
                     "recalibrated": _recal_summary(p_base, dev),
                     "structure": list(struct_nom.effects)},
        "localisation": loc_base,
        "findings": out_findings,
        "rejected": rejected,
        "unexplained": unexplained[:5],
        "final": {"effects": list(struct_final.effects), "rmse": final_rmse, "nrmse": nrmse(recs, final_rmse),
                  "structured_rms": final_struct_rms, "tests": tests, "verdict": verdict,
                  "nothing_missing": nothing_missing},
        "validation": {
            "method": "interleaved blocks: each recording is cut into equal consecutive blocks; every "
                      f"{HELDOUT_EVERY}th block (starting with block {HELDOUT_EVERY // 2}) is held out",
            "blocks_per_recording": int(np.max(first.block) + 1), "block_s": block_s,
            "heldout_fraction": float(np.mean(np.concatenate([r.heldout for r in recs]))),
            "fitted_on": "the other blocks only (every parameter, every candidate)",
            "simulation": "the model is driven by the recorded command through the whole recording "
                          "(held-out blocks included); only the measured outputs of held-out blocks are "
                          "withheld from fitting",
            "selection": "candidates are accepted on training-row statistics (likelihood ratio, BIC with "
                         "effective sample size) and on held-out improvement (share of the structured "
                         "residual removed, one-sided test over held-out blocks); every rmse reported is "
                         "over held-out samples",
            "thresholds": ACCEPT,
        },
        "notes": notes,
    }


def _bandpass(e, band, fs):
    from scipy.signal import butter, sosfiltfilt

    lo, hi = band
    ny = fs / 2
    lo = max(lo, 1e-3 * ny)
    hi = min(max(hi, lo * 1.2), 0.99 * ny)
    try:
        sos = butter(2, [lo / ny, hi / ny], btype="band", output="sos")
        return sosfiltfilt(sos, e)
    except ValueError:
        return e - np.mean(e)


def _trend(e, t, noise):
    """A quadratic trend in time that carries most of a structured residual, or ``None``."""
    tn = t / max(float(t[-1]), 1e-12)
    a = np.vstack([np.ones_like(tn), tn, tn * tn]).T
    coef, *_ = np.linalg.lstsq(a, e, rcond=None)
    fit = a @ coef
    structured = max(float(np.mean(e * e)) - noise ** 2, 0.0)
    trend_var = float(np.var(fit))
    if structured <= 0 or trend_var < 0.5 * structured or math.sqrt(trend_var) < 0.5 * noise:
        return None
    return {"rms": math.sqrt(trend_var), "change": float(fit[-1] - fit[0]),
            "share": min(1.0, trend_var / structured)}


def _range_sentence(e, u, rate, noise):
    """Where over the operating range a residual is largest, when it clearly depends on it."""
    rng = locate.operating_range(e, u, rate)
    parts = []
    for key, label, unit in (("rate", "command rate", "V/s"), ("amplitude", "command level", "V")):
        rows = rng.get(key, [])
        if len(rows) < 3:
            continue
        rms = np.array([r["rms"] for r in rows])
        struct = np.sqrt(np.clip(rms ** 2 - noise ** 2, 0.0, None))
        k_hi, k_lo = int(np.argmax(struct)), int(np.argmin(struct))
        if struct[k_hi] > 1.5 * struct[k_lo] + 0.2 * noise:
            lo, hi = rows[k_hi]["range"]
            parts.append(f"largest at {label} {lo:.3g}-{hi:.3g} {unit} ({rms[k_hi]:.3g} rms against "
                         f"{rms[k_lo]:.3g} at {rows[k_lo]['range'][0]:.3g}-{rows[k_lo]['range'][1]:.3g} {unit})")
    return "; ".join(parts)


def _dominant_freq(u, dt):
    """Frequency [Hz] of a command dominated by one periodic component (else ``None``)."""
    u = np.asarray(u, float) - np.mean(u)
    if u.size < 16:
        return None
    spec = np.abs(np.fft.rfft(u * np.hanning(u.size))) ** 2
    spec[0] = 0.0
    k = int(np.argmax(spec))
    share = float(np.sum(spec[max(1, k - 3):k + 4]) / max(np.sum(spec), 1e-300))
    if share < 0.5 or k < 1 or k >= spec.size - 1:
        return None
    a, b, c = np.log(spec[k - 1:k + 2] + 1e-300)
    off = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) != 0 else 0.0
    return float((k + off) / (u.size * dt))


def _describe_band(b, noise, f0=None):
    lo, hi = b["band_hz"]
    width = hi - lo
    harmonic = None
    if f0:
        k = round(b["peak_hz"] / f0)
        if k >= 1 and abs(b["peak_hz"] - k * f0) <= max(0.03 * k * f0, b.get("df", 0.0)):
            harmonic = k
    if harmonic:
        rel = (f"harmonic {harmonic} of the command's {f0:.4g} Hz: a periodic, phase-locked response to the "
               "input that the model's loop shape (or another rate-independent nonlinearity) gets wrong")
        if harmonic % 2 == 0:
            rel += ("; an even harmonic means an asymmetry the symmetric play operators cannot draw (e.g. an "
                    "asymmetric loop, or a displacement sensor that is not linear, like a capacitive gap sensor)")
    elif b["coherence"] > 0.5:
        rel = "coherent with the command: a response to the input that the model gets wrong"
    elif b["coherence"] > 0.2:
        rel = "partly coherent with the command"
    else:
        rel = "not coherent with the command: a disturbance or an interference, not a response to the input"
    if width <= max(4.0 * b.get("df", 0.0), 0.25 * b["peak_hz"]) and b["peak_hz"] > 0:
        kind = f"narrow-band line at {b['peak_hz']:.4g} Hz"
    elif hi < 2.0:
        kind = f"slow residual below {hi:.3g} Hz"
    else:
        kind = f"broad-band residual {lo:.4g}-{hi:.4g} Hz"
    return f"{kind}, {b['rms']:.3g} rms ({b['rms'] / noise:.2g} x the noise), {rel}"


def _recal_summary(p, dev):
    return {"amplifier_tau_s": float(f"{p.tau:.5g}"), "u_norm_V": p.u_norm,
            "pi_scale": float(f"{np.sum(p.weights):.6g}"), "x_offset": float(f"{p.off_x:.6g}"),
            "sensor_sensitivity_V_per_N": float(f"{p.S:.6g}"), "sensor_offset_V": float(f"{p.off_s:.6g}")}
