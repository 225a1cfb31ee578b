"""Plane: n . p + offset = 0, optionally bounded to the disk its inliers cover.

theta = (nx, ny, nz, offset); three points per sample.
"""

from __future__ import annotations

import math
from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from . import _geometry as g
from ._base import INVARIANT, LENGTH, POINT, Cut, Model, register


@register
class Plane(Model):
    """Plane ``normal . p + offset = 0``.

    normal : (3,) unit vector; sign rule: its largest-magnitude component is positive.
    offset : () signed offset.
    center, radius : optional disk patch ((3,) centre on the plane, () radius) around
        the inliers, for ``to_mesh``. ``None`` means no patch.

    One plane per model: the methods take unbatched fields (see ``Model``).
    """

    normal: np.ndarray
    offset: np.ndarray
    center: np.ndarray | None = None
    radius: np.ndarray | None = None

    name: ClassVar[str] = "plane"
    colour: ClassVar[tuple[int, int, int, int]] = (155, 89, 182, 255)
    sample_size: ClassVar[int] = 3
    pointwise_theta: ClassVar[bool] = True
    axis_index: ClassVar[int] = 0  # the normal
    num_params: ClassVar[int] = 4
    batched_canonical: ClassVar[bool] = True
    field_specs: ClassVar = {
        "normal": ((3,), INVARIANT),
        "offset": ((), INVARIANT),  # handled in rescaled()
        "center": ((3,), POINT),
        "radius": ((), LENGTH),
    }

    @staticmethod
    def estimate(sample, support):
        normal, valid, _ = g.triangle(sample[0], sample[1], sample[2])
        return jnp.concatenate([normal, -jnp.dot(normal, sample[0])[None]]), valid

    @staticmethod
    def theta_residual(theta, p, xp):
        return theta[0] * p[0] + theta[1] * p[1] + theta[2] * p[2] + theta[3]

    @staticmethod
    def theta_jacobian(theta, p, xp):
        return xp.stack([p[0], p[1], p[2], xp.ones_like(p[0])])

    @staticmethod
    def canonicalize(theta, xp=jnp):
        normal, length = g.safe_normalize(theta[..., :3], xp)
        return xp.concatenate([normal, theta[..., 3:] / xp.where(length > 0, length,
                                                                 1.0)[..., None]], axis=-1)

    @staticmethod
    def least_squares(points, weights):
        # Through the weighted centroid, normal along the scatter's least direction: the
        # least-squares plane in one step, where Levenberg-Marquardt takes several.
        centroid, scatter = g.weighted_scatter(points, weights)
        normal = g.smallest_eigenvector(scatter)  # (no LAPACK call)
        return jnp.concatenate([normal, -(normal @ centroid)[None]])

    @staticmethod
    def host_least_squares(jtj, theta):
        # ``least_squares`` from the moments: the residual's Jacobian is (x, y, z, 1), so
        # J^T J holds the points' count, sums and second moments; the normal keeps
        # theta's side (the same plane either way; the refit's steps stay continuous).
        count = jtj[3, 3]
        if not count >= 3:  # (no plane through fewer points: the refit refuses NaN)
            return np.full(4, np.nan)
        centroid = jtj[:3, 3] / count
        scatter = jtj[:3, :3] - count * np.outer(centroid, centroid)
        normal = np.linalg.eigh(scatter)[1][:, 0]
        normal = normal if normal @ theta[:3] >= 0 else -normal
        return np.concatenate([normal, [-(normal @ centroid)]])

    @classmethod
    def from_theta(cls, theta, points, inliers, threshold):
        # Unit in float64, the offset with it (as Cylinder's axis: a float32 kernel's
        # normal is unit to ~1e-7 only, which the patch's box amplifies near an axis).
        theta = np.asarray(theta, np.float64)
        length = math.sqrt(theta[:3] @ theta[:3])
        normal = g.sign_canonical(theta[:3] / length)
        offset = theta[3] / length * (1.0 if normal @ theta[:3] > 0 else -1.0)
        # The patch: around the inliers' median, out to where they thin out (strays in
        # the plane's slab far from the patch are sparse and are left outside). In the
        # plane's own 2-D coordinates: two 1-D medians, not a gather of (M, 3) rows and
        # three (docs/shapes.md).
        in_plane = g.frame(normal)[:, :2]  # (3, 2)
        inside = points.compress(inliers, axis=0)  # (as points[inliers], ~4x faster)
        u, v = (_project(inside, in_plane[:, i]) for i in range(2))
        mu, mv = g.median(u), g.median(v)
        spread = _length_2d(u - mu, v - mv)
        _, radius = g.main_interval(spread, g.GAP_THRESHOLDS * threshold)
        patch = spread <= radius
        kept = np.count_nonzero(patch)
        center = _patch_center(in_plane, u[patch].sum() / kept, v[patch].sum() / kept,
                               offset, normal)
        return cls(normal, np.float64(offset), center, np.float64(radius))

    @classmethod
    def from_theta_many(cls, thetas, points, inliers, thresholds, scales=None, shifts=None):
        # ``from_theta`` (and ``rescaled``) of every cloud, bit for bit: the same
        # elementwise arithmetic on arrays of all clouds; the medians and the patch's
        # radius are segment versions over all clouds (``_geometry``).
        thetas = np.asarray(thetas, np.float64)
        # (each squared length by stacked matmul: the same dot product as theta @ theta)
        lengths = np.sqrt(np.matmul(thetas[:, None, :3], thetas[:, :3, None])[:, 0, 0])
        normals = g.sign_canonical(thetas[:, :3] / lengths[:, None])
        flips = np.where((normals * thetas[:, :3]).sum(axis=1) > 0, 1.0, -1.0)  # (signs
        offsets = thetas[:, 3] / lengths * flips  # of +-|n|^2, as exact as normal @ theta[:3]'s)
        in_plane = g.frames(normals)[:, :, :2]  # (C, 3, 2)
        counts = np.add.reduceat(inliers, np.cumsum([0] + [len(p) for p in points[:-1]]),
                                 dtype=np.int64)
        inside = np.concatenate(points).compress(inliers, axis=0)  # (M, 3)
        u, v = (_project(inside, np.repeat(in_plane[:, :, i], counts, axis=0).T)
                for i in range(2))
        mu, mv = np.split(g.segment_medians(np.concatenate([u, v]), np.tile(counts, 2)), 2)
        spread = _length_2d(u - np.repeat(mu, counts), v - np.repeat(mv, counts))
        _, radius = g.main_intervals(spread, counts, g.GAP_THRESHOLDS * np.asarray(thresholds))
        patch = spread <= np.repeat(radius, counts)
        kept = np.add.reduceat(patch, np.cumsum(counts) - counts, dtype=np.int64)
        starts = (np.cumsum(kept) - kept).tolist()
        up, vp = u[patch], v[patch]
        # (each patch summed over its own slice: reduceat sums in another order)
        su, sv = np.array([(up[s:s + k].sum(), vp[s:s + k].sum())
                           for s, k in zip(starts, kept.tolist(), strict=True)]).reshape(-1, 2).T
        centers = _patch_center(in_plane.transpose(1, 2, 0), su / kept, sv / kept,
                                offsets, normals.T).T  # (C, 3)
        if scales is not None:
            scales, shifts = np.asarray(scales, np.float64), np.asarray(shifts, np.float64)
            offsets, centers, radius = _rescaled(normals, offsets, centers, radius, scales,
                                                 shifts)
        return [cls(n, d, c, r) for n, d, c, r in zip(normals, offsets, centers, radius,
                                                        strict=True)]

    def theta(self):
        return np.concatenate([self._array("normal"), [float(self.offset)]])

    def rescaled(self, scale, shift):
        # ``Model.rescaled``'s arithmetic for the patch, written out (its field loop and
        # ``dataclasses.replace`` had cost ~12 us of a fit's results, docs/engine.md),
        # elementwise as ``from_theta_many``'s.
        offset, center, radius = _rescaled(
            self._array("normal"), self._array("offset"), self.center,
            None if self.radius is None else self._array("radius"), scale,
            np.asarray(shift, np.float64))
        return type(self)(self.normal, offset, center, radius)

    def sample(self, count, rng):
        """(count, 3) points uniform on the disk patch and their normals (count, 3)."""
        radius = np.sqrt(rng.uniform(size=count)) * self.radius
        angle = rng.uniform(0, 2 * np.pi, count)
        rot = g.frame(self.normal)
        local = np.stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros(count)], 1)
        return local @ rot.T + self.center, np.tile(rot[:, 2], (count, 1))

    def distance(self, points):
        """Distance to the plane. A plane counts as unbounded here (its inliers may cover
        any outline); the disk patch only gives ``to_mesh`` a size."""
        return np.abs(self.residual(points))

    def contains(self, points):
        """A plane bounds no solid (``volume`` is 0): ValueError. The two-sided measures
        (jaxfit.evaluation.twosided) count its patch as surface only, never as volume."""
        raise ValueError("a plane bounds no solid, so it contains no points; the two-sided "
                         "measures count a plane's patch as surface only")

    def to_mesh(self, sections: int = 64):
        if self.radius is None:
            raise ValueError("an unbounded plane has no mesh; fit it to get a bounded patch")
        return _disk(float(self.radius), sections, self.transform())

    # ----- pose and mass ------------------------------------------------------------------
    def transform(self):
        """+Z along ``normal`` (``_geometry.frame``), at the patch's centre."""
        if self.center is None:
            raise ValueError("an unbounded plane has no pose; fit it to get a bounded patch")
        return g.transform(g.frame(self._array("normal")), self._array("center"))

    def volume(self):
        """0: a plane is a surface. Its mass is 0 and its inertia the zero tensor at any
        density (a patch of vanishing thickness); simulator models give it a thin disk
        without mass (``jaxfit.io.sim``)."""
        return 0.0

    def surface_area(self):
        """The disk patch (one side)."""
        return self.area()

    def centroid(self):
        """The patch's centre."""
        return self.transform()[:3, 3]

    def unit_inertia(self):
        """A thin disk's, per unit mass (its mass is 0)."""
        r2 = float(self.radius) ** 2
        return np.array([0.25 * r2, 0.25 * r2, 0.5 * r2])

    # ----- facts for scenes, scenarios and the evaluation ---------------------------------
    removed_share: ClassVar[float] = 0.5
    shown_measures: ClassVar[tuple[str, ...]] = ("normal_angle_deg", "offset_error")

    @classmethod
    def random(cls, rotation, center, size, rng):
        """Normal ``rotation[:, 2]`` through ``center``, disk patch of radius ``size``;
        ``rng`` is not used."""
        axis = g.sign_canonical(rotation[:, 2])
        return cls(axis, np.float64(-axis @ center), center, np.float64(size))

    def size(self):
        """The disk patch's radius."""
        return float(self.radius)

    def area(self):
        """Area of the disk patch."""
        return np.pi * float(self.radius) ** 2

    def bounding_box(self):
        """Bounds of the disk patch."""
        return g.disk_bounds(self.center, self.normal, self.radius)

    def random_cut(self, rng):
        """The half of the disk patch on one side of a random line through its centre
        (50 %; not in the thesis)."""
        return Cut(np.asarray(self.center, dtype=np.float64),
                   g.axial_cut_direction(self.normal, rng))

    def error_measures(self, fitted):
        """normal_angle_deg (signs ignored), offset_error (|offset_e - offset_o| once the
        fitted normal's sign agrees with the true one)."""
        # n . p + d = 0 and -n . p - d = 0 are one plane: align the signs before comparing d.
        t_n, f_n = g.unit(self.normal), np.asarray(fitted.normal, float)
        f_len = np.linalg.norm(f_n)
        sign = 1.0 if t_n @ f_n >= 0 else -1.0
        offset = sign * float(fitted.offset) / f_len
        t_offset = float(self.offset) / np.linalg.norm(np.asarray(self.normal, float))
        return {"normal_angle_deg": g.axis_angle_deg(t_n, f_n),
                "offset_error": abs(offset - t_offset)}


