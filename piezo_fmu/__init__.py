"""piezo-fmu: a piezoelectric stack actuator with hysteresis and an integrated quartz force sensor
(Shan et al., Sensors 2021) as plain Python physics, FMI 2.0 co-simulation FMUs, and tools.

The Python API underneath the ``piezo-fmu`` command::

    from piezo_fmu import load_model, simulate, Signal
    model = load_model()                                   # models/paper.toml
    res = simulate(model, Signal("sine", 45, 45, 10), 0.3)  # 0-90 V reference at 10 Hz
    res["x"], res["x_ref"]                                  # displacement and reference [um]
"""
__version__ = "0.1.0"

from .errors import UserError  # noqa: E402
from .model import Model, ModelError, dump_model, load_model, validate_model  # noqa: E402
from .simulate import Signal, SimResult, simulate  # noqa: E402

__all__ = ["UserError", "Model", "ModelError", "load_model", "validate_model", "dump_model",
           "Signal", "SimResult", "simulate", "__version__"]
