"""Cold start: whole-process wall time of "load a cloud, fit one sphere, print", and the
first-call compile time of each primitive.

Every measurement is a fresh interpreter (``subprocess``), timed from launch to exit (wall,
and CPU: user and system), on the same 10,000-point sphere cloud with 30 % outliers saved
as ``.npy``, beside a bare JAX process (``import jax; jax.numpy.zeros(1)``, the yardstick
of issue 18's goal):
- jaxfit from Python, first process (an empty compilation-cache folder: it compiles and
  fills the cache), second process (the folder the first one filled), and with the cache
  off (``JAXFIT_CACHE=0``);
- the jaxfit command line, ``python -m jaxfit fit CLOUD --shape sphere`` (the ``jaxfit``
  console script runs the same code; called through ``-m`` to leave pyenv's shim out),
  first and second process;
- pyRANSAC-3D (``pip install ".[bench]"``; skipped if missing): its default 1000
  iterations, and stopped by its callback at the confidence-0.99 count (as jaxfit stops);
- the NumPy reference loop (``jaxfit.evaluation.reference.ransac``). It imports jaxfit and so JAX.
The methods take turns within each repeat, so the machine's load affects them alike.

Then, per primitive, a fresh process fits a 2,000-point cloud twice and reports the first
and second call and JAX's own compile-phase durations (``jax.monitoring``), with the cache
off, first process (empty folder) and second process, and a first process fitting with
``refine=False, polish=True`` (LO on the host: no refinement program; its own empty
folder).

Then the README's ``jaxfit demo`` (``demo``): per turn a first process on an empty cache
folder and a second on the folder it filled, whole-process wall and CPU seconds (the
issue's goal: at most 8 s cold on the 2-core machine).

Then, per primitive, the programs of a cold first fit (each one's trace, lowering and
compile seconds from ``jax_log_compiles``), with the refinement compiled ahead in a thread
or in turn; each of those programs compiled again alone from the fit's own arguments
(``sizes``: process CPU per phase, the optimised program's size and LAPACK calls, its run
time); the kernel and the refinement compiled under other XLA CPU options (``options``:
compile CPU, run time, same bits or not); and ``jaxfit.warmup()`` in one and two threads.

Run: ``python -m benchmarks.coldstart [--repeats 5] [--sections process,first-call,...]``.
Writes ``benchmarks/results/coldstart.json``, ``coldstart.md`` and ``coldstart.png``
(sections not run keep their committed results).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from jaxfit.evaluation.synthetic import demo_cloud
from jaxfit.io.preview import pyplot

RESULTS = Path(__file__).resolve().parent / "results"
SHAPES = ("plane", "sphere", "cylinder", "cone", "box")
THRESHOLD = 0.01

JAXFIT_PY = """
import sys
import numpy as np
import jaxfit
points = np.load(sys.argv[1])
result = jaxfit.fit(points, "sphere", threshold={threshold})
print(result.model, result.num_inliers)
"""

PYRANSAC = """
import random, sys
import numpy as np
import pyransac3d
points = np.load(sys.argv[1])
random.seed(0)
adaptive = sys.argv[2] == "adaptive"

def stop(state):  # the confidence-0.99 count T for the best inlier share (sphere: k = 4)
    w = len(state["best_inliers"]) / len(points)
    needed = float("inf") if w <= 0 else (0.0 if w >= 1 else
                                          np.log(0.01) / np.log1p(-w ** 4))
    return adaptive and state["iteration"] + 1 >= needed

center, radius, inliers = pyransac3d.Sphere().fit(points, thresh={threshold},
                                                  maxIteration=1000, callback=stop)
print(center, radius, len(inliers))
"""

REFERENCE = """
import sys
import numpy as np
from jaxfit.evaluation import reference
points = np.load(sys.argv[1])
center = 0.5 * (points.min(axis=0) + points.max(axis=0))
scale = np.linalg.norm(points - center, axis=1).max()
out = reference.ransac((points - center) / scale, "sphere", threshold={threshold} / scale,
                       max_hypotheses=100_000, max_stall=20_000, seed=0)
