"""Input preparation: a user's cloud checked, centred and scaled into the unit ball (so
float32 keeps its precision far from the origin), and padded to a power-of-two bucket
with its count of real points (so a new cloud size reuses a compiled kernel)."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from .. import _checks
from ..shapes import Model
from ..shapes import _geometry as g
from .backend import cores, in_threads
from .keys import normals_key_data, seed_normals_data
from .options import Bounds

#: Smallest point-count bucket; larger clouds pad to the next power of two.
MIN_BUCKET = 1024
#: Default threshold as a fraction of the cloud's bounding-box diagonal.
DEFAULT_THRESHOLD_FRACTION = 0.005
#: Oriented estimators draw their samples from a random pool of at most this many points,
#: the only ones whose normals are estimated (when none are given): ~512^2 distinct pairs
#: are plenty, and the normals were 40 % of a 1e3-point cylinder fit at 2048 (the same
#: errors either way: docs/engine.md, "Session 38").
NORMAL_POOL = 512
#: Neighbours of the PCA normals estimated for a fit.
NORMAL_NEIGHBOURS = 16
#: In a cloud of more points the pool's neighbours are looked for among the pool and
#: this many random draws of the cloud's points: a KD-tree over all of 1e5 points had
#: been ~40 % of an oriented fit, and a neighbourhood over a third of the points is still
#: a small patch of the surface (docs/engine.md, "Session 14").
NORMAL_SUPPORT = 1 << 15
#: ``prepare_many`` prepares a call of at least this many points in two halves at once
#: (1000 clouds of 500 points: 22 -> 12 ms on two cores).
SPLIT_POINTS = 1 << 17


def default_threshold(sides) -> float:
    """The default inlier threshold of a cloud whose bounding box has sides (3,):
    ``DEFAULT_THRESHOLD_FRACTION`` of its diagonal (``default_thresholds``)."""
    return float(default_thresholds(sides)[0])


def default_thresholds(sides) -> np.ndarray:
    """``default_threshold`` of each of C clouds whose bounding boxes have sides (C, 3):
    (C,), each squared diagonal by one stacked matmul (the dot product of one cloud's,
    without np.linalg.norm's ~6 us of checks)."""
    sides = np.asarray(sides, np.float64).reshape(-1, 3)
    squares = np.matmul(sides[:, None, :], sides[:, :, None])[:, 0, 0]
    return DEFAULT_THRESHOLD_FRACTION * np.sqrt(squares)


def bucket_size(n: int) -> int:
    """Padded point count for a cloud of n points: a power of two, at least MIN_BUCKET."""
    return max(MIN_BUCKET, 1 << (int(n) - 1).bit_length())


def normalise(points: np.ndarray):
    """Centre (3,) and scale that map the cloud (N, 3) into the unit ball."""
    return unit_frame(points)[2:4]


def unit_frame(points: np.ndarray):
    """(lowest (3,), highest (3,), centre (3,), scale, unit points (N, 3) float64, the
    same as columns (3, N)) of the cloud (N, 3): its bounds, the centre and scale of
    ``normalise``, ``Cloud.unit`` and ``Cloud.columns``,
    worked on as contiguous columns: an (N, 3) array broadcast against a (3,) centre runs
    NumPy's inner loop over 3 values (1e5 points: the centring alone 0.46 ms, 0.05 ms in
    columns). The same bits as in rows: elementwise the same operations, and the largest
    root is the root of the largest square sum."""
    columns = np.array(points, dtype=np.float64, order="F").T  # (3, N), a copy
    lo, hi = columns.min(axis=1), columns.max(axis=1)
    center = 0.5 * (lo + hi)
    _checks.spanning(lo, hi)
    columns -= center[:, None]
    scale = float(np.sqrt(_square_norms(columns).max()))
    if not scale > 0:
        raise _checks.FitError("all points coincide: there is no shape to fit")
    columns /= scale
    return lo, hi, center, scale, g.rows(columns), columns


def _square_norms(columns: np.ndarray) -> np.ndarray:
    """The squared norms (N,) of the points in columns (3, N), summed as ``row_norms``
    sums its rows (x^2 + y^2, then + z^2)."""
    norms = columns[0] ** 2
    norms += columns[1] ** 2
    norms += columns[2] ** 2
    return norms


def padded(rows: np.ndarray, dtype, size: int | None = None):
    """rows (N, 3) as ``dtype``, zero-padded to ``size`` rows (default its bucket)."""
    n = rows.shape[0]
    out = np.zeros((size or bucket_size(n), 3), dtype=dtype)
    out[:n] = rows
    return out


@dataclasses.dataclass
class Cloud:
    """One validated cloud, in the normalised frame the kernels see."""

    points: np.ndarray  # (N, 3) float64, as given
    # (M, 3) unit normals of points[pool] (all N points without a pool), kept when the
    # estimator or the normal gate reads them
    normals: np.ndarray | None
    pool: np.ndarray | None  # (M,) indices samples are drawn from (None: all points)
    center: np.ndarray
    scale: float
    unit: np.ndarray  # (N, 3) float64: (points - center) / scale, the frame the kernels see
    # (3, N) float64: unit.T, each row contiguous (the final refit's and the bounding's
    # passes read coordinates by column; a transposed copy of 1e5 points cost ~0.5 ms)
    columns: np.ndarray
    threshold: float  # in the cloud's units
    bounds: Bounds  # the user's bounds, in the cloud's units
    wanted: np.ndarray | None = None  # indices whose normals are still to be estimated
    # (S,) sorted indices of the points their neighbours are taken from (None: all)
    support: np.ndarray | None = None

    @functools.cached_property
    def gated(self) -> bool:
        return self.bounds.gated

    def unit_bounds(self) -> Bounds:
        """The bounds in the normalised frame."""
        return self.bounds.scaled(self.scale)

    def kernel_rows(self):
        """Unit points (N, 3) with the pool first, the pool's normals (M, 3) or None,
        and M: the kernel draws samples among the first M rows and scores all."""
        if self.pool is None:
            return self.unit, self.normals, len(self.points)
        rest = np.setdiff1d(np.arange(len(self.points)), self.pool, assume_unique=True)
        return (self.unit.take(np.concatenate([self.pool, rest]), axis=0), self.normals,
                len(self.pool))


def prepare(points, cls: type[Model], normals, threshold, uses_normals: bool, key, index,
            bounds: Bounds) -> Cloud:
    """Cloud ``index`` of a call, validated; ``key`` is the call's (see ``normals_key``).
    Normals the fit needs and was not given are left for ``estimate_normals``: its
    ``normals`` is None and ``wanted`` holds the indices to estimate them at."""
    cloud = _checks.points_for(points, cls)
    normals, center, scale, unit, columns, threshold = _framed(cloud, normals, threshold)
    pool = wanted = support = None
    if not (uses_normals or bounds.gated):
        normals = None
    elif normals is None and bounds.gated:  # the gate reads every point's normal
        wanted = np.arange(len(cloud))
    elif normals is None:
        if len(cloud) > NORMAL_POOL:
            # (derived here only: its key costs a dispatch)
            seed = _checks.seed_of(key)
            rng = np.random.default_rng(normals_key_data(_checks.prng_key(key), index)
                                        if seed is None else seed_normals_data(seed, index))
            pool = np.sort(rng.choice(len(cloud), NORMAL_POOL, replace=False))
            if len(cloud) > NORMAL_SUPPORT:  # (the pool and NORMAL_SUPPORT draws, distinct)
                taken = np.zeros(len(cloud), bool)
                taken[pool] = True
                taken[rng.integers(0, len(cloud), NORMAL_SUPPORT)] = True
                support = np.flatnonzero(taken)
        wanted = np.arange(len(cloud)) if pool is None else pool
    return Cloud(cloud, normals, pool, center, scale, unit, columns, threshold, bounds, wanted,
                 support)


def _framed(cloud: np.ndarray, normals, threshold):
    """(normals checked or None, centre, scale, unit (N, 3), columns (3, N), threshold)
    of a checked cloud (N, 3) float64: ``prepare``'s work for every shape alike."""
    normals = _checks.normals_for(normals, cloud)
    lo, hi, center, scale, unit, columns = unit_frame(cloud)
    if threshold is None:
        threshold = default_threshold(hi - lo)
    return normals, center, scale, unit, columns, _checks.positive(threshold, "threshold")


def shared(points, normals, threshold) -> Cloud:
    """One cloud with its normals (N, 3), prepared once for several shapes: ``for_shape``
    gives each shape's Cloud, the one ``prepare`` makes from the same inputs. Why: detect
    fits every shape to each group, and the checks and frame cost ~0.1 ms a cloud."""
    if normals is None:
        raise ValueError("a shared cloud needs its normals (N, 3)")
    cloud = _checks.cloud(points)
    normals, center, scale, unit, columns, threshold = _framed(cloud, normals, threshold)
    return Cloud(cloud, normals, None, center, scale, unit, columns, threshold, None)


def for_shape(cloud: Cloud, cls: type[Model], uses_normals: bool, bounds: Bounds) -> Cloud:
    """The ``shared`` cloud as ``prepare`` makes it for shape cls, whose estimator reads
    normals or not (``uses_normals``), with the call's ``bounds``: its normals kept only
    where the estimator or the normal gate reads them. Raises as ``prepare`` does for
    fewer points than a minimal sample."""
    _checks.enough_points(len(cloud.points), cls)
    normals = cloud.normals if uses_normals or bounds.gated else None
    return dataclasses.replace(cloud, normals=normals, bounds=bounds)


def prepare_many(clouds, cls: type[Model], thresholds, bounds: Bounds) -> list[Cloud] | None:
    """``prepare`` of every cloud of a call in a few NumPy passes over their concatenated
    columns, for clouds that need no normals: (N_i, 3) real ndarrays, ``thresholds`` one
    per cloud (None: the default). The same Clouds, bit for bit (the same elementwise
    operations; min, max and their reduceat are exact), with ``unit`` already made. None
    when any cloud would fail a check: then ``prepare``, cloud by cloud, raises (or
    skips) with the message naming the first bad one.

    Why: ``prepare`` is ~40 us of NumPy calls per cloud, 15 % of ``fit_batch`` on 500-point
    clouds (docs/engine.md, "Host path (this round)"). A call of at least ``SPLIT_POINTS``
    points is prepared in two halves side by side: its passes are memory-bound NumPy
    loops, which release the GIL, and the second core has nothing else to do yet."""
    if not all(isinstance(c, np.ndarray) and c.ndim == 2 and c.shape[1] == 3
               and c.dtype.kind in "fiu" and len(c) >= cls.sample_size for c in clouds):
        return None
    half = len(clouds) // 2
    if half and cores() > 1 and sum(len(c) for c in clouds) >= SPLIT_POINTS:
        halves = [found for _, found in in_threads(
            lambda part: _prepared(clouds[part], thresholds[part], bounds),
            (slice(None, half), slice(half, None)), 2)]
        return None if None in halves else halves[0] + halves[1]
    return _prepared(clouds, thresholds, bounds)


def _prepared(clouds, thresholds, bounds: Bounds) -> list[Cloud] | None:
    """``prepare_many``'s passes over clouds that passed its first checks."""
    sizes = np.fromiter((len(c) for c in clouds), np.int64, len(clouds))
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    every = np.concatenate(clouds, dtype=np.float64, casting="unsafe")  # (N, 3), a copy
    columns = np.ascontiguousarray(every.T)  # (3, N); worked on in place (fresh pages of
    # large temporaries were half of this function's time)
    # A NaN spreads to its cloud's min and max, an inf is one of them.
    lo = np.stack([np.minimum.reduceat(col, starts) for col in columns], axis=1)  # (C, 3)
    hi = np.stack([np.maximum.reduceat(col, starts) for col in columns], axis=1)
    limit = _checks.MAX_COORDINATE
    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and -limit <= lo.min()
            and hi.max() <= limit):
        return None
    extent = (hi - lo).max(axis=1)
    center = 0.5 * (lo + hi)
    columns -= np.repeat(center.T, sizes, axis=1)  # points - center
    norms = _square_norms(columns)
    scale = np.maximum.reduceat(np.sqrt(norms, out=norms), starts)
    if np.any((extent > 0) & (extent < _checks.MIN_EXTENT)) or not np.all(scale > 0):
        return None
    defaults = default_thresholds(hi - lo).tolist()
    try:
        limits = [defaults[i] if t is None else _checks.positive(t, "threshold")
                  for i, t in enumerate(thresholds)]
    except ValueError:
        return None
    columns /= np.repeat(scale, sizes)
    # (N, 3) in rows, as prepare's: a shape's bounding multiplies it by vectors, and in
    # columns BLAS sums those products in another order (a plane's patch moved by ulps)
    unit = g.rows(columns)
    out = []
    for i, (start, n) in enumerate(zip(starts.tolist(), sizes.tolist(), strict=True)):
        part = slice(start, start + n)
        out.append(Cloud(every[part], None, None, center[i], float(scale[i]), unit[part],
                         columns[:, part], limits[i], bounds))
    return out


def estimate_normals(clouds: list[Cloud]):
    """Fill in the normals ``prepare`` left wanted, for all clouds in one batched call
    (scipy's KD-tree: imported only when needed)."""
    todo = [c for c in clouds if c.wanted is not None]
    if todo:
        from ..normals import normals_at_many

        sources = [c.points if c.support is None else c.points.take(c.support, axis=0)
                   for c in todo]
        at = [c.wanted if c.support is None else np.searchsorted(c.support, c.wanted)
              for c in todo]
        found = normals_at_many(sources, at, [min(NORMAL_NEIGHBOURS, len(s)) for s in sources])
        for cloud, normals in zip(todo, found, strict=True):
            cloud.normals, cloud.wanted = normals, None
