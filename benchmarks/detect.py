"""jaxfit.detect on synthetic scenes and on the Fit4CAD scans PC33 and PC21.

    python -m benchmarks.detect            # the tables below
    python -m benchmarks.detect --cgal     # side by side with CGAL (cgal.md, cgal.json)

Synthetic: 20 scenes (floor + 2-5 of sphere, standing / lying cylinder, cone; 3000
points), each true primitive matched to the detection sharing most of its points;
precision and recall of that detection. Real: the Fit4CAD point clouds from
``../shared/data/fit4cad`` (per-primitive ground-truth point indices in the
``_primitives`` files), scored the same way and drawn as coloured points (truth left,
detection right) to benchmarks/results/detect/*.png, with summary.md and results.json.

``--cgal``: the scenes of ``benchmarks.peers`` alone (its five ~22k-point synthetic
scenes with 10 % outliers and the two Fit4CAD scans), jaxfit.detect (its own normals, and
given CGAL's) and CGAL's efficient_RANSAC interleaved in one process, ``--repeats`` timed
warm runs each, the medians kept, written to benchmarks/results/detect/cgal.{md,json}
(peers.py has no option that runs its scenes only; this uses its generator, CGAL call
and scoring).
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import time
from pathlib import Path

import numpy as np

import jaxfit
from jaxfit.evaluation.synthetic import scene
from jaxfit.io.preview import pyplot

OUT = Path(__file__).resolve().parent / "results" / "detect"
DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "fit4cad"
KINDS = ("sphere", "cylinder", "lying_cylinder", "cone")
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def load_fit4cad(name: str):
    """Points (N, 3), ground-truth point indices (0-based) per primitive and the
    primitives' type names of the Fit4CAD cloud ``name`` (e.g. "PC33")."""
    text = (DATA / f"{name}.txt").read_text()
    points = np.array(re.findall(_NUMBER, text), float).reshape(-1, 3)
    groups = re.findall(r"Primitive\d+\s*:=\s*\[([^\]]*)\]",
                        (DATA / f"{name}_primitives.txt").read_text())
    truth = [np.array(g.split(), int) - 1 for g in groups]
    kinds = re.findall(r":=\s*\[\s*(\w+)", (DATA / f"{name}_implicit.txt").read_text())
    return points, truth, [k.lower() for k in kinds]


def match(truth, scene_result):
    """Per true primitive (index array): the detection with the largest overlap, its
    shape, precision and recall."""
    rows = []
    for t, members in enumerate(truth):
        overlaps = [len(np.intersect1d(members, d.indices)) for d in scene_result.shapes]
        if not overlaps or max(overlaps) == 0:
            rows.append({"truth": t, "detection": None, "precision": 0.0, "recall": 0.0})
            continue
        best = int(np.argmax(overlaps))
        d = scene_result.shapes[best]
        rows.append({"truth": t, "detection": best, "shape": d.shape,
                     "precision": overlaps[best] / len(d.indices),
                     "recall": overlaps[best] / len(members)})
    return rows


def synthetic(count: int = 5):
    rows = []
    for n_objects in (2, 3, 4, 5):
        for i in range(count):
            seed = 100 * n_objects + i
            kinds = [KINDS[j] for j in np.random.default_rng(seed).integers(0, 4, n_objects)]
            points, models, labels = scene(seed, objects=kinds, count=3000)
            start = time.perf_counter()
            result = jaxfit.detect(points, key=i)
            seconds = time.perf_counter() - start
            truth = [np.flatnonzero(labels == t) for t in range(len(models))]
            matched = match(truth, result)
            types_ok = all(m.get("shape") == models[m["truth"]].name for m in matched)
            rows.append({
                "seed": seed, "objects": kinds, "primitives": len(models),
                "detected": len(result.shapes), "types_ok": types_ok, "seconds": seconds,
                "min_precision": min(m["precision"] for m in matched),
                "min_recall": min(m["recall"] for m in matched),
            })
            print(rows[-1], flush=True)
    return rows


