"""The FMUs' native FMI runtime: compiled from ``fmu_src/runtime`` with the system C compiler.

pythonfmu's export binary links no libpython, takes its interpreter's home from ``PATH``, reports
every error as fmi2Fatal and crashes some hosts at exit; the project's own runtime replaces it in
every FMU (``binaries/linux64/<modelIdentifier>.so``, see ``fmu_src/runtime/runtime.h``):

* :func:`compile_runtime` builds its two halves once per build: the FMI layer (libc and libdl
  only) and the Python bridge (``piezo_fmu_bridge.so``, against the building Python's headers,
  linked to no libpython);
* :func:`python_facts` records what the runtime needs to start Python in a host that has none:
  the Python library (the one this interpreter runs on, or found beside it), the home
  (``sys.base_prefix``) and the module path (standard library, ``lib-dynload``, the
  site-packages of the building environment, and wherever numpy, numba and pythonfmu were
  found), written per FMU into ``resources/piezo_runtime.cfg`` with the slave's module, class
  and the modelDescription's GUID (:func:`config_text`);
* :func:`install` puts the three files into a built FMU.

Without a C compiler or without ``Python.h`` :func:`compile_runtime` says so in one line and
returns ``None``: the FMUs then keep pythonfmu's binary (see the README for what those need).
The environment variables ``PIEZO_FMU_LIBPYTHON``, ``PIEZO_FMU_PYTHONHOME`` and
``PIEZO_FMU_PYTHONPATH`` override the recorded values at run time; ``CC`` chooses the compiler.
"""
from __future__ import annotations

import importlib.util
import os
import platform
import shlex
import shutil
import site
import subprocess
import sys
import sysconfig
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path

__all__ = ["BRIDGE_FILE", "CONFIG_FILE", "PROTOCOL", "RUNTIME_SRC", "RuntimeBinaries", "compile_runtime",
           "config_text", "find_compiler", "install", "python_facts"]

RUNTIME_SRC = Path(str(files("piezo_fmu.fmu_src"))) / "runtime"
CONFIG_FILE = "piezo_runtime.cfg"          # runtime.h: PZ_CONFIG_FILE
BRIDGE_FILE = "piezo_fmu_bridge.so"        # runtime.h: PZ_BRIDGE_FILE
PROTOCOL = 1                               # runtime.h: PZ_PROTOCOL, nativeslave.PROTOCOL
PLATFORM_DIR = "linux64"
CFLAGS = ["-std=gnu11", "-O2", "-fPIC", "-shared", "-fvisibility=hidden", "-Wall", "-Wextra",
          "-Wno-unused-parameter"]
# modules the FMUs import from the recorded module path (numba only for the compiled engine)
NEEDED = ("numpy", "pythonfmu", "numba")


@dataclass
class RuntimeBinaries:
    """The compiled runtime: the FMI layer, the bridge, and what was recorded about Python."""

    fmi: Path
    bridge: Path
    python: dict = field(default_factory=dict)


def find_compiler():
    """``(argv, description)`` of the C compiler: ``$CC``, else the one Python was built with, else
    ``cc``/``gcc``; ``(None, why)`` when there is none."""
    cc = os.environ.get("CC")
    if cc:
        argv = shlex.split(cc)
        if argv and shutil.which(argv[0]):
            return argv, f"$CC={cc}"
        return None, f"the C compiler $CC={cc!r} was not found"
    candidates = []
    built_with = sysconfig.get_config_var("CC")
    if built_with:
        candidates.append(shlex.split(built_with)[:1])
    candidates += [["cc"], ["gcc"]]
    for argv in candidates:
        if argv and shutil.which(argv[0]):
            return argv, argv[0]
    return None, "no C compiler (cc, gcc or $CC) was found"


def _loaded_libpython():
    """The Python library this process runs on, if it is a shared one (from /proc/self/maps)."""
    want = f"libpython{sys.version_info.major}.{sys.version_info.minor}"
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as f:
            for line in f:
                parts = line.split(None, 5)
                if len(parts) == 6 and os.path.basename(parts[5].strip()).startswith(want + ".so"):
                    return parts[5].strip()
    except OSError:
        pass
    return None


def find_libpython():
    """Path of a shared libpython of this Python version (``None`` if there is none)."""
    loaded = _loaded_libpython()
    if loaded and os.path.exists(loaded):
        return loaded
    cv = sysconfig.get_config_var
    names = [n for n in (cv("INSTSONAME"), cv("LDLIBRARY")) if n and ".so" in n]
    dirs = [cv("LIBDIR"), cv("LIBPL"), os.path.join(sys.base_prefix, "lib")]
    if cv("MULTIARCH"):
        dirs += [os.path.join(d, cv("MULTIARCH")) for d in (cv("LIBDIR") or "", "/usr/lib", "/lib")]
    for d in dirs:
        for n in names:
            p = os.path.join(d or "", n)
            if d and os.path.isfile(p):
                return p
    return None


