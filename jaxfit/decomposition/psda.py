"""The Primitive Shape Decomposition Algorithm (PSDA, THESIS.md section 5): an object's
points (N, 3) as a set of primitives, one per part.

1. BoxDecomposition splits the cloud into parts (``boxdecomp``, volumes against the root).
2. Fitting: every part is fitted with every primitive in ``shapes``, with a threshold of
   ``threshold_fraction`` of the part's diagonal; all parts of one primitive go through
   one ``fit_batch`` call.
3. Evaluation: each candidate scores the mean distance of *all* the part's points (of a
   hollow part, its outside) to its closed, bounded surface; the part's own bounding box
   competes too; among the plausible candidates the lowest wins.
4. The object is the set of winning primitives (``Decomposition``).

Departures from the thesis, each for an object the thesis's rule got wrong:

- The whole object first (``_whole_object``): every primitive is fitted to all the
  points and scored two-sided (``measure.Scorer``); one that explains the object within
  the noise of a fit (``_explains``; the first in ``shapes`` that does) is the one part,
  and no box is cut (an exact ball was cut into three slabs, fitted and merged back, 8x
  slower). Otherwise the thesis's parts stand only if they fit the object better than
  that primitive two-sided (``_splits_better``): one-sided, a box inscribed in the YCB
  soup can's middle slab won it and took the can's recessed lids.

- Reassignment (``reassign`` rounds after step 3): every point goes to the nearest
  part's best fitted primitive (cylinders and cones first grown along their surface,
  ``Model.axial_bounds``), parts that changed are fitted again, parts left tiny or of one
  kind and overlapping are merged; a round is kept only if it merges parts or lowers
  ``overall_distance``. Box cuts are planes, so a leaf keeps slivers of its neighbours.
- Plausibility (``MAX_OVERSHOOT``): a candidate reaching far out of the object's bounding
  box cannot win, nor (``OWNER_SLACK``) claim points; the mean distance cannot see a
  surface far from the points.
- Hollow parts (``HOLLOW``, ``HOLLOW_DEPTH``): a part with an inner wall is fitted and
  judged on its outside; one-sided, a surface midway between two walls is nearest.

``decompose(method="measured")`` replaces steps 1-3 by the two-sided split search of
``jaxfit.decomposition.measured``. Measurements and the cases behind each departure:
docs/decomposition.md.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import json
import numbers
import sys
import time
from pathlib import Path

import numpy as np

from .. import _checks
from ..shapes import Box, Model, mass_properties, trimesh_scene
from .boxdecomp import BoxNode, BoxTree, box_volume, decompose_boxes, mvbb, volume_floor
from .hull import shallow
from .measure import EXPLAINED, SPLIT_MARGIN, Scorer, mean_distance, parts_score
from .parts import (
    MAX_FIT_POINTS,
    THRESHOLD_FRACTION,
    Candidate,
    Part,
    SharedNormals,
    _grown,
    _threshold,
    fits,
)

#: The primitives tried on every part by default: the thesis's four.
SHAPES = ("sphere", "cylinder", "cone", "box")
#: A part is hollow when at least this fraction of its points lie deeper than
#: ``HOLLOW_DEPTH`` thresholds inside its convex hull (an inner wall): it is fitted and
#: judged on the others, its outside (``_outside``).
HOLLOW = 0.25
HOLLOW_DEPTH = 2.0
#: Ownership in reassignment skips implausible candidates unless the best plausible one
#: is more than this many times as far from its part's points as the part's MVBB.
OWNER_SLACK = 2.0
#: In reassignment a point keeps its part unless another part's primitive is nearer by
#: this fraction of its part's threshold (``_regroup``).
KEEP_MARGIN = 0.1


@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class Decomposition:
    """The object as a set of primitives.

    points : (N, 3) the cloud the decomposition worked on.
    parts : one Part per leaf of ``tree``, less those reassignment merged.
    tree : the box hierarchy (which box split into which); for ``method="measured"`` the
        split hierarchy (``reference`` "measured").
    seconds : wall time of decompose (boxes, fits and evaluation).
    levels : (measured) the parts for every part count of the run: ``levels[k - 1]``
        holds k parts, the last is ``parts`` (``with_parts``); empty for the thesis.
    method : the ``decompose`` method that made it.
    """

    points: np.ndarray
    parts: tuple[Part, ...]
    tree: BoxTree
    seconds: float
    levels: tuple[tuple[Part, ...], ...] = ()
    method: str = "thesis"

    def with_parts(self, count: int) -> Decomposition:
        """The decomposition of ``count`` parts from the split hierarchy of one run
        (``method="measured"``: ``levels[count - 1]``, the greedy's ``count``-part state;
        the last level is ``parts``); ValueError for a count the run did not
        reach (1 .. ``len(levels)``)."""
        if isinstance(count, bool) or not isinstance(count, numbers.Integral):
            raise TypeError(f"count must be an integer, got {count!r}")
        if not self.levels:
            raise ValueError("this decomposition has no split hierarchy (method='thesis'); "
                             "decompose with method='measured'")
        if not 1 <= count <= len(self.levels):
            raise ValueError(f"count must be in 1..{len(self.levels)} (the part counts of "
                             f"the split hierarchy), got {count}")
        return dataclasses.replace(self, parts=self.levels[count - 1])

    def to_scene(self):
        """A ``trimesh.Scene`` of the winning primitives, coloured by type."""
        return trimesh_scene([p.model for p in self.parts],
                             [f"part{i}_{p.kind}" for i, p in enumerate(self.parts)])

    def labels(self) -> np.ndarray:
        """(N,) index into ``parts`` of each point's part (-1 for a point in none)."""
        out = np.full(len(self.points), -1)
        for i, part in enumerate(self.parts):
            out[part.indices] = i
        return out

    def masks(self) -> np.ndarray:
        """(P, N) bool: row i marks the points of ``parts[i]`` (its ``indices``)."""
        return np.stack([p.mask(len(self.points)) for p in self.parts]) if self.parts \
            else np.zeros((0, len(self.points)), bool)

    def to_dict(self, *, with_points: bool = False) -> dict:
        """JSON-ready: per part its primitive, score, indices, size, every candidate, and
        its pose (``transform``, 4x4 rows), volume and centroid (``Part.to_dict``); the
        totals (``mass_properties`` at density 1: the volume, centroid and inertia per
        unit density); the hierarchy, with each point's leaf (``leaf_labels``) so that
        ``from_dict`` rebuilds it. With ``with_points`` the points too (N x 3 numbers;
        ``save`` writes them to points.npy instead)."""
        volume, centroid, inertia = self.mass_properties(1.0)
        totals = {"volume": volume, "centroid": centroid.tolist(),
                  "inertia_per_density": inertia.tolist()}
        hierarchy = self.tree.to_dict()
        hierarchy["leaf_labels"] = self.tree.leaf_labels(len(self.points)).tolist()
        out = {"num_points": int(len(self.points)), "seconds": self.seconds,
               "method": self.method, "parts": [part.to_dict() for part in self.parts],
               "totals": totals, "hierarchy": hierarchy}
        if self.levels:
            out["levels"] = [[part.to_dict() for part in level] for level in self.levels]
        if with_points:
            out["points"] = np.asarray(self.points).tolist()
        return out

    @classmethod
    def from_dict(cls, data: dict, points=None) -> Decomposition:
        """Inverse of ``to_dict``: the points from ``data["points"]``, else ``points``
        (N, 3), which a decomposition needs (its parts index them); ValueError without."""
        if "points" in data:
            points = data["points"]
        if points is None:
            raise ValueError("the decomposition's dictionary holds no points: pass "
                             "points=(N, 3) array, or write it with to_dict(with_points=True)")
        points = _checks.cloud(points)
        if len(points) != data["num_points"]:
            raise ValueError(f"the decomposition was of {data['num_points']} points, "
                             f"{len(points)} were given")
        tree = _tree_from_dict(data["hierarchy"], len(points))
        levels = tuple(tuple(Part.from_dict(p) for p in level)
                       for level in data.get("levels", ()))
        return cls(points, tuple(Part.from_dict(p) for p in data["parts"]), tree,
                   float(data["seconds"]), levels, data.get("method", "thesis"))

    @classmethod
    def load(cls, directory) -> Decomposition:
        """The Decomposition ``save`` wrote into ``directory`` (parts.json, points.npy)."""
        folder = Path(directory)
        try:
            data = json.loads((folder / "parts.json").read_text())
            points = np.load(folder / "points.npy")
        except (OSError, ValueError) as err:
            raise ValueError(f"no saved decomposition in {folder}: {err}") from err
        return cls.from_dict(data, points)

    def __repr__(self):
        kinds = ", ".join(p.winner for p in self.parts)
        return (f"Decomposition({len(self.parts)} parts from {len(self.points)} points: "
                f"{kinds}; {self.seconds:.2f} s)")

    def mass_properties(self, density: float = 1.0):
        """(mass (), centre of mass (3,), inertia tensor (3, 3) about it) of the parts'
        primitives as one rigid body at ``density`` (``shapes.mass_properties``: parts
        that overlap count once each; planes weigh nothing)."""
        return mass_properties([part.model for part in self.parts], density)

    def to_urdf(self, path, *, name: str = "object", density: float = 1000.0, mesh_dir=None,
                **options) -> Path:
        """Write the parts as a URDF robot of one link, one collision geometry per part
        (``jaxfit.io.sim.write_urdf``; ``options``: ``scale``, ``visual``,
        ``visual_mesh``). Returns ``path``."""
        from ..io.sim import write_urdf

        return write_urdf([p.model for p in self.parts], path, name=name, density=density,
                          mesh_dir=mesh_dir, **options)

    def to_mjcf(self, path, *, name: str = "object", density: float = 1000.0, mesh_dir=None,
                **options) -> Path:
        """Write the parts as a MuJoCo model of one free body, one geom per part
        (``jaxfit.io.sim.write_mjcf``; ``options``: ``scale``, ``free``,
        ``visual_mesh``). Returns ``path``."""
        from ..io.sim import write_mjcf

        return write_mjcf([p.model for p in self.parts], path, name=name, density=density,
                          mesh_dir=mesh_dir, **options)

    def save(self, directory) -> Path:
        """Write parts.json (``to_dict``), points.npy (the points: ``load`` reads both
        back), decomposition.glb and preview.png into ``directory``: all are written to
        temporary files first and renamed into place only when all are done
        (``io.atomic``), so a save that fails or is interrupted while writing leaves the
        old files."""
        from ..io.atomic import replacing_all
        from ..io.preview import render

        names = ("parts.json", "points.npy", "decomposition.glb", "preview.png")
        with replacing_all(directory, names) as files:
            files["parts.json"].write_text(json.dumps(self.to_dict(), indent=1))
            np.save(files["points.npy"], np.asarray(self.points, np.float64))
            self.to_scene().export(files["decomposition.glb"])
            render(self, files["preview.png"])
        return Path(directory)

    def summary(self) -> str:
        lines = [f"{len(self.parts)} parts from {len(self.points)} points "
                 f"in {self.seconds:.2f} s:"]
        for i, part in enumerate(self.parts):
            size = np.linalg.norm(part.box.extents)
            lines.append(f"  part {i}: {part.winner:<8} {part.indices.size:6d} points, mean "
                         f"distance {part.mean_distance:.3g} ({part.mean_distance / size:.1%} "
                         "of the part's diagonal)")
        return "\n".join(lines)


