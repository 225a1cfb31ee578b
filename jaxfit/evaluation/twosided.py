"""Two-sided measures of a set of primitives against the object they stand for.

The PSDA's score is one-sided (the mean distance of a part's points to its primitive), so
it cannot see a primitive that reaches far beyond the points. These measures look both
ways (definitions, estimator variance and sample counts: docs/measures.md):

- ``volumetric_iou``: |object solid ∩ union of the primitives' solids| / |... ∪ ...|,
  Monte Carlo in the joint bounding box, with its standard error.
- ``winding_numbers`` / ``inside_mesh``: the object's inside test, by generalised winding
  numbers (Jacobson et al. 2013), so meshes that are not watertight still have an inside.
- ``surface_distances``: two-sided Chamfer and Hausdorff distances between the object's
  surface and the union's surface (a primitive's surface inside another is not surface).
- ``coverage``: for a point cloud without a mesh, the share of the primitives' surface
  with no point near it, where the volume cannot be measured.
- ``compare``: all of them in one dictionary, distances relative to the object's
  bounding-box diagonal.

A "model" here is anything with ``contains``, ``distance``, ``bounding_box`` and
``surface_area`` (jaxfit's primitives, and ``ConvexSolid`` for convex pieces such as
CoACD's). Everything is NumPy; every random choice comes from an explicit ``seed``.
"""

from __future__ import annotations

import numpy as np

from ..normals import kd_tree

__all__ = ["compare", "volumetric_iou", "surface_distances", "coverage", "winding_numbers",
           "inside_mesh", "solid_angles", "union_contains", "union_surface", "closed_surface",
           "mesh_distances", "sample_triangles", "triangles", "ConvexSolid", "oriented_box"]

#: Monte-Carlo points in the joint bounding box for the volumetric IoU: the standard
#: error is sqrt(IoU (1 - IoU) / n_union), at most 0.0025 for 40,000 points in the union.
VOLUME_SAMPLES = 40_000
#: Points sampled on each surface (the object's, the union's) for Chamfer and Hausdorff.
SURFACE_SAMPLES = 20_000
#: ``coverage``'s distance: a surface point with no cloud point within this fraction of
#: the object's diagonal is uncovered.
COVERAGE_RADIUS = 0.02
#: Triangles per cluster of the winding numbers' far field.
LEAF_SIZE = 32
#: A cluster counts as far from a point beyond FAR times its radius: its solid angle is
#: then its area vector's dipole term (docs/measures.md gives the error measured).
FAR = 3.0
#: A point at most this fraction of the diagonal inside a primitive is on its surface, not
#: in it (``_to_union``'s exact branch).
STRICT = 1e-9
#: A surface sample is on the union's surface if the point this fraction of the diagonal
#: out along its outward normal is in no other solid (``union_surface``): faces buried in
#: another solid and faces two solids share are not, and a slit narrower than this counts
#: as closed (CoACD's pieces meet across gaps of ~1e-5 of the diagonal: on the GraspIt
#: phone such a face 0.002 mm from its neighbour made a Hausdorff distance of 9.5 %).
OUTWARD = 1e-4
#: Elements per block of the exact per-triangle work (bounds the memory: ~8 of these
#: float64 arrays live at once, 64 MiB).
BLOCK = 1 << 20
#: Nearest object samples whose triangles are searched for a point's distance to a mesh.
CANDIDATES = 16


