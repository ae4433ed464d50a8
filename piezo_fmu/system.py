"""Build the physics units (actuator, sensor, compensator) from a validated :class:`Model`.

The mapping itself lives in :mod:`piezo_fmu.core.units` (it also runs inside the FMUs); these are
the model-typed entry points used by the monolithic model, identification and diagnose.
"""
from __future__ import annotations

import math

from .core.units import actuator_from, compensator_from, sensor_from
from .model import Model

__all__ = ["make_actuator", "make_sensor", "make_compensator", "displacement_gain"]


def make_actuator(model: Model):
    return actuator_from(model.sections)


def make_sensor(model: Model, noise=True):
    return sensor_from(model.sections, noise)


def make_compensator(model: Model, **kw):
    return compensator_from(model.sections, **kw)


def displacement_gain(model: Model) -> float:
    """Static displacement per free stroke of the device, k_a / (k_a + k_f) times the creep gain [1]."""
    me = model["mechanics"]
    return me["k_a"] / (me["k_a"] + me["k_f"]) * (1.0 + math.fsum(model["creep"]["gains"]))
