"""A headless picture of grasps: the object's points and primitives with the top grasps drawn as
parallel-jaw outlines (palm bar, two fingers at the opening, approach line from the
pre-grasp standoff), best in the darkest colour."""

from __future__ import annotations

import numpy as np

from .preview import _shaded, framed, pyplot, view_angles


def gripper_lines(pose, width, gripper, standoff=None) -> np.ndarray:
    """(S, 2, 3) line segments of one grasp in the cloud's coordinates: the palm bar, the
    two fingers (from the palm to the fingertips at y = +-width / 2) and the approach
    from the standoff (default the finger depth) to the palm."""
    fd = gripper.finger_depth
    standoff = fd if standoff is None else standoff
    half = width / 2
    local = np.array([
        [[0, -half, -fd], [0, half, -fd]],  # palm bar
        [[0, -half, -fd], [0, -half, 0]],  # fingers
        [[0, half, -fd], [0, half, 0]],
        [[0, 0, -fd - standoff], [0, 0, -fd]],  # approach
    ], np.float64)
    return local @ pose[:3, :3].T + pose[:3, 3]


def render(decomposition, grasps, path, *, top: int = 10, size=(6.5, 6), dpi=110):
    """Write a PNG of the decomposition's points (grey) and primitives and its first
    ``top`` grasps."""
    plt = pyplot()
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    points = decomposition.points
    elevation, azimuth = view_angles(points)
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = 0.5 * (lo + hi)
    half = 0.55 * max((hi - lo).max(), 2.5 * grasps.gripper.finger_depth)
    fig = plt.figure(figsize=size)
    ax = fig.add_subplot(1, 1, 1, projection="3d")
    step = max(1, len(points) // 4000)
    ax.scatter(*points[::step].T, s=0.6, c="0.55", alpha=0.5, depthshade=False)
    for part in decomposition.parts:
        mesh = part.model.to_mesh()
        ax.add_collection3d(Poly3DCollection(
            mesh.triangles, facecolors=_shaded(mesh, part.model.colour), edgecolors="none",
            alpha=0.35))
    shown = min(top, len(grasps))
    colours = plt.get_cmap("viridis")(np.linspace(0.0, 0.85, max(shown, 1)))
    for i in reversed(range(shown)):
        lines = gripper_lines(grasps.poses[i], grasps.widths[i], grasps.gripper)
        ax.add_collection3d(Line3DCollection(lines, colors=[colours[i]], linewidths=2.0))
    ax.set_title(f"top {shown} of {len(grasps)} grasps ({grasps.num_candidates} candidates)",
                 fontsize=10)
    framed(ax, centre, half, elevation, azimuth)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.93)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
