"""Synthetic clouds of known primitives: the demo, the tests and the benchmarks use them.

Every random choice comes from ``numpy.random.default_rng(seed)``.
"""

from __future__ import annotations

import numpy as np

from . import _checks
from .shapes import Box, Cone, Cylinder, Model, Plane, Sphere


def random_rotation(rng) -> np.ndarray:
    """A uniformly random proper rotation (3, 3)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def random_model(shape, rng) -> Model:
    """A primitive of unit-order size in a random pose (not axis-aligned)."""
    cls = _checks.model_class(shape)
    rot = random_rotation(rng)
    center = rng.uniform(-1, 1, 3)
    size = rng.uniform(0.7, 1.3)
    if cls is Plane:
        return Plane(rot[:, 2], -rot[:, 2] @ center, center, size)
    if cls is Sphere:
        return Sphere(center, size)
    if cls is Cylinder:
        return Cylinder(center, rot[:, 2], 0.5 * size, 2.0 * size)
    if cls is Cone:
        half_angle = rng.uniform(np.radians(20), np.radians(40))
        height = 2.0 * size
        return Cone(center - 0.5 * height * rot[:, 2], rot[:, 2], half_angle, height)
    return Box(center, rot, size * rng.uniform(0.6, 1.4, 3))


def noisy_cloud(model: Model, *, count: int = 2000, outlier_ratio: float = 0.5,
                noise: float = 0.005, seed: int = 0):
    """Points on ``model`` displaced along the normal by U(-noise, noise), plus uniform
    outliers in the model's bounding cube grown by 50 %, shuffled.

    Returns points (count, 3) and the ground-truth inlier mask (count,).
    """
    rng = np.random.default_rng(seed)
    n_out = int(round(outlier_ratio * count))
    surface, normals = model.sample(count - n_out, rng)
    surface = surface + normals * rng.uniform(-noise, noise, (len(surface), 1))
    lo, hi = surface.min(axis=0), surface.max(axis=0)
    mid, half = 0.5 * (lo + hi), 0.75 * (hi - lo).max()
    outliers = rng.uniform(mid - half, mid + half, (n_out, 3))
    points = np.vstack([surface, outliers])
    truth = np.arange(count) < count - n_out
    order = rng.permutation(count)
    return points[order], truth[order]


def demo_cloud(shape="cylinder", *, count: int = 2000, outlier_ratio: float = 0.5,
               noise: float = 0.005, seed: int = 0):
    """(points (count, 3), true model, true inlier mask) of a random primitive."""
    model = random_model(shape, np.random.default_rng(seed))
    points, truth = noisy_cloud(model, count=count, outlier_ratio=outlier_ratio,
                                noise=noise, seed=seed + 1)
    return points, model, truth