def load_source(source, *, num_points: int = 20000, seed: int = 0) -> np.ndarray:
    """(N, 3) points of any cloud ``jaxfit.as_cloud`` reads: an array, a trimesh or
    Open3D geometry (meshes and scenes surface-sampled), or a file path (anything
    ``jaxfit.io.load_points`` reads, Open Inventor ``.iv`` included)."""
    from ..io.inputs import as_cloud

    return as_cloud(source, num_points=num_points, seed=seed, with_normals=False)[0]


#: The methods of ``decompose``.
METHODS = ("thesis", "measured")


def decompose(source, *, method: str = "thesis", max_parts: int | None = None,
              gain: float | None = None, min_points: int | None = None,
              shapes=SHAPES, num_points: int = 20000, threshold_fraction=THRESHOLD_FRACTION,
              key=0, reassign: int | None = None, progress: bool = False) -> Decomposition:
    """Decompose an object into primitives.

    Both methods first fit every primitive to the whole object (``_whole_object``): if
    one explains it two-sided within the noise of a fit (``measure.EXPLAINED``), it is
    the one part. Otherwise ``method="thesis"`` runs the PSDA (BoxDecomposition, a fit
    of every primitive to every leaf, the lowest mean distance wins, reassignment), and
    keeps its parts if they lower the two-sided score below that primitive's by
    ``measure.SPLIT_MARGIN`` (else it is the one part);
    ``method="measured"`` splits greedily where the two-sided score falls most
    (``jaxfit.decomposition.measured``) and keeps every part count of the run
    (``Decomposition.levels``, ``with_parts``).

    Parameters
    ----------
    source : (N, 3) points, or any cloud ``jaxfit.as_cloud`` reads: a trimesh
        ``PointCloud``, ``Trimesh`` or ``Scene`` (a glTF's), an Open3D ``PointCloud`` or
        ``TriangleMesh``, a path to a mesh / point file / Open Inventor ``.iv`` model.
    method : "thesis" or "measured" (see above).
    max_parts : at most this many parts (a positive integer; default: the thesis's
        BoxDecomposition decides, the measured method stops at ``measured.MAX_PARTS``).
    gain : (thesis; default 0.96) BoxDecomposition's split threshold (children's volume /
        parent's volume must fall below it); nearer 1 splits more.
    min_points : smallest part; default 2 % of the points (at least 30).
    shapes : primitives to try on every part.
    num_points : points sampled from a mesh.
    threshold_fraction : inlier threshold of a part's fits, as a fraction of its bounding
        box's diagonal.
    key : int seed or JAX PRNG key, for the sampling of a mesh and of large parts
        (``_checks.numpy_seed``) and for the fits.
    reassign : (thesis; default 3) rounds (at most) of giving every point to the nearest
        part's primitive (its best fitted one, cylinders and cones grown along their
        surface) and fitting the parts that changed again, so parts follow the primitives
        rather than the box cuts (see the module docstring); 0 keeps the leaves as they are.
    progress : print the stages to stderr.
    """
    started = time.perf_counter()
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if max_parts is not None and (isinstance(max_parts, bool)
                                  or not isinstance(max_parts, numbers.Integral)
                                  or max_parts < 1):
        raise ValueError(f"max_parts must be a positive integer, got {max_parts!r}")
    if method == "measured" and (gain is not None or reassign is not None):
        raise ValueError("gain and reassign are the thesis method's: method='measured' "
                         "does not read them")
    gain = 0.96 if gain is None else gain
    reassign = 3 if reassign is None else reassign
    if isinstance(shapes, str | type):  # one shape, not its letters
        shapes = [shapes]
    classes = [_checks.model_class(s) for s in shapes]
    if isinstance(reassign, bool) or not isinstance(reassign, numbers.Integral) or reassign < 0:
        raise ValueError(f"reassign must be a non-negative integer, got {reassign!r}")
    if not 0 < gain <= 1:
        raise ValueError(f"gain must be in (0, 1], got {gain!r}")
    seed = _checks.numpy_seed(key)
    points = load_source(source, num_points=num_points, seed=seed)
    if min_points is None:
        min_points = max(30, int(0.02 * len(points)))
    min_points = _checks.positive(min_points, "min_points", integer=True)
    say = _say if progress else (lambda *_: None)

    scorer = Scorer(points, seed)
    root = mvbb(points)
    whole = _whole_object(points, classes, root, threshold_fraction, key, seed, scorer)
    single = BoxTree((BoxNode(root, np.arange(len(points))),), float(gain), int(min_points),
                     "root")
    if _explains(whole.candidates[whole.winner], _threshold(root, threshold_fraction),
                 scorer.spacing) or max_parts == 1:
        say(f"one {whole.winner} explains the object ({time.perf_counter() - started:.2f} s)")
        return Decomposition(points, (whole,), single, time.perf_counter() - started,
                             ((whole,),) if method == "measured" else (), method)
    if method == "measured":
        from .measured import split_greedily

        parts, tree, levels = split_greedily(
            points, whole, classes=classes, scorer=scorer, min_points=min_points,
            max_parts=max_parts, threshold_fraction=threshold_fraction, key=key, seed=seed,
            say=say, started=started)
        return Decomposition(points, parts, tree, time.perf_counter() - started, levels,
                             method)

    # The thesis's split rule, with volumes measured against the root box: measured
    # against the parent, every curved patch keeps splitting (see jaxfit.boxdecomp).
    tree = decompose_boxes(points, gain=gain, min_points=min_points, reference="root",
                           max_leaves=max_parts, root=root)
    groups = [tree.nodes[i].indices for i in tree.leaves]
    say(f"box decomposition: {len(groups)} parts ({time.perf_counter() - started:.2f} s)")
    box_of = _BoxCache(points, {n.indices.tobytes(): n.box for n in tree.nodes})
    fit = functools.partial(_fit_parts, points, classes=classes, bounds=tree.nodes[0].box,
                            threshold_fraction=threshold_fraction, key=key, seed=seed,
                            say=say, started=started, box_of=box_of)
    parts = fit(groups)
    for _ in range(reassign if len(parts) > 1 else 0):
        regrouped, kinds = _regroup(points, parts, threshold_fraction, max(5, min_points // 2))
        regrouped = _merge(points, regrouped, kinds, tree.nodes[0].box, gain, box_of)
        # A part whose points did not change keeps its fits: only the others are refitted.
        known = {p.indices.tobytes(): p for p in parts}
        changed = [g for g in regrouped if g.tobytes() not in known]
        if not changed:
            break
        fresh = dict(zip((g.tobytes() for g in changed), fit(changed), strict=True))
        candidate = [known.get(g.tobytes()) or fresh[g.tobytes()] for g in regrouped]
        # Fewer parts (a merge) is progress by itself: finer parts always lie nearer
        # their points. Otherwise a round must lower the PSDA's own measure.
        if (len(candidate) >= len(parts)
                and overall_distance(candidate) >= overall_distance(parts)):
            say("reassignment: no better by the mean distance; kept the previous parts")
            break
        parts = candidate
    if len(parts) > 1 and not _splits_better(whole, parts, scorer):
        say(f"the parts fit no better than one {whole.winner} (two-sided); one part")
        return Decomposition(points, (whole,), single, time.perf_counter() - started)
    return Decomposition(points, tuple(parts), tree, time.perf_counter() - started)


def _splits_better(whole: Part, parts, scorer: Scorer) -> bool:
    """Whether ``parts`` lower the object's two-sided score (``measure.parts_score``)
    below the whole object's best primitive's by at least ``SPLIT_MARGIN`` of the
    diagonal. The one-sided evaluation of the leaves cannot see a box inscribed in a
    round body (the YCB soup can's middle slab: a box 0.641 thresholds from its points
    against the cylinder's 0.692), which then claims the recessed lids in reassignment."""
    one = whole.candidates[whole.winner].two_sided / scorer.diagonal
    return one - parts_score(scorer, parts) >= SPLIT_MARGIN





def _whole_object(points, classes, box: Box, threshold_fraction, key, seed,
                  scorer: Scorer) -> Part:
    """The object as one part: the primitives fitted to it in turn (``MAX_FIT_POINTS``
    of its points, one ``fit_batch`` per primitive, their normals estimated once) and its
    MVBB, each scored two-sided (``Scorer.score`` on all points); the lowest
    ``two_sided`` wins. The first primitive that explains the object (``_explains``)
    wins at once, the others left untried: the ball is a sphere whatever a box
    would score (a warm decompose of the pyvista sphere: 0.2 s -> docs/decomposition.md)."""
    threshold = _threshold(box, threshold_fraction)
    rng = np.random.default_rng(seed)  # the thesis's draw for a part of all the points
    sample = points if len(points) <= MAX_FIT_POINTS else \
        points[rng.choice(len(points), MAX_FIT_POINTS, False)]
    shared = SharedNormals([sample])
    found = {}
    for cls in classes:
        (result,) = fits([sample], cls, [threshold], key, shared.of(cls))
        if result is not None:
            found[cls.name] = Candidate(result.model, *_scores(scorer, result.model, points, box))
            if _explains(found[cls.name], threshold, scorer.spacing):
                break
    # (scored even after an early accept: ``Part.candidates`` always holds the MVBB)
    found["mvbb"] = Candidate(box, *_scores(scorer, box, points, box))
    winner = min(found, key=lambda name: found[name].two_sided)
    model = found[winner].model
    return Part(np.arange(len(points)), box, model.name, winner, model,
                found[winner].mean_distance, found)


def _scores(scorer: Scorer, model: Model, points, bounds: Box) -> tuple[float, float, float]:
    """(mean distance, overshoot out of ``bounds``, surface distance) of a candidate."""
    mean, surface = scorer.score(model, points)
    reach = _overshoot(model, bounds) if np.isfinite(mean) else float("inf")
    return mean, reach, surface


def _explains(candidate: Candidate, threshold: float, spacing: float) -> bool:
    """Whether one primitive explains the object within the noise of a fit: its points'
    mean distance, and its surface's beyond the cloud's own spacing (a perfect fit's
    surface samples lie about that far from the nearest point), are both at most
    ``EXPLAINED`` thresholds."""
    return (candidate.mean_distance <= EXPLAINED * threshold
            and candidate.surface_distance - spacing <= EXPLAINED * threshold)


def _tree_from_dict(data: dict, num_points: int) -> BoxTree:
    """The BoxTree of ``Decomposition.to_dict``'s hierarchy: each leaf's points from
    ``leaf_labels``, each inner node's the union of its children's (the boxes split
    their points in two)."""
    labels = np.asarray(data.get("leaf_labels", ()), dtype=np.int64).reshape(-1)
    if len(labels) != num_points:
        raise ValueError(f"the hierarchy's leaf_labels must give one leaf per point "
                         f"({num_points}), got {len(labels)}")
    nodes = data["nodes"]
    indices: dict[int, np.ndarray] = {
        node: np.flatnonzero(labels == k) for k, node in enumerate(data["leaves"])}
    for node in reversed(nodes):  # breadth-first order: children after parents
        if node["children"]:
            indices[node["id"]] = np.sort(np.concatenate([indices[c] for c in node["children"]]))
    built = tuple(BoxNode(Box.from_dict(n["box"]), indices[n["id"]], tuple(n["children"]),
                          n["parent"], int(n["depth"])) for n in nodes)
    return BoxTree(built, float(data["gain"]), int(data["min_points"]), data["reference"])


def overall_distance(parts) -> float:
    """The PSDA's measure over the whole object: the mean distance of every point to its
    part's winning primitive (each part's ``mean_distance`` weighted by its size)."""
    sizes = np.array([p.indices.size for p in parts], np.float64)
    return float(np.dot(sizes, [p.mean_distance for p in parts]) / sizes.sum())


def _regroup(points, parts, threshold_fraction, smallest):
    """Give every point to the part whose primitive is nearest to it; a part left with
    fewer than ``smallest`` points is merged into the others (its primitive is explained
    by theirs). Returns the new index groups (ascending) and the kind of the primitive
    that claimed each.

    Box cuts are planes, so a part can keep a sliver of its neighbour (the top of a
    post in the shade's box). Ownership is judged with each part's best *fitted*
    primitive, grown along its surface (``_grown``), not with its bounding box: a box
    enclosing a mixed part is near every point in it and would keep the sliver.
    A point leaves its part only for a primitive nearer by ``KEEP_MARGIN`` of its part's
    threshold: where two primitives meet, both explain the points of the seam, and the
    nearer by a hair (the other's fit off by a few micrometres) had taken a foot of
    base-plate points into a post's cylinder, stretching it.
    """
    thresholds = np.array([_threshold(p.box, threshold_fraction) for p in parts])
    models = [_grown(_best_fitted(p), points, t) for p, t in zip(parts, thresholds, strict=True)]
    current = np.full(len(points), -1)
    for i, p in enumerate(parts):
        current[p.indices] = i
    alive = np.arange(len(models))
    while True:
        distances = np.stack([models[i].distance(points) for i in alive])  # (P, N)
        owner = alive[np.argmin(distances, axis=0)]
        # (the position in ``alive`` of each point's part; -1 where that part is gone)
        mine = np.where(np.isin(current, alive), np.searchsorted(alive, current), -1)
        at = np.arange(len(points))
        own = distances[np.maximum(mine, 0), at]
        stays = (mine >= 0) & (own <= distances.min(axis=0)
                               + KEEP_MARGIN * thresholds[np.maximum(current, 0)])
        owner = np.where(stays, current, owner)
        sizes = np.bincount(owner, minlength=len(models))[alive]
        if sizes.min() >= smallest or len(alive) == 1:
            return [np.flatnonzero(owner == i) for i in alive], [models[i].name for i in alive]
        alive = np.delete(alive, np.argmin(sizes))


class _BoxCache:
    """``mvbb(points[group])`` of index groups (ascending), each computed once: the tree's
    boxes are its leaves' MVBBs, and a reassignment round's groups recur in ``_merge``
    and ``_fit_parts`` (the MVBB is most of the PSDA's time; the same points give the
    same box, so the parts are unchanged)."""

    def __init__(self, points, known: dict):
        self.points, self.known = points, dict(known)

    def __call__(self, group) -> Box:
        key = np.asarray(group).tobytes()
        if key not in self.known:
            self.known[key] = mvbb(self.points[group])
        return self.known[key]


def _merge(points, groups, kinds, root: Box, gain: float, box_of=None):
    """Merge, pair by pair, parts claimed by the same kind of primitive that have come to
    overlap: the box around both is larger than the larger of their boxes by less than
    BoxDecomposition's split must save (``(1 - gain)`` of the root's volume). So the
    three slabs the box cuts make of a soup can, each of which then fits the whole can,
    become one part again. Parts of different kinds stay apart (they are different
    primitives, even if they cross), and so do neighbours that merely touch (the plain
    inverse of the split test merged too much: docs/decomposition.md). ``groups`` are
    index arrays into ``points`` (N, 3), ``kinds`` their primitives' names; ``box_of``
    gives a group's MVBB (default: computed)."""
    box_of = box_of or _BoxCache(points, {})
    volume = functools.partial(box_volume, floor=volume_floor(root))
    need = (1.0 - gain) * volume(root)
    groups = list(groups)
    sizes = [volume(box_of(g)) for g in groups]
    while len(groups) > 1:
        pairs = [(i, j) for i, j in itertools.combinations(range(len(groups)), 2)
                 if kinds[i] == kinds[j]]
        if not pairs:
            return groups
        unions = [np.union1d(groups[i], groups[j]) for i, j in pairs]
        whole = [volume(box_of(u)) for u in unions]
        grown = [w - max(sizes[i], sizes[j]) for (i, j), w in zip(pairs, whole, strict=True)]
        best = int(np.argmin(grown))
        if grown[best] > need:
            return groups
        (i, j), union = pairs[best], unions[best]
        groups = [g for k, g in enumerate(groups) if k not in (i, j)] + [union]
        kinds = [c for k, c in enumerate(kinds) if k not in (i, j)] + [kinds[i]]
        sizes = [s for k, s in enumerate(sizes) if k not in (i, j)] + [whole[best]]
    return groups


def _best_fitted(part: Part) -> Model:
    """The part's fitted primitive with the lowest mean distance, its bounding box left
    out, among the plausible ones (``Candidate.plausible``) unless the best of those is
    more than ``OWNER_SLACK`` times as far from the part's points as the bounding box
    (then among all of them, as before the plausibility gate)."""
    fitted = [c for k, c in part.candidates.items() if k != "mvbb"]
    if not fitted:
        return part.model
    best = min(fitted, key=lambda c: c.rank)
    if best.plausible and best.mean_distance <= OWNER_SLACK * part.candidates["mvbb"].mean_distance:
        return best.model
    return min(fitted, key=lambda c: c.mean_distance).model








def _fit_parts(points, groups, *, classes, bounds, threshold_fraction, key, seed, say,
               started, box_of=None):
    """Fitting and evaluation phases: every primitive on every part (one fit_batch per
    primitive), and the candidate nearest to the part's points wins. ``box_of`` gives a
    group's MVBB (default: computed)."""
    clouds = [points[g] for g in groups]
    boxes = [(box_of or _BoxCache(points, {}))(g) for g in groups]
    thresholds = [_threshold(b, threshold_fraction) for b in boxes]
    clouds = [_outside(cloud, t) for cloud, t in zip(clouds, thresholds, strict=True)]
    # RANSAC needs no more than a few thousand points of a part to find its primitive;
    # the candidates are still judged on all of them.
    rng = np.random.default_rng(seed)
    samples = [c if len(c) <= MAX_FIT_POINTS else c[rng.choice(len(c), MAX_FIT_POINTS, False)]
               for c in clouds]
    candidates = [{"mvbb": Candidate(box, mean_distance(box, cloud))}
                  for box, cloud in zip(boxes, clouds, strict=True)]
    shared = SharedNormals(samples)
    for cls in classes:
        results = fits(samples, cls, thresholds, key, shared.of(cls))
        for found, result, cloud in zip(candidates, results, clouds, strict=True):
            if result is not None:
                model, mean = result.model, mean_distance(result.model, cloud)
                reach = _overshoot(model, bounds) if np.isfinite(mean) else float("inf")
                found[cls.name] = Candidate(model, mean, reach)
        say(f"fitted {cls.name} to {len(clouds)} parts ({time.perf_counter() - started:.2f} s)")
    parts = []
    for group, box, found in zip(groups, boxes, candidates, strict=True):
        winner = min(found, key=lambda name: found[name].rank)
        model = found[winner].model
        parts.append(Part(group, box, model.name, winner, model, found[winner].mean_distance,
                          found))
    return parts


def _outside(cloud, threshold):
    """A hollow part's outside: its points within ``HOLLOW_DEPTH`` thresholds of its
    convex hull (``hull.shallow``), when at least ``HOLLOW`` of them lie deeper;
    otherwise all of them."""
    from scipy.spatial import QhullError

    try:
        outside = shallow(cloud, HOLLOW_DEPTH * threshold)
    except (QhullError, ValueError):  # flat or tiny parts have no inside
        return cloud
    return cloud[outside] if 1.0 - outside.mean() >= HOLLOW else cloud


def _overshoot(model: Model, bounds: Box) -> float:
    """How far the surface of ``model`` (its mesh's vertices) reaches out of ``bounds``,
    as a fraction of the diagonal of ``bounds``."""
    vertices = model.to_mesh().vertices
    local = np.abs((vertices - bounds.center) @ bounds.rotation) - 0.5 * bounds.extents
    return float(np.max(local, initial=0.0) / np.linalg.norm(bounds.extents))


def _say(message):
    print(message, file=sys.stderr, flush=True)
