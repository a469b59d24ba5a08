"""Absent or broken Rerun viewers: a run never hangs and always finishes its outputs; `recon view`
refuses what is not a recording."""

from __future__ import annotations

import json
import socket
import threading

from hostile_tools import Snapshot, check, recon

RUN = ["--method", "sift", "--max-size", "320", "--no-progress"]


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _outputs_complete(out) -> dict:
    rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert rep["status"] == "ok" and (out / "sparse" / "0").is_dir() and (out / "points.ply").is_file()
    return rep


def test_connect_with_no_viewer_listening(scene, tmp_path):
    out = tmp_path / "out"
    url = f"rerun+http://127.0.0.1:{_closed_port()}/proxy"
    res = check(recon("run", scene, "--out", out, *RUN, "--rerun", f"connect:{url}"), 0)
    assert len(res.warnings) == 1 and url in res.warnings[0], res.err
    _outputs_complete(out)


def test_connect_to_something_that_never_answers(scene, tmp_path):
    """A port that accepts connections but never speaks gRPC (a dead viewer): the final flush
    would wait for ever; it gives up after a few seconds with one warning."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    held: list[socket.socket] = []
    stop = threading.Event()

    def accept() -> None:
        srv.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(srv.accept()[0])
            except OSError:
                continue

    t = threading.Thread(target=accept, daemon=True)
    t.start()
    try:
        out = tmp_path / "out"
        url = f"rerun+http://127.0.0.1:{srv.getsockname()[1]}/proxy"
        res = check(recon("run", scene, "--out", out, *RUN, "--rerun", f"connect:{url}"), 0)
        assert len(res.warnings) == 1 and "did not take the recording" in res.warnings[0], res.err
        _outputs_complete(out)
    finally:
        stop.set()
        t.join(2)
        for c in held:
            c.close()
        srv.close()


def test_spawn_a_viewer_that_cannot_start(scene, tmp_path):
    """What `--rerun spawn` meets on a machine without a display: the viewer exits at once."""
    fake = tmp_path / "rerun"
    fake.write_text("#!/bin/sh\necho 'error: neither WAYLAND_DISPLAY nor DISPLAY is set' >&2\nexit 1\n")
    fake.chmod(0o755)
    out = tmp_path / "out"
    res = check(recon("run", scene, "--out", out, *RUN, "--rerun", "spawn", env={"RECON_RERUN_VIEWER": str(fake)}),
                0)
    assert len(res.warnings) == 1 and "DISPLAY" in res.warnings[0], res.err
    _outputs_complete(out)


def test_spawn_without_a_viewer_installed(scene, tmp_path):
    snap = Snapshot(tmp_path)
    check(recon("run", scene, "--out", tmp_path / "out", *RUN, "--rerun", "spawn", env={"RECON_RERUN_VIEWER": ""}),
          2, text="not installed")
    snap.assert_unchanged()


def test_view_a_text_file(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    check(recon("view", tmp_path / "notes.txt"), 2, text="not a Rerun recording")


def test_view_a_folder_without_recording(tmp_path):
    check(recon("view", tmp_path), 2, text="no recording.rrd")


def test_view_without_a_viewer(tmp_path):
    (tmp_path / "recording.rrd").write_bytes(b"RRF2" + bytes(64))
    check(recon("view", tmp_path, env={"RECON_RERUN_VIEWER": ""}), 2, text="not installed")
