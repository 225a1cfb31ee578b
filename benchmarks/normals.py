"""Normal estimation: which k-NN search, how fast, how accurate.

    python -m benchmarks.normals [--quick]

Times (1) scipy's cKDTree (build + query on all cores), (2) pykdtree (build + query on
its OpenMP threads: ``jaxfit.normals.knn``, which the package uses) and (3) a batched
brute-force kNN in JAX (query blocks of 1024 against all points, ``lax.top_k``; warm,
compilation timed apart) for N = 1e3, 1e4, 1e5, 1e6 points on a sphere, k = 16, and
the share of pykdtree's neighbours equal to cKDTree's, place by place; the JAX search is
O(N^2) and is skipped where it would take minutes (its time is then extrapolated, and
marked so). Then times
the whole ``jaxfit.estimate_normals`` per orientation, and measures the angle between
estimated and true normals on noisy synthetic shapes, and the share of normals that point
outward where the shape is closed. Last, among outliers (``benchmarks.peers``' cylinder
clouds, 10 and 60 % outliers): the normals' error on the true surface points and their
time with and without the trimmed passes (``jaxfit.normals.TRIM_PASSES``), and how often
a cylinder fit on those normals misses the axis by more than 0.1 deg. Writes
benchmarks/results/normals.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import time
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxfit
from jaxfit.normals import TRIM_PASSES, estimate_normals, kd_tree, knn, pca_normals
from jaxfit.shapes import Cone, Cylinder, Plane, Sphere

OUT = Path(__file__).resolve().parent / "results"
K = 16
BLOCK = 1024
#: Largest N the brute-force JAX search is run at (N^2 distances: 1e6 would be 1e12).
JAX_MAX_N = 100_000


@partial(jax.jit, static_argnames=("k",))
def _jax_knn_padded(points, k: int):
    """Indices (B, k) of the k nearest of padded points (B, 3), B a multiple of BLOCK."""
    norms = jnp.sum(points * points, axis=1)

    def block(queries):
        d2 = jnp.sum(queries * queries, axis=1)[:, None] - 2.0 * queries @ points.T + norms
        return jax.lax.top_k(-d2, k)[1]

    return jax.lax.map(block, points.reshape(-1, BLOCK, 3)).reshape(-1, k)


def jax_knn(points: np.ndarray, k: int) -> np.ndarray:
    """Indices (N, k) of each point's k nearest, by brute force in JAX. Padding points
    sit far away, so they are never anyone's neighbour."""
    n = len(points)
    size = -(-n // BLOCK) * BLOCK
    padded = np.full((size, 3), 1e6, np.float32)
    padded[:n] = points - points.mean(axis=0)
    return np.asarray(_jax_knn_padded(jnp.asarray(padded), k))[:n]


def _timed(fn, *args, repeats: int = 1):
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn(*args)
        best = min(best, time.perf_counter() - start)
    return best, out


def speed(sizes, seed: int = 0):
    rows = []
    rng = np.random.default_rng(seed)
    for n in sizes:
        points, _ = Sphere(np.zeros(3), np.float64(1.0)).sample(n, rng)
        repeats = 3 if n <= 10_000 else 1
        scipy_s, scipy_idx = _timed(lambda p: kd_tree(p).query(p, k=K, workers=-1)[1],
                                    points, repeats=repeats)
        tree_s, tree_idx = _timed(knn, points, K, repeats=repeats)
        row = {"n": n, "k": K, "ckdtree_s": scipy_s, "pykdtree_s": tree_s,
               "pykdtree_same": float(np.mean(tree_idx == scipy_idx))}
        if n <= JAX_MAX_N:
            compile_s, _ = _timed(jax_knn, points, K)
            jax_s, jax_idx = _timed(jax_knn, points, K, repeats=repeats)
            # Same neighbour sets up to float32 ties.
            agree = np.mean([len(np.intersect1d(a, b)) / K for a, b in
                             zip(tree_idx[:2000], jax_idx[:2000], strict=True)])
            row.update(jax_s=jax_s, jax_first_call_s=compile_s, jax_agreement=float(agree))
        else:
            last = next(r for r in reversed(rows) if "jax_s" in r)
            row.update(jax_s=None, jax_estimate_s=last["jax_s"] * (n / last["n"]) ** 2)
        for orient in ("mst", "direct", None):
            row[f"estimate_normals_{orient}_s"] = _timed(
                partial(estimate_normals, orient=orient), points)[0]
        rows.append(row)
        print(row, flush=True)
    return rows


def _shapes():
    up = np.array([0.0, 0.0, 1.0])
    return {
        "plane": Plane(up, np.float64(0.0), np.zeros(3), np.float64(1.0)),
        "sphere": Sphere(np.zeros(3), np.float64(1.0)),
        "cylinder": Cylinder(np.zeros(3), up, np.float64(0.5), np.float64(2.0)),
        "cone": Cone(np.zeros(3), up, np.radians(30.0), np.float64(2.0)),
    }


def _angles(estimated, true):
    cos = np.abs(np.einsum("ij,ij->i", estimated, true))
    return np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))


