"""Shared test fixtures: the optional real-data folder and small helpers."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
REALDATA = Path(os.environ.get("LABELAUDIT_REALDATA", REPO_ROOT.parent / "shared" / "realdata"))


@pytest.fixture(scope="session")
def realdata() -> Path:
    """Path of ../shared/realdata; tests that use it skip cleanly when it is absent (users' clones)."""
    if not REALDATA.is_dir():
        pytest.skip(f"real data folder not present: {REALDATA}")
    return REALDATA
