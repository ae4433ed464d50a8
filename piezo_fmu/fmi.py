"""The FMI 2.0 co-simulation binding the master uses: one FMU instance driven through ctypes.

:class:`Slave` loads an FMU with fmpy (extract, read the modelDescription, ``FMU2Slave``) and binds
the FMI functions on a ``ctypes.PyDLL`` view of the library (the GIL is kept: the FMUs' native
runtime serves ``fmi2SetReal``/``fmi2GetReal`` of inputs and outputs without Python and enters
Python in ``fmi2DoStep`` without any GIL operation for a caller that holds it). The stepping
loop's three functions are also bound without ``argtypes`` (:attr:`Slave.hot`): ctypes converts
``POINTER`` arguments in Python, ~0.5 us per call, so the loop passes ctypes objects of the exact
C types instead, and nothing is allocated per call but the step's ``c_double`` time. Every FMU's log messages arrive through the one process-wide logger of
:mod:`piezo_fmu.fmilog` and are kept per instance (:class:`LogBook`) to explain a failing call.
:func:`load_slaves` loads several FMUs as one context manager (:class:`Slaves`) that frees them
all, and after an fmi2Fatal makes no further call on any instance.
"""
from __future__ import annotations

import collections
import ctypes
import shutil
import signal as _signal
import sys
import tempfile
import threading
from pathlib import Path

from . import fmilog
from .connections import COMPONENTS
from .errors import UserError

__all__ = ["BUILD_HINT", "DEFAULT_FMU_DIR", "STATUS", "DeferredInterrupt", "FmuError", "LogBook", "Slave",
           "Slaves", "fmu_paths", "load_slaves"]

DEFAULT_FMU_DIR = Path("models")      # relative to the current folder, where `piezo-fmu build` puts them
BUILD_HINT = "build them first: piezo-fmu build --out-dir DIR"
STATUS = ("ok", "warning", "discard", "error", "fatal", "pending")


class FmuError(UserError):
    """An FMU could not be loaded or an FMI call failed; the message carries the FMU's log."""


# -- FMU paths ------------------------------------------------------------------------------------

def fmu_paths(fmus=None, names=tuple(COMPONENTS)) -> dict:
    """``{name: Path}`` of the FMUs, from a folder (``<folder>/<name>.fmu``) or a dict of paths.

    Raises :class:`UserError` (one line, with the remedy) when a file is missing.
    """
    if fmus is None:
        fmus = DEFAULT_FMU_DIR
    if isinstance(fmus, (str, Path)):
        folder = Path(fmus)
        if not folder.is_dir():
            raise UserError(f"{folder}: FMU folder not found; {BUILD_HINT}")
        paths = {n: folder / f"{n}.fmu" for n in names}
    else:
        paths = {}
        for n in names:
            if n not in fmus:
                raise UserError(f"no FMU given for {n} (expected keys {', '.join(names)})")
            paths[n] = Path(fmus[n])
    missing = [str(p) for p in paths.values() if not p.is_file()]
    if missing:
        raise UserError(f"{', '.join(missing)}: not found; {BUILD_HINT}")
    return paths


# -- one FMU instance driven through raw ctypes calls ---------------------------------------------

_c_double_p = ctypes.POINTER(ctypes.c_double)
_c_uint_p = ctypes.POINTER(ctypes.c_uint)
_c_int_p = ctypes.POINTER(ctypes.c_int)


class LogBook:
    """Collects the FMUs' log messages (per instance, the last few) from the process-wide logger
    of :mod:`piezo_fmu.fmilog` (never a per-run native callback: see that module)."""

    KEEP = 25

    def __init__(self):
        self.messages = collections.defaultdict(lambda: collections.deque(maxlen=self.KEEP))
        self._token = fmilog.listen(self._log)
        self.callbacks = fmilog.callbacks()

    def _log(self, instance, status, category, text):
        name = instance or "?"
        # one line per message (the CLI reports errors on one line)
        text = " | ".join(line.strip() for line in text.strip().splitlines() if line.strip())
        self.messages[name].append((status, text))

    def close(self):
        fmilog.unlisten(self._token)

    def describe(self, name, min_status=1):
        """The instance's logged messages (warnings and worse; else the last ones), one per line."""
        msgs = list(self.messages.get(name, ()))
        picked = [m for m in msgs if m[0] >= min_status] or msgs[-3:]
        return "; ".join(f"[{STATUS[s] if 0 <= s < len(STATUS) else s}] {t}" for s, t in picked)


