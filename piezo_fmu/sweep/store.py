"""The results of a sweep on disk: ``DIR/results.parquet``, streamed as runs finish, resumable.

A Parquet file cannot be appended to once closed, and one left open has no footer until it is
closed (a killed process leaves it unreadable). So rows arrive as small Parquet *parts*
(``DIR/results.parts/part-000042.parquet``, each written to a temporary name and renamed, so a
part is whole or absent), and :meth:`ResultStore.compact` merges ``results.parquet`` and the parts
into a new ``results.parquet`` (sorted by run index, the latest row of an index kept), written
beside and renamed into place, then removes the merged parts. The sweep compacts every few
seconds and at the end, so ``results.parquet`` is always readable and at most seconds behind; an
interruption loses no part already written (Ctrl-C writes the rows in hand first; a killed
process loses at most the last ``flush_s`` seconds of rows).

``DIR/sweep.json`` records the spec (its TOML as read, the base model's text and a hash of both).
``--resume`` refuses a directory whose hash differs, reads the rows that are there and computes
only the missing runs (and those whose workers died: ``status = "lost"``); a finished run,
``ok`` or ``error``, is never computed again.

One row per run: ``index, grid, draw``, the varied values (columns named by their keys,
``hysteresis.weights[3]``), the metrics, ``status`` (ok | error | lost), ``error`` (the message)
and ``seconds`` (the run's wall time in its worker, the one column that differs between two
sweeps of the same spec).
"""
from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

from ..errors import UserError
from .runner import ROW_FIELDS
from .space import columns
from .spec import SpecError, SweepSpec

__all__ = ["PARTS", "RESULTS", "SPEC_JSON", "ResultStore", "read_results", "schema"]

RESULTS = "results.parquet"
PARTS = "results.parts"
SPEC_JSON = "sweep.json"
OUTPUTS = (RESULTS, PARTS, SPEC_JSON, "report.html", "figures", "fmus")
TYPES = {"float": "float64", "int": "int64", "str": "string", "bool": "bool"}


def schema(spec: SweepSpec):
    """The pyarrow schema of the results table of ``spec`` (with the spec's hash as metadata)."""
    import pyarrow as pa

    cols = [ROW_FIELDS[0], ROW_FIELDS[1], ROW_FIELDS[2]] + columns(spec)
    cols += [(m, "bool" if m == "stable" else "float") for m in spec.metric_names]
    cols += list(ROW_FIELDS[3:])
    meta = {"piezo_fmu.sweep": json.dumps({"name": spec.name, "hash": spec.hash, "runs": spec.n_runs})}
    return pa.schema([pa.field(name, TYPES[kind]) for name, kind in cols], metadata=meta)


