"""Time to solution: wall time of a whole fit with adaptive stopping, and the accuracy reached.

For plane, sphere and cylinder clouds of 1e3, 1e4 and 1e5 points (``jaxfit.evaluation.synthetic``:
surface noise U(-0.005, 0.005) on a unit-size primitive, 10 / 30 / 60 % uniform outliers,
several seeds), side by side in one run on the same clouds and the same inlier threshold:
- jaxfit: ``jaxfit.fit`` with its defaults (confidence 0.99, LO refinement), warm (a
  warm-up call compiles first), median of repeats, for several ``batch_size`` values;
- reference: ``jaxfit.evaluation.reference.ransac``, the NumPy one-hypothesis-at-a-time
  loop with the same adaptive stopping rule (confidence 0.99), no refinement;
- pyRANSAC-3D (``pip install ".[bench]"``; skipped with a note if missing), two ways:
  "fixed", 1000 iterations (its default for plane and sphere; its cylinder's default of
  10000 takes ~40 s on 1e4 points), and "adaptive", stopped by its callback as soon as
  T = log(1 - 0.99) / log(1 - w^k) is reached for its best inlier share w: the same rule
  as the others, and its fastest sensible setting.

Accuracy against the true primitive: plane normal angle (degrees), sphere centre error
relative to the radius, cylinder axis angle (degrees); secondary measures in the JSON.

Run: ``python -m benchmarks.solution [--quick]``. Writes
``benchmarks/results/solution.json``, ``solution.md`` and ``solution.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import random
import statistics
import time
from pathlib import Path

import jax
import numpy as np

import jaxfit
from jaxfit.engine import required_hypotheses
from jaxfit.engine.cloud import normalise
from jaxfit.engine.fit import bounded
from jaxfit.evaluation import reference
from jaxfit.evaluation.synthetic import demo_cloud
from jaxfit.io.preview import pyplot
from jaxfit.shapes import REGISTRY

RESULTS = Path(__file__).resolve().parent / "results"
SHAPES = ("plane", "sphere", "cylinder")
SIZES = (1_000, 10_000, 100_000)
OUTLIERS = (0.1, 0.3, 0.6)
BATCH_SIZES = (64, 128, 256, 512, 1024)
DEFAULT_BATCH = jaxfit.FitOptions().batch_size
NO_REFINE_BATCHES = (128, 1024)  # also timed with refine=False
NOISE = 0.005  # half-width of the surface noise, unit-size primitives
THRESHOLD = 0.01  # inlier distance for every method: twice the noise half-width
CONFIDENCE = 0.99
PYRANSAC_ITERATIONS = 1000
#: The main accuracy measure per shape and the bar a fit must meet to count as solved.
PRIMARY = {"plane": ("normal_deg", 1.0), "sphere": ("center_rel", 0.01),
           "cylinder": ("axis_deg", 2.0)}

try:
    import pyransac3d
except ImportError:  # an optional extra: the benchmark runs without it
    pyransac3d = None


# ----- accuracy -----------------------------------------------------------------------


def _angle_deg(a, b) -> float:
    """Angle between the lines along a and b, in degrees (signs ignored)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    cos = abs(a @ b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(min(1.0, cos))))


def _line_distance(point, origin, direction) -> float:
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    v = np.asarray(point, float) - np.asarray(origin, float)
    return float(np.linalg.norm(v - (v @ d) * d))


def accuracy(shape: str, truth, params: dict | None) -> dict[str, float]:
    """Errors of fitted parameters (plane normal/offset, sphere center/radius, cylinder
    center/axis/radius; the plane's a point on it) against the true model; NaN if none."""
    if params is None:
        return {PRIMARY[shape][0]: math.nan}
    if shape == "plane":
        n = np.asarray(params["normal"], float)
        n = n / np.linalg.norm(n)
        # distance of the true patch centre to the fitted plane: the offset error
        return {"normal_deg": _angle_deg(n, truth.normal),
                "offset_error": float(abs(n @ truth.center + params["offset"]))}
    if shape == "sphere":
        r = float(truth.radius)
        return {"center_rel": float(np.linalg.norm(params["center"] - truth.center)) / r,
                "radius_rel": abs(float(params["radius"]) - r) / r}
    r = float(truth.radius)
    return {"axis_deg": _angle_deg(params["axis"], truth.axis),
            "radius_rel": abs(float(params["radius"]) - r) / r,
            "axis_offset_rel": _line_distance(truth.center, params["center"], params["axis"]) / r}


