"""The order in which a search round fits what it screened: a loop shape goes behind the physical
mechanisms that screened close to it, so a round whose budget ends after one fit tries them."""
from __future__ import annotations

from piezo_fmu.diagnose.rivals import SHAPE_LAST, shape_after_physics


def _screened(**gains):
    # (gain, name, start, alternatives), best first, as select's screening gives them
    return sorted(((g, n, None, []) for n, g in gains.items()), key=lambda s: -s[0])


def test_a_physical_mechanism_screened_close_to_the_loop_shape_is_fitted_before_it():
    # rig-d29-061's round 2: the shape 0.215, a delay 0.209, a further mode 0.194, leakage below zero
    got = [s[1] for s in shape_after_physics(_screened(hysteresis_shape=0.215, time_delay=0.209,
                                                       extra_resonance=0.194, sensor_leakage=-0.0256))]
    assert got == ["time_delay", "extra_resonance", "hysteresis_shape", "sensor_leakage"]


def test_a_loop_shape_well_ahead_keeps_its_place():
    gains = dict(hysteresis_shape=0.5, creep=0.99 * SHAPE_LAST * 0.5, thermal_drift=0.1)
    assert [s[1] for s in shape_after_physics(_screened(**gains))] == ["hysteresis_shape", "creep",
                                                                         "thermal_drift"]
    # ... and a round without a loop shape, or with one that gains nothing, is left as screened
    assert [s[1] for s in shape_after_physics(_screened(creep=0.3, thermal_drift=0.2))] == ["creep",
                                                                                           "thermal_drift"]
    neg = _screened(creep=-0.1, hysteresis_shape=-0.05, thermal_drift=-0.2)
    assert shape_after_physics(neg) == neg


def test_a_round_whose_budget_ends_after_one_fit_tries_the_delay_beside_a_drift(rig_diagnosis):
    # rig-d29-061: a 5-sample delay (0.48 ms at 10.5 kHz, beside a 0.94 + 0.24 ms amplifier) and a
    # drift. Round 1 named the drift; round 2 screened the shape 0.215 and the delay 0.209, fitted the
    # shape (taken into the recalibration, not named) and the budget ended: the delay was missed.
    # Fitted first, it passes and is named (confidence 0.94, stop 85); the budget is work, not time,
    # so this holds on any machine and load
    res = rig_diagnosis("rig-d29-061")
    assert res["final"]["effects"] == ["thermal_drift", "time_delay"], res["final"]["verdict"]
    assert all(f["confidence"] >= 0.5 for f in res["findings"])