print(out["theta"], out["num_inliers"])
"""

# First call of one primitive in a fresh process, with JAX's compile-phase durations.
FIRST_CALL = """
import collections, json, sys, time
import jax.monitoring
phases = collections.Counter()
jax.monitoring.register_event_duration_secs_listener(
    lambda name, secs, **_: phases.update({{name.rsplit("/", 1)[-1]: secs}}))
import jaxfit
from jaxfit.evaluation.synthetic import demo_cloud
points, _, _ = demo_cloud(sys.argv[1], count=2000, outlier_ratio=0.3, seed=0)
options = dict(refine=False, polish=True) if sys.argv[2:] == ["polish"] else {{}}
calls = []
for _ in range(2):
    start = time.perf_counter()
    jaxfit.fit(points, sys.argv[1], key=0, **options)
    calls.append(time.perf_counter() - start)
print(json.dumps({{"first": calls[0], "second": calls[1], **phases}}))
"""


# A first fit in a fresh process with an empty cache: each program JAX traced, lowered and
# compiled (jax_log_compiles' lines), with the refinement compiled ahead or not.
PROGRAMS = r"""
import json, logging, re, sys, threading, time
import jax
jax.config.update("jax_log_compiles", True)
lines = []
class Keep(logging.Handler):
    def emit(self, record):
        lines.append((threading.current_thread().name, record.getMessage()))
logging.getLogger("jax").addHandler(Keep())
logging.getLogger("jax").setLevel(logging.WARNING)
import jaxfit
import jaxfit.engine.loop as loop
from jaxfit.evaluation.synthetic import demo_cloud
loop.COMPILE_AHEAD = sys.argv[2] == "ahead"
points, _, _ = demo_cloud(sys.argv[1], count=2000, outlier_ratio=0.3, seed=0)
cpu, start = time.process_time(), time.perf_counter()
jaxfit.fit(points, sys.argv[1], key=0)
first, cpu = time.perf_counter() - start, time.process_time() - cpu
phase = {"Finished tracing": "trace", "Finished jaxpr to MLIR": "lower",
         "Finished XLA compilation": "compile"}
programs, last = [], {}
for thread, line in lines:
    kind = next((v for k, v in phase.items() if line.startswith(k)), None)
    if kind is None:
        continue
    name = re.search(r"(?:tracing |jit\()([\w<>.]+)", line).group(1)
    seconds = float(re.search(r"in ([0-9.e-]+) sec", line).group(1))
    if kind == "trace" and name != "call":
        last[thread] = name  # an exported program's call is named after the function
    label = last.get(thread, name) if name == "call" else name
    programs.append({"program": label, "phase": kind, "seconds": seconds, "thread": thread})
print(json.dumps({"first": first, "cpu": cpu, "programs": programs}))
"""


# The head of SIZES and OPTIONS: a first fit (refinement compiled in turn) whose stored
# programs' calls are kept in ``calls`` (name -> (program, args, kwargs)).
RECORDED = r"""
import json, re, statistics, sys, time
import jax
import numpy as np
import jaxfit
import jaxfit.engine.loop as loop
from jaxfit import _cache
from jaxfit.evaluation.synthetic import demo_cloud
loop.COMPILE_AHEAD = False
calls = {}
original = _cache.Stored.__call__
def record(self, *args, **kwargs):
    calls.setdefault(self.name, (self, args, kwargs))
    return original(self, *args, **kwargs)
_cache.Stored.__call__ = record
def first_fit(shape, count):
    points, _, _ = demo_cloud(shape, count=count, outlier_ratio=0.3, seed=0)
    jaxfit.fit(points, shape, key=0)
def dynamic(stored, args, kwargs):  # the arguments its compiled program takes
    return ([a for i, a in enumerate(args) if i not in stored.static_positions],
            {k: v for k, v in kwargs.items() if k not in stored.static_names})