def _palette(n):
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return [cmap(i % 10) for i in range(n)]


def shared_colours(truth_labels, labels) -> list[int]:
    """Palette index per detection: that of the true primitive most of its points belong
    to, so a primitive and its detection share a colour (largest detections choose
    first); a detection whose primitive is already taken, or that covers none, gets a
    colour after the truth's."""
    n_truth = max(truth_labels.max() + 1, 0)
    out, taken, fresh = [0] * max(labels.max() + 1, 0), set(), n_truth
    for j in sorted(range(len(out)), key=lambda j: -np.sum(labels == j)):
        owners = truth_labels[(labels == j) & (truth_labels >= 0)]
        t = int(np.bincount(owners).argmax()) if len(owners) else -1
        if t >= 0 and t not in taken:
            out[j] = t
            taken.add(t)
        else:
            out[j], fresh = fresh, fresh + 1
    return out


def draw(points, truth_labels, labels, names, title, path):
    """Two 3-D scatter plots side by side: truth and detection (grey: unassigned), a
    detection in the colour of the true primitive it mostly covers."""
    plt = pyplot()

    fig = plt.figure(figsize=(12, 6))
    detection_colours = shared_colours(truth_labels, labels)
    palette = _palette(max([truth_labels.max() + 1, *[c + 1 for c in detection_colours]]))
    for col, (lab, heading) in enumerate([(truth_labels, "ground truth"),
                                          (labels, "jaxfit.detect")]):
        ax = fig.add_subplot(1, 2, col + 1, projection="3d")
        grey = lab < 0
        ax.scatter(*points[grey].T, s=2, c="lightgrey")
        for j in range(lab.max() + 1):
            sel = lab == j
            name = names[col][j] if j < len(names[col]) else str(j)
            colour = palette[j if col == 0 else detection_colours[j]]
            ax.scatter(*points[sel].T, s=3, color=colour, label=f"{j}: {name}")
        ax.set_title(f"{title}: {heading}")
        ax.legend(loc="upper left", fontsize=7, markerscale=3)
        ax.set_box_aspect(np.ptp(points, axis=0))
        ax.view_init(elev=25, azim=-60)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def real(name: str):
    OUT.mkdir(parents=True, exist_ok=True)
    points, truth, kinds = load_fit4cad(name)
    start = time.perf_counter()
    result = jaxfit.detect(points, progress=True)
    seconds = time.perf_counter() - start
    matched = match(truth, result)
    truth_labels = np.full(len(points), -1)
    for t, members in enumerate(truth):
        truth_labels[members] = t
    names = [kinds, [d.shape for d in result.shapes]]
    draw(points, truth_labels, result.labels(), names, name, OUT / f"{name}.png")
    row = {"cloud": name, "points": len(points), "seconds": seconds,
           "detections": [{"shape": d.shape, "points": len(d.indices),
                           "model": d.model.to_dict()} for d in result.shapes],
           "unassigned": len(result.unassigned),
           "truth": [{"type": k, "points": len(m), **r}
                     for k, m, r in zip(kinds, truth, matched, strict=True)]}
    print(json.dumps(row["truth"]), flush=True)
    return row


