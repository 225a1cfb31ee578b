"""Whole datasets: models per minute of ``jaxfit.batch.run_batch`` for 1 and 2 local
worker processes and a Dask LocalCluster of 2 single-threaded workers.

Models: ``--models`` (default 50) point files, each a built-in composite object
(``jaxfit.evaluation.synthetic.composite``: mallet, lollipop, hammer, lamp in turn) of
``--points`` (default 4000) surface points with seed = model index, written as ``.npy``.
Task: ``decompose`` (the robotics use: parts.json, decomposition.glb and preview.png per
model), default options, seed 0.

Each configuration writes a fresh output folder, so nothing is reused; its wall time
includes starting the worker processes (each imports jaxfit and loads the stored
kernels). Before them one untimed in-process run over the four objects stores the
kernels in the compilation cache, so the figures are warm-cache ones (a cold cache adds
each worker's compilation; run with ``JAXFIT_CACHE_DIR=$(mktemp -d)`` to see it).
The machine is shared: the load average is recorded beside each figure.

Run: ``python -m benchmarks.batch_models [--models 50] [--points 4000]``.
Writes ``benchmarks/results/batch_models.json`` and ``batch_models.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from jaxfit.batch import run_batch
from jaxfit.evaluation.synthetic import COMPOSITES, composite

RESULTS = Path(__file__).resolve().parent / "results"
#: (label, run_batch options): the configurations compared.
CONFIGS = (("1 local process", {"workers": 1}),
           ("2 local processes", {"workers": 2}),
           ("Dask LocalCluster, 2 workers", {"workers": 2, "scheduler": "local"}))


def write_models(folder: Path, count: int, points: int) -> list[Path]:
    """``count`` composite objects as .npy point files in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(count):
        name = COMPOSITES[i % len(COMPOSITES)]
        cloud, _, _ = composite(name, count=points, seed=i)
        paths.append(folder / f"{i:03d}_{name}.npy")
        np.save(paths[-1], cloud)
    return paths


def measure(models: Path, out: Path, options: dict) -> dict:
    """One timed run of decompose over every model into a fresh ``out``."""
    load = os.getloadavg()[0]
    start = time.perf_counter()
    summary = run_batch([models], out, task="decompose", **options)
    seconds = time.perf_counter() - start
    per_model = [r["seconds"] for r in summary.rows if r["seconds"] is not None]
    return {"models": len(summary.rows), "failed": summary.num_failed,
            "seconds": round(seconds, 2),
            "models_per_minute": round(60 * len(summary.rows) / seconds, 1),
            "median_model_seconds": round(float(np.median(per_model)), 3),
            "load_before": round(load, 2), "load_after": round(os.getloadavg()[0], 2)}


def table(results: dict) -> str:
    lines = ["| executor | models | failed | wall s | models / min | median s per model "
             "(in its worker) | load avg before / after |", "|---|---|---|---|---|---|---|"]
    for label, r in results["runs"].items():
        lines.append(f"| {label} | {r['models']} | {r['failed']} | {r['seconds']} | "
                     f"{r['models_per_minute']} | {r['median_model_seconds']} | "
                     f"{r['load_before']} / {r['load_after']} |")
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", type=int, default=50, help="models generated (50)")
    parser.add_argument("--points", type=int, default=4000, help="points per model (4000)")
    parser.add_argument("--commit", default=None,
                        help="the jaxfit commit measured, recorded with the results")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="jaxfit-batch-models-"))
    models = work / "models"
    write_models(models, args.models, args.points)
    warm = work / "warm"
    write_models(warm, len(COMPOSITES), args.points)
    run_batch([warm], work / "warm-out", task="decompose", workers=0)  # stores the kernels
    runs = {}
    for i, (label, options) in enumerate(CONFIGS):
        runs[label] = measure(models, work / f"out{i}", options)
        print(label, runs[label], flush=True)
    results = {"task": "decompose", "models": args.models, "points": args.points,
               "cpus": os.cpu_count(), "platform": platform.platform(),
               "jax": jax.__version__, "commit": args.commit, "runs": runs}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "batch_models.json").write_text(json.dumps(results, indent=1))
    (RESULTS / "batch_models.md").write_text(
        "# Batch: models per minute (python -m benchmarks.batch_models)\n\n"
        f"decompose on {args.models} composite objects of {args.points} points (.npy), "
        f"{os.cpu_count()} CPUs shared with other work, warm compilation cache, wall time "
        f"including worker start-up; jaxfit commit {args.commit or '?'}.\n\n"
        + table(results) + "\n")
    print(table(results))


if __name__ == "__main__":
    main()
