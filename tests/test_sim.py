"""Simulator models: ``jaxfit.io.sim`` (URDF, MJCF), ``Decomposition.to_urdf`` /
``to_mjcf`` and the CLI's ``--urdf --mjcf``, validated in MuJoCo (the ``sim`` extra):
the models load, have the primitives' mass, inertia and bounds, and the object dropped
onto a floor comes to rest. The benchmark meshes' decompositions are ``slow`` (each
compiles kernels with a cold cache); the rest is fast."""

import functools
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh
from conftest import benchmark_decomposition
from scipy.spatial.transform import Rotation

import jaxfit
from benchmarks.grasping import MODELS, up_vector  # the meshes: file, scale, up
from jaxfit.decomposition import decompose
from jaxfit.io import sim
from jaxfit.shapes import Box, Cone, Cylinder, Plane, Sphere, mass_properties
from jaxfit.shapes._geometry import union_bounds

try:
    import mujoco
except ImportError:  # the tests that need it skip
    mujoco = None

needs_mujoco = pytest.mark.skipif(
    mujoco is None, reason="mujoco is not installed (pip install -e '.[sim]')")
try:
    import pybullet
except ImportError:  # the tests that need it skip
    pybullet = None

needs_pybullet = pytest.mark.skipif(
    pybullet is None, reason="pybullet is not installed (pip install -e '.[sim]')")

DROP = 0.02  # m above the floor
SETTLE = 2.0  # s simulated
REST_SPEED, REST_SPIN = 0.01, 0.1  # m/s, rad/s


def figure():
    """A standing object of every primitive: a box base, a cylinder post, a sphere on
    top, a cone leaning out and a plane patch (a thin massless disk)."""
    tilt = Rotation.from_euler("x", 35, degrees=True).as_matrix()
    return [
        Box(np.array([0.0, 0.0, 0.02]), np.eye(3), np.array([0.2, 0.16, 0.04])),
        Cylinder(np.array([0.0, 0.0, 0.14]), np.array([0.0, 0.0, 1.0]), np.float64(0.02),
                 np.float64(0.2)),
        Sphere(np.array([0.0, 0.0, 0.27]), np.float64(0.04)),
        Cone(np.array([0.0, 0.02, 0.1]), tilt[:, 1], np.float64(0.4), np.float64(0.08)),
        Plane(np.array([1.0, 0.0, 0.0]), np.float64(-0.02), np.array([0.02, 0.0, 0.12]),
              np.float64(0.03)),
    ]


def random_models(seed):
    rng = np.random.default_rng(seed)
    return [cls.random(Rotation.random(random_state=seed + i).as_matrix(),
                       rng.normal(size=3) * 0.1, 0.05, rng)
            for i, cls in enumerate([Box, Cone, Cylinder, Sphere, Plane])]


def geom_bounds(model, data, geom):
    """World bounds (lo, hi) of one MuJoCo geom: exact for boxes, spheres and cylinders,
    its vertices' for a mesh."""
    rot, centre, size = data.geom_xmat[geom].reshape(3, 3), data.geom_xpos[geom], \
        model.geom_size[geom]
    kind = model.geom_type[geom]
    if kind == mujoco.mjtGeom.mjGEOM_MESH:
        mesh = model.geom_dataid[geom]
        start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
        vertices = model.mesh_vert[start:start + count] @ rot.T + centre
        return vertices.min(axis=0), vertices.max(axis=0)
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        reach = np.abs(rot) @ size
    elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        reach = np.full(3, size[0])
    else:  # a cylinder: its two end disks
        axis = rot[:, 2]
        reach = size[0] * np.sqrt(np.clip(1 - axis**2, 0, None)) + size[1] * np.abs(axis)
    return centre - reach, centre + reach


def object_geoms(model):
    return np.flatnonzero(model.geom_bodyid > 0)


