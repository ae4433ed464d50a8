"""Where a search starts: ordinary physics fitted while a mechanism was still missing.

The cases come from the recognition study's generator (``diagnose.synth``; the last two from the
independent rig, draw 33): the saturation and the thresholds' voltage scale are fitted before
anything is named, and a large missing mechanism can pull them where its own fit cannot start from
(or a further mode's start, re-solved too briefly, from its place).
"""
import pytest

import piezo_fmu.diagnose.run as run
from piezo_fmu.diagnose import recalibrate, select
from piezo_fmu.diagnose.evaluate import cases
from piezo_fmu.diagnose.run import analyse
from piezo_fmu.diagnose.synth import make_case


def _rig_recording(case_id):
    from piezo_fmu import rig

    rec = rig.generate(next(s for s in rig.cases(draw=int(case_id.split("-")[1][1:])) if s.case_id == case_id))
    return rec, [{"name": case_id, "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}]


def _recording(seed):
    spec = next(s for s in cases() if s["seed"] == seed)
    case = make_case(spec["seed"], spec["effects"], spec["noise"], spec["kinds"],
                     channels=tuple(spec.get("channels", ("x", "us"))))
    raw = [{"name": f"synth-{seed}", "time": case.t, "u": case.u, "x": case.x, "us": case.us}]
    return raw, case.truth


def test_a_leakage_the_saturation_stood_in_for_is_named(monkeypatch, rules_before):
    # synth-1079: the sensor channel alone, its charge leaking with 2.0 s. Without the leakage the
    # recalibration draws the saturation in (3.5 um for the nominal 49) to bend the decays; from
    # there even the true leakage fits to 1.5e4 x the noise cost, and nothing was named
    raw, truth = _recording(1079)
    assert truth["effects"] == ["sensor_leakage"] and raw[0]["x"] is None
    d = analyse(raw)
    assert d.result["final"]["effects"] == ["sensor_leakage"], d.result["final"]["verdict"]
    assert d.p_final.tau_leak == pytest.approx(truth["parameters"]["sensor_leakage"]["tau_leak"], rel=0.05)
    noise = d.search["noise"]["us"]
    assert d.result["final"]["rmse"]["us"] < 1.2 * noise
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # without the search from the nominal saturation (the rule before): nothing is named
    monkeypatch.setattr(select, "SAG_DRAWN", 0.0)
    assert analyse(raw).result["final"]["effects"] == []


def test_a_threshold_scale_pulled_by_missing_physics_is_fitted_again(monkeypatch, rules_before):
    # synth-1055: creep and a 306 Hz mode, the device's thresholds at the nominal 30 V. Fitted
    # before either was in, the thresholds' scale went to 41.5 V; with creep named, the scale asked
    # again returns to 30 V, and the mode is found next
    raw, truth = _recording(1055)
    assert sorted(truth["effects"]) == ["creep", "extra_resonance"]
    d = analyse(raw)
    assert sorted(d.result["final"]["effects"]) == ["creep", "extra_resonance"], d.result["final"]["verdict"]
    assert d.p_final.u_norm == pytest.approx(30.0, rel=0.05)
    f, _ = d.p_final.res
    assert f == pytest.approx(truth["parameters"]["extra_resonance"]["f_n"], rel=0.02)
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # a scale identified once and never asked again (the rule before): 41.5 V, and the mode missed
    fit_scale = recalibrate._threshold_scale

    def once(fitter, rc, struct, sat):
        if rc.report.get("threshold_scale", {}).get("identified"):
            return False
        return fit_scale(fitter, rc, struct, sat)

    monkeypatch.setattr(recalibrate, "_threshold_scale", once)
    d = analyse(raw)
    assert d.p_final.u_norm > 1.3 * 30.0
    assert "extra_resonance" not in d.result["final"]["effects"]


def test_a_delay_beside_a_named_mode_is_fitted_though_its_screening_gained_nothing(monkeypatch, rules_before):
    # synth-1067: a 0.2 ms delay (one sample at 5 kHz) beside a 248 Hz mode. Once the mode is
    # named, the delay's screening (the mode held, whose phase had taken part of the delay) is 31 %
    # worse than the model without it; fitted, it explains 97 % and 95 % of what is left
    raw, truth = _recording(1067)
    assert sorted(truth["effects"]) == ["extra_resonance", "time_delay"]
    d = analyse(raw)
    final = d.result["final"]
    assert sorted(final["effects"]) == ["extra_resonance", "time_delay"], final["verdict"]
    assert d.p_final.delay == pytest.approx(truth["parameters"]["time_delay"]["delay"], abs=0.5 / 5000)
    for c in ("x", "us"):
        assert final["rmse"][c] < 1.1 * d.search["noise"][c]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # fitted only where its screening gained something (the rule before): the delay is missed
    monkeypatch.setattr(select, "beside_named_mode", lambda struct, screened, tried: [])
    assert analyse(raw).result["final"]["effects"] == ["extra_resonance"]


def test_a_delay_a_moved_mode_and_a_second_stage_stood_in_for_is_named(monkeypatch, rules_before):
    # rig-d22-117 (the independent rig at 494 Hz: a Krasnosel'skii-Pokrovskii loop, the first mode
    # at 554 Hz, above the Nyquist frequency): a one-sample delay (2.02 ms) beside a two-stage amplifier
    # (1.19 + 0.65 ms). The recalibration drew it as a 131 Hz mode at damping 0.25 and stages of
    # 1.09 + 1.81 ms; the delay screened worse than that model from every start until it was
    # screened without the mode alone (the second stage kept) and with the lag left beside it
    # split afresh between the stages. Fitted, it explains 94-98 % of the structured residual
    from piezo_fmu import rig
    from piezo_fmu.diagnose import delays

    spec = next(s for s in rig.cases(draw=22) if s.case_id == "rig-d22-117")
    rec = rig.generate(spec)
    assert rec.truth["mechanisms"] == ["time_delay"]
    raw = [{"name": "rig-d22-117", "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}]
    d = analyse(raw)
    final = d.result["final"]
    assert final["effects"] == ["time_delay"], final["verdict"]
    assert d.p_final.delay == pytest.approx(rec.truth["params"]["time_delay.delay"]["value"], abs=0.5 / 494)
    for c in ("x", "us"):
        assert final["rmse"][c] < 1.15 * d.search["noise"][c]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # either rule alone (the code before had neither): the search names nothing, the residual 1.7 x
    # the noise (the delay searched between the samples afterwards, stop 79, switched off: it finds
    # this delay too)
    monkeypatch.setattr(run, "delay_between", lambda *a, **k: None)
    monkeypatch.setattr(delays, "SPLIT_SHARES", ())
    assert analyse(raw).result["final"]["effects"] == []
    monkeypatch.undo()
    monkeypatch.setattr(run, "delay_between", lambda *a, **k: None)
    monkeypatch.setitem(select.ALONE, "time_delay", ("order",))
    assert analyse(raw).result["final"]["effects"] == []


def test_a_delay_that_passed_beside_a_winning_loop_shape_is_fitted_again(monkeypatch, rules_before):
    # rig-141 (the independent rig at 1.5 kHz): a delay beside a loop shape. In round 1 both pass
    # and the finer loop, explaining 0.78 of x against the delay's 0.26, is added; its cells bend
    # to part of the delay's phase lag, and from the model with them the delay screens worse than
    # that model (-0.07) and was never fitted again. Fitted again whatever its screening, it passes
    # (explaining about half of what is left on both channels) and both are named
    from piezo_fmu import rig

    spec = next(s for s in rig.cases() if s.case_id == "rig-141")
    rec = rig.generate(spec)
    assert sorted(rec.truth["mechanisms"]) == ["hysteresis_shape", "time_delay"]
    raw = [{"name": "rig-141", "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}]
    said = []
    d = analyse(raw, say=said.append)
    final = d.result["final"]
    assert sorted(final["effects"]) == ["hysteresis_shape", "time_delay"], final["verdict"]
    assert any("passed beside the finer loop last round: fitted again" in m for m in said)
    assert d.p_final.delay == pytest.approx(rec.truth["params"]["time_delay.delay"]["value"], rel=0.3)
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # the rule switched off: the delay is lost behind the loop shape
    monkeypatch.setattr(select, "REFIT_BESIDE_SHAPE", False)
    assert analyse(raw).result["final"]["effects"] == ["hysteresis_shape"]


def test_a_further_mode_beside_a_deep_saturation_is_screened_with_its_weights_solved_further():
    # rig-d33-120 (4.78 kHz, a KP device): a further mode at 74.6 Hz (zeta 0.005) on the drive, 78 x
    # the noise on x; the recalibration drew a strain saturation at 1.7 um. The mode's start at its
    # place costs 0.44 x the model without it with the weights held; re-solved with one Gauss-Newton
    # step of the saturation every start went the wrong way (1.4 x): the mode screened worse than
    # none, was never fitted, and a loop shape was named in its place. Three steps: 0.16 x
    rec, raw = _rig_recording("rig-d33-120")
    truth = rec.truth["params"]
    assert rec.truth["mechanisms"] == ["extra_resonance"] and rec.truth["hidden"] == ["hysteresis_shape"]
    d = analyse(raw, max_rounds=1)
    assert d.result["final"]["effects"] == ["extra_resonance"], d.result["rejected"]
    f, z = d.p_final.res
    assert f == pytest.approx(truth["extra_resonance.f"]["value"], rel=0.01)
    assert z < 0.02
    # (with one step, the rule before, round 1 named the loop shape and not the mode)


def test_a_damped_further_mode_beside_a_ringing_first_mode_is_read_the_other_way_round():
    # rig-d33-129 (3.94 kHz, the sensor on the push rod): the device's own mode at 278 Hz (zeta 0.19)
    # and a further mode at 548 Hz (zeta 0.007). The further mode's fit took the first mode's place
    # (279 Hz, zeta 0.19) and moved the first mode to 548 Hz, 0.007: it explained 99 % of the
    # residual and was refused, "damping ratio 0.19: not a lightly damped mode". The same two modes
    # the other way round fit as well, and the further mode rings
    rec, raw = _rig_recording("rig-d33-129")
    truth = rec.truth["params"]
    assert rec.truth["mechanisms"] == ["extra_resonance"]
    said = []
    d = analyse(raw, say=said.append, max_rounds=1)
    assert d.result["final"]["effects"] == ["extra_resonance"], d.result["rejected"]
    f, z = d.p_final.res
    assert f == pytest.approx(truth["extra_resonance.f"]["value"], rel=0.01)
    assert z == pytest.approx(truth["extra_resonance.zeta"]["value"], rel=0.2)
    f1, z1 = d.p_final.mode(d.search["fitter"].dev)
    assert f1 == pytest.approx(truth["mechanics.f1"]["value"], rel=0.02)
    assert z1 == pytest.approx(truth["mechanics.zeta1"]["value"], rel=0.2)
    assert any("fits the other way round as well" in s for s in said), said
    # (not exchanged, the rule before, it failed "damping ratio 0.19: not a lightly damped mode" and
    # nothing was named)
