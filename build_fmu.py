#!/usr/bin/env python
"""Build the piezo-fmu co-simulation FMUs (FMI 2.0, pythonfmu) from a model file.

    python build_fmu.py [--model models/paper.toml] [--out-dir models] [--floor]

writes ``Actuator.fmu``, ``Sensor.fmu``, ``Compensator.fmu`` (and with ``--floor`` the trivial
``PassThrough.fmu`` used by the benchmark) into the output folder, then ``PiezoSystem.ssp`` through
:func:`piezo_fmu.ssp.write_system_ssp` when that module exists. From Python::

    from build_fmu import build_all
    fmus = build_all("models/paper.toml", "models")     # {"Actuator": Path, ...}; fmus.ssp

For each FMU:

1. **Model**: the file is validated with :func:`piezo_fmu.model.load_model`; its sections and the
   schema (units, docs, constraints) go into ``resources/piezo_model.json``, from which the slave
   registers its parameters and builds its core unit at instantiation.
2. **Staging**: ``fmu_src/<Name>.py`` plus one bundled package ``_pz_<name>_<hash>`` holding a copy
   of ``piezo_fmu/core`` and ``fmu_src/slavebase.py`` (hash over their content), the script renamed
   ``<Name>_<hash>.py``. Imports of ``slavebase`` and ``piezo_fmu.core`` are rewritten with
   :mod:`ast` at their exact spans; any other import outside the standard library, NumPy, pythonfmu
   and the bundle fails the build. So FMUs built from different core versions load side by side.
3. **pythonfmu build** in a subprocess (it imports the script and changes ``sys.path``), which also
   instantiates the slave once to collect the metadata.
4. **modelDescription post-processing**: UnitDefinitions, unit + description on every variable,
   explicit variability, exact start values (``repr``; pythonfmu's ``%.16g`` is lossy), min/max,
   Outputs + InitialUnknowns exactly as FMI 2.0 (and fmpy) require, DefaultExperiment,
   canGetAndSetFMUstate/canSerializeFMUstate (implemented by the base class), version; then a safe
   rewrite of the zip (new file beside the old, verified, fsync, atomic replace).
5. **Checks**: the interface against :mod:`piezo_fmu.connections`, every model parameter present,
   ``fmpy.validation.validate_fmu`` with zero problems, and a default-experiment run of every FMU
   in a subprocess that cannot import ``piezo_fmu`` (so the FMUs are self-contained).
   Any problem fails the build; the output folder only receives FMUs that passed.
"""
from __future__ import annotations

import argparse
import ast
import hashlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent
FMU_SRC = ROOT / "fmu_src"
CORE_DIR = ROOT / "piezo_fmu" / "core"
SLAVEBASE = FMU_SRC / "slavebase.py"
DEFAULT_MODEL = ROOT / "models" / "paper.toml"
DEFAULT_OUT = ROOT / "models"
SYSTEM = ("Actuator", "Sensor", "Compensator")
FLOOR = ("PassThrough",)
MODEL_JSON = "piezo_model.json"          # must equal slavebase.MODEL_JSON
SSP_NAME = "PiezoSystem.ssp"

# the regex the pythonfmu C++ wrapper applies to the staged script to find the class
CLASS_RE = re.compile(r"^class (\w+)\(\s*Fmi2Slave\s*\)\s*:", re.MULTILINE)

# model sections of each FMU (checked after the build: every key must be a parameter)
FMU_SECTIONS = {
    "Actuator": {"amplifier": None, "hysteresis": None, "creep": None, "mechanics": None,
                 "resonance": None, "drift": None, "simulation": ("actuator_max_step",)},
    "Sensor": {"sensor": None},
    "Compensator": {"compensator": None, "compensator.hysteresis": None, "compensator.dynamics": None},
    "PassThrough": {},
}


class BuildError(RuntimeError):
    """The build failed; the message says where and why."""


class StageError(BuildError):
    pass


