"""Which pairs of a scene get view simulation: the second pass of `match.simulate = "needed"`.

The match stage's first pass matches every pair's unwarped originals only (the extra-affine
matcher with `simulate=False`: about stock COLMAP's cost). Most pairs of a real capture are then
solved; view simulation (the coarse search, the fine views, the escalation) pays only where the
originals leave a pair weak *and* the scene needs that pair. The strong pairs (at least
`strong_inliers` verified matches) form a graph on the images; a weak pair is simulated when

- either of its images has fewer than `min_partners` strong partners (the image hangs on few or
  no pairs: its registration and the triangulation of its points rest on the weak ones), and
  the pair is among that image's most promising weak pairs, or
- its images lie in different connected components of the strong graph (the pair may be the
  only bridge between two parts of the scene), and it is among the most promising pairs out of
  one of them.

The first kind carries an image's registration and gets the full matcher; the second, when both
its images have `min_partners` strong partners, only joins parts that their strong pairs already
reconstruct, and is marked `bridge` so that the match stage can give it a cheaper matcher
(`MatchConfig.simulate_bridges`). A weak pair between two well-connected images of one
component is left with its first-pass matches: the scene registers and triangulates through its
strong pairs, and simulating it costs 1-3 s per pair (most such pairs of an exhaustive selection
do not overlap at all). A scene of only extreme pairs (no strong graph) simulates every pair
when it is small (each image's 2 x `min_partners` most promising pairs: all of a 4-view scene's),
and a few per image when it is large.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class ScheduleConfig:
    """Thresholds of the second-pass selection (`pairs_to_simulate`)."""

    strong_inliers: int = 100
    """A pair whose first pass verified at least this many matches is strong (a graph edge)."""
    min_partners: int = 2
    """A weak pair is simulated when one of its images has fewer strong partners than this (and
    it is among that image's 2 x (this - partners) most promising weak pairs); also the number of
    pairs simulated out of each part of the strong graph."""


@dataclass(frozen=True)
class SimulationChoice:
    """One weak pair's second-pass decision and why."""

    index: int
    """The pair's index in the stage's pair list."""
    simulate: bool
    reason: str
    bridge: bool = False
    """Simulated only as a bridge between parts of the strong graph, both images having
    `min_partners` strong partners: the match stage may give it a cheaper matcher
    (`MatchConfig.simulate_bridges`)."""


def components(names: Sequence[str], edges: Sequence[tuple[str, str]]) -> dict[str, int]:
    """Connected-component id of every image under `edges` (union-find; ids are the smallest
    index in `names` of the component, so they do not depend on the edge order)."""
    index = {n: i for i, n in enumerate(names)}
    parent = list(range(len(names)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in edges:
        ra, rb = find(index[a]), find(index[b])
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    return {n: find(i) for n, i in index.items()}


def pairs_to_simulate(names: Sequence[str], pairs: Sequence[tuple[str, str]], verified: Sequence[int],
                      cfg: ScheduleConfig, first: int = 0) -> list[SimulationChoice]:
    """The decision for every weak pair (fewer than `cfg.strong_inliers` first-pass `verified`
    matches) from index `first` on, in pair order (module doc); strong pairs are not listed. The
    pairs before `first` (matched earlier, e.g. before a match-graph expansion round) count in
    the strong graph but are not decided again.

    Bounded so that the simulated pairs grow linearly with the images (at most 3 x
    `min_partners` per image): an image short of `min_partners` strong partners by d gets its 2d
    most promising weak pairs simulated (most first-pass matches first, then pair order), not
    all of them; a pair between two parts of the strong graph is simulated while either part has
    had fewer than `min_partners` such pairs simulated."""
    strong = [p for p, n in zip(pairs, verified) if n >= cfg.strong_inliers]
    degree = {n: 0 for n in names}
    for a, b in strong:
        degree[a] += 1
        degree[b] += 1
    comp = components(names, strong)
    weak = sorted((i for i, n in enumerate(verified) if n < cfg.strong_inliers and i >= first),
                  key=lambda i: (-verified[i], i))
    reasons: dict[int, str] = {}
    taken = {n: 0 for n in names}
    for i in weak:  # images short of strong partners: their most promising weak pairs
        a, b = pairs[i]
        short = [x for x in (a, b) if taken[x] < 2 * (cfg.min_partners - degree[x])]
        if short:
            for x in short:
                taken[x] += 1
            why = ", ".join(f"{x} has {degree[x]}" for x in short)
            reasons[i] = f"{why} strong partners (< {cfg.min_partners})"
    bridges = dict.fromkeys(comp.values(), 0)
    bridged: set[int] = set()
    for i in weak:  # each part of the strong graph: its most promising pairs to other parts
        a, b = pairs[i]
        if comp[a] == comp[b] or i in reasons:
            continue
        if bridges[comp[a]] < cfg.min_partners or bridges[comp[b]] < cfg.min_partners:
            bridges[comp[a]] += 1
            bridges[comp[b]] += 1
            reasons[i] = "the images are in different parts of the strong pair graph"
            if min(degree[a], degree[b]) >= cfg.min_partners:  # an image short of partners: not only a bridge
                bridged.add(i)
    out = []
    for i in sorted(weak):
        head = f"{verified[i]} first-pass matches (< {cfg.strong_inliers})"
        if i in reasons:
            out.append(SimulationChoice(i, True, f"{head}; {reasons[i]} -> simulated", bridge=i in bridged))
        else:
            out.append(SimulationChoice(i, False, f"{head}; its images have enough strong partners or better "
                                                   "candidates -> not simulated"))
    return out
