"""Mechanisms that pass only together (piezo_fmu.diagnose.pairs), or once a loop that hid one went in."""
import pytest

from piezo_fmu.diagnose import select


def test_creep_and_a_drift_failing_alone_on_the_bic_gain_are_named_together(rig_diagnosis, monkeypatch):
    # rig-d29-059: creep and a drift (1.54 kHz). Alone each took half the slow residual with the
    # held-out data taking it (beta 1.14 and 1.11), but the slow residual left few effective samples:
    # BIC gains 7.0 and 7.5 < 10 and nothing was named. Fitted together they gain 515.9; the drift
    # goes in first and creep then passes on its own (measured stop 84)
    said = []
    monkeypatch.setattr(select, "slow_pair", _spy(select.slow_pair, said))
    res = rig_diagnosis("rig-d29-059")
    assert said.count(True) == 1
    assert res["final"]["effects"] == ["creep", "thermal_drift"], res["final"]["verdict"]
    assert all(f["confidence"] >= 0.5 for f in res["findings"])
    assert all(res["final"]["rmse"][c] < res["baseline"]["rmse"][c] for c in ("x", "us"))
    # without the pair nothing is named
    monkeypatch.setattr(select, "slow_pair", lambda *a, **k: None)
    res = rig_diagnosis("rig-d29-059")
    assert res["final"]["effects"] == []


def _spy(fn, said):
    def spy(*a, **k):
        out = fn(*a, **k)
        said.append(out is not None)
        return out
    return spy


@pytest.mark.machine_dependent("rig-d30-068's recalibration re-fit diverges (2.98e5 -> 1.11e6) and a drift "
                                "is named for creep and a leakage (stop 94)")
def test_creep_takes_a_drift_s_place_when_it_fits_better_by_the_evidence_a_name_needs(rig_diagnosis):
    # rig-d30-068: creep (log law, 3.3 decades over 16.4 s: up in a 9.8 s hold at 30 V, down after the
    # return to 0 V) and a sensor leakage (8.4 s, 96 x the noise on the sensor). Round 1 fitted the
    # drift first (screening 0.95 against creep's 0.41) and creep, measured against the leakage not yet
    # in, made the sensor 9.5 % worse; once the leakage was in, the drift had taken creep's place and
    # the drift was named (stop 85). Creep in the drift's place, checked at the end, fits better by
    # BIC 51.8 (training cost 8423 -> 2128): creep is named, the drift is not (measured stop 86)
    res = rig_diagnosis("rig-d30-068")
    assert sorted(res["final"]["effects"]) == ["creep", "sensor_leakage"], res["final"]["verdict"]
    assert all(f["confidence"] >= 0.5 for f in res["findings"])
    why = next(r["why"] for r in res["rejected"] if r["effect"] == "thermal_drift")
    assert why.startswith("creep in its place fits better"), why
    creep = next(f for f in res["findings"] if f["effect"] == "creep")
    assert creep["evidence"]["strongest_alternative"]["effect"] == "thermal_drift"
    assert all(res["final"]["rmse"][c] < res["baseline"]["rmse"][c] for c in ("x", "us"))


def test_a_command_holds_still_where_it_stays_within_a_percent_of_its_span_measured_or_exact():
    import numpy as np

    from piezo_fmu.diagnose.residuals import holds_still

    dt = 1e-3
    t = np.arange(0.0, 4.0, dt)
    rng = np.random.default_rng(0)
    assert not holds_still(np.sin(2 * np.pi * t), dt)                        # a 1 Hz sine never does
    assert not holds_still(np.sin(2 * np.pi * (0.5 + 5 * t) * t), dt)       # nor a chirp
    hold = np.where(t < 1.0, np.sin(2 * np.pi * t), 0.0)                    # a sine, then 3 s at 0 V
    assert holds_still(hold, dt)
    # measured: noise of 0.002 rms (0.1 % of the span) on the hold still holds; a slow ramp (3 % of the
    # span in 0.2 s) does not
    assert holds_still(hold + 0.002 * rng.standard_normal(t.size), dt)
    assert not holds_still(np.where(t < 1.0, np.sin(2 * np.pi * t), 0.25 * (t - 1.0)), dt)


def test_creep_is_not_named_where_the_command_never_holds_still(rig_diagnosis):
    # rig-d31-101: a probe-quantisation control (no catalogue mechanism), a triangle and three chirps
    # at 811 Hz, a Bouc-Wen loop: creep of 4 ms and 0.13 s was named at 0.91 (stop 86's draw 31),
    # a rate-dependent misfit of the loop. Without a hold creep cannot be told from that: refused
    res = rig_diagnosis("rig-d31-101")
    assert res["final"]["effects"] == [], res["final"]["verdict"]
    assert any(r["effect"] == "creep" and "never holds still" in r["why"] for r in res["rejected"]), res["rejected"]