def loaded(path):
    model = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def drop(path, up: int = 2, height: float = DROP, seconds: float = SETTLE):
    """Simulate the MJCF object at ``path`` dropped from ``height`` onto a floor normal to
    the axis ``up`` (gravity along -up) for ``seconds``. Returns the final speed, spin,
    the height of the object's lowest point above the floor and whether all stayed
    finite."""
    spec = mujoco.MjSpec.from_file(str(path))
    model, data = loaded(path)
    lo, hi = union_bounds([geom_bounds(model, data, g) for g in object_geoms(model)])
    axis = np.eye(3)[up]
    floor = spec.worldbody.add_geom()
    floor.type, floor.size = mujoco.mjtGeom.mjGEOM_PLANE, [0.0, 0.0, 1.0]
    floor.pos = (lo[up] - height) * axis + 0.5 * (lo + hi) * (1 - axis)
    frame = np.roll(np.eye(3), -(up + 1), axis=1)  # a right-handed frame with z along up
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, frame.reshape(-1))
    floor.quat = quat
    spec.option.gravity = -9.81 * axis
    model = spec.compile()
    data = mujoco.MjData(model)
    finite = True
    for _ in range(int(round(seconds / model.opt.timestep))):
        mujoco.mj_step(model, data)
        finite &= bool(np.all(np.isfinite(data.qpos)))
    low = min(geom_bounds(model, data, g)[0][up] for g in object_geoms(model))
    return (float(np.linalg.norm(data.qvel[:3])), float(np.linalg.norm(data.qvel[3:6])),
            low - (lo[up] - height), finite)


def assert_rests(path, up=2):
    speed, spin, above, finite = drop(path, up)
    assert finite, "the simulation produced NaN"
    assert speed < REST_SPEED and spin < REST_SPIN, (speed, spin)
    assert -2e-3 < above < 2e-3, f"lowest point {above:.4f} m from the floor"


def pybullet_parts(path):
    """The URDF at ``path`` loaded by pybullet (DIRECT, its own inertia, native cylinders):
    the number of links besides the base, and per collision shape its pybullet geometry
    type, dimensions, world centre and world rotation, then the base's world bounds (as
    bullet computes them), mass and centre of mass."""
    client = pybullet.connect(pybullet.DIRECT)
    try:
        body = pybullet.loadURDF(str(path), physicsClientId=client,
                                 flags=pybullet.URDF_USE_INERTIA_FROM_FILE
                                 | pybullet.URDF_USE_IMPLICIT_CYLINDER)
        position, quat = pybullet.getBasePositionAndOrientation(body, physicsClientId=client)
        rot = np.array(pybullet.getMatrixFromQuaternion(quat)).reshape(3, 3)
        shapes = [(s[2], np.array(s[3]), np.array(position) + rot @ np.array(s[5]),
                   rot @ np.array(pybullet.getMatrixFromQuaternion(s[6])).reshape(3, 3))
                  for s in pybullet.getCollisionShapeData(body, -1, physicsClientId=client)]
        lo, hi = pybullet.getAABB(body, -1, physicsClientId=client)
        mass = pybullet.getDynamicsInfo(body, -1, physicsClientId=client)[0]
        return (pybullet.getNumJoints(body, physicsClientId=client), shapes,
                (np.array(lo), np.array(hi)), mass, np.array(position))
    finally:
        pybullet.disconnect(client)


