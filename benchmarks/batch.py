"""Scale-out: ``jaxfit.fit_batch`` of many small clouds against one ``jaxfit.fit`` per cloud.

For each primitive, C clouds of 500 points (``jaxfit.evaluation.synthetic.demo_cloud``: unit-size
primitive, surface noise U(-0.005, 0.005), 30 % outliers, seed = cloud index) are fitted,
side by side in one run, on the same clouds with the same options (defaults: confidence
0.99, LO refinement):
- ``fit``: a Python loop of C ``jaxfit.fit(cloud, shape, key=i)`` calls;
- ``fit_batch``: one ``jaxfit.fit_batch(clouds, shape)`` call.
Each with LO refinement (the default) and without (``refine=False``). Both warm (one
untimed call of each first compiles the kernels), best of ``--repeats``, the two
interleaved; wall and process CPU seconds (on a shared machine the CPU ratio is the one
other jobs disturb least; fit_batch's CPU exceeds its wall time where XLA runs threads).
Accuracy: median over the clouds of the main error against the true primitive (as in
``benchmarks/solution.py``), so the speed-up is not bought with worse fits.

With ``--hard K`` (default 10) the first shape is also timed on clouds of which K have
75 % outliers: they need several batches where the others need one, and after the first
batch fit_batch runs only on them.

With ``--devices D`` the batch is also timed in a subprocess with D forced host devices
(``XLA_FLAGS=--xla_force_host_platform_device_count=D``), where fit_batch shards the clouds
across the devices (on a GPU machine the same code splits them over the GPUs).

With ``--stages`` it instead times each stage of the host path (process CPU seconds,
so that other jobs on a shared machine count less; the clouds searched in one loop, not
in concurrent parts): one ``fit_batch`` of the clouds and
single ``fit`` calls (a plane of 1e3 points with 10 % outliers, a 500-point demo cloud of
each shape), by wrapping the engine's stage functions (``stage_times``). The kernel and
refinement calls are waited on, so their time is the device's plus the dispatch.

Run: ``python -m benchmarks.batch [--clouds 1000] [--shapes sphere plane cylinder]
[--hard 10]``; ``python -m benchmarks.batch --stages [--shapes sphere plane]``.
Writes ``benchmarks/results/batch.json`` and ``batch.md`` (``batch.stages.json`` and
``batch.stages.md`` with ``--stages``).
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
    singles, batched = None, batch()
    wall, cpu = {"loop": [], "batch": []}, {"loop": [], "batch": []}
    for _ in range(repeats):  # interleaved: a change of the machine's load hits both
        for name, fn in (("loop", loop), ("batch", batch)):
            start, start_cpu = time.perf_counter(), time.process_time()
            out = fn()
            wall[name].append(time.perf_counter() - start)
            cpu[name].append(time.process_time() - start_cpu)
            singles, batched = (out, batched) if name == "loop" else (singles, out)
    t_loop, t_batch = min(wall["loop"]), min(wall["batch"])
    c_loop, c_batch = min(cpu["loop"]), min(cpu["batch"])
    return {
        "shape": shape, "clouds": count, "points": POINTS, "refine": refine, "hard": hard,
        "fit_loop_s": t_loop, "fit_batch_s": t_batch, "speedup": t_loop / t_batch,
        "fit_loop_cpu_s": c_loop, "fit_batch_cpu_s": c_batch, "speedup_cpu": c_loop / c_batch,
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


#: The stages ``stage_times`` reports: (module, function, label, waited on). Where a
#: stage has no such function in the code measured, it is left out.
STAGES = (("jaxfit.engine.fit", "converted_batch", "convert", False),
          ("jaxfit.engine.fit", "prepare", "prepare", False),
          ("jaxfit.engine.fit", "prepare_many", "prepare", False),
          ("jaxfit.engine.fit", "search", "search", False),
          ("jaxfit.engine.loop", "search_group", "search", False),
          ("jaxfit.engine.loop", "batch_best_many", "kernel", True),
          ("jaxfit.engine.loop", "refine_many", "refinement", True),
          ("jaxfit.engine.fit", "refitted", "final refit", False),
          ("jaxfit.engine.fit", "results_many", "results", False),
          ("jaxfit.engine.fit", "result", "results", False))


def stage_times(run, repeats: int) -> dict:
    """Process CPU ms of each stage of ``run()`` (a fit or fit_batch call), summed over
    one call: the fastest of ``repeats`` calls. 'host loop' is the search less its kernel
    and refinement calls, 'other' the call less every stage (options, keys, ...)."""
    import importlib

    totals: dict = {}
    restore = []
    # One loop, not parts in threads (``loop.searches``): a thread's process CPU would
    # count the other parts' too.
    loop = importlib.import_module("jaxfit.engine.loop")
    if hasattr(loop, "cores"):
        restore.append((loop, "cores", loop.cores))
        loop.cores = lambda: 0
    for module_name, name, label, wait in STAGES:
        module = importlib.import_module(module_name)
        fn = getattr(module, name, None)
        if fn is None:
            continue

        def timed(*args, _fn=fn, _label=label, _wait=wait, **kwargs):
            start = time.process_time()
            out = _fn(*args, **kwargs)
            if _wait:
                jax.block_until_ready(out)
            totals[_label] = totals.get(_label, 0.0) + time.process_time() - start
            return out

        restore.append((module, name, fn))
        setattr(module, name, timed)
    try:
        run()  # (compiles)
        best = None
        for _ in range(repeats):
            totals.clear()
            start = time.process_time()
            run()
            total = time.process_time() - start
            if best is None or total < best[0]:
                best = (total, dict(totals))
    finally:
        for module, name, fn in restore:
            setattr(module, name, fn)
    total, parts = best
    parts["host loop"] = parts.get("search", 0.0) - parts.get("kernel", 0.0) - parts.get(
        "refinement", 0.0)
    parts["other"] = total - sum(v for k, v in parts.items()
                                 if k not in ("kernel", "refinement", "host loop"))
    parts.pop("search", None)
    return {"total": 1e3 * total, **{k: 1e3 * v for k, v in parts.items()}}


STAGE_ORDER = ("convert", "prepare", "kernel", "refinement", "host loop", "final refit",
               "results", "other")


def stages(shapes, count: int, repeats: int) -> list[dict]:
    """``stage_times`` of fit_batch over ``count`` demo clouds and of single fits."""
    rows = []
    for shape in shapes:
        clouds, _ = clouds_for(shape, count)
        rows.append({"call": f"fit_batch({count} x {POINTS}) {shape}",
                     **stage_times(lambda c=clouds, s=shape: jaxfit.fit_batch(
                                       c, s, skip_failures=True), repeats)})
        rows.append({"call": f"fit({POINTS}) {shape}, mean of 100",
                     **{k: v / 100 for k, v in stage_times(
                         lambda c=clouds[:100], s=shape: [jaxfit.fit(p, s, key=i)
                                                          for i, p in enumerate(c)],
                         repeats).items()}})
    plane, _, _ = demo_cloud("plane", count=1000, outlier_ratio=0.1, seed=1)
    rows.append({"call": "fit(1e3) plane 10 % outliers, mean of 100",
                 **{k: v / 100 for k, v in stage_times(
                     lambda: [jaxfit.fit(plane, "plane", key=k) for k in range(100)],
                     repeats).items()}})
    return rows


def stage_table(rows) -> str:
    lines = ["| call | total ms | " + " | ".join(STAGE_ORDER) + " |",
             "|---|---|" + "---|" * len(STAGE_ORDER)]
    for r in rows:
        lines.append(f"| {r['call']} | {r['total']:.3g} | "
                     + " | ".join(f"{r[k]:.3g}" if k in r else "" for k in STAGE_ORDER) + " |")
    return "\n".join(lines)


def _hard(row) -> str:
    hard = row.get("hard", 0)
    return f" ({hard} with {HARD_OUTLIERS:.0%} outliers)" if hard else ""


def _cpu(row) -> str:
    if "fit_loop_cpu_s" not in row:
        return ""
    return (f"{row['fit_loop_cpu_s']:.2f} / {row['fit_batch_cpu_s']:.3f} "
            f"({row['speedup_cpu']:.1f}x)")


def table(rows) -> str:
    lines = ["| shape | clouds x points | refine | C `fit` calls (s) | one `fit_batch` (s) "
             "| speed-up | process CPU s: fit calls / fit_batch (speed-up) "
             "| ms per cloud: fit / batch | median error: fit / batch "
             "| fit_batch on forced host devices: s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    unit = {"sphere": "centre/R", "plane": "deg", "cylinder": "deg", "cone": "deg"}
    for r in rows:
        devices = ", ".join(f"{d} devices: {s:.3f}" for d, s in r.get("devices", {}).items())
        lines.append(
            f"| {r['shape']} | {r['clouds']} x {r['points']}{_hard(r)} "
            f"| {'yes' if r['refine'] else 'no'} "
            f"| {r['fit_loop_s']:.2f} "
            f"| {r['fit_batch_s']:.3f} | {r['speedup']:.1f}x "
            f"| {_cpu(r)} "
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
    parser.add_argument("--stages", action="store_true",
                        help="time the host path's stages instead (process CPU)")
    args = parser.parse_args(argv)
    meta = {"machine": platform.processor() or platform.machine(), "jax": jax.__version__,
            "cpus": os.cpu_count()}
    if args.stages:
        rows = stages(args.shapes, args.clouds[0], args.repeats)
        RESULTS.mkdir(parents=True, exist_ok=True)
        (RESULTS / "batch.stages.json").write_text(json.dumps({"meta": meta, "rows": rows},
                                                              indent=2))
        md = stage_table(rows)
        (RESULTS / "batch.stages.md").write_text(md + "\n")
        print(md)
        return
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
    (RESULTS / "batch.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    md = table(rows)
    (RESULTS / "batch.md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":
    main()
