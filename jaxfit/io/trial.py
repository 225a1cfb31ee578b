"""Grasp trials in MuJoCo: a parallel-jaw gripper built from ``ParallelJaw``'s
dimensions closes on an object at a planned grasp and lifts it (docs/grasping.md).

The scene (``trial_mjcf``), in metres, with +Z up and gravity along -Z:

- **the object**: its *original mesh*, not the primitives, as one free body with one
  mesh geom per convex piece (MuJoCo collides with each geom's convex hull). Without
  pieces given, the pieces are the mesh's connected bodies (faces joined by shared
  vertices, coincident vertices merged): an object that is one connected body (a mug)
  is then its convex hull, which fills a mug's opening and the hole of its handle. Pass
  ``pieces`` (say, CoACD's ``run_coacd`` parts, as benchmarks/grasping.py does) for a
  closer collision shape. Mass from ``density`` (kg/m^3) over the pieces' hulls;
- **a floor** under the object's lowest point (or none: the object then floats without
  gravity until the fingers have closed);
- **the gripper**: the palm and two finger boxes of ``ParallelJaw.boxes`` in a hand body
  whose frame is the grasp frame (origin between the fingertips, +Z approach, +Y
  closing); the hand is free and welded to a mocap body (position control of the base,
  gravity compensated); each finger slides along the closing axis under a position
  actuator whose force is capped at ``grip_force`` (a squeeze, not a rigid clamp).

The trial (``lift_trial``): the object settles (the hand parked 1 m above), the grasp
moves with it (as if the object were seen again where it came to rest); the open hand
(at the grasp's opening) starts at the pre-grasp pose (``finger_depth`` back), moves
to the grasp pose, the fingers close, the hand lifts ``lift`` and holds for ``hold``
seconds. Success: the object rose by at least half of
``lift`` and the object's point that lay midway between the fingertips when they had
closed still lies between the fingers (within the fingers' span along the closing axis,
within ``slack`` of the pads across them and along the approach).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .sim import _numbers

#: Simulation step (s) and the phases' durations (s): settle, approach, close.
TIMESTEP = 0.001
SETTLE, APPROACH, CLOSE = 0.5, 0.5, 0.6
#: Friction (sliding) of every geom; MuJoCo's default torsional and rolling friction.
FRICTION = 1.0
#: Mass of each finger and of the hand (kg).
FINGER_MASS, HAND_MASS = 0.05, 0.5


@dataclasses.dataclass(frozen=True)
class Trial:
    """The outcome of one lift trial; true when it succeeded.

    success : lifted and still between the fingers.
    rise : (m) how far the object's centre of mass rose from its rest.
    offset : (3,) (m) in the hand frame, the object's point that was midway between the
        fingertips when they had closed, at the end.
    finite : the simulation stayed finite.
    """

    success: bool
    rise: float
    offset: np.ndarray
    finite: bool

    def __bool__(self) -> bool:
        return bool(self.success)


def _up_frame(up) -> np.ndarray:
    """(3, 3) columns: the object's axes that become world X, Y, Z (Z along ``up``: an
    axis index 0, 1, 2, or a direction (3,), which may point down an axis, say (0, -1, 0)
    for a mug modelled with its opening at -Y)."""
    if isinstance(up, (int, np.integer)) and not isinstance(up, bool):
        if up not in (0, 1, 2):
            raise ValueError(f"up must be an axis 0, 1, 2 or a direction (3,), got {up!r}")
        return np.roll(np.eye(3), -(up + 1), axis=1)
    from ..shapes._geometry import frame

    direction = np.asarray(up, np.float64)
    norm = float(np.linalg.norm(direction)) if direction.shape == (3,) else 0.0
    if direction.shape != (3,) or not np.isfinite(norm) or norm == 0:
        raise ValueError(f"up must be an axis 0, 1, 2 or a direction (3,), got {up!r}")
    return frame(direction / norm)


def _pieces(mesh, pieces):
    import trimesh

    parts = _connected_bodies(mesh) if pieces is None else pieces
    out = []
    for part in parts:
        vertices = np.asarray(part.vertices if hasattr(part, "vertices") else part, np.float64)
        if len(vertices) < 4 or np.linalg.matrix_rank(vertices - vertices.mean(axis=0),
                                                      tol=1e-12) < 3:
            continue  # flat or a point: no volume, no collision shape
        try:
            hull = trimesh.convex.convex_hull(vertices)
        except Exception:  # flat or degenerate: no volume, no collision shape
            continue
        if hull.volume > 0:
            out.append(hull)
    if not out:
        raise ValueError("the object has no piece with volume to collide with")
    return out


def _connected_bodies(mesh) -> list[np.ndarray]:
    """The vertices (n, 3) of each connected body of ``mesh`` (its faces joined by shared
    vertices, coincident vertices merged)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    vertices, inverse = np.unique(np.round(np.asarray(mesh.vertices, np.float64), 12),
                                  axis=0, return_inverse=True)
    faces = inverse.reshape(-1)[np.asarray(mesh.faces)]
    if len(faces) == 0:
        return []
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])),
                       shape=(len(vertices),) * 2)
    count, label = connected_components(graph, directed=False)
    used = np.zeros(len(vertices), bool)
    used[faces.reshape(-1)] = True
    return [vertices[(label == c) & used] for c in range(count) if np.any(used[label == c])]


