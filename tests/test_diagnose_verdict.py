"""The verdict and the "before" model it is judged against.

A candidate below ``results.WEAK`` (0.25) confidence is listed, but does not keep a residual
below ``ORDINARY`` noise rms from "nothing is missing"; one at or above it does. The recalibrated
model is not replaced by a refit that fits worse.
"""
import pytest

from piezo_fmu.diagnose import results


def _rig_diagnosis(case_id):
    from piezo_fmu import rig
    from piezo_fmu.diagnose.run import analyse

    draw = int(case_id.split("-")[1][1:])
    rec = rig.generate(next(s for s in rig.cases(draw=draw) if s.case_id == case_id))
    return analyse([{"name": case_id, "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}]).result


@pytest.mark.parametrize("weak", [results.WEAK, 0.0], ids=["rule", "rule-before"])
def test_a_faint_candidate_on_a_clean_device_leaves_nothing_missing(monkeypatch, weak):
    # rig-d4-101: a clean Bouc-Wen device at 657 Hz; a delay screened in as a candidate at confidence
    # 0.10, the residual 1.4 noise rms on both channels. The verdict is "nothing is missing", the
    # delay listed as a candidate; with every candidate counted (the rule before) it was "a
    # structured residual remains"
    monkeypatch.setattr(results, "WEAK", weak)
    res = _rig_diagnosis("rig-d4-101")
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


def test_a_candidate_above_the_faint_level_still_counts():
    # rig-d3-005: a clean device at 503 Hz with a creep candidate at 0.45 and a residual of 0.4 noise
    # rms: a candidate that strong is not passed over ("a structured residual remains")
    res = _rig_diagnosis("rig-d3-005")
    final = res["final"]
    cands = {c["effect"]: c["confidence"] for c in res["candidates"]}
    assert final["effects"] == [] and cands and min(cands.values()) >= results.WEAK, cands
    assert all(t["structured_rms"] <= results.ORDINARY * t["noise"] for t in final["tests"].values())
    assert not final["nothing_missing"], final["verdict"]


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
