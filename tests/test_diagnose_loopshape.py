"""How far a fitted loop lies from every classical PI loop (``diagnose.loopshape``)."""
import numpy as np
import pytest

from piezo_fmu.core.preisach import grid_cells
from piezo_fmu.diagnose.engine import device_from_model, params_from_model, predict
from piezo_fmu.diagnose.fit import Fitter
from piezo_fmu.diagnose.loopshape import beyond_classical, further_from_nominal
from piezo_fmu.diagnose.recordings import make_recordings
from piezo_fmu.model import load_model

FS = 2000.0                                    # [Hz]


def _fitter_and_model():
    """A 4 s record of nested triangles (minor loops at two levels) and the paper's model."""
    t = np.arange(int(4 * FS)) / FS
    tri = lambda f: 2 * np.abs(((t * f) % 1.0) - 0.5)          # 0..1
    u = np.where(t < 2, 6.0 * tri(1.0), 3.0 + 2.0 * tri(3.0))  # [V] command
    model = load_model()
    dev, p = device_from_model(model), params_from_model(model, 1 / FS)
    recs = make_recordings([{"name": "r", "time": t, "u": u, "x": 0.1 * u, "us": 0.001 * u}])
    return Fitter(recs, dev, {"x": 1.0, "us": 1.0}), p


def _with_cells(p, fitter, weight):
    """``p`` with a 6-step KP grid whose only weighted cells switch up near the top and back down
    above the middle (a band of domains switching at fixed voltages, off the loop's centre: full
    cycles alone would let a classical loop draw a band centred on them), ``weight`` [um] each."""
    q = p.copy()
    v = fitter.recs[0].u * fitter.dev.k_amp / q.u_norm
    up, down, width = grid_cells(min(float(v.min()), 0.0), float(v.max()), 6)
    band = (up > 0.8 * v.max()) & (down > 0.45 * v.max())
    q.cells = np.array([up, down, width])
    q.cell_w = np.where(band, weight, 0.0)
    return q


def test_a_classical_loop_is_zero_and_a_switching_band_is_not():
    fitter, p = _fitter_and_model()
    assert np.all(np.asarray(p.weights) >= 0)            # the paper's PI: a classical loop
    x = predict(fitter.recs[0], fitter.dev, p)["x"]
    noise = {"x": 0.01 * float(np.ptp(x)), "us": 1.0}
    clean = beyond_classical(fitter, p, noise)
    assert clean["x"] < 0.05, clean
    shaped = _with_cells(p, fitter, 0.02 * float(np.ptp(x)))
    got = beyond_classical(fitter, shaped, noise)
    assert got["x"] > 20 * max(clean["x"], 0.05), (clean, got)
    # in multiples of the noise: ten times the noise, a tenth of the figure
    quieter = beyond_classical(fitter, shaped, {c: 10 * s for c, s in noise.items()})
    assert quieter["x"] == pytest.approx(got["x"] / 10, rel=1e-9)


def test_a_negative_weight_that_keeps_the_partial_sums_positive_is_not_classical():
    # the recalibrated PI only keeps its weights' partial sums positive: a negative weight draws a
    # loop no classical PI draws (the recalibration can bend part of a loop shape in this way)
    fitter, p = _fitter_and_model()
    w = np.asarray(p.weights, float).copy()
    q = p.copy()
    q.weights = w.copy()
    q.weights[3] = -0.25 * w.sum()                 # a negative weight at a middle threshold ...
    q.weights[6] += 0.25 * w.sum() + w[3]           # ... the same stroke from a higher one
    assert np.all(np.cumsum(q.weights) > 0) and q.weights.sum() == pytest.approx(w.sum())
    x = predict(fitter.recs[0], fitter.dev, p)["x"]
    noise = {"x": 0.01 * float(np.ptp(x)), "us": 1.0}
    classical = beyond_classical(fitter, p, noise)["x"]
    assert classical < 0.05
    assert beyond_classical(fitter, q, noise)["x"] > max(0.5, 10 * classical)