# ----- the object's inside: generalised winding numbers ---------------------------------
def triangles(vertices, faces) -> np.ndarray:
    """(F, 3, 3) float64 corners of a triangle mesh (vertices (V, 3), faces (F, 3) ints),
    with a clear error for anything else."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.isfinite(vertices).all():
        raise ValueError(f"vertices must be finite with shape (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu" or not len(faces):
        raise ValueError(f"faces must be a non-empty (F, 3) integer array, got {faces.shape} "
                         f"{faces.dtype}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"faces index vertices outside 0..{len(vertices) - 1}")
    return vertices[faces]


def solid_angles(tri, points) -> np.ndarray:
    """(P, T) signed solid angles of triangles (T, 3, 3) seen from points (P, 3): positive
    where a triangle's corners run counter-clockwise seen from the point (from inside a
    mesh with outward normals). Van Oosterom & Strackee's formula, exact; the work runs
    in blocks of about ``BLOCK`` (point, triangle) pairs."""
    points = np.asarray(points, dtype=np.float64)
    out = np.empty((len(points), len(tri)))
    step = max(1, BLOCK // max(len(tri), 1))
    for s in range(0, len(points), step):
        p = points[s:s + step, None, :]
        a, b, c = tri[None, :, 0] - p, tri[None, :, 1] - p, tri[None, :, 2] - p
        la, lb, lc = (np.sqrt(np.einsum("ptk,ptk->pt", v, v)) for v in (a, b, c))
        det = np.einsum("ptk,ptk->pt", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ptk,ptk->pt", a, b) * lc
               + np.einsum("ptk,ptk->pt", b, c) * la + np.einsum("ptk,ptk->pt", c, a) * lb)
        out[s:s + step] = 2.0 * np.arctan2(det, den)
    return out


def _clusters(tri, leaf_size: int) -> list[np.ndarray]:
    """Triangle indices split at the median of the longest side of their centroids' box
    until at most ``leaf_size`` remain: compact clusters for the far field."""
    centroids = tri.mean(axis=1)
    stack, leaves = [np.arange(len(tri))], []
    while stack:
        idx = stack.pop()
        if len(idx) <= leaf_size:
            leaves.append(idx)
            continue
        spread = np.ptp(centroids[idx], axis=0)
        order = np.argsort(centroids[idx, int(np.argmax(spread))], kind="stable")
        half = len(idx) // 2
        stack += [idx[order[:half]], idx[order[half:]]]
    return leaves


def winding_numbers(vertices, faces, points, *, far: float = FAR,
                    leaf_size: int = LEAF_SIZE) -> np.ndarray:
    """(N,) generalised winding numbers of a triangle mesh at points (N, 3).

    w(p) = sum of the triangles' signed solid angles seen from p / (4 pi): 1 inside and 0
    outside a closed, outward-oriented mesh, and a smooth in-between value near the holes
    of one that is not closed (a cube missing one face: 5/6 at its centre). Triangles are
    grouped in clusters of ``leaf_size``; a cluster farther than ``far`` times its radius
    contributes its dipole term, (sum of its area vectors) . (centre - p) / |centre - p|^3
    (Barill et al. 2018, order 0), the others their exact solid angles. ``far=np.inf``
    gives the exact sum. Memory stays bounded: one cluster at a time, the exact part in
    blocks (``solid_angles``).
    """
    tri = triangles(vertices, faces)
    points = _points(points)
    out = np.zeros(len(points))
    for idx in _clusters(tri, leaf_size):
        group = tri[idx]
        cross = np.cross(group[:, 1] - group[:, 0], group[:, 2] - group[:, 0])
        area = np.linalg.norm(cross, axis=1)
        centroids = group.mean(axis=1)
        centre = (area @ centroids / area.sum()) if area.sum() > 0 else centroids.mean(axis=0)
        radius = np.linalg.norm(group - centre, axis=2).max()
        diff = centre - points
        dist = np.linalg.norm(diff, axis=1)
        near = dist <= far * radius
        away = ~near
        out[away] += diff[away] @ (0.5 * cross.sum(axis=0)) / dist[away] ** 3
        if near.any():
            out[near] += solid_angles(group, points[near]).sum(axis=1)
    return out / (4.0 * np.pi)


def inside_mesh(vertices, faces, points, **options) -> np.ndarray:
    """(N,) bool: points (N, 3) inside the mesh, |winding number| >= 1/2 (the sign does
    not matter, so an inward-oriented mesh has an inside too). ``options`` go to
    ``winding_numbers``."""
    return np.abs(winding_numbers(vertices, faces, points, **options)) >= 0.5


# ----- convex pieces (CoACD's hulls) as models ------------------------------------------
class ConvexSolid:
    """The convex hull of vertices (V, 3), with the methods the measures read: a convex
    decomposition's piece (CoACD's) measured by the same code as the primitives."""

    name = "hull"
    colour = (149, 165, 166, 255)

    def __init__(self, vertices):
        from scipy.spatial import ConvexHull  # lazily: 0.3 s of import

        self.vertices = _points(vertices)
        hull = ConvexHull(self.vertices)
        self.equations = hull.equations  # outward unit normals and offsets (F, 4)
        faces = hull.simplices.copy()  # (qhull's corners run either way round)
        tri = self.vertices[faces]
        inward = np.einsum("fk,fk->f", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]),
                           self.equations[:, :3]) < 0
        faces[inward] = faces[inward][:, ::-1]
        self.faces = faces  # (F, 3), counter-clockwise seen from outside
        self.tri = self.vertices[faces]

    def contains(self, points) -> np.ndarray:
        """(N,) bool: on the inner side of every face plane (the surface included, to
        1e-9 of the hull's diagonal)."""
        tol = 1e-9 * np.linalg.norm(np.ptp(self.vertices, axis=0))
        return (_points(points, empty=True) @ self.equations[:, :3].T + self.equations[:, 3]
                <= tol).all(axis=1)

    def distance(self, points) -> np.ndarray:
        """(N,) unsigned distance to the hull's surface: inside, to the nearest face
        plane (exact for a convex solid); outside, to the nearest triangle."""
        points = _points(points, empty=True)
        planes = points @ self.equations[:, :3].T + self.equations[:, 3]
        out = -planes.max(axis=1)
        outside = out < 0
        if outside.any():
            out[outside] = _triangle_distances(points[outside], self.tri)
        return out

    def bounding_box(self):
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def surface_area(self) -> float:
        return float(0.5 * np.linalg.norm(
            np.cross(self.tri[:, 1] - self.tri[:, 0], self.tri[:, 2] - self.tri[:, 0]),
            axis=1).sum())

    def volume(self) -> float:
        from scipy.spatial import ConvexHull

        return float(ConvexHull(self.vertices).volume)

    def to_mesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def oriented_box(vertices):
    """The jaxfit ``Box`` of trimesh's minimum-volume oriented bounding box of vertices
    (V, 3) (``bounding_box_oriented``): a convex piece replaced by a primitive."""
    import trimesh

    from ..shapes import Box
    from ..shapes.box import canonical_rotation

    obb = trimesh.PointCloud(_points(vertices)).bounding_box_oriented
    pose = np.asarray(obb.primitive.transform, dtype=np.float64)
    rotation = pose[:3, :3]
    if np.linalg.det(rotation) < 0:
        rotation = rotation * np.array([1.0, 1.0, -1.0])
    rotation = canonical_rotation(rotation)
    # the box is symmetric, so sign flips of its axes leave it the same box
    return Box(pose[:3, 3].copy(), rotation, np.asarray(obb.primitive.extents, np.float64))


# ----- surfaces: sampling and distances -------------------------------------------------
def sample_triangles(tri, count: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """(count, 3) points uniform by area on triangles (F, 3, 3) and the index (count,) of
    the triangle each lies on, from the NumPy generator ``rng``."""
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not area.sum() > 0:
        raise ValueError("the mesh has no surface area to sample")
    face = rng.choice(len(tri), size=count, p=area / area.sum())
    u, v = rng.uniform(size=(2, count))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[face]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0]), face


