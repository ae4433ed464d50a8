"""A rig recording (what a real rig would hand over, plus the concealed truth) and its CSV."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

UNITS = {"time": "s", "u": "V", "x": "um", "us": "V"}


@dataclass
class RigRecording:
    """One synthetic recording.

    Attributes
    ----------
    time : ndarray
        Sample times [s], uniform, starting at 0.
    u : ndarray
        Amplifier command [V] (stack volts before the amplifier's gain error).
    x : ndarray or None
        Displacement probe [um]; None when the case has no probe channel.
    us : ndarray or None
        Sensor voltage [V]; None when the case has no sensor channel.
    truth : dict
        Ground truth (never written to the CSV): ``mechanisms``, ``hidden``, ``group``,
        ``control``, ``params``, ``visibility`` and more (see ``piezo_fmu.rig``).
    """

    time: np.ndarray
    u: np.ndarray
    x: np.ndarray | None
    us: np.ndarray | None
    truth: dict = field(default_factory=dict)

    @property
    def channels(self) -> list[str]:
        """Present measured channels, in CSV order."""
        return [c for c in ("x", "us") if getattr(self, c) is not None]

    @property
    def fs(self) -> float:
        """Sample rate [Hz]."""
        return 1.0 / (self.time[1] - self.time[0])


def write_csv(rec: RigRecording, path: str | Path) -> Path:
    """Write ``time,u[,x][,us]`` with one ``#`` line of units and ``%.10g`` numbers.

    Nothing of the truth goes into the file.

    Parameters
    ----------
    rec : RigRecording
    path : str or Path

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    cols = ["time", "u"] + rec.channels
    data = np.column_stack([getattr(rec, c) for c in cols])
    units = ", ".join(f"{c} [{UNITS[c]}]" for c in cols)
    with open(path, "w", newline="") as fh:
        fh.write(f"# units: {units}\n")
        fh.write(",".join(cols) + "\n")
        np.savetxt(fh, data, fmt="%.10g", delimiter=",")
    return path


def read_csv(path: str | Path) -> dict:
    """Read a file written by ``write_csv``: ``{column: ndarray}``."""
    with open(path) as fh:
        lines = [ln for ln in fh if not ln.startswith("#")]
    header = lines[0].strip().split(",")
    data = np.loadtxt(lines[1:], delimiter=",", ndmin=2)
    return {name: data[:, i] for i, name in enumerate(header)}