# ---------------------------------------------------------------------------------------------
# the model bundled into the FMUs
# ---------------------------------------------------------------------------------------------
def model_payload(model) -> dict:
    """The model as the JSON the slaves read: sections, schema (unit/kind/check/doc), identity."""
    import pythonfmu

    import piezo_fmu
    from piezo_fmu.model import SCHEMA

    sections = json.loads(json.dumps(model.sections, allow_nan=True))
    schema = {sec: {key: {"unit": spec.unit, "kind": spec.kind, "check": spec.check, "doc": spec.doc,
                          "choices": list(spec.choices)}
                    for key, spec in specs.items()}
              for sec, specs in SCHEMA.items()}
    canon = json.dumps(sections, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return {"format": 1, "model_name": model.name, "model_file": str(model.path),
            "hash": hashlib.sha256(canon.encode()).hexdigest()[:12],
            "pythonfmu": pythonfmu.__version__, "piezo_fmu": piezo_fmu.__version__,
            "sections": sections, "schema": schema}


# ---------------------------------------------------------------------------------------------
# staging: unique bundled package, imports rewritten with ast
# ---------------------------------------------------------------------------------------------
def tree_hash(paths) -> str:
    """sha256 over files (relative names and bytes), skipping caches."""
    h = hashlib.sha256()
    for base in paths:
        base = Path(base)
        files = [base] if base.is_file() else sorted(
            p for p in base.rglob("*") if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc")
        for f in files:
            h.update((f.relative_to(base.parent).as_posix()).encode() + b"\0")
            h.update(f.read_bytes() + b"\0")
    return h.hexdigest()


def rewrite_imports(source: str, old: str, new: str, filename="<src>") -> str:
    """Rewrite absolute imports of module/package ``old`` to ``new``, keeping the bound names.

    ``from old[.sub] import a, b as c`` -> ``from new[.sub] import a, b as c``;
    ``import old [as x]`` -> ``import new as old|x``; ``import old.sub as x`` -> ``import new.sub as x``;
    ``import old.sub`` (binds ``old``) and string constants naming ``old`` (dynamic imports) raise
    :class:`StageError`. Edits replace exact byte spans (ast column offsets are UTF-8 bytes).
    """
    data = source.encode("utf-8")
    tree = ast.parse(data, filename)
    line_start = [0]
    for line in data.splitlines(keepends=True):
        line_start.append(line_start[-1] + len(line))

    def span(node):
        return (line_start[node.lineno - 1] + node.col_offset,
                line_start[node.end_lineno - 1] + node.end_col_offset)

    def alias(a):
        return a.name + (f" as {a.asname}" if a.asname else "")

    def hits(name):
        return name == old or name.startswith(old + ".")

    edits = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and hits(node.module):
            mod = new + node.module[len(old):]
            edits.append((*span(node), f"from {mod} import {', '.join(alias(a) for a in node.names)}"))
        elif isinstance(node, ast.Import):
            parts, touched = [], False
            for a in node.names:
                if a.name == old:
                    parts.append(f"{new} as {a.asname or old.rsplit('.', 1)[-1]}")
                    touched = True
                    if "." in old and not a.asname:
                        raise StageError(f"{filename}:{node.lineno}: 'import {old}' binds the top-level "
                                         f"package; use 'from {old.rsplit('.', 1)[0]} import ...'")
                elif a.name.startswith(old + "."):
                    if not a.asname:
                        raise StageError(f"{filename}:{node.lineno}: 'import {a.name}' binds the top-level "
                                         f"package; use 'from ... import' or 'import {a.name} as x'")
                    parts.append(f"{new}{a.name[len(old):]} as {a.asname}")
                    touched = True
                else:
                    parts.append(alias(a))
            if touched:
                edits.append((*span(node), "import " + ", ".join(parts)))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and hits(node.value):
            raise StageError(f"{filename}:{node.lineno}: string constant {node.value!r} looks like a "
                             f"dynamic import of {old!r} that cannot be rewritten")
    for start, end, text in sorted(edits, reverse=True):
        data = data[:start] + text.encode("utf-8") + data[end:]
    return data.decode("utf-8")


def imported_top_levels(source: str, filename="<src>") -> set:
    """Top-level names of every absolute import in ``source``."""
    names = set()
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
        elif isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
    return names


def stage(name: str, payload: dict, stage_root: Path) -> dict:
    """Stage ``fmu_src/<name>.py`` with its uniquely named bundle; returns the staging facts."""
    script = FMU_SRC / f"{name}.py"
    text = script.read_text(encoding="utf-8")
    classes = CLASS_RE.findall(text)
    if classes != [name]:
        raise StageError(f"{script}: needs exactly one line 'class {name}(Fmi2Slave):', found {classes}")
    pkg = f"_pz_{name.lower()}_{tree_hash([CORE_DIR, SLAVEBASE])[:10]}"
    sdir = stage_root / name
    if sdir.exists():
        shutil.rmtree(sdir)
    (sdir / pkg).mkdir(parents=True)
    (sdir / pkg / "__init__.py").write_text(
        f'"""piezo-fmu bundle of {name}.fmu: piezo_fmu.core and slavebase (imports rewritten)."""\n')
    shutil.copytree(CORE_DIR, sdir / pkg / "core", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    shutil.copy2(SLAVEBASE, sdir / pkg / "slavebase.py")
    new_text = text
    for old, new in (("slavebase", f"{pkg}.slavebase"), ("piezo_fmu.core", f"{pkg}.core")):
        new_text = rewrite_imports(new_text, old, new, str(script))
    if CLASS_RE.findall(new_text) != [name]:
        raise StageError(f"{script}: the class line was lost while rewriting imports")
    module = f"{name}_{hashlib.sha256((new_text + pkg).encode()).hexdigest()[:10]}"
    staged = sdir / f"{module}.py"
    staged.write_text(new_text, encoding="utf-8")
    # everything bundled may import only the standard library, numpy, pythonfmu and the bundle;
    # core/compiled.py also numba, imported only when the compiled engine is selected
    allowed = set(sys.stdlib_module_names) | {"numpy", "pythonfmu", pkg}
    optional = {sdir / pkg / "core" / "compiled.py": {"numba"}}
    for f in [staged, *sorted((sdir / pkg).rglob("*.py"))]:
        bad = imported_top_levels(f.read_text(encoding="utf-8"), str(f)) - allowed - optional.get(f, set())
        if bad:
            raise StageError(f"{f.relative_to(sdir)}: imports {sorted(bad)}, which the FMU does not "
                             "bundle (allowed: standard library, numpy, pythonfmu, the bundle)")
    (sdir / MODEL_JSON).write_text(json.dumps(payload, indent=1, allow_nan=True), encoding="utf-8")
    return {"name": name, "module": module, "package": pkg, "stage_dir": sdir, "script": staged}


# ---------------------------------------------------------------------------------------------
# pythonfmu build + metadata, in a subprocess
# ---------------------------------------------------------------------------------------------
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


# ---------------------------------------------------------------------------------------------
# modelDescription post-processing
# ---------------------------------------------------------------------------------------------
# unit -> BaseUnit exponents (SI) and factor/offset; {} = dimensionless
UNIT_TABLE = {
    "1": {}, "V/V": {},
    "s": {"s": 1}, "1/s": {"s": -1}, "Hz": {"s": -1},
    "m": {"m": 1}, "m^2": {"m": 2}, "um": {"m": 1, "factor": 1e-6},
    "um/s": {"m": 1, "s": -1, "factor": 1e-6}, "um/s^2": {"m": 1, "s": -2, "factor": 1e-6},
    "kg": {"kg": 1}, "N": {"kg": 1, "m": 1, "s": -2}, "N/m": {"kg": 1, "s": -2}, "N*s/m": {"kg": 1, "s": -1},
    "A": {"A": 1}, "V": {"kg": 1, "m": 2, "s": -3, "A": -1}, "ohm": {"kg": 1, "m": 2, "s": -3, "A": -2},
    "F": {"kg": -1, "m": -2, "s": 4, "A": 2}, "C/N": {"kg": -1, "m": -1, "s": 3, "A": 1},
    "um/V": {"kg": -1, "m": -1, "s": 3, "A": 1, "factor": 1e-6},
    "V/um": {"kg": 1, "m": 1, "s": -3, "A": -1, "factor": 1e6},
    "rad": {"rad": 1}, "deg": {"rad": 1, "factor": math.pi / 180.0},
}
_BASE_ORDER = ("kg", "m", "s", "A", "K", "mol", "cd", "rad", "factor", "offset")
# children of <fmiModelDescription> in XSD order
_TOP_ORDER = ("ModelExchange", "CoSimulation", "UnitDefinitions", "TypeDefinitions", "LogCategories",
              "DefaultExperiment", "VendorAnnotations", "ModelVariables", "ModelStructure")
_LEGAL = {("parameter", "fixed"), ("parameter", "tunable"), ("input", "continuous"),
          ("output", "continuous")}


class PostProcessError(BuildError):
    pass


def _insert_in_order(root, element):
    for old in root.findall(element.tag):
        root.remove(old)
    rank = _TOP_ORDER.index(element.tag)
    pos = 0
    for i, child in enumerate(root):
        if child.tag in _TOP_ORDER and _TOP_ORDER.index(child.tag) < rank:
            pos = i + 1
    root.insert(pos, element)


def patch_model_description(xml_bytes: bytes, meta: dict, version: str = "") -> bytes:
    """The modelDescription pythonfmu wrote, completed from the slave's ``fmu_meta()``."""
    from lxml import etree

    root = etree.fromstring(xml_bytes, etree.XMLParser(remove_blank_text=True))
    if root.get("fmiVersion") != "2.0":
        raise PostProcessError("only FMI 2.0 is supported")
    if meta.get("description"):
        root.set("description", meta["description"])
    if version:
        root.set("version", version)
    cs = root.find("CoSimulation")
    cs.set("canGetAndSetFMUstate", "true" if meta["can_get_set_state"] else "false")
    cs.set("canSerializeFMUstate", "true" if meta["can_serialize_state"] else "false")

    vmeta = meta["variables"]
    svs = root.find("ModelVariables").findall("ScalarVariable")
    names = [sv.get("name") for sv in svs]
    if len(set(names)) != len(names):
        raise PostProcessError("duplicate variable names")
    if set(names) != set(vmeta):
        raise PostProcessError(f"variables and metadata differ: {sorted(set(names) ^ set(vmeta))}")
    index = {n: i + 1 for i, n in enumerate(names)}           # ModelStructure indices are 1-based
    used_units = []
    for sv in svs:
        name = sv.get("name")
        m = vmeta[name]
        type_el = sv[0]
        if type_el.tag != m["type"]:
            raise PostProcessError(f"{name}: type {type_el.tag} in the XML, {m['type']} in the slave")
        if (m["causality"], m["variability"]) not in _LEGAL:
            raise PostProcessError(f"{name}: causality={m['causality']} variability={m['variability']}")
        if not m.get("description"):
            raise PostProcessError(f"{name}: empty description")
        sv.set("description", m["description"])
        sv.set("causality", m["causality"])
        sv.set("variability", m["variability"])           # pythonfmu may leave it out
        if "initial" in sv.attrib:
            del sv.attrib["initial"]                        # the defaults are right for all of ours
        for attr in ("start", "min", "max", "unit"):
            type_el.attrib.pop(attr, None)
        if m["causality"] in ("input", "parameter"):
            if m["start"] is None:
                raise PostProcessError(f"{name}: an {m['causality']} needs a start value")
            type_el.set("start", m["start"])              # exact (repr), INF for infinity
        if m.get("min") is not None:
            type_el.set("min", m["min"])
        if m.get("max") is not None:
            type_el.set("max", m["max"])
        if m["type"] == "Real":
            unit = m.get("unit")
            if not unit:
                raise PostProcessError(f"{name}: Real variable without a unit")
            if unit not in UNIT_TABLE:
                raise PostProcessError(f"{name}: unit {unit!r} is not in build_fmu.UNIT_TABLE")
            type_el.set("unit", unit)
            if unit not in used_units:
                used_units.append(unit)

    ud = etree.Element("UnitDefinitions")
    for u in used_units:
        ue = etree.SubElement(ud, "Unit", name=u)
        base = UNIT_TABLE[u]
        etree.SubElement(ue, "BaseUnit", {k: (repr(float(base[k])) if k in ("factor", "offset")
                                              else str(base[k])) for k in _BASE_ORDER if k in base})
    if used_units:
        _insert_in_order(root, ud)

    de = meta.get("default_experiment")
    if de:
        el = etree.Element("DefaultExperiment")
        for key in ("startTime", "stopTime", "tolerance", "stepSize"):
            if de.get(key) is not None:
                el.set(key, repr(float(de[key])))
        _insert_in_order(root, el)

    # ModelStructure, from scratch. Outputs: every output; ours are computed in do_step (and at
    # initialization) only, so they depend on no input within a step: dependencies="".
    # InitialUnknowns (FMI 2.0, 2.2.8) = outputs with initial calculated/approx (all of ours) +
    # calculatedParameters (none); no dependencies attribute = depends on all knowns.
    ms = etree.Element("ModelStructure")
    outputs = [n for n in names if vmeta[n]["causality"] == "output"]
    if outputs:
        oe = etree.SubElement(ms, "Outputs")
        ie = etree.SubElement(ms, "InitialUnknowns")
        for n in outputs:
            u = etree.SubElement(oe, "Unknown", index=str(index[n]))
            deps = vmeta[n].get("depends_on")
            if deps is not None:
                u.set("dependencies", " ".join(str(index[d]) for d in deps))
            u2 = etree.SubElement(ie, "Unknown", index=str(index[n]))
            ideps = vmeta[n].get("init_depends_on")
            if ideps is not None:
                u2.set("dependencies", " ".join(str(index[d]) for d in ideps))
    _insert_in_order(root, ms)
    return etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True)


def rewrite_zip_member(fmu_path, member: str, data: bytes):
    """Replace one member of a zip: write the complete new zip beside the old one, verify it, fsync,
    then atomically replace the original; the temp file is removed on any failure."""
    src = Path(fmu_path)
    fd, tmp = tempfile.mkstemp(prefix=f".{src.name}.", suffix=".tmp", dir=src.parent)
    os.close(fd)
    try:
        with zipfile.ZipFile(src) as zin, zipfile.ZipFile(tmp, "w") as zout:
            infos = zin.infolist()
            if len({i.filename for i in infos}) != len(infos):
                raise PostProcessError(f"{src}: duplicate zip entries")
            seen = False
            for info in infos:
                if info.filename == member:
                    seen = True
                    zi = zipfile.ZipInfo(member, date_time=info.date_time)
                    zi.external_attr = info.external_attr
                    zi.compress_type = zipfile.ZIP_DEFLATED
                    zout.writestr(zi, data)
                else:
                    zout.writestr(info, zin.read(info.filename))   # same name, time, mode, method
            if not seen:
                zout.writestr(zipfile.ZipInfo(member), data, compress_type=zipfile.ZIP_DEFLATED)
        with zipfile.ZipFile(tmp) as zchk:
            if zchk.testzip() is not None:
                raise PostProcessError(f"{src}: CRC error in the rewritten zip")
            if zchk.read(member) != data:
                raise PostProcessError(f"{src}: rewritten member differs")
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, src)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


# ---------------------------------------------------------------------------------------------
# checks
# ---------------------------------------------------------------------------------------------
def check_interface(name: str, fmu: Path, payload: dict) -> list:
    """Problems of the built FMU's interface against piezo_fmu.connections and the model."""
    from fmpy import read_model_description

    from piezo_fmu.connections import COMPONENTS

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


# ---------------------------------------------------------------------------------------------
# the build
# ---------------------------------------------------------------------------------------------
class BuildResult(dict):
    """``{name: path of the FMU}``; ``.ssp`` is the SSP path (``None`` when skipped)."""
    ssp = None


def build_one(name: str, payload: dict, work: Path, log=print) -> Path:
    """Stage, build, post-process and check one FMU in the work folder; returns its path there."""
    t0 = time.perf_counter()
    log(f"{name}: staging fmu_src/{name}.py with piezo_fmu/core and slavebase")
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
    import piezo_fmu
    version = (f"piezo-fmu {piezo_fmu.__version__}; core+slavebase {st['package'].rsplit('_', 1)[-1]}; "
               f"model {payload.get('model_name', '?')} {payload.get('hash', '')}")
    rewrite_zip_member(fmu, "modelDescription.xml", patch_model_description(xml, meta, version))
    log(f"{name}: checking the interface and validating with fmpy")
    problems = check_interface(name, fmu, payload)
    from fmpy.validation import validate_fmu
    problems += validate_fmu(str(fmu))
    if problems:
        raise BuildError(f"{name}.fmu has {len(problems)} problem(s):\n  " + "\n  ".join(problems))
    n_par = sum(1 for v in meta["variables"].values() if v["causality"] == "parameter")
    log(f"{name}: ok ({n_par} parameters, {time.perf_counter() - t0:.1f} s)")
    return fmu


def build_all(model_path=DEFAULT_MODEL, out_dir=DEFAULT_OUT, floor=False, ssp=True, log=print) -> BuildResult:
    """Build the FMUs of ``model_path`` into ``out_dir``; returns ``{name: path}`` (and ``.ssp``).

    ``floor`` also builds PassThrough.fmu; ``ssp`` writes ``PiezoSystem.ssp`` of the three system
    FMUs through ``piezo_fmu.ssp.write_system_ssp`` when that module is importable.

    Raises :class:`BuildError` (or :class:`piezo_fmu.model.ModelError`) on any problem; FMUs that
    were not all checked never reach ``out_dir``.
    """
    from piezo_fmu.model import load_model

    model = load_model(model_path)
    payload = model_payload(model)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = SYSTEM + (FLOOR if floor else ())
    log(f"building {', '.join(names)} from {model_path} (model {model.name!r}, {payload['hash']}) "
        f"into {out_dir}")
    work = Path(tempfile.mkdtemp(prefix="piezo_fmu_build_"))
    try:
        built = {name: build_one(name, payload, work, log) for name in names}
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
    try:
        import piezo_fmu.ssp as ssp_module
    except ModuleNotFoundError as e:
        if e.name != "piezo_fmu.ssp":
            raise
        log("SSP skipped: piezo_fmu.ssp is not available")
    else:
        result.ssp = out_dir / SSP_NAME
        ssp_module.write_system_ssp(result.ssp, {n: result[n] for n in SYSTEM})
        log(f"wrote {result.ssp}")
    return result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=str(DEFAULT_MODEL), metavar="FILE.toml",
                    help="model file (default: models/paper.toml)")
    ap.add_argument("--out-dir", default=str(DEFAULT_OUT), metavar="DIR",
                    help="where the FMUs go (default: models)")
    ap.add_argument("--floor", action="store_true",
                    help="also build PassThrough.fmu (y = u on the same base: the benchmark's floor)")
    args = ap.parse_args(argv)
    from piezo_fmu.errors import UserError
    try:
        build_all(args.model, args.out_dir, floor=args.floor)
    except (BuildError, UserError) as e:
        print(f"build_fmu: error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
