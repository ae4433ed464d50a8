"""The build: stage, pythonfmu, post-process, check; only FMUs that passed every check reach the
output folder (each replaced atomically), then the SSP of the three system FMUs."""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

from . import runtime as native
from .checks import check_interface, smoke_run
from .description import patch_model_description, rewrite_zip_member
from .errors import BuildError
from .staging import MODEL_JSON, stage

__all__ = ["DEFAULT_OUT", "FLOOR", "SSP_NAME", "SYSTEM", "BuildResult", "build_all", "build_one",
           "model_payload"]

DEFAULT_OUT = Path("models")             # relative to the current folder, never site-packages
SYSTEM = ("Actuator", "Sensor", "Compensator")
FLOOR = ("PassThrough",)
SSP_NAME = "PiezoSystem.ssp"


def model_payload(model) -> dict:
    """The model as the JSON the slaves read: sections, schema (unit/kind/check/doc), identity."""
    import pythonfmu

    from .. import __version__
    from ..model import SCHEMA

    sections = json.loads(json.dumps(model.sections, allow_nan=True))
    schema = {sec: {key: {"unit": spec.unit, "kind": spec.kind, "check": spec.check, "doc": spec.doc,
                          "choices": list(spec.choices)}
                    for key, spec in specs.items()}
              for sec, specs in SCHEMA.items()}
    canon = json.dumps(sections, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return {"format": 1, "model_name": model.name, "model_file": str(model.path),
            "hash": hashlib.sha256(canon.encode()).hexdigest()[:12],
            "pythonfmu": pythonfmu.__version__, "piezo_fmu": __version__,
            "sections": sections, "schema": schema}




_WORKER = r'''
import json, sys
from pathlib import Path
stage_dir, script, dest, pkg, cls_name = sys.argv[1:6]
sys.path.insert(0, stage_dir)
from pythonfmu.builder import FmuBuilder
fmu = FmuBuilder.build_FMU(script, dest=dest,
                           project_files=[Path(stage_dir) / pkg, Path(stage_dir) / "piezo_model.json"],
                           canGetAndSetFMUstate=True, canSerializeFMUstate=True)
mod = sys.modules[Path(script).stem]
meta = getattr(mod, cls_name)(instance_name="build", resources=stage_dir).fmu_meta()
print("@@RESULT@@" + json.dumps({"fmu": str(fmu), "meta": meta}))
'''


def run_pythonfmu(st: dict, dest: Path) -> tuple:
    proc = subprocess.run([sys.executable, "-c", _WORKER, str(st["stage_dir"]), str(st["script"]), str(dest),
                           st["package"], st["name"]],
                          cwd=st["stage_dir"], capture_output=True, text=True, check=False)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("@@RESULT@@")]
    if proc.returncode != 0 or not lines:
        raise BuildError(f"{st['name']}: pythonfmu build failed (exit code {proc.returncode}):\n"
                         f"{proc.stderr.strip()[-3000:]}")
    res = json.loads(lines[-1][len("@@RESULT@@"):])
    return Path(res["fmu"]), res["meta"]




class BuildResult(dict):
    """``{name: path of the FMU}``; ``.ssp`` is the SSP path (``None`` when skipped)."""
    ssp = None


