"""`MatcherConfig`: every option of the extra-affine matcher, composed of the stage configs.

One source for every option: each field is typed and documented by the string right below it
(`field_docs` reads those, so a CLI or a check can show them), each stage config lives with its
stage (`views.GridConfig`, `reference.ReferenceConfig`, `coarse.CoarseConfig`,
`fine.FineConfig`, `escalation.EscalationConfig`), and the one `seed` seeds every stage's
RANSAC and FLANN (the stage configs have no seed of their own, so none can disagree).
Measured reasons for the defaults are in docs/decisions.md.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
import typing
from dataclasses import dataclass, field, fields, replace
from functools import cache
from typing import Any, Literal

from .adaptive import AdaptiveConfig
from .coarse import CoarseConfig
from .escalation import EscalationConfig, SteepConfig
from .fine import FineConfig
from .mser import MserConfig
from .planar import PlanarConfig
from .reference import ReferenceConfig
from .refine import RefineConfig
from .views import GridConfig

Variant = Literal["default", "paper", "multiview", "3d"]
VARIANTS: tuple[str, ...] = typing.get_args(Variant)
"""The presets `MatcherConfig.from_overrides(variant=...)` knows, in that order."""


def _check_path(section: Any, sec_name: str, path: list[str], key: str) -> None:
    """ValueError unless `path` names a field of `section`, through nested sections (e.g.
    escalation's `mser.pool`), naming the valid fields where it does not."""
    obj, where = section, sec_name
    for i, name in enumerate(path):
        valid = {f.name for f in fields(obj)}
        if name not in valid:
            raise ValueError(f"unknown option {key!r}; {where} has {', '.join(sorted(valid))}")
        if i < len(path) - 1:
            obj = getattr(obj, name)
            if not dataclasses.is_dataclass(obj):
                raise ValueError(f"unknown option {key!r}; {where}.{name} is not a section")
            where = f"{where}.{name}"


def _replace_nested(obj: Any, vals: dict[str, Any]) -> Any:
    """`obj` (a frozen dataclass) with `vals` set, keys dotted through nested dataclasses."""
    here: dict[str, Any] = {}
    deeper: dict[str, dict[str, Any]] = {}
    for key, value in vals.items():
        head, sep, rest = key.partition(".")
        if sep:
            deeper.setdefault(head, {})[rest] = value
        else:
            here[head] = value
    for head, sub in deeper.items():
        here[head] = _replace_nested(getattr(obj, head), sub)
    return replace(obj, **here)


@dataclass(frozen=True)
class MatcherConfig:
    """Everything the extra-affine matcher does, with the paper's choices where they measure best
    (`MatcherConfig.paper()` is the plain reading, `MatcherConfig.multiview()` what `recon run` uses)."""

    grid: GridConfig = field(default_factory=GridConfig)
    """The simulated views (t, phi, s) of the coarse search (§III-B)."""
    reference: ReferenceConfig = field(default_factory=ReferenceConfig)
    """How the image to simulate is chosen (§III-A)."""
    coarse: CoarseConfig = field(default_factory=CoarseConfig)
    """The ORB coarse search that ranks the views (§III-B)."""
    fine: FineConfig = field(default_factory=FineConfig)
    """The SIFT fine stage on the best views (§III-C)."""
    escalation: EscalationConfig = field(default_factory=EscalationConfig)
    """What a pair the fast path leaves unverified tries next."""
    refine: RefineConfig = field(default_factory=lambda: RefineConfig(match_blur=True))
    """Least-squares patch refinement of the final matches (`matching.refine`; not in the paper),
    with resolution-matched patches (`RefineConfig.match_blur`): on the shared pairs and the
    rendered tilt pairs the refined matches end closer to the ground truth with it (graf 1-6
    median 0.438 -> 0.401 px, all ten rendered tilt pairs 2-27 % closer; docs/decisions.md,
    "Resolution-matched patches")."""
    simulate: bool = True
    """False: match only the unwarped originals (no coarse search, no simulated view, no
    escalation; the finishing steps still run). The first pass of `recon run`'s
    `match.simulate = "needed"` schedule (`recon.core.schedule`), which spends view simulation
    only on the pairs that this pass leaves weak and the scene needs."""
    adaptive: bool = True
    """Decide per pair how much simulation it needs from the originals' SIFT geometry
    (`matching.adaptive`: `originals`, `targeted` or `full` path, cheapest first, falling through
    when a path verifies too little). False runs the full coarse grid on every pair, as the paper."""
    paths: AdaptiveConfig = field(default_factory=AdaptiveConfig)
    """Thresholds of the adaptive path decision (used with `adaptive`)."""
    fine_top_k: int = 2
    """How many of the best coarse views the fine stage fuses (paper: 1); two views give more
    correct matches at equal precision (docs/decisions.md)."""
    fine_min_view_distance: float = 0.0
    """(>= 0) Fine views at least this far apart in the tilt plane (`adaptive.tilt_plane_point`:
    radius log t, angle 2 phi), so the fused views rectify different surfaces instead of one peak
    twice (e.g. (5.66, 0°) and (5.66, 178°) are the same view); 0 = the best `fine_top_k` as
    ranked. Opt-in: on a photo-textured facade at 78° steps, where every neighbour pair's two
    best views rectified the ground and COLMAP found no initial pair, 1.0 registered 3 of 3 at
    0.030°, but on the real scenes it matched 3-11 % fewer inliers per pair and raised
    fountain_P11's rotation error above stock's; 0.25 (only the grid's near-duplicates) changed
    the real scenes by nothing and the renders by a few inliers (docs/decisions.md, "Distinct
    fine views")."""
    planar: PlanarConfig = field(default_factory=PlanarConfig)
    """One more, distinct fine view for pairs whose fused matches fit one homography
    (`matching.planar`; on in `multiview`, off for the pair matcher, whose homography
    verification makes every pair planar)."""
    fine_include_original: bool = False
    """Also fine-match the unwarped originals (multi-view: keypoints shared across pairs form long
    tracks, and matches cover the surfaces the best view does not rectify)."""
    final_homography: bool = True
    """Fit a RANSAC homography to the final matches and flag inliers (planar pairs, benchmarks);
    the multi-view pipeline turns it off and leaves verification to COLMAP."""
    final_ransac_px: float = 1.5
    """Threshold of the final homography, px of image 1: 3 px (OpenCV's default) admits SIFT
    localisation errors of 2-3 px that the sqrt(3) px precision test rejects (docs/decisions.md)."""
    guided: bool = True
    """After the final homography, re-match the fine views' keypoints only against target
    keypoints within `guided_px` of their predicted position (more matches at equal precision)."""
    guided_px: float = 4.0
    """Radius of the guided round under H, px of the original target."""
    guided_ratio: float = 0.8
    """Lowe's ratio of the guided round under H."""
    guided_epipolar: bool = False
    """Without a final homography (multi-view): fit a fundamental matrix (RANSAC,
    `guided_epipolar_px`) to the matches and re-match the fine views' keypoints only against
    target keypoints within `guided_epipolar_px` of their epipolar line, keeping the
    F-consistent union with the first round (`guided.GuidedEpipolar`)."""
    guided_epipolar_px: float = 1.0
    """Band half-width around the epipolar line and F's RANSAC threshold, px: a wider band lets in
    matches near the line that are wrong (docs/decisions.md)."""
    guided_epipolar_ratio: float = 0.7
    """Lowe's ratio inside the epipolar band (0.8 lets in more wrong matches, docs/decisions.md)."""
    guided_epipolar_min_inliers: int = 50
    """The epipolar round runs only when the first round's F has at least this many inliers..."""
    guided_epipolar_min_ratio: float = 0.35
    """...and at least this fraction of the first round's matches: around a wrong F the band
    collects chance matches consistent with it (docs/decisions.md)."""
    guided_epipolar_add: bool = False
    """When the round's F-consistent union has no more matches than the first round (the first
    round's matches off F's 1 px band outnumber the round's new ones: 12 of the 78 pairs of the
    difficulty curve's 13-view facade, its nearest neighbours among them), keep the first round
    whole and add the round's new F-consistent matches, instead of keeping the first round alone
    (docs/decisions.md, "Adding the epipolar round's matches to a larger first round"). Off."""
    guided_epipolar_neighbour_px: float = 0.0
    """(>= 0) Drop the epipolar round's new matches (those the first round did not have) that lie
    more than this many px of the target from where the affine of their 12 nearest first-round
    F-consistent matches puts them (`refine.neighbour_transfer_residuals`): the band admits wrong
    matches that sit on the right epipolar line but not where the surface around them goes. 0 =
    off (the default: alone it loses the difficulty curve's 78° step, and with the polished F and
    ratio 0.8, where it makes the renders most precise, fountain_P11's rotation error is above
    stock's; docs/decisions.md, "Neighbour check of the epipolar round")."""
    guided_epipolar_polish: bool = False
    """Polish the round's F (`matching_utils.polish_fundamental`: eight-point refits to the
    matches it explains, while they grow) before drawing the band: OpenCV's RANSAC returns a
    seven-point sample's F, whose lines miss true matches by more than the 1 px band. Measured on
    the difficulty curve (render 0): verified inliers per pair 892 -> 939 at 13° and 812 -> 862 at
    19.5° (stock `high` 980 / 849), rotation error 0.002° -> 0.005° and 0.004° -> 0.004°; but on
    the real scenes a slightly worse model (fountain_P11 0.226 -> 0.234 px, 0.2333° -> 0.2363°
    against stock's 0.2340°), so off (docs/decisions.md, "Polished F in the epipolar round");
    `recon run --set matcher.guided_epipolar_polish=true` turns it on."""
    verify: Literal["auto", "homography", "fundamental"] = "auto"
    """The model that counts verified matches for the escalation decision ("auto" = homography
    with `final_homography`, else fundamental matrix)."""
    min_result_inliers: int = 10
    """A final result with fewer verified matches is returned empty, with the reason (random
    matches between unrelated images reach a few RANSAC inliers, docs/decisions.md)."""
    workers: int = 0
    """Threads for independent views (0 = all cores, 1 = none, for callers that already run pairs
    in parallel). Results do not depend on it."""
    seed: int = 0
    """Seeds every RANSAC and FLANN of every stage: results are deterministic per seed."""

    @staticmethod
    def paper() -> MatcherConfig:
        """A plain reading of the paper: Eq. 1 reference, most-matches ranking, no blur, no escalation."""
        return MatcherConfig(reference=ReferenceConfig(mode="paper", decision_scale=1.0), guided=False, final_ransac_px=3.0,
                             coarse=CoarseConfig(rank_by="matches", max_area_ratio=0.0, max_side=0,
                                                     search="grid", settle_targeted=False),
                             fine=FineConfig(antialias=False, max_area_ratio=0.0), fine_top_k=1,
                             escalation=EscalationConfig(enabled=False), adaptive=False,
                             refine=RefineConfig(enabled=False))

    @staticmethod
    def multiview() -> MatcherConfig:
        """For `recon run`: no final homography (COLMAP verifies with F / E; the escalation trigger
        counts fundamental-matrix inliers), the originals always fine-matched too (keypoints shared
        by all pairs of an image form long tracks), the epipolar-guided round, and only the cheap
        escalation levels (`topk`, `swap`; `mser`'s frame check needs a homography), only for pairs
        whose coarse search found some overlap
        (>= 15 ORB inliers in a view): in exhaustive matching most weak pairs simply do not overlap,
        and the two-sided levels cost seconds each on them (docs/decisions.md).

        No adaptive paths here: in a scene the cheap paths cost accuracy where this project is
        meant to be best (rendered facade-wide: 0.23° instead of 0.11° relative rotation error;
        corner / corner-wide: 66-83 % of the verified inliers per pair; the difficulty curve's
        13°-39° steps: 89-92 %, for at most 14 % less time now that the covariant extraction of the
        originals, which every path needs, dominates), while they cut fountain_P11's
        matching time by half at equal accuracy; `recon run --preset adaptive` (or
        `--set matcher.adaptive=true`) turns them on, and `recon run` does so by itself on scenes
        of more than 30 images (`recon.config.MatchConfig.adaptive_above`), which are mostly
        easy neighbouring pairs (docs/decisions.md, "Adaptive per-pair paths").

        Patch refinement on (`matching.refine`, each match's local affine fitted robustly to its
        20 nearest matches: there is no final homography): the simulated side's points
        re-localised by NCC under the local geometry. On a rendered 60° pair the median error
        against the exact homography falls from 0.35 to 0.10 px (0.15 px with the plain fit to 12
        neighbours used before, docs/decisions.md "Robust local affines"); in scenes it lowers the
        mean reprojection error (when it was turned on: fountain_P11 0.471 -> 0.421 px,
        sceaux_castle 0.752 -> 0.709, castle_P30 0.641 -> 0.602, the difficulty curve's three
        renders by up to 0.08 px at every step) at about the same rotation error
        (fountain 0.243° -> 0.240°, castle 0.449° -> 0.458°; smaller at 52° on all three renders).
        It was off before the consistent-tracks check and the centred SIFT keypoints, when it
        raised fountain's reprojection error (docs/decisions.md, "Patch refinement in `recon
        run`"); `--set matcher.refine.enabled=false` turns it off. Without the pair matcher's
        resolution-matched patches (`RefineConfig.match_blur`): in scenes they measured flat
        (fountain_P11 0.226 -> 0.227 px and 0.2333° -> 0.2341°, sacre_coeur 0.251 -> 0.244 px,
        sceaux_castle 0.454 -> 0.456 px; docs/decisions.md, "Resolution-matched patches").

        The coarse search scores the full grid too (`CoarseConfig.search`): the coarse-to-fine
        search was measured on planar pairs only, and a scene pair's second surface may peak
        where the sparse first pass finds nothing.

        The originals are matched with COLMAP's SIFT with affine shape and domain-size pooling
        (`FineConfig.original_detector` = "colmap-sift", the simulated views keep OpenCV's SIFT):
        on the rendered difficulty curve 1.27-1.42x the verified inliers per pair, at or above
        stock `high`'s at every step, for about 3 s more CPU per 800x600 image
        (docs/decisions.md, "COLMAP's covariant SIFT on the originals").

        A pair whose fused matches fit one homography gets one more fine view far from the chosen
        ones (`matching.planar`): on a photo-textured facade at 78° steps both neighbour pairs'
        views rectified only the ground and nothing registered; with it 3 of 3 register. It
        leaves the real scenes' models unchanged (no distinct view overlaps there) and adds
        verified inliers on the rendered scenes (docs/decisions.md, "A distinct view for
        one-surface pairs")."""
        return MatcherConfig(final_homography=False, fine_include_original=True, guided_epipolar=True,
                             reference=ReferenceConfig(decision_scale=1.0),
                             planar=PlanarConfig(enabled=True),
                             fine=FineConfig(original_detector="colmap-sift"),
                             escalation=EscalationConfig(pairs=False, two_sided=False, min_coarse_inliers=15,
                                                         steep=SteepConfig(enabled=False),
                                                         mser=MserConfig(enabled=False)),
                             adaptive=False, refine=RefineConfig(enabled=True, neighbours=20),
                             coarse=CoarseConfig(search="grid", settle_targeted=False))

    @staticmethod
    def pair3d() -> MatcherConfig:
        """For one pair of photos of a 3D scene (`recon match --variant 3d`): the pair preset's
        adaptive paths and escalation levels, without its final homography (fundamental-matrix
        verification), with the unwarped originals fine-matched too, by COLMAP's SIFT with
        affine shape but no domain-size pooling ("colmap-sift-affine"), and the epipolar-guided
        round.

        Why: on a wide 3D pair the simulated view rectifies one surface and the escalation sees
        only what it matches; the covariant originals add the rest of the scene and give the
        epipolar round a true F to grow from. On `recon bench posed`'s 46 real pairs
        (fountain_P11, castle_P30, 8-114°, 1024 px; docs/decisions.md, "A preset for one 3D
        pair"): solved 38 -> 41, AUC@5 / 10 / 20° 0.730 / 0.788 / 0.830 -> 0.792 / 0.850 /
        0.882, median correct 190 -> 840, for 1.49x the total time (about 5 s of extraction per
        pair: 5x on narrow pairs, a quarter on those the pair preset sends to `mser`). Pooling
        ("colmap-sift", `multiview`'s) solved 40 for 3.3x; `multiview` itself 42 for a median
        18.7 s per pair. fountain_P11 0001-0010 (99°): `mser`, 26.8° off in 32.5 s -> the fast
        path at 0.88° in 9.7 s; lost: castle_P30 0028-0029 (51°, 2.8° -> 8.0°). On 40 rendered
        3D pairs (the project's corner and facade presets) 30 -> 36 solved, AUC@5 0.727 -> 0.861:
        the pair preset's matches lie on the one surface its views rectify, from which the
        essential matrix is ambiguous (poses 47-130° off with hundreds of correct matches)."""
        return MatcherConfig(final_homography=False, fine_include_original=True, guided_epipolar=True,
                             fine=FineConfig(original_detector="colmap-sift-affine"))

    @staticmethod
    def from_overrides(**kw: Any) -> MatcherConfig:
        """Build from flat overrides: `variant` ("default", "paper", "multiview", "3d"), top-level
        fields, or a section's field as `section__field` (or `section.field`, via `**{...}`).

        e.g. `from_overrides(final_homography=False, coarse__rank_by="matches", seed=3)`.
        Unknown names raise ValueError listing the valid ones.
        """
        variant = kw.pop("variant", "default")
        presets = {"default": MatcherConfig, "paper": MatcherConfig.paper, "multiview": MatcherConfig.multiview,
                   "3d": MatcherConfig.pair3d}
        if variant not in presets:
            raise ValueError(f"unknown variant {variant!r}; choose one of {', '.join(presets)}")
        base = presets[variant]()
        top = {f.name for f in fields(MatcherConfig)}
        sections = {f.name for f in fields(MatcherConfig) if dataclasses.is_dataclass(getattr(base, f.name))}
        by_section: dict[str, dict[str, Any]] = {}
        flat: dict[str, Any] = {}
        for key, value in kw.items():
            sec, sep, name = key.replace(".", "__", 1).partition("__")
            if sep:
                if sec not in sections:
                    raise ValueError(f"unknown config section {sec!r} in {key!r}; "
                                     f"sections: {', '.join(sorted(sections))}")
                _check_path(getattr(base, sec), sec, name.replace("__", ".").split("."), key)
                by_section.setdefault(sec, {})[name.replace("__", ".")] = value
            elif key in top:
                flat[key] = value
            else:
                raise ValueError(f"unknown matcher option {key!r}; valid: {', '.join(sorted(top))} "
                                 f"(or section__field for {', '.join(sorted(sections))})")
        for sec, vals in by_section.items():
            flat[sec] = _replace_nested(getattr(base, sec), vals)
        return replace(base, **flat)

    @property
    def verify_model(self) -> Literal["homography", "fundamental"]:
        """The model that counts verified matches (`verify` with "auto" resolved)."""
        if self.verify != "auto":
            return self.verify
        return "homography" if self.final_homography else "fundamental"


@cache
def field_docs(cls: type) -> dict[str, str]:
    """{field name: its docstring} of a dataclass whose fields are documented by the string
    literal right below them (attribute docstrings, as in this module); inherited fields
    included, the subclass's text winning. Fields without one are absent."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass) or klass is object:
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for node, nxt in zip(body, body[1:], strict=False):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
                    and isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                    and isinstance(nxt.value.value, str)):
                docs[node.target.id] = inspect.cleandoc(nxt.value.value)
    return docs
