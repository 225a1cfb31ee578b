"""Surface normals of a point cloud by local PCA, oriented where that can be done.

``estimate_normals(points, k=16)`` gives unit normals (N, 3) of a cloud (N, 3): for each
point, the eigenvector with the smallest eigenvalue of the 3 x 3 covariance of its k
nearest neighbours (the point itself included). Neighbours come from scipy's ``cKDTree``
(a brute-force kNN in JAX is O(N^2)); the covariances are batched in NumPy, and their
smallest eigenvectors found in closed form (``smallest_eigenvectors``;
``numpy.linalg.eigh`` where that is ill-conditioned).

Orientation (the sign of each normal) follows Hoppe et al. 1992, "Surface reconstruction
from unorganized points": a minimum spanning tree over the (undirected) k-NN graph with edge
weights 1 - |n_i . n_j| (``scipy.sparse.csgraph``), so the sign is propagated across
smooth stretches first, from one seed per connected component whose sign is fixed to
point away from the centroid (or toward a viewpoint). The cheap option flips every normal
on its own toward the same direction, which is right for convex objects seen from
outside and for scans seen from one viewpoint.

Measurements: docs/normals.md.
"""

from __future__ import annotations

import numbers
import os

import numpy as np

from . import _checks

#: Orientation methods: Hoppe's propagation, each normal on its own, or no orientation.
ORIENTATIONS = ("mst", "direct", None)
#: Points per block of covariances: bounds the (block, k, 3) neighbour array's memory.
BLOCK = 65536
#: Added to every MST edge weight, since csgraph treats a weight of 0 as a missing edge.
_EPS = 1e-9


#: Below this many queries a cloud's KD-tree query runs on one thread: scipy's own
#: threads cost more than they save on small clouds, which are instead queried side by
#: side, one per core (docs/normals.md).
SMALL_QUERY = 4096


def knn(points: np.ndarray, k: int, queries: np.ndarray | None = None,
        workers: int = -1, distances: bool = False):
    """Indices (M, k) of the k nearest points of points (N, 3) to each query (M, 3)
    (default: the points themselves, each first among its own neighbours up to ties),
    on ``workers`` threads (-1: all cores); with ``distances``, (distances (M, k),
    indices)."""
    from scipy.spatial import cKDTree

    queries = points if queries is None else queries
    found = cKDTree(points).query(queries, k=k, workers=workers)
    return found if distances else found[1]


def knn_many(clouds, queries, ks, distances: bool = False) -> list:
    """``knn(clouds[i], ks[i], queries[i], distances=distances)`` for every cloud: large
    ones one after the other on all cores; small ones (< SMALL_QUERY queries), if there
    are several, one per core at a time (cKDTree releases the GIL while it queries)."""
    out = [None] * len(clouds)
    small = [i for i, q in enumerate(queries) if len(q) < SMALL_QUERY]
    if len(small) < 2:  # nothing to run side by side
        small = []
    for i in sorted(set(range(len(clouds))) - set(small)):
        out[i] = knn(clouds[i], ks[i], queries[i], distances=distances)
    if small:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(os.cpu_count() or 1) as pool:
            found = pool.map(lambda i: knn(clouds[i], ks[i], queries[i], workers=1,
                                           distances=distances), small)
            for i, hood in zip(small, found, strict=True):
                out[i] = hood
    return out


