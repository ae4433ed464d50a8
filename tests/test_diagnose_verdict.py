"""The verdict and the "before" model it is judged against.

A candidate below ``results.WEAK`` (0.25) confidence, or one whose correction removes less than
``results.FAINT_REMOVED`` (0.5) x the noise rms from every channel on held-out data, is listed, but
does not keep a residual below ``ORDINARY`` noise rms from "nothing is missing"; one beyond both
does. The recalibrated model is not replaced by a refit that fits worse. A rival taken into the
recalibration after a finding does not keep the finding from being named.
"""
import numpy as np
import pytest

from piezo_fmu.diagnose import results

RULE = results.FAINT_REMOVED      # (the tests below switch it off)


@pytest.mark.parametrize("weak", [results.WEAK, 0.0], ids=["rule", "rule-before"])
def test_a_faint_candidate_on_a_clean_device_leaves_nothing_missing(monkeypatch, weak, rig_diagnosis):
    # rig-d4-101: a clean Bouc-Wen device at 657 Hz; a delay screened in as a candidate at confidence
    # 0.10, the residual 1.4 noise rms on both channels. The verdict is "nothing is missing", the
    # delay listed as a candidate; with every candidate counted (the rule before) it was "a
    # structured residual remains"
    monkeypatch.setattr(results, "WEAK", weak)
    res = rig_diagnosis("rig-d4-101")
    final = res["final"]
    assert final["effects"] == []
    cands = {c["effect"]: c["confidence"] for c in res["candidates"]}
    assert cands and 0 < max(cands.values()) < 0.25, cands
    assert all(t["structured_rms"] <= results.ORDINARY * t["noise"] for t in final["tests"].values())
    if weak:
        assert final["nothing_missing"], final["verdict"]
        assert final["verdict"].startswith("nothing is missing")
        assert all(name in final["verdict"] for name in cands), final["verdict"]
    else:
        assert not final["nothing_missing"], final["verdict"]


@pytest.mark.parametrize("floor", [RULE, 0.0], ids=["rule", "rule-before"])
def test_a_candidate_below_half_the_noise_leaves_nothing_missing(monkeypatch, floor, rig_diagnosis):
    # rig-d3-005: a clean device at 503 Hz with a creep candidate at confidence 0.42 and a residual
    # of 0.3 noise rms: the creep's correction removes less than half the noise rms on both
    # channels, below what the recording can show. The verdict is "nothing is missing", the creep
    # listed; with every candidate from WEAK counted (the rule before) a structured residual remained
    monkeypatch.setattr(results, "FAINT_REMOVED", floor)
    res = rig_diagnosis("rig-d3-005")
    final = res["final"]
    cands = {c["effect"]: c for c in res["candidates"]}
    assert final["effects"] == [] and "creep" in cands, cands
    creep = cands["creep"]
    assert creep["confidence"] >= results.WEAK
    assert max(creep["evidence"]["removed_noise_multiples"].values()) < RULE
    assert all(t["structured_rms"] <= 0.5 * t["noise"] for t in final["tests"].values())
    if floor:
        assert final["nothing_missing"] and final["verdict"].startswith("nothing is missing"), final["verdict"]
        assert "creep (0.4" in final["verdict"], final["verdict"]
    else:
        assert not final["nothing_missing"], final["verdict"]


def test_a_candidate_above_the_faint_level_still_counts(rig_diagnosis):
    # rig-135: a control (a disturbance off the catalogue) with a creep candidate at 0.31 whose
    # correction removes 1.6 x the noise rms from x on held-out data, the residual below ORDINARY:
    # a candidate that strong is not passed over ("a structured residual remains")
    res = rig_diagnosis("rig-135")
    final = res["final"]
    cands = {c["effect"]: c for c in res["candidates"]}
    assert final["effects"] == [] and cands, cands
    assert min(c["confidence"] for c in cands.values()) >= results.WEAK, cands
    assert max(max(c["evidence"]["removed_noise_multiples"].values()) for c in cands.values()) >= results.FAINT_REMOVED
    assert all(t["structured_rms"] <= results.ORDINARY * t["noise"] for t in final["tests"].values())
    assert not final["nothing_missing"], final["verdict"]


def test_a_rival_taken_into_the_recalibration_leaves_the_finding_unique(rig_diagnosis):
    # rig-d28-073: sensor leakage and a thermal drift (3.75 kHz). In round 2 the drift (BIC gain 4774)
    # had a delay beside it as its rival (it passed, explaining 0.31 of x against the drift's 0.61:
    # uniqueness 0.19, confidence 0.43, a candidate); in round 3 that delay was the amplifier's
    # second lag stage and went into the recalibration. With it there the backward check keeps the
    # drift's evidence (BIC gain 4331): the rival explained another part, and the drift is named
    # (confidence 0.998; measured stop 83). rig-179's false drift, whose rival became the first
    # mode, fell from 4393 to 107 beside it and stays a candidate (not run here: 22 s)
    res = rig_diagnosis("rig-d28-073")
    assert res["final"]["effects"] == ["sensor_leakage", "thermal_drift"], res["final"]["verdict"]
    assert res["baseline"]["recalibrated"]["amplifier_order"] == 2
    drift = next(f for f in res["findings"] if f["effect"] == "thermal_drift")
    rival = drift["evidence"]["strongest_alternative"]
    assert rival["effect"] == "time_delay" and rival["taken_into_recalibration"]
    assert drift["confidence"] >= 0.9
    assert all(res["final"]["rmse"][c] < res["baseline"]["rmse"][c] for c in ("x", "us"))


