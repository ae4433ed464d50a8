"""The verdict on a slowly sampled recording with nothing named: what is left may be the stroke's
path between the samples (diagnose.between), not missing physics."""
from __future__ import annotations

import math

import pytest

import piezo_fmu.diagnose.run as run


def test_a_slow_clean_device_leaves_only_the_path_between_its_samples(rig_diagnosis, monkeypatch):
    # rig-d23-071: a clean device sampled at 1.51 kHz. At one step per sample the recalibrated model
    # leaves 2.2 x the noise in x (0.045 um against 0.0207) and the verdict was "a structured
    # residual remains"; refitted with 6 steps per sample it leaves 1.7 x (0.035 um): the path
    # between the samples, nothing missing (measured, stop 76)
    res = rig_diagnosis("rig-d23-071")
    fin, noise = res["final"], res["baseline"]["noise"]
    assert not fin["effects"] and fin["nothing_missing"], fin["verdict"]
    assert "path between the samples" in fin["verdict"]
    fine = fin["refitted_between_samples"]
    assert fine["steps_per_sample"] == 6
    assert fin["structured_rms"]["x"] > 2.0 * noise["x"]                   # at one step per sample
    assert all(fine["structured_rms"][c] <= 2.0 * noise[c] for c in noise)  # with the path between
    # without the refit the verdict is the one of before
    monkeypatch.setattr(run, "between_samples", lambda *a, **k: None)
    res = rig_diagnosis("rig-d23-071")
    assert not res["final"]["nothing_missing"]
    assert res["final"]["verdict"].startswith("a structured residual remains")
    assert "refitted_between_samples" not in res["final"]


@pytest.mark.machine_dependent("rig-d23-118 keeps a structured residual and its verdict is not 'nothing is "
                                "missing' (stop 94)")
def test_a_first_mode_above_the_nyquist_frequency_is_found_between_the_samples(rig_diagnosis):
    # rig-d23-118: a clean device with a 314 Hz first mode (zeta 0.05) sampled at 307 Hz, a
    # 2.6 + 0.6 ms amplifier, steps after two rests. The recalibration's mode search stops at 0.8 x
    # the sample rate and a straight line between the samples cannot ring it: x is left at 2.0 x
    # the noise (0.0270 um against 0.0133). Replayed with 27 steps per sample, a first mode searched
    # up to twice the sample rate leaves 0.96 x (measured, stop 76): nothing missing
    res = rig_diagnosis("rig-d23-118")
    fin, noise = res["final"], res["baseline"]["noise"]
    assert not fin["effects"] and fin["nothing_missing"], fin["verdict"]
    assert res["baseline"]["recalibrated"]["first_mode_hz"]["identified"] is False
    fine = fin["refitted_between_samples"]
    assert fine["steps_per_sample"] == 27
    assert fin["structured_rms"]["x"] > 2.0 * noise["x"]
    assert fine["structured_rms"]["x"] < 1.2 * noise["x"]
    assert fine["first_mode"]["found_here"] and fine["first_mode"]["frequency_hz"] > 0.5 * 307.0


def test_a_missed_mechanism_is_not_taken_for_the_path_between_the_samples(rig_diagnosis):
    # rig-033: creep at 398 Hz, nothing named; the refit between the samples is asked and leaves
    # more than twice the noise: the residual stays "a structured residual remains", not a silent miss
    res = rig_diagnosis("rig-033")
    fin, noise = res["final"], res["baseline"]["noise"]
    assert not fin["effects"] and not fin["nothing_missing"], fin["verdict"]
    fine = fin["refitted_between_samples"]
    assert any(fine["structured_rms"][c] > 2.0 * noise[c] for c in noise)


def test_a_one_sample_delay_beside_a_fast_lag_is_named_between_the_samples(rig_diagnosis, monkeypatch):
    # rig-d24-000: a one-sample delay (1.77 ms at 564 Hz) beside a 0.33 ms amplifier and a 1036 Hz
    # first mode. At one step per sample a 1.07 ms lag and a 120 Hz mode with zeta 0.23 replay the
    # record to the noise and the search named nothing; replayed with 15 steps per sample the delay
    # beside a first mode fits better than any account without it (BIC gain 350, held-out beta 0.93
    # at z 18.6 with the first version of the search; confidence 0.93 with the final one; stop 79)
    res = rig_diagnosis("rig-d24-000")
    fin = res["final"]
    assert fin["effects"] == ["time_delay"], fin["verdict"]
    (f,) = res["findings"]
    assert f["confidence"] >= 0.5 and f["parameters"]["samples"] == 1
    # the model and its report are replayed between the samples from there on
    assert res["recordings"][0]["replay_steps_per_sample"] == 15
    assert all(fin["rmse"][c] < res["baseline"]["rmse"][c] for c in ("x", "us"))
    # without that search the verdict is the one of before: nothing named
    monkeypatch.setattr(run, "delay_between", lambda *a, **k: None)
    res = rig_diagnosis("rig-d24-000")
    assert not res["final"]["effects"]
    assert res["recordings"][0]["replay_steps_per_sample"] == 1


