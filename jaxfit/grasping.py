"""Pre-grasps of a parallel-jaw gripper from an object's primitives, after GraspIt!'s
primitive planner (Miller, Knoop, Christensen & Allen 2003, "Automatic grasp planning
using shape primitives").

Each part's primitive proposes approach directions and closing axes in its canonical
frame (``model.transform()``, docs/robot.md):

- box: along each face normal, closing across either pair of faces perpendicular to it,
  on three lines across the face;
- cylinder: radial at five heights and eight azimuths, closing around the diameter or
  along the axis; along the axis from both ends, closing at four rotations about it;
- sphere: 32 directions around it (a randomly rotated Fibonacci sphere), three closing
  rotations about each;
- cone: radial at four heights and eight azimuths (both closings), from the base and from
  the apex at four rotations;
- plane (a bounded patch): from eight directions in its plane, closing across it;
- every part, whatever its primitive: 16 of its points spread over it (farthest-point
  sampling), closing along the point's normal, approached along the four directions
  perpendicular to it that follow the primitive's axes: on a hollow cylinder's wall these
  are rim grasps (along the axis from the open end, one finger inside the wall, one
  outside), on a thin part (a handle) grasps across its thin side.

Azimuths, rotations and the seeds' first point are drawn per part (NumPy, seeded from
``key``: the same key gives the same grasps). All candidates of all parts are then filtered and
scored in one jitted JAX call against the object's points (the whole cloud, so a grasp
on one part also avoids the others): the open hand slides along its approach axis until
its fingers or palm would touch a point, or its fingertips reach the approach line's
centre; the points between the fingers are the closing region, the jaws close on them
(the hand re-centred between them, as a compliant wrist would), and the grasp is kept
when the region holds enough points, the contact width fits (``max_width``), the gripper
at that opening (palm and finger boxes) touches no point, and the surface normals at the
points nearest the two finger pads are close to the closing axis (antipodal quality).
The pre-grasp opening is then as wide as the fingers can open there without touching a
point. With ``support`` (a table plane) grasps whose gripper boxes at the grasp or the
pre-grasp would reach the table are dropped; near-duplicates of better grasps are
dropped; the rest are ranked by the score: antipodal quality x alignment of the contacts
with the closing axis x patch / (patch + lever), the pads' contact patch radius against
the lever of the centre of mass about the closing line (gravity's torque about that line
is what the pads' friction must resist).

Grasp frame (``Grasps.poses``, 4x4 in the cloud's coordinates): origin midway between
the fingertips; local +Z the approach direction (from the palm towards the fingertips,
into the object); local +Y the closing axis (the fingers sit at y = +-width/2 and close
along it); +X = Y x Z, across the finger pads. The pre-grasp of GraspIt!'s planner, the
hand at a standoff, is ``Grasps.pregrasp(standoff)``: the pose moved back along -Z.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import numbers
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from . import _checks
from .engine.backend import LOOP_EMITTERS, jit_tuned
from .engine.cloud import bucket_size
from .shapes import mass_properties
from .shapes._geometry import frame

#: Candidates are padded to a multiple of this and points to the fits' point buckets
#: (``engine.bucket_size``), so the filter compiles once per bucket, not per object.
CANDIDATE_BUCKET = 64
#: Surface-seeded candidates per part (``_seeded_candidates``): points drawn per part,
#: each approached from four directions.
SEEDS_PER_PART = 16


@dataclasses.dataclass(frozen=True)
class ParallelJaw:
    """A parallel-jaw gripper: two finger boxes on a palm box, in the grasp frame (module
    docstring), in the cloud's units.

    max_width : widest opening, between the inner faces of the fingers.
    finger_depth : length of the fingers along the approach axis (Z); the fingers span
        z in [-finger_depth, 0].
    finger_width : width of the finger pads across them (X).
    finger_thickness : thickness of a finger along the closing axis (Y); default a quarter
        of ``finger_width``.
    palm_depth : palm thickness along Z, behind the fingers (z in [-finger_depth -
        palm_depth, -finger_depth]); default half of ``finger_depth``.
    palm_width : palm size along X; default ``finger_width``. Along Y the palm spans the
        fingers at ``max_width``.
    clearance : margin kept between the gripper and the points while approaching and
        added to the contact width on each side for the pre-grasp opening; default 2 % of
        ``max_width``; less than ``max_width / 4``.
    """

    max_width: float
    finger_depth: float
    finger_width: float
    finger_thickness: float | None = None
    palm_depth: float | None = None
    palm_width: float | None = None
    clearance: float | None = None

    def __post_init__(self):
        put = functools.partial(object.__setattr__, self)
        for name in ("max_width", "finger_depth", "finger_width"):
            put(name, _checks.positive(getattr(self, name), f"ParallelJaw {name}"))
        defaults = {"finger_thickness": self.finger_width / 4, "palm_depth": self.finger_depth / 2,
                    "palm_width": self.finger_width, "clearance": 0.02 * self.max_width}
        for name, default in defaults.items():
            value = getattr(self, name)
            if value is None:
                put(name, float(default))
            elif name == "clearance":
                value = _checks.non_negative(value, "ParallelJaw clearance")
                if not value < self.max_width / 4:
                    raise ValueError(f"ParallelJaw clearance must be less than max_width / 4 "
                                     f"= {self.max_width / 4!r}, got {value!r}")
                put(name, value)
            else:
                put(name, _checks.positive(value, f"ParallelJaw {name}"))
        if self.palm_width < self.finger_width:
            raise ValueError(f"ParallelJaw palm_width ({self.palm_width!r}) must be at least "
                             f"finger_width ({self.finger_width!r})")

    def boxes(self, width: float) -> np.ndarray:
        """(3, 2, 3): lower and upper corners in the grasp frame of the palm and the two
        fingers (-Y, +Y) at opening ``width``."""
        t, hw, fd = self.finger_thickness, self.finger_width / 2, self.finger_depth
        span = self.max_width / 2 + t
        return np.array([
            [[-self.palm_width / 2, -span, -fd - self.palm_depth],
             [self.palm_width / 2, span, -fd]],
            [[-hw, -width / 2 - t, -fd], [hw, -width / 2, 0.0]],
            [[-hw, width / 2, -fd], [hw, width / 2 + t, 0.0]],
        ])

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True, eq=False)
class Grasps:
    """Grasp candidates that passed the filter, best first.

    poses : (K, 4, 4) grasp frames in the cloud's coordinates (module docstring: +Z
        approach, +Y closing axis, origin midway between the fingertips).
    widths : (K,) pre-grasp opening: as wide as the fingers open at the grasp pose
        without touching a point (within the region the approach swept), at least the
        contact width plus the clearance on each side, at most ``max_width``.
    contact_widths : (K,) distance between the outermost points the jaws close on.
    contacts : (K, 2, 3) centroids of the points nearest the -Y and +Y finger pads.
    parts : (K,) index of the part (``Decomposition.parts``) whose primitive proposed it.
    primitives : (K,) that primitive's name.
    scores : (K,) antipodal quality x alignment x patch / (patch + lever), in [0, 1]
        (module docstring).
    antipodal : (K,) the lower of the two pads' mean |normal . closing axis|.
    gripper : the ParallelJaw.
    num_candidates : candidates proposed before filtering.
    seconds : planning time.
    """

    poses: np.ndarray
    widths: np.ndarray
    contact_widths: np.ndarray
    contacts: np.ndarray
    parts: np.ndarray
    primitives: np.ndarray
    scores: np.ndarray
    antipodal: np.ndarray
    gripper: ParallelJaw
    num_candidates: int
    seconds: float

    def __len__(self) -> int:
        return len(self.scores)

    @property
    def approach(self) -> np.ndarray:
        """(K, 3) approach directions (the poses' +Z)."""
        return self.poses[:, :3, 2]

    @property
    def closing(self) -> np.ndarray:
        """(K, 3) closing axes (the poses' +Y)."""
        return self.poses[:, :3, 1]

    def pregrasp(self, standoff: float | None = None) -> np.ndarray:
        """(K, 4, 4) the poses moved back by ``standoff`` along their -Z (default the
        finger depth): where the open hand starts before approaching."""
        standoff = self.gripper.finger_depth if standoff is None else _checks.non_negative(
            standoff, "standoff")
        out = self.poses.copy()
        out[:, :3, 3] -= standoff * self.approach
        return out

    def to_dict(self) -> dict:
        """JSON-ready: the gripper, the frame convention and one record per grasp."""
        return {
            "frame": "origin midway between the fingertips, +Z approach, +Y closing axis",
            "gripper": self.gripper.to_dict(),
            "num_candidates": self.num_candidates,
            "seconds": self.seconds,
            "grasps": [{"pose": self.poses[i].tolist(), "width": float(self.widths[i]),
                        "contact_width": float(self.contact_widths[i]),
                        "contacts": self.contacts[i].tolist(), "part": int(self.parts[i]),
                        "primitive": str(self.primitives[i]), "score": float(self.scores[i]),
                        "antipodal": float(self.antipodal[i])} for i in range(len(self))],
        }


    def save(self, directory, decomposition, *, top: int = 10) -> Path:
        """Write grasps.json (``to_dict``) and grasps.png (the first ``top`` grasps drawn on
        ``decomposition``'s primitives) into ``directory``, both renamed into place only
        when both are written (``io.atomic``)."""
        from .io.atomic import replacing_all
        from .io.grasp_preview import render

        with replacing_all(directory, ("grasps.json", "grasps.png")) as files:
            files["grasps.json"].write_text(json.dumps(self.to_dict(), indent=1))
            render(decomposition, self, files["grasps.png"], top=top)
        return Path(directory)


# ----------------------------------------------------------------------------------------
# Candidates per primitive (NumPy), in the primitive's canonical frame.


def _circle(angles):
    return np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=-1)


