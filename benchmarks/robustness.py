"""Bounded memory and time on the inputs that used to blow up (issue 14): peak RSS and
wall time of each case next to the case it must stay close to.

Every case is a fresh interpreter (``subprocess``) that builds its input, runs the call
once and reports the call's wall time and the process's peak resident set size
(``resource.getrusage``, so the interpreter and JAX count too: ~0.3-0.4 GB of every
figure). The compilation cache is whatever ``JAXFIT_CACHE_DIR`` says (the default: the
user's warm one); ``--cold`` gives every process an empty folder instead. All cases run
``--repeats`` times (whole passes, so a first process that traces and stores kernels
does not count as warm) and each reports its fastest run, with every run's figures in
the JSON.

Cases and the bound each must meet (the issue's "Done when"):
- detect on a 100k-point synthetic scene, and on the same scene plus 20,000 copies of one
  of its points: ≤ 2x the scene alone;
- fit_batch (plane) of 511 clouds of 100 points plus one of 1e6 points: ≤ 1.5x the sum of
  the separate calls (fit_batch of the 511, fit of the big one);
- decompose of an exact cylinder (every point on its surface, so on its convex hull) of
  20k and 80k points, and of the GraspIt mug sampled at 20k and 100k points: the larger
  one's time per point ≤ 3x the 20k one's;
- the .iv bombs (USE doubling, a 3e9 vertex count: a clear ``IVError``; 5,000 nested
  Separators: read, the reader does not recurse): each ≤ 1 s.

Run: ``python -m benchmarks.robustness [--cold] [--repeats 2] [--only GROUP ...]``. Writes
``benchmarks/results/robustness.json`` and ``robustness.md`` (not with ``--only``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

# Each snippet defines `run()`; the harness times it and reads the peak RSS afterwards.
PRELUDE = """
import resource, sys, time, json
import numpy as np
import jaxfit
"""

HARNESS = """
start = time.perf_counter()
outcome = run()
seconds = time.perf_counter() - start
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # KiB on Linux
print("RESULT " + json.dumps({"seconds": seconds, "peak_bytes": peak, "outcome": outcome}))
"""

SCENE = """
from jaxfit.evaluation.synthetic import scene
points, _, _ = scene(0, objects=4, count=100_000)
copies = {copies}
if copies:
    points = np.concatenate([points, np.repeat(points[:1], copies, axis=0)])
def run():
    found = jaxfit.detect(points, key=0)
    return f"{{len(points)}} points, {{len(found.shapes)}} shapes: " + ", ".join(
        f"{{s.model.name}} {{len(s.indices)}}" for s in found.shapes)
"""

BATCH = """
rng = np.random.default_rng(0)
def plane(n):
    xy = rng.uniform(-1, 1, (n, 2))
    return np.column_stack([xy, 0.002 * rng.standard_normal(n)])
small = [plane(100) for _ in range({small})]
big = [plane(1_000_000)] if {big} else []
def run():
    if small and big:
        results = jaxfit.fit_batch(small + big, "plane", key=0)
    elif small:
        results = jaxfit.fit_batch(small, "plane", key=0)
    else:
        results = [jaxfit.fit(big[0], "plane", key=0)]
    return f"{{len(results)}} clouds, inliers {{sum(r.num_inliers for r in results)}}"
"""

CYLINDER = """
rng = np.random.default_rng(0)
n, radius, height = {points}, 0.5, 2.0
side, cap = 2 * np.pi * radius * height, np.pi * radius ** 2
which = rng.choice(3, n, p=np.array([side, cap, cap]) / (side + 2 * cap))
angle = rng.uniform(0, 2 * np.pi, n)
rho = np.where(which == 0, radius, radius * np.sqrt(rng.uniform(0, 1, n)))
z = np.where(which == 0, rng.uniform(-height / 2, height / 2, n),
             np.where(which == 1, -height / 2, height / 2))
points = np.column_stack([rho * np.cos(angle), rho * np.sin(angle), z])
def run():
    result = jaxfit.decompose(points, key=0)
    return f"{{len(points)}} points, parts: " + ", ".join(p.winner for p in result.parts)