"""


# Each stored program a first fit calls (cloud keys, kernel, refinement), compiled again
# alone with JAX's AOT API from the fit's own arguments: CPU seconds of each phase, the
# optimised program's size, its LAPACK calls and its run time. Cache off (every program
# is the plain jitted one), refinement compiled in turn.
SIZES = RECORDED + r"""
first_fit(sys.argv[1], 2000)
out = {}
for name, (stored, args, kwargs) in calls.items():
    jax.clear_caches()
    cpu = [time.process_time()]
    traced = stored.jitted.trace(*args, **kwargs); cpu.append(time.process_time())
    lowered = traced.lower(); cpu.append(time.process_time())
    compiled = lowered.compile(); cpu.append(time.process_time())
    text = compiled.as_text()
    dyn, dyn_kw = dynamic(stored, args, kwargs)
    jax.block_until_ready(compiled(*dyn, **dyn_kw))
    runs = []
    for _ in range(15):
        start = time.perf_counter()
        jax.block_until_ready(compiled(*dyn, **dyn_kw))
        runs.append(time.perf_counter() - start)
    out[name.rsplit(".", 1)[-1]] = {
        "trace": cpu[1] - cpu[0], "lower": cpu[2] - cpu[1], "compile": cpu[3] - cpu[2],
        "hlo_lines": text.count("\n"), "fusions": text.count(" fusion("),
        "lapack_calls": len(re.findall(r'custom_call_target="lapack', text)),
        "run_ms": 1e3 * statistics.median(runs)}
print(json.dumps(out))
"""


def _env(cache: str | None) -> dict:
    """The environment with jaxfit's cache in folder ``cache``, or off if None."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("JAXFIT_CACHE", "JAX_COMPILATION_CACHE"))}
    if cache is None:
        env["JAXFIT_CACHE"] = "0"
    else:
        env["JAXFIT_CACHE_DIR"] = cache
    return env


def wall(argv, env) -> tuple[float, str]:
    """Seconds from launch to exit of a fresh process, and its output."""
    seconds, _, out = timed(argv, env)
    return seconds, out


