"""The recalibrated ordinary physics says which of its values the recording determines.

A recalibrated value at a bound of its search range, or with a standard uncertainty larger than
the value, is reported as not determined (``determined`` false, ``why_undetermined``), in
diagnosis.json and in report.html; with two amplifier lag stages the total lag is reported with
its own uncertainty (the stages' covariance), which a record may determine when it cannot split it.
"""
import math

import pytest

from piezo_fmu.diagnose.results import UNDETERMINED

NONLINEAR = ("amplifier_tau_s", "amplifier_tau2_s", "amplifier_total_lag_s", "first_mode_hz", "first_mode_zeta",
             "threshold_scale_V", "saturation_um")


def _rig(case_id):
    from piezo_fmu import rig
    from piezo_fmu.diagnose.run import analyse

    draw = int(case_id.split("-")[1][1:]) if case_id.startswith("rig-d") else 0
    rec = rig.generate(next(s for s in rig.cases(draw=draw) if s.case_id == case_id))
    d = analyse([{"name": case_id, "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}])
    return rec.truth["params"], d


def _check_judged(rc):
    """Every fitted nonlinear value carries a judgement that follows from its own numbers."""
    judged = 0
    for key in NONLINEAR:
        v = rc.get(key)
        if not isinstance(v, dict) or v["value"] <= 0 or (v.get("relative_uncertainty") is None
                                                          and "determined" not in v):
            continue
        judged += 1
        assert "determined" in v, (key, v)
        at_bound = "search_range" in v
        if v["relative_uncertainty"] is None:       # fitted, and no sample responds to it
            assert v["determined"] is False and (at_bound or "changes no sample" in v["why_undetermined"]), (key, v)
            continue
        if at_bound:
            lo, hi = v["search_range"]               # (value and range each rounded to 5-6 digits)
            assert lo * (1 - 1e-4) <= v["value"] <= hi * (1 + 1e-4), (key, v)
            assert min(abs(math.log(v["value"] / lo)), abs(math.log(hi / v["value"]))) <= 0.01 * math.log(hi / lo)
        assert v["determined"] is (not at_bound and v["relative_uncertainty"] <= UNDETERMINED), (key, v)
        assert ("why_undetermined" in v) is (not v["determined"]), (key, v)
    return judged


def test_a_lag_the_recording_cannot_resolve_is_reported_as_not_determined(tmp_path):
    # rig-d3-165: a 0.62 ms amplifier lag sampled at 264 Hz (3.8 ms a sample) behind a current limit.
    # The recalibrated lag (0.10 ms, 1.7e12 x its value as standard uncertainty, stop 44) is six times
    # off the truth: it is reported as not determined, with the reason, in the json and the html.
    # Between samples it decays by exp(-38), below round-off: on some CPUs no sample moves with it
    # at all (stop 61, an Intel Xeon: its Jacobian column exactly zero, and then no value had an
    # uncertainty); it is then reported without a figure, as not determined, and the rest keep theirs
    from piezo_fmu.diagnose.report import write_outputs

    truth, d = _rig("rig-d3-165")
    rc = d.result["baseline"]["recalibrated"]
    assert _check_judged(rc) >= 2
    tau = rc["amplifier_tau_s"]
    assert abs(math.log(tau["value"] / truth["amplifier.tau_output"]["value"])) > math.log(2), tau
    assert tau["determined"] is False and "does not determine" in tau["why_undetermined"], tau
    assert rc["pi_scale_um"]["relative_uncertainty"] is not None, rc["pi_scale_um"]
    write_outputs(d, tmp_path / "out", figures=False)
    html = (tmp_path / "out" / "report.html").read_text()
    assert html.count("not determined:") == sum(1 for k in NONLINEAR if rc.get(k, {}).get("determined") is False)


def test_two_lag_stages_report_their_total_lag():
    # rig-d3-017: a two-stage amplifier (1.70 ms after 0.84 ms, 2.54 ms in all) at 1.22 kHz with a
    # thermal drift. The record cannot split the lag between the stages (stop 45: 1.89 and 0.48 ms, at
    # 1.1 and 3.8 x their values) but fixes their sum: the total lag, with the uncertainty from the
    # stages' covariance (0.47), is determined and lies near the true sum
    truth, d = _rig("rig-d3-017")
    rc = d.result["baseline"]["recalibrated"]
    _check_judged(rc)
    assert rc["amplifier_order"] == 2
    one, two, total = rc["amplifier_tau_s"], rc["amplifier_tau2_s"], rc["amplifier_total_lag_s"]
    assert one["determined"] is False and two["determined"] is False, (one, two)
    assert total["determined"] is True, total
    assert total["value"] == pytest.approx(one["value"] + two["value"], rel=1e-4)
    true_total = truth["amplifier.tau_output"]["value"] + truth["amplifier.tau_internal"]["value"]
    assert abs(total["value"] / true_total - 1) < 0.2, (total, true_total)


def test_a_lag_the_recording_resolves_is_reported_as_determined():
    # the project's own model, clean, under steps and sines at 2 kHz: its amplifier lag is fitted
    # within a few per cent and reported as determined
    from piezo_fmu.diagnose.run import analyse
    from piezo_fmu.diagnose.synth import make_case

    case = make_case(31, [], "low", ["steps", "sines"], fs=2000.0)
    rc = analyse([{"name": "clean", "time": case.t, "u": case.u, "x": case.x, "us": case.us}]).result[
        "baseline"]["recalibrated"]
    assert _check_judged(rc) >= 1
    tau = rc["amplifier_tau_s"]
    assert tau["determined"] is True and tau["relative_uncertainty"] < 0.5, tau


def test_a_parameter_no_sample_responds_to_has_no_figure_and_leaves_the_others_theirs():
    import numpy as np

    from piezo_fmu.diagnose.uncertainty import sensitive

    rng = np.random.default_rng(3)
    r0 = rng.normal(size=200)                       # the residual: norm about 14
    J = rng.normal(size=(200, 3))
    J[:, 1] = 0.0
    assert sensitive(J, r0) == [True, False, True]
    J[:, 1] = 1e-13 * J[:, 0]                       # round-off, not a response
    assert sensitive(J, r0) == [True, False, True]
    J[:, 1] = 1e-6 * rng.normal(size=200)           # weak, but a response
    assert sensitive(J, r0) == [True, True, True]
    assert sensitive(np.zeros((5, 2)), r0[:5]) == [False, False]


def test_the_lag_is_searched_again_once_the_first_mode_has_moved(rig_diagnosis):
    # rig-d26-094 (fresh draw 26, clean: 4.53 kHz, force pick-off, a 0.27 + 0.10 ms amplifier, a
    # 746 Hz first mode at zeta 0.011). Fitted with the nominal mechanics the lag came out 1.65 ms;
    # the mode recalibrated beside it settled at zeta 0.14, and from there a current limit "binding
    # on 8 samples" took the misfit: named on a clean device (stop 79 and 80 code). With the lag
    # searched again over its range once the mode moved and the ordinary parameters refitted from
    # there, the cost falls to 0.08 of what it was: 0.39 ms, the mode lightly damped, nothing named
    res = rig_diagnosis("rig-d26-094")
    assert res["final"]["effects"] == [], res["findings"]
    rc = res["baseline"]["recalibrated"]
    assert rc["amplifier_tau_s"]["value"] < 0.6e-3
    assert rc["first_mode_zeta"]["value"] < 0.1
    # (with LAG_AGAIN_RATIO 0, a bar no fit reaches, the false current limit of before came back;
    # that second diagnosis, 40 s, went for rig-d35-019's below, stop 91)


def test_a_mode_at_its_damping_bound_is_fitted_with_a_second_lag_stage(monkeypatch, rules_before):
    # rig-d26-040 (fresh draw 26, clean: 14.9 kHz, force pick-off, a 2.91 + 0.91 ms amplifier, a
    # 485 Hz first mode at zeta 0.28). A second lag stage beside the nominal mechanics did not pay;
    # the mode beside one stage settled at zeta 0.9, the end of its range: neither was taken, and
    # 17 x the noise rms was left in x, 52 x in us ("a structured residual remains", stop 80 code).
    # Fitted together they take 99 % of the cost: order 2 and the mode, in the contact force
    from piezo_fmu import rig
    from piezo_fmu.diagnose import recalibrate
    from piezo_fmu.diagnose.run import analyse

    rec = rig.generate(next(s for s in rig.cases(draw=26) if s.case_id == "rig-d26-040"))
    truth = rec.truth["params"]
    raw = [{"name": "rig-d26-040", "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}]
    res = analyse(raw, max_rounds=0).result
    rc, noise = res["baseline"]["recalibrated"], res["baseline"]["noise"]
    assert rc["amplifier_order"] == 2 and rc["first_mode_hz"]["identified"]
    assert rc["sensor_follows"]["value"] == "contact"
    f1 = truth["mechanics.f1"]["value"]
    assert abs(math.log(rc["first_mode_hz"]["value"] / f1)) < math.log(1.25)
    lag = truth["amplifier.tau_output"]["value"] + truth["amplifier.tau_internal"]["value"]
    assert rc["amplifier_total_lag_s"]["value"] == pytest.approx(lag, rel=0.15)
    assert res["final"]["rmse"]["x"] < 1.5 * noise["x"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # each alone, as before: neither is taken and the residual stays many times the noise (since stop 95
    # the mode searched afresh beside two stages, `_mode_after_order`, finds them too: switched off here)
    monkeypatch.setattr(recalibrate, "_mode_with_order", lambda fitter, p, struct, free, tried: tried[0])
    monkeypatch.setattr(recalibrate, "_mode_after_order", lambda *a, **k: False)
    res = analyse(raw, max_rounds=0).result
    rc = res["baseline"]["recalibrated"]
    assert rc["amplifier_order"] == 1 and not rc["first_mode_hz"].get("identified")
    assert res["final"]["rmse"]["x"] > 5 * res["baseline"]["noise"]["x"]


def test_the_report_replays_on_the_fit_s_grid_when_the_file_s_times_are_rounded(tmp_path):
    # times written with 8 decimals at 13.2 kHz: the median step is 7.576e-05 s for 7.5757576e-05,
    # and the file's last time (2 s) is 26399.2 of those steps; the report's replay went to the last
    # time and came out a sample short of the fit's 26401 (the diagnosis finished, the report failed)
    import numpy as np

    from piezo_fmu.diagnose import diagnose
    from piezo_fmu.diagnose.synth import make_case

    case = make_case(3, [], "mid", ["steps"], fs=13200.0, duration=2.0)
    path = tmp_path / "rounded.csv"
    cols = case.columns()
    cols["time"] = np.round(cols["time"], 8)
    with open(path, "w") as fh:
        fh.write(",".join(cols) + "\n")
        np.savetxt(fh, np.column_stack(list(cols.values())), delimiter=",", fmt="%.10g")
    t = cols["time"]
    assert round(t[-1] / float(np.median(np.diff(t)))) + 1 < t.size     # the file's grid is short
    d = diagnose([path], out=tmp_path / "out", time_budget_s=2.0, figures=False)
    with open(tmp_path / "out" / "fit.csv") as fh:
        rows = [line for line in fh if line[:1].isdigit() or line[:1] == "-"]
    assert len(rows) == t.size
    assert d.result["check"]["simulate_vs_fit_max_abs"] < 1e-6


def test_the_first_mode_is_fitted_with_a_further_mode_that_hid_it():
    # rig-d35-019 (fresh draw 35: a 144 Hz further mode at zeta 0.005 beside the device's 330 Hz first
    # mode at zeta 0.028, displacement pick-off, 9.38 kHz). Once the further mode is named, every
    # first mode screened with the rest held fits worse (the first mode changes how much the drive
    # rings at 144 Hz, which the lags had taken up: cost 7158 against 2180); the mode stayed nominal
    # and a 0.85 ms delay was named for its phase lag. Fitted with the further mode and the lags, from
    # four frequencies below 0.4 fs, it is found and nothing else is named (stop 91)
    from piezo_fmu.diagnose.recalibrate import BESIDE_FURTHER

    truth, d = _rig("rig-d35-019")
    res = d.result
    assert res["final"]["effects"] == ["extra_resonance"], (res["findings"], res["rejected"])
    mode = res["baseline"]["recalibrated"]["first_mode_hz"]
    assert mode["identified"] and mode["fitted_with"] == BESIDE_FURTHER
    assert abs(math.log(mode["value"] / truth["mechanics.f1"]["value"])) < math.log(1.5)
    _check_judged(res["baseline"]["recalibrated"])