def closed_surface(model, count: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """(count, 3) points uniform by area on a model's closed, bounded surface and their
    unit outward normals (count, 3): a cylinder's caps and a cone's base included
    (``Model.sample`` draws only the side), a box's six faces, a sphere, a plane's patch
    (its normal); a convex piece's triangles."""
    kind = getattr(model, "name", None)
    if kind in ("sphere", "box", "plane"):
        return model.sample(count, rng)
    if kind in ("cylinder", "cone"):
        pose = model.transform()
        radius = float(model.radius if kind == "cylinder" else model.base_radius)
        caps = 2 if kind == "cylinder" else 1
        disk = np.pi * radius ** 2
        on_disk = rng.binomial(count, caps * disk / (model.area() + caps * disk))
        side, side_normals = model.sample(count - on_disk, rng)
        rho = radius * np.sqrt(rng.uniform(size=on_disk))
        angle = rng.uniform(0, 2 * np.pi, on_disk)
        if kind == "cylinder":  # caps at z = +-height/2 of the canonical frame
            sign = np.where(rng.uniform(size=on_disk) < 0.5, -1.0, 1.0)
            z = 0.5 * sign * float(model.height)
        else:  # the base at z = 0, the apex at +z (Cone.transform)
            sign, z = -np.ones(on_disk), np.zeros(on_disk)
        local = np.stack([rho * np.cos(angle), rho * np.sin(angle), z], axis=1)
        points = np.concatenate([side, local @ pose[:3, :3].T + pose[:3, 3]])
        return points, np.concatenate([side_normals, sign[:, None] * pose[:3, 2]])
    if isinstance(model, ConvexSolid):
        points, face = sample_triangles(model.tri, count, rng)
        return points, model.equations[face, :3]
    raise TypeError(f"no closed-surface sampler for {type(model).__name__}")


def _has_solid(model) -> bool:
    return getattr(model, "name", None) != "plane"


def union_contains(models, points) -> np.ndarray:
    """(N,) bool: points (N, 3) in any model's solid (planes have none)."""
    points = _points(points)
    out = np.zeros(len(points), dtype=bool)
    for model in models:
        if _has_solid(model):
            out |= model.contains(points)
    return out


def union_surface(models, count: int, rng, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points on the union's surface: ``count`` drawn over the models' closed surfaces in
    proportion to their areas, keeping those where the point ``step`` out along the
    outward normal lies in no other model's solid (for a plane's patch, which has two
    sides: unless both sides do). So faces inside another solid and faces two solids
    share are dropped, and the kept points are uniform on the union's surface (where two
    solids' surfaces coincide on the outside, that strip is drawn twice). Returns points
    (S, 3) and the index (S,) of the model each lies on."""
    models = list(models)
    area = np.array([float(m.surface_area()) for m in models])
    if not area.sum() > 0:
        raise ValueError("the models have no surface area")
    counts = rng.multinomial(count, area / area.sum())
    points, owner = [], []
    for i, (model, n) in enumerate(zip(models, counts, strict=True)):
        if n == 0:
            continue
        p, normals = closed_surface(model, int(n), rng)
        others = [m for j, m in enumerate(models) if j != i]
        buried = union_contains(others, p + step * normals)
        if not _has_solid(model):
            buried &= union_contains(others, p - step * normals)
        points.append(p[~buried])
        owner.append(np.full(int((~buried).sum()), i))
    return np.concatenate(points), np.concatenate(owner)


def _triangle_distances(points, tri) -> np.ndarray:
    """(N,) distance of points (N, 3) to the nearest of triangles (T, 3, 3), exact: the
    projection where it falls in a triangle, else the nearest of its three edges."""
    out = np.full(len(points), np.inf)
    step = max(1, BLOCK // max(len(tri), 1))
    for s in range(0, len(points), step):
        out[s:s + step] = _pair_distances(points[s:s + step, None, :], tri[None]).min(axis=1)
    return out


def _pair_distances(p, tri) -> np.ndarray:
    """Distances of points p (..., 3) to triangles tri (..., 3, 3), broadcasting."""
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    n = np.cross(b - a, c - a)
    nn = np.einsum("...k,...k->...", n, n)
    inside = nn > 0
    for u, v in ((a, b), (b, c), (c, a)):
        inside = inside & (np.einsum("...k,...k->...", np.cross(v - u, p - u), n) >= 0)
    plane = np.abs(np.einsum("...k,...k->...", p - a, n)) / np.sqrt(np.where(nn > 0, nn, 1.0))
    edges = np.minimum(np.minimum(_segment(p, a, b), _segment(p, b, c)), _segment(p, c, a))
    return np.where(inside, plane, edges)


def _segment(p, a, b) -> np.ndarray:
    ab = b - a
    length = np.einsum("...k,...k->...", ab, ab)
    t = np.clip(np.einsum("...k,...k->...", p - a, ab) / np.where(length > 0, length, 1.0), 0, 1)
    d = p - a - t[..., None] * ab
    return np.sqrt(np.einsum("...k,...k->...", d, d))


def mesh_distances(tri, points, samples, faces_of) -> np.ndarray:
    """(N,) distance of points (N, 3) to a mesh's triangles (F, 3, 3): the exact distance
    to the nearest of the candidate triangles, those of the ``CANDIDATES`` nearest surface
    samples (``samples`` (S, 3) on triangles ``faces_of`` (S,): large triangles hold many)
    and the ``CANDIDATES`` nearest triangle centroids (small ones may hold none). Exact
    wherever the nearest triangle is a candidate; never above the nearest sample's
    distance."""
    k = min(CANDIDATES, len(samples))
    by_sample = faces_of[kd_tree(samples).query(points, k=k)[1].reshape(len(points), k)]
    j = min(CANDIDATES, len(tri))
    by_centre = kd_tree(tri.mean(axis=1)).query(points, k=j)[1].reshape(len(points), j)
    candidates = np.concatenate([by_sample, by_centre], axis=1)
    out = np.empty(len(points))
    step = max(1, BLOCK // candidates.shape[1])
    for s in range(0, len(points), step):
        cand = tri[candidates[s:s + step]]  # (n, k + j, 3, 3)
        out[s:s + step] = _pair_distances(points[s:s + step, None, :], cand).min(axis=1)
    return out


def _to_union(models, points, union_points, tol: float) -> np.ndarray:
    """(N,) distance of points (N, 3) to the union's surface.

    Outside every solid it is exact: the nearest model's ``distance`` (the union's
    nearest surface point is the nearest model's). Deeper than ``tol`` inside some
    solids it lies between L, the largest distance to the surface of a solid holding the
    point (a ball of that radius is inside the union), and U, the distance to the nearest
    kept union sample (``union_points``). It is taken as L where U - L is within two
    sample spacings (the nearest surface of the holding solid is on the union's surface,
    so L is exact), else U (the point sits where solids overlap).
    """
    points = _points(points)
    distances = [m.distance(points) for m in models]
    out = np.min(distances, axis=0)
    depth = np.zeros(len(points))  # L: the largest distance to a holding solid's surface
    for model, distance in zip(models, distances, strict=True):
        if _has_solid(model):
            held = model.contains(points)
            depth[held] = np.maximum(depth[held], distance[held])
    deep = depth > tol
    if deep.any():
        inner, lower = points[deep], depth[deep]
        upper = kd_tree(union_points).query(inner)[0]
        area = sum(float(m.surface_area()) for m in models)
        spacing = np.sqrt(area / len(union_points))
        out[deep] = np.where(upper - lower <= 2.0 * spacing, lower, upper)
    return out


# ----- the measures ---------------------------------------------------------------------
def volumetric_iou(tri, models, *, seed=0, samples: int = VOLUME_SAMPLES) -> dict:
    """Volumetric IoU of the solid of a mesh (triangles (F, 3, 3); ``inside_mesh``) and
    the union of the models' solids, by ``samples`` points uniform in the joint bounding
    box drawn from ``seed``. Returns ``viou``, its standard error ``viou_se`` =
    sqrt(viou (1 - viou) / n) with n the samples in either solid, the two volumes
    (``object_volume``, ``union_volume``) and ``volume_samples``."""
    rng = np.random.default_rng(seed)
    lo, hi = tri.reshape(-1, 3).min(axis=0), tri.reshape(-1, 3).max(axis=0)
    for model in models:
        if _has_solid(model):
            mlo, mhi = model.bounding_box()
            lo, hi = np.minimum(lo, mlo), np.maximum(hi, mhi)
    points = rng.uniform(lo, hi, (int(samples), 3))
    a = inside_mesh(tri.reshape(-1, 3), np.arange(3 * len(tri)).reshape(-1, 3), points)
    b = union_contains(models, points)
    either, both = int((a | b).sum()), int((a & b).sum())
    iou = both / either if either else float("nan")
    box = float(np.prod(hi - lo))
    return {"viou": iou, "viou_se": float(np.sqrt(iou * (1 - iou) / either)) if either else
            float("nan"), "object_volume": box * a.mean(), "union_volume": box * b.mean(),
            "volume_samples": int(samples)}


def surface_distances(object_points, to_object, models, union_points, diagonal: float,
                      tol: float) -> dict:
    """Two-sided distances between the object's surface and the union's, relative to
    ``diagonal``: ``object_points`` (A, 3) on the object's surface, ``to_object``
    (a function (B, 3) -> (B,) distances to the object's surface), ``union_points``
    (B, 3) on the union's surface (``union_surface``).

    ``chamfer`` = (mean over A of d(a, union) + mean over B of d(b, object)) / 2, with
    its standard error ``chamfer_se`` (of the two sample means); ``hausdorff`` = the
    larger of the two sampled maxima (a lower bound of the true one); both directions
    are returned too (``chamfer_object_to_union``, ``chamfer_union_to_object``).
    """
    forward = _to_union(models, object_points, union_points, tol)
    backward = to_object(union_points)
    se = 0.5 * np.sqrt(forward.var() / len(forward) + backward.var() / len(backward))
    return {"chamfer": 0.5 * (forward.mean() + backward.mean()) / diagonal,
            "chamfer_se": se / diagonal,
            "hausdorff": max(forward.max(), backward.max()) / diagonal,
            "chamfer_object_to_union": forward.mean() / diagonal,
            "chamfer_union_to_object": backward.mean() / diagonal}


def coverage(points, models, *, seed=0, samples: int = SURFACE_SAMPLES,
             radius: float = COVERAGE_RADIUS) -> dict:
    """The surface-to-points direction for a cloud (N, 3) without a mesh: the share of the
    union's surface (``union_surface``, ``samples`` points from ``seed``) with no cloud
    point within ``radius`` times the cloud's bounding-box diagonal: ``uncovered`` over
    the union and ``uncovered_per_model`` (M,) (NaN for a model with nothing kept)."""
    points = _points(points)
    models = list(models)
    diagonal = _diagonal(points)
    surface, owner = union_surface(models, samples, np.random.default_rng(seed),
                                   OUTWARD * diagonal)
    far = kd_tree(points).query(surface)[0] > radius * diagonal
    per = [float(far[owner == i].mean()) if (owner == i).any() else float("nan")
           for i in range(len(models))]
    return {"uncovered": float(far.mean()), "uncovered_per_model": per,
            "coverage_radius": radius}


def compare(mesh_or_points, models, *, seed=0, samples: int = VOLUME_SAMPLES,
            surface_samples: int = SURFACE_SAMPLES, coverage_radius: float = COVERAGE_RADIUS
            ) -> dict:
    """Every two-sided measure of ``models`` against an object.

    mesh_or_points : a ``trimesh.Trimesh``, a (vertices (V, 3), faces (F, 3)) pair, or a
        point cloud (N, 3) (then no volume: ``viou`` is absent and ``uncovered`` stands in).
    models : primitives (``jaxfit.shapes``) or ``ConvexSolid`` pieces; planes count as
        surface only.
    seed : seeds the volume samples, the object's and the union's surface samples
        (independent streams of one ``numpy.random.SeedSequence``).
    samples, surface_samples : Monte-Carlo points in the joint box; points on each surface.

    Returns a dict: ``diagonal`` (the object's bounding-box diagonal, the unit of every
    distance), ``chamfer``, ``hausdorff`` and their two directions (``surface_distances``),
    ``union_surface_kept`` (share of the models' surface on the union's surface) and,
    for a mesh, ``viou``, ``viou_se``, the volumes (``volumetric_iou``); for a cloud,
    ``uncovered`` (``coverage``).
    """
    models = list(models)
    if not models:
        raise ValueError("compare needs at least one model")
    volume_seed, object_seed, union_seed = np.random.SeedSequence(seed).spawn(3)
    tri = _as_triangles(mesh_or_points)
    cloud = _points(mesh_or_points) if tri is None else None
    diagonal = _diagonal(cloud if tri is None else tri.reshape(-1, 3))
    if not diagonal > 0:
        raise ValueError("the object has no extent (its bounding-box diagonal is 0)")
    tol = STRICT * diagonal
    union_points, _ = union_surface(models, surface_samples, np.random.default_rng(union_seed),
                                    OUTWARD * diagonal)
    out = {"diagonal": diagonal, "union_surface_kept": len(union_points) / surface_samples}
    if tri is None:
        rng = np.random.default_rng(object_seed)
        keep = cloud if len(cloud) <= surface_samples else cloud[
            rng.choice(len(cloud), surface_samples, replace=False)]
        tree = kd_tree(cloud)
        out.update(surface_distances(keep, lambda q: tree.query(q)[0], models, union_points,
                                     diagonal, tol))
        out.update(coverage(cloud, models, seed=union_seed, samples=surface_samples,
                            radius=coverage_radius))
        return out
    object_points, faces_of = sample_triangles(tri, surface_samples,
                                               np.random.default_rng(object_seed))
    out.update(surface_distances(
        object_points, lambda q: mesh_distances(tri, q, object_points, faces_of), models,
        union_points, diagonal, tol))
    out.update(volumetric_iou(tri, models, seed=volume_seed, samples=samples))
    return out


def _as_triangles(obj) -> np.ndarray | None:
    """(F, 3, 3) triangles of a mesh or a (vertices, faces) pair; None for a cloud."""
    if hasattr(obj, "vertices") and hasattr(obj, "faces"):
        return triangles(obj.vertices, obj.faces)
    if isinstance(obj, tuple | list) and len(obj) == 2:
        return triangles(*obj)
    return None


def _points(points, empty: bool = False) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if (arr.ndim != 2 or arr.shape[1] != 3 or not (len(arr) or empty)
            or not np.isfinite(arr).all()):
        raise ValueError(f"points must be a non-empty finite (N, 3) array, got {arr.shape}")
    return arr


def _diagonal(points) -> float:
    return float(np.linalg.norm(np.ptp(points, axis=0)))
