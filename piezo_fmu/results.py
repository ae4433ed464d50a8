"""Writing the recorded signals of a run: CSV or Parquet, streamed, and a plot.

A run of :func:`piezo_fmu.simulate` or :func:`piezo_fmu.cosim.cosimulate` hands its recorded rows
(``(n, 7)`` arrays in :data:`~piezo_fmu.simulate.COLUMNS` order) to a ``sink`` as they are computed.
:class:`RunWriter` is such a sink: it writes them to a CSV (a ``# units`` line, then a header row)
or, for a path ending in ``.parquet``, to Parquet (the units in the schema's metadata), through
pyarrow's writers (a 100 s run at 1e-4 s, 1e6 rows, takes about 1 s either way, against 4 s for
``numpy.savetxt``), and keeps the tracking-error summary on the way. The file appears only when the
run finishes (:func:`piezo_fmu.io.atomic_writer`), so an interrupted run leaves nothing half-written.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .errors import UserError
from .io import atomic_writer, check_writable
from .simulate import COLUMNS, UNITS

__all__ = ["CSV_HEADER", "FORMATS", "RunWriter", "TrackingError", "output_format", "plot_run", "summarize",
           "write_run"]

CSV_HEADER = ("# units: " + ", ".join(f"{c} [{UNITS[c]}]" for c in COLUMNS) + "\n"
              + ",".join(COLUMNS) + "\n")
FORMATS = {".csv": "csv", ".parquet": "parquet"}


def output_format(path) -> str:
    """``"csv"`` or ``"parquet"`` from the file's suffix; anything else is a :class:`UserError`."""
    fmt = FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise UserError(f"{path}: unknown output format; use a .csv or .parquet file name")
    return fmt


class TrackingError:
    """Running summary of the tracking error ``x - x_ref`` [um] over streamed rows."""

    def __init__(self):
        self.n = 0
        self.sum_abs = 0.0
        self.sum_sq = 0.0
        self.max = 0.0

    def add(self, x_ref, x):
        e = np.asarray(x) - np.asarray(x_ref)
        if e.size:
            self.n += e.size
            self.sum_abs += float(np.sum(np.abs(e)))
            self.sum_sq += float(np.sum(e * e))
            self.max = max(self.max, float(np.max(np.abs(e))))

    def as_dict(self) -> dict:
        """``{"max_um", "avg_um", "rms_um"}``."""
        n = max(self.n, 1)
        return {"max_um": self.max, "avg_um": self.sum_abs / n, "rms_um": math.sqrt(self.sum_sq / n)}


def summarize(data) -> dict:
    """Tracking error of a run held in memory: ``{"max_um", "avg_um", "rms_um"}`` of ``x - x_ref``."""
    acc = TrackingError()
    acc.add(data["x_ref"], data["x"])
    return acc.as_dict()


class RunWriter:
    """A ``sink`` that streams a run's rows to ``path`` (CSV or Parquet by suffix).

    Use as a context manager; the file appears when the block ends without an exception::

        with RunWriter("run.parquet") as out:
            simulate(model, signal, 100.0, record_step=1e-4, sink=out)
        out.summary          # tracking error [um]

    Parameters
    ----------
    path : str or Path
        Output file, ``.csv`` or ``.parquet``.
    force : bool
        Replace an existing file.
    """

    def __init__(self, path, force=False):
        self.path = Path(path)
        self.format = output_format(self.path)
        self.force = force
        self.tracking = TrackingError()
        self.rows = 0
        check_writable(self.path, force)
        self._ctx = None
        self._fh = None
        self._writer = None

    def __enter__(self):
        self._ctx = atomic_writer(self.path, "wb", force=self.force)
        self._fh = self._ctx.__enter__()
        if self.format == "csv":
            self._fh.write(CSV_HEADER.encode())
        return self

    def __call__(self, rows):
        import pyarrow as pa

        rows = np.asarray(rows, dtype=float)
        if rows.ndim != 2 or rows.shape[1] != len(COLUMNS):
            raise ValueError(f"RunWriter: rows must be (n, {len(COLUMNS)}), got {rows.shape}")
        if not rows.shape[0]:
            return
        table = pa.table({c: np.ascontiguousarray(rows[:, i]) for i, c in enumerate(COLUMNS)})
        if self._writer is None:
            self._writer = self._open(table.schema)
        self._writer.write_table(table)
        self.rows += rows.shape[0]
        self.tracking.add(rows[:, 1], rows[:, 2])

    def _open(self, schema):
        if self.format == "csv":
            import pyarrow.csv as pc

            return pc.CSVWriter(self._fh, schema, write_options=pc.WriteOptions(include_header=False))
        import pyarrow.parquet as pq

        schema = schema.with_metadata({f"unit:{c}": UNITS[c] for c in COLUMNS})
        return pq.ParquetWriter(self._fh, schema)

    def __exit__(self, *exc):
        try:
            if self._writer is not None:
                self._writer.close()
        finally:
            self._ctx.__exit__(*exc)
        return False

    @property
    def summary(self) -> dict:
        """Tracking error of the rows written so far (see :class:`TrackingError`)."""
        return self.tracking.as_dict()


def write_run(path, data, force=False) -> dict:
    """Write a run held in memory (``{column: array}``) to ``path``; returns its tracking error."""
    with RunWriter(path, force=force) as out:
        out(np.column_stack([np.asarray(data[c], dtype=float) for c in COLUMNS]))
    return out.summary


def plot_run(data, path, title, force=False):
    """Reference, displacement, tracking error and command over time, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(data["time"])
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    axes[0].plot(t, data["x_ref"], "k--", lw=1, label="x_ref")
    axes[0].plot(t, data["x"], lw=1, label="x")
    axes[0].set_ylabel("displacement [um]")
    axes[0].legend()
    axes[1].plot(t, np.asarray(data["x"]) - np.asarray(data["x_ref"]), color="C3", lw=1)
    axes[1].set_ylabel("x - x_ref [um]")
    axes[2].plot(t, data["uc"], color="C2", lw=1)
    axes[2].set_ylabel("command uc [V]")
    axes[2].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_writer(path, "wb", force=force) as fh:
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)
