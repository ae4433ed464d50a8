"""The fitter's weights-held evaluations (``diagnose.fit.Fitter.quick`` / ``held``): a stroke
computed once serves every model that differs only after the loop, with the same numbers, and is
counted as the chain-only work it is."""
import numpy as np

from piezo_fmu.diagnose import fit
from piezo_fmu.diagnose.engine import device_from_model, params_from_model
from piezo_fmu.diagnose.fit import Fitter
from piezo_fmu.diagnose.recordings import make_recordings
from piezo_fmu.model import load_model

FS = 5000.0                                    # [Hz]


def _fitter():
    """Steps and a 7 Hz sine, 2 s at 5 kHz, recorded through the paper's model plus a slow decay."""
    t = np.arange(int(2 * FS)) / FS
    u = np.where(t < 1.0, np.where(t > 0.2, 5.0, 0.0), 3.0 + 2.0 * np.sin(2 * np.pi * 7.0 * t))   # [V]
    model = load_model()
    dev, p = device_from_model(model), params_from_model(model, 1 / FS)
    x = 1.1 * u + 0.05 * np.exp(-t / 0.3)                                                     # [um]
    recs = make_recordings([{"name": "r", "time": t, "u": u, "x": x, "us": 0.002 * u}])
    return Fitter(recs, dev, {"x": 1.0, "us": 1.0}), p


def _variants(p):
    """Models that share ``p``'s stroke (a mode, creep, a sampling lag) and ones that do not."""
    same, other = [], []
    for res in ((900.0, 0.02), (1500.0, 0.005)):
        q = p.copy()
        q.res, q.res_at = res, "output"
        same.append(q)
    q = p.copy()
    q.creep = [(0.05, 0.3)]
    same.append(q)
    q = p.copy()
    q.lag_x = 1
    same.append(q)
    q = p.copy()
    q.tau = 2.0 * p.tau                          # the stack voltage changes
    other.append(q)
    q = p.copy()
    q.weights = np.asarray(p.weights, float) * 1.2   # the loop changes
    other.append(q)
    q = p.copy()
    q.delay = 3.0 / FS
    other.append(q)
    return same, other


def test_a_cached_stroke_gives_the_numbers_of_a_fresh_evaluation():
    fitter, p = _fitter()
    same, other = _variants(p)
    fitter.quick(p)
    for q in same + other:
        fresh, _ = _fitter()                     # nothing cached: every stroke computed anew
        assert fitter.quick(q) == fresh.quick(q)
        assert fitter.quick(q, drift=True) == fresh.quick(q, drift=True)


def test_only_a_model_with_the_cached_stroke_is_counted_as_chain_only_work():
    fitter, p = _fitter()
    same, other = _variants(p)
    unit = fitter.n_samples + fit.EVAL_OVERHEAD
    w0 = fitter.work
    fitter.quick(p)
    assert fitter.work - w0 == unit              # a new stroke: a whole evaluation
    for q in same:
        w0 = fitter.work
        fitter.quick(q)
        assert fitter.work - w0 == fit.CHAIN_ONLY_WEIGHT * unit, q
    for q in other:
        w0 = fitter.work
        fitter.quick(q)
        assert fitter.work - w0 == unit, q
