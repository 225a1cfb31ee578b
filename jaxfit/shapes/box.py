"""Box from five points and histogram modes (THESIS.md section 3), or from two points
with normals (the default).

Thesis: p1..p3 give the first face's normal n1; the plane through p4, its projection on
that face and p5 is orthogonal to it (n2); n3 = n1 x n2. Oriented: n1 is p1's normal, n2
the part of p2's normal orthogonal to n1. Either way each face's offset is not the
sample's own but the mode of the histogram of the cloud's projections on n_i, which is
where most points lie. After the loop the three parallel faces are found from the
histograms of the points that are not inliers of the first three.

The oriented estimator needs p1 and p2 on any two non-parallel faces (the thesis's needs
three points on one face and two on an adjacent one), so it needs far fewer hypotheses
at about the same accuracy (measurements: docs/shapes.md).

theta = (n1 (3), n2 (3), n3 (3), D1, D2, D3) with faces n_i . p = D_i.
"""

from __future__ import annotations

import functools
import itertools
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from . import _geometry as g
from ._base import INVARIANT, LENGTH, POINT, Cut, Model, as_points, register

#: Bins of the in-loop histogram over [-1, 1], the range of a normalised cloud.
HISTOGRAM_BINS = 128
# After the loop: bins are one threshold wide; counts are summed over _SUM_BINS so a
# face spans several bins, then median-filtered over _MEDIAN_BINS to drop lone spikes.
_SUM_BINS = 3
_MEDIAN_BINS = 3
#: Newton steps of ``canonicalize``'s polar factor: each squares the distance from a
#: rotation, and a refinement step leaves the normals within a few degrees of one.
POLAR_STEPS = 3
#: The oriented estimator's two normals must be at least 60 degrees apart (sine 0.87): a
#: box's faces meet at 90, and estimated normals are off by a few degrees.
ORIENTED_MIN_SIN = 0.87
#: The faces (axis i, sign) a scan sees of a box resting on its -rotation[:, 2] face, in
#: the order ``scene_surfaces`` gives them.
UPPER_FACES = ((0, 1), (0, -1), (1, 1), (1, -1), (2, 1))



def histogram_mode_offsets(normals, support):
    """Offsets (3,) of the three planes with normals (3, 3) (rows) through the densest slab.

    The projections of ``support`` (M, 3), points in the unit ball, are binned into
    ``HISTOGRAM_BINS`` bins over [-1, 1]; the offset is the mean projection in the fullest
    bin (the first on ties), which is closer to the face than the bin's centre.
    """
    proj = support @ normals.T  # (M, 3)
    bins = jnp.clip(jnp.floor((proj + 1.0) * (HISTOGRAM_BINS / 2)), 0, HISTOGRAM_BINS - 1)
    bins = bins.astype(jnp.int32)
    counts = jnp.zeros((3, HISTOGRAM_BINS), proj.dtype).at[jnp.arange(3)[None, :], bins].add(1.0)
    in_mode = bins == jnp.argmax(counts, axis=1)[None, :]
    return jnp.sum(jnp.where(in_mode, proj, 0.0), axis=0) / jnp.maximum(jnp.sum(in_mode, axis=0), 1)


