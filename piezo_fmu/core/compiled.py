"""The compiled engine: the core's kernels compiled by numba, and packed runners for the units.

numba is optional. Nothing here imports it until :func:`kernels` is called, so the units, the
FMUs and the interpreted engine need only NumPy; :func:`available` tells whether it can be used.

* :func:`kernels` compiles every kernel of the core (and the two runners below) once per process.
  Each kernel is cloned with its global names re-bound to the compiled callees, so the source
  compiled is the very function the interpreted engine runs: one copy of the physics. Options
  (measured on the paper's 10 Hz closed loop at 1e-5 s): callees inlined at numba-IR level;
  reference counting off (``_nrt=False``: nothing allocates arrays, and counting the ~40 array
  arguments cost 2/3 of the time); divisions with the NumPy error model (no zero-divisor
  branches; validated parameters never divide by zero): 271 -> 92 ns per step of the
  single-rate loop when introduced. Results are bit-identical to the interpreted engine (tested).
* A compiled function called from Python pays numba's dispatch for every argument (~70 ns per
  array: 1.4-2 us for the kernels' 14-21 arrays, as much as the interpreted kernel costs). The
  runners take instead ONE float64 buffer holding a unit's data back to back and the offsets of
  its regions (:func:`.buffers.pack`), and slice the kernel's arguments out of it inside compiled code
  (views: no allocation). A unit switched to the compiled engine (:func:`compile_unit`) keeps its
  data as views of that buffer, so its state stays in one place for both engines.
* Compiled code is cached on disk (:func:`cache_dir`), in a folder named by a digest of the
  sources it is compiled from (this package's ``core`` and the modules that compile kernels of
  their own) and of the numba and Python versions: numba's own cache checks only the file of the
  function it compiles, so a kernel with a callee inlined from another file would be loaded
  stale after that file changed. With the cache a process loads the kernels (about 1.5 s for
  the whole set on 2 cores) instead of compiling them (6-15 s). ``PIEZO_FMU_CACHE`` names the cache's parent folder
  (default ``$XDG_CACHE_HOME/piezo-fmu`` or ``~/.cache/piezo-fmu``; ``off``: nothing cached).
  When a new folder is made there, the folders of other sources untouched for
  :data:`STALE_CACHE_DAYS` are removed (:func:`prune_caches`).
* Dependencies point one way: this module imports the units' modules (to compile their kernels);
  they never import it. A unit only knows that it may be handed a runner
  (``use_runner``); :func:`compile_unit` hands it the compiled one.
"""
from __future__ import annotations

import hashlib
import os
import sys
import threading
import types
from functools import lru_cache
from pathlib import Path


from . import control, hysteresis, linear, plant, preisach
from .control import compensator_step
from .plant import actuator_step

__all__ = ["ENGINES", "available", "cache_dir", "prune_caches", "STALE_CACHE_DAYS", "jit", "sources_digest",
           "kernels", "compile_function", "rebind", "compile_unit", "warm", "actuator_run", "compensator_run", "KERNEL_ORDER", "ACTUATOR_REGIONS", "COMPENSATOR_REGIONS"]

ENGINES = {"python": 0, "numba": 1}     # Integer codes of the FMUs' simulation.engine parameter

# callees before callers: each is compiled with the compiled versions of those before it
KERNEL_ORDER = (
    (hysteresis, "pi_tail"), (hysteresis, "pi_step"), (preisach, "kp_step"), (plant, "amp_step"),
    (linear, "lti_advance"), (plant, "drift_curvature"), (plant, "drift_at"),
    (control, "reference_value"), (control, "pid_step"),
    (plant, "actuator_step"), (plant, "sensor_step"), (control, "compensator_step"),
)

# the buffer regions of the runners, in :func:`~.plant.actuator_step` / :func:`~.control.compensator_step`
# argument order
ACTUATOR_REGIONS = ("amp", "amp_s", "dly", "dly_buf", "pi_r", "pi_w", "pi_z", "pi_k", "kp_c", "kp_s", "cr_phi",
                    "cr_g", "cr_cd", "cr_xs", "cr_tmp", "frc", "me_phi", "me_g", "me_cd",
                    "me_xs", "me_tmp", "drift", "out")
COMPENSATOR_REGIONS = ("cfg", "ref", "gains", "pid_s", "inv_r", "inv_w", "inv_z", "inv_k",
                       "gi_phi", "gi_g", "gi_cd", "gi_xs", "gi_tmp", "out")


