"""Post-processing of the modelDescription pythonfmu writes: units, descriptions, exact starts,
ModelStructure as FMI 2.0 requires, DefaultExperiment, capability flags; and a safe rewrite of one
member of the FMU's zip."""
from __future__ import annotations

import math
import os
import tempfile
import zipfile
from pathlib import Path

from .errors import BuildError

__all__ = ["UNIT_TABLE", "PostProcessError", "patch_model_description", "rewrite_zip_member"]

# unit -> BaseUnit exponents (SI) and factor/offset; {} = dimensionless
UNIT_TABLE = {
    "1": {}, "V/V": {},
    "s": {"s": 1}, "1/s": {"s": -1}, "Hz": {"s": -1},
    "m": {"m": 1}, "m^2": {"m": 2}, "um": {"m": 1, "factor": 1e-6},
    "um/s": {"m": 1, "s": -1, "factor": 1e-6}, "um/s^2": {"m": 1, "s": -2, "factor": 1e-6},
    "kg": {"kg": 1}, "N": {"kg": 1, "m": 1, "s": -2}, "N/m": {"kg": 1, "s": -2}, "N*s/m": {"kg": 1, "s": -1},
    "A": {"A": 1}, "V": {"kg": 1, "m": 2, "s": -3, "A": -1}, "ohm": {"kg": 1, "m": 2, "s": -3, "A": -2},
    "F": {"kg": -1, "m": -2, "s": 4, "A": 2}, "C/N": {"kg": -1, "m": -1, "s": 3, "A": 1},
    "um/V": {"kg": -1, "m": -1, "s": 3, "A": 1, "factor": 1e-6},
    "V/um": {"kg": 1, "m": 1, "s": -3, "A": -1, "factor": 1e6},
    "rad": {"rad": 1}, "deg": {"rad": 1, "factor": math.pi / 180.0},
}
_BASE_ORDER = ("kg", "m", "s", "A", "K", "mol", "cd", "rad", "factor", "offset")
# children of <fmiModelDescription> in XSD order
_TOP_ORDER = ("ModelExchange", "CoSimulation", "UnitDefinitions", "TypeDefinitions", "LogCategories",
              "DefaultExperiment", "VendorAnnotations", "ModelVariables", "ModelStructure")
_LEGAL = {("parameter", "fixed"), ("parameter", "tunable"), ("input", "continuous"),
          ("output", "continuous")}


class PostProcessError(BuildError):
    pass


def _insert_in_order(root, element):
    for old in root.findall(element.tag):
        root.remove(old)
    rank = _TOP_ORDER.index(element.tag)
    pos = 0
    for i, child in enumerate(root):
        if child.tag in _TOP_ORDER and _TOP_ORDER.index(child.tag) < rank:
            pos = i + 1
    root.insert(pos, element)