def test_a_warm_up_the_sensor_follows_is_named_alone_not_beside_creep(rig_diagnosis, monkeypatch, rules_before):
    # rig-d38-170 (382 Hz, 19.5 s): a thermal warm-up of -0.14 um settling with 3.4 s, the sensor on
    # the push rod (the drift reaches it: 6.2 noise rms there), a decaying triangle, then 9 s at rest.
    # While a drift the sensor follows could only be a quadratic, it bent on through the rest where
    # the data had settled: refused in round 1 by the hold test, creep took its place and the drift
    # was named beside it in round 2 (draw 38: creep named falsely). Its warm-up on the load spring
    # settles within the record: the drift alone (measured stop 94)
    import math

    from piezo_fmu.diagnose import catalogue, drifts
    from piezo_fmu.diagnose.starts import with_params

    res = rig_diagnosis("rig-d38-170")
    assert res["final"]["effects"] == ["thermal_drift"], res["final"]["verdict"]
    drift = next(f for f in res["findings"] if f["effect"] == "thermal_drift")
    assert drift["parameters"]["time_constant_s"] == pytest.approx(3.44, rel=0.35), drift["parameters"]
    assert drift["evidence"]["explained_share"]["us"] > 0.9, drift["evidence"]     # it reaches the sensor
    assert all(res["final"]["rmse"][c] < res["baseline"]["rmse"][c] for c in ("x", "us"))
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # the rule before: a drift on the load spring a quadratic only (its warm-up on the other pick-offs)
    start, alternatives = drifts.drift_start, select.drift_alternatives

    def quadratic_on_load(fitter, p):
        return p.copy() if p.pick == "load" else start(fitter, p)

    def warm_up_elsewhere(fitter, s, cctx):
        out = [a for a in alternatives(fitter, s, cctx) if not (a.pick == "load" and math.isfinite(a.drift_tau))]
        if s.pick == "load" and not math.isfinite(s.drift_tau) and "us" in cctx["channels"]:
            warm = start(fitter, with_params(s, pick="stack"))
            out += [warm] + ([with_params(warm, pick="contact")] if "mech_f" in fitter.ordinary else [])
        return out

    monkeypatch.setattr(catalogue, "drift_start", quadratic_on_load)
    monkeypatch.setattr(select, "drift_alternatives", warm_up_elsewhere)
    assert "creep" in rig_diagnosis("rig-d38-170")["final"]["effects"]


def test_two_mechanisms_that_each_spoil_the_other_s_channel_alone_are_named_together(rig_diagnosis, monkeypatch,
                                                                                      rules_before):
    # rig-d39-038 (6.06 kHz, 95 k samples): a current limit (69 noise rms in x, 47 in us) and a leaking
    # sensor (26 noise rms in us). Alone, leakage took us's held-out error from 0.031 to 0.0075 V but
    # pulled the shared parameters so that x got 9.2 % worse; the limit alone made x 4.6 % worse:
    # nothing was named ("a structured residual remains"). Fitted together they pass (BIC gain 60353,
    # x 0.068 -> 0.054 um, us 0.038 -> 0.008 V); leakage goes in first and the limit then passes on
    # its own (binds on 29 samples; measured stop 95)
    said = []
    monkeypatch.setattr(select, "cross_pair", _spy(select.cross_pair, said))
    res = rig_diagnosis("rig-d39-038")
    assert said.count(True) == 1
    assert res["final"]["effects"] == ["amplifier_current_limit", "sensor_leakage"], res["final"]["verdict"]
    assert all(f["confidence"] >= 0.5 for f in res["findings"])
    assert all(res["final"]["rmse"][c] < 0.5 * res["baseline"]["rmse"][c] for c in ("x", "us")), res["final"]["rmse"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    monkeypatch.setattr(select, "cross_pair", lambda *a, **k: None)
    assert rig_diagnosis("rig-d39-038")["final"]["effects"] == []


def test_a_loop_the_held_out_data_take_in_part_goes_into_the_recalibration_and_creep_beside_it_is_named(
        rig_diagnosis, monkeypatch, rules_before):
    # rig-d40-113 (708 Hz, 4.6 k samples): creep (4.9 noise rms in x) beside a loop shape (12.5). The
    # finer loop failed on the BIC alone (gain -103) while the held-out data took 0.79 (x) and 0.74 (us)
    # of its correction at z 4.8 and 5.5: under the 0.8 of before it stayed out of the recalibration,
    # its misfit hid the creep (held-out 0.69 of its correction, z 2.2) and nothing was named. Taken in
    # from 0.7 (`loopshape.LOOP_HELDOUT_BETA`), creep passes next round (x 0.023 -> 0.011 um away from
    # the command's jumps; measured stop 96). The loop itself is not named: an ordinary refinement
    said = []
    monkeypatch.setattr(select, "_confirmed_loop", _spy(select._confirmed_loop, said))
    res = rig_diagnosis("rig-d40-113")
    assert True in said
    assert res["final"]["effects"] == ["creep"], res["final"]["verdict"]
    assert res["findings"][0]["confidence"] >= 0.5
    assert res["final"]["rmse"]["x"] < 0.7 * res["baseline"]["rmse"]["x"], res["final"]["rmse"]     # [um]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    monkeypatch.setattr(select, "LOOP_HELDOUT_BETA", (0.8, 1.25))
    assert rig_diagnosis("rig-d40-113")["final"]["effects"] == []
