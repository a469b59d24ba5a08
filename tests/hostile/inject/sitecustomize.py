"""Test-only fault injection for the hostile suite, loaded by Python at start-up (this folder is
put first on PYTHONPATH of a `python -m recon ...` subprocess; nothing here is imported
otherwise). `RECON_HOSTILE=STAGE:ACTION` makes the real CLI hit a fault at a known point, so
signals and races are tested deterministically rather than with sleeps:

* STAGE: `import` (while `matching` imports, in the first second of the program), `pycolmap`
  (while pycolmap's extension initialises, its glog handler already in place), `load` (after the first image is
  decoded), `match` (after the second pair result is written to the cache), `sfm` (at the first
  registration step, inside COLMAP's mapper), `export` (before points.ply is written);
* ACTION: `SIGINT` / `SIGTERM` (the process signals itself: the real signal path), `pause`
  (create `$RECON_HOSTILE_FLAG.paused`, then wait until `$RECON_HOSTILE_FLAG.go` exists: lets a
  test start a second run while this one holds the output folder), `bug` (an unexpected
  exception, as a programming error would raise) or `eacces` (a PermissionError naming a file).
"""

from __future__ import annotations

import os
import signal
import sys
import time


def _act(action: str) -> None:
    if action in ("SIGINT", "SIGTERM"):
        os.kill(os.getpid(), getattr(signal, action))
        time.sleep(0.5)  # let the signal arrive here, inside the stage
        return
    if action == "bug":
        raise ZeroDivisionError("injected bug")
    if action == "eacces":
        raise PermissionError(13, "Permission denied", "/injected/cache/file.npz")
    if action == "pause":
        flag = os.environ["RECON_HOSTILE_FLAG"]
        open(flag + ".paused", "w").close()
        deadline = time.monotonic() + 120
        while not os.path.exists(flag + ".go") and time.monotonic() < deadline:
            time.sleep(0.05)


def _patch(module) -> None:
    stage, _, action = os.environ.get("RECON_HOSTILE", "").partition(":")
    name = module.__name__
    fired = []

    def once() -> bool:
        if fired:
            return False
        fired.append(1)
        return True

    if stage == "load" and name == "recon.core.scene":
        real = module._decode_one

        def decode(*a, **k):
            out = real(*a, **k)
            if once():
                _act(action)
            return out

        module._decode_one = decode
    elif stage == "match" and name == "recon.core.paircache":
        real_save = module.save_pair_result
        count = []

        def save(*a, **k):
            real_save(*a, **k)
            count.append(1)
            if len(count) == 2 and once():
                _act(action)

        module.save_pair_result = save
    elif stage in ("sfm", "export") and name == "recon.core.sfm":
        if stage == "sfm":
            real_run = module.run_incremental

            def run_incremental(db_path, image_dir, options, on_step=None):
                def step(s, live):
                    if once():
                        _act(action)
                    if on_step is not None:
                        on_step(s, live)

                return real_run(db_path, image_dir, options, on_step=step)

            module.run_incremental = run_incremental
        else:
            real_ply = module.write_points_ply

            def write_points_ply(*a, **k):
                if once():
                    _act(action)
                return real_ply(*a, **k)

            module.write_points_ply = write_points_ply


class _PatchAfterImport:
    TARGETS = ("recon.core.scene", "recon.core.paircache", "recon.core.sfm")
    DURING = {"import": "matching.features", "pycolmap": "pyceres"}  # signal while these import

    def find_spec(self, fullname, path=None, target=None):
        stage, _, action = os.environ.get("RECON_HOSTILE", "").partition(":")
        if self.DURING.get(stage) == fullname:
            sys.meta_path.remove(self)
            _act(action)  # the module is being imported right now: its parent package is half done
            return None
        if fullname not in self.TARGETS:
            return None
        import importlib.util

        sys.meta_path.remove(self)
        try:
            spec = importlib.util.find_spec(fullname)
        finally:
            sys.meta_path.insert(0, self)
        if spec is None or spec.loader is None:
            return spec
        exec_module = spec.loader.exec_module

        def exec_and_patch(module):
            exec_module(module)
            _patch(module)

        spec.loader.exec_module = exec_and_patch
        return spec


if os.environ.get("RECON_HOSTILE"):
    sys.meta_path.insert(0, _PatchAfterImport())