def test_a_delay_is_searched_beside_a_first_mode_recalibrated_below_the_finer_search_span(rig_diagnosis):
    # rig-d31-073: a 1.4 ms delay (3 samples at 2.14 kHz), a second-order 0.3 + 0.1 ms amplifier and a
    # first mode at 260 Hz (0.12 x the sample rate), recalibrated at one step per sample to 201 Hz.
    # The finer search's range for the mode began at 0.15 x the rate (321 Hz), so the delay's fit had
    # its mode at a bound and failed (stop 86's draw 31: nothing named); with the range reaching down
    # to the recalibrated mode the delay is named (confidence 0.89, BIC 4920 better than a second stage)
    res = rig_diagnosis("rig-d31-073")
    fin = res["final"]
    assert fin["effects"] == ["time_delay"], fin["verdict"]
    (f,) = res["findings"]
    assert f["confidence"] >= 0.5
    assert all(fin["rmse"][c] < res["baseline"]["rmse"][c] for c in ("x", "us"))
    assert not any("mech_f" in r["why"] and "bound" in r["why"] for r in res["rejected"]), res["rejected"]


def test_a_current_limit_ramping_the_jumps_over_a_sample_is_named_between_the_samples(rig_diagnosis, monkeypatch):
    # rig-d28-025: sensor leakage and a current limit (Bouc-Wen loop) at 1.24 kHz, a 0.39 ms
    # amplifier and an 819 Hz first mode. At one step per sample a 1.0 + 0.4 ms lag drew the ramps
    # and only the leakage was named; replayed with 7 steps per sample the limit binds on 12 samples
    # and takes the held-out displacement error from 0.033 to 0.021 um (confidence 0.82, stop 82)
    res = rig_diagnosis("rig-d28-025")
    fin = res["final"]
    assert fin["effects"] == ["amplifier_current_limit", "sensor_leakage"], fin["verdict"]
    (f,) = [f for f in res["findings"] if f["effect"] == "amplifier_current_limit"]
    assert f["confidence"] >= 0.5 and "between its samples" in f["evidence"]["note"]
    assert res["recordings"][0]["replay_steps_per_sample"] > 1
    # without that search the limit is not named
    monkeypatch.setattr(run, "limit_between", lambda *a, **k: None)
    res = rig_diagnosis("rig-d28-025")
    assert res["final"]["effects"] == ["sensor_leakage"]
    assert res["recordings"][0]["replay_steps_per_sample"] == 1


def test_a_current_limit_between_the_samples_must_beat_a_second_amplifier_stage(rig_diagnosis, monkeypatch):
    # rig-d29-158: a KP loop with a knee (not named), 751 Hz, a 0.82 + 0.39 ms amplifier and a
    # 283 Hz first mode at zeta 0.020. At one step per sample the amplifier was first order; replayed
    # with 11 steps per sample a limit binding on one sample took the training cost from 9186 to 1705
    # and was named at confidence 1.00. A second amplifier stage in its place fits to 267 (0.80 +
    # 0.38 ms): the limit is refused for it (stop 84)
    res = rig_diagnosis("rig-d29-158")
    assert "amplifier_current_limit" not in res["final"]["effects"], res["final"]["verdict"]
    (why,) = [r["why"] for r in res["rejected"] if r["effect"] == "amplifier_current_limit"
              and "between the samples" in r["why"]]
    assert "second amplifier lag stage" in why
    # without that rival the limit is named
    from piezo_fmu.diagnose import between
    monkeypatch.setattr(between, "_second_stage", lambda *a, **k: (None, 0.0))
    res = rig_diagnosis("rig-d29-158")
    assert "amplifier_current_limit" in res["final"]["effects"]