def accuracy(count: int = 20_000, noises=(0.0, 0.005, 0.01), ks=(8, 16, 32), seed: int = 0):
    """Angle errors (degrees, signs ignored) against the true normals of shapes of unit
    size, points displaced along the normal by U(-noise, noise); and the share of
    normals oriented outward on the closed sphere (and for the open shapes, the share
    agreeing with the majority sign, i.e. consistency)."""
    rows = []
    for name, model in _shapes().items():
        for noise in noises:
            rng = np.random.default_rng(seed)
            points, true = model.sample(count, rng)
            points = points + true * rng.uniform(-noise, noise, (count, 1))
            for k in ks:
                row = {"shape": name, "noise": noise, "k": k}
                for orient in ("mst", "direct"):
                    est = estimate_normals(points, k, orient=orient)
                    agree = np.einsum("ij,ij->i", est, true) > 0
                    row[f"outward_{orient}"] = float(agree.mean())
                    row[f"consistent_{orient}"] = float(max(agree.mean(), 1 - agree.mean()))
                err = _angles(est, true)
                row.update(mean_deg=float(err.mean()), median_deg=float(np.median(err)),
                           p95_deg=float(np.percentile(err, 95)))
                rows.append(row)
                print(row, flush=True)
    return rows


#: ``outliers``: cloud sizes, outlier shares, clouds per setting (fits: at 60 % only).
OUTLIER_SIZES = (500, 1_000, 10_000)
OUTLIER_SHARES = (0.1, 0.6)
OUTLIER_CLOUDS = 40
#: A fit "misses" when its axis is further than this from the true one (degrees).
MISS_DEG = 0.1


def outliers(sizes=OUTLIER_SIZES, clouds: int = OUTLIER_CLOUDS):
    """Per size and outlier share: the median (over clouds) of the median angle error of
    the normals at the true surface points, without and with the trimmed passes; the
    best-of-5 time of each PCA over the normals a fit estimates (at most 2048 points:
    ``engine.cloud.NORMAL_POOL``); at 60 % outliers, the fits (``jaxfit.fit``, given
    each set of normals) whose axis misses by more than MISS_DEG."""
    from benchmarks import peers
    from jaxfit.engine.cloud import NORMAL_POOL

    rows = []
    for n in sizes:
        for share in OUTLIER_SHARES:
            errors, times, misses = {0: [], TRIM_PASSES: []}, {0: [], TRIM_PASSES: []}, {
                0: 0, TRIM_PASSES: 0}
            for c in range(clouds):
                seed = 1000 * c + int(100 * share) + n
                points, truth, model, threshold = peers.cloud("cylinder", n, share, seed)
                axis = model.axis / np.linalg.norm(model.axis)
                radial = points[truth] - model.center
                radial -= (radial @ axis)[:, None] * axis
                radial /= np.linalg.norm(radial, axis=1, keepdims=True)
                hood = knn(points, K)
                pool = hood[:NORMAL_POOL]
                for passes in errors:
                    normals = pca_normals(points, hood, passes)
                    errors[passes].append(float(np.median(_angles(normals[truth], radial))))
                    if c < 5:
                        times[passes].append(_timed(pca_normals, points, pool, passes,
                                                    repeats=5)[0])
                    if share == OUTLIER_SHARES[-1]:
                        fit = jaxfit.fit(points, "cylinder", normals=normals,
                                         threshold=threshold, key=seed)
                        angle = peers.accuracy(model, {"center": fit.model.center,
                                                       "radius": fit.model.radius,
                                                       "axis": fit.model.axis})["angle_deg"]
                        misses[passes] += angle > MISS_DEG
            row = {"n": n, "outliers": share, "clouds": clouds}
            for passes, name in ((0, "plain"), (TRIM_PASSES, "trimmed")):
                row[f"{name}_median_deg"] = float(np.median(errors[passes]))
                row[f"{name}_ms"] = 1e3 * float(np.median(times[passes]))
                row[f"{name}_misses"] = (misses[passes] if share == OUTLIER_SHARES[-1]
                                         else None)
            rows.append(row)
            print(row, flush=True)
    return rows


