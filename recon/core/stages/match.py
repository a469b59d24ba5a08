"""Stage `match`: every pair matched by an independent task, resumed pair by pair.

Needs: `scene`, `store`, `pairs`. Makes: `results` (one PairResult per pair, full-resolution
pixels, pair order) and `cached`. Each pair is the pure task `match_pair_task(store, matcher,
name0, name1) -> PairResult`, submitted to `run.executor` (`recon.core.engine`: a thread pool by
default; OpenCV releases the GIL). Each finished pair is converted to full-resolution pixels
and written atomically to `OUT/cache/pairs/<key>.npz` (`recon.core.paircache`; the key hashes
the matcher's identity, both images' pixel digests and working sizes), so an interrupted run
recomputes only the missing pairs: that per-pair key is this stage's cache, so the stage itself
has none and always runs. Results are collected in pair order, never completion order, so a
fixed seed gives the same output whatever the scheduling. One failing pair is a warning and an
empty result, never the end of the run.

With `--simulate needed` (`match.simulate`; `auto`, the default, is `needed` above
`match.adaptive_above` images, `simulate_mode`) the pairs run in two passes: every pair's
originals first (`first_pass_overrides`: nothing simulated), then the default matcher on the
weak pairs the strong-pair graph needs (`recon.core.schedule`; a pair needed only as a bridge
between parts of that graph with the first pass's originals, `bridge_overrides`); each pass has
its own matcher identity and so its own pair cache entries, and a weak pair left out keeps its
first-pass matches, or none below `verify.min_num_inliers` (`PairResult.without_matches`).

With `--pairs retrieval:K+expand:E` the stage then runs match-graph expansion rounds
(`recon.core.expansion`): each round appends the pairs the matched ones say overlap to
`pairs` (after the proposed ones, in a fixed order) and matches them the same way, so a resumed
run finds the same rounds in the pair cache. `report.pairs_expanded` holds the new pairs of
each round.

Options: `match.method` and `match.matcher` (the matcher's own options, see `make_matcher`),
`match.engine`, `workers`, `seed`, and the `+expand:E` term of `pairs.spec`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from concurrent.futures import FIRST_COMPLETED, Future, wait
from pathlib import Path
from typing import Any, cast

from matching.colmap_sift import extraction_processes
from matching.registry import PairMatcher, get_matcher
from matching.store import FeatureStore
from matching.types import PairResult
from recon.config import MatchConfig
from recon.core.context import Run
from recon.core.expansion import ExpansionConfig, expand
from recon.core.paircache import load_pair_result, pair_cache_key, result_to_full_res, save_pair_result
from recon.errors import UserError

log = logging.getLogger(__name__)


def match_pair_task(store: FeatureStore, matcher: PairMatcher, name0: str, name1: str) -> PairResult:
    """One pair: a pure function of the per-image store and the matcher (no pipeline state)."""
    return matcher.match(store, name0, name1)


def matcher_overrides(cfg: MatchConfig | str, seed: int = 0, inner_workers: int = 1,
                      num_images: int | None = None) -> dict[str, Any]:
    """The registry overrides of the multi-view matcher: no final homography filter (COLMAP
    verifies), the extra-affine matcher's `multiview` variant, seeded, single-threaded inside when
    pairs already run in parallel (`inner_workers`), then the user's `cfg.matcher` options on top
    (`section.field` keys become the registry's `section__field`; deeper ones replace the nested
    dataclass). The extra-affine matcher's adaptive per-pair paths are switched on for scenes of
    more than `cfg.adaptive_above` images (`num_images`) unless the user set `matcher.adaptive`.
    Plain picklable data: Dask workers rebuild the same matcher from it. A plain method name
    means `MatchConfig(method=name)`."""
    cfg = MatchConfig(method=cfg) if isinstance(cfg, str) else cfg
    try:
        probe = get_matcher(cfg.method)
    except (ValueError, ImportError) as e:
        raise UserError(f"--method {cfg.method}: {e}") from None
    base_cfg = getattr(probe, "cfg", None)
    known = {f.name for f in dataclasses.fields(base_cfg)} if dataclasses.is_dataclass(base_cfg) else set()
    wanted = {"final_homography": False, "seed": int(seed), "workers": int(inner_workers)}
    overrides: dict[str, Any] = {k: v for k, v in wanted.items() if k in known}
    if cfg.method == "extra-affine":
        overrides["variant"] = "multiview"
        if uses_adaptive_paths(cfg, num_images):
            overrides["adaptive"] = True
    if cfg.matcher:
        try:
            base = getattr(get_matcher(cfg.method, **overrides), "cfg", None)
        except (TypeError, ValueError) as e:
            raise UserError(f"matcher options {cfg.matcher}: {e}") from None
        for key, value in cfg.matcher.items():
            section, _, rest = key.partition(".")
            if not rest:
                overrides[key] = value
            elif "." not in rest:
                overrides[f"{section}__{rest}"] = value
            else:  # deeper: replace the nested dataclass of the section (e.g. escalation.two_sided_grid.a)
                name, _, leaf = rest.partition(".")
                current = overrides.get(f"{section}__{name}", getattr(getattr(base, section), name))
                overrides[f"{section}__{name}"] = _replace_path(current, leaf, value)
    return overrides


def is_large_capture(cfg: MatchConfig, num_images: int | None) -> bool:
    """More than `cfg.adaptive_above` images (0 = never): the size at which the adaptive paths
    and `--simulate auto`'s `needed` switch on."""
    return cfg.adaptive_above > 0 and num_images is not None and num_images > cfg.adaptive_above


