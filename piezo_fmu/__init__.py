"""piezo-fmu: a piezoelectric stack actuator with hysteresis and an integrated quartz force sensor
(Shan et al., Sensors 2021) as plain Python physics, FMI 2.0 co-simulation FMUs, and tools.

The Python API underneath the ``piezo-fmu`` command::

    from piezo_fmu import load_model, simulate, cosimulate, Signal
    from piezo_fmu.diagnose import diagnose
    model = load_model()                                   # the paper's model (shipped)
    res = simulate(model, Signal("sine", 45, 45, 10), 0.3)  # 0-90 V reference at 10 Hz
    res["x"], res["x_ref"]                                  # displacement and reference [um]
    # the same loop with the three FMUs (built by `piezo-fmu build` into ./models)
    cos = cosimulate("models", Signal("sine", 45, 45, 10), 0.3, step=1e-4, model=model)
    diag = diagnose(["rec.csv"], out="diag")               # what the model misses in a recording

``cosimulate`` is imported on first use (``import piezo_fmu`` stays light: NumPy and the model
format). ``diagnose`` and ``sweep`` live in their subpackages (``piezo_fmu.diagnose.diagnose``,
``piezo_fmu.sweep.sweep``): a top-level name would shadow the subpackage of the same name.
"""
__version__ = "0.1.0"

from .errors import UserError  # noqa: E402
from .model import Model, ModelError, dump_model, load_model, validate_model  # noqa: E402
from .simulate import Signal, SimResult, simulate  # noqa: E402

__all__ = ["UserError", "Model", "ModelError", "load_model", "validate_model", "dump_model",
           "Signal", "SimResult", "simulate", "cosimulate", "__version__"]

# name -> module that defines it, imported when the name is first used
_LAZY = {"cosimulate": "piezo_fmu.cosim"}


def __getattr__(name):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'piezo_fmu' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
