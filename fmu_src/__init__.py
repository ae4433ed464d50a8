"""The FMU slave scripts (thin adapters over :mod:`piezo_fmu.core`) and their shared base.

Not imported as a package: these files are the sources :mod:`piezo_fmu.builder` stages into each
FMU. ``pyproject.toml`` maps this top-level folder into the wheel as ``piezo_fmu.fmu_src`` (one
source of truth for a checkout and an installed package); this file makes it a regular package
so that ``importlib.resources`` finds it in an editable install too.
"""
