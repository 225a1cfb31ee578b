"""Depth of points below their convex hull: the PSDA's test for a hollow part.

One jitted kernel over blocks of points with the hull's faces on the vector axis, both
padded to ``bucket_size`` so that few sizes compile; float32 about the cloud's centre
(measurements: docs/decomposition.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._cache import stored_jit
from ..engine import bucket_size

#: Points per step of the hull-depth kernel (see ``_hull_depth_blocks``).
HULL_BLOCK = 256


def hull_depth(cloud, equations):
    """Depth (N,) of points cloud (N, 3) below the nearest of the hull faces
    ``equations`` (F, 4) (scipy's: outward unit normal, offset), in float32 about the
    cloud's centre.

    Positive inside the hull, about 0 on it; the float32 depths are within ~1e-5 of the
    cloud's size of the float64 ones (docs/decomposition.md).
    """
    centre = cloud.mean(axis=0)
    points = np.zeros((bucket_size(len(cloud)), 3), np.float32)
    points[: len(cloud)] = cloud - centre
    faces = np.zeros((bucket_size(len(equations)), 4), np.float32)
    faces[:, 3] = -np.inf  # padding faces: never the nearest
    faces[: len(equations), :3] = equations[:, :3]
    faces[: len(equations), 3] = equations[:, 3] + equations[:, :3] @ centre
    return np.asarray(_hull_depth(points, faces), np.float64).reshape(-1)[: len(cloud)]


def _hull_depth_blocks(points, faces):
    """-max over faces (F, 4) of the signed distances of points (B, 3), B a multiple of
    HULL_BLOCK: (B / HULL_BLOCK, HULL_BLOCK)."""

    def block(p):
        return -jnp.max(p[:, 0:1] * faces[:, 0] + p[:, 1:2] * faces[:, 1]
                        + p[:, 2:3] * faces[:, 2] + faces[:, 3], axis=1)

    return jax.lax.map(block, points.reshape(-1, HULL_BLOCK, 3))


_hull_depth = stored_jit(_hull_depth_blocks)