def read_results(out_dir):
    """The results table of a sweep folder (``pyarrow.Table``), with any parts not yet merged."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    out_dir = Path(out_dir)
    tables = []
    if (out_dir / RESULTS).exists():
        tables.append(pq.read_table(out_dir / RESULTS))
    for part in sorted((out_dir / PARTS).glob("part-*.parquet")) if (out_dir / PARTS).is_dir() else []:
        tables.append(pq.read_table(part))
    if not tables:
        raise UserError(f"{out_dir}: no sweep results there ({RESULTS})")
    return _latest(pa.concat_tables(tables, promote_options="none") if len(tables) > 1 else tables[0])


def _latest(table):
    """Sorted by index; of repeated indices the last row."""
    import numpy as np

    idx = table.column("index").to_numpy()
    if idx.size == 0:
        return table
    order = np.arange(idx.size)
    # the last occurrence of each index: unique on the reversed array
    _, rev_pos = np.unique(idx[::-1], return_index=True)
    keep = order[::-1][rev_pos]
    keep = keep[np.argsort(idx[keep], kind="stable")]
    return table.take(keep)


class ResultStore:
    """Rows of one sweep streamed into ``out_dir`` (see the module docstring).

    Parameters
    ----------
    out_dir : path
        The sweep's folder (created).
    spec : SweepSpec
    resume : bool
        Continue the sweep in ``out_dir`` (same spec and model), keeping its rows.
    force : bool
        Delete a previous sweep's outputs in ``out_dir`` and start over.
    flush_s : float
        Rows are written as a part at least this often [s] (and every ``flush_rows`` rows).
    compact_s : float
        ``results.parquet`` is rewritten from the parts at least this often [s].
    """

    def __init__(self, out_dir, spec: SweepSpec, resume=False, force=False, flush_s=2.0, flush_rows=200,
                 compact_s=10.0):
        self.dir = Path(out_dir)
        self.spec = spec
        self.schema = schema(spec)
        self.flush_s, self.flush_rows, self.compact_s = flush_s, flush_rows, compact_s
        self.buffer = []
        self.last_flush = self.last_compact = time.monotonic()
        if self.dir.exists() and not self.dir.is_dir():
            raise UserError(f"{self.dir}: exists and is not a folder")
        present = [n for n in OUTPUTS if (self.dir / n).exists()]
        if present and force:
            for n in present:
                p = self.dir / n
                shutil.rmtree(p) if p.is_dir() else p.unlink()
            present = []
        if present and not resume:
            raise UserError(f"{self.dir}: holds a sweep ({', '.join(present)}); use --resume to complete "
                            "it or --force to start over")
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            (self.dir / PARTS).mkdir(exist_ok=True)
        except OSError as exc:
            raise UserError(f"{self.dir}: cannot create the output folder ({exc.strerror or exc})") from None
        self._check_or_write_spec()
        self.seq = 1 + max((int(p.stem.split("-")[1]) for p in (self.dir / PARTS).glob("part-*.parquet")),
                           default=0)
        self.done = self._finished()

    # -- the folder's spec ---------------------------------------------------------------------------
    def _check_or_write_spec(self):
        path = self.dir / SPEC_JSON
        if path.exists():
            try:
                old = json.loads(path.read_text())
            except (OSError, ValueError):
                raise UserError(f"{path}: unreadable; use --force to start over") from None
            if old.get("hash") != self.spec.hash:
                raise SpecError(f"{self.dir}: was started with another spec or base model (hash "
                                f"{old.get('hash')}, now {self.spec.hash}); use --force to start over "
                                "or another --out")
            return
        from .. import __version__

        doc = {"name": self.spec.name, "hash": self.spec.hash, "runs": self.spec.n_runs,
               "spec_file": self.spec.origin, "model_file": self.spec.model_origin,
               "piezo_fmu": __version__, "spec": self.spec.raw, "model": self.spec.model_text}
        tmp = path.with_suffix(".json.part")
        tmp.write_text(json.dumps(doc, indent=1, default=str))
        os.replace(tmp, path)

    def _finished(self) -> set:
        try:
            table = read_results(self.dir)
        except UserError:
            return set()
        if table.schema.remove_metadata() != self.schema.remove_metadata():
            raise SpecError(f"{self.dir}: its results have other columns than this spec makes; use --force")
        idx = table.column("index").to_numpy()
        status = table.column("status").to_pylist()
        return {int(i) for i, s in zip(idx, status) if s != "lost"}

    # -- rows --------------------------------------------------------------------------------------
    def add(self, row: dict):
        """Take one row; writes a part when ``flush_rows`` rows or ``flush_s`` seconds have
        gathered, and compacts every ``compact_s`` seconds."""
        self.buffer.append(row)
        if row.get("status") != "lost":
            self.done.add(int(row["index"]))
        now = time.monotonic()
        if len(self.buffer) >= self.flush_rows or now - self.last_flush >= self.flush_s:
            self.flush()
        if now - self.last_compact >= self.compact_s:
            self.compact()

    def _table(self, rows):
        import pyarrow as pa

        arrays = []
        for f in self.schema:
            vals = [r.get(f.name) for r in rows]
            if pa.types.is_floating(f.type):
                vals = [None if v is None else float(v) for v in vals]
            elif pa.types.is_string(f.type):
                vals = [None if v is None else str(v) for v in vals]
            arrays.append(pa.array(vals, type=f.type))
        return pa.Table.from_arrays(arrays, schema=self.schema)

    def flush(self):
        """Write the rows in hand as one part (whole or not at all)."""
        import pyarrow.parquet as pq

        self.last_flush = time.monotonic()
        if not self.buffer:
            return
        table = self._table(self.buffer)
        path = self.dir / PARTS / f"part-{self.seq:06d}.parquet"
        tmp = path.with_name(f".{path.name}.tmp")
        pq.write_table(table, tmp)
        os.replace(tmp, path)
        self.seq += 1
        self.buffer = []

    def compact(self):
        """Merge ``results.parquet`` and the parts into a new ``results.parquet``; remove the parts."""
        import pyarrow.parquet as pq

        self.flush()
        self.last_compact = time.monotonic()
        parts = sorted((self.dir / PARTS).glob("part-*.parquet"))
        if not parts and (self.dir / RESULTS).exists():
            return
        try:
            table = read_results(self.dir)
        except UserError:
            table = self._table([])
        table = table.replace_schema_metadata(self.schema.metadata)
        path = self.dir / RESULTS
        tmp = path.with_name(f".{path.name}.tmp")
        pq.write_table(table, tmp)
        os.replace(tmp, path)
        for p in parts:
            p.unlink(missing_ok=True)

    def close(self):
        """Write everything in hand and compact (also after an interruption)."""
        self.compact()
