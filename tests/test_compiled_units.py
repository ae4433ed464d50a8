"""The units' compiled engine (``compiled.compile_unit``): the same kernels
run by numba on the unit's data packed into one buffer must give the interpreted results bit for
bit, through every branch the FMUs reach (delay line resized, creep of order 0-3, extra resonance,
drift, current limit, saturation, second-order amplifier, load and contact pick-offs, sub-steps, every compensator mode and inverse), and the state
must move between the engines unchanged."""
import copy
import math

import numpy as np
import pytest

from piezo_fmu.core import compiled
from piezo_fmu.core.buffers import pack
from piezo_fmu.core.control import INVERSES, MODES, pid_step
from piezo_fmu.model import load_model
from piezo_fmu.system import make_actuator, make_compensator, make_sensor

pytestmark = pytest.mark.skipif(not compiled.available(), reason="numba is not installed")

MODEL = load_model()


def _actuator(**changes):
    m = MODEL.copy()
    for key, value in changes.items():
        sec, _, k = key.rpartition(".")
        m.sections.setdefault(sec, {})[k] = value
    return make_actuator(m)


ACTUATORS = {
    "paper": {},
    "everything": {"amplifier.delay": 3e-4, "amplifier.I_max": 2e-3, "creep.gains": [0.02, 0.01, 0.005],
                   "creep.time_constants": [0.01, 0.1, 1.0], "resonance.f_n": 3000.0,
                   "resonance.zeta": 0.1, "drift.offset": 0.01, "drift.rate": 0.2,
                   "drift.curvature": -0.05, "simulation.actuator_max_step": 2.5e-5,
                   "amplifier.tau_2": 2e-4, "mechanics.pickoff": "load"},
    "one creep element": {"creep.gains": [0.03], "creep.time_constants": [0.05]},
    "warm-up drift": {"drift.offset": 0.02, "drift.rate": 0.1, "drift.curvature": 0.4, "drift.time_constant": 0.02,
                      "mechanics.pickoff": "load"},
    "contact pick-off": {"mechanics.pickoff": "contact", "amplifier.tau_2": 1e-4, "resonance.f_n": 900.0},
    "stroke along the lag": {"simulation.stroke_path": "amplifier_lag", "mechanics.pickoff": "contact",
                             "amplifier.tau_2": 1e-4, "creep.gains": [0.05], "creep.time_constants": [0.2]},
    "mode on the drive": {"resonance.f_n": 700.0, "resonance.position": "drive", "creep.gains": [0.05],
                          "creep.time_constants": [0.2]},
    # KP cells over -0.2..4.6 (u_norm units: -6..138 V), both signs of weight, a prepared start
    "KP cells": {"hysteresis.cells_up": [1.0, 2.2, 4.6, 0.4], "hysteresis.cells_down": [-0.2, 1.0, 1.0, 0.1],
                 "hysteresis.cells_width": [0.6, 0.4, 1.2, 0.3], "hysteresis.cells_weights": [0.2, -0.05, 0.1, 0.07],
                 "hysteresis.prepared": 60.0, "hysteresis.saturation": 20.0},
}


def _command(k):
    """A command with turns at every scale: slow sine, fast ripple, jumps, rail excursions [V]."""
    return 4.5 + 4.4 * math.sin(k / 40) + 0.3 * math.sin(k * 1.7) + (6.0 if k % 97 == 0 else 0.0)


def _drive(act, steps, k0=0, step=1e-4):
    return [(act.advance(_command(k), step), float(act.F), float(act.ua)) for k in range(k0, k0 + steps)]


@pytest.mark.parametrize("name", sorted(ACTUATORS))
def test_compiled_actuator_equals_interpreted_bit_for_bit(name):
    py = _actuator(**ACTUATORS[name])
    nb = compiled.compile_unit(_actuator(**ACTUATORS[name]))
    assert isinstance(nb.pi_z, np.ndarray) and isinstance(py.pi_z, list)
    a = _drive(py, 600)
    b = _drive(nb, 600)
    assert a == b
    assert py.get_state() == nb.get_state()
    assert all(type(v) is float for v in nb.get_state()["z"])        # plain data, JSON-ready
    # a different communication step: re-discretised, the delay line resized (for "everything")
    assert _drive(py, 300, 600, step=1.1e-4) == _drive(nb, 300, 600, step=1.1e-4)
    assert py.get_state() == nb.get_state()