def test_a_classical_loop_on_other_thresholds_is_far_only_from_the_nominal_operators():
    # one more play operator between two nominal thresholds (what the synthetic generator's
    # shapes add): a classical loop, which no PI on the nominal thresholds draws
    fitter, p = _fitter_and_model()
    x = predict(fitter.recs[0], fitter.dev, p)["x"]
    noise = {"x": 0.001 * float(np.ptp(x)), "us": 1.0}
    nominal = np.asarray(p.thresholds, float)
    assert beyond_classical(fitter, p, noise, nominal)["x"] < 1e-6
    for extra in (0.05, 0.15, 0.25):                       # between 0-0.1, 0.1-0.2, 0.2-0.3
        q = p.copy()
        q.thresholds = np.sort(np.append(nominal, extra))
        q.weights = np.insert(np.asarray(p.weights, float), int(np.searchsorted(q.thresholds, extra)),
                              0.3 * float(np.sum(p.weights)))
        far = beyond_classical(fitter, q, noise, nominal)["x"]
        assert far > 1.0 and far > 3 * beyond_classical(fitter, q, noise)["x"], extra
        # the increase over the recalibrated (here: nominal) loop, and its reverse
        assert further_from_nominal(fitter, q, p, noise, nominal) == pytest.approx(
            far - max(beyond_classical(fitter, p, noise, nominal).values()), rel=1e-9)
        assert further_from_nominal(fitter, p, q, noise, nominal) < -1.0


def _synth(seed):
    from piezo_fmu.diagnose import evaluate
    from piezo_fmu.diagnose.synth import make_case

    spec = next(s for s in evaluate.cases() if s["seed"] == seed)
    case = make_case(spec["seed"], spec["effects"], spec["noise"], spec["kinds"])
    return case, [{"name": f"synth-{seed}", "time": case.t, "u": case.u, "x": case.x, "us": case.us}]


