"""The package as a user gets it from an index: a wheel installed into a fresh virtual environment
outside the repository, used from an empty folder.

The editable install of the test suite would hide everything a checkout provides (the model file,
the FMU sources, the builder beside the package); this test does not: the wheel is built from the
source tree, installed with its dependencies (pip's cache makes that quick after the first time),
and run with the repository neither on ``sys.path`` nor the current folder.
"""
from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


def _run(cmd, cwd, env, timeout=900):
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout, check=False)
    assert proc.returncode == 0, (f"{' '.join(map(str, cmd))} exited {proc.returncode}\n"
                                  f"stdout: {proc.stdout[-2000:]}\nstderr: {proc.stderr[-4000:]}")
    return proc


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """``(venv bin folder, clean environment, wheel path)`` with the wheel installed."""
    base = tmp_path_factory.mktemp("wheel")
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP")}
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", base / "dist", ROOT], base, env)
    wheel = next((base / "dist").glob("piezo_fmu-*.whl"))
    _run([sys.executable, "-m", "venv", base / "venv"], base, env)
    bin_dir = base / "venv" / "bin"
    env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
    env["VIRTUAL_ENV"] = str(base / "venv")
    _run([bin_dir / "python", "-m", "pip", "install", "-q", "--prefer-binary", wheel], base, env)
    return bin_dir, env, wheel


def test_wheel_carries_model_file_fmu_sources_and_runtime(installed):
    _, _, wheel = installed
    names = set(zipfile.ZipFile(wheel).namelist())
    for need in ("piezo_fmu/model_files/paper.toml", "piezo_fmu/fmu_src/Actuator.py",
                 "piezo_fmu/fmu_src/Sensor.py", "piezo_fmu/fmu_src/Compensator.py",
                 "piezo_fmu/fmu_src/slavebase.py", "piezo_fmu/builder/build.py", "piezo_fmu/py.typed"):
        assert need in names
    assert not any(n.endswith(".fmu") for n in names)


def test_installed_wheel_runs_the_main_job_from_an_empty_folder(installed, tmp_path):
    bin_dir, env, _ = installed
    work = tmp_path / "empty"
    work.mkdir()
    where = _run([bin_dir / "python", "-c", "import piezo_fmu; print(piezo_fmu.__file__)"], work, env)
    site = Path(where.stdout.strip()).parent
    assert ROOT not in site.parents and "site-packages" in site.parts

    _run([bin_dir / "piezo-fmu", "demo", "--quiet"], work, env)
    assert (work / "demo-out" / "demo.json").is_file()
    assert {p.name for p in (work / "models").iterdir()} >= {"Actuator.fmu", "Sensor.fmu", "Compensator.fmu",
                                                            "PiezoSystem.ssp"}

    _run([bin_dir / "piezo-fmu", "build", "--out-dir", "fmus", "--quiet"], work, env)
    _run([bin_dir / "fmpy", "simulate", "fmus/Sensor.fmu"], work, env)              # exits 0
    assert (work / "fmus" / "Sensor.fmu").is_file()
    # nothing was written into the installed package
    assert not list(site.rglob("*.fmu")) and not list(site.rglob("*.ssp"))

    # python -m piezo_fmu is the same command line
    out = _run([bin_dir / "python", "-m", "piezo_fmu", "--version"], work, env)
    assert out.stdout.startswith("piezo-fmu ")