def _markdown(synthetic_rows, real_rows):
    ok = sum(r["types_ok"] and r["min_precision"] >= 0.9 and r["min_recall"] >= 0.9
             and r["detected"] == r["primitives"] for r in synthetic_rows)
    lines = ["# jaxfit.detect", "",
             f"Synthetic scenes (3000 points, floor + 2-5 objects): {ok} of "
             f"{len(synthetic_rows)} with every primitive found, of the right type, with "
             "precision and recall >= 90 %.", "",
             "| seed | objects | primitives | detected | types right | min precision | "
             "min recall | s |", "|---|---|---|---|---|---|---|---|"]
    for r in synthetic_rows:
        lines.append(f"| {r['seed']} | {', '.join(r['objects'])} | {r['primitives']} | "
                     f"{r['detected']} | {r['types_ok']} | {r['min_precision']:.3f} | "
                     f"{r['min_recall']:.3f} | {r['seconds']:.2f} |")
    for r in real_rows:
        lines += ["", f"## Fit4CAD {r['cloud']} ({r['points']} points, {r['seconds']:.1f} s, "
                  f"{r['unassigned']} unassigned)", "", f"![{r['cloud']}]({r['cloud']}.png)", "",
                  "| true primitive | points | matched detection | precision | recall |",
                  "|---|---|---|---|---|"]
        for t in r["truth"]:
            det = "none" if t["detection"] is None else f"{t['detection']}: {t['shape']}"
            lines.append(f"| {t['type']} | {t['points']} | {det} | {t['precision']:.3f} | "
                         f"{t['recall']:.3f} |")
    return "\n".join(lines) + "\n"


def _clouds():
    """(name, points, truth indices, truth types) of benchmarks.peers' scenes: its
    ``SCENES`` synthetic ones and the Fit4CAD scans found in DATA."""
    from benchmarks import peers

    for seed in range(peers.SCENES):
        points, truth, kinds, objects = peers.synthetic_scene(seed)
        yield f"synthetic {seed} ({objects})", points, truth, kinds
    for name in ("PC33", "PC21"):
        if (DATA / f"{name}.txt").exists():
            yield (f"Fit4CAD {name}", *load_fit4cad(name))
        else:
            print(f"Fit4CAD {name} skipped: not found in {DATA}", flush=True)


def _side_row(name, points, truth, kinds, repeats: int) -> dict:
    """One scene: jaxfit.detect with its own normals (as benchmarks.peers times it),
    jaxfit.detect given CGAL's normals, and CGAL with peers' matched parameters; each
    warm, then ``repeats`` interleaved timed runs (median wall and CPU seconds)."""
    from types import SimpleNamespace

    from benchmarks import peers
    from jaxfit.engine.cloud import default_threshold

    threshold = default_threshold(np.ptp(points, axis=0))  # detect's default
    spacing = peers.median_spacing(points)
    normals = peers.o3d_normals(points)
    point_set = peers.cgal_point_set(points, normals)
    runs = {
        "jaxfit": lambda: jaxfit.detect(points, key=0),
        "jaxfit_given_normals": lambda: jaxfit.detect(points, normals=normals, key=0),
        "cgal": lambda: peers.cgal_detect(
            point_set, len(points), ("plane", "sphere", "cylinder", "cone"), threshold,
            4.0 * spacing, 0.01 * len(points), normal_threshold=np.cos(np.radians(30.0))),
    }
    results = {m: run() for m, run in runs.items()}  # warm
    wall, cpu = {m: [] for m in runs}, {m: [] for m in runs}
    for _ in range(repeats):
        for m, run in runs.items():
            start, start_cpu = time.perf_counter(), time.process_time()
            run()
            wall[m].append(time.perf_counter() - start)
            cpu[m].append(time.process_time() - start_cpu)
    lines, labels = results.pop("cgal")
    labels = labels()
    results["cgal"] = SimpleNamespace(shapes=[
        SimpleNamespace(shape=peers.parse_cgal(line)[0], indices=np.flatnonzero(labels == j))
        for j, line in enumerate(lines)])
    row = {"scene": name, "points": len(points), "primitives": len(truth), "methods": {}}
    for m in runs:
        row["methods"][m] = {"s": float(np.median(wall[m])), "cpu_s": float(np.median(cpu[m])),
                             "detected": len(results[m].shapes),
                             "found": peers.found_count(truth, kinds, results[m].shapes)}
    return row