def uses_adaptive_paths(cfg: MatchConfig, num_images: int | None) -> bool:
    """Whether the scene's size alone switches the adaptive paths on: a large capture
    (`is_large_capture`) and no explicit `matcher.adaptive`."""
    return cfg.method == "extra-affine" and "adaptive" not in cfg.matcher and is_large_capture(cfg, num_images)


def simulate_mode(cfg: MatchConfig, num_images: int | None) -> str:
    """`match.simulate` resolved for a scene of `num_images` images: "needed" or "all". `auto`
    is "needed" for the extra-affine matcher on a large capture (`is_large_capture`: mostly easy
    neighbouring pairs) and "all" otherwise. Other methods simulate nothing, so "needed" is only
    kept for the extra-affine matcher."""
    if cfg.method != "extra-affine":
        return "all"
    if cfg.simulate == "auto":
        return "needed" if is_large_capture(cfg, num_images) else "all"
    return cfg.simulate


def make_matcher(cfg: MatchConfig | str, seed: int = 0, inner_workers: int = 1,
                 num_images: int | None = None, extra: dict[str, Any] | None = None) -> PairMatcher:
    """The registry's matcher for multi-view use, built from `matcher_overrides` (see there) and
    `extra` overrides on top (e.g. `first_pass_overrides`)."""
    cfg = MatchConfig(method=cfg) if isinstance(cfg, str) else cfg
    overrides = {**matcher_overrides(cfg, seed, inner_workers, num_images), **(extra or {})}
    try:
        return get_matcher(cfg.method, **overrides)
    except (TypeError, ValueError) as e:
        raise UserError(f"matcher options {cfg.matcher}: {e}") from None


def first_pass_overrides(cfg: MatchConfig) -> dict[str, Any]:
    """The extra-affine matcher of `simulate = "needed"`'s first pass: the originals only
    (`simulate=False`), matched with OpenCV's SIFT at `cfg.first_pass_contrast` (about the
    keypoints of COLMAP's default extraction, for a sixth of its time at 1600 px), whatever the
    original detector of the second pass; no adaptive paths (nothing is simulated) and no
    epipolar-guided round: a strong pair's originals already give hundreds to thousands of
    matches, and the round took a third of the pass (on fountain_P11 without it: 15673 instead
    of 17647 points, reprojection error 0.396 instead of 0.442 px, rotation error 0.233° instead
    of 0.234°, total time 48 instead of 66-72 s; docs/decisions.md). With OpenCV's SIFT on the
    originals the (unused) views' detector gets their contrast, so each original is detected once
    (the database stage's descriptors take the same set: `descriptor_detector`)."""
    same_set = {"fine__sift_contrast": float(cfg.first_pass_contrast)} if cfg.first_pass_detector == "sift" else {}
    return {"simulate": False, "adaptive": False, "guided_epipolar": False, **_first_pass_originals(cfg), **same_set}


def bridge_overrides(cfg: MatchConfig) -> dict[str, Any]:
    """The second pass's matcher for the pairs simulated only as bridges between parts of the
    strong pair graph, on top of the default one: with `simulate_bridges = "cheap"` the first
    pass's detector on the originals (`first_pass_detector`, OpenCV's SIFT by default) instead of
    COLMAP's covariant SIFT, and no epipolar round (with the cheap originals' fewer matches its F
    can be wrong, and the round then adds matches along the wrong lines that COLMAP's
    verification keeps); the views and the escalation stay. Nothing with "full"
    (`MatchConfig.simulate_bridges`)."""
    if cfg.simulate_bridges == "full":
        return {}
    return {"guided_epipolar": False, **_first_pass_originals(cfg)}