def build_one(name: str, payload: dict, work: Path, log=print, runtime="auto") -> Path:
    """Stage, build, post-process and check one FMU in the work folder; returns its path there.

    ``runtime``: the FMU's binary. ``"auto"`` compiles the native runtime into ``work/runtime``
    (once) and falls back to pythonfmu's binary when that is impossible; a
    :class:`~piezo_fmu.builder.runtime.RuntimeBinaries` is used as it is; ``None`` keeps
    pythonfmu's binary.
    """
    t0 = time.perf_counter()
    if runtime == "auto":
        runtime = native.compile_runtime(Path(work) / "runtime", log)
    log(f"{name}: staging fmu_src/{name}.py with piezo_fmu/core and the slave base")
    st = stage(name, payload, work / "stage")
    log(f"{name}: pythonfmu build (module {st['module']}, bundle {st['package']})")
    fmu, meta = run_pythonfmu(st, work / "fmu")
    if fmu.name != f"{name}.fmu":
        raise BuildError(f"{name}: pythonfmu wrote {fmu.name}")
    with zipfile.ZipFile(fmu) as z:
        members = set(z.namelist())
        if z.read("resources/slavemodule.txt").decode().strip() != st["module"]:
            raise BuildError(f"{name}: slavemodule.txt does not name the staged module")
        for need in (f"resources/{st['package']}/core/units.py", f"resources/{st['package']}/slavebase.py",
                     f"resources/{MODEL_JSON}", f"resources/{st['module']}.py"):
            if need not in members:
                raise BuildError(f"{name}: {need} missing from the FMU")
        xml = z.read("modelDescription.xml")
    log(f"{name}: post-processing modelDescription.xml ({len(meta['variables'])} variables)")
    from .. import __version__
    version = (f"piezo-fmu {__version__}; core+slavebase {st['package'].rsplit('_', 1)[-1]}; "
               f"model {payload.get('model_name', '?')} {payload.get('hash', '')}")
    new_xml = patch_model_description(xml, meta, version)
    rewrite_zip_member(fmu, "modelDescription.xml", new_xml)
    if runtime is not None:
        from lxml import etree
        root = etree.fromstring(new_xml)
        ident = root.find("CoSimulation").get("modelIdentifier")
        log(f"{name}: native FMI runtime as binaries/{native.PLATFORM_DIR}/{ident}.so")
        native.install(fmu, runtime, ident, st["module"], name, root.get("guid"), rewrite_zip_member)
    log(f"{name}: checking the interface and validating with fmpy")
    problems = check_interface(name, fmu, payload)
    from fmpy.validation import validate_fmu
    problems += validate_fmu(str(fmu))
    if problems:
        raise BuildError(f"{name}.fmu has {len(problems)} problem(s):\n  " + "\n  ".join(problems))
    n_par = sum(1 for v in meta["variables"].values() if v["causality"] == "parameter")
    log(f"{name}: ok ({n_par} parameters, {time.perf_counter() - t0:.1f} s)")
    return fmu


def build_all(model_path=None, out_dir=DEFAULT_OUT, floor=False, ssp=True, log=print,
              native_runtime=True) -> BuildResult:
    """Build the FMUs of ``model_path`` into ``out_dir``; returns ``{name: path}`` (and ``.ssp``).

    ``model_path``: the model file (default: the paper's, shipped with the package); ``out_dir``:
    the folder that receives the FMUs (default ``./models``, created); ``floor`` also builds
    PassThrough.fmu; ``ssp`` writes ``PiezoSystem.ssp`` of the three system FMUs
    (:func:`piezo_fmu.ssp.write_system_ssp`). ``native_runtime``: the FMUs' binary is the
    project's C runtime (:mod:`.runtime`; pythonfmu's when it cannot be compiled, said in one
    line); ``False`` keeps pythonfmu's.

    Raises :class:`BuildError` (or :class:`piezo_fmu.model.ModelError`) on any problem; FMUs that
    were not all checked never reach ``out_dir``.
    """
    from .. import ssp as ssp_module
    from ..model import load_model

    model = load_model(model_path)
    payload = model_payload(model)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = SYSTEM + (FLOOR if floor else ())
    log(f"building {', '.join(names)} from {model.path} (model {model.name!r}, {payload['hash']}) "
        f"into {out_dir}")
    work = Path(tempfile.mkdtemp(prefix="piezo_fmu_build_"))
    try:
        runtime = native.compile_runtime(work / "runtime", log) if native_runtime else None
        built = {name: build_one(name, payload, work, log, runtime) for name in names}
        log("running the default experiment of each FMU (fmpy, without piezo_fmu importable)")
        smoke = smoke_run(built.values())
        for name, path in built.items():
            last = smoke[str(path)]["last"]
            log(f"  {name}: {smoke[str(path)]['rows']} rows, final " +
                ", ".join(f"{k}={v:.6g}" for k, v in last.items()))
        result = BuildResult()
        for name, path in built.items():     # only checked FMUs arrive, each replaced atomically
            dest = out_dir / path.name
            part = out_dir / f".{path.name}.part"
            try:
                shutil.copyfile(path, part)
                os.replace(part, dest)
            finally:
                part.unlink(missing_ok=True)
            result[name] = dest
            log(f"wrote {dest}")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if not ssp:
        return result
    result.ssp = out_dir / SSP_NAME
    ssp_module.write_system_ssp(result.ssp, {n: result[n] for n in SYSTEM})
    log(f"wrote {result.ssp}")
    return result
