"""A full disk (a small tmpfs, where this machine lets us mount one) and a damaged database."""

from __future__ import annotations

import json
import os
import re
import subprocess

import pytest

from hostile_tools import FAST, Snapshot, check, model_figures, recon

TEMP = re.compile(r"\.tmp|\.old-|\.write-test")


@pytest.fixture
def tmpfs(tmp_path):
    """A 2 MB tmpfs (a full run needs about 2.6 MB); skipped where mounting is not permitted."""
    mnt = tmp_path / "small-disk"
    mnt.mkdir()
    try:
        p = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True,
                           text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as e:
        pytest.skip(f"cannot mount a tmpfs here ({e})")
    if p.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({p.stderr.strip() or p.returncode}); needs root")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=30)


def _grow(mnt, size: str) -> None:
    subprocess.run(["mount", "-o", f"remount,size={size}", str(mnt)], check=True, capture_output=True, timeout=30)


def _temp_files(root) -> list[str]:
    return [os.path.join(d, f) for d, ds, fs in os.walk(root) for f in fs + ds if TEMP.search(f)]


def test_full_disk_stops_with_one_line_then_resumes(scene, tmpfs, tmp_path, reference):
    out = tmpfs / "out"
    snap = Snapshot(tmp_path, skip=(tmpfs,))
    res = check(recon("run", scene, "--out", out, *FAST), 2, text="no space left on device writing")
    assert str(out) in res.error_lines[0]
    assert "every pair" not in res.err and "matching" not in res.err  # not reported as failed pairs
    assert not _temp_files(tmpfs)  # no *.tmp.npz, .state.json.tmp-PID, database.db.tmp left
    _grow(tmpfs, "16m")  # the user frees some space
    check(recon("run", scene, "--out", out, *FAST), 0)
    rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert model_figures(rep) == model_figures(reference)
    assert rep["pairs_cached"] + rep["features_reused"] > 0  # what was written before the disk filled is reused
    snap.assert_unchanged()


def test_a_tiny_disk_fails_at_the_first_cache_write(scene, tmpfs, tmp_path):
    subprocess.run(["mount", "-o", "remount,size=64k", str(tmpfs)], check=True, capture_output=True, timeout=30)
    res = check(recon("run", scene, "--out", tmpfs / "out", *FAST), 2, text="no space left on device writing")
    assert "cache" in res.error_lines[0]
    assert not _temp_files(tmpfs)


def test_a_recording_on_a_full_disk_costs_one_warning(scene, tmpfs, tmp_path):
    subprocess.run(["mount", "-o", "remount,size=100k", str(tmpfs)], check=True, capture_output=True, timeout=30)
    out = tmp_path / "out"
    res = check(recon("run", scene, "--out", out, "--method", "sift", "--max-size", "320", "--no-progress",
                      "--rerun", f"save:{tmpfs / 'big.rrd'}"), 0)
    rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert rep["status"] == "ok" and (out / "sparse" / "0").is_dir()
    assert len(res.warnings) == 1 and "Rerun recording" in res.warnings[0], res.err
    assert not (tmpfs / "big.rrd").exists() and not _temp_files(tmpfs)  # no half-written recording


@pytest.mark.parametrize("damage", ["bytes", "text"])
def test_a_damaged_database_with_a_matching_fingerprint_is_rebuilt(scene, tmp_path, reference, damage):
    out = tmp_path / "out"
    check(recon("run", scene, "--out", out, *FAST), 0)
    db = out / "database.db"
    if damage == "bytes":  # pages overwritten in the middle, the SQLite header intact
        data = bytearray(db.read_bytes())
        data[len(data) // 3: len(data) // 3 + 8192] = os.urandom(8192)
        db.write_bytes(bytes(data))
    else:
        db.write_text("not a database at all\n")
    res = check(recon("run", scene, "--out", out, *FAST), 0)
    rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert not rep["database_reused"], res.err
    assert model_figures(rep) == model_figures(reference)
