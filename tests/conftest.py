"""Shared fixtures: where the real public test data lives, and a skip marker when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("RECON_SHARED_DATA", REPO.parent / "shared" / "data"))

requires_shared = pytest.mark.skipif(
    not (SHARED_DATA / "oxford" / "graf" / "img1.png").exists(),
    reason=f"real test data not found at {SHARED_DATA} (set RECON_SHARED_DATA)",
)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not (SHARED_DATA / "oxford" / "graf" / "img1.png").exists():
        pytest.skip(f"real test data not found at {SHARED_DATA} (set RECON_SHARED_DATA)")
    return SHARED_DATA
