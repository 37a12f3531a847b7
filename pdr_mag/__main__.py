"""``python -m pdr_mag`` forwards to the ``pdr-mag`` command line (the one place the library points at replay)."""

import sys

from replay.cli import main

sys.exit(main())
