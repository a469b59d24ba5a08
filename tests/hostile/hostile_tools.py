"""Helpers of the hostile suite (see conftest.py): run the CLI as a subprocess with a timeout,
check the exit contract, snapshot the user's files, compare models."""

from __future__ import annotations

import hashlib
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
INJECT = Path(__file__).resolve().parent / "inject"
TIMEOUT_S = 180  # a hang guard only (the machine may be loaded), never a timing assertion
FOREIGN_LOG_LINE = re.compile(r"^(\[ ?(WARN|ERROR|INFO):\d|[IWE]\d{8} \d\d:\d\d:\d\d)")
"""A log line of a library rather than of recon: OpenCV's ("[ WARN:0@0.8] global ...",
"[ERROR:0@0.8] ...") or COLMAP's glog ("I20261208 00:13:01.557255 ... bundle_adjustment.cc:46]")."""
FAST = ["--method", "sift", "--max-size", "320", "--no-progress", "--rerun", "none"]
PRESET, SIZE = "facade-4x30", (320, 240)


@dataclass
class Result:
    rc: int
    out: str
    err: str
    args: list[str]

    @property
    def error_lines(self) -> list[str]:
        return [ln for ln in self.err.splitlines() if ln.startswith("recon: error:")]

    @property
    def warnings(self) -> list[str]:
        return [ln for ln in self.err.splitlines() if ln.startswith("recon: warning:")]


def _env(extra: dict[str, str] | None = None, inject: bool = False) -> dict[str, str]:
    env = dict(os.environ)
    paths = ([str(INJECT)] if inject else []) + [str(REPO)]
    env["PYTHONPATH"] = os.pathsep.join(paths + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    env.pop("RECON_DEBUG", None)
    env.update(extra or {})
    return env


def default_sigint() -> None:
    """Child-process preamble: Ctrl-C (SIGINT) at its default disposition, as in a terminal. A
    shell starts background jobs with SIGINT ignored and children inherit that, so without this
    the signal tests would test the launcher (`nohup make test &`), not `recon`."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def recon(*args: object, env: dict[str, str] | None = None, cwd: Path | None = None,
          inject: bool = False, timeout: float = TIMEOUT_S) -> Result:
    """`python -m recon ARGS` with a timeout; a hang fails the test."""
    argv = [str(a) for a in args]
    try:
        p = subprocess.run([sys.executable, "-m", "recon", *argv], capture_output=True, text=True,
                           env=_env(env, inject), cwd=cwd, timeout=timeout, preexec_fn=default_sigint)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"recon {' '.join(argv)} hung (no exit within {timeout:.0f} s); stderr: {e.stderr!r}")
    return Result(p.returncode, p.stdout, p.stderr, argv)


def start(*args: object, env: dict[str, str] | None = None, inject: bool = False) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "recon", *[str(a) for a in args]], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=_env(env, inject), preexec_fn=default_sigint)


def finish(p: subprocess.Popen, timeout: float = TIMEOUT_S) -> Result:
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        out, err = p.communicate()
        pytest.fail(f"recon {' '.join(p.args[3:])} hung; stderr: {err!r}")  # type: ignore[index]
    return Result(p.returncode, out, err, list(p.args[3:]))  # type: ignore[index]


def wait_for(path: Path, proc: subprocess.Popen, timeout: float = TIMEOUT_S) -> None:
    """Wait until `path` exists (the injected pause point was reached) or the process ended."""
    deadline = time.monotonic() + timeout
    while not path.exists():
        if proc.poll() is not None:
            pytest.fail(f"the run ended before reaching the pause point: {proc.stderr.read() if proc.stderr else ''}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail("the run never reached the pause point")
        time.sleep(0.05)


def check(res: Result, code: int, *, text: str | None = None) -> Result:
    """The contract every case keeps: exit code, no traceback or C stack dump, <= 1 error line."""
    where = f"recon {' '.join(res.args)}\nstdout: {res.out[-2000:]}\nstderr: {res.err[-3000:]}"
    assert res.rc == code, f"exit {res.rc}, expected {code}\n{where}"
    assert "Traceback" not in res.err and "Traceback" not in res.out, where
    assert "*** Aborted at" not in res.err and "stack trace:" not in res.err, where
    assert not [ln for ln in res.err.splitlines() if FOREIGN_LOG_LINE.match(ln)], where  # OpenCV's, glog's
    assert len(res.error_lines) <= 1, where
    if code == 2:
        assert len(res.error_lines) == 1, where
    if text is not None:
        assert text in res.err, f"{text!r} not in stderr\n{where}"
    return res


# the user's files ---------------------------------------------------------------------------------
class Snapshot:
    """Paths, sizes, mtimes and content hashes of every file under `root` (folders and symlinks
    too), except under the `skip` folders (recon's own output folders) and files named in
    `ignore`."""

    def __init__(self, root: Path, skip: tuple[Path, ...] = (), ignore: tuple[str, ...] = ()):
        self.root = Path(root)
        self.skip = tuple(Path(s).absolute() for s in skip)
        self.ignore = set(ignore)
        self.state = self._take()

    def _take(self) -> dict[str, tuple]:
        state: dict[str, tuple] = {}
        for dirpath, dirs, files in os.walk(self.root):
            d = Path(dirpath)
            dirs[:] = [x for x in dirs if (d / x).absolute() not in self.skip]
            for name in dirs + files:
                if name in self.ignore:
                    continue
                p = d / name
                rel = str(p.relative_to(self.root))
                if p.is_symlink():
                    state[rel] = ("link", os.readlink(p))
                elif p.is_dir():
                    state[rel] = ("dir", p.stat().st_mode)
                elif not p.is_file():  # a FIFO or device: reading it could block
                    state[rel] = ("special", p.stat().st_mode)
                else:
                    st = p.stat()
                    state[rel] = ("file", st.st_size, st.st_mtime_ns, st.st_mode,
                                  hashlib.sha1(p.read_bytes()).hexdigest())
        return state

    def assert_unchanged(self) -> None:
        now = self._take()
        added = sorted(set(now) - set(self.state))
        removed = sorted(set(self.state) - set(now))
        changed = sorted(k for k in set(now) & set(self.state) if now[k] != self.state[k])
        assert not (added or removed or changed), f"user files changed: added {added}, removed {removed}, " \
                                                  f"changed {changed}"


def model_figures(report: dict) -> dict:
    """The figures a resumed run must reproduce exactly."""
    return {k: report[k] for k in ("status", "num_images", "registered_images", "num_points3D", "registered")} | {
        "mean_reprojection_error": round(report["mean_reprojection_error"] or 0.0, 6),
        "mean_track_length": round(report["mean_track_length"], 6),
        "verified": [p["verified_inliers"] for p in report["pairs"]]}


def image_names(scene: Path) -> list[str]:
    return sorted(p.name for p in (scene / "images").iterdir())
