"""Method names -> matcher objects, so the CLI, the benchmarks and the pipeline share one list."""

from __future__ import annotations

from typing import Protocol

from numpy.typing import NDArray

from .io import image_size, resize_max
from .store import FeatureStore
from .types import PairResult

METHODS: tuple[str, ...] = ("extra-affine", "sift", "orb", "asift", "aorb")


class PairMatcher(Protocol):
    """Anything that matches two images of a FeatureStore into a PairResult.

    Keypoints in the result are in the pixel frame of the images as stored (OpenCV convention).
    Implementations must be safe to call from several threads at once on one store.
    """

    name: str

    def match(self, store: FeatureStore, name0: str, name1: str) -> PairResult: ...


def get_matcher(method: str, **overrides) -> PairMatcher:
    """The matcher called `method` (one of METHODS); `overrides` set fields of its config."""
    if method == "extra-affine":
        from .matcher import ExtraAffineMatcher, MatcherConfig

        return ExtraAffineMatcher(MatcherConfig.from_overrides(**overrides))
    if method in ("sift", "orb", "asift", "aorb"):
        from .baselines import make_baseline

        return make_baseline(method, **overrides)
    raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")


def match_images(img0: NDArray, img1: NDArray, method: str = "extra-affine", max_size: int = 0,
                 **overrides) -> PairResult:
    """Match two 8-bit gray images with a throw-away store (convenience for scripts).

    `max_size` > 0 matches them downscaled so their longer side is at most that many px (SIFT's
    time and memory grow with the pixels: a 24 Mpx photo takes gigabytes) and returns the
    result in the originals' pixels (`PairResult.in_original_frame`); 0 = full resolution."""
    return match_at_size(get_matcher(method, **overrides), img0, img1, max_size)[0]


def match_at_size(matcher: PairMatcher, img0: NDArray, img1: NDArray, max_size: int,
                  names: tuple[str, str] = ("0", "1")) -> tuple[PairResult, tuple[float, float]]:
    """(`matcher`'s result for the two gray images stored under `names`, matched at most
    `max_size` px on the longer side (0 = full) and returned in the originals' pixels; the
    working / original scale of each image, 1.0 where it was not resized)."""
    work0, scale0 = resize_max(img0, max_size)
    work1, scale1 = resize_max(img1, max_size)
    store = FeatureStore()
    store.add_image(names[0], work0)
    store.add_image(names[1], work1)
    result = matcher.match(store, names[0], names[1])
    if (scale0, scale1) != (1.0, 1.0):
        result = result.in_original_frame((image_size(work0), image_size(work1)), (image_size(img0), image_size(img1)))
    return result, (scale0, scale1)
