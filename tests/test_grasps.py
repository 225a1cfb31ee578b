"""Parallel-jaw grasps from primitives (jaxfit.grasping): the returned grasps are checked
here independently of the planner's own filter (gripper boxes against the points, width,
approach directions per primitive), plus determinism and input errors."""

import json

import jax
import numpy as np
import pytest
import trimesh
from conftest import benchmark_decomposition

import jaxfit
from benchmarks.grasping import MODELS, support_of  # the meshes: file, scale, up
from jaxfit import Box, Cone, Cylinder, Decomposition, Grasps, ParallelJaw, Part, Sphere, grasps

GRIPPER = ParallelJaw(max_width=0.085, finger_depth=0.04, finger_width=0.02)


def _decomposed(mesh, key=0):
    return jaxfit.decompose(mesh, num_points=2000, key=key)


def one_part(model, count=2000, seed=0):
    """A Decomposition of one exact primitive and 2,000 points on its closed surface
    (the planner reads only the parts' models and the points: no fit, no compile)."""
    mesh = model.to_mesh()
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    lo, hi = points.min(axis=0), points.max(axis=0)
    box = Box(0.5 * (lo + hi), np.eye(3), hi - lo)
    part = Part(np.arange(count), box, model.name, model.name, model, 0.0, {})
    return Decomposition(np.asarray(points, np.float64), (part,), None, 0.0)


@pytest.fixture(scope="module")
def objects():
    """name -> a one-part Decomposition: a box 6 x 16 x 21 cm (its short side fits the
    jaw), a cylinder r 3.3 cm h 10 cm along Z, a sphere r 3 cm, a cone r 2.5 cm h 6 cm
    with its base at z = 0 and its apex up."""
    z = np.array([0.0, 0.0, 1.0])
    return {"box": one_part(Box(np.zeros(3), np.eye(3), np.array([0.06, 0.16, 0.21]))),
            "cylinder": one_part(Cylinder(np.zeros(3), z, np.float64(0.033), np.float64(0.1))),
            "sphere": one_part(Sphere(np.zeros(3), np.float64(0.03))),
            "cone": one_part(Cone(np.array([0.0, 0.0, 0.06]), -z, np.arctan2(0.025, 0.06),
                                  np.float64(0.06)))}


def colliding(grasp_set: Grasps, points) -> np.ndarray:
    """(K,) whether the palm or a finger box of each grasp, at its opening, holds a point
    (no margin): an oracle written apart from the planner's filter."""
    out = np.zeros(len(grasp_set), bool)
    for i, (pose, width) in enumerate(zip(grasp_set.poses, grasp_set.widths, strict=True)):
        local = (points - pose[:3, 3]) @ pose[:3, :3]
        for lo, hi in grasp_set.gripper.boxes(width):
            out[i] |= bool(np.any(np.all((local >= lo) & (local <= hi), axis=1)))
    return out


def below_support(grasp_set: Grasps, up, height) -> np.ndarray:
    """(K,) whether a corner of a grasp's palm or finger boxes, at the grasp or at its
    pre-grasp (``Grasps.pregrasp()``), lies below the plane p . up = height plus the
    clearance: an oracle apart from ``clears_support``."""
    out = np.zeros(len(grasp_set), bool)
    for poses in (grasp_set.poses, grasp_set.pregrasp()):
        for i, (pose, width) in enumerate(zip(poses, grasp_set.widths, strict=True)):
            for lo, hi in grasp_set.gripper.boxes(width):
                corners = np.array([[(lo, hi)[b >> k & 1][k] for k in range(3)]
                                    for b in range(8)])
                world = corners @ pose[:3, :3].T + pose[:3, 3]
                out[i] |= bool(np.any(world @ up < height + grasp_set.gripper.clearance - 1e-9))
    return out