def timed(argv, env) -> tuple[float, float, str]:
    """Wall seconds from launch to exit of a fresh process, its CPU seconds (user and
    system, children included), and its output."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=600)
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"{argv[:3]} failed:\n{proc.stderr}")
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    return seconds, cpu, proc.stdout


def has_pyransac() -> bool:
    import importlib.util

    return importlib.util.find_spec("pyransac3d") is not None


#: The whole-process goal's yardstick (issue 18): a bare JAX process.
BARE_JAX = "bare JAX: import jax; jax.numpy.zeros(1)"


def whole_process(cloud: Path, work: Path, repeats: int
                  ) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """Each method's wall and CPU times over ``repeats`` turns; cold runs get an empty
    folder."""
    py = sys.executable
    script = {"jaxfit": JAXFIT_PY, "pyransac": PYRANSAC, "reference": REFERENCE}
    script = {k: v.format(threshold=THRESHOLD) for k, v in script.items()}
    cli = [py, "-m", "jaxfit", "fit", str(cloud), "--shape", "sphere",
           "--threshold", str(THRESHOLD)]
    times: dict[str, list[float]] = {}
    cpus: dict[str, list[float]] = {}
    for turn in range(repeats):
        py_cache, cli_cache = str(work / f"py-{turn}"), str(work / f"cli-{turn}")
        runs = [  # (label, argv, cache folder): a "second" run reuses its turn's "first"
            (BARE_JAX, [py, "-c", "import jax; jax.numpy.zeros(1)"], None),
            ("jaxfit Python, first process (empty cache)", [py, "-c", script["jaxfit"],
                                                            str(cloud)], py_cache),
            ("jaxfit Python, second process (warm cache)", [py, "-c", script["jaxfit"],
                                                            str(cloud)], py_cache),
            ("jaxfit Python, cache off", [py, "-c", script["jaxfit"], str(cloud)], None),
            ("jaxfit CLI, first process (empty cache)", cli, cli_cache),
            ("jaxfit CLI, second process (warm cache)", cli, cli_cache),
            ("NumPy reference loop", [py, "-c", script["reference"], str(cloud)], None),
        ]
        if has_pyransac():
            runs += [("pyRANSAC-3D, 1000 iterations", [py, "-c", script["pyransac"],
                                                       str(cloud), "fixed"], None),
                     ("pyRANSAC-3D, adaptive stop", [py, "-c", script["pyransac"],
                                                     str(cloud), "adaptive"], None)]
        for label, argv, cache in runs:
            seconds, cpu, _ = timed(argv, _env(cache))
            times.setdefault(label, []).append(seconds)
            cpus.setdefault(label, []).append(cpu)
        print(f"turn {turn}: " + ", ".join(f"{k.split(',')[0]} {v[-1]:.2f}"
                                           for k, v in times.items()), flush=True)
    return times, cpus


def demo_runs(work: Path, repeats: int) -> dict[str, dict[str, list[float]]]:
    """The README's ``jaxfit demo`` (a decomposition of the built-in mallet, its files
    written) as whole processes: per turn a first process on an empty cache folder, then
    a second on the same folder; wall and CPU seconds of each."""
    runs: dict[str, dict[str, list[float]]] = {}
    for turn in range(repeats):
        cache, out = str(work / f"demo-{turn}"), str(work / f"demo-out-{turn}")
        for label in ("first process (empty cache)", "second process (warm cache)"):
            seconds, cpu, _ = timed([sys.executable, "-m", "jaxfit", "demo", "--out", out],
                                    _env(cache))
            runs.setdefault(label, {"wall": [], "cpu": []})
            runs[label]["wall"].append(seconds)
            runs[label]["cpu"].append(cpu)
        print(f"demo turn {turn}: " + ", ".join(f"{k.split(' (')[0]} {v['wall'][-1]:.2f} s"
                                                 for k, v in runs.items()), flush=True)
    return runs


def demo_table(runs) -> str:
    lines = ["| `jaxfit demo` | median s | min s | max s | CPU s (median) | runs |",
             "|---|---|---|---|---|---|"]
    for label, r in runs.items():
        lines.append(f"| {label} | {statistics.median(r['wall']):.2f} | {min(r['wall']):.2f} "
                     f"| {max(r['wall']):.2f} | {statistics.median(r['cpu']):.2f} "
                     f"| {len(r['wall'])} |")
    return "\n".join(lines)


def first_calls(work: Path, repeats: int) -> list[dict]:
    """Per primitive and cache state, medians of the first and second fit in a process."""
    rows = []
    for shape in SHAPES:
        samples: dict[str, list[dict]] = {}
        for turn in range(repeats):
            folder = str(work / f"first-{shape}-{turn}")
            for state, cache, extra in (("cache off", None, []),
                                        ("first process", folder, []),
                                        ("second process", folder, []),
                                        ("first process, polish", folder + "-polish",
                                         ["polish"])):
                _, out = wall([sys.executable, "-c", FIRST_CALL.format(), shape, *extra],
                              _env(cache))
                samples.setdefault(state, []).append(json.loads(out.strip().splitlines()[-1]))
        for state, runs in samples.items():
            keys = sorted(set().union(*runs))
            row = {"shape": shape, "cache": state, "runs": len(runs)}
            row.update({k: statistics.median(r.get(k, 0.0) for r in runs) for k in keys})
            rows.append(row)
        print(f"{shape}: " + ", ".join(f"{r['cache']} {r['first']:.2f} s" for r in rows
                                       if r["shape"] == shape), flush=True)
    return rows


def program_costs(work: Path, repeats: int) -> list[dict]:
    """Per primitive, a first fit in a fresh process with an empty cache, the refinement
    compiled ahead (in a thread, ``loop.COMPILE_AHEAD``) or not, taking turns: wall and
    CPU seconds, and each program's trace, lowering and compile seconds (medians)."""
    rows = []
    for shape in SHAPES:
        runs: dict[str, list[dict]] = {}
        for turn in range(repeats):
            for mode in ("ahead", "in turn"):
                folder = str(work / f"programs-{shape}-{mode.replace(' ', '')}-{turn}")
                _, out = wall([sys.executable, "-c", PROGRAMS, shape,
                               "ahead" if mode == "ahead" else "serial"], _env(folder))
                runs.setdefault(mode, []).append(json.loads(out.strip().splitlines()[-1]))
        for mode, found in runs.items():
            per: dict[tuple, list[float]] = {}
            for run in found:  # (an exported program is traced and lowered twice: summed)
                sums: dict[tuple, float] = {}
                for p in run["programs"]:
                    key = (p["program"], p["phase"])
                    sums[key] = sums.get(key, 0.0) + p["seconds"]
                for key, seconds in sums.items():
                    per.setdefault(key, []).append(seconds)
            compiled = [len([p for p in r["programs"] if p["phase"] == "compile"])
                        for r in found]
            rows.append({
                "shape": shape, "refinement": mode, "runs": len(found),
                "first": statistics.median(r["first"] for r in found),
                "cpu": statistics.median(r["cpu"] for r in found),
                "programs_compiled": statistics.median(compiled),
                "phases": {f"{name} {phase}": statistics.median(v)
                           for (name, phase), v in per.items()},
            })
        print(f"{shape}: " + ", ".join(f"{r['refinement']} {r['first']:.2f} s"
                                       for r in rows if r["shape"] == shape), flush=True)
    return rows


