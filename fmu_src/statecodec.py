"""The exact, deterministic codec of the slaves' FMU states (``fmi2SerializeFMUstate``).

An FMU state is plain data (dicts, lists, tuples, numbers, strings, NumPy arrays and scalars).
It is written as compact JSON: ``json`` writes floats with ``float.__repr__``, which round-trips
bit-exactly (also -0.0, and inf/nan as Infinity/NaN), and big ints are exact. Types JSON would
silently change are tagged::

    {"__t": [...]}                          tuple
    {"__d": [[k, v], ...]}                  dict with non-str keys (or keys starting "__")
    {"__nd": [...], "dt": str, "sh": [...]} NumPy array (bool, int, uint, float)
    {"__ns": v, "dt": str}                  NumPy scalar

so ``state_loads(state_dumps(s))`` equals ``s`` in type and bits, and the same state always gives
the same bytes. Bundled into every FMU next to ``slavebase`` (standard library only; NumPy is
used when the state holds NumPy objects).
"""
from __future__ import annotations

import json
import sys

__all__ = ["InvalidState", "State", "state_dumps", "state_loads"]

_PLAIN = (str, int, float, bool, type(None))


def _encode(o):
    t = type(o)
    if t in _PLAIN:                   # exact type: np.float64 (a float subclass) is tagged
        return o
    if t is list:
        return [_encode(x) for x in o]
    if t is tuple:
        return {"__t": [_encode(x) for x in o]}
    if t is dict or t is State:
        if all(type(k) is str and not k.startswith("__") for k in o):
            return {k: _encode(v) for k, v in o.items()}
        return {"__d": [[_encode(k), _encode(v)] for k, v in o.items()]}
    np = sys.modules.get("numpy")
    if np is not None:
        if t is np.ndarray:
            if o.dtype.kind not in "biuf":
                raise TypeError(f"unsupported ndarray dtype {o.dtype}")
            return {"__nd": o.ravel().tolist(), "dt": o.dtype.str, "sh": list(o.shape)}
        if isinstance(o, np.generic):
            return {"__ns": o.item(), "dt": o.dtype.str}
    raise TypeError(f"cannot serialize an object of type {t.__name__}")


def _decode(o):
    t = type(o)
    if t is list:
        return [_decode(x) for x in o]
    if t is dict:
        if "__t" in o:
            return tuple(_decode(x) for x in o["__t"])
        if "__d" in o:
            return {_decode(k): _decode(v) for k, v in o["__d"]}
        if "__nd" in o:
            import numpy as np
            return np.array(o["__nd"], dtype=np.dtype(o["dt"])).reshape(o["sh"])
        if "__ns" in o:
            import numpy as np
            return np.dtype(o["dt"]).type(o["__ns"])
        return {k: _decode(v) for k, v in o.items()}
    return o


def state_dumps(state) -> bytes:
    """Serialize a state object (plain data) to compact JSON bytes, exactly and deterministically."""
    return json.dumps(_encode(state), separators=(",", ":"), allow_nan=True).encode("utf-8")


def state_loads(data: bytes):
    """The state object of :func:`state_dumps` bytes (raises on bytes it did not write)."""
    return _decode(json.loads(bytes(data).decode("utf-8")))


class State(dict):
    """An FMU state as a slave hands it out; ``owner`` (a weak reference to the slave) lets the
    pythonfmu fallback binary's static serializer report an error on the right instance."""
    __slots__ = ("owner",)


class InvalidState(dict):
    """What deserializing returns for bytes it cannot decode: the deserializer has no instance to
    report to (and must not raise), so ``fmi2SetFMUstate`` with it fails cleanly instead."""
    __slots__ = ()