class Slave:
    """One co-simulation FMU instance with the FMI 2.0 calls bound to ctypes.

    Use :meth:`bind` to get preallocated arrays for batched ``fmi2SetReal``/``fmi2GetReal``.
    """

    def __init__(self, name, path, logbook: LogBook):
        from fmpy import extract, read_model_description
        from fmpy.fmi2 import FMU2Slave

        self.name = name
        self.path = Path(path)
        self.log = logbook
        self.state = "new"
        self.unzip = None
        self.fmu = None
        try:
            md = read_model_description(str(path), validate=False)
        except Exception as exc:  # noqa: BLE001 - fmpy raises bare Exception
            raise FmuError(f"{path}: not a readable FMU ({exc}); {BUILD_HINT}") from None
        if md.fmiVersion != "2.0" or md.coSimulation is None:
            raise FmuError(f"{path}: not an FMI 2.0 co-simulation FMU; {BUILD_HINT}")
        self.md = md
        self.variables = {v.name: v for v in md.modelVariables}
        self.unzip = tempfile.mkdtemp(prefix=f"piezo-fmu-{name}-")
        try:
            extract(str(path), unzipdir=self.unzip)
            self.fmu = FMU2Slave(guid=md.guid, unzipDirectory=self.unzip,
                                 modelIdentifier=md.coSimulation.modelIdentifier, instanceName=name)
        except Exception as exc:  # noqa: BLE001 - fmpy raises bare Exception
            self.close()
            raise FmuError(f"{path}: cannot load the FMU ({exc}); {BUILD_HINT}") from None
        # the calls keep the GIL (a PyDLL view of the loaded library): the native runtime needs
        # no GIL operation for such a caller, and releasing it around each call cost 1.3-1.9 us
        # per step
        dll = ctypes.PyDLL(self.fmu.dll._name, handle=self.fmu.dll._handle)
        vp, sz, dbl, i = ctypes.c_void_p, ctypes.c_size_t, ctypes.c_double, ctypes.c_int

        def bind(fname, argtypes):
            f = getattr(dll, fname)
            f.argtypes = argtypes
            f.restype = ctypes.c_int
            return f

        self.set_real = bind("fmi2SetReal", [vp, _c_uint_p, sz, _c_double_p])
        self.get_real = bind("fmi2GetReal", [vp, _c_uint_p, sz, _c_double_p])
        self.set_integer = bind("fmi2SetInteger", [vp, _c_uint_p, sz, _c_int_p])
        self.get_integer = bind("fmi2GetInteger", [vp, _c_uint_p, sz, _c_int_p])
        self.do_step = bind("fmi2DoStep", [vp, dbl, dbl, i])
        self._setup = bind("fmi2SetupExperiment", [vp, i, dbl, dbl, i, dbl])
        self._enter = bind("fmi2EnterInitializationMode", [vp])
        self._exit = bind("fmi2ExitInitializationMode", [vp])
        self._terminate = bind("fmi2Terminate", [vp])
        # (fmi2SetReal, fmi2DoStep, fmi2GetReal) without argtypes for the stepping loop: call them
        # with (c_void_p, c_uint array, c_size_t, c_double array) and (c_void_p, c_double,
        # c_double, c_int) objects only
        self.hot = tuple(self._raw(dll, f) for f in ("fmi2SetReal", "fmi2DoStep", "fmi2GetReal"))
        try:
            self.fmu.instantiate(callbacks=logbook.callbacks, loggingOn=True)
        except Exception:  # noqa: BLE001 - fmpy raises bare Exception
            detail = logbook.describe(name)
            self.close()
            raise FmuError(f"{name} ({path}): fmi2Instantiate failed"
                           + (f": {detail}" if detail else "")) from None
        self.c = ctypes.c_void_p(self.fmu.component)
        self.state = "instantiated"

    @staticmethod
    def _raw(dll, name):
        f = dll[name]            # a new function object (attribute access shares one with argtypes)
        f.restype = ctypes.c_int
        return f

    # -- variables ------------------------------------------------------------------------------
    def variable(self, name):
        v = self.variables.get(name)
        if v is None:
            raise FmuError(f"{self.path}: has no variable {name!r} (the FMU does not match "
                           f"piezo_fmu.connections); {BUILD_HINT}")
        return v

    def start_value(self, name):
        v = self.variable(name)
        if v.start is None:
            return None
        return int(v.start) if v.type == "Integer" else float(v.start)

    def bind(self, names):
        """``(vr array, value array, n)`` for a batch of Real variables (preallocated ctypes arrays)."""
        n = len(names)
        vr = (ctypes.c_uint * max(n, 1))(*[self.variable(x).valueReference for x in names])
        values = (ctypes.c_double * max(n, 1))(*[float(self.variable(x).start or 0.0) for x in names])
        return vr, values, n

    # -- calls ----------------------------------------------------------------------------------
    def check(self, status, what, t=None):
        """Raise :class:`FmuError` with the FMU's log for a status worse than warning."""
        if status <= 1:
            return
        self.state = "fatal" if status == 4 else "failed"
        label = STATUS[status] if 0 <= status < len(STATUS) else str(status)
        at = f" at t={t:.9g} s" if t is not None else ""
        detail = self.log.describe(self.name)
        raise FmuError(f"{self.name}: {what} failed{at} (status {label})"
                       + (f": {detail}" if detail else " (the FMU logged nothing)"))

    def set_values(self, values: dict):
        """Set start values ``{name: value}`` (Real and Integer) with one call per type."""
        reals = [(self.variable(k).valueReference, float(v)) for k, v in values.items()
                 if self.variable(k).type == "Real"]
        ints = [(self.variable(k).valueReference, int(v)) for k, v in values.items()
                if self.variable(k).type in ("Integer", "Enumeration")]
        other = [k for k in values if self.variable(k).type not in ("Real", "Integer", "Enumeration")]
        if other:
            raise FmuError(f"{self.name}: cannot set {', '.join(other)} (not Real or Integer)")
        if reals:
            vr = (ctypes.c_uint * len(reals))(*[r[0] for r in reals])
            val = (ctypes.c_double * len(reals))(*[r[1] for r in reals])
            self.check(self.set_real(self.c, vr, len(reals), val),
                       "fmi2SetReal of the start values " + ", ".join(
                           k for k in values if self.variables[k].type == "Real"))
        if ints:
            vr = (ctypes.c_uint * len(ints))(*[r[0] for r in ints])
            val = (ctypes.c_int * len(ints))(*[r[1] for r in ints])
            self.check(self.set_integer(self.c, vr, len(ints), val),
                       "fmi2SetInteger of the start values " + ", ".join(
                           k for k in values if self.variables[k].type != "Real"))

    def get_values(self, names):
        """Current values of Real/Integer variables as a dict (initialisation and reporting)."""
        out = {}
        for k in names:
            v = self.variable(k)
            vr = (ctypes.c_uint * 1)(v.valueReference)
            if v.type == "Real":
                val = (ctypes.c_double * 1)()
                self.check(self.get_real(self.c, vr, 1, val), f"fmi2GetReal({k})")
            else:
                val = (ctypes.c_int * 1)()
                self.check(self.get_integer(self.c, vr, 1, val), f"fmi2GetInteger({k})")
            out[k] = val[0]
        return out

    def setup(self, t0, stop=None):
        self.check(self._setup(self.c, 0, 0.0, t0, 0 if stop is None else 1,
                               0.0 if stop is None else stop), "fmi2SetupExperiment", t0)

    def enter_initialization(self, t0):
        self.check(self._enter(self.c), "fmi2EnterInitializationMode", t0)
        self.state = "initialization"

    def exit_initialization(self, t0):
        self.check(self._exit(self.c), "fmi2ExitInitializationMode", t0)
        self.state = "step"

    def close(self):
        """Terminate and free the instance (not after a fatal status: the FMI forbids any call)."""
        try:
            if self.fmu is not None and self.state not in ("new", "fatal"):
                if self.state == "step":
                    self._terminate(self.c)
                self.fmu.freeInstance()  # fmi2FreeInstance and unload the library
            elif self.fmu is not None and self.state == "new":
                self.fmu.freeLibrary()
        finally:
            self.state = "closed" if self.state != "fatal" else "fatal"
            self.fmu = None
            if self.unzip:
                shutil.rmtree(self.unzip, ignore_errors=True)
                # the runtime puts each FMU's resources/ on sys.path (its modules): take ours off
                sys.path[:] = [p for p in sys.path if not str(p).startswith(self.unzip)]
                self.unzip = None


