"""The evaluation runner end to end on a small setting, from Python and the CLI."""

import csv

import numpy as np

from jaxfit.cli import main
from jaxfit.evaluation import evaluate, scenarios


def test_run_and_write(tmp_path):
    rows = evaluate.run(("sphere",), ("RN", "SNIM"), repeats=2, count=600, progress=False)
    assert len(rows) == 2 * (len(scenarios.RN_LEVELS) + len(scenarios.SN_LEVELS))
    assert {r["seed"] for r in rows} == {0, 1}
    rn60 = [r for r in rows if r["scenario"] == "RN" and r["level"] == 0.6]
    assert all(r["center_rel"] < 0.01 and r["recall"] > 0.95 for r in rn60)
    out = evaluate.write(rows, tmp_path)
    with open(out / "runs.csv") as f:
        assert len(list(csv.DictReader(f))) == len(rows)
    text = (out / "summary.md").read_text()
    assert "### sphere, RN" in text and "### sphere, SNIM" in text
    assert (out / "sphere.png").stat().st_size > 10_000


def test_summary_means_and_medians():
    rows = [{"shape": "sphere", "scenario": "RN", "level": 0.1, "center_rel": v,
             "radius_rel": 0.0, "mee": 0.0, "precision": 1.0, "recall": 1.0, "runtime_s": 1.0}
            for v in (1.0, 2.0, 6.0)]
    (entry,) = evaluate.summarise(rows)
    assert entry["center_rel_mean"] == 3.0 and entry["center_rel_median"] == 2.0
    assert entry["runs"] == 3 and entry["failed"] == 0


def test_threshold_follows_the_noise():
    sn = scenarios.make("sphere", "SN", 0.1, count=300)
    rn = scenarios.make("sphere", "RN", 0.3, count=300)
    assert np.isclose(evaluate.threshold_for(sn), 0.1 * sn.size)
    assert np.isclose(evaluate.threshold_for(rn), 0.01 * rn.size)


def test_cli(tmp_path, capsys):
    argv = ["evaluate", "--shape", "plane", "--scenario", "SN", "--repeats", "1",
            "--count", "300", "--out", str(tmp_path)]
    assert main(argv) == 0
    assert "6 fits" in capsys.readouterr().out
    assert (tmp_path / "plane.png").exists()


def test_shown_measures_come_from_the_shapes():
    from jaxfit.shapes import REGISTRY

    assert set(evaluate.MEASURES) == set(REGISTRY)
    for name, cls in REGISTRY.items():
        assert evaluate.MEASURES[name] == cls.shown_measures
    assert evaluate.MEASURES["sphere"] == ("center_rel", "radius_rel", "mee")


def test_behaviour_compare_reads_the_earlier_run_before_writing_over_it(tmp_path, monkeypatch):
    # `--out F --compare F` (how the committed digests are regenerated) once compared the
    # new run with itself and always said "identical".
    import json

    from benchmarks import behaviour

    monkeypatch.setattr(behaviour, "cases", lambda: [("one", lambda: np.arange(3.0))])
    path = tmp_path / "refit.json"
    path.write_text(json.dumps({"jax": "x", "digests": {"one": "not this digest"}}))
    assert behaviour.main(["--out", str(path), "--compare", str(path)]) == 1
    assert behaviour.main(["--out", str(path), "--compare", str(path)]) == 0
