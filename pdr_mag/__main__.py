"""``python -m pdr_mag`` forwards to the ``pdr-mag`` command line.

The one place the library points at the ``replay`` application layer.
"""

from replay.cli import run

run()
