"""The public API: every name in ``pdr_mag.__all__`` resolves, and ``import pdr_mag`` stays light."""

import subprocess
import sys

import pdr_mag


def test_every_exported_name_resolves():
    for name in pdr_mag.__all__:
        assert getattr(pdr_mag, name) is not None, name


def test_import_does_not_load_the_compiled_kernel_or_the_sinks():
    code = (
        "import sys, pdr_mag; "
        "names = ('numba', 'mcap', 'rerun', 'pdr_mag.sim', 'pdr_mag.modelcheck'); "
        "heavy = [m for m in names if m in sys.modules]; "
        "print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
