"""The physics as plain, FMU-free units with explicit state (NumPy only, bundled into the FMUs).

* :mod:`.hysteresis` - play operators, Prandtl-Ishlinskii model and its exact inverse
* :mod:`.linear` - exact discretisation of linear blocks, matrix exponential
* :mod:`.plant` - amplifier, hysteretic stack, mechanics (the actuator) and the quartz sensor
* :mod:`.control` - reference generator, inverse feedforward, PID, the compensator
* :mod:`.buffers` - a unit's data packed in one buffer (what a compiled runner takes)
* :mod:`.compiled` - the same kernels compiled by numba (optional), the packed runners, and
  ``compile_unit`` that switches a unit to them (the units never import this module)
"""
