"""jaxfit on whatever device JAX runs on: the issue's GPU table (throughput, time to
solution, ``fit_batch``), measured by the same functions as the CPU benchmarks.

Run: ``python -m benchmarks.device [--quick] [--out DIR]``. The code needs no change for a
GPU: JAX picks its default backend, and every figure names the device it ran on. Each
program is called once before it is timed (compile excluded); the first calls' seconds
are reported apart, so a run on a fresh machine also shows its cold start.

- throughput: ``benchmarks.throughput.measure``, the kernel's point-hypothesis
  evaluations per second (best of 9) beside NumPy's vectorised scoring of 64 of the same
  hypotheses on this machine's CPU;
- time to solution: ``benchmarks.solution.run_jaxfit`` (a whole ``fit``, adaptive
  stopping, median of 3) with its accuracy on the demo clouds of ``solution.py``;
- fit_batch: ``benchmarks.batch.measure``, 1000 clouds of 500 points against 1000 ``fit``
  calls.

On the lent GPU machine (its image has JAX with CUDA, NumPy, SciPy and matplotlib, not
trimesh or pykdtree: carry their wheels as the device tool's README says), from the
repository root: ``PYTHONPATH=. python3 -m benchmarks.device --out $OUT``. Writes
``device_<platform>.json`` and ``.md`` to ``--out`` (default ``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax

from benchmarks import batch, solution, throughput
from jaxfit.evaluation.synthetic import demo_cloud

RESULTS = Path(__file__).resolve().parent / "results"
SHAPES = ("plane", "sphere", "cylinder")
HYPOTHESES = 4096
#: (throughput sizes, time-to-solution sizes, fit_batch clouds): the full run and --quick.
FULL = ((10_000, 100_000, 1_000_000), (10_000, 100_000, 1_000_000), 1000)
QUICK = ((10_000, 100_000), (10_000, 100_000), 200)
OUTLIERS = 0.3


def _timed_first(fn):
    """(seconds of the first call, its value): the first call compiles."""
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def throughput_rows(sizes, say) -> list[dict]:
    rows = []
    for shape in SHAPES:
        for n in sizes:
            first, row = _timed_first(lambda s=shape, n=n: throughput.measure(
                s, n, HYPOTHESES, loop_hypotheses=4, vec_hypotheses=64))
            rows.append({"shape": shape, "N": n, "H": HYPOTHESES,
                         "jaxfit_evals_per_s": row["jaxfit_evals_per_s"],
                         "numpy_vectorised_evals_per_s": row["numpy_vectorised_evals_per_s"],
                         "speedup_vs_vectorised": row["speedup_vs_vectorised"],
                         "measure_seconds": first})
            say(f"throughput {shape} N={n}: {row['jaxfit_evals_per_s']:.3g} evals/s "
                f"({row['speedup_vs_vectorised']:.0f}x NumPy)")
    return rows


def solution_rows(sizes, say) -> list[dict]:
    rows = []
    for shape in SHAPES:
        for n in sizes:
            points, truth, _ = demo_cloud(shape, count=n, outlier_ratio=OUTLIERS,
                                          noise=solution.NOISE, seed=0)
            first, _ = _timed_first(lambda p=points, s=shape: solution.run_jaxfit(
                p, s, solution.DEFAULT_BATCH, 0, 1))
            seconds, params, hypotheses = solution.run_jaxfit(
                points, shape, solution.DEFAULT_BATCH, 0, 3)
            key = solution.PRIMARY[shape][0]
            error = solution.accuracy(shape, truth, params)[key]
            rows.append({"shape": shape, "N": n, "outliers": OUTLIERS, "ms": 1e3 * seconds,
                         "first_call_s": first, "hypotheses": hypotheses,
                         "error_measure": key, "error": error})
            say(f"solution {shape} N={n}: {1e3 * seconds:.1f} ms, {key} {error:.3g} "
                f"(first call {first:.1f} s)")
    return rows


def batch_rows(clouds: int, say) -> list[dict]:
    rows = []
    for shape in SHAPES:
        row = batch.measure(shape, clouds, repeats=3)
        rows.append({k: row[k] for k in ("shape", "clouds", "points", "fit_loop_s",
                                         "fit_batch_s", "speedup", "batch_median_error",
                                         "batch_failures")})
        say(f"fit_batch {shape} x {clouds}: {row['fit_batch_s']:.3f} s against "
            f"{row['fit_loop_s']:.3f} s of fit calls ({row['speedup']:.1f}x)")
    return rows


def markdown(meta, rows) -> str:
    out = [f"# jaxfit on {meta['device']}", "",
           f"`python -m benchmarks.device{' --quick' if meta['quick'] else ''}` "
           f"({meta['when']}; JAX {meta['jax']} on {meta['backend']}, host "
           f"{meta['host']}, {meta['cpus']} CPUs; compile excluded: each program called "
           "once first, the first fit's seconds in its own column; cache folder "
           f"{meta['cache']}).", "",
           "## Throughput (kernel, H = 4096; NumPy vectorised on the host CPU)", "",
           "| shape | N | jaxfit evals/s | NumPy evals/s | ratio | s, all of its runs |",
           "|---|---|---|---|---|---|"]
    out += [f"| {r['shape']} | {r['N']} | {r['jaxfit_evals_per_s']:.3g} | "
            f"{r['numpy_vectorised_evals_per_s']:.3g} | {r['speedup_vs_vectorised']:.0f}x | "
            f"{r['measure_seconds']:.1f} |" for r in rows["throughput"]]
    out += ["", f"## Time to solution (`fit`, {int(OUTLIERS * 100)} % outliers, median of 3)",
            "", "| shape | N | ms | hypotheses | error | first call s |",
            "|---|---|---|---|---|---|"]
    out += [f"| {r['shape']} | {r['N']} | {r['ms']:.1f} | {r['hypotheses']} | "
            f"{r['error_measure']} {r['error']:.3g} | {r['first_call_s']:.1f} |"
            for r in rows["solution"]]
    out += ["", "## fit_batch (500-point clouds, best of 3)", "",
            "| shape | clouds | fit_batch s | fit calls s | ratio | median error | failures |",
            "|---|---|---|---|---|---|---|"]
    out += [f"| {r['shape']} | {r['clouds']} | {r['fit_batch_s']:.3f} | {r['fit_loop_s']:.3f} | "
            f"{r['speedup']:.1f}x | {r['batch_median_error']:.3g} | {r['batch_failures']} |"
            for r in rows["batch"]]
    return "\n".join(out) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="N up to 1e5 and 200 clouds (a CPU run in a few minutes)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    sizes, solve_sizes, clouds = QUICK if args.quick else FULL
    start = time.perf_counter()

    def say(text):
        print(f"[{time.perf_counter() - start:6.1f} s] {text}", flush=True)

    device = jax.devices()[0]
    meta = {"device": getattr(device, "device_kind", str(device)),
            "backend": jax.default_backend(), "jax": jax.__version__,
            "host": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
            "quick": args.quick, "when": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "cache": "empty at start" if os.environ.get("JAXFIT_CACHE_DIR") and not any(
                Path(os.environ["JAXFIT_CACHE_DIR"]).iterdir()) else "as found"}
    say(f"device: {meta['device']} ({meta['backend']})")
    rows = {"throughput": throughput_rows(sizes, say),
            "solution": solution_rows(solve_sizes, say),
            "batch": batch_rows(clouds, say)}
    meta["seconds"] = time.perf_counter() - start
    meta["median_speedup"] = statistics.median(r["speedup_vs_vectorised"]
                                               for r in rows["throughput"])
    args.out.mkdir(parents=True, exist_ok=True)
    name = f"device_{meta['backend']}"
    (args.out / f"{name}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    (args.out / f"{name}.md").write_text(markdown(meta, rows))
    say(f"wrote {args.out / name}.json and .md")


if __name__ == "__main__":
    main()
