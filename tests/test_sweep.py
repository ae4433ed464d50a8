"""piezo-fmu sweep on dask.distributed (issue 13): a real scheduler and workers on loopback, the
sweep through --scheduler equal to the serial run, a worker killed mid-sweep, --resume after an
interruption, bad specs exit 2; and the parts: values per index, model overrides, metrics, store."""
from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from piezo_fmu.cli import main
from piezo_fmu.errors import UserError
from piezo_fmu.model import ModelError, load_model, with_values
from piezo_fmu.parallel import Engine, TaskFailed, map_as_completed
from piezo_fmu.sweep import SpecError, loads_spec, read_results, sweep
from piezo_fmu.sweep.metrics import compute
from piezo_fmu.sweep.runner import run_one
from piezo_fmu.sweep.space import columns, run_values

DASK = Path(sys.executable).parent / "dask"

# 40 short runs: 2 modes x 5 frequencies x 4 units (weights +-20 %, R, sensor gain, Kp); 2 periods
SPEC = """
[sweep]
name = "test"
seed = 11
count = 4

[experiment]
periods = 2
samples_per_period = 400
kernels = "{kernels}"

[metrics]
tolerance = {{ metric = "rms_um", max = 0.02 }}

[grid]
"experiment.mode" = ["ff", "ff+fb"]
"experiment.freq" = {{ start = 40.0, stop = 160.0, num = 5, log = true }}

[random]
"hysteresis.weights" = {{ tolerance_pct = 20 }}
"amplifier.R" = {{ normal = [400.0, 20.0], unit = "ohm" }}
"sensor.d11" = {{ tolerance_pct = 5, distribution = "normal" }}
"compensator.Kp" = {{ uniform = [0.1, 0.3] }}
"""


def write_spec(folder, kernels="numba", text=SPEC):
    path = Path(folder) / "spec.toml"
    path.write_text(text.format(kernels=kernels))
    return path


def same_results(a, b):
    """Two results tables equal in every column but the wall time (NaN equal to NaN)."""
    assert a.column_names == b.column_names
    for name in a.column_names:
        if name == "seconds":
            continue
        x, y = a.column(name).to_pylist(), b.column(name).to_pylist()
        for i, (u, v) in enumerate(zip(x, y)):
            both_nan = isinstance(u, float) and isinstance(v, float) and math.isnan(u) and math.isnan(v)
            assert both_nan or u == v, f"{name} of run {i}: {u!r} != {v!r}"
    assert a.num_rows == b.num_rows


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Cluster:
    """A `dask scheduler` and `dask worker` processes on 127.0.0.1, started and killed here."""

    def __init__(self, tmp):
        self.tmp = Path(tmp)
        self.port = free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.procs = []
        self.log = open(self.tmp / "dask.log", "w")      # noqa: SIM115 - closed in stop()
        self.start([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", str(self.port),
                    "--no-dashboard"])

    def start(self, argv):
        p = subprocess.Popen(argv, cwd=self.tmp, stdout=self.log, stderr=subprocess.STDOUT)
        self.procs.append(p)
        return p

    def worker(self):
        return self.start([str(DASK), "worker", self.address, "--nthreads", "1", "--no-nanny",
                           "--no-dashboard", "--host", "127.0.0.1", "--memory-limit", "0",
                           "--local-directory", str(self.tmp)])

    def wait_for(self, n, timeout=120):
        from distributed import Client

        with Client(self.address, timeout=timeout, set_as_default=False) as c:
            c.wait_for_workers(n, timeout=timeout)
            return list(c.scheduler_info()["workers"])

    def stop(self):
        for p in reversed(self.procs):       # test processes: nothing to save
            if p.poll() is None:
                p.kill()
        for p in self.procs:
            p.wait()
        self.log.close()


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    c = Cluster(tmp_path_factory.mktemp("dask"))
    try:
        c.worker()
        c.worker()
        c.wait_for(2)
        yield c
    finally:
        c.stop()


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    """The 40-run spec computed serially in this process (the reference)."""
    tmp = tmp_path_factory.mktemp("serial")
    spec = write_spec(tmp)
    summary = sweep(spec, tmp / "out", workers=0, report=False)
    return spec, tmp / "out", summary


