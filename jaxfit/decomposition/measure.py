"""The two-sided score of a primitive standing for a set of points: the decomposition's
cheap variant of ``jaxfit.evaluation.twosided`` (docs/measures.md), used by
``decompose`` to judge the whole object (``whole_object``) and by ``method="measured"``
to judge every candidate and split (``jaxfit.decomposition.measured``).

A candidate primitive m for a part's points P (M, 3) of an object's cloud C (N, 3) scores

- ``mean_distance``: the mean distance of P to m's closed, bounded surface (the PSDA's
  one-sided score: the points side), and
- ``surface_distance``: the mean distance of ``SURFACE_SAMPLES`` points uniform on m's
  closed surface (``twosided.closed_surface``) to the nearest point of the whole cloud C
  (the surface side: a box's corners around a ball, a cylinder longer than its part, a
  cap across a cut through a solid body lie far from every point).

Their sum, ``two_sided``, is a Chamfer distance between the part and its primitive; the
surface side is measured against the whole cloud, not the part, so a primitive that runs
on into its neighbours' points (a post through the shade's part) is not penalised for it.
Every random choice (the surface samples) comes from the scorer's seed.
"""

from __future__ import annotations

import numpy as np

from ..evaluation.twosided import closed_surface
from ..normals import kd_tree

__all__ = ["SURFACE_SAMPLES", "EXPLAINED", "SPLIT_MARGIN", "Scorer", "mean_distance",
           "parts_score"]

#: Points drawn on a candidate's closed surface for its ``surface_distance``: the
#: standard error of the mean is about the spread of the gaps over 22, a few per cent
#: of a good candidate's score.
SURFACE_SAMPLES = 512
#: Points whose nearest neighbours give the cloud's ``spacing``.
SPACING_POINTS = 2048
#: One primitive explains the whole object when both sides of its score, the points'
#: mean distance and the surface's, are at most this fraction of the fit threshold
#: (``THRESHOLD_FRACTION`` of the object's diagonal), the surface's beyond the cloud's
#: ``spacing`` (a perfect fit's surface samples lie about that far from the nearest
#: point): within the noise of a fit
#: (docs/decomposition.md gives the values measured on both sides of the line).
EXPLAINED = 0.25
#: Parts stand for the object instead of one primitive only if they lower its two-sided
#: score (``parts_score``, over the object's diagonal) by at least this much: the
#: measured method's split margin, and the PSDA's test of its parts against the whole
#: object's best primitive.
SPLIT_MARGIN = 0.001


class Scorer:
    """Two-sided scores against one object's cloud ``points`` (N, 3): its KD-tree is
    built once, and every surface sample comes from ``numpy.random.default_rng(seed)``."""

    def __init__(self, points, seed: int = 0):
        self.points = np.asarray(points, np.float64)
        self.tree = kd_tree(self.points)
        self.diagonal = float(np.linalg.norm(np.ptp(self.points, axis=0)))
        self._rng = np.random.default_rng(seed)
        # The cloud's spacing: the mean distance of (an even subset of) its points to
        # their nearest other point, about the surface_distance of a perfect fit.
        probe = self.points[::-(-len(self.points) // SPACING_POINTS)]
        self.spacing = float(np.mean(self.tree.query(probe, k=2)[0][:, 1])) \
            if len(self.points) > 1 else 0.0

    def surface_distance(self, model, count: int = SURFACE_SAMPLES) -> float:
        """Mean distance of ``count`` points uniform on ``model``'s closed surface to the
        nearest cloud point; inf for a model without a finite surface."""
        try:
            samples, _ = closed_surface(model, count, self._rng)
        except (TypeError, ValueError, FloatingPointError):
            return float("inf")
        if not np.all(np.isfinite(samples)):
            return float("inf")
        return float(np.mean(self.tree.query(samples)[0]))

    def score(self, model, points) -> tuple[float, float]:
        """(mean distance of ``points`` (M, 3) to ``model``'s bounded surface, its
        ``surface_distance``); (inf, inf) where the distances are not finite."""
        mean = mean_distance(model, points)
        return (mean, self.surface_distance(model)) if np.isfinite(mean) else (mean, mean)


def mean_distance(model, points) -> float:
    """Mean distance of ``points`` (M, 3) to ``model``'s bounded surface (the PSDA's
    one-sided score); inf where a distance is not finite."""
    distance = model.distance(points)
    return float(np.mean(distance)) if np.all(np.isfinite(distance)) else float("inf")


def parts_score(scorer: Scorer, parts) -> float:
    """The two-sided score of a set of parts over the object's diagonal: the
    points-weighted mean, over the parts, of the mean distance of a part's points to its
    primitive (``Part.mean_distance``) plus the mean distance of the primitive's closed
    surface to the whole cloud (``Scorer.surface_distance``, drawn afresh)."""
    sizes = np.array([p.indices.size for p in parts], np.float64)
    sides = [p.mean_distance + scorer.surface_distance(p.model) for p in parts]
    return float(np.dot(sizes, sides) / sizes.sum() / scorer.diagonal)
