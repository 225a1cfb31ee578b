"""The Primitive Shape Decomposition Algorithm (PSDA, THESIS.md section 5).

1. BoxDecomposition splits the cloud into parts (``jaxfit.boxdecomp``).
2. Fitting: every part is fitted with every primitive, with a threshold scaled to the
   part's size; all parts of one primitive go through one ``fit_batch`` call.
3. Evaluation: each candidate scores the mean distance of *all* the part's points to its
   closed, bounded surface; the part's own bounding box competes too; the lowest wins.
4. The object is the set of winning primitives (``Decomposition``).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from . import _checks
from .boxdecomp import BoxTree, decompose_boxes, mvbb
from .ransac import fit_batch
from .shapes import Box, Model

SHAPES = ("sphere", "cylinder", "cone", "box")
#: Part threshold: this fraction of the diagonal of the part's bounding box. Wider than
#: for a single fit, as in the thesis: a part is only approximately a primitive.
THRESHOLD_FRACTION = 0.02
#: Points of a part handed to RANSAC (a random subset when the part is larger).
MAX_FIT_POINTS = 2048
#: Colours (RGBA) of the primitives in scenes and previews.
COLOURS = {
    "sphere": (231, 76, 60, 255), "cylinder": (52, 152, 219, 255),
    "cone": (241, 196, 15, 255), "box": (46, 204, 113, 255), "plane": (155, 89, 182, 255),
    "mvbb": (127, 140, 141, 255),
}


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One primitive tried on a part: the fitted model and its mean distance."""

    model: Model
    mean_distance: float


@dataclasses.dataclass(frozen=True, eq=False)
class Part:
    """A leaf of the box decomposition and the primitive that won it.

    indices : (M,) indices into ``Decomposition.points`` (the leaf's points, or with
        ``reassign`` the points nearest to this part's primitive).
    box : the minimum-volume bounding box of those points.
    kind : the primitive type of the winner ("sphere", "cylinder", "cone" or "box").
    winner : the winning candidate: ``kind``, or "mvbb" when the bounding box won.
    model : the winning primitive (a ``Box`` when the MVBB wins).
    mean_distance : its mean distance to the part's points.
    candidates : name -> Candidate for every primitive tried, and "mvbb".
    """

    indices: np.ndarray
    box: Box
    kind: str
    winner: str
    model: Model
    mean_distance: float
    candidates: dict[str, Candidate]


@dataclasses.dataclass(frozen=True, eq=False)
class Decomposition:
    """The object as a set of primitives.

    points : (N, 3) the cloud the decomposition worked on.
    parts : one Part per leaf of ``tree``.
    tree : the box hierarchy (which box split into which).
    seconds : wall time of decompose (boxes, fits and evaluation).
    """

    points: np.ndarray
    parts: tuple[Part, ...]
    tree: BoxTree
    seconds: float

    def to_scene(self):
        """A ``trimesh.Scene`` of the winning primitives, coloured by type."""
        import trimesh

        scene = trimesh.Scene()
        for i, part in enumerate(self.parts):
            mesh = part.model.to_mesh()
            mesh.visual.face_colors = COLOURS[part.kind]
            scene.add_geometry(mesh, node_name=f"part{i}_{part.kind}")
        return scene

    def to_dict(self) -> dict:
        """JSON-ready: per part its primitive, score, size and every candidate; the
        hierarchy; the settings."""
        parts = []
        for part in self.parts:
            parts.append({
                "kind": part.kind,
                "winner": part.winner,
                "model": part.model.to_dict(),
                "mean_distance": part.mean_distance,
                "num_points": int(part.indices.size),
                "box": part.box.to_dict(),
                "candidates": {name: {"model": c.model.to_dict(), "mean_distance": c.mean_distance}
                               for name, c in part.candidates.items()},
            })
        return {"num_points": int(len(self.points)), "seconds": self.seconds, "parts": parts,
                "hierarchy": self.tree.to_dict()}

    def save(self, directory) -> Path:
        """Write parts.json, decomposition.glb and preview.png into ``directory``."""
        from .preview import render

        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        (out / "parts.json").write_text(json.dumps(self.to_dict(), indent=1))
        self.to_scene().export(out / "decomposition.glb")
        render(self, out / "preview.png")
        return out

    def summary(self) -> str:
        lines = [f"{len(self.parts)} parts from {len(self.points)} points "
                 f"in {self.seconds:.2f} s:"]
        for i, part in enumerate(self.parts):
            size = np.linalg.norm(part.box.extents)
            lines.append(f"  part {i}: {part.winner:<8} {part.indices.size:6d} points, mean "
                         f"distance {part.mean_distance:.3g} ({part.mean_distance / size:.1%} "
                         "of the part's diagonal)")
        return "\n".join(lines)


def load_source(source, *, num_points: int = 20000, seed: int = 0) -> np.ndarray:
    """(N, 3) points from an array, a trimesh mesh (surface-sampled) or a file path
    (anything ``jaxfit.io.load_points`` reads, Open Inventor ``.iv`` included)."""
    import trimesh

    from .io import load_points, sample_surface

    if isinstance(source, trimesh.Trimesh):
        return _checks.cloud(sample_surface(source, num_points, seed))
    if isinstance(source, str | Path):
        return load_points(source, num_points=num_points, seed=seed)
    return _checks.cloud(source)