"""

MESH = """
from jaxfit.decomposition import load_source
points = load_source({path!r}, num_points={points}, seed=0)
def run():
    result = jaxfit.decompose(points, key=0)
    return f"{{len(points)}} points, parts: " + ", ".join(p.winner for p in result.parts)
"""

BOMB = """
from jaxfit.io.iv import loads_iv, IVError
text = {text!r}
def run():
    try:
        mesh = loads_iv(text)
    except IVError as err:
        return "IVError: " + str(err)[:160]
    return f"read {{len(mesh.vertices)}} vertices (no error)"
"""


def _doubling(levels: int) -> str:
    lines = ["#Inventor V2.1 ascii", "DEF L0 Sphere { }"]
    lines += [f"DEF L{i} Separator {{ USE L{i - 1} USE L{i - 1} }}" for i in range(1, levels + 1)]
    return "\n".join(lines)


def cases():
    """(group, name, code) of every case; each group is compared within itself."""
    mug = DATA / "graspit" / "mug.iv"
    out = [
        ("detect", "scene 100k", SCENE.format(copies=0)),
        ("detect", "scene 100k + 20k coincident", SCENE.format(copies=20_000)),
        ("fit_batch", "511 x 100 (separate)", BATCH.format(small=511, big=False)),
        ("fit_batch", "1 x 1e6 (separate)", BATCH.format(small=0, big=True)),
        ("fit_batch", "511 x 100 + 1 x 1e6", BATCH.format(small=511, big=True)),
        ("cylinder", "exact cylinder 20k", CYLINDER.format(points=20_000)),
        ("cylinder", "exact cylinder 80k", CYLINDER.format(points=80_000)),
    ]
    if mug.is_file():
        out += [("mesh", "GraspIt mug 20k", MESH.format(path=str(mug), points=20_000)),
                ("mesh", "GraspIt mug 100k", MESH.format(path=str(mug), points=100_000))]
    else:
        print(f"skipping the mesh cases: no {mug}", file=sys.stderr)
    out += [
        ("iv", "USE doubling (60 levels)", BOMB.format(text=_doubling(60))),
        ("iv", "numVertices 3e9", BOMB.format(
            text="#Inventor V2.1 ascii\nFaceSet { numVertices [ 3000000000 ] }")),
        ("iv", "5,000 nested Separators", BOMB.format(
            text="#Inventor V2.1 ascii\n" + "Separator { " * 5000 + "Sphere { }"
            + " }" * 5000)),
    ]
    return out


def measure(code: str, cold: bool, timeout: float = 1800) -> dict:
    """Run one case's code in a fresh interpreter; its seconds, peak bytes and outcome."""
    env = dict(os.environ)
    with tempfile.TemporaryDirectory() as empty:
        if cold:
            env["JAXFIT_CACHE_DIR"] = empty
        started = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", PRELUDE + code + HARNESS], env=env,
                              capture_output=True, text=True, timeout=timeout)
        process = time.perf_counter() - started
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("RESULT ")]
    if done.returncode != 0 or not lines:
        tail = (done.stderr or done.stdout).strip().splitlines()[-3:]
        return {"error": f"exit {done.returncode}: " + " | ".join(tail), "process": process}
    return {**json.loads(lines[-1][len("RESULT "):]), "process": process}


