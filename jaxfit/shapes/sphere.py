"""Sphere: |p - center| = radius. theta = (cx, cy, cz, radius).

Estimators: the thesis's four points (Cramer's rule), or two points with normals (the
centre is where the two normal lines pass closest).
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from . import _geometry as g
from ._base import LENGTH, POINT, Cut, Model, as_points, register


@register
class Sphere(Model):
    """Sphere.

    center : (3,).
    radius : () positive.

    One sphere per model: the methods take unbatched fields (see ``Model``).
    """

    center: np.ndarray
    radius: np.ndarray

    name: ClassVar[str] = "sphere"
    colour: ClassVar[tuple[int, int, int, int]] = (231, 76, 60, 255)
    sample_size: ClassVar[int] = 4
    oriented_sample_size: ClassVar[int] = 2
    radius_index: ClassVar[int] = 3
    num_params: ClassVar[int] = 4
    batched_canonical: ClassVar[bool] = True
    pointwise_theta: ClassVar[bool] = True
    # The MSAC cost of a sphere has one basin near the truth: one start is as accurate
    # as four at a quarter of the refinement (measurements: docs/shapes.md).
    lo_starts: ClassVar[int] = 1
    # Three steps a round are as accurate as five on the thesis suite (docs/engine.md).
    lm_steps: ClassVar[int] = 3
    field_specs: ClassVar = {"center": ((3,), POINT), "radius": ((), LENGTH)}

    @staticmethod
    def estimate(sample, support):
        # The linear system 2 (p_i - p_1) . x = |p_i - p_1|^2 (x = centre - p_1), solved by
        # Cramer's rule so a singular sample gives a flag, not a NaN.
        q = sample[1:] - sample[0]
        c34, c42, c23 = jnp.cross(q[1], q[2]), jnp.cross(q[2], q[0]), jnp.cross(q[0], q[1])
        det = jnp.dot(q[0], c34)
        lengths = g.safe_norm(q)
        valid = (jnp.abs(det) > g.SIN_TOL * jnp.prod(lengths)) & (jnp.min(lengths) > g.LEN_TOL)
        sq = jnp.sum(q * q, axis=1)
        x = (sq[0] * c34 + sq[1] * c42 + sq[2] * c23) / (2.0 * jnp.where(valid, det, 1.0))
        radius = g.safe_norm(x)
        return jnp.concatenate([sample[0] + x, radius[None]]), valid & (radius < g.MAX_EXTENT)

    @staticmethod
    def estimate_oriented(sample, normals, support):
        c1, c2, valid = g.closest_points(sample[0], normals[0], sample[1], normals[1])
        center = 0.5 * (c1 + c2)
        radius = 0.5 * (g.safe_norm(sample[0] - center) + g.safe_norm(sample[1] - center))
        valid &= (radius > g.LEN_TOL) & (radius < g.MAX_EXTENT)
        return jnp.concatenate([center, radius[None]]), valid

    @staticmethod
    def theta_residual(theta, p, xp):
        dx, dy, dz = p[0] - theta[0], p[1] - theta[1], p[2] - theta[2]
        return xp.sqrt(dx * dx + dy * dy + dz * dz) - theta[3]

    @staticmethod
    def theta_jacobian(theta, p, xp):
        dx, dy, dz = p[0] - theta[0], p[1] - theta[1], p[2] - theta[2]
        inv = -1.0 / xp.maximum(xp.sqrt(dx * dx + dy * dy + dz * dz), 1e-300)
        return xp.stack([dx * inv, dy * inv, dz * inv, xp.full_like(dx, -1.0)])

    @staticmethod
    def canonicalize(theta, xp=jnp):
        return xp.concatenate([theta[..., :3], xp.abs(theta[..., 3:])], axis=-1)

    @classmethod
    def from_theta(cls, theta, points, inliers, threshold):
        return cls(np.asarray(theta[:3], np.float64), np.float64(abs(theta[3])))

    @classmethod
    def from_theta_many(cls, thetas, points, inliers, thresholds, scales=None, shifts=None):
        # (the points are not read: no per-cloud slices of the masks; ``rescaled``'s
        # arithmetic on arrays of all clouds)
        thetas = np.asarray(thetas, np.float64)
        centers, radii = thetas[:, :3], np.abs(thetas[:, 3])
        if scales is not None:
            scales = np.asarray(scales, np.float64)
            centers = centers * scales[:, None] + np.asarray(shifts, np.float64)
            radii = radii * scales + 0.0
        return [cls(c, r) for c, r in zip(centers, radii, strict=True)]

    def theta(self):
        return np.concatenate([self._array("center"), [float(self.radius)]])

    def rescaled(self, scale, shift):
        # ``Model.rescaled``'s rule written out: its field loop and ``dataclasses.replace``
        # were most of a 500-point fit's ~7 us here.
        return type(self)(self.center * scale + shift, self.radius * scale + 0.0)

    def sample(self, count, rng):
        """(count, 3) points uniform on the sphere and their outward normals (count, 3)."""
        normals = g.random_units(count, rng)
        return self.center + self.radius * normals, normals

    def distance(self, points):
        return np.abs(self.residual(points))

    def contains(self, points):
        """(N,) bool: |p - center| <= radius (the surface included, to a relative 1e-9)."""
        local = as_points(points) - self.transform()[:3, 3]
        return np.einsum("ij,ij->i", local, local) <= (float(self.radius) * (1 + 1e-9)) ** 2

    def to_mesh(self, subdivisions: int = 3):
        import trimesh

        mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=float(self.radius))
        return mesh.apply_transform(self.transform())

    # ----- pose and mass ------------------------------------------------------------------
    def transform(self):
        """The cloud's axes at the centre (a sphere has no axes of its own)."""
        return g.transform(np.eye(3), self._array("center"))

    def volume(self):
        return 4.0 / 3.0 * np.pi * float(self.radius) ** 3

    def surface_area(self):
        return self.area()

    def centroid(self):
        return self._array("center")

    def unit_inertia(self):
        return np.full(3, 0.4 * float(self.radius) ** 2)

    # ----- facts for scenes, scenarios and the evaluation ---------------------------------
    removed_share: ClassVar[float] = 0.5
    shown_measures: ClassVar[tuple[str, ...]] = ("center_rel", "radius_rel", "mee")

    @classmethod
    def random(cls, rotation, center, size, rng):
        """Radius ``size``; ``rotation`` and ``rng`` are not used."""
        return cls(center, np.float64(size))

    def size(self):
        """The radius."""
        return float(self.radius)

    def area(self):
        return 4.0 * np.pi * float(self.radius) ** 2

    def bounding_box(self):
        return self.center - self.radius, self.center + self.radius

    def random_cut(self, rng):
        """The hemisphere on one side of a random plane through the centre (50 %)."""
        return Cut(self.center, g.random_units(1, rng)[0])

    def error_measures(self, fitted):
        """radius_error |R_e - R_o|, radius_rel (/ R_o), center_error |C_e - C_o|,
        center_rel (/ R_o)."""
        radius = float(self.radius)
        center = g.point_distance(self.center, fitted.center)
        radius_error = abs(float(fitted.radius) - radius)
        return {"radius_error": radius_error, "radius_rel": radius_error / radius,
                "center_error": center, "center_rel": center / radius}
