"""Shared fixtures: the FMUs, built once per test session from models/paper.toml."""
from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

SYSTEM_FMUS = ("Actuator", "Sensor", "Compensator")


def pytest_collection_modifyitems(config, items):
    """Keep the tests that share a module-scoped fixture on one pytest-xdist worker.

    The suite runs on every core (``-n auto --dist loadgroup`` in pyproject.toml). Tests are
    dealt out one by one, but a module-scoped fixture (a diagnosis, an installed wheel, a
    co-simulation) would then be computed once per worker that draws one of its tests; the
    tests of a module that use any are put in one ``xdist_group`` named after the module.
    Session fixtures (the FMUs) are built once per worker.
    """
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None:
            continue
        if any(defs and defs[-1].scope == "module" for defs in info.name2fixturedefs.values()):
            item.add_marker(pytest.mark.xdist_group(item.module.__name__))


@pytest.fixture(scope="session")
def fmu_build(tmp_path_factory):
    """``piezo_fmu.builder.build_all`` of models/paper.toml into a temp folder, with PassThrough.fmu.

    The SSP is not written here (``ssp=False``) so that these tests do not depend on
    piezo_fmu.ssp; tests of the SSP call ``piezo_fmu.ssp.write_system_ssp`` with ``built_fmus``.
    """
    from piezo_fmu.builder import build_all

    out = tmp_path_factory.mktemp("fmus")
    return build_all(ROOT / "models" / "paper.toml", out, floor=True, ssp=False, log=lambda msg: None)


@pytest.fixture(scope="session")
def built_fmus(fmu_build):
    """``{"Actuator": Path, "Sensor": Path, "Compensator": Path}`` of FMUs built for this session."""
    return {name: fmu_build[name] for name in SYSTEM_FMUS}


@pytest.fixture(scope="session")
def passthrough_fmu(fmu_build):
    """Path of PassThrough.fmu (y = u on the same base class), built with the session's FMUs."""
    return fmu_build["PassThrough"]
