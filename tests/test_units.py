"""Linear blocks, amplifier, mechanics, sensor and controller units against closed forms and SciPy."""
import math

import numpy as np
import pytest
import scipy.linalg
import scipy.signal

from piezo_fmu.core.control import pid_step, reference_value
from piezo_fmu.core.hysteresis import PrandtlIshlinskii
from piezo_fmu.core.linear import LinearSystem, balance, discretize, expm, is_hurwitz, tf2ss
from piezo_fmu.core.plant import Actuator, NoiseSource, Sensor, amp_step
from piezo_fmu.model import load_model
from piezo_fmu.system import make_actuator, make_sensor


@pytest.mark.parametrize("seed", range(5))
def test_expm_matches_scipy(seed):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(4, 4)) * 10 ** rng.uniform(-3, 1.5)
    np.testing.assert_allclose(expm(a), scipy.linalg.expm(a), rtol=1e-11, atol=1e-13)


@pytest.mark.parametrize("f_mode", [69.9, 3000.0, 8640.0])
def test_a_stiff_chain_discretises_to_its_exact_poles(f_mode):
    # the mechanics (first mode 15.1 kHz, zeta 0.05) times a further mode (zeta 0.005) at 19.2 kHz:
    # the companion matrix's coefficients run from 1 to 3e19 s^-4. Unbalanced, scaling and squaring
    # put a pole at |z| = 1.10 for the 8.64 kHz mode (0.986: an unstable chain, NaN after 0.5 s)
    # and moved the first mode's 0.7811 to 0.7867 beside a 3 kHz mode.
    from piezo_fmu.core.plant import mechanics_tf

    m, c, k_a, k_f = 0.021579, 204.74, 176594600.0, 17659460.0
    h = 1.0 / 19200.0
    a, b, _, _ = tf2ss(*mechanics_tf(m, c, k_a, k_f, (f_mode, 0.005)))
    phi, _, _ = discretize(a, b, h, "foh")
    exact = np.exp(np.roots(np.polymul([m, c, k_a + k_f], [1.0, 2 * 0.005 * 2 * math.pi * f_mode,
                                                              (2 * math.pi * f_mode) ** 2])) * h)
    got = np.linalg.eigvals(phi)
    for z in exact:
        assert np.min(np.abs(got - z)) < 1e-9 * abs(z)
    # balancing is a similarity by powers of two: exact, and what it leaves balanced
    bal, d = balance(a)
    np.testing.assert_array_equal(bal * d[:, None] / d[None, :], a)
    assert np.all(np.log2(d) == np.round(np.log2(d)))


@pytest.mark.parametrize("bad", [np.inf, np.nan])
def test_a_non_finite_matrix_is_an_error_not_a_hang(bad):
    # balancing scales a row and its column by powers of two until their norms meet: an infinite
    # entry off the diagonal never meets, and the loop never ended
    with pytest.raises(ValueError, match="finite"):
        expm(np.array([[0.0, bad], [1.0, 0.0]]))
    b, d = balance(np.array([[0.0, bad], [1.0, 0.0]]))        # and the balancing itself returns
    assert np.all(np.isfinite(d))


@pytest.mark.parametrize("method", ["zoh", "foh"])
def test_discretisation_matches_scipy(method):
    num, den = [2.0, 5.0], [1.0, 3.0, 40.0]
    a, b, c, d = tf2ss(num, den)
    h = 0.013
    phi, g0, g1 = discretize(a, b, h, method)
    ad, bd, cd, dd, _ = scipy.signal.cont2discrete((a, b, c, d), h, method=method)
    np.testing.assert_allclose(phi, ad, rtol=1e-12, atol=1e-14)
    if method == "zoh":
        np.testing.assert_allclose(g0, bd, rtol=1e-12, atol=1e-14)
    else:
        # scipy's FOH uses the state x~ = x - G1 u; the input-output map is what must agree
        u = np.sin(np.arange(200) * 0.3)
        sys = LinearSystem(num, den, "foh")
        ours = [sys.step(v, h) for v in u]
        _, ref, _ = scipy.signal.dlsim((ad, bd, cd, dd, h), np.concatenate([[0.0], u]))
        np.testing.assert_allclose(ours, ref[1:, 0], rtol=1e-9, atol=1e-12)


def test_first_order_step_response_is_exact():
    sys = LinearSystem([1.0], [0.01, 1.0], "zoh")
    y = [sys.step(1.0, 0.001) for _ in range(50)]
    t = 0.001 * np.arange(1, 51)
    np.testing.assert_allclose(y, 1 - np.exp(-t / 0.01), rtol=1e-12)


