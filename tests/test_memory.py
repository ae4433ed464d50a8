"""Long runs keep memory flat: output is streamed to disk (issue 6)."""
import subprocess
import sys

import pytest

PEAK = r"""
import resource, sys
from piezo_fmu.cli import main
code = main(sys.argv[1:])
print("PEAK_KB", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, "CODE", code)
"""


def peak_kb(args):
    r = subprocess.run([sys.executable, "-c", PEAK] + args, capture_output=True, text=True, timeout=900)
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("PEAK_KB"))
    _, kb, _, code = line.split()
    assert code == "0", r.stderr[-2000:]
    return int(kb)


@pytest.mark.parametrize("command, step, short, long", [
    ("cosim", "1e-4", 6.0, 60.0),        # 600 000 communication steps of three FMUs
    ("simulate", "1e-5", 6.0, 60.0),     # 6 million internal steps
])
def test_peak_memory_does_not_grow_with_run_length(tmp_path, built_fmus, command, step, short, long):
    extra = []
    if command == "cosim":
        fmu_dir = tmp_path / "fmus"
        fmu_dir.mkdir()
        for n in ("Actuator", "Sensor", "Compensator"):
            (fmu_dir / f"{n}.fmu").write_bytes(built_fmus[n].read_bytes())
        extra = ["--fmu-dir", str(fmu_dir)]
    peaks = {}
    for length in (short, long):
        out = tmp_path / f"{command}_{length:g}.csv"
        peaks[length] = peak_kb([command, "--stop-time", str(length), "--step", step, "--record-step", "1e-4",
                                 "--out", str(out), "--quiet"] + extra)
        rows = sum(1 for _ in out.open()) - 2
        assert rows == round(length / 1e-4) + 1, (length, rows)
    growth_mb = (peaks[long] - peaks[short]) / 1024
    stored_mb = (long - short) / 1e-4 * 7 * 8 / 2 ** 20   # what the extra rows would take in memory
    print(f"\n  {command}: peak RSS {peaks[short] / 1024:.1f} MB at {short:g} s, {peaks[long] / 1024:.1f} MB at "
          f"{long:g} s (the extra rows alone would be {stored_mb:.1f} MB)")
    assert growth_mb < 3.0


FRESH_PAGES = r"""
import resource
import numpy as np
from piezo_fmu.diagnose.heap import kept

def fresh_pages():
    # five rounds of twenty 2 MB arrays alive together, as a fit's residuals and columns (numpy
    # asks for huge pages only from 4 MB), every page written
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(5):
        arrays = [np.ones(250_000) for _ in range(20)]
        del arrays
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

outside = fresh_pages()
with kept():
    inside = fresh_pages()
after = fresh_pages()
print("PAGES", outside, inside, after)
"""


def test_diagnose_keeps_freed_memory_for_reuse_and_gives_it_back():
    # with glibc's defaults the memory of each round is unmapped or trimmed from the heap once
    # freed, and the next round faults every page in anew; while diagnose runs (heap.kept) the
    # heap serves the later rounds from the memory the first one left; afterwards the defaults are
    # back. rig-136: 2.0 million page faults in a 56 s diagnosis, 0.11 million and 40 s kept
    from piezo_fmu.diagnose import heap

    if heap._libc() is None:
        pytest.skip("no glibc mallopt in this process")
    r = subprocess.run([sys.executable, "-c", FRESH_PAGES], capture_output=True, text=True, timeout=300)
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("PAGES"))
    outside, inside, after = (int(v) for v in line.split()[1:])
    pages = 5 * 20 * 2_000_000 // 4096
    assert outside > 0.9 * pages, line
    assert inside < 0.4 * pages, line
    assert after > 0.9 * pages, line
