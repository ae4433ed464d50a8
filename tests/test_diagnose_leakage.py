"""Sensor leakage against a slow drift of the sensor offset (not in the catalogue): the drift the
leakage is weighed against may wander (a quadratic in time, or a line in each of a few parts of the
record), and neither draws the level-dependent decays after the command's jumps."""
from __future__ import annotations

import math

import numpy as np

from piezo_fmu.diagnose import offsets
from piezo_fmu.diagnose.engine import device_from_model, params_from_model, predict
from piezo_fmu.diagnose.fit import Fitter
from piezo_fmu.diagnose.recordings import make_recordings
from piezo_fmu.model import load_model

FS = 2000.0          # [Hz]
T = 16.0             # [s]
NOISE = 1e-4         # [V] the sensor voltage's noise rms


def _case(us_extra, tau_leak):
    """A staircase command (a level every 0.8 s), recorded through the paper's model whose sensor
    leaks with ``tau_leak`` [s] (inf: none), ``us_extra(t)`` [V] added to the sensor voltage. Returns
    the fitter and the model without leakage."""
    t = np.arange(int(T * FS)) / FS
    rng = np.random.default_rng(7)
    u = np.repeat(rng.uniform(0.0, 8.0, int(T / 0.8)), int(0.8 * FS))[:t.size]   # [V]
    model = load_model()
    dev, p = device_from_model(model), params_from_model(model, 1 / FS)
    rec = make_recordings([{"name": "r", "time": t, "u": u, "x": np.zeros_like(t), "us": np.zeros_like(t)}])[0]
    q = p.copy()
    q.tau_leak = tau_leak
    y = predict(rec, dev, q, direct=True)
    us = y["us"] + us_extra(t) + NOISE * rng.standard_normal(t.size)
    recs = make_recordings([{"name": "r", "time": t, "u": u, "x": y["x"], "us": us}])
    fitter = Fitter(recs, dev, {"x": 1.0, "us": 1.0})
    fitter.noise = {"x": 1e-3, "us": NOISE}
    return fitter, p, q


def test_an_offset_wandering_in_straight_parts_explains_the_sensor_as_well_as_leakage():
    # the offset wanders through five knots (a random walk, as the rig's control draws it), no
    # leakage: the model without leakage plus the drift leaves the noise, a leakage model (its time
    # constant 3 x the record) far more
    knots = np.array([0.0, 1.0, -0.5, 0.8, 0.2]) * 20 * NOISE
    wander = lambda t: np.interp(t, np.linspace(0.0, T, knots.size), knots)   # noqa: E731
    fitter, p, _ = _case(wander, math.inf)
    q = p.copy()
    q.tau_leak = 3 * T
    quad, parts, own = offsets.offset_drift_rival(fitter, q)
    assert own > 3 * NOISE
    assert parts < 0.5 * NOISE < own               # in straight parts: as well as leakage, and better
    assert quad > NOISE                            # a quadratic (the alternative before stop 85) is not


def test_the_decays_of_true_leakage_are_not_drawn_by_a_wandering_offset():
    # leakage with a 0.5 s time constant: after every level of the staircase the sensor decays;
    # the leakage model leaves the noise, the offset drift in any of its forms far more
    fitter, _, q = _case(lambda t: 0.0 * t, 0.5)
    quad, parts, own = offsets.offset_drift_rival(fitter, q)
    assert own < 0.5 * NOISE
    assert min(quad, parts) > own + 5 * NOISE
