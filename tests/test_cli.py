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