def model_params(model) -> dict:
    fields = {"plane": ("normal", "offset"), "sphere": ("center", "radius"),
              "cylinder": ("center", "axis", "radius")}[model.name]
    return {f: np.asarray(getattr(model, f), float) for f in fields}


# ----- the methods --------------------------------------------------------------------


def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def run_jaxfit(points, shape, batch_size, seed, repeats, refine=True):
    """(median seconds, params, hypotheses) of warm jaxfit.fit calls with one key."""
    times, result = [], None
    for _ in range(repeats):
        seconds, result = _timed(lambda: jaxfit.fit(points, shape, threshold=THRESHOLD,
                                                     batch_size=batch_size, refine=refine,
                                                     key=seed))
        times.append(seconds)
    return statistics.median(times), model_params(result.model), result.num_hypotheses


def run_reference(points, shape, seed):
    """The NumPy loop on the cloud normalised as jaxfit does, its model bounded the same
    way (both outside the timing: they are the same code for every method)."""
    center, scale = normalise(points)
    unit = (points - center) / scale
    seconds, out = _timed(lambda: reference.ransac(
        unit, shape, threshold=THRESHOLD / scale, confidence=CONFIDENCE,
        max_hypotheses=100_000, max_stall=20_000, seed=seed))
    if not np.all(np.isfinite(out["theta"])):
        return seconds, None, out["num_hypotheses"]
    cls = REGISTRY[shape]
    model = bounded(cls, out["theta"], unit, THRESHOLD / scale).rescaled(scale, center)
    return seconds, model_params(model), out["num_hypotheses"]


def _stop_at_confidence(n_points, sample_size):
    """pyRANSAC-3D callback: stop once T(best inlier share) iterations were drawn."""

    def callback(state):
        ratio = len(state["best_inliers"]) / n_points
        needed = required_hypotheses(ratio, sample_size, CONFIDENCE)
        return state["iteration"] + 1 >= needed

    return callback


def run_pyransac(points, shape, seed, adaptive):
    """(seconds, params, iterations) of pyRANSAC-3D; it draws from Python's global random."""
    random.seed(seed)
    fitter = {"plane": pyransac3d.Plane, "sphere": pyransac3d.Sphere,
              "cylinder": pyransac3d.Cylinder}[shape]()
    sample_size = REGISTRY[shape].sample_size
    drawn = []

    def count(state):  # the iterations drawn, for the table
        drawn.append(state["iteration"])
        return stop(state) if adaptive else False

    stop = _stop_at_confidence(len(points), sample_size)
    seconds, res = _timed(lambda: fitter.fit(points, thresh=THRESHOLD,
                                             maxIteration=PYRANSAC_ITERATIONS, callback=count))
    iterations = drawn[-1] + 1 if drawn else 0
    if shape == "plane":
        eq = np.asarray(res.equation, float)
        if eq.size != 4 or not np.any(eq[:3]):
            return seconds, None, iterations
        norm = np.linalg.norm(eq[:3])
        params = {"normal": eq[:3] / norm, "offset": eq[3] / norm}
    elif shape == "sphere":
        params = {"center": np.asarray(res.center, float), "radius": float(res.radius)}
    else:
        params = {"center": np.asarray(res.center, float), "axis": np.asarray(res.axis, float),
                  "radius": float(res.radius)}
    if not all(np.all(np.isfinite(v)) and np.size(v) for v in params.values()):
        return seconds, None, iterations
    return seconds, params, iterations


# ----- one case -----------------------------------------------------------------------


def _summary(method, shape, n, outliers, runs, batch_size=None) -> dict:
    """Medians over the clouds of a case: seconds, hypotheses and every error measure."""
    key, bar = PRIMARY[shape]
    errs = [r[1] for r in runs]
    primary = [e.get(key, math.nan) for e in errs]
    row = {"method": method, "shape": shape, "N": n, "outliers": outliers,
           "batch_size": batch_size, "clouds": len(runs),
           "seconds": statistics.median(r[0] for r in runs),
           "hypotheses": statistics.median(r[2] for r in runs),
           "accuracy_measure": key, "accuracy_bar": bar,
           "accuracy": statistics.median(primary), "accuracy_worst": max(primary),
           "solved": sum(p <= bar for p in primary)}
    for name in errs[0]:
        row[name] = statistics.median(e.get(name, math.nan) for e in errs)
    return row


