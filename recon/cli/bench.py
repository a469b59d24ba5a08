"""`recon bench ...`: benchmarks. `recon bench pairs DATA_ROOT` runs the GT-homography pair benchmark;
`recon bench scenes ROOT` runs `recon compare` on every scene under ROOT (see `recon.eval.compare`);
`recon bench scale` measures time, memory and registration against the number of photos
(see `recon.eval.bench_scale`); `recon bench tilt` renders frontal/oblique pairs of a textured plane
with exact homographies and counts the pairs each method solves per viewing angle
(`recon.eval.bench_tilt`); `recon bench posed ROOT` matches real photo pairs of scenes with GT cameras
and judges each method's relative pose and epipolar precision per angle between the cameras
(`recon.eval.bench_posed`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Optional

import typer

from matching.config import VARIANTS
from recon.cli._options import check_textures, json_file
from recon.cli.options import image_size as parse_image_size
from recon.cli.options import (
    our_settings,
    progress_option,
    seed_option,
    set_option,
    simulate_option,
    stock_presets,
    stock_presets_option,
    workers_option,
)
from recon.config import DEFAULT_MAX_SIZE

bench_app = typer.Typer(name="bench", help="Benchmarks against ground truth.", no_args_is_help=True,
                        add_completion=False, pretty_exceptions_enable=False)


def parse_methods(text: str | None) -> list[str]:
    """Comma-separated method names (all of METHODS when empty); UserError for an unknown one."""
    from matching.registry import METHODS
    from recon.errors import UserError

    if not text or not text.strip():
        return list(METHODS)
    methods = [m.strip() for m in text.split(",") if m.strip()]
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise UserError(f"unknown method{'s' if len(bad) > 1 else ''} {', '.join(map(repr, bad))}; "
                        f"choose from {', '.join(METHODS)}")
    return list(dict.fromkeys(methods))


def build_matchers(names: list[str], seed: int, baseline_ransac_px: float) -> dict:
    """One PairMatcher per method name; the baselines with their final RANSAC at `baseline_ransac_px`."""
    from matching.registry import get_matcher
    from recon.errors import UserError

    matchers = {}
    for m in names:
        try:
            matchers[m] = get_matcher(m, seed=seed) if m == "extra-affine" \
                else get_matcher(m, seed=seed, ransac_px=baseline_ransac_px)
        except ImportError as e:  # a method whose module is not in this checkout yet
            raise UserError(f"method {m!r} is not available: {e}") from None
    return matchers


BASELINE_RANSAC_HELP = ("Final RANSAC threshold of the baselines (5 = OpenCV's asift sample, i.e. stock; 1.5 = the "
                        "extra-affine matcher's own filter).")


@bench_app.command("pairs")
def pairs_cmd(
    data_root: Annotated[Path, typer.Argument(help="Folder holding oxford/, hpatches/ and/or evd/ pairs "
                                                   "with ground-truth homographies.", metavar="DATA_ROOT")],
    methods: Annotated[Optional[str], typer.Option(
        "--methods", help="Comma-separated methods (default: all: extra-affine,sift,orb,asift,aorb).")] = None,
    th: Annotated[float, typer.Option("--th", help="Correctness threshold in pixels (paper: sqrt(3)).")]
        = math.sqrt(3.0),
    json_out: Annotated[Optional[Path], typer.Option("--json", callback=json_file,
                                                     help="Write the rows to this JSON file.")] = None,
    only: Annotated[Optional[str], typer.Option(
        "--only", help="Run only pairs whose name contains this text (case-insensitive).")] = None,
    progress: Annotated[bool, progress_option()] = True,
    seed: Annotated[int, seed_option()] = 0,
    baseline_ransac_px: Annotated[float, typer.Option("--baseline-ransac-px", help=BASELINE_RANSAC_HELP)] = 5.0,
) -> None:
    """Precision, points, time and peak memory of each method on each GT pair (paper's Table I)."""
    from recon.errors import UserError
    from recon.eval.bench_pairs import discover_pairs, print_report, run_bench

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
    matchers = build_matchers(names, seed, baseline_ransac_px)
    rows = run_bench(pairs, names, th=th, json_path=json_out, progress=progress, matchers=matchers)
    print_report(rows, th=th)
    if json_out is not None:
        typer.echo(f"wrote {len(rows)} rows to {json_out}")


@bench_app.command("tilt")
def tilt_cmd(
    out: Annotated[Path, typer.Option("--out", help="Rendered pairs: OUT/<texture>/<view>/{0,1}.png and "
                                                    "H_1_from_0.txt.")] = Path("out") / "bench-tilt",
    textures: Annotated[str, typer.Option("--textures", help="Comma-separated textures pasted on the plane: "
                                                             "procedural:SEED or image files.")]
        = "procedural:0,procedural:1",
    angles: Annotated[str, typer.Option("--angles", help="Comma-separated viewing angles of the oblique view, "
                                                         "degrees from the plane's normal (tilt = 1/cos).")]
        = "45,60,70,75,80",
    azimuths: Annotated[str, typer.Option("--azimuths", help="Comma-separated in-plane directions of the "
                                                             "oblique camera, degrees.")] = "0,45",
    roll: Annotated[float, typer.Option("--roll", help="Rotation of the oblique camera about its axis, "
                                                       "degrees.")] = 20.0,
    zooms: Annotated[str, typer.Option("--zooms", help="Comma-separated focal lengths of the oblique camera over "
                                                       "the frontal one's (0.5 = half the detail).")] = "1",
    gain: Annotated[float, typer.Option("--gain", help="Exposure of the oblique photo (intensity factor).")] = 1.0,
    gamma: Annotated[float, typer.Option("--gamma", help="Tone curve of the oblique photo (255 (I/255)^gamma).")]
        = 1.0,
    noise: Annotated[float, typer.Option("--noise", help="Gaussian noise on the oblique photo, grey levels.")] = 0.0,
    jpeg: Annotated[int, typer.Option("--jpeg", help="JPEG quality of the oblique photo (0 = lossless).")] = 0,
    methods: Annotated[Optional[str], typer.Option(
        "--methods", help="Comma-separated methods.")] = "extra-affine,asift,sift",
    json_out: Annotated[Optional[Path], typer.Option("--json", callback=json_file,
                                                     help="Write the rows to this JSON file.")] = None,
    progress: Annotated[bool, progress_option()] = True,
    seed: Annotated[int, seed_option()] = 0,
    baseline_ransac_px: Annotated[float, typer.Option("--baseline-ransac-px", help=BASELINE_RANSAC_HELP)] = 5.0,
) -> None:
    """Rendered frontal/oblique pairs of a textured plane with exact homographies: solved pairs per viewing angle."""
    import sys

    from rich.console import Console

    from recon.core.outdir import claim_output
    from recon.errors import UserError
    from recon.eval.bench_pairs import print_report
    from recon.eval.bench_tilt import parse_floats, parse_textures, run_tilt_bench, tilt_table, tilt_views
    from scenes.tilt import Photometry

    names = parse_methods(methods)
    specs = parse_textures(textures)
    if not math.isfinite(roll):
        raise UserError(f"--roll must be a finite number of degrees, got {roll}")
    views = tilt_views(parse_floats(angles, "--angles", 0.0, 89.0), parse_floats(azimuths, "--azimuths", -360.0, 360.0),
                       roll, parse_floats(zooms, "--zooms", 0.05, 20.0))
    try:
        photometry = Photometry(gain, gamma, noise, jpeg)
    except ValueError:
        raise UserError(f"--gain {gain} / --gamma {gamma} must be positive, --noise {noise} >= 0, "
                        f"--jpeg {jpeg} in 0..100") from None
    matchers = build_matchers(names, seed, baseline_ransac_px)
    err = Console(stderr=True, highlight=False)
    with claim_output(out, "bench") as out:
        rows = run_tilt_bench(out, specs, views, names, matchers, json_path=json_out, progress=progress,
                              log=lambda m: err.print(f"recon: {m}", markup=False),
                              photometry=None if photometry == Photometry() else photometry)
    console = Console(width=None if sys.stdout.isatty() else 160)
    print_report(rows, console=console)
    console.print(tilt_table(rows))
    if json_out is not None:
        typer.echo(f"wrote {len(rows)} rows to {json_out}")


def build_posed_matchers(names: list[str], seed: int, variant: str) -> dict:
    """One PairMatcher per method name for 3D pairs: no final homography anywhere (the posed
    benchmark's common essential-matrix filter replaces it); extra-affine from its `variant`."""
    from matching.registry import get_matcher
    from recon.errors import UserError

    try:
        return {m: get_matcher(m, seed=seed, final_homography=False, **({"variant": variant} if m == "extra-affine" else {}))
                for m in names}
    except ValueError as e:
        raise UserError(str(e)) from None


@bench_app.command("posed")
def posed_cmd(
    root: Annotated[Path, typer.Argument(help="A scene folder with GT cameras in gt/ (Strecha .camera files or "
                                              "a COLMAP text model), or a folder of such scenes.", metavar="ROOT")],
    scenes: Annotated[Optional[str], typer.Option("--scenes", help="Comma-separated scene names (default: every "
                                                                   "scene with GT cameras).")] = None,
    methods: Annotated[Optional[str], typer.Option("--methods", help="Comma-separated methods.")]
        = "extra-affine,asift,sift",
    per_bin: Annotated[int, typer.Option("--per-bin", min=0, help="Pairs per 15° bin of the angle between the "
                                                                  "cameras, per scene (0 = all).")] = 3,
    max_angle: Annotated[float, typer.Option("--max-angle", help="Widest angle between the cameras, degrees.")]
        = 120.0,
    max_size: Annotated[int, typer.Option("--max-size", min=64, help="Working resolution (longer side, px).")] = 1024,
    th: Annotated[float, typer.Option("--th", help="Correct: symmetric epipolar distance under the true cameras, "
                                                   "px at the working size.")] = math.sqrt(3.0),
    variant: Annotated[str, typer.Option("--variant", help=f"extra-affine's preset: {', '.join(VARIANTS)} "
                                                            "(its final homography off in every case).")]
        = "default",
    json_out: Annotated[Optional[Path], typer.Option("--json", callback=json_file,
                                                     help="Write the rows to this JSON file.")] = None,
    progress: Annotated[bool, progress_option()] = True,
    seed: Annotated[int, seed_option()] = 0,
) -> None:
    """Real wide-baseline pairs with GT cameras: pose error, correct matches and time per angle between the cameras."""
    import sys

    from rich.console import Console

    from recon.errors import UserError
    from recon.eval.bench_posed import discover_posed_pairs, posed_tables, run_posed_bench

    names = parse_methods(methods)
    if not th > 0 or not math.isfinite(th):
        raise UserError(f"--th must be a positive number of pixels, got {th}")
    if not 0 < max_angle <= 180:
        raise UserError(f"--max-angle must be in (0, 180] degrees, got {max_angle}")
    root = root.expanduser()
    if not root.is_dir():
        raise UserError(f"{root}: no such folder")
    wanted = [s.strip() for s in scenes.split(",") if s.strip()] if scenes else None
    pairs = discover_posed_pairs(root, wanted, per_bin, max_angle)
    if not pairs:
        raise UserError(f"{root}: no scene with GT cameras (gt/cameras/*.camera or gt/cameras.txt + images.txt) "
                        "and covisible pairs" + (f" among {', '.join(wanted)}" if wanted else ""))
    from recon.log import quiet_colmap

    matchers = build_posed_matchers(names, seed, variant)
    with quiet_colmap():  # the multiview preset's covariant SIFT would log each extraction
        rows = run_posed_bench(pairs, names, matchers, max_size=max_size, th=th, seed=seed, json_path=json_out,
                               progress=progress)
    console = Console(width=None if sys.stdout.isatty() else 200)
    for table in posed_tables(rows):
        console.print(table)
    if json_out is not None:
        typer.echo(f"wrote {len(rows)} rows to {json_out}")


@bench_app.command("scenes")
def scenes_cmd(
    root: Annotated[Path, typer.Argument(help="Folder of scene folders (photos in <scene>/images/ or at its "
                                              "top level, optional ground truth in <scene>/gt/).", metavar="ROOT")],
    stock_presets_: Annotated[str, stock_presets_option()] = "default",
    json_out: Annotated[Optional[Path], typer.Option("--json", callback=json_file, help="Write every scene's comparison to this "
                                                                   "JSON file.")] = None,
    scenes: Annotated[Optional[str], typer.Option("--scenes", help="Comma-separated scene names (default: all).")]
        = None,
    out: Annotated[Optional[Path], typer.Option("--out", help="Outputs: OUT/<scene>/{stock-*,extra_affine} "
                                                              "(default: out/bench-scenes).")] = None,
    max_size: Annotated[int, typer.Option("--max-size", help="Working resolution (longer side, px; 0 = full).")]
        = DEFAULT_MAX_SIZE,
    pairs: Annotated[str, typer.Option("--pairs", help="Pair selection for both pipelines.")] = "exhaustive",
    simulate: Annotated[str, simulate_option()] = "auto",
    settings: Annotated[Optional[list[str]], set_option()] = None,
    seed: Annotated[int, seed_option()] = 0,
    workers: Annotated[int, workers_option()] = 0,
    progress: Annotated[bool, progress_option()] = True,
) -> None:
    """`recon compare` on every scene under ROOT (stock COLMAP vs extra-affine), one summary table."""
    import sys

    from rich.console import Console

    from recon.core.outdir import claim_output
    from recon.eval.compare import run_scenes, scenes_table

    presets = stock_presets(stock_presets_)
    names = [s.strip() for s in scenes.split(",") if s.strip()] if scenes else None
    root = root.expanduser()
    out_root = out if out is not None else Path("out") / "bench-scenes"
    err = Console(stderr=True, highlight=False)
    if not root.is_dir():  # before the output folder is created
        from recon.errors import UserError

        raise UserError(f"{root}: no such folder")
    with claim_output(out_root, "bench", default_out=out is None, legacy=("*/compare.json",)) as out_root:
        results = run_scenes(root, out_root, names, presets=presets, max_size=max_size, pairs=pairs, seed=seed,
                             workers=workers, progress=progress, json_path=json_out,
                             log=lambda m: err.print(f"recon: {m}", markup=False),
                             settings=our_settings(simulate, settings))
    Console(width=None if sys.stdout.isatty() else 160).print(scenes_table(results, max_size))
    if json_out is not None:
        typer.echo(f"JSON: {json_out}")


@bench_app.command("difficulty")
def difficulty_cmd(
    out: Annotated[Path, typer.Option("--out", help="Rendered scenes, runs, difficulty.json and difficulty.png.")]
        = Path("out") / "bench-difficulty",
    views: Annotated[str, typer.Option("--views", help="Comma-separated numbers of views (>= 3); the step "
                                                       "between neighbours is 2*MAX_AZIMUTH/(N-1).")] = "3,4,5,7,9,13",
    max_azimuth: Annotated[float, typer.Option("--max-azimuth", help="Cameras spread over +-this many degrees "
                                                                     "about the facade normal.")] = 78.0,
    stock_presets_: Annotated[str, stock_presets_option()] = "default,high",
    image_size: Annotated[Optional[str], typer.Option("--image-size", help="Rendered size WxH (default: the "
                                                                           "preset's 800x600).")] = None,
    texture: Annotated[Optional[list[Path]], typer.Option("--texture", help="Photo(s) to texture the facade's "
                                                          "planes with (repeatable; default: procedural).")] = None,
    json_out: Annotated[Optional[Path], typer.Option("--json", callback=json_file,
                                                     help="Also copy the rows to this JSON file.")] = None,
    seed: Annotated[int, seed_option()] = 0,
    workers: Annotated[int, workers_option()] = 0,
    progress: Annotated[bool, progress_option()] = True,
    recompute: Annotated[bool, typer.Option("--recompute", help="Run scenes again whose compare.json already exists.",
                                            metavar="")] = False,
) -> None:
    """Difficulty curve: azimuth step between views vs registered images and rotation error (stock vs ours)."""
    import shutil
    import sys

    from rich.console import Console

    from recon.core.outdir import claim_output
    from recon.errors import UserError
    from recon.eval.difficulty import baseline_table, difficulty_table, plot_difficulty, run_difficulty

    try:
        counts = [int(v) for v in views.split(",") if v.strip()]
    except ValueError:
        raise UserError(f"--views {views!r}: expected numbers of views, e.g. 3,4,5") from None
    size = parse_image_size(image_size)
    presets = stock_presets(stock_presets_)
    check_textures(texture)
    textures = [t.expanduser().resolve() for t in texture or []]
    err = Console(stderr=True, highlight=False)
    with claim_output(out, "bench", legacy=("difficulty.json",)) as out:
        data = run_difficulty(out, counts, max_azimuth, presets, seed=seed, image_size=size,  # type: ignore[arg-type]
                              recompute=recompute, workers=workers, progress=progress, textures=textures or None,
                              log=lambda m: err.print(f"recon: {m}", markup=False))
    console = Console(width=None if sys.stdout.isatty() else 160)
    console.print(difficulty_table(data))
    console.print(baseline_table(data))
    js = Path(out) / "difficulty.json"
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(js, json_out)
    png = plot_difficulty(data, Path(out) / "difficulty.png")
    typer.echo(f"JSON: {json_out or js}")
    typer.echo(f"plot: {png}" if png else "plot: skipped (matplotlib not installed: pip install -e '.[bench]')")


@bench_app.command("scale")
def scale_cmd(
    out: Annotated[Path, typer.Option("--out", help="Rendered scenes, runs, scale.json (and scale.png).")]
        = Path("out") / "bench-scale",
    sizes: Annotated[str, typer.Option("--sizes", help="Comma-separated numbers of views of the rendered walk "
                                                       "around a building (orbit-N, 800x600); none = no rendered "
                                                       "scenes.")] = "25,50,100,200",
    pairs: Annotated[str, typer.Option("--pairs", help="Comma-separated pair selections run on every size: "
                                                       "exhaustive, auto, retrieval:K[+sequential:S].")]
        = "exhaustive,retrieval:10",
    max_exhaustive: Annotated[int, typer.Option("--max-exhaustive", help="Exhaustive runs only up to this many "
                                                                         "images; larger ones are reported as "
                                                                         "skipped.")] = 50,
    engine: Annotated[str, typer.Option("--engine", help="Engine of the size sweep and the real scenes: "
                                                         "threads:W or dask:W.")] = "threads:2",
    engines: Annotated[str, typer.Option("--engines", help="Engines compared on the --engine-size scene "
                                                           "(none = no comparison); /cvT pins OpenCV to T "
                                                           "threads per process, e.g. dask:2/cv1.")]
        = "threads:1,threads:2,dask:1,dask:2",
    engine_size: Annotated[int, typer.Option("--engine-size", help="Views of the scene the engines are compared "
                                                                   "on.")] = 50,
    engine_pairs: Annotated[str, typer.Option("--engine-pairs", help="Pair selection of the engine comparison.")]
        = "retrieval:10",
    real: Annotated[str, typer.Option("--real", help="Comma-separated real scene folders, or names under "
                                                     "$RECON_SHARED_DATA/scenes; missing ones are reported as "
                                                     "skipped; none = no real scenes.")] = "castle_P30,fox",
    real_pairs: Annotated[str, typer.Option("--real-pairs", help="Pair selection of the real scenes.")] = "auto",
    max_size: Annotated[int, typer.Option("--max-size", help="Working resolution (longer side, px; 0 = full).")]
        = DEFAULT_MAX_SIZE,
    image_size: Annotated[str, typer.Option("--image-size", help="Rendered size WxH.")] = "800x600",
    json_out: Annotated[Optional[Path], typer.Option("--json", callback=json_file,
                                                     help="Also copy scale.json to this file.")] = None,
    plot: Annotated[Optional[Path], typer.Option("--plot", help="Log-log plot of total time against N "
                                                                "(default: OUT/scale.png).")] = None,
    seed: Annotated[int, seed_option()] = 0,
    recompute: Annotated[bool, typer.Option("--recompute", help="Run again the runs whose results are already in "
                                                                "OUT.", metavar="")] = False,
    collect: Annotated[bool, typer.Option("--collect", help="Run nothing: gather the finished runs in OUT into the "
                                                            "table, JSON and plot (others are listed as not run).",
                                          metavar="")] = False,
) -> None:
    """Time per stage, peak memory and registration against the number of photos (issue 10)."""
    import shutil
    import sys

    from rich.console import Console

    from recon.core.outdir import claim_output
    from recon.errors import UserError
    from recon.eval.bench_scale import (
        parse_engines,
        parse_pairs_modes,
        parse_sizes,
        plot_scale,
        resolve_real,
        run_scale,
        scale_table,
        targets_lines,
    )

    size_list = parse_sizes(sizes)
    modes = parse_pairs_modes(pairs)
    main_engine = parse_engines(engine, "--engine")
    if len(main_engine) != 1:
        raise UserError(f"--engine {engine!r}: give one engine, threads:W or dask:W")
    engine_list = parse_engines(engines)
    eng_pairs = parse_pairs_modes(engine_pairs, "--engine-pairs")
    r_pairs = parse_pairs_modes(real_pairs, "--real-pairs")
    if len(eng_pairs) != 1 or len(r_pairs) != 1:
        raise UserError("--engine-pairs and --real-pairs take one pair selection each")
    if max_exhaustive < 0:
        raise UserError(f"--max-exhaustive must be >= 0, got {max_exhaustive}")
    if engine_list and engine_size:
        parse_sizes(str(engine_size))
    if engine_size < 0:
        raise UserError(f"--engine-size must be >= 0 (0 = no engine comparison), got {engine_size}")
    if max_size < 0:
        raise UserError(f"--max-size must be >= 0, got {max_size}")
    size = parse_image_size(image_size)
    real_list = resolve_real(real)
    if not size_list and not real_list and not (engine_list and engine_size):
        raise UserError("nothing to run: give --sizes, --real or --engines with --engine-size")
    err = Console(stderr=True, highlight=False)
    with claim_output(out, "bench", legacy=("scale.json",)) as out:
        result = run_scale(out, size_list, modes, main_engine[0], engine_size, eng_pairs[0], engine_list, real_list,
                           r_pairs[0], max_exhaustive, seed=seed, max_size=max_size, recompute=recompute,
                           log=lambda m: err.print(f"recon: {m}", markup=False), image_size=size,  # type: ignore[arg-type]
                           collect=collect)
    console = Console(width=None if sys.stdout.isatty() else 200, highlight=False)
    console.print(scale_table(result))
    for line in targets_lines(result):
        console.print(line, markup=False)
    js = Path(out) / "scale.json"
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(js, json_out)
    png = plot_scale(result, plot or Path(out) / "scale.png")
    typer.echo(f"JSON: {json_out or js}")
    typer.echo(f"plot: {png}" if png else "plot: skipped (matplotlib not installed: pip install -e '.[bench]')")


def register(app: typer.Typer) -> None:
    """Add the `bench` sub-app to the recon CLI (idempotent: `main()` may register twice)."""
    if any(g.typer_instance is bench_app for g in app.registered_groups):
        return
    app.add_typer(bench_app, name="bench")
