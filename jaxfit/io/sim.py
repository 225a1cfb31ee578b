"""Simulator models of a set of primitives: URDF and MJCF (MuJoCo) files (docs/robot.md).

The object is one rigid body (a URDF link, an MJCF body) with one collision geometry
per primitive, in the primitives' own coordinates times ``scale`` (the body's frame is
the cloud's frame):

- box, cylinder and sphere as the formats' native geometries, posed by
  ``Model.transform``;
- a cone, which no format has, as a convex mesh file (binary STL) of ``to_mesh`` in its
  canonical frame, written next to the model or into ``mesh_dir``; so is any primitive
  without a native geometry;
- a plane (no volume) as a thin disk, a cylinder of ``PLANE_THICKNESS`` of its patch's
  radius, without mass.

Mass, centre of mass and inertia tensor come from the primitives at one ``density``
(``shapes.mass_properties``: overlaps count once per primitive). Every file is written
to a temporary name and renamed into place only when all are written (``io.atomic``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..shapes._base import Model, check_density, mass_properties
from .atomic import replacing

#: Native geometries of both formats; any other primitive becomes a convex mesh.
NATIVE = ("box", "cylinder", "sphere")
#: A plane's disk is a cylinder this fraction of its patch's radius thick.
PLANE_THICKNESS = 0.02
#: Allowed model names: they become file names and XML names.
NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")


@dataclasses.dataclass(frozen=True, eq=False)
class Geometry:
    """One collision geometry of the body, in the body's (scaled) frame.

    name : "part{i}_{primitive}".
    kind : "box", "cylinder", "sphere" or "mesh".
    transform : (4, 4) pose of the geometry's frame (the primitive's ``transform``).
    size : box (3,) full sides; cylinder (radius, length); sphere (radius,); mesh ().
    mesh : for "mesh", a convex ``trimesh.Trimesh`` in the geometry's frame; else None.
    rgba : (4,) colour in [0, 1].
    """

    name: str
    kind: str
    transform: np.ndarray
    size: tuple[float, ...]
    mesh: object
    rgba: tuple[float, ...]


@dataclasses.dataclass(frozen=True, eq=False)
class Body:
    """The rigid body: its geometries, mass (), centre of mass (3,) and inertia tensor
    (3, 3) about it in the body's axes."""

    geometries: tuple[Geometry, ...]
    mass: float
    center_of_mass: np.ndarray
    inertia: np.ndarray


def geometry(model: Model, name: str) -> Geometry:
    """The collision geometry of one primitive (already scaled)."""
    rgba = tuple(c / 255.0 for c in model.colour)
    transform = model.transform()
    if model.name == "box":
        return Geometry(name, "box", transform, tuple(map(float, model.extents)), None, rgba)
    if model.name == "sphere":
        return Geometry(name, "sphere", transform, (float(model.radius),), None, rgba)
    if model.name == "cylinder":
        return Geometry(name, "cylinder", transform,
                        (float(model.radius), float(model.height)), None, rgba)
    if model.name == "plane":
        radius = float(model.radius)
        return Geometry(name, "cylinder", transform, (radius, PLANE_THICKNESS * radius), None,
                        rgba)
    mesh = model.to_mesh().convex_hull
    mesh.apply_transform(np.linalg.inv(transform))
    return Geometry(name, "mesh", transform, (), mesh, rgba)


def rigid_body(models, *, density: float = 1000.0, scale: float = 1.0) -> Body:
    """The body of ``models`` scaled by ``scale`` at ``density``; ValueError when they
    have no mass (only planes) or are not finite."""
    models = list(models)
    if not models:
        raise ValueError("a simulator model needs at least one primitive")
    density, scale = check_density(density), _positive(scale, "scale")
    scaled = [m.rescaled(scale, np.zeros(3)) for m in models]
    mass, centre, inertia = mass_properties(scaled, density)
    if not mass > 0:
        raise ValueError("the primitives have no volume (only planes): a simulator body "
                         "needs mass")
    geometries = tuple(geometry(m, f"part{i}_{m.name}") for i, m in enumerate(scaled))
    for g in geometries:
        if not (np.all(np.isfinite(g.transform)) and np.all(np.isfinite(g.size))
                and all(s > 0 for s in g.size)):
            raise ValueError(f"{g.name}: its pose or size is not finite and positive")
    return Body(geometries, mass, centre, inertia)