def measure_case(shape, n, outliers, seeds, batch_sizes, repeats, pyr_max_n) -> list[dict]:
    runs: dict[tuple, list] = {}
    for i, seed in enumerate(seeds):
        points, truth, _ = demo_cloud(shape, count=n, outlier_ratio=outliers, noise=NOISE,
                                      seed=seed)
        for bs in batch_sizes:
            if i == 0:  # compile this (shape, batch size, bucket) outside the timing
                jaxfit.fit(points, shape, threshold=THRESHOLD, batch_size=bs, key=seed)
            sec, params, hyp = run_jaxfit(points, shape, bs, seed, repeats)
            runs.setdefault(("jaxfit", bs), []).append((sec, accuracy(shape, truth, params), hyp))
            if bs in NO_REFINE_BATCHES:  # what the LO refinement costs and buys
                if i == 0:
                    jaxfit.fit(points, shape, threshold=THRESHOLD, batch_size=bs, refine=False)
                sec, params, hyp = run_jaxfit(points, shape, bs, seed, repeats, refine=False)
                runs.setdefault(("jaxfit_norefine", bs), []).append(
                    (sec, accuracy(shape, truth, params), hyp))
        sec, params, hyp = run_reference(points, shape, seed)
        runs.setdefault(("reference", None), []).append((sec, accuracy(shape, truth, params), hyp))
        if pyransac3d is None:
            continue
        for mode, adaptive in (("pyransac3d_adaptive", True), ("pyransac3d_fixed", False)):
            if not adaptive and n > pyr_max_n.get(shape, n):
                continue  # minutes per cloud: the adaptive run stands for it
            sec, params, hyp = run_pyransac(points, shape, seed, adaptive)
            runs.setdefault((mode, None), []).append((sec, accuracy(shape, truth, params), hyp))
    return [_summary(m, shape, n, outliers, r, bs) for (m, bs), r in runs.items()]


# ----- tables and plot ----------------------------------------------------------------


def _find(rows, method, shape, n, outliers, batch_size=None):
    for r in rows:
        if (r["method"], r["shape"], r["N"], r["outliers"]) == (method, shape, n, outliers) \
                and (batch_size is None or r["batch_size"] == batch_size):
            return r
    return None


def best_batch(rows, shape, n, outliers):
    mine = [r for r in rows if r["method"] == "jaxfit" and (r["shape"], r["N"], r["outliers"])
            == (shape, n, outliers)]
    return min(mine, key=lambda r: r["seconds"])


def _acc(r):
    if r is None:
        return "–"
    unit = "°" if r["accuracy_measure"].endswith("deg") else " %"
    scale = 1.0 if unit == "°" else 100.0
    return f"{r['accuracy'] * scale:.2g}{unit}"


def _ms(r):
    return "–" if r is None else f"{r['seconds'] * 1e3:,.1f}"


def _ratio(a, b):
    if a is None or b is None:
        return "–"
    x = a["seconds"] / b["seconds"]
    return f"{x:,.0f}×" if x >= 10 else f"{x:.2g}×"


def cases(rows):
    return list(dict.fromkeys((r["shape"], r["N"], r["outliers"]) for r in rows))


