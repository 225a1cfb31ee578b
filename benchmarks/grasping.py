"""Lift success of jaxfit's grasps on the real meshes in ../shared/data (issue 15).

Run: ``python -m benchmarks.grasping``. For each of the six benchmark meshes (the YCB
soup can and cracker box, the GraspIt mug and phone, the pybullet mug, the Inventor duck;
scales and up axes as tests/test_sim.py's) it decomposes 4,000 surface points (key 0),
plans grasps for an 8.5 cm jaw (4 cm fingers, 2 cm pads) with ``jaxfit.grasps`` twice
(the second timed warm), and runs ``jaxfit.io.trial.lift_trial`` on the top 20 grasps
against the *original mesh*, as CoACD's convex pieces (``pip install coacd``; threshold
0.05, seed 0; without coacd, or with ``--pieces bodies``, one convex piece per connected
body): approach from the pre-grasp, close, lift 10 cm, hold 2 s. Each grasp is tried
twice: with the object standing on a floor (grasps from below then hit the floor), and
floating without gravity until the fingers have closed (the grasp alone). It writes the
top-1 / top-5 / top-20 success rates and the times to ``benchmarks/results/grasping.md``
and each grasp's outcome to ``benchmarks/results/grasping.json``.

No baseline yet: the issue's antipodal grasps sampled on the mesh are not written.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
RESULTS = Path(__file__).resolve().parent / "results"
#: name -> (file, scale to metres, the axis that points up when the object stands)
MODELS = {
    "ycb_soup_can": ("ycb/005_tomato_soup_can_textured.gltf", 1.0, 1),
    "ycb_cracker_box": ("ycb/003_cracker_box_textured.gltf", 1.0, 1),
    "graspit_mug": ("graspit/mug.iv", 1e-3, 1),
    "graspit_phone": ("graspit/phone.iv", 1e-3, 2),
    "pybullet_mug": ("misc/pybullet_data_objects_mug.obj", 1.0, 2),
    "inventor_duck": ("misc/inventor_mentor_duck.iv", 0.2, 2),
}
NUM_POINTS = 4000
TOP = 20
JAW_METRES = dict(max_width=0.085, finger_depth=0.04, finger_width=0.02)


def load_mesh(path: Path):
    import trimesh

    if path.suffix == ".iv":
        from jaxfit.io.iv import load_iv

        return load_iv(path)
    return trimesh.load(path, force="mesh")


def convex_pieces(mesh, method: str):
    """The object's convex pieces as vertex arrays: CoACD's, or None (``lift_trial`` then
    takes the mesh's connected bodies)."""
    if method == "bodies":
        return None
    import coacd

    coacd.set_log_level("error")
    parts = coacd.run_coacd(coacd.Mesh(np.asarray(mesh.vertices, np.float64),
                                       np.asarray(mesh.faces, np.int64)), threshold=0.05,
                            seed=0)
    return [np.asarray(vertices) for vertices, _ in parts]


def rate(outcomes, k: int) -> str:
    if not outcomes:
        return "–"
    first = outcomes[:k]
    return f"{sum(first)}/{len(first)}"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", nargs="*", default=list(MODELS), choices=list(MODELS))
    try:
        import coacd  # noqa: F401
        default = "coacd"
    except ImportError:
        default = "bodies"
    parser.add_argument("--pieces", choices=["coacd", "bodies"], default=default)
    args = parser.parse_args()
    if not DATA.is_dir():
        raise SystemExit(f"no shared data at {DATA}")
    import jaxfit
    from jaxfit.decomposition import load_source
    from jaxfit.io.trial import _pieces, lift_trial

    RESULTS.mkdir(parents=True, exist_ok=True)
    lines = ["| model | parts | candidates | grasps | from below | convex pieces "
             "| on floor: top-1 | top-5 | top-20 | floating: top-1 | top-5 | top-20 "
             "| plan warm (s) | plan first (s) |", "|---" * 14 + "|"]
    record = {}
    totals = {(floor, k): [] for floor in (True, False) for k in (1, 5, 20)}
    for name in args.models:
        rel, scale, up = MODELS[name]
        mesh = load_mesh(DATA / rel)
        d = jaxfit.decompose(load_source(DATA / rel, num_points=NUM_POINTS, seed=0), key=0)
        jaw = jaxfit.ParallelJaw(**{k: v / scale for k, v in JAW_METRES.items()})
        start = time.perf_counter()
        jaxfit.grasps(d, jaw, key=0, top=TOP)
        first = time.perf_counter() - start
        start = time.perf_counter()
        g = jaxfit.grasps(d, jaw, key=0, top=TOP)
        warm = time.perf_counter() - start
        pieces = convex_pieces(mesh, args.pieces)
        trials = {floor: [lift_trial(mesh, pose, width, jaw, scale=scale, up=up,
                                     pieces=pieces, floor=floor)
                          for pose, width in zip(g.poses, g.widths, strict=True)]
                  for floor in (True, False)}
        outcomes = {floor: [bool(t) for t in ts] for floor, ts in trials.items()}
        for floor, k in totals:
            if outcomes[floor]:
                totals[floor, k].append(np.mean(outcomes[floor][:k]))
        below = int(np.sum(g.approach @ np.eye(3)[up] > 0.5))
        record[name] = {
            "pieces": len(_pieces(mesh, pieces)), "parts": [p.winner for p in d.parts],
            "candidates": g.num_candidates, "plan_seconds_warm": warm,
            "grasps": [{"rank": i, "primitive": str(g.primitives[i]), "part": int(g.parts[i]),
                        "score": float(g.scores[i]), "width_m": float(g.widths[i] * scale),
                        "approach_up": float(g.approach[i] @ np.eye(3)[up]),
                        **{f"{where}_{key}": getattr(trials[floor][i], key).tolist()
                           if key == "offset" else getattr(trials[floor][i], key)
                           for floor, where in ((True, "floor"), (False, "floating"))
                           for key in ("success", "rise", "offset")}}
                       for i in range(len(g))]}
        cells = " | ".join(rate(outcomes[floor], k) for floor in (True, False)
                           for k in (1, 5, 20))
        lines.append(f"| {name} | {len(d.parts)} | {g.num_candidates} | {len(g)} | {below} "
                     f"| {record[name]['pieces']} | {cells} | {warm:.3f} | {first:.2f} |")
        print(lines[-1], flush=True)
    mean = " | ".join(f"{100 * np.mean(totals[key]):.0f} %" if totals[key] else "–"
                      for key in totals)
    lines.append(f"| mean over models with grasps | | | | | | {mean} | | |")
    text = ["# Lift trials of jaxfit's grasps (`python -m benchmarks.grasping`)", "",
            __doc__.split("\n\n")[1].replace("\n", " "), "",
            f"Convex pieces: {args.pieces}. From below: grasps approaching upwards "
            "(approach . up > 0.5), which a floor blocks. "
            "Success: the object rose at least 5 cm and its point that lay between the "
            "fingertips when they closed is still between the fingers after the hold. "
            "top-k: successes among the k best grasps (fewer when fewer were found).", "",
            *lines, ""]
    (RESULTS / "grasping.md").write_text("\n".join(text))
    (RESULTS / "grasping.json").write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