def test_actuator_state_moves_between_engines():
    py = _actuator(**ACTUATORS["everything"])
    _drive(py, 400)
    saved = copy.deepcopy(py.get_state())
    ref = _drive(py, 300, 400)
    nb = compiled.compile_unit(_actuator(**ACTUATORS["everything"]))
    nb.set_state(copy.deepcopy(saved))               # interpreted -> compiled
    assert _drive(nb, 300, 400) == ref
    back = _actuator(**ACTUATORS["everything"])
    nb.set_state(copy.deepcopy(saved))
    _drive(nb, 150, 400)
    back.set_state(copy.deepcopy(nb.get_state()))    # compiled -> interpreted, mid-run
    assert _drive(back, 150, 550) == ref[150:]
    # a state from elsewhere must change the result (the comparison above can fail)
    nb.set_state(copy.deepcopy(saved))
    nb.set_state(copy.deepcopy(_actuator(**ACTUATORS["everything"]).get_state()))
    assert _drive(nb, 300, 400) != ref


@pytest.mark.parametrize("drift", [(0.0, 0.0), (0.2, 0.01)])
def test_a_compiled_actuator_resets_to_the_same_state(drift):
    """reset() on a unit whose lists became arrays of one buffer (no drift: an empty array); a
    prepared load pick-off exercises every branch of the settled start."""
    kw = dict(ACTUATORS["everything"], **{"drift.offset": drift[0], "drift.rate": drift[1], "drift.curvature": 0.0,
                                          "mechanics.pickoff": "load", "hysteresis.prepared": 60.0})
    ref = _actuator(**kw)
    act = compiled.compile_unit(_actuator(**kw))
    act.advance(1.0, 1e-4)
    act.reset()
    ref.reset()
    assert list(act.out) == list(ref.out) and ref.out[3] > 0.0


@pytest.mark.parametrize("engine", ["python", "numba"])
def test_a_warm_up_drift_settles_into_a_ramp(engine):
    """The drift's warm-up form, written as a ramp and an exponential settling of amplitude
    -2 T^2 c (c the curvature, T the time constant): the same start as a quadratic drift, then a
    straight line; the load pick-off's force follows the drift's change."""
    off, rate, curv, T = 0.02, 0.1, 0.4, 0.02
    kw = {"drift.offset": off, "drift.rate": rate, "drift.curvature": curv, "drift.time_constant": T,
          "mechanics.pickoff": "load"}
    act = _actuator(**kw) if engine == "python" else compiled.compile_unit(_actuator(**kw))
    still = _actuator(**{"mechanics.pickoff": "load"})
    t, x, f, x0, f0 = 0.0, [], [], [], []
    for _ in range(1000):
        act.advance(0.0, 1e-4)
        still.advance(0.0, 1e-4)
        t += 1e-4
        x.append(float(act.x) - float(still.x))
        f.append(float(act.F) - float(still.F))
    t = np.arange(1, 1001) * 1e-4
    want = off + (rate + 2 * T * curv) * t - 2 * T * T * curv * (1.0 - np.exp(-t / T))
    assert np.allclose(x, want, rtol=0, atol=1e-12)
    assert np.allclose(want[:5] - off - rate * t[:5], curv * t[:5] ** 2, rtol=0.01)     # starts as t^2
    k_f = MODEL.sections["mechanics"]["k_f"] * 1e-6
    assert np.allclose(f, k_f * (want - off), rtol=1e-9, atol=1e-15)


def test_compiled_actuator_works_on_its_own_buffer():
    """The unit's lists become views of one buffer; replacing the delay line re-packs it."""
    act = compiled.compile_unit(_actuator(**ACTUATORS["everything"]))
    buf, offsets = act.packed
    assert np.shares_memory(act.pi_z, buf) and np.shares_memory(act.mech.xs, buf)
    assert np.shares_memory(act.out, buf) and offsets[-1] == buf.size
    act.advance(1.0, 1e-4)
    old = act.packed[0]
    n = act.dly_buf.size
    act.advance(1.0, 1.1e-4)                     # another internal step: the delay line is resized
    assert act.dly_buf.size != n
    assert act.packed[0] is not old and np.shares_memory(act.dly_buf, act.packed[0])