def near_duplicates(g: Grasps, separation: float, degrees: float) -> int:
    """How many pairs of grasps lie within ``separation`` of each other with approach and
    closing line within ``degrees``."""
    cos, count = np.cos(np.radians(degrees)), 0
    for i in range(len(g)):
        for j in range(i):
            count += bool(np.linalg.norm(g.poses[i, :3, 3] - g.poses[j, :3, 3]) <= separation
                          and g.approach[i] @ g.approach[j] >= cos
                          and abs(g.closing[i] @ g.closing[j]) >= cos)
    return count


def _assert_sound(g: Grasps, points, *, distinct: bool = True):
    assert len(g) > 0
    assert not colliding(g, points).any()
    assert np.all(g.widths <= g.gripper.max_width + 1e-12)
    assert np.all(g.contact_widths <= g.widths + 1e-9)
    assert np.all(np.diff(g.scores) <= 1e-12)  # best first
    assert np.all((g.scores >= 0) & (g.scores <= 1))
    rotations = g.poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1),
                               np.broadcast_to(np.eye(3), rotations.shape), atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-6)
    # The jaws close on the object: the points between the contacts span the contact width.
    gap = np.abs(np.einsum("kj,kj->k", g.contacts[:, 1] - g.contacts[:, 0], g.closing))
    assert np.all(gap <= g.contact_widths + 1e-6)
    # Both contacts lie between the open fingers, within the finger depth, one per pad.
    local = np.einsum("kcj,kjl->kcl", g.contacts - g.poses[:, None, :3, 3], rotations)
    tol = 1e-4 * g.gripper.max_width
    assert np.all(np.abs(local[..., 0]) <= g.gripper.finger_width / 2 + tol)
    assert np.all(np.abs(local[..., 1]) <= g.widths[:, None] / 2 + tol)
    assert np.all((local[..., 2] >= -g.gripper.finger_depth - tol) & (local[..., 2] <= tol))
    assert np.all(local[:, 0, 1] < local[:, 1, 1])
    # The pre-grasp opening holds the contact width and the clearance on both sides.
    assert np.all(g.widths >= np.minimum(g.contact_widths + 2 * g.gripper.clearance,
                                         g.gripper.max_width) - 1e-6)
    if distinct:  # the default separation
        assert near_duplicates(g, g.gripper.finger_width, 30.0) == 0


def sampled(meshes_and_models, count=2000, seed=0):
    """A Decomposition whose parts are the given (mesh, model) pairs, with ``count``
    points on the meshes' surfaces (the planner reads only the parts' models, their
    points and the cloud), and the points' exact normals (their faces')."""
    meshes = [m for m, _ in meshes_and_models]
    union = trimesh.util.concatenate(meshes)
    points, faces = trimesh.sample.sample_surface(union, count, seed=seed)
    owner = np.repeat(np.arange(len(meshes)), [len(m.faces) for m in meshes])[faces]
    parts = []
    for index, (_, model) in enumerate(meshes_and_models):
        idx = np.flatnonzero(owner == index)
        lo, hi = points[idx].min(axis=0), points[idx].max(axis=0)
        box = Box(0.5 * (lo + hi), np.eye(3), hi - lo)
        parts.append(Part(idx, box, model.name, model.name, model, 0.0, {}))
    return (Decomposition(np.asarray(points, np.float64), tuple(parts), None, 0.0),
            np.asarray(union.face_normals)[faces])


@pytest.mark.parametrize("name", ["box", "cylinder", "sphere", "cone"])
def test_grasps_do_not_collide_and_fit_the_jaw(objects, name):
    d = objects[name]
    g = grasps(d, GRIPPER, key=0)
    _assert_sound(g, d.points)
    assert g.num_candidates >= len(g)
    assert set(g.primitives) <= {p.model.name for p in d.parts}


