"""PassThrough FMU: y = u, on the same base as the piezo FMUs (the benchmark's cost floor)."""
from slavebase import SlaveBase as Fmi2Slave


class PassThrough(Fmi2Slave):
    description = "Trivial pass-through y = u (measures the per-call cost of the FMU machinery)"
    DEFAULT_EXPERIMENT = {"startTime": 0.0, "stopTime": 1.0, "stepSize": 0.01}
    NEEDS_MODEL = False

    def define(self):
        self.add_input("u", 0.0, "1", "input")
        self.add_output("y", "1", "output: the input as set before the last step")

    def initialize(self, t0):
        self.y = self.u

    def step(self, t, h):
        self.y = self.u            # inputs are checked finite when set
        return True
