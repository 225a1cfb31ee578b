"""Headless pictures of a decomposition: the input points beside the fitted primitives."""

from __future__ import annotations

import numpy as np

from ..shapes import REGISTRY


def view_angles(points) -> tuple[float, float]:
    """(elevation, azimuth) in degrees for matplotlib: a three-quarter view that looks
    mostly along the cloud's thinnest principal axis, so its two long axes are seen."""
    centred = points - points.mean(axis=0)
    _, _, axes = np.linalg.svd(centred[:: max(1, len(points) // 5000)], full_matrices=False)
    view = 0.8 * axes[2] + 0.45 * axes[1] + 0.4 * axes[0]
    view /= np.linalg.norm(view)
    elevation = np.degrees(np.arcsin(np.clip(view[2], -1, 1)))
    azimuth = np.degrees(np.arctan2(view[1], view[0]))
    return float(elevation), float(azimuth)


def _shaded(mesh, rgba):
    light = np.array([0.4, 0.3, 0.85])
    light /= np.linalg.norm(light)
    shade = 0.45 + 0.55 * np.abs(mesh.face_normals @ light)
    colour = np.asarray(rgba[:3]) / 255.0
    return np.clip(shade[:, None] * colour, 0, 1)


#: ``surface_patch`` splits a patch's faces at most this many times (each split makes four
#: faces of one) and stops splitting once the patch holds this many faces.
PATCH_SPLITS = 6
PATCH_FACES = 8_000


def surface_patch(mesh, points, reach: float):
    """The part of ``mesh`` (a primitive's surface) that ``points`` (M, 3) cover: its faces
    whose centre lies within ``reach`` of a point and no corner beyond twice that, each
    split (into four, up to ``PATCH_SPLITS`` times) until none is wider than 1.5
    ``reach`` or the patch holds ``PATCH_FACES``. None where no face is that near. Why:
    a detection explains a patch of its primitive, and a free-form scan's spheres and
    cones, drawn whole, are many times the scan's size and hide it."""
    from ..normals import kd_tree

    tree = kd_tree(np.asarray(points, np.float64))
    for split in range(PATCH_SPLITS + 1):
        corners = mesh.triangles  # (F, 3, 3)
        centres = corners.mean(axis=1)
        widths = np.linalg.norm(corners - centres[:, None], axis=2).max(axis=1)  # (F,)
        gap = tree.query(centres)[0]
        # (a face wider than reach may cover a point its centre is not near)
        near = np.flatnonzero(gap <= reach + widths)
        if not len(near):
            return None
        if widths[near].max() <= 1.5 * reach or split == PATCH_SPLITS \
                or 4 * len(near) > PATCH_FACES:
            break
        mesh = mesh.submesh([near], append=True).subdivide()
    # Its centre within reach, no corner beyond twice that: a sliver (a cone's faces at
    # its apex) that split too few times is left out rather than drawn as a spike.
    far = tree.query(corners[near].reshape(-1, 3))[0].reshape(-1, 3).max(axis=1)
    keep = near[(gap[near] <= reach) & (far <= 2 * reach)]
    return mesh.submesh([keep], append=True) if len(keep) else None


def pyplot():
    """matplotlib.pyplot on the headless Agg backend (imported here: it is slow to import
    and only pictures need it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def render(decomposition, path, *, size=(11, 5.5), dpi=110):
    """Write a PNG: left the points coloured by part, right the primitives by type (a
    part's ``mesh`` where it has one, e.g. ``surface_patch``'s, else its model's)."""
    plt = pyplot()
    from matplotlib.patches import Patch
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    points = decomposition.points
    elevation, azimuth = view_angles(points)
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre, half = 0.5 * (lo + hi), 0.55 * (hi - lo).max()
    fig = plt.figure(figsize=size)
    left = fig.add_subplot(1, 2, 1, projection="3d")
    right = fig.add_subplot(1, 2, 2, projection="3d")
    labels = np.full(len(points), -1)
    for i, part in enumerate(decomposition.parts):
        labels[part.indices] = i
    step = max(1, len(points) // 8000)
    palette = plt.get_cmap("tab20")
    left.scatter(*points[::step].T, s=1.5, c=[palette(k % 20) for k in labels[::step]],
                 depthshade=False)
    left.set_title(f"input: {len(points)} points, coloured by part", fontsize=10)
    kinds = []
    for part in decomposition.parts:
        mesh = getattr(part, "mesh", None)
        mesh = part.model.to_mesh() if mesh is None else mesh
        right.add_collection3d(Poly3DCollection(
            mesh.triangles, facecolors=_shaded(mesh, part.model.colour), edgecolors="none",
            alpha=0.95))
        kinds.append(part.kind)
    right.set_title(f"{len(decomposition.parts)} primitives", fontsize=10)
    right.legend(handles=[Patch(color=np.asarray(REGISTRY[k].colour[:3]) / 255, label=k)
                          for k in dict.fromkeys(kinds)], loc="upper right", fontsize=8)
    for ax in (left, right):
        framed(ax, centre, half, elevation, azimuth)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.92, wspace=0.0)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def framed(ax, centre, half: float, elevation: float, azimuth: float) -> None:
    """Point a 3-D axes at the cube of half-side ``half`` about ``centre`` (3,), seen from
    ``elevation`` and ``azimuth`` (degrees), equal scales and no axes drawn."""
    ax.view_init(elev=elevation, azim=azimuth)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_axis_off()