def _radial(heights, azimuths):
    """Approaches towards the Z axis at each height and azimuth, closing around it
    (tangent) and along it (axial): (centres, approaches, closings)."""
    h, a = np.meshgrid(heights, azimuths, indexing="ij")
    h, a = h.ravel(), a.ravel()
    inward = -_circle(a)
    tangent = np.cross([0.0, 0.0, 1.0], inward)
    centres = np.stack([np.zeros_like(h), np.zeros_like(h), h], axis=-1)
    z = np.broadcast_to([0.0, 0.0, 1.0], inward.shape)
    return (np.concatenate([centres, centres]), np.concatenate([inward, inward]),
            np.concatenate([tangent, z]))


def _along_z(centre_z, direction, rotations):
    """Approaches along +-Z (``direction``) through (0, 0, centre_z), closing at each
    rotation about Z."""
    n = len(rotations)
    centres = np.tile([0.0, 0.0, centre_z], (n, 1))
    return centres, np.tile([0.0, 0.0, direction], (n, 1)), _circle(rotations)


def _join(*groups):
    return tuple(np.concatenate(parts) for parts in zip(*groups, strict=True))


def _box_candidates(model, rng):
    e = np.asarray(model.extents, np.float64)
    centres, approaches, closings = [], [], []
    for a in range(3):
        for b in range(3):
            if b == a:
                continue
            c = 3 - a - b  # the axis along the face that neither approach nor closing takes
            for sign in (-1.0, 1.0):
                for offset in (-0.25, 0.0, 0.25):
                    centres.append(offset * e[c] * np.eye(3)[c])
                    approaches.append(-sign * np.eye(3)[a])
                    closings.append(np.eye(3)[b])
    return np.array(centres), np.array(approaches), np.array(closings)


