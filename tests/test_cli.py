"""The command line: demo, fit on files, JSON and mesh output, errors as messages."""

import json
import os
import re

import numpy as np
import pytest
import trimesh

from jaxfit.cli import main
from jaxfit.evaluation.synthetic import demo_cloud


def test_demo_writes_json_and_mesh(tmp_path, capsys):
    out_json, out_mesh = tmp_path / "fit.json", tmp_path / "fit.ply"
    argv = ["demo", "--shape", "sphere", "--json", str(out_json), "--mesh", str(out_mesh)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "true sphere" in printed and "fitted sphere" in printed and "inliers" in printed
    payload = json.loads(out_json.read_text())
    assert payload["model"]["type"] == "sphere" and payload["num_points"] == 2000
    _, truth, _ = demo_cloud("sphere", seed=0)
    assert abs(payload["model"]["radius"] / truth.radius - 1) < 0.01
    mesh = trimesh.load(out_mesh)
    assert np.allclose(mesh.bounding_sphere.primitive.center, truth.center, atol=0.02)


def test_fit_reads_a_point_file(tmp_path, capsys):
    points, _, _ = demo_cloud("plane", seed=1)
    path = tmp_path / "cloud.xyz"
    np.savetxt(path, points)
    assert main(["fit", str(path), "--shape", "plane", "--threshold", "0.02"]) == 0
    printed = capsys.readouterr().out
    assert "fitted plane" in printed and "2000 points" in printed
    assert "threshold 0.02" in printed


def test_fit_polish_refits_on_the_host(tmp_path, capsys):
    # --polish: FitOptions.polish, the same draws; the host refit's plane is as close to
    # the truth as LO's (2000 points, the demo's noise), and its cost is no higher.
    points, truth, _ = demo_cloud("plane", seed=1)
    path = tmp_path / "cloud.npy"
    np.save(path, points)
    found = {}
    for flags in ([], ["--polish"]):
        out = tmp_path / f"{len(flags)}.json"
        assert main(["fit", str(path), "--shape", "plane", "--json", str(out), *flags]) == 0
        found[len(flags)] = json.loads(out.read_text())
    lo, host = found[0], found[1]
    assert host["num_hypotheses"] == lo["num_hypotheses"]
    assert host["cost"] <= lo["cost"] * (1 + 1e-6)
    for payload in (lo, host):
        assert abs(abs(np.dot(payload["model"]["normal"], truth.normal)) - 1) < 1e-6


def test_fit_takes_the_estimator(tmp_path, capsys):
    points, truth, _ = demo_cloud("cylinder", seed=1)
    path = tmp_path / "cloud.npy"
    np.save(path, points)
    for name in ("thesis", "oriented"):
        out = tmp_path / f"{name}.json"
        assert main(["fit", str(path), "--shape", "cylinder", "--estimator", name,
                     "--json", str(out)]) == 0
        payload = json.loads(out.read_text())
        assert abs(payload["model"]["radius"] / truth.radius - 1) < 0.01
    thesis = json.loads((tmp_path / "thesis.json").read_text())["num_hypotheses"]
    oriented = json.loads((tmp_path / "oriented.json").read_text())["num_hypotheses"]
    assert oriented < thesis


def test_errors_are_messages_not_tracebacks(tmp_path, capsys):
    assert main(["fit", str(tmp_path / "missing.xyz"), "--shape", "plane"]) == 2
    assert "jaxfit: error:" in capsys.readouterr().err
    path = tmp_path / "two.xyz"
    np.savetxt(path, np.random.default_rng(0).normal(size=(2, 3)))
    assert main(["fit", str(path), "--shape", "sphere"]) == 2
    assert "too few points" in capsys.readouterr().err


def test_shape_and_estimator_choices_come_from_the_registry(monkeypatch, capsys):
    import pytest

    from jaxfit.cli import _parser
    from jaxfit.shapes import REGISTRY, Sphere
    from jaxfit.shapes._base import ESTIMATORS

    for name in REGISTRY:
        assert _parser().parse_args(["fit", "x.npy", "--shape", name]).shape == name
    for name in ESTIMATORS:
        args = _parser().parse_args(["fit", "x.npy", "--shape", "cone", "--estimator", name])
        assert args.estimator == name
    with pytest.raises(SystemExit):
        _parser().parse_args(["fit", "x.npy", "--shape", "torus"])
    assert "invalid choice: 'torus'" in capsys.readouterr().err
    # A newly registered primitive is a choice at once, in fit and in evaluate.
    monkeypatch.setitem(REGISTRY, "torus", Sphere)
    assert _parser().parse_args(["fit", "x.npy", "--shape", "torus"]).shape == "torus"
    assert _parser().parse_args(["evaluate", "--shape", "torus"]).shape == ["torus"]


def test_output_paths_are_checked_before_any_work(tmp_path, capsys, monkeypatch):
    """A bad --json, --mesh or --out fails at once, naming the flag (it had failed only
    after the whole fit or decomposition)."""
    import jaxfit

    def never(*args, **kwargs):
        raise AssertionError("the work started")

    monkeypatch.setattr(jaxfit, "fit", never)
    cloud = tmp_path / "cloud.npy"
    np.save(cloud, np.zeros((10, 3)))
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    cases = [(["--json", str(tmp_path)], "--json .* is a folder"),
             (["--json", str(tmp_path / "missing" / "x.json")], "does not exist"),
             (["--mesh", str(tmp_path / "m.xyz2")], "unsupported extension '.xyz2'.*.ply")]
    for extra, message in cases:
        assert main(["fit", str(cloud), "--shape", "plane", *extra]) == 2
        err = capsys.readouterr().err
        assert re.search(message, err), err
    assert main(["decompose", str(cloud), "--out", str(a_file)]) == 2
    assert "--out" in (err := capsys.readouterr().err) and "is a file, not a folder" in err


def test_an_unexpected_error_is_one_line(tmp_path, capsys, monkeypatch):
    import jaxfit.io

    def broken(*args, **kwargs):
        raise IndexError("face index 7 out of range")

    monkeypatch.setattr(jaxfit.io, "load_points", broken)
    monkeypatch.delenv("JAXFIT_DEBUG", raising=False)
    assert main(["fit", str(tmp_path / "x.ply"), "--shape", "plane"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("jaxfit: error: IndexError: face index 7") and "Traceback" not in err



def test_the_compile_notice_waits_for_a_compile(tmp_path, capsys, monkeypatch):
    """The first-run notice shows when a program is about to compile: a run that stops
    on its input says only what is wrong, and leaves no notice for later calls."""
    from jaxfit import _cache

    monkeypatch.setattr(_cache, "compile_notice", lambda: "jaxfit: compiling kernels (test)")
    bad = tmp_path / "bad.xyz"
    bad.write_text("1 2 3\n4 five 6\n")
    assert main(["fit", str(bad), "--shape", "plane"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxfit: error: non-numeric value") and "compiling" not in err
    assert _cache._notice == []
    _cache.announce("jaxfit: compiling kernels (test)")
    try:  # (a first call of a program this process has not run prints it, once)
        _cache._announce()
        _cache._announce()
    finally:
        _cache.announce(None)
    assert capsys.readouterr().err.count("compiling kernels (test)") == 1


@pytest.mark.slow
def test_a_first_run_says_it_compiles_and_a_second_does_not(tmp_path):
    """A fresh machine's first CLI run compiles for seconds: it says so once, on stderr,
    and a later run with the kernels stored stays quiet."""
    import subprocess
    import sys

    env = {**os.environ, "JAXFIT_CACHE_DIR": str(tmp_path / "cache")}
    code = ("import sys; from jaxfit import cli; "
            "sys.exit(cli.main(['demo', '--shape', 'sphere', '--out', sys.argv[1]]))")
    runs = [subprocess.run([sys.executable, "-c", code, str(tmp_path / f"out{i}")], env=env,
                           capture_output=True, text=True, timeout=300) for i in range(2)]
    assert [r.returncode for r in runs] == [0, 0], runs[0].stderr
    assert runs[0].stderr.count("jaxfit: compiling kernels (first run only") == 1
    assert "compiling kernels" not in runs[1].stderr
    off = subprocess.run([sys.executable, "-c", code, str(tmp_path / "out2")],
                         env={**env, "JAXFIT_CACHE": "0"}, capture_output=True, text=True,
                         timeout=300)
    assert "the compilation cache is off" in off.stderr


def _never(*args, **kwargs):
    raise AssertionError("the work started")


def test_every_bad_output_path_fails_at_once_in_one_line(tmp_path, capsys, monkeypatch):
    """Each command's output paths are checked before any work: rc 2 and one line on
    stderr naming the flag (and, for a bad extension, the formats that work)."""
    import importlib

    import jaxfit

    for module, name in ((jaxfit, "fit"), (jaxfit, "decomposition.decompose"),
                         (jaxfit, "detect.detect")):
        *path, attribute = name.split(".")
        target = importlib.import_module(".".join(["jaxfit", *path])) if path else module
        monkeypatch.setattr(target, attribute, _never)
    cloud = tmp_path / "cloud.npy"
    np.save(cloud, np.zeros((10, 3)))
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    missing = tmp_path / "missing" / "x.json"
    c = str(cloud)
    cases = [
        (["fit", c, "--shape", "plane", "--json", str(tmp_path / "x.txt")],
         r"--json .*unsupported extension '.txt'; use one of .json"),
        (["fit", c, "--shape", "plane", "--mesh", str(tmp_path / "m.gltf")],
         r"--mesh .*'.gltf'; use one of .ply, .stl, .obj, .off, .glb"),
        (["detect", c, "--out", str(a_file)], "--out .* is a file, not a folder"),
        (["detect", c, "--json", str(missing)], "--json .* does not exist"),
        (["detect", c, "--mesh", str(tmp_path)], "--mesh .* is a folder"),
        (["decompose", c, "--json", str(tmp_path)], "--json .* is a folder"),
        (["decompose", c, "--urdf"], "--urdf and --mjcf write into the --out folder"),
        (["decompose", c, "--method", "greedy"], "invalid choice: 'greedy'"),
        (["demo", "--json", str(missing)], "--json .* does not exist"),
        (["demo", "--out", str(a_file)], "--out .* is a file"),
        (["demo", "--shape", "sphere", "--out", str(a_file)], "--out .* is a file"),
        (["demo", "--shape", "sphere", "--object", "lamp"], "give one of them"),
        (["grasp", c, "--out", str(a_file)], "--out .* is a file"),
        (["evaluate", "--out", str(a_file)], "--out .* is a file"),
        (["batch", c, "--out", str(a_file)], "--out .* is a file"),
        (["fit", c, "--shape", "plane", "--bogus"], "unrecognized arguments: --bogus"),
        # Options the command would not read are refused, not ignored.
        (["decompose", c, "--out", str(tmp_path), "--scale", "0.001"],
         "--scale set the --urdf/--mjcf files"),
        (["demo", "--shape", "sphere", "--gain", "0.9"], "--gain applies to the decomposition"),
        (["decompose", c, "--method", "measured", "--gain", "0.9"],
         "--method measured does not read it"),
        (["demo", "--threshold", "0.01"], "--threshold and --estimator apply to the fit demo"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert re.search(message, err) and err.count("\n") == 1, (argv, err)


def test_version_and_help_texts(capsys):
    """--version; every option of every command has a help text, in plain text."""
    from jaxfit import __version__
    from jaxfit.cli import _parser

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.startswith(f"jaxfit {__version__} (jax ")
    commands = _parser()._subparsers._group_actions[0].choices
    assert {"fit", "detect", "decompose", "grasp", "batch", "demo", "evaluate",
            "warmup"} <= set(commands)
    for name, command in commands.items():
        for action in command._actions:
            assert action.help, f"{name} {action.option_strings or action.dest}: no help"
        assert main([name, "--help"]) == 0
        text = capsys.readouterr().out
        assert "``" not in text and ":class:" not in text, name
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "``" not in text and "jaxfit batch" in text


def test_entry_returns_mains_status_and_freezes_the_collector(monkeypatch, capsys, tmp_path):
    """The command's entry point (``jaxfit``, ``python -m jaxfit``) returns ``main``'s
    status, success or bad input, and leaves the objects frozen (``gc.freeze``), so the
    interpreter's final collections skip them; ``main`` alone leaves the collector be."""
    import gc
    import sys

    from jaxfit.cli import entry

    gc.unfreeze()
    try:
        assert main(["--version"]) == 0 and gc.get_freeze_count() == 0
        monkeypatch.setattr(sys, "argv", ["jaxfit", "--version"])
        assert entry() == 0 and gc.get_freeze_count() > 0
        gc.unfreeze()
        missing = str(tmp_path / "missing.npy")
        monkeypatch.setattr(sys, "argv", ["jaxfit", "fit", missing, "--shape", "plane"])
        assert entry() == 2 and gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()
    assert "missing.npy" in capsys.readouterr().err


def test_demo_fit_honours_out(tmp_path, capsys):
    """demo --shape S --out DIR writes the fit's JSON and mesh there (it ignored --out)."""
    assert main(["demo", "--shape", "sphere", "--out", str(tmp_path / "demo")]) == 0
    assert "wrote" in capsys.readouterr().out
    payload = json.loads((tmp_path / "demo" / "fit.json").read_text())
    assert payload["model"]["type"] == "sphere" and payload["num_points"] == 2000
    assert trimesh.load(tmp_path / "demo" / "sphere.ply").vertices.shape[1] == 3


def test_a_closed_pipe_prints_no_traceback():
    """`jaxfit --help | head -1`: the reader leaves before the output is flushed; no
    BrokenPipeError reaches the user."""
    import subprocess
    import sys

    process = subprocess.Popen([sys.executable, "-m", "jaxfit", "--help"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    process.stdout.close()  # the reader is gone before anything is written
    err = process.stderr.read().decode()
    assert process.wait(timeout=120) in (0, 1)
    assert "BrokenPipeError" not in err and "Traceback" not in err, err


def test_warmup_compiles_into_the_cache_or_refuses_without_one(capsys, monkeypatch):
    from jaxfit import _cache

    assert main(["warmup", "--shapes", "sphere", "--buckets", "2048"]) == 0
    captured = capsys.readouterr()
    assert "warmed sphere/2048" in captured.err and "kernels compiled and stored" in captured.out
    monkeypatch.setattr(_cache, "compilation_cache_dir", lambda: None)
    assert main(["warmup"]) == 2
    assert "the compilation cache, which is off" in capsys.readouterr().err


@pytest.mark.slow
def test_detect_writes_its_scene_and_prints_progress_on_stderr(tmp_path, capsys):
    from jaxfit.evaluation.synthetic import scene

    points, _, _ = scene(200, objects=["sphere", "lying_cylinder"], count=3000)  # test_detect's
    cloud = tmp_path / "scene.npy"
    np.save(cloud, points)
    out, js, mesh = tmp_path / "out", tmp_path / "scene.json", tmp_path / "scene.ply"
    assert main(["detect", str(cloud), "--out", str(out), "--json", str(js), "--mesh",
                 str(mesh)]) == 0
    captured = capsys.readouterr()
    assert "round 0:" in captured.err and "round 0:" not in captured.out
    assert re.search(r"\d+ primitives from \d+ points", captured.out)
    assert {"scene.json", "scene.glb", "points.npy", "preview.png"} <= {
        p.name for p in out.iterdir()}
    assert json.loads(js.read_text()) == json.loads((out / "scene.json").read_text())
    assert len(trimesh.load(mesh).vertices) > 0


@pytest.mark.slow
def test_demo_honours_json_and_mesh_and_decompose_without_out_prints_the_parts(
        tmp_path, capsys, monkeypatch):
    import jaxfit.decomposition
    from jaxfit.decomposition import Decomposition

    js, mesh, out = tmp_path / "demo.json", tmp_path / "demo.glb", tmp_path / "demo"
    assert main(["demo", "--object", "lollipop", "--out", str(out), "--json", str(js),
                 "--mesh", str(mesh)]) == 0
    captured = capsys.readouterr()
    assert re.search(r"box decomposition: \d+ parts \(\d+\.\d\d s\)", captured.err)
    assert len(json.loads(js.read_text())["parts"]) >= 2
    assert (out / "parts.json").is_file() and len(trimesh.load(mesh).geometry) >= 1
    # decompose without --out, --json or --mesh: the parts on stdout, a note on stderr
    # (the demo's decomposition stands in for a second one).
    monkeypatch.setattr(jaxfit.decomposition, "decompose",
                        lambda *args, **kwargs: Decomposition.load(out))
    assert main(["decompose", str(out / "points.npy")]) == 0
    captured = capsys.readouterr()
    assert re.search(r"\d+ parts from \d+ points", captured.out) and "part 0:" in captured.out
    assert captured.err.strip().endswith("nothing written (give --out DIR, --json OUT or "
                                         "--mesh OUT)")


def test_decompose_passes_method_and_max_parts(tmp_path, capsys, monkeypatch):
    """--method and --max-parts reach decompose (defaults: the thesis, no limit)."""
    import jaxfit.decomposition

    seen = []

    def recorded(source, **kwargs):
        seen.append(kwargs)
        raise ValueError("recorded")

    cloud = tmp_path / "c.npy"
    np.save(cloud, np.zeros((10, 3)))
    assert main(["decompose", str(cloud), "--max-parts", "0"]) == 2
    assert "max_parts must be a positive integer, got 0" in capsys.readouterr().err
    monkeypatch.setattr(jaxfit.decomposition, "decompose", recorded)
    assert main(["decompose", str(cloud), "--method", "measured", "--max-parts", "3"]) == 2
    assert main(["decompose", str(cloud)]) == 2
    assert "recorded" in capsys.readouterr().err
    assert (seen[0]["method"], seen[0]["max_parts"]) == ("measured", 3)
    assert (seen[1]["method"], seen[1]["max_parts"]) == ("thesis", None)