def pca_normals(points: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Unit normals (M, 3), unoriented: the least-variance direction of each
    neighbourhood points[neighbours] (M, k, 3)."""
    out = np.empty((len(neighbours), 3), points.dtype)
    for start in range(0, len(neighbours), BLOCK):
        hood = points[neighbours[start:start + BLOCK]]  # (B, k, 3)
        out[start:start + BLOCK] = smallest_eigenvectors(_covariances(hood))
    return out


def _covariances(hood: np.ndarray) -> np.ndarray:
    """Scatter matrices (B, 3, 3) of neighbourhoods (B, k, 3), from sums of products of
    coordinate arrays (faster than centring and an einsum over (B, k, 3)). Each
    neighbourhood is first shifted to its first point, so the sums lose no digits on a
    cloud far from the origin."""
    x, y, z = (hood[:, :, i] - hood[:, :1, i] for i in range(3))  # (B, k) each
    k = hood.shape[1]
    sx, sy, sz = x.sum(axis=1), y.sum(axis=1), z.sum(axis=1)

    def scatter(u, v, su, sv):
        return np.einsum("bk,bk->b", u, v) - su * sv / k

    xx, yy, zz = scatter(x, x, sx, sx), scatter(y, y, sy, sy), scatter(z, z, sz, sz)
    xy, xz, yz = scatter(x, y, sx, sy), scatter(x, z, sx, sz), scatter(y, z, sy, sz)
    return np.stack([xx, xy, xz, xy, yy, yz, xz, yz, zz], axis=1).reshape(-1, 3, 3)


def smallest_eigenvectors(cov: np.ndarray) -> np.ndarray:
    """Unit eigenvectors (B, 3) of the smallest eigenvalue of symmetric 3 x 3 matrices
    cov (B, 3, 3), in closed form: the eigenvalue by the trigonometric solution of the
    characteristic cubic, the vector as the largest cross product of two rows of
    cov - lambda I (as PCL's eigen33), a few times faster than batched
    ``numpy.linalg.eigh`` (docs/normals.md). Where the smallest eigenvalue is (nearly)
    repeated the cross products vanish and the direction is ill-defined: those rows fall
    back to ``eigh``.
    """
    a, b, c = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]  # element arrays: NumPy's
    d, e, f = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]  # batched det/cross were slow
    mean = (a + b + c) / 3.0
    a0, b0, c0 = a - mean, b - mean, c - mean
    p = np.sqrt((a0 * a0 + b0 * b0 + c0 * c0 + 2.0 * (d * d + e * e + f * f)) / 6.0)
    det = a0 * (b0 * c0 - f * f) - d * (d * c0 - f * e) + e * (d * f - b0 * e)
    cubed = np.where(p > 0, p, 1.0) ** 3
    phi = np.arccos(np.clip(det / (2.0 * cubed), -1.0, 1.0)) / 3.0
    smallest = mean + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    r0 = np.stack([a - smallest, d, e], axis=1)  # rows of cov - smallest * I
    r1 = np.stack([d, b - smallest, f], axis=1)
    r2 = np.stack([e, f, c - smallest], axis=1)
    crosses = np.stack([_cross(r0, r1), _cross(r0, r2), _cross(r1, r2)], axis=1)  # (B, 3, 3)
    lengths = np.sqrt(np.sum(crosses * crosses, axis=2))
    pick = np.argmax(lengths, axis=1)
    every = np.arange(len(cov))
    best = lengths[every, pick]
    out = crosses[every, pick] / np.where(best > 0, best, 1.0)[:, None]
    scale = np.maximum(np.abs(mean) * 3.0, np.finfo(cov.dtype).tiny)
    unclear = best <= 1e-8 * scale * scale
    if unclear.any():  # eigh sorts eigenvalues ascending: column 0
        out[unclear] = np.linalg.eigh(cov[unclear])[1][:, :, 0]
    return out


def _cross(u, v):
    """Row-wise cross products of u, v (B, 3)."""
    return np.stack([u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1], u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
                     u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]], axis=1)


def _reference_direction(points: np.ndarray, viewpoint) -> np.ndarray:
    """(N, 3) directions a normal should agree with: toward the viewpoint if given,
    else away from the centroid."""
    if viewpoint is None:
        return points - points.mean(axis=0)
    return viewpoint - points


def orient_direct(normals: np.ndarray, points: np.ndarray, viewpoint=None) -> np.ndarray:
    """Each normal (N, 3) flipped on its own to agree with ``_reference_direction``."""
    flip = np.einsum("ij,ij->i", normals, _reference_direction(points, viewpoint)) < 0
    return np.where(flip[:, None], -normals, normals)


def _knn_graph(neighbours: np.ndarray, normals: np.ndarray):
    """Sparse (N, N) k-NN graph weighted 1 - |n_i . n_j| + eps. Built in CSR form
    directly (row i holds i's neighbours) and left unsymmetrised: csgraph's spanning
    tree reads it as undirected, and the weights are symmetric anyway. Self-loops are
    harmless: a tree never takes them."""
    from scipy.sparse import csr_matrix

    n, k = neighbours.shape
    dots = np.einsum("ij,ikj->ik", normals, normals[neighbours])
    weight = (1.0 - np.abs(dots) + _EPS).reshape(-1)
    return csr_matrix((weight, neighbours.reshape(-1), np.arange(0, n * k + 1, k)), (n, n))


def _seeds(normals, points, labels, viewpoint):
    """One seed per component and the sign (+-1) that makes its normal agree with
    ``_reference_direction``. The seed is where that sign is least ambiguous: toward a
    viewpoint, the point nearest to it (its normal faces the viewpoint on any smooth
    surface); away from the centroid, the point whose tangent plane is farthest from the
    centroid (on a closed surface, a point on the far side, never one facing inward)."""
    ref = _reference_direction(points, viewpoint)
    dot = np.einsum("ij,ij->i", normals, ref)
    score = np.abs(dot) if viewpoint is None else -np.linalg.norm(ref, axis=1)
    order = np.lexsort((score, labels))  # by label, the best score last in each
    last = np.r_[labels[order][1:] != labels[order][:-1], True]
    seeds = order[last]
    return seeds, np.where(dot[seeds] < 0, -1.0, 1.0)


def _path_signs(parent: np.ndarray, edge_sign: np.ndarray) -> np.ndarray:
    """Product (N,) of the edge signs on the path from every node to its root, roots
    included, in a forest given by parent (N,) (a root is its own parent and edge_sign
    holds its own sign). Pointer jumping: O(N log depth) in whole-array steps, where a
    walk along the breadth-first order would be a Python loop over N."""
    acc, up = edge_sign.copy(), parent.copy()
    while True:
        jump = up != up[up]  # nodes whose current ancestor is not yet a root
        if not jump.any():
            break
        acc = np.where(jump, acc * acc[up], acc)
        up = up[up]
    is_root = up == np.arange(len(up))
    return np.where(is_root, acc, acc * acc[up])


def orient_mst(normals: np.ndarray, points: np.ndarray, neighbours: np.ndarray,
               viewpoint=None) -> np.ndarray:
    """Normals (N, 3) made consistent along a minimum spanning tree of the k-NN graph
    (Hoppe et al. 1992), each component's seed agreeing with ``_reference_direction``."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import (
        breadth_first_order,
        connected_components,
        minimum_spanning_tree,
    )

    n = len(points)
    tree = minimum_spanning_tree(_knn_graph(neighbours, normals))
    count, labels = connected_components(tree, directed=False)
    seeds, seed_sign = _seeds(normals, points, labels, viewpoint)
    # A virtual root (node n) joined to every seed makes the forest one tree, so a single
    # breadth-first pass gives every node its parent.
    rows, cols = tree.nonzero()
    rows, cols = np.r_[rows, np.full(count, n)], np.r_[cols, seeds]
    joined = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n + 1, n + 1))
    _, parent = breadth_first_order(joined, n, directed=False, return_predecessors=True)
    parent = parent[:n]
    is_seed = parent == n
    parent = np.where(is_seed, np.arange(n), parent)
    edge = np.where(np.einsum("ij,ij->i", normals, normals[parent]) < 0, -1.0, 1.0)
    edge[seeds] = seed_sign
    return normals * _path_signs(parent, edge)[:, None]