def _angles(rng, count: int, span: float) -> np.ndarray:
    """(count,) angles evenly spaced over ``span`` from one random offset in [0, span)."""
    return rng.uniform(0, span) + np.arange(count) * (span / count)


def _cylinder_candidates(model, rng):
    h = float(model.height)
    heights = np.linspace(-h / 2, h / 2, 7)[1:-1]
    azimuths = _angles(rng, 8, 2 * np.pi)
    rotations = _angles(rng, 4, np.pi)
    return _join(_radial(heights, azimuths), _along_z(0.0, -1.0, rotations),
                 _along_z(0.0, 1.0, rotations))


def _cone_candidates(model, rng):
    h = float(model.height)
    heights = np.linspace(0.0, h, 6)[1:-1]
    azimuths = _angles(rng, 8, 2 * np.pi)
    rotations = _angles(rng, 4, np.pi)
    return _join(_radial(heights, azimuths), _along_z(h / 4, 1.0, rotations),
                 _along_z(h / 4, -1.0, rotations))


def _sphere_candidates(model, rng, count: int = 32, rotations: int = 3):
    i = np.arange(count) + 0.5
    polar, azimuth = np.arccos(1 - 2 * i / count), np.pi * (1 + 5**0.5) * i
    directions = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth),
                           np.cos(polar)], axis=-1)
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    directions = directions @ (q * np.sign(np.diag(r))).T
    approaches = np.repeat(-directions, rotations, axis=0)
    angles = _angles(rng, rotations, np.pi)
    angles = np.tile(angles, count)
    frames = np.array([frame(d) for d in approaches])
    closings = np.cos(angles)[:, None] * frames[:, :, 0] + np.sin(angles)[:, None] * frames[:, :, 1]
    return np.zeros_like(approaches), approaches, closings