def assert_pybullet_matches(path, models, scale=1.0, density=1000.0):
    """pybullet reads the URDF as one link with one collision shape per primitive, of
    its kind (cones as meshes), sizes, centre and world bounds (from its size and pose;
    the cones' meshes aside), the primitives' mass and centre of mass; bullet's own
    bounds of the link hold the primitives' (they are loose for a rotated compound)."""
    links, shapes, (lo, hi), mass, com = pybullet_parts(path)
    assert links == 0 and len(shapes) == len(models)
    kinds = {"box": pybullet.GEOM_BOX, "sphere": pybullet.GEOM_SPHERE,
             "cylinder": pybullet.GEOM_CYLINDER, "plane": pybullet.GEOM_CYLINDER,
             "cone": pybullet.GEOM_MESH}
    for (kind, size, centre, rot), m in zip(shapes, models, strict=True):
        assert kind == kinds[m.name], (m.name, kind)
        tol = 1e-6 * scale * float(np.max(np.abs(m.bounding_box())))
        if m.name == "box":
            np.testing.assert_allclose(size, scale * np.asarray(m.extents), atol=tol)
        elif m.name == "sphere":
            assert size[0] == pytest.approx(scale * float(m.radius), abs=tol)
        elif m.name == "cylinder":
            np.testing.assert_allclose(size[:2], scale * np.array([m.height, m.radius]),
                                       atol=tol)
        if m.name == "cone":  # a mesh's centre is its file's origin
            continue
        want_lo, want_hi = (scale * np.asarray(b) for b in m.bounding_box())
        tol = 1e-5 * float(np.linalg.norm(want_hi - want_lo)) + 1e-9
        np.testing.assert_allclose(centre, scale * np.asarray(m.center), atol=tol)
        if kind == pybullet.GEOM_BOX:
            reach = np.abs(rot) @ (size / 2)
        elif kind == pybullet.GEOM_SPHERE:
            reach = np.full(3, size[0])
        else:  # a cylinder (height, radius) along its local z: its two end disks
            axis = rot[:, 2]
            reach = (size[1] * np.sqrt(np.clip(1 - axis**2, 0, None))
                     + size[0] / 2 * np.abs(axis))
        if m.name == "plane":  # the thin disk's half thickness
            tol += scale * sim.PLANE_THICKNESS * float(m.radius)
        np.testing.assert_allclose(centre - reach, want_lo, atol=tol)
        np.testing.assert_allclose(centre + reach, want_hi, atol=tol)
    want_mass, want_com, _ = mass_properties(models, density)
    assert mass == pytest.approx(want_mass * scale**3, rel=1e-6)
    np.testing.assert_allclose(com, scale * want_com, atol=1e-6 * scale)
    want_lo, want_hi = (scale * b for b in union_bounds([m.bounding_box() for m in models]))
    diagonal = float(np.linalg.norm(want_hi - want_lo))
    assert np.all(lo <= want_lo + 2e-3 * diagonal) and np.all(hi >= want_hi - 2e-3 * diagonal)


@needs_pybullet
def test_urdf_loads_in_pybullet_with_the_same_parts(tmp_path):
    models = figure()
    assert_pybullet_matches(sim.write_urdf(models, tmp_path / "fig.urdf", density=1000.0),
                            models)


# ----- the writers, without a simulator ----------------------------------------------------
def test_urdf_has_one_link_a_collision_per_part_and_their_mass(tmp_path):
    models = figure()
    path = sim.write_urdf(models, tmp_path / "fig.urdf", name="fig", density=500.0)
    link, = ET.parse(path).getroot().findall("link")
    assert link.get("name") == "fig"
    collisions = link.findall("collision")
    assert [c.get("name") for c in collisions] == [f"part{i}_{m.name}"
                                                  for i, m in enumerate(models)]
    assert len(link.findall("visual")) == len(models)
    kinds = [c.find("geometry")[0].tag for c in collisions]
    assert kinds == ["box", "cylinder", "sphere", "mesh", "cylinder"]  # cone: mesh; plane: disk
    mass, centre, inertia = mass_properties(models, 500.0)
    inertial = link.find("inertial")
    assert float(inertial.find("mass").get("value")) == pytest.approx(mass, rel=1e-8)
    xyz = [float(v) for v in inertial.find("origin").get("xyz").split()]
    np.testing.assert_allclose(xyz, centre, atol=1e-9)
    tensor = inertial.find("inertia")
    assert float(tensor.get("ixy")) == pytest.approx(inertia[0, 1], abs=1e-9)
    cone_file = tmp_path / collisions[3].find("geometry/mesh").get("filename")
    cone = trimesh.load(cone_file)
    assert cone.is_convex and cone.volume == pytest.approx(models[3].volume(), rel=5e-3)
    disk = collisions[4].find("geometry/cylinder")
    assert float(disk.get("length")) == pytest.approx(sim.PLANE_THICKNESS * 0.03)


