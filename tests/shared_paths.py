"""Where the real public test data lives: `$RECON_SHARED_DATA`, else `../shared/data` beside the
repository. A module of its own (not conftest) so test files can import it whatever conftest
Python loaded last (tests/hostile has its own)."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("RECON_SHARED_DATA") or REPO.parent / "shared" / "data")
