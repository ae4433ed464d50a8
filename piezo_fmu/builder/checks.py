"""Checks of a built FMU: its interface against :mod:`piezo_fmu.connections` and the model, and a
default-experiment run with fmpy in a process that cannot import ``piezo_fmu``."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from .errors import BuildError

__all__ = ["FMU_SECTIONS", "check_interface", "smoke_run"]

# model sections of each FMU (checked after the build: every key must be a parameter)
FMU_SECTIONS = {
    "Actuator": {"amplifier": None, "hysteresis": None, "creep": None, "mechanics": None,
                 "resonance": None, "drift": None, "simulation": ("actuator_max_step", "stroke_path")},
    "Sensor": {"sensor": None},
    "Compensator": {"compensator": None, "compensator.hysteresis": None, "compensator.dynamics": None},
    "PassThrough": {},
}


def check_interface(name: str, fmu: Path, payload: dict) -> list:
    """Problems of the built FMU's interface against piezo_fmu.connections and the model."""
    from fmpy import read_model_description

    from ..connections import COMPONENTS

    md = read_model_description(str(fmu))
    by_name = {v.name: v for v in md.modelVariables}
    problems = []
    for port in COMPONENTS.get(name, ()):
        v = by_name.get(port.name)
        if v is None:
            problems.append(f"missing {port.causality} {port.name!r} (piezo_fmu.connections)")
            continue
        for attr, want in (("causality", port.causality), ("unit", port.unit), ("type", "Real"),
                           ("description", port.description)):
            if getattr(v, attr) != want:
                problems.append(f"{port.name}: {attr} {getattr(v, attr)!r}, connections.py says {want!r}")
    ports = {p.name for p in COMPONENTS.get(name, ())}
    extra = [v.name for v in md.modelVariables if v.causality in ("input", "output") and v.name not in ports]
    if name in COMPONENTS and extra:
        problems.append(f"inputs/outputs not declared in piezo_fmu.connections: {extra}")
    sections = payload["sections"]
    for sec, keys in FMU_SECTIONS[name].items():
        for key in (keys if keys is not None else payload["schema"][sec]):
            value = sections[sec][key]
            wanted = ([f"{sec}.{key}[{i}]" for i in range(1, len(value) + 1)] if isinstance(value, list)
                      else [f"{sec}.{key}"])
            for w in wanted:
                v = by_name.get(w)
                if v is None or v.causality != "parameter":
                    problems.append(f"model parameter {w!r} is not a parameter of the FMU")
    return problems


_SMOKE = r'''
import json, math, sys
sys.modules["piezo_fmu"] = None          # the FMUs must not need the project package
from fmpy import simulate_fmu
out = {}
for path in sys.argv[1:]:
    r = simulate_fmu(path)
    cols = r.dtype.names[1:]
    bad = [c for c in cols if not all(math.isfinite(float(v)) for v in r[c])]
    out[path] = {"rows": len(r), "bad": bad, "last": {c: float(r[c][-1]) for c in cols}}
print("@@SMOKE@@" + json.dumps(out))
'''


def smoke_run(paths) -> dict:
    """Default-experiment run of each FMU with fmpy, in a subprocess without piezo_fmu."""
    proc = subprocess.run([sys.executable, "-c", _SMOKE, *map(str, paths)], capture_output=True, text=True, check=False)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("@@SMOKE@@")]
    if proc.returncode != 0 or not lines:
        raise BuildError(f"default-experiment run failed (exit code {proc.returncode}):\n"
                         f"{proc.stderr.strip()[-3000:]}")
    res = json.loads(lines[-1][len("@@SMOKE@@"):])
    for path, r in res.items():
        if r["bad"] or r["rows"] < 2:
            raise BuildError(f"{Path(path).name}: default-experiment run gave non-finite {r['bad']} "
                             f"or too few rows ({r['rows']})")
    return res
