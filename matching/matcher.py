"""ExtraAffineMatcher: reference choice -> coarse ORB search -> fine SIFT stage -> escalation.

The fast path is the paper's: one reference, one simulated grid, one fine view. A pair whose
fast path ends with fewer than `min_inliers` verified matches escalates, cheapest first (see
`matching.escalation`), so easy pairs keep the paper's speed and hard pairs still get solved.
"""

from __future__ import annotations

import math
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, fields, replace
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from .coarse import CoarseConfig, coarse_search, original_features, rank_views, view_features
from .escalation import Attempt, EscalationConfig, escalate
from .fine import (FineConfig, FineMatches, epipolar_guided_match, epipolar_pair_distance, fine_match, guided_match,
                   select_fine_views)
from .matching_utils import ransac_homography, unique_train
from .metrics import local_scale
from .reference import ReferenceConfig, ReferenceDecision, choose_reference
from .store import FeatureStore
from .types import CoarseScore, PairResult
from .verify import verify_matches
from .views import GridConfig, capped_view, view_grid


@dataclass(frozen=True)
class MatcherConfig:
    """Everything the extra-affine matcher does, with the paper's choices where they measure best.

    `final_homography`: fit a RANSAC homography to the final matches and flag inliers (planar
    pairs, benchmarks); the multi-view pipeline turns it off and leaves verification to COLMAP.
    `verify`: the model that counts verified inliers for the escalation decision ("auto" =
    homography when `final_homography`, else fundamental matrix).
    `fine_include_original`: also fine-match the unwarped originals (multi-view: shared
    keypoints across pairs, matches on every surface, not only the one the best view rectifies).
    `final_ransac_px`: 1.5 px keeps precision above 96 % on graf; 3 px (OpenCV's default)
    admits SIFT localisation errors of 2-3 px that the sqrt(3) px precision test rejects.
    `guided`: after the homography, re-match the fine views' keypoints only against target
    keypoints within `guided_px` of their predicted position (more matches at equal precision).
    `guided_epipolar` (multi-view, where no homography is fitted): fit a fundamental matrix
    (RANSAC, `guided_epipolar_px`) to the matches and re-match the fine views' keypoints only
    against target keypoints within `guided_epipolar_px` of their epipolar line
    (`fine.epipolar_guided_match`, ratio `guided_epipolar_ratio`), keeping the F-consistent
    union with the first round. Measured with `recon compare` on the rendered facades
    (800x600; verified inliers per verified pair / median GT relative rotation error / AUC@5):
    facade-wide without it 360 / 0.10° / 0.981, with 1 px and ratio 0.7 449 / 0.11° / 0.977,
    0.8: 575 / 0.13° / 0.973, 2 px and 0.8: 628 / 0.28° / 0.940; facade-extreme without it
    236 / 0.12° / 0.977, 1 px and 0.7: 347 / 0.14° / 0.971, 0.8: 472 / 0.20° / 0.963. A wider
    band or looser ratio lets in matches that lie near the line but are wrong (and a nearly
    planar scene makes F itself shaky off the plane), so 1 px and 0.7 keep the accuracy within
    0.02° while adding 25-50 % inliers and 30-90 % points. The round runs only on pairs whose
    first-round F is trustworthy (`guided_epipolar_min_inliers`, `guided_epipolar_min_ratio`,
    see `_guided_epipolar`).
    `fine_top_k`: how many of the best coarse views the fine stage fuses (paper: 1). Two
    views gave 12-38 % more correct matches on graf 1-2..1-6 at equal precision.
    `min_result_inliers`: a final result with fewer verified matches than this is returned
    empty, with the reason (random matches between unrelated images reach ~4-8).
    `workers`: threads for independent views (0 = all cores, 1 = none, for callers that already
    run pairs in parallel).
    """

    grid: GridConfig = field(default_factory=GridConfig)
    reference: ReferenceConfig = field(default_factory=ReferenceConfig)
    coarse: CoarseConfig = field(default_factory=CoarseConfig)
    fine: FineConfig = field(default_factory=FineConfig)
    escalation: EscalationConfig = field(default_factory=EscalationConfig)
    fine_top_k: int = 2
    fine_include_original: bool = False
    final_homography: bool = True
    final_ransac_px: float = 1.5
    guided: bool = True
    guided_px: float = 4.0
    guided_ratio: float = 0.8
    guided_epipolar: bool = False
    guided_epipolar_px: float = 1.0
    guided_epipolar_ratio: float = 0.7
    guided_epipolar_min_inliers: int = 50
    guided_epipolar_min_ratio: float = 0.35
    verify: Literal["auto", "homography", "fundamental"] = "auto"
    min_result_inliers: int = 10
    workers: int = 0
    seed: int = 0

    @staticmethod
    def paper() -> "MatcherConfig":
        """A plain reading of the paper: Eq. 1 reference, most-matches ranking, no blur, no escalation."""
        return MatcherConfig(reference=ReferenceConfig(mode="paper"), guided=False, final_ransac_px=3.0,
                             coarse=CoarseConfig(rank_by="matches", max_area_ratio=0.0, max_side=0),
                             fine=FineConfig(antialias=False, max_area_ratio=0.0), fine_top_k=1,
                             escalation=EscalationConfig(enabled=False))

    @staticmethod
    def multiview() -> "MatcherConfig":
        """For `recon run`: no final homography (COLMAP verifies with F / E; the escalation
        trigger counts fundamental-matrix inliers), the originals always fine-matched too
        (keypoints shared by all pairs of an image form long tracks), and only the cheap escalation levels,
        and only for pairs whose coarse search found some overlap (>= 15 ORB inliers in a view)
        (`topk`, `swap`): in exhaustive matching most weak pairs simply do not overlap, and the
        two-sided levels cost 5-30 s each on them."""
        return MatcherConfig(final_homography=False, fine_include_original=True, guided_epipolar=True,
                             escalation=EscalationConfig(pairs=False, two_sided=False, min_coarse_inliers=15))

    @staticmethod
    def from_overrides(**kw) -> "MatcherConfig":
        """Build from flat overrides: `variant` ("default", "paper", "multiview"), top-level
        fields, or `section__field`.

        e.g. `from_overrides(final_homography=False, coarse__rank_by="matches", seed=3)`.
        Unknown names raise ValueError listing the valid ones.
        """
        variant = kw.pop("variant", "default")
        presets = {"default": MatcherConfig, "paper": MatcherConfig.paper, "multiview": MatcherConfig.multiview}
        if variant not in presets:
            raise ValueError(f"unknown variant {variant!r}; choose one of {', '.join(presets)}")
        base = presets[variant]()
        top = {f.name for f in fields(MatcherConfig)}
        sections: dict[str, dict] = {}
        flat: dict = {}
        for k, v in kw.items():
            if "__" in k:
                sec, name = k.split("__", 1)
                if sec not in top:
                    raise ValueError(f"unknown config section {sec!r}")
                valid = {f.name for f in fields(getattr(base, sec))}
                if name not in valid:
                    raise ValueError(f"unknown option {k!r}; {sec} has {', '.join(sorted(valid))}")
                sections.setdefault(sec, {})[name] = v
            elif k in top:
                flat[k] = v
            else:
                raise ValueError(f"unknown matcher option {k!r}; valid: {', '.join(sorted(top))}")
        for sec, vals in sections.items():
            flat[sec] = replace(getattr(base, sec), **vals)
        cfg = replace(base, **flat)
        if "seed" in kw:  # one seed drives every stage's RANSAC
            cfg = replace(cfg, reference=replace(cfg.reference, seed=cfg.seed),
                          coarse=replace(cfg.coarse, seed=cfg.seed))
        return cfg

    @property
    def verify_model(self) -> str:
        if self.verify != "auto":
            return self.verify
        return "homography" if self.final_homography else "fundamental"


