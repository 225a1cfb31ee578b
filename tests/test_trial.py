"""Grasp trials in MuJoCo (jaxfit.io.trial): grasps planned by ``jaxfit.grasps`` on a box
and a cylinder lift the object; a gripper 20 cm away, fingers closing on air and an
object too heavy for the grip fail; the gripper's geoms follow ``ParallelJaw``; units and
up axes do not change the outcome. Skipped without mujoco (the ``sim`` extra)."""

import numpy as np
import pytest
import trimesh

import jaxfit
from jaxfit import Box, Cylinder, Decomposition, ParallelJaw, Part

mujoco = pytest.importorskip("mujoco", reason="mujoco is not installed (pip install -e '.[sim]')")

from jaxfit.io.trial import lift_trial, trial_mjcf  # noqa: E402 - after the skip

JAW = ParallelJaw(max_width=0.085, finger_depth=0.04, finger_width=0.02)
Z = np.array([0.0, 0.0, 1.0])


def one_part(model, count=2000, seed=0):
    """A one-part Decomposition of an exact primitive (its closed surface's points), and
    the primitive's mesh: the object of the trial."""
    mesh = model.to_mesh()
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    lo, hi = points.min(axis=0), points.max(axis=0)
    part = Part(np.arange(count), Box(0.5 * (lo + hi), np.eye(3), hi - lo), model.name,
                model.name, model, 0.0, {})
    return Decomposition(np.asarray(points, np.float64), (part,), None, 0.0), mesh


@pytest.fixture(scope="module")
def planned():
    """name -> (mesh, grasps top 3): a 5 x 7 x 10 cm box and a can-sized cylinder (r 3.3 cm,
    h 10 cm), both standing on +Z."""
    out = {}
    for name, model in {"box": Box(np.zeros(3), np.eye(3), np.array([0.05, 0.07, 0.1])),
                        "cylinder": Cylinder(np.zeros(3), Z, np.float64(0.033),
                                             np.float64(0.1))}.items():
        d, mesh = one_part(model)
        out[name] = mesh, jaxfit.grasps(d, JAW, key=0, top=3)
    return out


@pytest.mark.parametrize("name", ["box", "cylinder"])
def test_planned_grasps_lift_the_object(planned, name):
    mesh, g = planned[name]
    assert len(g) == 3
    for pose, width in zip(g.poses, g.widths, strict=True):
        trial = lift_trial(mesh, pose, width, JAW)
        assert trial, trial
        assert trial.finite and 0.09 < trial.rise < 0.105
        assert np.all(np.abs(trial.offset) < 0.01)  # the held point stayed between the pads


def test_bad_grasps_fail(planned):
    mesh, g = planned["cylinder"]
    pose, width = g.poses[0], g.widths[0]
    away = pose.copy()
    away[:3, 3] += 0.2 * pose[:3, 0]  # 20 cm aside, across the pads: nothing between them
    air = pose.copy()
    air[:3, 3] -= 0.2 * pose[:3, 2]  # 20 cm back along the approach: closes on air
    for bad in (away, air):
        trial = lift_trial(mesh, bad, width, JAW)
        assert not trial and trial.finite
        assert abs(trial.rise) < 0.01  # the object stayed on the floor
    # A 20 kg can in a 10 N grip (friction 1) slips out.
    heavy = lift_trial(mesh, pose, width, JAW, density=60000.0, grip_force=10.0)
    assert not heavy and heavy.rise < 0.05


