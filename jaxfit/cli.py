"""Command line: ``jaxfit fit CLOUD --shape S``, ``demo``, ``decompose`` (``--urdf``,
``--mjcf``: simulator models), ``grasp`` (parallel-jaw grasps) and ``evaluate``.

The choices of ``--shape``, ``--estimator``, ``--scenario`` and ``--object`` come from
``jaxfit.shapes.REGISTRY``, ``ESTIMATORS``, ``scenarios.SCENARIOS`` and
``synthetic.COMPOSITES``, so a new primitive is a choice without touching this file.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from . import _cache
from .evaluation import evaluate as evaluation
from .evaluation import scenarios
from .evaluation.synthetic import COMPOSITES
from .io.atomic import replacing
from .shapes import REGISTRY
from .shapes._base import ESTIMATORS

#: Formats ``--mesh`` writes (trimesh's exporters).
MESH_OUTPUTS = (".ply", ".stl", ".obj", ".off", ".glb", ".gltf")
#: Set to see the traceback of an unexpected error instead of its one-line message.
DEBUG_ENV = "JAXFIT_DEBUG"


def _file_target(path: str, flag: str, suffixes=None) -> None:
    """Raise ValueError unless a file can be written at ``path`` (checked before any
    work, so a long run never ends on a bad output path)."""
    target = Path(path)
    if suffixes and target.suffix.lower() not in suffixes:
        raise ValueError(f"{flag} {path}: unsupported extension {target.suffix!r}; use one "
                         f"of {', '.join(suffixes)}")
    if target.is_dir():
        raise ValueError(f"{flag} {path} is a folder; give a file name")
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"{flag} {path}: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK) or (target.exists() and not os.access(target, os.W_OK)):
        raise ValueError(f"{flag} {path}: not writable")


def _folder_target(path: str, flag: str) -> None:
    """Raise ValueError unless ``path`` is, or can be made, a writable folder."""
    target = Path(path)
    if target.exists() and not target.is_dir():
        raise ValueError(f"{flag} {path} is a file, not a folder")
    try:
        target.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"{flag} {path}: cannot make the folder ({err.strerror})") from None
    if not os.access(target, os.W_OK):
        raise ValueError(f"{flag} {path}: not writable")


def _check_outputs(args) -> None:
    """Every output path of the command, checked before it starts."""
    if getattr(args, "json", None):
        _file_target(args.json, "--json")
    if getattr(args, "mesh", None):
        _file_target(args.mesh, "--mesh", MESH_OUTPUTS)
    if getattr(args, "out", None) and not (args.command == "demo" and args.shape):
        _folder_target(args.out, "--out")  # (demo --shape fits one cloud: no folder)
    if getattr(args, "urdf", False) or getattr(args, "mjcf", False):
        _check_sim_options(args)


def _check_sim_options(args) -> None:
    """--urdf and --mjcf: they need --out, a usable --name, and positive --density and
    --scale; their files must be writable."""
    from .io.sim import NAME

    if not args.out:
        raise ValueError("--urdf and --mjcf write into the --out folder: give --out DIR")
    if not NAME.fullmatch(args.name):
        raise ValueError(f"--name {args.name!r}: use letters, digits, '_', '.' or '-'")
    for flag, value in (("--density", args.density), ("--scale", args.scale)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{flag} must be positive and finite, got {value}")
    for flag, suffix in (("--urdf", ".urdf"), ("--mjcf", ".xml")):
        if getattr(args, flag[2:]):
            _file_target(str(Path(args.out) / f"{args.name}{suffix}"), flag)


def _print_model(model, title):
    params = model.to_dict()
    print(f"{title} {params.pop('type')}:")
    for name, value in params.items():
        text = np.array2string(np.asarray(value), precision=6, prefix=" " * 14)
        print(f"  {name:<11} {text}")


def _print_result(result, seconds: float):
    _print_model(result.model, "fitted")
    print(f"inliers     {result.num_inliers} of {result.inliers.size} "
          f"(threshold {result.threshold:.6g})")
    print(f"hypotheses  {result.num_hypotheses} ({result.status.value}), "
          f"{seconds:.3f} s including compilation")


def _fit_and_report(points, args):
    import jaxfit

    start = time.perf_counter()
    result = jaxfit.fit(points, args.shape, threshold=args.threshold, key=args.seed,
                        estimator=args.estimator)
    _print_result(result, time.perf_counter() - start)
    if args.json:
        payload = {"model": result.model.to_dict(), "num_inliers": result.num_inliers,
                   "num_points": int(result.inliers.size), "cost": result.cost,
                   "threshold": result.threshold, "num_hypotheses": result.num_hypotheses,
                   "status": result.status.value}
        with replacing(args.json) as path:
            path.write_text(json.dumps(payload, indent=2))
        print(f"wrote {args.json}")
    if args.mesh:
        with replacing(args.mesh) as path:
            result.model.to_mesh().export(path)
        print(f"wrote {args.mesh}")
    return result


def _cmd_fit(args):
    from .io import load_points

    points = load_points(args.cloud, num_points=args.num_points, seed=args.seed)
    print(f"{args.cloud}: {len(points)} points")
    _fit_and_report(points, args)


def _cmd_demo(args):
    if args.shape is None:
        return _demo_decomposition(args)
    from .evaluation.synthetic import demo_cloud

    points, truth, _ = demo_cloud(args.shape, seed=args.seed)
    print(f"demo: {len(points)} points, half of them uniform outliers, around a known "
          f"{args.shape}")
    _print_model(truth, "true")
    _fit_and_report(points, args)


def _parser():
    parser = argparse.ArgumentParser(prog="jaxfit", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    def common(p, default_shape=None, required=True):
        p.add_argument("--shape", default=default_shape, required=required,
                       choices=list(REGISTRY))
        p.add_argument("--threshold", type=float, default=None,
                       help="inlier distance (default: 0.5%% of the bounding-box diagonal)")
        p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
        p.add_argument("--estimator", choices=ESTIMATORS, default=None,
                       help="minimal-sample estimator (default: the shape's best)")
        p.add_argument("--json", metavar="OUT", help="write the result as JSON")
        p.add_argument("--mesh", metavar="OUT", help="write the primitive's mesh (.ply, .stl, ...)")

    fit = sub.add_parser("fit", help="fit one primitive to a point cloud or mesh file")
    fit.add_argument("cloud", help=".ply .obj .stl .off .glb .gltf .iv .xyz .txt .csv .crd .npy")
    fit.add_argument("--num-points", type=int, default=20000,
                     help="points sampled from a mesh's surface (default 20000)")
    common(fit)
    fit.set_defaults(run=_cmd_fit)

    demo = sub.add_parser(
        "demo", help="decompose a built-in object (no input needed); with --shape, fit one "
                     "primitive among outliers instead")
    demo.add_argument("--object", default="mallet",
                      choices=COMPOSITES)
    demo.add_argument("--out", default="jaxfit-demo", help="output folder (./jaxfit-demo)")
    demo.add_argument("--gain", type=float, default=0.96)
    common(demo, default_shape=None, required=False)
    demo.set_defaults(run=_cmd_demo)

    decompose = sub.add_parser("decompose", help="decompose an object into primitives")
    decompose.add_argument("input", help="mesh, point file or Open Inventor .iv model")
    decompose.add_argument("--gain", type=float, default=0.96,
                           help="split while children/parent volume < gain (0.96)")
    decompose.add_argument("--min-points", type=int, default=None,
                           help="smallest part (default 2%% of the points)")
    decompose.add_argument("--num-points", type=int, default=20000,
                           help="points sampled from a mesh (20000)")
    decompose.add_argument("--seed", type=int, default=0)
    decompose.add_argument("--out", default=None,
                           help="folder for parts.json, decomposition.glb, preview.png")
    decompose.add_argument("--urdf", action="store_true",
                           help="also write the primitives as a URDF robot, OUT/NAME.urdf")
    decompose.add_argument("--mjcf", action="store_true",
                           help="also write them as a MuJoCo model, OUT/NAME.xml")
    decompose.add_argument("--name", default="object",
                           help="--urdf/--mjcf: the body's name and file stem (object)")
    decompose.add_argument("--density", type=float, default=1000.0,
                           help="--urdf/--mjcf: mass per unit volume in written units (1000)")
    decompose.add_argument("--scale", type=float, default=1.0,
                           help="--urdf/--mjcf: multiplies every length (0.001 for a model "
                                "in millimetres; default 1)")
    decompose.set_defaults(run=_cmd_decompose)
    grasp = sub.add_parser("grasp", help="plan parallel-jaw grasps on an object's primitives")
    grasp.add_argument("input", help="mesh, point file or Open Inventor .iv model")
    grasp.add_argument("--out", required=True, help="folder for grasps.json and grasps.png")
    grasp.add_argument("--gripper-width", type=float, default=None,
                       help="widest opening in the model's units (default 0.085 / --scale)")
    grasp.add_argument("--finger-depth", type=float, default=None,
                       help="finger length along the approach (default 0.47 x the width)")
    grasp.add_argument("--finger-width", type=float, default=None,
                       help="finger pad width (default 0.235 x the width)")
    grasp.add_argument("--scale", type=float, default=1.0,
                       help="metres per model unit for the default gripper (0.001 for "
                            "millimetres; default 1)")
    grasp.add_argument("--top", type=int, default=10, help="grasps kept, best first (10)")
    grasp.add_argument("--num-points", type=int, default=20000,
                       help="points sampled from a mesh (20000)")
    grasp.add_argument("--seed", type=int, default=0)
    grasp.set_defaults(run=_cmd_grasp)
    evaluate = sub.add_parser(
        "evaluate", help="the thesis's RN/RNIM/SN/SNIM evaluation: CSV, tables and plots")
    evaluate.add_argument("--shape", nargs="+", default=list(evaluation.SHAPES),
                          choices=list(REGISTRY))
    evaluate.add_argument("--scenario", nargs="+", default=list(scenarios.SCENARIOS),
                          choices=scenarios.SCENARIOS)
    evaluate.add_argument("--repeats", type=int, default=10, help="clouds per level (10)")
    evaluate.add_argument("--count", type=int, default=2000, help="points per cloud (2000)")
    evaluate.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    evaluate.add_argument("--out", default="evaluation", help="output folder (./evaluation)")
    evaluate.add_argument("--estimator", choices=ESTIMATORS, default=None,
                          help="minimal-sample estimator (default: each shape's best)")
    evaluate.add_argument("--normals", choices=evaluation.NORMALS, default="estimated",
                          help="normals the oriented estimators read (default: estimated)")
    evaluate.set_defaults(run=_cmd_evaluate)
    return parser


def _report_decomposition(result, out):
    print(result.summary())
    if out:
        folder = result.save(out)
        print(f"wrote {folder / 'parts.json'}, {folder / 'decomposition.glb'}, "
              f"{folder / 'preview.png'}")


def _cmd_decompose(args):
    from .decomposition import decompose

    result = decompose(args.input, gain=args.gain, min_points=args.min_points,
                       num_points=args.num_points, key=args.seed, progress=True)
    _report_decomposition(result, args.out)
    if args.urdf or args.mjcf:
        from .io.sim import write_mjcf, write_urdf

        models = [part.model for part in result.parts]
        options = {"name": args.name, "density": args.density, "scale": args.scale}
        out = Path(args.out)
        if args.urdf:
            print(f"wrote {write_urdf(models, out / f'{args.name}.urdf', **options)}")
        if args.mjcf:
            print(f"wrote {write_mjcf(models, out / f'{args.name}.xml', **options)}")


def _cmd_grasp(args):
    from .decomposition import decompose
    from .grasping import ParallelJaw, grasps

    if not (np.isfinite(args.scale) and args.scale > 0):
        raise ValueError(f"--scale must be positive and finite, got {args.scale}")
    width = 0.085 / args.scale if args.gripper_width is None else args.gripper_width
    gripper = ParallelJaw(
        max_width=width,
        finger_depth=0.47 * width if args.finger_depth is None else args.finger_depth,
        finger_width=0.235 * width if args.finger_width is None else args.finger_width)
    if args.top < 1:
        raise ValueError(f"--top must be a positive integer, got {args.top}")
    result = decompose(args.input, num_points=args.num_points, key=args.seed, progress=True)
    print(result.summary())
    found = grasps(result, gripper, key=args.seed, top=args.top)
    print(f"{len(found)} grasps kept of {found.num_candidates} candidates in "
          f"{found.seconds:.2f} s")
    for i in range(len(found)):
        print(f"  grasp {i}: part {found.parts[i]} ({found.primitives[i]}), score "
              f"{found.scores[i]:.3f}, width {found.widths[i]:.4g}")
    folder = found.save(args.out, result, top=args.top)
    print(f"wrote {folder / 'grasps.json'}, {folder / 'grasps.png'}")


def _demo_decomposition(args):
    from .decomposition import decompose
    from .evaluation.synthetic import composite

    points, models, _ = composite(args.object, seed=args.seed)
    print(f"demo: a {args.object} of {len(points)} points sampled from "
          + ", ".join(m.name for m in models))
    for model in models:
        _print_model(model, "true")
    result = decompose(points, gain=args.gain, key=args.seed, progress=True)
    _report_decomposition(result, args.out)
    for i, part in enumerate(result.parts):
        _print_model(part.model, f"part {i}:")


def _cmd_evaluate(args):
    rows = evaluation.run(args.shape, args.scenario, repeats=args.repeats, count=args.count,
                        seed=args.seed, normals=args.normals, estimator=args.estimator)
    out = evaluation.write(rows, args.out)
    print(f"{len(rows)} fits; wrote {out / 'runs.csv'}, {out / 'summary.md'} and plots")


def main(argv=None) -> int:
    """Run the command line; returns the exit status: 0, 2 for bad input (a message
    naming it), 1 for any other error (its one-line message; the traceback with
    JAXFIT_DEBUG=1), 130 when interrupted."""
    args = _parser().parse_args(argv)
    try:
        _check_outputs(args)
        if (notice := _cache.compile_notice()) is not None:
            print(notice, file=sys.stderr, flush=True)
        args.run(args)
    except BrokenPipeError:  # `jaxfit ... | head`: the reader left; say nothing more
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except KeyboardInterrupt:
        print("jaxfit: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError) as err:  # bad input or an unusable file: a message
        print(f"jaxfit: error: {err}", file=sys.stderr)
        return 2
    except Exception as err:  # anything else (a MemoryError, a bug): still no traceback
        if os.environ.get(DEBUG_ENV):
            raise
        print(f"jaxfit: error: {type(err).__name__}: {err} (set {DEBUG_ENV}=1 for the "
              "traceback)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