# -- through a real scheduler ------------------------------------------------------------------------

def test_sweep_through_scheduler_equals_serial(cluster, serial, tmp_path, capsys):
    spec, serial_out, summary = serial
    assert summary["runs"] == summary["computed"] == summary["ok"] == 40
    code = main(["sweep", str(spec), "--out", str(tmp_path / "out"), "--scheduler", cluster.address,
                 "--quiet"])
    assert code == 0, capsys.readouterr().err
    assert "40 runs (40 computed now): 40 ok" in capsys.readouterr().out
    same_results(read_results(serial_out), read_results(tmp_path / "out"))
    # the rows are the runs, with their values and the metrics
    t = read_results(tmp_path / "out")
    assert t.column("index").to_pylist() == list(range(40))
    assert set(t.column("experiment.mode").to_pylist()) == {"ff", "ff+fb"}
    rms = np.array(t.column("rms_um").to_pylist())
    mode = np.array(t.column("experiment.mode").to_pylist())
    assert np.median(rms[mode == "ff+fb"]) < 0.5 * np.median(rms[mode == "ff"])   # the PID helps
    html = (tmp_path / "out" / "report.html").read_text()
    for fig in ("curves.png", "distributions.png", "rms_um_vs_parameters.png", "yield.png"):
        assert (tmp_path / "out" / "figures" / fig).stat().st_size > 1000
        assert fig in html
    assert "Yield:" in html and "worst runs" in html


def test_worker_killed_mid_sweep_every_row_completes(cluster, tmp_path):
    """A third worker is killed (SIGKILL) while it holds tasks; dask runs them elsewhere."""
    from distributed import Client

    spec = write_spec(tmp_path, kernels="python")    # interpreted: the new worker needs no compile
    before = set(cluster.wait_for(2))
    victim = cluster.worker()
    addr = (set(cluster.wait_for(3)) - before).pop()
    killed = []
    client = Client(cluster.address, set_as_default=False)

    def progress(fraction, message=""):
        if killed or fraction is None or fraction < 0.2:
            return
        deadline = time.monotonic() + 5
        while not client.processing(workers=[addr]).get(addr) and time.monotonic() < deadline:
            time.sleep(0.01)
        killed.append(len(client.processing(workers=[addr]).get(addr, ())))
        os.kill(victim.pid, signal.SIGKILL)

    try:
        summary = sweep(spec, tmp_path / "out", scheduler=cluster.address, workers=3, progress=progress,
                        report=False)
    finally:
        client.close()
    assert killed and killed[0] > 0, "the worker held no task when it was killed"
    assert victim.wait(10) == -signal.SIGKILL
    assert summary["ok"] == summary["runs"] == 40 and summary["lost"] == 0
    ref = sweep(spec, tmp_path / "ref", workers=0, report=False)
    assert ref["ok"] == 40
    same_results(read_results(tmp_path / "ref"), read_results(tmp_path / "out"))


def test_resume_after_interruption_recomputes_nothing_finished(cluster, serial, tmp_path):
    spec, serial_out, _ = serial
    out = tmp_path / "out"

    def interrupt(fraction, message=""):
        # at the first finished task (the engine's first tasks are single runs, before it knows how
        # long a run takes); a later threshold raced the batching: 5 ms runs put the remaining 36
        # into one batch, and a stop at 25 % came with all 40 written
        if fraction is not None and fraction > 0:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sweep(spec, out, scheduler=cluster.address, progress=interrupt, report=False)
    first = read_results(out)
    done = first.num_rows
    assert 1 <= done < 40 and (out / "results.parquet").exists()
    seconds = dict(zip(first.column("index").to_pylist(), first.column("seconds").to_pylist()))
    with pytest.raises(UserError, match="--resume"):             # not silently overwritten
        sweep(spec, out, scheduler=cluster.address)
    summary = sweep(spec, out, scheduler=cluster.address, resume=True, report=False)
    assert summary["computed"] == 40 - done
    final = read_results(out)
    again = dict(zip(final.column("index").to_pylist(), final.column("seconds").to_pylist()))
    assert all(again[i] == s for i, s in seconds.items()), "a finished run was computed again"
    same_results(read_results(serial_out), final)
    # a changed spec is not resumed into the same folder
    spec.write_text(spec.read_text().replace("seed = 11", "seed = 12"))
    with pytest.raises(SpecError, match="another spec"):
        sweep(spec, out, scheduler=cluster.address, resume=True)


