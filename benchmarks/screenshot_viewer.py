"""Screenshot of a recording in Rerun's web viewer, in a real browser (headless Chromium).

    python benchmarks/screenshot_viewer.py OUT_DIR_OR_RRD [--out docs/viewer.png] [--size 1600x1000]

Serves the recording the way `recon view --web` does (`rerun --serve-web` on localhost, free
ports), opens the viewer's address in headless Chromium and takes the screenshot through the
DevTools protocol over a pipe (`--remote-debugging-pipe`: JSON messages on file descriptors 3 and
4, no extra package). `chromium --screenshot` alone is not enough: it shoots at the page's load
event, and with `--virtual-time-budget` the viewer's WebAssembly never finishes starting (the
shot shows "Loading Application Bundle... 100%"). Here the page runs in real time and is shot
every few seconds until it no longer looks like the loading screen (almost one colour), then
once more after the layout settles. Chromium comes from the system's packages (`apt-get install
chromium`); `find_browser()` returns None where there is none (the test then skips).

Exit status 0 and the PNG path on stdout when the screenshot shows a loaded viewer; 1 otherwise.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def find_browser() -> str | None:
    """A Chromium-family browser on PATH, or None."""
    return next((p for p in map(shutil.which, BROWSERS) if p), None)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_http(url: str, timeout_s: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            urllib.request.urlopen(url, timeout=2).read(64)
            return True
        except OSError:
            time.sleep(0.5)
    return False


def looks_loaded(png: Path) -> bool:
    """A loaded viewer has panels, text, plots and images: hundreds of distinct colours (in
    16-level bins); the loading screen has a handful (a flat background and one line of text)."""
    import cv2
    import numpy as np

    img = cv2.imread(str(png))
    if img is None:
        return False
    q = (img // 16).reshape(-1, 3)
    _, counts = np.unique(q, axis=0, return_counts=True)
    return len(counts) > 200


class DevTools:
    """A minimal Chrome DevTools Protocol client over `--remote-debugging-pipe`."""

    def __init__(self, browser: str, size: tuple[int, int], profile: str) -> None:
        to_chrome_r, self._w = os.pipe()
        self._r, from_chrome_w = os.pipe()

        def fds() -> None:  # in the child: the pipe ends on 3 (commands in) and 4 (replies out)
            import fcntl

            # copies above 10 first: a pipe end may itself be fd 3 or 4 (dup2 onto itself would
            # keep its close-on-exec flag); dup2 makes 3 and 4 inheritable
            high_r, high_w = fcntl.fcntl(to_chrome_r, fcntl.F_DUPFD, 10), fcntl.fcntl(from_chrome_w, fcntl.F_DUPFD, 10)
            os.dup2(high_r, 3)
            os.dup2(high_w, 4)

        self.proc = subprocess.Popen(
            [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
             "--disable-component-update", "--no-first-run", "--hide-scrollbars", "--enable-unsafe-swiftshader",
             "--remote-debugging-pipe", f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
             "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, close_fds=False,
            preexec_fn=fds, start_new_session=True)
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._buf = b""
        self._id = 0
        self.session: str | None = None

    def call(self, method: str, timeout_s: float = 60.0, **params) -> dict:
        import json
        import select

        self._id += 1
        msg = {"id": self._id, "method": method, "params": params}
        if self.session:
            msg["sessionId"] = self.session
        os.write(self._w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout_s
        while True:
            while b"\0" in self._buf:
                raw, self._buf = self._buf.split(b"\0", 1)
                reply = json.loads(raw)
                if reply.get("id") == self._id:
                    if "error" in reply:
                        raise RuntimeError(f"{method}: {reply['error']}")
                    return reply.get("result", {})
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._r], [], [], left)[0]:
                raise TimeoutError(f"{method}: no reply from the browser")
            chunk = os.read(self._r, 1 << 20)
            if not chunk:
                raise RuntimeError("the browser closed the DevTools pipe")
            self._buf += chunk

    def close(self) -> None:
        try:
            self.session = None
            self.call("Browser.close", timeout_s=10)
        except Exception:
            pass
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        os.close(self._w)
        os.close(self._r)


def screenshot(browser: str, url: str, out: Path, size: tuple[int, int], timeout_s: float = 120.0,
               settle_s: float = 8.0, log=print) -> bool:
    """Open `url` in headless Chromium, wait (real time) until the page stops looking like a
    loading screen, let it settle, and write the PNG to `out`; False when it never loads."""
    import base64

    with tempfile.TemporaryDirectory(prefix="recon-chromium-") as profile:
        dt = DevTools(browser, size, profile)
        try:
            target = dt.call("Target.createTarget", url="about:blank")["targetId"]
            dt.session = dt.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
            dt.call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1,
                    mobile=False)
            dt.call("Page.enable")
            dt.call("Page.navigate", url=url)
            t0 = time.monotonic()
            out.parent.mkdir(parents=True, exist_ok=True)
            while time.monotonic() - t0 < timeout_s:
                time.sleep(3.0)
                out.write_bytes(base64.b64decode(dt.call("Page.captureScreenshot", format="png")["data"]))
                if looks_loaded(out):
                    time.sleep(settle_s)  # the recording streams in and the layout settles
                    out.write_bytes(base64.b64decode(dt.call("Page.captureScreenshot", format="png")["data"]))
                    log(f"loaded after {time.monotonic() - t0:.0f} s")
                    return True
            log(f"still the loading screen after {timeout_s:.0f} s")
            return False
        finally:
            dt.close()


def shoot(target: Path, out: Path, size: tuple[int, int] = (1600, 1000), log=print) -> bool:
    """Serve `target` (a recording or an output folder) with the web viewer and screenshot it."""
    from recon.cli.view import resolve_recording, web_command, web_url
    from recon.viz.rerun_log import find_viewer

    browser, viewer = find_browser(), find_viewer()
    if browser is None or viewer is None:
        log(f"missing: {'a Chromium browser' if browser is None else 'the rerun executable'}")
        return False
    rrd = resolve_recording(target)
    port, grpc = free_port(), free_port()
    url = web_url(port, grpc) + "&renderer=webgl"  # software WebGL (SwiftShader) without a GPU
    server = subprocess.Popen(web_command(viewer, rrd, port, grpc), stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        if not wait_http(f"http://127.0.0.1:{port}/"):
            log("the web viewer did not start")
            return False
        ok = screenshot(browser, url, out, size, log=log)
        if ok:
            log(f"wrote {out}")
        return ok
    finally:
        os.killpg(server.pid, signal.SIGINT)
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("target", type=Path, help="a recording (.rrd) or a recon run / compare output folder")
    ap.add_argument("--out", type=Path, default=Path("docs/viewer.png"), help="PNG to write")
    ap.add_argument("--size", default="1600x1000", help="browser window WxH")
    a = ap.parse_args(argv)
    w, h = (int(v) for v in a.size.lower().split("x"))
    return 0 if shoot(a.target, a.out, (w, h), log=lambda m: print(m, file=sys.stderr)) else 1


if __name__ == "__main__":
    sys.exit(main())
