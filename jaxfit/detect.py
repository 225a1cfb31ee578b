"""Scene detection: several primitives in one cloud (N, 3), found one after another.

``detect(points)`` repeats: fit every candidate shape, keep the best-supported one, take
its points out of the cloud, until no shape has ``min_inliers`` points of support. The
support of a fitted model (Schnabel, Wahl & Klein 2007, "Efficient RANSAC for point-cloud
shape detection") is the largest connected component of its *compatible* points: within
the fit's distance threshold of the model, with an estimated normal within ``max_angle``
of the model's surface normal there, and connected at a radius of ``connect`` times the
cloud's median nearest-neighbour spacing. The normal test keeps a plane from taking the
bottom rim of a cylinder standing on it; the connectivity keeps a plane from taking the
coplanar tops of two separate boxes.

One neighbour structure serves the whole call (``RadiusGraph``): the distinct points in
one KD-tree, every pair of them within the connectivity radius listed once (and held as
a sparse matrix, each pair once). The groups, the supports, the final assignment and
(when none are given) the normals, a PCA over each point's neighbours within that radius
(``normals.pair_normals``), all read it.

Each round works on *groups*: the connected components of the points still unassigned
(at the same radius). Objects resting on a floor fall apart into one group each once the
floor is taken. Every live group gives up at most one primitive per round: each shape is
fitted to every group at once (one ``jaxfit.fit_batch`` call per shape and round, group g
its cloud g, on at most ``fit_points`` of each group's points) and its support measured
on the whole group. Each group is searched in a loop of its own (``separate``): a round's
group count changes from scene to scene and round to round, and a batch compiles each
shape's kernel once per slot count it meets, where one cloud's kernel serves them all. A
group can only lose points to a primitive fitted inside it, so the groups of a round do
not interact. The candidates are fitted without LO-RANSAC
(``CANDIDATE_OPTIONS``); each group's winner is refitted instead, by a least-squares fit
on its support (``_polished``). Every shape's first batch is dispatched at the start of
the round; then the most complex shape is finished first, and a simpler one's search
stops once it would have found any model that could still matter (``_cap``).

Choice per group (deliberately simple): the candidate with the largest support wins; but
a more complex shape only beats a simpler one (earlier in ``shapes``) when its support is
larger by more than ``tolerance`` (default 5 %), since a cone or a huge sphere can always
imitate a plane's points. When a more complex shape wins, each simpler one is refitted to
the winner's support and is reported instead if its own support is within the tolerance.
Ties in support go to the lower MSAC cost. A support is measured only where its count of
compatible points (a bound on it) could still win. At the end (``settle``) every point
within the threshold of a detection and near its points goes to the nearest one
(``_settled``).

Keys: every random choice is seeded from the key's words (``_entropy``) and its place:
round r's fit_batch call for shape s of S is seeded ``_seed(r, s)`` (its refits of shape s
``_seed(r, S + s)``), group g's subsample ``_rng(r, g)`` (for a refit ``_rng(r, g, S +
s)``, for the winner's refit ``_rng(r, g, 2 S)``). A key gives the same scene every time.

Measurements: docs/detect.md.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
import types
from pathlib import Path

import jax
import numpy as np

from . import _checks
from .engine import FitOptions, default_threshold
from .engine.cloud import shared
from .engine.fit import started_shared
from .io.inputs import converted
from .normals import distinct_inverse, distinct_rows, kd_tree, pair_normals
from .shapes import Model, trimesh_scene
from .shapes._base import short
from .shapes._geometry import column_bounds, median, offsets

#: Candidate shapes, simplest first (the order breaks near-ties in support).
DEFAULT_SHAPES = ("plane", "sphere", "cylinder", "cone")
#: Most passes of the final assignment (see ``_settled``); scenes settle in 2-4.
SETTLE_ROUNDS = 8
#: Neighbours of a point's estimated normal where fewer than ``normals.PAIR_LEAST``
#: points lie within the connectivity radius (see ``estimate_normals``).
NORMAL_K = 16
#: Most support points a winner's least-squares refit reads (``_polished``): LO's own
#: ``LO_POINTS``; the accuracy is set by the noise long before.
POLISH_POINTS = 2048
#: Fit options of the candidates unless the caller sets them: no LO-RANSAC (on the CPU
#: LO was 25 ms of a 1000-point cylinder fit and 67 ms of a cone's, against 1-2 ms
#: for the search); the winner of each group is refitted instead (``_polished``).
#: When a more complex shape wins a group, a simpler one is refitted to its support only
#: if the simpler one's own candidate had at least this fraction of the winner's support
#: in compatible points. On the 20 benchmark scenes, peers' 5 and the 2 Fit4CAD scans,
#: 1 of 205 refits was taken (a plane, whose candidate had 1.0 of the cone's support);
#: this skips 184 of them, that one not.
SIMPLER_REACH = 0.5
#: A FitOptions passed whole (``options=``) is used as it is.
CANDIDATE_OPTIONS = {"refine": False}
#: Most hypotheses of a simpler shape's refit to a winner's support (one kernel batch of
#: the default ``batch_size``), unless the caller sets ``max_hypotheses`` or ``options``:
#: the refit can only be taken where the simpler shape explains nearly all the support
#: (within ``tolerance``), which 256 minimal samples find with certainty (a plane at 40 %
#: of inliers needs 70 for 99 %); the adaptive count had run up to 8 batches on
#: supports the simpler shape did not fit (a plane on a sphere's points).
REFIT_HYPOTHESES = 256
#: A simpler shape's candidates are searched (``_cap``) only as long as it
#: takes to find a model explaining this fraction of the largest share of a group's
#: fitted points that a more complex shape's candidate explains.
RELEVANT = 0.25


@dataclasses.dataclass(frozen=True, repr=False)
class Detection:
    """One primitive found in a scene.

    model : the fitted primitive (bounded, in the input's coordinates).
    indices : (M,) sorted indices into the input points of its support (compatible,
        connected inliers), the points it took out of the cloud (``Scene.masks`` gives
        them as masks).
    cost : MSAC cost of the fit over the points it was fitted to (at most ``fit_points``
        of its group).
    round : detection round (0-based) in which it was taken.
    """

    model: Model
    indices: np.ndarray
    cost: float
    round: int

    @property
    def shape(self) -> str:
        return self.model.name

    def to_dict(self) -> dict:
        """JSON-ready: the model (``Model.to_dict``), its indices, cost and round."""
        return {"model": self.model.to_dict(), "num_points": int(len(self.indices)),
                "indices": np.asarray(self.indices).tolist(), "cost": float(self.cost),
                "round": int(self.round)}

    @classmethod
    def from_dict(cls, data: dict) -> Detection:
        return cls(Model.from_dict(data["model"]), _indices(data["indices"], "indices"),
                   float(data["cost"]), int(data["round"]))

    def __repr__(self):
        return (f"Detection(model={self.model!r}, {len(self.indices)} points, "
                f"cost={short(self.cost)}, round={self.round})")


@dataclasses.dataclass(frozen=True, repr=False)
class Scene:
    """Outcome of ``detect``.

    shapes : list of Detection, in the order they were taken.
    unassigned : (U,) sorted indices of the points no detection took.
    threshold : inlier distance used; spacing : median nearest-neighbour distance;
    radius : connectivity radius (``connect * spacing``).
    points : (N, 3) the cloud detect worked on (None for a Scene built without it);
        ``save`` draws its preview from them.
    """

    shapes: list[Detection]
    unassigned: np.ndarray
    threshold: float
    spacing: float
    radius: float
    points: np.ndarray | None = None

    @property
    def num_points(self) -> int:
        """N, the number of points of the cloud (assigned or not)."""
        return sum(len(d.indices) for d in self.shapes) + len(self.unassigned)

    def labels(self) -> np.ndarray:
        """(N,) index into ``shapes`` of each input point's detection, -1 if unassigned."""
        out = np.full(self.num_points, -1)
        for i, d in enumerate(self.shapes):
            out[d.indices] = i
        return out

    def masks(self) -> np.ndarray:
        """(D, N) bool: row i marks the points of ``shapes[i]`` (its ``indices``)."""
        return self.labels()[None, :] == np.arange(len(self.shapes))[:, None]

    def to_dict(self, *, with_points: bool = False) -> dict:
        """JSON-ready: every detection (``Detection.to_dict``, indices included), the
        unassigned indices and the settings; the points too with ``with_points`` (N x 3
        numbers: ``save`` writes them to points.npy instead)."""
        out = {"num_points": self.num_points,
               "shapes": [d.to_dict() for d in self.shapes],
               "unassigned": np.asarray(self.unassigned).tolist(),
               "threshold": float(self.threshold), "spacing": float(self.spacing),
               "radius": float(self.radius)}
        if with_points and self.points is not None:
            out["points"] = np.asarray(self.points).tolist()
        return out

    @classmethod
    def from_dict(cls, data: dict, points=None) -> Scene:
        """Inverse of ``to_dict``: the points from ``data["points"]``, else ``points``
        (an (N, 3) array, or None)."""
        if "points" in data:
            points = data["points"]
        if points is not None:
            points = _checks.cloud(points)
        scene = cls([Detection.from_dict(d) for d in data["shapes"]],
                    _indices(data["unassigned"], "unassigned"), float(data["threshold"]),
                    float(data["spacing"]), float(data["radius"]), points)
        if points is not None and len(points) != scene.num_points:
            raise ValueError(f"the scene covers {scene.num_points} points, but "
                             f"{len(points)} points were given")
        return scene

    def to_trimesh(self):
        """A ``trimesh.Scene`` of the detected primitives, coloured by type."""
        return trimesh_scene([d.model for d in self.shapes],
                             [f"shape{i}_{d.shape}" for i, d in enumerate(self.shapes)])

    def save(self, directory) -> Path:
        """Write into ``directory``: scene.json (``to_dict``), and where they exist
        points.npy (the points), scene.glb (the primitives, ``to_trimesh``) and
        preview.png (the points coloured by detection beside the primitives, as
        ``Decomposition.save`` draws). All are written to temporary files and renamed
        into place together (``io.atomic``). Returns the directory."""
        from .io.atomic import replacing_all
        from .io.preview import render

        names = ["scene.json"]
        if self.points is not None:
            names += ["points.npy"] + (["preview.png"] if len(self.points) else [])
        if self.shapes:
            names.append("scene.glb")
        with replacing_all(directory, names) as files:
            files["scene.json"].write_text(json.dumps(self.to_dict(), indent=1))
            if "points.npy" in files:
                np.save(files["points.npy"], np.asarray(self.points, np.float64))
            if "scene.glb" in files:
                self.to_trimesh().export(files["scene.glb"])
            if "preview.png" in files:
                render(_Preview(self), files["preview.png"])
        return Path(directory)

    @classmethod
    def load(cls, directory) -> Scene:
        """The Scene ``save`` wrote into ``directory`` (its points when points.npy is
        there)."""
        folder = Path(directory)
        try:
            data = json.loads((folder / "scene.json").read_text())
        except (OSError, ValueError) as err:
            raise ValueError(f"no readable scene.json in {folder}: {err}") from err
        points = folder / "points.npy"
        return cls.from_dict(data, np.load(points) if points.is_file() else None)

    def __repr__(self):
        found = ", ".join(f"{d.shape} ({len(d.indices)} points)" for d in self.shapes)
        return (f"Scene({len(self.shapes)} shapes: {found or 'none'}; "
                f"{len(self.unassigned)} of {self.num_points} points unassigned, "
                f"threshold={short(self.threshold)})")


class _Preview:
    """A Scene as ``io.preview.render`` reads a decomposition: points and parts (each
    with indices, model, kind, and the mesh of the patch of its model that its points
    cover: ``io.preview.surface_patch`` within the connectivity radius, at least two
    thresholds; the whole model where no face is that near)."""

    def __init__(self, scene: Scene):
        from .io.preview import surface_patch

        self.points = np.asarray(scene.points, np.float64)
        reach = max(float(scene.radius), 2.0 * float(scene.threshold))
        self.parts = []
        for d in scene.shapes:
            whole = d.model.to_mesh()
            patch = surface_patch(whole, self.points[d.indices], reach) \
                if reach > 0 and len(d.indices) else None
            self.parts.append(types.SimpleNamespace(indices=d.indices, model=d.model,
                                                    kind=d.shape,
                                                    mesh=whole if patch is None else patch))


def _indices(values, name: str) -> np.ndarray:
    """values as an ascending (M,) int64 array, or ValueError."""
    arr = np.asarray(values, dtype=np.int64).reshape(-1) if len(values) else np.empty(0, np.int64)
    if arr.size and arr.min() < 0:
        raise ValueError(f"{name} must be non-negative indices")
    return arr


#: The pairs are first listed at this many times the radius a subsample's spacing
#: gives (``RadiusGraph.of``); the subsample's median is within ~2 % of the cloud's.
SPACING_MARGIN = 1.1
#: Mean radius pairs per point above which ``RadiusGraph`` joins points through
#: ``capped_pairs`` (bounded memory) instead of listing every pair (a dense cluster of k
#: points has ~k^2 / 2: 20,000 near-copies of one point needed 9 GB).
PAIR_BUDGET = 32
#: ``RadiusGraph.components`` labels up to this many pairs by NumPy hooking
#: (``hooked_labels``), more with scipy's csgraph: the hooking's passes over the pairs
#: cost more than scipy's graph beyond ~30,000 (docs/detect.md).
HOOKING_PAIRS = 1 << 15
#: Most hooking rounds before scipy takes over; each at least halves the distance to a
#: root in the scenes measured (2-5 rounds).
HOOKING_ROUNDS = 32

# ----- pure pieces --------------------------------------------------------------------


def _spacing(tree, distinct: np.ndarray) -> float:
    """Median distance from each of the distinct points (M, 3) to its nearest other one
    (``tree`` over them); 0 if fewer than two. The query is bounded by 4 times the
    median of a subsample's: an outlier's nearest neighbour, far away, had cost a search
    through much of the tree, and the median does not read how far it is unless more
    than half of the points are that far (then the query runs unbounded)."""
    m = len(distinct)
    if m < 2:
        return 0.0
    guess = _subsample_spacing(tree, distinct)
    if guess > 0:
        near = tree.query(distinct, k=2, distance_upper_bound=4.0 * guess)[0][:, 1]
        if np.count_nonzero(np.isfinite(near)) * 2 > m:
            return float(np.median(near))
    return float(np.median(tree.query(distinct, k=2)[0][:, 1]))


def _subsample_spacing(tree, distinct: np.ndarray) -> float:
    """The median nearest-neighbour distance of at most 1024 evenly spread points of
    distinct (M, 3), M >= 2 (``tree`` over them): within a few per cent of the whole
    cloud's."""
    rows = np.linspace(0, len(distinct) - 1, min(len(distinct), 1024)).astype(np.int64)
    return float(np.median(tree.query(distinct[rows], k=2)[0][:, 1]))


def median_spacing(points: np.ndarray) -> float:
    """Median distance from each distinct point of points (N, 3) to its nearest other one
    (copies of a point do not make the spacing 0); 0 if fewer than two are distinct."""
    distinct = distinct_rows(points)
    return _spacing(kd_tree(distinct), distinct) if len(distinct) >= 2 else 0.0


def capped_pairs(tree, points: np.ndarray, radius: float) -> np.ndarray:
    """(E, 2) pairs of points (N, 3) within radius, each once (first < second): at most
    ``PAIR_BUDGET`` per point (its nearest ones, from ``tree`` over points), plus every
    point joined to the first point of its cell of side radius / sqrt(3) (any two points
    of a cell lie within radius). Memory O(N) however dense the cloud; the components
    match the full radius graph's unless two regions denser than ``PAIR_BUDGET`` points
    within radius meet only through pairs neither side lists (across a cell border)."""
    dist, near = tree.query(points, k=PAIR_BUDGET + 1, distance_upper_bound=radius)
    rows = np.broadcast_to(np.arange(len(points))[:, None], near.shape)
    listed = np.isfinite(dist) & (near != rows)
    cells = np.floor(points / (radius / np.sqrt(3.0))).astype(np.int64)
    _, first, cell_of = np.unique(cells, axis=0, return_index=True, return_inverse=True)
    same_cell = np.column_stack([np.arange(len(points)), first[cell_of.reshape(-1)]])
    pairs = np.concatenate([np.column_stack([rows[listed], near[listed]]), same_cell])
    pairs = np.sort(pairs[pairs[:, 0] != pairs[:, 1]], axis=1)
    return np.unique(pairs, axis=0)


def pair_bound(points: np.ndarray, radius: float) -> float:
    """An upper bound on the pairs of points (N, 3) within radius: every pair lies in one
    cubic cell of side radius or in two neighbouring ones, so it is at most the pairs
    within each cell plus, over the 13 neighbour offsets that count each pair of cells
    once, the products of their counts. On the scenes' surfaces about 3 times the true
    count, so that a cloud well within ``PAIR_BUDGET`` needs no exact count
    (``count_neighbors`` cost twice the listing)."""
    cells = np.floor(offsets(points, column_bounds(points)[0]) / radius).astype(np.int64) + 1
    dims = column_bounds(cells)[1] + 2
    size = float(np.prod(dims.astype(np.float64)))
    if size >= 2.0 ** 62:
        return np.inf  # (no exact int64 key: the caller counts exactly)
    keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    if size <= DENSE_CELLS * len(points):
        return _dense_pair_bound(np.bincount(keys, minlength=int(size)).reshape(dims))
    cell, count = np.unique(keys, return_counts=True)
    count = count.astype(np.float64)
    # (products summed, not np.dot: OpenBLAS's threads had made a dot of 20k counts
    # cost up to 5 ms on a loaded machine)
    within = float((count * (count - 1.0)).sum()) / 2.0  # pairs inside one cell
    # Pairs across two neighbouring cells: each of the 13 offsets with a positive first
    # non-zero component counts every neighbouring pair of cells once.
    for dx, dy, dz in _HALF_OFFSETS:
        shifted = cell + (dx * dims[1] + dy) * dims[2] + dz
        at = np.minimum(np.searchsorted(cell, shifted), len(cell) - 1)
        within += float((count * np.where(cell[at] == shifted, count[at], 0.0)).sum())
    return within


#: The 13 neighbour offsets of a cell whose first non-zero component is positive: each
#: pair of neighbouring cells once.
_HALF_OFFSETS = ((1, -1, -1), (1, -1, 0), (1, -1, 1), (1, 0, -1), (1, 0, 0), (1, 0, 1),
                 (1, 1, -1), (1, 1, 0), (1, 1, 1), (0, 1, -1), (0, 1, 0), (0, 1, 1),
                 (0, 0, 1))
#: ``pair_bound`` counts on a dense grid of cells while it has at most this many cells a
#: point (13 shifted products of the grid: 4.0 -> ~1 ms on 23k points, the same sum).
DENSE_CELLS = 16


def _dense_pair_bound(grid: np.ndarray) -> float:
    """``pair_bound``'s sum from the counts of points per cell, grid (X, Y, Z) (a border
    of empty cells round the occupied ones): the pairs within each cell plus, for each
    of the 13 ``_HALF_OFFSETS``, the products of neighbouring cells' counts."""
    grid = grid.astype(np.float64)
    within = float((grid * (grid - 1.0)).sum()) / 2.0
    for offset in _HALF_OFFSETS:
        here = tuple(slice(max(0, -d), n - max(0, d)) for d, n in zip(offset, grid.shape,
                                                                       strict=True))
        there = tuple(slice(max(0, d), n - max(0, -d)) for d, n in zip(offset, grid.shape,
                                                                        strict=True))
        within += float((grid[here] * grid[there]).sum())
    return within


@dataclasses.dataclass(frozen=True)
class RadiusGraph:
    """A cloud's points joined within ``radius``, over its distinct rows (copies of a
    point share its row and its answers): the one neighbour structure of a ``detect``
    call. Its components (groups, supports), its neighbour sums (the final assignment)
    and the estimated normals all read it, so the cloud is put in one KD-tree once.

    distinct : (M, 3) distinct points; inverse : (N,) each point's row in it;
    pairs : (E, 2) rows within radius, first < second (at most ``PAIR_BUDGET`` a row on
    average; a denser cloud lists ``capped_pairs``);
    upper : (M, M) CSR matrix of float64 ones at the pairs (first, second), each pair
    once (the adjacency's upper triangle; each row's columns in no particular order:
    half the entries of the symmetric matrix, so half the work of every component
    call); tree : the cKDTree over distinct; spacing : median
    nearest-neighbour distance among distinct points; radius : the radius.
    """

    distinct: np.ndarray
    inverse: np.ndarray
    pairs: np.ndarray
    upper: object
    tree: object
    spacing: float
    radius: float

    @classmethod
    def of(cls, points: np.ndarray, connect: float | None = None,
           radius: float | None = None) -> RadiusGraph:
        """The graph of points (N, 3) at ``radius``, or at ``connect`` times their
        median spacing."""
        distinct, inverse = distinct_inverse(points)
        tree = kd_tree(distinct)
        m = len(distinct)
        spacing = np.nan
        if radius is None and m >= 2:
            # The pairs at a radius a little above the one a subsample's spacing gives
            # hold every point's nearest neighbour within it, hence the exact median
            # spacing (a query of its own had cost as much as listing the pairs).
            reach = connect * _subsample_spacing(tree, distinct) * SPACING_MARGIN
            pairs = _pairs(tree, distinct, reach, SPACING_MARGIN ** 2)
            length = np.sqrt(sum((np.take(c, pairs[:, 1]) - np.take(c, pairs[:, 0])) ** 2
                                 for c in np.ascontiguousarray(distinct.T)))
            nearest = np.full(m, np.inf)
            np.minimum.at(nearest, pairs[:, 0], length)
            np.minimum.at(nearest, pairs[:, 1], length)
            known = np.count_nonzero(np.isfinite(nearest)) * 2 > m + 1  # (the middle two)
            spacing = float(median(nearest)) if known else _spacing(tree, distinct)
            radius = connect * spacing
            if known and radius <= reach:
                pairs = pairs.take(np.flatnonzero(length <= radius), axis=0)
            else:
                pairs = _pairs(tree, distinct, radius)
        elif radius is None:
            spacing, radius = 0.0, 0.0
            pairs = _pairs(tree, distinct, radius)
        else:
            pairs = _pairs(tree, distinct, radius)
        return cls(distinct, inverse, pairs, _csr(pairs[:, 0], pairs[:, 1], m), tree, spacing,
                   float(radius))

    def components(self, members: np.ndarray) -> np.ndarray:
        """Labels (K,) of the connected components of the points ``members`` (K,)
        (indices into the cloud) joined within the radius, numbered by decreasing size
        in points (0 is the largest; ties in order of first appearance)."""
        if len(members) == 0:
            return np.empty(0, np.int64)
        rows = self.inverse[members]
        mark = np.zeros(len(self.distinct), bool)
        mark[rows] = True
        position = np.cumsum(mark) - 1
        count = int(position[-1]) + 1
        first, second = self.pairs[:, 0], self.pairs[:, 1]
        joined = np.flatnonzero(mark[first] & mark[second])  # (the members' own pairs)
        labels = None
        if len(joined) <= HOOKING_PAIRS:
            labels = hooked_labels(count, position[first[joined]], position[second[joined]])
        if labels is None:
            from scipy.sparse.csgraph import connected_components

            keep = np.flatnonzero(mark)
            graph = self.upper if count == len(mark) else self.upper[keep][:, keep]
            # (weak components of the one-way pairs: the undirected graph's components)
            _, labels = connected_components(graph, directed=True, connection="weak")
        labels = labels[position[rows]]
        by_size = np.argsort(-np.bincount(labels), kind="stable")
        return np.argsort(by_size)[labels]

    def near(self, owner: np.ndarray, count: int, at=None) -> np.ndarray:
        """(count, K) bool: whether each point ``at`` (K,) (indices into the cloud;
        default all N) lies within the radius of (or is) a point with ``owner`` (N,)
        equal to the row's index (-1: no owner)."""
        rows = self.inverse[owner >= 0]
        member = np.zeros((len(self.distinct), count))
        member[rows, owner[owner >= 0]] = 1.0
        asked = self.inverse if at is None else self.inverse[at]
        touching = (member > 0) | (self.neighbour_sums(member) > 0)
        return touching[asked].T

    def neighbour_sums(self, values: np.ndarray) -> np.ndarray:
        """(M, K): for each distinct point, the sum of values (M, K) over the points it
        is paired with (the symmetric adjacency's product, from its upper triangle)."""
        return self.upper @ values + self.upper.T @ values


def hooked_labels(count: int, first, second, rounds: int = HOOKING_ROUNDS):
    """Component labels (count,) of the graph of ``count`` nodes with edges (first,
    second) (E,), numbered by their lowest node (as scipy's ``connected_components``
    numbers them), by hooking each root onto the lowest root it touches and pointer
    jumping to the roots, until nothing moves; None if that takes more than ``rounds``
    rounds. Why: at the few thousand pairs of a group's leftovers, scipy's graph and its
    checks cost ~0.3 ms a call, these NumPy passes tens of us (docs/detect.md)."""
    label = np.arange(count)
    for _ in range(rounds):
        a, b = label[first], label[second]
        low = np.minimum(a, b)
        hooked = label.copy()
        np.minimum.at(hooked, a, low)
        np.minimum.at(hooked, b, low)
        while not np.array_equal(jumped := hooked[hooked], hooked):
            hooked = jumped
        if np.array_equal(hooked, label):
            return np.unique(label, return_inverse=True)[1]
        label = hooked
    return None


def _pairs(tree, points: np.ndarray, radius: float, allowance: float = 1.0) -> np.ndarray:
    """(E, 2) int64 pairs of points (M, 3) (distinct; ``tree`` over them) within radius,
    each once, first < second: all of them while they are at most ``allowance`` x
    ``PAIR_BUDGET`` a point (``pair_bound``, else counted exactly), else
    ``capped_pairs``."""
    m = len(points)
    if m < 2 or not radius > 0:
        return np.empty((0, 2), np.int64)
    budget = allowance * PAIR_BUDGET * m
    # count_neighbors prunes whole node pairs within radius, so it counts a dense
    # cluster's ~k^2 pairs without listing them (ordered pairs, each point with itself).
    if (pair_bound(points, radius) <= budget
            or (tree.count_neighbors(tree, radius) - m) // 2 <= budget):
        return tree.query_pairs(radius, output_type="ndarray").astype(np.int64)
    return capped_pairs(tree, points, radius)


def _csr(rows, columns, size: int):
    """The (size, size) float64 CSR matrix of ones at the distinct (rows, columns) (E,),
    in any order, each row's columns left in their order: scipy's counting conversion
    without the sort and duplicate sum it runs on a COO matrix it does not know to hold
    distinct entries (11.6 -> 4.7 ms on 300k entries); csgraph and the products need
    neither. float64, the dtype ``connected_components`` converts any other to."""
    from scipy.sparse import coo_matrix

    entries = coo_matrix((np.ones(len(rows)), (rows, columns)), shape=(size, size))
    entries.has_canonical_format = True  # (distinct entries: nothing to sum)
    return entries.tocsr()


def estimate_normals(graph: RadiusGraph, k: int = NORMAL_K) -> np.ndarray:
    """(N, 3) unoriented normals of the graph's cloud, as detect estimates them when it
    is given none: ``normals.pair_normals`` over each distinct point's neighbours within
    the radius (its k nearest where fewer than ``normals.PAIR_LEAST`` are that near),
    one per distinct point, shared by its copies. (Not ``jaxfit.estimate_normals``,
    which takes points and queries k nearest neighbours for every point.)"""
    return pair_normals(graph.distinct, graph.pairs, min(k, len(graph.distinct)),
                        graph.tree, graph.neighbour_sums)[graph.inverse]


def components(points: np.ndarray, radius: float) -> np.ndarray:
    """Labels (N,) of the connected components of points (N, 3) joined within radius,
    numbered by decreasing size (0 is the largest)."""
    return RadiusGraph.of(points, radius=radius).components(np.arange(len(points)))


def compatible(model: Model, points, normals, threshold: float, cos_max: float) -> np.ndarray:
    """Indices into points (N, 3) of the model's compatible points: within threshold,
    with normals (N, 3) (any sign) within the angle arccos(cos_max) of the model's
    surface normal there."""
    points, normals = np.asarray(points), np.asarray(normals)
    near = np.flatnonzero(model.distance(points) < threshold)
    if near.size == 0:
        return near
    # (one central difference, where ``Model.surface_normal`` takes three; ``take``:
    # fancy indexing of (N, 3) rows is ~4x slower)
    cosines = model.normal_cosines(points.take(near, axis=0), normals.take(near, axis=0),
                                   0.1 * threshold)
    return near[np.abs(cosines) >= cos_max]


def support(model: Model, points, normals, threshold: float, cos_max: float,
            radius: float) -> np.ndarray:
    """Indices into points (N, 3) of the model's support: the largest connected
    component of its compatible points (``compatible``) joined within radius."""
    near = compatible(model, points, normals, threshold, cos_max)
    if near.size == 0:
        return near
    return near[components(np.asarray(points).take(near, axis=0), radius) == 0]


def choose(sizes: np.ndarray, costs: np.ndarray, tolerance: float) -> int:
    """Index of the winning candidate (shapes in order of complexity): the simplest whose
    support sizes (S,) is within a factor (1 + tolerance) of the largest, ties by the
    lower cost (S,)."""
    contenders = np.flatnonzero(sizes * (1.0 + tolerance) >= sizes.max())
    simplest = contenders[0]
    tied = contenders[sizes[contenders] == sizes[simplest]]
    return int(tied[np.argmin(costs[tied])]) if sizes[simplest] == sizes.max() else simplest


# ----- the loop -----------------------------------------------------------------------


def _check_options(points, shapes, min_inliers, threshold, normals, max_angle, connect,
                   tolerance, fit_options):
    cloud = _checks.cloud(points)
    if isinstance(shapes, str | type):
        shapes = (shapes,)  # one shape
    try:
        shapes = tuple(shapes)
    except TypeError:
        raise TypeError(f"shapes must be a sequence of shape names or classes, got "
                        f"{shapes!r}") from None
    classes = [_checks.model_class(s) for s in shapes]
    if not classes:
        raise ValueError("shapes is empty: give at least one shape to detect")
    if len(set(classes)) != len(classes):
        raise ValueError(f"shapes has repeated entries: {tuple(shapes)}")
    smallest = max(cls.sample_size for cls in classes)
    if min_inliers is None:
        min_inliers = max(smallest, int(np.ceil(0.01 * len(cloud))))
    min_inliers = _checks.positive(min_inliers, "min_inliers", integer=True)
    if min_inliers < smallest:
        raise ValueError(f"min_inliers must be at least {smallest} (the largest minimal "
                         f"sample of {', '.join(c.name for c in classes)}), got {min_inliers}")
    if len(cloud) < min_inliers:
        raise ValueError(f"too few points: {len(cloud)} < min_inliers = {min_inliers}")
    lo, hi = column_bounds(cloud)
    _checks.spanning(lo, hi)
    if threshold is None:
        sides = hi - lo
        if not sides.max() > 0:
            raise _checks.FitError("all points coincide: there is no shape to detect")
        threshold = default_threshold(sides)
    threshold = _checks.positive(threshold, "threshold")
    max_angle = _checks.positive(max_angle, "max_angle")
    if max_angle > 90:
        raise ValueError(f"max_angle is in degrees and must be in (0, 90], got {max_angle}")
    connect = _checks.positive(connect, "connect")
    tolerance = _checks.non_negative(tolerance, "tolerance")  # (NaN: no shape could win)
    normals = _checks.normals_for(normals, cloud)
    # The fits' options, checked now rather than at the first fit (after the normals),
    # and only FitOptions' own: detect's fits get their normals, threshold and key from
    # detect, and fit_batch's skip_failures would have made a failed fit None.
    settings = dict(fit_options)
    options = FitOptions.build(settings.pop("options", None), **settings)
    for cls in classes:
        options.check(cls)
    return cloud, classes, min_inliers, threshold, normals, max_angle, connect, tolerance


def detect(points, shapes=DEFAULT_SHAPES, *, min_inliers: int | None = None,
           threshold: float | None = None, normals=None, max_angle: float = 30.0,
           connect: float = 4.0, tolerance: float = 0.05, fit_points: int = 1024,
           settle: bool = True, key=0, progress: bool = False, **fit_options) -> Scene:
    """Find several primitives in one cloud, one after another.

    Parameters
    ----------
    points : (N, 3) array-like of finite coordinates, or any cloud ``jaxfit.as_cloud``
        reads (a trimesh or Open3D geometry, a path; a mesh gives
        ``io.inputs.MESH_POINTS`` points sampled with the seed of ``key``).
    shapes : candidate shapes, simplest first (the order breaks near-ties, see the
        module docstring): names or model classes (or one name or class).
    min_inliers : smallest support worth reporting; the loop stops when no candidate
        reaches it. Default 1 % of the points (at least the largest minimal sample).
    threshold : inlier distance. Default: 0.5 % of the whole cloud's bounding-box
        diagonal, fixed for all rounds.
    normals : optional (N, 3) normals (any sign); default the source's own (a mesh's
        face normals, an Open3D cloud's or a point file's normals), else estimated by PCA
        over each point's neighbours within the connectivity radius (its ``NORMAL_K``
        nearest where fewer than ``normals.PAIR_LEAST`` are that near:
        ``normals.pair_normals``). Used for the compatibility test and passed on to the
        fits.
    max_angle : largest angle in degrees between a point's normal and the model's.
    connect : connectivity radius in units of the median nearest-neighbour spacing.
    tolerance : relative support margin a more complex shape needs to beat a simpler one.
    fit_points : most points a fit sees: a random subsample of the group (or of the
        winner's support, for a refit) drawn from the key; its support is then
        measured on the whole group.
    settle : give every point within ``threshold`` of a detection, and within the
        connectivity radius of its points, to the nearest one at the end (``_settled``).
    key : int seed or JAX key (``key=0`` and ``jax.random.key(0)`` give the same
        scene); every random choice is seeded from it and its place in the loop (module
        docstring, "Keys").
    progress : print one line per detected primitive on stderr, with the seconds since
        the call began.
    **fit_options : passed to every ``jaxfit.fit_batch`` call: ``FitOptions`` fields
        (e.g. ``batch_size``, ``min_hypotheses``, ``estimator``, ``refine=True`` to run
        LO-RANSAC on every candidate) over ``CANDIDATE_OPTIONS``, or ``options`` (a
        FitOptions, used as it is), checked for every shape before any work; not
        ``normals``, ``threshold`` or ``key``, which detect sets.

    Returns
    -------
    Scene, with ``.shapes`` (list of Detection) and ``.unassigned`` (indices).
    """
    points, own = converted(points, seed=lambda: _checks.numpy_seed(key))
    normals = own if normals is None else normals
    cloud, classes, min_inliers, threshold, normals, max_angle, connect, tolerance = \
        _check_options(points, shapes, min_inliers, threshold, normals, max_angle, connect,
                       tolerance, fit_options)
    fit_points = _checks.positive(fit_points, "fit_points", integer=True)
    graph = RadiusGraph.of(cloud, connect)
    if len(graph.distinct) < 3:  # (no primitive fits two points: nothing to find)
        return Scene([], np.arange(len(cloud)), threshold, graph.spacing, graph.radius,
                     cloud)
    if normals is None:
        normals = estimate_normals(graph)
    if "options" not in fit_options:  # (a FitOptions given whole is taken as it is)
        fit_options = {**CANDIDATE_OPTIONS, **fit_options}
    context = _Context(cloud, normals, threshold, float(np.cos(np.radians(max_angle))),
                       graph, fit_points, tolerance, fit_options, tuple(classes),
                       _entropy(key), min_inliers)
    found: list[Detection] = []
    live = np.ones(len(cloud), bool)  # unassigned points in groups that may still give
    rnd, started = 0, time.perf_counter()
    while groups := _groups(graph, np.flatnonzero(live), min_inliers):
        live[:] = False
        for group, best in zip(groups, _round(context, groups, rnd), strict=True):
            if best is None or len(best[1]) < min_inliers:
                continue  # nothing left to find here: its points stay unassigned
            model, taken, cost = best
            found.append(Detection(model, np.sort(taken), cost, rnd))
            live[group] = True
            live[taken] = False
            if progress:  # (on stderr, seconds since the call began: as decompose's lines)
                print(f"round {rnd}: {model.name} with {len(taken)} of {len(group)} points "
                      f"({time.perf_counter() - started:.2f} s)", file=sys.stderr, flush=True)
        rnd += 1
    if settle and found:
        # Settling can leave a detection with fewer than min_inliers points (a sliver
        # between two surfaces that each took theirs back): it is dropped, and its
        # points stay unassigned.
        found = [d for d in _settled(found, cloud, threshold, graph)
                 if len(d.indices) >= min_inliers]
    free = np.ones(len(cloud), bool)
    for d in found:
        free[d.indices] = False
    unassigned = np.flatnonzero(free)
    return Scene(found, unassigned, threshold, graph.spacing, graph.radius, cloud)


@dataclasses.dataclass(frozen=True)
class _Context:
    """What every fit of one ``detect`` call shares."""

    cloud: np.ndarray  # (N, 3)
    normals: np.ndarray  # (N, 3)
    threshold: float
    cos_max: float
    graph: RadiusGraph
    fit_points: int
    tolerance: float
    fit_options: dict
    classes: tuple
    entropy: tuple  # the key's words (``_entropy``)
    min_inliers: int


def _entropy(key) -> tuple[int, ...]:
    """The words of ``key`` (an int seed or a JAX key) that seed every random choice of
    a detect call (``_seed``, ``_rng``): one conversion, where a ``fold_in`` per fit had
    cost ~1 ms of dispatch each."""
    return tuple(int(w) for w in np.asarray(jax.random.key_data(_checks.prng_key(key))).ravel())


def _rng(ctx: _Context, *path: int) -> np.random.Generator:
    """The NumPy generator of the choice at ``path`` (round, group, ...)."""
    return np.random.default_rng([*ctx.entropy, *path])


def _seed(ctx: _Context, *path: int) -> int:
    """The int seed of the fit_batch call at ``path`` (round, shape)."""
    return int(np.random.SeedSequence([*ctx.entropy, *path]).generate_state(1)[0])


def _groups(graph: RadiusGraph, idx, min_inliers):
    """Index arrays into the cloud of the connected components of its points idx with at
    least min_inliers points, largest first."""
    if len(idx) < min_inliers:
        return []
    labels = graph.components(idx)
    sizes = np.bincount(labels)  # (decreasing: label 0 is the largest)
    order = idx[np.argsort(labels, kind="stable")]
    ends = np.cumsum(sizes)
    # (only the large ones are cut out: an outlier is a component of its own)
    return [order[end - size:end] for end, size in zip(ends, sizes, strict=False)
            if size >= min_inliers]


def _round(ctx: _Context, groups, rnd):
    """The winning (model, support, cost) of each group of round ``rnd`` (None where no
    shape fits), every group's candidates of one shape fitted in one ``fit_batch`` call.

    Shape s of S is fitted to every group in the call seeded ``_seed(rnd, s)`` (group g
    its cloud g), on the subsample ``_rng(rnd, g)`` draws; the calls run from the most
    complex shape down, each simpler one capped by ``_cap``. When a more
    complex shape wins, each simpler one whose own candidate had at least
    ``SIMPLER_REACH`` times the winner's support in compatible points is refitted to the
    winner's support (call ``_seed(rnd, S + s)``, subsample ``_rng(rnd, g, S + s)``, at
    most ``REFIT_HYPOTHESES``) and takes its place if its own support is within the
    tolerance: a big sphere that won a box's face with a few stray points is reported as
    the plane it imitates. A winner whose support is below
    ``min_inliers`` by more than the tolerance is neither refitted nor polished (detect
    drops it): a group's last rounds are mostly such slivers.
    """
    count = len(ctx.classes)
    samples = [_fit_points(group, ctx.fit_points, _rng(ctx, rnd, g))
               for g, group in enumerate(groups)]
    # Every shape's first batch is dispatched at once (it does not depend on the caps),
    # so a GPU runs the later shapes' while the host works on the earlier ones (on the
    # CPU a kernel's loops run mostly inside its call: docs/detect.md, session 38).
    # The most complex shape is finished first: each simpler one's search is then capped
    # where it could only find models that matter (``_cap``).
    prepared = _shared(ctx, samples, min(c.sample_size for c in ctx.classes))  # (once)
    started = [_candidates(ctx, ctx.classes[s], samples, groups, _seed(ctx, rnd, s),
                           start=True, prepared=prepared) for s in range(count)]
    per_shape = [None] * count
    for s in reversed(range(count)):
        per_shape[s] = started[s](_cap(ctx, ctx.classes[s], per_shape[s + 1:], samples))
    best = [None] * len(groups)
    wins, bounds = {}, {}
    for g, found in enumerate(zip(*per_shape, strict=True)):
        decided = _decided(ctx, found)
        if decided is not None and len(decided[1][1]) * (1.0 + ctx.tolerance) < ctx.min_inliers:
            continue  # (too small to be reported, even after a refit or the polish)
        if decided is not None:
            wins[g], best[g] = decided
            bounds[g] = [len(c[1]) if c else 0 for c in found]
    for s in range(count - 1):
        # (refitted only where its own candidate came near: SIMPLER_REACH)
        pending = [g for g, win in wins.items() if win > s
                   and bounds[g][s] >= SIMPLER_REACH * len(best[g][1])]
        if not pending:
            break
        fit_on = [_fit_points(best[g][1], ctx.fit_points, _rng(ctx, rnd, g, count + s))
                  for g in pending]
        simpler = _candidates(ctx, ctx.classes[s], fit_on, [groups[g] for g in pending],
                              _seed(ctx, rnd, count + s), _refit_options(ctx.fit_options))
        for g, c in zip(pending, simpler, strict=True):
            # (the compatible points bound the support: most refits need no components)
            if c and len(c[1]) * (1.0 + ctx.tolerance) >= len(best[g][1]):
                taken = _largest(ctx, c[1])
                if len(taken) * (1.0 + ctx.tolerance) >= len(best[g][1]):
                    best[g] = c[0], taken, c[2]
                    del wins[g]
    return [None if b is None else _polished(ctx, *b, group, _rng(ctx, rnd, g, 2 * count))
            for g, (b, group) in enumerate(zip(best, groups, strict=True))]


def _polished(ctx: _Context, model: Model, taken, cost, group, rng):
    """(model, support, cost) after a float64 least-squares refit of the model on its
    support taken (at most ``POLISH_POINTS`` of them, drawn by rng), by
    ``engine.refine.final_refit`` in their unit frame, its support then measured again
    on cloud[group]; as given where the refit does not widen the support. The
    candidates are fitted without LO (``CANDIDATE_OPTIONS``): this one refit of each
    winner replaces LO's on every candidate."""
    from .engine.refine import final_refit

    if len(taken) < 2 * type(model).sample_size:
        return model, taken, cost
    points = ctx.cloud.take(_fit_points(taken, POLISH_POINTS, rng), axis=0)
    lo, hi = column_bounds(points)
    center = 0.5 * (lo + hi)
    unit = offsets(points, center)
    scale = float(np.sqrt((unit ** 2).sum(axis=1).max()))
    if not scale > 0:
        return model, taken, cost
    unit /= scale
    threshold = ctx.threshold / scale
    cls = type(model)
    theta, new_cost, start = final_refit(cls, model.rescaled(1.0 / scale, -center / scale)
                                         .theta(), unit, threshold)
    if not (np.all(np.isfinite(theta)) and new_cost < start):
        return model, taken, cost
    # Bounded by all the group's points near it, as the fits bound their models by the
    # points they saw (its support alone leaves out an edge whose normals are blurred:
    # a small cone's base, which then went to the floor).
    unit = offsets(ctx.cloud.take(group, axis=0), center) / scale
    inliers = np.abs(cls.theta_residual(theta, tuple(unit.T), np)) < threshold
    if not inliers.any():
        return model, taken, cost
    refitted = cls.from_theta(theta, unit, inliers, threshold).rescaled(scale, center)
    near = _compatible(ctx, refitted, group)
    least = len(taken) / (1.0 + ctx.tolerance)
    if len(near) < least:  # (its support cannot be large enough)
        return model, taken, cost
    support = _largest(ctx, near)
    return (refitted, support, cost) if len(support) >= least else (model, taken, cost)


def _decided(ctx: _Context, found):
    """(index of the winner, its (model, support, cost)) among one group's candidates
    found (S,) (each (model, compatible indices, cost) or None; ``choose`` on their
    supports), or None when no support has a point. A support is the largest component
    of the compatible points, so their count bounds it: supports are measured from the
    largest bound down, and one whose bound is below what the tolerance lets win is
    left unmeasured (it could neither be the largest nor a contender)."""
    sizes = np.zeros(len(found), np.int64)
    supports = [None] * len(found)
    bounds = np.array([len(c[1]) if c else 0 for c in found])
    for s in np.argsort(-bounds, kind="stable"):
        if bounds[s] == 0 or bounds[s] * (1.0 + ctx.tolerance) < sizes.max():
            break
        supports[s] = _largest(ctx, found[s][1])
        sizes[s] = len(supports[s])
    if not sizes.any():
        return None
    costs = np.array([c[2] if c else np.inf for c in found])
    win = choose(sizes, costs, ctx.tolerance)
    return win, (found[win][0], supports[win], found[win][2])


def _settled(found, cloud, threshold, graph: RadiusGraph):
    """Detections after a final assignment: every point within threshold of at least one
    detection's model, and within the radius of that detection's points (``graph``), goes
    to the nearest such model, repeated while points move (at most SETTLE_ROUNDS times).
    This gives the points whose estimated normals an edge blurred (they failed the
    normal test) to their surface, and splits the band where two surfaces meet (a lying
    cylinder's underside within threshold of the floor) by distance instead of by which
    was taken first; the repetition lets a surface take back a band wider than radius
    (docs/detect.md). Other points stay unassigned."""
    model_dist = np.stack([d.model.distance(cloud) for d in found])  # (D, N)
    owner = np.full(len(cloud), -1)
    for i, d in enumerate(found):
        owner[d.indices] = i
    # Only points within threshold of some model can be assigned (every detection's
    # points are: a support is within threshold of its model); the others keep -1.
    open_ = np.flatnonzero(model_dist.min(axis=0) < threshold)
    model_dist = model_dist[:, open_]
    every = np.arange(len(open_))
    for _ in range(SETTLE_ROUNDS):
        dist = np.where(graph.near(owner, len(found), open_), model_dist, np.inf)
        new = np.argmin(dist, axis=0)
        new[dist[new, every] >= threshold] = -1
        if np.array_equal(new, owner[open_]):
            break
        owner[open_] = new
    return [dataclasses.replace(d, indices=np.flatnonzero(owner == i))
            for i, d in enumerate(found)]


def _fit_points(group, fit_points, rng):
    """At most fit_points indices of group, drawn without replacement by rng: the fit
    sees a subsample, its support is then measured on the whole group."""
    if len(group) <= fit_points:
        return group
    return np.sort(rng.choice(group, fit_points, replace=False))


def _cap(ctx: _Context, cls, later, samples) -> int | None:
    """The ``max_hypotheses`` of shape cls's candidates, given those of the more complex
    shapes already fitted (later: one list per shape, one candidate or None per group,
    fitted to cloud[samples[g]]): the count that finds, with the call's confidence, a
    model with ``RELEVANT`` times the largest share of a group's fitted points any of
    them explains, in every group; None (the call's own) where a group has no such
    candidate, or the caller set ``max_hypotheses`` or ``options``. A simpler candidate
    with less can neither win (it needs its support within ``tolerance`` of the
    winner's) nor be refitted to the winner's support (``SIMPLER_REACH``) unless the
    winner's support is that much below its fitted share; the adaptive count had run a
    plane on a cylinder's points (16 % inliers) to 5 batches."""
    from .engine.stopping import required_hypotheses

    options = ctx.fit_options
    if not later or "options" in options or "max_hypotheses" in options:
        return None
    confidence = float(options.get("confidence", FitOptions.confidence))  # (checked already)
    sample_size = cls.estimator(options.get("estimator")).sample_size
    needed = 0.0
    for g, sample in enumerate(samples):
        shares = [c[3] / len(sample) for found in later if (c := found[g]) is not None]
        if not shares:
            return None  # (nothing to compare with: the adaptive count)
        needed = max(needed, required_hypotheses(RELEVANT * max(shares), sample_size,
                                                 confidence))
    if not np.isfinite(needed):
        return None
    return int(needed)


def _refit_options(fit_options: dict) -> dict:
    """The fit options of a simpler shape's refit: ``max_hypotheses`` capped at
    ``REFIT_HYPOTHESES`` unless the caller set it (or gave ``options`` whole)."""
    if "options" in fit_options or "max_hypotheses" in fit_options:
        return fit_options
    return {**fit_options, "max_hypotheses": REFIT_HYPOTHESES}


def _shared(ctx: _Context, fit_on, least: int) -> list:
    """The points cloud[fit_on[g]] of each group with their normals, prepared for every
    shape at once (``cloud.shared``); None where they coincide (no shape fits them) or
    are fewer than ``least``, the smallest minimal sample of the shapes they serve (those
    are never fitted, so never checked or prepared)."""
    out = []
    for sample in fit_on:
        if len(sample) < least:
            out.append(None)
            continue
        try:
            out.append(shared(ctx.cloud.take(sample, axis=0), ctx.normals.take(sample, axis=0),
                              ctx.threshold))
        except _checks.FitError:
            out.append(None)
    return out


def _candidates(ctx: _Context, cls, fit_on, groups, seed: int, fit_options=None,
                start: bool = False, prepared=None):
    """Per group: (model, compatible indices into the cloud, cost, inliers among the
    fitted points) of shape cls fitted to the points cloud[fit_on[g]], its compatible
    points taken from cloud[groups[g]] (``_largest`` of them is its support); None where
    no model could be fitted. One ``fit_batch`` call (seed ``seed``, ``fit_options``,
    default the context's) for all groups, on their ``_shared`` clouds (``prepared``, made
    here if not given). With ``start``, the call's first batch is
    dispatched and ``finish(max_hypotheses=None)`` returned, which gives that list
    (``max_hypotheses``: a lower count than the options', ``_cap``)."""
    out = [None] * len(groups)
    which = [g for g, sample in enumerate(fit_on) if len(sample) >= cls.sample_size]
    if not which:
        return (lambda max_hypotheses=None: out) if start else out
    prepared = _shared(ctx, fit_on, cls.sample_size) if prepared is None else prepared
    fits = started_shared(
        [prepared[g] for g in which], cls, key=seed, skip_failures=True, start=start,
        separate=True, **(ctx.fit_options if fit_options is None else fit_options))

    def finish(max_hypotheses=None):
        for g, result in zip(which, fits(max_hypotheses), strict=True):
            if result is not None:
                out[g] = (result.model, _compatible(ctx, result.model, groups[g]),
                          result.cost, result.num_inliers)
        return out

    return finish if start else finish()


def _compatible(ctx: _Context, model: Model, group) -> np.ndarray:
    """``compatible`` points of model among cloud[group], as indices into the cloud."""
    return group[compatible(model, ctx.cloud.take(group, axis=0),
                            ctx.normals.take(group, axis=0), ctx.threshold, ctx.cos_max)]


def _largest(ctx: _Context, near) -> np.ndarray:
    """The largest connected component (the call's graph) of the points near (indices
    into the cloud): the support, when near are a model's compatible points."""
    return near[ctx.graph.components(near) == 0] if near.size else near
