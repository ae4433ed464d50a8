"""Reading time-series CSV files (references and recordings) with errors a user can act on.

:func:`read_csv_table` accepts a header row, ``#`` comment lines and comma-separated numbers. A
header name may carry its unit in brackets or parentheses (``time [ms]``, ``x (nm)``): the column is
converted to the unit the tool works in (time s, displacement um, voltages V, force N), see
:data:`UNITS`. Every problem raises :class:`~piezo_fmu.errors.UserError` with one line naming the
file, the row or column, and what to do: a missing, empty or binary file, a file that is not comma-separated,
missing or duplicate columns, non-numeric cells, NaN or inf, time that does not increase or is
not uniformly sampled, and a recording too short to use, a unit the tool cannot convert.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import UserError

__all__ = ["Table", "read_csv_table", "parse_mapping", "UNITS", "QUANTITY"]

#: Units a header may give, per quantity: (the unit the tool works in, {unit: factor to it}).
UNITS = {
    "time": ("s", {"s": 1.0, "ms": 1e-3, "us": 1e-6, "\u00b5s": 1e-6, "\u03bcs": 1e-6, "ns": 1e-9,
                   "min": 60.0}),
    "displacement": ("um", {"um": 1.0, "\u00b5m": 1.0, "\u03bcm": 1.0, "micron": 1.0, "microns": 1.0,
                            "nm": 1e-3, "mm": 1e3, "m": 1e6}),
    "voltage": ("V", {"V": 1.0, "v": 1.0, "mV": 1e-3, "kV": 1e3}),
    "force": ("N", {"N": 1.0, "mN": 1e-3, "kN": 1e3}),
}
#: The quantity of each column the commands read (after ``--columns``).
QUANTITY = {"time": "time", "x": "displacement", "x_ref": "displacement", "u": "voltage", "us": "voltage",
            "u_ref": "voltage", "uc": "voltage", "ua": "voltage", "F": "force"}
_WITH_UNIT = re.compile(r"^(.*?)\s*(?:\[\s*([^\]]*?)\s*\]|\(\s*([^)]*?)\s*\))$")


def split_unit(name):
    """``"x [nm]"`` -> ``("x", "nm")``; a name without a unit -> ``(name, "")``."""
    m = _WITH_UNIT.match(name)
    if not m or not m.group(1):
        return name, ""
    return m.group(1), m.group(2) if m.group(2) is not None else m.group(3)


@dataclass
class Table:
    """Columns by name (float arrays) and the file they came from."""

    path: str
    columns: dict
    #: canonical name -> (unit in the header, factor applied) for every column converted
    converted: dict = field(default_factory=dict)

    def __getitem__(self, key):
        return self.columns[key]

    def __contains__(self, key):
        return key in self.columns

    @property
    def n(self):
        return len(next(iter(self.columns.values())))


def parse_mapping(items, what, numeric=False):
    """Parse ``name=value`` pairs (``--columns time=t,u=V`` or ``--scale x=1e6``)."""
    out = {}
    for item in items or []:
        for part in item.split(","):
            if not part.strip():
                continue
            if "=" not in part:
                raise UserError(f"{what}: {part!r} is not of the form name=value")
            k, v = (s.strip() for s in part.split("=", 1))
            if numeric:
                try:
                    v = float(v)
                except ValueError:
                    raise UserError(f"{what}: {k}={v!r} is not a number") from None
                if not (math.isfinite(v) and v != 0):
                    raise UserError(f"{what}: {k}={v} must be a finite non-zero number")
            out[k] = v
    return out


def read_csv_table(path, required=(), one_of=(), optional=(), columns=None, scale=None,
                   uniform=False, min_rows=2, max_jitter=1e-3) -> Table:
    """Read a numeric CSV time series.

    Parameters
    ----------
    path : path of the CSV file.
    required : column names that must be present (after renaming), e.g. ``("time",)``.
    one_of : at least one of these must be present (e.g. ``("x", "us")``).
    optional : further columns that are kept when present.
    columns : mapping canonical name -> name in the file, with or without its unit (``--columns``).
    scale : mapping canonical name -> factor to multiply by (``--scale``); a column given a factor
        is not converted from the unit in its header.
    uniform : require uniformly sampled time (relative jitter below ``max_jitter``).
    min_rows : fewest data rows accepted.
    """
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: file not found")
    if path.is_dir():
        raise UserError(f"{path}: is a folder, expected a CSV file")
    raw = path.read_bytes()
    if not raw.strip():
        raise UserError(f"{path}: file is empty (expected a header row and data rows)")
    if b"\x00" in raw[:4096]:
        raise UserError(f"{path}: binary file, expected comma-separated text")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise UserError(f"{path}: not UTF-8 text, expected a comma-separated text file") from None
    lines = [(i + 1, line.strip()) for i, line in enumerate(text.splitlines())]
    lines = [(i, line) for i, line in lines if line and not line.startswith("#")]
    if not lines:
        raise UserError(f"{path}: no header row (only comments or blank lines)")
    header_row, header = lines[0]
    names = [h.strip() for h in header.split(",")]
    if len(names) < 2:
        sep = next((s for s in (";", "\t", " ") if s in header), None)
        hint = f" (it looks {'semicolon' if sep == ';' else 'tab' if sep == chr(9) else 'space'}-separated)" \
            if sep else ""
        raise UserError(f"{path}: row {header_row}: header {header!r} has one column; expected "
                        f"comma-separated columns such as time,u,x{hint}")
    bases, units = zip(*(split_unit(n) for n in names))
    dup = sorted({n for n in bases if bases.count(n) > 1})
    if dup:
        raise UserError(f"{path}: row {header_row}: duplicate column(s) {', '.join(dup)}; rename them")
    rename, whole = {}, set()
    for canon, given in (columns or {}).items():
        # a column is named as in the header, with or without its unit (named whole, ``x(t)``, what
        # its brackets hold is a unit only when it is one the tool knows)
        j = names.index(given) if given in names else bases.index(given) if given in bases else None
        if j is None:
            raise UserError(f"{path}: --columns {canon}={given}: no column {given!r} in the header "
                            f"({', '.join(names)})")
        rename[j] = canon
        if given in names:
            whole.add(j)
    canon_names = [rename.get(j, b) for j, b in enumerate(bases)]
    dup = sorted({n for n in canon_names if canon_names.count(n) > 1})
    if dup:
        raise UserError(f"{path}: --columns maps two columns to {', '.join(dup)}")
    missing = [c for c in required if c not in canon_names]
    if missing:
        raise UserError(f"{path}: missing column(s) {', '.join(missing)} (header: {', '.join(names)}); "
                        f"use --columns {missing[0]}=NAME to map a column")
    if one_of and not any(c in canon_names for c in one_of):
        raise UserError(f"{path}: needs at least one of the columns {', '.join(one_of)} "
                        f"(header: {', '.join(names)})")
    keep = [c for c in canon_names if c in set(required) | set(one_of) | set(optional)]
    idx = {c: canon_names.index(c) for c in keep}
    data = {c: [] for c in keep}
    for row, line in lines[1:]:
        cells = line.split(",")
        if len(cells) != len(names):
            raise UserError(f"{path}: row {row}: {len(cells)} cells, the header has {len(names)}; "
                            f"every row needs one value per column")
        for c, j in idx.items():
            cell = cells[j].strip()
            try:
                v = float(cell)
            except ValueError:
                raise UserError(f"{path}: row {row}, column {names[j]}: {cell!r} is not a number") from None
            if not math.isfinite(v):
                raise UserError(f"{path}: row {row}, column {names[j]}: {cell} is not finite; remove "
                                f"or fill the sample")
            data[c].append(v)
    n = len(lines) - 1
    if n < min_rows:
        raise UserError(f"{path}: {n} data row(s); at least {min_rows} are needed")
    cols = {c: np.asarray(v, dtype=float) for c, v in data.items()}
    converted = {}
    for c, j in idx.items():
        unit, quantity = units[j], QUANTITY.get(c)
        if not unit or quantity is None or c in (scale or {}):
            continue                 # no unit, a column of no known quantity, or the user's own factor
        to, known = UNITS[quantity]
        if unit not in known and j in whole:
            continue
        if unit not in known:
            raise UserError(f"{path}: column {names[j]!r}: {unit!r} is not a {quantity} unit piezo-fmu "
                            f"converts ({', '.join(k for k in known if k.isascii())}); {c} is read in "
                            f"{to}: give --scale {c}=FACTOR to convert it yourself")
        if known[unit] != 1.0:
            cols[c] = cols[c] * known[unit]
            converted[c] = (unit, known[unit])
    for c, f in (scale or {}).items():
        if c not in cols:
            raise UserError(f"{path}: --scale {c}=...: no column {c!r}")
        cols[c] = cols[c] * f
    if "time" in cols:
        t = cols["time"]
        dt = np.diff(t)
        if np.any(dt <= 0):
            k = int(np.argmax(dt <= 0))
            raise UserError(f"{path}: row {lines[k + 2][0]}: time {t[k + 1]:g} does not increase "
                            f"(previous {t[k]:g}); sort the rows or remove duplicates")
        if uniform:
            step = float(np.median(dt))
            bad = np.abs(dt - step) > max_jitter * step
            if np.any(bad):
                k = int(np.argmax(bad))
                raise UserError(f"{path}: row {lines[k + 2][0]}: time step {dt[k]:g} s differs from the "
                                f"sampling interval {step:g} s; resample to a uniform grid")
    return Table(str(path), cols, converted)