def main_table(rows) -> str:
    lines = [
        f"| shape | N | outliers | jaxfit ms (bs {DEFAULT_BATCH}) | accuracy | best bs | ms | "
        "reference ms | accuracy | pyRANSAC-3D adaptive ms | accuracy | pyRANSAC-3D 1000 it ms "
        "| accuracy | ref ÷ jaxfit | pyR adaptive ÷ jaxfit | pyR 1000 ÷ jaxfit |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for shape, n, out in cases(rows):
        jf = _find(rows, "jaxfit", shape, n, out, DEFAULT_BATCH)
        best = best_batch(rows, shape, n, out)
        ref = _find(rows, "reference", shape, n, out)
        pa = _find(rows, "pyransac3d_adaptive", shape, n, out)
        pf = _find(rows, "pyransac3d_fixed", shape, n, out)
        lines.append(
            f"| {shape} | {n:,} | {out:.0%} | {_ms(jf)} | {_acc(jf)} | {best['batch_size']} "
            f"| {_ms(best)} | {_ms(ref)} | {_acc(ref)} | {_ms(pa)} | {_acc(pa)} | {_ms(pf)} "
            f"| {_acc(pf)} | {_ratio(ref, jf)} | {_ratio(pa, jf)} | {_ratio(pf, jf)} |")
    return "\n".join(lines)


def batch_table(rows, batch_sizes) -> tuple[str, dict]:
    """Time per batch size relative to the default per case, and their geometric
    mean over the cases: < 1 is faster than the default."""
    head = "| shape | N | outliers | " + " | ".join(f"bs {b} ms" for b in batch_sizes) + " |"
    lines = [head, "|---|---|---|" + "---|" * len(batch_sizes)]
    rel = {b: [] for b in batch_sizes}
    for shape, n, out in cases(rows):
        base = _find(rows, "jaxfit", shape, n, out, DEFAULT_BATCH)
        cells = []
        for b in batch_sizes:
            r = _find(rows, "jaxfit", shape, n, out, b)
            rel[b].append(r["seconds"] / base["seconds"])
            cells.append(f"{r['seconds'] * 1e3:,.1f} ({_acc(r)})")
        lines.append(f"| {shape} | {n:,} | {out:.0%} | " + " | ".join(cells) + " |")
    gmean = {b: float(np.exp(np.mean(np.log(v)))) for b, v in rel.items()}
    lines.append(f"| **geometric mean, ÷ bs {DEFAULT_BATCH}** | | | "
                 + " | ".join(f"**{gmean[b]:.2f}**" for b in batch_sizes) + " |")
    return "\n".join(lines), gmean


def refine_table(rows) -> str:
    """jaxfit with and without LO refinement (refine=False), per batch size."""
    lines = ["| shape | N | outliers | " + " | ".join(
        f"bs {b}: refine ms | accuracy | refine=False ms | accuracy" for b in NO_REFINE_BATCHES)
        + " |", "|---|---|---|" + "---|---|---|---|" * len(NO_REFINE_BATCHES)]
    for shape, n, out in cases(rows):
        cells = []
        for b in NO_REFINE_BATCHES:
            on = _find(rows, "jaxfit", shape, n, out, b)
            off = _find(rows, "jaxfit_norefine", shape, n, out, b)
            cells += [_ms(on), _acc(on), _ms(off), _acc(off)]
        lines.append(f"| {shape} | {n:,} | {out:.0%} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(rows, path):
    """Time to solution against N: one panel per (outlier share, shape), log-log."""
    plt = pyplot()
    shapes = list(dict.fromkeys(r["shape"] for r in rows))
    levels = list(dict.fromkeys(r["outliers"] for r in rows))
    fig, axes = plt.subplots(len(levels), len(shapes), figsize=(3.4 * len(shapes),
                             2.8 * len(levels)), sharey=True, squeeze=False)
    series = [("jaxfit", DEFAULT_BATCH, f"jaxfit (bs {DEFAULT_BATCH})"),
              ("jaxfit", 128, "jaxfit (bs 128)"),
              ("reference", None, "NumPy reference loop"),
              ("pyransac3d_adaptive", None, "pyRANSAC-3D, adaptive stop"),
              ("pyransac3d_fixed", None, "pyRANSAC-3D, 1000 iterations")]
    for row_axes, out in zip(axes, levels, strict=True):
        for ax, shape in zip(row_axes, shapes, strict=True):
            for method, bs, label in series:
                pts = [(r["N"], r["seconds"]) for r in rows if r["method"] == method and
                       r["shape"] == shape and r["outliers"] == out and
                       (bs is None or r["batch_size"] == bs)]
                if pts:
                    ax.loglog(*zip(*pts, strict=True), "o-", label=label)
            ax.set_title(f"{shape}, {out:.0%} outliers", fontsize=9)
            ax.grid(True, which="both", alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("points N")
    for ax in axes[:, 0]:
        ax.set_ylabel("time to solution (s)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Time to solution, warm, same clouds and threshold (median of clouds)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    print(f"wrote {path}")


def verdict(rows) -> list[str]:
    """The issue's bar: 10k points, 30 % outliers, plane and sphere: <= 10 ms warm and
    >= 20x faster than pyRANSAC-3D at equal or better accuracy."""
    out = []
    for shape in ("plane", "sphere"):
        jf = _find(rows, "jaxfit", shape, 10_000, 0.3, DEFAULT_BATCH)
        if jf is None:
            continue
        best = best_batch(rows, shape, 10_000, 0.3)
        line = (f"- {shape}, 10k points, 30 % outliers: jaxfit {jf['seconds'] * 1e3:.1f} ms "
                f"(bs {DEFAULT_BATCH}), {best['seconds'] * 1e3:.1f} ms (bs {best['batch_size']}); "
                f"≤ 10 ms: {'yes' if jf['seconds'] <= 0.01 else 'no'} (bs {DEFAULT_BATCH}), "
                f"{'yes' if best['seconds'] <= 0.01 else 'no'} (best bs)")
        for mode in ("pyransac3d_fixed", "pyransac3d_adaptive"):
            p = _find(rows, mode, shape, 10_000, 0.3)
            if p is not None:
                better = "better" if jf["accuracy"] <= p["accuracy"] else "worse"
                line += (f"; vs {mode}: {_ratio(p, jf)} (bs {DEFAULT_BATCH}), {_ratio(p, best)} "
                         f"(best bs), jaxfit's accuracy {_acc(jf)} vs {_acc(p)} ({better})")
        out.append(line)
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="N up to 1e4, one seed")
    parser.add_argument("--shapes", nargs="+", default=list(SHAPES), choices=SHAPES)
    parser.add_argument("--seeds", type=int, default=3, help="clouds per case (3)")
    parser.add_argument("--repeats", type=int, default=3, help="warm fits per cloud (3)")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=list(BATCH_SIZES))
    parser.add_argument("--render", action="store_true",
                        help="only rewrite solution.md and .png from solution.json")
    args = parser.parse_args(argv)
    if args.render:
        saved = json.loads((RESULTS / "solution.json").read_text())
        sizes = sorted({r["batch_size"] for r in saved["rows"] if r["method"] == "jaxfit"})
        return write(saved["rows"], saved["meta"], sizes)
    sizes = SIZES[:2] if args.quick else SIZES
    seeds = range(1 if args.quick else args.seeds)
    batch_sizes = sorted(set(args.batch_sizes) | {DEFAULT_BATCH})
    if pyransac3d is None:
        print("pyRANSAC-3D is not installed (pip install '.[bench]'): its columns stay empty")
    # pyRANSAC-3D's fixed 1000-iteration cylinder takes minutes on 1e5 points
    pyr_max_n = {"cylinder": 10_000}
    rows = []
    for shape in args.shapes:
        for n in sizes:
            for outliers in OUTLIERS:
                case = measure_case(shape, n, outliers, seeds, batch_sizes, args.repeats,
                                    pyr_max_n)
                rows.extend(case)
                print(main_table(case).splitlines()[-1], flush=True)
    meta = {"machine": platform.processor() or platform.machine(), "jax": jax.__version__,
            "cpus": os.cpu_count(), "pyransac3d": getattr(pyransac3d, "__version__", None)
            if pyransac3d else None, "noise": NOISE, "threshold": THRESHOLD,
            "confidence": CONFIDENCE, "seeds": list(seeds), "repeats": args.repeats,
            "accuracy": PRIMARY, "batch_sizes": batch_sizes}
    write(rows, meta, batch_sizes)


def write(rows, meta, batch_sizes):
    """solution.json, solution.md and solution.png from the measured rows."""
    batch_md, gmean = batch_table(rows, batch_sizes)
    checks = verdict(rows)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "solution.json").write_text(json.dumps(
        {"meta": meta, "rows": rows, "batch_size_gmean_vs_default": gmean, "verdict": checks},
        indent=2))
    md = "\n\n".join([
        "## Time to solution (warm; median over clouds; accuracy: plane normal angle, "
        "sphere centre error / R, cylinder axis angle)", main_table(rows),
        "## jaxfit batch size (ms, accuracy in brackets)", batch_md,
        "## jaxfit with and without LO refinement", refine_table(rows),
        "## The issue's bar", "\n".join(checks) or "(not measured)"])
    (RESULTS / "solution.md").write_text(md + "\n")
    print(md)
    plot(rows, RESULTS / "solution.png")


if __name__ == "__main__":
    main()