def test_hurwitz():
    assert is_hurwitz([1, 3, 2])
    assert not is_hurwitz([1, -1, 2])
    assert not is_hurwitz([1, 0, 4])


def test_amplifier_step_is_exact_and_slew_limited():
    tau, h = 1e-3, 2e-4
    # no current limit: exponential approach
    ua = 0.0
    for k in range(1, 6):
        ua = amp_step(ua, 10.0, tau, math.inf, h, math.exp(-h / tau))
        assert ua == pytest.approx(10 * (1 - math.exp(-k * h / tau)), rel=1e-12)
    # slew 1e4 V/s: a 30 V step ramps at the limit until the remaining error is slew*tau = 10 V
    # (t = 2 ms), then approaches exponentially; a step that crosses the switch is split exactly
    slew = 1e4
    ua, out = 0.0, []
    for _ in range(25):
        ua = amp_step(ua, 30.0, tau, slew, 3e-4, math.exp(-3e-4 / tau))
        out.append(ua)
    t = 3e-4 * np.arange(1, 26)
    expected = np.where(t <= 2e-3, slew * t, 30.0 - 10.0 * np.exp(-(t - 2e-3) / tau))
    np.testing.assert_allclose(out, expected, rtol=1e-12)
    assert np.max(np.diff([0.0] + out)) <= slew * 3e-4 * (1 + 1e-12)


def _paper_actuator():
    return make_actuator(load_model())


def test_actuator_static_gain_and_rails():
    model = load_model()
    act = _paper_actuator()
    pi = model.hysteresis("hysteresis")
    me = model["mechanics"]
    y_sat = model["hysteresis"]["saturation"]
    for _ in range(500):           # 50 ms = 31 amplifier time constants at 2 V command: settled
        act.advance(2.0, 1e-4)
    x_h = float(pi.apply(np.linspace(0, 20.0, 50))[-1])
    x_h = x_h / (1 + x_h / y_sat)
    assert act.ua == pytest.approx(20.0, rel=1e-9)
    assert act.F == pytest.approx(me["k_a"] * 1e-6 * x_h, rel=1e-9)
    assert act.x == pytest.approx(x_h * me["k_a"] / (me["k_a"] + me["k_f"]), rel=1e-6)
    for _ in range(500):
        act.advance(100.0, 1e-4)    # 1000 V asked: held at the 150 V rail
    assert act.ua == pytest.approx(model["amplifier"]["u_max"])


def test_mechanical_resonance_frequency():
    """With hysteresis reduced to its identity operator, a force step rings at sqrt(k/m)."""
    model = load_model()
    me = model["mechanics"]
    act = Actuator(k_amp=1, R=1e-6, C_a=1e-6, u_min=-1e9, u_max=1e9,
                   hysteresis=PrandtlIshlinskii((0.0,), (1.0,), 1.0, 1.0),
                   m=me["m"], c=0.0, k_a=me["k_a"], k_f=me["k_f"], max_step=1e-6)
    xs = [act.advance(1.0, 2e-6) for _ in range(2000)]
    x = np.array(xs) - np.mean(xs)
    crossings = np.where(np.diff(np.sign(x)) != 0)[0]
    period = 2 * np.mean(np.diff(crossings)) * 2e-6
    f_expected = math.sqrt((me["k_a"] + me["k_f"]) / me["m"]) / (2 * math.pi)
    assert 1 / period == pytest.approx(f_expected, rel=0.01)


@pytest.mark.parametrize("pickoff", ["stack", "contact", "load"])
def test_a_prepared_actuator_starts_where_a_relaxed_one_ends_after_the_sweep(pickoff):
    """``prepared``: the memory of a sweep up to that stack voltage and back, everything after the
    hysteresis settled; the same state a relaxed actuator reaches when it is driven through the
    sweep and left to settle (no creep here: its slow elements would take minutes to settle)."""
    model = load_model()
    model.set("mechanics", "pickoff", pickoff, "test")
    relaxed = make_actuator(model)
    top = 0.8 * model["amplifier"]["u_max"]
    k = model["amplifier"]["k_amp"]
    model.set("hysteresis", "prepared", top, "test")
    prepared = make_actuator(model)
    for uc in np.concatenate([np.linspace(0.0, top / k, 4000), np.linspace(top / k, 0.0, 4000), np.zeros(4000)]):
        relaxed.advance(float(uc), 1e-4)
    assert prepared.out[3] == pytest.approx(relaxed.out[3], rel=1e-9)   # x_h: the remnant stroke
    assert prepared.x == pytest.approx(relaxed.x, rel=1e-6)
    assert prepared.F == pytest.approx(relaxed.F, rel=1e-6)
    assert prepared.out[3] > 0.01                                        # [um]: not relaxed
    model.set("hysteresis", "prepared", 0.0, "test")
    assert make_actuator(model).out[3] == 0.0                            # 0: relaxed, as before