def _markdown(speed_rows, accuracy_rows, outlier_rows):
    lines = [
        "# Normal estimation", "",
        f"k = {K}; points uniform on the unit sphere; 2 shared CPU cores; seconds, best of "
        "3 runs for N <= 1e4, one run above. JAX: brute-force kNN in query blocks of "
        f"{BLOCK} (warm; first call with compilation in brackets).", "",
        "| N | scipy cKDTree kNN | pykdtree kNN (`knn`) | same neighbours | "
        "JAX brute-force kNN | estimate_normals (mst) | (direct) | (no orientation) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in speed_rows:
        if r.get("jax_s") is not None:
            jax_cell = f"{r['jax_s']:.3f} ({r['jax_first_call_s']:.2f})"
        else:
            jax_cell = f"not run (~{r['jax_estimate_s']:.0f} s extrapolated as N^2)"
        lines.append(f"| {r['n']:,} | {r['ckdtree_s']:.4f} | {r['pykdtree_s']:.4f} | "
                     f"{100 * r['pykdtree_same']:.2f} % | {jax_cell} | "
                     f"{r['estimate_normals_mst_s']:.2f} | {r['estimate_normals_direct_s']:.2f} "
                     f"| {r['estimate_normals_None_s']:.2f} |")
    lines += [
        "", "Accuracy: 20,000 points on unit-size shapes (plane disk r 1, sphere r 1, "
        "cylinder r 0.5 h 2, cone 30 deg h 2; caps not sampled), displaced along the normal "
        "by U(-noise, noise). Angle to the true normal in degrees (signs ignored). "
        "'outward' is the share of normals pointing outward (for the plane: along +z); "
        "'consistent' the share agreeing with the majority sign.", "",
        "| shape | noise | k | mean | median | p95 | outward mst | outward direct | "
        "consistent mst |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in accuracy_rows:
        lines.append(f"| {r['shape']} | {r['noise']} | {r['k']} | {r['mean_deg']:.2f} | "
                     f"{r['median_deg']:.2f} | {r['p95_deg']:.2f} | {r['outward_mst']:.3f} | "
                     f"{r['outward_direct']:.3f} | {r['consistent_mst']:.3f} |")
    lines += [
        "", f"Among outliers: `benchmarks.peers`' cylinder clouds (radius 0.5, height 2, "
        f"noise 0.2 %, outliers uniform in the box), {outlier_rows[0]['clouds']} per "
        "setting, k = 16. Error: the median over clouds of the median angle between the "
        "normals and the true ones at the true surface points (degrees). Time: the PCA "
        "over the first 2048 points' neighbourhoods (what a fit estimates), median of 5 "
        f"clouds, best of 5 runs. Misses: fits whose axis is off by more than {MISS_DEG} "
        "deg (60 % outliers only).", "",
        "| N | outliers | error plain | error trimmed | ms plain | ms trimmed | "
        "misses plain | misses trimmed |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in outlier_rows:
        miss = ("—", "—") if r["plain_misses"] is None else (
            f"{r['plain_misses']} of {r['clouds']}", f"{r['trimmed_misses']} of {r['clouds']}")
        lines.append(f"| {r['n']:,} | {100 * r['outliers']:.0f} % | "
                     f"{r['plain_median_deg']:.2f} | {r['trimmed_median_deg']:.2f} | "
                     f"{r['plain_ms']:.2f} | {r['trimmed_ms']:.2f} | {miss[0]} | {miss[1]} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="N <= 1e5, k = 16 only")
    args = parser.parse_args(argv)
    sizes = (1_000, 10_000, 100_000) if args.quick else (1_000, 10_000, 100_000, 1_000_000)
    speed_rows = speed(sizes)
    accuracy_rows = accuracy(ks=(16,) if args.quick else (8, 16, 32))
    outlier_rows = outliers(clouds=10 if args.quick else OUTLIER_CLOUDS)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "normals.json").write_text(json.dumps(
        {"speed": speed_rows, "accuracy": accuracy_rows, "outliers": outlier_rows}, indent=1))
    (OUT / "normals.md").write_text(_markdown(speed_rows, accuracy_rows, outlier_rows))
    print((OUT / "normals.md").read_text())


if __name__ == "__main__":
    main()
