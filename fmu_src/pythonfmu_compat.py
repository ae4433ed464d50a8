"""What a slave needs when it runs under pythonfmu 0.7.0's binary instead of the native runtime.

``piezo-fmu build`` bundles the project's own FMI runtime (``fmu_src/runtime``); only when no C
compiler or no Python headers are available does it fall back to pythonfmu's export binary.
That binary has two defects that would take a host down, and this module is the slave's answer
to both; it is active only under that binary (:func:`install` is called when the wrapper's
``logger`` argument is present) and never under the native runtime:

1. On every Python exception the wrapper's ``handle_py_exception`` drops one reference to the
   slave class, the instance and its log queue without having taken them: the second error of
   an instance frees the log queue and the next call crashes the host. :func:`pay_references`
   takes them in advance, before ``_fail`` raises (only for the wrapper versions listed in
   :data:`WRAPPERS_STEALING_REFS`; the build records the bundled binary's version).
2. At process exit the binary resets its interpreter holder (a static ``std::shared_ptr``) from
   an ELF destructor that runs after the C++ static destructors have freed it: a write into
   freed memory that aborts some exits ("corrupted double-linked list"). In a Python host
   (fmpy, libcosimpy) the holder is empty (the host owns the interpreter), so resetting it early,
   from a Python exit handler, is harmless and leaves the late reset nothing to free. In a host
   that is not Python the binary's own interpreter runs the exit handlers from inside that very
   destructor, so nothing is registered there.
"""
from __future__ import annotations

import atexit
import ctypes
import os
import sys

__all__ = ["WRAPPERS_STEALING_REFS", "install", "pay_references", "reset_interpreter_holders"]

WRAPPERS_STEALING_REFS = frozenset({"0.7.0"})

_incref = ctypes.pythonapi.Py_IncRef
_incref.argtypes = [ctypes.py_object]
_incref.restype = None
_exit_handler = []


def pay_references(slave):
    """Take the three references the 0.7.0 wrapper will drop for the exception about to be raised."""
    for obj in (type(slave), slave, slave.log_queue):
        _incref(obj)


def _no_debt(slave):
    return None


def install(slave, wrapper_version):
    """The error hook for a slave instantiated by pythonfmu's binary of ``wrapper_version``; also
    registers the exit-time reset once per process when the host is a Python program."""
    if not _exit_handler and sys.orig_argv:     # empty when the binary embeds its own interpreter
        _exit_handler.append(atexit.register(reset_interpreter_holders))
    return pay_references if wrapper_version in WRAPPERS_STEALING_REFS else _no_debt


def reset_interpreter_holders() -> int:
    """Reset the interpreter holder of every pythonfmu library in the process (see item 2 of the
    module docstring); returns how many. Only libraries already loaded are touched
    (``RTLD_NOLOAD``); native-runtime FMUs export no such function and are skipped."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as f:
            paths = {line.split(None, 5)[5].strip().removesuffix(" (deleted)")
                     for line in f if line.count(" ") >= 5 and "/binaries/" in line}
    except OSError:          # not Linux: the defect is in pythonfmu's Linux exit path only
        return 0
    done = 0
    for path in sorted(p for p in paths if p.endswith(".so")):
        try:
            lib = ctypes.CDLL(path, mode=os.RTLD_NOLOAD | os.RTLD_LAZY)
        except OSError:
            continue
        reset = getattr(lib, "finalizePythonInterpreter", None)
        if reset is not None:
            reset.restype = None
            reset.argtypes = []
            reset()
            done += 1
    return done