def test_a_loop_the_nominal_operators_cannot_draw_is_named(monkeypatch, rules_before):
    # synth-1046: two more play operators' worth of loop between the nominal thresholds. The
    # finer loop explains all the structured residual but removes 2.75 noise rms (under the 3 a
    # name took alone) and its loop is 1.3 from the classical loops (it is one); it lies 2.75
    # further from every PI on the nominal thresholds than the recalibrated loop: a loop shape
    from piezo_fmu.diagnose import select
    from piezo_fmu.diagnose.run import analyse

    case, raw = _synth(1046)
    assert case.truth["effects"] == ["hysteresis_shape"]
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == ["hysteresis_shape"], res["final"]["verdict"]
    assert any("further from the nominal operators' loops" in m for m in steps), steps
    from piezo_fmu.diagnose import loopshape
    assert res["findings"][0]["confidence"] > loopshape.SHAPE_NOMINAL_RIGHT + 0.05, res["findings"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # without that measure (the rule before) found only when the search ends (its loop lies 4.7
    # noise rms from every classical loop of the nominal operators, at any scale), as confident as
    # such findings were right on the fresh draws ...
    monkeypatch.setattr(select, "SHAPE_BEYOND_NOMINAL", float("inf"))
    res = analyse(raw).result
    assert res["final"]["effects"] == ["hysteresis_shape"]
    assert res["findings"][0]["confidence"] == pytest.approx(loopshape.SHAPE_NOMINAL_RIGHT, abs=1e-3)
    # ... and without both an ordinary loop difference: nothing is missing
    monkeypatch.setattr(loopshape, "SHAPE_NOMINAL_FAR", float("inf"))
    monkeypatch.setattr(loopshape, "SHAPE_NAMED_NEAR", float("inf"))
    res = analyse(raw).result
    assert res["final"]["effects"] == [] and res["candidates"] == []


def test_a_loop_near_the_classical_and_the_nominal_ones_is_not_named_on_its_removal(monkeypatch, rules_before):
    # rig-138 (927 Hz; a current limit and a 54 Hz mode, no loop shape): in its third round a finer loop
    # removes 3.1 noise rms, 98 % of what is left, enough for a name on removal alone, but lies
    # 0.8 from the classical loops and 1.7 further from the nominal operators' loops: ordinary
    from piezo_fmu.diagnose import loopshape, select
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig("rig-138")
    truth = sorted(rec.truth["mechanisms"])
    assert truth == ["amplifier_current_limit", "extra_resonance"]
    assert sorted(analyse(raw).result["final"]["effects"]) == truth
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # named on its removal alone (the rule before, also in the backward check, which measures the
    # loop again beside the mechanisms named with it): a false loop shape
    monkeypatch.setattr(select, "SHAPE_BEYOND_NOMINAL", -float("inf"))
    monkeypatch.setattr(loopshape, "SHAPE_BEYOND_NOMINAL", -float("inf"))
    # (then the search's end finds it a loop the nominal operators draw, and does not name it ...)
    assert sorted(analyse(raw).result["final"]["effects"]) == truth
    # (... unless that measure is off too)
    monkeypatch.setattr(loopshape, "SHAPE_NOMINAL_FAR", -float("inf"))
    monkeypatch.setattr(loopshape, "SHAPE_NAMED_NEAR", -float("inf"))
    assert "hysteresis_shape" in analyse(raw).result["final"]["effects"]


def _rig(case_id):
    from piezo_fmu import rig

    draw = int(case_id.split("-")[1][1:]) if case_id.startswith("rig-d") else 0
    spec = next(s for s in rig.cases(draw=draw) if s.case_id == case_id)
    rec = rig.generate(spec)
    return rec, [{"name": case_id, "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}]


def test_a_switching_band_the_recalibration_bent_in_is_named(monkeypatch, spy, rules_before):
    # rig-108 (533 Hz): a PI device on other thresholds with a band of domains switching at fixed
    # voltages. The recalibrated PI (partial sums of its weights positive, one weight negative) bends
    # part of the band in; the finer loop then removes 2.4 noise rms more, under the 3 a name took
    # alone, but the loop it draws lies 2.8 noise rms from every classical loop: a loop shape
    from piezo_fmu.diagnose import select
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig("rig-108")
    assert rec.truth["mechanisms"] == ["hysteresis_shape"]
    seen = spy(select, "beyond_classical")
    res = analyse(raw).result
    assert res["final"]["effects"] == ["hysteresis_shape"], res["final"]["verdict"]
    assert len(seen) == 1 and max(seen[0].values()) >= select.SHAPE_BEYOND
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # without the measures (the rule before) the same loop is an ordinary difference
    # (and without the measure of the search's end: its loop lies far from the nominal operators')
    from piezo_fmu.diagnose import loopshape
    monkeypatch.setattr(select, "SHAPE_BEYOND", float("inf"))
    monkeypatch.setattr(select, "SHAPE_BEYOND_NOMINAL", float("inf"))
    monkeypatch.setattr(loopshape, "SHAPE_NOMINAL_FAR", float("inf"))
    monkeypatch.setattr(loopshape, "SHAPE_NAMED_NEAR", float("inf"))
    assert analyse(raw).result["final"]["effects"] == []


def test_a_loop_far_from_every_classical_one_is_named_beside_other_misfit(monkeypatch, rules_before):
    # rig-169: a KP device whose loop widens around 57 V (level_width). The finer loop removes
    # 2.1 noise rms but explains only 59 % of the structured residual (the rest: the device's own
    # family, 1.4 noise rms from the best nine-operator PI); its loop lies 4.7 noise rms from every
    # classical loop: a loop shape with other misfit beside it
    from piezo_fmu.diagnose import select
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig("rig-169")
    assert rec.truth["mechanisms"] == ["hysteresis_shape"]
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == ["hysteresis_shape"], res["final"]["verdict"]
    assert any("other misfit stays beside it" in m for m in steps), steps
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # asked for 70 % of the residual (the rule before): an ordinary difference, nothing named
    # (and without the measure of the search's end: its loop lies far from the nominal operators')
    from piezo_fmu.diagnose import loopshape
    monkeypatch.setattr(select, "SHAPE_PARTIAL_EXPLAINED", select.SHAPE_EXPLAINED)
    monkeypatch.setattr(loopshape, "SHAPE_NOMINAL_FAR", float("inf"))
    monkeypatch.setattr(loopshape, "SHAPE_NAMED_NEAR", float("inf"))
    assert analyse(raw).result["final"]["effects"] == []


def test_a_loop_with_other_misfit_beside_it_waits_for_the_physics_that_passed():
    # rig-158: a 1.05 ms (8-sample) delay and a band of switching domains at 7.65 kHz. In the first
    # round the finer loop explains 45-47 % (2.6 noise rms, 3.3 from every classical loop) and the
    # delay, which passed beside it, 35 %. Named on that partial evidence the loop's cells took the delay's
    # misfit and both were lost (the shape a candidate at 0.30); taken in as an ordinary
    # difference, the delay is named in the next round
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig("rig-158")
    assert sorted(rec.truth["mechanisms"]) == ["hysteresis_shape", "time_delay"]
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == ["time_delay"], (res["candidates"], res["rejected"])
    loop = [m for m in steps if "round 1: the finer loop explains" in m and "not named" in m]
    assert loop, steps
    # measured: 45 % with bvls, 47 % with the active-set solve (2026-12-02)
    assert 40 <= float(loop[0].split("explains ")[1].split(" %")[0]) <= 50, loop


def test_a_loop_of_another_family_is_not_named_on_its_distance_from_the_nominal_operators(monkeypatch, rules_before):
    # rig-d7-091 (925 Hz; a clean Bouc-Wen stack): a finer loop removes 3.0 noise rms and lies 2.7
    # further from every PI on the nominal thresholds than the recalibrated loop, but 0.35 from the
    # classical loops, and explains 93 % of the structured residual: the finer grid does not draw
    # the device's loop (as it draws synth's added operators: five of eight at 98 % or more)
    from piezo_fmu.diagnose import select
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig("rig-d7-091")
    assert rec.truth["mechanisms"] == []
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == [], res["findings"]
    assert any("a loop of another family" in m for m in steps), steps
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # named on that distance alone (the rule before): a false loop shape on a clean device
    monkeypatch.setattr(select, "SHAPE_FURTHER_EXPLAINED", 0.0)
    # (then the search's end finds it a loop the nominal operators draw, and does not name it ...)
    assert analyse(raw).result["final"]["effects"] == []
    # (... unless that measure is off too)
    from piezo_fmu.diagnose import loopshape
    monkeypatch.setattr(loopshape, "SHAPE_NOMINAL_FAR", -float("inf"))
    monkeypatch.setattr(loopshape, "SHAPE_NAMED_NEAR", -float("inf"))
    assert analyse(raw).result["final"]["effects"] == ["hysteresis_shape"]


def _negative_weight(p):
    """``p`` with a negative weight at a middle threshold, the partial sums kept positive (the
    recalibration's freedom; a loop no classical PI draws)."""
    w = np.asarray(p.weights, float).copy()
    q = p.copy()
    q.weights = w.copy()
    q.weights[3] = -0.25 * w.sum()
    q.weights[6] += 0.25 * w.sum() + w[3]
    return q


def test_a_classical_solve_keeps_every_weight_non_negative():
    from piezo_fmu.diagnose.fit import Structure

    fitter, p = _fitter_and_model()
    q = _negative_weight(p)
    pred = predict(fitter.recs[0], fitter.dev, q)
    t, u = fitter.recs[0].t, fitter.recs[0].u
    recs = make_recordings([{"name": "r", "time": t, "u": u, "x": pred["x"], "us": pred["us"]}])
    f = Fitter(recs, fitter.dev, {"x": 1.0, "us": 1.0 / float(np.var(pred["us"]))})
    signed = p.copy()
    signed.weights = np.zeros(signed.weights.size)
    f.varpro(signed, Structure(), gn_iter=2)
    assert signed.weights.min() < -0.1 * signed.weights.sum()      # the negative weight is found again
    assert f.cost(signed) < 1e-8 * float(pred["x"] @ pred["x"])
    classical = signed.copy()
    classical.weights = np.zeros(classical.weights.size)
    classical.classical = True
    f.varpro(classical, Structure(), gn_iter=2)
    assert classical.weights.min() >= 0.0
    assert f.cost(classical) > 1e3 * max(f.cost(signed), 1e-30)


def test_the_distance_from_the_nominal_operators_is_taken_at_their_best_voltage_scale():
    # a classical loop on the nominal thresholds at 1.6 times their voltage scale: far from the
    # nominal operators at the model's scale, on them at its own
    from piezo_fmu.diagnose.loopshape import nominal_distance

    fitter, p = _fitter_and_model()
    q = p.copy()
    q.u_norm = 1.6 * p.u_norm
    x = predict(fitter.recs[0], fitter.dev, q)["x"]
    noise = {"x": 1e-3 * float(np.ptp(x)), "us": 1.0}
    nominal = np.asarray(p.thresholds, float)
    at_model_scale = beyond_classical(fitter, q, noise, nominal * p.u_norm / q.u_norm)["x"]
    far, u_norm, each = nominal_distance(fitter, q, noise, nominal)
    assert far == max(each.values())
    assert at_model_scale > 1.0
    assert far < 0.05 * at_model_scale and far < 0.2
    assert u_norm == pytest.approx(q.u_norm, rel=0.03)
    # a negative weight is far at every scale
    assert nominal_distance(fitter, _negative_weight(p), noise, nominal)[0] > 1.0


def test_a_loop_far_from_the_nominal_operators_at_the_search_end_with_weak_held_out_evidence_is_a_candidate(
        monkeypatch, rules_before):
    # rig-d10-030 (1.16 kHz): a KP device with a band of switching domains. The recalibrated PI
    # (free-signed weights, thresholds at 0.57 of the stroke's voltage span) draws most of it; the
    # finer loop removes 1.4 noise rms more and is taken in as an ordinary loop difference. The loop
    # the search ends with lies 10.8 noise rms from every classical loop of the nominal operators,
    # and refitted with one the model fits far worse: a loop shape, found only there (right in 26 of
    # 38 on the fresh draws 11 and 13-16: at most 0.58), named at its own 0.53 at stop 66. Its
    # held-out rows explain 0.11 of what it removes (the record's largest reversal lies in a training
    # block), z 7.1 < SHAPE_NOMINAL_HELDOUT_Z: a candidate, as the false loops there are
    from piezo_fmu.diagnose import loopshape
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig("rig-d10-030")
    assert rec.truth["mechanisms"] == ["hysteresis_shape"]
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == [], res["final"]["verdict"]
    far = [m for m in steps if "from every classical loop of the nominal operators" in m]
    assert far and float(far[0].split("lies ")[1].split(" x")[0]) >= loopshape.SHAPE_NOMINAL_FAR, far
    assert any("held-out z" in m and f"< {loopshape.SHAPE_NOMINAL_HELDOUT_Z:g}" in m for m in steps), steps[-20:]
    shape = [c for c in res["candidates"] if c["effect"] == "hysteresis_shape"]
    assert shape and shape[0]["confidence"] == pytest.approx(loopshape.SHAPE_NOMINAL_WEAK_RIGHT, abs=1e-3)
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # without the held-out bar it is named, at most at the cap of the class
    monkeypatch.setattr(loopshape, "SHAPE_NOMINAL_HELDOUT_Z", float("-inf"))
    res = analyse(raw).result
    assert res["final"]["effects"] == ["hysteresis_shape"], res["final"]["verdict"]
    assert 0.5 <= res["findings"][0]["confidence"] <= loopshape.SHAPE_NOMINAL_RIGHT, res["findings"]
    assert "refitted with one the model fits the data worse" in res["findings"][0]["evidence"]["note"]
    # without the final measure (the rule before): an ordinary loop difference, no candidate either
    monkeypatch.setattr(loopshape, "SHAPE_NOMINAL_FAR", float("inf"))
    monkeypatch.setattr(loopshape, "SHAPE_NAMED_NEAR", float("inf"))
    res = analyse(raw).result
    assert res["final"]["effects"] == [] and not [c for c in res["candidates"] if c["effect"] == "hysteresis_shape"]


def test_a_loop_alone_is_judged_on_the_held_out_evidence_of_the_channels_it_is_seen_on(monkeypatch, rules_before):
    # rig-d36-039 (278 Hz; a PI device on other thresholds, its loop shape alone): the loop the
    # search ends with lies 4.07 noise rms from every classical loop of the nominal operators on x and
    # 0.31 on us, where it has little to show; against its classical refit the held-out z is 27 on x
    # and 8.4 on us. Nothing else is named: the held-out bar counts on x alone, and the loop is named at
    # the cap of its class. Counted on every channel (the rule before stop 92) it was a candidate at
    # the precision of weak loops
    from piezo_fmu.diagnose import loopshape
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig("rig-d36-039")
    assert rec.truth["mechanisms"] == ["hysteresis_shape"]
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == ["hysteresis_shape"], res["final"]["verdict"]
    assert res["findings"][0]["confidence"] == pytest.approx(loopshape.SHAPE_NOMINAL_RIGHT, abs=1e-3)
    counted = [m for m in steps if "held-out evidence counted on" in m]
    assert counted and "hysteresis_shape: held-out evidence counted on x (us: its loop departs 0.3" in counted[0], steps
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    monkeypatch.setattr(loopshape, "SHAPE_NOMINAL_SEEN", float("inf"))
    res = analyse(raw).result
    assert res["final"]["effects"] == [], res["final"]["verdict"]
    shape = [c for c in res["candidates"] if c["effect"] == "hysteresis_shape"]
    assert shape and shape[0]["confidence"] == pytest.approx(loopshape.SHAPE_NOMINAL_WEAK_RIGHT, abs=1e-3)


def test_a_loop_that_drew_ordinary_physics_is_not_named_when_its_classical_refit_fits():
    # rig-d10-053 (354 Hz; a Bouc-Wen stack with sensor leakage, no loop shape): the final loop has
    # weights of both signs (12.2, -1.3, -10.8, ...) and lies 18.8 noise rms from every classical
    # loop of the nominal operators, but refitted with one (the thresholds' scale and the lags
    # free) the model fits the data as well: the loop had drawn ordinary physics, nothing is named
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig("rig-d10-053")
    assert rec.truth["mechanisms"] == ["sensor_leakage"]
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == ["sensor_leakage"], res["final"]["verdict"]
    assert any("the classical refit is not refused" in m for m in steps), steps
    assert any(r["effect"] == "hysteresis_shape" and "refitted with one the data do not refuse it" in r["why"]
               for r in res["rejected"]), res["rejected"]


def test_a_loop_that_removes_little_of_its_departure_on_a_channel_is_not_named(monkeypatch, rules_before):
    # rig-d10-133 (632 Hz; a clean KP device whose 511 Hz first mode lies above the Nyquist frequency,
    # 89 noise rms in the sensor channel that no model here draws): the final loop lies 2.65 noise rms
    # from the classical ones on x and 1.06 on us, and its classical refit is refused on x, but on us
    # the loop removes nothing of its departure: it bent to other misfit
    # The path to the outcome is chaotic in round-off (stop 61: on an Intel Xeon the active-set solve
    # of the weights, within 3e-9 of bvls's cost in every one of its 1632 solves on rig-d10-133, led
    # to the same names by another rule); the rule tested is the one it was set with on bvls's solves,
    # so the test runs every bounded solve by bvls (the reference solver)
    from piezo_fmu.diagnose import varpro
    monkeypatch.setattr(varpro, "_active_set", lambda *args, **kwargs: None)
    from piezo_fmu.diagnose import loopshape
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig("rig-d10-133")
    assert rec.truth["mechanisms"] == []
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == [], res["final"]["verdict"]
    assert any("on us it removes 0.00 x the noise" in m for m in steps), steps
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # without the rule (and the end's finding trusted as named) the held-out bar keeps it out ...
    monkeypatch.setattr(loopshape, "SHAPE_NOMINAL_SHOWN", 0.0)
    monkeypatch.setattr(loopshape, "SHAPE_NOMINAL_RIGHT", 1.0)
    steps = []
    assert analyse(raw, say=steps.append).result["final"]["effects"] == []
    assert any("held-out z" in m and f"< {loopshape.SHAPE_NOMINAL_HELDOUT_Z:g}" in m for m in steps), steps[-20:]
    # (its z on us is -5.6: the held-out rows take the loop the other way; without both rules it was
    # a false loop shape, a third diagnosis of 29 s dropped at stop 91 for the tests it paid for)


def test_a_named_loop_the_nominal_operators_draw_is_an_ordinary_loop_difference(monkeypatch, rules_before):
    # rig-d10-114 (1.59 kHz; leakage and a delay on a PI device of its own thresholds, no loop shape): a
    # finer loop is named in round 2 (it explains 98 % of what is left beside the leakage), the delay
    # after it; with both in, the loop lies 0.87 noise rms from a classical loop of the nominal
    # operators: a loop they draw, kept as the recalibration's finer loop and not named. With the
    # noise bounded by what a decisive gain leaves (stats.NOISE_BOUND, stop 75: the x channel's level
    # lay above the loop's held-out rmse) the loop explains 94 % in round 2 and is taken as an
    # ordinary loop difference there already; the rule is checked on the path of before
    from piezo_fmu.diagnose import loopshape, stats
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig("rig-d10-114")
    assert sorted(rec.truth["mechanisms"]) == ["sensor_leakage", "time_delay"]
    res = analyse(raw).result
    assert sorted(res["final"]["effects"]) == ["sensor_leakage", "time_delay"], res["final"]["verdict"]
    assert res["baseline"]["recalibrated"]["loop"]["refined"]
    monkeypatch.setattr(stats, "NOISE_BOUND", 0.0)
    res = analyse(raw).result
    assert sorted(res["final"]["effects"]) == ["sensor_leakage", "time_delay"], res["final"]["verdict"]
    assert any(r["effect"] == "hysteresis_shape" and "a loop they draw" in r["why"] for r in res["rejected"])
    assert res["baseline"]["recalibrated"]["loop"]["refined"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    monkeypatch.setattr(loopshape, "SHAPE_NOMINAL_FAR", 0.0)
    monkeypatch.setattr(loopshape, "SHAPE_NAMED_NEAR", 0.0)
    assert "hysteresis_shape" in analyse(raw).result["final"]["effects"]


def test_a_named_loop_between_the_two_bars_stays_named(monkeypatch, rules_before):
    # synth-1062 (sensor leakage and two more operators' worth of loop, on the model's own structure):
    # the rounds name the loop shape beside the leakage; with both in, the loop lies 1.9 noise rms from
    # the nominal operators' classical loops: above the bar that undoes a named loop, under the one a
    # loop the rounds did not name must clear
    from piezo_fmu.diagnose import loopshape
    from piezo_fmu.diagnose.run import analyse

    case, raw = _synth(1062)
    assert sorted(case.truth["effects"]) == ["hysteresis_shape", "sensor_leakage"]
    steps = []
    res = analyse(raw, say=steps.append).result
    assert sorted(res["final"]["effects"]) == ["hysteresis_shape", "sensor_leakage"], res["final"]["verdict"]
    named = [m for m in steps if "the named loop lies" in m]
    far = float(named[0].split("lies ")[1].split(" x")[0])
    assert loopshape.SHAPE_NAMED_NEAR <= far < loopshape.SHAPE_NOMINAL_FAR, named
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # undone at the other bar: the leakage alone
    monkeypatch.setattr(loopshape, "SHAPE_NAMED_NEAR", loopshape.SHAPE_NOMINAL_FAR)
    assert analyse(raw).result["final"]["effects"] == ["sensor_leakage"]


def test_a_loop_found_at_the_search_end_is_as_confident_as_the_lower_end_of_its_fresh_precision():
    # the Wilson score interval of 5 right in 10 at z = 1.96 is 0.2366-0.7634 (the textbook value);
    # the end's loop shapes, 11 right of 19 on the fresh draws 11, 13 and 14, stayed below CONFIDENT
    # (candidates); 26 of 38 with draws 15 and 16 clear it: named, at the interval's lower end
    from piezo_fmu.diagnose import loopshape
    from piezo_fmu.diagnose.decide import CONFIDENT

    assert loopshape._wilson_lower(5, 10, 1.96) == pytest.approx(0.2366, abs=1e-4)
    assert loopshape._wilson_lower(10, 10, 1.2816) < 1.0
    assert loopshape._wilson_lower(11, 19, loopshape.SHAPE_NOMINAL_Z) == pytest.approx(0.4333, abs=1e-4)
    right, found = loopshape.SHAPE_NOMINAL_FRESH
    assert (right, found) == (26, 38)
    assert loopshape.SHAPE_NOMINAL_RIGHT == pytest.approx(0.5817, abs=1e-4)
    assert CONFIDENT < loopshape.SHAPE_NOMINAL_RIGHT < right / found
    # below the held-out bar: right in 2 of 8 when the bar was set (0.1089), 12 of 30 with draws 23-26
    # counted (stop 80): a candidate whatever its own confidence, as often right as the lower end says
    assert loopshape._wilson_lower(2, 8, loopshape.SHAPE_NOMINAL_Z) == pytest.approx(0.1089, abs=1e-4)
    assert loopshape.SHAPE_NOMINAL_WEAK == (12, 30)
    assert loopshape.SHAPE_NOMINAL_WEAK_RIGHT == pytest.approx(0.2935, abs=1e-4)
    assert loopshape.SHAPE_NOMINAL_WEAK_RIGHT < 12 / 30 < CONFIDENT


def test_a_loop_at_the_search_end_without_a_held_out_z_is_a_candidate(monkeypatch):
    # the held-out bar reads a z of nan (no held-out evidence, :func:`.stats.compare` leaves such a
    # channel out of its total) as below it; a z at the bar on every channel is named at the cap. A
    # channel where the loop departs less than SHAPE_NOMINAL_SEEN from the classical loops is not
    # counted when nothing else is named (and is, beside a named mechanism, or when no channel is seen)
    from piezo_fmu.diagnose import loopshape
    from piezo_fmu.diagnose.fit import Structure

    def shape(zs, departs):
        return {"name": "hysteresis_shape", "confidence": 0.97, "departs": departs,
                "cmp": {"channels": {c: {"z_heldout": z} for c, z in zs.items()}}}

    seen, quiet = 1.01 * loopshape.SHAPE_NOMINAL_SEEN, 0.99 * loopshape.SHAPE_NOMINAL_SEEN
    creep = [{"name": "creep", "confidence": 0.99}]
    for zs, departs, beside, named in (
            ({"x": float("nan"), "us": 40.0}, {"x": seen, "us": seen}, [], False),
            ({"x": 3.0}, {"x": seen}, [], False),
            ({"x": loopshape.SHAPE_NOMINAL_HELDOUT_Z, "us": 40.0}, {"x": seen, "us": seen}, [], True),
            ({"x": 40.0, "us": 3.0}, {"x": seen, "us": quiet}, [], True),
            ({"x": 40.0, "us": 3.0}, {"x": seen, "us": quiet}, creep, False),
            ({"x": 40.0, "us": 3.0}, {"x": quiet, "us": quiet}, [], False),
            ({"x": 40.0, "us": float("nan")}, {"x": seen, "us": quiet}, [], True)):
        monkeypatch.setattr(loopshape, "nominal_shape", lambda *a, zs=zs, d=departs: shape(zs, d))
        steps = []
        struct = Structure()
        s2, strong, weak = loopshape.shape_from_nominal(None, None, struct, list(beside), [], [], None, {}, None,
                                                        steps.append)
        strong = [f for f in strong if f["name"] == "hysteresis_shape"]
        if named:
            assert not weak and strong[0]["confidence"] == pytest.approx(loopshape.SHAPE_NOMINAL_RIGHT)
            assert s2.effects == ("hysteresis_shape",)
        else:
            assert not strong and weak[0]["confidence"] == pytest.approx(loopshape.SHAPE_NOMINAL_WEAK_RIGHT)
            assert s2 is struct and any("held-out z" in m for m in steps), steps


def test_cells_whose_weights_cancel_on_the_training_rows_are_held_by_the_ridge(monkeypatch, rules_before):
    # rig-d22-154 (the independent rig at 267 Hz): a loop shape beside a sensor leakage. The finer
    # loop improves every held-out block about 3 x but one, whose step from 23.9 to 51.5 V no
    # training row repeats: with the cells' ridge at 1e-9 the weights that cancel on the training
    # rows drew a step there (0.008 -> 0.35 um rms), x got 108 % worse on held-out data and the
    # shape failed. With CELL_RIDGE both are named and the held-out fit improves
    from piezo_fmu import rig
    from piezo_fmu.diagnose import varpro
    from piezo_fmu.diagnose.run import analyse

    spec = next(s for s in rig.cases(draw=22) if s.case_id == "rig-d22-154")
    rec = rig.generate(spec)
    assert sorted(rec.truth["mechanisms"]) == ["hysteresis_shape", "sensor_leakage"]
    raw = [{"name": "rig-d22-154", "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}]
    res = analyse(raw).result
    assert sorted(res["final"]["effects"]) == ["hysteresis_shape", "sensor_leakage"], res["final"]["verdict"]
    assert res["final"]["rmse"]["x"] < 0.5 * res["baseline"]["rmse"]["x"]        # [um]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    monkeypatch.setattr(varpro, "CELL_RIDGE", 1e-9)
    assert analyse(raw).result["final"]["effects"] == ["sensor_leakage"]


def test_play_operators_the_training_rows_barely_see_move_are_left_out_of_the_finer_loop(rig_diagnosis, monkeypatch,
                                                                                       spy, rules_before):
    # rig-d40-095 (282 Hz, 5.2 k samples; a Bouc-Wen loop with a shape, nothing else): a 38 V step and
    # back, then a 1 Hz sine of 29 V. The finer loop's operators at 0.5-0.8 of the voltage scale move
    # in 0-7 training rows and 42-57 held-out rows (the sine's first rise); fitted to those few rows
    # their weights (-15.2, +13.7, -12.3 um) cancelled on the training rows, took that held-out block
    # from 0.098 to 0.317 um, x got 186 % worse on held-out data and nothing was named. Left out, the
    # loop passes and is named (measured stop 96: x 0.028 -> 0.005 um held out)
    from piezo_fmu.diagnose import catalogue

    kept = spy(catalogue, "_plays_supported")
    res = rig_diagnosis("rig-d40-095")
    assert kept and not kept[0].all()            # the first finer loop leaves operators out
    assert res["final"]["effects"] == ["hysteresis_shape"], res["final"]["verdict"]
    assert res["final"]["rmse"]["x"] < 0.3 * res["baseline"]["rmse"]["x"], res["final"]["rmse"]     # [um]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    monkeypatch.setattr(catalogue, "_plays_supported", lambda fitter, q: np.ones(len(q.thresholds), bool))
    assert rig_diagnosis("rig-d40-095")["final"]["effects"] == []