class Slaves(dict):
    """name -> :class:`Slave`; a context manager that frees them all."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        fatal = any(s.state == "fatal" for s in self.values())
        for s in self.values():
            if fatal and s.state != "closed":
                s.state = "fatal"   # after a fatal status no FMI call on any instance
            s.close()


class DeferredInterrupt:
    """Ctrl-C during a run is taken at the next chunk boundary instead of inside FMU code.

    A ``KeyboardInterrupt`` raised while an FMU's Python code runs would fail that FMI call (the
    native runtime returns fmi2Error and re-posts the interrupt; pythonfmu's binary returned
    fmi2Fatal); with this handler the master raises it itself, between FMI calls, and the
    instances are freed normally.
    """

    def __enter__(self):
        self.hit = False
        self.old = None
        if (threading.current_thread() is threading.main_thread()
                and _signal.getsignal(_signal.SIGINT) is _signal.default_int_handler):
            self.old = _signal.signal(_signal.SIGINT, self._handler)
        return self

    def _handler(self, signum, frame):
        self.hit = True

    def check(self):
        if self.hit:
            self.hit = False
            raise KeyboardInterrupt

    def __exit__(self, *exc):
        if self.old is not None:
            _signal.signal(_signal.SIGINT, self.old)
        if exc[0] is None:
            self.check()


def load_slaves(paths: dict) -> Slaves:
    log = LogBook()
    slaves = Slaves()
    slaves.log = log
    try:
        for name, path in paths.items():
            slaves[name] = Slave(name, path, log)
    except BaseException:
        slaves.close()
        raise
    return slaves
