"""Scale-out: ``jaxfit.fit_batch`` of many small clouds against one ``jaxfit.fit`` per cloud.

For each primitive, C clouds of 500 points (``jaxfit.evaluation.synthetic.demo_cloud``: unit-size
primitive, surface noise U(-0.005, 0.005), 30 % outliers, seed = cloud index) are fitted,
side by side in one run, on the same clouds with the same options (defaults: confidence
0.99, LO refinement):
- ``fit``: a Python loop of C ``jaxfit.fit(cloud, shape, key=i)`` calls;
- ``fit_batch``: one ``jaxfit.fit_batch(clouds, shape)`` call.
Each with LO refinement (the default) and without (``refine=False``). Both warm (one
untimed call of each first compiles the kernels), best of ``--repeats``.
Accuracy: median over the clouds of the main error against the true primitive (as in
``benchmarks/solution.py``), so the speed-up is not bought with worse fits.

With ``--hard K`` (default 10) the first shape is also timed on clouds of which K have
75 % outliers: they need several batches where the others need one, and after the first
batch fit_batch runs only on them.

With ``--devices D`` the batch is also timed in a subprocess with D forced host devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=D``), where fit_batch shards the clouds
across the devices (on a GPU machine the same code splits them over the GPUs).

Run: ``python -m benchmarks.batch [--clouds 1000] [--shapes sphere plane cylinder]
[--hard 10]``.
Writes ``benchmarks/results/batch.json`` and ``batch.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

import jaxfit
from jaxfit.evaluation.synthetic import demo_cloud

RESULTS = Path(__file__).resolve().parent / "results"
POINTS = 500
OUTLIERS = 0.3
#: A few clouds with this outlier share need several batches where the others need one.
HARD_OUTLIERS = 0.75


def clouds_for(shape: str, count: int, hard: int = 0):
    """(clouds, truths): ``count`` demo clouds of ``shape`` with seeds 0..count-1, of which
    ``hard`` (spread evenly) have HARD_OUTLIERS instead of OUTLIERS."""
    every = count // hard if hard else count + 1
    made = [demo_cloud(shape, count=POINTS, seed=i,
                       outlier_ratio=HARD_OUTLIERS if i % every == 0 else OUTLIERS)
            for i in range(count)]
    return [m[0] for m in made], [m[1] for m in made]


def error(shape: str, fitted, true) -> float:
    """The main accuracy measure: normal / axis angle in degrees, or centre error / R."""
    if fitted is None:
        return float("nan")
    if shape == "sphere":
        return float(np.linalg.norm(fitted.center - true.center) / true.radius)
    a, b = ((fitted.normal, true.normal) if shape == "plane" else (fitted.axis, true.axis))
    return float(np.degrees(np.arccos(min(1.0, abs(float(np.dot(a, b)))))))


def best_time(fn, repeats: int):
    best, out = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def measure(shape: str, count: int, repeats: int, refine: bool = True, hard: int = 0) -> dict:
    clouds, truths = clouds_for(shape, count, hard)

    def loop():
        return [jaxfit.fit(c, shape, key=i, refine=refine) for i, c in enumerate(clouds)]

    def batch():
        return jaxfit.fit_batch(clouds, shape, skip_failures=True, refine=refine)

    jaxfit.fit(clouds[0], shape, refine=refine)  # compile both paths
    batch()
    t_loop, singles = best_time(loop, repeats)
    t_batch, batched = best_time(batch, repeats)
    return {
        "shape": shape, "clouds": count, "points": POINTS, "refine": refine, "hard": hard,
        "fit_loop_s": t_loop, "fit_batch_s": t_batch, "speedup": t_loop / t_batch,
        "fit_ms_per_cloud": 1e3 * t_loop / count, "batch_ms_per_cloud": 1e3 * t_batch / count,
        "fit_median_error": float(np.nanmedian([error(shape, r.model, t)
                                                for r, t in zip(singles, truths, strict=True)])),
        "batch_median_error": float(np.nanmedian([error(shape, r and r.model, t)
                                                  for r, t in zip(batched, truths, strict=True)])),
        "batch_failures": sum(r is None for r in batched),
    }


def on_devices(devices: int, shape: str, count: int, repeats: int) -> float:
    """Seconds for the same fit_batch with ``devices`` forced host devices (subprocess)."""
    root = str(Path(__file__).resolve().parents[1])
    script = "\n".join([
        f"import sys; sys.path.insert(0, {root!r})",
        "import jax, jaxfit",
        "from benchmarks.batch import clouds_for, best_time",
        f"assert len(jax.local_devices()) == {devices}, jax.local_devices()",
        f"clouds, _ = clouds_for({shape!r}, {count})",
        f"run = lambda: jaxfit.fit_batch(clouds, {shape!r}, skip_failures=True)",
        "run()",
        f"print(best_time(run, {repeats})[0])",
    ])
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                         text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def _hard(row) -> str:
    hard = row.get("hard", 0)
    return f" ({hard} with {HARD_OUTLIERS:.0%} outliers)" if hard else ""


def table(rows) -> str:
    lines = ["| shape | clouds x points | refine | C `fit` calls (s) | one `fit_batch` (s) "
             "| speed-up | ms per cloud: fit / batch | median error: fit / batch "
             "| fit_batch on forced host devices: s |",
             "|---|---|---|---|---|---|---|---|---|"]
    unit = {"sphere": "centre/R", "plane": "deg", "cylinder": "deg", "cone": "deg"}
    for r in rows:
        devices = ", ".join(f"{d} devices: {s:.3f}" for d, s in r.get("devices", {}).items())
        lines.append(
            f"| {r['shape']} | {r['clouds']} x {r['points']}{_hard(r)} "
            f"| {'yes' if r['refine'] else 'no'} "
            f"| {r['fit_loop_s']:.2f} "
            f"| {r['fit_batch_s']:.3f} | {r['speedup']:.1f}x "
            f"| {r['fit_ms_per_cloud']:.2f} / {r['batch_ms_per_cloud']:.2f} "
            f"| {r['fit_median_error']:.2g} / {r['batch_median_error']:.2g} {unit[r['shape']]} "
            f"| {devices} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clouds", type=int, nargs="+", default=[1000])
    parser.add_argument("--shapes", nargs="+", default=["sphere", "plane", "cylinder"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--hard", type=int, default=10,
                        help="also time the first shape with this many hard clouds (0: no)")
    parser.add_argument("--devices", type=int, nargs="*", default=[2],
                        help="also time fit_batch with this many forced host devices")
    args = parser.parse_args(argv)
    rows = []
    for shape in args.shapes:
        for count in args.clouds:
            for refine in (True, False):
                row = measure(shape, count, args.repeats, refine)
                if refine:
                    row["devices"] = {d: on_devices(d, shape, count, args.repeats)
                                      for d in args.devices}
                rows.append(row)
                print(table([row]).splitlines()[-1], flush=True)
    if args.hard:  # a few clouds need several batches: the others must not pay for them
        rows.append(measure(args.shapes[0], args.clouds[0], args.repeats, True, args.hard))
        print(table(rows[-1:]).splitlines()[-1], flush=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    meta = {"machine": platform.processor() or platform.machine(), "jax": jax.__version__,
            "cpus": os.cpu_count()}
    (RESULTS / "batch.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    md = table(rows)
    (RESULTS / "batch.md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":
    main()
