"""Write the rig's cases to a folder: one CSV per case, the truth kept apart.

::

    python -m piezo_fmu.rig --out DIR [--quick] [--only rig-003,rig-017]

writes ``DIR/recordings/<case_id>.csv`` (what diagnose may see) and ``DIR/truth.json``
(``{case_id: truth}``, what it must not see), and prints one line per case.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from . import cases, generate, write_csv


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m piezo_fmu.rig", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, type=Path, help="output folder")
    ap.add_argument("--quick", action="store_true", help="the 16 short cases instead of the full set")
    ap.add_argument("--only", default="", help="comma-separated case ids")
    args = ap.parse_args(argv)
    specs = cases(quick=args.quick)
    if args.only:
        wanted = set(args.only.split(","))
        specs = [s for s in specs if s.case_id in wanted]
        if not specs:
            print(f"error: no case among {sorted(wanted)}", file=sys.stderr)
            return 2
    rec_dir = args.out / "recordings"
    rec_dir.mkdir(parents=True, exist_ok=True)
    truth_path = args.out / "truth.json"
    truth = json.loads(truth_path.read_text()) if truth_path.exists() else {}
    for spec in specs:
        t0 = time.perf_counter()
        rec = generate(spec)
        write_csv(rec, rec_dir / f"{spec.case_id}.csv")
        truth[spec.case_id] = rec.truth
        print(f"{spec.case_id}: {rec.u.size} samples at {rec.fs:g} Hz "
              f"({time.perf_counter() - t0:.1f} s)", flush=True)
    truth_path.write_text(json.dumps(truth, indent=1, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
