"""Shared test helpers: the real recordings in ../shared/datasets, skipped with a reason when absent
(except under CI=true — also CI=1 or yes —, where their absence is an error)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DATASETS = (ROOT / ".." / "shared" / "datasets").resolve()


def absent(msg: str) -> None:
    """Something of ../shared is missing: skip the test with ``msg``, or fail it under CI=true."""
    if os.environ.get("CI", "").strip().lower() in ("true", "1", "yes"):
        pytest.fail(msg + " — required under CI=true")
    pytest.skip(msg)


def dataset(*parts: str) -> Path:
    """Path to a file or folder under ../shared/datasets; skip (or fail under CI=true) if absent."""
    p = DATASETS.joinpath(*parts)
    if not p.exists():
        absent(f"real recording {p} not found (../shared/datasets is not beside this checkout)")
    return p
