"""The hostile suite: the real CLI as a subprocess, against bad inputs, options, folders, signals,
full disks and absent viewers (helpers in `hostile_tools`). Every case checks the documented
exit code, no traceback (and no C stack dump), at most one `recon: error:` line, no hang (a
timeout on every call), and that no user file outside recon's own output folder changed.

Scenes are rendered once per session (`scenes.render`, 320x240, 4 views of the stepped facade)
and copied per test; runs use `--method sift --max-size 320 --rerun none` where the method does
not matter. Faults are injected at known points through `inject/sitecustomize.py`
(`RECON_HOSTILE=STAGE:ACTION`), never with sleeps.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from hostile_tools import FAST, PRESET, SIZE, check, recon


# scenes -------------------------------------------------------------------------------------------
@pytest.fixture(scope="session")
def rendered(tmp_path_factory) -> Path:
    """The stepped facade, 4 views at 320x240, rendered once per session (read-only: copy it)."""
    from scenes.render import render_scene

    root = tmp_path_factory.mktemp("hostile") / "facade"
    render_scene(root, PRESET, seed=0, image_size=SIZE)
    return root


@pytest.fixture(scope="session")
def reference(rendered, tmp_path_factory) -> dict:
    """report.json of one clean run of the rendered scene (what every resumed run must match)."""
    out = tmp_path_factory.mktemp("reference") / "out"
    res = recon("run", rendered, "--out", out, *FAST)
    check(res, 0)
    return json.loads((out / "report.json").read_text(encoding="utf-8"))


@pytest.fixture
def scene(rendered, tmp_path) -> Path:
    """A private copy of the rendered scene (images/ and gt/)."""
    d = tmp_path / "scene"
    shutil.copytree(rendered, d, ignore=shutil.ignore_patterns(".recon*"))
    return d


def pytest_collection_modifyitems(config, items):
    """The whole suite is `slow` (68 tests, some 90 CLI runs; `make test` and CI run it,
    `make test-fast` does not)."""
    here = Path(__file__).parent
    for item in items:
        if here in Path(str(item.fspath)).parents:
            item.add_marker(pytest.mark.slow)
