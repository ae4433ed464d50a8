#!/usr/bin/env python
"""Build the FMUs: a thin script over ``piezo-fmu build`` (see :mod:`piezo_fmu.builder`).

    python build_fmu.py [--model FILE.toml] [--out-dir DIR] [--floor]
"""
import sys

from piezo_fmu.cli import main

if __name__ == "__main__":
    sys.exit(main(["build", *sys.argv[1:]]))
