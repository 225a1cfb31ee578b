"""Surface normals of a point cloud by local PCA, oriented where that can be done.

``estimate_normals(points, k=16)`` gives unit normals (N, 3) of a cloud (N, 3): for each
point, the eigenvector with the smallest eigenvalue of the 3 x 3 covariance of its k
nearest neighbours (the point itself included). Neighbours come from pykdtree's exact
KD-tree (``nearest``; a brute-force kNN in JAX is O(N^2)); for few queries in a large
cloud, a tree over the points near them only (``knn_near``: cubic cells hashed in one
pass over the cloud, the same neighbours). The covariances are batched in NumPy, and
their smallest eigenvectors found in closed form (``smallest_eigenvectors``;
``numpy.linalg.eigh`` where that is ill-conditioned). Where a neighbourhood is far from
flat (outliers or a second surface among the k nearest), its plane is refitted on the
neighbours near it (``TRIM_PASSES`` trimmed passes): a surface point's normal then
follows its surface rather than the outliers around it.

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

import functools
import numbers
import os
import threading

import numpy as np

from . import _checks
from .engine.backend import cores, in_threads, submitted
from .io.inputs import converted
from .shapes._geometry import column_bounds, offsets

#: Orientation methods: Hoppe's propagation, each normal on its own, or no orientation.
ORIENTATIONS = ("mst", "direct", None)
#: Points per block of covariances: bounds the (block, k, 3) neighbour array's memory.
BLOCK = 65536
#: Added to every MST edge weight, since csgraph treats a weight of 0 as a missing edge.
_EPS = 1e-9


#: Points per leaf of ``nearest``'s pykdtree: 16-32 query fastest on 1e3-1e5 points.
NEAREST_LEAF = 16
#: Clouds of fewer queries are queried side by side, one per core, when there are
#: several: their searches are too short for the OpenMP threads of each (docs/normals.md).
SMALL_QUERY = 4096


def kd_tree(points: np.ndarray):
    """The ``scipy.spatial.cKDTree`` over points (N, 3) for the searches pykdtree has no
    form of (radius pairs, bounded distances, several ranks at once; ``knn``'s k nearest
    use ``nearest``): sliding-midpoint splits and no node shrinking, the same answers as
    the default tree (the search is exact) from a tree built in about half the time
    (docs/engine.md, "Session 14")."""
    from scipy.spatial import cKDTree

    return cKDTree(points, balanced_tree=False, compact_nodes=False)


def knn(points: np.ndarray, k: int, queries: np.ndarray | None = None,
        workers: int = -1, distances: bool = False):
    """Indices (M, k) of the k nearest points of points (N, 3) to each query (M, 3)
    (default: the points themselves, each first among its own neighbours up to ties);
    with ``distances``, (distances (M, k), indices). Few queries in a large cloud
    (``few_queries``) are answered from the points near them (``knn_near``, its scipy
    queries on ``workers`` threads, -1: all cores), the same neighbours up to ties,
    without a tree over all; the others by ``nearest``."""
    if queries is not None and few_queries(len(queries), len(points)):
        found = knn_near(points, k, queries, workers)
        if found is not None:
            return found if distances else found[1]
    queries = points if queries is None else queries
    found = nearest(points, queries, k)
    return found if distances else found[1]


def nearest(points: np.ndarray, queries: np.ndarray, k: int):
    """(distances (M, k) float64, indices (M, k) intp) of the k nearest of points (N, 3),
    k <= N, to each query (M, 3), nearest first: pykdtree's exact search, on its OpenMP
    threads (``OMP_NUM_THREADS``). The same neighbours and distances as scipy's
    ``cKDTree`` up to ties, in 1/3 of its time at k = 16 on 1e3 points and 2/3 on 1e4-1e5
    (its heap of k is cheaper; docs/normals.md, "pykdtree for the k nearest"). Raises
    ValueError for k > N, where pykdtree would pad with out-of-range indices."""
    KDTree = _pykdtree()
    if k > len(points):
        raise ValueError(f"k = {k} nearest asked of {len(points)} points")
    points = np.ascontiguousarray(points, np.float64)
    queries = np.ascontiguousarray(queries, np.float64)
    dist, hood = KDTree(points, leafsize=NEAREST_LEAF).query(queries, k=k)
    return dist, hood.astype(np.intp)


#: The spin count pykdtree's own OpenMP runtime is loaded with (``_pykdtree``).
KDTREE_SPIN = "0"


_pykdtree_lock = threading.Lock()  # (knn_many's threads may make the first call at once)


@functools.cache
def _pykdtree():
    """pykdtree's KDTree class. Its wheels bundle a private copy of GNU OpenMP, which
    reads its settings once, as it loads: where that copy is there and not yet loaded,
    it is loaded with ``GOMP_SPINCOUNT=KDTREE_SPIN`` (the environment as it was before
    and after), unless the user set the spin count or the wait policy. Why: after each
    query its threads would spin for milliseconds on the cores the fit's kernel needs
    next (a cylinder fit of 1e3 points after a pause: 9.2 -> 5.6 ms; docs/normals.md).
    A libgomp that others share (no private copy) is left as it is."""
    import importlib.util
    import sys
    from pathlib import Path

    with _pykdtree_lock:
        spec = importlib.util.find_spec("pykdtree")
        private = spec is not None and spec.origin is not None and any(
            (Path(spec.origin).parent.parent / "pykdtree.libs").glob("libgomp*"))
        if ("pykdtree.kdtree" in sys.modules or not private
                or {"GOMP_SPINCOUNT", "OMP_WAIT_POLICY"} & set(os.environ)):
            from pykdtree.kdtree import KDTree
            return KDTree
        os.environ["GOMP_SPINCOUNT"] = KDTREE_SPIN
        try:
            from pykdtree.kdtree import KDTree
        finally:
            os.environ.pop("GOMP_SPINCOUNT", None)
        return KDTree


def knn_many(clouds, queries, ks, distances: bool = False) -> list:
    """``knn(clouds[i], ks[i], queries[i], distances=distances)`` for every cloud: large
    ones one after the other; small ones (< SMALL_QUERY queries), if there are several,
    one per core at a time (pykdtree releases the GIL while it queries)."""
    out = [None] * len(clouds)
    small = [i for i, q in enumerate(queries) if len(q) < SMALL_QUERY]
    if len(small) < 2:  # nothing to run side by side
        small = []
    for i in sorted(set(range(len(clouds))) - set(small)):
        out[i] = knn(clouds[i], ks[i], queries[i], distances=distances)
    if small:
        for i, hood in in_threads(lambda i: knn(clouds[i], ks[i], queries[i], workers=1,
                                                distances=distances), small, cores()):
            out[i] = hood
    return out


#: ``knn_near`` replaces the tree over all N points when N >= NEAR_MIN and the queries
#: number at most N / NEAR_FACTOR: below that the tree costs less (docs/normals.md).
NEAR_MIN = 1 << 20
NEAR_FACTOR = 1024
#: Each query's first radius is the distance to its SUBSAMPLE_RANK-th nearest point in a
#: random 1 / SUBSAMPLE of the points, scaled to hold COUNT_SCALE * k points of the whole
#: cloud (``_radii``): some 90 % of the queries are certified at it (docs/normals.md).
SUBSAMPLE = 32
SUBSAMPLE_RANK = 8
COUNT_SCALE = 2.25
#: One pass over the cloud keeps the points within HARVEST radii of each query, so that
#: the queries whose k-th neighbour lies between one and HARVEST radii need no other.
HARVEST = 1.5
#: Passes over the cloud after which the tree over all points is used instead.
MAX_PASSES = 4
#: Points per block of a pass over the cloud: bounds its temporary arrays' memory.
CELL_BLOCK = 1 << 18
#: A k-th neighbour distance certifies a radius r when it is at most r * CERTIFY: the
#: margin covers the rounding of the cell coordinates (the queries kept within 2^28 base
#: cells of the origin, radii of at least 4 base cells, ``_radii``: an error under 1e-7
#: of a cell) and of the distances.
CERTIFY = 1.0 - 1e-6
#: Odd 64-bit multipliers of the cell keys (one per axis, one for the level) and of the
#: two hash tables' slots (the first two).
_MIX = np.array([0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9,
                 0xD6E8FEB86659FD93], dtype=np.uint64)


def few_queries(m: int, n: int) -> bool:
    """Whether m queries among n points go to ``knn_near`` rather than a tree over all."""
    return n >= NEAR_MIN and 0 < m * NEAR_FACTOR <= n


def _cells(points: np.ndarray, origin: np.ndarray, side: float, out=None) -> np.ndarray:
    """Integer cell coordinates (B, 3) of points (B, 3) in cubic cells of the given side
    with a corner at origin. ``out``: an optional (>= B, 3) float64 scratch array."""
    t = np.subtract(points, origin, out=None if out is None else out[:len(points)])
    t /= side
    return _floor(t)


def _floor(t: np.ndarray) -> np.ndarray:
    """floor(t) as int64, clipped to +-2^40 (far points stay far, without overflow);
    overwrites t."""
    np.floor(t, out=t)
    np.clip(t, -2.0 ** 40, 2.0 ** 40, out=t)
    return t.astype(np.int64)


def _cell_key(cells: np.ndarray, level) -> np.ndarray:
    """64-bit keys (B,) of integer cells (B, 3) at levels (B,) or one level."""
    u = cells.view(np.uint64)
    key = (u[:, 0] * _MIX[0]) ^ (u[:, 1] * _MIX[1]) ^ (u[:, 2] * _MIX[2])
    key ^= np.asarray(level, np.uint64) * _MIX[3]
    return key


def _slot(key: np.ndarray, which: int, bits: int) -> np.ndarray:
    """Slots (B,) in [0, 2^bits) of keys (B,) in hash table ``which`` (0 or 1)."""
    return (key * _MIX[which]) >> np.uint64(64 - bits)


def _levels(radii: np.ndarray, base: float) -> np.ndarray:
    """Cell level (M,) of each query's box of half-side radii (M,) (>= 4 base): a cell
    side in (radii / 4, radii / 2], except that the levels within one of the median's
    take the median's (sides in (radii / 8, radii]), so that a pass over the cloud
    hashes most points once."""
    own = np.maximum(np.floor(np.log2(radii / base)).astype(np.int64) - 1, 0)
    shared = int(np.median(own))
    return np.where(np.abs(own - shared) <= 1, shared, own)


def _box_cells(queries, radii, origin, base: float):
    """(cells (C, 3), levels (C,)): every cell at each query's level (``_levels``) that
    meets the box of half-side radii around it. The box is taken in base-cell units, as
    the points' cells are, so its rounding is that of the points' (``CERTIFY``)."""
    levels = _levels(radii, base)
    t, half = (queries - origin) / base, (radii / base)[:, None]
    lo = _floor(t - half) >> levels[:, None]
    span = (_floor(t + half) >> levels[:, None]) - lo + 1
    sizes = span.prod(axis=1)
    owner = np.repeat(np.arange(len(queries)), sizes)
    j = np.arange(sizes.sum()) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    ny, nz = span[owner, 1], span[owner, 2]
    steps = np.stack([j // (ny * nz), (j // nz) % ny, j % nz], axis=1)
    return lo[owner] + steps, levels[owner]


def near_mask(points, queries, radii, origin, base: float) -> np.ndarray:
    """Boolean mask (N,) of points (N, 3) holding at least every point within radii[j]
    (>= 4 base) of query j (M, 3) along each axis: the points of the cells that meet the
    query's box (``_box_cells``; cells of side base * 2^level, nested across levels, a
    corner at origin). Those cells are marked in two one-bit hash tables, a point is kept
    where its cell is marked in both: a few points of other cells (collisions) are kept
    too, one in some thousand per level where a table is 1/32 full."""
    cells, levels = _box_cells(queries, radii, origin, base)
    bits = int(min(24, max(16, (32 * len(cells) - 1).bit_length())))
    keys = _cell_key(cells, levels)
    tables = np.zeros((2, 1 << bits), bool)
    for which in (0, 1):
        tables[which, _slot(keys, which, bits)] = True
    out = np.empty(len(points), bool)
    scratch = np.empty((min(CELL_BLOCK, len(points)), 3))
    present = np.unique(levels)
    for start in range(0, len(points), CELL_BLOCK):
        cells = _cells(points[start:start + CELL_BLOCK], origin, base, scratch)
        hit = out[start:start + CELL_BLOCK]
        hit[:] = False
        for level in present:
            keys = _cell_key(cells >> level, level)
            first = np.flatnonzero(tables[0, _slot(keys, 0, bits)])
            hit[first[tables[1, _slot(keys[first], 1, bits)]]] = True
    return out


def _radii(points, k: int, queries, origin) -> tuple[float, np.ndarray, np.ndarray]:
    """(base, radii (M,), bounds (M,)): each query's first search radius, the finest
    cell side, and a radius at which each is sure to be certified (counting repeated
    points as many): its k-th neighbour distance in a random 1 / SUBSAMPLE of the points
    (inf if that holds fewer).

    The radius scales the query's SUBSAMPLE_RANK-th neighbour distance in the subsample
    by the subsample's density ratio to the power 1 / d, d the cloud's dimension (1 to
    3) from how that distance grows with the rank. The base is a quarter of the least
    radius, or more to keep the queries within 2^28 cells of the origin; it is 0 where
    every sampled point and query coincide."""
    rng = np.random.default_rng(0)
    picked = np.sort(rng.integers(0, len(points), max(k, len(points) // SUBSAMPLE)))
    sub = points.take(picked[np.r_[True, picked[1:] != picked[:-1]]], axis=0)  # (distinct)
    rank = min(SUBSAMPLE_RANK, len(sub))
    ranks = [max(1, rank // 2), rank, min(k, len(sub))]
    half, far, bounds = kd_tree(sub).query(queries, k=ranks)[0].T
    if len(sub) < k:
        bounds = np.full(len(queries), np.inf)
    growth = np.log(far[half > 0] / half[half > 0])  # log(2) / d for d dimensions
    dim = 3.0 if not growth.size else float(
        np.clip(np.log(2.0) / max(np.median(growth), np.log(2.0) / 3.0), 1.0, 3.0))
    radii = (COUNT_SCALE * k / (rank * SUBSAMPLE)) ** (1.0 / dim) * far
    least = radii[radii > 0].min(initial=np.inf) / 4.0
    base = max(least if least < np.inf else 0.0, np.abs(queries - origin).max() * 2.0 ** -28)
    return float(base), np.maximum(radii, 4.0 * base), bounds


def _differs_from_previous(rows: np.ndarray) -> np.ndarray:
    """(N - 1,) bool: whether each row of rows (N, D) after the first differs from the one
    before, column by column over contiguous columns (``np.any(..., axis=1)`` over an
    (N, 3) comparison was 0.34 ms on 23k rows, this 0.06 ms)."""
    columns = np.ascontiguousarray(rows.T)
    out = columns[0, 1:] != columns[0, :-1]
    for column in columns[1:]:
        out |= column[1:] != column[:-1]
    return out


def distinct_rows(points: np.ndarray) -> np.ndarray:
    """The distinct rows of points (N, 3) in lexicographic order, as
    ``numpy.unique(points, axis=0)`` (-0.0 equal to 0.0), by a lexsort of the
    columns, several times faster."""
    ordered = points.take(np.lexsort(points.T[::-1]), axis=0)
    keep = np.ones(len(ordered), bool)
    keep[1:] = _differs_from_previous(ordered)
    return ordered.compress(keep, axis=0)


def distinct_inverse(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distinct (M, 3), inverse (N,)): ``distinct_rows(points)`` and the row of each
    point of points (N, 3) in it, as ``numpy.unique(points, axis=0,
    return_inverse=True)`` (one lexsort: about twice as fast; where the first
    coordinates are all distinct, the common case, one argsort of them is the order)."""
    order = np.argsort(points[:, 0], kind="stable")
    ordered = points.take(order, axis=0)
    if np.any(ordered[1:, 0] == ordered[:-1, 0]):  # (ties: the other columns decide)
        order = np.lexsort(points.T[::-1])
        ordered = points.take(order, axis=0)
    keep = np.ones(len(ordered), bool)
    keep[1:] = _differs_from_previous(ordered)
    inverse = np.empty(len(points), np.int64)
    inverse[order] = np.cumsum(keep) - 1
    return ordered.compress(keep, axis=0), inverse


