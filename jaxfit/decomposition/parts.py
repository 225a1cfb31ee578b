"""What a decomposition is made of, shared by both methods (``psda``, ``measured``):
a part's candidates and the part, the fit of every part with one primitive
(``fits``), and a part's threshold."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..engine import fit_batch
from ..shapes import Box, Model
from ..shapes._base import short

#: Part threshold: this fraction of the diagonal of the part's bounding box. Wider than
#: for a single fit, as in the thesis: a part is only approximately a primitive.
THRESHOLD_FRACTION = 0.02
#: Points of a part handed to RANSAC (a random subset when the part is larger).
MAX_FIT_POINTS = 2048
#: A fitted candidate whose surface reaches further out of the object's bounding box
#: (the root MVBB) than this fraction of the box's diagonal cannot win its part, nor
#: (but see ``OWNER_SLACK``) claim points in reassignment.
MAX_OVERSHOOT = 0.05

@dataclasses.dataclass(frozen=True)
class Candidate:
    """One primitive tried on a part: the fitted model, its mean distance, how far its
    surface reaches out of the object's bounding box (the root MVBB), as a fraction of
    that box's diagonal (0 when inside; always 0 for the part's own MVBB), and the mean
    distance of its closed surface to the object's points (``measure.Scorer``; NaN where
    it was not measured: the thesis's candidates)."""

    model: Model
    mean_distance: float
    overshoot: float = 0.0
    surface_distance: float = float("nan")

    @property
    def two_sided(self) -> float:
        """The two-sided score: ``mean_distance + surface_distance`` (NaN if the surface
        side was not measured)."""
        return self.mean_distance + self.surface_distance

    @property
    def plausible(self) -> bool:
        """Whether the candidate may win its part (``overshoot <= MAX_OVERSHOOT``)."""
        return self.overshoot <= MAX_OVERSHOOT

    @property
    def rank(self) -> tuple[bool, float]:
        """Sort key of the PSDA's choice: plausible candidates first, then the lowest
        mean distance."""
        return not self.plausible, self.mean_distance


@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class Part:
    """A leaf of the box decomposition and the primitive that won it.

    indices : (M,) indices into ``Decomposition.points`` (the leaf's points, or with
        ``reassign`` the points nearest to this part's primitive); ``mask(N)`` gives
        them as a mask, ``Decomposition.masks()`` every part's.
    box : the minimum-volume bounding box of those points.
    kind : the winning primitive's name (``Model.name``; "box" when the MVBB wins).
    winner : the winning candidate: ``kind``, or "mvbb" when the bounding box won.
    model : the winning primitive (a ``Box`` when the MVBB wins).
    mean_distance : its mean distance to the part's points.
    candidates : name -> Candidate for every primitive tried, and "mvbb".
    """

    indices: np.ndarray
    box: Box
    kind: str
    winner: str
    model: Model
    mean_distance: float
    candidates: dict[str, Candidate]

    def mask(self, num_points: int) -> np.ndarray:
        """(num_points,) bool marking ``indices`` (``Decomposition.masks`` gives all)."""
        out = np.zeros(num_points, bool)
        out[self.indices] = True
        return out

    def to_dict(self) -> dict:
        """JSON-ready: primitive, score, indices, box, every candidate, and the winning
        primitive's pose (``transform``, 4x4 rows), volume and centroid."""
        return {
            "kind": self.kind,
            "winner": self.winner,
            "model": self.model.to_dict(),
            "mean_distance": self.mean_distance,
            "num_points": int(self.indices.size),
            "indices": np.asarray(self.indices).tolist(),
            "box": self.box.to_dict(),
            "candidates": {name: _candidate_dict(c) for name, c in self.candidates.items()},
            "transform": self.model.transform().tolist(),
            "volume": self.model.volume(),
            "centroid": self.model.centroid().tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict) -> Part:
        """Inverse of ``to_dict`` (its derived entries, pose, volume and centroid, are
        recomputed from the model rather than read)."""
        if "indices" not in data:
            raise ValueError("a part's dictionary has no 'indices' (written before "
                             "jaxfit stored them?)")
        candidates = {name: Candidate(Model.from_dict(c["model"]), float(c["mean_distance"]),
                                      float(c.get("overshoot", 0.0)),
                                      float(c.get("surface_distance", "nan")))
                      for name, c in data["candidates"].items()}
        box = Box.from_dict(data["box"])
        if "mvbb" in candidates:  # the part's own box is its MVBB candidate (one object)
            candidates["mvbb"] = dataclasses.replace(candidates["mvbb"], model=box)
        winner = data["winner"]
        model = candidates[winner].model if winner in candidates else \
            Model.from_dict(data["model"])
        return cls(np.asarray(data["indices"], dtype=np.int64).reshape(-1), box, data["kind"],
                   winner, model, float(data["mean_distance"]), candidates)

    def __repr__(self):
        return (f"Part(kind={self.kind!r}, winner={self.winner!r}, {self.indices.size} points, "
                f"mean_distance={short(self.mean_distance)}, model={self.model!r})")