def _project(points, axis):
    """Coordinates (M,) of points (M, 3) along axis (3,) or per-point axes (3, M):
    elementwise, so one cloud and many give the same bits (a BLAS product sums in its
    own order)."""
    return points[:, 0] * axis[0] + points[:, 1] * axis[1] + points[:, 2] * axis[2]


def _length_2d(du, dv):
    """sqrt(du^2 + dv^2) (M,), elementwise, written over du (M,) and dv (M,), the
    caller's temporaries (1e5 values: ~0.4 ms less than three fresh arrays, the same
    bits). ``np.hypot`` guards over/underflow that normalised coordinates never meet, at
    ~5x the time."""
    du *= du
    dv *= dv
    du += dv
    return np.sqrt(du, out=du)


def _patch_center(in_plane, mean_u, mean_v, offset, normal):
    """The patch's centre (3,) on the plane from its mean in-plane coordinates: in_plane
    (3, 2), scalars and normal (3,) for one plane, or (3, 2, C), (C,) and (3, C) for C."""
    return in_plane[:, 0] * mean_u + in_plane[:, 1] * mean_v - offset * normal


def _rescaled(normal, offset, center, radius, scale, shift):
    """``Plane.rescaled``'s fields (offset, centre, radius) for points p * scale + shift:
    normal, centre and shift (..., 3), offset, radius and scale (...) or scalars, so one
    plane, a batched one and ``from_theta_many``'s C planes share the arithmetic."""
    moved = offset * scale - (normal[..., 0] * shift[..., 0] + normal[..., 1] * shift[..., 1]
                              + normal[..., 2] * shift[..., 2])
    return (moved, None if center is None else center * np.expand_dims(scale, -1) + shift,
            None if radius is None else radius * scale + 0.0)


def _disk(radius, sections, matrix):
    """A flat triangle fan of the given radius in the local z = 0 plane."""
    angles = np.linspace(0.0, 2 * np.pi, sections, endpoint=False)
    rim = np.stack([radius * np.cos(angles), radius * np.sin(angles), np.zeros(sections)], 1)
    vertices = np.vstack([[0.0, 0.0, 0.0], rim])
    faces = np.stack([np.zeros(sections, int), 1 + np.arange(sections),
                      1 + (np.arange(sections) + 1) % sections], 1)
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.apply_transform(matrix)
    return mesh