def test_actuator_state_round_trip_is_bit_exact():
    act = _paper_actuator()
    for k in range(300):
        act.advance(5 + 4 * math.sin(k / 20), 1e-4)
    saved = act.get_state()
    a = [act.advance(5 + 4 * math.sin(k / 7), 1e-4) for k in range(200)]
    act.set_state(saved)
    b = [act.advance(5 + 4 * math.sin(k / 7), 1e-4) for k in range(200)]
    assert a == b


def test_sensor_sensitivity_and_leakage():
    model = load_model()
    s = model["sensor"]
    sen = make_sensor(model, noise=False)
    c_s = 8.8541878128e-12 * s["eps_r"] * s["area"] / s["thickness"]
    assert sen.sensitivity == pytest.approx(s["d11"] / (c_s + s["C_load"]))
    assert sen.step(100.0, 1e-4) == pytest.approx(100.0 * sen.sensitivity)
    leaky = Sensor(d11=2.31e-12, thickness=1e-3, eps_r=4.5, area=9.3e-5, C_load=1e-9, tau_leak=0.1)
    leaky.reset()
    us = [leaky.step(100.0, 1e-3) for _ in range(300)]
    # after the force ramp in the first step the voltage decays with tau_leak
    assert us[200] / us[100] == pytest.approx(math.exp(-0.1 / 0.1), rel=1e-3)


def test_second_order_amplifier_follows_two_lags():
    """amplifier.tau_2: the stack voltage of two cascaded lags, to second order in the step; 0 keeps
    the first-order amplifier bit for bit."""
    tau, tau2, k = 1e-3, 0.4e-3, 10.0
    pi = PrandtlIshlinskii((0.0,), (1.0,), 1.0, 1.0)
    kw = dict(k_amp=k, R=tau / 1e-6, C_a=1e-6, u_min=-1e9, u_max=1e9, hysteresis=pi, m=1e-3, c=10.0,
              k_a=1e8, k_f=1e7)
    t = np.arange(1, 101) * 1e-4
    exact = k * (1 - (tau * np.exp(-t / tau) - tau2 * np.exp(-t / tau2)) / (tau - tau2))
    for h, tol in ((1e-4, 2e-3), (1e-5, 2e-5)):
        act = Actuator(tau_2=tau2, max_step=h, **kw)
        got = []
        for _ in range(100):
            act.advance(1.0, 1e-4)
            got.append(act.ua)
        assert np.max(np.abs(np.array(got) - exact)) < tol * k
    one = Actuator(max_step=1e-4, **kw)
    zero = Actuator(tau_2=0.0, max_step=1e-4, **kw)
    assert [one.advance(1.0 + (j % 7), 1e-4) for j in range(50)] == [zero.advance(1.0 + (j % 7), 1e-4) for j in range(50)]
    assert [one.advance(1.0, 1e-4) for _ in range(5)] != [Actuator(tau_2=tau2, **kw).advance(1.0, 1e-4) for _ in range(5)]


def test_pickoffs_sense_the_spring_or_the_contact_force():
    """mechanics.pickoff = load: the sensed force is k_f x with the mechanics' ringing, and a drift's
    change moves the push rod, so the spring feels it too (not the reading's constant offset);
    contact: k_a (x_free - x)."""
    model = load_model()
    m = model.copy()
    m.sections["mechanics"]["pickoff"] = "load"
    m.sections["drift"]["rate"] = 0.3
    m.sections["drift"]["offset"] = 0.7
    act = make_actuator(m)
    me = model["mechanics"]
    for j in range(300):
        act.advance(3.0 + 2.0 * (j > 100), 1e-5)
        assert act.F == pytest.approx(me["k_f"] * 1e-6 * (act.x - 0.7), rel=1e-12, abs=1e-15)
    assert make_actuator(model).advance(3.0, 1e-5) != 0.0
    m.sections["mechanics"]["pickoff"] = "contact"
    act = make_actuator(m)
    ref = make_actuator(model)
    for j in range(300):
        act.advance(3.0 + 2.0 * (j > 100), 1e-5)
        ref.advance(3.0 + 2.0 * (j > 100), 1e-5)
        # the contact force k_a (x_free - x) = F_out - k_a x (the mechanics' inertia and damping show)
        assert act.F == pytest.approx(ref.F - me["k_a"] * 1e-6 * (act.x - 0.7 - 0.3 * act.time), rel=1e-9, abs=1e-12)


