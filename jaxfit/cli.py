"""Command line: ``jaxfit fit CLOUD --shape S``, ``detect``, ``decompose`` (``--urdf``,
``--mjcf``: simulator models), ``grasp`` (parallel-jaw grasps), ``batch`` (a whole
dataset), ``demo``, ``evaluate`` and ``warmup``.

Contract: every output path is checked (kind, folder, writable, extension) before any
work, so a long run never ends on a bad path; every flag given is honoured or refused;
bad input exits 2 and any other error 1, each with one line on stderr (the traceback
with ``JAXFIT_DEBUG=1``). Results go to stdout and progress to stderr, each line of
progress ending with the seconds since the command started.

The choices of ``--shape``, ``--estimator``, ``--scenario`` and ``--object`` come from
``jaxfit.shapes.REGISTRY``, ``ESTIMATORS``, ``scenarios.SCENARIOS`` and
``synthetic.COMPOSITES``, so a new primitive is a choice without touching this file.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from . import _cache, _checks
from .evaluation import evaluate as evaluation
from .evaluation import scenarios
from .evaluation.synthetic import COMPOSITES
from .io.atomic import replacing
from .shapes import REGISTRY
from .shapes._base import ESTIMATORS

#: Formats ``--mesh`` writes (trimesh's exporters; ``.gltf`` is left out because it
#: writes its buffers as separate files beside it: use ``.glb``).
MESH_OUTPUTS = (".ply", ".stl", ".obj", ".off", ".glb")
#: Set to see the traceback of an unexpected error instead of its one-line message.
DEBUG_ENV = "JAXFIT_DEBUG"

DESCRIPTION = """\
Fit primitive shapes (plane, sphere, cylinder, cone, box) to 3-D point clouds, find
several in a scene, decompose objects into primitives and plan grasps on them.

Inputs: meshes (.ply .obj .stl .off .glb .gltf .iv, surface-sampled), point files
(.xyz .txt .csv .crd .pts: x y z per row) and .npy arrays. Results go to stdout,
progress to stderr. Run 'jaxfit COMMAND --help' for a command's options."""

EPILOG = """\
examples:
  jaxfit demo                                  decompose a built-in mallet
  jaxfit fit scan.ply --shape cylinder --json fit.json
  jaxfit detect scene.xyz --out scene/
  jaxfit decompose mug.obj --out mug/ --urdf
  jaxfit batch models/ --out results/ --workers 2

exit status: 0 done, 1 an unexpected error (or a failed model in batch), 2 bad input,
130 interrupted."""