@pytest.mark.parametrize("mode", sorted(MODES))
@pytest.mark.parametrize("inverse", sorted(INVERSES))
def test_compiled_compensator_equals_interpreted_bit_for_bit(mode, inverse):
    def make():
        return make_compensator(MODEL, mode=mode, inverse=inverse, signal="sine", amplitude=45.0,
                                offset=45.0, freq=20.0)

    py, nb = make(), compiled.compile_unit(make())
    rng = np.random.default_rng(3)
    us = (0.4 + 0.35 * np.sin(np.arange(800) / 30) + 0.01 * rng.standard_normal(800)).tolist()
    h = 1e-4
    a = [py.initialize(0.0, 0.0, us[0])] + [py.step(k * h, 0.0, us[k], h) for k in range(1, 800)]
    b = [nb.initialize(0.0, 0.0, us[0])] + [nb.step(k * h, 0.0, us[k], h) for k in range(1, 800)]
    assert a == b
    assert all(type(v) is float for v in b)
    assert py.get_state() == nb.get_state()
    saved = copy.deepcopy(py.get_state())
    ref = [py.step(k * h, 0.0, us[k - 400], h) for k in range(800, 900)]
    nb2 = compiled.compile_unit(make())
    nb2.set_state(copy.deepcopy(saved))
    assert [nb2.step(k * h, 0.0, us[k - 400], h) for k in range(800, 900)] == ref


def test_pack_lays_regions_back_to_back():
    buf, offsets, views = pack([[1.0, 2.0], [], [3.0], np.array([4.0, 5.0, 6.0])])
    assert buf.tolist() == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    assert offsets.tolist() == [0, 2, 2, 3, 6] and offsets.dtype == np.int64
    views[2][0] = 9.0
    assert buf[2] == 9.0 and [v.size for v in views] == [2, 0, 1, 3]


def test_regions_follow_the_kernels_signatures():
    """The runners slice the kernels' arguments in the order of the region tables."""
    import inspect

    from piezo_fmu.core.control import compensator_step
    from piezo_fmu.core.plant import actuator_step

    assert list(inspect.signature(actuator_step).parameters)[3:] == list(compiled.ACTUATOR_REGIONS)
    assert list(inspect.signature(compensator_step).parameters)[4:] == list(compiled.COMPENSATOR_REGIONS)


def test_without_numba_the_error_says_what_to_install(monkeypatch):
    monkeypatch.setattr(compiled, "available", lambda: False)
    with pytest.raises(RuntimeError, match="pip install numba"):
        compiled.compile_unit(_actuator())


def test_a_changed_source_of_any_compiled_module_gives_another_cache_folder(tmp_path):
    # numba's own cache checks only the compiled function's file; a kernel with a callee inlined
    # from another file (the runners, the diagnose engine's amp_run) must not load stale code
    from pathlib import Path
    import shutil

    pkg = Path(compiled.__file__).resolve().parent.parent
    copy_ = tmp_path / "piezo_fmu"
    shutil.copytree(pkg / "core", copy_ / "core")
    (copy_ / "diagnose").mkdir()
    for name in ("engine.py", "kernels.py"):
        shutil.copy(pkg / "diagnose" / name, copy_ / "diagnose" / name)
    shutil.copy(pkg / "simulate.py", copy_ / "simulate.py")
    first = compiled.sources_digest(copy_)
    assert first == compiled.sources_digest(pkg)
    seen = {first}
    for rel in ("core/plant.py", "core/hysteresis.py", "diagnose/engine.py", "diagnose/kernels.py", "simulate.py"):
        f = copy_ / rel
        f.write_text(f.read_text() + "\n# changed\n")
        seen.add(compiled.sources_digest(copy_))
    assert len(seen) == 6


