"""The benchmark keeps working (issue 5): tiny size, keys and sane values; speeds are not asserted."""
import json
import math

import shutil

from piezo_fmu.bench import KEYS, RUNTIME_KEYS, SWEEP_KEYS
from piezo_fmu.cli import main


def test_bench_tiny_writes_every_key(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench", "--size", "tiny", "--json", str(out), "--quiet"]) == 0
    r = json.loads(out.read_text())
    for key in KEYS:
        assert isinstance(r[key], (int, float)) and math.isfinite(r[key]) and r[key] > 0, key
    for key in SWEEP_KEYS:         # sweeps on dask (issue 13)
        assert isinstance(r[key], (int, float)) and math.isfinite(r[key]) and r[key] > 0, key
    # the figures are consistent with each other
    assert math.isclose(r["cosim_to_floor"], r["cosim_us_per_step"] / r["floor_us_per_step"])
    assert math.isclose(r["cosim_realtime_factor"], 1e-4 / (r["cosim_us_per_step"] * 1e-6))
    # (no speed comparisons: at the tiny size a busy machine can make the floor slower than the
    # co-simulation, as it once did in CI)
    for key in ("monolithic_python_samples_per_s", "pi_forward_interpreted_ns_per_sample_operator",
                "pi_inverse_ns_per_sample_operator", "monolithic_single_rate_samples_per_s",
                "monolithic_single_rate_speedup_vs_cosim", "pi_forward_ns_per_sample",
                "cosim_python_us_per_step", "cosim_python_to_floor", "cosim_python_realtime_factor",
                "monolithic_end_to_end_samples_per_s", "monolithic_end_to_end_speedup_vs_cosim",
                "monolithic_python_speedup_vs_cosim_python"):
        assert math.isfinite(r[key]) and r[key] > 0, key
    assert r["cosim_engine"] in ("numba", "python")
    assert math.isclose(r["cosim_python_to_floor"], r["cosim_python_us_per_step"] / r["floor_us_per_step"])
    # the speed-up is wall time per simulated second: co-simulation loop (H = 1e-4 s) against the
    # monolithic loop (1e-5 s steps)
    assert math.isclose(r["monolithic_speedup_vs_cosim"],
                        r["cosim_us_per_step"] * 1e-6 / 1e-4 * r["monolithic_samples_per_s"] * 1e-5)
    assert r["monolithic_control_step_s"] == 1e-4     # the controller sampled as in the co-simulation
    assert r["diagnose_recording"]["channels"] == ["x", "us"]
    from piezo_fmu.diagnose.workers import thread_count

    assert r["diagnose_threads"] == thread_count()      # (one in the suite's xdist workers: conftest)
    assert r["machine"]["cores"] >= 1
    # the native runtime's figures: every key there; the C host's in a checkout with a compiler
    for key in RUNTIME_KEYS:
        assert key in r and (r[key] is None or (math.isfinite(r[key]) and r[key] > 0)), key
    for key in ("call_master_dostep_us", "call_master_setget_us", "cosim_command_fixed_s"):
        assert r[key] is not None, key
    if shutil.which("gcc") or shutil.which("cc"):
        for key in ("call_c_dostep_us", "call_c_thread_dostep_us", "loop_c_us_per_step", "loop_c_to_master"):
            assert r[key] is not None, key
        assert math.isclose(r["loop_c_to_master"], r["loop_c_us_per_step"] / r["cosim_us_per_step"])
    printed = capsys.readouterr().out
    assert "us/step" in printed and "samples/s" in printed
    # refusing to overwrite
    assert main(["bench", "--size", "tiny", "--json", str(out), "--quiet"]) == 2