def _plane_candidates(model, rng):
    if model.radius is None:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    azimuths = _angles(rng, 8, 2 * np.pi)
    inward = -_circle(azimuths)
    return np.zeros_like(inward), inward, np.tile([0.0, 0.0, 1.0], (len(inward), 1))


#: primitive name -> candidates (centres, approaches, closings) in its canonical frame.
PROPOSERS = {"box": _box_candidates, "cylinder": _cylinder_candidates,
             "cone": _cone_candidates, "sphere": _sphere_candidates,
             "plane": _plane_candidates}


def _spread(points, count: int, rng) -> np.ndarray:
    """(count,) indices of points spread over ``points`` (n, 3): farthest-point sampling
    from a random first point, so the seeds reach the part's ends and edges (a rim) rather
    than landing where the points are dense."""
    pick = [int(rng.integers(len(points)))]
    gap = np.linalg.norm(points - points[pick[0]], axis=1)
    for _ in range(count - 1):
        pick.append(int(np.argmax(gap)))
        gap = np.minimum(gap, np.linalg.norm(points - points[pick[-1]], axis=1))
    return np.asarray(pick)


def _seeded_candidates(model, points, normals, rng, count: int = SEEDS_PER_PART):
    """Candidates on ``count`` of a part's points (spread over it, ``_spread``), in the cloud's
    coordinates: closing along the point's normal (the pad lands on that surface), the
    approach line through the point along the four directions perpendicular to the
    normal that follow the primitive's axes (cylinder and cone: along the axis and around
    it; box: its two axes most perpendicular to the normal; sphere and plane: a frame
    about the normal). On a hollow cylinder's wall this gives rim grasps (from the open
    end along the axis, one finger inside the wall, one outside); on a thin part (a
    handle) grasps across its thin side; the filter drops the rest."""
    if len(points) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    pick = _spread(points, min(count, len(points)), rng)
    p, n = points[pick], normals[pick]
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    axes = np.asarray(model.transform(), np.float64)[:3, :3]
    if model.name in ("cylinder", "cone"):
        guide = np.broadcast_to(axes[:, 2], n.shape)
    elif model.name == "box":
        guide = axes.T[np.argmin(np.abs(n @ axes), axis=1)]
    else:
        guide = np.array([frame(v)[:, 0] for v in n])
    e1 = guide - np.sum(guide * n, axis=1, keepdims=True) * n
    norm = np.linalg.norm(e1, axis=1, keepdims=True)
    good = norm[:, 0] > 0.5  # the axis is far from the normal: a wall, not an end face
    e1 = e1[good] / norm[good]
    p, n = p[good], n[good]
    e2 = np.cross(n, e1)
    approaches = np.concatenate([e1, -e1, e2, -e2])
    return np.tile(p, (4, 1)), approaches, np.tile(n, (4, 1))


def candidates(decomposition, *, key=0, normals=None, seeds: int = SEEDS_PER_PART):
    """All parts' candidates in the cloud's coordinates: centres (K, 3) of the approach
    lines, rotations (K, 3, 3) with columns X, Y (closing), Z (approach), part indices
    (K,). The primitive's own approaches (``PROPOSERS``) come first, then, when
    ``normals`` (N, 3) of the decomposition's points are given, ``seeds`` surface-seeded
    ones per part (``_seeded_candidates``)."""
    seed = _checks.numpy_seed(key)
    centres, rotations, parts = [], [], []
    points = np.asarray(decomposition.points, np.float64)
    for index, part in enumerate(decomposition.parts):
        propose = PROPOSERS.get(part.model.name)
        if propose is None:
            continue
        rng = np.random.default_rng([seed, index])
        c, z, y = propose(part.model, rng)
        transform = np.asarray(part.model.transform(), np.float64)
        r0, o = transform[:3, :3], transform[:3, 3]
        c, z, y = c @ r0.T + o, z @ r0.T, y @ r0.T
        if normals is not None and seeds:
            idx = np.asarray(part.indices)
            c2, z2, y2 = _seeded_candidates(part.model, points[idx], normals[idx], rng, seeds)
            c, z, y = np.concatenate([c, c2]), np.concatenate([z, z2]), np.concatenate([y, y2])
        if not len(c):
            continue
        y = y - np.sum(y * z, axis=1, keepdims=True) * z
        y /= np.linalg.norm(y, axis=1, keepdims=True)
        centres.append(c)
        rotations.append(np.stack([np.cross(y, z), y, z], axis=-1))
        parts.append(np.full(len(c), index))
    if not centres:
        return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, int)
    return np.concatenate(centres), np.concatenate(rotations), np.concatenate(parts)