def test_a_second_process_loads_the_compiled_kernels_from_the_cache(fresh_processes):
    import os
    import subprocess
    import sys

    tmp_path = fresh_processes.cache
    probe = ("import json, numpy as np\n"
             "from piezo_fmu.core import compiled\n"
             "from piezo_fmu.model import load_model\n"
             "from piezo_fmu.system import make_actuator\n"
             "act = compiled.compile_unit(make_actuator(load_model()))\n"
             "x = [act.advance(1.0 + 0.5 * k, 1e-4) for k in range(50)]\n"
             "run = compiled.kernels()['actuator_run']\n"
             "print(json.dumps({'dir': str(compiled.cache_dir()), 'hits': len(run.stats.cache_hits),\n"
             "                  'x': [float(v) for v in x]}))\n")
    runs = fresh_processes(probe)
    assert runs[0]["dir"].startswith(str(tmp_path)) and runs[0]["dir"] == runs[1]["dir"]
    assert runs[0]["hits"] == 0 and runs[1]["hits"] >= 1
    assert runs[0]["x"] == runs[1]["x"]
    off = subprocess.run([sys.executable, "-c", "from piezo_fmu.core import compiled; print(compiled.cache_dir())"],
                         env={**os.environ, "PIEZO_FMU_CACHE": "off"}, capture_output=True, text=True, check=True)
    assert off.stdout.strip() == "None"


def test_cache_folders_of_other_sources_unused_for_a_month_are_removed_when_a_new_one_is_made(tmp_path,
                                                                                           monkeypatch):
    # every edited or upgraded install compiles into a folder of its own (the digest): those of
    # installs long gone must not pile up; a recent one (another version in use) and what is not a
    # cache folder stay
    import os
    import time

    month_ago = time.time() - 40 * 86400.0
    folders = {}
    for name in ("numba-old", "numba-recent", "notes"):
        d = tmp_path / name
        (d / "kernels").mkdir(parents=True)
        (d / "kernels" / "k.nbi").write_text("index")
        folders[name] = d
    for name in ("numba-old", "notes"):
        d = folders[name]
        for f in (d / "kernels" / "k.nbi", d / "kernels", d):
            os.utime(f, (month_ago, month_ago))
    keep = tmp_path / "numba-current"
    keep.mkdir()
    os.utime(keep, (month_ago, month_ago))
    assert compiled.prune_caches(tmp_path, keep) == [folders["numba-old"]]
    assert not folders["numba-old"].exists()
    assert folders["numba-recent"].exists() and folders["notes"].exists() and keep.exists()
    # cache_dir prunes when it makes its folder, and only then
    old = tmp_path / "numba-older"
    (old / "k").mkdir(parents=True)
    for f in (old / "k", old):
        os.utime(f, (month_ago, month_ago))
    monkeypatch.setenv("PIEZO_FMU_CACHE", str(tmp_path))
    compiled.cache_dir.cache_clear()
    try:
        made = compiled.cache_dir()
        assert made.parent == tmp_path and made.name.startswith("numba-") and not old.exists()
        (old / "k").mkdir(parents=True)
        for f in (old / "k", old):
            os.utime(f, (month_ago, month_ago))
        compiled.cache_dir.cache_clear()
        assert compiled.cache_dir() == made and old.exists()      # the folder was there already
    finally:
        compiled.cache_dir.cache_clear()


def _subnormals(values):
    a = np.abs(np.asarray(values, dtype=float))
    return int(np.count_nonzero((a > 0.0) & (a < np.finfo(float).tiny)))


def test_no_state_of_the_units_decays_into_subnormal_numbers():
    # a pulse, then the command back at exactly 0 V: the amplifier, creep, mechanics, the sensor's
    # leakage and the PID's derivative decay geometrically towards zero and, left alone, end in
    # subnormal doubles held there by their rounding (stop 62: the monolithic model 4.3x slower on
    # an Intel Xeon). Every state below core.linear.TINY is zero instead.
    act = compiled.compile_unit(_actuator(**ACTUATORS["everything"]))
    sen = make_sensor(MODEL.copy(), noise=False)
    sen.tau_leak = 0.05
    sen.reset(0.0)
    for k in range(60000):
        uc = 50.0 if k < 200 else 0.0
        act.advance(uc, 1e-4)
        sen.step(float(act.F), 1e-4)
    buf, _ = act.packed
    assert _subnormals(buf) == 0
    assert _subnormals(sen.sen_s) == 0
    assert float(np.max(np.abs(buf))) > 0.0     # the hysteresis keeps its memory: not all zero
    gains, st = [0.5, 10.0, 1e-3, 1e-4], [0.0, 0.0, 0.0, 0.0]      # Kp, Ki, Kd, Tf [s]
    for k in range(60000):
        pid_step(1.0 if k < 200 else 0.0, 1e-4, gains, st, 0.0)     # the error pulses, then 0 um
    assert _subnormals(st) == 0 and st[0] != 0.0
