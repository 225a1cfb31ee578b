"""decompose's whole-object check, part budget and method="measured" (issue 17): one
part per primitive on the built-in composites, the teapot's body as one part, the split
hierarchy (every part count from one run), and its round trip."""

import numpy as np
import pytest
from conftest import matches

from jaxfit import decompose
from jaxfit.decomposition import Decomposition
from jaxfit.evaluation.synthetic import composite

OBJECTS = ("mallet", "lollipop", "hammer", "lamp")


#: Keys each object is decomposed with: the lamp's stem meets its base plate in a seam
#: that leaves 9-18 points on the wrong side on some keys (its height then 6-8 % off),
#: and which keys depends on the CPU's float rounding: of keys 0-23, 3 on an AMD EPYC
#: (0, 3, 21; docs/engine.md "Session 39"), 5 on an Intel Xeon (0, 2, 10, 21, 22;
#: "Session 41"). So it must be right on two keys in three at least, over nine keys: three
#: (keys 0-2, at most one wrong) had failed on the Xeon with two.
KEYS = {"lamp": tuple(range(9))}


@pytest.fixture(scope="module")
def measured():
    out = {}
    for name in OBJECTS:
        points, models, labels = composite(name, count=4000, seed=1)
        out[name] = ([decompose(points, method="measured", key=k)
                      for k in KEYS.get(name, (0,))], models, labels)
    return out


def _one_part_per_primitive(result, models, labels) -> str | None:
    """Why the measured decomposition is not one right part per primitive, or None."""
    if result.method != "measured" or len(result.parts) != len(models):
        return f"{result.method}: {len(result.parts)} parts for {len(models)} primitives"
    for k, model in enumerate(models):
        counts = [np.sum(labels[p.indices] == k) for p in result.parts]
        part = result.parts[int(np.argmax(counts))]
        if part.kind != model.name:
            return f"the {model.name} became a {part.kind}"
        if not matches(part.model, model, 0.05):
            return f"{part.model!r} against {model!r}"
        if not np.mean(labels[part.indices] == k) > 0.95:
            return f"the {model.name}'s part holds others' points"
    return None


@pytest.mark.parametrize("bad", [0, -2, 1.5, True, "3"])
def test_max_parts_must_be_a_positive_integer(bad):
    points = composite("mallet", count=1000, seed=0)[0]
    with pytest.raises(ValueError, match="max_parts must be a positive integer"):
        decompose(points, max_parts=bad)


def test_an_unknown_method_is_refused():
    points = composite("mallet", count=1000, seed=0)[0]
    with pytest.raises(ValueError, match="method must be one of"):
        decompose(points, method="greedy")


@pytest.mark.slow  # (24 s with an empty cache when run alone: the 2048-point fits)
def test_one_part_at_most_is_the_whole_object_and_a_ball_is_one_part():
    # max_parts=1: the whole-object check's best primitive, whatever it is.
    mallet = composite("mallet", count=3000, seed=0)[0]
    one = decompose(mallet, max_parts=1, key=0)
    assert len(one.parts) == 1 and one.parts[0].indices.size == len(mallet)
    assert len(one.tree.nodes) == 1
    # A ball is explained by one sphere, two-sided, so no box is cut.
    from jaxfit.shapes import Sphere

    rng = np.random.default_rng(0)
    ball, _ = Sphere(np.zeros(3), np.float64(0.5)).sample(3000, rng)
    result = decompose(ball, key=0)
    assert [p.kind for p in result.parts] == ["sphere"]
    assert result.parts[0].model.radius == pytest.approx(0.5, rel=0.01)
    winner = result.parts[0].candidates[result.parts[0].winner]
    assert winner.two_sided == min(c.two_sided for c in result.parts[0].candidates.values())


@pytest.mark.slow
def test_the_thesis_keeps_to_max_parts():
    points = composite("lamp", count=4000, seed=1)[0]
    assert len(decompose(points, gain=0.96, key=0).parts) == 4
    assert len(decompose(points, gain=0.96, key=0, max_parts=2).parts) <= 2


@pytest.mark.slow
@pytest.mark.parametrize("name", OBJECTS)
def test_measured_gives_one_part_per_primitive(measured, name):
    results, models, labels = measured[name]
    why = {k: _one_part_per_primitive(r, models, labels)
           for k, r in zip(KEYS.get(name, (0,)), results, strict=True)}
    wrong = {k: w for k, w in why.items() if w is not None}
    assert len(wrong) <= len(why) // 3, wrong  # (one key: none; the lamp's nine: three)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["thesis", "measured"])
def test_the_teapot_body_is_one_part_not_slabs(method):
    points, models, labels = composite("teapot", count=4000, seed=1)
    result = decompose(points, method=method, key=0)
    body = models[0]
    shares = [np.mean(labels[p.indices] == 0) for p in result.parts]
    holding = [np.sum(labels[p.indices] == 0) / np.sum(labels == 0) for p in result.parts]
    part = result.parts[int(np.argmax(holding))]
    # one part holds the body: nearly all its points, nearly only them, as one cylinder
    assert max(holding) > 0.95, holding
    assert shares[int(np.argmax(holding))] > 0.8, shares
    assert part.kind == "cylinder" and matches(part.model, body, 0.05), part.model


@pytest.mark.slow
def test_the_split_hierarchy_gives_every_part_count_and_round_trips(measured):
    result = measured["lamp"][0][0]
    assert len(result.levels) == len(result.parts)
    assert result.levels[-1] == result.parts
    for k, level in enumerate(result.levels, start=1):
        assert len(level) == k
        covered = np.sort(np.concatenate([p.indices for p in level]))
        assert np.array_equal(covered, np.arange(len(result.points)))
        assert result.with_parts(k).parts == level
    with pytest.raises(ValueError, match=r"count must be in 1\.\.4"):
        result.with_parts(5)
    with pytest.raises(TypeError, match="count must be an integer"):
        result.with_parts(2.0)
    again = Decomposition.from_dict(result.to_dict(with_points=True))
    assert again.method == "measured" and len(again.levels) == len(result.levels)
    for mine, theirs in zip(result.levels, again.levels, strict=True):
        for a, b in zip(mine, theirs, strict=True):
            assert np.array_equal(a.indices, b.indices) and a.winner == b.winner
            np.testing.assert_allclose(a.model.theta(), b.model.theta())
            assert a.candidates[a.winner].surface_distance == pytest.approx(
                b.candidates[b.winner].surface_distance)
    assert len(again.tree.nodes) == len(result.tree.nodes)
    thesis = decompose(composite("mallet", count=3000, seed=0)[0], gain=0.9, reassign=0)
    with pytest.raises(ValueError, match="no split hierarchy"):
        thesis.with_parts(1)
    assert Decomposition.from_dict(thesis.to_dict(with_points=True)).levels == ()