def test_a_current_limit_may_leave_a_channel_it_hardly_touches_within_a_share_of_its_gain(rig_diagnosis, monkeypatch):
    # rig-d29-039: a current limit alone (Bouc-Wen loop) at 292 Hz, a 336 Hz first mode. Replayed with
    # 28 steps per sample the limit took the sensor voltage's held-out error from 0.00175 to 0.00131 V
    # (0.46 noise rms) and left x 0.014 noise rms worse (z -0.4): named (confidence 0.84, stop 85).
    # rig-103 (a drift alone, a false limit) made x 0.25 of the sensor's gain worse: still refused
    res = rig_diagnosis("rig-d29-039")
    assert res["final"]["effects"] == ["amplifier_current_limit"], res["final"]["verdict"]
    (f,) = res["findings"]
    assert f["confidence"] >= 0.5 and "between its samples" in f["evidence"]["note"]
    res = rig_diagnosis("rig-103")
    assert res["final"]["effects"] == ["thermal_drift"], res["final"]["verdict"]
    assert any("every channel follows" in r["why"] for r in res["rejected"])
    # asked to leave every channel no worse, the true limit is refused as before
    from piezo_fmu.diagnose import between
    monkeypatch.setattr(between, "LIMIT_WORSE_SHARE", 0.0)
    res = rig_diagnosis("rig-d29-039")
    assert not res["final"]["effects"]


def test_a_limit_s_ramps_shorter_than_a_sample_are_counted_by_their_time():
    # the amplifier slews at the limit while its error exceeds slew * tau (core.plant.amp_step); at
    # 400 Hz a 40 V jump at 1e5 V/s beside a 0.1 ms lag ramps for (40 - 10) / 1e5 = 0.3 ms, 0.12 of
    # a sample: no whole step at the limit, yet 0.12 samples' worth per jump, at any replay rate
    import dataclasses

    import numpy as np

    from piezo_fmu.diagnose.engine import device_from_model, limited_samples, params_from_model
    from piezo_fmu.diagnose.recordings import make_recordings
    from piezo_fmu.model import load_model

    fs, jumps = 400.0, 10                                          # [Hz], jumps up and down
    t = np.arange(1600) / fs                                       # [s]
    model = load_model()
    dev, p = device_from_model(model), params_from_model(model, 1 / fs)
    a = 40.0 / dev.k_amp                                           # [V] of command: 40 V at the stack
    u = np.where((t * 2.5).astype(int) % 2 == 1, a, 0.0)           # a jump every 0.4 s
    assert np.count_nonzero(np.diff(u)) == jumps - 1
    (rec,) = make_recordings([{"name": "r", "time": t, "u": u, "x": u, "us": u}])
    p.tau, p.tau2, p.delay, p.slew = 1e-4, 0.0, 0.0, 1e5           # [s], [s], [s], [V/s]
    per_jump = (40.0 - p.slew * p.tau) / p.slew * fs               # [samples]
    whole, ramps = limited_samples(rec, dev, p)
    assert whole == 0 and ramps == pytest.approx((jumps - 1) * per_jump, rel=1e-6)
    fine = dataclasses.replace(rec, oversample=8)
    assert limited_samples(fine, dev, p)[1] == pytest.approx((jumps - 1) * per_jump, rel=1e-6)
    p.slew = 3e5                                                   # slew * tau = 30 V: 10 V to ramp
    assert limited_samples(rec, dev, p)[1] == pytest.approx((jumps - 1) * 10.0 / 3e5 * fs, rel=1e-6)
    p.slew = 2e3                                                   # 19.9 ms ramps: 7 whole samples
    whole, ramps = limited_samples(rec, dev, p)
    assert whole == (jumps - 1) * 7 and ramps == pytest.approx((jumps - 1) * (40.0 - 0.2) / 2e3 * fs, rel=1e-6)
    p.slew = math.inf
    assert limited_samples(rec, dev, p) == (0, 0.0)


def test_a_current_limit_whose_ramps_are_shorter_than_a_sample_is_named(rig_diagnosis, monkeypatch):
    # rig-d35-014: a current limit alone at 423 Hz (a 0.43 ms amplifier, 31 kV/s). The limit fitted at
    # one step per sample (0.08 ms, 266 kV/s) explains 100 % and 87 % of the structured residual and
    # takes the training cost from 10 871 to 5 596, yet slews a whole step on 2 samples only: it was
    # refused as never binding. Its ramps within the steps last 105 samples' worth (stop 91)
    from piezo_fmu.diagnose import catalogue

    res = rig_diagnosis("rig-d35-014")
    assert res["final"]["effects"] == ["amplifier_current_limit"], (res["rejected"], res["candidates"])
    (f,) = res["findings"]
    assert "its ramps within the steps" in f["evidence"]["note"] and f["confidence"] >= 0.5
    # counted by whole steps, as before, it never binds
    monkeypatch.setattr(catalogue, "LIMIT_RAMPS_EXPLAINED", math.inf)
    res = rig_diagnosis("rig-d35-014")
    assert "amplifier_current_limit" not in res["final"]["effects"]
    assert any("never binds" in r["why"] for r in res["rejected"] if r["effect"] == "amplifier_current_limit")
