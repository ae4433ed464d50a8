"""The paper's results reproduced (issue 2 acceptance), and the identification behind them."""
import json
import warnings

import numpy as np
import pytest

from piezo_fmu.cli import main
from piezo_fmu.control_design import loop, margins
from piezo_fmu.identify import identify_compensator
from piezo_fmu.model import load_model
from piezo_fmu.reproduce import FREQS, error_stats, fkey, run_reproduction


@pytest.fixture(scope="module")
def repro(tmp_path_factory):
    out = tmp_path_factory.mktemp("repro")
    result = run_reproduction(load_model(), out)
    return out, result


def test_json_layout_and_every_cell_recomputes_from_its_csv(repro):
    out, result = repro
    on_disk = json.loads((out / "reproduction.json").read_text())
    assert set(on_disk["figure5"]) >= {"max_width_um", "at_voltage_V"}
    cells = {"table2": ("static", "dynamic"), "table3": ("static_inverse", "dynamic_inverse"),
             "table4": ("ff_pid",)}
    for table, names in cells.items():
        for name in names:
            assert set(on_disk[table][name]) == {fkey(f) for f in FREQS}
            for f in FREQS:
                k = fkey(f)
                csv = out / on_disk["csv"][f"{table}/{name}/{k}"]
                head = csv.read_text().splitlines()[0]
                assert head == "time,ideal,output"
                t, ideal, output = np.loadtxt(csv, delimiter=",", skiprows=1, unpack=True)
                assert t.size >= 3 * 2000
                again = error_stats(ideal, output)
                for stat in ("max", "avg", "rms"):
                    assert again[stat] == pytest.approx(on_disk[table][name][k][stat], rel=1e-6)


def test_figure5_widest_loop(repro):
    f5 = repro[1]["figure5"]
    assert f5["max_width_um"] == pytest.approx(0.26, abs=0.02)
    assert f5["at_voltage_V"] == pytest.approx(15.0, abs=2.0)
    assert 0.02 < f5["repeatability_um"] < 0.1   # paper: 0.06 um


def test_table2_static_grows_dynamic_stays_flat(repro):
    t2 = repro[1]["table2"]
    assert t2["static"]["50"]["avg"] >= 3 * t2["static"]["0.5"]["avg"]
    base = t2["dynamic"]["0.5"]["avg"]
    for f in FREQS:
        assert t2["dynamic"][fkey(f)]["avg"] <= 1.5 * base
    for k in ("20", "50"):
        assert t2["dynamic"][k]["avg"] < t2["static"][k]["avg"]


def test_table3_dynamic_inverse_beats_static_everywhere(repro):
    t3 = repro[1]["table3"]
    for f in FREQS:
        k = fkey(f)
        assert t3["dynamic_inverse"][k]["avg"] < t3["static_inverse"][k]["avg"], k


def test_table4_pid_cuts_rms_at_least_fourfold(repro):
    r = repro[1]
    for k in ("0.5", "50"):
        cut = r["table3"]["dynamic_inverse"][k]["rms"] / r["table4"]["ff_pid"][k]["rms"]
        assert cut >= 4.0, (k, cut)
    # Our goal was 10x. The shipped PID trades bandwidth for stability under Jacobi co-simulation
    # masters (see test_pid_design_margins_hold_for_the_shipped_gains): measured x8.3 at 50 Hz
    # (x20.8 with the Gauss-Seidel-only design, unstable in Jacobi masters at 1e-4 s). Guard it.
    assert r["checks"]["table4_rms_cut_by_pid"]["50"] >= 8.0


def test_feedforward_alone_leaves_real_model_error(repro):
    """The device is not the model the compensator inverts: feedforward leaves a visible error."""
    t3 = repro[1]["table3"]
    assert t3["dynamic_inverse"]["0.5"]["avg"] > 0.03


def test_figures_written(repro):
    out, result = repro
    for name in result["figures"].values():
        png = out / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert png.stat().st_size > 20_000


def test_pid_design_margins_hold_for_the_shipped_gains():
    m = load_model()
    c = m["compensator"]
    lz = loop(m, c["Kp"], c["Ki"], c["Kd"], c["Tf"])
    mg = margins(lz)
    assert mg["stable"] and mg["pm_deg"] >= 55.0 and mg["gm_db"] >= 10.0
    assert mg["S_at_hz"] < 0.1
    for ratio in (0.5, 2.0):
        assert margins(loop(m, c["Kp"], c["Ki"], c["Kd"], c["Tf"], s_ratio=ratio))["stable"]
    # Jacobi masters (fmpy.ssp, libcosim) add two steps of delay: still stable with margin
    jac = margins(loop(m, c["Kp"], c["Ki"], c["Kd"], c["Tf"], delay_steps=2))
    assert jac["stable"] and jac["pm_deg"] >= 45.0 and jac["gm_db"] >= 6.0


def test_identification_reproduces_the_shipped_compensator():
    """models/paper.toml's compensator is what `piezo-fmu identify` finds (no hand-tuned values)."""
    m = load_model()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        new, report = identify_compensator(m, design=False)
    for key in ("k_ideal", "sensor_gain"):
        assert new["compensator"][key] == pytest.approx(m["compensator"][key], rel=1e-6)
    np.testing.assert_allclose(new["compensator.hysteresis"]["weights"],
                               m["compensator.hysteresis"]["weights"], atol=1e-7)
    tau_true = m["amplifier"]["R"] * m["amplifier"]["C_a"]
    tau_id = new["compensator.dynamics"]["den"][0]
    assert tau_id == pytest.approx(m["compensator.dynamics"]["den"][0], rel=1e-6)
    assert tau_id == pytest.approx(tau_true, rel=0.01)           # the amplifier corner is found
    assert report["pi_rms_um"] < 2 * m["measurement"]["x_noise_std"]


def test_reproduce_cli_refuses_to_overwrite(tmp_path, capsys):
    (tmp_path / "reproduction.json").write_text("{}")
    assert main(["reproduce", "--out", str(tmp_path), "--quiet"]) == 2
    assert "exists" in capsys.readouterr().err
    assert (tmp_path / "reproduction.json").read_text() == "{}"