#: ``pair_normals`` takes a point's normal from its k nearest neighbours instead when
#: fewer than this many points (itself included) lie within the radius.
PAIR_LEAST = 6


#: ``pair_normals`` sums the neighbourhoods by one sparse product with the coordinates
#: taken from the cloud's centre where the rounding this costs (about eps x count x the
#: squared distance from the centre) stays below this fraction of a neighbourhood's
#: scatter; the rows above it are summed from the pairs' differences instead.
PRODUCT_ROUNDING = 1e-9


def pair_normals(points: np.ndarray, pairs: np.ndarray, k: int = 16, tree=None,
                 neighbour_sums=None) -> np.ndarray:
    """Unoriented unit normals (M, 3) of distinct points (M, 3) by PCA over each point
    and the points ``pairs`` (E, 2) joins it to (its neighbours within a radius, each
    pair listed once); a point with fewer than ``PAIR_LEAST`` such points takes its
    normal from its k nearest neighbours (from ``tree``, a cKDTree over points, when
    given). No tree query, no (M, k, 3) neighbourhoods: ``detect`` lists the pairs for
    its connectivity anyway (docs/normals.md). With ``neighbour_sums`` (values (M, K)
    -> (M, K), each row summed over the points it is paired with: a sparse product,
    ``RadiusGraph.neighbour_sums``) the scatter sums are one such product of the
    centred coordinates and their products (PRODUCT_ROUNDING bounds the digits this
    loses); else, or where it would lose too many, bincounts over the pairs'
    differences, taken from each point itself."""
    m = len(points)
    if m < 3:
        raise ValueError(f"normals need at least 3 distinct points, got {m}")
    count = np.bincount(pairs[:, 0], minlength=m) + np.bincount(pairs[:, 1], minlength=m) + 1.0
    few = count < PAIR_LEAST
    sparse = np.flatnonzero(few)
    k = min(k, m)
    # (the sparse points' neighbours, a KD-tree query that releases the GIL, found
    # meanwhile: ~6 ms for the 10 % outliers of a 23k-point scene)
    hood = submitted(
        lambda: knn(points, k, points.take(sparse, axis=0)) if tree is None
        else tree.query(points.take(sparse, axis=0), k=k)[1]) if len(sparse) else None
    cov = None if neighbour_sums is None else _product_scatter(points, neighbour_sums,
                                                               count)
    if cov is None:
        cov = _pair_scatter(points, pairs, count)
    out = np.empty((m, 3))
    out[~few] = smallest_eigenvectors(cov[~few])
    if hood is not None:
        out[sparse] = pca_normals(points, np.reshape(hood.result(), (len(sparse), k)),
                                  passes=0)
    return out