def test_engine_reports_failing_items_and_keeps_going(cluster):
    with Engine(cluster.address) as engine:
        out = dict(engine.map(math.sqrt, [4.0, -1.0, 9.0], errors="return"))
        assert out[0] == 2.0 and out[2] == 3.0 and isinstance(out[1], TaskFailed)
        assert "math domain error" in str(out[1])
        with pytest.raises(ValueError):
            dict(engine.map(math.sqrt, [4.0, -1.0]))
    assert dict(map_as_completed(abs, [-1, 2, -3], workers=0)) == {0: 1, 1: 2, 2: 3}


# -- bad specs ---------------------------------------------------------------------------------------

BAD_SPECS = [
    ("[grid]\n\"amplifier.Rx\" = [1.0, 2.0]\n", "amplifier.Rx"),
    ("[grid]\n\"hysteresis.weights[12]\" = [0.1]\n", "hysteresis.weights[12]"),
    ("[grid]\n\"amplifier.R\" = [400.0, -1.0]\n", "amplifier.R"),
    ("[grid]\n\"experiment.freq\" = { start = 0, stop = 10, num = 3, log = true }\n", "experiment.freq"),
    ("[grid]\n\"experiment.mode\" = [\"ff\", \"pid\"]\n", "experiment.mode"),
    ("[random]\n\"amplifier.R\" = { gauss = [1, 2] }\n", "amplifier.R"),
    ("[random]\n\"amplifier.R\" = { normal = [400.0, 20.0], unit = \"kohm\" }\n", "kohm"),
    ("[sweep]\ncount = 3\n", "sweep.count"),
    ("[sweep]\ncount = 0\n[random]\n\"amplifier.R\" = { uniform = [1, 2] }\n", "sweep.count"),
    ("[experiment]\nfrequency = 10.0\n", "experiment.frequency"),
    ("[experiment]\nperiods = 3\nstop_time = 0.1\n", "experiment.periods"),
    ("[experiment]\nfreq = { value = 10.0, unit = \"kHz\" }\n", "experiment.freq"),
    ("[metrics]\ntolerance = { metric = \"rms\", max = 1 }\n", "metrics.tolerance.metric"),
    ("[sweep]\nmodel = \"nowhere.toml\"\n", "sweep.model"),
    ("[sweeps]\nseed = 1\n", "[sweeps]"),
    ("[grid]\n\"hysteresis.weights\" = [0.1, 0.2]\n", "hysteresis.weights"),
    ("[grid]\n\"amplifier.R\" = [400.0]\n[random]\n\"amplifier.R\" = { uniform = [1, 2] }\n", "varied twice"),
    ("not toml [", "not valid TOML"),
]


