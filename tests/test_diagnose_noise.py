"""The noise level a candidate is judged against.

The noise of each channel is estimated from the upper half of the residual's spectrum
(:func:`piezo_fmu.diagnose.stats.noise_level`). At a low sample rate under steps a misfit fills that
half too, the level comes out too high and every structured residual passes for noise: no
candidate "explains" anything. A candidate that takes a channel's held-out mean square to at most
``stats.NOISE_BOUND`` (0.5) of before bounds that channel's noise by what it leaves; a smaller gain
does not (it would explain "all" of a residual the level hides).
"""
import numpy as np
import pytest

from piezo_fmu.diagnose import stats
from piezo_fmu.diagnose.stats import compare

RULE = stats.NOISE_BOUND        # (the tests below switch it off)


def _sets(e):
    n = e.size
    train, held = e[n // 4:], e[:n // 4]
    return {"x": {"train": train, "heldout": held, "blocks": np.array_split(held, 8), "lam": 1.0}}


def _explained(after_share, noise_est, bound, monkeypatch):
    monkeypatch.setattr(stats, "NOISE_BOUND", bound)
    rng = np.random.default_rng(3)
    n = 8000
    t = np.arange(n) / 400.0
    noise = 0.01 * rng.standard_normal(n)                 # [um] the true noise
    misfit = 0.03 * np.sign(np.sin(2 * np.pi * 3.0 * t))  # [um] a structured residual, 3 x the noise
    cmp = compare(_sets(noise + misfit), _sets(noise + after_share * misfit), 2, {"x": noise_est})
    ch = cmp["channels"]["x"]
    return ch["explained"], ch["explained_heldout"]


@pytest.mark.parametrize("bound", [RULE, 0.0], ids=["rule", "rule-before"])
def test_a_decisive_gain_below_a_noise_level_estimated_too_high_explains_the_residual(monkeypatch, bound):
    # the residual before: rms 0.0316 um; the noise taken as 0.04 um (a misfit in the upper half of
    # the spectrum). The candidate removes the misfit: held-out mean square 1e-4 of 1e-3 before
    explained, held = _explained(0.0, 0.04, bound, monkeypatch)
    if bound:
        assert explained > 0.95 and held > 0.95, (explained, held)
    else:
        assert explained == 0.0 and held == 0.0          # everything below the level: "explains 0 %"
    # with the noise level right the rule changes nothing that matters: all of it explained either way
    right, right_held = _explained(0.0, 0.01, bound, monkeypatch)
    assert right > 0.95 and right_held > 0.95, (right, right_held)


def test_a_small_gain_does_not_lower_the_noise_level(monkeypatch):
    # a candidate that removes 10 % of the misfit (held-out mean square 0.82 of before) under the
    # level estimated too high explains nothing, with the rule as without it
    assert _explained(0.9, 0.04, RULE, monkeypatch) == (0.0, 0.0)
    # (bounding by any gain, it would "explain" much of what it barely touches)
    explained, _ = _explained(0.9, 0.04, 1.0, monkeypatch)
    assert explained > 0.5, explained


@pytest.mark.parametrize("bound", [RULE, 0.0], ids=["rule", "rule-before"])
def test_a_delay_at_a_low_sample_rate_is_named_through_a_noise_level_too_high(monkeypatch, bound,
                                                                               rig_diagnosis):
    # rig-d23-045 (independent rig, 373 Hz, steps and a chirp): a one-sample delay. The recalibrated
    # model's misfit filled the upper half of the spectrum; the delay took the held-out rmse from
    # 0.0647 to 0.0284 um and from 2.11 to 0.29 mV and "explained 0 %": nothing was named. Since
    # stop 96 the finer loop leaves out the play operators the training rows barely see move
    # (`catalogue._plays_supported`), and the delay is named without the bound too (x 0.028 um held
    # out): the case before is that rule off as well
    from piezo_fmu.diagnose import catalogue

    monkeypatch.setattr(stats, "NOISE_BOUND", bound)
    if not bound:
        monkeypatch.setattr(catalogue, "_plays_supported", lambda fitter, q: np.ones(len(q.thresholds), bool))
    res = rig_diagnosis("rig-d23-045")
    if bound:
        assert res["final"]["effects"] == ["time_delay"], res["final"]["verdict"]
    else:
        assert res["final"]["effects"] == [], res["final"]["verdict"]


@pytest.mark.parametrize("bound", [RULE, 1.0], ids=["rule", "any-gain"])
def test_creep_at_a_low_sample_rate_is_named_without_a_drift_beside_it(monkeypatch, bound, rig_diagnosis):
    # rig-d22-174 (263 Hz, the displacement alone, steps): creep under a noise level 5.9 x the probe's.
    # Named; bounded by any gain, a thermal drift that took the held-out rmse from 0.0505 to
    # 0.0476 um "explained 58 %" after it and was named too
    monkeypatch.setattr(stats, "NOISE_BOUND", bound)
    res = rig_diagnosis("rig-d22-174")
    if bound < 1.0:
        assert res["final"]["effects"] == ["creep"], res["final"]["verdict"]
    else:
        assert set(res["final"]["effects"]) == {"creep", "thermal_drift"}, res["final"]["verdict"]
