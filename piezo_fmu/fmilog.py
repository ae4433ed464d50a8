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

The FMUs' native runtime (``fmu_src/runtime``) needs nothing else from the host: it starts or
adopts the interpreter, never finalizes it, and is safe at any exit order (the exit-time
workaround for pythonfmu's binary that used to live here is gone; a fallback FMU built with
pythonfmu's binary carries its own, see ``fmu_src/pythonfmu_compat.py``).
"""
from __future__ import annotations

import ctypes
import itertools
import weakref

from fmpy import calloc, free
from fmpy.fmi2 import (
    fmi2CallbackAllocateMemoryTYPE,
    fmi2CallbackFreeMemoryTYPE,
    fmi2CallbackFunctions,
    fmi2CallbackLoggerTYPE,
)

__all__ = ["callbacks", "listen", "unlisten"]

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
