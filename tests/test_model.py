"""Model files: load, validate (errors name the key), write and read back."""
import re
from pathlib import Path

import pytest

from piezo_fmu.model import (DEFAULT_MODEL, SCHEMA, ModelError, dump_model, load_model, loads_model,
                             validate_model)

PAPER = DEFAULT_MODEL.read_text()


def test_paper_model_loads_with_units_and_sources():
    m = load_model()
    assert m.name == "paper"
    for section, specs in SCHEMA.items():
        for key, spec in specs.items():
            if spec.unit is None or key not in m.sections.get(section, {}):
                continue
            assert m.units[section][key] == spec.unit
            assert m.sources[section][key], f"{section}.{key} has no provenance"


def test_every_paper_parameter_states_its_provenance_in_the_file():
    raw = [line for line in PAPER.splitlines() if "value =" in line]
    assert raw and all('source = "' in line for line in raw)


def test_dump_and_load_round_trip(tmp_path):
    m = load_model()
    path = tmp_path / "copy.toml"
    path.write_text(dump_model(m, "a copy"))
    again = load_model(path)
    assert again.sections == m.sections
    assert again.sources == m.sources


def _edit(pattern, repl, count=1):
    text, n = re.subn(pattern, repl, PAPER, count=count, flags=re.M)
    assert n == count, pattern
    return text


@pytest.mark.parametrize("text, key", [
    (_edit(r"^m = \{ value = [^,]+", "m = { value = -0.02"), "mechanics.m"),
    (_edit(r"^R = \{ value = [^,]+", 'R = { value = "400"'), "amplifier.R"),
    (_edit(r'^R = \{ value = ([^,]+), unit = "ohm"', r'R = { value = \1, unit = "kohm"'), "amplifier.R"),
    (_edit(r"^k_amp = .*\n", "", 2), "amplifier.k_amp"),
    (_edit(r"^\[amplifier\]\n", "[amplifier]\nbogus = { value = 1.0, unit = \"1\", source = \"x\" }\n"),
     "amplifier.bogus"),
    (_edit(r"^c = \{ value = [^,]+", "c = { value = nan"), "mechanics.c"),
    (_edit(r"^den = \{ value = \[[^\]]+\]", "den = { value = [0.0015, -1.0]"),
     "compensator.dynamics.den"),
    (_edit(r"^num = \{ value = \[[^\]]+\]", "num = { value = [-0.001, 1.0]"),
     "compensator.dynamics.num"),
    (_edit(r"^weights = \{ value = \[[^\]]+\]", "weights = { value = [0.0, 0.4, 0.1, 0, 0, 0, 0, 0, 0]"),
     "hysteresis.weights"),
    (_edit(r"^u_max = \{ value = [^,]+", "u_max = { value = -30.0"), "amplifier.u_max"),
    (_edit(r'^mode = "ff\+fb"', 'mode = "fastest"'), "compensator.mode"),
    (_edit(r'source = "paper Sec. 3.1: r = \[0, 0.1, ..., 0.8\]"', 'source = ""'), "hysteresis.thresholds"),
    (_edit(r"^\[sensor\]", "[sensors]"), "sensor"),
])
def test_invalid_models_name_the_key(text, key):
    with pytest.raises(ModelError, match=re.escape(key)):
        loads_model(text, "bad.toml")
    assert any(key in p for p in validate_model(text))


def test_not_toml_and_missing_file(tmp_path):
    with pytest.raises(ModelError, match="not valid TOML"):
        loads_model("[amplifier\nR = 1", "x.toml")
    with pytest.raises(ModelError, match="not found"):
        load_model(tmp_path / "nope.toml")
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(ModelError, match="not a text file"):
        load_model(binary)


def test_optional_sections_default_to_the_papers_physics():
    m = load_model()
    assert m["creep"]["gains"] == []
    assert m["resonance"]["f_n"] == 0.0
    assert m["sensor"]["tau_leak"] == float("inf")
    assert m["amplifier"]["I_max"] == float("inf")


def test_compensator_models_differ_from_the_device():
    """The compensator's models were identified, not copied from the device (issue 2)."""
    m = load_model()
    assert m["compensator.hysteresis"]["weights"] != m["hysteresis"]["weights"]
    assert "identified" in m.sources["compensator.hysteresis"]["weights"]
    assert "identified" in m.sources["compensator.dynamics"]["den"]


def test_models_folder_files_are_all_valid():
    for path in Path(DEFAULT_MODEL).parent.glob("*.toml"):
        assert validate_model(path) == [], path