def program_sizes(repeats: int) -> list[dict]:
    """Per primitive, each program of a first fit compiled alone (``SIZES``), in a fresh
    process with the cache off: medians over ``repeats`` processes."""
    rows = []
    for shape in SHAPES:
        found = []
        for _ in range(repeats):
            _, out = wall([sys.executable, "-c", SIZES, shape], _env(None))
            found.append(json.loads(out.strip().splitlines()[-1]))
        for program in found[0]:
            rows.append({"shape": shape, "program": program, "runs": len(found),
                         **{k: statistics.median(f[program][k] for f in found)
                            for k in found[0][program]}})
        print(f"{shape}: " + ", ".join(f"{r['program']} {r['compile']:.2f} s"
                                       for r in rows if r["shape"] == shape), flush=True)
    return rows


def sizes_table(rows) -> str:
    lines = ["| shape | program | trace CPU s | lower CPU s | XLA compile CPU s | HLO lines "
             "| fusions | LAPACK calls | run ms |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['shape']} | `{r['program']}` | {r['trace']:.2f} | {r['lower']:.2f} "
                     f"| {r['compile']:.2f} | {r['hlo_lines']:g} | {r['fusions']:g} "
                     f"| {r['lapack_calls']:g} | {r['run_ms']:.2f} |")
    return "\n".join(lines)


# The kernel and the refinement of a first fit compiled again alone, under the XLA CPU
# option sets of OPTION_VARIANTS added to each program's own options (backend.py), in
# turn and in one process: compile CPU s, median run ms, and whether the outputs are
# bit for bit those of the program's own options.
OPTIONS = RECORDED + r"""
shape, count, variants = sys.argv[1], int(sys.argv[2]), json.loads(sys.argv[3])
first_fit(shape, count)
out = {}
for name, (stored, args, kwargs) in calls.items():
    if "seed_keys" in name:
        continue
    dyn, dyn_kw = dynamic(stored, args, kwargs)
    compiled, reference = {}, None
    for label, extra in variants.items():
        jax.clear_caches()
        lowered = stored.jitted.trace(*args, **kwargs).lower()
        cpu = time.process_time()
        compiled[label] = lowered.compile(compiler_options={**stored.options, **extra})
        cpu = time.process_time() - cpu
        leaves = [np.asarray(a) for a in jax.tree_util.tree_leaves(
            jax.block_until_ready(compiled[label](*dyn, **dyn_kw)))]
        reference = leaves if reference is None else reference
        same = all(np.array_equal(a, b, equal_nan=True) for a, b in zip(leaves, reference))
        out.setdefault(name.rsplit(".", 1)[-1], {})[label] = {"compile": cpu, "same": same,
                                                               "runs": []}
    for _ in range(20):  # the variants take turns
        for label, program in compiled.items():
            start = time.perf_counter()
            jax.block_until_ready(program(*dyn, **dyn_kw))
            out[name.rsplit(".", 1)[-1]][label]["runs"].append(time.perf_counter() - start)
for programs in out.values():
    for row in programs.values():
        row["run_ms"] = 1e3 * statistics.median(row.pop("runs"))
print(json.dumps(out))
"""
#: Option sets added to a program's own XLA CPU options (``backend.CPU_OPTIONS`` for the
#: kernel, ``backend.REFINE_OPTIONS`` for the refinement); the first is the reference.
OPTION_VARIANTS = {
    "own": {},
    "fusion emitters": {"xla_cpu_use_fusion_emitters": True},
    "loop emitters": {"xla_cpu_use_fusion_emitters": False},
    "loop emitters, LLVM level 1": {"xla_cpu_use_fusion_emitters": False,
                                    "xla_backend_optimization_level": 1},
}
OPTION_POINTS = (2000, 50000)