def trial_mjcf(mesh, gripper, width: float, *, pieces=None, scale: float = 1.0, up=2,
               density: float = 500.0, floor: bool = True,
               grip_force: float = 40.0) -> tuple[str, float]:
    """The MJCF text of the trial's scene (module docstring) and each finger's joint
    position at the opening ``width`` (0 is fully open). ``mesh``: a
    ``trimesh.Trimesh`` in the cloud's coordinates (or a list of convex pieces);
    ``gripper``: a ``ParallelJaw`` in the cloud's units; ``width``: the fingers' opening
    at the start (cloud units); ``scale`` turns cloud units into metres; ``up`` is the
    object's axis that points up. The object body's frame is the world frame; the hand's
    pose is set by ``lift_trial``."""
    frame = _up_frame(up)
    hulls = [h.copy() for h in _pieces(mesh, pieces)]
    for h in hulls:
        h.vertices = (np.asarray(h.vertices) * scale) @ frame  # world = frame.T @ local
    lo = min(h.vertices[:, 2].min() for h in hulls)
    s = scale
    t, fw, fd = gripper.finger_thickness * s, gripper.finger_width * s, gripper.finger_depth * s
    pw, pd, wmax = gripper.palm_width * s, gripper.palm_depth * s, gripper.max_width * s
    opening = float(np.clip(width * s, 0.0, wmax))
    travel = wmax / 2  # each finger slides from the open stop (0) to the middle
    assets = "\n".join(f'    <mesh name="piece{i}" vertex="{_numbers(h.vertices)}" '
                       f'inertia="convex"/>' for i, h in enumerate(hulls))
    geoms = "\n".join(f'      <geom name="piece{i}" type="mesh" mesh="piece{i}" '
                      f'density="{density:.9g}" rgba="0.8 0.6 0.3 1"/>'
                      for i in range(len(hulls)))
    floor_geom = (f'    <geom name="floor" type="plane" size="0 0 1" pos="0 0 {lo:.9g}" '
                  f'rgba="0.5 0.5 0.5 1"/>') if floor else ""
    fingers = []
    for side, sign in (("left", -1), ("right", 1)):
        # qpos 0 is the finger fully open; positive qpos moves it towards the middle.
        fingers.append(f"""
      <body name="finger_{side}" gravcomp="1" pos="0 {sign * (wmax / 2 + t / 2):.9g} {-fd / 2:.9g}">
        <joint name="finger_{side}" type="slide" axis="0 {-sign} 0" range="0 {travel:.9g}"
               damping="5" armature="0.01"/>
        <geom name="finger_{side}" type="box" size="{fw / 2:.9g} {t / 2:.9g} {fd / 2:.9g}"
              mass="{FINGER_MASS}" condim="4" rgba="0.2 0.2 0.8 1"/>
      </body>""")
    close_range = f'0 {travel:.9g}'
    return f"""<mujoco model="grasp_trial">
  <compiler angle="radian"/>
  <option timestep="{TIMESTEP}" gravity="0 0 -9.81" cone="elliptic" impratio="10"
          integrator="implicitfast"/>
  <default>
    <geom friction="{FRICTION} 0.005 0.0001" solref="0.004 1"/>
  </default>
  <asset>
{assets}
  </asset>
  <worldbody>
{floor_geom}
    <body name="object" pos="0 0 0">
      <freejoint name="object"/>
{geoms}
    </body>
    <body name="target" mocap="true" pos="0 0 1"/>
    <body name="hand" pos="0 0 1" gravcomp="1">
      <freejoint name="hand"/>
      <geom name="palm" type="box" size="{pw / 2:.9g} {wmax / 2 + t:.9g} {pd / 2:.9g}"
            pos="0 0 {-fd - pd / 2:.9g}" mass="{HAND_MASS}" rgba="0.3 0.3 0.3 1"/>
      {"".join(fingers)}
    </body>
  </worldbody>
  <equality>
    <weld body1="target" body2="hand" solref="0.01 1"/>
  </equality>
  <contact>
    <exclude body1="finger_left" body2="finger_right"/>
  </contact>
  <actuator>
    <position name="finger_left" joint="finger_left" kp="2000" kv="20" ctrlrange="{close_range}"
              forcelimited="true" forcerange="{-grip_force:.9g} {grip_force:.9g}"/>
    <position name="finger_right" joint="finger_right" kp="2000" kv="20"
              ctrlrange="{close_range}" forcelimited="true"
              forcerange="{-grip_force:.9g} {grip_force:.9g}"/>
  </actuator>
</mujoco>
""", (wmax - opening) / 2


