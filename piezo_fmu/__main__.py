"""``python -m piezo_fmu``: the ``piezo-fmu`` command line."""
import sys

from .cli import main

sys.exit(main())