def test_the_recalibrated_model_is_not_replaced_by_a_worse_refit():
    # rig-d4-008: the recalibrated model, re-fitted once the channels' weights were set, ended at a
    # training cost of 2.9e11 against 2.9e5 as it came (the refit starts from its weights re-solved,
    # and the saturation's Gauss-Newton steps went astray). That refit was the diagnosis's "before":
    # 25.9 um held-out rmse in x for a 0.03 um misfit, every candidate "explaining 100 %" of it and
    # a false current limit named. The model as it came is kept when it fits better
    from piezo_fmu import rig
    from piezo_fmu.diagnose.run import analyse

    rec = rig.generate(next(s for s in rig.cases(draw=4) if s.case_id == "rig-d4-008"))
    kept = []
    d = analyse([{"name": "rig-d4-008", "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}],
                say=lambda msg: kept.append(msg) if "kept as it was" in msg else None, time_budget_s=5.0)
    rmse = d.result["baseline"]["rmse"]
    assert kept
    assert rmse["x"] < 0.1 and rmse["us"] < 0.05, rmse          # [um], [V]
    assert "amplifier_current_limit" not in d.result["final"]["effects"]


def test_a_search_that_ends_worse_than_the_refitted_nominal_model_starts_again(monkeypatch):
    # rig-d29-050, clean (Bouc-Wen loop, 5.16 kHz): the recalibration's threshold scale settled at
    # 1.44 x the recording's span, 0.047 um held out in x against a noise of 0.0087 um; a current
    # limit took part of that (confidence 0.87) and was named. The nominal model refitted after the
    # search fitted the held-out data better than the final one (x 0.017 against 0.041 um) at a
    # lower training cost: the search starts again from it and names nothing (measured stop 84).
    # Since stop 96 the finer loop leaves out the play operators the training rows barely see move
    # (`catalogue._plays_supported`) and the first search names nothing (x 0.0157 um held out): the
    # search's new start is checked with that rule off, as before
    from piezo_fmu import rig
    from piezo_fmu.diagnose import catalogue
    from piezo_fmu.diagnose.run import analyse

    rec = rig.generate(next(s for s in rig.cases(draw=29) if s.case_id == "rig-d29-050"))
    raw = [{"name": "rig-d29-050", "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}]
    again = []
    now = analyse(raw, say=lambda msg: again.append(msg) if "starts again" in msg else None).result
    assert not again and now["final"]["effects"] == [], now["final"]["verdict"]
    assert now["final"]["rmse"]["x"] < 0.02, now["final"]["rmse"]           # [um]
    monkeypatch.setattr(catalogue, "_plays_supported", lambda fitter, q: np.ones(len(q.thresholds), bool))
    res = analyse(raw, say=lambda msg: again.append(msg) if "starts again" in msg else None).result
    assert len(again) == 1
    assert res["final"]["effects"] == [], res["final"]["verdict"]
    assert res["final"]["nothing_missing"], res["final"]["verdict"]
    assert res["final"]["rmse"]["x"] < 0.02, res["final"]["rmse"]           # [um]
    assert any("searched again" in n for n in res["notes"])


def test_a_second_lag_stage_and_a_mode_each_refused_alone_are_recalibrated_together(rig_diagnosis, monkeypatch,
                                                                                      rules_before):
    # rig-d39-092 (clean, 2.25 kHz): an amplifier of two stages (1.28 + 0.62 ms) and a first mode at
    # 715 Hz (zeta 0.016) in the sensor's contact force. A second stage alone took x from 0.030 to
    # 0.021 um but made the sensor worse (the mode it rings with not yet in): BIC -968; the mode beside
    # one stage settled at its damping bound (0.35) and with a second stage started from there too.
    # The residual, 2.2 x the noise in x, was left as "a structured residual remains". The mode searched
    # again beside two stages: 710.7 Hz, 1.33 + 0.57 ms, nothing is missing (measured stop 95)
    from piezo_fmu.diagnose import recalibrate

    res = rig_diagnosis("rig-d39-092")
    rc = res["baseline"]["recalibrated"]
    assert res["final"]["effects"] == [] and res["final"]["nothing_missing"], res["final"]["verdict"]
    assert rc["amplifier_order"] == 2
    assert rc["amplifier_tau2_s"]["value"] == pytest.approx(0.62e-3, rel=0.3), rc["amplifier_tau2_s"]
    assert rc["first_mode_hz"]["identified"]
    assert rc["first_mode_hz"]["value"] == pytest.approx(715.1, rel=0.02), rc["first_mode_hz"]
    assert res["baseline"]["rmse"]["x"] < 1.2 * res["baseline"]["noise"]["x"], res["baseline"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    monkeypatch.setattr(recalibrate, "_mode_after_order", lambda *a, **k: False)
    res = rig_diagnosis("rig-d39-092")
    assert not res["final"]["nothing_missing"] and res["baseline"]["recalibrated"]["amplifier_order"] == 1
