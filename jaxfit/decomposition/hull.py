"""Depth of points below their convex hull: the PSDA's test for a hollow part.

One jitted kernel over blocks of points with the hull's faces on the vector axis, both
padded to ``bucket_size`` so that few sizes compile; float32 about the cloud's centre.
``shallow`` asks which points lie within a depth of the hull at a cost that does not grow
with the hull's size: the faces of a coarse hull (Qhull's merged one, at most
``HULL_VERTICES`` vertices) bound every depth, and only the points those bounds leave
undecided meet the exact hull's faces (measurements: docs/decomposition.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..engine import bucket_size
from ..engine.backend import LOOP_EMITTERS, jit_tuned

#: Points per step of the hull-depth kernel (see ``_hull_depth_blocks``).
HULL_BLOCK = 256
#: Most vertices of the coarse hull in ``shallow`` (an even subset of Qhull's merged
#: hull's when it has more).
HULL_VERTICES = 1024
#: Qhull's merging tolerance for the coarse hull in ``shallow``, as a fraction of the
#: depth asked about.
MERGE_DEPTH = 0.02
#: Margin of ``shallow``'s bounds, as a fraction of the cloud's diagonal: ten times the
#: float32 error of ``hull_depth``, so that a point the bounds decide is decided as the
#: exact faces would.
DEPTH_MARGIN = 1e-4


def hull_depth(cloud, equations, centre=None):
    """Depth (N,) of points cloud (N, 3) below the nearest of the hull faces
    ``equations`` (F, 4) (scipy's: outward unit normal, offset), in float32 about
    ``centre`` (3,) (default the cloud's mean).

    Positive inside the hull, about 0 on it; the float32 depths are within ~1e-5 of the
    cloud's size of the float64 ones (docs/decomposition.md).
    """
    centre = cloud.mean(axis=0) if centre is None else centre
    points = np.zeros((bucket_size(len(cloud)), 3), np.float32)
    points[: len(cloud)] = cloud - centre
    faces = np.zeros((bucket_size(len(equations)), 4), np.float32)
    faces[:, 3] = -np.inf  # padding faces: never the nearest
    faces[: len(equations), :3] = equations[:, :3]
    faces[: len(equations), 3] = equations[:, 3] + equations[:, :3] @ centre
    return np.asarray(_hull_depth(points, faces), np.float64).reshape(-1)[: len(cloud)]


def shallow(cloud, limit):
    """Whether each point of cloud (N, 3) lies at most ``limit`` below its convex hull:
    (N,) bool, decided as ``hull_depth(cloud, ConvexHull(cloud).equations) <= limit``
    decides it wherever the exact pass below runs. Raises ``QhullError`` (or
    ``ValueError``) where the cloud has no hull (flat, too few points).

    A coarse hull bounds every depth (``_bounds``: ``lower <= depth <= upper``). Points
    whose bounds leave them within ``DEPTH_MARGIN`` of undecided meet the exact hull's
    faces when that costs no more than the coarse pass (points x faces, padded);
    otherwise they are decided on the coarse hull (``lower <= limit``), off by at most
    ``max(upper - lower)``. The cost is Qhull's and O(N * HULL_VERTICES) for any cloud;
    the exact hull is built only when some point is undecided.
    """
    from scipy.spatial import ConvexHull  # lazily: 0.3 s of import

    cloud = np.asarray(cloud, np.float64)
    centre = cloud.mean(axis=0)
    margin = DEPTH_MARGIN * float(np.linalg.norm(np.ptp(cloud, axis=0)))
    lower, upper, coarse = _bounds(cloud, centre, MERGE_DEPTH * limit)
    result = upper <= limit - margin
    unsure = ~result & (lower <= limit + margin)
    if not unsure.any():
        return result
    faces = ConvexHull(cloud).equations
    if bucket_size(unsure.sum()) * bucket_size(len(faces)) > (
            bucket_size(len(cloud)) * bucket_size(len(coarse))):
        return lower <= limit
    result[unsure] = hull_depth(cloud[unsure], faces, centre) <= limit
    return result


def _bounds(cloud, centre, merge):
    """(lower (N,), upper (N,), coarse faces (F', 4)): bounds on the depths of cloud
    (N, 3) below its convex hull, in float32 about ``centre``, from a coarse hull: of
    the vertices of Qhull's hull with faces merged where their centrums lie within
    ``merge`` of their neighbours' planes (option ``C-``), an even subset of
    HULL_VERTICES of them if more.

    The coarse hull lies inside the hull (its vertices are points), so the depth below
    it, ``lower``, is at most the exact depth. Each coarse face moved out to the
    furthest point beyond it (``_support``) is a supporting plane of the hull, and a
    point's depth below its hull is at most its depth below any supporting plane:
    ``upper``.
    """
    from scipy.spatial import ConvexHull, QhullError  # lazily: 0.3 s of import

    try:
        merged = ConvexHull(cloud, qhull_options=f"C-{max(merge, 0.0):.9g}")
    except QhullError:  # (the bounds hold for any subset: try the exact hull's)
        merged = ConvexHull(cloud)
    kept = cloud[merged.vertices]
    coarse = ConvexHull(kept[:: -(-len(kept) // HULL_VERTICES)]).equations
    lower = hull_depth(cloud, coarse, centre)
    reach = _support(coarse[:, :3], cloud - centre) + coarse[:, :3] @ centre
    support = np.c_[coarse[:, :3], -np.maximum(reach, -coarse[:, 3])]
    return lower, hull_depth(cloud, support, centre), coarse


def _support(directions, points):
    """max over points (N, 3) of directions (F, 3) . point: (F,), in float32. The points
    are padded with the origin, so it must lie in their hull (centre them)."""
    padded = np.zeros((bucket_size(len(points)), 3), np.float32)
    padded[: len(points)] = points
    faces = np.zeros((bucket_size(len(directions)), 3), np.float32)
    faces[: len(directions)] = directions
    return np.asarray(_support_max(padded, faces), np.float64)[: len(directions)]


def _support_blocks(points, directions):
    """max over points (B, 3), B a multiple of HULL_BLOCK, of directions (F, 3) . point:
    (F,)."""

    def block(p):
        return jnp.max(p[:, 0:1] * directions[:, 0] + p[:, 1:2] * directions[:, 1]
                       + p[:, 2:3] * directions[:, 2], axis=0)

    return jnp.max(jax.lax.map(block, points.reshape(-1, HULL_BLOCK, 3)), axis=0)


def _hull_depth_blocks(points, faces):
    """-max over faces (F, 4) of the signed distances of points (B, 3), B a multiple of
    HULL_BLOCK: (B / HULL_BLOCK, HULL_BLOCK)."""

    def block(p):
        return -jnp.max(p[:, 0:1] * faces[:, 0] + p[:, 1:2] * faces[:, 1]
                        + p[:, 2:3] * faces[:, 2] + faces[:, 3], axis=1)

    return jax.lax.map(block, points.reshape(-1, HULL_BLOCK, 3))


# (XLA's loop emitters on the CPU: half the compile, the same run time and bits)
_hull_depth = jit_tuned(_hull_depth_blocks, (), LOOP_EMITTERS)
_support_max = jit_tuned(_support_blocks, (), LOOP_EMITTERS)
