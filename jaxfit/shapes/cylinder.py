"""Cylinder. Estimators: the thesis's three points (the plane of the sample gives the axis
direction, its circumcircle the axis position and the radius, THESIS.md section 3), or two
points with normals (the axis is perpendicular to both normals; across it, the two normal
lines meet on the axis). The oriented one is the default: it does not need its points on
one cross-section, so it needs far fewer hypotheses (256 against the thesis's floor of
8192; docs/shapes.md).

theta = (point on axis (3), unit axis (3), radius); the height and centre are fixed after
the loop from the inliers' projections on the axis.
"""

from __future__ import annotations

from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from . import _geometry as g
from ._base import INVARIANT, LENGTH, POINT, Cut, Model, as_points, register


@register
class Cylinder(Model):
    """Finite cylinder.

    center : (3,) middle of the axis segment.
    axis : (3,) unit; sign rule: its largest-magnitude component is positive.
    radius : () positive.
    height : () length of the axis segment.

    One cylinder per model: the methods take unbatched fields (see ``Model``).
    """

    center: np.ndarray
    axis: np.ndarray
    radius: np.ndarray
    height: np.ndarray

    name: ClassVar[str] = "cylinder"
    colour: ClassVar[tuple[int, int, int, int]] = (52, 152, 219, 255)
    sample_size: ClassVar[int] = 3
    oriented_sample_size: ClassVar[int] = 2
    default_estimator: ClassVar[str] = "oriented"
    radius_index: ClassVar[int] = 6
    axis_index: ClassVar[int] = 3
    num_params: ClassVar[int] = 7
    batched_canonical: ClassVar[bool] = True
    # Three steps a round are as accurate as five on the thesis suite (docs/engine.md).
    lm_steps: ClassVar[int] = 3
    min_hypotheses: ClassVar[int] = 8192  # see Model.min_hypotheses
    field_specs: ClassVar = {
        "center": ((3,), POINT),
        "axis": ((3,), INVARIANT),
        "radius": ((), LENGTH),
        "height": ((), LENGTH),
    }

    @staticmethod
    def estimate(sample, support):
        center, normal, radius, valid = g.circle3(sample[0], sample[1], sample[2])
        return jnp.concatenate([center, normal, radius[None]]), valid

    @staticmethod
    def estimate_oriented(sample, normals, support):
        axis, _ = g.safe_normalize(jnp.cross(normals[0], normals[1]))
        q1, q2 = (v - jnp.dot(v, axis) * axis for v in (sample[0], sample[1]))
        c1, c2, valid = g.closest_points(q1, normals[0], q2, normals[1])
        center = 0.5 * (c1 + c2)
        radius = 0.5 * (g.safe_norm(q1 - center) + g.safe_norm(q2 - center))
        valid &= (radius > g.LEN_TOL) & (radius < g.MAX_EXTENT)
        return jnp.concatenate([center, axis, radius[None]]), valid

    @staticmethod
    def theta_residual(theta, p, xp):
        rho2 = g.line_terms(theta, p)[4]
        return g.radial_distance(rho2, xp) - theta[6]

    @staticmethod
    def theta_jacobian(theta, p, xp):
        # d rho / d centre = -(d - t a) / rho, d rho / d axis = -t d / rho (d = p - c)
        dx, dy, dz, t, rho2 = g.line_terms(theta, p)
        inv = g.negative_inverse_root(rho2, xp)
        ti = t * inv
        return xp.stack([(dx - t * theta[3]) * inv, (dy - t * theta[4]) * inv,
                         (dz - t * theta[5]) * inv, dx * ti, dy * ti, dz * ti,
                         xp.full_like(dx, -1.0)])

    @staticmethod
    def canonicalize(theta, xp=jnp):
        axis, _ = g.safe_normalize(theta[..., 3:6], xp)
        return xp.concatenate([theta[..., :3], axis, xp.abs(theta[..., 6:])], axis=-1)

    @classmethod
    def from_theta(cls, theta, points, inliers, threshold):
        # (unit in float64: a float32 kernel's axis is unit to ~1e-7 only, which a
        # bounding box's sqrt(1 - a_i^2) turns into up to ~3e-4 of the radius near an axis)
        axis = g.sign_canonical(g.unit(theta[3:6]))
        t = g.axial(points.compress(inliers, axis=0), theta[:3], axis)
        lo, hi = g.main_interval(t, g.GAP_THRESHOLDS * threshold)
        center = theta[:3] + axis * 0.5 * (lo + hi)
        return cls(center, axis, np.float64(abs(theta[6])), np.float64(hi - lo))

    def theta(self):
        return np.concatenate([self._array("center"), self._array("axis"), [float(self.radius)]])

    def sample(self, count, rng):
        """(count, 3) points uniform on the side (not the caps) and their normals."""
        rot = g.frame(self.axis)
        angle = rng.uniform(0, 2 * np.pi, count)
        normals = np.stack([np.cos(angle), np.sin(angle), np.zeros(count)], 1) @ rot.T
        t = rng.uniform(-0.5, 0.5, count) * self.height
        return self.center + self.radius * normals + np.outer(t, self.axis), normals

    def distance(self, points):
        t, rho = g.axial_radial(as_points(points), self._array("center"), self._array("axis"))
        dx, dy = rho - self.radius, np.abs(t) - 0.5 * self.height
        outside = np.hypot(np.maximum(dx, 0.0), np.maximum(dy, 0.0))
        return np.abs(outside + np.minimum(np.maximum(dx, dy), 0.0))

    def contains(self, points):
        """(N,) bool: in the canonical frame (``transform``), |z| <= height / 2 and
        x^2 + y^2 <= radius^2 (the surface included, to a relative 1e-9)."""
        pose = self.transform()
        local = (as_points(points) - pose[:3, 3]) @ pose[:3, :3]
        slack = 1 + 1e-9
        radial = local[:, 0] ** 2 + local[:, 1] ** 2 <= (float(self.radius) * slack) ** 2
        return radial & (np.abs(local[:, 2]) <= 0.5 * float(self.height) * slack)

    def to_mesh(self, sections: int = 64):
        import trimesh

        return trimesh.creation.cylinder(
            radius=float(self.radius), height=float(self.height), sections=sections,
            transform=self.transform(),
        )

    # ----- pose and mass ------------------------------------------------------------------
    def transform(self):
        """+Z along ``axis`` (``_geometry.frame``), at the centre."""
        return g.transform(g.frame(self._array("axis")), self._array("center"))

    def volume(self):
        return np.pi * float(self.radius) ** 2 * float(self.height)

    def surface_area(self):
        """The side and both caps."""
        return self.area() + 2.0 * np.pi * float(self.radius) ** 2

    def centroid(self):
        return self._array("center")

    def unit_inertia(self):
        r2, h2 = float(self.radius) ** 2, float(self.height) ** 2
        return np.array([(3.0 * r2 + h2) / 12.0, (3.0 * r2 + h2) / 12.0, 0.5 * r2])

    # ----- facts for scenes, scenarios and the evaluation ---------------------------------
    removed_share: ClassVar[float] = 0.5
    shown_measures: ClassVar[tuple[str, ...]] = ("axis_angle_deg", "radius_rel", "height_rel")
    axial_bounds: ClassVar[bool] = True

    @classmethod
    def random(cls, rotation, center, size, rng):
        """Radius size / 2 and height 2 size along ``rotation[:, 2]``; ``rng`` is not used."""
        axis = g.sign_canonical(rotation[:, 2])
        return cls(center, axis, np.float64(0.5 * size), np.float64(2.0 * size))

    def size(self):
        """The radius."""
        return float(self.radius)

    def area(self):
        """Area of the side (the caps are not sampled)."""
        return 2.0 * np.pi * float(self.radius) * float(self.height)

    def bounding_box(self):
        ends = self.center + np.outer([-0.5, 0.5], self.axis) * self.height
        return g.union_bounds([g.disk_bounds(end, self.axis, self.radius) for end in ends])

    def random_cut(self, rng):
        """The half of the side on one side of a random plane containing the axis (50 %)."""
        return Cut(np.asarray(self.center, dtype=np.float64), g.axial_cut_direction(self.axis, rng))

    def error_measures(self, fitted):
        """radius_error, radius_rel (/ R_o), height_error, height_rel (/ H_o),
        axis_angle_deg (signs ignored), axis_offset (distance of the true centre C_o to
        the fitted axis line), center_error."""
        radius_error = abs(float(fitted.radius) - float(self.radius))
        height_error = abs(float(fitted.height) - float(self.height))
        # How far the fitted axis line passes from the true centre (a point of the true axis).
        axis = g.unit(fitted.axis)
        v = np.asarray(self.center, float) - np.asarray(fitted.center, float)
        return {
            "radius_error": radius_error, "radius_rel": radius_error / float(self.radius),
            "height_error": height_error, "height_rel": height_error / float(self.height),
            "axis_angle_deg": g.axis_angle_deg(self.axis, fitted.axis),
            "axis_offset": float(np.linalg.norm(v - (v @ axis) * axis)),
            "center_error": g.point_distance(self.center, fitted.center),
        }