def test_gripper_geoms_follow_the_jaw(planned):
    mesh, _ = planned["box"]
    jaw = ParallelJaw(max_width=0.06, finger_depth=0.05, finger_width=0.03,
                      finger_thickness=0.01, palm_depth=0.02, palm_width=0.04)
    xml, start = trial_mjcf(mesh, jaw, 0.04)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    assert start == pytest.approx(0.01)  # each finger 1 cm in from the 6 cm stop
    data.qpos[[model.joint("finger_left").qposadr[0],
               model.joint("finger_right").qposadr[0]]] = start
    mujoco.mj_forward(model, data)
    hand = model.body("hand").id
    rot, origin = data.xmat[hand].reshape(3, 3), data.xpos[hand]
    for name, (lo, hi) in zip(["palm", "finger_left", "finger_right"], jaw.boxes(0.04),
                              strict=True):
        geom = model.geom(name).id
        centre = rot.T @ (data.geom_xpos[geom] - origin)
        np.testing.assert_allclose(centre, 0.5 * (lo + hi), atol=1e-9)
        np.testing.assert_allclose(model.geom_size[geom], 0.5 * (hi - lo), atol=1e-9)


def test_units_and_up_axis_do_not_change_the_outcome(planned):
    mesh, g = planned["cylinder"]
    base = lift_trial(mesh, g.poses[0], g.widths[0], JAW)
    mm = mesh.copy()
    mm.apply_scale(1000.0)
    pose = g.poses[0].copy()
    pose[:3, 3] *= 1000.0
    jaw_mm = ParallelJaw(max_width=85.0, finger_depth=40.0, finger_width=20.0)
    in_mm = lift_trial(mm, pose, g.widths[0] * 1000.0, jaw_mm, scale=1e-3)
    turn = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])  # z -> y
    standing_y = mesh.copy()
    standing_y.apply_transform(turn)
    y_up = lift_trial(standing_y, turn @ g.poses[0], g.widths[0], JAW, up=1)
    # Up as a direction, down an axis: the object modelled upside down along -Y.
    flip = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])  # z -> -y
    minus_y = mesh.copy()
    minus_y.apply_transform(flip)
    down_y = lift_trial(minus_y, flip @ g.poses[0], g.widths[0], JAW, up=(0.0, -1.0, 0.0))
    for other in (in_mm, y_up, down_y):
        assert bool(other) == bool(base) is True
        assert other.rise == pytest.approx(base.rise, abs=1e-4)


def test_without_a_floor_and_convex_pieces(planned):
    mesh, g = planned["box"]
    halves = [trimesh.creation.box([0.05, 0.07, 0.05]).apply_translation([0, 0, z])
              for z in (-0.025, 0.025)]
    assert lift_trial(mesh, g.poses[0], g.widths[0], JAW, floor=False)
    assert lift_trial(None, g.poses[0], g.widths[0], JAW, pieces=halves)


def test_bad_input(planned):
    mesh, g = planned["box"]
    with pytest.raises(ValueError, match="pose"):
        lift_trial(mesh, np.eye(3), 0.05, JAW)
    for up in (3, (0.0, 0.0, 0.0), (1.0, 0.0)):
        with pytest.raises(ValueError, match="up"):
            lift_trial(mesh, g.poses[0], 0.05, JAW, up=up)
    with pytest.raises(ValueError, match="volume"):
        lift_trial(None, g.poses[0], 0.05, JAW, pieces=[np.zeros((4, 3))])


def test_connected_bodies_are_the_pieces():
    """Without pieces, each connected body of the mesh is one convex piece: two boxes
    apart give two geoms (their joint hull would fill the gap between them)."""
    from jaxfit.io.trial import _pieces

    boxes = [trimesh.creation.box([0.02, 0.02, 0.02]).apply_translation([x, 0, 0])
             for x in (-0.03, 0.03)]
    mesh = trimesh.Trimesh(np.concatenate([b.vertices for b in boxes]),
                           np.concatenate([boxes[0].faces, boxes[1].faces + 8]), process=False)
    pieces = _pieces(mesh, None)
    assert len(pieces) == 2
    assert sum(p.volume for p in pieces) == pytest.approx(2 * 0.02**3)
    xml, _ = trial_mjcf(mesh, JAW, 0.05)
    model = mujoco.MjModel.from_xml_string(xml)
    assert sum(model.geom_bodyid == model.body("object").id) == 2
