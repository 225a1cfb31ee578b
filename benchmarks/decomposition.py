"""PSDA on the real models in ../shared/data: previews, a gain sweep, and timings.

Run: ``python -m benchmarks.decomposition``. For each model it decomposes 20,000 surface
points at gain 0.96 twice (the first run compiles, the second is timed warm) and writes
``benchmarks/results/decomposition/<model>/{parts.json,preview.png}``; it then sweeps the
thesis's gains on one model and writes ``gain_sweep.md`` and ``summary.md``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from jaxfit.decomposition import decompose, load_source
from jaxfit.decomposition.boxdecomp import decompose_boxes

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
RESULTS = Path(__file__).resolve().parent / "results" / "decomposition"
MODELS = {
    "graspit_mug": "graspit/mug.iv",
    "graspit_phone": "graspit/phone.iv",
    "graspit_arizona": "graspit/arizonaObject_revised.iv",
    "inventor_duck": "misc/inventor_mentor_duck.iv",
    "vhacd_homer": "misc/vhacd_homer.off",
    "ycb_soup_can": "ycb/005_tomato_soup_can_textured.gltf",
    "ycb_cracker_box": "ycb/003_cracker_box_textured.gltf",
}
SWEEP_MODEL = "vhacd_homer"
GAINS = (0.80, 0.85, 0.90, 0.96, 0.98, 0.99)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.parse_args()  # (no options: --help describes the run and writes nothing)
    if not DATA.is_dir():
        raise SystemExit(f"no shared data at {DATA}")
    RESULTS.mkdir(parents=True, exist_ok=True)
    lines = ["| model | points | parts | primitives | mean distance / part diagonal (worst) "
             "| first run (s) | warm run (s) |", "|---|---|---|---|---|---|---|"]
    for name, rel in MODELS.items():
        points = load_source(DATA / rel, num_points=20000, seed=0)
        start = time.perf_counter()
        decompose(points, gain=0.96, key=0)
        first = time.perf_counter() - start
        result = decompose(points, gain=0.96, key=0)
        out = RESULTS / name
        out.mkdir(exist_ok=True)
        (out / "parts.json").write_text(json.dumps(result.to_dict(), indent=1))
        from jaxfit.io.preview import render

        render(result, out / "preview.png")
        worst = max(p.mean_distance / np.linalg.norm(p.box.extents) for p in result.parts)
        kinds = ", ".join(p.winner for p in result.parts)
        lines.append(f"| {name} | {len(points)} | {len(result.parts)} | {kinds} | {worst:.2%} "
                     f"| {first:.1f} | {result.seconds:.1f} |")
        print(lines[-1], flush=True)
    (RESULTS / "summary.md").write_text("\n".join(lines) + "\n")

    points = load_source(DATA / MODELS[SWEEP_MODEL], num_points=20000, seed=0)
    sweep = [f"Gain sweep on {SWEEP_MODEL} (20,000 points, min_points 400):", "",
             "| gain | parts | seconds |", "|---|---|---|"]
    for gain in GAINS:
        start = time.perf_counter()
        tree = decompose_boxes(points, gain=gain, min_points=400, reference="root")
        sweep.append(f"| {gain:.2f} | {len(tree.leaves)} | {time.perf_counter() - start:.2f} |")
        print(sweep[-1], flush=True)
    (RESULTS / "gain_sweep.md").write_text("\n".join(sweep) + "\n")


if __name__ == "__main__":
    main()
