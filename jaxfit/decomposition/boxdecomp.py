"""BoxDecomposition (Hübner & Kragic 2008), the first step of the PSDA (THESIS.md section 5):
a cloud (N, 3) split into boxes whose leaves are the object's parts.

The root is the minimum-volume bounding box (MVBB, ``mvbb``) of all points. A box is
split by a plane orthogonal to one of its axes, at one of several fractions along it; the
cut whose two halves have the smallest total MVBB volume is kept if it saves enough
volume (``gain``, against the parent's volume or, with ``reference="root"``, the root's)
and both halves keep ``min_points`` points. The halves are split in turn; the boxes that
are not split are the leaves.

Departures, so the cuts fall on the junctions between parts: cuts are tried across the
box's axes *and* its points' principal axes; the best grid cuts also slide to the
smallest halves nearby (``_slide``); among near ties (``CUT_TIE``) the cut crossing
clearly fewer points (``CUT_BAND``, ``CUT_NARROWER``) wins. The MVBB is the hull-face
heuristic of ``trimesh.bounds.oriented_bounds``, vectorised, on exact face normals, and
never larger than the axis-aligned or principal box.

Measurements and the cases behind each choice: docs/decomposition.md.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ..shapes import Box
from ..shapes.box import canonical_rotation

__all__ = ["DEFAULT_CUTS", "BoxNode", "BoxTree", "box_volume", "decompose_boxes", "mvbb",
           "volume_floor"]

#: Fractions along a box's axes (and its points' principal axes) where cut planes are
#: tried first: 0.1, 0.15, ..., 0.9. The best of them then slide (see ``_slide``).
DEFAULT_CUTS = tuple(round(0.1 + 0.05 * i, 2) for i in range(17))
#: Extents of thin boxes are floored at this fraction of the root's largest extent when
#: volumes are compared, so a flat part has a small positive volume instead of zero.
VOLUME_FLOOR = 1e-3
#: Candidate cuts are ranked on at most this many points of the box; the chosen halves
#: get MVBBs of all their points.
RANKING_POINTS = 2000
#: Cuts with the best volume bounds that are re-ranked by their halves' MVBBs.
RERANKED_CUTS = 4
#: Re-ranked cuts whose halves' total volume is within this fraction of the box's volume
#: of the smallest tie; among them the one with the fewest points within ``CUT_BAND``
#: of its span of its plane wins if that is at most ``CUT_NARROWER`` times the count of
#: the cut with the smallest halves (see ``_best_cut``).
CUT_TIE = 0.01
CUT_BAND = 0.02
CUT_NARROWER = 0.5
# Relative singular value under which a cloud counts as flat (or a line).
_FLAT = 1e-9
#: Hull face normals that get the exact rectangle search in ``mvbb`` (the most promising
#: ones by a volume lower bound) ...
MAX_DIRECTIONS = 128
#: ... and in the cheaper MVBBs that rank candidate cuts.
RANKING_DIRECTIONS = 16
#: Hull vertices the frame search of an MVBB uses at most (an even subset beyond that).
MAX_HULL_VERTICES = 500
# Distinct hull normals considered at most (see _hull_frame).
_MAX_NORMALS = 1024
# Vertex-edge projections per block of directions, to bound memory on large hulls.
_BLOCK = 1 << 20


# ----- minimum-volume bounding box ----------------------------------------------------------
def mvbb(points, *, min_extent: float | None = None) -> Box:
    """Minimum-volume oriented bounding box of a point cloud.

    Parameters
    ----------
    points : (N, 3) array_like
        N >= 1 finite points.
    min_extent : float, optional
        Floor on every extent, so flat, collinear or single-point input gives a thin box
        rather than a zero one. Default: 1e-6 times the largest extent (1e-12 if all
        points coincide).

    Returns
    -------
    box : jaxfit.Box
        ``center`` (3,), ``rotation`` (3, 3) with the box axes as columns (proper, the
        first two columns with their largest component positive), ``extents`` (3,) full
        side lengths. It contains every point.
    """
    rotation, center, extents = _mvbb_frame(_as_cloud(points))
    floor = min_extent if min_extent is not None else max(1e-6 * extents.max(), 1e-12)
    return _make_box(rotation, center, np.maximum(extents, floor))


def _as_cloud(points) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"points must have shape (N, 3) with N >= 1, got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points contain NaN or inf")
    return pts


def _make_box(rotation, center, extents) -> Box:
    # The Box sign rule: flipping an axis leaves the box unchanged.
    return Box(center, canonical_rotation(rotation), extents)


def _fit_frame(points, rotation):
    """Centre (3,) and extents (3,) of the tightest box with axes ``rotation`` (3, 3)."""
    local = points @ rotation
    lo, hi = local.min(axis=0), local.max(axis=0)
    return rotation @ (0.5 * (lo + hi)), hi - lo


def _principal_axes(centred):
    """Rotation (3, 3) of the principal axes (columns) and singular values (3,)."""
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    s = np.pad(s, (0, 3 - len(s)))
    r = vt.T if vt.shape[0] == 3 else np.linalg.qr(np.c_[vt.T, np.eye(3)])[0][:, :3]
    if np.linalg.det(r) < 0:
        r[:, 2] = -r[:, 2]
    return r, s


def _mvbb_frame(points, max_directions=None):
    """(rotation (3, 3), centre (3,), extents (3,)) of the MVBB of points (N, 3)."""
    from scipy.spatial import ConvexHull, QhullError  # lazily: 0.3 s of import
    origin = points.mean(axis=0)
    centred = points - origin  # better conditioned hull and projections
    axes, s = _principal_axes(centred)
    candidates = [np.eye(3), axes]
    flat = len(points) < 4 or s[2] <= _FLAT * s[0]
    if not flat:
        try:
            hull = ConvexHull(centred)
            centred = centred[hull.vertices]  # the same boxes, from far fewer points
            if len(centred) > MAX_HULL_VERTICES:
                # The frame is searched on an even subset of the hull's vertices; the
                # extents below still come from all of them.
                stride = -(-len(centred) // MAX_HULL_VERTICES)
                hull = ConvexHull(centred[::stride])
            candidates.append(_hull_frame(hull, max_directions or MAX_DIRECTIONS))
        except QhullError:
            flat = True  # flatter than the singular values showed
    if flat and s[1] > _FLAT * s[0]:
        try:
            candidates.append(_flat_frame(centred, axes))
        except QhullError:
            pass  # collinear after all: the principal frame is the answer

    def volume(rotation):
        # Floored, so that flat candidates are compared by their area.
        extents = _fit_frame(centred, rotation)[1]
        return np.prod(np.maximum(extents, 1e-6 * extents.max()))

    best = min(candidates, key=volume)
    center, extents = _fit_frame(centred, best)
    return best, center + origin, extents


def _flat_frame(centred, axes):
    """Frame of the minimum-area rectangle of a planar cloud, the plane normal third."""
    from scipy.spatial import ConvexHull  # lazily: 0.3 s of import
    flat = centred @ axes[:, :2]
    hull = flat[ConvexHull(flat).vertices]
    edges = np.roll(hull, -1, axis=0) - hull
    u = edges / np.linalg.norm(edges, axis=1, keepdims=True)
    w = np.c_[-u[:, 1], u[:, 0]]
    area = np.ptp(hull @ u.T, axis=0) * np.ptp(hull @ w.T, axis=0)
    k = int(np.argmin(area))
    x = axes[:, :2] @ u[k]
    return np.c_[x, np.cross(axes[:, 2], x), axes[:, 2]]


def _hull_frame(hull, max_directions):
    """Best frame (3, 3) with one axis along a hull face normal and one along the
    projection of a silhouette edge for that normal (a side of the 2-D rectangle).

    Only the ``max_directions`` normals with the smallest lower bound on their box
    volume (height times the hull's shadow area, which the rectangle exceeds by a factor
    between 1 and 2) get the exact rectangle search.
    """
    centred = hull.points
    verts = centred[hull.vertices]
    normals = hull.equations[:, :3]  # (F, 3) unit, outward
    corners = centred[hull.simplices]
    areas = 0.5 * np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)

    # Distinct directions: n and -n give the same box; coplanar facets share a normal.
    flip = np.take_along_axis(normals, np.argmax(np.abs(normals), axis=1)[:, None], 1) < 0
    directions, group = np.unique(np.round(np.where(flip, -normals, normals), 9), axis=0,
                                  return_inverse=True)
    if len(directions) > _MAX_NORMALS:
        # A large hull is a finely curved one, where neighbouring normals give nearly the
        # same box: keep the directions with the most facet area (the flat sides).
        directions = directions[np.argsort(-np.bincount(group.ravel(), areas))[:_MAX_NORMALS]]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    heights = np.ptp(verts @ directions.T, axis=0)
    shadow = 0.5 * (areas @ np.abs(normals @ directions.T))  # area of the projected hull
    keep = np.argsort(heights * shadow)[:max_directions]
    return _best_rectangle(centred, hull, directions[keep], heights[keep])


def _best_rectangle(centred, hull, directions, heights):
    """Frame (3, 3) of the smallest box over ``directions`` (K, 3), each with its
    ``heights`` (K,), whose in-plane sides follow the projected silhouette edges.

    The projected hull is the polygon of silhouette edges, so each rectangle is measured
    on the silhouette vertices of its own direction only.
    """
    from scipy.spatial import QhullError  # lazily: 0.3 s of import
    # Hull edges from the facet adjacency: neighbours[i, j] is opposite vertex j of facet i.
    simplices, neighbours = hull.simplices, hull.neighbors
    facet, corner = np.nonzero(neighbours > np.arange(len(simplices))[:, None])
    other = neighbours[facet, corner]
    a = simplices[facet, (corner + 1) % 3]
    b = simplices[facet, (corner + 2) % 3]
    # Silhouette for a direction: one adjacent facet faces away from it, the other not.
    # Side-on facets (dot ~ 0) count as facing, so the loop runs along the far rim of
    # a side wall and never through it.
    front = hull.equations[:, :3] @ directions.T > -1e-10  # (F, K)
    silhouette = front[facet] != front[other]
    which, edge = np.nonzero(silhouette.T)  # grouped by direction
    d = directions[which]
    e = centred[b[edge]] - centred[a[edge]]
    u = e - np.sum(e * d, axis=1, keepdims=True) * d
    length = np.linalg.norm(u, axis=1)
    ok = length > 1e-12 * np.abs(centred).max()
    which, edge, u = which[ok], edge[ok], u[ok] / length[ok, None]
    if not len(which):
        raise QhullError("no hull edge is usable as a rectangle side")
    w = np.cross(directions[which], u)

    # Pad each direction's edges to a common count by repeating its last edge, so one
    # batched product measures every (direction, edge) rectangle.
    dirs, first, count = np.unique(which, return_index=True, return_counts=True)
    slots = first[:, None] + np.minimum(np.arange(count.max()), count[:, None] - 1)
    ends = np.c_[centred[a[edge]], centred[b[edge]]].reshape(-1, 2, 3)

    best, best_volume = None, np.inf
    step = max(1, _BLOCK // slots.shape[1] ** 2)
    for lo in range(0, len(dirs), step):
        s = slots[lo:lo + step]  # (k, E)
        pts = ends[s].reshape(len(s), -1, 3)  # (k, 2E, 3) the silhouette vertices
        width = np.ptp(pts @ u[s].transpose(0, 2, 1), axis=1)  # (k, E)
        depth = np.ptp(pts @ w[s].transpose(0, 2, 1), axis=1)
        volume = width * depth * heights[dirs[lo:lo + step], None]
        k, j = np.unravel_index(np.argmin(volume), volume.shape)
        if volume[k, j] < best_volume:
            best, best_volume = s[k, j], volume[k, j]
    return np.c_[u[best], w[best], directions[which[best]]]


# ----- the tree -------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class BoxNode:
    """One box of the hierarchy.

    box : jaxfit.Box
        MVBB of the node's points.
    indices : (M,) int array
        Indices of the node's points into the decomposed cloud, ascending.
    children : tuple of int
        Ids of the two halves; empty for a leaf.
    parent : int or None
        Id of the parent; None for the root.
    depth : int
        0 for the root.
    """

    box: Box
    indices: np.ndarray
    children: tuple[int, ...] = ()
    parent: int | None = None
    depth: int = 0

    @property
    def is_leaf(self) -> bool:
        return not self.children


@dataclasses.dataclass(frozen=True, eq=False)
class BoxTree:
    """Result of ``decompose_boxes``: ``nodes[0]`` is the root; a node's id is its index.

    nodes : tuple of BoxNode
        In breadth-first order (parents before children).
    gain, min_points, reference :
        The settings that produced the tree.
    """

    nodes: tuple[BoxNode, ...]
    gain: float
    min_points: int
    reference: str = "parent"

    @property
    def leaves(self) -> list[int]:
        """Ids of the leaves, in breadth-first order."""
        return [i for i, n in enumerate(self.nodes) if n.is_leaf]

    @property
    def leaf_boxes(self) -> list[Box]:
        """The parts: MVBBs of the leaves, in the order of ``leaves``."""
        return [self.nodes[i].box for i in self.leaves]

    def leaf_labels(self, num_points: int | None = None) -> np.ndarray:
        """(N,) position in ``leaves`` of the leaf that holds each point."""
        n = num_points if num_points is not None else len(self.nodes[0].indices)
        labels = np.full(n, -1, dtype=np.int64)
        for k, i in enumerate(self.leaves):
            labels[self.nodes[i].indices] = k
        return labels

    def to_dict(self) -> dict:
        """JSON-ready hierarchy: settings, leaf ids, and per node its id, parent,
        children, depth, point count, volume and box (``Box.to_dict``). Point indices
        are left out (they are as long as the cloud)."""
        nodes = [
            {
                "id": i,
                "parent": n.parent,
                "children": list(n.children),
                "depth": n.depth,
                "num_points": int(len(n.indices)),
                "volume": float(np.prod(n.box.extents)),
                "box": n.box.to_dict(),
            }
            for i, n in enumerate(self.nodes)
        ]
        return {"gain": self.gain, "min_points": self.min_points,
                "reference": self.reference, "leaves": self.leaves, "nodes": nodes}


# ----- decomposition ----------------------------------------------------------------------
def volume_floor(root: Box) -> float:
    """The floor on extents when volumes of boxes under ``root`` are compared."""
    return VOLUME_FLOOR * float(np.max(root.extents))


def box_volume(box: Box, floor: float) -> float:
    """Volume of ``box`` with every extent floored at ``floor``, so a flat part has a
    small positive volume instead of zero."""
    return float(np.prod(np.maximum(box.extents, floor)))


def decompose_boxes(points, *, gain: float = 0.96, min_points: int = 50, cuts=DEFAULT_CUTS,
                    reference: str = "parent", max_leaves: int | None = None,
                    root: Box | None = None) -> BoxTree:
    """Split a cloud into boxes by recursive MVBB splitting (Hübner & Kragic 2008).

    Parameters
    ----------
    points : (N, 3) array_like
        The object's surface points.
    gain : float, default 0.96
        A box is split when its best halves' total volume over its own volume is below
        ``gain`` (see ``reference``); higher values split more (thesis: 0.80 -> 1 box,
        0.96 -> 3-5 boxes).
    min_points : int, default 50
        Each half of a split keeps at least this many points; cuts that leave fewer on
        one side are not considered.
    cuts : sequence of float, default ``DEFAULT_CUTS`` (0.1, 0.15, ..., 0.9)
        Fractions of the span along each box axis and each principal axis of the box's
        points where cut planes are tried, in (0, 1); the best cuts may then slide by up
        to the widest gap between neighbouring fractions.
    reference : {"parent", "root"}, default "parent"
        What the saved volume is measured against. "parent": split when
        ``V(c1) + V(c2) < gain * V(parent)``. "root": split when the split saves more
        than ``(1 - gain) * V(root)``, so small boxes are only split for a saving that
        matters for the whole object. Surface points make every curved open patch split
        well under any parent-relative gain (halving an arc quarters its box), so
        "parent" splits curved objects into many boxes; "root" stops at the main parts.
    max_leaves : int, optional
        Stop splitting (in breadth-first order) once the tree has this many leaves.
    root : jaxfit.Box, optional
        ``mvbb(points)`` when the caller has it already (it is not checked).

    Returns
    -------
    tree : BoxTree
        Every input index is in exactly one leaf. The split tried at a box depends only
        on the box's points, so a higher ``gain`` only adds splits below the same boxes.

    Notes
    -----
    Every cut that leaves ``min_points`` on both sides is first ranked by a cheap upper
    bound of its halves' volumes (the smaller of their boxes in the parent's frame and in
    their principal frames, on at most ``RANKING_POINTS`` points); the best
    ``RERANKED_CUTS``, each as it is and slid to the smallest halves' boxes within a grid
    step (``_slide``, on all the box's points), are re-ranked by their halves' MVBBs, and
    the winner's halves get exact MVBBs for the gain test.
    """
    pts = _as_cloud(points)
    if not 0 < gain:
        raise ValueError(f"gain must be positive, got {gain}")
    if isinstance(min_points, bool) or int(min_points) != min_points or min_points < 1:
        raise ValueError(f"min_points must be an integer >= 1, got {min_points!r}")
    fractions = np.asarray(cuts, dtype=np.float64).ravel()
    if fractions.size == 0 or np.any((fractions <= 0) | (fractions >= 1)):
        raise ValueError(f"cuts must be fractions strictly between 0 and 1, got {cuts!r}")
    if reference not in ("parent", "root"):
        raise ValueError(f"reference must be 'parent' or 'root', got {reference!r}")
    if max_leaves is not None and (isinstance(max_leaves, bool) or int(max_leaves) != max_leaves
                                   or max_leaves < 1):
        raise ValueError(f"max_leaves must be an integer >= 1, got {max_leaves!r}")

    root = mvbb(pts) if root is None else root
    floor = volume_floor(root)
    volume = functools.partial(box_volume, floor=floor)

    # Breadth-first; each entry is [box, indices, children, parent, depth].
    nodes = [[root, np.arange(len(pts)), (), None, 0]]
    i, leaves = 0, 1
    while i < len(nodes) and (max_leaves is None or leaves < max_leaves):
        box, idx, _, _, depth = nodes[i]
        halves = _best_cut(pts, idx, box, fractions, int(min_points), floor)
        if halves is not None:
            boxes = [mvbb(pts[h]) for h in halves]
            saved = volume(box) - sum(map(volume, boxes))
            if saved > (1.0 - gain) * volume(box if reference == "parent" else root):
                nodes[i][2] = (len(nodes), len(nodes) + 1)
                nodes += [[b, h, (), i, depth + 1] for b, h in zip(boxes, halves, strict=True)]
                leaves += 1
        i += 1
    return BoxTree(tuple(BoxNode(*n) for n in nodes), float(gain), int(min_points), reference)


def _best_cut(points, idx, box, fractions, min_points, floor):
    """The halves (two ascending index arrays) of ``idx`` with the smallest total MVBB
    volume, among the cuts that leave ``min_points`` on both sides; None if there is no
    such cut. Cuts are tried across the three axes of ``box`` and the three principal
    axes of its points, at ``fractions`` of the points' span, each of the best then slid
    to the best place between its neighbouring fractions (``_slide``)."""
    if len(idx) < 2 * min_points:
        return None
    local = (points[idx] - box.center) @ box.rotation  # (M, 3) in the box frame
    # The MVBB of a body of revolution can lie tilted (a ball on a stick, a shade on a
    # post): its axes then cross the junctions at an angle, the principal axes do not.
    directions = np.c_[np.eye(3), _principal_axes(local - local.mean(axis=0))[0]]  # (3, 6)
    coords = local @ directions
    lo, hi = coords.min(axis=0), coords.max(axis=0)  # (6,) spans of the 6 directions
    planes = lo[:, None] + fractions[None, :] * (hi - lo)[:, None]  # (6, K)
    below = np.stack([np.searchsorted(np.sort(c), p) for c, p in zip(coords.T, planes,
                                                                      strict=True)])
    axis, k = np.nonzero((below >= min_points) & (len(idx) - below >= min_points))
    if not len(axis):
        return None

    # An even stride (not a random draw), so the ranking depends only on the box's
    # points: then a higher gain only adds splits below the same boxes.
    stride = -(-len(idx) // RANKING_POINTS)  # ceil
    sample, along = local[::stride], coords[::stride]
    bound = _split_bounds(sample, along[:, axis] < planes[axis, k], floor)
    top = np.argsort(bound, kind="stable")[:RERANKED_CUTS]
    # Each of the best grid cuts also slides to the best place near it, so it can land
    # on a junction between the grid's planes; both compete in the exact re-ranking, so
    # a slide the halves' MVBBs do not confirm is not taken. The widest gap between
    # neighbouring fractions bounds the slide (the whole span for a single fraction).
    gap = np.diff(np.sort(fractions)).max() if fractions.size > 1 else 1.0
    cuts = {}
    for c in top:
        d, plane = axis[c], planes[axis[c], k[c]]
        # Directions 0-2 measure volumes in the box's frame, 3-5 in the principal one.
        slid = _slide(coords[:, d // 3 * 3:d // 3 * 3 + 3], coords[:, d], plane,
                      (hi - lo)[d] * gap, min_points, floor)
        cuts.update(dict.fromkeys([(d, plane), (d, slid)]))
    totals = np.array([_mvbb_volume(sample[along[:, d] < p], floor)
                       + _mvbb_volume(sample[along[:, d] >= p], floor) for d, p in cuts])
    # Along one direction the halves' volumes place the cut (and the slide lands it on
    # a junction). Between directions, cuts whose halves are about as small tie, and the
    # one crossing the fewest points wins (the narrowest cross-section: a junction). A
    # surface crossed by the plane has points on both sides of it, a face lying in it
    # (a base's top under a post) on one only, so the smaller side counts.
    keys = list(cuts)
    parallel = np.abs(directions.T @ directions) > 0.99  # (6, 6)
    best = [c for c, (d, _) in enumerate(keys)
            if all(totals[c] <= totals[o] for o, (e, _) in enumerate(keys) if parallel[d, e])]
    band = CUT_BAND * (hi - lo)

    def crossing(c):
        d, plane = keys[c]
        a, w = along[:, d], band[d]
        return min(np.sum((a >= plane - w) & (a < plane)), np.sum((a >= plane) & (a < plane + w)))

    tied = [c for c in best if totals[c] <= totals.min() + CUT_TIE * box_volume(box, floor)]
    # A crossing count differs by noise between similar cuts: only a clearly narrower
    # cut overrides the smallest halves.
    first = int(np.argmin(totals))
    narrow = min(tied, key=lambda c: (crossing(c), totals[c]))
    d, plane = keys[narrow if crossing(narrow) <= CUT_NARROWER * crossing(first) else first]
    lower = coords[:, d] < plane
    return idx[lower], idx[~lower]


def _split_bounds(sample, below, floor) -> np.ndarray:
    """Upper bounds (C,) on the total MVBB volume of the two halves of C cuts of the
    sample (S, 3), given by which points lie below each cut (S, C)."""
    return _bound_volumes(sample, below, floor) + _bound_volumes(sample, ~below, floor)


def _slide(frame, along, plane, step, min_points, floor) -> float:
    """The position of a cut within ``step`` of ``plane`` whose halves have the smallest
    total box volume in ``frame`` (M, 3), the box's points in the frame of the cut's
    direction; ``along`` (M,) are their coordinates along it. Every split between two
    consecutive distinct coordinates that leaves ``min_points`` on both sides is tried.

    A cut that leaves a sliver of one part in its neighbour's half costs the
    neighbour's whole cross-section per unit of sliver, so the best place is the
    junction itself, wherever it falls between the grid's planes. Sorted along the
    cut, the halves are a prefix and a suffix, so running minima and maxima give every
    split's boxes at once.
    """
    order = np.argsort(along, kind="stable")
    values, pts = along[order], frame[order]
    first = np.maximum.accumulate(pts) - np.minimum.accumulate(pts)  # prefix extents
    last = (np.maximum.accumulate(pts[::-1]) - np.minimum.accumulate(pts[::-1]))[::-1]
    i = np.arange(max(min_points, 1), len(values) - max(min_points, 1) + 1)  # below = i
    middle = 0.5 * (values[i - 1] + values[i])
    ok = (values[i - 1] < values[i]) & (np.abs(middle - plane) < step)
    if not ok.any():
        return plane
    i, middle = i[ok], middle[ok]
    volume = (np.prod(np.maximum(first[i - 1], floor), axis=1)
              + np.prod(np.maximum(last[i], floor), axis=1))
    return float(middle[int(np.argmin(volume))])


def _bound_volumes(points, member, floor) -> np.ndarray:
    """Upper bounds (C,) on the MVBB volumes of C subsets of points (S, 3) given by the
    columns of ``member`` (S, C): the smaller floored volume of the subset's box in the
    given frame and in its principal frame; 0 for an empty subset."""
    count = member.sum(axis=0)
    weights = member / np.maximum(count, 1)
    mean = weights.T @ points  # (C, 3)
    outer = (points[:, :, None] * points[:, None, :]).reshape(len(points), 9)
    scatter = (weights.T @ outer).reshape(-1, 3, 3) - mean[:, :, None] * mean[:, None, :]
    _, axes = np.linalg.eigh(scatter)  # (C, 3, 3), columns are the principal axes
    # One coordinate at a time over a contiguous (C, S) mask: masked (S, C, 3) blocks
    # had been 90 % of this function (the same maxima and minima: they are exact).
    inside = np.ascontiguousarray(member.T)  # (C, S)
    principal = np.moveaxis(points @ axes, 2, 0)  # (3, C, S)
    volumes = []
    for coords in (points.T, principal):  # coordinate j of every point: (S,) or (C, S)
        extents = np.stack([np.where(inside, c, -np.inf).max(axis=1)
                            - np.where(inside, c, np.inf).min(axis=1) for c in coords],
                           axis=1)  # (C, 3)
        volumes.append(np.prod(np.maximum(extents, floor), axis=1))
    return np.where(count > 0, np.minimum(*volumes), 0.0)


def _mvbb_volume(points, floor) -> float:
    """Floored MVBB volume of points (M, 3), with the cheaper direction search used for
    ranking; 0 for an empty set (a sampled side can be empty when the full one is not)."""
    if len(points) == 0:
        return 0.0
    _, _, extents = _mvbb_frame(points, RANKING_DIRECTIONS)
    return float(np.prod(np.maximum(extents, floor)))
