"""Result and parameter types shared by every matcher.

Pixel convention everywhere in `matching/`: keypoints are (x, y) in pixels of the *original,
full-resolution* image, OpenCV convention (the centre of the top-left pixel is (0, 0)).
COLMAP's convention (centre at (0.5, 0.5)) is applied only when writing a COLMAP database.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

Float2 = NDArray[np.float32]  # (N, 2) pixel coordinates
Reference = Literal[0, 1]


@dataclass(frozen=True, order=True)
class ViewParams:
    """One simulated affine view: tilt t >= 1, longitude phi in degrees, scale s > 0.

    The simulated image is `s * T_t * R(phi) * I` (rotate by phi, compress x by 1/t, zoom by s),
    translated so that the whole warped image lies on the canvas (see `matching.views`).
    """

    t: float
    phi: float
    s: float = 1.0

    @property
    def key(self) -> str:
        """Stable cache name of the view, e.g. 't2.828_p25.46_s2.00'."""
        return f"t{self.t:.3f}_p{self.phi:.2f}_s{self.s:.2f}"

    @property
    def is_identity(self) -> bool:
        return abs(self.t - 1.0) < 1e-9 and abs(self.phi) < 1e-9 and abs(self.s - 1.0) < 1e-9


@dataclass
class CoarseScore:
    """Coarse-search outcome of one simulated view of the reference image."""

    view: ViewParams
    matches: int  # ratio-test ORB matches between the view and the target
    inliers: int  # RANSAC homography inliers among them (0 when not computed)
    score: float  # what the search ranks by (matches, or inliers; see CoarseConfig)
    # the RANSAC homography, original reference pixels -> target pixels (None below 8 matches)
    H_target_from_ref: NDArray[np.float64] | None = field(default=None, repr=False, compare=False)


@dataclass
class PairResult:
    """Matches between image 0 and image 1 of a pair, as pure data.

    `kpts0`/`kpts1` are keypoints in original-image pixels (OpenCV convention, see module doc);
    `matches[i] = (i0, i1)` indexes them. `H_1_from_0` maps image 0 to image 1 when a final
    homography was fitted, and `inlier_mask` flags the matches consistent with it (all True
    when no homography was fitted). Timings are wall-clock seconds per stage.
    """

    method: str
    kpts0: Float2
    kpts1: Float2
    matches: NDArray[np.int32]  # (K, 2)
    distances: NDArray[np.float32]  # (K,) descriptor distance of each match
    reference: Reference | None = None  # which image was simulated (None: method does not choose)
    reference_reason: str = ""
    f0: float | None = None  # Eq. 1 coefficient with image 0 as the source (paper's f1)
    f1: float | None = None  # Eq. 1 coefficient with image 1 as the source (paper's f2)
    best_views: list[ViewParams] = field(default_factory=list)  # fine-stage views, best first
    coarse_scores: list[CoarseScore] = field(default_factory=list)
    H_1_from_0: NDArray[np.float64] | None = None
    inlier_mask: NDArray[np.bool_] | None = None
    escalation: str = ""  # "" when the fast path sufficed, else the escalation level used
    reason: str = ""  # why the result is empty or weak; "" when fine
    path: str = ""  # "originals" / "targeted" / "full" (adaptive), "deferred" (simulate=False, weak); "" other methods
    path_reason: str = ""  # why that path (the evidence from the originals and any fall-through)
    planned_path: str = ""  # the path the originals' evidence points to (`adaptive.plan_pair`), adaptive or
    # not (with adaptive paths `path` differs where an attempt fell through); "" when nothing is simulated
    verified: int = -1  # matches its own check verified (H / F inliers) before the finishing steps; -1: not counted
    finishing: str = ""  # what the finishing steps did ("; "-joined: a guided round's gain or why it was skipped, refinement)
    timings: dict[str, float] = field(default_factory=dict)
    image_sizes: tuple[tuple[int, int], tuple[int, int]] | None = None  # ((w0, h0), (w1, h1))

    @property
    def num_matches(self) -> int:
        return int(len(self.matches))

    @property
    def num_inliers(self) -> int:
        if self.inlier_mask is None:
            return self.num_matches
        return int(np.count_nonzero(self.inlier_mask))

    @property
    def best_view(self) -> ViewParams | None:
        return self.best_views[0] if self.best_views else None

    def matched_points(self, inliers_only: bool = True) -> tuple[Float2, Float2]:
        """(pts0, pts1): the matched pixel coordinates, (K, 2) each."""
        m = self.matches
        if inliers_only and self.inlier_mask is not None:
            m = m[self.inlier_mask]
        return self.kpts0[m[:, 0]], self.kpts1[m[:, 1]]

    def swapped(self) -> PairResult:
        """The same result seen from image 1 (image indices and directions exchanged)."""
        H = None if self.H_1_from_0 is None else np.asarray(np.linalg.inv(self.H_1_from_0), np.float64)
        ref: Reference | None = None if self.reference is None else (1 - self.reference)  # type: ignore[assignment]
        sizes = None if self.image_sizes is None else (self.image_sizes[1], self.image_sizes[0])
        # every other field (diagnostics) is the same seen from either side
        return dataclasses.replace(self, kpts0=self.kpts1, kpts1=self.kpts0, matches=self.matches[:, ::-1].copy(),
                                   reference=ref, f0=self.f1, f1=self.f0, H_1_from_0=H,
                                   timings=dict(self.timings), image_sizes=sizes)

    def in_original_frame(self, work_sizes: tuple[tuple[int, int], tuple[int, int]],
                          sizes: tuple[tuple[int, int], tuple[int, int]]) -> PairResult:
        """This result, matched on images resized from `sizes` to `work_sizes` ((w, h) of image 0
        and image 1; `matching.io.resize_max`), in the originals' pixels: keypoints through
        `io.to_original_px` with the exact per-axis scales, `H_1_from_0` conjugated by
        `io.work_from_original`, `image_sizes` = `sizes`. Views, scores and timings are unchanged
        (they describe the matching itself)."""
        from .io import to_original_px, work_from_original

        s0, s1 = ((w / W, h / H) for (w, h), (W, H) in zip(work_sizes, sizes))
        H_1_from_0 = self.H_1_from_0
        if H_1_from_0 is not None:
            H_1_from_0 = np.linalg.inv(work_from_original(s1)) @ np.asarray(H_1_from_0, np.float64) @ work_from_original(s0)
            H_1_from_0 = H_1_from_0 / H_1_from_0[2, 2]
        return dataclasses.replace(self, kpts0=to_original_px(self.kpts0, s0), kpts1=to_original_px(self.kpts1, s1),
                                   H_1_from_0=H_1_from_0, image_sizes=sizes, timings=dict(self.timings))

    def without_matches(self, reason: str) -> PairResult:
        """This result with no matches and `reason`, its diagnostics (reference, views, coarse
        scores, path, finishing notes, timings, verified count) kept; no homography."""
        empty = PairResult.empty(self.method, reason)
        return dataclasses.replace(self, kpts0=empty.kpts0, kpts1=empty.kpts1, matches=empty.matches,
                                   distances=empty.distances, H_1_from_0=None, inlier_mask=None, reason=reason)

    @staticmethod
    def empty(method: str, reason: str, **kw) -> PairResult:
        z2 = np.zeros((0, 2), np.float32)
        return PairResult(method=method, kpts0=z2, kpts1=z2.copy(),
                          matches=np.zeros((0, 2), np.int32),
                          distances=np.zeros((0,), np.float32), reason=reason, **kw)