class ExtraAffineMatcher:
    """The extra-affine matcher. Thread-safe: state lives in the FeatureStore and the config."""

    name = "extra-affine"

    def __init__(self, cfg: MatcherConfig | None = None):
        self.cfg = cfg or MatcherConfig()
        self.views = view_grid(self.cfg.grid)
        self._threads = self.cfg.workers or os.cpu_count() or 1
        self._pool_obj: ThreadPoolExecutor | None = None
        self._pool_lock = threading.Lock()

    @property
    def _pool(self) -> ThreadPoolExecutor | None:
        """The view thread pool, created on first use (None with `workers` = 1)."""
        if self._threads <= 1:
            return None
        with self._pool_lock:
            if self._pool_obj is None:
                self._pool_obj = ThreadPoolExecutor(max_workers=self._threads, thread_name_prefix="views")
            return self._pool_obj

    # ------------------------------------------------------------------------------------------
    def _attempt(self, store: FeatureStore, names: tuple[str, str], ref: int,
                 scores: list[CoarseScore], top_k: int, label: str) -> Attempt:
        views = select_fine_views(rank_views(scores), top_k, self.cfg.fine_include_original)
        fm = fine_match(store, names[ref], names[1 - ref], views, self.cfg.fine, self._pool)
        n_verified, _ = verify_matches(fm.kpts_ref[fm.matches[:, 0]], fm.kpts_target[fm.matches[:, 1]],
                                       self.cfg.verify_model, self.cfg.seed)
        return Attempt(label=label, reference=ref, fine=fm, views=views, coarse=scores, verified=n_verified)

    def _coarse_both_if_needed(self, store: FeatureStore, names: tuple[str, str],
                               decision: ReferenceDecision) -> dict[int, list[CoarseScore]]:
        """Coarse scores per simulated side; settles an undecided reference on the way.

        With an undecided reference (the originals barely match), the side Eq. 1 prefers is
        searched first. If its best view is verified (>= `coarse.accept_inliers` / 2 inliers),
        that view's homography gives the relative scale at image 0's centre, the quantity the
        ground truth uses: the larger image (by > `reference.scale_tolerance`) becomes the
        reference, and the first side stays when the scales are about equal. With no verified view, both sides are searched and
        the better best view wins. `decision` is updated in place with the outcome.
        """
        cfg = self.cfg
        if decision.reference is not None:
            s = decision.reference
            return {s: coarse_search(store, names[s], names[1 - s], self.views, cfg.coarse, self._pool)}
        first = 0 if decision.f0 >= decision.f1 else 1
        out = {first: coarse_search(store, names[first], names[1 - first], self.views, cfg.coarse, self._pool)}
        best = rank_views(out[first])[0]
        if best.inliers >= cfg.coarse.accept_inliers // 2 and best.H_target_from_ref is not None:
            H = best.H_target_from_ref
            H_1_from_0 = H if first == 0 else np.linalg.inv(H)
            h, w = store.image(names[0]).shape[:2]
            area = local_scale(H_1_from_0, ((w - 1) / 2.0, (h - 1) / 2.0))  # as the ground truth
            lin = math.sqrt(area) if math.isfinite(area) and area > 0 else 1.0
            chosen = first if abs(math.log(lin)) < math.log(cfg.reference.scale_tolerance) else (0 if lin < 1 else 1)
            if chosen not in out:
                out[chosen] = coarse_search(store, names[chosen], names[1 - chosen], self.views, cfg.coarse, self._pool)
            decision.reference = chosen
            decision.reason += (f"; coarse view geometry: image 0 maps {lin:.2f}x into image 1 at its centre, "
                                f"so image {chosen} is the reference")
            return out
        second = 1 - first
        out[second] = coarse_search(store, names[second], names[first], self.views, cfg.coarse, self._pool)
        return out

    def match(self, store: FeatureStore, name0: str, name1: str) -> PairResult:
        cfg = self.cfg
        t_start = time.perf_counter()
        timings: dict[str, float] = {}
        names = (name0, name1)
        sift = cfg.fine.detector

        t = time.perf_counter()
        feats = list(self._pool.map(lambda n: original_features(store, n, sift), names)) if self._pool \
            else [original_features(store, n, sift) for n in names]
        decision = choose_reference(feats[0], feats[1], cfg.reference, store.image(name0).shape[1::-1])
        timings["reference"] = time.perf_counter() - t

        t = time.perf_counter()
        coarse = self._coarse_both_if_needed(store, names, decision)
        ref = decision.reference if decision.reference is not None else \
            max(coarse, key=lambda s: (max(c.score for c in coarse[s]), -s))
        timings["coarse"] = time.perf_counter() - t

        t = time.perf_counter()
        best = self._attempt(store, names, ref, coarse[ref], cfg.fine_top_k, "")
        timings["fine"] = time.perf_counter() - t

        escalation_label = ""
        coarse_evidence = max((c.inliers for scores in coarse.values() for c in scores), default=0)
        if (cfg.escalation.enabled and best.verified < cfg.escalation.min_inliers
                and coarse_evidence >= cfg.escalation.min_coarse_inliers):
            t = time.perf_counter()
            best = escalate(self, store, names, best, coarse)
            escalation_label = best.label
            timings["escalation"] = time.perf_counter() - t

        result = self._to_result(store, names, best, decision)
        result.escalation = escalation_label
        t = time.perf_counter()
        if cfg.final_homography and result.num_matches >= 4:
            p0, p1 = result.matched_points(inliers_only=False)
            H, inl = ransac_homography(p0, p1, cfg.final_ransac_px, seed=cfg.seed)
            result.H_1_from_0, result.inlier_mask = H, inl
            if H is None:
                result.reason = "no homography fits the matches"
        if cfg.guided and result.H_1_from_0 is not None and best.views:
            result = self._guided(store, names, best, result)
        elif cfg.guided_epipolar and not cfg.final_homography and best.views and result.num_matches >= 15:
            result = self._guided_epipolar(store, names, best, result)
        if result.escalation in ("pairs", "two-sided") and result.H_1_from_0 is not None:
            result = self._reference_from_final_h(store, names, result)
        timings["ransac"] = time.perf_counter() - t
        timings["total"] = time.perf_counter() - t_start
        result.timings = timings
        if result.num_inliers < cfg.min_result_inliers:
            why = result.reason or (f"only {result.num_inliers} verified matches (< {cfg.min_result_inliers}): "
                                    "the images probably do not overlap")
            empty = PairResult.empty(self.name, why, reference=result.reference,
                                     reference_reason=result.reference_reason, f0=result.f0, f1=result.f1,
                                     best_views=result.best_views, coarse_scores=result.coarse_scores,
                                     escalation=result.escalation, timings=timings, image_sizes=result.image_sizes)
            return empty
        return result

    def _guided(self, store: FeatureStore, names: tuple[str, str], att: Attempt, res: PairResult) -> PairResult:
        """Re-match the fine views under the fitted homography (see `fine.guided_match`), then
        refit the final homography on the union of first-round and guided matches."""
        cfg = self.cfg
        det = cfg.fine.detector
        ref = att.reference
        H_t_from_ref = res.H_1_from_0 if ref == 0 else np.linalg.inv(res.H_1_from_0)
        ft = original_features(store, names[1 - ref], det)
        kr, m_all, d_all = self._rematch_views(
            store, names[ref], att.views, ft,
            lambda fv: guided_match(fv.kpts, fv.descriptors, ft.kpts, ft.descriptors, H_t_from_ref,
                                    cfg.guided_px, cfg.guided_ratio))
        if len(m_all) == 0:
            return res
        m_all, d_all = unique_train(m_all, d_all)
        used = np.unique(m_all[:, 0])
        remap = np.full(len(kr), -1, np.int64)
        remap[used] = np.arange(len(used))
        fm = FineMatches(kr[used], ft.kpts, np.stack([remap[m_all[:, 0]], m_all[:, 1]], 1).astype(np.int32), d_all, {})
        guided = Attempt("guided", ref, fm, att.views, att.coarse, 0)
        out = self._to_result(store, names, guided, None)
        out.reference_reason, out.f0, out.f1 = res.reference_reason, res.f0, res.f1
        out.escalation = res.escalation
        p0, p1 = out.matched_points(inliers_only=False)
        H, inl = ransac_homography(p0, p1, cfg.final_ransac_px, seed=cfg.seed)
        if H is None or inl.sum() < res.num_inliers:
            res.timings["guided_rejected"] = float(inl.sum())
            return res
        out.H_1_from_0, out.inlier_mask = H, inl
        return out

    def _rematch_views(self, store: FeatureStore, ref_name: str, views, ft, match_fn,
                       first: FineMatches | None = None) -> tuple[NDArray, NDArray, NDArray]:
        """(reference keypoints, (K, 2) matches into them and into `ft`, distances) of every view
        re-matched by `match_fn(view_features) -> (matches, distances)`, after `first`'s when given."""
        cfg = self.cfg
        size = store.image(ref_name).shape[1::-1]
        kpts_ref, pairs, dists = [], [], []
        offset = 0
        if first is not None:
            kpts_ref, pairs, dists, offset = [first.kpts_ref], [first.matches], [first.distances], len(first.kpts_ref)
        for view in views:
            rendered = capped_view(view, size, cfg.fine.max_area_ratio)
            fv = view_features(store, ref_name, rendered, cfg.fine.detector, cfg.fine.interp, cfg.fine.antialias)
            m, d = match_fn(fv)
            kpts_ref.append(fv.kpts[m[:, 0]])
            pairs.append(np.stack([np.arange(len(m)) + offset, m[:, 1]], axis=1))
            dists.append(d)
            offset += len(m)
        kr = np.concatenate(kpts_ref) if kpts_ref else np.zeros((0, 2), np.float32)
        m_all = np.concatenate(pairs).astype(np.int32) if pairs else np.zeros((0, 2), np.int32)
        d_all = np.concatenate(dists).astype(np.float32) if dists else np.zeros(0, np.float32)
        return kr, m_all, d_all

    def _guided_epipolar(self, store: FeatureStore, names: tuple[str, str], att: Attempt,
                         res: PairResult) -> PairResult:
        """Re-match the fine views under a fundamental matrix fitted to `res` (see
        `fine.epipolar_guided_match`); returns the F-consistent union of both rounds, or `res`
        unchanged when the first round's F is not trustworthy: fewer than
        `guided_epipolar_min_inliers` inliers, or under `guided_epipolar_min_ratio` of its
        matches. Without that gate a pair whose matches are mostly wrong (repeated structure,
        little overlap) gets an F through chance inliers, and the band around its wrong lines
        collects hundreds of chance matches that are consistent with it, so COLMAP verifies
        them: sacre_coeur fell from 1096 to 136 points with a wrong model. On sacre_coeur the
        first-round F (1 px) holds 44-59 % of the matches of overlapping pairs and 7-23 % of
        the others. (Also capping new matches' descriptor distance at the 90th percentile of the
        verified ones removed every gain on the rendered facades: the matches the band brings
        back are by nature the less distinctive ones.)"""
        cfg = self.cfg
        det = cfg.fine.detector
        ref = att.reference
        fm = att.fine
        p_ref, p_t = fm.kpts_ref[fm.matches[:, 0]], fm.kpts_target[fm.matches[:, 1]]
        cv2.setRNGSeed(cfg.seed)
        F, mask = cv2.findFundamentalMat(p_ref.astype(np.float32), p_t.astype(np.float32), cv2.FM_RANSAC,
                                         cfg.guided_epipolar_px, 0.999, 10000)
        if F is None or F.shape != (3, 3) or mask is None:
            return res
        inl = mask.ravel().astype(bool)
        if inl.sum() < cfg.guided_epipolar_min_inliers or inl.sum() < cfg.guided_epipolar_min_ratio * len(inl):
            return res  # no trustworthy geometry: a band around wrong lines only collects chance matches
        ft = original_features(store, names[1 - ref], det)
        kr, m_all, d_all = self._rematch_views(
            store, names[ref], att.views, ft,
            lambda fv: epipolar_guided_match(fv.kpts, fv.descriptors, ft.kpts, ft.descriptors, F,
                                             cfg.guided_epipolar_px, cfg.guided_epipolar_ratio),
            first=fm)
        # one match per reference position and per target keypoint (first round wins ties: it comes first)
        key = np.c_[np.round(kr[m_all[:, 0]] * 4).astype(np.int64), m_all[:, 1].astype(np.int64)]
        _, first = np.unique(key, axis=0, return_index=True)
        m_all, d_all = m_all[np.sort(first)], d_all[np.sort(first)]
        m_all, d_all = unique_train(m_all, d_all)
        keep = epipolar_pair_distance(F, kr[m_all[:, 0]], ft.kpts[m_all[:, 1]]) <= cfg.guided_epipolar_px
        m_all, d_all = m_all[keep], d_all[keep]
        used = np.unique(m_all[:, 0])
        remap = np.full(len(kr), -1, np.int64)
        remap[used] = np.arange(len(used))
        fm2 = FineMatches(kr[used], ft.kpts, np.stack([remap[m_all[:, 0]], m_all[:, 1]], 1).astype(np.int32), d_all, {})
        if len(fm2.matches) <= res.num_matches:
            return res
        out = self._to_result(store, names, Attempt("guided", ref, fm2, att.views, att.coarse, 0), None)
        out.reference_reason, out.f0, out.f1 = res.reference_reason, res.f0, res.f1
        out.escalation = res.escalation
        return out

    def _reference_from_final_h(self, store: FeatureStore, names: tuple[str, str], res: PairResult) -> PairResult:
        """Two-sided levels simulate both images, so neither was "the" reference: report the
        one the verified final homography says is more detailed (scale at image 0's centre)."""
        h, w = store.image(names[0]).shape[:2]
        area = local_scale(res.H_1_from_0, ((w - 1) / 2.0, (h - 1) / 2.0))
        if not (math.isfinite(area) and area > 0) or res.num_inliers < self.cfg.escalation.min_inliers:
            return res
        lin = math.sqrt(area)
        ref = 0 if lin <= 1.0 else 1
        res.reference = ref  # type: ignore[assignment]
        res.reference_reason += f"; both images simulated, final homography: image {ref} is {max(lin, 1 / lin):.2f}x larger"
        return res

    def _to_result(self, store: FeatureStore, names: tuple[str, str], att: Attempt, decision) -> PairResult:
        fm = att.fine
        sizes = tuple((store.image(n).shape[1], store.image(n).shape[0]) for n in names)
        if decision is None:
            reason, f0, f1 = "", None, None
        else:
            f0, f1 = decision.f0, decision.f1
            reason = decision.reason if att.reference == decision.reference else \
                f"{decision.reason}; chose image {att.reference} by coarse score"
        res = PairResult(method=self.name, kpts0=fm.kpts_ref, kpts1=fm.kpts_target,
                         matches=fm.matches, distances=fm.distances, reference=0,
                         reference_reason=reason, f0=f0, f1=f1,
                         best_views=att.views, coarse_scores=att.coarse, image_sizes=sizes)  # type: ignore[arg-type]
        if att.reference == 1:
            res = res.swapped()
            res.f0, res.f1 = f0, f1
        return res

    def close(self) -> None:
        if self._pool_obj is not None:
            self._pool_obj.shutdown(wait=False)
            self._pool_obj = None