# ----------------------------------------------------------------------------------------
# The filter (JAX): one call for all candidates against all points.


#: Candidates filtered together in one step of ``_filter``'s loop: a (32, N) block of
#: each per-point quantity stays in the cache; the whole (C, N) at once ran ~15x slower
#: (0.40 s against 0.025 s for the duck's 584 candidates, 2 shared cores).
FILTER_CHUNK = 32


def _filter_all(points, valid, normals, centres, rotations, com, dims):
    """``_filter_block`` over the candidates (C,) in chunks of ``FILTER_CHUNK`` (C a
    multiple of it), its outputs joined."""
    out = jax.lax.map(
        lambda block: _filter_block(points, valid, normals, *block, com, dims),
        (centres.reshape(-1, FILTER_CHUNK, 3), rotations.reshape(-1, FILTER_CHUNK, 3, 3)))
    return tuple(o.reshape((-1, *o.shape[2:])) for o in out)


# Kept between processes with the fitting kernels (jaxfit's cache is scoped to them);
# XLA's loop emitters on the CPU: 0.6 of the compile for ~12 % more run time, and a
# grasp search runs it once per object (docs/grasping.md).
_filter = jit_tuned(_filter_all, (), LOOP_EMITTERS)


def _filter_block(points, valid, normals, centres, rotations, com, dims):
    """For candidates (C,) against points (N,): whether each passes, its origin, opening,
    contact width, pad contacts, antipodal quality and score (module docstring). ``dims``
    holds max_width, finger_depth, finger_width / 2, finger_thickness, palm_depth,
    palm_width / 2, clearance, the minimum antipodal quality, the minimum points in the
    closing region."""
    w0, fd, hw, t, pd, hp, cl, min_q, min_n = (dims[i] for i in range(9))
    big = jnp.asarray(jnp.finfo(points.dtype).max / 4, points.dtype)
    # Points in each candidate's frame: (p - c) R, as one (N, 3) x (C, 3, 3) product.
    shift = jnp.einsum("cj,cjk->ck", centres, rotations)
    x, y, z = (jnp.einsum("nj,cj->cn", points, rotations[:, :, k]) - shift[:, k, None]
               for k in range(3))
    ax, ay = jnp.abs(x), jnp.abs(y)
    v = valid[None]
    # Open hand sliding along +Z until a finger (fingertip at z - cl) or the palm (its
    # face fd behind the fingertips) meets a point of its footprint; the finger footprint
    # lies inside the palm's, where the finger stops first.
    in_palm = v & (ax <= hp + cl) & (ay <= w0 / 2 + t + cl)
    in_finger = (ax <= hw + cl) & (ay >= w0 / 2 - cl)
    stop = jnp.where(in_palm, z - cl + jnp.where(in_finger, 0.0, fd), big)
    s = jnp.minimum(jnp.min(stop, axis=1), 0.0)  # fingertips stop at the line's centre
    # The closing region between the open fingers.
    z0 = z - s[:, None]
    band = v & (ax <= hw) & (z0 >= -fd) & (z0 <= 0) & (ay < w0 / 2)
    count = jnp.sum(band, axis=1)
    lo = jnp.min(jnp.where(band, y, big), axis=1)
    hi = jnp.max(jnp.where(band, y, -big), axis=1)
    has = count >= min_n
    lo, hi = jnp.where(has, lo, 0.0), jnp.where(has, hi, 0.0)
    mid, contact_width = 0.5 * (lo + hi), hi - lo
    width = jnp.minimum(w0, contact_width + 2 * cl)
    # The gripper at the final pose and opening (boxes grown by half the clearance) must
    # touch no point.
    m = 0.5 * cl
    ay1 = jnp.abs(y - mid[:, None])
    finger_hit = ((ax <= hw + m) & (ay1 >= width[:, None] / 2 - m)
                  & (ay1 <= width[:, None] / 2 + t + m) & (z0 >= -fd - m) & (z0 <= m))
    palm_hit = ((ax <= hp + m) & (ay1 <= w0 / 2 + t + m) & (z0 >= -fd - pd - m)
                & (z0 <= -fd + m))
    collides = jnp.any(v & (finger_hit | palm_hit), axis=1)
    # The pre-grasp opening: as wide as the fingers can open at this pose without
    # touching a point (the nearest point beyond the fingers' outer faces in their
    # footprint), within the swept region the approach checked (the original line's
    # fingers at max_width), at least the contact width plus the clearance.
    beside = (v & (ax <= hw + m) & (z0 >= -fd - m) & (z0 <= m)
              & (ay1 > width[:, None] / 2 + t + m))
    nearest = jnp.min(jnp.where(beside, ay1, big), axis=1)
    opening = jnp.clip(jnp.minimum(w0 - 2 * jnp.abs(mid), 2 * (nearest - t - m)), width, w0)
    # Antipodal quality: mean |normal . closing axis| over the region's points within
    # ``tol`` of each pad.
    closing = rotations[:, :, 1]
    cos = jnp.abs(jnp.einsum("nj,cj->cn", normals, closing))
    # (at most 0.45 of the contact width: on a wall thinner than twice the clearance the
    # two pads keep apart sets, its two faces)
    tol = jnp.minimum(jnp.maximum(2 * cl, 0.05 * contact_width), 0.45 * contact_width)[:, None]

    def pad(near):
        w = near.astype(points.dtype)
        n = jnp.maximum(jnp.sum(w, axis=1), 1.0)

        def mean(a):
            return jnp.sum(w * a, axis=1) / n

        # The patch's radius in the pad's plane: RMS distance of its points from their
        # centroid across the pad (x) and along the finger (z) (centred first: float32).
        dx, dz = x - mean(x)[:, None], z0 - mean(z0)[:, None]
        spread = jnp.sqrt(mean(dx * dx + dz * dz))
        return mean(cos), (w @ points) / n[:, None], spread

    q_lo, c_lo, r_lo = pad(band & (y - lo[:, None] <= tol))
    q_hi, c_hi, r_hi = pad(band & (hi[:, None] - y <= tol))
    antipodal = jnp.minimum(q_lo, q_hi)
    line = c_hi - c_lo
    alignment = jnp.abs(jnp.sum(line * closing, axis=1)) / jnp.maximum(
        jnp.linalg.norm(line, axis=1), 1e-30)
    origin = centres + jnp.einsum("cjk,ck->cj", rotations,
                                  jnp.stack([jnp.zeros_like(s), mid, s], axis=1))
    grip = 0.5 * (c_lo + c_hi)
    # Gravity's torque about the closing line (lever: the centre of mass's distance from
    # it) against what the pads' friction patches resist (their radius): r / (r + lever).
    arm = com - grip
    lever = jnp.linalg.norm(arm - jnp.sum(arm * closing, axis=1, keepdims=True) * closing,
                            axis=1)
    patch = jnp.minimum(r_lo, r_hi)
    holding = patch / jnp.maximum(patch + lever, 1e-30)
    score = antipodal * alignment * holding
    ok = (has & ~collides & (antipodal >= min_q) & (contact_width > 0) & (contact_width < w0)
          & jnp.isfinite(score) & (s > -big / 2))
    return ok, origin, opening, contact_width, jnp.stack([c_lo, c_hi], axis=1), antipodal, score


