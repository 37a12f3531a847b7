"""The numba cache of a kernel built from several modules is refreshed when any of them changes."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CALLEE = """
from numba import njit


@njit(cache=True)
def g():
    return {value}
"""

KERNEL = """
import sys

from numba import njit

from pdr_mag import _jit_cache
from pkg import callee


@njit(cache=True)
def f():
    return callee.g()


_jit_cache.refresh_if_changed((callee, sys.modules[__name__]), "pkg")
"""


def _run(tmp_path: Path) -> str:
    """``"<f()> <cache hits>"`` of a fresh interpreter."""
    code = "from pkg import kernel; v = kernel.f(); print(v, sum(kernel.f.stats.cache_hits.values()))"
    env = {"PYTHONPATH": f"{tmp_path}:{ROOT}", "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip()


def test_an_edit_of_a_called_module_reaches_the_cached_kernel(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "kernel.py").write_text(textwrap.dedent(KERNEL))
    (pkg / "callee.py").write_text(CALLEE.format(value=1))
    assert _run(tmp_path) == "1 0"  # compiled
    assert _run(tmp_path) == "1 1"  # loaded from the cache
    (pkg / "callee.py").write_text(CALLEE.format(value=2))  # kernel.py unchanged
    assert _run(tmp_path) == "2 0"  # compiled afresh