def _scatter_matrices(xx, yy, zz, xy, xz, yz) -> np.ndarray:
    """(M, 3, 3) symmetric matrices from their six element arrays (M,)."""
    return np.stack([xx, xy, xz, xy, yy, yz, xz, yz, zz], axis=1).reshape(-1, 3, 3)


def _pair_scatter(points, pairs, count) -> np.ndarray:
    """Scatter matrices (M, 3, 3) of each point of points (M, 3) and its paired points
    (pairs (E, 2), count (M,) of each neighbourhood, itself included): bincounts over
    each pair's coordinate differences from its first point (the second sees their
    negatives: the products are the same from either end, the sums change sign), which
    lose no digits on a cloud far from the origin."""
    m = len(points)
    first, second = pairs[:, 0], pairs[:, 1]
    diff = [np.take(c, second) - np.take(c, first) for c in np.ascontiguousarray(points.T)]
    sums = [np.bincount(first, d, m) - np.bincount(second, d, m) for d in diff]

    def scatter(a, b):
        product = diff[a] * diff[b]
        both = np.bincount(first, product, m) + np.bincount(second, product, m)
        return both - sums[a] * sums[b] / count

    return _scatter_matrices(scatter(0, 0), scatter(1, 1), scatter(2, 2), scatter(0, 1),
                             scatter(0, 2), scatter(1, 2))


