"""Synthetic clouds of known primitives: the demo, the tests and the benchmarks use them.

Every random choice comes from ``numpy.random.default_rng(seed)``.
"""

from __future__ import annotations

import numpy as np

from . import _checks
from .shapes import Box, Cone, Cylinder, Model, Plane, Sphere
from .shapes import _geometry as g


def random_rotation(rng) -> np.ndarray:
    """A uniformly random proper rotation (3, 3)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def random_model(shape, rng, *, axis_aligned: bool = False) -> Model:
    """A primitive of unit-order size in a random pose, following the models' sign rules.

    With s ~ U(0.7, 1.3): sphere radius s; cylinder radius s/2 and height 2s; cone height
    2s and half-angle U(20, 40) degrees; box sides s * U(0.6, 1.4) each; plane disk radius
    s. The centre is uniform in [-1, 1]^3; the rotation is random unless ``axis_aligned``.
    """
    cls = _checks.model_class(shape)
    rot = np.eye(3) if axis_aligned else random_rotation(rng)
    center = rng.uniform(-1.0, 1.0, 3)
    size = rng.uniform(0.7, 1.3)
    if cls is Sphere:
        return Sphere(center, np.float64(size))
    if cls is Box:
        first = g.sign_canonical(rot[:, :2].T)  # the box's sign rule; det stays +1
        rot = np.stack([first[0], first[1], np.cross(first[0], first[1])], axis=1)
        return Box(center, rot, size * rng.uniform(0.6, 1.4, 3))
    axis = rot[:, 2]
    if cls is Cone:  # the cone's axis points into it, so it has no sign rule to apply
        half_angle = rng.uniform(np.radians(20.0), np.radians(40.0))
        height = 2.0 * size
        return Cone(center - 0.5 * height * axis, axis, np.float64(half_angle), np.float64(height))
    axis = g.sign_canonical(axis)
    if cls is Cylinder:
        return Cylinder(center, axis, np.float64(0.5 * size), np.float64(2.0 * size))
    return Plane(axis, np.float64(-axis @ center), center, np.float64(size))


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


def _composites():
    """Objects made of touching primitives with known parameters (metres, z up)."""
    up = np.array([0.0, 0.0, 1.0])
    return {
        # a handle standing on the floor with a head across its top
        "mallet": [Cylinder(np.array([0.0, 0.0, 0.15]), up, 0.025, 0.3),
                   Box(np.array([0.0, 0.0, 0.33]), np.eye(3), np.array([0.2, 0.07, 0.06]))],
        # a ball on a stick
        "lollipop": [Cylinder(np.array([0.0, 0.0, 0.135]), up, 0.012, 0.27),
                     Sphere(np.array([0.0, 0.0, 0.33]), 0.06)],
        # a flat base, a post, a conical shade and a ball on its apex
        "lamp": [Box(np.array([0.0, 0.0, 0.01]), np.eye(3), np.array([0.2, 0.2, 0.02])),
                 Cylinder(np.array([0.0, 0.0, 0.145]), up, 0.01, 0.25),
                 Cone(np.array([0.0, 0.0, 0.37]), -up, np.radians(40.0), 0.1),
                 Sphere(np.array([0.0, 0.0, 0.39]), 0.02)],
    }


COMPOSITES = tuple(_composites())


def composite(name: str = "mallet", *, count: int = 20000, seed: int = 0):
    """A built-in object made of known primitives, its surface sampled.

    The primitives' closed surfaces (caps included) are sampled in proportion to their
    areas; they touch without overlapping, and the patches where one is glued onto
    another (a handle's cap on the head's face) are dropped, as a scan would not see them.
    Returns points (M <= count, 3), the true models (list), and the index of the model
    each point came from (M,).
    """
    import trimesh

    objects = _composites()
    if name not in objects:
        raise ValueError(f"unknown object {name!r}; expected one of {sorted(objects)}")
    models = objects[name]
    meshes = [m.to_mesh() for m in models]
    areas = np.array([mesh.area for mesh in meshes])
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(count, areas / areas.sum())
    points = [trimesh.sample.sample_surface(mesh, int(k), seed=seed + i)[0]
              for i, (mesh, k) in enumerate(zip(meshes, counts, strict=True))]
    points, labels = np.vstack(points), np.repeat(np.arange(len(models)), counts)
    hidden = np.zeros(len(points), bool)
    for j, other in enumerate(models):
        hidden |= (labels != j) & (other.distance(points) < 1e-6 * np.ptp(points))
    return points[~hidden], models, labels[~hidden]