def _check_k(k, n: int) -> int:
    if isinstance(k, bool) or not isinstance(k, numbers.Integral) or k < 3:
        raise ValueError(f"k must be an integer >= 3 (a plane needs 3 points), got {k!r}")
    if k > n:
        raise ValueError(f"k = {k} is larger than the number of points ({n})")
    return int(k)


def distinct_neighbours(points, queries, k, dist, hood):
    """(base, k, neighbours (M, k) into base) for PCA, from the k nearest neighbours
    ``hood`` of queries (M, 3) among points (N, 3) at distances ``dist``: as given,
    unless a point has an exact copy; then among the distinct points (neighbourhoods of
    repeated points can hold fewer than three distinct ones: a scan with every point
    stored 16 times had none, and every normal was arbitrary)."""
    if dist.shape[1] < 2 or not (dist[:, 1] == 0).any():
        return points, k, hood
    distinct = np.unique(points, axis=0)
    if len(distinct) < 3:
        return points, k, hood
    k = min(k, len(distinct))
    return distinct, k, knn(distinct, k, queries)


def normals_at(points: np.ndarray, indices: np.ndarray, k: int = 16) -> np.ndarray:
    """Unoriented unit normals (M, 3) at points[indices] only, from their k nearest
    neighbours among all points (N, 3): what ``fit`` needs, since it draws minimal
    samples from a pool of points and never reads the others' normals."""
    return normals_at_many([points], [indices], [k])[0]