def available() -> bool:
    """True when numba can be imported (the compiled engine can be used)."""
    try:
        import numba  # noqa: F401
    except Exception:  # noqa: BLE001 - any import failure means: not available
        return False
    return True


def actuator_run(uc, h, n, t, buf, o):
    """``n`` internal steps of :func:`~.plant.actuator_step` with the command ``uc`` [V] held,
    each ``h`` [s], from time ``t`` [s], on the unit data packed in ``buf`` (regions
    :data:`ACTUATOR_REGIONS` at offsets ``o``). Returns the time at the end."""
    for _ in range(n):
        t += h
        actuator_step(uc, h, t, buf[o[0]:o[1]], buf[o[1]:o[2]], buf[o[2]:o[3]], buf[o[3]:o[4]],
                      buf[o[4]:o[5]], buf[o[5]:o[6]], buf[o[6]:o[7]], buf[o[7]:o[8]],
                      buf[o[8]:o[9]], buf[o[9]:o[10]], buf[o[10]:o[11]], buf[o[11]:o[12]],
                      buf[o[12]:o[13]], buf[o[13]:o[14]], buf[o[14]:o[15]], buf[o[15]:o[16]],
                      buf[o[16]:o[17]], buf[o[17]:o[18]], buf[o[18]:o[19]], buf[o[19]:o[20]],
                      buf[o[20]:o[21]], buf[o[21]:o[22]], buf[o[22]:o[23]])
    return t


def compensator_run(t, x_ref_in, us, h, buf, o):
    """:func:`~.control.compensator_step` on the unit data packed in ``buf`` (regions
    :data:`COMPENSATOR_REGIONS` at offsets ``o``); returns the command ``uc`` [V]."""
    compensator_step(t, x_ref_in, us, h, buf[o[0]:o[1]], buf[o[1]:o[2]], buf[o[2]:o[3]],
                     buf[o[3]:o[4]], buf[o[4]:o[5]], buf[o[5]:o[6]], buf[o[6]:o[7]],
                     buf[o[7]:o[8]], buf[o[8]:o[9]], buf[o[9]:o[10]], buf[o[10]:o[11]],
                     buf[o[11]:o[12]], buf[o[12]:o[13]], buf[o[13]:o[14]])
    return buf[o[13]]


# the modules whose functions are compiled (besides the core's): a change to any of them, or to the
# core, gives a new cache folder
_COMPILING_MODULES = ("simulate.py", "diagnose/engine.py", "diagnose/kernels.py")
_CACHE_LOCK = threading.Lock()


def sources_digest(package: Path | None = None) -> str:
    """A digest of the sources compiled (``package``'s ``core/*.py`` and the modules that compile
    kernels; default: this package) and of the numba and Python versions."""
    import numba

    pkg = Path(package) if package is not None else Path(__file__).resolve().parent.parent
    files = sorted((pkg / "core").glob("*.py")) + [pkg / m for m in _COMPILING_MODULES]
    h = hashlib.sha256(f"numba {numba.__version__} python {sys.version}".encode())
    for f in files:
        h.update(f.name.encode())
        h.update(f.read_bytes() if f.is_file() else b"")
    return h.hexdigest()[:16]


@lru_cache(maxsize=1)
def cache_dir() -> Path | None:
    """The folder compiled kernels are cached in, or None when nothing is cached (``PIEZO_FMU_CACHE``
    is ``off``, or the folder cannot be created or written). Its name is a digest of the sources
    compiled (see the module's notes), so a changed source never loads an old kernel."""
    root = os.environ.get("PIEZO_FMU_CACHE", "")
    if root.lower() in ("off", "0", "no", "false"):
        return None
    if not root:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = os.path.join(base, "piezo-fmu")
    path = Path(root) / f"numba-{sources_digest()}"
    made = not path.exists()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    if made:        # another version's first run here: the folders of versions long unused go
        prune_caches(path.parent, path)
    return path if os.access(path, os.W_OK) else None


# a cache folder of other sources (an edited or upgraded install) in which nothing was written for
# this long is removed when a new one is made [days]
STALE_CACHE_DAYS = 30.0


def prune_caches(root, keep, max_age_days=STALE_CACHE_DAYS, now=None) -> list:
    """Remove the cache folders ``numba-*`` under ``root`` other than ``keep`` in which no file or
    folder changed for ``max_age_days`` [days] before ``now`` [s since the epoch; default: now];
    returns those removed. Best effort: a folder another process is using or removing is left or
    skipped without an error (a kernel whose cache went away is compiled again)."""
    import shutil
    import time

    now = time.time() if now is None else now
    removed = []
    try:
        folders = [d for d in Path(root).glob("numba-*") if d.is_dir() and d.resolve() != Path(keep).resolve()]
    except OSError:
        return removed
    for d in folders:
        try:
            newest = max([d.stat().st_mtime] + [f.stat().st_mtime for f in d.rglob("*")])
        except OSError:
            continue
        if now - newest > max_age_days * 86400.0:
            shutil.rmtree(d, ignore_errors=True)
            if not d.exists():
                removed.append(d)
    return removed