def test_box_closes_across_the_side_that_fits(objects):
    g = grasps(objects["box"], GRIPPER, key=0)
    # Only the 6 cm side fits an 8.5 cm jaw: every grasp closes along X ...
    np.testing.assert_allclose(np.abs(g.closing[:, 0]), 1.0, atol=0.05)
    np.testing.assert_allclose(g.contact_widths, 0.06, atol=0.006)
    # ... approaching along the normals of the four other faces, all of them used.
    axes = np.argmax(np.abs(g.approach), axis=1)
    signs = np.sign(g.approach[np.arange(len(g)), axes])
    assert set(axes) == {1, 2}
    assert {(a, s) for a, s in zip(axes, signs, strict=True)} == {(1, 1), (1, -1), (2, 1), (2, -1)}
    assert np.all(np.abs(g.approach).max(axis=1) > 0.99)


def test_cylinder_radial_and_from_both_ends(objects):
    g = grasps(objects["cylinder"], GRIPPER, key=0)
    along = np.abs(g.approach[:, 2])
    radial, ends = along < 0.05, along > 0.99
    assert radial.sum() >= 8 and ends.sum() >= 2
    assert (g.approach[ends, 2] > 0).any() and (g.approach[ends, 2] < 0).any()
    # From the ends the jaws close across the diameter; radially they close around it.
    assert np.all(np.abs(g.closing[ends, 2]) < 0.05)
    np.testing.assert_allclose(g.contact_widths[ends], 0.066, atol=0.006)
    # Radial approaches point at the axis.
    r = g.approach[radial, :2] / np.linalg.norm(g.approach[radial, :2], axis=1, keepdims=True)
    origin = g.poses[radial, :2, 3]
    assert np.all(np.abs(origin[:, 0] * r[:, 1] - origin[:, 1] * r[:, 0]) < 0.01)


def test_sphere_grasped_from_all_around(objects):
    d = objects["sphere"]
    g = grasps(d, GRIPPER, key=0)
    assert len(g) >= 40
    # Directions spread over the sphere: every octant is approached.
    octants = {tuple(s) for s in (g.approach > 0).astype(int)}
    assert len(octants) == 8
    # Each approach line passes near the centre and the jaws close across a diameter.
    centre = d.parts[0].model.center
    offset = (g.poses[:, :3, 3] - centre)
    off_axis = offset - np.einsum("kj,kj->k", offset, g.approach)[:, None] * g.approach
    assert np.all(np.linalg.norm(off_axis, axis=1) < 0.01)
    assert np.median(g.antipodal) > 0.9


def test_cone_radial_and_from_base_and_apex(objects):
    d = objects["cone"]
    assert [p.kind for p in d.parts] == ["cone"]
    g = grasps(d, GRIPPER, key=0)
    along = g.approach[:, 2]
    radial = np.abs(along) < 0.05
    assert radial.sum() >= 8
    assert (along > 0.99).any() and (along < -0.99).any()  # from below the base, from the apex
    assert set(g.primitives) == {"cone"}


def test_rim_grasps_on_a_cup_wider_than_the_jaw():
    """A cup 11 cm across (4 mm wall, closed bottom at z = -5 cm, open top) is too wide for
    the 8.5 cm jaw everywhere but its rim (a chord that fits meets the wall more than 37
    degrees off the closing axis): every grasp approaches down the axis from the open end,
    closing radially across the wall, one finger inside."""
    wall = trimesh.creation.annulus(r_min=0.051, r_max=0.055, height=0.1)
    bottom = trimesh.creation.cylinder(radius=0.051, height=0.004)
    bottom.apply_translation([0.0, 0.0, -0.048])
    model = Cylinder(np.zeros(3), np.array([0.0, 0.0, 1.0]), np.float64(0.055), np.float64(0.1))
    d, normals = sampled([(trimesh.util.concatenate([wall, bottom]), model)], count=3000)
    g = grasps(d, GRIPPER, key=0, normals=normals)
    _assert_sound(g, d.points)
    assert len(g) >= 4
    assert np.all(g.approach[:, 2] < -0.95)  # from the open top, down the axis
    radial = g.poses[:, :2, 3] / np.linalg.norm(g.poses[:, :2, 3], axis=1, keepdims=True)
    assert np.all(np.abs(np.sum(g.closing[:, :2] * radial, axis=1)) > 0.9)
    np.testing.assert_allclose(np.linalg.norm(g.poses[:, :2, 3], axis=1), 0.053, atol=0.004)
    assert np.all(g.contact_widths < 0.01)
    assert np.all(g.poses[:, 2, 3] > 0.01)  # the fingertips near the rim, not the bottom