@register
class Box(Model):
    """Oriented box.

    center : (3,).
    rotation : (3, 3) proper rotation whose columns are the box's axes; sign rule: the
        first two columns have their largest-magnitude component positive.
    extents : (3,) full side lengths along those columns.

    One box per model: the methods take unbatched fields (see ``Model``).
    """

    center: np.ndarray
    rotation: np.ndarray
    extents: np.ndarray

    name: ClassVar[str] = "box"
    colour: ClassVar[tuple[int, int, int, int]] = (46, 204, 113, 255)
    sample_size: ClassVar[int] = 5
    oriented_sample_size: ClassVar[int] = 2
    default_estimator: ClassVar[str] = "oriented"
    reads_support: ClassVar[bool] = True
    num_params: ClassVar[int] = 12
    batched_canonical: ClassVar[bool] = True
    lm_analytic: ClassVar[bool] = False  # (its refinement compiles faster with the JVPs)
    field_specs: ClassVar = {
        "center": ((3,), POINT),
        "rotation": ((3, 3), INVARIANT),
        "extents": ((3,), LENGTH),
    }

    @staticmethod
    def estimate(sample, support):
        n1, valid, _ = g.triangle(sample[0], sample[1], sample[2])
        h4 = jnp.dot(sample[3] - sample[0], n1)
        # (p4 - p4') x (p5 - p4) with p4 - p4' = h4 n1 written out: subtracting p4's
        # projection from p4 would cancel digits in float32 when p4 is near the face.
        n2, length = g.safe_normalize(jnp.cross(h4 * n1, sample[4] - sample[3]))
        valid &= length > g.SIN_TOL * jnp.abs(h4) * g.safe_norm(sample[4] - sample[3])
        valid &= jnp.abs(h4) > g.LEN_TOL
        normals = jnp.stack([n1, n2, jnp.cross(n1, n2)])
        offsets = histogram_mode_offsets(normals, support)
        return jnp.concatenate([normals.reshape(-1), offsets]), valid

    @staticmethod
    def estimate_oriented(sample, normals, support):
        # n1 is p1's normal, n2 the part of p2's normal orthogonal to it; p2 must sit on
        # a face at a clear angle to p1's (not the same face or its parallel one).
        n1, _ = g.safe_normalize(normals[0])
        m2, _ = g.safe_normalize(normals[1])
        n2, length = g.safe_normalize(m2 - jnp.dot(m2, n1) * n1)
        valid = length > ORIENTED_MIN_SIN
        faces = jnp.stack([n1, n2, jnp.cross(n1, n2)])
        return jnp.concatenate([faces.reshape(-1), histogram_mode_offsets(faces, support)]), valid

    @staticmethod
    def theta_residual(theta, p, xp):
        # Distance to the nearest of the three planes, keeping its sign.
        r, (first, _, last) = _nearest_plane(theta, p, xp)
        near01 = xp.where(first, r[0], r[1])
        return xp.where(~last, near01, r[2])

    @staticmethod
    def theta_jacobian(theta, p, xp):
        # Only the nearest plane's entries move the residual: its normal's by the point,
        # its offset's by -1.
        _, nearest = _nearest_plane(theta, p, xp)
        return xp.stack([xp.where(w, c, 0.0) for w in nearest for c in p]
                        + [xp.where(w, -1.0, 0.0) for w in nearest])

    @staticmethod
    def canonicalize(theta, xp=jnp):
        # Nearest rotation to the refined normals (the polar factor, ``polar``):
        # refinement differentiates through this, and the SVD's derivative is undefined
        # at a rotation (three equal singular values).
        lead = theta.shape[:-1]
        rot = theta[..., :9].reshape(lead + (3, 3))
        rot = _polar_steps(rot, xp) if xp is np else polar(rot)
        return xp.concatenate([rot.reshape(lead + (9,)), theta[..., 9:]], axis=-1)

    @classmethod
    def from_theta(cls, theta, points, inliers, threshold):
        # The normals made orthonormal in float64 (a float32 kernel's are to ~1e-7 only).
        theta = cls.canonicalize(np.asarray(theta, np.float64), np)
        normals = theta[:9].reshape(3, 3)
        near, far = np.asarray(theta[9:], np.float64), np.empty(3)
        proj = points @ normals.T  # (N, 3)
        face = np.argmin(np.abs(proj - near), axis=1)
        for i in range(3):
            far[i] = _opposite_face(proj[~inliers, i], near[i], threshold)
            if np.isnan(far[i]):
                # No clear peak (the far face is hidden or too noisy): the other faces'
                # inliers still show how far the box reaches along n_i.
                # No such inliers (all on face i): nothing reaches past it, a flat box.
                others = proj[inliers & (face != i), i]
                if len(others) == 0:
                    far[i] = near[i]
                    continue
                lo, hi = g.main_interval(others, g.GAP_THRESHOLDS * threshold)
                far[i] = hi if hi - near[i] > near[i] - lo else lo
        near, far = _polish_faces(proj, near, far, threshold)
        rotation = g.sign_canonical(normals[:2])
        rotation = np.stack([rotation[0], rotation[1], g.cross3(rotation[0], rotation[1])], 1)
        middle = normals.T @ (0.5 * (near + far))
        return cls(middle, rotation, np.abs(far - near))

    def theta(self):
        """The hypothesis of the three faces on the near side of each axis (``residual``
        measures all six)."""
        rot, center = self._array("rotation"), self._array("center")
        return np.concatenate([rot.T.ravel(), rot.T @ center - 0.5 * self._array("extents")])

    def residual(self, points):
        local = (as_points(points) - self._array("center")) @ self._array("rotation")
        q = np.abs(local) - 0.5 * self._array("extents")
        return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)

    def coordinate_residual(self, p):
        # (the six faces are measured in the box's frame, from the (N, 3) array)
        return self.residual(np.stack(p, axis=1))

    def sample(self, count, rng):
        """(count, 3) points uniform on the six faces and their outward normals."""
        ext = self._array("extents")
        areas = np.array([ext[1] * ext[2], ext[0] * ext[2], ext[0] * ext[1]]).repeat(2)
        if not areas.sum() > 0:  # two extents 0 (a segment, a fit's degenerate answer)
            raise ValueError(f"a box with extents {ext.tolist()} has no surface to sample")
        face = rng.choice(6, size=count, p=areas / areas.sum())
        axis, sign = face // 2, np.where(face % 2, 1.0, -1.0)
        local = (rng.uniform(-0.5, 0.5, (count, 3))) * ext
        local[np.arange(count), axis] = sign * 0.5 * ext[axis]
        normals = np.zeros((count, 3))
        normals[np.arange(count), axis] = sign
        rot = self._array("rotation")
        return local @ rot.T + self.center, normals @ rot.T

    def distance(self, points):
        return np.abs(self.residual(points))

    def contains(self, points):
        """(N,) bool: |local| <= extents / 2 on every axis of the canonical frame
        (``transform``), the surface included (to a relative 1e-9)."""
        pose = self.transform()
        local = (as_points(points) - pose[:3, 3]) @ pose[:3, :3]
        return np.all(np.abs(local) <= 0.5 * self._array("extents") * (1 + 1e-9), axis=1)

    def to_mesh(self):
        import trimesh

        return trimesh.creation.box(extents=self._array("extents"), transform=self.transform())

    # ----- pose and mass ------------------------------------------------------------------
    def transform(self):
        """The box's axes (``rotation``) at its centre."""
        return g.transform(self._array("rotation"), self._array("center"))

    def volume(self):
        return float(np.prod(self._array("extents")))

    def surface_area(self):
        return self.area()

    def centroid(self):
        return self._array("center")

    def unit_inertia(self):
        sq = self._array("extents") ** 2
        return np.array([sq[1] + sq[2], sq[0] + sq[2], sq[0] + sq[1]]) / 12.0

    # ----- facts for scenes, scenarios and the evaluation ---------------------------------
    #: The thesis deletes a strip of 10 % of the area (``random_cut``).
    removed_share: ClassVar[float] = 0.1
    shown_measures: ClassVar[tuple[str, ...]] = ("side_rel_max", "axis_angle_deg", "center_error")

    @classmethod
    def random(cls, rotation, center, size, rng):
        """Sides size * U(0.6, 1.4) each along the columns of ``rotation`` (with the box's
        sign rule)."""
        return cls(center, canonical_rotation(rotation), size * rng.uniform(0.6, 1.4, 3))

    def size(self):
        """The mean side."""
        return float(np.mean(self.extents))

    def area(self):
        """Area of the six faces."""
        ext = self._array("extents")
        return float(2.0 * (ext[0] * ext[1] + ext[0] * ext[2] + ext[1] * ext[2]))

    def bounding_box(self):
        half = 0.5 * np.abs(self.rotation) @ self.extents
        return self.center - half, self.center + half

    def random_cut(self, rng):
        """A strip along one edge of one of the two largest faces, with 10 % of the area.

        The face is perpendicular to the shortest side (axis i, random sign). Of its two
        in-face axes, a random one k is the strip's length direction; the strip lies
        against the face's edge at +-e_j / 2 along the other axis j (random sign) and has
        width w = 10 % of the total area / e_k. The largest faces hold at least 1/6 of the
        area, so w < e_j always.
        """
        ext = np.asarray(self.extents, dtype=np.float64)
        rot = np.asarray(self.rotation, dtype=np.float64)
        i = int(np.argmin(ext))
        j, k = rng.permutation([a for a in range(3) if a != i])
        face_sign, edge_sign = rng.choice([-1, 1], size=2)
        width = self.removed_share * self.area() / ext[k]
        direction = edge_sign * rot[:, j]
        origin = self.center + (0.5 * ext[j] - width) * direction
        return Cut(origin, direction, (i, int(face_sign)))

    def on_face(self, points, face):
        """(N,) bool: the points (N, 3) nearest to the face (axis i, sign +-1) of all six."""
        local = (points - np.asarray(self.center)) @ np.asarray(self.rotation)
        axis = np.argmin(np.abs(0.5 * np.asarray(self.extents) - np.abs(local)), axis=1)
        nearest = 2 * axis + (local[np.arange(len(points)), axis] > 0)
        return nearest == face[0] * 2 + (face[1] > 0)

    def error_measures(self, fitted):
        """side_error_0..2 (|side_e - side_o| for the true sides extents[0..2], each fitted
        side matched to a true one by ``match_box_axes``), side_error_max, side_rel_max
        (largest error relative to its true side), center_error, axis_angle_deg (largest
        angle between matched axes)."""
        perm = list(match_box_axes(self.rotation, fitted.rotation))
        true_sides = np.asarray(self.extents, float)
        side = np.abs(np.asarray(fitted.extents, float)[perm] - true_sides)
        t_rot, f_rot = np.asarray(self.rotation, float), np.asarray(fitted.rotation, float)
        angles = [g.axis_angle_deg(t_rot[:, i], f_rot[:, perm[i]]) for i in range(3)]
        out = {f"side_error_{i}": float(side[i]) for i in range(3)}
        out.update({
            "side_error_max": float(side.max()),
            "side_rel_max": float(np.max(side / true_sides)),
            "center_error": g.point_distance(self.center, fitted.center),
            "axis_angle_deg": max(angles),
        })
        return out

    def scene_surfaces(self):
        """The five faces a scan sees of the box resting on the floor (``UPPER_FACES``)
        as Planes (a disk patch around each face, for ``to_mesh``), each with its
        rectangle's area and a sampler of the rectangle."""
        from .plane import Plane  # here: at the top it would register Plane before Box

        rot, ext, center = self._array("rotation"), self._array("extents"), self._array("center")
        out = []
        for axis, sign in UPPER_FACES:
            normal = g.sign_canonical(sign * rot[:, axis])
            middle = center + sign * 0.5 * ext[axis] * rot[:, axis]
            others = np.delete(ext, axis)
            face = Plane(normal, np.float64(-normal @ middle), middle,
                         np.float64(0.5 * np.hypot(*others)))
            out.append((face, float(np.prod(others)),
                        functools.partial(self.sample_face, axis, sign)))
        return out

    def sample_face(self, axis: int, sign: int, count: int, rng):
        """(count, 3) points uniform on the face (axis, sign +-1) and its outward normal,
        repeated (count, 3)."""
        rot, ext = self._array("rotation"), self._array("extents")
        local = rng.uniform(-0.5, 0.5, (count, 3)) * ext
        local[:, axis] = sign * 0.5 * ext[axis]
        return local @ rot.T + self._array("center"), np.tile(sign * rot[:, axis], (count, 1))


