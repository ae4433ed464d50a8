"""The README's quick start stays true: exactly two commands, and CI runs the second."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def quick_start_commands():
    text = (ROOT / "README.md").read_text()
    section = text.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```sh\n(.*?)```", section, re.S).group(1)
    return [line for line in block.splitlines() if line.strip()]


def test_quick_start_has_exactly_two_commands():
    cmds = quick_start_commands()
    assert len(cmds) == 2
    assert "piezo-fmu" in cmds[0]
    assert "pytest" in cmds[1]


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    assert quick_start_commands()[1] in ci


@pytest.fixture(scope="module")
def readme_text():
    return (ROOT / "README.md").read_text()


def test_tests_sharing_a_module_fixture_are_kept_on_one_worker(request, readme_text):
    # conftest.pytest_collection_modifyitems: with `--dist loadgroup` an xdist_group keeps the
    # fixture's users together, so the fixture is computed once, not once per worker
    marker = request.node.get_closest_marker("xdist_group")
    assert marker is not None and marker.args == (f"{__name__}::readme_text",)
    assert "pytest-xdist" in readme_text


def test_a_test_without_a_module_fixture_is_dealt_out_alone(request):
    assert request.node.get_closest_marker("xdist_group") is None