def option_costs(repeats: int) -> list[dict]:
    """Per primitive and cloud size (``OPTION_POINTS``), the kernel and the refinement
    compiled under each of ``OPTION_VARIANTS`` (``OPTIONS``) in a fresh process with the
    cache off: medians over ``repeats`` processes."""
    rows = []
    for shape in SHAPES:
        for count in OPTION_POINTS:
            found = []
            for _ in range(repeats):
                _, out = wall([sys.executable, "-c", OPTIONS, shape, str(count),
                               json.dumps(OPTION_VARIANTS)], _env(None))
                found.append(json.loads(out.strip().splitlines()[-1]))
            for program, variants in found[0].items():
                for label in variants:
                    cells = [f[program][label] for f in found]
                    rows.append({"shape": shape, "points": count, "program": program,
                                 "options": label, "runs": len(found),
                                 "compile": statistics.median(c["compile"] for c in cells),
                                 "run_ms": statistics.median(c["run_ms"] for c in cells),
                                 "same": all(c["same"] for c in cells)})
            print(f"{shape} {count}: " + ", ".join(
                f"{r['program']} {r['options']} {r['compile']:.2f} s" for r in rows
                if r["shape"] == shape and r["points"] == count), flush=True)
    return rows


def options_table(rows) -> str:
    labels = list(dict.fromkeys(r["options"] for r in rows))
    lines = ["| shape | points | program | " + " | ".join(
                 f"{label}: compile CPU s / run ms" for label in labels) + " |",
             "|---|---|---|" + "---|" * len(labels)]
    cells: dict = {}
    for r in rows:
        mark = "" if r["same"] else " (other bits)"
        cells.setdefault((r["shape"], r["points"], r["program"]), {})[r["options"]] = \
            f"{r['compile']:.2f} / {r['run_ms']:.2f}{mark}"
    for (shape, points, program), by_label in cells.items():
        lines.append(f"| {shape} | {points:,} | `{program}` | "
                     + " | ".join(by_label.get(label, "") for label in labels) + " |")
    return "\n".join(lines)

WARMUP = """
import json, sys, time
cpu, start = time.process_time(), time.perf_counter()
from jaxfit.warmup import warmup
jobs = warmup(workers=int(sys.argv[1]))
print(json.dumps({"wall": time.perf_counter() - start, "cpu": time.process_time() - cpu,
                  "jobs": jobs}))
"""


def warmup_costs(work: Path, repeats: int) -> list[dict]:
    """``jaxfit.warmup()`` (every shape, the default buckets) in a fresh process with an
    empty cache, in 1 and 2 threads taking turns, and then again with the cache it filled."""
    rows = []
    for turn in range(repeats):
        for workers in (1, 2):
            folder = str(work / f"warmup-{workers}-{turn}")
            for state in ("empty cache", "warm cache"):
                _, out = wall([sys.executable, "-c", WARMUP, str(workers)], _env(folder))
                rows.append({"workers": workers, "cache": state,
                             **json.loads(out.strip().splitlines()[-1])})
        print(f"warmup turn {turn}: " + ", ".join(f"{r['workers']} {r['cache']} "
                                                  f"{r['wall']:.1f} s" for r in rows[-4:]),
              flush=True)
    return rows


# ----- tables and plot ----------------------------------------------------------------