def normals_at_many(clouds, indices, ks) -> list[np.ndarray]:
    """``normals_at(clouds[i], indices[i], ks[i])`` for every cloud: one KD-tree each,
    one PCA per neighbourhood size over all their clouds stacked (the eigen-solver's fixed
    cost, some 50 NumPy calls, is paid once per block, not once per cloud)."""
    ks = [_check_k(k, len(c)) for c, k in zip(clouds, ks, strict=True)]
    queries = [c[i] for c, i in zip(clouds, indices, strict=True)]
    found = knn_many(clouds, queries, ks, distances=True)
    clouds, neighbours = list(clouds), [None] * len(clouds)
    for i, (dist, hood) in enumerate(found):
        clouds[i], ks[i], neighbours[i] = distinct_neighbours(clouds[i], queries[i], ks[i],
                                                              dist, hood)
    out = [None] * len(clouds)
    for k in set(ks):
        which = [i for i, ki in enumerate(ks) if ki == k]
        offsets = np.cumsum([0] + [len(clouds[i]) for i in which[:-1]])
        normals = pca_normals(np.concatenate([clouds[i] for i in which]),
                              np.concatenate([neighbours[i] + o
                                              for i, o in zip(which, offsets, strict=True)]))
        splits = np.cumsum([len(neighbours[i]) for i in which])[:-1]
        for i, part in zip(which, np.split(normals, splits), strict=True):
            out[i] = part
    return out


def estimate_normals(points, k: int = 16, *, orient: str | None = "mst",
                     viewpoint=None) -> np.ndarray:
    """Unit normals (N, 3) of a point cloud (N, 3) by PCA over k nearest neighbours.

    Parameters
    ----------
    points : (N, 3) array-like of finite coordinates.
    k : neighbourhood size, the point itself included; 3 <= k <= N.
    orient : "mst" (default): signs propagated along a minimum spanning tree of the k-NN
        graph (Hoppe et al. 1992), one seed per connected component pointing away from
        the centroid, or toward ``viewpoint``; consistent on any smooth closed or open
        surface. "direct": each normal flipped on its own away from the centroid (or
        toward ``viewpoint``); cheap, right for convex objects and single-view scans.
        None: signs as the eigen-solver leaves them.
    viewpoint : optional (3,) point the normals should face (a scanner's position).

    Returns
    -------
    (N, 3) float64 unit normals.
    """
    cloud = _checks.cloud(points)
    k = _check_k(k, len(cloud))
    if orient not in ORIENTATIONS:
        raise ValueError(f"unknown orient {orient!r}; expected one of {ORIENTATIONS}")
    if viewpoint is not None:
        viewpoint = _checks.cloud(np.reshape(viewpoint, (1, 3)), "viewpoint")[0]
    dist, neighbours = knn(cloud, k, distances=True)
    normals = pca_normals(*distinct_neighbours(cloud, cloud, k, dist, neighbours)[::2])
    if orient == "mst":
        return orient_mst(normals, cloud, neighbours, viewpoint)
    if orient == "direct":
        return orient_direct(normals, cloud, viewpoint)
    return normals
