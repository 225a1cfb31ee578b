"""Lift success of jaxfit's grasps on the real meshes in ../shared/data (issue 15).

Run: ``python -m benchmarks.grasping``. For each of the six benchmark meshes (the YCB
soup can and cracker box, the GraspIt mug and phone, the pybullet mug, the Inventor duck;
scales and up axes in ``MODELS``; the GraspIt mug stands on its base, -Y up) it
decomposes 4,000 surface points (key 0), plans grasps for an 8.5 cm jaw (4 cm fingers,
2 cm pads) with ``jaxfit.grasps`` (a first call, then timed warm: once told of the floor,
``support=`` the plane through the cloud's lowest point, as a robot that sees the table
is, and once floating, without), and runs ``jaxfit.io.trial.lift_trial`` on the top 20 grasps
against the *original mesh*, as CoACD's convex pieces (``pip install coacd``; threshold
0.05, seed 0; without coacd, or with ``--pieces bodies``, one convex piece per connected
body): approach from the pre-grasp, close, lift 10 cm, hold 2 s. Each grasp is tried
twice: with the object standing on a floor (the grasps planned with the floor given),
and floating without gravity until the fingers have closed (the grasp alone; the grasps
planned without a support). It writes the
top-1 / top-5 / top-20 success rates and the times to ``benchmarks/results/grasping.md``
and each grasp's outcome to ``benchmarks/results/grasping.json``.

Baseline (a second table): antipodal grasps sampled directly on the mesh
(``antipodal``), the same count, gripper and trials, told of the floor the same way.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
RESULTS = Path(__file__).resolve().parent / "results"
#: name -> (file, scale to metres, the axis that points up when the object stands: an
#: index, or a direction (3,) where up runs down an axis). The GraspIt mug's opening is at
#: -Y (its closed, recessed base at +Y): it stands with -Y up (before, +Y stood it on its
#: rim).
MODELS = {
    "ycb_soup_can": ("ycb/005_tomato_soup_can_textured.gltf", 1.0, 1),
    "ycb_cracker_box": ("ycb/003_cracker_box_textured.gltf", 1.0, 1),
    "graspit_mug": ("graspit/mug.iv", 1e-3, (0.0, -1.0, 0.0)),
    "graspit_phone": ("graspit/phone.iv", 1e-3, 2),
    "pybullet_mug": ("misc/pybullet_data_objects_mug.obj", 1.0, 2),
    "inventor_duck": ("misc/inventor_mentor_duck.iv", 0.2, 2),
}
NUM_POINTS = 4000
TOP = 20
JAW_METRES = dict(max_width=0.085, finger_depth=0.04, finger_width=0.02)


def up_vector(up) -> np.ndarray:
    """(3,) the unit up direction of a ``MODELS`` entry's up (an axis index or a vector)."""
    if isinstance(up, int):
        return np.eye(3)[up]
    up = np.asarray(up, np.float64)
    return up / np.linalg.norm(up)


def support_of(points, up) -> tuple[np.ndarray, float]:
    """The floor a standing object rests on, as ``jaxfit.grasps``' ``support``: the plane
    through the cloud's lowest point along ``up`` (what a robot that sees the table knows)."""
    up = up_vector(up)
    return up, float(np.min(np.asarray(points) @ up))


def load_mesh(path: Path):
    import trimesh

    if path.suffix == ".iv":
        from jaxfit.io.iv import load_iv

        return load_iv(path)
    return trimesh.load(path, force="mesh")


def convex_pieces(mesh, method: str, cache: Path | None = None):
    """The object's convex pieces as vertex arrays: CoACD's, or None (``lift_trial`` then
    takes the mesh's connected bodies). With ``cache`` (a .npz path), CoACD's pieces are
    read from it when it exists and written to it otherwise (CoACD is seeded: the same
    mesh gives the same pieces; it is most of the benchmark's time)."""
    if method == "bodies":
        return None
    if cache is not None and cache.is_file():
        with np.load(cache) as stored:
            return [stored[f"piece{i}"] for i in range(len(stored.files))]
    import coacd

    coacd.set_log_level("error")
    parts = coacd.run_coacd(coacd.Mesh(np.asarray(mesh.vertices, np.float64),
                                       np.asarray(mesh.faces, np.int64)), threshold=0.05,
                            seed=0)
    pieces = [np.asarray(vertices) for vertices, _ in parts]
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cache, **{f"piece{i}": v for i, v in enumerate(pieces)})
    return pieces