def _candidate_dict(c: Candidate) -> dict:
    out = {"model": c.model.to_dict(), "mean_distance": c.mean_distance,
           "overshoot": c.overshoot}
    if np.isfinite(c.surface_distance):
        out["surface_distance"] = c.surface_distance
    return out

def _grown(model: Model, points, threshold) -> Model:
    """A primitive bounded along its axis (``Model.axial_bounds``: cylinder, cone)
    re-bounded on the inliers of its unbounded surface in the whole cloud (others
    unchanged), so it reaches the points of it that a box cut gave to a neighbour. The
    bounds are the shape's own (``from_theta``): the main run of inliers along the axis,
    so a gap of a few thresholds stops the growth."""
    if not model.axial_bounds:
        return model
    inliers = np.abs(model.residual(points)) < threshold
    if not inliers.any():
        return model
    return type(model).from_theta(model.theta(), points, inliers, threshold)

def _threshold(box: Box, fraction: float) -> float:
    """A part's inlier threshold: ``fraction`` of its bounding box's diagonal."""
    return fraction * float(np.linalg.norm(box.extents))

def sample_normals(samples) -> list:
    """(M_i, 3) normals of every point of each sample (M_i, 3), estimated as ``fit_batch``
    estimates those it is not given (``normals_at_many``, the engine's neighbourhood):
    computed once, they serve the fits of every primitive, where each ``fit_batch`` call
    would estimate them again (45 of the 200 ms of a warm decompose of the pyvista
    sphere). Samples have at most ``MAX_FIT_POINTS`` points. Up to ``NORMAL_POOL``
    points these are the engine's own normals, which ``fit_batch`` renormalises (~1e-16)
    as it does any it is given, so the fits are the same up to rounding
    (docs/decomposition.md: where that changed a result); a larger sample's fits, given
    every point's normal, draw from every point where the engine would draw from a pool
    of NORMAL_POOL (as they did while the pool was 2048: docs/engine.md, "Session 38")."""
    from ..engine.cloud import NORMAL_NEIGHBOURS
    from ..normals import normals_at_many

    if any(len(s) > MAX_FIT_POINTS for s in samples):
        raise ValueError(f"samples must have at most {MAX_FIT_POINTS} points to share normals")
    return normals_at_many(list(samples), [np.arange(len(s)) for s in samples],
                           [min(NORMAL_NEIGHBOURS, len(s)) for s in samples])


class SharedNormals:
    """``sample_normals(samples)``, estimated on the first ``of(cls)`` for a primitive
    whose default estimator reads normals (None for the others, and for samples the
    engine would refuse: it then reports them itself)."""

    def __init__(self, samples):
        self.samples, self._normals, self._done = list(samples), None, False

    def of(self, cls):
        if not cls.estimator().uses_normals:
            return None
        if not self._done:
            self._done = True
            try:
                self._normals = sample_normals(self.samples)
            except ValueError:
                self._normals = None
        return self._normals


def fits(samples, cls, thresholds, key, normals=None) -> list:
    """``fit_batch`` of ``samples`` (failures None), with their ``normals`` if given
    (``sample_normals``), each sample in a loop of its own (``separate``): a
    decomposition's part count changes from object to object and from round to round,
    and each slot count of a batch was a kernel and a refinement per primitive to
    compile (docs/engine.md, "Session 35"). A lone cloud is fitted twice (its own key
    and a second draw's, fold_in(key, 1); the lower MSAC cost kept): that once let it
    share a two-part object's programs, and stays so that the decompositions' results
    stay as they were."""
    if len(samples) != 1:
        return fit_batch(samples, cls, normals=normals, thresholds=thresholds, key=key,
                         skip_failures=True, separate=True)
    results = fit_batch(samples * 2, cls, normals=None if normals is None else normals * 2,
                        thresholds=list(thresholds) * 2, key=key, skip_failures=True,
                        separate=True)
    done = [r for r in results if r is not None]
    return [min(done, key=lambda r: r.cost) if done else None]
