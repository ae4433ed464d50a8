"""Sensor FMU: the quartz force sensor (piezo_fmu.core.plant.Sensor, paper eq. 3).

Input ``F`` [N] (the force at the end of the step; it moves linearly over the step); output
``us`` [V]. do_step(t, h) is ``unit.step(F, h)``; the initial output is the sensor at rest under
the initial force (``unit.reset(F)``). All physics is in the core.
"""
from slavebase import SlaveBase as Fmi2Slave

from piezo_fmu.core import units


class Sensor(Fmi2Slave):
    description = ("x-cut quartz force sensor integrated in the piezo stack (eq. 3), with cable "
                   "capacitance, optional charge leakage, offset and white noise; input force F, "
                   "output voltage us (after Shan et al., Sensors 2021)")
    # standalone run: the sensor at rest (F = 0) shows its noise
    DEFAULT_EXPERIMENT = {"startTime": 0.0, "stopTime": 0.1, "stepSize": 1e-4}
    PARAMETERS = {"sensor": None}
    # tunable: offset and noise level (additive; the noise sequence keeps its position) and the
    # leakage time constant (the leaked voltage stays valid). Fixed: what sets the sensitivity
    # (d11, geometry, C_load) and the seed.
    TUNABLE = ("sensor.offset", "sensor.noise_std", "sensor.tau_leak")

    def define(self):
        self.add_input("F", 0.0, "N", "force through the quartz wafer")
        self.add_output("us", "V", "quartz sensor voltage")
        self.add_model_parameters(self.PARAMETERS, self.TUNABLE)

    def make_unit(self, sections):
        return units.sensor_from(sections)

    def initialize(self, t0):
        u = self.unit
        u.reset(self.F)
        self.us = u.us

    def step(self, t, h):
        us = self.unit.step(self.F, h)
        if us - us != 0.0:
            return False
        self.us = us
        return True

    def describe_outputs(self):
        return f"us={self.unit.us!r} for input F={self.F!r}"