def test_rpy_gives_the_rotation_back():
    rotations = list(Rotation.random(50, random_state=0).as_matrix())
    rotations += [Rotation.from_euler("xyz", [0.3, s * np.pi / 2, -1.1]).as_matrix()
                  for s in (-1, 1)]  # gimbal lock
    for rotation in rotations:
        back = Rotation.from_euler("xyz", sim.rpy(rotation)).as_matrix()  # Rz Ry Rx
        np.testing.assert_allclose(back, rotation, atol=1e-9)


def test_scale_multiplies_lengths_and_the_mass_by_its_cube(tmp_path):
    models = figure()
    one = sim.rigid_body(models, density=1000.0)
    milli = sim.rigid_body(models, density=1000.0, scale=1e-3)
    assert milli.mass == pytest.approx(1e-9 * one.mass)
    np.testing.assert_allclose(milli.center_of_mass, 1e-3 * one.center_of_mass)
    np.testing.assert_allclose(milli.inertia, 1e-15 * one.inertia, atol=1e-30)
    assert milli.geometries[0].size == pytest.approx(tuple(1e-3 * np.array(one.geometries[0].size)))


def test_bad_arguments_are_clear_errors(tmp_path):
    models = figure()
    with pytest.raises(ValueError, match="no volume"):
        sim.write_mjcf([models[4]], tmp_path / "a.xml")
    with pytest.raises(ValueError, match="at least one"):
        sim.write_mjcf([], tmp_path / "a.xml")
    with pytest.raises(ValueError, match="name"):
        sim.write_urdf(models, tmp_path / "a.urdf", name="a b")
    with pytest.raises(ValueError, match="density"):
        sim.write_urdf(models, tmp_path / "a.urdf", density=0)
    with pytest.raises(ValueError, match="scale"):
        sim.write_urdf(models, tmp_path / "a.urdf", scale=-1.0)
    with pytest.raises(ValueError, match="folder"):
        sim.write_urdf(models, tmp_path)
    with pytest.raises(ValueError, match="does not exist"):
        sim.write_urdf(models, tmp_path / "missing" / "a.urdf")
    assert not list(tmp_path.iterdir())