def antipodal(mesh, jaw, count: int, *, seed: int = 0, num_points: int = NUM_POINTS,
              pairs: int = 20000, min_quality: float = 0.8, approaches: int = 8,
              support=None):
    """Up to ``count`` grasps sampled on the mesh itself: random pairs of its surface
    points (with the faces' normals) closer than the jaw's opening, best antipodal
    quality first (the lower |normal . closing axis| of the two, at least
    ``min_quality``); for each pair ``approaches`` approach directions around the closing
    axis, origin midway between the points; kept when the palm and finger boxes at the
    opening (the span plus the clearance on each side) hold none of the points and, with
    ``support`` (up, height) given, the boxes clear that plane as ``jaxfit.grasps``'
    do (``clears_support``). Returns poses (K, 4, 4), widths (K,) and the seconds it took."""
    import trimesh

    from jaxfit.grasping import clears_support

    start = time.perf_counter()
    rng = np.random.default_rng(seed)
    points, faces = trimesh.sample.sample_surface(mesh, num_points, seed=seed)
    points, normals = np.asarray(points), np.asarray(mesh.face_normals)[faces]
    i, j = rng.integers(0, len(points), (2, pairs))
    span = points[j] - points[i]
    length = np.linalg.norm(span, axis=1)
    ok = (length > 1e-9) & (length + 2 * jaw.clearance <= jaw.max_width)
    axis = span / np.where(ok, length, 1.0)[:, None]
    quality = np.minimum(np.abs(np.sum(normals[i] * axis, axis=1)),
                         np.abs(np.sum(normals[j] * axis, axis=1)))
    ok &= quality >= min_quality
    poses, widths = [], []
    for k in np.flatnonzero(ok)[np.argsort(-quality[ok], kind="stable")]:
        y = axis[k]
        e1 = np.cross(y, np.eye(3)[np.argmin(np.abs(y))])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(y, e1)
        width = length[k] + 2 * jaw.clearance
        boxes = jaw.boxes(width)
        for a in rng.uniform(0, 2 * np.pi) + np.arange(approaches) * 2 * np.pi / approaches:
            z = np.cos(a) * e1 + np.sin(a) * e2
            pose = np.eye(4)
            pose[:3, :3] = np.column_stack([np.cross(y, z), y, z])
            pose[:3, 3] = 0.5 * (points[i[k]] + points[j[k]])
            local = (points - pose[:3, 3]) @ pose[:3, :3]
            if not any(np.any(np.all((local >= lo) & (local <= hi), axis=1))
                       for lo, hi in boxes) and (support is None or clears_support(
                           pose[None], [width], jaw, *support)[0]):
                poses.append(pose)
                widths.append(width)
                break
        if len(poses) == count:
            break
    return np.array(poses).reshape(-1, 4, 4), np.array(widths), time.perf_counter() - start


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
    parser.add_argument("--cache", type=Path, default=None, metavar="DIR",
                        help="keep CoACD's pieces per model in DIR (read when there)")
    args = parser.parse_args()
    if not DATA.is_dir():
        raise SystemExit(f"no shared data at {DATA}")
    import jaxfit
    from jaxfit.decomposition import load_source
    from jaxfit.io.trial import _pieces, lift_trial

    RESULTS.mkdir(parents=True, exist_ok=True)
    lines = ["| model | parts | candidates | grasps (floor / floating) | from below "
             "| convex pieces | on floor: top-1 | top-5 | top-20 | floating: top-1 | top-5 "
             "| top-20 "
             "| plan warm (s) | plan first (s) |", "|---" * 14 + "|"]
    record = {}
    totals = {(floor, k): [] for floor in (True, False) for k in (1, 5, 20)}
    base_lines = ["| model | grasps (floor / floating) | on floor: top-1 | top-5 | top-20 "
                  "| floating: top-1 | top-5 | top-20 | sampling (s) |", "|---" * 9 + "|"]
    base_totals = {key: [] for key in totals}
    for name in args.models:
        rel, scale, up = MODELS[name]
        mesh = load_mesh(DATA / rel)
        d = jaxfit.decompose(load_source(DATA / rel, num_points=NUM_POINTS, seed=0), key=0)
        jaw = jaxfit.ParallelJaw(**{k: v / scale for k, v in JAW_METRES.items()})
        floor_plane = support_of(d.points, up)
        start = time.perf_counter()
        jaxfit.grasps(d, jaw, key=0, top=TOP, support=floor_plane)
        first = time.perf_counter() - start
        plans, warm = {}, {}
        for floor in (True, False):  # on a floor the planner is told where it is
            start = time.perf_counter()
            plans[floor] = jaxfit.grasps(d, jaw, key=0, top=TOP,
                                         support=floor_plane if floor else None)
            warm[floor] = time.perf_counter() - start
        pieces = convex_pieces(mesh, args.pieces,
                               None if args.cache is None else args.cache / f"{name}.npz")
        trials = {floor: [lift_trial(mesh, pose, width, jaw, scale=scale, up=up,
                                     pieces=pieces, floor=floor)
                          for pose, width in zip(g.poses, g.widths, strict=True)]
                  for floor, g in plans.items()}
        outcomes = {floor: [bool(t) for t in ts] for floor, ts in trials.items()}
        base = {}
        for floor in (True, False):  # the baseline is told of the floor too
            base_poses, base_widths, base_seconds = antipodal(
                mesh, jaw, TOP, support=floor_plane if floor else None)
            base[floor] = [bool(lift_trial(mesh, pose, width, jaw, scale=scale, up=up,
                                           pieces=pieces, floor=floor))
                           for pose, width in zip(base_poses, base_widths, strict=True)]
        for floor, k in base_totals:
            base_totals[floor, k].append(np.mean(base[floor][:k]) if base[floor] else 0.0)
        base_lines.append(f"| {name} | {len(base[True])} / {len(base[False])} | "
                          + " | ".join(rate(base[floor], k) for floor in (True, False)
                                       for k in (1, 5, 20)) + f" | {base_seconds:.2f} |")
        for floor, k in totals:  # a model without grasps counts as 0
            totals[floor, k].append(np.mean(outcomes[floor][:k]) if outcomes[floor] else 0.0)
        upv = up_vector(up)
        below = int(np.sum(plans[False].approach @ upv > 0.5))
        record[name] = {
            "pieces": len(_pieces(mesh, pieces)), "parts": [p.winner for p in d.parts],
            "candidates": plans[False].num_candidates,
            "plan_seconds_warm": {"floor": warm[True], "floating": warm[False]},
            "baseline": {"floor": base[True], "floating": base[False]},
            **{where: [{"rank": i, "primitive": str(g.primitives[i]), "part": int(g.parts[i]),
                        "score": float(g.scores[i]), "width_m": float(g.widths[i] * scale),
                        "contact_width_m": float(g.contact_widths[i] * scale),
                        "approach_up": float(g.approach[i] @ upv),
                        **{key: getattr(trials[floor][i], key).tolist() if key == "offset"
                           else getattr(trials[floor][i], key)
                           for key in ("success", "rise", "offset")}}
                       for i in range(len(g))]
               for floor, where in ((True, "floor"), (False, "floating"))
               for g in (plans[floor],)}}
        cells = " | ".join(rate(outcomes[floor], k) for floor in (True, False)
                           for k in (1, 5, 20))
        lines.append(f"| {name} | {len(d.parts)} | {plans[False].num_candidates} "
                     f"| {len(plans[True])} / {len(plans[False])} | {below} "
                     f"| {record[name]['pieces']} | {cells} | {max(warm.values()):.3f} "
                     f"| {first:.2f} |")
        print(lines[-1], flush=True)
    mean = " | ".join(f"{100 * np.mean(totals[key]):.0f} %" if totals[key] else "–"
                      for key in totals)
    lines.append(f"| mean over the models | | | | | | {mean} | | |")
    base_lines.append("| mean over the models | | " + " | ".join(
        f"{100 * np.mean(base_totals[key]):.0f} %" for key in base_totals) + " | |")
    text = ["# Lift trials of jaxfit's grasps (`python -m benchmarks.grasping`)", "",
            __doc__.split("\n\n")[1].replace("\n", " "), "",
            f"Convex pieces: {args.pieces}. Grasps: kept on the floor / floating. From "
            "below: grasps of the floating plan approaching upwards (approach . up > "
            "0.5), which a floor would block. Plan warm: the slower of the two plans. "
            "A model without grasps counts as 0 in the means. "
            "Success: the object rose at least 5 cm and its point that lay between the "
            "fingertips when they closed is still between the fingers after the hold. "
            "top-k: successes among the k best grasps (fewer when fewer were found).", "",
            *lines, "", "Baseline: antipodal grasps sampled on the mesh (``antipodal``: 20,000 "
            "random point pairs, quality >= 0.8, 8 approaches each, the first that clears "
            "the points and, on the floor, the floor), the same trials:", "", *base_lines, ""]
    (RESULTS / "grasping.md").write_text("\n".join(text))
    (RESULTS / "grasping.json").write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
