"""Play operators, the PI model and its analytic inverse (paper eqs. 8-17)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezo_fmu.core.hysteresis import (
    Hysteresis,
    PrandtlIshlinskii,
    pi_load,
    pi_memory,
    pi_save,
    pi_state,
    pi_step,
    pi_table,
    play_scan,
)

PAPER_R = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8]
PAPER_W = [0.58751, 0.46211, 0.06758, 0.00092, 0.30240, 0.99999, 0.20197, 0.73566, 0.15913]


def test_play_operator_by_hand():
    # r = 1: output stays 0 until the input leaves [-1, 1], then follows at distance 1
    z = play_scan([0.5, 2.0, 3.0, 2.5, 1.0, -1.0, 0.0], [1.0])[:, 0]
    np.testing.assert_allclose(z, [0.0, 1.0, 2.0, 2.0, 2.0, 0.0, 0.0])


def test_zero_threshold_operator_is_identity():
    v = np.sin(np.linspace(0, 10, 300)) * 3
    np.testing.assert_array_equal(play_scan(v, [0.0])[:, 0], v)


@st.composite
def pi_models(draw, max_n=10):
    n = draw(st.integers(1, max_n))
    gaps = draw(st.lists(st.floats(0.01, 1.0), min_size=n - 1, max_size=n - 1))
    r = np.concatenate([[0.0], np.cumsum(gaps)])
    w0 = draw(st.floats(0.05, 5.0))
    rest = draw(st.lists(st.floats(0.0, 5.0), min_size=n - 1, max_size=n - 1))
    in_scale = draw(st.floats(0.1, 100.0))
    out_scale = draw(st.floats(0.1, 10.0))
    return PrandtlIshlinskii(tuple(r), (w0, *rest), in_scale, out_scale)


@st.composite
def signals(draw, scale=1.0):
    """Random piecewise-linear inputs with reversals (arbitrary start, not only from 0)."""
    knots = draw(st.lists(st.floats(-5.0, 5.0), min_size=1, max_size=12))
    per = draw(st.integers(1, 30))
    v = np.concatenate([np.linspace(a, b, per, endpoint=False) for a, b in zip(knots, knots[1:])]
                       + [np.array(knots[-1:])])
    return v * scale


@settings(max_examples=300, deadline=None)
@given(pi_models(), signals())
def test_inverse_of_forward_is_identity(model, v):
    u = v * model.in_scale
    y = model.apply(u)
    back = model.inverse().apply(y)
    assert np.max(np.abs(back - u)) <= 1e-9 * max(1.0, np.max(np.abs(u)))


@settings(max_examples=300, deadline=None)
@given(pi_models(), signals())
def test_forward_of_inverse_is_identity(model, v):
    y = v * model.out_scale * 2.0
    u = model.inverse().apply(y)
    again = model.apply(u)
    assert np.max(np.abs(again - y)) <= 1e-9 * max(1.0, np.max(np.abs(y)))


@settings(max_examples=100, deadline=None)
@given(pi_models(max_n=6), signals())
def test_stepping_unit_matches_scan(model, v):
    unit = Hysteresis(model)
    stepped = np.array([unit.step(x) for x in v * model.in_scale])
    np.testing.assert_allclose(stepped, model.apply(v * model.in_scale), rtol=0, atol=1e-12)


def test_inverse_needs_the_papers_threshold_construction():
    """A plausible-looking but wrong inverse (thresholds not on the loading curve) is not an inverse:
    the identity tests above would catch it."""
    model = PrandtlIshlinskii(PAPER_R, PAPER_W, 30.0, 1.44)
    good = model.inverse()
    wrong = PrandtlIshlinskii(tuple(np.array(PAPER_R) * 1.44), good.weights, good.in_scale,
                              good.out_scale)
    u = 15 - 15 * np.cos(np.linspace(0, 6 * np.pi, 3000))
    assert np.max(np.abs(good.apply(model.apply(u)) - u)) < 1e-9
    assert np.max(np.abs(wrong.apply(model.apply(u)) - u)) > 0.1


def test_inverse_matches_the_papers_printed_values_where_legible():
    inv = PrandtlIshlinskii(PAPER_R, PAPER_W).inverse()
    # printed: q^-1 = 1.70209, first inverse weight 0.74937 (its minus sign was lost in extraction),
    # thresholds 0, 0.0588, 0.1637 (the later printed thresholds do not follow from eq. 17)
    assert inv.weights[0] == pytest.approx(1.70209, abs=1e-5)
    assert inv.weights[1] == pytest.approx(-0.74937, abs=1e-5)
    np.testing.assert_allclose(inv.thresholds[:3], [0.0, 0.0588, 0.1637], atol=1e-4)
    assert all(w < 0 for w in inv.weights[1:] if w != 0)


def test_loading_curve_is_the_virgin_response():
    model = PrandtlIshlinskii(PAPER_R, PAPER_W, 30.0, 1.0)
    u = np.linspace(0, 45, 200)
    np.testing.assert_allclose(model.apply(u), model.loading_curve(u / 30.0), atol=1e-12)


def test_paper_loop_is_widest_around_15_volts_with_0p180_pi_units():
    """The reading notes' claim, checked: steady 0-30 V loop width 0.1803 PI units on 12-18 V."""
    model = PrandtlIshlinskii(PAPER_R, PAPER_W, 30.0, 1.0)
    ph = np.linspace(0, 3, 30001)
    u = 15 - 15 * np.cos(2 * np.pi * ph)
    y = model.apply(u)
    last = ph >= 2
    rising = np.gradient(u[last]) > 0
    grid = np.linspace(1, 29, 57)
    up = np.interp(grid, np.sort(u[last][rising]), y[last][rising][np.argsort(u[last][rising])])
    down = np.interp(grid, np.sort(u[last][~rising]), y[last][~rising][np.argsort(u[last][~rising])])
    width = down - up
    assert width.max() == pytest.approx(0.180302, abs=2e-4)
    plateau = grid[width > 0.99 * width.max()]
    assert 11.5 <= plateau.min() and plateau.max() <= 18.5
    assert np.mean(plateau) == pytest.approx(15.0, abs=0.5)


