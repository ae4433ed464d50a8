"""The closed loop as an SSP 1.0 package (``models/PiezoSystem.ssp``) that fmpy.ssp and libcosim run.

Layout of the archive::

    SystemStructure.ssd          the system (fmpy reads exactly this name at the archive root)
    resources/Actuator.fmu
    resources/Sensor.fmu
    resources/Compensator.fmu

The SSD has one component per FMU (instance names Actuator, Sensor, Compensator), connectors
with their units (``<ssc:Real unit="um"/>``, units defined in ``ssd:Units``), the connections of
:mod:`piezo_fmu.connections`, and a ``DefaultExperiment`` for the paper's 10 Hz closed-loop run
(0 - 0.3 s) whose fixed step (1e-4 s) is given by the OSP annotation
``osp:FixedStepAlgorithm baseStepSize`` (SSP 1.0 itself has no step size), with
``numWorkerThreads="0"`` (libcosim steps the three FMUs on its calling thread: they share one
embedded Python, so a worker pool could only add hand-offs). The Compensator's
experiment parameters (reference generator, mode, inverse) are bound inline
(``ssd:ParameterBindings``).

Compatibility notes (see the SSP prototype's report):

* libcosim parses the SSD without namespaces, so the prefixes must be literally ``ssd:``,
  ``ssc:``, ``ssv:`` and ``osp:``; every connector needs a type child (``<ssc:Real/>``).
* fmpy.ssp ignores the DefaultExperiment and the parameter bindings (pass ``stop_time``,
  ``step_size`` and :func:`fmpy_parameter_set` to ``simulate_ssp``), and requires every input
  connector declared in the SSD to be connected. The Compensator's ``x_ref`` input is therefore
  not declared: in the SSP run the built-in reference generator drives the loop.

Both fmpy.ssp and libcosim are Jacobi masters: every connection adds a step of delay, two more in
the feedback path than :mod:`piezo_fmu.cosim`'s Gauss-Seidel. The PID is designed for that
(:mod:`piezo_fmu.control_design`): at the default 1e-4 s the loop with the two extra delays keeps
a 45.6 deg phase margin and 6.3 dB gain margin, and a Jacobi run differs from the Gauss-Seidel run
by about 0.7 % of the stroke (shrinking with the step). A PID tuned for Gauss-Seidel alone
(crossover 1.5 kHz) had a phase margin of -48 deg there and ran into a limit cycle.
"""
from __future__ import annotations

import io
import math
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

from .connections import COMPONENTS, CONNECTIONS, EXTERNAL_INPUTS
from .core.control import INVERSES, MODES, SIGNALS
from .errors import UserError
from .io import atomic_writer

__all__ = [
    "DEFAULT_SSP",
    "NS",
    "fmpy_parameter_set",
    "read_ssp",
    "read_ssp_bindings",
    "read_ssp_connections",
    "system_ssd",
    "write_system_ssp",
]

DEFAULT_SSP = Path("models") / "PiezoSystem.ssp"     # relative to the current folder

NS = {
    "ssd": "http://ssp-standard.org/SSP1/SystemStructureDescription",
    "ssc": "http://ssp-standard.org/SSP1/SystemStructureCommon",
    "ssv": "http://ssp-standard.org/SSP1/SystemStructureParameterValues",
    "osp": "http://opensimulationplatform.com/SSP/OSPAnnotations",
}
for _prefix, _uri in NS.items():
    ET.register_namespace(_prefix, _uri)

# SI base-unit exponents and factor of the connector units (ssc:Unit / ssc:BaseUnit).
UNIT_DEFINITIONS = {
    "um": {"m": "1", "factor": "1e-06"},
    "V": {"kg": "1", "m": "2", "s": "-3", "A": "-1"},
    "N": {"kg": "1", "m": "1", "s": "-2"},
}

# The paper's 10 Hz closed-loop experiment (0-90 V sine, ff+fb with the dynamic inverse).
PAPER_EXPERIMENT = {"signal": "sine", "amplitude": 45.0, "offset": 45.0, "freq": 10.0,
                    "phase": -90.0, "mode": "ff+fb", "inverse": "dynamic"}


def _q(prefix, tag):
    return f"{{{NS[prefix]}}}{tag}"