def test_a_mode_on_the_drive_shows_in_the_stack_force():
    """resonance.position = drive: the further mode shapes the free stroke, so the stack force rings
    at f_n after a step; on the output it stays in the displacement."""
    model = load_model()
    out = {}
    for pos in ("output", "drive"):
        m = model.copy()
        m.sections["resonance"].update(f_n=400.0, zeta=0.02, position=pos)
        act = make_actuator(m)
        F = np.array([(act.advance(3.0, 1e-4), act.F)[1] for _ in range(600)])
        out[pos] = F
    settled = out["output"][-1]
    assert np.max(np.abs(out["output"][300:] - settled)) < 1e-6 * abs(settled)      # the lag settling
    tail = out["drive"][100:] - out["drive"][-1]
    crossings = np.nonzero(np.diff(np.sign(tail)) != 0)[0]
    assert np.max(np.abs(tail)) > 1e-3 * abs(settled)
    assert 2 * np.mean(np.diff(crossings)) * 1e-4 == pytest.approx(1 / 400.0, rel=0.03)


def test_sensor_lag_delays_the_voltage_by_whole_steps():
    """sensor.lag: the output is the noise-free voltage of lag/h steps before plus this step's noise."""
    kw = dict(d11=2.31e-12, thickness=1e-3, eps_r=4.5, area=9.3e-5, C_load=1e-9, tau_leak=0.2,
              offset=0.01, noise_std=0.001, seed=4)
    forces = [100.0 * math.sin(j / 5) for j in range(80)]
    ref = Sensor(**{**kw, "noise_std": 0.0})
    ref.reset()
    clean = [ref.step(f, 1e-4) for f in forces]
    lagged = Sensor(**kw, lag=2e-4)
    lagged.reset()
    got = [lagged.step(f, 1e-4) for f in forces]
    noise = NoiseSource(0.001, 4)
    noise = [noise.next() for _ in forces]
    want = [ref.sensitivity * 0 + 0.01 + n for n in noise[:2]] + [c + n for c, n in zip(clean, noise[2:])]
    assert got == pytest.approx(want, rel=0, abs=1e-15)
    state = lagged.get_state()
    more = [lagged.step(3.0, 1e-4) for _ in range(4)]
    lagged.set_state(state)
    assert [lagged.step(3.0, 1e-4) for _ in range(4)] == more


def test_noise_is_reproducible_and_resumable():
    a = NoiseSource(1.0, 7)
    first = [a.next() for _ in range(5000)]
    b = NoiseSource(1.0, 7)
    assert [b.next() for _ in range(5000)] == first
    c = NoiseSource(1.0, 7)
    [c.next() for _ in range(4100)]
    state = c.get_state()
    tail = [c.next() for _ in range(50)]
    d = NoiseSource(1.0, 7)
    d.set_state(state)
    assert [d.next() for _ in range(50)] == tail
    assert np.std(first) == pytest.approx(1.0, rel=0.05)
    e = NoiseSource(1.0, 7)
    mixed = list(e.take(3)) + [e.next() for _ in range(4090)] + list(e.take(907))
    assert mixed == first


def test_pid_discrete_with_conditional_integration():
    gains, st = [2.0, 100.0, 0.0, 1e-4], [0.0, 0.0, 0.0, 0.0]
    out = [pid_step(1.0, 0.01, gains, st, 0.0) for _ in range(3)]
    assert out == pytest.approx([2 + 1, 2 + 2, 2 + 3])
    # saturated high with positive error: the integrator holds
    held = pid_step(1.0, 0.01, gains, st, 1.0)
    assert held == pytest.approx(2 + 3)
    # saturated high but the error pulls back: it integrates
    assert pid_step(-1.0, 0.01, gains, st, 1.0) == pytest.approx(-2 + 2)


@pytest.mark.parametrize("kind", [1, 3])
def test_reference_starts_at_minimum_and_has_sine_extrema(kind):
    f, ph = 10.0, -math.pi / 2
    assert reference_value(kind, 0.0, 45.0, 45.0, f, ph) == pytest.approx(0.0, abs=1e-9)
    assert reference_value(kind, 0.05, 45.0, 45.0, f, ph) == pytest.approx(90.0)
    assert reference_value(2, -1e-9, 2.0, 1.0, f, 0) == 1.0
    assert reference_value(2, 0.0, 2.0, 1.0, f, 0) == 3.0