@pytest.mark.parametrize("text, words", BAD_SPECS, ids=[w for _, w in BAD_SPECS])
def test_bad_spec_names_the_key(tmp_path, capsys, text, words):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    code = main(["sweep", str(path), "--out", str(tmp_path / "out"), "--workers", "0"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and words in err and "bad.toml" in err, err
    assert not (tmp_path / "out").exists()


def test_bad_spec_exits_2_from_the_command_line(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[grid]\n\"amplifier.R\" = [\"big\"]\n")
    r = subprocess.run([sys.executable, "-m", "piezo_fmu", "sweep", str(path), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 2
    assert "amplifier.R" in r.stderr and "Traceback" not in r.stderr


# -- the parts ---------------------------------------------------------------------------------------

def test_values_depend_on_the_index_only(tmp_path):
    spec = loads_spec(SPEC.format(kernels="numba"))
    assert spec.n_runs == 40 and spec.n_grid == 10
    a = [run_values(spec, i) for i in range(40)]
    assert [run_values(spec, i) for i in reversed(range(40))][::-1] == a
    # unit j is the same at every grid point; the grid's last axis varies fastest
    assert a[3]["amplifier.R"] == a[4 + 3]["amplifier.R"] == a[36 + 3]["amplifier.R"]
    assert a[0]["experiment.freq"] == 40.0 and a[4]["experiment.freq"] == pytest.approx(40.0 * 4 ** 0.25)
    assert a[0]["experiment.mode"] == "ff" and a[20]["experiment.mode"] == "ff+fb"
    # another key drawn, or another count, leaves a key's values alone
    other = loads_spec(SPEC.format(kernels="numba").replace('"compensator.Kp"', '"compensator.Ki"')
                       .replace("[0.1, 0.3]", "[1000.0, 5000.0]").replace("count = 4", "count = 7"))
    b = [run_values(other, 7 * (i // 4) + i % 4) for i in range(40)]
    assert [x["amplifier.R"] for x in a] == [x["amplifier.R"] for x in b]
    # +-20 % around the base weights, each element on its own
    w0 = load_model()["hysteresis"]["weights"]
    w = np.array([[x[f"hysteresis.weights[{k + 1}]"] for k in range(9)] for x in a])
    assert np.all(np.abs(w / w0 - 1) <= 0.2) and np.std(w / w0) > 0.05
    names = [c for c, _ in columns(spec)]
    assert names[:2] == ["experiment.mode", "experiment.freq"] and "hysteresis.weights[9]" in names


def test_with_values_overrides_and_validates():
    m = load_model()
    n = with_values(m, {"hysteresis.weights[3]": 0.5, "amplifier.R": 410.0, "compensator.mode": "ff"})
    assert n["amplifier"]["R"] == 410.0 and n["hysteresis"]["weights"][2] == 0.5
    assert n["compensator"]["mode"] == "ff" and m["amplifier"]["R"] == 400.0        # a copy
    for bad, words in (({"amplifier.R": -1.0}, "amplifier.R"), ({"hysteresis.weights[0]": 1.0}, "1-based"),
                       ({"hysteresis.weights[10]": 1.0}, "out of range"), ({"amplifier.R[1]": 1.0}, "single"),
                       ({"hysteresis.weights[1]": -5.0}, "hysteresis.weights"), ({"foo.x": 1}, "foo")):
        with pytest.raises(ModelError, match=words.replace("[", r"\[")):
            with_values(m, bad)


def test_metrics_of_a_step_and_an_oscillating_command():
    t = np.linspace(0.0, 0.1, 1001)
    x_ref = np.full_like(t, 2.0)
    x = 2.0 * (1 - np.exp(-t / 0.005) * np.cos(2 * np.pi * 100 * t))      # overshoots, settles
    x[0] = 0.0
    c = compute(t, x_ref, x, uc=np.full_like(t, 3.0), uc_limits=(-2.0, 15.0))
    assert c["stroke_um"] == pytest.approx(x.max())
    assert c["overshoot_pct"] == pytest.approx(100 * (x.max() - 2.0) / 2.0)
    inside = np.abs(x - 2.0) <= 0.04
    last_out = np.flatnonzero(~inside)[-1]
    assert c["settling_time_s"] == pytest.approx(t[last_out + 1])
    assert c["rms_um"] == pytest.approx(np.sqrt(np.mean((x - 2) ** 2)))
    assert c["stable"] is True
    rails = np.where(np.arange(t.size) % 4 < 2, -2.0, 15.0)                 # a command railing at 2.5 kHz
    assert compute(t, x_ref, x, uc=rails, uc_limits=(-2.0, 15.0))["stable"] is False
    grow = x_ref + 1e-3 * np.exp(t / 0.01)                                  # a growing error
    assert compute(t, x_ref, grow)["stable"] is False
    assert compute(t, x_ref, np.full_like(t, np.nan))["stable"] is False


def test_failing_runs_are_rows(tmp_path):
    text = SPEC.format(kernels="python").replace('"amplifier.R" = { normal = [400.0, 20.0], unit = "ohm" }',
                                                 '"amplifier.R" = { uniform = [-400.0, 400.0] }')
    spec = loads_spec(text.replace("count = 4", "count = 3"))
    rows = [run_one(spec, i) for i in range(3)]
    bad = [r for r in rows if r["amplifier.R"] <= 0]
    assert bad and all(r["status"] == "error" and "amplifier.R" in r["error"] for r in bad)
    assert all(math.isnan(r["rms_um"]) and r["stable"] is None for r in bad)


def test_cosim_engine_runs_the_fmus(built_fmus):
    fmu_dir = built_fmus["Actuator"].parent
    text = f"""
[experiment]
engine = "cosim"
kernels = "python"
freq = 50.0
periods = 1
samples_per_period = 200
fmu_dir = "{fmu_dir}"
[grid]
"compensator.Kp" = [0.1, 0.3]
"""
    spec = loads_spec(text)
    rows = [run_one(spec, i) for i in range(2)]
    assert all(r["status"] == "ok" for r in rows), rows
    # the FMUs shipped as bytes (no fmu_dir) give the same row
    nodir = loads_spec(text.replace(f'fmu_dir = "{fmu_dir}"', ""))
    fmus = {n: p.read_bytes() for n, p in built_fmus.items()}
    again = run_one(nodir, 1, fmus)
    assert again["rms_um"] == rows[1]["rms_um"]
    # against the monolithic model sampled like the co-simulation (README: agree within 0.3 %)
    mono = loads_spec(text.replace('engine = "cosim"', "control_step = 1e-4")
                      .replace(f'fmu_dir = "{fmu_dir}"', ""))
    m = run_one(mono, 1)
    assert m["stroke_um"] == pytest.approx(rows[1]["stroke_um"], rel=0.01)


def test_linked_grid_axis_varies_keys_together():
    text = """
[grid]
"experiment.amplitude, experiment.offset" = [[15.0, 15.0], [30.0, 30.0], [45.0, 45.0]]
"experiment.freq" = [10.0, 20.0]
"""
    spec = loads_spec(text)
    assert spec.n_runs == 6
    v = [run_values(spec, i) for i in range(6)]
    assert all(x["experiment.amplitude"] == x["experiment.offset"] for x in v)
    assert [x["experiment.amplitude"] for x in v] == [15.0, 15.0, 30.0, 30.0, 45.0, 45.0]
    assert [c for c, _ in columns(spec)] == ["experiment.amplitude", "experiment.offset", "experiment.freq"]
    with pytest.raises(SpecError, match="one value per key"):
        loads_spec(text.replace("[45.0, 45.0]", "[45.0]"))
    with pytest.raises(SpecError, match="amplifier.R"):
        loads_spec('[grid]\n"amplifier.R, experiment.freq" = [[-1.0, 10.0]]\n')


def test_the_local_cluster_runs_without_the_profiler_and_with_slow_housekeeping():
    # the engine's own cluster: dask's 10 ms stack sampler and 20 ms watchdog cost the tasks CPU
    import dask

    from piezo_fmu.parallel import LOCAL_CLUSTER_CONFIG, Engine

    def settings():
        import dask
        return {k: dask.config.get(k) for k in LOCAL_CLUSTER_CONFIG}

    def trim():
        import os
        return os.environ.get("MALLOC_TRIM_THRESHOLD_")

    with Engine(workers=1) as engine:
        on_workers = list(engine.client.run(settings).values())
        trims = list(engine.client.run(trim).values())
    assert on_workers and all(s == LOCAL_CLUSTER_CONFIG for s in on_workers)
    # dask's 65536 turns off glibc's adaptive mmap threshold (diagnose 2x slower): not in our workers
    assert trims == [None]
    assert dask.config.get("distributed.worker.profile.enabled") is True    # this process untouched
