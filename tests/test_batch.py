"""Whole datasets (jaxfit.batch): inputs, the summary, failures recorded, resuming, worker
processes that die, and a Dask LocalCluster of 2 workers.

Models are demo clouds of 2000 points (bucket 2048, the sphere fit test_cli runs), so the
in-process runs compile nothing new."""

import csv
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxfit import Sphere, batch
from jaxfit.batch import COLUMNS, Job, find_jobs, run_batch
from jaxfit.cli import main
from jaxfit.evaluation.synthetic import demo_cloud


def _models(folder: Path, count: int = 2, bad: bool = True) -> Path:
    """``count`` sphere clouds (sphere0.xyz, ...) and, with ``bad``, a two-point file
    that every task fails on."""
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        np.savetxt(folder / f"sphere{i}.xyz", demo_cloud("sphere", seed=i)[0])
    if bad:
        (folder / "bad.xyz").write_text("0 0 0\n1 1 1\n")
    return folder


def _summary(out: Path) -> dict:
    with open(out / "summary.csv", newline="") as handle:
        rows = {row["model"]: row for row in csv.DictReader(handle)}
    assert list(next(iter(rows.values()))) == list(COLUMNS)
    return rows


def test_inputs_are_files_folders_globs_and_manifests(tmp_path):
    data = tmp_path / "data"
    (data / "a").mkdir(parents=True)
    (data / "a" / "mug.xyz").write_text("0 0 0\n" * 30)
    (data / "a" / "mug.npy").write_bytes(b"x" * 10)  # same stem: names get the extension
    (data / "b.ply").write_text("y" * 20)
    (data / "notes.md").write_text("not a model")
    (data / ".hidden.xyz").write_text("0 0 0\n")
    out = data / "results"  # inside the input folder: its files are never inputs
    out.mkdir()
    (out / "old.ply").write_text("z")
    jobs = find_jobs([data], out)
    assert [j.name for j in jobs] == ["a/mug-npy", "b", "a/mug-xyz"]  # smallest first
    assert [j.size for j in jobs] == sorted(j.size for j in jobs)
    assert [j.name for j in find_jobs([str(data / "**" / "*.ply")], out)] == ["b"]
    assert [j.name for j in find_jobs([data], out, extensions=["xyz"])] == ["a/mug"]
    # The same file twice is one model.
    assert len(find_jobs([data / "b.ply", data / "b.ply"])) == 1
    # Manifests: JSON lines and a CSV with a path column; relative to their folder.
    (data / "list.jsonl").write_text('{"path": "b.ply", "name": "bee"}\n\n'
                                     '{"path": "a/mug.xyz"}\n')
    assert {j.name for j in find_jobs([data / "list.jsonl"])} == {"bee", "mug"}
    (data / "list.csv").write_text("name,path\ncup,a/mug.xyz\n")
    assert [(j.name, Path(j.source)) for j in find_jobs([data / "list.csv"])] == [
        ("cup", (data / "a" / "mug.xyz").resolve())]
    # A point file whose first line is not a header with 'path' is a model, not a list.
    (data / "cloud.csv").write_text("x,y,z\n0,0,0\n")
    assert [j.name for j in find_jobs([data / "cloud.csv"])] == ["cloud"]


@pytest.mark.parametrize("inputs, message", [
    (["missing-folder"], "no such file or folder"),
    (["*.nothing-matches"], "no model file matches"),
    (["empty"], "no model files in"),
    (["list.jsonl"], "model file 'gone.xyz' not found"),
])
def test_bad_inputs_are_one_clear_error(tmp_path, monkeypatch, inputs, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "empty").mkdir()
    (tmp_path / "list.jsonl").write_text('{"path": "gone.xyz"}\n')
    with pytest.raises(ValueError, match=message):
        find_jobs(inputs)