def lift_trial(mesh, pose, width: float, gripper, *, pieces=None, scale: float = 1.0,
               up=2, lift: float = 0.10, hold: float = 2.0, density: float = 500.0,
               floor: bool = True, grip_force: float = 40.0, slack: float = 0.01) -> Trial:
    """Simulate one grasp (module docstring) and return its ``Trial`` (true on success).

    mesh : the object's original ``trimesh.Trimesh`` in the cloud's coordinates (split
        into its connected bodies), unless ``pieces`` (convex meshes or (n, 3) vertex
        arrays, same coordinates) are given.
    pose : (4, 4) grasp frame in the cloud's coordinates (``Grasps.poses[i]``).
    width : the opening the fingers start at (``Grasps.widths[i]``), cloud units.
    gripper : the ``ParallelJaw`` the grasp was planned for (cloud units).
    scale : cloud units to metres (0.001 for GraspIt!'s millimetres).
    up : the object's axis that points up (gravity along its minus): 0, 1, 2, or a
        direction (3,) (``_up_frame``).
    lift, hold : metres lifted, seconds held after the lift.
    floor : rest the object on a floor; without, it floats without gravity until the
        fingers have closed.
    grip_force : the most force (N) each finger's actuator pushes with.
    slack : (m) how far outside the fingers' footprint the held point may drift.
    """
    import mujoco

    pose = np.asarray(pose, np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError("pose must be a finite (4, 4) matrix")
    xml, start = trial_mjcf(mesh, gripper, width, pieces=pieces, scale=scale, up=up,
                            density=density, floor=floor, grip_force=grip_force)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    frame = _up_frame(up)
    rotation = frame.T @ pose[:3, :3]
    position = frame.T @ (pose[:3, 3] * scale)
    s = scale
    adr = model.joint("hand").qposadr[0]
    quat = np.zeros(4)

    def place_hand(at, rotation):
        mujoco.mju_mat2Quat(quat, rotation.reshape(-1))
        data.qpos[adr:adr + 3], data.qpos[adr + 3:adr + 7] = at, quat
        data.qvel[model.joint("hand").dofadr[0]:][:6] = 0.0
        data.mocap_pos[0], data.mocap_quat[0] = at, quat
        mujoco.mj_forward(model, data)

    fingers = [model.joint(f"finger_{side}").qposadr[0] for side in ("left", "right")]
    data.qpos[fingers] = start
    data.ctrl[:] = start
    if not floor:
        model.opt.gravity[:] = 0.0
    obj = model.body("object").id
    hand = model.body("hand").id
    place_hand(position + np.array([0.0, 0.0, 1.0]), rotation)  # parked 1 m above
    finite = True

    def run(seconds, update=None):
        nonlocal finite
        steps = max(1, int(round(seconds / model.opt.timestep)))
        for k in range(steps):
            if update is not None:
                update((k + 1) / steps)
            mujoco.mj_step(model, data)
        finite &= bool(np.all(np.isfinite(data.qpos)))

    def smooth(u):
        return 3 * u**2 - 2 * u**3

    run(SETTLE)
    rest = data.xipos[obj].copy()
    # The grasp moves with the object as it settled (as if the object were seen again).
    settled = data.xmat[obj].reshape(3, 3).copy()
    rotation, position = settled @ rotation, settled @ position + data.xpos[obj]
    pre = position - gripper.finger_depth * s * rotation[:, 2]
    place_hand(pre, rotation)
    run(APPROACH, lambda u: data.mocap_pos.__setitem__(0, pre + smooth(u) * (position - pre)))
    travel = gripper.max_width * s / 2
    run(CLOSE, lambda u: data.ctrl.__setitem__(slice(None), start + smooth(u) * (travel - start)))
    # The object's point midway between the fingertips now, in the object's frame.
    hand_pos = data.xpos[hand].copy()
    obj_rot, obj_pos = data.xmat[obj].reshape(3, 3).copy(), data.xpos[obj].copy()
    held = obj_rot.T @ (hand_pos - obj_pos)
    if not floor:
        model.opt.gravity[:] = (0.0, 0.0, -9.81)
    top = position + np.array([0.0, 0.0, lift])
    run(max(lift / 0.1, 0.5), lambda u: data.mocap_pos.__setitem__(0, position + smooth(u)
                                                                    * (top - position)))
    run(hold)
    hand_rot, hand_pos = data.xmat[hand].reshape(3, 3), data.xpos[hand]
    point = data.xmat[obj].reshape(3, 3) @ held + data.xpos[obj]
    offset = hand_rot.T @ (point - hand_pos)
    rise = float(data.xipos[obj][2] - rest[2])
    g = gripper
    inside = (abs(offset[1]) <= g.max_width * s / 2
              and abs(offset[0]) <= g.finger_width * s / 2 + slack
              and -g.finger_depth * s - slack <= offset[2] <= slack)
    success = bool(finite and inside and rise >= 0.5 * lift)
    return Trial(success, rise, offset, finite)