def _product_scatter(points, neighbour_sums, count):
    """Scatter matrices (M, 3, 3) as ``_pair_scatter``'s, from ``neighbour_sums`` (see
    ``pair_normals``) of the coordinates from the centre of points (M, 3) and their six
    products (a 9-column sparse product: ~6x faster than the 20 bincounts); None where, for some
    neighbourhood of at least ``PAIR_LEAST`` points, the rounding of those sums (bound
    ~4 eps x count x the largest squared distance from the centre) exceeds
    ``PRODUCT_ROUNDING`` times its scatter's trace."""
    centred = offsets(points, 0.5 * sum(column_bounds(points)))
    x, y, z = centred.T
    terms = np.column_stack([x, y, z, x * x, y * y, z * z, x * y, x * z, y * z])
    sums = neighbour_sums(terms) + terms  # (itself included)
    s = sums[:, :3]
    mean = s / count[:, None]
    xx, yy, zz = (sums[:, 3 + i] - s[:, i] * mean[:, i] for i in range(3))
    trace = xx + yy + zz
    rounding = 4.0 * np.finfo(np.float64).eps * count * float(np.max(x * x + y * y + z * z))
    if np.any((rounding > PRODUCT_ROUNDING * trace) & (count >= PAIR_LEAST)):
        return None
    return _scatter_matrices(xx, yy, zz, sums[:, 6] - s[:, 0] * mean[:, 1],
                             sums[:, 7] - s[:, 0] * mean[:, 2],
                             sums[:, 8] - s[:, 1] * mean[:, 2])