def test_handle_grasped_across_its_thin_side():
    """A 12 cm block (too wide for the jaw) with a thin fin (2 x 1.2 x 8 cm) on its +X
    face: every grasp is on the fin, across its 1.2 cm side."""
    block = Box(np.zeros(3), np.eye(3), np.array([0.12, 0.12, 0.12]))
    fin = Box(np.array([0.07, 0.0, 0.0]), np.eye(3), np.array([0.02, 0.012, 0.08]))
    d, normals = sampled([(block.to_mesh(), block), (fin.to_mesh(), fin)], count=3000)
    g = grasps(d, GRIPPER, key=0, normals=normals, separation=0.0)  # lines 2 cm apart
    _assert_sound(g, d.points, distinct=False)
    assert len(g) >= 3 and set(g.parts) == {1}
    np.testing.assert_allclose(np.abs(g.closing[:, 1]), 1.0, atol=0.05)
    np.testing.assert_allclose(g.contact_widths, 0.012, atol=0.003)


def test_support_drops_grasps_that_reach_the_table(objects):
    """The 6 x 16 x 21 cm box standing on a table at its bottom face (z = -10.5 cm): told
    of the table, no grasp (nor its pre-grasp) puts a gripper box below it, so none comes
    from below; without, some do."""
    d, up = objects["box"], np.array([0.0, 0.0, 1.0])
    floating = grasps(d, GRIPPER, key=0)
    assert (floating.approach[:, 2] > 0.5).any() and below_support(floating, up, -0.105).any()
    g = grasps(d, GRIPPER, key=0, support=(2 * up, -0.105))  # up need not be unit
    _assert_sound(g, d.points)
    assert not below_support(g, up, -0.105).any()
    assert not (g.approach[:, 2] > 0.5).any()
    assert len(g) < len(floating)
    assert np.array_equal(jaxfit.grasping.clears_support(g.poses, g.widths, GRIPPER, up, -0.105),
                          np.ones(len(g), bool))


def test_near_duplicates_are_dropped(objects):
    d = objects["cylinder"]
    g, every = grasps(d, GRIPPER, key=0), grasps(d, GRIPPER, key=0, separation=0.0)
    assert near_duplicates(g, GRIPPER.finger_width, 30.0) == 0
    assert near_duplicates(every, GRIPPER.finger_width, 30.0) > 0
    assert len(every) > len(g)
    # Each dropped grasp is a near-duplicate of a kept one that scores at least as well.
    kept = {tuple(np.round(p[:3, 3], 9)) for p in g.poses}
    for pose, score in zip(every.poses, every.scores, strict=True):
        if tuple(np.round(pose[:3, 3], 9)) in kept:
            continue
        close = ((np.linalg.norm(g.poses[:, :3, 3] - pose[:3, 3], axis=1) <= 0.02)
                 & (g.approach @ pose[:3, 2] >= np.cos(np.radians(30)))
                 & (np.abs(g.closing @ pose[:3, 1]) >= np.cos(np.radians(30))))
        assert close.any() and g.scores[close].max() >= score - 1e-12


def test_score_prefers_a_short_lever(objects):
    """On the 6 x 16 x 21 cm box, grasps whose closing line passes nearer the centre of
    mass score higher (the pads' patches alike)."""
    g = grasps(objects["box"], GRIPPER, key=0)
    arm = -g.contacts.mean(axis=1)  # the centre of mass is the origin
    lever = np.linalg.norm(arm - np.sum(arm * g.closing, axis=1, keepdims=True) * g.closing,
                           axis=1)
    assert np.corrcoef(lever, g.scores)[0, 1] < -0.5


