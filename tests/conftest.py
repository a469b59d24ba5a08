"""Shared test setup: where the real public data lives, the markers, and the rendered scenes
(and their reconstructions) that several test files share, built once per session.

Real data (read-only, never copied into the repository) is found at `SHARED_DATA`:
`$RECON_SHARED_DATA`, else `../shared/data` beside the repository. A test that reads it either
takes one of the fixtures `shared_data`, `graf_dir`, `evd_dir`, `scene_dir` or carries
`@pytest.mark.requires_shared("oxford/graf/H1to2p", ...)` (paths relative to SHARED_DATA);
either way it is skipped, with a reason naming the missing path, when the data is absent.
Everything else (rendered scenes, synthetic images, synthesized COLMAP databases) runs
everywhere: `RECON_SHARED_DATA=/nonexistent python -m pytest` skips only the tests that read
real data.

Markers (registered in pyproject.toml):

* `slow`: an end-to-end run (the whole pipeline, stock COLMAP, `recon compare`, the difficulty
  sweep, the matcher's escalation levels) or anything else over about 3 s; `make test-fast`
  (`-m "not slow"`) leaves them out, `make test` runs everything.
* `requires_shared(*paths)`: skipped unless every path exists under SHARED_DATA; added
  automatically (without paths) to tests that use the shared-data fixtures, so
  `-m "not requires_shared"` selects the tests that need nothing but the repository.

Session fixtures: `rendered_scene(preset, size)` renders a preset (seed 0) once per session and
hands out its folder; `corner_scene`, `corner_wide_scene` and `facade_extreme_scene` are the
three scenes the test files share; `corner_sift_run` and `corner_wide_cli_run` reconstruct a
scene once. These folders are shared: a test that changes files in them must copy them to its
`tmp_path` first.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2  # noqa: F401  (first: importing pycolmap before cv2 made cv2.imwrite(PNG) crash, double free in zlib)
import pytest

from shared_paths import REPO, SHARED_DATA  # noqa: E402, F401  (re-exported for fixtures)

SHARED_FIXTURES = ("shared_data", "graf_dir", "evd_dir", "scene_dir")
SMALL = (480, 360)  # image size (px) of the small rendered scenes: seconds per run, not minutes


def missing_shared(*paths: str) -> list[Path]:
    """The paths (relative to SHARED_DATA) that do not exist; SHARED_DATA itself when no path is given."""
    wanted = [SHARED_DATA / p for p in paths] or [SHARED_DATA]
    return [p for p in wanted if not p.exists()]


def skip_reason(missing: list[Path]) -> str:
    """'...not found' naming what the test reads (relative to SHARED_DATA), or the missing files."""
    if not SHARED_DATA.is_dir():
        leaves = [p for p in missing if p != SHARED_DATA and not any(p in q.parents for q in missing)]
        wanted = ", ".join(str(p.relative_to(SHARED_DATA)) for p in leaves)
        reads = f"; reads {wanted}" if wanted else ""
        return f"shared data folder {SHARED_DATA} not found (set RECON_SHARED_DATA){reads}"
    top = [p for p in missing if not any(q in p.parents for q in missing)]  # a missing folder, not its files
    return f"shared data not found: {', '.join(map(str, top))} (set RECON_SHARED_DATA)"


def skip_unless_shared(*paths: str) -> Path:
    """SHARED_DATA / paths[0] (or SHARED_DATA), skipping the calling test when any path is missing."""
    __tracebackhide__ = True  # the skip is reported at the test's line, not here
    missing = missing_shared(*paths)
    if missing:
        pytest.skip(skip_reason(missing))
    return SHARED_DATA / paths[0] if paths else SHARED_DATA


# markers ----------------------------------------------------------------------------------------
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark the users of the shared-data fixtures `requires_shared`; skip (at the test's own
    location in the summary) the tests whose `requires_shared` paths are missing."""
    for item in items:
        if any(f in getattr(item, "fixturenames", ()) for f in SHARED_FIXTURES):
            item.add_marker(pytest.mark.requires_shared)  # the fixture skips, naming what it looked for
        missing = sorted({p for mark in item.iter_markers("requires_shared") for p in missing_shared(*mark.args)
                          if mark.args})
        if missing:
            item.add_marker(pytest.mark.skip(reason=skip_reason(missing)))