def _neighbours(points, near, queries, k: int, distinct: bool, workers: int):
    """(distances (M, k), indices (M, k) into pool, pool) of the k nearest of
    pool = points[near] (with ``distinct``: its distinct points) to each query (M, 3);
    distances inf where pool has fewer than k points."""
    pool = points.take(near, axis=0)
    pool = distinct_rows(pool) if distinct else pool
    if len(pool) < k:
        return np.full((len(queries), k), np.inf), np.zeros((len(queries), k), np.int64), pool
    dist, hood = kd_tree(pool).query(queries, k=k, workers=workers)
    return dist.reshape(len(queries), k), hood.reshape(len(queries), k), pool


def knn_near(points, k: int, queries, workers: int = -1, distinct: bool = False):
    """``knn(points, k, queries, distances=True)``, the same neighbours up to ties, from
    trees over the points near the queries only; with ``distinct``, (base, indices
    (M, k) into base) of the k nearest distinct points, base made of them; None where
    that would cost about a tree over all points.

    A query is certified at radius r when its k-th neighbour among the points near it
    (``near_mask``) is within r: they are then its k nearest among all. One pass over
    the cloud keeps the points within HARVEST radii (``_radii``) of the queries; a small
    tree certifies what it can at one radius, then one at HARVEST; the others go round
    again at twice that, or less where a k-th distance found (among the points kept, or
    a subsample) shows a radius that certifies."""
    origin = queries[0]
    base, radii, bounds = _radii(points, k, queries, origin)
    if not base > 0:
        return None
    m = len(queries)
    dist, hood, pools, size = np.empty((m, k)), np.empty((m, k), np.int64), [], 0
    pending = np.arange(m)
    for _ in range(MAX_PASSES):
        if not len(pending) or radii[pending].max() > 2.0 ** 36 * base:  # (exact cells)
            break
        harvest = np.flatnonzero(near_mask(points, queries[pending],
                                           HARVEST * radii[pending], origin, base))
        if len(harvest) * 2 > len(points):
            return None
        for reach in (1.0, HARVEST):
            ahead, r = queries.take(pending, axis=0), reach * radii[pending]
            near = harvest[near_mask(points.take(harvest, axis=0), ahead, r, origin, base)]
            found, into, pool = _neighbours(points, near, ahead, k, distinct, workers)
            ok = found[:, -1] <= r * CERTIFY
            dist[pending[ok]] = found[ok]
            hood[pending[ok]] = into[ok] + size if distinct else near[into[ok]]
            if distinct and ok.any():
                pools.append(pool)
                size += len(pool)
            pending, far = pending[~ok], found[~ok, -1]
            if not len(pending):
                break
        bound = np.minimum(bounds[pending], far) / CERTIFY  # certifies (a superset's)
        radii[pending] = np.maximum(np.minimum(2.0 * HARVEST * radii[pending], bound),
                                    radii[pending])
    if len(pending):
        return None
    return (np.concatenate(pools), hood) if distinct else (dist, hood)


