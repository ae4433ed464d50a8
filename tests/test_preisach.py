"""KP cells (``piezo_fmu.core.preisach``): the kernel against a direct Preisach construction, the
relaxed start, rate independence, what it adds to a PI, the model file and the actuator."""
import numpy as np
import pytest

from piezo_fmu.core.preisach import KPCells, grid_cells, kp_relax, kp_step, kp_table
from piezo_fmu.model import ModelError, load_model, with_values
from piezo_fmu.system import make_actuator


def _cell_by_history(v_hist, a, b, w):
    """One KP cell written from its definition instead of the clip recursion: the mean over
    relays spread across its ramps (up at ``alpha' = a - w + t w``, down at ``beta' = b + t w``);
    each relay is +1 when the last input outside (beta', alpha') was above alpha'."""
    out = []
    for k in range(len(v_hist)):
        acc = []
        for t in np.linspace(0.0, 1.0, 201)[1:-1]:
            alpha, beta = a - w + t * w, b + t * w
            state = 1.0 if alpha + beta <= 0.0 else -1.0      # the staircase alpha + beta = 0
            for v in [0.0] + list(v_hist[:k + 1]):
                if v >= alpha:
                    state = 1.0
                elif v <= beta:
                    state = -1.0
            acc.append(state)
        out.append(float(np.mean(acc)))
    return np.array(out)


def test_a_cell_is_a_relay_spread_over_its_ramp():
    v = np.concatenate([np.linspace(0, 3, 40), np.linspace(3, 1.2, 30), np.linspace(1.2, 2.6, 25),
                        np.linspace(2.6, -0.5, 50), np.linspace(-0.5, 1.9, 30)])
    for a, b, w in ((2.0, 1.0, 0.6), (1.5, -0.2, 1.0), (0.4, 0.1, 0.3)):
        c = kp_table([a], [b], [w], [1.0])
        s = [0.0]
        kp_relax(c, s)
        got = np.array([kp_step(x, c, s) for x in v]) - c[-1]     # the state itself
        ref = _cell_by_history(v, a, b, w)
        assert np.max(np.abs(got - ref)) < 0.011, (a, b, w)        # 199 relays: 1/199 resolution
        # and the ramp did something on this path (the check above can fail)
        assert np.ptp(got) > 1.0


def test_relaxed_output_is_zero_and_monotone_paths_can_be_jumped():
    up, down, width = grid_cells(-0.3, 4.0, 6)
    rng = np.random.default_rng(1)
    c = kp_table(up, down, width, rng.normal(size=up.size))
    s = [0.0] * up.size
    assert kp_relax(c, s) == pytest.approx(0.0, abs=1e-12)
    s_fine = list(s)
    for x in np.linspace(0.0, 3.3, 400):
        y_fine = kp_step(float(x), c, s_fine)
    for x in np.linspace(3.3, 0.7, 400):
        y_fine = kp_step(float(x), c, s_fine)
    kp_step(3.3, c, s)
    y_jump = kp_step(0.7, c, s)
    assert y_jump == pytest.approx(y_fine, abs=1e-12) and s == pytest.approx(s_fine, abs=1e-12)
    assert abs(y_jump) > 1e-3


def test_cells_draw_a_level_dependent_loop_width_a_pi_cannot():
    """Minor loops of equal amplitude at two levels: a PI draws them congruent (Masing), cells
    centred at one level make the loop there wider."""
    up, down, width = grid_cells(0.0, 4.0, 8)
    mu = np.where((up + down) / 2 > 2.5, 0.05, 0.0)
    k = KPCells(up, down, width, mu)

    def width_of_minor_loop(centre):
        v = np.concatenate([np.linspace(0, 4, 200), np.linspace(4, centre - 0.4, 200),
                            np.tile(np.concatenate([np.linspace(centre - 0.4, centre + 0.4, 50),
                                                    np.linspace(centre + 0.4, centre - 0.4, 50)]), 2)])
        y = k.apply(v)
        last = y[-100:]
        return abs(last[25] - last[75])          # up and down branch at the same input

    assert width_of_minor_loop(3.2) > 10 * max(width_of_minor_loop(1.0), 1e-6)


def test_model_file_validates_cells_and_the_actuator_runs_them():
    m = load_model()
    with pytest.raises(ModelError, match="cells_up"):
        with_values(m, {"hysteresis.cells_up": [1.0], "hysteresis.cells_down": [0.9],
                        "hysteresis.cells_width": [0.5], "hysteresis.cells_weights": [0.1]})
    with pytest.raises(ModelError, match="equal lengths"):
        with_values(m, {"hysteresis.cells_up": [1.0, 2.0], "hysteresis.cells_down": [0.0],
                        "hysteresis.cells_width": [0.5], "hysteresis.cells_weights": [0.1]})
    m = with_values(m, {"hysteresis.saturation": float("inf")})
    plain = make_actuator(m)
    with_cells = make_actuator(with_values(m, {
        "hysteresis.cells_up": [2.0], "hysteresis.cells_down": [1.0], "hysteresis.cells_width": [0.5],
        "hysteresis.cells_weights": [0.3]}))
    xs = []
    for act in (plain, with_cells):
        assert act.x == pytest.approx(0.0, abs=1e-15)          # at rest: no offset from the cells
        xs.append([act.advance(u, 1e-4) for u in np.repeat([9.0, 5.0, 2.0], 200)])
    d = np.array(xs[1]) - np.array(xs[0])
    # up to 90 V the cell (its up ramp 45-60 V) adds 0.3 x 2 PI units of stroke; back at 50 V it
    # stays up (its down ramp is 30-45 V), at 20 V it is down again: nothing added
    full = 0.6 * m.sections["hysteresis"]["scale"] * plain.static_gain()
    assert d[199] == pytest.approx(full, rel=0.02)
    assert d[399] == pytest.approx(full, rel=0.02)
    assert abs(d[-1]) < 0.01 * full
