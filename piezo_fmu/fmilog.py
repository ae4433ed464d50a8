"""One FMI logger for every FMU host in the process.

fmpy formats the FMUs' printf-style log messages in a small native proxy
(``fmpy.logging.addLoggerProxy``). The proxy keeps the Python logger of the **last** registration
in a single process-global variable and routes every FMU's messages there, whatever callback struct
the FMU was instantiated with. A host that registers a temporary callback which is later garbage
collected leaves that global dangling: the next log message of *any* FMU in the process jumps into
freed memory (we hit exactly this segfault when a co-simulation run was followed by other FMU
work in the same process).

So there is one logger here, kept alive for the life of the process, registered again before
each instantiation (fmpy registers its own default at import), and it dispatches every message to
the listeners that want it. Listeners are held weakly, so a forgotten one costs nothing.

The second process-global trap is pythonfmu's binary (0.7.0): it keeps the embedded interpreter's
state in a static ``std::shared_ptr`` and resets it again from an ELF destructor
(``finalizePythonInterpreter``) that runs at process exit *after* the C++ static destructors have
already freed it: a write into freed memory for every pythonfmu FMU library still loaded (dlclose
does not unload them). Depending on the heap's layout the process then aborts at exit
("corrupted double-linked list", exit status 134) after a run that succeeded. At interpreter exit
:func:`release_pythonfmu_libraries` calls that exported reset for every loaded pythonfmu library
while its static is still alive, so the exit-time call finds it empty.
"""
from __future__ import annotations

import atexit
import ctypes
import itertools
import os
import weakref

from fmpy import calloc, free
from fmpy.fmi2 import (
    fmi2CallbackAllocateMemoryTYPE,
    fmi2CallbackFreeMemoryTYPE,
    fmi2CallbackFunctions,
    fmi2CallbackLoggerTYPE,
)

__all__ = ["callbacks", "listen", "unlisten", "release_pythonfmu_libraries"]

_listeners: dict = {}
_tokens = itertools.count()


def _dispatch(env, instance, status, category, message):
    try:
        inst = instance.decode("utf-8", "replace") if instance else ""
        cat = category.decode("utf-8", "replace") if category else ""
        text = message.decode("utf-8", "replace") if message else ""
        for token, ref in list(_listeners.items()):
            fn = ref()
            if fn is None:
                _listeners.pop(token, None)
            else:
                fn(inst, int(status), cat, text)
    except Exception:  # noqa: BLE001 - an exception must never cross back into C
        pass


_LOGGER = fmi2CallbackLoggerTYPE(_dispatch)
_CALLBACKS = fmi2CallbackFunctions()
_CALLBACKS.logger = _LOGGER
_CALLBACKS.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
_CALLBACKS.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
_PROXIED = fmi2CallbackFunctions()       # the struct handed to FMUs (logger = the native proxy)


def callbacks():
    """The callback struct to instantiate FMUs with (re-registers the process-wide logger)."""
    try:
        from fmpy.logging import addLoggerProxy
    except Exception:  # noqa: BLE001 - no native proxy: messages arrive unformatted
        return _CALLBACKS
    ctypes.memmove(ctypes.byref(_PROXIED), ctypes.byref(_CALLBACKS), ctypes.sizeof(_CALLBACKS))
    addLoggerProxy(ctypes.byref(_PROXIED))
    return _PROXIED


def listen(fn) -> int:
    """Call ``fn(instance, status, category, message)`` for every FMU log message; returns a token.

    Bound methods are held through :class:`weakref.WeakMethod`, functions through a weak reference.
    """
    ref = weakref.WeakMethod(fn) if hasattr(fn, "__self__") else weakref.ref(fn)
    token = next(_tokens)
    _listeners[token] = ref
    return token


def unlisten(token):
    _listeners.pop(token, None)


def release_pythonfmu_libraries() -> int:
    """Reset the interpreter-state holder of every loaded pythonfmu FMU library (see the module
    docstring); returns how many. Only libraries already in the process are touched
    (``RTLD_NOLOAD``); instances still alive keep their own reference, so this is safe at any
    time, and it is what the library's exit handler would do if it ran in the right order."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as f:
            paths = {line.split(None, 5)[5].strip().removesuffix(" (deleted)")
                     for line in f if line.count(" ") >= 5 and "/binaries/" in line}
    except OSError:          # not Linux: the bug is in pythonfmu's Linux exit path only
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


atexit.register(release_pythonfmu_libraries)