#: Trimmed passes of ``pca_normals``: each refits a neighbourhood's plane on the
#: neighbours within TRIM_SPREAD times their median distance to the previous plane, so
#: that outliers and a second surface among the k nearest pull the normal less.
TRIM_PASSES = 2
TRIM_SPREAD = 2.5
#: ... but only where some neighbour lies beyond TRIM_TAIL times that median: a heavy
#: tail (outliers), not noise, which trimming would cut into (a noisy plane's normals
#: were 10-15 % worse without this rule; docs/normals.md).
TRIM_TAIL = 4.0
#: Only neighbourhoods whose surface variation (least eigenvalue / trace of the scatter,
#: 0 on a plane, 1/3 where isotropic) lies between these bounds are trimmed: below, a
#: clean patch (most of a cloud with few outliers) would keep its neighbours anyway;
#: above, no surface holds most of them (an outlier's own neighbourhood, mostly).
TRIM_VARIATION = (0.01, 0.15)
#: A neighbourhood takes another pass only where the last one changed its neighbours and
#: left a plane whose variation is below this (a surface found, not yet settled).
TRIM_SETTLED = 0.05
#: A trimmed plane is kept only where its neighbours are not (nearly) on a line:
#: lambda2 * lambda3 of their scatter > TRIM_FLAT * trace^2 (lambda2 / lambda3 >~ TRIM_FLAT).
TRIM_FLAT = 1e-3
#: Inverse-iteration steps (adjugate products) from the previous normal per trimmed pass.
TRIM_STEPS = 2


def pca_normals(points: np.ndarray, neighbours: np.ndarray,
                passes: int = TRIM_PASSES) -> np.ndarray:
    """Unit normals (M, 3), unoriented: the least-variance direction of each
    neighbourhood points[neighbours] (M, k, 3); then, where its surface variation lies
    within TRIM_VARIATION, up to ``passes`` times that of its neighbours near the plane
    so found (``_near``, ``_refit``; the first neighbour, the point itself, always
    kept), while the kept neighbours change (``TRIM_SETTLED``)."""
    out = np.empty((len(neighbours), 3), points.dtype)
    columns = np.ascontiguousarray(points.T)  # (3, N): each block's gather is contiguous
    for start in range(0, len(neighbours), BLOCK):
        coords = _shifted(columns, neighbours[start:start + BLOCK])
        centres, scatter = _moments(*coords)
        normals, least = smallest_eigenvectors(_scatter_matrices(*scatter), values=True)
        if passes and coords.shape[2] > 3:
            trace = scatter[0] + scatter[1] + scatter[2]
            _trim(coords, normals, centres, least / np.where(trace > 0, trace, np.inf), passes)
        out[start:start + BLOCK] = normals
    return out


def _trim(coords: np.ndarray, normals: np.ndarray, centres, variation: np.ndarray,
          passes: int) -> None:
    """``pca_normals``'s trimmed passes over neighbourhoods with coordinates coords
    (3, B, k), centres (3 of (B,)) and surface variation (B,) (0 where the scatter is
    0): normals (B, 3) overwritten in place."""
    low, high = TRIM_VARIATION
    active = np.flatnonzero((variation > low) & (variation < high))
    if not active.size:
        return
    stacked = coords.take(active, axis=1)  # (3, A, k)
    rows = np.arange(len(active))
    keep = np.ones(stacked.shape[1:], bool)
    plane = np.ascontiguousarray(normals.take(active, axis=0).T)  # (3, A)
    centre = np.stack([c.take(active) for c in centres])  # (3, A)
    for _ in range(passes):
        hood = stacked.take(rows, axis=1)
        near = _near(hood, plane.take(rows, axis=1), centre.take(rows, axis=1))
        changed = (near != keep.take(rows, axis=0)).any(axis=1)  # (the others: settled)
        if not changed.any():
            break
        rows, near = rows[changed], near[changed]
        fitted, mean, variation = _refit(hood.take(np.flatnonzero(changed), axis=1), near,
                                         plane.take(rows, axis=1))
        fine = np.isfinite(variation)  # (where the kept neighbours lie near a line, the
        rows, near = rows[fine], near[fine]  # previous plane and neighbours stay)
        plane[:, rows], keep[rows], centre[:, rows] = fitted[:, fine], near, mean[:, fine]
        rows = rows[variation[fine] < TRIM_SETTLED]
        if not rows.size:
            break
    normals[active] = plane.T


