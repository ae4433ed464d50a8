"""The strain saturation is ordinary physics the recalibration keeps only when the recording asks.

Over a stroke of a few um a saturation level of 50 um or of 3000 um bends the loop by a few per
cent or not at all, and the PI weights bend to either: a flat direction of the ordinary fit. Which
end a fit settled at turned on the recording's last digits (rig-d19-007, stop 69: 49 um from its
CSV, 3319 um from the arrays in memory), and the search that followed named different mechanisms
from the file and from memory. Since stop 70 the saturation stays only when it beats the model
without it by the naming threshold (BIC 10); otherwise it is left out and the report says so.
"""
import math
import warnings

import pytest


def _analyse(raw):
    from piezo_fmu.diagnose.run import analyse

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return analyse(raw)


def test_a_saturation_the_recording_does_not_ask_for_is_left_out_and_a_file_diagnoses_as_memory(tmp_path):
    # rig-d19-007 (Krasnosel'skii-Pokrovskii loop, a further mode of 55 Hz; the rig has no strain
    # saturation): before the rule the CSV's diagnosis named the further mode alone and the arrays'
    # the mode and a loop shape, from saturations of 49 and 3319 um
    from piezo_fmu import rig
    from piezo_fmu.diagnose.recordings import load_recordings
    from piezo_fmu.diagnose.report import write_outputs
    from piezo_fmu.model import load_model

    spec = next(s for s in rig.cases(draw=19) if s.case_id == "rig-d19-007")
    rec = rig.generate(spec, twins=False)
    path = rig.write_csv(rec, tmp_path / "rig-d19-007.csv")
    mem = _analyse([{"name": "rig-d19-007", "time": rec.time, "u": rec.u, "x": rec.x, "us": rec.us}])
    csv = _analyse(load_recordings([path]))
    for d in (mem, csv):
        sat = d.result["baseline"]["recalibrated"]["saturation_um"]
        assert sat["value"] is None and sat["identified"] is False, sat
        assert sat["why"].startswith("left out: the recording does not ask for it"), sat
        assert not math.isfinite(d.p_nominal.y_sat) and not d.struct_nominal.saturation
    assert csv.result["final"]["effects"] == mem.result["final"]["effects"]
    tau = [d.result["baseline"]["recalibrated"]["amplifier_tau_s"]["value"] for d in (mem, csv)]
    assert tau[1] == pytest.approx(tau[0], rel=1e-3)
    # the model written has no saturation, and says why
    out = tmp_path / "out"
    write_outputs(csv, out, figures=False)
    model = load_model(out / "model.toml")
    assert not math.isfinite(model["hysteresis"]["saturation"])
    assert "left out" in model.sources["hysteresis"]["saturation"]
    assert "saturation_um" in (out / "report.html").read_text() and "none (not identified: left out" in \
        (out / "report.html").read_text()


def test_a_saturation_the_recording_shows_is_kept():
    # synth-1002: the project's own device (saturation 50 um) on steps and sines, nothing missing
    from piezo_fmu.diagnose.synth import make_case

    case = make_case(1002, [], "low", ["steps", "sines"])
    d = _analyse([{"name": "synth-1002", "time": case.t, "u": case.u, "x": case.x, "us": case.us}])
    sat = d.result["baseline"]["recalibrated"]["saturation_um"]
    assert sat["value"] == pytest.approx(50.0, rel=0.02) and sat["determined"] is True, sat
    assert d.struct_nominal.saturation
    assert d.result["final"]["nothing_missing"] is True
