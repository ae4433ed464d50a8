"""Compensator FMU: inverse-model feedforward + PID feedback (piezo_fmu.core.control.Compensator).

A sampled controller. Inputs ``x_ref`` [um] (used when ``reference.signal`` = 0) and ``us`` [V];
outputs ``uc`` [V] (the command for the next interval) and ``x_target`` [um] (the reference it
tracks). do_step(t, h) computes the command from the inputs as set (in Gauss-Seidel order: the
values at t+h) and the reference at t+h: ``unit.step(t + h, x_ref, us, h)``.
exit_initialization_mode computes the initial command from the inputs at the start time
(``unit.initialize``). All control law code is in the core.
"""
from slavebase import SlaveBase as Fmi2Slave

from piezo_fmu.core import units
from piezo_fmu.core.compiled import ENGINES, compile_unit
from piezo_fmu.core.control import INVERSES, MODES, SIGNALS


class Compensator(Fmi2Slave):
    description = ("Hysteresis compensator: built-in reference generator, exact inverse "
                   "Prandtl-Ishlinskii feedforward with optional inverse dynamics, PID feedback on "
                   "the quartz sensor signal; inputs x_ref, us, outputs command uc and x_target "
                   "(after Shan et al., Sensors 2021)")
    # standalone run: one period of the built-in 10 Hz reference (no plant: the PID winds up)
    DEFAULT_EXPERIMENT = {"startTime": 0.0, "stopTime": 0.1, "stepSize": 1e-4}
    COMPILE = staticmethod(compile_unit)     # simulation.engine = numba
    PARAMETERS = {"compensator": None, "compensator.hysteresis": None, "compensator.dynamics": None}
    CODES = {"compensator.mode": MODES, "compensator.inverse": INVERSES}
    # tunable: gains, calibration, limits and the reference (no state depends on them; a change
    # acts from the next step). Fixed: mode and inverse (no bumpless transfer: the inverse model's
    # memory is only tracked while it is in use), the inverse model and G_inv (their states).
    TUNABLE = ("compensator.k_ideal", "compensator.k_amp", "compensator.sensor_gain",
               "compensator.sensor_offset", "compensator.Kp", "compensator.Ki", "compensator.Kd",
               "compensator.Tf", "compensator.uc_min", "compensator.uc_max")
    CHECK = staticmethod(units.check_sections)   # the same consistency rules as model files
    # the paper's 10 Hz closed-loop experiment: a 0-90 V sine (45 V about 45 V) from its minimum
    REFERENCE = (("signal", SIGNALS["sine"]), ("amplitude", 45.0), ("offset", 45.0), ("freq", 10.0),
                 ("phase", -90.0))

    def define(self):
        self.add_input("x_ref", 0.0, "um", "reference displacement (used when reference.signal = 0)")
        self.add_input("us", 0.0, "V", "quartz sensor voltage")
        self.add_output("uc", "V", "amplifier command voltage")
        self.add_output("x_target", "um", "reference displacement the compensator tracks")
        self.add_model_parameters(self.PARAMETERS, self.TUNABLE, self.CODES)
        r = dict(self.REFERENCE)
        codes = ", ".join(f"{c} {n}" for n, c in sorted(SIGNALS.items(), key=lambda i: i[1]))
        self.add_parameter("reference.signal", r["signal"], None,
                           f"reference generator: {codes} (0: use the input x_ref)", tunable=True,
                           integer=True, lo=min(SIGNALS.values()), hi=max(SIGNALS.values()), codes=SIGNALS)
        self.add_parameter("reference.amplitude", r["amplitude"], "V",
                           "amplitude of the reference voltage u_ref (x_ref = k_ideal u_ref)", tunable=True)
        self.add_parameter("reference.offset", r["offset"], "V", "offset of the reference voltage u_ref",
                           tunable=True)
        self.add_parameter("reference.freq", r["freq"], "Hz", "frequency of the sine or triangle",
                           tunable=True, check="nonneg")
        self.add_parameter("reference.phase", r["phase"], "deg",
                           "phase of the sine or triangle (-90: starts at its minimum)", tunable=True)
        self.add_engine_parameter(ENGINES)

    def make_unit(self, sections):
        r = sections["reference"]
        return units.compensator_from(sections, signal=r["signal"], amplitude=r["amplitude"],
                                      offset=r["offset"], freq=r["freq"], phase_deg=r["phase"])

    def initialize(self, t0):
        u = self.unit
        u.reset()
        self.uc = u.initialize(t0, self.x_ref, self.us)
        self.x_target = float(u.out[1])

    def step(self, t, h):
        u = self.unit
        uc = u.step(t + h, self.x_ref, self.us, h)
        xt = float(u.out[1])            # a list, or a NumPy view under the compiled engine
        if (uc - uc) + (xt - xt) != 0.0:
            return False
        self.uc = uc
        self.x_target = xt
        return True

    def describe_outputs(self):
        o = self.unit.out
        return f"uc={float(o[0])!r}, x_target={float(o[1])!r} for inputs x_ref={self.x_ref!r}, us={self.us!r}"