def _bucket(n: int, step: int) -> int:
    return max(step, -(-n // step) * step)


def _support(support):
    """``support`` as (unit up (3,), height) or None, checked."""
    if support is None:
        return None
    try:
        up, height = support
        up = np.asarray(up, np.float64)
    except (TypeError, ValueError):
        raise ValueError("support must be (up, height): a direction (3,) out of the table "
                         f"and the table's offset along it, got {support!r}") from None
    norm = float(np.linalg.norm(up)) if up.shape == (3,) else 0.0
    if up.shape != (3,) or not np.all(np.isfinite(up)) or norm == 0:
        raise ValueError(f"support's up must be a finite non-zero (3,) direction, got {up!r}")
    if isinstance(height, bool) or not isinstance(height, numbers.Real) or not np.isfinite(
            height):
        raise ValueError(f"support's height must be a finite number, got {height!r}")
    return up / norm, float(height)


def clears_support(poses, widths, gripper: ParallelJaw, up, height: float,
                   standoff: float | None = None) -> np.ndarray:
    """(K,) whether the palm and finger boxes at each pose (K, 4, 4) and opening (K,), and
    at its pre-grasp ``standoff`` back along the approach (default the finger depth: where
    the hand starts, ``Grasps.pregrasp``), stay at least the clearance above the support
    plane {p : p . up = height}. The approach between them is a straight line, so both
    ends clearing means the whole path does."""
    standoff = gripper.finger_depth if standoff is None else standoff
    if len(poses) == 0:
        return np.zeros(0, bool)
    bounds = np.array([gripper.boxes(w) for w in widths])  # (K, 3, 2, 3)
    pick = np.array([[i >> k & 1 for k in range(3)] for i in range(8)])  # (8, 3) corners
    corners = np.where(pick[None, None] == 1, bounds[:, :, None, 1], bounds[:, :, None, 0])
    local_up = np.einsum("kji,j->ki", poses[:, :3, :3], up)  # up in each grasp frame
    lowest = np.min(np.einsum("kbcj,kj->kbc", corners, local_up), axis=(1, 2))
    base = poses[:, :3, 3] @ up + lowest
    back = standoff * (poses[:, :3, 2] @ up)
    return np.minimum(base, base - back) >= height + gripper.clearance


def distinct(poses, order, *, separation: float, degrees: float,
             limit: int | None = None) -> np.ndarray:
    """Indices from ``order`` (best first) whose pose (K, 4, 4) is not a near-duplicate of
    one kept before it: a duplicate lies within ``separation`` of a kept grasp's origin
    with its approach and closing line (sign ignored: a parallel jaw turned half a turn is
    the same grasp) both within ``degrees``. Stops after ``limit`` kept."""
    cos = np.cos(np.radians(degrees))
    kept: list[int] = []
    for i in order:
        if kept:
            k = np.asarray(kept)
            near = np.linalg.norm(poses[k, :3, 3] - poses[i, :3, 3], axis=1) <= separation
            same = ((poses[k, :3, 2] @ poses[i, :3, 2] >= cos)
                    & (np.abs(poses[k, :3, 1] @ poses[i, :3, 1]) >= cos))
            if np.any(near & same):
                continue
        kept.append(int(i))
        if limit is not None and len(kept) == limit:
            break
    return np.asarray(kept, int)


def grasps(decomposition, gripper: ParallelJaw, *, key=0, top: int | None = None,
           min_quality: float = 0.8, min_points: int = 4, normals=None, support=None,
           separation: float | None = None, separation_degrees: float = 30.0) -> Grasps:
    """Parallel-jaw grasps of a decomposed object (module docstring).

    Parameters
    ----------
    decomposition : a ``jaxfit.Decomposition`` (its parts' primitives propose, its points
        filter).
    gripper : a ParallelJaw in the cloud's units.
    key : int seed or JAX key for the sampled azimuths, rotations and sphere directions.
    top : keep at most this many grasps, best first (default all that pass).
    min_quality : least antipodal quality, the mean |cos| between the points' normals
        and the closing axis at each pad (0.8: about 37 degrees).
    min_points : fewest points between the fingers.
    normals : (N, 3) the points' normals (signs ignored); default estimated (k = 16).
    support : None (the object floats: any approach) or (up, height): the table the object
        stands on, the plane {p : p . up = height} with ``up`` (3,) pointing away from it;
        grasps whose gripper boxes, at the grasp or at the pre-grasp, would come within
        the clearance of it are dropped (``clears_support``), as a robot that knows where
        the table is would.
    separation, separation_degrees : near-duplicates are dropped (``distinct``): a grasp
        within ``separation`` (default the finger width; 0 keeps all) of a better one's
        origin, with approach and closing line within ``separation_degrees`` (30).
    """
    from .decomposition import Decomposition
    from .normals import estimate_normals

    started = time.perf_counter()
    if not isinstance(decomposition, Decomposition):
        raise TypeError(f"grasps needs a jaxfit.Decomposition, got {type(decomposition).__name__}")
    if not isinstance(gripper, ParallelJaw):
        raise TypeError(f"gripper must be a ParallelJaw, got {type(gripper).__name__}")
    if top is not None:
        top = _checks.positive(top, "top", integer=True)
    if isinstance(min_quality, bool) or not isinstance(min_quality, numbers.Real) or not (
            0 <= min_quality <= 1):
        raise ValueError(f"min_quality must be in [0, 1], got {min_quality!r}")
    min_points = _checks.positive(min_points, "min_points", integer=True)
    points = np.asarray(decomposition.points, np.float64)
    if normals is None:
        normals = estimate_normals(points, k=min(16, len(points)), orient=None)
    normals = _checks.normals_for(normals, points)
    support = _support(support)
    separation = gripper.finger_width if separation is None else _checks.non_negative(
        separation, "separation")
    if isinstance(separation_degrees, bool) or not isinstance(
            separation_degrees, numbers.Real) or not 0 <= separation_degrees <= 180:
        raise ValueError(f"separation_degrees must be in [0, 180], got {separation_degrees!r}")
    centres, rotations, parts = candidates(decomposition, key=key, normals=normals)
    count = len(centres)
    models = [p.model for p in decomposition.parts]
    com = mass_properties(models)[1] if models else points.mean(axis=0)
    lo, hi = points.min(axis=0), points.max(axis=0)
    shift = 0.5 * (lo + hi)

    if count:
        ok, origin, width, contact_width, contacts, antipodal, score = _run_filter(
            points - shift, normals, centres - shift, rotations, com - shift, gripper,
            min_quality, min_points)
        width = np.minimum(width, gripper.max_width)  # float32's rounding of max_width
        keep = np.flatnonzero(ok)
        keep = keep[np.argsort(-score[keep], kind="stable")]
        if support is not None:
            placed = np.tile(np.eye(4), (len(keep), 1, 1))
            placed[:, :3, :3], placed[:, :3, 3] = rotations[keep], origin[keep] + shift
            keep = keep[clears_support(placed, width[keep], gripper, *support)]
        if separation > 0:
            placed = np.tile(np.eye(4), (len(origin), 1, 1))
            placed[:, :3, :3], placed[:, :3, 3] = rotations, origin
            keep = distinct(placed, keep, separation=separation,
                            degrees=float(separation_degrees), limit=top)
        keep = keep[:top]
    else:
        keep = np.zeros(0, int)
        origin, width, contact_width = np.zeros((0, 3)), np.zeros(0), np.zeros(0)
        contacts, antipodal, score = np.zeros((0, 2, 3)), np.zeros(0), np.zeros(0)
    poses = np.tile(np.eye(4), (len(keep), 1, 1))
    poses[:, :3, :3] = rotations[keep]
    poses[:, :3, 3] = origin[keep] + shift
    names = np.array([decomposition.parts[i].model.name for i in parts[keep]], dtype=object)
    return Grasps(
        poses=poses, widths=width[keep], contact_widths=contact_width[keep],
        contacts=contacts[keep] + shift, parts=parts[keep], primitives=names,
        scores=score[keep], antipodal=antipodal[keep],
        gripper=gripper, num_candidates=count, seconds=time.perf_counter() - started)


def _run_filter(points, normals, centres, rotations, com, gripper, min_quality, min_points):
    """``_filter`` on padded float32 copies (points to a power of two, candidates to a
    multiple of ``CANDIDATE_BUCKET``), its outputs cut back to the C candidates, float64."""
    count, dtype = len(centres), np.float32
    c_pad = _bucket(count, CANDIDATE_BUCKET)
    n_pad = bucket_size(len(points))
    pts, nrm = np.zeros((n_pad, 3), dtype), np.zeros((n_pad, 3), dtype)
    pts[:len(points)], nrm[:len(points)] = points, normals
    valid = np.arange(n_pad) < len(points)
    cen = np.zeros((c_pad, 3), dtype)
    cen[:count] = centres
    rot = np.tile(np.eye(3, dtype=dtype), (c_pad, 1, 1))
    rot[:count] = rotations
    g = gripper
    dims = np.array([g.max_width, g.finger_depth, g.finger_width / 2, g.finger_thickness,
                     g.palm_depth, g.palm_width / 2, g.clearance, min_quality, min_points],
                    dtype)
    out = _filter(pts, valid, nrm, cen, rot, np.asarray(com, dtype), dims)
    ok, *rest = (np.asarray(a)[:count] for a in out)
    return (ok, *(a.astype(np.float64) for a in rest))
