"""``decompose(method="measured")``: parts found where a cut improves the two-sided score
most (issue 17; docs/decomposition.md has the measurements).

The object starts as one part, its best primitive by the two-sided score
(``measure.Scorer``: the points' mean distance to the primitive plus the mean distance
of the primitive's surface to the object's points, so a primitive reaching beyond its
points loses by itself). The score of a set of parts is the points-weighted sum of their
scores, in units of the object's diagonal. Then, greedily:

1. Every part not yet searched gets candidate cuts (``cuts``): planes across its
   principal axes and the axes of its bounding box at ``FRACTIONS`` of its span, and at
   its necks and steps (``necks``: where the cross-section along an axis has a local
   minimum, or changes sharply between neighbouring slabs).
   Every half of every cut of every part searched in the round is fitted with every
   primitive in one ``fit_batch`` call per primitive (hundreds of (half, primitive) fits
   per call), each half on at most ``SEARCH_POINTS`` points; its best primitive, by the
   two-sided score, is its score. A part's best split is its cut with the lowest sum of
   its halves' weighted scores.
2. The part whose best split lowers the score most is split, unless that lowers it by
   less than ``SPLIT_MARGIN`` of the diagonal or the parts number ``max_parts``.

Each split is a node of the split hierarchy (a ``BoxTree``: each node's points, their
MVBB, the two halves), so one run gives the decomposition for every part count from 1 to
the last (``Decomposition.levels``). The parts of the last level are fitted again as the
thesis fits its leaves (``MAX_FIT_POINTS`` points, every primitive, the MVBB too) and
the lowest two-sided score wins; there are no plausibility or hollow-part gates: the
surface side of the score does their work.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import numpy as np

from ..engine import fit_batch
from ..shapes import Box
from .boxdecomp import BoxNode, BoxTree, _principal_axes, mvbb
from .measure import SPLIT_MARGIN, Scorer
from .parts import MAX_FIT_POINTS, Candidate, Part, SharedNormals, _grown, _threshold, fits

__all__ = ["MAX_PARTS", "SPLIT_MARGIN", "FRACTIONS", "split_greedily", "cuts", "necks"]

#: Parts at most when ``max_parts`` is not given.
MAX_PARTS = 8
#: Positions of the cuts tried along each axis, as fractions of the part's span.
FRACTIONS = (0.25, 0.5, 0.75)
#: Slabs along an axis whose cross-sections are compared to find necks.
SLABS = 16
#: A neck: a slab whose cross-section is at most this fraction of the largest
#: cross-section on each side of it.
NECK = 0.7
#: Cuts tried per part at most (each gives two halves to fit).
MAX_CUTS = 48
#: Necks kept per axis (the narrowest).
NECKS_PER_AXIS = 2
#: Points of a candidate half given to RANSAC, and its hypotheses: the search only ranks
#: the cuts; the parts that remain are fitted again in full.
SEARCH_POINTS = 1024
SEARCH_HYPOTHESES = 1024
#: Neighbours of a point (itself included) that make two parts adjacent when they differ.
ADJACENT = 6
#: Axes closer than this (|cos|) to one already tried are not tried again.
SAME_AXIS = 0.97


@dataclasses.dataclass
class _Node:
    """A part of the greedy: its points, its best candidate and score, and (once
    searched) its best split (two index arrays, their candidates) and its gain."""

    indices: np.ndarray
    name: str
    candidate: Candidate
    parent: int | None = None
    depth: int = 0
    children: tuple[int, ...] = ()
    split: tuple | None = None
    gain: float = -np.inf


def split_greedily(points, whole: Part, *, classes, scorer: Scorer, min_points: int,
                   max_parts, threshold_fraction, key, seed, say, started):
    """The measured method on points (N, 3) from the whole object's part ``whole``
    (``psda._whole_object``). Returns (the last level's parts, the split hierarchy as a
    ``BoxTree``, the levels: a tuple of part tuples, one per part count)."""
    limit = MAX_PARTS if max_parts is None else int(max_parts)
    total = len(points)
    nodes = [_Node(whole.indices, whole.winner, whole.candidates[whole.winner])]
    alive, history = [0], [[0]]
    rng = np.random.default_rng(seed)
    for round_ in range(limit - 1):
        pending = [i for i in alive if nodes[i].split is None]
        if pending:
            _search(points, nodes, pending, classes=classes, scorer=scorer, total=total,
                    min_points=min_points, threshold_fraction=threshold_fraction,
                    key=_checks_seed(key) + round_, rng=rng)
        best = max(alive, key=lambda i: nodes[i].gain)
        say(f"round {round_}: best split gains {nodes[best].gain:.4f} of the diagonal "
            f"({time.perf_counter() - started:.2f} s)")
        if not nodes[best].gain >= SPLIT_MARGIN:
            break
        node = nodes[best]
        first = len(nodes)
        for half, (name, candidate) in zip(_reassigned(points, node, scorer), node.split[1],
                                           strict=True):
            mean, _, surface = _two(scorer, candidate.model, points[half])
            nodes.append(_Node(half, name, dataclasses.replace(candidate, mean_distance=mean),
                               best, node.depth + 1))
        node.children = (first, first + 1)
        alive = [i for i in alive if i != best] + [first, first + 1]
        history.append(sorted(alive))
    # (the root's box is the whole object's MVBB, computed once by decompose)
    tree = BoxTree(tuple(BoxNode(whole.box if k == 0 else mvbb(points[n.indices]), n.indices,
                                 n.children, n.parent, n.depth) for k, n in enumerate(nodes)),
                   0.0, int(min_points), "measured")
    fit = functools.partial(_fit_groups, points, classes=classes, scorer=scorer,
                            threshold_fraction=threshold_fraction, key=key, seed=seed)
    final = fit([tree.nodes[i].indices for i in history[-1]],
                [tree.nodes[i].box for i in history[-1]])
    by_node = dict(zip(history[-1], final, strict=True))
    final = _merged(points, final, scorer, fit)
    final = _reassigned_all(points, final, fit, threshold_fraction, min_points)
    levels = [tuple(by_node.get(i) or _as_part(tree.nodes[i], nodes[i]) for i in level)
              for level in history[:len(final) - 1]]
    levels.append(tuple(final))
    say(f"measured: {len(final)} parts ({time.perf_counter() - started:.2f} s)")
    return tuple(final), tree, tuple(levels)


def _reassigned(points, node: _Node, scorer: Scorer) -> tuple[np.ndarray, np.ndarray]:
    """The split node's points given each to the nearer of its halves' primitives, so a
    cut that missed the junction leaves no sliver of one half in the other; the halves
    of the cut stand where a side would keep fewer than a tenth of its points."""
    a, b = (candidate.model for _, candidate in node.split[1])
    idx = node.indices
    first = a.distance(points[idx]) <= b.distance(points[idx])
    cut = node.split[0]
    if min(first.sum(), (~first).sum()) < 0.1 * min(cut[0].size, cut[1].size):
        return cut
    return idx[first], idx[~first]


def _checks_seed(key) -> int:
    from .. import _checks

    return _checks.numpy_seed(key)


def _as_part(node: BoxNode, found: _Node) -> Part:
    """A level's part from the greedy's fit of it (its search candidate)."""
    model = found.candidate.model
    return Part(node.indices, node.box, model.name, found.name, model,
                found.candidate.mean_distance, {found.name: found.candidate})


def _search(points, nodes, pending, *, classes, scorer, total, min_points,
            threshold_fraction, key, rng):
    """Give every node in ``pending`` its best split and its gain (the fall of the
    points-weighted two-sided score, over the diagonal); nodes without a cut that
    leaves ``min_points`` on both sides keep gain -inf."""
    halves, owner = [], []  # every candidate half, and (node, cut) it belongs to
    for i in pending:
        idx = nodes[i].indices
        for c, below in enumerate(cuts(points[idx], min_points)):
            halves += [idx[below], idx[~below]]
            owner += [(i, c), (i, c)]
    if not halves:
        return
    samples = [points[h] if h.size <= SEARCH_POINTS else
               points[h[rng.choice(h.size, SEARCH_POINTS, False)]] for h in halves]
    frames = [_frame_box(s) for s in samples]
    thresholds = [_threshold(b, threshold_fraction) for b in frames]
    best = [("mvbb", Candidate(b, *_two(scorer, b, s))) for b, s in zip(frames, samples,
                                                                         strict=True)]
    for cls in classes:
        results = fit_batch(samples, cls, thresholds=thresholds, key=key, skip_failures=True,
                            max_hypotheses=SEARCH_HYPOTHESES, final_refit=False)
        for k, (result, sample) in enumerate(zip(results, samples, strict=True)):
            if result is None:
                continue
            found = Candidate(result.model, *_two(scorer, result.model, sample))
            if found.two_sided < best[k][1].two_sided:
                best[k] = (cls.name, found)
    by_cut: dict[tuple[int, int], list[int]] = {}
    for k, o in enumerate(owner):
        by_cut.setdefault(o, []).append(k)
    for i in pending:
        node = nodes[i]
        before = node.indices.size / total * node.candidate.two_sided
        for (j, _), (a, b) in by_cut.items():
            if j != i:
                continue
            after = sum(halves[k].size / total * best[k][1].two_sided for k in (a, b))
            gain = (before - after) / scorer.diagonal
            if gain > node.gain:
                node.gain = gain
                node.split = ((halves[a], halves[b]), (best[a], best[b]))


def _two(scorer: Scorer, model, sample) -> tuple[float, float, float]:
    """(mean distance, overshoot 0, surface distance) of a candidate on a sample."""
    mean, surface = scorer.score(model, sample)
    return mean, 0.0, surface


def _frame_box(cloud) -> Box:
    """The bounding box of ``cloud`` (M, 3) in its principal frame: a cheap stand-in for
    its MVBB while cuts are ranked."""
    from ..shapes.box import canonical_rotation

    centre = cloud.mean(axis=0)
    axes, _ = _principal_axes(cloud - centre)
    local = (cloud - centre) @ axes
    lo, hi = local.min(axis=0), local.max(axis=0)
    extents = np.maximum(hi - lo, 1e-9 * max(float((hi - lo).max()), 1e-300))
    return Box(centre + axes @ (0.5 * (lo + hi)), canonical_rotation(axes), extents)


def cuts(cloud, min_points: int) -> list[np.ndarray]:
    """Candidate cuts of a part's points (M, 3), each as the (M,) bool mask of the points
    below its plane: across the part's principal axes and the axes of its MVBB (one
    within ``SAME_AXIS`` of another is skipped), at the necks and steps (``necks``) and
    at ``FRACTIONS`` of the span; only cuts that leave ``min_points`` on both sides, at
    most ``MAX_CUTS`` (necks and steps first, then the middles, then the rest)."""
    if len(cloud) < 2 * min_points:
        return []
    centred = cloud - cloud.mean(axis=0)
    principal, _ = _principal_axes(centred)
    stride = -(-len(cloud) // 2048)
    axes = []
    for axis in np.c_[principal, mvbb(cloud[::stride]).rotation].T:
        if all(abs(float(axis @ other)) < SAME_AXIS for other in axes):
            axes.append(axis)
    ranked, seen = [], set()
    for axis in axes:
        along = centred @ axis
        lo, hi = np.quantile(along, [0.005, 0.995])
        # necks and steps first, then the middle, then the quarters
        planes = [(0, p) for p in necks(centred, axis, lo, hi)] + [
            (1 + abs(f - 0.5), lo + f * (hi - lo)) for f in FRACTIONS]
        for priority, plane in planes:
            below = along < plane
            count = int(below.sum())
            if min(count, len(cloud) - count) < min_points:
                continue
            signature = below.tobytes()
            if signature not in seen:
                seen.add(signature)
                ranked.append((priority, len(ranked), below))
    return [below for _, _, below in sorted(ranked, key=lambda r: r[:2])[:MAX_CUTS]]


def necks(centred, axis, lo: float, hi: float) -> list[float]:
    """Positions along ``axis`` (unit (3,)) of a part's necks and steps: of ``SLABS``
    slabs between ``lo`` and ``hi``, those whose cross-section (the area of their points'
    bounding rectangle across the axis) is a local minimum and at most ``NECK`` times the
    largest cross-section on each side (the ``NECKS_PER_AXIS`` narrowest, at the slab's
    centre), and the boundaries between neighbouring slabs whose cross-sections differ
    by more than that factor (the ``NECKS_PER_AXIS`` sharpest: a lid on a body, a spout
    out of its side, where no neck lies beyond)."""
    basis = np.linalg.svd(np.eye(3) - np.outer(axis, axis))[0][:, :2]  # (3, 2) across
    along, across = centred @ axis, centred @ basis
    edges = np.linspace(lo, hi, SLABS + 1)
    slab = np.clip(np.searchsorted(edges, along, side="right") - 1, 0, SLABS - 1)
    area = np.zeros(SLABS)
    for s in range(SLABS):
        inside = across[slab == s]
        if len(inside) > 1:
            area[s] = float(np.prod(np.ptp(inside, axis=0)))
    found, steps = [], []
    for s in range(1, SLABS - 1):
        left, right = area[:s].max(), area[s + 1:].max()
        if (area[s] <= area[s - 1] and area[s] <= area[s + 1]
                and area[s] <= NECK * min(left, right)):
            found.append((area[s] / min(left, right), 0.5 * (edges[s] + edges[s + 1])))
    for s in range(SLABS - 1):
        low, high = sorted((area[s], area[s + 1]))
        if high > 0 and low <= NECK * high:
            steps.append((low / high, edges[s + 1]))
    return ([position for _, position in sorted(found)[:NECKS_PER_AXIS]]
            + [position for _, position in sorted(steps)[:NECKS_PER_AXIS]])


def _merged(points, parts: list[Part], scorer: Scorer, fit) -> list[Part]:
    """Adjacent parts (some point's ``ADJACENT`` nearest neighbours lie in both) merged,
    pair by pair, while one primitive fits a pair's union about as well as the two
    (the union's points-weighted score at most ``SPLIT_MARGIN`` of the diagonal above
    theirs: the split between them would not have been made). A top-down cut can fall
    across a part (the lamp's post, cut by the first plane between base and shade), and
    its two pieces are each explained again; this puts them back together. ``fit``
    fits index groups (``_fit_groups``)."""
    parts = list(parts)
    total = len(points)
    near = scorer.tree.query(points[::-(-total // 4096)], k=ADJACENT)[1]
    tried: dict[bytes, Part] = {}
    while len(parts) > 1:
        labels = np.full(total, -1)
        for k, part in enumerate(parts):
            labels[part.indices] = k
        linked = labels[near]
        pairs = sorted({(int(a), int(b)) for a, b in
                        zip(linked[:, :1].repeat(ADJACENT - 1, 1).ravel(),
                            linked[:, 1:].ravel(), strict=True) if a < b})
        unions = [np.union1d(parts[a].indices, parts[b].indices) for a, b in pairs]
        fresh = [u for u in unions if u.tobytes() not in tried]
        if fresh:
            tried.update(zip((u.tobytes() for u in fresh), fit(fresh), strict=True))
        best, excess = None, np.inf
        for (a, b), union in zip(pairs, unions, strict=True):
            whole = tried[union.tobytes()]
            cost = (union.size * _score(whole) - parts[a].indices.size * _score(parts[a])
                    - parts[b].indices.size * _score(parts[b])) / total / scorer.diagonal
            if cost < excess:
                best, excess = (a, b, whole), cost
        if best is None or excess > SPLIT_MARGIN:
            return parts
        a, b, whole = best
        parts = [p for k, p in enumerate(parts) if k not in (a, b)] + [whole]
    return parts


def _reassigned_all(points, parts: list[Part], fit, threshold_fraction,
                    min_points: int) -> list[Part]:
    """One round of the thesis's reassignment on the last level: every point to the part
    whose primitive (cylinders and cones first grown along their surface, ``_grown``)
    is nearest, the parts that changed fitted again; kept if the points-weighted
    two-sided score falls and every part keeps ``min_points`` // 2 points. The split
    planes need not fall on the junctions; this moves them there and regrows a post
    that a cut shortened."""
    if len(parts) < 2:
        return parts
    models = [_grown(p.model, points, _threshold(p.box, threshold_fraction)) for p in parts]
    owner = np.argmin(np.stack([m.distance(points) for m in models]), axis=0)
    groups = [np.flatnonzero(owner == k) for k in range(len(parts))]
    if min(g.size for g in groups) < max(1, min_points // 2):
        return parts
    changed = [k for k, (g, p) in enumerate(zip(groups, parts, strict=True))
               if not np.array_equal(g, p.indices)]
    if not changed:
        return parts
    fresh = dict(zip(changed, fit([groups[k] for k in changed]), strict=True))
    candidate = [fresh.get(k, p) for k, p in enumerate(parts)]

    def total(ps):
        return sum(p.indices.size * _score(p) for p in ps)

    return candidate if total(candidate) < total(parts) else parts


def _score(part: Part) -> float:
    return part.candidates[part.winner].two_sided


def _fit_groups(points, groups, boxes=None, *, classes, scorer: Scorer, threshold_fraction,
                key, seed) -> list[Part]:
    """Parts for index groups, fitted as the thesis fits its leaves (every primitive, one
    ``fit_batch`` per primitive, ``MAX_FIT_POINTS`` points each), each candidate scored
    two-sided on all the part's points; the group's MVBB (``boxes``, or computed)
    competes; the lowest wins."""
    rng = np.random.default_rng(seed)
    clouds = [points[g] for g in groups]
    boxes = [mvbb(c) for c in clouds] if boxes is None else boxes
    samples = [c if len(c) <= MAX_FIT_POINTS else c[rng.choice(len(c), MAX_FIT_POINTS, False)]
               for c in clouds]
    thresholds = [_threshold(b, threshold_fraction) for b in boxes]
    found = [{"mvbb": Candidate(b, *_two(scorer, b, c))}
             for b, c in zip(boxes, clouds, strict=True)]
    shared = SharedNormals(samples)
    for cls in classes:
        results = fits(samples, cls, thresholds, key, shared.of(cls))
        for candidates, result, cloud in zip(found, results, clouds, strict=True):
            if result is not None:
                candidates[cls.name] = Candidate(result.model,
                                                 *_two(scorer, result.model, cloud))
    parts = []
    for group, box, candidates in zip(groups, boxes, found, strict=True):
        winner = min(candidates, key=lambda name: candidates[name].two_sided)
        model = candidates[winner].model
        parts.append(Part(group, box, model.name, winner, model,
                          candidates[winner].mean_distance, candidates))
    return parts
