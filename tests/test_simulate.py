"""The monolithic closed loop: engines, streaming, references, and the loop's behaviour."""
import numpy as np
import pytest

from piezo_fmu.errors import UserError
from piezo_fmu.model import load_model
from piezo_fmu.simulate import COLUMNS, Signal, numba_available, simulate


@pytest.fixture(scope="module")
def model():
    return load_model()


@pytest.mark.skipif(not numba_available(), reason="numba is not installed")
@pytest.mark.parametrize("mode", ["open", "ff", "fb", "ff+fb"])
def test_compiled_and_interpreted_engines_agree_bit_for_bit(model, mode):
    sig = Signal("sine", 45.0, 45.0, 20.0)
    a = simulate(model, sig, 0.06, mode=mode, engine="python")
    b = simulate(model, sig, 0.06, mode=mode, engine="numba")
    for name in COLUMNS:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_streaming_sink_equals_in_memory_run(model):
    sig = Signal("triangle", 20.0, 30.0, 15.0)
    full = simulate(model, sig, 0.1, record_step=1e-4)
    chunks = []
    simulate(model, sig, 0.1, record_step=1e-4, sink=chunks.append, chunk=3000)
    streamed = np.vstack(chunks)
    assert streamed.shape == (len(full["time"]), len(COLUMNS))
    np.testing.assert_array_equal(streamed[:, 2], full["x"])
    np.testing.assert_allclose(np.diff(streamed[:, 0]), 1e-4, rtol=1e-9)


def test_closed_loop_tracks_the_reference(model):
    res = simulate(model, Signal("sine", 45.0, 45.0, 10.0), 0.3, record_step=1e-4)
    err = res["x"] - res["x_ref"]
    stroke = np.ptp(res["x_ref"])
    assert stroke == pytest.approx(90 * model["compensator"]["k_ideal"], rel=1e-3)
    assert np.sqrt(np.mean(err ** 2)) < 0.005 * stroke
    # the sensor voltage follows the displacement through the calibrated gain
    x_meas = (res["us"] - model["compensator"]["sensor_offset"]) / model["compensator"]["sensor_gain"]
    assert np.max(np.abs(x_meas - res["x"])) < 0.02


def test_open_loop_drives_the_amplifier_with_the_reference_voltage(model):
    res = simulate(model, Signal("sine", 15.0, 15.0, 0.5), 2.0, mode="open", record_step=1e-3)
    np.testing.assert_allclose(res["uc"] * model["amplifier"]["k_amp"], 15 - 15 * np.cos(np.pi * res["time"]),
                               atol=1e-9)


def test_table_reference_columns(model):
    t = np.linspace(0, 0.05, 11)
    u = np.linspace(0, 4.0, 11)
    k_ideal, k_amp = model["compensator"]["k_ideal"], model["compensator"]["k_amp"]
    by_u = simulate(model, Signal("table", t=t, values=u, column="u"), 0.05, mode="open")
    np.testing.assert_allclose(by_u["uc"], np.interp(by_u["time"], t, u), atol=1e-12)
    by_x = simulate(model, Signal("table", t=t, values=u * k_ideal * k_amp, column="x_ref"), 0.05,
                    mode="open")
    np.testing.assert_allclose(by_x["x"], by_u["x"], atol=1e-12)


def test_step_reference_holds_after_the_jump(model):
    res = simulate(model, Signal("step", 30.0, 0.0), 0.05, record_step=1e-4)
    assert res["x_ref"][0] == pytest.approx(30 * model["compensator"]["k_ideal"])
    assert abs(res["x"][-1] - res["x_ref"][-1]) < 0.005


@pytest.mark.parametrize("kwargs, message", [
    (dict(stop_time=0.0), "--stop-time"),
    (dict(stop_time=0.1, step=-1e-5), "--step"),
    (dict(stop_time=1e-7), "shorter than one step"),
])
def test_bad_run_options_raise_user_errors(model, kwargs, message):
    stop = kwargs.pop("stop_time")
    with pytest.raises(UserError, match=message):
        simulate(model, Signal("sine", 1, 1, 1), stop, **kwargs)


def test_bad_signals_raise_user_errors():
    with pytest.raises(UserError, match="--freq"):
        Signal("sine", 1.0, 0.0, 0.0)
    with pytest.raises(UserError, match="unknown signal"):
        Signal("square")
    with pytest.raises(UserError, match="--amplitude"):
        Signal("sine", float("nan"), 0.0, 1.0)