def _num(v):
    return repr(float(v))


def system_ssd(*, start_time=0.0, stop_time=0.3, step=1e-4, experiment=None, parameters=None,
               name="PiezoSystem") -> bytes:
    """The ``SystemStructure.ssd`` document (bytes, UTF-8).

    ``experiment`` overrides entries of :data:`PAPER_EXPERIMENT`; ``parameters`` adds bindings
    ``{component: {variable: value}}`` (float -> ssv:Real, int -> ssv:Integer).
    """
    if not (math.isfinite(step) and step > 0):
        raise UserError(f"SSP step: must be a positive number of seconds, got {step}")
    if not (math.isfinite(stop_time) and stop_time > start_time):
        raise UserError(f"SSP stop time: must be after the start time {start_time}, got {stop_time}")
    exp = dict(PAPER_EXPERIMENT, **(experiment or {}))
    if exp["signal"] not in SIGNALS or exp["signal"] == "external":
        raise UserError(f"SSP experiment signal: {exp['signal']!r} (sine, step, triangle, constant)")
    bindings = {"Compensator": {
        "reference.signal": SIGNALS[exp["signal"]],
        "reference.amplitude": float(exp["amplitude"]),
        "reference.offset": float(exp["offset"]),
        "reference.freq": float(exp["freq"]),
        "reference.phase": float(exp["phase"]),
        "compensator.mode": MODES[exp["mode"]],
        "compensator.inverse": INVERSES[exp["inverse"]],
    }}
    for comp, values in (parameters or {}).items():
        bindings.setdefault(comp, {}).update(values)
    external = set(EXTERNAL_INPUTS)

    root = ET.Element(_q("ssd", "SystemStructureDescription"),
                      {"version": "1.0", "name": name, "generationTool": "piezo-fmu"})
    system = ET.SubElement(root, _q("ssd", "System"), {
        "name": name, "description": "piezo stack actuator, quartz force sensor and compensator "
                                     "in closed loop (Shan et al., Sensors 2021)"})
    elements = ET.SubElement(system, _q("ssd", "Elements"))
    for comp, ports in COMPONENTS.items():
        el = ET.SubElement(elements, _q("ssd", "Component"), {
            "name": comp, "type": "application/x-fmu-sharedlibrary",
            "source": f"resources/{comp}.fmu"})
        conns = ET.SubElement(el, _q("ssd", "Connectors"))
        for port in ports:
            if (comp, port.name) in external:
                continue  # unconnected inputs break fmpy.ssp; the generator drives the loop
            c = ET.SubElement(conns, _q("ssd", "Connector"), {
                "name": port.name, "kind": port.causality, "description": port.description})
            ET.SubElement(c, _q("ssc", "Real"), {"unit": port.unit})
        if bindings.get(comp):
            pbs = ET.SubElement(el, _q("ssd", "ParameterBindings"))
            pb = ET.SubElement(pbs, _q("ssd", "ParameterBinding"))
            pv = ET.SubElement(pb, _q("ssd", "ParameterValues"))
            ps = ET.SubElement(pv, _q("ssv", "ParameterSet"), {"version": "1.0",
                                                                "name": f"{comp}-experiment"})
            params = ET.SubElement(ps, _q("ssv", "Parameters"))
            for pname, value in bindings[comp].items():
                p = ET.SubElement(params, _q("ssv", "Parameter"), {"name": pname})
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise UserError(f"SSP parameter {comp}.{pname}: expected a number, got {value!r}")
                if isinstance(value, int):
                    ET.SubElement(p, _q("ssv", "Integer"), {"value": str(value)})
                else:
                    ET.SubElement(p, _q("ssv", "Real"), {"value": _num(value)})
    connections = ET.SubElement(system, _q("ssd", "Connections"))
    for a, av, b, bv in CONNECTIONS:
        ET.SubElement(connections, _q("ssd", "Connection"), {
            "startElement": a, "startConnector": av, "endElement": b, "endConnector": bv})
    units = ET.SubElement(root, _q("ssd", "Units"))
    used = sorted({port.unit for ports in COMPONENTS.values() for port in ports})
    for u in used:
        unit = ET.SubElement(units, _q("ssc", "Unit"), {"name": u})
        ET.SubElement(unit, _q("ssc", "BaseUnit"), UNIT_DEFINITIONS[u])
    de = ET.SubElement(root, _q("ssd", "DefaultExperiment"),
                       {"startTime": _num(start_time), "stopTime": _num(stop_time)})
    anns = ET.SubElement(de, _q("ssd", "Annotations"))
    ann = ET.SubElement(anns, _q("ssc", "Annotation"), {"type": "com.opensimulationplatform"})
    alg = ET.SubElement(ann, _q("osp", "Algorithm"))
    # zero workers: libcosim steps the FMUs on the calling thread. They share one embedded Python
    # and cannot step in parallel; its worker pool only adds hand-offs (13-95 us per step on two
    # cores, see piezo_fmu.bench_runtime)
    ET.SubElement(alg, _q("osp", "FixedStepAlgorithm"), {"baseStepSize": _num(step), "numWorkerThreads": "0"})
    ET.indent(root)
    return ET.tostring(root, encoding="utf-8", xml_declaration=True)