def _first_pass_originals(cfg: MatchConfig) -> dict[str, Any]:
    """The first pass's detector of the originals, as matcher overrides (shared with cheap bridges)."""
    return {"fine__original_detector": cfg.first_pass_detector, "fine__original_contrast": float(cfg.first_pass_contrast),
            "fine__original_cross_check": bool(cfg.first_pass_cross_check)}


def _replace_path(obj: Any, path: str, value: Any) -> Any:
    head, _, rest = path.partition(".")
    return dataclasses.replace(obj, **{head: _replace_path(getattr(obj, head), rest, value) if rest else value})


def matcher_identity(matcher: PairMatcher) -> str:
    """A stable text naming the matcher and the config fields that change its output (part of
    the pair cache key; thread counts are left out)."""
    cfg = getattr(matcher, "cfg", None) or getattr(matcher, "config", None)
    kind = f"{type(matcher).__module__}.{type(matcher).__qualname__}"
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        if "workers" in {f.name for f in dataclasses.fields(cfg)}:
            cfg = dataclasses.replace(cfg, workers=0)
        return f"{kind}:{cfg!r}"
    return f"{kind}:{getattr(matcher, 'name', '')}"


class Match:
    name = "match"
    needs = ("scene", "store", "pairs")
    makes = ("results", "cached")

    def key(self, run: Run) -> str | None:
        return None  # resumed pair by pair (see module doc)

    def reuse(self, run: Run, record: dict[str, Any]) -> bool:
        return False

    def run(self, run: Run) -> None:
        cfg, pairs, store = run.cfg, run.data.pairs, run.data.store
        matcher = run.matcher or make_matcher(cfg.match, cfg.seed,
                                              inner_workers=1 if len(pairs) >= cfg.num_workers else 0,
                                              num_images=len(run.data.scene.images))
        log.debug("matcher: %s", matcher_identity(matcher))
        results, cached = self._match_pairs(run, matcher, run.cache / "pairs")
        run.data.results, run.data.cached = results, cached
        self._expand(run, matcher)
        pairs, cached = run.data.pairs, run.data.cached
        report = run.report
        report.pairs_cached = int(sum(cached))
        report.pairs_simulated = int(sum(1 for r in run.data.results if r.path in ("targeted", "full")))
        if cfg.match.method == "extra-affine":
            report.simulate_used = simulate_mode(cfg.match, len(run.data.scene.images))
        report.pairs_computed = len(pairs) - report.pairs_cached
        report.features_computed, report.features_reused = int(store.misses), int(store.hits)
        if store.persist_error is not None:
            run.warn(f"the feature cache could not be written ({store.persist_error}); features were kept in memory")
        return None

    @staticmethod
    def _expand(run: Run, matcher: PairMatcher) -> None:
        """Match-graph expansion rounds for a `+expand:E` pairs spec (see module doc)."""
        from recon.core.pairs import parse_pairs_spec

        spec = parse_pairs_spec(run.cfg.pairs.spec)
        if spec.kind != "retrieval" or spec.expand < 1:
            return
        ecfg = ExpansionConfig(per_image=spec.expand)

        def match_round(new: list[tuple[str, str]]) -> list[int]:
            first = len(run.data.pairs)
            run.data.pairs = run.data.pairs + new
            results, cached = Match._match_pairs(run, matcher, run.cache / "pairs", first)
            run.data.results = run.data.results + results
            run.data.cached = run.data.cached + cached
            counts = [r.num_matches for r in results]
            run.report.pairs_expanded.append(len(new))
            log.info("expansion round %d: %d new pairs, %d with >= %d matches", len(run.report.pairs_expanded),
                     len(new), sum(1 for n in counts if n >= ecfg.min_matches), ecfg.min_matches)
            return counts

        matched = {p: r.num_matches for p, r in zip(run.data.pairs, run.data.results)}
        expand(run.data.scene.names, matched, match_round, ecfg)

    @staticmethod
    def _submit(run: Run, matcher: PairMatcher, todo: list[int],
                extra: dict[str, Any] | None = None) -> dict[Future, int]:
        """Submit the pairs `todo` to the run's executor: `match_pair_task` over the shared store in
        threads, or `match_pair_on_worker` (a picklable spec: image paths, working size, matcher
        name and options, seed, the shared feature cache) on Dask workers, which rebuild the same
        matcher (its identity, and so the pair cache key, is the same as the driver's)."""
        pairs, ex = run.data.pairs, run.executor
        if not getattr(ex, "distributed", False):
            return {ex.submit(match_pair_task, run.data.store, matcher, *pairs[i]): i for i in todo}
        from recon.core.dask_engine import match_pair_on_worker, pair_task_specs

        cfg = run.cfg
        overrides = tuple(sorted({**matcher_overrides(cfg.match, cfg.seed, inner_workers=1,
                                                      num_images=len(run.data.scene.images)),
                                  **(extra or {})}.items()))
        specs = pair_task_specs(run.data.scene, [pairs[i] for i in todo], cfg.match.method, cfg.seed,
                                cfg.load.max_size or None, run.cache / "features", overrides)
        return {ex.submit(match_pair_on_worker, spec): i for spec, i in zip(specs, todo)}

    @staticmethod
    def _match_pairs(run: Run, matcher: PairMatcher, pair_dir: Path, first: int = 0
                     ) -> tuple[list[PairResult], list[bool]]:
        """The pairs `run.data.pairs[first:]` under `match.simulate` (one pass for "all", two for
        "needed", `_match_needed`); their results and cache flags in pair order."""
        if simulate_mode(run.cfg.match, len(run.data.scene.images)) == "needed":
            return Match._match_needed(run, matcher, pair_dir, first)
        return Match._match_all(run, matcher, pair_dir, first)

    @staticmethod
    def _match_needed(run: Run, matcher: PairMatcher, pair_dir: Path, first: int
                      ) -> tuple[list[PairResult], list[bool]]:
        """`simulate = "needed"`: every pair's originals first (`first_pass_overrides`), then
        `matcher` (the full one) on the weak pairs the scene needs (`recon.core.schedule`); the
        others keep their first-pass result, with the decision appended to its `path_reason`."""
        from recon.core.schedule import ScheduleConfig, pairs_to_simulate

        cfg = run.cfg.match

        def matcher_with(extra: dict[str, Any], num_pairs: int) -> PairMatcher:
            # threads inside the matcher only when there are fewer pairs than pair threads (as `run`)
            return make_matcher(cfg, run.cfg.seed, inner_workers=1 if num_pairs >= run.cfg.num_workers else 0,
                                num_images=len(run.data.scene.images), extra=extra)

        n = len(run.data.pairs)
        extra = first_pass_overrides(cfg)
        cheap = matcher_with(extra, n - first)
        done = Match._match_indices(run, cheap, pair_dir, list(range(first, n)), extra, emit=False, part="originals")
        results = {i: r for i, (r, _) in done.items()}
        cached = {i: c for i, (_, c) in done.items()}
        earlier = list(run.data.results[:first]) if first else []  # expansion: the earlier rounds count too
        every = earlier + [results[i] for i in range(first, n)]
        verified = [r.verified if r.verified >= 0 else r.num_matches for r in every]
        choices = pairs_to_simulate(run.data.scene.names, run.data.pairs, verified,
                                    ScheduleConfig(cfg.simulate_strong_inliers, cfg.simulate_min_partners), first)
        todo = [c.index for c in choices if c.simulate]
        log.info("simulate=needed: %d of %d pairs solved by their originals (>= %d matches), %d weak pairs "
                 "simulated, %d left", n - first - len(choices), n - first, cfg.simulate_strong_inliers, len(todo),
                 len(choices) - len(todo))
        bridge_extra = bridge_overrides(cfg)
        bridges = {c.index for c in choices if c.simulate and c.bridge} if bridge_extra else set()
        floor = run.cfg.verify.min_num_inliers
        for c in choices:
            r = results[c.index]
            why = f"{c.reason} with the first pass's originals (bridge)" if c.index in bridges else c.reason
            r.path_reason = f"{r.path_reason}; {why}" if r.path_reason else why
            if not c.simulate and 0 <= r.verified < floor:
                # nearly all wrong ratio matches: COLMAP's RANSAC would spend up to 20000 trials per
                # model rejecting each such pair (86 of castle_P30's 232 s, docs/decisions.md)
                results[c.index] = r.without_matches(f"first pass verified {r.verified} matches (< verify.min_num_inliers "
                                                      f"{floor}) and the pair is not simulated: left unmatched")
        simulate = set(todo)
        for i in range(first, n):
            if i not in simulate:
                run.observer.on_pair(i, *run.data.pairs[i], results[i], cached[i])
        groups: list[tuple[PairMatcher, dict[str, Any] | None, list[int], str]] = [
            (matcher, None, [i for i in todo if i not in bridges], "simulated views")]
        if bridges:
            groups.append((matcher_with(bridge_extra, len(bridges)), bridge_extra, sorted(bridges),
                           "bridges (simulated views)"))
        for group_matcher, group_extra, indices, part in groups:
            if not indices:
                continue
            simulated = Match._match_indices(run, group_matcher, pair_dir, indices, group_extra, emit=True, part=part)
            for i, (r, from_cache) in simulated.items():
                r.path_reason = f"{results[i].path_reason}; {r.path_reason}" if r.path_reason else results[i].path_reason
                results[i], cached[i] = r, from_cache and cached[i]
        return [results[i] for i in range(first, n)], [cached[i] for i in range(first, n)]

    @staticmethod
    def _match_all(run: Run, matcher: PairMatcher, pair_dir: Path, first: int = 0
                   ) -> tuple[list[PairResult], list[bool]]:
        """The pairs `run.data.pairs[first:]`, from the cache or computed on the executor; their
        results and cache flags in pair order (indices in events and tasks are the global ones)."""
        n = len(run.data.pairs)
        done = Match._match_indices(run, matcher, pair_dir, list(range(first, n)), None, emit=True)
        return [done[i][0] for i in range(first, n)], [done[i][1] for i in range(first, n)]

    @staticmethod
    def _match_indices(run: Run, matcher: PairMatcher, pair_dir: Path, indices: list[int],
                       extra: dict[str, Any] | None, emit: bool, part: str = "") -> dict[int, tuple[PairResult, bool]]:
        """The pairs `run.data.pairs[i]` for `i` in `indices`, from the cache or computed on the
        executor: {index: (result, cached)}. `extra` = the matcher's overrides beyond
        `matcher_overrides` (for Dask workers); `emit` = report each pair to the observers;
        `part` names the progress bar's part of the stage."""
        pairs = run.data.pairs
        advance = run.bar(len(indices), part)
        images = {im.name: im for im in run.data.scene.images}
        mid = matcher_identity(matcher)
        results: list[PairResult | None] = [None] * len(pairs)
        cached = [False] * len(pairs)
        paths: list[Path | None] = [None] * len(pairs)
        todo: list[int] = []
        for i in indices:
            a, b = pairs[i]
            paths[i] = pair_dir / f"{pair_cache_key(mid, images[a], images[b])}.npz"
            r = load_pair_result(paths[i])  # type: ignore[arg-type]
            if r is None:
                todo.append(i)
                continue
            results[i], cached[i] = r, True
            advance()
            if emit:
                run.observer.on_pair(i, a, b, r, True)
        if todo:
            pair_dir.mkdir(parents=True, exist_ok=True)
            with contextlib.ExitStack() as stack:
                if not getattr(run.executor, "distributed", False):
                    # pair threads: COLMAP's covariant SIFT in child processes (it holds the GIL)
                    stack.enter_context(extraction_processes(min(run.cfg.num_workers, len(todo))))
                Match._collect(run, Match._submit(run, matcher, todo, extra), paths, results, advance, images,
                               matcher, emit)
        return {i: (cast(PairResult, results[i]), cached[i]) for i in indices}  # every index is filled above

    @staticmethod
    def _collect(run: Run, futures: dict[Future, int], paths: list[Path | None], results: list[PairResult | None],
                 advance: Any, images: dict[str, Any], matcher: PairMatcher, emit: bool = True) -> None:
        """Wait for the submitted pairs; write each to the pair cache as it finishes and store what
        a resumed run would load in `results` (pair order); one failing pair is a warning."""
        pairs = run.data.pairs
        pending = set(futures)
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in sorted(done, key=lambda f: futures[f]):
                    i = futures[f]
                    a, b = pairs[i]
                    try:
                        raw = f.result()
                    except Exception as e:  # one bad pair must not end the run
                        run.warn(f"matching {a} / {b} failed: {type(e).__name__}: {e}")
                        results[i] = PairResult.empty(getattr(matcher, "name", "?"),
                                                      f"matcher error: {type(e).__name__}: {e}")
                        advance()
                        if emit:
                            run.observer.on_pair(i, a, b, results[i], False)  # type: ignore[arg-type]
                        continue
                    full = result_to_full_res(raw, images[a], images[b])
                    path = cast(Path, paths[i])
                    save_pair_result(path, full)
                    # use exactly what a resumed run would load, so both give identical output
                    r = results[i] = load_pair_result(path) or full
                    advance()
                    log.debug("pair %d %s / %s: %d matches in %.2f s%s", i, a, b, r.num_matches,
                              r.timings.get("total", 0.0), f" ({r.reason})" if r.reason else "")
                    if emit:
                        run.observer.on_pair(i, a, b, r, False)
        except BaseException:  # Ctrl-C, a failing cache write: drop the tasks not started yet
            for f in pending:
                f.cancel()
            raise