#: The six assignments of fitted box axes to true ones.
_PERMUTATIONS = tuple(itertools.permutations(range(3)))


def match_box_axes(true_rotation, fitted_rotation) -> tuple[int, int, int]:
    """For each true axis i (column i of ``true_rotation`` (3, 3)), the fitted column that
    matches it: the permutation maximising the sum of |cos| between matched axes."""
    cos = np.abs(np.asarray(true_rotation, float).T @ np.asarray(fitted_rotation, float))
    return max(_PERMUTATIONS, key=lambda perm: cos[[0, 1, 2], list(perm)].sum())


def canonical_rotation(rotation):
    """``rotation`` (3, 3) under the box's sign rule: its first two columns flipped to a
    positive largest-magnitude component, the third their cross product (det stays +1)."""
    first = g.sign_canonical(rotation[:, :2].T)
    return np.stack([first[0], first[1], np.cross(first[0], first[1])], axis=1)


def _polish_faces(proj, near, far, threshold, rounds: int = 2):
    """Move each of the six faces to the median projection of the points near it.

    proj : (N, 3) projections of all points on the three normals; near, far : (3,) face
    offsets. A face's points are those within two thresholds of its plane (the histogram
    peak of a far face can be off by more than a threshold; the wider band still catches
    its points) and inside the face, two thresholds away from its edges: near an edge the
    band also holds the neighbouring faces' points, which would pull the face inwards.
    """
    faces = np.stack([near, far])  # (2, 3)
    margin = 2 * threshold
    for _ in range(rounds):
        lo, hi = faces.min(axis=0), faces.max(axis=0)
        # Thin boxes have no interior to spare: keep the whole face there.
        shrink = np.where(hi - lo > 4 * margin, margin, -threshold)
        inside = (proj >= lo + shrink) & (proj <= hi - shrink)  # (N, 3)
        for i in range(3):
            others = inside[:, (i + 1) % 3] & inside[:, (i + 2) % 3]
            for side in range(2):
                band = others & (np.abs(proj[:, i] - faces[side, i]) < margin)
                if np.count_nonzero(band) >= 3:
                    faces[side, i] = g.median(proj[band, i])
    return faces[0], faces[1]


