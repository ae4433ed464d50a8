"""piezo-fmu diagnose: blind recognition on synthetic recordings, the output contract, a real
recording, speed, and the round trip through rebuilt FMUs.

The synthetic recordings come from :mod:`piezo_fmu.diagnose.synth` (a plant with ordinary parameter
mismatch plus the mechanisms switched on, and noise); diagnose only ever sees the CSV. The larger
recognition study (rates, false positives, tables) is ``python -m piezo_fmu.diagnose.evaluate``.
"""
from __future__ import annotations

import csv
import json
import math
import pickle
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import piezo_fmu.diagnose.run as run_module
from piezo_fmu.cli import main
from piezo_fmu.diagnose import diagnose
from piezo_fmu.diagnose.engine import Recording, device_from_model, params_from_model, predict
from piezo_fmu.diagnose.synth import NOISE, make_case, write_recording
from piezo_fmu.model import load_model
from piezo_fmu.simulate import Signal, simulate

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "tests" / "data" / "dbo" / "piezo_1hz_sine.csv"
# real recordings of piezo actuators shipped with their licences: (file, --scale)
REAL_RECORDINGS = [
    (REAL, None),
    (ROOT / "tests" / "data" / "dbo_test" / "dbo_test_ramped_sine.csv", None),
    (ROOT / "tests" / "data" / "jpk_cellhesion_00758" / "jpk00758_extend_retract.csv", {"u": 0.1}),
    (ROOT / "tests" / "data" / "jpk_cellhesion_01466" / "jpk01466_extend_hold_retract.csv", {"u": 0.1}),
]


def run_blind(tmp_path, case, name="rec.csv", **kw):
    """Write the case as a CSV and diagnose the file (the truth stays here)."""
    path = tmp_path / name
    write_recording(path, case)
    return diagnose([path], out=tmp_path / "out", force=True, figures=kw.pop("figures", False), **kw)


def named(diag):
    return sorted(f["effect"] for f in diag.result["findings"])


def read_fit_csv(path):
    with open(path) as fh:
        rows = [r for r in csv.reader(line for line in fh if not line.startswith("#"))]
    head, body = rows[0], np.array(rows[1:], dtype=float)
    return {h: body[:, i] for i, h in enumerate(head)}


# -- the fitting engine is the core's physics -------------------------------------------------------

@pytest.mark.parametrize("pickoff,position", [("stack", "output"), ("contact", "drive"), ("load", "output")])
def test_engine_replays_the_monolithic_model_with_every_mechanism_on(pickoff, position):
    m = load_model()
    for sec, key, v in (("amplifier", "I_max", 0.02), ("amplifier", "delay", 3e-4), ("creep", "gains", [0.1, 0.05]),
                        ("creep", "time_constants", [0.5, 3.0]), ("resonance", "f_n", 800.0),
                        ("resonance", "zeta", 0.03), ("drift", "rate", 0.02), ("drift", "curvature", -0.001),
                        ("drift", "offset", 0.3), ("drift", "time_constant", 1.5), ("sensor", "tau_leak", 2.0),
                        ("sensor", "offset", 0.01),
                        # the ordinary physics recalibration fits: second lag stage, a first mode at
                        # 1.5 kHz, what the sensor follows, the sensor's sampling lag
                        ("amplifier", "tau_2", 2e-4), ("mechanics", "m", 8.6), ("mechanics", "pickoff", pickoff),
                        ("resonance", "position", position), ("sensor", "lag", 2e-4),
                        # a device exercised up to 40 V before the run starts with that memory
                        ("hysteresis", "prepared", 40.0),
                        # KP cells beside the PI (hysteresis_shape), one straddling the rest voltage
                        ("hysteresis", "cells_up", [0.1, 0.16, 0.12]), ("hysteresis", "cells_down", [-0.05, 0.08, 0.02]),
                        ("hysteresis", "cells_width", [0.1, 0.05, 0.08]),
                        ("hysteresis", "cells_weights", [0.3, -0.1, 0.2])):
        m.set(sec, key, v, "test")
    m.check()
    dt = 1e-4
    t = np.arange(30001) * dt
    u = 1.5 + 1.5 * np.sin(2 * np.pi * 10 * t) + (t > 1.0) * 1.0
    u[20000:] = np.where((t[20000:] % 0.5) < 0.25, 0.5, 4.0)
    ref = simulate(m, Signal("table", t=t, values=u, column="u"), t[-1], step=dt, mode="open", noise=False)
    rec = Recording("a", t, dt, u, ref["x"], ref["us"], np.zeros(t.size, bool))
    pr = predict(rec, device_from_model(m), params_from_model(m, dt))
    for c in ("x", "us", "ua"):
        assert np.max(np.abs(pr[c] - ref[c])) < 1e-6 * np.ptp(ref[c]), c
    direct = predict(rec, device_from_model(m), params_from_model(m), direct=True)
    assert np.max(np.abs(direct["x"] - ref["x"])) < 1e-6 * np.ptp(ref["x"])


def test_engine_replays_between_the_samples_as_the_core_does_with_a_finer_step():
    # a recording at 1 kHz of a device whose amplifier settles within a sample and whose first mode
    # (400 Hz) rings within a few: replayed with 8 internal steps per sample, the engine is the
    # core's simulation with a step of dt / 8 read at the samples; at one step per sample the
    # contact force misses it by far more than any noise (the replay takes the stroke as a straight
    # line from sample to sample)
    m = load_model()
    for sec, key, v in (("mechanics", "m", 8.6 * (1500.0 / 400.0) ** 2), ("mechanics", "pickoff", "contact"),
                        ("amplifier", "delay", 2e-3), ("creep", "gains", [0.05]), ("creep", "time_constants", [0.5])):
        m.set(sec, key, v, "test")
    m.check()
    dt, k = 1e-3, 8
    n = 3000
    t = np.arange(n) * dt
    u = 1.5 + 1.5 * np.sin(2 * np.pi * 7 * t)
    u[1500:] = np.where((t[1500:] % 0.2) < 0.1, 0.5, 4.0)
    tf = np.arange(n * k) * (dt / k)
    ref = simulate(m, Signal("table", t=tf, values=np.repeat(u, k), column="u"), tf[-1], step=dt / k, mode="open",
                   noise=False)
    ref = {c: np.asarray(ref[c])[::k] for c in ("x", "us", "ua")}
    dev, p = device_from_model(m), params_from_model(m, dt)
    fine = predict(Recording("a", t, dt, u, ref["x"], ref["us"], np.zeros(n, bool), oversample=k), dev, p)
    for c in ("x", "us", "ua"):
        assert np.max(np.abs(fine[c] - ref[c])) < 1e-6 * np.ptp(ref[c]), c
    coarse = predict(Recording("a", t, dt, u, ref["x"], ref["us"], np.zeros(n, bool)), dev, p)
    assert np.max(np.abs(coarse["ua"] - ref["ua"])) < 1e-6 * np.ptp(ref["ua"])   # the same voltage at the samples
    # 1.1 % of the force's range (measured), against a noise of ~0.1 % in a typical recording
    assert np.sqrt(np.mean((coarse["us"] - ref["us"]) ** 2)) > 0.005 * np.ptp(ref["us"])


def test_a_replay_rate_sets_the_internal_steps_of_slower_recordings():
    from piezo_fmu.diagnose.recordings import MAX_INTERNAL, internal_steps, make_recordings
    from piezo_fmu.errors import UserError

    t = np.arange(4000) / 1000.0
    raw = [{"name": "a", "time": t, "u": np.sin(t), "x": np.sin(t)}]
    assert make_recordings(raw)[0].oversample == 1                     # the default: one step per sample
    rec = make_recordings(raw, replay_rate=8000.0)[0]
    assert rec.oversample == 8 and rec.h == pytest.approx(1e-3 / 8)
    assert internal_steps(1.0 / 5000.0, 10 ** 4, 8000.0) == 2
    assert internal_steps(1.0 / 8000.0, 10 ** 4, 8000.0) == 1          # from the rate up: one step
    assert internal_steps(1.0 / 200.0, 10 ** 5, 8000.0) * 10 ** 5 <= MAX_INTERNAL   # long slow ones: capped
    with pytest.raises(UserError, match="positive number of Hz"):
        make_recordings(raw, replay_rate=-1.0)


def test_a_replayed_recording_is_rerun_by_the_monolithic_model_with_the_same_step(tmp_path):
    # fit.csv's x_final is model.toml re-run by simulate: with --replay-rate at the fit's finer step,
    # so the check (simulate against the fitting engine) stays at round-off
    case = make_case(1003, effects=("creep",), fs=1000.0, duration=3.0)
    diag = run_blind(tmp_path, case, replay_rate=4000.0)
    res = diag.result
    assert res["recordings"][0]["replay_steps_per_sample"] == 4
    assert res["check"]["simulate_vs_fit_max_abs"] < 1e-6 * np.ptp(case.x)
    fit = read_fit_csv(tmp_path / "out" / "fit.csv")
    assert fit["x_final"].size == case.x.size


@pytest.mark.parametrize("v0", [0.0, 0.35, -0.2])
def test_a_prepared_start_is_the_core_operators_after_the_preparation_sweep(v0):
    # the diagnose engine's prepared state against the core's play operators driven through the
    # sweep itself (rest -> top -> first sample), and the whole replay from that state
    from piezo_fmu.core.hysteresis import play_scan
    from piezo_fmu.diagnose.engine import initial_state, operators

    m = load_model()
    p = params_from_model(m)
    p.prep = 0.9 * p.u_norm
    r = np.asarray(p.thresholds, float)
    sweep = np.concatenate([np.linspace(0.0, 0.9, 2001), np.linspace(0.9, v0, 2001)])
    z_core = play_scan(sweep, r)[-1]
    assert np.allclose(initial_state(v0 * p.u_norm, p), z_core, atol=1e-12)
    ua = p.u_norm * (v0 + 0.3 * np.sin(np.linspace(0.0, 6.0, 500)))
    ref = play_scan(ua / p.u_norm, r, z0=z_core)
    assert np.allclose(operators(ua, p).T, ref, atol=1e-12)
    p.prep = 0.0                                                   # relaxed: the default
    assert np.array_equal(initial_state(v0 * p.u_norm, p), np.zeros(r.size))


def test_the_compiled_sos_filter_is_scipys_sosfilt_to_the_bit():
    # the engine filters every column of the replay with its own kernel: the same recursion as
    # scipy's, so a diagnosis gives the same numbers; rows of unlike scale, 1-D and a strided view
    from scipy.signal import butter, sosfilt

    from piezo_fmu.diagnose.engine import sos_filter

    rng = np.random.default_rng(7)
    sos = np.vstack([butter(4, 0.02, output="sos"), [[0.3, -0.1, 0.0, 1.0, -0.999, 0.0]]])
    x = rng.normal(size=(7, 3001)) * np.logspace(-6, 3, 7)[:, None]
    assert np.array_equal(sos_filter(sos, x), sosfilt(sos, x, axis=-1))
    assert np.array_equal(sos_filter(sos, x[3]), sosfilt(sos, x[3]))
    assert np.array_equal(sos_filter(sos[:1], x[:, ::2]), sosfilt(sos[:1], x[:, ::2], axis=-1))
    assert not np.array_equal(sos_filter(sos[:1], x), sosfilt(sos, x, axis=-1))
    # the chain's ends in the same pass: a gain, a settled start c0 per row, the static gain dc
    # (one value, or one per sample: a sensor's leakage) - the numpy expression's numbers
    gain, c0 = 0.37, x[:, :1] * 0.37
    dc = np.exp(-np.arange(x.shape[1]) * 1e-3)
    for d in (1.7, dc):
        want = sosfilt(sos, x * gain - c0, axis=-1) + d * c0
        assert np.array_equal(sos_filter(sos, x, gain, c0, d), want)
        assert np.array_equal(sos_filter(sos, x[2], gain, c0[2], d), want[2])
    assert np.array_equal(sos_filter(sos, x, gain), sosfilt(sos, x * gain, axis=-1))
    assert not np.array_equal(sos_filter(sos, x, gain, c0, 1.7), sosfilt(sos, x * gain, axis=-1))
    # every path of the kernel (a row alone with one, two or more sections; rows four at a time
    # and one by one; rows side by side) gives every row scipy's numbers
    y = rng.normal(size=(11, 1001)).cumsum(axis=1)
    for ns in (1, 2, 3, 5):
        for n in (1, 2, 4, 6, 8, 11):
            c0 = y[:n, :1] * 0.37
            want = sosfilt(sos[:ns], y[:n] * 0.37 - c0, axis=-1) + dc[:1001] * c0
            assert np.array_equal(sos_filter(sos[:ns], y[:n], 0.37, c0, dc[:1001]), want), (ns, n)
            assert np.array_equal(sos_filter(sos[:ns], y[:n]), sosfilt(sos[:ns], y[:n], axis=-1)), (ns, n)


def test_a_second_process_loads_the_diagnose_kernels_from_the_cache(fresh_processes):
    # every diagnosis is a process of its own (the CLI, the evaluation's cases): until stop 67 the
    # kernels were closures over their compiled callees, which numba's cache keys by their pickled
    # cells (new in every process): each diagnosis compiled them again (~10 s) and added copies to
    # the cache folder. A second process must find every kernel there and compile none
    probe = ("import json, numpy as np\n"
             "from piezo_fmu.diagnose.kernels import kernels\n"
             "amp_run, play_run, pi_run, cell_run, sos_run = kernels()\n"
             "v = np.sin(np.linspace(0.0, 6.0, 300))\n"
             "r, w, z0 = np.linspace(0.0, 0.5, 5), np.full(5, 0.2), np.zeros(5)\n"
             "out = [amp_run(10 * v, 2, 1.0, 1e-3, 1e6, -5.0, 5.0, 1e-4, 0.0, np.empty(v.size)),\n"
             "       play_run(v, r, np.empty((5, v.size)), z0), pi_run(v, r, w, 0.1, np.empty(v.size), z0),\n"
             "       cell_run(v, r, -r, np.full(5, 0.1), np.zeros(5), np.zeros(5), w, np.zeros((1, v.size)))]\n"
             "sos = np.array([[0.1, 0.2, 0.1, 1.0, -0.5, 0.2]] * 3)\n"
             "for ns, rows in ((1, 1), (2, 4), (3, 5)):\n"
             "    x = np.tile(v, (rows, 1))\n"
             "    out.append(sos_run(sos[:ns], x, 1.0, np.empty(0), np.zeros(1), np.empty_like(x)))\n"
             "k = dict(zip(('amp_run', 'play_run', 'pi_run', 'cell_run', 'sos_run'), kernels()))\n"
             "print(json.dumps({'hits': {n: len(f.stats.cache_hits) for n, f in k.items()},\n"
             "                  'misses': {n: len(f.stats.cache_misses) for n, f in k.items()},\n"
             "                  'sum': [float(np.sum(o)) for o in out]}))\n")
    runs = fresh_processes(probe)
    assert all(m >= 1 for m in runs[0]["misses"].values()), runs[0]        # compiled, then saved
    assert runs[1]["misses"] == dict.fromkeys(runs[1]["misses"], 0), runs[1]
    assert all(h >= 1 for h in runs[1]["hits"].values()), runs[1]
    assert runs[0]["sum"] == runs[1]["sum"]


def test_the_compiled_operators_are_the_play_rule_summed_in_order():
    # the engine's play operators run several side by side: each is still the play rule sample
    # after sample, and the weighted sum adds them one after another, as the core does (to the bit)
    from piezo_fmu.diagnose.kernels import kernels

    _, play_run, pi_run, _, _ = kernels()
    rng = np.random.default_rng(3)
    v = np.cumsum(rng.normal(scale=0.05, size=400))
    for n in (1, 3, 4, 5, 9):
        r = np.linspace(0.0, 0.8, n)
        w = rng.uniform(0.1, 1.0, n)
        z0 = rng.uniform(-0.2, 0.2, n)
        ref = np.empty((n, v.size))
        for i in range(n):
            zi = z0[i]
            for k in range(v.size):
                zi = max(v[k] - r[i], min(zi, v[k] + r[i]))
                ref[i, k] = zi
        total = np.zeros(v.size)
        for i in range(n):
            total = total + w[i] * ref[i]
        assert np.array_equal(play_run(v, r, np.empty((n, v.size)), z0), ref), n
        assert np.array_equal(pi_run(v, r, w, 0.0, np.empty(v.size), z0), total), n
        sat = pi_run(v, r, w, 0.5, np.empty(v.size), z0)
        assert np.array_equal(sat, total / (1.0 + np.abs(total) * 0.5)), n


def test_the_sos_filter_flushes_states_that_decay_into_subnormal_numbers():
    # an input back at exact zero lets a filter's state decay into subnormal doubles (some hundred
    # cycles an operation on an Intel Xeon), where scipy's recursion can stay in a limit cycle;
    # the engine's states below TINY are zero at the end of each BLOCK samples: the same numbers
    # while they are larger, exact zeros after, in a design (rows side by side) as row by row
    from scipy.signal import sosfilt

    from piezo_fmu.core.linear import TINY
    from piezo_fmu.diagnose.engine import sos_filter
    from piezo_fmu.diagnose.kernels import BLOCK

    sos = np.array([[0.02, 0.01, 0.0, 1.0, -1.0, 0.36]])         # poles at radius 0.6
    x = np.zeros((6, 40 * BLOCK))
    x[:, 3] = np.array([1.0, -2.0, 3e-3, 5e5, 1e-200, 7.0])      # an impulse, then exact zeros
    ref = sosfilt(sos, x, axis=-1)
    got = sos_filter(sos, x)
    tiny = np.abs(ref) < 2.2250738585072014e-308
    assert np.any(tiny & (ref != 0.0), axis=1).all()            # scipy's rows do go subnormal
    big = np.abs(ref) > 1e6 * TINY
    assert np.array_equal(got[big], ref[big])
    assert np.all(got[:, -BLOCK:] == 0.0)                        # flushed, not ringing in subnormals
    assert not np.any((got != 0.0) & (np.abs(got) < 2.2250738585072014e-308))
    rows = np.vstack([sos_filter(sos, x[i]) for i in range(x.shape[0])])
    assert np.array_equal(rows, got)
    two = np.vstack([sos, sos])                                  # (two sections: four rows at a time)
    assert np.array_equal(sos_filter(two, x), np.vstack([sos_filter(two, x[i]) for i in range(x.shape[0])]))
    three = np.vstack([sos, sos, sos])                           # (three: side by side)
    assert np.array_equal(sos_filter(three, x), np.vstack([sos_filter(three, x[i]) for i in range(x.shape[0])]))
    assert np.all(sos_filter(three, x)[:, -BLOCK:] == 0.0)


@pytest.mark.parametrize("settled", [False, True])
def test_a_sensor_held_under_force_before_the_record_has_leaked_its_charge(settled):
    # a record that starts under a force (the operators prepared by a sweep to 100 V, the command
    # then held at 0 V): a sensor charged with that force at the first sample leaks it away with
    # its time constant; one that held it over a rest before the record has leaked it already
    # and reads a constant. Either is possible; diagnose screens both (leak_settled)
    m = load_model()
    dt, tau = 1e-3, 0.5
    t = np.arange(2001) * dt
    p = params_from_model(m, dt)
    p.prep, p.tau_leak, p.leak_settled = 100.0, tau, settled
    rec = Recording("a", t, dt, np.zeros(t.size), None, None, np.zeros(t.size, bool))
    us = predict(rec, device_from_model(m), p)["us"]
    relaxed = p.copy()
    relaxed.prep = 0.0
    level = predict(rec, device_from_model(m), relaxed)["us"]
    assert np.ptp(level) < 1e-12                      # no force, no charge: the offset
    start = us[0] - level[0]
    assert abs(start) > 1e-3                         # the prepared stroke's force is seen at the start
    if settled:
        assert np.ptp(us) < 1e-9 * abs(start)
    else:
        assert us[-1] - level[-1] == pytest.approx(start * math.exp(-t[-1] / tau), rel=1e-3)


