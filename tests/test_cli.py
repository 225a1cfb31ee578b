"""The command line: demo, fit on files, JSON and mesh output, errors as messages."""

import json

import numpy as np
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
