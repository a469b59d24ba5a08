"""`recon bench ...`: benchmarks. `recon bench pairs DATA_ROOT` runs the GT-homography pair benchmark."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Optional

import typer

bench_app = typer.Typer(name="bench", help="Benchmarks against ground truth.", no_args_is_help=True,
                        add_completion=False, pretty_exceptions_enable=False)


def parse_methods(text: str | None) -> list[str]:
    """Comma-separated method names (all of METHODS when empty); UserError for an unknown one."""
    from matching.registry import METHODS

    from .cli import UserError

    if not text or not text.strip():
        return list(METHODS)
    methods = [m.strip() for m in text.split(",") if m.strip()]
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise UserError(f"unknown method{'s' if len(bad) > 1 else ''} {', '.join(map(repr, bad))}; "
                        f"choose from {', '.join(METHODS)}")
    return list(dict.fromkeys(methods))


@bench_app.command("pairs")
def pairs_cmd(
    data_root: Annotated[Path, typer.Argument(help="Folder holding oxford/, hpatches/ and/or evd/ pairs "
                                                   "with ground-truth homographies.")],
    methods: Annotated[Optional[str], typer.Option(
        "--methods", help="Comma-separated methods (default: all: extra-affine,sift,orb,asift,aorb).")] = None,
    th: Annotated[float, typer.Option("--th", help="Correctness threshold in pixels (paper: sqrt(3)).")]
        = math.sqrt(3.0),
    json_out: Annotated[Optional[Path], typer.Option("--json", help="Write the rows to this JSON file.")] = None,
    only: Annotated[Optional[str], typer.Option(
        "--only", help="Run only pairs whose name contains this text (case-insensitive).")] = None,
    no_progress: Annotated[bool, typer.Option("--no-progress", help="Hide the progress bar.")] = False,
    baseline_ransac_px: Annotated[float, typer.Option(
        "--baseline-ransac-px", help="Final RANSAC threshold of the baselines (5 = OpenCV's asift sample, "
                                     "i.e. stock; 1.5 = the extra-affine matcher's own filter).")] = 5.0,
) -> None:
    """Precision, points, time and peak memory of each method on each GT pair (paper's Table I)."""
    from matching.registry import get_matcher

    from .bench_pairs import discover_pairs, print_report, run_bench
    from .cli import UserError

    names = parse_methods(methods)
    if not th > 0 or not math.isfinite(th):
        raise UserError(f"--th must be a positive number of pixels, got {th}")
    if not data_root.is_dir():
        raise UserError(f"{data_root}: no such folder")
    pairs = discover_pairs(data_root)
    if not pairs:
        raise UserError(f"{data_root}: no ground-truth pairs found (expected oxford/<set>/img1..6 + H1to<k>p, "
                        f"hpatches/<seq>/1..6 + H_1_<k>, or evd/1, evd/2, evd/h)")
    if only:
        pairs = [p for p in pairs if only.lower() in p.name.lower()]
        if not pairs:
            raise UserError(f"no pair name contains {only!r}")
    matchers = {}
    for m in names:
        try:
            matchers[m] = get_matcher(m) if m == "extra-affine" else get_matcher(m, ransac_px=baseline_ransac_px)
        except ImportError as e:  # a method whose module is not in this checkout yet
            raise UserError(f"method {m!r} is not available: {e}") from None
    rows = run_bench(pairs, names, th=th, json_path=json_out, progress=not no_progress, matchers=matchers)
    print_report(rows, th=th)
    if json_out is not None:
        typer.echo(f"wrote {len(rows)} rows to {json_out}")


def register(app: typer.Typer) -> None:
    """Add the `bench` sub-app to the recon CLI (idempotent: `main()` may register twice)."""
    if any(g.typer_instance is bench_app for g in app.registered_groups):
        return
    app.add_typer(bench_app, name="bench")
