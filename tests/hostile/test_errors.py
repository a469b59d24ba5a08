"""Unexpected failures mid-run: one line and the documented exit code, the traceback only on request."""

from __future__ import annotations

from hostile_tools import FAST, check, recon


def test_an_internal_error_is_one_line_exit_1(scene, tmp_path):
    res = check(recon("run", scene, "--out", tmp_path / "out", *FAST, inject=True,
                      env={"RECON_HOSTILE": "export:bug"}), 1)
    lines = [ln for ln in res.err.splitlines() if ln.startswith("recon:")]
    assert lines == [lines[0]] and lines[0].startswith("recon: internal error: ZeroDivisionError: injected bug")
    assert "for the traceback" in lines[0]


def test_the_traceback_on_request(scene, tmp_path):
    res = recon("run", scene, "--out", tmp_path / "out", *FAST, inject=True,
                env={"RECON_HOSTILE": "export:bug", "RECON_DEBUG": "1"})
    assert res.rc == 1 and "Traceback" in res.err and "ZeroDivisionError: injected bug" in res.err


def test_a_permission_error_mid_run_names_the_file(scene, tmp_path):
    res = check(recon("run", scene, "--out", tmp_path / "out", *FAST, inject=True,
                      env={"RECON_HOSTILE": "match:eacces"}), 2)
    assert res.error_lines == ["recon: error: permission denied: /injected/cache/file.npz"]