def test_same_key_same_grasps(objects):
    d = objects["sphere"]
    a, b = grasps(d, GRIPPER, key=3), grasps(d, GRIPPER, key=3)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.scores, b.scores)
    k1, k2 = grasps(d, GRIPPER, key=jax.random.key(7)), grasps(d, GRIPPER, key=jax.random.key(7))
    np.testing.assert_array_equal(k1.poses, k2.poses)
    c = grasps(d, GRIPPER, key=4)
    assert a.poses.shape != c.poses.shape or not np.array_equal(a.poses, c.poses)


def test_top_pregrasp_and_json(objects):
    g = grasps(objects["cylinder"], GRIPPER, key=0, top=5)
    full = grasps(objects["cylinder"], GRIPPER, key=0)
    assert len(g) == 5
    np.testing.assert_array_equal(g.poses, full.poses[:5])
    pre = g.pregrasp(0.1)
    np.testing.assert_allclose(pre[:, :3, 3], g.poses[:, :3, 3] - 0.1 * g.approach)
    record = json.loads(json.dumps(g.to_dict()))
    assert len(record["grasps"]) == 5
    assert record["gripper"]["max_width"] == GRIPPER.max_width
    np.testing.assert_allclose(record["grasps"][0]["pose"], g.poses[0])


def test_narrow_gripper_gets_nothing_it_cannot_reach(objects):
    narrow = ParallelJaw(max_width=0.05, finger_depth=0.04, finger_width=0.02)
    g = grasps(objects["box"], narrow, key=0)  # 6 cm is the box's narrowest side
    assert len(g) == 0 and g.poses.shape == (0, 4, 4)
    assert json.dumps(g.to_dict())


@pytest.mark.parametrize("kwargs, match", [
    ({"max_width": 0}, "max_width"),
    ({"max_width": -1}, "max_width"),
    ({"finger_depth": float("nan")}, "finger_depth"),
    ({"finger_width": "2"}, "finger_width"),
    ({"finger_thickness": 0}, "finger_thickness"),
    ({"palm_depth": True}, "palm_depth"),
    ({"palm_width": 0.01}, "palm_width"),
    ({"clearance": -0.1}, "clearance"),
    ({"clearance": 0.05}, "clearance"),
])
def test_bad_gripper_parameters(kwargs, match):
    args = {"max_width": 0.085, "finger_depth": 0.04, "finger_width": 0.02} | kwargs
    with pytest.raises(ValueError, match=match):
        ParallelJaw(**args)


def test_bad_arguments(objects):
    with pytest.raises(TypeError, match="Decomposition"):
        grasps(np.zeros((10, 3)), GRIPPER)
    with pytest.raises(TypeError, match="ParallelJaw"):
        grasps(objects["box"], {"max_width": 1})
    with pytest.raises(ValueError, match="top"):
        grasps(objects["box"], GRIPPER, top=0)
    with pytest.raises(ValueError, match="min_quality"):
        grasps(objects["box"], GRIPPER, min_quality=2)
    for support, match in [((np.zeros(3), 0.0), "up"), (([0, 0, 1, 0], 0.0), "up"),
                           (([0, 0, 1], float("nan")), "height"), ((0, 0, 1), "support"),
                           (([0, 0, 1], "0"), "height")]:
        with pytest.raises(ValueError, match=match):
            grasps(objects["box"], GRIPPER, support=support)
    with pytest.raises(ValueError, match="separation"):
        grasps(objects["box"], GRIPPER, separation=-1.0)
    with pytest.raises(ValueError, match="separation_degrees"):
        grasps(objects["box"], GRIPPER, separation_degrees=200)


@pytest.mark.slow  # ~40 s with an empty compilation cache (the decomposition's fits)
def test_decomposed_soup_can(data_dir):
    """The YCB soup can (metres) decomposed from 2,000 points: grasps on its parts,
    around the can and across it from the ends."""
    mesh = trimesh.load(data_dir / "ycb" / "005_tomato_soup_can_textured.gltf", force="mesh")
    d = _decomposed(mesh)
    g = grasps(d, GRIPPER, key=0)
    _assert_sound(g, d.points)
    assert len(g) >= 10
    np.testing.assert_array_less(g.contact_widths, 0.075)




