"""Staging an FMU's Python sources: the slave script with a uniquely named bundle of
:mod:`piezo_fmu.core` and the slave base (``slavebase`` and the modules it is split into,
:data:`BUNDLED`), imports rewritten with :mod:`ast` at their exact spans.

The sources come from the installed package (``piezo_fmu.fmu_src``, which is the repository's
top-level ``fmu_src/`` mapped into the package by ``pyproject.toml``; one source of truth), so a
wheel installed anywhere builds the same FMUs as a checkout.
"""
from __future__ import annotations

import ast
import hashlib
import json
import re
import shutil
import sys
from importlib.resources import files
from pathlib import Path

from .errors import BuildError

__all__ = ["BUNDLED", "CLASS_RE", "CORE_DIR", "FMU_SRC", "MODEL_JSON", "SLAVEBASE", "StageError",
           "imported_top_levels", "rewrite_imports", "stage", "tree_hash"]

FMU_SRC = Path(str(files("piezo_fmu.fmu_src")))
CORE_DIR = Path(str(files("piezo_fmu.core")))
SLAVEBASE = FMU_SRC / "slavebase.py"
# the slave base and the modules it is split into (each imports the others by their plain names)
BUNDLED = tuple(FMU_SRC / f"{m}.py" for m in ("slavebase", "slavevars", "statecodec", "nativeslave",
                                               "pythonfmu_compat"))
MODEL_JSON = "piezo_model.json"          # must equal slavebase.MODEL_JSON

# the regex the pythonfmu C++ wrapper applies to the staged script to find the class
CLASS_RE = re.compile(r"^class (\w+)\(\s*Fmi2Slave\s*\)\s*:", re.MULTILINE)


class StageError(BuildError):
    """A slave script or the bundle cannot be staged (imports, class line)."""


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
    pkg = f"_pz_{name.lower()}_{tree_hash([CORE_DIR, *BUNDLED])[:10]}"
    sdir = stage_root / name
    if sdir.exists():
        shutil.rmtree(sdir)
    (sdir / pkg).mkdir(parents=True)
    (sdir / pkg / "__init__.py").write_text(
        f'"""piezo-fmu bundle of {name}.fmu: piezo_fmu.core and the slave base (imports rewritten)."""\n')
    shutil.copytree(CORE_DIR, sdir / pkg / "core", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    renames = [(src.stem, f"{pkg}.{src.stem}") for src in BUNDLED] + [("piezo_fmu.core", f"{pkg}.core")]

    def rewritten(source, filename):
        for old, new in renames:
            source = rewrite_imports(source, old, new, filename)
        return source

    for src in BUNDLED:
        (sdir / pkg / src.name).write_text(rewritten(src.read_text(encoding="utf-8"), str(src)), encoding="utf-8")
    new_text = rewritten(text, str(script))
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