def jit(func=None, **opts):
    """``numba.njit(**opts)(func)``, cached in :func:`cache_dir` (not cached when it is None);
    without ``func`` a decorator."""
    import numba
    from numba.core import config

    if func is None:
        return lambda f: jit(f, **opts)
    where = cache_dir()
    # numba caches only functions whose code names a source file it finds: inside an FMU the
    # bundled core's do not (stop 61: "cannot cache function 'pi_tail': no locator available for
    # file .../resources/_pz_actuator_.../core/hysteresis.py", the Actuator's engine refused)
    if where is None or not os.path.isfile(func.__code__.co_filename):
        return numba.njit(**opts)(func)
    with _CACHE_LOCK:       # numba reads its cache folder when the dispatcher is made
        saved = config.CACHE_DIR
        config.CACHE_DIR = str(where)
        try:
            return numba.njit(cache=True, **opts)(func)
        except RuntimeError:        # no cache locator for this function: compiled each time
            return numba.njit(**opts)(func)
        finally:
            config.CACHE_DIR = saved


def rebind(func, compiled):
    """A copy of ``func`` (same code, defaults and file) whose global names in ``compiled`` (a dict
    name -> compiled function) are re-bound to those: a module-level function compiled with
    compiled callees. Unlike a closure over the callees, its numba cache entry is found again in
    the next process (numba keys a closure by its pickled cells, a dispatcher's differ per process)."""
    env = dict(func.__globals__)
    env.update(compiled)
    return types.FunctionType(func.__code__, env, func.__name__, func.__defaults__, func.__closure__)


def compile_function(func, compiled, inline=False):
    """``func`` compiled by numba (:func:`jit`) with its global names re-bound to the ``compiled``
    callees (a dict name -> compiled function, :func:`rebind`); ``inline``: inline it into its
    compiled callers."""
    clone = rebind(func, compiled)
    opts = {"nogil": True, "error_model": "numpy"}
    if inline:
        opts["inline"] = "always"
    try:
        return jit(clone, _nrt=False, **opts)
    except TypeError:       # a numba without the _nrt option: reference counting stays on
        return jit(clone, **opts)


def warm(func, *args):
    """Compile ``func`` now for the types of ``args`` (instead of at its first call)."""
    import numba

    func.compile(tuple(numba.typeof(a) for a in args))


def kernels():
    """The compiled kernels and runners by name (each compiled at its first call, once per
    process). Raises RuntimeError when numba is not installed."""
    if not available():
        raise RuntimeError("the compiled engine needs numba in this Python (pip install numba); "
                           "use the interpreted engine instead")
    return _kernels()


@lru_cache(maxsize=1)
def _kernels():
    compiled = {}
    for module, name in KERNEL_ORDER:
        compiled[name] = compile_function(getattr(module, name), compiled, inline=True)
    for func in (actuator_run, compensator_run):
        compiled[func.__name__] = compile_function(func, compiled)
    return compiled


# unit class -> (its runner, the arguments before the packed buffer that type-check a call)
_RUNNERS = {
    plant.Actuator: ("actuator_run", lambda unit: (0.0, 1.0, 0, unit.time)),
    control.Compensator: ("compensator_run", lambda unit: (0.0, 0.0, 0.0, 1.0)),
}


def compile_unit(unit):
    """Switch a core unit (:class:`~.plant.Actuator` or :class:`~.control.Compensator`) to the
    compiled engine: same kernel, same results bit for bit, ~0.5 us per call instead of ~2.5 us
    (an actuator's sub-steps run in one call). The first use in a process compiles (a few
    seconds). Returns ``unit``.

    Raises RuntimeError without numba, TypeError for a unit that has no compiled runner.
    """
    entry = _RUNNERS.get(type(unit))
    if entry is None:
        raise TypeError(f"{type(unit).__name__} has no compiled engine "
                        f"(only {', '.join(k.__name__ for k in _RUNNERS)})")
    name, probe = entry
    run = kernels()[name]
    unit.use_runner(run)
    warm(run, *probe(unit), *unit.packed)
    return unit