@pytest.mark.slow
@pytest.mark.parametrize("name", list(MODELS))
def test_benchmark_meshes_grasps_do_not_collide(data_dir, name):
    """The six benchmark meshes at 4,000 points (decomposed once, for tests/test_sim.py too):
    no grasp collides with the points, floating or told of the floor (then none reaches
    it), and the same key gives the same grasps."""
    _, scale, up = MODELS[name]
    d = benchmark_decomposition(name)
    gripper = ParallelJaw(max_width=0.085 / scale, finger_depth=0.04 / scale,
                          finger_width=0.02 / scale)
    g = grasps(d, gripper, key=0)
    _assert_sound(g, d.points)
    floor = support_of(d.points, up)
    on_floor = grasps(d, gripper, key=0, support=floor)
    _assert_sound(on_floor, d.points)
    assert not below_support(on_floor, *floor).any()
    again = grasps(d, gripper, key=0, support=floor)
    np.testing.assert_array_equal(again.poses, on_floor.poses)
    np.testing.assert_array_equal(again.widths, on_floor.widths)


def test_save_writes_json_and_preview(objects, tmp_path):
    d = objects["cylinder"]
    g = grasps(d, GRIPPER, key=0, top=6)
    folder = g.save(tmp_path / "out", d, top=4)
    record = json.loads((folder / "grasps.json").read_text())
    assert len(record["grasps"]) == 6
    assert (folder / "grasps.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in folder.iterdir()) == ["grasps.json", "grasps.png"]


def test_cli_grasp(tmp_path, capsys, monkeypatch, objects):
    """The command's plumbing, with the decomposition stubbed (decomposing compiles the
    fits: ~40 s with an empty cache; the slow tests decompose)."""
    import jaxfit.decomposition
    from jaxfit.cli import main

    seen = {}

    def fake_decompose(source, **options):
        seen.update(options, source=source)
        return objects["sphere"]

    monkeypatch.setattr(jaxfit.decomposition, "decompose", fake_decompose)
    cloud = tmp_path / "ball.npy"
    np.save(cloud, objects["sphere"].points)
    out = tmp_path / "grasps"
    assert main(["grasp", str(cloud), "--out", str(out), "--top", "3"]) == 0
    record = json.loads((out / "grasps.json").read_text())
    assert 1 <= len(record["grasps"]) <= 3
    assert record["gripper"]["max_width"] == pytest.approx(0.085)
    assert "grasps kept" in capsys.readouterr().out
    assert seen["source"] == str(cloud) and seen["key"] == 0
    # A bad gripper is refused before any work, with a message naming it.
    assert main(["grasp", str(cloud), "--out", str(tmp_path / "bad"),
                 "--gripper-width", "-1"]) == 2
    assert "max_width" in capsys.readouterr().err


def test_cli_grasp_floor(tmp_path, capsys, monkeypatch, objects):
    """--floor z tells the planner of a table under the lowest point: no grasp approaches
    from below (the 6 x 16 x 21 cm box, decomposition stubbed as above)."""
    import jaxfit.decomposition
    from jaxfit.cli import main

    monkeypatch.setattr(jaxfit.decomposition, "decompose", lambda source, **_: objects["box"])
    cloud = tmp_path / "box.npy"
    np.save(cloud, objects["box"].points)
    for floor, out in ((None, tmp_path / "free"), ("z", tmp_path / "floor")):
        assert main(["grasp", str(cloud), "--out", str(out), "--top", "50"]
                    + ([] if floor is None else ["--floor", floor])) == 0
    def approaches(name):
        record = json.loads((tmp_path / name / "grasps.json").read_text())
        return np.array([np.asarray(g["pose"])[:3, 2] for g in record["grasps"]])

    assert (approaches("free")[:, 2] > 0.5).any()
    assert not (approaches("floor")[:, 2] > 0.5).any()