def patch_model_description(xml_bytes: bytes, meta: dict, version: str = "") -> bytes:
    """The modelDescription pythonfmu wrote, completed from the slave's ``fmu_meta()``."""
    from lxml import etree

    root = etree.fromstring(xml_bytes, etree.XMLParser(remove_blank_text=True))
    if root.get("fmiVersion") != "2.0":
        raise PostProcessError("only FMI 2.0 is supported")
    if meta.get("description"):
        root.set("description", meta["description"])
    if version:
        root.set("version", version)
    cs = root.find("CoSimulation")
    cs.set("canGetAndSetFMUstate", "true" if meta["can_get_set_state"] else "false")
    cs.set("canSerializeFMUstate", "true" if meta["can_serialize_state"] else "false")

    vmeta = meta["variables"]
    svs = root.find("ModelVariables").findall("ScalarVariable")
    names = [sv.get("name") for sv in svs]
    if len(set(names)) != len(names):
        raise PostProcessError("duplicate variable names")
    if set(names) != set(vmeta):
        raise PostProcessError(f"variables and metadata differ: {sorted(set(names) ^ set(vmeta))}")
    index = {n: i + 1 for i, n in enumerate(names)}           # ModelStructure indices are 1-based
    used_units = []
    for sv in svs:
        name = sv.get("name")
        m = vmeta[name]
        type_el = sv[0]
        if type_el.tag != m["type"]:
            raise PostProcessError(f"{name}: type {type_el.tag} in the XML, {m['type']} in the slave")
        if (m["causality"], m["variability"]) not in _LEGAL:
            raise PostProcessError(f"{name}: causality={m['causality']} variability={m['variability']}")
        if not m.get("description"):
            raise PostProcessError(f"{name}: empty description")
        sv.set("description", m["description"])
        sv.set("causality", m["causality"])
        sv.set("variability", m["variability"])           # pythonfmu may leave it out
        if "initial" in sv.attrib:
            del sv.attrib["initial"]                        # the defaults are right for all of ours
        for attr in ("start", "min", "max", "unit"):
            type_el.attrib.pop(attr, None)
        if m["causality"] in ("input", "parameter"):
            if m["start"] is None:
                raise PostProcessError(f"{name}: an {m['causality']} needs a start value")
            type_el.set("start", m["start"])              # exact (repr), INF for infinity
        if m.get("min") is not None:
            type_el.set("min", m["min"])
        if m.get("max") is not None:
            type_el.set("max", m["max"])
        if m["type"] == "Real":
            unit = m.get("unit")
            if not unit:
                raise PostProcessError(f"{name}: Real variable without a unit")
            if unit not in UNIT_TABLE:
                raise PostProcessError(f"{name}: unit {unit!r} is not in piezo_fmu.builder.UNIT_TABLE")
            type_el.set("unit", unit)
            if unit not in used_units:
                used_units.append(unit)

    ud = etree.Element("UnitDefinitions")
    for u in used_units:
        ue = etree.SubElement(ud, "Unit", name=u)
        base = UNIT_TABLE[u]
        etree.SubElement(ue, "BaseUnit", {k: (repr(float(base[k])) if k in ("factor", "offset")
                                              else str(base[k])) for k in _BASE_ORDER if k in base})
    if used_units:
        _insert_in_order(root, ud)

    de = meta.get("default_experiment")
    if de:
        el = etree.Element("DefaultExperiment")
        for key in ("startTime", "stopTime", "tolerance", "stepSize"):
            if de.get(key) is not None:
                el.set(key, repr(float(de[key])))
        _insert_in_order(root, el)

    # ModelStructure, from scratch. Outputs: every output; ours are computed in do_step (and at
    # initialization) only, so they depend on no input within a step: dependencies="".
    # InitialUnknowns (FMI 2.0, 2.2.8) = outputs with initial calculated/approx (all of ours) +
    # calculatedParameters (none); no dependencies attribute = depends on all knowns.
    ms = etree.Element("ModelStructure")
    outputs = [n for n in names if vmeta[n]["causality"] == "output"]
    if outputs:
        oe = etree.SubElement(ms, "Outputs")
        ie = etree.SubElement(ms, "InitialUnknowns")
        for n in outputs:
            u = etree.SubElement(oe, "Unknown", index=str(index[n]))
            deps = vmeta[n].get("depends_on")
            if deps is not None:
                u.set("dependencies", " ".join(str(index[d]) for d in deps))
            u2 = etree.SubElement(ie, "Unknown", index=str(index[n]))
            ideps = vmeta[n].get("init_depends_on")
            if ideps is not None:
                u2.set("dependencies", " ".join(str(index[d]) for d in ideps))
    _insert_in_order(root, ms)
    return etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True)


def rewrite_zip_member(fmu_path, member: str, data: bytes):
    """Replace one member of a zip: write the complete new zip beside the old one, verify it, fsync,
    then atomically replace the original; the temp file is removed on any failure."""
    src = Path(fmu_path)
    fd, tmp = tempfile.mkstemp(prefix=f".{src.name}.", suffix=".tmp", dir=src.parent)
    os.close(fd)
    try:
        with zipfile.ZipFile(src) as zin, zipfile.ZipFile(tmp, "w") as zout:
            infos = zin.infolist()
            if len({i.filename for i in infos}) != len(infos):
                raise PostProcessError(f"{src}: duplicate zip entries")
            seen = False
            for info in infos:
                if info.filename == member:
                    seen = True
                    zi = zipfile.ZipInfo(member, date_time=info.date_time)
                    zi.external_attr = info.external_attr
                    zi.compress_type = zipfile.ZIP_DEFLATED
                    zout.writestr(zi, data)
                else:
                    zout.writestr(info, zin.read(info.filename))   # same name, time, mode, method
            if not seen:
                zout.writestr(zipfile.ZipInfo(member), data, compress_type=zipfile.ZIP_DEFLATED)
        with zipfile.ZipFile(tmp) as zchk:
            if zchk.testzip() is not None:
                raise PostProcessError(f"{src}: CRC error in the rewritten zip")
            if zchk.read(member) != data:
                raise PostProcessError(f"{src}: rewritten member differs")
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, src)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