def test_the_linear_solve_recovers_the_weights_of_kp_cells(monkeypatch):
    # the cells' weights (any sign) are solved with the PI's, exactly, from wrong starting values
    # (with the cells' ridge at the 1e-9 it had before stop 74); the ridge of varpro.CELL_RIDGE
    # holds directions the rows barely determine and moves the fit by less than 1e-3 of the stroke
    from piezo_fmu.core.preisach import grid_cells
    from piezo_fmu.diagnose import varpro
    from piezo_fmu.diagnose.varpro import solve_linear

    m = load_model()
    dt = 1e-3
    t = np.arange(8001) * dt
    u = 4.0 + 3.5 * np.sin(2 * np.pi * 1.0 * t) * np.exp(-t / 4.0) - 3.5 * np.exp(-t / 0.3)
    dev = device_from_model(m)
    true = params_from_model(m, dt)
    true.y_sat = math.inf
    true.cells = np.array(grid_cells(-0.1, 1.5, 4))
    true.cell_w = np.random.default_rng(4).normal(0.0, 0.2, true.n_cells)
    rec = Recording("a", t, dt, u, None, None, np.zeros(t.size, bool))
    pr = predict(rec, dev, true)
    rec = Recording("a", t, dt, u, pr["x"], pr["us"], np.zeros(t.size, bool))
    p = true.copy()
    p.cell_w = np.zeros(p.n_cells)
    p.weights = p.weights * 0.7
    lam = {"x": 1.0 / np.var(rec.x), "us": 1.0 / np.var(rec.us)}
    q = p.copy()
    solve_linear([rec], dev, q, lam, fit_sensor_gain=False)
    assert 0 < np.max(np.abs(predict(rec, dev, q)["x"] - pr["x"])) < 1e-3 * np.ptp(pr["x"])
    monkeypatch.setattr(varpro, "CELL_RIDGE", 1e-9)
    solve_linear([rec], dev, p, lam, fit_sensor_gain=False)
    got = predict(rec, dev, p)
    assert np.max(np.abs(got["x"] - pr["x"])) < 1e-6 * np.ptp(pr["x"])
    # the cells carry a visible part of the stroke, so the recovery above can fail
    without = true.copy()
    without.cell_w = np.zeros(true.n_cells)
    assert np.max(np.abs(predict(rec, dev, without)["x"] - pr["x"])) > 0.01 * np.ptp(pr["x"])


@pytest.mark.parametrize("tau_leak", [math.inf, 3.0])
def test_the_linear_solve_recovers_a_drift_that_reaches_a_load_pickoff(tau_leak):
    # a sensor on the load spring follows the push rod: a thermal drift reaches it too; the exact
    # linear solve (weights, sensor gain, offsets, drift in both channels) recovers it from the
    # engine's own noise-free signals, started from wrong values
    from piezo_fmu.diagnose.varpro import solve_linear

    m = load_model()
    m.set("mechanics", "pickoff", "load", "test")
    m.set("sensor", "tau_leak", tau_leak, "test")
    dt = 1e-3
    t = np.arange(6001) * dt
    u = 2.0 + 2.0 * np.sin(2 * np.pi * 1.0 * t) * (t > 0.5)
    dev = device_from_model(m)
    true = params_from_model(m, dt)
    true.rate, true.curv, true.off_x, true.off_s = 0.03, -0.004, 0.2, 0.01
    true.y_sat = math.inf               # no saturation: one exact solve, no Gauss-Newton steps
    rec = Recording("a", t, dt, u, None, None, np.zeros(t.size, bool))
    pr = predict(rec, dev, true)
    rec = Recording("a", t, dt, u, pr["x"], pr["us"], np.zeros(t.size, bool))
    p = true.copy()
    p.rate = p.curv = p.off_x = p.off_s = 0.0
    p.S *= 3.0
    p.weights = p.weights * 0.5
    lam = {"x": 1.0 / np.var(rec.x), "us": 1.0 / np.var(rec.us)}
    solve_linear([rec], dev, p, lam, drift_terms=2)
    assert p.rate == pytest.approx(true.rate, rel=1e-5)
    assert p.curv == pytest.approx(true.curv, rel=1e-5)
    assert p.S == pytest.approx(true.S, rel=1e-6)
    got = predict(rec, dev, p)
    for c in ("x", "us"):
        assert np.max(np.abs(got[c] - pr[c])) < 1e-6 * np.ptp(pr[c]), c


def test_the_sensor_gain_alternation_reaches_the_same_gain_in_fewer_rounds(monkeypatch):
    # the sensor gain and the weights alternate until the gain settles (linear convergence: tens of
    # rounds from a gain far from the data's); the gain's sequence extrapolated every third round
    # (varpro._aitken) ends at the same gain and weights in a fraction of the solves
    from piezo_fmu.diagnose import varpro

    m = load_model()
    dt = 1e-3
    t = np.arange(6001) * dt
    u = 2.0 + 2.0 * np.sin(2 * np.pi * 1.0 * t) * (t > 0.5) + 0.8 * np.sin(2 * np.pi * 7.0 * t)
    dev = device_from_model(m)
    true = params_from_model(m, dt)
    true.y_sat = math.inf
    rec = Recording("a", t, dt, u, None, None, np.zeros(t.size, bool))
    pr = predict(rec, dev, true)
    rng = np.random.default_rng(5)
    x = pr["x"] + 0.02 * np.ptp(pr["x"]) * rng.standard_normal(t.size)
    us = pr["us"] + 0.02 * np.ptp(pr["us"]) * rng.standard_normal(t.size)
    rec = Recording("a", t, dt, u, x, us, np.zeros(t.size, bool))
    lam = {"x": 1.0 / np.var(rec.x), "us": 1.0 / np.var(rec.us)}
    solves = []
    real = varpro._bounded_normal_solve

    def counted(*a, **k):
        solves.append(1)
        return real(*a, **k)

    monkeypatch.setattr(varpro, "_bounded_normal_solve", counted)
    out = {}
    for name, aitken in (("plain", lambda seq, S: S), ("extrapolated", varpro._aitken)):
        monkeypatch.setattr(varpro, "_aitken", aitken)
        solves.clear()
        p = true.copy()
        p.S *= 3.0
        p.weights = p.weights * 0.5
        varpro.solve_linear([rec], dev, p, lam)
        out[name] = (len(solves), p)
    (n_plain, p_plain), (n_fast, p_fast) = out["plain"], out["extrapolated"]
    assert n_plain >= 20, n_plain                                  # a genuinely slow alternation
    assert n_fast < 0.5 * n_plain, (n_fast, n_plain)                 # measured: 13 against 34
    assert p_fast.S == pytest.approx(p_plain.S, rel=1e-6)
    assert p_fast.weights == pytest.approx(p_plain.weights, rel=1e-5)
    assert p_fast.S == pytest.approx(true.S, rel=0.05)


def _saturated_recording(rate=0.0):
    """A noise-free recording of the paper's model with a sag of a third at the top of its stroke
    (and a displacement drift of ``rate`` [um/s]): ``(rec, dev, true params, prediction, lam)``."""
    m = load_model()
    dt = 1e-3
    t = np.arange(6001) * dt
    u = 3.0 + 2.5 * np.sin(2 * np.pi * 1.0 * t) * (t > 0.5)
    dev = device_from_model(m)
    true = params_from_model(m, dt)
    rec = Recording("a", t, dt, u, None, None, np.zeros(t.size, bool))
    true.y_sat = 2.0 * np.max(np.abs(predict(rec, dev, true)["x_h"]))
    true.rate = rate
    pr = predict(rec, dev, true)
    rec = Recording("a", t, dt, u, pr["x"], pr["us"], np.zeros(t.size, bool))
    return rec, dev, true, pr, {"x": 1.0 / np.var(rec.x), "us": 1.0 / np.var(rec.us)}


def test_the_linear_solve_starts_afresh_from_weights_deep_in_saturation():
    # weights left from other dynamics can drive the stroke far past the saturation level (rig-145:
    # 2e6 against 9.8e3 after its lag was swapped for a current limit); Gauss-Newton steps from
    # there swung the cost by orders of magnitude and the screening never saw the limit
    from piezo_fmu.diagnose.varpro import DEEP_SAT, solve_linear

    assert DEEP_SAT < 200.0             # the weights below put the stroke 200 x past the sag level

    rec, dev, true, pr, lam = _saturated_recording()
    p = true.copy()
    p.weights = p.weights * 400.0      # |h| 200 x y_sat
    for _ in range(2):                  # as an optimisation calls it: the steps accumulate
        r = solve_linear([rec], dev, p, lam, gn_iter=2)
    assert float(r @ r) < 1e-6 * rec.n
    got = predict(rec, dev, p)
    assert np.max(np.abs(got["x"] - pr["x"])) < 1e-3 * np.ptp(pr["x"])


def test_a_linear_solve_with_a_drift_never_takes_a_step_that_raises_its_cost(monkeypatch):
    # with a saturation the solve is Gauss-Newton steps; with a drift's rate and curvature columns
    # one full step from weights fitted without them landed at a cost of 3.9e9 against 1.8e5
    # (rig-d11-021: the drift then screened 0.71 worse than none and was never fitted). Such a step
    # is re-solved with a Levenberg-Marquardt term towards where it started, or not taken
    from piezo_fmu.diagnose import varpro

    rec, dev, true, pr, lam = _saturated_recording(rate=0.02)
    start = true.copy()
    start.rate = 0.0
    start.weights = start.weights * 0.9
    r0 = varpro.residuals([rec], dev, start, lam)
    cost0 = float(r0 @ r0)
    # the undamped step made to land far off, as on rig-d11-021 (the damped ones solve as they are)
    solve = varpro._solve_into

    def wild(p, grams, dims, lam_, hint, before, prior, lm):
        solve(p, grams, dims, lam_, hint, before, prior, lm)
        if lm == 0.0:
            p.weights = p.weights * 0.07
    monkeypatch.setattr(varpro, "_solve_into", wild)
    for drift_terms in (1, 2):
        p = start.copy()
        r = varpro.solve_linear([rec], dev, p, lam, drift_terms=drift_terms, gn_iter=1)
        assert float(r @ r) <= cost0, drift_terms
        # not the wild step (a tenth of the stroke): the weights back near the true ones
        assert np.linalg.norm(p.weights - true.weights) < 0.2 * np.linalg.norm(true.weights)


def test_synthetic_recordings_are_reproducible_and_hide_the_truth(tmp_path):
    a = make_case(3, ["creep"], "mid", ["steps", "sines"], fs=1000.0)
    b = make_case(3, ["creep"], "mid", ["steps", "sines"], fs=1000.0)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.us, b.us)
    write_recording(tmp_path / "r.csv", a)
    text = (tmp_path / "r.csv").read_text()
    assert "creep" not in text and "gains" not in text
    assert text.splitlines()[1] == "time,u,x,us"


# -- the output contract ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def creep_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("creep")
    case = make_case(11, ["creep"], "mid", ["steps", "triangles"], fs=2000.0)
    write_recording(tmp / "rec.csv", case)
    t0 = time.perf_counter()
    code = main(["diagnose", str(tmp / "rec.csv"), "--out", str(tmp / "out")])
    return {"dir": tmp / "out", "rec": tmp / "rec.csv", "code": code, "case": case,
            "seconds": time.perf_counter() - t0}


def test_cli_writes_every_output(creep_run):
    out = creep_run["dir"]
    assert creep_run["code"] == 0
    for name in ("diagnosis.json", "fit.csv", "model.toml", "report.html", "residual_time.png",
                 "residual_spectrum.png", "fit_before_after.png"):
        assert (out / name).stat().st_size > 0, name
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 3          # self-contained


def test_diagnosis_json_follows_the_interface(creep_run):
    d = json.loads((creep_run["dir"] / "diagnosis.json").read_text())
    assert set(d["baseline"]["rmse"]) == {"x", "us"} and d["baseline"]["nrmse"] > 0
    assert [f["effect"] for f in d["findings"]] == ["creep"]
    f = d["findings"][0]
    assert 0.5 < f["confidence"] <= 1.0
    assert f["channel"] in ("x", "us") and f["channels"] == ["x", "us"]
    assert f["where"] and all(w["t1_s"] >= w["t0_s"] and w["why"] for w in f["where"])
    assert f["band_hz"][0] < 1.0                             # a slow mechanism
    truth = creep_run["case"].truth["parameters"]["creep"]
    # the fitted elements lie in the span of the true ones (one element may stand for two)
    lo, hi = min(truth["time_constants"]) / 1.5, max(truth["time_constants"]) * 1.5
    assert all(lo <= t <= hi for t in f["parameters"]["time_constants_s"]), (f["parameters"], truth)
    assert set(f["rmse_after"]) == {"x", "us"}
    assert d["final"]["effects"] == ["creep"]
    assert isinstance(d["unexplained"], list)
    assert "held out" in d["validation"]["method"]
    assert 0.2 < d["validation"]["heldout_fraction"] < 0.3


def test_fit_csv_lets_anyone_recompute_the_improvement(creep_run):
    d = json.loads((creep_run["dir"] / "diagnosis.json").read_text())
    fit = read_fit_csv(creep_run["dir"] / "fit.csv")
    assert list(fit) == ["time", "x", "us", "x_nominal", "us_nominal", "x_final", "us_final", "heldout"]
    ho = fit["heldout"] == 1
    for c in ("x", "us"):
        before = math.sqrt(np.mean((fit[c] - fit[f"{c}_nominal"])[ho] ** 2))
        after = math.sqrt(np.mean((fit[c] - fit[f"{c}_final"])[ho] ** 2))
        assert before == pytest.approx(d["baseline"]["rmse"][c], rel=1e-3)
        assert after == pytest.approx(d["final"]["rmse"][c], rel=1e-3)
        assert after < 0.5 * before                          # creep was most of the misfit
        assert after < 1.3 * NOISE["mid"][0 if c == "x" else 1]


def test_model_toml_is_loadable_and_replays_fit_csv(creep_run):
    out = creep_run["dir"]
    model = load_model(out / "model.toml")
    assert model["creep"]["gains"] and len(model["creep"]["gains"]) == len(model["creep"]["time_constants"])
    assert main(["validate", str(out / "model.toml")]) == 0
    fit = read_fit_csv(out / "fit.csv")
    t = fit["time"] - fit["time"][0]
    res = simulate(model, Signal("table", t=t, values=creep_run["case"].u, column="u"), t[-1], step=t[1] - t[0],
                   mode="open", noise=False)
    assert np.max(np.abs(res["x"] - fit["x_final"])) < 1e-6 * np.ptp(fit["x"])


def test_existing_outputs_are_not_overwritten_without_force(creep_run, capsys):
    out = creep_run["dir"]
    before = (out / "diagnosis.json").read_bytes()
    assert main(["diagnose", str(creep_run["rec"]), "--out", str(out), "--quiet"]) == 2
    assert "exists" in capsys.readouterr().err
    assert (out / "diagnosis.json").read_bytes() == before