@pytest.mark.parametrize("weights, message", [
    ((0.0, 1.0), "W_0"),
    ((1.0, -2.0), "W_1"),
])
def test_non_invertible_models_are_rejected(weights, message):
    with pytest.raises(ValueError, match=message):
        PrandtlIshlinskii((0.0, 0.5), weights)


def test_thresholds_must_start_at_zero_and_increase():
    with pytest.raises(ValueError, match="first threshold"):
        PrandtlIshlinskii((0.1, 0.5), (1.0, 1.0))
    with pytest.raises(ValueError, match="increasing"):
        PrandtlIshlinskii((0.0, 0.5, 0.5), (1.0, 1.0, 1.0))


def test_kernel_updates_memory_in_place_and_state_round_trips():
    model = PrandtlIshlinskii(PAPER_R, PAPER_W, 30.0, 1.44)
    unit = model.unit()
    for u in (10.0, 25.0, 5.0):
        unit.step(u)
    saved = unit.get_state()
    a = [unit.step(u) for u in (12.0, 3.0, 20.0)]
    unit.set_state(saved)
    b = [unit.step(u) for u in (12.0, 3.0, 20.0)]
    assert a == b
    r, z = [0.0, 1.0], pi_state(2)
    assert pi_step(2.0, r, pi_table(r, [1.0, 1.0]), z) == 3.0
    assert pi_memory(r, z) == [2.0, 1.0]


def _clamped(v, r, z):
    """The play-operator rule written out: every operator clamped to [v - r_i, v + r_i]."""
    return [min(max(zi, v - ri), v + ri) for zi, ri in zip(z, r)]


@settings(max_examples=200, deadline=None)
@given(pi_models(), signals(), st.integers(0, 400))
def test_kernel_equals_the_clamping_rule_and_saves_exactly(model, v, cut):
    """The O(1) kernel (followers written out only at reversals) against the plain rule applied to
    every operator at every step; a memory saved at any step and loaded into a fresh memory
    continues bit for bit; loading it with other weights gives the new weights' output."""
    r, w = list(model.thresholds), list(model.weights)
    table, z, ref = pi_table(r, w), pi_state(len(r)), [0.0] * len(r)
    cut = min(cut, len(v) - 1)
    tail = []
    for k, x in enumerate(v.tolist()):
        y = pi_step(x, r, table, z)
        ref = _clamped(x, r, ref)
        assert pi_memory(r, z) == pytest.approx(ref, rel=0, abs=1e-12)
        assert y == pytest.approx(sum(a * b for a, b in zip(w, ref)), rel=0, abs=1e-9)
        if k == cut:
            saved = pi_save(r, z)
        elif k > cut:
            tail.append(y)
    again = pi_state(len(r))
    pi_load(r, table, again, saved)
    assert [pi_step(x, r, table, again) for x in v[cut + 1:].tolist()] == tail
    w2 = [2.0 * x for x in w]
    other = pi_state(len(r))
    pi_load(r, pi_table(r, w2), other, pi_save(r, z))
    assert pi_step(v[-1], r, pi_table(r, w2), other) == pytest.approx(
        sum(a * b for a, b in zip(w2, ref)), rel=0, abs=1e-9)


def test_memory_load_rejects_a_wrong_length_or_follower_count():
    r = [0.0, 0.5]
    z = pi_state(2)
    with pytest.raises(ValueError, match="needs 2 or 5 values"):
        pi_load(r, pi_table(r, [1.0, 1.0]), z, [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="follower count"):
        pi_load(r, pi_table(r, [1.0, 1.0]), z, [0.0, 0.0, 0.0, 3.0, 1.0])
