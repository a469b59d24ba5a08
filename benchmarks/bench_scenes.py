"""Scene benchmark: `recon run` (extra-affine) vs COLMAP's stock SIFT pipeline, same images.

    python benchmarks/bench_scenes.py [SCENES_ROOT] [--scenes a,b] [--max-size PX]
        [--json benchmarks/results/scenes.json] [--stock-presets default[,high]]
        [--out out/bench] [--pairs exhaustive] [--seed 0] [--set KEY=VALUE ...]

SCENES_ROOT (default: ../shared/data/scenes next to the repository, or $RECON_SHARED_DATA/scenes)
holds one folder per scene (photos in `images/` or at the top level, optional ground truth in
`gt/`, see `recon.eval.gt`). For each scene, in this one process, `recon.eval.compare.compare_scene` (the logic behind
`recon compare` and `recon bench scenes`; this script is a thin wrapper kept for its command line):

1. `recon.eval.stock.run_stock` for each stock preset into `OUT/<scene>/stock-<preset>`;
2. `recon.core.pipeline.run_scene` (method extra-affine) into `OUT/<scene>/extra_affine`;
3. each model is evaluated against the GT when the scene has one (`recon.eval.evaluate`), matched by
   image name; a malformed GT is reported and the scene is still run without it;
4. the two point clouds are compared after a similarity alignment (`recon.eval.compare.compare_clouds`);
   `OUT/<scene>/compare.json` holds the scene's comparison.

Peak memory: every run is wrapped in `matching.memory.PeakRss` (RSS sampled from /proc; the
process-lifetime `ru_maxrss` that `recon run` reports would carry the first run's peak into the
later ones), and `peak MB` is the highest RSS seen during that run.

Prints one rich table (one row per scene and method, plus "ours / stock" ratio rows: registered
images, 3D points, mean track length, total time and peak memory ratios) and writes all rows,
evaluations and reports' headline numbers to the JSON file (atomically, after every scene).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a plain script from anywhere
    sys.path.insert(0, str(REPO))

from recon.config import DEFAULT_MAX_SIZE  # noqa: E402
from recon.errors import UserError  # noqa: E402
from recon.eval.compare import OURS, discover_scenes, run_scenes, scenes_table  # noqa: E402,F401
from recon.eval.stock import PRESETS  # noqa: E402


def default_root() -> Path:
    data = Path(os.environ.get("RECON_SHARED_DATA") or REPO.parent / "shared" / "data")
    return data / "scenes"


def main(argv: list[str] | None = None) -> int:
    from rich.console import Console

    from matching.memory import return_large_buffers_to_os

    return_large_buffers_to_os()  # as the recon CLI does

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", nargs="?", type=Path, default=None,
                    help="folder of scene folders (default: ../shared/data/scenes)")
    ap.add_argument("--scenes", default="", help="comma-separated scene names (default: all)")
    ap.add_argument("--max-size", type=int, default=DEFAULT_MAX_SIZE, help="working resolution, longer side px (0 = full)")
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "scenes.json")
    ap.add_argument("--stock-presets", default="default", help=f"comma-separated, of {', '.join(PRESETS)}")
    ap.add_argument("--out", type=Path, default=REPO / "out" / "bench",
                    help="outputs: OUT/<scene>/{extra_affine,stock-*}")
    ap.add_argument("--pairs", default="exhaustive", help="pair selection for both pipelines (as recon run --pairs)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="settings",
                    help="an option of our run, as `recon run --set` (repeatable), e.g. matcher.adaptive=true")
    ap.add_argument("--progress", action="store_true", help="recon run's progress bars on stderr")
    a = ap.parse_args(argv)

    console = Console(width=None if sys.stdout.isatty() else 160)  # a pipe or file: don't wrap at 80
    err = Console(stderr=True, highlight=False)
    root = (a.root or default_root()).expanduser()
    presets = [p.strip() for p in a.stock_presets.split(",") if p.strip()]
    bad = [p for p in presets if p not in PRESETS]
    if bad:
        err.print(f"[red]bench_scenes: unknown stock preset(s) {', '.join(bad)}; choose from {', '.join(PRESETS)}[/red]")
        return 2
    wanted = [s.strip() for s in a.scenes.split(",") if s.strip()] or None
    try:
        results = run_scenes(root, a.out, wanted, presets=presets, max_size=a.max_size, pairs=a.pairs,
                             seed=a.seed, progress=a.progress, json_path=a.json, settings=a.settings,
                             log=lambda m: err.print(m, markup=False))
    except UserError as e:
        err.print(f"[red]bench_scenes: {e}[/red]", highlight=False)
        return 2
    console.print(scenes_table(results, a.max_size))
    console.print(f"JSON: {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