def _opposite_face(proj, near, threshold):
    """Offset of the face parallel to the one at ``near``: the highest peak of the
    median-filtered histogram (bins one threshold wide) of the leftover projections
    (M,), away from the near face; NaN when no peak stands out."""
    if proj.size < _MEDIAN_BINS:
        return np.nan
    edges = np.arange(proj.min(), proj.max() + 2 * threshold, threshold)
    counts, _ = np.histogram(proj, bins=edges)
    # "full" then trimmed: "same" would return the kernel's length for tiny histograms.
    counts = np.convolve(counts, np.ones(_SUM_BINS))[_SUM_BINS // 2 : -(_SUM_BINS // 2)]
    padded = np.pad(counts, _MEDIAN_BINS // 2, mode="edge")
    smooth = np.median(np.lib.stride_tricks.sliding_window_view(padded, _MEDIAN_BINS), axis=1)
    centres = 0.5 * (edges[:-1] + edges[1:])
    smooth[np.abs(centres - near) < 3 * threshold] = 0
    peak = int(np.argmax(smooth))
    background = g.median(smooth[smooth > 0]) if np.any(smooth > 0) else 0.0
    if smooth[peak] < max(3.0, 3.0 * background):
        return np.nan
    close = np.abs(proj - centres[peak]) < threshold  # the smoothed peak may hold none
    return float(proj[close].mean()) if close.any() else np.nan


def _polar_steps(x, xp):
    """``POLAR_STEPS`` steps of Newton's iteration X <- (X + X^-T) / 2 from x (3, 3),
    towards its polar factor (``xp``: jax.numpy or numpy). The inverse's transpose is the
    cofactor matrix over the determinant: no LAPACK call (``linalg.inv`` is one on the
    CPU, 12 in the refinement's program)."""
    for _ in range(POLAR_STEPS):
        x = 0.5 * (x + g.inverse_transpose3(x, xp))
    return x


@jax.custom_jvp
def polar(x):
    """``_polar_steps`` of x (3, 3) in JAX, its derivative in closed form (below)."""
    return _polar_steps(x, jnp)


@polar.defjvp
def _polar_jvp(primals, tangents):
    # Each step's derivative written out, d(X^-T) = -X^-T dX^T X^-T, as sums of
    # elementwise products: the same derivative as JAX's through the cofactors, and the
    # box's refinement compiles in ~0.65 of the time (docs/engine.md, "Session 28").
    (x,), (dx,) = primals, tangents
    for _ in range(POLAR_STEPS):
        y = g.inverse_transpose3(x)
        dx = 0.5 * (dx - _product3(_product3(y, dx.T), y))
        x = 0.5 * (x + y)
    return x, dx


def _product3(a, b):
    """a @ b of (3, 3) matrices as a sum of elementwise products: full float32 on every
    backend, where a matrix product may round its inputs (a GPU's TF32)."""
    return jnp.sum(a[:, :, None] * b[None, :, :], axis=1)


def _nearest_plane(theta, p, xp):
    """The signed residuals [3 x (...)] of points p (3 coordinates) to the box's three
    planes (theta as ``Box.theta_residual``'s) and which plane is nearest, as three
    masks (first wins ties, as ``theta_residual`` picks)."""
    r = [theta[3 * i] * p[0] + theta[3 * i + 1] * p[1] + theta[3 * i + 2] * p[2] - theta[9 + i]
         for i in range(3)]
    first = xp.abs(r[0]) <= xp.abs(r[1])
    last = ~(xp.abs(xp.where(first, r[0], r[1])) <= xp.abs(r[2]))
    return r, (first & ~last, ~first & ~last, last)