def _shifted(columns: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Coordinates (3, B, k) of the neighbourhoods columns[:, neighbours] (columns: the
    points (3, N), neighbours (B, k)), each shifted to its first point, so that sums
    over them lose no digits far from the origin."""
    coords = columns.take(neighbours, axis=1)
    coords -= coords[:, :, :1]
    return coords


def _moments(x, y, z, weights=None):
    """(centres (3,) of (B,), scatter (xx, yy, zz, xy, xz, yz) of (B,)) of neighbourhoods
    with coordinates x, y, z (B, k) each, neighbour j of row b weighted by
    weights[b, j] (default 1), from sums of products of coordinate arrays (faster than
    centring and an einsum over (B, k, 3); the row sums as products with a vector of
    ones, several times faster than ``sum(axis=1)`` over short rows)."""
    ones = np.ones(x.shape[1], x.dtype)
    if weights is None:
        count, wx, wy, wz = float(x.shape[1]), x, y, z
    else:
        count, wx, wy, wz = weights @ ones, x * weights, y * weights, z * weights
    sx, sy, sz = wx @ ones, wy @ ones, wz @ ones

    def scatter(wu, v, su, sv):
        return np.einsum("bk,bk->b", wu, v) - su * sv / count

    return (sx / count, sy / count, sz / count), (
        scatter(wx, x, sx, sx), scatter(wy, y, sy, sy), scatter(wz, z, sz, sz),
        scatter(wx, y, sx, sy), scatter(wx, z, sx, sz), scatter(wy, z, sy, sz))


def _near(coords: np.ndarray, normals: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(A, k) bool: the neighbours of neighbourhoods with coordinates coords (3, A, k)
    within TRIM_SPREAD times the median (the upper one of an even k) distance to the
    plane of normals (3, A) through centres (3, A), where one lies beyond TRIM_TAIL
    times it (else all); the first, the point itself, always."""
    distance = np.einsum("iak,ia->ak", coords, normals)
    distance -= np.einsum("ia,ia->a", centres, normals)[:, None]
    np.abs(distance, out=distance)
    half = distance.shape[1] // 2
    median = np.partition(distance, half, axis=1)[:, half]
    near = distance <= TRIM_SPREAD * median[:, None]
    near[:, 0] = True
    near[distance.max(axis=1) <= TRIM_TAIL * median] = True
    return near


def _refit(coords: np.ndarray, keep: np.ndarray, normals: np.ndarray):
    """(normals (3, A), centres (3, A), variation (A,)): the planes of the neighbours
    ``keep`` (A, k) of neighbourhoods with coordinates coords (3, A, k), their mean and
    surface variation about the new plane: TRIM_STEPS steps of inverse iteration
    (products with the adjugate of their scatter) from the previous normals (3, A),
    which converge at the ratio of the two least eigenvalues (a surface's normal in a
    step, without an eigen-solve). Variation is inf where the kept neighbours lie near
    a line (``TRIM_FLAT``): their plane is undefined."""
    mean, scatter = _moments(*coords, keep.astype(coords.dtype))
    a, b, c, d, e, f = scatter  # (xx, yy, zz, xy, xz, yz)
    adjugate = np.stack([b * c - f * f, e * f - d * c, d * f - b * e,
                         e * f - d * c, a * c - e * e, d * e - a * f,
                         d * f - b * e, d * e - a * f, a * b - d * d]).reshape(3, 3, -1)
    v, trace = normals, a + b + c
    for step in range(TRIM_STEPS):
        v = np.einsum("ija,ja->ia", adjugate, v)
        length = np.sqrt(np.einsum("ia,ia->a", v, v))
        if step == 0:
            flat = length > TRIM_FLAT * trace * trace
        v = v / np.where(length > 0, length, 1.0)
    variation = np.einsum("ai,aij,aj->a", v.T, _scatter_matrices(*scatter), v.T)
    return v, np.stack(mean), np.where(flat, variation / np.where(flat, trace, 1.0), np.inf)


def smallest_eigenvectors(cov: np.ndarray, values: bool = False):
    """Unit eigenvectors (B, 3) of the smallest eigenvalue of symmetric 3 x 3 matrices
    cov (B, 3, 3), in closed form: the eigenvalue by the trigonometric solution of the
    characteristic cubic, the vector as the largest cross product of two rows of
    cov - lambda I (as PCL's eigen33), a few times faster than batched
    ``numpy.linalg.eigh`` (docs/normals.md). Where the smallest eigenvalue is (nearly)
    repeated the cross products vanish and the direction is ill-defined: those rows fall
    back to ``eigh``. All on (B,) element arrays: NumPy's batched det/cross and its
    reductions over an axis of 3 were slow (the lengths' sum and argmax: 5.1 -> 2.7 ms
    on 21k matrices, the same bits). With ``values``: (vectors, smallest eigenvalues (B,)).
    """
    a, b, c = (np.ascontiguousarray(cov[:, i, i]) for i in range(3))
    d, e, f = (np.ascontiguousarray(cov[:, i, j]) for i, j in ((0, 1), (0, 2), (1, 2)))
    mean = (a + b + c) / 3.0
    a0, b0, c0 = a - mean, b - mean, c - mean
    p = np.sqrt((a0 * a0 + b0 * b0 + c0 * c0 + 2.0 * (d * d + e * e + f * f)) / 6.0)
    det = a0 * (b0 * c0 - f * f) - d * (d * c0 - f * e) + e * (d * f - b0 * e)
    cubed = np.where(p > 0, p, 1.0) ** 3
    phi = np.arccos(np.clip(det / (2.0 * cubed), -1.0, 1.0)) / 3.0
    smallest = mean + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    r0, r1, r2 = (a - smallest, d, e), (d, b - smallest, f), (e, f, c - smallest)  # rows
    crosses = (_cross(r0, r1), _cross(r0, r2), _cross(r1, r2))  # of cov - smallest * I
    lengths = [np.sqrt(x * x + y * y + z * z) for x, y, z in crosses]
    best, pick = lengths[0], np.zeros(len(a), np.int8)  # (the first longest, as argmax)
    for i in (1, 2):
        longer = lengths[i] > best
        pick[longer] = i
        best = np.where(longer, lengths[i], best)
    divisor = np.where(best > 0, best, 1.0)
    out = np.empty((len(a), 3), cov.dtype)
    for k in range(3):
        out[:, k] = np.where(pick == 0, crosses[0][k],
                             np.where(pick == 1, crosses[1][k], crosses[2][k])) / divisor
    scale = np.maximum(np.abs(mean) * 3.0, np.finfo(cov.dtype).tiny)
    unclear = best <= 1e-8 * scale * scale
    if unclear.any():  # eigh sorts eigenvalues ascending: column 0
        out[unclear] = np.linalg.eigh(cov[unclear])[1][:, :, 0]
    return (out, smallest) if values else out


def _cross(u, v):
    """The cross product of u and v, each a tuple of 3 element arrays (B,): a tuple of 3."""
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


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
    if few_queries(len(queries), len(points)):
        found = knn_near(points, k, queries, distinct=True)
        if found is not None:
            return found[0], k, found[1]
    distinct = distinct_rows(points)
    if len(distinct) < 3:
        return points, k, hood
    k = min(k, len(distinct))
    return distinct, k, knn(distinct, k, queries)


def normals_at(points: np.ndarray, indices: np.ndarray, k: int = 16) -> np.ndarray:
    """Unoriented unit normals (M, 3) at points[indices] only, from their k nearest
    neighbours among all points (N, 3): what ``fit`` needs, since it draws minimal
    samples from a pool of points and never reads the others' normals."""
    return normals_at_many([points], [indices], [k])[0]


def read_rows(points: np.ndarray, neighbours: np.ndarray):
    """(rows, neighbours into rows): the points (N, 3) that neighbours (M, k) read, where
    they are few (else points and neighbours as given), so that stacking clouds for one
    PCA copies only those (a cloud of 1e7 points was copied whole for 2048 normals)."""
    if neighbours.size * 4 >= len(points):
        return points, neighbours
    flat = np.sort(neighbours, axis=None)
    read = flat[np.r_[True, flat[1:] != flat[:-1]]]
    return points[read], np.searchsorted(read, neighbours)


def normals_at_many(clouds, indices, ks) -> list[np.ndarray]:
    """``normals_at(clouds[i], indices[i], ks[i])`` for every cloud: one neighbour search
    each (``knn``), one PCA per neighbourhood size over all their clouds stacked (the
    points their neighbourhoods read, ``read_rows``: the eigen-solver's fixed cost, some
    50 NumPy calls, is paid once per block, not once per cloud)."""
    ks = [_check_k(k, len(c)) for c, k in zip(clouds, ks, strict=True)]
    queries = [c[i] for c, i in zip(clouds, indices, strict=True)]
    found = knn_many(clouds, queries, ks, distances=True)
    clouds, neighbours = list(clouds), [None] * len(clouds)
    for i, (dist, hood) in enumerate(found):
        base, ks[i], hood = distinct_neighbours(clouds[i], queries[i], ks[i], dist, hood)
        clouds[i], neighbours[i] = read_rows(base, hood)
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
    points : (N, 3) array-like of finite coordinates, or any cloud ``jaxfit.as_cloud``
        reads (a trimesh or Open3D geometry, a path; a mesh gives
        ``io.inputs.MESH_POINTS`` points, seed 0). Its own normals are not read: these
        are estimated.
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
    cloud = _checks.cloud(converted(points, with_normals=False)[0])
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
