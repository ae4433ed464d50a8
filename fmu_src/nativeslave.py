"""The slave's side of the calling protocol of the piezo-fmu native FMI runtime (``fmu_src/runtime``).

The FMUs' binary is the project's own C runtime, not pythonfmu's (see ``fmu_src/runtime/runtime.h``).
It instantiates the slave class named in ``resources/piezo_runtime.cfg`` with
``cls(instance_name=..., resources=..., visible=...)`` and then talks to it only through the
``_rt_*`` methods of :class:`NativeSlave` (protocol :data:`PROTOCOL`):

* ``_rt_bind(protocol)`` -> ``(values, control, slots, n_inputs)``. ``values`` (``array('d')``)
  holds the continuous Real inputs, then outputs; ``slots`` (``array('i')``) their value
  references; ``control`` (``array('i')``) says whether ``fmi2GetReal`` (``control[0]``) and
  ``fmi2SetReal`` (``control[1]``) may be served from ``values`` without entering Python (the
  slave rewrites it at every mode change: step mode allows both). The runtime holds a buffer
  view on each array, so they can neither move nor be resized while it uses them.
* ``_rt_do_step(t, h)`` -> status: the hot path (the only Python call of a communication step
  when inputs are set and outputs read through ``values``). ``_rt_bind`` replaces it on the
  instance by a function generated for the slave's own inputs and outputs (the copies unrolled:
  a loop over (index, name) pairs cost ~0.3 us per step and FMU).
* ``_rt_call(method, *args)`` -> ``(status, result)`` for every other FMI function (the checked
  ``set_real``/``get_real`` slow paths, modes, FMU state).

Between calls ``values`` is the truth for the inputs (the runtime writes there, after checking
they are finite) and each entry point first copies them into the slave's attributes; on the way
out it copies the slave's outputs (``_rt_call``: also its inputs) back. Every entry point
returns an FMI status and never raises: an :class:`~slavevars.FmuUsageError` has already been
logged by ``_fail`` and becomes fmi2Error; any other exception is logged here (type, message, the
last frames) and becomes fmi2Error too; the instance stays usable. The runtime forwards the log
queue to the host's logger after each call. A ``KeyboardInterrupt`` (a Python host's Ctrl-C
arriving while the slave runs) is reported as fmi2Error and handed back to the host's main
thread with ``_thread.interrupt_main``.
"""
from __future__ import annotations

import _thread
import traceback
from array import array

from pythonfmu.enums import Fmi2Status  # not re-exported by pythonfmu 0.7.0
from slavevars import FmuUsageError
from statecodec import state_dumps

__all__ = ["PROTOCOL", "NativeSlave"]

PROTOCOL = 1
OK, WARNING, DISCARD, ERROR, FATAL = range(5)


class NativeSlave:
    """Mixin of :class:`slavebase.SlaveBase`: the entry points of the native runtime (see the
    module docstring). Expects ``_vars``, ``_mode``, ``do_step`` and ``log`` of the slave, and
    :meth:`_rt_publish` to be called at every mode change."""

    RT_FAST = None        # {mode: (get without Python, set without Python)}; set by SlaveBase

    def _rt_init(self):
        """Attributes of the protocol (before the slave freezes its attribute set)."""
        self._rt_values = None
        self._rt_control = None
        self._rt_in = ()
        self._rt_out = ()
        self._rt_io = ()
        self.__dict__["_rt_do_step"] = self._rt_do_step   # replaced by _rt_bind

    def _rt_bind(self, protocol):
        if protocol != PROTOCOL:
            raise FmuUsageError(f"the FMU's runtime speaks protocol {protocol}, this slave base "
                                f"protocol {PROTOCOL}: rebuild the FMU")
        ins = [v for v in self._vars.values() if v.type == "Real" and v.causality == "input"]
        outs = [v for v in self._vars.values() if v.type == "Real" and v.causality == "output"]
        d = self.__dict__
        self._rt_values = array("d", [float(d[v.name]) for v in ins + outs])
        self._rt_control = array("i", [0, 0])
        self._rt_in = tuple((i, v.name) for i, v in enumerate(ins))
        self._rt_out = tuple((len(ins) + i, v.name) for i, v in enumerate(outs))
        self._rt_io = self._rt_in + self._rt_out
        self._rt_publish()
        self.__dict__["_rt_do_step"] = self._rt_step_function()
        return self._rt_values, self._rt_control, array("i", [v.vr for v in ins + outs]), len(ins)

    def _rt_step_function(self):
        """``_rt_do_step`` for this slave's inputs and outputs, the copies unrolled (the same
        behaviour as :meth:`_rt_do_step`)."""
        pull = "".join(f"    d[{name!r}] = values[{i}]\n" for i, name in self._rt_in)
        push = "".join(f"    values[{i}] = d[{name!r}]\n" for i, name in self._rt_out)
        source = ("def _rt_do_step(t, h):\n" + pull
                  + "    try:\n        do_step(t, h)\n        status = 0\n"
                  + "    except BaseException as e:  # noqa: BLE001\n"
                  + "        status = error('do_step', e)\n" + push + "    return status\n")
        scope = {"d": self.__dict__, "values": self._rt_values, "do_step": self.do_step,
                 "error": self._rt_error}
        exec(compile(source, f"<{type(self).__name__} runtime step>", "exec"), scope)  # noqa: S102
        return scope["_rt_do_step"]

    def _rt_publish(self):
        """Tell the runtime what it may serve without Python in the current mode."""
        control = self._rt_control
        if control is not None:
            control[0], control[1] = self.RT_FAST[self._mode]

    def _rt_do_step(self, t, h):
        d = self.__dict__
        values = self._rt_values
        for i, name in self._rt_in:
            d[name] = values[i]
        try:
            self.do_step(t, h)
            status = OK
        except BaseException as e:  # noqa: BLE001 - nothing may cross into C as an exception
            status = self._rt_error("do_step", e)
        for i, name in self._rt_out:
            values[i] = d[name]
        return status

    def _rt_call(self, method, *args):
        d = self.__dict__
        values = self._rt_values
        for i, name in self._rt_in:
            d[name] = values[i]
        try:
            result = getattr(self, method)(*args)
            status = OK
        except BaseException as e:  # noqa: BLE001 - nothing may cross into C as an exception
            result = None
            status = self._rt_error(method, e)
        for i, name in self._rt_io:
            values[i] = d[name]
        return status, result

    def _rt_serialize(self, state):
        """``fmi2SerializeFMUstate`` (an error is reported on this instance)."""
        try:
            return state_dumps(dict(state))
        except Exception as e:  # noqa: BLE001 - reported on this instance
            self._fail(f"serialize_fmu_state: {type(e).__name__}: {e}")

    def _rt_error(self, where, e):
        if isinstance(e, FmuUsageError):        # _fail logged it, naming the variable
            return ERROR
        if isinstance(e, KeyboardInterrupt):
            self.log(f"[{self.instance_name}] {where}: interrupted (KeyboardInterrupt); the "
                     "interrupt is passed on to the host", Fmi2Status.error)
            _thread.interrupt_main()
            return ERROR
        text = "".join(traceback.format_exception(e)[-3:]).rstrip()
        self.log(f"[{self.instance_name}] {where}: unexpected {type(e).__name__}: {e}\n{text}",
                 Fmi2Status.error)
        return ERROR
