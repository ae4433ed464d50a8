"""Long runs as a user expects them: a recording step that suits the run, Parquet, progress with an
ETA, and output paths that cannot be written refused before any work (exit 2, one line)."""
from __future__ import annotations

import io
import math
import time

import numpy as np
import pytest

from piezo_fmu.cli import main
from piezo_fmu.progress import Progress, format_seconds
from piezo_fmu.results import CSV_HEADER, RunWriter, write_run
from piezo_fmu.simulate import COLUMNS, UNITS


class _Tty(io.StringIO):
    def isatty(self):
        return True


# -- progress ------------------------------------------------------------------------------------

def test_progress_lines_in_a_log_carry_percent_and_eta():
    out = io.StringIO()
    bar = Progress("run", stream=out, log_interval=0.0)
    bar(0.0, "stage one")
    time.sleep(0.02)
    bar(0.5)
    bar(1.0)
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("run:   0.0 %") and lines[0].endswith("stage one")
    assert "50.0 %" in lines[1] and "ETA" in lines[1] and "ETA ?" not in lines[1]
    assert lines[-1].startswith("run: done in ")
    assert "\r" not in out.getvalue()


def test_progress_eta_counts_from_the_current_stage():
    bar = Progress("run", stream=io.StringIO())
    bar.t0 -= 100.0                              # 100 s of compiling before the work started
    bar(0.0, "working")
    bar._stage_start = (bar._stage_start[0] - 10.0, 0.0)   # 10 s into the work
    assert bar.eta(0.5, time.perf_counter()) == pytest.approx(10.0, rel=0.01)
    assert bar.eta(0.005, time.perf_counter()) == math.inf


def test_progress_on_a_terminal_redraws_one_line_and_quiet_prints_nothing():
    tty = _Tty()
    bar = Progress("sim", stream=tty, interval=0.0)
    bar(0.25)
    bar(0.75)
    bar(1.0)
    text = tty.getvalue()
    assert text.count("\r") == 3 and text.count("\n") == 1 and "[######" in text
    quiet = io.StringIO()
    q = Progress("sim", quiet=True, stream=quiet)
    q(0.5, "x")
    q.note("y")
    assert quiet.getvalue() == ""


def test_format_seconds():
    assert format_seconds(12.34) == "12.3 s"
    assert format_seconds(245) == "4 min 05 s"
    assert format_seconds(3720) == "1 h 02 min"
    assert format_seconds(math.inf) == "?"


# -- writing runs ----------------------------------------------------------------------------------

def _rows(n, t0=0.0):
    t = t0 + 1e-4 * np.arange(n)
    return np.column_stack([t] + [np.sin(t * (k + 1)) + k for k in range(len(COLUMNS) - 1)])


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_run_writer_streams_chunks_exactly(tmp_path, suffix):
    path = tmp_path / f"run{suffix}"
    a, b = _rows(1000), _rows(500, t0=0.1)
    with RunWriter(path) as out:
        out(a)
        assert not path.exists()                 # appears only when the run ends
        out(b)
    whole = np.vstack([a, b])
    if suffix == ".csv":
        text = path.read_text()
        assert text.startswith(CSV_HEADER)
        back = np.loadtxt(path, delimiter=",", comments="#", skiprows=2)
    else:
        import pyarrow.parquet as pq

        table = pq.read_table(path)
        assert table.column_names == list(COLUMNS)
        meta = {k.decode(): v.decode() for k, v in table.schema.metadata.items()}
        assert all(meta[f"unit:{c}"] == UNITS[c] for c in COLUMNS)
        back = np.column_stack([table[c].to_numpy() for c in COLUMNS])
    np.testing.assert_array_equal(back, whole)   # shortest round-trip text: exact
    e = whole[:, 2] - whole[:, 1]
    assert out.summary["rms_um"] == pytest.approx(math.sqrt(np.mean(e * e)), rel=1e-12)
    assert out.summary["max_um"] == pytest.approx(np.max(np.abs(e)), rel=1e-12)


def test_run_writer_leaves_nothing_when_the_run_fails(tmp_path):
    path = tmp_path / "run.parquet"
    with pytest.raises(RuntimeError), RunWriter(path) as out:
        out(_rows(10))
        raise RuntimeError("the run broke")
    assert list(tmp_path.iterdir()) == []


def test_run_writer_refuses_unknown_formats_and_existing_files(tmp_path):
    from piezo_fmu.errors import UserError

    with pytest.raises(UserError, match=r"run\.txt: unknown output format"):
        RunWriter(tmp_path / "run.txt")
    write_run(tmp_path / "a.csv", {c: np.zeros(3) for c in COLUMNS})
    with pytest.raises(UserError, match="exists"):
        RunWriter(tmp_path / "a.csv")


# -- the command line --------------------------------------------------------------------------------

def test_simulate_records_every_1e4_s_by_default_and_writes_parquet(tmp_path, capsys):
    import pyarrow.parquet as pq

    out = tmp_path / "run.parquet"
    assert main(["simulate", "--stop-time", "0.05", "--out", str(out), "--engine", "python"]) == 0
    err = capsys.readouterr().err
    assert "recorded every 0.0001 s" in err
    t = pq.read_table(out)["time"].to_numpy()
    assert len(t) == 501 and np.allclose(np.diff(t), 1e-4)
    # --record-step still chooses
    out2 = tmp_path / "fine.csv"
    assert main(["simulate", "--stop-time", "0.01", "--record-step", "1e-5", "--out", str(out2), "--quiet",
                 "--engine", "python"]) == 0
    assert len(np.loadtxt(out2, delimiter=",", comments="#", skiprows=2)) == 1001


def test_simulate_help_says_the_default_recording_step(capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "default: 0.0001 s" in text and ".parquet" in text


UNWRITABLE = "/proc/piezo-fmu-test/x"


@pytest.mark.parametrize("argv", [
    ["simulate", "--stop-time", "0.01", "--out", UNWRITABLE + ".csv"],
    ["simulate", "--stop-time", "0.01", "--plot", UNWRITABLE + ".png"],
    ["reproduce", "--out", UNWRITABLE],
    ["identify", "--out", UNWRITABLE + ".toml"],
    ["build", "--out-dir", UNWRITABLE],
    ["demo", "--out", UNWRITABLE],
    ["bench", "--size", "tiny", "--json", UNWRITABLE + ".json"],
    ["diagnose", "tests/data/dbo/piezo_1hz_sine.csv", "--out", UNWRITABLE],
    ["simulate", "--stop-time", "0.01", "--out", "/proc/version"],
], ids=lambda a: a[0] + ("-" + a[-2].lstrip("-") if len(a) > 2 else ""))
def test_unwritable_outputs_exit_2_with_one_line_before_any_work(argv, capsys, monkeypatch):
    # any work would call these; they must not be reached
    import sys

    import piezo_fmu.builder.build as build

    sim = sys.modules["piezo_fmu.simulate"]      # the package's `simulate` attribute is the function

    def no_work(*a, **k):
        raise AssertionError("work started before the output path was checked")
    monkeypatch.setattr(sim, "simulate", no_work)
    monkeypatch.setattr(build, "build_all", no_work)
    monkeypatch.chdir(__import__("pathlib").Path(__file__).resolve().parents[1])
    t0 = time.perf_counter()
    code = main(argv)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith(f"piezo-fmu {argv[0]}: error: ")
    assert "/proc/" in lines[0] and "Traceback" not in err
    assert time.perf_counter() - t0 < 5.0
