"""What the benchmark scripts share: paths, the tyrex walks and their scorer, the imufusion peer's
settings (as in ../shared/benchmarks/PEERS.md), peak memory, and writing one section of RESULTS.md.

Scripts run as ``python benchmarks/NAME.py``, so this folder is on ``sys.path`` and ``import _common`` works.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SHARED = (ROOT / ".." / "shared").resolve()
TYREX = SHARED / "datasets" / "tyrex-pdrcsv"
SCORER = SHARED / "benchmarks" / "tyrex" / "score.py"
RESULTS = ROOT / "benchmarks" / "RESULTS.md"

DIST = (
    "Thibaud_Nexus5_Dist_FrontPocket",
    "Thibaud_Nexus5_Dist_Swinging",
    "Thibaud_Nexus5_Dist_Texting",
    "Thibaud_iPhone5_Dist_Texting",
)
NODIST = ("Thibaud_Nexus5_NoDist_Swinging", "Thibaud_Nexus5_NoDist_Texting", "Thibaud_iPhone5_NoDist_Texting")
TRIALS = DIST + NODIST

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def load_scorer():
    """The shared tyrex scorer (``../shared/benchmarks/tyrex/score.py``) as a module."""
    sys.path.insert(0, str(SCORER.parent))
    spec = importlib.util.spec_from_file_location("tyrex_score", SCORER)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def imufusion_ahrs(sample_rate_hz: float):
    """imufusion's Ahrs as PEERS.md runs it: ENU, gain 0.5, rejections 10°, recovery 5 s."""
    import imufusion

    ahrs = imufusion.Ahrs()
    s = imufusion.AhrsSettings()
    s.convention = imufusion.CONVENTION_ENU
    s.gain = 0.5
    s.gyroscope_range = 2000.0
    s.acceleration_rejection = 10.0
    s.magnetic_rejection = 10.0
    s.rejection_timeout = 5.0
    s.sample_rate = sample_rate_hz
    ahrs.set_settings(s)
    return ahrs


def rss_mb() -> float:
    """Resident memory now (psutil), else the peak so far (resource), MB."""
    try:
        import psutil

        return psutil.Process().memory_info().rss / 2**20
    except ImportError:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def write_section(section: str, text: str, path: Path = RESULTS) -> None:
    """Replace (or append) the section headed ``section`` of ``path`` (RESULTS.md unless given), leaving the
    others untouched; ``text`` is the whole section, its heading line first."""
    old = path.read_text() if path.exists() else "# Benchmark results\n\n"
    start = old.find(section)
    if start < 0:
        new = old.rstrip("\n") + "\n\n" + text
    else:
        nxt = old.find("\n## ", start + len(section))
        new = old[:start] + text.rstrip("\n") + "\n" + ("\n" + old[nxt + 1 :] if nxt >= 0 else "")
    path.write_text(new)