def test_bad_recordings_are_user_errors(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("time,volts,x\n0,0,0\n0.1,1,1\n0.2,2,2\n")
    assert main(["diagnose", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "missing column(s) u" in capsys.readouterr().err
    bad.write_text("time,u,y\n" + "".join(f"{i * 0.01},{i},{i}\n" for i in range(100)))
    assert main(["diagnose", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "x, us" in capsys.readouterr().err
    bad.write_text("time,u,x\n" + "".join(f"{i * 0.01 + (0.003 if i == 50 else 0)},{i},{i}\n" for i in range(100)))
    assert main(["diagnose", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "uniform" in capsys.readouterr().err


# -- the report reads right -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def rest_step_run(tmp_path_factory):
    """A recording that rests at 0 V for 1.2 s, then steps up, holds, steps down and holds (the
    paper's device with creep, so there is something to find and locate)."""
    tmp = tmp_path_factory.mktemp("reststep")
    m = load_model()
    m.set("creep", "gains", [0.1], "test")
    m.set("creep", "time_constants", [0.4], "test")
    m.check()
    fs = 2000.0
    t = np.arange(int(5.0 * fs) + 1) / fs
    u = np.where(t < 1.2, 0.0, np.where(t < 3.0, 4.5, 1.0))
    res = simulate(m, Signal("table", t=t, values=u, column="u"), float(t[-1]), step=1 / fs, mode="open", noise=False)
    rng = np.random.default_rng(5)
    path = tmp / "rest_step.csv"
    with open(path, "w") as fh:
        fh.write("time,u,x,us\n")
        np.savetxt(fh, np.column_stack([t, u, res["x"] + 0.01 * rng.standard_normal(t.size),
                                        res["us"] + 0.002 * rng.standard_normal(t.size)]), delimiter=",", fmt="%.10g")
    out = tmp / "out"
    assert main(["diagnose", str(path), "--out", str(out), "--quiet", "--no-figures"]) == 0
    return {"json": json.loads((out / "diagnosis.json").read_text()), "html": (out / "report.html").read_text(),
            "steps": [1.2, 3.0]}


def _leaves(o, path=""):
    if isinstance(o, dict):
        for k, v in o.items():
            yield from _leaves(v, f"{path}.{k}")
    elif isinstance(o, list):
        for i, v in enumerate(o):
            yield from _leaves(v, f"{path}[{i}]")
    else:
        yield path, o


def _windows(o):
    """Every located window ({t0_s, t1_s, why}) anywhere in diagnosis.json."""
    if isinstance(o, dict):
        if "t0_s" in o and "why" in o:
            yield o
        for v in o.values():
            yield from _windows(v)
    elif isinstance(o, list):
        for v in o:
            yield from _windows(v)


def test_every_number_is_plain_with_its_unit(rest_step_run):
    import re

    d, html = rest_step_run["json"], rest_step_run["html"]
    for text in (json.dumps(d), html):
        assert "np.float" not in text and "float64" not in text and "np.int" not in text
    for where, v in _leaves(d):
        assert v is None or isinstance(v, (bool, int, float, str)), where
        if isinstance(v, float):
            assert math.isfinite(v), where
    # the findings table: bands and parameters as plain numbers with units
    assert d["findings"], d["rejected"]
    cells = re.findall(r"<td>([^<]*)</td>", html)
    bands = [c for c in cells if c.endswith(" Hz") and "-" in c and "," not in c]
    assert bands and all(re.fullmatch(r"[0-9.e+-]+-[0-9.e+-]+ Hz", b) for b in bands)
    for f in d["findings"]:
        assert f["band_hz"] is None or all(type(v) is float for v in f["band_hz"])
    assert "time_constants [" in html and "] s" in html          # creep's parameters carry their unit
    heads = re.findall(r"<th>([^<]*)</th>", html)
    assert "rmse x [um]" in heads and "rmse us [V]" in heads


def test_every_window_is_described_by_where_it_lies(rest_step_run):
    import re

    d = rest_step_run["json"]
    wins = list(_windows(d))
    assert wins
    seen_step = False
    for w in wins:
        t0, t1, why = w["t0_s"], w["t1_s"], w["why"]
        assert t1 >= t0
        # the residual in the window carries its channel's unit (until stop 83 x had "x units")
        unit = r"(x residual rms \S+ -> \S+ um|us residual rms \S+ -> \S+ V)$"
        assert "residual rms" not in why or re.search(unit, why), why
        for m in re.finditer(r"(hold after the step|before the step|step) of ([-+0-9.e]+) V at ([0-9.e+-]+) s", why):
            kind, at = m.group(1), float(m.group(3))
            assert any(abs(at - s) < 2e-3 for s in rest_step_run["steps"]), why
            if kind == "hold after the step":
                assert at <= t0 + 1e-3, why                      # the step lies before the window
            elif kind == "before the step":
                assert at >= t1 - 1e-3, why                      # ... or after it
            else:
                assert t0 - 1e-3 <= at <= t1 + 1e-3, why         # ... or inside it
                seen_step = True
        if t1 < rest_step_run["steps"][0]:
            assert "after the step" not in why, why              # the rest is before any step
    assert seen_step or any("hold after the step" in w["why"] for w in wins)


# -- blind recognition --------------------------------------------------------------------------------

@pytest.mark.parametrize("seed,noise,kinds", [(21, "low", ["sines", "steps", "chirp"]),
                                              (22, "high", ["triangles", "chirp"])])
def test_clean_recordings_name_nothing(tmp_path, seed, noise, kinds):
    d = run_blind(tmp_path, make_case(seed, [], noise, kinds, fs=2000.0))
    assert named(d) == []
    assert d.result["final"]["nothing_missing"]
    assert "nothing is missing" in d.result["final"]["verdict"]


SINGLE = [
    ("creep", 31, "mid", ["steps", "sines"]),
    ("sensor_leakage", 32, "mid", ["steps", "chirp"]),
    ("amplifier_current_limit", 33, "low", ["sines", "steps"]),
    ("time_delay", 34, "mid", ["chirp", "steps", "triangles"]),
    ("extra_resonance", 35, "low", ["steps", "chirp"]),
    ("thermal_drift", 36, "high", ["triangles", "sines"]),
    ("hysteresis_shape", 37, "mid", ["sines", "triangles"]),
]


@pytest.mark.parametrize("effect,seed,noise,kinds", SINGLE, ids=[s[0] for s in SINGLE])
def test_each_mechanism_is_named_blind(tmp_path, effect, seed, noise, kinds):
    # a loop-shape difference of less than twice the noise is ordinary (the recalibration refines
    # the loop, nothing is named): the shape here is the upper end of synth's range
    params = {"hysteresis_shape": {"extra_weight": 0.8}} if effect == "hysteresis_shape" else None
    case = make_case(seed, [effect], noise, kinds, fs=2000.0, params=params)
    d = run_blind(tmp_path, case)
    assert named(d) == [effect], d.result["rejected"]
    f = d.result["findings"][0]
    assert f["confidence"] > 0.3
    for c, v in d.result["final"]["rmse"].items():            # explained down to the noise
        assert v < 1.25 * case.truth["noise"][c]


PAIRS = [(("creep", "sensor_leakage"), 41, ["steps", "sines"]),
         (("amplifier_current_limit", "extra_resonance"), 42, ["steps", "chirp"])]


@pytest.mark.parametrize("effects,seed,kinds", PAIRS, ids=["+".join(p[0]) for p in PAIRS])
def test_pairs_of_mechanisms_are_both_named(tmp_path, effects, seed, kinds):
    d = run_blind(tmp_path, make_case(seed, list(effects), "mid", kinds, fs=2000.0))
    assert named(d) == sorted(effects), d.result["rejected"]


def test_an_unknown_disturbance_is_described_not_named(tmp_path):
    case = make_case(51, ["hum"], "mid", ["steps", "triangles"], fs=2000.0)
    d = run_blind(tmp_path, case)
    assert named(d) == []
    hum = case.truth["parameters"]["hum"]["freq"]
    bands = [u for u in d.result["unexplained"] if u["channel"] == "x"]
    assert any(u["band_hz"][0] - 2 <= hum <= u["band_hz"][1] + 2 for u in bands), d.result["unexplained"]
    assert not d.result["final"]["nothing_missing"]


def test_a_drifting_sensor_offset_is_not_called_leakage(tmp_path):
    case = make_case(52, ["sensor_drift"], "mid", ["triangles", "sines", "steps"], fs=2000.0)
    d = run_blind(tmp_path, case)
    assert named(d) == [], d.result["findings"]
    assert any(u["channel"] == "us" and "trend" in u["description"] for u in d.result["unexplained"])


def test_columns_units_and_an_inverted_channel(tmp_path):
    case = make_case(61, ["time_delay"], "low", ["chirp", "steps"], fs=2000.0)
    path = tmp_path / "renamed.csv"
    with open(path, "w") as fh:
        fh.write("# x in metres and pointing the other way\nt,V_cmd,disp,sensor\n")
        np.savetxt(fh, np.column_stack([case.t, case.u, -case.x * 1e-6, case.us]), delimiter=",", fmt="%.12g")
    code = main(["diagnose", str(path), "--columns", "time=t,u=V_cmd,x=disp,us=sensor", "--scale", "x=1e6",
                 "--out", str(tmp_path / "out"), "--quiet", "--no-figures"])
    assert code == 0
    d = json.loads((tmp_path / "out" / "diagnosis.json").read_text())
    assert [f["effect"] for f in d["findings"]] == ["time_delay"]
    assert d["recordings"][0]["sign"]["x"] == -1
    fit = read_fit_csv(tmp_path / "out" / "fit.csv")
    assert np.allclose(fit["x"], -case.x, atol=1e-9)          # reported in the file's orientation
    assert np.sqrt(np.mean((fit["x"] - fit["x_final"]) ** 2)) < 1.3 * NOISE["low"][0]


def test_several_recordings_are_fitted_together(tmp_path):
    params = {"sensor_leakage": {"tau_leak": 1.5}}
    a = make_case(71, ["sensor_leakage"], "mid", ["steps"], fs=1000.0, params=params)
    b = make_case(71, ["sensor_leakage"], "mid", ["sines"], fs=1000.0, params=params)
    write_recording(tmp_path / "a.csv", a)
    write_recording(tmp_path / "b.csv", b)
    d = diagnose([tmp_path / "a.csv", tmp_path / "b.csv"], out=tmp_path / "out", figures=False)
    assert named(d) == ["sensor_leakage"]
    assert d.result["findings"][0]["parameters"]["tau_leak_s"] == pytest.approx(1.5, rel=0.1)
    fit = read_fit_csv(tmp_path / "out" / "fit.csv")
    assert set(np.unique(fit["recording"])) == {0.0, 1.0}


# -- the real recordings ------------------------------------------------------------------------------

@pytest.fixture(scope="module", params=REAL_RECORDINGS, ids=lambda r: r[0].parent.name)
def real_run(request, tmp_path_factory):
    path, scale = request.param
    out = tmp_path_factory.mktemp("real") / "out"
    return path, diagnose([path], out=out, scale=scale, figures=False), out


def test_real_recordings_improve_on_held_out_data_and_name_nothing_weak(real_run):
    path, diag, out = real_run
    res = diag.result
    assert (path.parent / "LICENSE").exists() and (path.parent / "README.md").exists()
    # units and scale unlike the paper's: the nominal model as given is far off, the recalibrated one close
    assert res["baseline"]["nominal_as_given_rmse"]["x"] > 20 * res["baseline"]["rmse"]["x"]
    fit = read_fit_csv(out / "fit.csv")
    ho = fit["heldout"] == 1
    before = math.sqrt(np.mean((fit["x"] - fit["x_nominal"])[ho] ** 2))
    after = math.sqrt(np.mean((fit["x"] - fit["x_final"])[ho] ** 2))
    assert before == pytest.approx(res["baseline"]["rmse"]["x"], rel=1e-3)
    assert after == pytest.approx(res["final"]["rmse"]["x"], rel=1e-3)
    assert after <= before * 1.0001                        # the final model never fits held-out data worse
    # nothing weak is named: every finding is confident, weaker ones are candidates only
    assert [f["effect"] for f in res["findings"]] == res["final"]["effects"]
    assert all(f["confidence"] >= 0.5 for f in res["findings"])
    assert all(c["confidence"] < 0.5 and c["effect"] not in res["final"]["effects"] for c in res["candidates"])
    # and nothing at a bound of its search range is accepted
    assert not any(r.get("at_bound") and r["effect"] in res["final"]["effects"] for r in res["rejected"])
    if not res["findings"]:
        assert after == pytest.approx(before, rel=1e-9)     # no finding: the final model is the recalibrated one


def test_a_finer_loop_the_held_out_data_confirm_is_an_ordinary_refinement(real_run):
    # dbo_test: 71 s of a 1 Hz drive with holds and nested minor loops. The finer loop fails on BIC
    # alone (the slow record has few effective samples) while the held-out data take all of it
    # (beta 1.01, z 7.2): it goes into the recalibration, never into the names, and the
    # recalibrated model fits the held-out data better than the nine-operator one (0.151)
    path, diag, out = real_run
    if path.parent.name != "dbo_test":
        pytest.skip("dbo_test only")
    res = diag.result
    loop = res["baseline"]["recalibrated"].get("loop", {})
    assert loop.get("refined"), res["baseline"]["recalibrated"]
    assert "hysteresis_shape" not in res["final"]["effects"]
    assert res["baseline"]["rmse"]["x"] < 0.125


# -- the benchmark's size (its speed is measured by `piezo-fmu bench`, diagnose_s) --------------------

@pytest.mark.slow
def test_twenty_seconds_at_ten_kilohertz_names_both_mechanisms(tmp_path):
    case = make_case(5, ["creep", "time_delay"], "mid", None, fs=10000.0, duration=20.0)
    path = tmp_path / "big.csv"
    write_recording(path, case)
    assert case.t.size == 200001
    # no time budget: the result must not depend on how busy the machine is (speed: piezo-fmu bench)
    d = diagnose([path], out=tmp_path / "out", time_budget_s=None)
    assert named(d) == ["creep", "time_delay"]
    assert d.result["final"]["rmse"]["x"] < 0.5 * d.result["baseline"]["rmse"]["x"]


# -- back into the FMUs ----------------------------------------------------------------------------------

@pytest.mark.slow
def test_fmus_rebuilt_from_the_diagnosed_model_reproduce_the_recording(creep_run, tmp_path):
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from piezo_fmu import builder
    cosim = pytest.importorskip("piezo_fmu.cosim")
    out = creep_run["dir"]
    fmus = tmp_path / "fmus"
    builder.build_all(out / "model.toml", fmus, ssp=False, log=lambda msg: None)
    fit = read_fit_csv(out / "fit.csv")
    t = fit["time"] - fit["time"][0]
    dt = float(t[1] - t[0])
    res = cosim.cosimulate(fmus, Signal("table", t=t, values=creep_run["case"].u, column="u"), float(t[-1]),
                           step=dt, mode="open")
    n = t.size
    x_co = np.asarray(res["x"][:n])
    us_co = np.asarray(res["us"][:n])
    d = json.loads((out / "diagnosis.json").read_text())
    noise = d["baseline"]["noise"]
    # the co-simulation is the final model (up to the actuator's sub-steps and the sensor noise)...
    assert np.sqrt(np.mean((x_co - fit["x_final"]) ** 2)) < 0.2 * noise["x"]
    assert np.sqrt(np.mean((us_co - fit["us_final"]) ** 2)) < 1.5 * noise["us"]
    # ...and so reproduces the recording as well as the diagnosis says, on its held-out part
    ho = fit["heldout"] == 1
    assert np.sqrt(np.mean((x_co - fit["x"])[ho] ** 2)) < 1.05 * d["final"]["rmse"]["x"] + 0.1 * noise["x"]
    shutil.rmtree(fmus, ignore_errors=True)


@pytest.mark.parametrize("seed, kinds", [(1001, None), (31, ["steps", "sines"])])
def test_the_channels_calibration_is_reported_with_an_uncertainty_that_covers_the_truth(seed, kinds):
    # a clean recording of the project's own model (exact structure, known offsets and quartz
    # sensitivity): the recalibrated offsets [um, V] and sensitivity [V/N] lie within three of
    # their standard uncertainties of what the recording was made with (measured: 0.02-1.9 of
    # one). The uncertainty is the noise's; it would not cover a wrong model
    from piezo_fmu.diagnose.run import analyse

    case = make_case(seed, [], "low", kinds, fs=2000.0 if kinds else 5000.0)
    plant = case.truth["plant"]
    s = plant["sensor"]
    c_quartz = 8.8541878128e-12 * s["eps_r"] * s["area"] / s["thickness"]
    truth = {"x_offset_um": plant["drift"]["offset"], "sensor_offset_V": s["offset"],
             "sensor_sensitivity_V_per_N": s["d11"] / (c_quartz + s["C_load"])}
    rc = analyse([{"name": "clean", "time": case.t, "u": case.u, "x": case.x, "us": case.us}]).result[
        "baseline"]["recalibrated"]
    for key, true in truth.items():
        v = rc[key]
        sigma = v["uncertainty"] if "uncertainty" in v else v["relative_uncertainty"] * abs(v["value"])
        assert sigma > 0, (key, v)
        assert abs(v["value"] - true) < 3 * sigma, (key, v, true, (v["value"] - true) / sigma)
    assert rc["pi_scale_um"]["relative_uncertainty"] > 0


def test_cancelling_weights_still_make_a_valid_model_file():
    # a poorly conditioned fit (rig-083: 1846 samples) gave +761 and -761 um on the first two
    # operators; rounded to 8 digits their partial sum was 0 and writing model.toml crashed
    from piezo_fmu.diagnose.model_io import model_from_params, params_from_model
    from piezo_fmu.model import load_model

    base = load_model()
    p = params_from_model(base, 1e-3)
    p.weights = np.array([761.659491, -761.659479, 0.0, 23.87, -23.22, 236.58, -22.05, -40.23, -106.71])
    m = model_from_params(base, p, {}, dt=1e-3).check()
    w = np.asarray(m["hysteresis"]["weights"], float)
    assert np.all(np.cumsum(w) > 0)
    assert m["hysteresis"]["scale"] * w[0] == pytest.approx(761.659491, rel=1e-9)


def test_an_operator_the_data_never_move_gets_no_weight():
    # rig-096: the top operator of a refined loop never moved (its column ~1e-160); the weights
    # solve gave it 2.5e145 um and the model file a negative scale
    from piezo_fmu.diagnose.varpro import _bounded_normal_solve

    rng = np.random.default_rng(3)
    m = np.column_stack([rng.standard_normal((500, 3)), 1e-160 * rng.standard_normal(500)])
    y = m[:, :3] @ np.array([1.0, 0.5, 0.25]) + 1e-3 * rng.standard_normal(500)
    theta = _bounded_normal_solve(m.T @ m, m.T @ y, n_bounded=0)
    assert np.all(np.isfinite(theta)) and abs(theta[3]) < 1e-6
    assert theta[:3] == pytest.approx([1.0, 0.5, 0.25], abs=1e-3)


def test_the_bounded_weights_solve_finds_what_bvls_finds_without_running_it(monkeypatch):
    # the weights' solve runs inside the sensor gain's alternation (tens of rounds per solve, 52 000
    # solves on rig-d13-034): the active sets (varpro._active_set) settle in one or two least-squares
    # solves on the bound-free columns where bvls iterates. Same minimiser, bvls never needed
    from scipy.optimize import lsq_linear

    from piezo_fmu.diagnose import varpro

    rng = np.random.default_rng(11)
    problems = []
    for k in range(40):
        n, nb = 12, 9
        m = rng.standard_normal((400, n))
        m[:, 1] = m[:, 0] + 10.0 ** -(k % 5) * m[:, 1]           # nearly collinear columns
        theta = rng.standard_normal(n)                            # some partial sums below zero
        y = m @ theta + 0.01 * rng.standard_normal(400)
        problems.append((m, y, nb))
    want = []
    for m, y, nb in problems:
        d = np.linalg.norm(m, axis=0)
        lb = np.full(m.shape[1], -np.inf)
        lb[:nb] = 1e-6 * d[:nb]
        want.append(lsq_linear(m / d, y, bounds=(lb, np.inf), method="bvls", lsmr_tol=None, tol=1e-14).x / d)

    def refuse(*args, **kwargs):
        raise AssertionError("bvls run")

    monkeypatch.setattr(varpro, "lsq_linear", refuse)
    active = 0
    for (m, y, nb), w in zip(problems, want):
        theta = varpro._bounded_normal_solve(m.T @ m, m.T @ y, n_bounded=nb)
        cost = np.sum((m @ theta - y) ** 2)
        assert cost <= np.sum((m @ w - y) ** 2) * (1 + 1e-9)
        assert np.all(theta[:nb] > 0)
        assert theta == pytest.approx(w, rel=1e-5, abs=1e-6 * np.max(np.abs(w)))
        active += int(np.sum(theta[:nb] < 1e-5 * np.max(np.abs(theta))))
    assert active >= 40                                           # the bounds did bind

    # a guess that holds the wrong entries still ends at the minimiser
    m, y, nb = problems[0]
    d = np.linalg.norm(m, axis=0)
    R = np.linalg.qr(m / d, mode="r")
    q = np.linalg.lstsq(R.T, (m / d).T @ y, rcond=None)[0]
    lb = np.full(m.shape[1], -np.inf)
    lb[:nb] = 1e-6 * d[:nb]
    for guess in (np.zeros(nb, bool), np.ones(nb, bool)):
        t = varpro._active_set(R, q, lb, nb, guess)
        assert t is not None and t / d == pytest.approx(want[0], rel=1e-5, abs=1e-6 * np.max(np.abs(want[0])))


# -- devices the tool was not built from (piezo_fmu.rig, written independently) ----------------------

def _rig_recording(case_id):
    from piezo_fmu import rig

    # rig-NNN: the established set; rig-dK-NNN: draw K (fresh seeds, `evaluate --draw K`)
    draw = int(case_id.split("-")[1][1:]) if case_id.startswith("rig-d") else 0
    spec = next(s for s in rig.cases(draw=draw) if s.case_id == case_id)
    rec = rig.generate(spec)
    return rec, [{"name": case_id, "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}]


def test_a_channel_keeps_its_sign_after_an_excursion_the_nominal_loop_would_hold():
    # rig-d24-049 (a clean KP device): a 250 V chirp, then one 470 V peak decaying to 0 V over 9 s.
    # The nominal PI, re-normalised to that span, holds half its stroke through the decay on its
    # wide plays: its prediction does not follow x, and a sign taken from it negated both channels
    # (nothing could be fitted after that; a false loop shape 206 x the noise was named). The sign
    # comes from the nominal dynamics with a linear loop
    from piezo_fmu.diagnose.engine import Device
    from piezo_fmu.diagnose.recordings import make_recordings
    from piezo_fmu.diagnose.run import orient

    rec, raw = _rig_recording("rig-d24-049")
    recs = make_recordings(raw)
    model = load_model()
    dev = device_from_model(model)
    p = params_from_model(model, recs[0].dt)
    span = float(np.max(rec.u)) * dev.k_amp
    assert span / p.u_norm > 3                      # so the diagnosis re-normalises to it, as here
    p.u_norm = span
    dev = Device(**{**dev.__dict__, "u_max": 1.05 * span})
    x = recs[0].x.copy()
    assert np.corrcoef(predict(recs[0], dev, p)["x"], x)[0, 1] < 0.1
    assert orient(recs, dev, p) == []
    assert recs[0].sign == {"x": 1, "us": 1}
    assert np.array_equal(recs[0].x, x)


def test_a_loop_that_explains_part_of_what_a_named_mode_leaves_is_not_named():
    # rig-d24-055 (761 Hz, a KP device without a shape): a 75 Hz further mode (zeta 0.005) beside a
    # first mode above the Nyquist frequency. Named, the mode leaves 68 x the probe's noise; a finer
    # loop then explains 43 % of it, 3.9 x the noise from every classical loop, and was named as a loop
    # shape "with other misfit beside it", then again at the search's end (z 46). Beside a named
    # mechanism such a loop is that mechanism's misfit the cells bend to: taken into the
    # recalibration in the round, at most a candidate at the end
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d24-055")
    assert rec.truth["mechanisms"] == ["extra_resonance"]
    lines = []
    res = analyse(raw, say=lines.append).result
    assert res["final"]["effects"] == ["extra_resonance"], res["final"]
    assert any("explains 43 %" in m and "beside extra_resonance: named from 70%" in m for m in lines)
    assert any("the rounds took its loop in explaining 43 %" in m for m in lines)
    assert [c["effect"] for c in res["candidates"]] == ["hysteresis_shape"]


def test_an_independent_device_is_recalibrated_not_named():
    # rig-046: a clean Krasnosel'skii-Pokrovskii device (not PI) on other thresholds, exercised up to
    # its top voltage before the record, a first mode near 300 Hz and a displacement pick-off. The
    # recalibration finds the stack's starting memory, the thresholds' voltage scale and the mode;
    # nothing is named and nothing is missing
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-046")
    assert rec.truth["mechanisms"] == [] and rec.truth["control"] is None
    res = analyse(raw).result
    rc = res["baseline"]["recalibrated"]
    assert rc["initial_state"]["value"] == "prepared"
    assert rc["threshold_scale_V"]["identified"]
    assert rc["first_mode_hz"]["identified"]
    assert rc["first_mode_hz"]["value"] == pytest.approx(rec.truth["params"]["mechanics.f1"]["value"], rel=0.05)
    assert res["final"]["effects"] == [] and res["candidates"] == []
    assert res["final"]["nothing_missing"], res["final"]["verdict"]


def test_a_slowly_sampled_device_is_replayed_between_its_samples():
    # rig-d6-116: a clean Bouc-Wen device sampled at 545 Hz (a 0.51 + 0.29 ms amplifier, a 246 Hz
    # first mode, force pick-off). At one step per sample its contact force differs from the rig's
    # by 61 noise rms for the true parameters, and the recalibrated model leaves a structured
    # residual "no catalogue mechanism explains"; replayed at 8 kHz (15 internal steps per sample)
    # it fits to the noise, and nothing is missing
    from piezo_fmu.diagnose.recordings import INTERNAL_RATE
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d6-116")
    assert rec.truth["group"] == "clean"
    res = analyse(raw, replay_rate=INTERNAL_RATE).result
    assert res["recordings"][0]["replay_steps_per_sample"] == 15
    assert res["final"]["nothing_missing"] and not res["final"]["effects"], res["final"]["verdict"]
    res1 = analyse(raw).result                                           # the default: one step per sample
    assert res1["recordings"][0]["replay_steps_per_sample"] == 1
    assert not res1["final"]["nothing_missing"]
    assert res["final"]["rmse"]["us"] < 0.5 * res1["final"]["rmse"]["us"]


def test_a_thermal_drift_seen_by_a_displacement_pickoff_is_named():
    # rig-085: the drift moves the push rod, so a sensor following it (a displacement pick-off)
    # shows it too; once this was taken for a force trend and the drift went unnamed
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-085")
    assert rec.truth["mechanisms"] == ["thermal_drift"]
    assert rec.truth["params"]["sensor.pickoff"]["value"] == "displacement"
    res = analyse(raw).result
    assert res["final"]["effects"] == ["thermal_drift"], res["rejected"]
    assert res["baseline"]["recalibrated"]["sensor_follows"]["value"] == "load"
    f = res["findings"][0]
    assert f["confidence"] >= 0.5
    assert min(f["evidence"]["explained_share_heldout"].values()) > 0.5        # both channels


def test_a_drift_does_not_hide_where_the_thresholds_sit():
    # rig-161: a PI device on other thresholds (dense below 20 V of a 49 V drive) with a thermal
    # drift. Before the drift is in, the residual is mostly trend (few effective samples) and the
    # better threshold scale is "not clearly better" (BIC gain 2.7); left at the start, the loop
    # misfit was named as a finer loop beside the drift. The scale is asked again once the drift
    # is in
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-161")
    assert rec.truth["mechanisms"] == ["thermal_drift"]
    res = analyse(raw).result
    assert res["final"]["effects"] == ["thermal_drift"], res["rejected"]
    assert res["baseline"]["recalibrated"]["threshold_scale_V"]["identified"]


def test_a_further_mode_at_the_devices_first_mode_is_recalibrated_not_named():
    # rig-098: a drift on a device whose first mode (232 Hz, zeta 0.038) the recalibration placed
    # elsewhere; the search then found it as a "further mode" that took the first mode's place and
    # named it beside the drift. Since the first mode may be heavily damped with a contact-force
    # pick-off, the recalibration finds that mode itself; rig-179 (creep, the displacement only,
    # a first mode of 444 Hz) still finds it where a further mode is searched. Started from what
    # the search found, the first mode explains it as well: ordinary physics. (rig-179's drift, a
    # candidate at 0.47 beside the creep, stays one: with the creep in, its backward BIC gain falls
    # from 4393 to 107, so the backward measure, 0.52, does not raise its confidence)
    from piezo_fmu.diagnose.run import analyse

    for case, truth in (("rig-098", ["thermal_drift"]), ("rig-179", ["creep"])):
        rec, raw = _rig_recording(case)
        assert rec.truth["mechanisms"] == truth
        res = analyse(raw).result
        assert res["final"]["effects"] == truth, (case, res["rejected"])
        mode = res["baseline"]["recalibrated"]["first_mode_hz"]
        assert mode["identified"], case
        assert mode["value"] == pytest.approx(rec.truth["params"]["mechanics.f1"]["value"], rel=0.03), case
        if case == "rig-179":
            assert "where a further mode was searched" in mode["why"]
            assert any(r["effect"] == "extra_resonance" and "first mode" in r["why"] for r in res["rejected"])


def test_a_diverged_refit_of_the_nominal_model_does_not_replace_it():
    # rig-025: a further mode (178 Hz) and a leakage on a device whose first mode is at 741 Hz.
    # Both are named; the nominal model re-fitted at the end without them (the ordinary physics
    # found since kept) diverged and was reported as the "before" model: 183 um rms in x against
    # 0.5 for the recalibrated nominal model (noise 0.026 um), 4e4 times its training cost. A
    # refit that diverged (run.DIVERGED times the cost of the model it replaces) is not taken
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-025")
    res = analyse(raw).result
    assert res["final"]["effects"] == ["extra_resonance", "sensor_leakage"], res["rejected"]
    before, after = res["baseline"]["rmse"], res["final"]["rmse"]
    assert before["x"] < 1.0 and before["us"] < 0.1, before
    assert after["x"] < 0.5 * before["x"] and after["us"] < 0.5 * before["us"]


def test_a_further_mode_taken_for_the_first_mode_is_found_in_its_place():
    # rig-119: a mode of 148 Hz (zeta 0.006) in series with a device whose own first mode is at
    # 485 Hz; the recalibration took the 148 Hz mode for the first mode and nothing was named
    # (16 noise rms left in x). A further mode is also screened where the first mode was, the
    # first mode restarted elsewhere. rig-089 (with a drift, 5 k samples): the same at 121 Hz
    from piezo_fmu.diagnose.run import analyse

    for case in ("rig-089", "rig-119"):
        rec, raw = _rig_recording(case)
        truth = rec.truth["params"]
        res = analyse(raw).result
        assert res["final"]["effects"] == sorted(rec.truth["mechanisms"]), (case, res["rejected"])
        found = next(f for f in res["findings"] if f["effect"] == "extra_resonance")["parameters"]
        assert found["f_n_Hz"] == pytest.approx(truth["extra_resonance.f"]["value"], rel=0.01), case
        assert found["zeta"] == pytest.approx(truth["extra_resonance.zeta"]["value"], rel=0.1), case
    # rig-119: the one-mode model left 0.150 um held-out (32 x the noise), the two modes 0.0058
    assert res["final"]["rmse"]["x"] < 0.05 * res["baseline"]["rmse"]["x"]
    # rig-004 (a drift and a delay, a first mode at 302 Hz, zeta 0.015): its own mode is drawn the
    # other way too. The swap explains 97 % in round 3 (the delay named a sample short), but it
    # moves the first mode to 710 Hz at zeta 0.35, a lag: a moved mode damped beyond
    # catalogue.MODE_LIGHT must beat the lags it may stand for, re-fitted in its place (a second
    # amplifier stage, the delay stepped), and there they kept 95 % of its gain (at least
    # MODE_LAG_KEPT rejects); before the first mode's damping was searched from 0.007, round 4
    # swapped with 67 %, under MODE_SWAP_EXPLAINED. Since stop 67 a moved mode at the end of its
    # search range is rejected before the lags are weighed: 0.35 is the end of the damping's range
    # for a displacement or load pick-off (rig-d19-074 below)
    from piezo_fmu.diagnose.catalogue import MODE_LIGHT

    rec, raw = _rig_recording("rig-004")
    assert "extra_resonance" not in rec.truth["mechanisms"]
    res = analyse(raw).result
    assert "extra_resonance" not in res["final"]["effects"]
    why = [r["why"] for r in res["rejected"] if r["effect"] == "extra_resonance"
           and "the end of its search range" in r["why"] and "the device's own mode" in r["why"]]
    assert why, res["rejected"]
    assert MODE_LIGHT < float(why[0].split("damping ratio ")[1].split(")")[0]) >= 0.35, why[0]


def test_a_further_mode_far_below_the_first_mode_is_swapped_with_restarts_far_enough_up():
    # rig-d23-090 (12.3 kHz, force pick-off): a further mode at 283 Hz (zeta 0.005) before a first
    # mode at 3.1 kHz. The recalibration took the 283 Hz mode for the first mode; the swap's restarts
    # of the first mode went up to 6.3 x that (1.8 kHz), its fit ran to the range's end (10.5 kHz)
    # and explained 78 % (< catalogue.MODE_SWAP_EXPLAINED): nothing named, x left at 0.14 um. With
    # restarts at 10 and 16 x it explains 97 % (held-out z 430) and the further mode is named
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d23-090")
    truth = rec.truth["params"]
    assert rec.truth["mechanisms"] == ["extra_resonance"]
    res = analyse(raw).result
    assert res["final"]["effects"] == ["extra_resonance"], res["rejected"]
    found = next(f for f in res["findings"] if f["effect"] == "extra_resonance")["parameters"]
    assert found["f_n_Hz"] == pytest.approx(truth["extra_resonance.f"]["value"], rel=0.01)
    assert res["final"]["rmse"]["x"] < 0.3 * res["baseline"]["rmse"]["x"]


def test_a_swap_whose_moved_mode_rings_where_it_was_moved_is_two_modes(monkeypatch, rules_before):
    # rig-d25-015 (1.12 kHz, displacement pick-off, a current limit beside): the device's own mode at
    # 213 Hz (zeta 0.048) and a further one at 373 Hz (zeta 0.017). After the limit, the further
    # mode's fit took the first mode's place (214 Hz) and moved the first mode to 374 Hz at zeta
    # 0.021: both modes found, but explaining 50 % of the structured residual (held-out beta 1.03,
    # z 11.5) it was refused as the device's own mode drawn another way (< MODE_SWAP_EXPLAINED).
    # 44 % of what the swap changes lies near the moved mode (its swaps that were a device's own
    # mode drawn another way: 0.00-0.08): it rings there, a second mode, and is named
    from piezo_fmu.diagnose import catalogue
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d25-015")
    truth = rec.truth["params"]
    assert sorted(rec.truth["mechanisms"]) == ["amplifier_current_limit", "extra_resonance"]
    res = analyse(raw).result
    assert res["final"]["effects"] == ["amplifier_current_limit", "extra_resonance"], res["rejected"]
    found = next(f for f in res["findings"] if f["effect"] == "extra_resonance")
    assert found["confidence"] >= 0.5
    # which of two modes in series is the "further" one the data do not say: one of the device's
    modes = (truth["mechanics.f1"]["value"], truth["extra_resonance.f"]["value"])
    assert min(abs(found["parameters"]["f_n_Hz"] / f - 1) for f in modes) < 0.02, found["parameters"]
    assert res["final"]["rmse"]["x"] < 0.1 * res["baseline"]["rmse"]["x"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # with the moved mode's ringing not counted, the swap is refused as before
    monkeypatch.setattr(catalogue, "MODE_MOVED_RINGS", math.inf)
    res = analyse(raw).result
    assert "extra_resonance" not in res["final"]["effects"]
    assert any("drawn another way" in r["why"] for r in res["rejected"] if r["effect"] == "extra_resonance")


def test_a_further_mode_whose_partner_ends_at_a_range_end_is_the_first_mode_found_again():
    # rig-d19-074 (fresh draw 19, clean: 12 kHz, force pick-off, first mode 2688 Hz, zeta 0.093):
    # the further mode's fit took the recalibrated first mode's place (2.64 kHz) and moved the first
    # mode to 10.2 kHz, zeta 0.26 - the top of its range (0.85 x the sample rate) - and the lags
    # in its place kept -39 % of the gain: named as two modes at confidence 1.0 (stop 66 code).
    # A value at the end of its search range is one the data did not place: not named
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d19-074")
    assert rec.truth["mechanisms"] == []
    res = analyse(raw).result
    assert "extra_resonance" not in res["final"]["effects"], res["findings"]
    why = [r["why"] for r in res["rejected"] if r["effect"] == "extra_resonance"]
    assert why and all("moves that to the end of its search range" in w for w in why), why


def test_a_further_mode_is_screened_with_the_first_mode_searched_again(monkeypatch, rules_before):
    # rig-d5-000 (1.47 kHz sampling): a further mode at 205 Hz (zeta 0.017) in series with the
    # device's own at 484 Hz (zeta 0.035). The recalibration bent the first mode to 997 Hz, zeta
    # 0.13, and from there a mode at the residual's 205 Hz peak screened 3.8 x worse than none:
    # never fitted, nothing named with 3.4 noise rms left in x. Each peak is now screened with the
    # first mode searched again (starts.MODE_RESEARCH). rig-d5-168: the recalibration took the
    # further 292 Hz mode for the first mode; the device's own 499 Hz rang in the residual, 1.7 x
    # it, between the swap's restarts: the residual's peaks are restarts too, and the best three
    # have the lag the old mode had absorbed searched again (the true pair: 0.98 x the old cost
    # before that, 0.09 x after)
    from piezo_fmu.diagnose import starts
    from piezo_fmu.diagnose.run import analyse

    for case in ("rig-d5-000", "rig-d5-168"):
        rec, raw = _rig_recording(case)
        truth = rec.truth["params"]
        assert rec.truth["mechanisms"] == ["extra_resonance"]
        res = analyse(raw).result
        assert res["final"]["effects"] == ["extra_resonance"], (case, res["rejected"])
        found = next(f for f in res["findings"] if f["effect"] == "extra_resonance")
        assert found["confidence"] >= 0.5
        assert found["parameters"]["f_n_Hz"] == pytest.approx(truth["extra_resonance.f"]["value"], rel=0.01), case
        assert res["final"]["rmse"]["x"] < 0.5 * res["baseline"]["rmse"]["x"], case
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # rig-d5-000 with the first mode left where the recalibration put it (the rule before)
    monkeypatch.setattr(starts, "first_mode_searched", lambda fitter, q, ctx: (fitter.quick(q), q))
    rec, raw = _rig_recording("rig-d5-000")
    assert "extra_resonance" not in analyse(raw).result["final"]["effects"]


def test_a_mode_the_held_weights_hide_is_screened_with_them_re_solved(monkeypatch, rules_before):
    # rig-d8-001 (Krasnosel'skii-Pokrovskii, 7.15 kHz): a further mode at 61.6 Hz, zeta 0.005, 22 x
    # the noise in x. The recalibrated PI weights and lag bent to it (lag 1.44 ms for a true 0.27 +
    # 0.14 ms), so with them held the true mode at the residual's peak screened 3.3-5.5 x worse than
    # none and the grid's best start was a 3.2 kHz mode that changed nothing: nothing named. The
    # residual's peaks are now also scored with the weights re-solved (starts.PEAK_SOLVED_ZETA)
    from piezo_fmu.diagnose import starts
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d8-001")
    truth = rec.truth["params"]
    assert rec.truth["mechanisms"] == ["extra_resonance"]
    res = analyse(raw).result
    assert res["final"]["effects"] == ["extra_resonance"], res["rejected"]
    found = next(f for f in res["findings"] if f["effect"] == "extra_resonance")
    assert found["confidence"] >= 0.5
    assert found["parameters"]["f_n_Hz"] == pytest.approx(truth["extra_resonance.f"]["value"], rel=0.01)
    assert found["parameters"]["zeta"] == pytest.approx(truth["extra_resonance.zeta"]["value"], rel=0.2)
    assert res["final"]["rmse"]["x"] < 0.2 * res["baseline"]["rmse"]["x"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # without the re-solved peak starts (the rule before) the mode is not named
    monkeypatch.setattr(starts, "PEAK_SOLVED_ZETA", ())
    assert "extra_resonance" not in analyse(raw).result["final"]["effects"]


def test_a_lightly_damped_fixture_mode_is_not_taken_for_the_first_mode():
    # rig-177: a further mode of 234 Hz at zeta 0.005 (a fixture's) on a device whose own first
    # mode (6.7 kHz, zeta 0.12) lies above the Nyquist frequency of its 4.39 kHz sampling. The
    # recalibration took the 234 Hz mode for the first mode (zeta 0.005, the sensor on the load
    # spring) and said "nothing is missing" with 41 noise rms of it in x. A stack's own mode is
    # searched at damping ratios from fit.MODE_ZETA_MIN (the device class's 0.01, -30 %): there the
    # fit settles at the end of its range and the further mode is named
    from piezo_fmu.diagnose.fit import MODE_ZETA_MIN
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-177")
    truth = rec.truth["params"]
    assert truth["extra_resonance.zeta"]["value"] < MODE_ZETA_MIN < truth["mechanics.zeta1"]["value"]
    res = analyse(raw).result
    assert res["final"]["effects"] == ["extra_resonance"], res["rejected"]
    found = next(f for f in res["findings"] if f["effect"] == "extra_resonance")
    assert found["confidence"] >= 0.5
    assert found["parameters"]["f_n_Hz"] == pytest.approx(truth["extra_resonance.f"]["value"], rel=0.01)
    mode = res["baseline"]["recalibrated"].get("first_mode_hz", {})
    assert not (mode.get("identified") and abs(math.log(mode["value"] / found["parameters"]["f_n_Hz"])) < 0.2), mode
    assert res["final"]["rmse"]["x"] < 0.3 * res["baseline"]["rmse"]["x"]


def test_a_further_mode_that_amplifies_the_drive_below_it_rings_at_its_own_frequency(monkeypatch, rules_before):
    # rig-d26-069 (fresh draw 26): a further mode of 79 Hz at zeta 0.005, 224 noise rms in x, driven
    # by sines of 2-50 Hz and two steps. Its fit explained all of the residual (held-out beta 0.99 at
    # z 473) but was refused: 6 % of what it changes lay within 1.25 x of 79 Hz - the rest is the
    # amplification of the 50 Hz sine below it. From f_n / 2 it is 99 %
    from piezo_fmu.diagnose import catalogue
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d26-069")
    truth = rec.truth["params"]
    res = analyse(raw).result
    assert "extra_resonance" in res["final"]["effects"], res["rejected"]
    found = next(f for f in res["findings"] if f["effect"] == "extra_resonance")
    assert found["parameters"]["f_n_Hz"] == pytest.approx(truth["extra_resonance.f"]["value"], rel=0.02)
    assert res["final"]["rmse"]["x"] < 0.1 * res["baseline"]["rmse"]["x"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # with the band around the mode alone (the rule before) it is refused
    monkeypatch.setattr(catalogue, "MODE_OWN_BELOW", (2.0, math.inf, 0.05))
    res = analyse(raw).result
    assert "extra_resonance" not in res["final"]["effects"]
    assert any("does not ring at its own frequency" in r["why"] for r in res["rejected"])


def test_a_share_the_held_out_data_confirm_counts_toward_the_size_of_a_finding():
    # size: the share over every sample counted in full from half, or the held-out share as it is
    from piezo_fmu.diagnose.decide import confidence

    def cmp(explained, heldout):
        ch = {"explained": explained, "explained_heldout": heldout}
        return {"channels": {"x": ch}, "dbic": 300.0, "beta_heldout": 1.0, "z_heldout": 30.0}

    assert confidence(cmp(0.19, 0.19), "thermal_drift") == pytest.approx(0.38, abs=0.01)
    assert confidence(cmp(0.19, 0.79), "thermal_drift") == pytest.approx(0.79, abs=0.01)
    assert confidence(cmp(0.45, 0.79), "thermal_drift") == pytest.approx(0.90, abs=0.01)
    assert confidence(cmp(0.6, 0.0), "thermal_drift") == pytest.approx(1.0, abs=0.01)
    assert confidence(cmp(0.19, -0.5), "thermal_drift") == pytest.approx(0.38, abs=0.01)


def test_a_drift_whose_training_blocks_hold_other_misfit_is_named_on_its_held_out_share():
    # rig-083: sensor leakage and a thermal drift, 1846 samples. With the leakage named, the drift
    # removes 28 % of the structured residual over every sample (the training blocks hold misfit it
    # does not touch) and all of it on the held-out samples (x 0.067 -> 0.031 um, beta 0.96 at z
    # 29): a candidate at confidence 0.33 when only the first share counted, named now
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-083")
    res = analyse(raw).result
    assert res["final"]["effects"] == sorted(rec.truth["mechanisms"]), (res["candidates"], res["rejected"])
    drift = next(f for f in res["findings"] if f["effect"] == "thermal_drift")
    ev = drift["evidence"]
    assert ev["explained_share"]["x"] < 0.35 and ev["explained_share_heldout"]["x"] > 0.9, ev
    assert drift["confidence"] >= 0.5


def test_a_rival_the_training_rows_tell_apart_leaves_the_best_unique():
    # two candidates against the same residual: one removes the structure, the other half of it
    from piezo_fmu.diagnose.decide import told_apart
    from piezo_fmu.diagnose.stats import compare

    rng = np.random.default_rng(5)
    n = 4000
    t = np.arange(n) / 1000.0
    noise = 0.01 * rng.standard_normal(n)
    fast = 0.02 * np.sin(2 * np.pi * 150.0 * t)      # a leftover with few samples' memory
    slow = 0.02 * np.sin(2 * np.pi * 0.3 * t)        # one with seconds of it

    def sets(e):
        train, held = e[n // 4:], e[:n // 4]
        return {"x": {"train": train, "heldout": held, "blocks": np.array_split(held, 8), "lam": 1.0}}

    def cmp(e):
        return compare(sets(noise + fast + slow), sets(e), 1, {"x": 0.01})

    best = cmp(noise)
    rival = cmp(noise + 0.5 * fast)
    assert told_apart(best, rival, 0) < 1e-6
    assert told_apart(rival, best, 0) == 1.0          # a rival that fits better stays open
    assert told_apart(best, best, 0) == 1.0           # the same fit: no evidence either way
    assert told_apart(best, rival, 0) < told_apart(best, rival, 200)   # parameters the best one has more
    # as much worse, but slowly varying: few effective samples, the data tell the two apart less
    assert told_apart(best, cmp(noise + 0.5 * slow), 0) > 100 * told_apart(best, rival, 0)
    # a rival that is worse by little: most of its closeness stays
    assert 0.5 < told_apart(best, cmp(noise + 0.02 * fast), 0) <= 1.0


def test_a_stiff_output_mode_steps_and_a_nan_screens_as_no_candidate(monkeypatch):
    # rig-039 (19.2 kHz): the mode screening's top grid point, a lightly damped mode at 0.45 fs beside
    # the nominal first mode above the Nyquist frequency. Its companion matrix (coefficients 1 to
    # 3e19 s^-4) lost every digit in scaling and squaring: a pole at |z| = 1.10 for 0.986, the
    # engine returned NaN, and a NaN among the screening's costs scrambled their sort (the true
    # 70 Hz mode was never fitted). Now the chain steps; a NaN, should an engine give one, is no
    # candidate.
    from piezo_fmu.diagnose import fit
    from piezo_fmu.diagnose.fit import Fitter
    from piezo_fmu.diagnose.recordings import make_recordings

    fs = 19200.0
    t = np.arange(int(0.5 * fs)) / fs
    u = np.where(t > 0.1, 40.0, 0.0)
    model = load_model()
    dev, p = device_from_model(model), params_from_model(model, 1 / fs)
    recs = make_recordings([{"name": "r", "time": t, "u": u, "x": 0.1 * u, "us": 0.001 * u}])
    fitter = Fitter(recs, dev, {"x": 1.0, "us": 1.0})
    q = p.copy()
    q.res, q.res_at = (0.45 * fs, 0.005), "output"
    x_out = predict(recs[0], dev, q, direct=True)["x"]
    q.res_at = "drive"
    x_drive = predict(recs[0], dev, q, direct=True)["x"]
    # the same mode after the mechanics or before them: one continuous chain, one step response
    # once the ringing (0.5 / (zeta wn) = 1.8 ms) has died away
    late = t > 0.15
    assert np.all(np.isfinite(x_out))
    np.testing.assert_allclose(x_out[late], x_drive[late], rtol=1e-6)
    assert math.isfinite(fitter.quick(q))
    # a model an engine cannot step is no candidate (not a NaN among the costs)
    monkeypatch.setattr(fit, "predict", lambda *a, **k: {"x": np.full(t.size, np.nan), "us": np.zeros(t.size)})
    assert fitter.quick(q) == math.inf


def test_a_lag_shorter_than_a_sample_is_searched_again_and_nothing_is_named():
    # rig-183: a clean device sampled at 306 Hz (a two-stage amplifier, 0.66 + 0.38 ms). The
    # thresholds' scale fit left the lag at 0.025 of a sample, 1.02x its lower limit, where its cost
    # is flat: the weighted refit stayed there (training cost 4671 against 4629 at 0.65 ms) and the
    # misfit went to a false thermal drift (confidence 0.78). Which side of the limit's 1 % margin
    # the lag landed on decided it; now a lag the samples cannot see restarts from the nominal one.
    from piezo_fmu.diagnose import run
    from piezo_fmu.diagnose.fit import LAG_UNSEEN

    rec, raw = _rig_recording("rig-183")
    assert rec.truth["mechanisms"] == []
    got = run.analyse(raw).result
    assert got["final"]["effects"] == [], got["findings"]
    dt = rec.time[1] - rec.time[0]
    assert got["baseline"]["recalibrated"]["amplifier_tau_s"]["value"] > LAG_UNSEEN * dt


def test_a_finding_a_later_one_diluted_is_judged_with_the_others_in():
    # rig-141 (479 Hz): a one-sample delay and a loop shape. The delay, added first, explained 26 %
    # of a residual the loop shape still filled (confidence 0.39, a candidate); with the shape in,
    # the backward check finds it explains 73 % at a BIC gain of 447 (55 forward)
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-141")
    assert sorted(rec.truth["mechanisms"]) == ["hysteresis_shape", "time_delay"]
    res = analyse(raw).result
    assert sorted(res["final"]["effects"]) == ["hysteresis_shape", "time_delay"], res["candidates"]
    delay = next(f for f in res["findings"] if f["effect"] == "time_delay")
    assert delay["confidence"] >= 0.5


def test_creep_beside_a_delay_is_named_when_a_drift_fits_worse():
    # rig-170: a KP device at 3.4 kHz with creep and a two-sample delay (4 noise rms each). In the
    # first round creep explained 40 % of the structured residual, a drift 29 %; by what each left
    # (60 against 71 %) the drift stayed a close rival and the creep a candidate at 0.30, while the
    # training rows set the two far apart (costs 31982 against 36527)
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-170")
    assert sorted(rec.truth["mechanisms"]) == ["creep", "time_delay"]
    res = analyse(raw).result
    assert sorted(res["final"]["effects"]) == ["creep", "time_delay"], (res["candidates"], res["rejected"])
    assert all(f["confidence"] >= 0.5 for f in res["findings"])


def test_a_current_limit_behind_weights_deep_in_saturation_is_named():
    # rig-145: a Bouc-Wen device with a 5.6 kV/s current limit (10 noise rms in x). The recalibrated
    # lag stood in for the limit with weights that drive the stroke 200 x past the saturation
    # level; the screening's solves started from them at the limit's dynamics, swung between 3e6
    # and 2e9 and passed the limit by ("the fitted current limit never binds")
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-145")
    res = analyse(raw).result
    assert res["final"]["effects"] == ["amplifier_current_limit"], res["rejected"]
    found = res["findings"][0]
    assert found["confidence"] >= 0.5
    truth = rec.truth["params"]           # the slew rate in the model's stack volts
    slew = truth["amplifier_current_limit.slew"]["value"] * load_model()["amplifier"]["k_amp"] \
        / truth["amplifier.gain"]["value"]
    assert found["parameters"]["slew_V_per_s"] == pytest.approx(slew, rel=0.1)
    assert res["final"]["rmse"]["x"] < 0.5 * res["baseline"]["rmse"]["x"]


def test_a_heavily_damped_mode_in_the_contact_force_is_recalibrated():
    # rig-014: a clean Bouc-Wen device whose first mode (1.4 kHz, zeta 0.28) is 11 noise rms in
    # the force channel (a force pick-off between stack and push rod). Its fit ran to the damping
    # bound of 0.35 and was dropped, leaving 4.2 noise rms of structured residual in the force. The
    # contact force carries the mode's damping force, which no lag draws: there the mechanics may
    # be heavily damped
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-014")
    assert rec.truth["mechanisms"] == [] and rec.truth["params"]["sensor.pickoff"]["value"] == "force"
    res = analyse(raw).result
    rc = res["baseline"]["recalibrated"]
    assert rc["first_mode_hz"]["identified"], rc["first_mode_hz"]
    assert rc["sensor_follows"]["value"] == "contact"
    assert rc["first_mode_zeta"]["value"] > 0.35
    assert res["final"]["effects"] == [] and res["candidates"] == []
    assert res["final"]["nothing_missing"], res["final"]["verdict"]


def test_a_further_mode_that_does_not_ring_at_its_frequency_is_not_named(monkeypatch):
    # rig-040: a Krasnosel'skii-Pokrovskii device at 442 Hz with a one-sample command delay. A
    # "further mode" at 164 Hz (zeta 0.12) was named: 1 % of what it changed lay near 164 Hz, the
    # rest reshaped the response elsewhere. A further mode must ring at its own frequency. (Since
    # the swapped start, the better fit there is a heavily damped "mode", rejected as such; since
    # the first mode hands its lag to the amplifier when switched off, the delay itself is found
    # first. The rule is checked on the grid's start alone, with the delay kept out of the search
    # as when its search had missed it)
    from piezo_fmu.diagnose import select
    from piezo_fmu.diagnose.catalogue import MODE_OWN_BAND
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-040")
    assert rec.truth["mechanisms"] == ["time_delay"]
    res = analyse(raw).result
    assert "extra_resonance" not in res["final"]["effects"], res["findings"]
    monkeypatch.setattr(select, "swapped_mode", lambda *args: None)
    propose = select.propose
    monkeypatch.setattr(select, "propose", lambda name, *a: None if name == "time_delay" else propose(name, *a))
    monkeypatch.setattr(run_module, "delay_between", lambda *a, **k: None)    # (and not searched afterwards)
    res = analyse(raw).result
    assert "extra_resonance" not in res["final"]["effects"], res["findings"]
    why = [r["why"] for r in res["rejected"] if r["effect"] == "extra_resonance"]
    assert any("does not ring at its own frequency" in w for w in why), why
    share = float(why[0].split("only ")[1].split(" %")[0]) / 100
    assert share < MODE_OWN_BAND / 5


def test_a_delay_that_is_the_amplifiers_second_stage_is_recalibrated_not_named():
    # rig-010: a clean Krasnosel'skii-Pokrovskii device whose amplifier has two lag stages (0.448 +
    # 0.202 ms), chirps up to 100 Hz at 15.1 kHz. The recalibration kept one stage (0.65 ms) and a
    # 3-sample delay (0.199 ms) was named at confidence 0.90: over such a drive a delay and a short
    # lag differ by a fraction of a percent. Refitted as a second stage in the delay's place, the
    # data prefer the stage (BIC 68): ordinary physics, recalibrated with its uncertainty
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-010")
    truth = rec.truth["params"]
    stages_true = sorted([truth["amplifier.tau_output"]["value"], truth["amplifier.tau_internal"]["value"]])
    assert rec.truth["mechanisms"] == [] and stages_true[0] > 0
    res = analyse(raw).result
    assert res["final"]["effects"] == [] and res["final"]["nothing_missing"], res["findings"]
    assert any(r["effect"] == "time_delay" and "second lag stage" in r["why"] for r in res["rejected"])
    rc = res["baseline"]["recalibrated"]
    assert rc["amplifier_order"] == 2
    stages = sorted([rc["amplifier_tau_s"], rc["amplifier_tau2_s"]], key=lambda v: v["value"])
    for got, true in zip(stages, stages_true):
        assert abs(got["value"] / true - 1) < 0.1, (got, true)       # measured: 2.5 %, 2.8 %
        assert got["relative_uncertainty"] is not None               # found after the recalibration


def test_a_delay_taken_for_both_lag_stages_is_searched_with_both(monkeypatch):
    # rig-151: a 3.4 ms (one-sample) command delay at 293 Hz, which the recalibration took for a
    # two-stage amplifier (1.5 + 2.2 ms). The delay's search kept the second stage and scaled the
    # first alone: every delay then carried 2.2 ms of lag too much. With both stages scaled
    # together the search starts from the true delay with the stages it leaves
    from piezo_fmu.diagnose import catalogue
    from piezo_fmu.diagnose.run import analyse

    calls = []
    search = catalogue.delay_search

    def recorded(fitter, p, struct, dt, both):
        q, cost = search(fitter, p, struct, dt, both)
        calls.append({"both": both, "cost": cost, "samples": q.delay / dt, "lag": q.tau + q.tau2,
                      "lag_before": p.tau + p.tau2, "two_stages": p.tau2 > 0})
        return q, cost

    monkeypatch.setattr(catalogue, "delay_search", recorded)
    rec, raw = _rig_recording("rig-151")
    delay = rec.truth["params"]["time_delay.delay"]["value"]
    assert abs(delay * 293.0 - 1.0) < 1e-9
    analyse(raw)
    pairs = [(a, b) for a, b in zip(calls, calls[1:]) if a["two_stages"] and not a["both"] and b["both"]]
    assert pairs, calls
    for held, scaled in pairs:
        # never worse; the later rounds search from stages the earlier fits had already shortened
        assert scaled["cost"] <= held["cost"], (held, scaled)
        assert scaled["samples"] == pytest.approx(1.0)
        assert scaled["lag"] < held["lag"]          # the second stage gave up what the delay takes
    held, first = pairs[0]
    # from the recalibration's two stages (1.5 + 2.2 ms): clearly better, most of the lag gone
    assert first["cost"] < 0.9 * held["cost"], (held, first)           # measured: 0.86
    assert first["lag"] < first["lag_before"] - 0.5 * delay, first     # measured: 3.96 -> 0.27 ms


def test_a_finding_turned_candidate_leaves_the_final_model_no_worse_than_the_recalibrated():
    # rig-004 (a delay of 5 samples at 3.95 kHz beside a drift) ended with its delay at 0.44, and the
    # final model, re-fitted from the model with the delay switched off, 24 % worse on held-out data
    # than the recalibrated one; it is re-fitted also from the ordinary physics as it was before the
    # weak finding came in. (rig-004's delay is named now: with the drift in, it explains 92 %.)
    # rig-076, creep in one channel at 402 Hz beside a one-sample delay that is as well that
    # channel's sampling lag (a candidate, 0.30), takes the same path
    from piezo_fmu.diagnose import select
    from piezo_fmu.diagnose.run import analyse

    calls = []
    real = select._without_weak

    def spy(*a, **k):
        calls.append(a[-1])
        return real(*a, **k)

    # Its search ends with a loop far from the nominal operators' classical ones (the one-channel
    # creep's misfit in the loop), a false loop shape: at the cap of 0.58 (stop 66) it was named; its
    # held-out evidence against the classical refit (z 11.2, under SHAPE_NOMINAL_HELDOUT_Z) keeps it a
    # candidate at the precision of such loops
    from piezo_fmu.diagnose import loopshape

    rec, raw = _rig_recording("rig-076")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(select, "_without_weak", spy)
        res = analyse(raw).result
    assert calls, "no finding was turned into a candidate"
    assert res["final"]["effects"] == ["creep"] == rec.truth["mechanisms"]
    assert [c["effect"] for c in res["candidates"]] == ["time_delay", "hysteresis_shape"], res["candidates"]
    assert res["candidates"][1]["confidence"] == pytest.approx(loopshape.SHAPE_NOMINAL_WEAK_RIGHT, abs=1e-3)
    before, after = res["baseline"]["rmse"], res["final"]["rmse"]
    for c in before:
        assert after[c] <= before[c], (c, before[c], after[c])      # measured: 0.90 of it


def test_a_drift_that_a_third_creep_element_explains_is_not_named():
    # rig-077: logarithmic creep (and a further mode) over 18 s at 365 Hz, a load pick-off. The
    # search's two creep elements (10 ms, 0.3 s) left the slowest part of the log law to a drift in
    # both channels, named at 0.83. A third element in the drift's place explains the data as well
    # (BIC 0.9 < 10), so the drift is dropped; the mode and the creep stay
    from piezo_fmu.diagnose.rivals import DRIFT_AS_CREEP
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-077")
    assert sorted(rec.truth["mechanisms"]) == ["creep", "extra_resonance"]
    res = analyse(raw).result
    assert sorted(res["final"]["effects"]) == ["creep", "extra_resonance"], res["findings"]
    assert any(r["effect"] == "thermal_drift" and "further creep element" in r["why"] for r in res["rejected"])
    creep = next(f for f in res["findings"] if f["effect"] == "creep")
    assert len(creep["parameters"]["time_constants_s"]) == DRIFT_AS_CREEP


def test_a_trend_the_holds_do_not_show_is_not_a_drift(monkeypatch, rules_before):
    # rig-050: a clean Bouc-Wen device at 1150 Hz, at rest for 0.9 s, then a multisine with a
    # 1.4 Hz part for 1.3 s. The loop's misfit over the slow part looks like a trend in both
    # channels, and a drift (rate and curvature) had stayed a candidate (0.26), so the verdict was
    # not "nothing is missing". A drift goes on while the command holds still; in the rest the data
    # take ~0.1 of its correction. Once the finer loop is taken in (held-out z 4.4 and 4.0) the
    # trend left is smaller: the holds take -0.01 of it at test strength 2.7
    from piezo_fmu.diagnose import catalogue
    from piezo_fmu.diagnose.catalogue import DRIFT_HOLD_TAKEN
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-050")
    assert rec.truth["mechanisms"] == [] and rec.truth["control"] is None
    res = analyse(raw).result
    assert res["final"]["effects"] == [] and res["candidates"] == [], res["candidates"]
    assert res["final"]["nothing_missing"], res["final"]["verdict"]
    why = [r["why"] for r in res["rejected"] if r["effect"] == "thermal_drift"]
    assert why and "holds still" in why[0], why
    assert float(why[0].split("the data take ")[1].split(" of")[0]) < DRIFT_HOLD_TAKEN
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # the holds asked only from strength 3 (the rule before): the smaller trend passes, a candidate
    monkeypatch.setattr(catalogue, "DRIFT_HOLD_STRENGTH", 3.0)
    assert "thermal_drift" in [c["effect"] for c in analyse(raw).result["candidates"]]


def test_the_holds_take_all_of_a_true_drift(monkeypatch):
    # the measure behind the rule above, on a drift the record really has (rig-012: a ramp-form
    # drift, holds over 98 % of the record) and on a command without holds
    from piezo_fmu.diagnose.residuals import hold_runs, taken_in_holds

    u = np.concatenate([np.zeros(300), np.full(50, 2.0), np.sin(np.arange(400) / 20.0), np.full(400, 1.0)])
    dt = 1e-3
    # holds of at least 0.2 s without their first 20 ms: the rest and the last level (not the
    # 50 ms one, not the sine)
    assert hold_runs(u, dt) == [(20, 300), (770, 1150)]
    assert hold_runs(np.sin(np.arange(1000) / 7.0), dt) == []

    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-012")
    assert rec.truth["mechanisms"] == ["thermal_drift"]
    seen = []
    orig = taken_in_holds

    def spy(fitter, p0, p1, ch, **kw):
        out = orig(fitter, p0, p1, ch, **kw)
        seen.append(out)
        return out

    import piezo_fmu.diagnose.catalogue as cat
    monkeypatch.setattr(cat, "taken_in_holds", spy)
    res = analyse(raw).result
    assert res["final"]["effects"] == ["thermal_drift"], res["rejected"]
    assert seen and all(s is not None for s in seen)
    beta, strength = seen[-1]
    assert strength > 10 and beta == pytest.approx(1.0, abs=0.2)


def test_the_holds_judge_a_drift_by_its_own_change(monkeypatch):
    # rig-060: the drift's fit also switched the pick-off, which moved the holds the other way; the
    # drift's own trend was taken at 0.86 there, the whole change at 0.06 - and a true drift was
    # rejected as "a trend of the moving part". Here: data that hold a drift of 0.3 um/s, a change
    # that adds it and a 1.5 s wobble the data do not have
    from types import SimpleNamespace as NS

    import piezo_fmu.diagnose.residuals as resid

    dt, n = 1e-3, 3000
    t = np.arange(n) * dt
    u = np.concatenate([np.sin(np.arange(600) / 30.0), np.full(n - 600, 0.5)])
    rng = np.random.default_rng(3)
    before = np.sin(t * 7.0)
    drift, wobble = 0.3 * t, 0.5 * np.sin(2 * np.pi * t / 1.5)
    rec = NS(u=u, dt=dt, t=t, x=before + drift + 0.01 * rng.standard_normal(n), us=None)
    fitter = NS(recs=[rec], dev=None, noise={"x": 0.01})
    p0, p1 = NS(pred=before, trend=0.0 * t), NS(pred=before + drift + wobble, trend=drift)
    monkeypatch.setattr(resid, "predict", lambda r, dev, p: {"x": p.pred})
    beta_all, _ = resid.taken_in_holds(fitter, p0, p1, "x")
    beta, strength = resid.taken_in_holds(fitter, p0, p1, "x", own=lambda r, p: p.trend)
    assert beta_all < 0.6                   # the whole change: the wobble drags it down
    assert beta == pytest.approx(1.0, abs=0.03) and strength > 100
    # with no other change the two agree
    p2 = NS(pred=before + drift, trend=drift)
    assert resid.taken_in_holds(fitter, p0, p2, "x", own=lambda r, p: p.trend) == pytest.approx(
        resid.taken_in_holds(fitter, p0, p2, "x"), rel=1e-9)


def test_a_whole_sample_delay_of_one_channel_is_also_its_sampling_lag():
    # rig-122: one channel (the displacement) of a KP device at 991 Hz whose command reaches the
    # amplifier one sample late. With one channel a one-sample latency and a one-sample sampling
    # lag of that channel are the same model (with two, the recalibration tells them apart by
    # their difference): the delay is a candidate, its rival the sampling lag, never named
    # (rig-076, creep at 402 Hz, had named such a delay at 0.57)
    from piezo_fmu.diagnose.run import analyse
    from piezo_fmu.diagnose.select import CONFIDENT

    rec, raw = _rig_recording("rig-122")
    assert rec.truth["mechanisms"] == ["time_delay"] and rec.truth["channels"] == ["x"]
    res = analyse(raw).result
    assert "time_delay" not in res["final"]["effects"]
    cand = next(c for c in res["candidates"] if c["effect"] == "time_delay")
    assert cand["confidence"] < CONFIDENT
    assert cand["parameters"]["samples"] == 1
    assert cand["evidence"]["strongest_alternative"]["effect"] == "sampling_lag"
    assert "sampling_lag" in cand["why_not_named"]


def test_a_delay_the_first_mode_stood_in_for_is_found_without_it():
    # rig-040: a one-sample (2.26 ms) command latency at 442 Hz, chirps to 63 Hz. The recalibration
    # drew the missing phase lag as a heavily damped first mode at 115 Hz (zeta 0.33) beside a
    # two-stage lag; the delay screened from the model without that mode started from a lag that
    # had lost the mode's 0.9 ms and scored worse than the recalibrated model, so it was never
    # fitted and the verdict was "nothing is missing". A mode switched off now hands its
    # low-frequency lag (c / k) to the first stage, as a second stage does
    from piezo_fmu.diagnose.model_io import Params
    from piezo_fmu.diagnose.recalibrate import Recalibration, without
    from piezo_fmu.diagnose.run import analyse

    rc = Recalibration(None, nominal_mode=(1e-4, 10.0), k_total=2.0e8)          # N s/m, N/m
    p = Params(tau=1e-3, u_norm=100.0, thresholds=np.zeros(1), weights=np.ones(1), m=0.004, c=190.0)
    q = without(p, "mode", rc)
    assert (q.m, q.c) == (1e-4, 10.0)
    assert q.tau == pytest.approx(1e-3 + (190.0 - 10.0) / 2.0e8)             # + c / k [s]
    assert p.tau == 1e-3 and p.c == 190.0                                    # the original is kept

    rec, raw = _rig_recording("rig-040")
    assert rec.truth["mechanisms"] == ["time_delay"]
    res = analyse(raw).result
    assert res["final"]["effects"] == ["time_delay"], (res["candidates"], res["rejected"])
    f = res["findings"][0]
    assert f["parameters"]["samples"] == 1 and f["confidence"] >= 0.5


def test_a_delay_beside_a_true_first_mode_is_found_without_the_second_lag_stage(monkeypatch, rules_before):
    # rig-147: a one-sample (0.60 ms) command latency at 1680 Hz beside the device's 897 Hz mode.
    # The recalibration kept the mode (841 Hz) and took the latency as a second lag stage of
    # 0.71 ms; the delay screened from the model without both lost the mode's ringing and scored
    # worse than the recalibrated model, so it was never fitted. Screened also without the second
    # stage alone, it is found - once the noise is taken from the model with the finer loop the
    # first round took in (before, the loop's misfit passed for noise and the delay's 18 % lower
    # held-out rmse counted as explaining none of the structured residual)
    from piezo_fmu.diagnose import select
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-147")
    assert rec.truth["mechanisms"] == ["time_delay"]
    d = analyse(raw)
    res = d.result
    assert res["final"]["effects"] == ["time_delay"], (res["candidates"], res["rejected"])
    f = res["findings"][0]
    assert f["parameters"]["samples"] == 1 and f["confidence"] >= 0.5
    assert d.p_final.tau2 == 0.0                                         # the delay in its place
    noise_x = rec.truth["params"]["probe.noise_rms"]["value"] * rec.truth["params"]["probe.gain"]["value"]
    assert d.search["noise"]["x"] == pytest.approx(noise_x, rel=0.15)
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # screened only without every ordinary item at once (the rule before): the search names nothing
    # (the delay searched between the samples afterwards, stop 79, switched off)
    monkeypatch.setattr(select, "ALONE", {})
    monkeypatch.setattr(run_module, "delay_between", lambda *a, **k: None)
    assert analyse(raw).result["final"]["effects"] == []


def test_a_further_mode_and_leakage_leave_no_finer_loop_to_refuse():
    # rig-136: a 160 Hz mode and sensor leakage, the amplifier's two stages (0.9 + 0.4 ms)
    # recalibrated as one lag of 5.0 ms. Until stop 45 the mode's fit left the displacement's
    # misfit to a third round, where a finer loop explained 80 % of it (1.01 noise rms) and 22 % of
    # the sensor's; the rule that a loop shape on the weaker evidence must explain 70 % on every
    # channel (select.SHAPE_EXPLAINED_EACH) kept it from being named, and the residual stayed
    # "unexplained". With the first mode searched again under the further mode's starts (stop 46)
    # the mode and the leakage take it all: the training cost after the leakage is 1421 where it
    # was 4156, and no band is left unexplained. (That rule has no witness since: on 17 cases of
    # rig draws 0, 4, 5 and 6 where it refuses a loop, switching it off names nothing else.)
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-136")
    assert sorted(rec.truth["mechanisms"]) == ["extra_resonance", "sensor_leakage"]
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == ["extra_resonance", "sensor_leakage"], (res["candidates"], res["rejected"])
    assert not any("finer loop" in m and "not named" in m for m in steps), [m for m in steps if "finer loop" in m]
    assert res["unexplained"] == [], res["unexplained"]
    noise = res["baseline"]["noise"]
    assert all(res["final"]["structured_rms"][c] < 1.0 * noise[c] for c in noise), (res["final"]["structured_rms"], noise)


def test_a_loop_beside_a_named_mechanism_must_lie_further_from_the_classical_ones(monkeypatch, rules_before):
    # rig-d1-046 (a device of draw 1, no rule was set from it): sensor leakage and a current limit
    # on a PI device of other thresholds. With the leakage named, a finer loop explained 76 % of
    # what was left, its loop 2.91 noise rms from every classical PI loop, and was named: the
    # leakage's own form is not the device's and its misfit is what the cells bent to. Beside a
    # named mechanism a loop must lie SHAPE_BESIDE_BEYOND (3) from them, as one with other misfit
    from piezo_fmu.diagnose import select
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d1-046")
    assert sorted(rec.truth["mechanisms"]) == ["amplifier_current_limit", "sensor_leakage"]
    steps = []
    res = analyse(raw, say=steps.append).result
    assert "hysteresis_shape" not in res["final"]["effects"], res["findings"]
    assert "sensor_leakage" in res["final"]["effects"]
    assert any("beside sensor_leakage it must lie 3 x the noise" in m and "not named" in m
               for m in steps), steps
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # the distance asked of a loop alone (the rule before): a false loop shape
    monkeypatch.setattr(select, "SHAPE_BESIDE_BEYOND", select.SHAPE_BEYOND)
    assert "hysteresis_shape" in analyse(raw).result["final"]["effects"]


def test_a_loop_named_before_another_mechanism_is_judged_again_beside_it(monkeypatch):
    # rig-d1-145: a current limit on a Bouc-Wen-like device. The first round names a loop shape
    # (47 % explained, 13.5 noise rms from every classical loop): the limit's misfit, which no
    # candidate yet explained, bent the loop. The second round names the limit. The backward check
    # judges the loop again with the limit in, and it goes. Which of the backward check's two tests
    # removes it is chaotic in round-off, so both are accepted here: on an Intel Xeon (stop 61) the
    # loop still passed the ordinary test and lay 0.66 noise rms from the classical loops beside the
    # limit (`loopshape.loop_beside`: an ordinary loop difference, its cells kept as the
    # recalibration's finer loop); on an AMD EPYC (stop 66) the loop fitted beside the limit made
    # the held-out x 76 % worse and the ordinary test dropped it. Every bounded solve by bvls (the
    # reference solver): on the Xeon the active-set solve, within 3e-9 of bvls's cost in every one
    # of its 1632 solves on rig-d10-133, led to the same names by another path
    from piezo_fmu.diagnose import varpro
    monkeypatch.setattr(varpro, "_active_set", lambda *args, **kwargs: None)
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d1-145")
    assert rec.truth["mechanisms"] == ["amplifier_current_limit"]
    steps = []
    d = analyse(raw, say=steps.append)
    res = d.result
    assert any("round 1: hysteresis_shape: passes" in m for m in steps), steps
    assert res["final"]["effects"] == ["amplifier_current_limit"], (res["candidates"], res["rejected"])
    why = next(r["why"] for r in res["rejected"] if r["effect"] == "hysteresis_shape"
               and "once the others are in" in r["why"])
    if "beside amplifier_current_limit" in why:
        # judged an ordinary loop difference: the finer loop kept, unnamed
        assert d.struct_final.refined and d.p_final.n_cells > 0
        assert res["baseline"]["recalibrated"]["loop"]["refined"] is True
    else:
        # refused by the ordinary test: with the limit in, the loop does not hold on held-out data
        assert why.startswith("not needed once the others are in: ") and "worse on held-out data" in why, why


def test_a_finer_loop_whose_refit_is_worse_on_held_out_data_keeps_its_own_fit(monkeypatch, rules_before):
    # rig-064: sensor leakage and a current limit on a KP device. The recalibration takes in a finer
    # loop (17 operators, 21 KP cells; 85 % of the loop misfit) and fits the model once more with it:
    # the training cost goes 89.23 -> 89.16, x on held-out data 0.021 -> 0.095 um (the weights and
    # cells moved where no training block looks). From the refit leakage made x worse away from the
    # jumps and the limit failed its own check: nothing was named. The loop's own fit stays
    # (select.REFIT_WORSE). Since stop 74 the cells' ridge (varpro.CELL_RIDGE) keeps the refit's
    # cells where the training blocks look, and the refit is no worse (x 0.0208 um on held-out
    # data). Since stop 96 the finer loop also leaves out the play operators the held-out rows see
    # move far more often than the training rows (`catalogue._plays_supported`: here the seven at
    # 0.45-0.75 of the voltage scale, moving in 18-51 of 4508 training rows and 25-91 of 1503 held-out
    # ones), and even with the ridge of before the refit is then no worse. The rule is checked with
    # both as before (the ridge at 1e-9, every operator kept)
    import piezo_fmu.diagnose.select as select
    from piezo_fmu.diagnose import catalogue, varpro
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-064")
    truth = sorted(rec.truth["mechanisms"])
    now = analyse(raw).result
    assert now["baseline"]["recalibrated"]["loop"]["refined"]
    assert now["final"]["effects"] == truth, (now["candidates"], now["rejected"])
    assert now["final"]["rmse"]["x"] < 0.25 * now["baseline"]["rmse"]["x"]
    monkeypatch.setattr(varpro, "CELL_RIDGE", 1e-9)
    ridge_before = analyse(raw).result
    assert ridge_before["baseline"]["recalibrated"]["loop"]["refit_undone"] is False
    assert ridge_before["final"]["effects"] == truth
    monkeypatch.setattr(catalogue, "_plays_supported", lambda fitter, q: np.ones(len(q.thresholds), bool))
    res = analyse(raw).result
    loop = res["baseline"]["recalibrated"]["loop"]
    assert loop["refined"] and loop["refit_undone"], loop
    assert "worse on held-out data" in loop["value"]
    assert res["final"]["effects"] == truth, (res["candidates"], res["rejected"])
    assert res["final"]["rmse"]["x"] < 0.25 * res["baseline"]["rmse"]["x"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    monkeypatch.setattr(select, "REFIT_WORSE", math.inf)     # the refit always taken: as before
    before = analyse(raw).result
    assert before["baseline"]["recalibrated"]["loop"]["refit_undone"] is False
    # (with numpy 2.4.6 / scipy 1.17.1 the names come out right from the refit too, 2026-12-02; the
    # final model is what it costs: x on held-out data 0.095 um against 0.021)
    assert before["final"]["effects"] != truth or before["final"]["rmse"]["x"] > 2 * res["final"]["rmse"]["x"]


def test_a_current_limit_a_slow_record_sees_on_two_samples_is_named(monkeypatch, rules_before):
    # rig-d8-069: a current limit on a record sampled at 884 Hz. The fitted limit binds on 2
    # samples (the largest steps) and explains all the misfit on both channels, confirmed on the
    # held-out data (beta 0.99 and 1.00 at z 72 and 43); it was refused as never binding
    import piezo_fmu.diagnose.catalogue as catalogue
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d8-069")
    assert rec.truth["mechanisms"] == ["amplifier_current_limit"]
    res = analyse(raw).result
    assert res["final"]["effects"] == ["amplifier_current_limit"], (res["candidates"], res["rejected"])
    assert "binds on 2 samples only" in res["findings"][0]["evidence"]["note"]
    assert res["final"]["rmse"]["x"] < 0.5 * res["baseline"]["rmse"]["x"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    monkeypatch.setattr(catalogue, "LIMIT_BRIEF_EXPLAINED", math.inf)      # at least 3 samples, as before
    res = analyse(raw).result
    assert "amplifier_current_limit" not in res["final"]["effects"]
    assert any("never binds" in r["why"] for r in res["rejected"] if r["effect"] == "amplifier_current_limit")


def test_a_drift_is_checked_on_the_displacement_alone_without_losing_the_joint_fit(spy):
    # rig-d9-152: a thermal drift alone (held-out x 0.097 -> 0.054 um, beta 0.97 at z 9.7). The
    # check that the drift is the displacement's own re-solved the fit on x alone with 2 Gauss-Newton
    # steps of the saturation; the re-solve landed at x rms 0.200 um where the joint fit has 0.053,
    # the drift "explained -363 %" and was refused. The better of re-solve and values as fitted
    # counts: the drift explains most of x's structured residual and is named
    import piezo_fmu.diagnose.catalogue as catalogue
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d9-152")
    assert rec.truth["mechanisms"] == ["thermal_drift"]
    shares = spy(catalogue, "_own_channel_share")
    res = analyse(raw).result
    assert res["final"]["effects"] == ["thermal_drift"], (res["candidates"], res["rejected"])
    assert shares and min(s for s, _ in shares) > 0.5, shares
    assert res["final"]["rmse"]["x"] < 0.7 * res["baseline"]["rmse"]["x"]


def test_a_drift_beside_creep_is_judged_by_what_it_removes_from_the_displacement(spy, monkeypatch, rules_before):
    # rig-d23-149: log creep and a warm-up drift on a force pick-off, a rest and steps at 3.24 kHz.
    # Fitted to the displacement alone the drift removed 15 % of that channel's structured residual
    # (most of it is the creep's), under the 15 % a trend from the sensor channel would reach, and
    # was refused; yet it removed 1.6 x the probe's noise variance, which no trend that came from the
    # sensor channel reached (at most 0.54 x). Judged by either, both mechanisms are named
    import piezo_fmu.diagnose.catalogue as catalogue
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d23-149")
    assert sorted(rec.truth["mechanisms"]) == ["creep", "thermal_drift"]
    shares = spy(catalogue, "_own_channel_share")
    res = analyse(raw).result
    assert {"creep", "thermal_drift"} <= set(res["final"]["effects"]), (res["candidates"], res["rejected"])
    assert any(s < catalogue.DRIFT_OWN_SHARE and r >= catalogue.DRIFT_OWN_REMOVED for s, r in shares), shares
    assert res["final"]["rmse"]["x"] < 0.5 * res["baseline"]["rmse"]["x"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    monkeypatch.setattr(catalogue, "DRIFT_OWN_REMOVED", math.inf)       # the share alone, as before
    res = analyse(raw).result
    assert "thermal_drift" not in res["final"]["effects"]
    assert any("fitted to the displacement alone" in r["why"] for r in res["rejected"]
               if r["effect"] == "thermal_drift")


def test_leakage_is_found_on_a_record_that_starts_under_a_force():
    # rig-d9-001: sensor leakage (5 s) and a command delay, the operators prepared before the
    # record (a force at the first sample). The rig's sensor has leaked that force's charge before
    # the record; the model's started charged with it and leaked it during the record: every
    # leakage time constant screened worse than none and the leakage was never fitted. Screened
    # with the charge leaked as well, it is named with the delay
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d9-001")
    assert sorted(rec.truth["mechanisms"]) == ["sensor_leakage", "time_delay"]
    res = analyse(raw).result
    assert res["baseline"]["recalibrated"]["initial_state"]["value"] == "prepared"
    assert res["final"]["effects"] == ["sensor_leakage", "time_delay"], (res["candidates"], res["rejected"])
    leak = next(f for f in res["findings"] if f["effect"] == "sensor_leakage")
    assert leak["parameters"]["charge_at_start"] == "leaked before the record"
    assert res["final"]["rmse"]["us"] < 0.5 * res["baseline"]["rmse"]["us"]


def test_leakage_is_weighed_against_an_offset_trend_away_from_the_jumps(spy):
    # rig-d21-165: leakage alone on a KP device at 2590 Hz (21 noise rms in the sensor channel).
    # Over all training rows the leakage left 0.00537 V of structured sensor residual and a
    # quadratic drift of the sensor offset in its place 0.00598 V: "as well" (within half the
    # noise), and leakage was refused although it took the held-out sensor rmse away from the
    # jumps from 0.0151 to 0.00126 V. Both rms were mostly the transients after the command's
    # jumps, alike in both models; compared where a slow mechanism is judged (away from them) the
    # quadratic is clearly worse and leakage is named
    from piezo_fmu.diagnose import catalogue
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d21-165")
    assert rec.truth["mechanisms"] == ["sensor_leakage"]
    seen = spy(catalogue, "offset_drift_rival")
    res = analyse(raw).result
    assert res["final"]["effects"] == ["sensor_leakage"], (res["candidates"], res["rejected"])
    alt, _, fit = seen[-1]       # [V] structured sensor residual: the quadratic's, the leakage's
    assert alt > fit + 0.5 * res["final"]["tests"]["us"]["noise"], seen     # 0.0018 against 0.0 V
    assert res["final"]["rmse"]["us"] < 0.3 * res["baseline"]["rmse"]["us"]


def test_leakage_is_weighed_against_an_offset_trend_with_the_noise_at_most_what_it_leaves(spy):
    # rig-d23-161: leakage (4.8 s) and a loop shape at 2420 Hz, force pick-off. The leakage took the
    # held-out sensor rmse from 0.0288 to 0.0046 V (z 26); the sensor noise level then stood at
    # 0.0105 V (the true noise is 0.0003 V), above what either the leakage or a quadratic offset
    # drift in its place leave, so both structured residuals were 0 V, "as well", and the leakage
    # was refused. The noise is at most what the leakage model leaves: the quadratic then leaves
    # 0.0093 V of structure and the leakage is named (with the loop shape)
    from piezo_fmu.diagnose import catalogue
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d23-161")
    assert sorted(rec.truth["mechanisms"]) == ["hysteresis_shape", "sensor_leakage"]
    seen = spy(catalogue, "offset_drift_rival")
    res = analyse(raw).result
    assert "sensor_leakage" in res["final"]["effects"], (res["candidates"], res["rejected"])
    alt, _, fit = seen[0]       # [V] structured sensor residual: the quadratic's, the leakage's
    assert fit == 0.0 and alt > 0.005, seen
    assert res["final"]["rmse"]["us"] < 0.3 * res["baseline"]["rmse"]["us"]


def test_a_drift_beside_creep_is_checked_after_the_search_budget_is_spent():
    # rig-d1-161: logarithmic creep alone. The search named creep (one element, 0.15 s) and then a
    # drift in both channels, and spent its budget; the check whether a further creep element
    # explains the drift was skipped with the search. It is a check of a finding, not a search:
    # made after the budget, creep with two elements explains the drift as well (BIC -3.7 < 10)
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d1-161")
    assert rec.truth["mechanisms"] == ["creep"]
    res = analyse(raw).result
    assert res["final"]["effects"] == ["creep"], (res["findings"], res["rejected"])
    assert any(r["effect"] == "-" and r["why"].startswith("time budget reached") for r in res["rejected"])
    assert any(r["effect"] == "thermal_drift" and "further creep element" in r["why"]
               for r in res["rejected"])


def _budget_case():
    # synth case 34 (creep and a delay, 2 kHz): the search-budget tests' recording
    case = make_case(34, ["creep", "time_delay"], "mid", ["chirp", "steps"], fs=2000.0)
    return [{"name": "budget", "time": case.t, "u": case.u, "x": case.x, "us": case.us}]


def test_a_later_round_whose_screening_spends_the_budget_fits_nothing():
    # synth case 34 (creep and a delay): round 3 begins at 10.22 reference seconds of work and its
    # screening ends at 11.09 (stop 94; 9.63 and 10.48 before a drift on the load spring could be a
    # warm-up). With a budget of 10.6 the round began inside it; its fits would be spent
    # past it (rig-d14-095, bench's slowest case: a third of its time in such a round 4). After the
    # first budget.FITTED_ROUNDS rounds such a round reports what it screened and fits nothing
    # (before: creep fitted, failing, and "the weaker screened candidates were not fitted")
    from piezo_fmu.diagnose import budget
    from piezo_fmu.diagnose.run import analyse

    assert budget.FITTED_ROUNDS == 2
    raw = _budget_case()
    lines = []
    res = analyse(raw, time_budget_s=10.6, say=lines.append).result
    notes = [r["why"] for r in res["rejected"] if r["effect"] == "-"]
    assert notes == ["time budget reached during round 3's screening: no candidate fitted "
                     "(the best screened: creep)"], res["rejected"]
    assert any("round 3: screening gains" in line for line in lines)
    assert not any("round 3: fitting" in line for line in lines), [m for m in lines if "fitting" in m]
    # rounds 1 and 2 fitted as without a budget
    assert res["final"]["effects"] == ["creep", "time_delay"]


def test_the_first_rounds_fit_though_their_screening_spends_the_budget():
    # the same case with a budget of 7.6: round 2 begins at 7.19 and screens to 8.06 (stop 94), and fits its
    # best candidate all the same (a pair's second mechanism in a long record whose round 1 took most
    # of the budget: rig-136's leakage, rig-d20-031's delay); the search ends after it
    from piezo_fmu.diagnose.run import analyse

    raw = _budget_case()
    lines = []
    res = analyse(raw, time_budget_s=7.6, say=lines.append).result
    assert any("round 2: fitting thermal_drift" in line for line in lines)
    assert not any("during round 2's screening" in r["why"] for r in res["rejected"])
    assert any(r["effect"] == "-" and r["why"].startswith("time budget reached") for r in res["rejected"])


def test_a_further_mode_must_beat_the_first_mode_there_by_the_naming_threshold(monkeypatch, rules_before):
    # rig-d2-126: a clean device (PI on other thresholds, 526 Hz sampling). A further mode at
    # 215.8 Hz beat the device's first mode at that frequency by BIC 6.9 and was named: positive
    # evidence (2) sufficed. The first mode there is ordinary physics, the account every name must
    # beat by the naming threshold (10): recalibrated, and nothing is missing
    from piezo_fmu.diagnose import rivals
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d2-126")
    assert rec.truth["mechanisms"] == [] and rec.truth["control"] is None
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == [] and res["final"]["verdict"].startswith("nothing is missing")
    assert any("is the device's first mode" in m and "would gain BIC 6.9" in m for m in steps), steps
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # positive evidence alone (the rule before): a false further mode
    monkeypatch.setattr(rivals, "MODE_EVIDENCE", 2.0)
    assert analyse(raw).result["final"]["effects"] == ["extra_resonance"]


def test_a_cell_switched_only_in_a_held_out_block_is_left_out(monkeypatch, rules_before):
    # rig-072: a 2-sample command latency on a device with PI hysteresis on other thresholds. The
    # record reaches its top voltage once, in a training block; the held-out block after it falls
    # through the thresholds where the KP cells switched on at that peak switch off again. Fitted
    # to the few training rows that tell them apart, those cells drew a step of 0.94 um in that
    # block: the finer loop failed on held-out data, the ordinary loop difference stayed in the
    # residual and the delay explained 31 % of it (confidence 0.34, a candidate). Since stop 74 the
    # cells' ridge (varpro.CELL_RIDGE) holds those cells as well: either rule alone names the delay
    from piezo_fmu.diagnose import support, varpro
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-072")
    assert rec.truth["mechanisms"] == ["time_delay"]
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == ["time_delay"], (res["candidates"], res["rejected"])
    assert any("an ordinary loop difference, taken into the recalibration" in m for m in steps), steps
    # every cell kept, the ridge holding them: the delay named
    monkeypatch.setattr(support, "CELL_SUPPORT", math.inf)
    assert analyse(raw).result["final"]["effects"] == ["time_delay"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # and with the ridge of before (1e-9) too (the rules before): the delay is a candidate only (the
    # delay searched between the samples afterwards, stop 79, switched off: it names it too)
    monkeypatch.setattr(varpro, "CELL_RIDGE", 1e-9)
    monkeypatch.setattr(run_module, "delay_between", lambda *a, **k: None)
    res = analyse(raw).result
    assert res["final"]["effects"] == [] and [c["effect"] for c in res["candidates"]] == ["time_delay"]


def test_a_loop_the_held_out_data_confirm_at_z_3_is_taken_in(monkeypatch, rules_before):
    # rig-060: a 374 Hz mode in series and a thermal drift of 0.14 um on a device with PI
    # hysteresis on other thresholds. After the mode, a finer loop removes 62 % of what is left;
    # the BIC refuses it (gain -68.5) but the held-out data take 0.98 and 0.97 of its correction at
    # z 3.1 and 3.2. Left in the residual, that loop difference hid the drift (fitted to the
    # displacement alone it explained 14 %); taken in, the drift explains 49 % and is named
    from piezo_fmu.diagnose import select
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-060")
    assert sorted(rec.truth["mechanisms"]) == ["extra_resonance", "thermal_drift"]
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == ["extra_resonance", "thermal_drift"], (res["candidates"], res["rejected"])
    assert any("but the held-out data take it on every channel" in m for m in steps), steps
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # at z >= 5 (the rule before) the loop stays in the residual and the drift is missed
    monkeypatch.setattr(select, "LOOP_HELDOUT_Z", 5.0)
    assert analyse(raw).result["final"]["effects"] == ["extra_resonance"]


def test_a_lone_fast_creep_element_is_not_called_creep():
    # rig-140: a clean Bouc-Wen device driven by multisines up to 195 Hz. A single creep element of
    # 3.2 ms (gain 0.15) was named at confidence 0.80: the loop's different gain for the small fast
    # and the large slow parts of the command, not the slow motion after input changes
    from piezo_fmu.diagnose.catalogue import CREEP_SLOWEST_S
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-140")
    assert rec.truth["mechanisms"] == [] and rec.truth["control"] is None
    res = analyse(raw).result
    assert res["final"]["effects"] == [] and res["candidates"] == [], res["findings"]
    assert res["final"]["nothing_missing"], res["final"]["verdict"]
    why = [r["why"] for r in res["rejected"] if r["effect"] == "creep"]
    assert why and "slowest element" in why[0], why
    assert float(why[0].split("(")[1].split(" ms")[0]) * 1e-3 < CREEP_SLOWEST_S



def test_creep_whose_fast_element_settles_at_the_floor_is_fitted_again_without_it(monkeypatch, rules_before):
    # rig-d8-025: log-law creep (4.2 % of a step per decade from t0 = 19 ms) on a 253 Hz device
    # sampled at 1.16 kHz. Two creep elements from none settled at 2.6 ms (the floor of the range,
    # gain 0.15: the fast dynamics) and 0.50 s, and the bound refused the whole of creep, which
    # explained 83 % of the residual. Without the element at the floor one element stays at 0.2 s
    from piezo_fmu.diagnose import select
    from piezo_fmu.diagnose.catalogue import CREEP_SLOWEST_S
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d8-025")
    assert rec.truth["mechanisms"] == ["creep"]
    steps = []
    res = analyse(raw, say=steps.append).result
    assert res["final"]["effects"] == ["creep"], res["rejected"]
    creep = next(f for f in res["findings"] if f["effect"] == "creep")
    assert creep["confidence"] >= 0.5
    assert len(creep["parameters"]["time_constants_s"]) == 1
    assert CREEP_SLOWEST_S < creep["parameters"]["time_constants_s"][0] < 2.0
    assert any("settled at the floor of its range" in m for m in steps), steps
    # (the recalibration takes in a finer loop since stop 96, which left out 7 play operators: the
    # baseline is better, x 0.112 -> 0.093 um, us 0.037 -> 0.028 V on held-out data, and so is the
    # final model, x 0.056 -> 0.041, us 0.028 -> 0.023; creep acts on the stroke: x's final/baseline
    # ratio 0.51 -> 0.44, the sensor's 0.75 -> 0.82)
    assert res["final"]["rmse"]["x"] < 0.5 * res["baseline"]["rmse"]["x"]
    assert res["final"]["rmse"]["us"] < res["baseline"]["rmse"]["us"]
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # refused as a whole (the rule before), creep is missed
    monkeypatch.setattr(select, "creep_at_floor", lambda *a: None)
    assert analyse(raw).result["final"]["effects"] == []


def test_the_samples_after_a_jump_of_the_command_are_marked_and_a_smooth_drive_has_none():
    from piezo_fmu.diagnose.recordings import JUMP, RESPONSE_S, after_jumps

    dt = 1e-3
    t = np.arange(0.0, 2.0, dt)
    u = np.where((t >= 0.5) & (t < 1.5), 40.0, 0.0)
    mask = after_jumps(u, dt)
    k = int(round(RESPONSE_S / dt))
    up, down = int(round(0.5 / dt)), int(round(1.5 / dt))
    assert mask.sum() == 2 * k
    assert mask[up:up + k].all() and mask[down:down + k].all()
    assert not mask[:up].any() and not mask[up + k:down].any() and not mask[down + k:].any()
    # a sine moves less than JUMP of its span per sample: no jump
    sine = 20.0 * (1.0 + np.sin(2 * np.pi * 5.0 * t))
    assert np.max(np.abs(np.diff(sine))) < JUMP * np.ptp(sine)
    assert not after_jumps(sine, dt).any()


def test_creep_is_judged_on_held_out_data_away_from_the_steps(monkeypatch, rules_before):
    # rig-d8-038: log-law creep (3.8 % of a step per decade from t0 = 0.1 s) after a 6.5 s rest and
    # three steps (47, 22, 0 V), 4.23 kHz. Only the step from rest to 47 V rises in a held-out
    # block; creep's fit solved the PI weights again (three levels do not fix nine weights), and
    # its step from rest rose with a plateau: over all held-out samples the data took 0.27 of its
    # correction and x was 59 % worse. Away from the 50 ms after each jump they take 1.00 of it
    from piezo_fmu.diagnose import residuals
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d8-038")
    assert rec.truth["mechanisms"] == ["creep"]
    res = analyse(raw).result
    assert res["final"]["effects"] == ["creep"], res["rejected"]
    creep = next(f for f in res["findings"] if f["effect"] == "creep")
    assert creep["confidence"] >= 0.5
    # away from the jumps creep takes x and us to a third; over every held-out sample the step from
    # rest, whose transient the weights draw, stays in the rmse
    for c in ("x", "us"):
        assert res["final"]["rmse_away_from_jumps"][c] < 0.5 * res["baseline"]["rmse_away_from_jumps"][c]
    assert res["baseline"]["rmse_away_from_jumps"]["x"] < res["baseline"]["rmse"]["x"]
    assert "away from the command's jumps" in res["validation"]["selection"]
    from piezo_fmu.cli.diagnose import summary
    assert "away from the command's jumps" in summary(res)
    if not rules_before:             # the case still needs the rule: `pytest --rules-before`
        return
    # judged on every held-out sample (the rule before), creep is refused
    monkeypatch.setattr(residuals, "SLOW_HELDOUT_MIN", 2.0)
    assert analyse(raw).result["final"]["effects"] == []

def test_a_slow_creep_element_is_not_called_a_drift():
    # synth-1053 (the recognition study's case): creep with two elements, 0.31 s and 3.6 s (the
    # slower as long as the record, so under a unipolar drive it grows almost like a trend), and
    # a current limit. A drift reaching both channels (as it would through a sensor on the push
    # rod) explained the slow element first and was named beside creep; the drift must now stand
    # against one more creep element, and lose
    from piezo_fmu.diagnose.evaluate import cases
    from piezo_fmu.diagnose.run import analyse

    spec = next(c for c in cases() if c["seed"] == 1053)
    case = make_case(spec["seed"], spec["effects"], spec["noise"], spec["kinds"])
    truth = case.truth["parameters"]["creep"]
    assert len(truth["time_constants"]) == 2
    raw = [{"name": "synth-1053", "time": case.t, "u": case.u, "x": case.x, "us": case.us}]
    res = analyse(raw).result
    assert res["final"]["effects"] == ["amplifier_current_limit", "creep"], res["rejected"]
    creep = next(f for f in res["findings"] if f["effect"] == "creep")["parameters"]
    assert sorted(creep["time_constants_s"]) == pytest.approx(sorted(truth["time_constants"]), rel=0.1)
    assert any(r["effect"] == "thermal_drift" for r in res["rejected"])


def test_figure_lines_keep_every_extreme_of_the_record():
    # the report draws at most 3000 points a line; a one-sample spike and the noise band survive
    from piezo_fmu.diagnose.report import _decimate

    t = np.arange(200_001) * 1e-4
    rng = np.random.default_rng(1)
    y = np.sin(t) + 0.01 * rng.standard_normal(t.size)
    y[123_457] = 3.0
    tt, yy = _decimate(t, y)
    assert tt.size <= 3000 and np.all(np.diff(tt) >= 0)
    assert yy.max() == 3.0 and yy.min() == pytest.approx(y.min(), abs=0.02)
    assert tt[np.argmax(yy)] == pytest.approx(t[123_457], abs=20 * 1e-4 * t.size / 3000)
    short = np.arange(100.0)
    assert _decimate(short, short)[1] is short


def test_a_loop_shape_of_another_kind_is_named_and_the_fmus_run_it(tmp_path):
    # rig-041: a PI device on other thresholds whose loop width grows with the level (no play
    # operators draw that). Named as hysteresis_shape with KP cells; model.toml carries them, and
    # the Actuator FMU rebuilt from it co-simulates the recording as the diagnosis says
    from piezo_fmu import builder
    from piezo_fmu.rig.recording import write_csv

    cosim = pytest.importorskip("piezo_fmu.cosim")
    rec, _ = _rig_recording("rig-041")
    assert rec.truth["mechanisms"] == ["hysteresis_shape"]
    path = write_csv(rec, tmp_path / "rec.csv")
    diag = diagnose([path], out=tmp_path / "out", force=True, figures=False)
    assert diag.result["final"]["effects"] == ["hysteresis_shape"]
    model = load_model(tmp_path / "out" / "model.toml")
    cells = model["hysteresis"]["cells_weights"]
    assert len(cells) >= 10 and max(abs(c) for c in cells) > 0
    fmus = tmp_path / "fmus"
    builder.build_all(tmp_path / "out" / "model.toml", fmus, ssp=False, log=lambda msg: None)
    fit = read_fit_csv(tmp_path / "out" / "fit.csv")
    t = fit["time"] - fit["time"][0]
    res = cosim.cosimulate(fmus, Signal("table", t=t, values=rec.u, column="u"), float(t[-1]),
                           step=float(t[1] - t[0]), mode="open")
    noise = diag.result["baseline"]["noise"]
    x_co = np.asarray(res["x"][:t.size])
    assert np.sqrt(np.mean((x_co - fit["x_final"]) ** 2)) < 0.2 * noise["x"]
    # and what the shape carries is visible: the held-out fit is a fifth better than the
    # recalibrated nominal model's (recomputed from fit.csv)
    ho = fit["heldout"] == 1
    assert np.sqrt(np.mean((fit["x"] - fit["x_final"])[ho] ** 2)) < 0.8 * diag.result["baseline"]["rmse"]["x"]
    shutil.rmtree(fmus, ignore_errors=True)


def test_recognition_scores_count_names_hidden_mechanisms_and_kinds():
    # five hand-made case results whose counts are known: the study's figures are these sums
    from piezo_fmu.diagnose.scoring import markdown, summarise

    results = [
        {"group": "single", "truth": ["hysteresis_shape"], "named": ["hysteresis_shape"], "seconds": 2.0,
         "confidence": {"hysteresis_shape": 0.95}, "variants": {"hysteresis_shape": "knee"}},
        # "nothing is missing", but the missed shape is reported as a candidate: not silent
        {"group": "single", "truth": ["hysteresis_shape"], "named": [], "seconds": 4.0, "nothing_missing": True,
         "candidates": {"hysteresis_shape": 0.3}, "variants": {"hysteresis_shape": "level_width"}},
        {"group": "pair", "truth": ["creep", "time_delay"], "hidden": ["thermal_drift"], "seconds": 6.0,
         "named": ["creep", "thermal_drift"], "confidence": {"creep": 0.8, "thermal_drift": 0.6}},
        {"group": "clean", "truth": [], "named": ["time_delay"], "seconds": 8.0, "nothing_missing": False,
         "confidence": {"time_delay": 0.55}},
        # a miss the case's verdict hides: "nothing is missing" with creep in the recording
        {"group": "single", "truth": ["creep"], "named": [], "seconds": 1.0, "nothing_missing": True},
    ]
    s = summarise(results, ["creep", "time_delay", "thermal_drift", "hysteresis_shape"])
    assert s["recognition_rate"] == pytest.approx(2 / 5)            # shape once, creep once; not the delay
    assert s["false_name_case_rate"] == pytest.approx(1 / 5)        # the hidden drift is no false name
    assert s["silent_miss_case_rate"] == pytest.approx(1 / 5)
    assert s["clean_nothing_missing_rate"] == 0.0
    assert s["by_effect"]["hysteresis_shape"] == {"true": 2, "recognised": 1, "named_wrongly": 0, "candidate": 1,
                                                  "silent": 0, "twin": 0}
    assert s["by_effect"]["creep"] == {"true": 2, "recognised": 1, "named_wrongly": 0, "candidate": 0, "silent": 1,
                                       "twin": 0}
    assert s["by_effect"]["time_delay"]["named_wrongly"] == 1
    assert s["by_effect"]["time_delay"]["silent"] == 0                 # missed beside a flagged residual
    assert s["by_variant"] == {"hysteresis_shape: knee": {"true": 1, "recognised": 1},
                               "hysteresis_shape: level_width": {"true": 1, "recognised": 0}}
    assert (s["named_right"], s["named_total"]) == (3, 4)
    band = {tuple(b["band"]): b for b in s["calibration"]}
    assert band[(0.5, 0.75)]["reported"] == 2 and band[(0.5, 0.75)]["right"] == 1
    assert (s["median_seconds"], s["max_seconds"]) == (4.0, 8.0)
    table = markdown(s)
    assert "| hysteresis_shape: knee | 100 % (1/1) |" in table and "recognised 40 %" in table
    # missed: a candidate 1 (shape), the delay's residual flagged 1, creep silently 1
    assert "| time_delay | 0 % (0/1) | 1 | 0 | 1 | 0 |" in table and "| creep | 50 % (1/2) | 0 | 0 | 0 | 1 |" in table
    assert "silent miss" in table and "20.0 %" in table


def test_the_search_budget_grows_in_proportion_beyond_twenty_seconds_at_ten_kilohertz():
    # 40 reference seconds up to 200 k samples (the speed goal's record), in proportion beyond: a
    # 338 k-sample record stopped after round 1 with its delay and drift unsearched (rig draw 31)
    from piezo_fmu.diagnose.budget import BUDGET_SAMPLES, WORK_PER_S, work_budget

    assert work_budget(40.0, 1_000) == work_budget(40.0, BUDGET_SAMPLES) == 40.0 * WORK_PER_S
    assert work_budget(40.0, 2 * BUDGET_SAMPLES) == 2 * work_budget(40.0, BUDGET_SAMPLES)
    assert work_budget(40.0, 300_000) == 1.5 * 40.0 * WORK_PER_S


def test_after_the_budget_a_round_s_runner_up_is_fitted_once_beside_what_it_named():
    # the best-screened physical candidate of round 1 when it named something, before round 2; not a
    # loop shape, not one with a negative screening gain, not one in the model
    from types import SimpleNamespace

    from piezo_fmu.diagnose.budget import runner_up
    from piezo_fmu.diagnose.fit import Structure

    # (the round's screening, best first; the work against the budget: round 1 ended 1.05 x past it)
    screened = [(5.0, "amplifier_current_limit"), (0.4, "hysteresis_shape"), (0.3, "thermal_drift"),
                (0.2, "sensor_leakage"), (-1.0, "creep")]
    named = Structure().with_effect("amplifier_current_limit")
    r1 = (0, screened, "amplifier_current_limit")
    fit = SimpleNamespace(work=1.05e6, budget=1e6)
    assert runner_up(fit, r1, 1, named) == "thermal_drift"
    assert runner_up(fit, r1, 1, named.with_effect("thermal_drift")) == "sensor_leakage"
    assert runner_up(fit, r1, 2, named) is None                                      # not right after it
    assert runner_up(fit, (1, screened, "amplifier_current_limit"), 2, named) is None  # only the second name
    assert runner_up(fit, None, 1, named) is None                                    # nothing named
    assert runner_up(fit, (0, screened[:2] + screened[4:], "amplifier_current_limit"), 1, named) is None
    # round 1 itself ran far past the budget: its fits are dear, no runner-up
    assert runner_up(SimpleNamespace(work=1.2e6, budget=1e6), r1, 1, named) is None


def test_a_budget_spent_by_round_one_still_fits_its_runner_up_beside_the_finding():
    # synth case 34 (creep and a delay, 2 kHz): round 1 names the delay and ends at 5.51 reference
    # seconds of work. With a budget of 5.2 (1.06 x) the drift screened next in round 1 is fitted
    # once beside the delay, passes, and creep then takes its place: both named, as with no budget.
    # With 4.0 round 1 ran 1.38 x past the budget (RUNNER_UP_WITHIN 1.1): the delay alone
    from piezo_fmu.diagnose.run import analyse

    lines = []
    res = analyse(_budget_case(), time_budget_s=5.2, say=lines.append).result
    assert res["final"]["effects"] == ["creep", "time_delay"], res["rejected"]
    assert any("only thermal_drift (round 1's runner-up)" in m for m in lines)
    assert [r["effect"] for r in res["rejected"]] == ["thermal_drift", "-"]
    lines = []
    res = analyse(_budget_case(), time_budget_s=4.0, say=lines.append).result
    assert res["final"]["effects"] == ["time_delay"]
    assert not any("runner-up" in m for m in lines)


def test_the_search_budget_is_work_so_a_busy_machine_searches_the_same(monkeypatch):
    # a budget small enough to end the search early: on an idle machine, and on one whose CPU clock
    # runs 1000 s per reading (a machine busy with other jobs, or very slow), the same candidates
    # are searched and the same result comes out (a CPU-time budget ends the second at once)
    import time

    from piezo_fmu.diagnose.run import analyse

    raw = _budget_case()
    idle = analyse(raw, time_budget_s=4.0).result
    clock = iter(range(0, 10 ** 9, 1000))
    monkeypatch.setattr(time, "process_time", lambda: float(next(clock)))
    busy = analyse(raw, time_budget_s=4.0).result
    # the budget ended the search after one round (no budget: creep and the delay, six rejected)
    assert [r["why"] for r in idle["rejected"]] == ["time budget reached after 1 round(s): no further candidates searched"]
    assert idle["final"]["effects"] == ["time_delay"]
    assert busy["final"]["effects"] == idle["final"]["effects"]
    assert [r["why"] for r in busy["rejected"]] == [r["why"] for r in idle["rejected"]]
    assert busy["final"]["rmse"] == idle["final"]["rmse"]


def test_a_miss_put_in_afterwards_says_whether_the_tests_see_it(monkeypatch):
    # rig-097: a one-sample command delay (3.4 ms at 294 Hz) that stays a candidate (0.48): a damped
    # mode (zeta 0.30, only phase lag) fits the training rows better (cost 344 against 823). The
    # evaluation's --ceiling puts each miss into the final model after the diagnosis: the delay
    # passes the tests (the miss is the selection's, through its rival); a leakage the recording
    # does not have is refused. (rig-072, the case here before, is named since its finer loop
    # leaves out the cells the training rows barely see switched.)
    from piezo_fmu.diagnose.evaluate import _ceiling
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-097")
    assert rec.truth["mechanisms"] == ["time_delay"]
    # (the delay searched between the samples afterwards names it since stop 79: switched off, the
    # search's miss stays one)
    monkeypatch.setattr(run_module, "delay_between", lambda *a, **k: None)
    diag = analyse(raw)
    res = diag.result
    assert res["final"]["effects"] == [] and [c["effect"] for c in res["candidates"]] == ["time_delay"]
    out = _ceiling(diag, ["time_delay", "sensor_leakage"])
    assert out["time_delay"]["passes"] and out["time_delay"]["explained"] > 0.2, out
    assert not out["sensor_leakage"]["passes"] and out["sensor_leakage"]["why"], out
    # the diagnosis still pickles (the search context stays behind)
    back = pickle.loads(pickle.dumps(diag))
    assert back.search == {} and back.result["final"]["effects"] == []


def test_the_evaluation_records_what_each_confidence_was_made_of():
    # each finding's and candidate's evidence goes into the evaluation's results (stop 97), so the
    # confidence's factors can be studied over a whole set without running it again
    from piezo_fmu.diagnose.evaluate import _EVIDENCE, _outcome

    def entry(name, conf, beta):
        ev = {"explained_share": {"x": 0.4}, "explained_share_heldout": {"x": 0.45}, "heldout_beta": beta,
              "heldout_z": 6.8, "delta_bic": 55.1, "strongest_alternative": None, "note": "not recorded"}
        return {"effect": name, "confidence": conf, "parameters": {}, "evidence": ev}

    res = {"final": {"effects": ["creep"], "nothing_missing": False, "verdict": "", "rmse": {"x": 0.01}},
           "findings": [entry("creep", 0.91, 0.97)], "candidates": [entry("thermal_drift", 0.44, 0.81)],
           "baseline": {"rmse": {"x": 0.02}, "noise": {"x": 0.003}, "recalibrated": {}}}
    out = _outcome(res)
    assert set(out["evidence"]) == {"creep", "thermal_drift"}
    assert set(out["evidence"]["thermal_drift"]) == set(_EVIDENCE)
    assert out["evidence"]["thermal_drift"]["heldout_beta"] == 0.81                 # [1]
    assert out["evidence"]["creep"]["delta_bic"] == 55.1                            # [1]


def test_the_ceiling_table_counts_what_the_tests_see_and_why_not():
    from piezo_fmu.diagnose.scoring import markdown, summarise

    results = [
        {"group": "single", "truth": ["time_delay"], "named": [], "seconds": 1.0,
         "ceiling": {"time_delay": {"passes": True, "why": ""}}},
        {"group": "single", "truth": ["time_delay"], "named": [], "seconds": 1.0,
         "ceiling": {"time_delay": {"passes": False, "why": "the fitted delay 0.25 ms is at a bound (x); BIC gain 3 < 10"}}},
        {"group": "pair", "truth": ["time_delay", "creep"], "named": ["creep"], "seconds": 1.0,
         "ceiling": {"time_delay": {"passes": False, "why": "the fitted delay 0.5 ms is at a bound"}}},
        {"group": "single", "truth": ["creep"], "named": ["creep"], "seconds": 1.0},
    ]
    s = summarise(results, ["creep", "time_delay"])
    assert s["ceiling"] == {"time_delay": {"missed": 3, "passes": 1,
                                           "why": {"the fitted delay is at a bound": 2}}}
    table = markdown(s)
    assert "| time_delay | 3 | 33 % (1/3) | the fitted delay is at a bound (2) |" in table
    assert "| creep | 0 |" not in table


def test_mechanisms_with_an_ordinary_twin_are_counted_apart_beside_the_rate_over_all():
    from piezo_fmu.diagnose.scoring import markdown, summarise

    same = {"twin": "no delay, the one channel sampled 1 sample(s) late", "distance": 0.0, "same": True}
    far = {"twin": "no delay, the amplifier's output stage slower", "distance": 5.5, "same": False}
    results = [
        {"group": "one channel", "truth": ["time_delay"], "named": [], "seconds": 1.0,
         "twins": {"time_delay": same}},
        {"group": "single", "truth": ["time_delay"], "named": ["time_delay"], "seconds": 1.0,
         "twins": {"time_delay": far}},
        {"group": "pair", "truth": ["time_delay", "creep"], "named": ["creep"], "seconds": 1.0,
         "twins": {"time_delay": far}},
        {"group": "single", "truth": ["creep"], "named": ["creep"], "seconds": 1.0, "twins": {}},
    ]
    s = summarise(results, ["creep", "time_delay"])
    assert s["recognition_rate"] == pytest.approx(3 / 5)
    assert s["twins"] == {"true": 1, "recognised": 0, "others_true": 4, "others_recognised": 3}
    assert s["recognition_rate_beyond_twins"] == pytest.approx(3 / 4)
    assert s["by_effect"]["time_delay"]["twin"] == 1
    assert "1 of the 5 true mechanisms (time_delay 1), 0 of them named; recognised among the others " \
           "75 % (3/4)" in markdown(s)
    # a study without twins measured (synth) reports none
    assert "twins" not in summarise([{k: v for k, v in r.items() if k != "twins"} for r in results],
                                    ["creep", "time_delay"])


def test_a_residual_that_looks_like_noise_does_not_end_the_search():
    # rig-180 (465 Hz): a command delay and a current limit. After the delay, the noise estimate
    # (the upper half of the residual's spectrum) took the limit's slew ramps for noise, and a rule
    # that stopped at a residual within 0.1 noise rms of pure noise ended the search: the limit was
    # never tried, though put in afterwards it explains all of that residual (BIC gain 19436)
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-180")
    assert sorted(rec.truth["mechanisms"]) == ["amplifier_current_limit", "time_delay"]
    res = analyse(raw).result
    assert res["final"]["effects"] == ["amplifier_current_limit", "time_delay"], res["rejected"]
    assert all(f["confidence"] >= 0.9 for f in res["findings"])


def test_a_warm_up_drift_is_named_with_its_time_constant():
    # rig-d9-130 (279 Hz): a thermal warm-up of -0.22 um settling with 1.95 s over a 15.4 s record
    # (and a current limit). A quadratic drift cannot follow a warm-up that settles within the
    # record: fitted, it bends back at the end, where the command's last hold sees the data go on
    # the other way (0.02 of its correction taken there) and the drift was refused as "a trend of
    # the moving part". The drift's curvature term in its warm-up form follows it: named, with the
    # warm-up's size and time constant
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d9-130")
    tr = rec.truth["params"]
    assert tr["thermal_drift.form"]["value"] == "warmup"
    res = analyse(raw).result
    assert "thermal_drift" in res["final"]["effects"], (res["candidates"], res["rejected"])
    drift = next(f for f in res["findings"] if f["effect"] == "thermal_drift")["parameters"]
    size = tr["thermal_drift.amplitude"]["value"] * tr["probe.gain"]["value"]      # in the recorded x [um]
    tau = tr["thermal_drift.tau"]["value"]
    # the rig's warm-up is normalised to reach its amplitude at the record's end
    settled = size / (1.0 - math.exp(-rec.truth["duration"] / tau))
    assert drift["warm_up_um"] == pytest.approx(settled, rel=0.2), drift
    assert drift["time_constant_s"] == pytest.approx(tau, rel=0.35), drift
    # mostly the warm-up: the ramp beside it moves less over the record (a ramp form, the other way)
    assert abs(drift["ramp_um_per_s"]) * rec.truth["duration"] < 0.5 * abs(drift["warm_up_um"]), drift


def test_a_drift_is_fitted_with_each_pick_off_of_the_sensor():
    # rig-d9-109 (780 Hz): a thermal drift of 0.30 um, the sensor on the stack's force. The
    # recalibration, which has no drift, took a first mode of 534 Hz with the sensor on the load
    # spring, where a drift of the displacement moves the force too: the drift fitted that way pulled
    # the sensor along (us 46 % worse on held-out data) and was refused. Fitted with every pick-off,
    # the stack's explains all of the displacement's structured residual and is named
    from piezo_fmu.diagnose.run import analyse

    rec, raw = _rig_recording("rig-d9-109")
    assert rec.truth["mechanisms"] == ["thermal_drift"] and rec.truth["params"]["sensor.pickoff"]["value"] == "force"
    res = analyse(raw).result
    assert res["final"]["effects"] == ["thermal_drift"], (res["candidates"], res["rejected"])
    assert res["final"]["rmse"]["x"] < 0.5 * res["baseline"]["rmse"]["x"]
    assert res["final"]["rmse"]["us"] < 1.1 * res["baseline"]["rmse"]["us"]