# real data --------------------------------------------------------------------------------------
@pytest.fixture(scope="session")
def shared_data() -> Path:
    """SHARED_DATA (tests that use it also mark the files they read with `requires_shared`)."""
    return skip_unless_shared()


@pytest.fixture(scope="session")
def graf_dir() -> Path:
    """Oxford graf: img1.png ... img6.png and the homographies H1to2p ... H1to6p."""
    return skip_unless_shared("oxford/graf", "oxford/graf/img1.png", "oxford/graf/H1to2p")


@pytest.fixture(scope="session")
def evd_dir() -> Path:
    """EVD: 1/<pair>.png, 2/<pair>.png and h/<pair>.txt."""
    return skip_unless_shared("evd", "evd/1", "evd/2", "evd/h")


@pytest.fixture(scope="session")
def scene_dir() -> Callable[..., Path]:
    """scene_dir("fountain_P11") -> SHARED_DATA/scenes/fountain_P11, skipping when the scene or its
    images/ is missing; scene_dir("fountain_P11", "gt") checks gt/ instead of images/."""

    def get(name: str, *parts: str) -> Path:
        __tracebackhide__ = True
        return skip_unless_shared(f"scenes/{name}", *(f"scenes/{name}/{p}" for p in parts or ("images",)))

    return get


# rendered scenes, once per session --------------------------------------------------------------
@pytest.fixture(scope="session")
def rendered_scene(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Path]:
    """rendered_scene(preset, size=SMALL) -> a folder <unique>/<preset> (images/, gt/), seed 0,
    rendered the first time it is asked for. The folder's parent holds nothing else."""
    from scenes.render import render_scene

    cache: dict[tuple[str, tuple[int, int]], Path] = {}

    def get(preset: str, size: tuple[int, int] = SMALL) -> Path:
        key = (preset, (int(size[0]), int(size[1])))
        if key not in cache:
            d = tmp_path_factory.mktemp(f"{preset}-{size[0]}x{size[1]}") / preset
            render_scene(d, preset, seed=0, image_size=key[1])
            cache[key] = d
        return cache[key]

    return get


@pytest.fixture(scope="session")
def corner_scene(rendered_scene) -> Path:
    """The building corner (4 views) at 480 x 360."""
    return rendered_scene("corner")


@pytest.fixture(scope="session")
def corner_wide_scene(rendered_scene) -> Path:
    """The wide building corner (4 views 29 deg apart, viewing angles to ~80 deg) at 480 x 360."""
    return rendered_scene("corner-wide")


@pytest.fixture(scope="session")
def facade_extreme_scene(rendered_scene) -> Path:
    """facade-extreme (4 views, grazing angles) at 640 x 480, in a folder named facade-extreme."""
    return rendered_scene("facade-extreme", (640, 480))


# reconstructions, once per session --------------------------------------------------------------
@pytest.fixture(scope="session")
def corner_sift_run(corner_scene, tmp_path_factory):
    """(out folder, RunReport, warnings) of `run_scene` on `corner_scene` with the SIFT baseline."""
    from recon.config import RunConfig
    from recon.core.observer import BaseRunObserver
    from recon.core.pipeline import run_scene

    out = tmp_path_factory.mktemp("corner-sift") / "out"
    warnings: list[str] = []

    class Warnings(BaseRunObserver):
        def on_warning(self, message: str) -> None:
            warnings.append(message)

    rep = run_scene(corner_scene, RunConfig.from_options(out=out, method="sift", progress=False), observer=Warnings())
    return out, rep, warnings


@pytest.fixture(scope="session")
def corner_wide_cli_run(corner_wide_scene, tmp_path_factory) -> dict:
    """`recon run` (default method, default Rerun sink OUT/recording.rrd) on `corner_wide_scene`:
    {"scene": folder, "out": folder, "rc": exit code}. A fresh run: the recording holds the growth replay."""
    from recon.cli import main

    out = tmp_path_factory.mktemp("corner-wide-run") / "out"
    rc = main(["run", str(corner_wide_scene), "--out", str(out), "--no-progress"])
    return {"scene": corner_wide_scene, "out": out, "rc": rc}