def test_summary_records_failures_and_a_rerun_skips_finished_models(tmp_path, monkeypatch):
    models, out = _models(tmp_path / "models"), tmp_path / "out"
    summary = run_batch([models], out, task="fit", shapes="sphere", workers=0)
    assert (len(summary.rows), summary.num_failed, summary.num_reused) == (3, 1, 0)
    rows = _summary(out)
    assert set(rows) == {"sphere0", "sphere1", "bad"}
    for name in ("sphere0", "sphere1"):
        row = rows[name]
        assert (row["status"], row["task"], row["points"], row["parts"], row["kinds"]) == (
            "ok", "fit", "2000", "1", "sphere:1")
        assert 0.4 < float(row["inlier_fraction"]) < 0.7  # half the demo cloud is outliers
        assert float(row["mean_distance"]) > 0 and float(row["seconds"]) > 0
        fit = json.loads((out / name / "fit.json").read_text())
        truth = demo_cloud("sphere", seed=int(name[-1]))[1]
        assert abs(fit["model"]["radius"] / truth.radius - 1) < 0.01
        assert (out / name / "model.ply").is_file()
    assert rows["bad"]["status"] == "failed" and "too few points" in rows["bad"]["error"]
    assert json.loads((out / "summary.json").read_text())["models"][0]["model"] == "bad"

    # A rerun runs only the failed model and a changed one; the others are reused.
    ran = []
    real = batch.TASK_FUNCTIONS["fit"]
    monkeypatch.setitem(batch.TASK_FUNCTIONS, "fit",
                        lambda source, *rest: ran.append(Path(source).name) or real(source, *rest))
    np.savetxt(models / "sphere1.xyz", demo_cloud("sphere", seed=5)[0])
    again = run_batch([models], out, task="fit", shapes="sphere", workers=0)
    assert sorted(ran) == ["bad.xyz", "sphere1.xyz"]
    assert {r["model"]: r["reused"] for r in again.rows} == {
        "bad": False, "sphere0": True, "sphere1": False}
    # Other options, or a finished model's file removed: run again.
    ran.clear()
    (out / "sphere0" / "model.ply").unlink()
    run_batch([models], out, task="fit", shapes="sphere", workers=0)
    assert sorted(ran) == ["bad.xyz", "sphere0.xyz"]
    ran.clear()
    run_batch([models], out, task="fit", shapes="sphere", workers=0, seed=1)
    assert len(ran) == 3
    # The same shape spelled otherwise (a class, capitals) is the same options: reused.
    ran.clear()
    run_batch([models], out, task="fit", shapes=[Sphere], workers=0, seed=1)
    run_batch([models], out, task="fit", shapes=" Sphere", workers=0, seed=1)
    assert ran == ["bad.xyz", "bad.xyz"]


def test_bad_arguments_fail_before_any_model_runs(tmp_path, monkeypatch):
    models = _models(tmp_path / "models", count=1, bad=False)
    monkeypatch.setattr(batch, "run_model", lambda *a, **k: pytest.fail("a model ran"))
    cases = [({"task": "segment"}, "unknown task 'segment'"),
             ({"task": "fit"}, "exactly one shape"),
             ({"task": "fit", "shapes": ["plane", "sphere"]}, "exactly one shape"),
             ({"shapes": ["torus"]}, "unknown shape 'torus'"),
             ({"workers": -1}, "non-negative integer"),
             ({"workers": 2, "scheduler": "tcp://127.0.0.1:1"}, "has its own workers")]
    for options, message in cases:
        with pytest.raises(ValueError, match=message):
            run_batch([models], tmp_path / "out", **options)
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if Dask were not installed
    with pytest.raises(ValueError, match=r"pip install 'jaxfit\[cluster\]'"):
        run_batch([models], tmp_path / "out", scheduler="local")