def side_by_side(repeats: int) -> None:
    """jaxfit.detect and CGAL on benchmarks.peers' scenes, interleaved in one run, to
    cgal.md and cgal.json."""
    from benchmarks import peers

    if "cgal" not in peers.available():
        raise SystemExit("CGAL (with Open3D for its normals) is needed for --cgal")
    start = time.perf_counter()
    rows = []
    for cloud in _clouds():
        rows.append(_side_row(*cloud, repeats))
        print(json.dumps(rows[-1]), flush=True)
    meta = {"machine": f"{platform.machine()}, {peers._cores()} cores",
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "seconds": time.perf_counter() - start, "repeats": repeats}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "cgal.json").write_text(json.dumps({"meta": meta, "scenes": rows}, indent=1))
    (OUT / "cgal.md").write_text(_side_markdown(rows, meta))
    print((OUT / "cgal.md").read_text())


def _side_markdown(rows, meta) -> str:
    truth = sum(r["primitives"] for r in rows)
    names = {"jaxfit": "jaxfit", "jaxfit_given_normals": "jaxfit, CGAL's normals",
             "cgal": "CGAL"}
    summary = []
    for m in ("jaxfit", "jaxfit_given_normals"):
        ratios = [r["methods"][m]["s"] / r["methods"]["cgal"]["s"] for r in rows]
        summary.append(f"{names[m]} / CGAL wall time {min(ratios):.2f}-{max(ratios):.2f} "
                       f"(median {np.median(ratios):.2f})")
    found = ", ".join(f"{names[m]} {sum(r['methods'][m]['found'] for r in rows)}"
                      for m in names)
    lines = [
        "# jaxfit.detect vs CGAL efficient_RANSAC, side by side", "",
        f"`python -m benchmarks.detect --cgal --repeats {meta['repeats']}` on "
        f"{meta['machine']} ({meta['date']}, {meta['seconds']:.0f} s): the scenes of "
        "`benchmarks.peers` (five ~22k-point synthetic floor scenes with 10 % outliers, "
        "the Fit4CAD scans PC33 and PC21), each method warm, then "
        f"{meta['repeats']} interleaved timed runs; medians of wall and process CPU "
        "seconds. CGAL gets Open3D's normals (16 neighbours), estimated outside its "
        "time, with peers' matched parameters; \"jaxfit\" estimates its own normals "
        "inside its time (as `benchmarks.peers` times it); \"jaxfit, CGAL's normals\" "
        "is given the same normals as CGAL. A true primitive is found when the detection "
        "sharing most of its points has its type and precision and recall >= 0.9.", "",
        "; ".join(summary) + f". Found of {truth}: {found}.", "",
        "| scene | points | primitives | " + " | ".join(
            f"{names[m]} s (CPU s) | found (detected)" for m in names) + " | ratio | "
        "ratio, same normals |",
        "|---|---|---|" + "---|---|" * len(names) + "---|---|"]
    for r in rows:
        v = r["methods"]
        cells = [f"{v[m]['s']:.3f} ({v[m]['cpu_s']:.3f}) | {v[m]['found']} ({v[m]['detected']})"
                 for m in names]
        lines.append(f"| {r['scene']} | {r['points']} | {r['primitives']} | "
                     + " | ".join(cells)
                     + f" | {v['jaxfit']['s'] / v['cgal']['s']:.2f} | "
                     f"{v['jaxfit_given_normals']['s'] / v['cgal']['s']:.2f} |")
    return "\n".join(lines) + "\n"


#: The stages ``stages`` times: (label, module, attribute path) for this round's code,
#: and for the code before it (5dab3bd), which had no RadiusGraph.
_STAGES = [("neighbour structure (tree, spacing, pairs)", "jaxfit.detect", "RadiusGraph.of"),
           ("normals", "jaxfit.detect", "estimate_normals"),
           ("groups", "jaxfit.detect", "_groups"),
           ("fits", "jaxfit.detect", "started_batch"),
           ("supports: compatible points", "jaxfit.detect", "_compatible"),
           ("supports: largest component", "jaxfit.detect", "_largest"),
           ("winners' refit", "jaxfit.engine.refine", "final_refit"),
           ("final assignment", "jaxfit.detect", "_settled")]