def write_system_ssp(path, fmus: dict, *, start_time=0.0, stop_time=0.3, step=1e-4,
                     experiment=None, parameters=None, force=True) -> Path:
    """Write the SSP archive ``path`` (atomically) with the FMUs ``{name: path}`` under resources/.

    The default experiment is the paper's 10 Hz closed loop, 0 - 0.3 s at a fixed step of
    1e-4 s. ``force=False`` refuses to replace an existing file.
    """
    path = Path(path)
    missing = [n for n in COMPONENTS if n not in fmus]
    if missing:
        raise UserError(f"write_system_ssp: no FMU given for {', '.join(missing)}")
    for n in COMPONENTS:
        if not Path(fmus[n]).is_file():
            raise UserError(f"{fmus[n]}: not found; build them first: piezo-fmu build --out-dir DIR")
    ssd = system_ssd(start_time=start_time, stop_time=stop_time, step=step,
                     experiment=experiment, parameters=parameters)
    with atomic_writer(path, "wb", force=force) as fh:
        with zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("SystemStructure.ssd", ssd)
            for n in COMPONENTS:
                # FMUs are zips already: store them uncompressed
                zf.write(fmus[n], f"resources/{n}.fmu", compress_type=zipfile.ZIP_STORED)
    return path


def read_ssp(path):
    """The parsed SSD of an ``.ssp`` archive (an ElementTree root)."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as zf:
            data = zf.read("SystemStructure.ssd")
    except (OSError, zipfile.BadZipFile, KeyError) as exc:
        raise UserError(f"{path}: not an SSP archive with SystemStructure.ssd ({exc})") from None
    return ET.parse(io.BytesIO(data)).getroot()


def read_ssp_connections(path):
    """The connections of an SSP as ``(start element, start connector, end element, end connector)``."""
    root = read_ssp(path)
    return tuple((c.get("startElement"), c.get("startConnector"), c.get("endElement"),
                  c.get("endConnector"))
                 for c in root.iter(_q("ssd", "Connection")))


def read_ssp_bindings(path) -> dict:
    """``{component: {parameter: value}}`` of the inline parameter bindings."""
    root = read_ssp(path)
    out = {}
    for comp in root.iter(_q("ssd", "Component")):
        values = {}
        for p in comp.iter(_q("ssv", "Parameter")):
            for kind, conv in (("Real", float), ("Integer", int)):
                e = p.find(_q("ssv", kind))
                if e is not None:
                    values[p.get("name")] = conv(e.get("value"))
        if values:
            out[comp.get("name")] = values
    return out


def fmpy_parameter_set(path):
    """The SSD's bindings as the ``parameter_set`` argument of ``fmpy.ssp.simulate_ssp``
    (fmpy parses but does not apply ``ssd:ParameterBindings``)."""
    from fmpy.ssp.ssd import Parameter, ParameterSet

    params = []
    for comp, values in read_ssp_bindings(path).items():
        for name, value in values.items():
            params.append(Parameter(name=f"{comp}.{name}",
                                    type="Integer" if isinstance(value, int) else "Real",
                                    value=value))
    return ParameterSet(name="bindings", parameters=params)
