"""The extra-affine matcher as a library (knows nothing of COLMAP or Rerun).

    from matching import match_images, load_gray
    result = match_images(load_gray("a.jpg"), load_gray("b.jpg"))   # method="extra-affine"

Keypoints are pixels of the original images, OpenCV convention (top-left pixel centre at (0, 0)).
"""

from .errors import InputError
from .features import DetectorConfig, Features
from .io import load_color, load_gray, read_homography
from .matcher import ExtraAffineMatcher, MatcherConfig
from .registry import METHODS, PairMatcher, get_matcher, match_images
from .store import FeatureStore
from .types import CoarseScore, PairResult, ViewParams

__all__ = [
    "METHODS", "CoarseScore", "DetectorConfig", "ExtraAffineMatcher", "FeatureStore", "Features",
    "InputError", "MatcherConfig", "PairMatcher", "PairResult", "ViewParams", "get_matcher",
    "load_color", "load_gray", "match_images", "read_homography",
]
