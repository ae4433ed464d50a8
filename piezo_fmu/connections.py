"""The wiring of the three FMUs, declared once: used by the co-simulation master and the SSP export.

Components (instance names in the SSP and the master) and their interface variables::

    Actuator     input  uc [V]          outputs x [um], F [N], ua [V]
    Sensor       input  F [N]           output  us [V]
    Compensator  inputs x_ref [um], us [V]   outputs uc [V], x_target [um]

``CONNECTIONS`` are (from component, from variable, to component, to variable).
``ORDER`` is the Gauss-Seidel order (each component uses the outputs just computed).
``EXTERNAL_INPUTS`` are inputs the master drives itself (a reference table); with the
Compensator's built-in reference generator they are left at their start values.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Port", "COMPONENTS", "CONNECTIONS", "ORDER", "EXTERNAL_INPUTS", "RECORDED"]


@dataclass(frozen=True)
class Port:
    name: str
    causality: str   # "input" or "output"
    unit: str
    description: str


COMPONENTS = {
    "Actuator": (
        Port("uc", "input", "V", "amplifier command voltage"),
        Port("x", "output", "um", "push-rod displacement"),
        Port("F", "output", "N", "force on the quartz sensor (as mechanics.pickoff says)"),
        Port("ua", "output", "V", "amplifier output (stack) voltage"),
    ),
    "Sensor": (
        Port("F", "input", "N", "force through the quartz wafer"),
        Port("us", "output", "V", "quartz sensor voltage"),
    ),
    "Compensator": (
        Port("x_ref", "input", "um", "reference displacement (used when reference.signal = 0)"),
        Port("us", "input", "V", "quartz sensor voltage"),
        Port("uc", "output", "V", "amplifier command voltage"),
        Port("x_target", "output", "um", "reference displacement the compensator tracks"),
    ),
}

CONNECTIONS = (
    ("Actuator", "F", "Sensor", "F"),
    ("Sensor", "us", "Compensator", "us"),
    ("Compensator", "uc", "Actuator", "uc"),
)

ORDER = ("Actuator", "Sensor", "Compensator")

EXTERNAL_INPUTS = (("Compensator", "x_ref"),)

# Output columns of a co-simulation run and where they come from (same columns as simulate).
RECORDED = (
    ("x_ref", "Compensator", "x_target"),
    ("x", "Actuator", "x"),
    ("us", "Sensor", "us"),
    ("uc", "Compensator", "uc"),
    ("ua", "Actuator", "ua"),
    ("F", "Actuator", "F"),
)