def program_table(rows) -> str:
    lines = ["| shape | refinement compiled | first fit s | CPU s | programs compiled "
             "| kernel trace / lower / compile s | refinement trace / lower / compile s |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        def three(name, ph=r["phases"]):
            return " / ".join(f"{ph.get(f'{name} {k}', 0):.2f}"
                              for k in ("trace", "lower", "compile"))
        lines.append(f"| {r['shape']} | {r['refinement']} | {r['first']:.2f} | {r['cpu']:.2f} "
                     f"| {r['programs_compiled']:g} | {three('_batch_best_many')} "
                     f"| {three('_refine_many')} |")
    return "\n".join(lines)


def warmup_table(rows) -> str:
    lines = ["| threads | cache | median wall s | median CPU s | runs |", "|---|---|---|---|---|"]
    for workers in (1, 2):
        for state in ("empty cache", "warm cache"):
            sel = [r for r in rows if r["workers"] == workers and r["cache"] == state]
            if sel:
                lines.append(f"| {workers} | {state} "
                             f"| {statistics.median(r['wall'] for r in sel):.2f} "
                             f"| {statistics.median(r['cpu'] for r in sel):.2f} | {len(sel)} |")
    return "\n".join(lines)


def process_table(times, cpus=None) -> str:
    """Whole-process rows: wall medians, their spread and ratios (to pyRANSAC-3D, and to
    bare JAX where it was run), and CPU medians where they were measured."""
    cpus = cpus or {}
    base = statistics.median(times.get("pyRANSAC-3D, 1000 iterations", [np.nan]))
    bare = statistics.median(times.get(BARE_JAX, [np.nan]))
    bare_cpu = statistics.median(cpus.get(BARE_JAX, [np.nan]))
    lines = ["| process: load .npy, fit one sphere, print | median s | min s | max s "
             "| ÷ pyRANSAC-3D (1000 it) | ÷ bare JAX | CPU s | CPU ÷ bare JAX |",
             "|---|---|---|---|---|---|---|---|"]
    for label, t in times.items():
        med = statistics.median(t)
        cpu = statistics.median(cpus[label]) if label in cpus else np.nan
        lines.append(f"| {label} | {med:.2f} | {min(t):.2f} | {max(t):.2f} | {med / base:.2f} "
                     f"| {med / bare:.2f} | {cpu:.2f} | {cpu / bare_cpu:.2f} |")
    return "\n".join(lines)


def first_call_table(rows) -> str:
    lines = ["| shape | cache | first fit s | second fit s | first − second s | trace s "
             "| lower to MLIR s | XLA compile or cache load s | of which cache read s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['shape']} | {r['cache']} | {r['first']:.2f} | {r['second']:.3f} "
            f"| {r['first'] - r['second']:.2f} | {r.get('jaxpr_trace_duration', 0):.2f} "
            f"| {r.get('jaxpr_to_mlir_module_duration', 0):.2f} "
            f"| {r.get('backend_compile_duration', 0):.2f} "
            f"| {r.get('cache_retrieval_time_sec', 0):.2f} |")
    return "\n".join(lines)


def plot(times, rows, path):
    plt = pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.2))
    labels = list(times)
    meds = [statistics.median(times[k]) for k in labels]
    left.barh(range(len(labels)), meds, color="tab:blue")
    for i, k in enumerate(labels):
        left.plot(times[k], [i] * len(times[k]), "k.", ms=4)
    left.set_yticks(range(len(labels)), labels, fontsize=8)
    left.invert_yaxis()
    left.set_xlabel("whole-process wall time (s); dots: repeats")
    left.set_title("load a 10k-point cloud, fit one sphere, print", fontsize=10)
    states = [s for s in ("cache off", "first process", "first process, polish",
                          "second process") if any(r["cache"] == s for r in rows)]
    width = 0.8 / len(states)
    for j, state in enumerate(states):
        vals = [next(r["first"] for r in rows if r["shape"] == s and r["cache"] == state)
                for s in SHAPES]
        right.bar(np.arange(len(SHAPES)) + (j - (len(states) - 1) / 2) * width, vals, width,
                  label=state)
    right.set_xticks(range(len(SHAPES)), SHAPES)
    right.set_ylabel("first fit in the process (s)")
    right.set_title("first-call time per primitive (2,000 points)", fontsize=10)
    right.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    print(f"wrote {path}")