def verdicts(rows: list[dict]) -> list[str]:
    """Each group's bound, checked against the measured figures."""
    by = {r["name"]: r for r in rows if "error" not in r}
    out = []

    def ratio(a, b, key):
        return by[a][key] / by[b][key]

    pairs = [("scene 100k + 20k coincident", "scene 100k", 2.0, "the scene alone")]
    for big, small, factor in (("exact cylinder 80k", "exact cylinder 20k", 4),
                               ("GraspIt mug 100k", "GraspIt mug 20k", 5)):
        if big in by and small in by:
            r = ratio(big, small, "seconds") / factor
            out.append(f"- {big}: {r:.2f}x the 20k time per point (bound 3x): "
                       f"{'met' if r <= 3 else 'NOT met'}")
    for a, b, bound, what in pairs:
        if a in by and b in by:
            for key in ("seconds", "peak_bytes"):
                r = ratio(a, b, key)
                out.append(f"- {a}: {key} {r:.2f}x {what} "
                           f"(bound {bound:g}x): {'met' if r <= bound else 'NOT met'}")
    together, parts = "511 x 100 + 1 x 1e6", ("511 x 100 (separate)", "1 x 1e6 (separate)")
    if together in by and all(p in by for p in parts):
        seconds = by[together]["seconds"] / sum(by[p]["seconds"] for p in parts)
        # Peak memory of the separate runs: the larger one (they do not run at once).
        peak = by[together]["peak_bytes"] / max(by[p]["peak_bytes"] for p in parts)
        out.append(f"- fit_batch together: {seconds:.2f}x the separate calls' time, "
                   f"{peak:.2f}x the larger one's peak (bound 1.5x): "
                   f"{'met' if max(seconds, peak) <= 1.5 else 'NOT met'}")
    for r in rows:
        if r["group"] == "iv" and "error" not in r:
            # Nesting has no limit to hit (the reader does not recurse): it must read.
            wanted = "read" if "nested" in r["name"] else "IVError"
            ok = r["seconds"] <= 1 and r["outcome"].startswith(wanted)
            out.append(f"- {r['name']}: {r['seconds']:.3f} s, {r['outcome'].split(':')[0]} "
                       f"(bound 1 s, {'read' if wanted == 'read' else 'a clear IVError'}): "
                       f"{'met' if ok else 'NOT met'}")
    return out


def markdown(rows: list[dict], cold: bool) -> str:
    lines = [f"# Robustness: peak memory and time ({'empty' if cold else 'warm'} "
             "compilation cache)", "",
             f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
             f"Python {platform.python_version()}. Command: "
             f"`python -m benchmarks.robustness{' --cold' if cold else ''}`. Peak RSS is the "
             "whole process's (Python and JAX included); time is the call alone; each "
             "case's fastest of the repeats (every run in the JSON).", "",
             "| case | call (s) | process (s) | peak RSS (MB) | outcome |",
             "|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['name']} | - | {r['process']:.1f} | - | {r['error']} |")
        else:
            lines.append(f"| {r['name']} | {r['seconds']:.2f} | {r['process']:.1f} | "
                         f"{r['peak_bytes'] / 1e6:.0f} | {r['outcome']} |")
    return "\n".join(lines + ["", "Bounds:", *verdicts(rows), ""])


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cold", action="store_true",
                        help="an empty compilation cache for every process")
    parser.add_argument("--only", nargs="*", help="run only the cases of these groups")
    parser.add_argument("--repeats", type=int, default=2,
                        help="passes over all cases; each case reports its fastest (2)")
    args = parser.parse_args()
    chosen = [c for c in cases() if not args.only or c[0] in args.only]
    runs: dict[str, list[dict]] = {name: [] for _, name, _ in chosen}
    for repeat in range(args.repeats):  # whole passes: a case's first process may trace
        for _group, name, code in chosen:
            run = measure(code, args.cold)
            runs[name].append(run)
            shown = run.get("error") or (f"{run['seconds']:.2f} s, "
                                         f"{run['peak_bytes'] / 1e6:.0f} MB: {run['outcome']}")
            print(f"[{repeat + 1}/{args.repeats}] {name}: {shown}", flush=True)
    rows = []
    for group, name, _ in chosen:
        done = [r for r in runs[name] if "error" not in r]
        if not done:
            rows.append({"group": group, "name": name, **runs[name][-1]})
            continue
        best = min(done, key=lambda r: r["seconds"])  # the least disturbed run
        rows.append({"group": group, "name": name, **best,
                     "all_seconds": [r["seconds"] for r in done],
                     "all_peak_bytes": [r["peak_bytes"] for r in done]})
    text = markdown(rows, args.cold)
    print(text)
    if not args.only:
        RESULTS.mkdir(exist_ok=True)
        stem = "robustness-cold" if args.cold else "robustness"
        (RESULTS / f"{stem}.json").write_text(json.dumps(rows, indent=1) + "\n")
        (RESULTS / f"{stem}.md").write_text(text)


if __name__ == "__main__":
    main()
