"""Actuator FMU: drive amplifier + hysteretic piezo stack + mechanics (piezo_fmu.core.plant.Actuator).

Input ``uc`` [V] (held over each communication step); outputs ``x`` [um], ``F`` [N], ``ua`` [V].
do_step(t, h) is ``unit.advance(uc, h)``; the initial outputs are those of the relaxed device at
rest at the start time (``unit.reset(t0)``). All physics is in the core.
"""
from slavebase import SlaveBase as Fmi2Slave

from piezo_fmu.core import units
from piezo_fmu.core.compiled import ENGINES, compile_unit
from piezo_fmu.core.plant import PICKOFFS, RESONANCE_AT, STROKE_PATHS


class Actuator(Fmi2Slave):
    description = ("Piezo stack actuator: drive amplifier (eq. 2), Prandtl-Ishlinskii hysteresis, "
                   "creep, mechanics (eq. 4-5); input amplifier command uc, outputs displacement x, "
                   "force F and stack voltage ua (after Shan et al., Sensors 2021)")
    # standalone run: with the start value uc = 3 V, the amplifier's 30 V step response
    DEFAULT_EXPERIMENT = {"startTime": 0.0, "stopTime": 0.02, "stepSize": 1e-4}
    COMPILE = staticmethod(compile_unit)     # simulation.engine = numba
    PARAMETERS = {"amplifier": None, "hysteresis": None, "creep": None, "mechanics": None,
                  "resonance": None, "drift": None, "simulation": ("actuator_max_step", "stroke_path")}
    # tunable: values that no state variable depends on; a change rebuilds the unit (new
    # discretisation) and carries the state over, effective from the next step. Fixed: delay (the
    # delay line's length), u_norm/thresholds (the play operators' memory), creep, mechanics and
    # resonance (the meaning of their filter states).
    TUNABLE = ("amplifier.k_amp", "amplifier.R", "amplifier.C_a", "amplifier.u_min", "amplifier.u_max",
               "amplifier.I_max", "hysteresis.scale", "hysteresis.weights", "hysteresis.saturation",
               "hysteresis.cells_weights",
               "drift.offset", "drift.rate", "drift.curvature", "drift.time_constant", "simulation.actuator_max_step")
    CHECK = staticmethod(units.check_sections)   # the same consistency rules as model files
    CODES = {"mechanics.pickoff": PICKOFFS, "resonance.position": RESONANCE_AT,
             "simulation.stroke_path": STROKE_PATHS}

    def define(self):
        self.add_input("uc", 3.0, "V", "amplifier command voltage")
        self.add_output("x", "um", "push-rod displacement")
        self.add_output("F", "N", "force on the quartz sensor (as mechanics.pickoff says)")
        self.add_output("ua", "V", "amplifier output (stack) voltage")
        self.add_model_parameters(self.PARAMETERS, self.TUNABLE, self.CODES)
        self.add_engine_parameter(ENGINES)

    def make_unit(self, sections):
        return units.actuator_from(sections)

    def initialize(self, t0):
        u = self.unit
        u.reset(t0)
        o = u.out
        self.x = float(o[0])
        self.F = float(o[1])
        self.ua = float(o[2])

    def step(self, t, h):
        u = self.unit
        u.advance(self.uc, h)
        o = u.out                   # a list, or a NumPy view under the compiled engine
        x = float(o[0])
        F = float(o[1])
        ua = float(o[2])
        if (x - x) + (F - F) + (ua - ua) != 0.0:      # NaN or inf somewhere
            return False
        self.x = x
        self.F = F
        self.ua = ua
        return True

    def describe_outputs(self):
        o = self.unit.out
        return f"x={float(o[0])!r}, F={float(o[1])!r}, ua={float(o[2])!r} for input uc={self.uc!r}"
