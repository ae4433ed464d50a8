"""Build the piezo-fmu co-simulation FMUs (FMI 2.0, pythonfmu) from a model file.

    piezo-fmu build [--model FILE.toml] [--out-dir DIR] [--floor]      (or: python build_fmu.py ...)

writes ``Actuator.fmu``, ``Sensor.fmu``, ``Compensator.fmu`` (and with ``--floor`` the trivial
``PassThrough.fmu`` used by the benchmark) into the output folder (default ``./models``), then
``PiezoSystem.ssp`` through :func:`piezo_fmu.ssp.write_system_ssp`. From Python::

    from piezo_fmu.builder import build_all
    fmus = build_all(None, "models")     # the paper's model; {"Actuator": Path, ...}; fmus.ssp

For each FMU:

1. **Model**: the file is validated with :func:`piezo_fmu.model.load_model`; its sections and the
   schema (units, docs, constraints) go into ``resources/piezo_model.json``, from which the slave
   registers its parameters and builds its core unit at instantiation.
2. **Staging** (:mod:`.staging`): ``fmu_src/<Name>.py`` plus one bundled package ``_pz_<name>_<hash>`` holding a copy
   of ``piezo_fmu/core`` and the slave base (``fmu_src/slavebase.py`` and the modules it is split
   into; hash over their content), the script renamed ``<Name>_<hash>.py``. Imports of those
   modules and of ``piezo_fmu.core`` are rewritten with
   :mod:`ast` at their exact spans; any other import outside the standard library, NumPy, pythonfmu
   and the bundle fails the build. So FMUs built from different core versions load side by side.
3. **pythonfmu build** in a subprocess (it imports the script and changes ``sys.path``), which also
   instantiates the slave once to collect the metadata.
4. **modelDescription post-processing** (:mod:`.description`): UnitDefinitions, unit + description on every variable,
   explicit variability, exact start values (``repr``; pythonfmu's ``%.16g`` is lossy), min/max,
   Outputs + InitialUnknowns exactly as FMI 2.0 (and fmpy) require, DefaultExperiment,
   canGetAndSetFMUstate/canSerializeFMUstate (implemented by the base class), version; then a safe
   rewrite of the zip (new file beside the old, verified, fsync, atomic replace).
4a. **Native runtime** (:mod:`.runtime`): ``binaries/linux64/<Name>.so`` becomes the project's own
   FMI runtime (``fmu_src/runtime``, compiled once per build with the system C compiler against
   this Python's headers), with ``piezo_fmu_bridge.so`` beside it and ``resources/piezo_runtime.cfg``
   (the Python library, home and module path it starts Python with where the host has none).
   Without a compiler or headers the build says so in one line and keeps pythonfmu's binary.
5. **Checks** (:mod:`.checks`): the interface against :mod:`piezo_fmu.connections`, every model parameter present,
   ``fmpy.validation.validate_fmu`` with zero problems, and a default-experiment run of every FMU
   in a subprocess that cannot import ``piezo_fmu`` (so the FMUs are self-contained).
   Any problem fails the build; the output folder only receives FMUs that passed.
"""
from __future__ import annotations

from .build import DEFAULT_OUT, FLOOR, SSP_NAME, SYSTEM, BuildResult, build_all, build_one, model_payload
from .checks import check_interface, smoke_run
from .description import UNIT_TABLE, PostProcessError, patch_model_description, rewrite_zip_member
from .errors import BuildError
from .staging import StageError, rewrite_imports, stage

__all__ = ["DEFAULT_OUT", "FLOOR", "SSP_NAME", "SYSTEM", "UNIT_TABLE", "BuildError", "BuildResult",
           "PostProcessError", "StageError", "build_all", "build_one", "check_interface", "model_payload",
           "patch_model_description", "rewrite_imports", "rewrite_zip_member", "smoke_run", "stage"]