SECTIONS = ("process", "first-call", "demo", "programs", "sizes", "options", "warmup")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="turns per method (5)")
    parser.add_argument("--first-call-repeats", type=int, default=3,
                        help="turns of every section but process: first-call, demo, "
                             "programs, sizes, options, warmup (3)")
    parser.add_argument("--sections", default=",".join(SECTIONS),
                        help="comma-separated among " + ", ".join(SECTIONS) + " (all); the "
                        "others keep their results from the committed JSON")
    args = parser.parse_args(argv)
    sections = args.sections.split(",")
    if unknown := set(sections) - set(SECTIONS):
        parser.error(f"unknown sections {sorted(unknown)}; expected among {SECTIONS}")
    path = RESULTS / "coldstart.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    load_before = os.getloadavg()[0]  # (the 2-core machine is shared: say how busy it was)
    work = Path(tempfile.mkdtemp(prefix="jaxfit-coldstart-"))
    try:
        if "process" in sections:
            points, _, _ = demo_cloud("sphere", count=10_000, outlier_ratio=0.3, seed=0)
            cloud = work / "sphere.npy"
            np.save(cloud, points)
            if not has_pyransac():
                print("pyRANSAC-3D is not installed (pip install '.[bench]'): its rows are "
                      "skipped")
            results["whole_process_seconds"], results["whole_process_cpu_seconds"] = \
                whole_process(cloud, work, args.repeats)
        if "first-call" in sections:
            results["first_call"] = first_calls(work, args.first_call_repeats)
        if "demo" in sections:
            results["demo"] = demo_runs(work, args.first_call_repeats)
        if "programs" in sections:
            results["programs"] = program_costs(work, args.first_call_repeats)
        if "sizes" in sections:
            results["sizes"] = program_sizes(args.first_call_repeats)
        if "options" in sections:
            results["options"] = option_costs(args.first_call_repeats)
        if "warmup" in sections:
            results["warmup"] = warmup_costs(work, args.first_call_repeats)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    import jax

    meta = results.get("meta", {})
    meta.update({"machine": platform.processor() or platform.machine(), "jax": jax.__version__,
                 "cpus": os.cpu_count(), "python": platform.python_version(),
                 "cloud": "sphere, 10,000 points, 30 % outliers, .npy",
                 "threshold": THRESHOLD,
                 "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)]})
    meta.setdefault("repeats_by_section", {}).update(
        {name: args.repeats if name == "process" else args.first_call_repeats
         for name in sections})
    results["meta"] = meta
    RESULTS.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=2))
    parts = []
    if "whole_process_seconds" in results:
        parts += ["## Whole process (median of repeats)",
                  process_table(results["whole_process_seconds"],
                                results.get("whole_process_cpu_seconds"))]
    if "first_call" in results:
        parts += ["## First call per primitive (fresh process, medians)",
                  first_call_table(results["first_call"])]
    if "demo" in results:
        parts += ["## The README's `jaxfit demo` (fresh processes, whole-process times)",
                  demo_table(results["demo"])]
    if "programs" in results:
        parts += ["## Programs of a first fit (fresh process, empty cache, 2,000 points, "
                  "medians): the refinement compiled ahead in a thread, or in turn",
                  program_table(results["programs"])]
    if "sizes" in results:
        parts += ["## Each program of a first fit compiled alone (AOT, cache off, 2,000 points, "
                  "process CPU, medians)", sizes_table(results["sizes"])]
    if "options" in results:
        parts += ["## The kernel and the refinement under XLA CPU option sets (AOT, cache off, "
                  "process CPU, medians; `own`: the options jaxfit compiles them with; "
                  "\"other bits\": outputs differ from `own`'s)",
                  options_table(results["options"])]
    if "warmup" in results:
        parts += ["## `jaxfit.warmup()`: every shape at the default buckets (fresh process)",
                  warmup_table(results["warmup"])]
    md = "\n\n".join(parts)
    (RESULTS / "coldstart.md").write_text(md + "\n")
    print(md)
    if "whole_process_seconds" in results and "first_call" in results:
        plot(results["whole_process_seconds"], results["first_call"],
             RESULTS / "coldstart.png")


if __name__ == "__main__":
    main()
