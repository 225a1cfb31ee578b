"""Cone. Estimators: the thesis's four points and its apex construction (THESIS.md
section 3), or three points with normals (Schnabel et al. 2007; the default).

Thesis: p1..p3 give a plane, its circumcircle (c0, r) and the axis through c0 along the plane
normal. p4 projected on the plane fixes the meridian half-plane through p4; the circle
meets it at s, and the line through s and p4 crosses the axis at the apex.

Oriented: the apex is where the three tangent planes meet; the unit vectors from the apex
to the points make one angle with the axis, so their tips lie on a circle whose plane is
normal to the axis.

theta = (apex (3), unit axis (3) pointing from the apex into the cone, half_angle).
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from . import _geometry as g
from ._base import INVARIANT, LENGTH, POINT, Cut, Model, as_points, register

# Half-angles this close to 0 or 90 degrees are a cylinder or a plane, not a cone.
MIN_ANGLE = 1e-3


@register
class Cone(Model):
    """Finite right circular cone.

    apex : (3,).
    axis : (3,) unit, pointing from the apex into the cone.
    half_angle : () in radians, in (0, pi/2).
    height : () distance from the apex to the base disk along the axis.

    One cone per model: the methods take unbatched fields (see ``Model``).
    """

    apex: np.ndarray
    axis: np.ndarray
    half_angle: np.ndarray
    height: np.ndarray

    name: ClassVar[str] = "cone"
    colour: ClassVar[tuple[int, int, int, int]] = (241, 196, 15, 255)
    sample_size: ClassVar[int] = 4
    oriented_sample_size: ClassVar[int] = 3
    default_estimator: ClassVar[str] = "oriented"
    axis_index: ClassVar[int] = 3
    num_params: ClassVar[int] = 7
    batched_canonical: ClassVar[bool] = True
    min_hypotheses: ClassVar[int] = 16384  # see Model.min_hypotheses
    field_specs: ClassVar = {
        "apex": ((3,), POINT),
        "axis": ((3,), INVARIANT),
        "half_angle": ((), INVARIANT),
        "height": ((), LENGTH),
    }

    @staticmethod
    def estimate(sample, support):
        c0, n, r, valid = g.circle3(sample[0], sample[1], sample[2])
        # Work in the meridian half-plane of p4: coordinates (rho, h) about the axis.
        v4 = sample[3] - c0
        h4 = jnp.dot(v4, n)
        rho4 = g.safe_norm(v4 - h4 * n)
        # The line from s = (r, 0) through p4 = (rho4, h4) meets the axis rho = 0 at h_apex.
        slope = rho4 - r
        valid &= (rho4 > g.LEN_TOL) & (jnp.abs(h4) > g.LEN_TOL) & (jnp.abs(slope) > g.LEN_TOL)
        h_apex = -r * h4 / jnp.where(valid, slope, 1.0)
        half_angle = jnp.arctan2(jnp.abs(slope), jnp.abs(h4))
        valid &= (half_angle > MIN_ANGLE) & (half_angle < jnp.pi / 2 - MIN_ANGLE)
        valid &= jnp.abs(h_apex) < g.MAX_EXTENT
        # The circle's centre lies inside the cone, so the axis points from apex to c0.
        axis = jnp.where(h_apex < 0, n, -n)
        return jnp.concatenate([c0 + h_apex * n, axis, half_angle[None]]), valid

    @staticmethod
    def estimate_oriented(sample, normals, support):
        n = normals
        c23, c31, c12 = jnp.cross(n[1], n[2]), jnp.cross(n[2], n[0]), jnp.cross(n[0], n[1])
        det = jnp.dot(n[0], c23)
        valid = jnp.abs(det) > g.SIN_TOL * jnp.prod(g.safe_norm(n))
        d = jnp.sum(n * sample, axis=1)  # tangent planes n_i . x = d_i
        apex = (d[0] * c23 + d[1] * c31 + d[2] * c12) / jnp.where(valid, det, 1.0)
        u, length = g.safe_normalize(sample - apex)
        axis, _ = g.safe_normalize(jnp.cross(u[1] - u[0], u[2] - u[0]))
        axis = jnp.where(jnp.sum(u @ axis) < 0, -axis, axis)  # into the points' nappe
        cos = u @ axis
        half_angle = jnp.mean(jnp.arctan2(g.safe_norm(jnp.cross(u, axis)), cos))
        valid &= (jnp.min(length) > g.LEN_TOL) & jnp.all(cos > 0)
        valid &= (half_angle > MIN_ANGLE) & (half_angle < jnp.pi / 2 - MIN_ANGLE)
        valid &= g.safe_norm(apex) < g.MAX_EXTENT
        return jnp.concatenate([apex, axis, half_angle[None]]), valid

    @staticmethod
    def theta_residual(theta, p, xp):
        # e = |p - apex| sin(phi - half_angle), phi the angle between p - apex and the axis,
        # expanded so that no arccos is needed: cos(a) |v x axis| - sin(a) (v . axis).
        _, _, _, t, rho2 = g.line_terms(theta, p)
        rho = g.radial_distance(rho2, xp)
        return xp.cos(theta[6]) * rho - xp.sin(theta[6]) * t

    @staticmethod
    def theta_jacobian(theta, p, xp):
        # e = cos(a) rho - sin(a) t (d = p - apex, t = d . w): d rho / d apex = -(d - t w) /
        # rho, d rho / d w = -t d / rho, d t / d apex = -w, d t / d w = d.
        dx, dy, dz, t, rho2 = g.line_terms(theta, p)
        inv = g.negative_inverse_root(rho2, xp)
        cos, sin = xp.cos(theta[6]), xp.sin(theta[6])
        along = cos * t * inv - sin
        return xp.stack([cos * (dx - t * theta[3]) * inv + sin * theta[3],
                         cos * (dy - t * theta[4]) * inv + sin * theta[4],
                         cos * (dz - t * theta[5]) * inv + sin * theta[5],
                         dx * along, dy * along, dz * along,
                         -sin * g.radial_distance(rho2, xp) - cos * t])

    @staticmethod
    def canonicalize(theta, xp=jnp):
        # A refinement step must not leave (0, pi/2): past either end it is no cone.
        axis, _ = g.safe_normalize(theta[..., 3:6], xp)
        angle = xp.clip(theta[..., 6:], MIN_ANGLE, np.pi / 2 - MIN_ANGLE)
        return xp.concatenate([theta[..., :3], axis, angle], axis=-1)

    @classmethod
    def from_theta(cls, theta, points, inliers, threshold):
        apex, axis = np.asarray(theta[:3], np.float64), g.unit(theta[3:6])  # (as Cylinder's)
        t = g.axial(points.compress(inliers, axis=0), apex, axis)
        if g.median(t) < 0:  # the inliers sit on the other nappe: turn the cone around
            axis, t = -axis, -t
        _, hi = g.main_interval(t, g.GAP_THRESHOLDS * threshold)
        return cls(apex, axis, np.float64(theta[6]), np.float64(max(hi, 0.0)))

    @property
    def base_radius(self):
        return self.height * np.tan(self.half_angle)

    def theta(self):
        return np.concatenate([self._array("apex"), self._array("axis"), [float(self.half_angle)]])

    def sample(self, count, rng):
        """(count, 3) points uniform on the side (not the base) and their outward normals."""
        rot = g.frame(self.axis)
        angle = rng.uniform(0, 2 * np.pi, count)
        radial = np.stack([np.cos(angle), np.sin(angle), np.zeros(count)], 1) @ rot.T
        t = np.sqrt(rng.uniform(size=count)) * self.height  # area grows with t
        rim = (t * np.tan(self.half_angle))[:, None] * radial
        points = self.apex + np.outer(t, self.axis) + rim
        normals = np.cos(self.half_angle) * radial - np.sin(self.half_angle) * self.axis
        return points, normals

    def distance(self, points):
        t, rho = g.axial_radial(as_points(points), self._array("apex"), self._array("axis"))
        h, r = float(self.height), float(self.base_radius)
        side = g.segment_distance_2d(t, rho, 0.0, 0.0, h, r)
        base = g.segment_distance_2d(t, rho, h, 0.0, h, r)
        return np.minimum(side, base)

    def contains(self, points):
        """(N,) bool: in the canonical frame (``transform``: base disk at z = 0, apex at
        z = height), 0 <= z <= height and sqrt(x^2 + y^2) <= base_radius (1 - z / height),
        the surface included (to 1e-9 of the height and the base radius)."""
        pose = self.transform()
        local = (as_points(points) - pose[:3, 3]) @ pose[:3, :3]
        h, r = float(self.height), float(self.base_radius)
        z, rho = local[:, 2], np.hypot(local[:, 0], local[:, 1])
        along = (z >= -1e-9 * h) & (z <= h * (1 + 1e-9))
        return along & (rho * h <= r * (h - z) + 1e-9 * r * h)

    def to_mesh(self, sections: int = 64):
        import trimesh

        return trimesh.creation.cone(
            radius=float(self.base_radius), height=float(self.height), sections=sections,
            transform=self.transform(),
        )

    # ----- pose and mass ------------------------------------------------------------------
    def transform(self):
        """trimesh's cone has its base at z = 0 and its apex at +z: +Z along ``-axis``
        (``_geometry.frame``), at the base's centre."""
        axis = self._array("axis")
        return g.transform(g.frame(-axis), self._array("apex") + float(self.height) * axis)

    def volume(self):
        return np.pi * float(self.base_radius) ** 2 * float(self.height) / 3.0

    def surface_area(self):
        """The side and the base."""
        return self.area() + np.pi * float(self.base_radius) ** 2

    def centroid(self):
        """Three quarters of the way from the apex to the base."""
        return self._array("apex") + 0.75 * float(self.height) * self._array("axis")

    def unit_inertia(self):
        r2, h2 = float(self.base_radius) ** 2, float(self.height) ** 2
        across = 3.0 / 20.0 * r2 + 3.0 / 80.0 * h2
        return np.array([across, across, 0.3 * r2])

    # ----- facts for scenes, scenarios and the evaluation ---------------------------------
    removed_share: ClassVar[float] = 0.5
    shown_measures: ClassVar[tuple[str, ...]] = (
        "axis_angle_deg", "aperture_error_deg", "height_rel")
    axial_bounds: ClassVar[bool] = True

    @classmethod
    def random(cls, rotation, center, size, rng):
        """Height 2 size along ``rotation[:, 2]`` (from the apex), centred on ``center``,
        half-angle U(20, 40) degrees. The axis points into the cone: no sign rule."""
        axis = rotation[:, 2]
        half_angle = rng.uniform(np.radians(20.0), np.radians(40.0))
        height = 2.0 * size
        return cls(center - 0.5 * height * axis, axis, np.float64(half_angle), np.float64(height))

    def size(self):
        """The base's radius."""
        return float(self.base_radius)

    def area(self):
        """Area of the side (the base is not sampled)."""
        slant = float(self.height) / np.cos(float(self.half_angle))
        return np.pi * float(self.base_radius) * slant

    def bounding_box(self):
        """Bounds of the apex and the base disk."""
        base = self.apex + self.height * self.axis
        return g.union_bounds([g.disk_bounds(base, self.axis, self.base_radius),
                               (self.apex, self.apex)])

    def random_cut(self, rng):
        """The half of the side on one side of a random plane containing the axis (50 %)."""
        return Cut(np.asarray(self.apex, dtype=np.float64), g.axial_cut_direction(self.axis, rng))

    def error_measures(self, fitted):
        """height_error, height_rel (/ H_o), aperture_error_deg |half_angle_e -
        half_angle_o| in degrees, axis_angle_deg (signs ignored), apex_error
        |apex_e - apex_o|."""
        height_error = abs(float(fitted.height) - float(self.height))
        aperture = abs(float(fitted.half_angle) - float(self.half_angle))
        return {
            "height_error": height_error, "height_rel": height_error / float(self.height),
            "aperture_error_deg": float(np.degrees(aperture)),
            "axis_angle_deg": g.axis_angle_deg(self.axis, fitted.axis),
            "apex_error": g.point_distance(self.apex, fitted.apex),
        }