def python_facts() -> dict:
    """What the runtime needs to start this Python where the host has none (see the module
    docstring); ``problems`` lists what makes the native runtime impossible."""
    problems = []
    include = sysconfig.get_paths()["include"]
    if not os.path.isfile(os.path.join(include, "Python.h")):
        problems.append(f"no Python headers ({include}/Python.h; install the python3-dev package)")
    libpython = find_libpython()
    stdlib = sysconfig.get_paths()["stdlib"]
    paths = [p for p in sys.path if p.endswith(".zip") and os.path.dirname(p) == os.path.dirname(stdlib)]
    paths += [stdlib, sysconfig.get_config_var("DESTSHARED") or os.path.join(stdlib, "lib-dynload")]
    sites = list(site.getsitepackages())
    user = site.getusersitepackages() if site.ENABLE_USER_SITE else None
    if user and user in sys.path:
        sites.append(user)
    paths += sites
    for name in NEEDED:       # wherever this interpreter finds them (also outside site-packages)
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.submodule_search_locations:
            parent = os.path.dirname(next(iter(spec.submodule_search_locations)))
            if parent not in paths:
                paths.append(parent)
    paths = [p for i, p in enumerate(paths) if p and p not in paths[:i]]
    for p in paths + [libpython or "", sys.base_prefix, sys.executable]:
        if "\n" in p or "\r" in p:
            problems.append(f"a path with a line break cannot be recorded: {p!r}")
    return {"python_version": f"{sys.version_info.major}.{sys.version_info.minor}",
            "libpython": libpython or "", "home": sys.base_prefix, "executable": sys.executable,
            "paths": paths, "include": include, "problems": problems}


def _platform_problem():
    if sys.platform != "linux" or platform.machine() not in ("x86_64", "AMD64"):
        return (f"the native runtime is built for Linux x86_64 only (this is {sys.platform} "
                f"{platform.machine()})")
    return ""


def compile_runtime(out_dir, log=print):
    """Compile the runtime into ``out_dir``; a :class:`RuntimeBinaries`, or ``None`` after one line
    through ``log`` saying why the FMUs keep pythonfmu's binary."""
    out_dir = Path(out_dir)
    facts = python_facts()
    argv, compiler = find_compiler()
    why = _platform_problem() or (compiler if argv is None else "") or "; ".join(facts["problems"])
    if not why:
        out_dir.mkdir(parents=True, exist_ok=True)
        fmi, bridge = out_dir / "fmi2_runtime.so", out_dir / BRIDGE_FILE
        jobs = [(fmi, [*CFLAGS, "-o", str(fmi), str(RUNTIME_SRC / "fmi2_runtime.c"), "-ldl", "-lpthread",
                       "-Wl,-z,defs"]),
                (bridge, [*CFLAGS, f"-I{facts['include']}", "-o", str(bridge),
                          str(RUNTIME_SRC / "fmi2_bridge.c"), "-lpthread"])]
        for target, args in jobs:
            try:
                proc = subprocess.run([*argv, *args], capture_output=True, text=True, check=False, timeout=300)
            except OSError as e:
                why = f"{compiler} could not run ({e})"
                break
            if proc.returncode != 0 or not target.is_file():
                first = next((ln for ln in proc.stderr.splitlines() if "error" in ln), proc.stderr.strip()[:300])
                why = f"{compiler} failed on {target.name}: {first}"
                break
    if why:
        log(f"native FMI runtime not built ({why}): the FMUs keep pythonfmu's binary, which needs "
            "a Python host or LD_PRELOAD of libpython (README: Dropping the FMUs into other tools)")
        return None
    if not facts["libpython"]:
        log("note: no shared libpython found for this Python: the FMUs run in Python hosts; other "
            "hosts need PIEZO_FMU_LIBPYTHON")
    return RuntimeBinaries(fmi=fmi, bridge=bridge, python=facts)


def config_text(python: dict, module: str, cls: str, guid: str) -> str:
    """``resources/piezo_runtime.cfg`` of one FMU (read by ``fmi2_runtime.c``)."""
    lines = ["# piezo-fmu native FMI runtime (fmu_src/runtime), written by piezo-fmu build.",
             "# At run time PIEZO_FMU_LIBPYTHON, PIEZO_FMU_PYTHONHOME and PIEZO_FMU_PYTHONPATH",
             "# override libpython, home and path (PATH, PYTHONHOME, PYTHONPATH are ignored).",
             f"protocol={PROTOCOL}", f"python_version={python['python_version']}",
             f"libpython={python['libpython']}", f"home={python['home']}",
             f"executable={python['executable']}"]
    lines += [f"path={p}" for p in python["paths"]]
    lines += [f"module={module}", f"class={cls}", f"guid={guid}"]
    return "\n".join(lines) + "\n"


def install(fmu_path, runtime: RuntimeBinaries, model_identifier: str, module: str, cls: str, guid: str,
            rewrite):
    """Put the runtime into a built FMU: the FMI layer as ``binaries/linux64/<modelIdentifier>.so``
    (replacing pythonfmu's), the bridge beside it, and the configuration into ``resources/``.
    ``rewrite(fmu, member, data)`` is the builder's safe zip-member rewrite."""
    binaries = f"binaries/{PLATFORM_DIR}/"
    rewrite(fmu_path, f"{binaries}{model_identifier}.so", runtime.fmi.read_bytes())
    rewrite(fmu_path, f"{binaries}{BRIDGE_FILE}", runtime.bridge.read_bytes())
    rewrite(fmu_path, f"resources/{CONFIG_FILE}", config_text(runtime.python, module, cls, guid).encode("utf-8"))