def test_cli_batch_exit_status_and_one_line_errors(tmp_path, capsys, monkeypatch):
    models, out = _models(tmp_path / "models", count=1), tmp_path / "out"
    assert main(["batch", str(models), "--out", str(out), "--task", "fit", "--shape",
                 "sphere", "--workers", "0"]) == 1  # a model failed
    captured = capsys.readouterr()
    assert "2 models in" in captured.out and "1 ok" in captured.out
    assert "batch: 2/2 models, 1 failed" in captured.err and "models/min" in captured.err
    assert _summary(out)["sphere0"]["status"] == "ok"
    monkeypatch.setitem(sys.modules, "distributed", None)
    cases = [(["batch", str(tmp_path / "none*.ply"), "--out", str(out)], "no model file"),
             (["batch", str(models), "--out", str(out), "--task", "segment"],
              "invalid choice: 'segment'"),
             (["batch", str(models), "--out", str(models / "bad.xyz")], "not a folder"),
             (["batch", str(models), "--out", str(out), "--scheduler", "local"],
              "needs Dask distributed")]
    for argv, message in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err


def _dies_on_crash(job: Job) -> dict:
    """Task for the process test: a model named crash* kills its worker process."""
    if job.name.startswith("crash"):
        os._exit(3)
    return {"model": job.name, "status": "ok", "reused": False}


@pytest.mark.slow
def test_a_worker_that_dies_is_replaced_and_only_its_model_fails(tmp_path):
    jobs = [Job(name, name, 0) for name in ("a", "b", "crash", "c", "d")]
    rows = []
    batch._run_processes(jobs, _dies_on_crash, rows.append, "fit", workers=2)
    outcome = {row["model"]: row["status"] for row in rows}
    assert outcome == {"a": "ok", "b": "ok", "crash": "failed", "c": "ok", "d": "ok"}
    assert "worker process died" in next(r["error"] for r in rows if r["model"] == "crash")


@pytest.mark.slow
def test_local_cluster_of_two_workers_and_local_processes_give_the_same_summary(tmp_path):
    models = _models(tmp_path / "models", count=3)
    options = {"task": "fit", "shapes": "sphere", "workers": 2}
    dask = run_batch([models], tmp_path / "dask", scheduler="local", **options)
    local = run_batch([models], tmp_path / "local", **options)
    for summary in (dask, local):
        assert [(r["model"], r["status"]) for r in summary.rows] == [
            ("bad", "failed"), ("sphere0", "ok"), ("sphere1", "ok"), ("sphere2", "ok")]
    same = ("parts", "kinds", "points", "inlier_fraction", "mean_distance")
    assert ([[r[k] for k in same] for r in dask.rows]
            == [[r[k] for k in same] for r in local.rows])
    for name in ("sphere0", "sphere1", "sphere2"):
        assert (tmp_path / "dask" / name / "fit.json").is_file()
    # Resumed on a running cluster given as an object (as a dask-jobqueue SLURMCluster
    # would be): nothing but the failed model runs again.
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        again = run_batch([models], tmp_path / "dask", task="fit", shapes="sphere",
                          scheduler=cluster)
    assert again.num_reused == 3 and [r["model"] for r in again.rows if not r["reused"]] == [
        "bad"]


@pytest.mark.slow
def test_detect_and_decompose_tasks_write_their_folders(tmp_path):
    from jaxfit.evaluation.synthetic import composite, scene

    models = tmp_path / "models"
    models.mkdir()
    np.save(models / "scene.npy", scene(200, objects=["sphere", "lying_cylinder"],
                                        count=3000)[0])  # test_detect's scene
    found = run_batch([models], tmp_path / "detect", task="detect", workers=0)
    row = found.rows[0]
    assert row["status"] == "ok" and row["parts"] >= 3 and "plane:" in row["kinds"]
    assert 0.8 < row["inlier_fraction"] <= 1 and row["mean_distance"] > 0
    assert {"scene.json", "scene.glb", "points.npy", "status.json"} <= {
        p.name for p in (tmp_path / "detect" / "scene").iterdir()}
    np.save(models / "scene.npy", composite("lollipop", count=4000, seed=0)[0])
    parts = run_batch([models], tmp_path / "decompose", task="decompose", workers=0)
    row = parts.rows[0]
    assert row["status"] == "ok" and row["parts"] >= 2 and row["inlier_fraction"] == 1.0
    assert {"parts.json", "decomposition.glb", "preview.png"} <= {
        p.name for p in (tmp_path / "decompose" / "scene").iterdir()}
