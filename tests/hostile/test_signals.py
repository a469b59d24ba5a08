"""Ctrl-C (SIGINT) and SIGTERM at each stage: one line, exit 130 / 143, no temporary file left,
and rerunning the same command resumes to the same model as an uninterrupted run."""

from __future__ import annotations

import json
import os
import re

import pytest

from hostile_tools import FAST, Snapshot, check, model_figures, recon

CASES = [(stage, sig) for stage in ("load", "match", "sfm", "export") for sig in ("SIGINT", "SIGTERM")]
TEMP = re.compile(r"\.tmp|\.old-|\.write-test")


@pytest.mark.parametrize("stage, sig", CASES, ids=[f"{s}-{g}" for s, g in CASES])
def test_signal_then_resume_gives_the_same_model(scene, tmp_path, reference, stage, sig):
    out = tmp_path / "out"
    snap = Snapshot(tmp_path, skip=(out,))
    res = check(recon("run", scene, "--out", out, *FAST, inject=True, env={"RECON_HOSTILE": f"{stage}:{sig}"}),
                130 if sig == "SIGINT" else 143)
    word = "interrupted" if sig == "SIGINT" else "terminated"
    lines = [ln for ln in res.err.splitlines() if ln.startswith("recon:")]
    assert lines == [f"recon: {word}; rerun the same command to resume"], res.err
    left = [os.path.join(d, f) for d, ds, fs in os.walk(out) for f in fs + ds if TEMP.search(f)]
    assert not left, left
    assert not (out / "report.json").exists() or stage == "export"
    resumed = check(recon("run", scene, "--out", out, *FAST), 0)
    rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert model_figures(rep) == model_figures(reference), resumed.err
    if stage in ("sfm", "export"):  # everything before the signal came from the caches
        assert rep["pairs_cached"] == len(rep["pairs"]) and rep["database_reused"]
    snap.assert_unchanged()


@pytest.mark.parametrize("stage", ["import", "pycolmap"])
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_signal_while_modules_import(scene, tmp_path, stage, sig):
    """Ctrl-C in the first second, and SIGTERM while pycolmap imports (when its glog failure
    handler comes in): one line, no traceback, no C stack dump, nothing created."""
    out = tmp_path / "out"
    snap = Snapshot(tmp_path)
    res = check(recon("run", scene, "--out", out, *FAST, inject=True, env={"RECON_HOSTILE": f"{stage}:{sig}"}),
                130 if sig == "SIGINT" else 143)
    assert [ln for ln in res.err.splitlines() if ln.strip()] == [
        f"recon: {'interrupted' if sig == 'SIGINT' else 'terminated'}; rerun the same command to resume"], res.err
    snap.assert_unchanged()