# ----- URDF ----------------------------------------------------------------------------------
def rpy(rotation) -> np.ndarray:
    """URDF's roll, pitch, yaw (3,) of a rotation (3, 3): R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r = np.asarray(rotation, np.float64)
    across = math.hypot(r[0, 0], r[1, 0])  # cos(pitch); atan2 keeps digits near +-90 deg
    pitch = math.atan2(-r[2, 0], across)
    if across > 1e-12:
        return np.array([math.atan2(r[2, 1], r[2, 2]), pitch, math.atan2(r[1, 0], r[0, 0])])
    return np.array([0.0, pitch, math.atan2(-r[0, 1], r[1, 1])])  # gimbal lock: roll 0


def urdf_element(body: Body, name: str, meshes: dict[str, str], *, visual: bool = True,
                 visual_mesh: str | None = None) -> ET.Element:
    """The ``<robot>`` element: one link ``name`` with the body's inertial, one
    ``<collision>`` per geometry, and ``<visual>``s: the visual mesh file where one is
    given, else the same geometries in the primitives' colours (with ``visual``).
    ``meshes`` maps a mesh geometry's name to its file, relative to the URDF's folder."""
    robot = ET.Element("robot", name=name)
    link = ET.SubElement(robot, "link", name=name)
    inertial = ET.SubElement(link, "inertial")
    ET.SubElement(inertial, "origin", xyz=_numbers(body.center_of_mass), rpy="0 0 0")
    ET.SubElement(inertial, "mass", value=_numbers([body.mass]))
    i = body.inertia
    ET.SubElement(inertial, "inertia", ixx=_number(i[0, 0]), ixy=_number(i[0, 1]),
                  ixz=_number(i[0, 2]), iyy=_number(i[1, 1]), iyz=_number(i[1, 2]),
                  izz=_number(i[2, 2]))
    if visual_mesh is not None:
        shown = ET.SubElement(link, "visual", name="visual_mesh")
        ET.SubElement(shown, "origin", xyz="0 0 0", rpy="0 0 0")
        ET.SubElement(ET.SubElement(shown, "geometry"), "mesh", filename=visual_mesh)
    for g in body.geometries:
        tags = ["collision"] + (["visual"] if visual and visual_mesh is None else [])
        for tag in tags:
            element = ET.SubElement(link, tag, name=g.name)
            ET.SubElement(element, "origin", xyz=_numbers(g.transform[:3, 3]),
                          rpy=_numbers(rpy(g.transform[:3, :3])))
            _urdf_shape(ET.SubElement(element, "geometry"), g, meshes)
            if tag == "visual":
                material = ET.SubElement(element, "material", name=g.name)
                ET.SubElement(material, "color", rgba=_numbers(g.rgba))
    return robot


def _urdf_shape(parent, g: Geometry, meshes):
    if g.kind == "box":
        ET.SubElement(parent, "box", size=_numbers(g.size))
    elif g.kind == "cylinder":
        ET.SubElement(parent, "cylinder", radius=_number(g.size[0]), length=_number(g.size[1]))
    elif g.kind == "sphere":
        ET.SubElement(parent, "sphere", radius=_number(g.size[0]))
    else:
        ET.SubElement(parent, "mesh", filename=meshes[g.name])


# ----- MJCF ----------------------------------------------------------------------------------
def mjcf_element(body: Body, name: str, meshes: dict[str, str], *, free: bool = True,
                 visual_mesh: str | None = None) -> ET.Element:
    """The ``<mujoco>`` element: a body ``name`` (with a free joint when ``free``) at the
    origin, its inertial, one geom per geometry. With a visual mesh file, that mesh is a
    geom that neither collides nor weighs (group 2) and the primitives go to group 3
    (MuJoCo's viewer hides it by default); without, the primitives show in their colours.
    ``meshes`` maps a mesh geometry's name to its file, relative to the MJCF's folder."""
    root = ET.Element("mujoco", model=name)
    ET.SubElement(root, "compiler", angle="radian")
    asset = ET.SubElement(root, "asset")
    for g in body.geometries:
        if g.kind == "mesh":
            ET.SubElement(asset, "mesh", name=g.name, file=meshes[g.name])
    if visual_mesh is not None:
        ET.SubElement(asset, "mesh", name=f"{name}_visual", file=visual_mesh)
    world = ET.SubElement(root, "worldbody")
    element = ET.SubElement(world, "body", name=name, pos="0 0 0")
    if free:
        ET.SubElement(element, "freejoint", name=f"{name}_free")
    i = body.inertia
    ET.SubElement(element, "inertial", pos=_numbers(body.center_of_mass),
                  mass=_number(body.mass),
                  fullinertia=_numbers([i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]))
    if visual_mesh is not None:
        ET.SubElement(element, "geom", name=f"{name}_visual", type="mesh",
                      mesh=f"{name}_visual", contype="0", conaffinity="0", group="2",
                      mass="0")
    for g in body.geometries:
        attributes = {"name": g.name, "type": g.kind, "pos": _numbers(g.transform[:3, 3]),
                      "xyaxes": _numbers(g.transform[:3, :2].T.reshape(-1)),
                      "rgba": _numbers(g.rgba)}
        if g.kind == "box":
            attributes["size"] = _numbers(0.5 * np.asarray(g.size))
        elif g.kind == "cylinder":
            attributes["size"] = _numbers([g.size[0], 0.5 * g.size[1]])
        elif g.kind == "sphere":
            attributes["size"] = _numbers(g.size)
        else:
            attributes["mesh"] = g.name
        if visual_mesh is not None:
            attributes["group"] = "3"
        ET.SubElement(element, "geom", attributes)
    return root


# ----- writing -------------------------------------------------------------------------------
def write_urdf(models, path, *, name: str = "object", density: float = 1000.0,
               mesh_dir=None, scale: float = 1.0, visual: bool = True,
               visual_mesh=None) -> Path:
    """Write ``models`` as a URDF robot of one link to ``path``.

    models : the primitives (``Model``), in the cloud's coordinates.
    name : the robot's and link's name, and the stem of the mesh files.
    density : mass per unit volume in the written units (1000: water, in kg/m^3 for a
        model in metres).
    mesh_dir : folder of the mesh files (cones, ``visual_mesh``); default the URDF's
        folder. The URDF names them relative to its own folder.
    scale : multiplies every length (0.001 for a cloud in millimetres).
    visual : give every part a ``<visual>`` (its primitive, in its colour).
    visual_mesh : a ``trimesh.Trimesh`` in the cloud's coordinates (say, the object's own
        mesh), written as ``{name}_visual.stl`` and shown instead of the primitives.
    """
    return _write(models, path, "urdf", name=name, density=density, mesh_dir=mesh_dir,
                  scale=scale, visual_mesh=visual_mesh, visual=visual)


def write_mjcf(models, path, *, name: str = "object", density: float = 1000.0,
               mesh_dir=None, scale: float = 1.0, free: bool = True,
               visual_mesh=None) -> Path:
    """Write ``models`` as an MJCF (MuJoCo) model of one body to ``path``: the arguments
    of ``write_urdf``, and ``free``: give the body a free joint (it falls and can be
    grasped); without one it is fixed to the world."""
    return _write(models, path, "mjcf", name=name, density=density, mesh_dir=mesh_dir,
                  scale=scale, visual_mesh=visual_mesh, free=free)


def _write(models, path, fmt, *, name, density, mesh_dir, scale, visual_mesh, **options):
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise ValueError(f"name must be letters, digits, '_', '.' or '-', got {name!r}")
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a folder; give a file name")
    if not path.parent.is_dir():
        raise ValueError(f"{path}: the folder {path.parent} does not exist")
    body = rigid_body(models, density=density, scale=scale)
    folder = path.parent if mesh_dir is None else Path(mesh_dir)
    files = {g.name: (folder / f"{name}_{g.name}.stl", g.mesh) for g in body.geometries
             if g.kind == "mesh"}
    if visual_mesh is not None:
        shown = visual_mesh.copy()
        shown.apply_scale(scale)
        files["visual"] = (folder / f"{name}_visual.stl", shown)
    if files:
        folder.mkdir(parents=True, exist_ok=True)
    refs = {key: Path(os.path.relpath(file, path.parent)).as_posix()
            for key, (file, _) in files.items()}
    visual_ref = refs.pop("visual", None)
    if fmt == "urdf":
        root = urdf_element(body, name, refs, visual_mesh=visual_ref, **options)
    else:
        root = mjcf_element(body, name, refs, visual_mesh=visual_ref, **options)
    ET.indent(root)
    text = ET.tostring(root, encoding="unicode") + "\n"
    # All files are renamed into place together, the model last: a reader never finds a
    # model that names a missing mesh.
    with contextlib.ExitStack() as stack:
        model_file = stack.enter_context(replacing(path))
        for file, mesh in files.values():
            mesh.export(stack.enter_context(replacing(file)), file_type="stl")
        model_file.write_text(text)
    return path


def _positive(value, what) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.number):
        raise ValueError(f"{what} must be a positive number, got {value!r}")
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{what} must be positive and finite, got {value!r}")
    return float(value)


def _number(x) -> str:
    return f"{float(x):.9g}"


def _numbers(values) -> str:
    return " ".join(_number(v) for v in np.ravel(values))