def test_a_failed_write_leaves_the_old_files(tmp_path, monkeypatch):
    models = figure()
    path = sim.write_mjcf(models, tmp_path / "fig.xml", name="fig")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def broken(self, *args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(trimesh.Trimesh, "export", broken)
    with pytest.raises(OSError, match="disk full"):
        sim.write_mjcf([m.rescaled(2.0, np.zeros(3)) for m in models], path, name="fig")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_mesh_dir_and_visual_mesh(tmp_path):
    models = figure()
    shown = trimesh.creation.icosphere(radius=0.1)
    path = sim.write_urdf(models, tmp_path / "fig.urdf", name="fig", mesh_dir=tmp_path / "m",
                          visual_mesh=shown)
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == ["fig_part3_cone.stl",
                                                                 "fig_visual.stl"]
    link = ET.parse(path).getroot().find("link")
    visual, = link.findall("visual")  # the mesh replaces the primitives' visuals
    assert visual.find("geometry/mesh").get("filename") == "m/fig_visual.stl"
    names = [c.find("geometry/mesh") for c in link.findall("collision")]
    assert [n.get("filename") for n in names if n is not None] == ["m/fig_part3_cone.stl"]


# ----- in MuJoCo -----------------------------------------------------------------------------
@needs_mujoco
@pytest.mark.parametrize("seed", [0, 1])
def test_both_formats_load_with_the_primitives_mass_inertia_and_bounds(tmp_path, seed):
    models = random_models(seed)
    density = 800.0
    mass, centre, inertia = mass_properties(models, density)
    poses = {}
    for path in (sim.write_mjcf(models, tmp_path / "o.xml", density=density),
                 sim.write_urdf(models, tmp_path / "o.urdf", density=density)):
        if path.suffix == ".urdf":  # MuJoCo fuses a URDF's fixed root link into the world
            spec = mujoco.MjSpec.from_file(str(path))
            spec.compiler.fusestatic = False
            model = spec.compile()
            data = mujoco.MjData(model)
            mujoco.mj_forward(model, data)
        else:
            model, data = loaded(path)
        geoms = object_geoms(model)
        assert len(geoms) == len(models)
        body = model.geom_bodyid[geoms[0]]
        assert model.body_mass[body] == pytest.approx(mass, rel=1e-6)
        np.testing.assert_allclose(data.xipos[body], centre, atol=1e-7)
        rot = data.ximat[body].reshape(3, 3)
        np.testing.assert_allclose(rot * model.body_inertia[body] @ rot.T, inertia,
                                   atol=1e-6 * np.abs(inertia).max())
        for geom, primitive in zip(geoms, models, strict=True):
            lo, hi = geom_bounds(model, data, geom)
            want_lo, want_hi = primitive.bounding_box()
            tol = 2e-3 * np.linalg.norm(want_hi - want_lo)  # the cone's 64 sections
            if primitive.name == "plane":  # the thin disk's half thickness
                tol += sim.PLANE_THICKNESS * float(primitive.radius)
            np.testing.assert_allclose(lo, want_lo, atol=tol)
            np.testing.assert_allclose(hi, want_hi, atol=tol)
        poses[path.suffix] = (data.geom_xpos[geoms].copy(), data.geom_xmat[geoms].copy())
    for a, b in zip(poses[".xml"], poses[".urdf"], strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6)


@needs_mujoco
def test_the_figure_dropped_on_a_floor_comes_to_rest(tmp_path):
    assert_rests(sim.write_mjcf(figure(), tmp_path / "fig.xml"))


@needs_mujoco
def test_visual_mesh_is_shown_and_does_not_collide(tmp_path):
    models = figure()
    shown = trimesh.creation.icosphere(radius=0.1)
    model, _ = loaded(sim.write_mjcf(models, tmp_path / "fig.xml", visual_mesh=shown))
    geoms = object_geoms(model)
    assert len(geoms) == len(models) + 1
    visual = [g for g in geoms if model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0]
    assert len(visual) == 1 and model.geom_group[visual[0]] == 2


@functools.cache
def sphere_decomposition():
    """A sphere decomposed with one primitive (fast: the kernels test_decompose's quick
    tests compile too)."""
    return decompose(trimesh.creation.icosphere(radius=0.05), num_points=1500, gain=0.8,
                     shapes=("sphere",), key=0)


def test_decomposition_dict_has_poses_and_totals():
    result = sphere_decomposition()
    data = json.loads(json.dumps(result.to_dict()))
    part, = data["parts"]
    model = result.parts[0].model
    np.testing.assert_allclose(part["transform"], model.transform())
    assert part["volume"] == pytest.approx(model.volume())
    np.testing.assert_allclose(part["centroid"], model.centroid())
    assert {"kind", "winner", "model", "mean_distance", "num_points", "box",
            "candidates"} <= set(part)
    assert data["totals"]["volume"] == pytest.approx(4 / 3 * np.pi * 0.05**3, rel=0.03)
    np.testing.assert_allclose(data["totals"]["inertia_per_density"], model.inertia(1.0),
                               atol=1e-12 * float(model.inertia(1.0).max()))
    mass, _, _ = result.mass_properties(1000.0)
    assert mass == pytest.approx(1000.0 * model.volume())


@needs_mujoco
def test_decomposition_to_mjcf_rests_and_to_urdf_loads(tmp_path):
    result = sphere_decomposition()
    assert_rests(result.to_mjcf(tmp_path / "ball.xml", name="ball"))
    model = mujoco.MjModel.from_xml_path(str(result.to_urdf(tmp_path / "ball.urdf")))
    assert model.ngeom == 1 and model.geom_type[0] == mujoco.mjtGeom.mjGEOM_SPHERE


@pytest.mark.slow  # ~13 s cold: the save renders the preview
def test_cli_writes_urdf_and_mjcf(tmp_path, monkeypatch, capsys):
    from jaxfit import decomposition
    from jaxfit.cli import main

    source = tmp_path / "ball.ply"
    trimesh.creation.icosphere(radius=50.0).export(source)
    # The CLI's wiring, not the PSDA: one primitive keeps it fast.
    monkeypatch.setattr(decomposition, "decompose",
                        functools.partial(decompose, shapes=("sphere",)))
    out = tmp_path / "out"
    assert main(["decompose", str(source), "--out", str(out), "--num-points", "1500",
                 "--urdf", "--mjcf", "--name", "ball", "--scale", "0.001"]) == 0
    assert {"ball.urdf", "ball.xml", "parts.json"} <= {p.name for p in out.iterdir()}
    if mujoco is not None:
        model = mujoco.MjModel.from_xml_path(str(out / "ball.xml"))
        assert model.geom_size[0][0] == pytest.approx(0.05, rel=0.02)  # metres
    capsys.readouterr()


@pytest.mark.parametrize("argv, message", [
    (["--urdf"], "give --out"),
    (["--mjcf", "--out", "{tmp}", "--name", "a/b"], "--name"),
    (["--urdf", "--out", "{tmp}", "--density", "0"], "--density"),
    (["--mjcf", "--out", "{tmp}", "--scale", "nan"], "--scale"),
])
def test_cli_sim_options_are_checked_before_any_work(tmp_path, capsys, monkeypatch, argv,
                                                     message):
    from jaxfit import decomposition
    from jaxfit.cli import main

    def never(*args, **kwargs):
        raise AssertionError("decompose ran")

    monkeypatch.setattr(decomposition, "decompose", never)
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert main(["decompose", str(tmp_path / "any.ply"), *argv]) == 2
    assert message in capsys.readouterr().err


# ----- the benchmark meshes -------------------------------------------------------------------
@needs_mujoco
@pytest.mark.slow
@pytest.mark.parametrize("name", list(MODELS))
def test_benchmark_mesh_models_load_match_and_rest(data_dir, tmp_path, name):
    _, scale, up = MODELS[name]
    up = int(np.argmax(np.abs(up_vector(up))))  # the drop's axis (either way up rests)
    result = benchmark_decomposition(name)
    mjcf = result.to_mjcf(tmp_path / f"{name}.xml", name=name, scale=scale)
    model, data = loaded(mjcf)
    geoms = object_geoms(model)
    assert len(geoms) == len(result.parts)
    lo, hi = union_bounds([geom_bounds(model, data, g) for g in geoms])
    want_lo, want_hi = union_bounds([p.model.bounding_box() for p in result.parts])
    tol = 2e-3 * scale * np.linalg.norm(want_hi - want_lo)
    np.testing.assert_allclose(lo, scale * want_lo, atol=tol)
    np.testing.assert_allclose(hi, scale * want_hi, atol=tol)
    mass, _, _ = result.mass_properties(1000.0)
    assert model.body_mass[model.geom_bodyid[geoms[0]]] == pytest.approx(mass * scale**3)
    assert_rests(mjcf, up)
    urdf = mujoco.MjModel.from_xml_path(str(result.to_urdf(tmp_path / f"{name}.urdf",
                                                            name=name, scale=scale)))
    assert urdf.ngeom == len(result.parts)
    np.testing.assert_array_equal(urdf.geom_type, model.geom_type[geoms])
    if pybullet is not None:  # the same URDF in a second parser
        assert_pybullet_matches(tmp_path / f"{name}.urdf",
                                [p.model for p in result.parts], scale=scale)


def test_the_package_exports_the_writers():
    assert jaxfit.Decomposition.to_urdf and jaxfit.Decomposition.to_mjcf
    assert callable(sim.write_urdf) and callable(sim.write_mjcf)
