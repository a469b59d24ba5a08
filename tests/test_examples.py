"""The example scripts run as a user would run them (they are documentation that must not rot)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(*args: str) -> str:
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / args[0]), *args[1:]], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


@pytest.mark.slow
def test_match_pair_example_on_a_3d_pair(corner_scene):
    """examples/match_pair.py `--3d` on two views of the rendered corner (two walls): F-verified
    matches, and no precision line without a homography."""
    out = _run("match_pair.py", str(corner_scene / "images" / "view_00.png"),
               str(corner_scene / "images" / "view_01.png"), "--3d")
    verified = int(out.split("verified: ")[1].split(",")[0])
    assert verified >= 100 and "precision" not in out


@pytest.mark.slow
def test_match_pair_example_with_a_ground_truth_homography(graf_dir):
    """examples/match_pair.py on graf 1-3 with its homography prints the precision."""
    out = _run("match_pair.py", str(graf_dir / "img1.png"), str(graf_dir / "img3.png"), str(graf_dir / "H1to3p"))
    pct = float(out.split("precision: ")[1].split("%")[0])
    assert pct >= 95.0, out