def decompose(source, *, gain: float = 0.96, min_points: int | None = None,
              shapes=SHAPES, num_points: int = 20000, threshold_fraction=THRESHOLD_FRACTION,
              key=0, reassign: int = 3, progress: bool = False) -> Decomposition:
    """Decompose an object into primitives (the PSDA).

    Parameters
    ----------
    source : (N, 3) points, a ``trimesh.Trimesh``, or a path to a mesh / point file /
        Open Inventor ``.iv`` model.
    gain : BoxDecomposition's split threshold (children's volume / parent's volume must
        fall below it); nearer 1 splits more.
    min_points : smallest part; default 2 % of the points (at least 30).
    shapes : primitives to try on every part.
    num_points : points sampled from a mesh.
    threshold_fraction : inlier threshold of a part's fits, as a fraction of its bounding
        box's diagonal.
    key : seed for sampling and fitting.
    reassign : rounds (at most) of giving every point to the nearest winning primitive
        and fitting the regrouped parts again, so parts follow the primitives rather than
        the box cuts; 0 keeps the leaves as they are.
    progress : print the stages to stderr.
    """
    started = time.perf_counter()
    classes = [_checks.model_class(s) for s in shapes]
    if not 0 < gain <= 1:
        raise ValueError(f"gain must be in (0, 1], got {gain!r}")
    seed = key if isinstance(key, int) else 0
    points = load_source(source, num_points=num_points, seed=seed)
    if min_points is None:
        min_points = max(30, int(0.02 * len(points)))
    min_points = _checks.positive(min_points, "min_points", integer=True)
    say = _say if progress else (lambda *_: None)

    # The thesis's split rule, with volumes measured against the root box: measured
    # against the parent, every curved patch keeps splitting (see jaxfit.boxdecomp).
    tree = decompose_boxes(points, gain=gain, min_points=min_points, reference="root")
    groups = [tree.nodes[i].indices for i in tree.leaves]
    say(f"box decomposition: {len(groups)} parts ({time.perf_counter() - started:.2f} s)")
    parts = _fit_parts(points, groups, classes, threshold_fraction, key, seed, say, started)
    for _ in range(reassign if len(parts) > 1 else 0):
        # Box cuts are planes, so a part can keep a sliver of its neighbour (the top of
        # a handle in the head's box). Give every point to the winner nearest to it and
        # fit again, so each primitive grows back to all of its points.
        distances = np.stack([p.model.distance(points) for p in parts])  # (P, N)
        owner = np.argmin(distances, axis=0)
        regrouped = [np.flatnonzero(owner == i) for i in range(len(parts))]
        if any(g.size < max(5, min_points // 2) for g in regrouped) or all(
                np.array_equal(g, p.indices) for g, p in zip(regrouped, parts, strict=True)):
            break
        parts = _fit_parts(points, regrouped, classes, threshold_fraction, key, seed, say,
                           started)
    return Decomposition(points, tuple(parts), tree, time.perf_counter() - started)


def _fit_parts(points, groups, classes, threshold_fraction, key, seed, say, started):
    """Fitting and evaluation phases: every primitive on every part (one fit_batch per
    primitive), and the candidate nearest to the part's points wins."""
    clouds = [points[g] for g in groups]
    boxes = [mvbb(cloud) for cloud in clouds]
    # RANSAC needs no more than a few thousand points of a part to find its primitive;
    # the candidates are still judged on all of them.
    rng = np.random.default_rng(seed)
    samples = [c if len(c) <= MAX_FIT_POINTS else c[rng.choice(len(c), MAX_FIT_POINTS, False)]
               for c in clouds]
    thresholds = [threshold_fraction * float(np.linalg.norm(b.extents)) for b in boxes]
    candidates = [{"mvbb": Candidate(box, _mean(box, cloud))}
                  for box, cloud in zip(boxes, clouds, strict=True)]
    for cls in classes:
        results = fit_batch(samples, cls, thresholds=thresholds, key=key, skip_failures=True)
        for found, result, cloud in zip(candidates, results, clouds, strict=True):
            if result is not None:
                found[cls.name] = Candidate(result.model, _mean(result.model, cloud))
        say(f"fitted {cls.name} to {len(clouds)} parts ({time.perf_counter() - started:.2f} s)")
    parts = []
    for group, box, found in zip(groups, boxes, candidates, strict=True):
        winner = min(found, key=lambda name: found[name].mean_distance)
        model = found[winner].model
        parts.append(Part(group, box, model.name, winner, model, found[winner].mean_distance,
                          found))
    return parts


def _mean(model: Model, cloud) -> float:
    distance = model.distance(cloud)
    return float(np.mean(distance)) if np.all(np.isfinite(distance)) else float("inf")


def _say(message):
    print(message, file=sys.stderr, flush=True)
