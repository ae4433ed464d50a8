"""Bad input gets one clear line and exit status 2; nothing is lost or half-written (issue 6)."""
import subprocess
import sys

import pytest

from piezo_fmu.cli import main
from piezo_fmu.model import DEFAULT_MODEL

GOOD = "time,u_ref\n0,0\n0.01,10\n0.02,20\n0.03,10\n"

# (name, file content as bytes or None for a missing file, words the message must contain)
BAD_INPUTS = [
    ("missing", None, ["file not found"]),
    ("empty", b"", ["empty"]),
    ("binary", b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00", ["binary"]),
    ("semicolons", b"time;u_ref\n0;0\n0.01;1\n", ["one column", "semicolon"]),
    ("missing column", b"time,volts\n0,0\n0.01,1\n", ["x_ref, u_ref, u"]),
    ("duplicate column", b"time,u_ref,u_ref\n0,0,0\n0.01,1,1\n", ["duplicate", "u_ref"]),
    ("non-numeric", b"time,u_ref\n0,0\n0.01,abc\n", ["row 3", "column u_ref", "'abc'"]),
    ("nan", b"time,u_ref\n0,0\n0.01,nan\n", ["row 3", "not finite"]),
    ("inf", b"time,u_ref\n0,inf\n0.01,1\n", ["row 2", "not finite"]),
    ("time backwards", b"time,u_ref\n0,0\n0.02,1\n0.01,2\n", ["row 4", "does not increase"]),
    ("ragged", b"time,u_ref\n0,0\n0.01\n", ["row 3", "cells"]),
    ("too short", b"time,u_ref\n0,0\n", ["1 data row", "at least 2"]),
]


def run_cli(args, capsys):
    code = main(args)
    captured = capsys.readouterr()
    return code, captured.err


@pytest.mark.parametrize("name, content, words", BAD_INPUTS, ids=[b[0] for b in BAD_INPUTS])
def test_simulate_reference_file_errors(tmp_path, capsys, name, content, words):
    path = tmp_path / "ref.csv"
    if content is not None:
        path.write_bytes(content)
    out = tmp_path / "run.csv"
    code, err = run_cli(["simulate", "--signal", "csv", "--input", str(path), "--stop-time", "0.02",
                         "--out", str(out), "--quiet"], capsys)
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert str(path) in lines[0]
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert "Traceback" not in err
    assert not out.exists()


def test_simulate_good_reference_file(tmp_path, capsys):
    path = tmp_path / "ref.csv"
    path.write_text(GOOD)
    out = tmp_path / "run.csv"
    code, err = run_cli(["simulate", "--signal", "csv", "--input", str(path), "--stop-time", "0.03",
                         "--record-step", "1e-3", "--out", str(out)], capsys)
    assert code == 0, err
    header = out.read_text().splitlines()[1]
    assert header.split(",")[:5] == ["time", "x_ref", "x", "us", "uc"]


def test_recordings_must_be_uniform_when_asked(tmp_path):
    from piezo_fmu.errors import UserError
    from piezo_fmu.recording import read_csv_table

    path = tmp_path / "rec.csv"
    path.write_text("time,u,x\n0,0,0\n0.01,1,1\n0.02,1,1\n0.035,1,1\n")
    with pytest.raises(UserError, match=r"row 5: time step 0.015 s differs from the sampling interval"):
        read_csv_table(path, required=("time", "u"), one_of=("x",), uniform=True)


def test_units_in_the_header_are_converted(tmp_path):
    """``time [ms]``, ``u (V)``, ``disp [nm]`` read as s, V and um; ``--columns`` names a column with or
    without its unit; a column given ``--scale`` keeps the user's factor alone."""
    from piezo_fmu.recording import read_csv_table

    plain, units = tmp_path / "plain.csv", tmp_path / "units.csv"
    plain.write_text("time,u,x\n0,0,0\n0.001,1.5,250\n0.002,3,500\n")
    units.write_text("time [ms],u (V),disp [nm]\n0,0,0\n1,1.5,250000\n2,3,500000\n")
    want = read_csv_table(plain, required=("time", "u"), one_of=("x",), uniform=True)
    for name in ("disp", "disp [nm]"):
        got = read_csv_table(units, required=("time", "u"), one_of=("x",), columns={"x": name}, uniform=True)
        for c in ("time", "u", "x"):
            assert got[c] == pytest.approx(want[c], rel=1e-12), (name, c)
        assert got.converted == {"time": ("ms", 1e-3), "x": ("nm", 1e-3)}
    own = read_csv_table(units, required=("time", "u"), one_of=("x",), columns={"x": "disp"},
                         scale={"x": 2.0})
    assert own["x"] == pytest.approx([0, 500000, 1000000])
    paren = tmp_path / "paren.csv"
    paren.write_text("time,u,x(t)\n0,0,0\n0.001,1.5,250\n0.002,3,500\n")
    got = read_csv_table(paren, required=("time", "u"), one_of=("x",), columns={"x": "x(t)"})
    assert got["x"] == pytest.approx(want["x"]) and got.converted == {}
    micro = tmp_path / "micro.csv"
    micro.write_text("time [\u00b5s],u [mV],x [um]\n0,0,0\n1000,1500,250\n")
    got = read_csv_table(micro, required=("time", "u"), one_of=("x",))
    assert got["time"] == pytest.approx([0, 1e-3]) and got["u"] == pytest.approx([0, 1.5])
    assert got["x"] == pytest.approx([0, 250]) and "x" not in got.converted


def test_a_unit_that_cannot_be_converted_is_bad_input(tmp_path, capsys):
    rec = tmp_path / "rec.csv"
    rows = "".join(f"{k * 1e-3},{k % 7},{k % 5}\n" for k in range(60))
    rec.write_text("time [s],u [V],x [furlong]\n" + rows)
    code, err = run_cli(["diagnose", str(rec), "--out", str(tmp_path / "d"), "--quiet"], capsys)
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "'furlong' is not a displacement unit" in lines[0], err
    assert "--scale x=FACTOR" in lines[0] and str(rec) in lines[0]
    assert not (tmp_path / "d" / "diagnosis.json").exists()


@pytest.mark.parametrize("rate, words", [("0", "positive number, got 0"), ("-8000", "positive number, got -8000"),
                                         ("fast", "number, got 'fast'"), ("inf", "positive number, got inf")])
def test_a_replay_rate_that_is_not_a_positive_rate_is_bad_input(tmp_path, capsys, rate, words):
    rec = tmp_path / "rec.csv"
    rec.write_text("time,u,x\n" + "".join(f"{k * 1e-3},{k % 7},{k % 5}\n" for k in range(60)))
    with pytest.raises(SystemExit) as exc:
        main(["diagnose", str(rec), "--out", str(tmp_path / "d"), "--replay-rate", rate, "--quiet"])
    assert exc.value.code == 2
    assert f"--replay-rate must be a {words}" in capsys.readouterr().err
    assert not (tmp_path / "d" / "diagnosis.json").exists()


@pytest.mark.parametrize("command", [
    ["simulate", "--stop-time", "0.01"],
    ["reproduce", "--out", "{tmp}/r"],
    ["identify", "--out", "{tmp}/m.toml"],
])
@pytest.mark.parametrize("problem, text, words", [
    ("unknown key", "[amplifier]\nbogus = 1\n", ["amplifier.bogus"]),
    ("not toml", "this is [not toml", ["not valid TOML"]),
    ("negative mass", None, ["mechanics.m", "> 0"]),
])
def test_every_command_rejects_a_bad_model_file(tmp_path, capsys, command, problem, text, words):
    model = tmp_path / "bad.toml"
    if text is None:
        text = DEFAULT_MODEL.read_text().replace("m = { value = 0.021579", "m = { value = -0.021579")
    elif problem == "unknown key":
        text = DEFAULT_MODEL.read_text().replace("[amplifier]\n", text)
    model.write_text(text)
    args = [a.replace("{tmp}", str(tmp_path)) for a in command] + ["--model", str(model), "--quiet"]
    code, err = run_cli(args, capsys)
    assert code == 2
    assert str(model) in err and all(w in err for w in words), err
    assert len(err.strip().splitlines()) == 1


def test_bad_option_values_exit_2(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--freq", "-3"])
    assert exc.value.code == 2
    assert "--freq must be a positive number" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--mode", "turbo"])
    assert exc.value.code == 2
    code = main(["simulate", "--control-step", "2.5e-5", "--stop-time", "0.01", "--quiet"])
    assert code == 2
    assert "--control-step: 2.5e-05 s is not a whole number of steps of 1e-05 s" in capsys.readouterr().err


def test_existing_output_is_not_overwritten_without_force(tmp_path, capsys):
    out = tmp_path / "run.csv"
    out.write_text("precious")
    code, err = run_cli(["simulate", "--stop-time", "0.01", "--out", str(out), "--quiet"], capsys)
    assert code == 2 and "--force" in err
    assert out.read_text() == "precious"
    code, err = run_cli(["simulate", "--stop-time", "0.01", "--out", str(out), "--force", "--quiet"],
                        capsys)
    assert code == 0 and out.read_text().startswith("# units")


def test_exception_half_way_leaves_the_old_file(tmp_path, monkeypatch, capsys):
    """A run that fails after writing part of its output leaves the previous file untouched."""
    import importlib

    sim = importlib.import_module("piezo_fmu.simulate")   # the package exports a function of that name

    out = tmp_path / "run.csv"
    out.write_text("previous good result")
    calls = {"n": 0}
    real = sim.closed_loop

    def failing(*args):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(*args)

    monkeypatch.setattr(sim, "closed_loop", failing)
    code = main(["simulate", "--stop-time", "1.2", "--engine", "python", "--out", str(out),
                 "--force", "--quiet"] + ["--record-step", "1e-5"])
    assert code == 130
    assert out.read_text() == "previous good result"
    assert calls["n"] == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.csv"]


def test_ctrl_c_in_a_real_process_leaves_no_partial_file(tmp_path):
    """SIGINT to a running `piezo-fmu simulate`: exit status 130, no output file, no temp file."""
    import signal
    import time

    out = tmp_path / "long.csv"
    proc = subprocess.Popen([sys.executable, "-m", "piezo_fmu", "simulate", "--stop-time", "60",
                             "--engine", "python", "--out", str(out), "--quiet"],
                            stderr=subprocess.PIPE, text=True,
                            # a shell's background job inherits SIGINT ignored, and Python then never
                            # turns it into KeyboardInterrupt: give the child a terminal's default
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 60
    while time.time() < deadline and not any(tmp_path.iterdir()):
        time.sleep(0.05)
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted" in err
    assert list(tmp_path.iterdir()) == []


def test_help_explains_every_command(capsys):
    for cmd in ("simulate", "reproduce", "identify", "validate"):
        with pytest.raises(SystemExit) as exc:
            main([cmd, "--help"])
        assert exc.value.code == 0
        assert len(capsys.readouterr().out) > 200


def test_debug_shows_the_traceback(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "piezo_fmu", "--debug", "simulate", "--model",
                           str(tmp_path / "none.toml")], capture_output=True, text=True)
    assert proc.returncode != 0 and "Traceback" in proc.stderr


def test_outputs_get_ordinary_permissions(tmp_path):
    import os

    from piezo_fmu.io import write_text

    write_text(tmp_path / "a.txt", "x")
    mask = os.umask(0)
    os.umask(mask)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o666 & ~mask


def test_a_reader_that_goes_away_ends_the_command_quietly():
    # `piezo-fmu ... | head`: the output's reader closes the pipe before the command writes; the
    # command stops with the shell's SIGPIPE status (141) and no traceback
    proc = subprocess.Popen([sys.executable, "-m", "piezo_fmu", "validate", str(DEFAULT_MODEL)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait() == 141, err
    assert "Traceback" not in err and "BrokenPipe" not in err


@pytest.mark.parametrize("args, words", [
    (["--generator", "rig", "--cases", "rig-999"], ["no rig case named rig-999"]),
    (["--cases", "rig-017,foo-1"], ["foo-1", "no case of rig or synth"]),
    (["--generator", "synth", "--cases", "rig-017"], ["rig-017", "no case of synth"]),
    (["--draw", "-1"], ["--draw -1", "positive"]),
    (["--replay-rate", "0"], ["--replay-rate 0", "positive"]),
    (["--replay-rate", "inf"], ["--replay-rate inf", "positive"]),
    (["--generator", "rig", "--noise-draw", "-2"], ["--noise-draw -2", "positive"]),
    (["--noise-draw", "1"], ["--noise-draw", "rig's", "--generator rig"]),
])
def test_the_evaluation_names_a_case_it_does_not_have(capsys, args, words):
    # a misspelt case name ran nothing and reported an empty table; now it is bad input
    from piezo_fmu.diagnose.evaluate import main as evaluate

    with pytest.raises(SystemExit) as ex:
        evaluate(args + ["--jobs", "0"])
    assert ex.value.code == 2
    err = capsys.readouterr().err
    assert all(w in err for w in words), err


def test_the_evaluation_draws_afresh_and_writes_each_case_log(tmp_path, capsys):
    # --draw 1: the rig's set on other seeds (rig-d1-111: a clean 250 Hz record of 1810 samples);
    # --logs: the diagnosis's every screening, fit and decision, for the post-mortem
    import json

    from piezo_fmu.diagnose.evaluate import main as evaluate

    logs, out = tmp_path / "logs", tmp_path / "eval.json"
    assert evaluate(["--generator", "rig", "--draw", "1", "--cases", "rig-d1-111", "--jobs", "0",
                     "--logs", str(logs), "--out", str(out)]) == 0
    res = json.loads(out.read_text())["rig"]["results"]
    assert [r["case"] for r in res] == ["rig-d1-111"] and res[0]["group"] == "clean"
    text = (logs / "rig-d1-111.log").read_text()
    assert "recalibrating the nominal model" in text and "round 1: screening gains" in text
    with pytest.raises(SystemExit) as ex:          # a case of draw 1 is no case of the established set
        evaluate(["--generator", "rig", "--cases", "rig-d1-111", "--jobs", "0"])
    assert ex.value.code == 2