_STAGES_BEFORE = [("normals", "jaxfit.detect", "estimate_normals"),
                  ("spacing", "jaxfit.detect", "median_spacing"),
                  ("groups", "jaxfit.detect", "_groups"), ("fits", "jaxfit.detect", "fit"),
                  ("supports (compatible points and components)", "jaxfit.detect", "support"),
                  ("final assignment", "jaxfit.detect", "_settled")]


def stages(name: str, runs: int = 3) -> dict:
    """Process CPU seconds per warm detect call by stage (``time.process_time`` around
    each stage function), on peers' five synthetic scenes and on the two Fit4CAD scans,
    ``runs`` calls of each; written to stages_<name>.json. Runs on the jaxfit it
    imports: ``PYTHONPATH=<a worktree> python benchmarks/detect.py --stages before``
    times that worktree's detect (the stage functions of 5dab3bd are known too)."""
    import collections
    import functools
    import importlib
    import sys

    from benchmarks import peers

    module = importlib.import_module("jaxfit.detect")
    spent, calls = collections.defaultdict(float), collections.Counter()

    def wrapped(owner, attr, label):
        inner = getattr(owner, attr)

        def timed(*args, _inner=inner, _first=True, **kwargs):
            start = time.process_time()
            try:
                out = _inner(*args, **kwargs)
            finally:
                spent[label] += time.process_time() - start
                calls[label] += _first
            # (a started fit returns its finish: timed as the same stage and call)
            return functools.partial(timed, _inner=out, _first=False) if callable(out) else out
        setattr(owner, attr, timed)

    for label, where, path in (_STAGES if hasattr(module, "RadiusGraph") else _STAGES_BEFORE):
        owner, attr = importlib.import_module(where), path
        if "." in path:
            first, attr = path.split(".")
            owner = getattr(owner, first)
        wrapped(owner, attr, label)
    sets = {"synthetic": [peers.synthetic_scene(seed)[0] for seed in range(peers.SCENES)],
            "Fit4CAD": [load_fit4cad(n)[0] for n in ("PC33", "PC21")
                        if (DATA / f"{n}.txt").exists()]}
    out = {"python": sys.version.split()[0], "runs": runs}
    for key, clouds in sets.items():
        for points in clouds:
            module.detect(points, key=0)  # (warm)
        spent.clear()
        calls.clear()
        start = time.process_time()
        for _ in range(runs):
            for points in clouds:
                module.detect(points, key=0)
        count = runs * len(clouds)
        total = (time.process_time() - start) / count
        rows = {label: {"ms": 1e3 * spent[label] / count, "calls": calls[label] / count}
                for label in spent}
        rows["other"] = {"ms": 1e3 * total - sum(r["ms"] for r in rows.values()), "calls": 0}
        out[key] = {"total_ms": 1e3 * total, "stages": rows}
        print(f"{key}: {1e3 * total:.0f} ms CPU per call", flush=True)
        for label, r in rows.items():
            print(f"  {label:46s} {r['ms']:6.1f} ms {r['calls']:6.1f} calls", flush=True)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"stages_{name}.json").write_text(json.dumps(out, indent=1))
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cgal", action="store_true",
                        help="only the scenes side by side with CGAL (cgal.md, cgal.json)")
    parser.add_argument("--repeats", type=int, default=5,
                        help="timed warm runs per method and scene with --cgal")
    parser.add_argument("--stages", metavar="NAME",
                        help="only the CPU time by stage (stages_NAME.json)")
    args = parser.parse_args(argv)
    if args.cgal:
        side_by_side(args.repeats)
        return
    if args.stages:
        stages(args.stages)
        return
    real_rows = [real(name) for name in ("PC33", "PC21")]
    synthetic_rows = synthetic()
    (OUT / "results.json").write_text(json.dumps(
        {"synthetic": synthetic_rows, "real": real_rows}, indent=1))
    (OUT / "summary.md").write_text(_markdown(synthetic_rows, real_rows))
    print((OUT / "summary.md").read_text())


if __name__ == "__main__":
    main()