class _Parser(argparse.ArgumentParser):
    """argparse, with a usage error as one line (the usage is one --help away)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


# ----- output paths, checked before any work -------------------------------------------


def _file_target(path: str, flag: str, suffixes=None) -> None:
    """Raise ValueError unless a file can be written at ``path`` with one of
    ``suffixes`` (checked before any work, so a long run never ends on a bad path)."""
    target = Path(path)
    if target.is_dir():
        raise ValueError(f"{flag} {path} is a folder; give a file name")
    if suffixes and target.suffix.lower() not in suffixes:
        raise ValueError(f"{flag} {path}: unsupported extension {target.suffix!r}; use one "
                         f"of {', '.join(suffixes)}")
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


#: Options that only some uses of a command read: (command, flags, when they are read,
#: what to say otherwise, their defaults). Given where they would not be read, they are
#: refused rather than silently ignored.
CONDITIONAL = (
    ("decompose", ("name", "density", "scale"), lambda a: a.urdf or a.mjcf,
     "--name, --density and --scale set the --urdf/--mjcf files: give --urdf or --mjcf",
     {"name": "object", "density": 1000.0, "scale": 1.0}),
    ("decompose", ("gain",), lambda a: a.method == "thesis",
     "--gain sets the thesis method's box cuts: --method measured does not read it", {}),
    ("demo", ("gain",), lambda a: a.shape is None,
     "--gain applies to the decomposition demo, not to the fit of --shape", {"gain": 0.96}),
    ("demo", ("object",), lambda a: a.shape is None,
     "--object picks the object to decompose; with --shape the demo fits one primitive "
     "instead: give one of them", {}),
    ("demo", ("threshold", "estimator"), lambda a: a.shape is not None,
     "--threshold and --estimator apply to the fit demo: give --shape S", {}),
)


def _check_flags(args) -> None:
    """Refuse an option the command would not read (see ``CONDITIONAL``), then fill in
    the defaults of those left out."""
    for command, flags, read, message, defaults in CONDITIONAL:
        if args.command != command:
            continue
        given = [f for f in flags if getattr(args, f) is not None]
        if given and not read(args):
            raise ValueError(message)
        for flag, value in defaults.items():
            if getattr(args, flag) is None:
                setattr(args, flag, value)
    if args.command == "demo" and args.shape is None and args.out is None:
        args.out = DEMO_OUT  # the decomposition demo always writes its folder


def _check_outputs(args) -> None:
    """Every output path of the command, checked before it starts."""
    if getattr(args, "json", None):
        _file_target(args.json, "--json", (".json",))
    if getattr(args, "mesh", None):
        _file_target(args.mesh, "--mesh", MESH_OUTPUTS)
    if getattr(args, "out", None):
        _folder_target(args.out, "--out")
    if getattr(args, "urdf", False) or getattr(args, "mjcf", False):
        _check_sim_options(args)


def _check_sim_options(args) -> None:
    """--urdf and --mjcf: they need --out, a usable --name, and positive --density and
    --scale; their files must be writable."""
    from .io.sim import NAME, _positive

    if not args.out:
        raise ValueError("--urdf and --mjcf write into the --out folder: give --out DIR")
    if not NAME.fullmatch(args.name):
        raise ValueError(f"--name {args.name!r}: use letters, digits, '_', '.' or '-'")
    for flag, value in (("--density", args.density), ("--scale", args.scale)):
        _positive(value, flag)
    for flag, suffix in (("--urdf", ".urdf"), ("--mjcf", ".xml")):
        if getattr(args, flag[2:]):
            _file_target(str(Path(args.out) / f"{args.name}{suffix}"), flag)


# ----- writing and printing ------------------------------------------------------------


def _write_json(path, payload) -> None:
    with replacing(path) as part:
        part.write_text(json.dumps(payload, indent=1))
    print(f"wrote {path}")


def _write_mesh(path, meshes) -> None:
    """One mesh file of the given trimesh meshes (concatenated, colours kept)."""
    import trimesh

    with replacing(path) as part:
        trimesh.util.concatenate(list(meshes)).export(part)
    print(f"wrote {path}")


def _print_model(model, title):
    params = model.to_dict()
    print(f"{title} {params.pop('type')}:")
    for name, value in params.items():
        text = np.array2string(np.asarray(value), precision=6, prefix=" " * 14)
        print(f"  {name:<11} {text}")


def _fit_and_report(points, args, json_path=None, mesh_path=None):
    import jaxfit

    start = time.perf_counter()
    polish = getattr(args, "polish", False)  # (LO on the host: see --polish)
    result = jaxfit.fit(points, args.shape, threshold=args.threshold, key=args.seed,
                        estimator=args.estimator, refine=not polish, polish=polish)
    seconds = time.perf_counter() - start
    _print_model(result.model, "fitted")
    print(f"inliers     {result.num_inliers} of {result.inliers.size} "
          f"(threshold {result.threshold:.6g})")
    print(f"hypotheses  {result.num_hypotheses} ({result.status.value}), "
          f"{seconds:.3f} s including compilation")
    if json_path:
        _write_json(json_path, result.to_dict())
    if mesh_path:
        _write_mesh(mesh_path, [result.model.to_mesh()])
    return result


def _progress(start: float):
    """A stderr printer of progress lines, each ending with the seconds since ``start``
    (the form decompose's own progress lines have)."""
    def say(message: str) -> None:
        print(f"{message} ({time.perf_counter() - start:.2f} s)", file=sys.stderr,
              flush=True)
    return say


# ----- commands ------------------------------------------------------------------------


def _cmd_fit(args):
    from .io import load_points

    points = load_points(args.cloud, num_points=args.num_points, seed=args.seed)
    print(f"{args.cloud}: {len(points)} points")
    _fit_and_report(points, args, args.json, args.mesh)


def _cmd_detect(args):
    from .detect import detect
    from .io.inputs import as_cloud

    start = time.perf_counter()
    points, normals = as_cloud(args.cloud, num_points=args.num_points, seed=args.seed)
    _progress(start)(f"{args.cloud}: {len(points)} points"
                     + (", normals from the file" if normals is not None else ""))
    scene = detect(points, args.shapes, min_inliers=args.min_inliers,
                   threshold=args.threshold, normals=normals, key=args.seed, progress=True)
    _report_scene(scene, len(points), time.perf_counter() - start, args)


def _report_scene(scene, num_points, seconds, args):
    left = len(scene.unassigned)
    print(f"{len(scene.shapes)} primitives from {num_points} points in {seconds:.2f} s "
          f"({left} point{'s' * (left != 1)} unassigned, threshold {scene.threshold:.4g}):")
    for i, found in enumerate(scene.shapes):
        _print_model(found.model, f"shape {i}: {len(found.indices)} points,")
    if args.out:
        print(f"wrote {scene.save(args.out)}")
    if args.json:
        _write_json(args.json, scene.to_dict())
    if args.mesh and not scene.shapes:
        print(f"jaxfit: no primitive found, so no mesh written to {args.mesh}",
              file=sys.stderr)
    elif args.mesh:
        with replacing(args.mesh) as part:
            scene.to_trimesh().export(part)
        print(f"wrote {args.mesh}")


def _report_decomposition(result, args, out):
    print(result.summary())
    for i, part in enumerate(result.parts):
        _print_model(part.model, f"part {i}:")
    if out:
        folder = result.save(out)
        print(f"wrote {folder / 'parts.json'}, {folder / 'decomposition.glb'}, "
              f"{folder / 'preview.png'}")
    if args.json:
        _write_json(args.json, result.to_dict())
    if args.mesh:
        _write_mesh(args.mesh, result.to_scene().geometry.values())
    if not (out or args.json or args.mesh):
        print("jaxfit: nothing written (give --out DIR, --json OUT or --mesh OUT)",
              file=sys.stderr)


def _cmd_decompose(args):
    from .decomposition import decompose

    result = decompose(args.input, method=args.method, max_parts=args.max_parts,
                       gain=args.gain, min_points=args.min_points,
                       num_points=args.num_points, key=args.seed, progress=True)
    _report_decomposition(result, args, args.out)
    if args.urdf or args.mjcf:
        options = {"name": args.name, "density": args.density, "scale": args.scale}
        out = Path(args.out)
        if args.urdf:
            print(f"wrote {result.to_urdf(out / f'{args.name}.urdf', **options)}")
        if args.mjcf:
            print(f"wrote {result.to_mjcf(out / f'{args.name}.xml', **options)}")


def _cmd_demo(args):
    if args.shape is None:
        return _demo_decomposition(args)
    from .evaluation.synthetic import demo_cloud

    points, truth, _ = demo_cloud(args.shape, seed=args.seed)
    print(f"demo: {len(points)} points, half of them uniform outliers, around a known "
          f"{args.shape}")
    _print_model(truth, "true")
    out = Path(args.out) if args.out else None
    _fit_and_report(points, args, args.json or (out and out / "fit.json"),
                    args.mesh or (out and out / f"{args.shape}.ply"))


def _demo_decomposition(args):
    from .decomposition import decompose
    from .evaluation.synthetic import composite

    name = args.object or DEMO_OBJECT
    points, models, _ = composite(name, seed=args.seed)
    print(f"demo: a {name} of {len(points)} points sampled from "
          + ", ".join(m.name for m in models))
    for model in models:
        _print_model(model, "true")
    result = decompose(points, gain=args.gain, key=args.seed, progress=True)
    _report_decomposition(result, args, args.out)


def _cmd_grasp(args):
    from .decomposition import decompose
    from .grasping import ParallelJaw, grasps
    from .io.sim import _positive

    _positive(args.scale, "--scale")
    _checks.positive(args.top, "--top", integer=True)
    width = 0.085 / args.scale if args.gripper_width is None else args.gripper_width
    gripper = ParallelJaw(
        max_width=width,
        finger_depth=0.47 * width if args.finger_depth is None else args.finger_depth,
        finger_width=0.235 * width if args.finger_width is None else args.finger_width)
    result = decompose(args.input, num_points=args.num_points, key=args.seed, progress=True)
    print(result.summary())
    support = None
    if args.floor:
        up = np.zeros(3)
        up["xyz".index(args.floor[-1])] = -1.0 if args.floor[0] == "-" else 1.0
        support = (up, float(np.min(np.asarray(result.points) @ up)))
    found = grasps(result, gripper, key=args.seed, top=args.top, support=support)
    print(f"{len(found)} grasps kept of {found.num_candidates} candidates in "
          f"{found.seconds:.2f} s")
    for i in range(len(found)):
        print(f"  grasp {i}: part {found.parts[i]} ({found.primitives[i]}), score "
              f"{found.scores[i]:.3f}, width {found.widths[i]:.4g}")
    folder = found.save(args.out, result, top=args.top)
    print(f"wrote {folder / 'grasps.json'}, {folder / 'grasps.png'}")


def _cmd_batch(args):
    from . import batch

    summary = batch.run_batch(args.inputs, args.out, task=args.task, shapes=args.shape,
                              workers=args.workers, scheduler=args.scheduler,
                              num_points=args.num_points, seed=args.seed,
                              extensions=args.ext, progress=True)
    print(summary.report())
    return 0 if summary.num_failed == 0 else 1


def _cmd_evaluate(args):
    rows = evaluation.run(args.shape, args.scenario, repeats=args.repeats, count=args.count,
                          seed=args.seed, normals=args.normals, estimator=args.estimator)
    out = evaluation.write(rows, args.out)
    print(f"{len(rows)} fits; wrote {out / 'runs.csv'}, {out / 'summary.md'} and plots")


def _cmd_warmup(args):
    from .warmup import warmup

    if _cache.compilation_cache_dir() is None:
        raise ValueError("warmup fills the compilation cache, which is off in this process "
                         f"(unset {_cache.ENV_SWITCH}=0, or configure JAX's cache)")
    start = time.perf_counter()
    warmup(args.shapes, buckets=args.buckets, say=_progress(start))
    print(f"kernels compiled and stored in {_cache.compilation_cache_dir()} "
          f"({time.perf_counter() - start:.1f} s)")


#: The object ``demo`` decomposes and the folder it writes when none is given.
DEMO_OBJECT = "mallet"
DEMO_OUT = "jaxfit-demo"

# ----- the parser ----------------------------------------------------------------------


def _version() -> str:
    import jax

    from . import __version__

    return f"jaxfit {__version__} (jax {jax.__version__})"


def _threshold(parser) -> None:
    parser.add_argument("--threshold", type=float, default=None,
                        help="inlier distance (default: 0.5%% of the bounding-box diagonal)")


def _seed(p, what="sampling and fitting"):
    p.add_argument("--seed", type=int, default=0,
                   help=f"random seed of the {what}: the same seed gives the same result "
                        "(default 0)")


def _num_points(p):
    p.add_argument("--num-points", type=int, default=20000, metavar="N",
                   help="points sampled from a mesh's surface (default 20000; point files "
                        "are read as stored)")


def _outputs(p, what):
    p.add_argument("--json", metavar="OUT.json", help=f"write {what} as JSON")
    p.add_argument("--mesh", metavar="OUT",
                   help=f"write {what} as one mesh ({', '.join(MESH_OUTPUTS)})")


def _add_fit(sub):
    fit = sub.add_parser("fit", help="fit one primitive to a point cloud or mesh file",
                         description="Fit one primitive to a point cloud or mesh file and "
                                     "print its parameters and inlier count.")
    fit.add_argument("cloud", help="input file: .ply .obj .stl .off .glb .gltf .iv .xyz "
                                   ".txt .csv .crd .pts .npy")
    _num_points(fit)
    _fit_options(fit, required=True)
    fit.add_argument("--polish", action="store_true",
                     help="refit on the host instead of LO's compiled program "
                          "(FitOptions.polish): a first run compiles one program, not two; "
                          "as accurate or more, slower once compiled")
    _outputs(fit, "the fitted primitive")
    fit.set_defaults(run=_cmd_fit)


def _fit_options(p, required):
    p.add_argument("--shape", required=required, choices=list(REGISTRY),
                   help="the primitive to fit")
    _threshold(p)
    _seed(p)
    p.add_argument("--estimator", choices=ESTIMATORS, default=None,
                   help="minimal-sample estimator (default: the shape's best)")


def _add_detect(sub):
    from .detect import DEFAULT_SHAPES

    detect = sub.add_parser(
        "detect", help="find several primitives in one scene",
        description="Find several primitives in one cloud, the best-supported first, "
                    "until none has --min-inliers points.")
    detect.add_argument("cloud", help="input file (as for fit)")
    detect.add_argument("--shapes", nargs="+", default=list(DEFAULT_SHAPES),
                        choices=list(REGISTRY), metavar="SHAPE",
                        help="candidate shapes, simplest first (default: "
                             f"{' '.join(DEFAULT_SHAPES)}; choices: {', '.join(REGISTRY)})")
    detect.add_argument("--min-inliers", type=int, default=None, metavar="M",
                        help="smallest primitive worth reporting (default 1%% of the points)")
    _threshold(detect)
    _num_points(detect)
    _seed(detect)
    detect.add_argument("--out", metavar="DIR",
                        help="folder for the scene's files (Scene.save)")
    _outputs(detect, "the primitives found")
    detect.set_defaults(run=_cmd_detect)


def _add_decompose(sub):
    decompose = sub.add_parser(
        "decompose", help="decompose an object into primitives",
        description="Decompose an object into primitives (the PSDA) and print its parts.")
    decompose.add_argument("input", help="mesh, point file or Open Inventor .iv model")
    decompose.add_argument("--gain", type=float, default=None,
                           help="(--method thesis) split a box while its children's volume "
                                "/ its volume < gain; nearer 1 splits more (default 0.96)")
    decompose.add_argument("--min-points", type=int, default=None, metavar="M",
                           help="smallest part (default 2%% of the points)")
    decompose.add_argument("--method", choices=("thesis", "measured"), default="thesis",
                           help="thesis: the PSDA (box cuts, lowest mean distance); "
                                "measured: greedy splits by the two-sided score "
                                "(default thesis)")
    decompose.add_argument("--max-parts", type=int, default=None, metavar="N",
                           help="at most N parts (a positive integer; default: no limit "
                                "for the thesis, 8 for measured)")
    _num_points(decompose)
    _seed(decompose)
    decompose.add_argument("--out", metavar="DIR",
                           help="folder for parts.json, decomposition.glb, preview.png")
    _outputs(decompose, "the parts")
    decompose.add_argument("--urdf", action="store_true",
                           help="also write the primitives as a URDF robot, DIR/NAME.urdf")
    decompose.add_argument("--mjcf", action="store_true",
                           help="also write them as a MuJoCo model, DIR/NAME.xml")
    decompose.add_argument("--name", default=None,
                           help="--urdf/--mjcf: the body's name and file stem (object)")
    decompose.add_argument("--density", type=float, default=None,
                           help="--urdf/--mjcf: mass per unit volume in written units (1000)")
    decompose.add_argument("--scale", type=float, default=None,
                           help="--urdf/--mjcf: multiplies every length (0.001 for a model "
                                "in millimetres; default 1)")
    decompose.set_defaults(run=_cmd_decompose)


def _add_grasp(sub):
    grasp = sub.add_parser(
        "grasp", help="plan parallel-jaw grasps on an object's primitives",
        description="Decompose an object and plan parallel-jaw grasps on its primitives.")
    grasp.add_argument("input", help="mesh, point file or Open Inventor .iv model")
    grasp.add_argument("--out", required=True, metavar="DIR",
                       help="folder for grasps.json and grasps.png")
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
    grasp.add_argument("--floor", choices=["x", "y", "z", "-x", "-y", "-z"], default=None,
                       help="the object stands on a table under its lowest point along this "
                            "up axis: grasps that would reach the table are dropped "
                            "(default: floating, every direction allowed)")
    _num_points(grasp)
    _seed(grasp)
    grasp.set_defaults(run=_cmd_grasp)


def _add_batch(sub):
    from .batch import TASKS

    batch = sub.add_parser(
        "batch", help="run fit, detect or decompose on every model of a dataset",
        description="Run one task on every model of a dataset: one output folder per "
                    "model, summary.csv and summary.json in --out. A failed model is "
                    "recorded and the run goes on; a rerun skips the models already done.")
    batch.add_argument("inputs", nargs="+", metavar="INPUT",
                       help="model files, folders (searched recursively by extension), "
                            "globs ('scans/**/*.ply') or manifests (.jsonl, or .csv with a "
                            "'path' column)")
    batch.add_argument("--out", required=True, metavar="DIR",
                       help="output folder: DIR/MODEL/ per model, DIR/summary.csv, "
                            "DIR/summary.json")
    batch.add_argument("--task", choices=TASKS, default="decompose",
                       help="what to do with each model (default decompose)")
    batch.add_argument("--shape", nargs="+", choices=list(REGISTRY), metavar="SHAPE",
                       default=None,
                       help="fit: the one primitive to fit (required); detect, decompose: "
                            "the candidate shapes (default: theirs)")
    batch.add_argument("--workers", type=int, default=None, metavar="N",
                       help="local worker processes, each keeping its compiled kernels "
                            "(default 1; 0 runs in this process); with --scheduler local "
                            "the LocalCluster's workers; not with a scheduler address")
    batch.add_argument("--scheduler", metavar="ADDRESS", default=None,
                       help="run on Dask distributed: 'local' (a LocalCluster of --workers "
                            "processes) or a scheduler address tcp://HOST:PORT; needs "
                            "pip install 'jaxfit[cluster]'")
    batch.add_argument("--ext", nargs="+", default=None, metavar="EXT",
                       help="extensions a folder or glob is searched for, e.g. .obj .ply "
                            "(default: every format jaxfit reads)")
    _num_points(batch)
    _seed(batch)
    batch.set_defaults(run=_cmd_batch)


def _add_demo(sub):
    demo = sub.add_parser(
        "demo", help="decompose a built-in object (no input needed); with --shape, fit one "
                     "primitive among outliers instead",
        description="Decompose a built-in object made of known primitives, or with "
                    "--shape fit one primitive among outliers; no input file needed.")
    demo.add_argument("--object", default=None, choices=COMPOSITES,
                      help=f"the built-in object to decompose (default {DEMO_OBJECT})")
    demo.add_argument("--out", default=None, metavar="DIR",
                      help=f"output folder (default ./{DEMO_OUT} for a decomposition; "
                           "with --shape, DIR/fit.json and DIR/SHAPE.ply)")
    demo.add_argument("--gain", type=float, default=None,
                      help="the decomposition's split threshold, as in decompose (0.96)")
    _fit_options(demo, required=False)
    _outputs(demo, "the fit or the parts")
    demo.set_defaults(run=_cmd_demo)


def _add_evaluate(sub):
    evaluate = sub.add_parser(
        "evaluate", help="the thesis's RN/RNIM/SN/SNIM evaluation: CSV, tables and plots",
        description="The thesis's evaluation: fits on synthetic clouds per scenario and "
                    "noise level, written as CSV, tables and plots.")
    evaluate.add_argument("--shape", nargs="+", default=list(evaluation.SHAPES),
                          choices=list(REGISTRY), help="primitives to evaluate (default all)")
    evaluate.add_argument("--scenario", nargs="+", default=list(scenarios.SCENARIOS),
                          choices=scenarios.SCENARIOS, help="scenarios (default all)")
    evaluate.add_argument("--repeats", type=int, default=10, help="clouds per level (10)")
    evaluate.add_argument("--count", type=int, default=2000, help="points per cloud (2000)")
    evaluate.add_argument("--seed", type=int, default=0,
                          help="seed of the first cloud; cloud i uses seed + i (default 0)")
    evaluate.add_argument("--out", default="evaluation", metavar="DIR",
                          help="output folder (./evaluation)")
    evaluate.add_argument("--estimator", choices=ESTIMATORS, default=None,
                          help="minimal-sample estimator (default: each shape's best)")
    evaluate.add_argument("--normals", choices=evaluation.NORMALS, default="estimated",
                          help="normals the oriented estimators read (default: estimated)")
    evaluate.set_defaults(run=_cmd_evaluate)


def _add_warmup(sub):
    warmup = sub.add_parser(
        "warmup", help="compile and store the kernels now, so later runs start warm",
        description="Compile jaxfit's kernels into the compilation cache (once per "
                    "machine and jaxfit version), so that later runs start warm.")
    warmup.add_argument("--shapes", nargs="+", default=None, choices=list(REGISTRY),
                        metavar="SHAPE",
                        help=f"primitives to compile for (default all: {', '.join(REGISTRY)})")
    warmup.add_argument("--buckets", nargs="+", type=int, default=None, metavar="N",
                        help="point buckets (powers of two a cloud is padded to) to compile "
                             "for (default: 1024 2048 16384: clouds of up to 1,024 and "
                             "2,048 points, every decomposition, and clouds of "
                             "8,193-16,384 points)")
    warmup.set_defaults(run=_cmd_warmup)


def _parser():
    parser = _Parser(prog="jaxfit", description=DESCRIPTION, epilog=EPILOG,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_fit, _add_detect, _add_decompose, _add_grasp, _add_batch, _add_demo,
                _add_evaluate, _add_warmup):
        add(sub)
    return parser


def _quiet_stdout() -> None:
    """Point stdout at /dev/null: the reader of a pipe left (``jaxfit ... | head``), and
    Python's final flush must not print a BrokenPipeError."""
    with contextlib.suppress(OSError, ValueError):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def main(argv=None) -> int:
    """Run the command line; returns the exit status: 0, 2 for bad input (a message
    naming it), 1 for any other error (its one-line message; the traceback with
    JAXFIT_DEBUG=1) or a batch with failed models, 130 when interrupted."""
    try:
        args = _parser().parse_args(argv)
        _check_flags(args)
        _check_outputs(args)
        # (batch: its workers compile, its progress says so; warmup: compiling is its job;
        # the notice shows when the first program is about to compile, not before the
        # input is read)
        _cache.announce(None if args.command in ("batch", "warmup") else
                        _cache.compile_notice())
        status = args.run(args) or 0
        sys.stdout.flush()  # a closed pipe shows here, not in Python's exit
    except SystemExit as exit_:  # --help, --version, a usage error
        try:
            sys.stdout.flush()
        except BrokenPipeError:
            _quiet_stdout()
        return exit_.code if isinstance(exit_.code, int) else 2
    except BrokenPipeError:  # `jaxfit ... | head`: the reader left; say nothing more
        _quiet_stdout()
        return 1
    except KeyboardInterrupt:
        print("jaxfit: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError) as err:  # bad input or an unusable file: a message
        print(f"jaxfit: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except Exception as err:  # anything else (a MemoryError, a bug): still no traceback
        if os.environ.get(DEBUG_ENV):
            raise
        print(f"jaxfit: error: {type(err).__name__}: {_one_line(err)} (set {DEBUG_ENV}=1 "
              "for the traceback)", file=sys.stderr)
        return 1
    finally:
        _cache.announce(None)  # (a run that never compiled leaves no notice behind)
    return status


def entry() -> int:
    """The ``jaxfit`` command (and ``python -m jaxfit``): ``main``, then every object the
    process holds moved out of the cyclic collector's reach (``gc.freeze``) before it
    exits. Why: the interpreter's final collections walk the ~180,000 objects that JAX,
    SciPy and matplotlib leave, 0.35-0.65 s of a 3 s warm ``jaxfit demo``, for a process
    about to end (docs/engine.md, "Session 35"). ``main`` itself leaves the collector
    alone: it also runs inside other processes (the tests)."""
    status = main()
    gc.freeze()
    return status


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split())


if __name__ == "__main__":
    sys.exit(entry())
