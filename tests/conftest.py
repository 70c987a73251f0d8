"""Fixtures shared by the test modules (pytest finds them by name)."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: the workplace's real RGB-D frame with ground truth (BOP format), beside the repository: <repo>/../shared/
LMO_SAMPLE = ROOT.parent / "shared" / "data" / "lmo_sample"


@pytest.fixture(scope="session")
def lmo_sample() -> Path:
    """The LM-O sample folder (models/, test/000002/); the test is skipped where the shared folder is absent."""
    if not LMO_SAMPLE.is_dir():
        pytest.skip(f"LM-O sample not found at {LMO_SAMPLE} (CI clones shared/ beside the repository)")
    return LMO_SAMPLE
