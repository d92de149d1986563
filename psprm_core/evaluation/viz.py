"""Top-view (x-y) plotting helpers for scenes, robot collision spheres, roadmaps and scored paths.

All functions draw onto a matplotlib ``Axes`` the caller provides, except :func:`save_scene_figure`, which builds
its own ``matplotlib.figure.Figure`` on the Agg canvas and writes a PNG. Nothing here touches pyplot, so no global
figure state is created or leaked, and the interactive backend (if any) is left alone. matplotlib is imported
lazily, inside the functions, so importing this module is cheap.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from ..errors import InputError
from ..geometry import quat_to_matrix

log = logging.getLogger(__name__)

#: Targets are drawn in this colour (edge) so they stand out from furniture.
TARGET_COLOR = (0.85, 0.10, 0.10, 1.0)
#: Goal regions.
GOAL_COLOR = (0.10, 0.55, 0.15, 1.0)
_LABEL_BOX = dict(boxstyle="round,pad=0.15", facecolor="white", edgecolor="none", alpha=0.7)


# ------------------------------------------------------------------------------------------------------------------
# geometry helpers
# ------------------------------------------------------------------------------------------------------------------
def box_footprint(center, size, quat) -> np.ndarray:
    """Convex footprint (projection onto the x-y plane) of an oriented box.

    Parameters
    ----------
    center : (3,) array_like
        Box centre.
    size : (3,) array_like
        Full extents along the box axes.
    quat : (4,) array_like
        Orientation ``(x, y, z, w)``.

    Returns
    -------
    (K, 2) ndarray
        Counter-clockwise polygon vertices (K = 4 for boxes rotated about z only, up to 6 otherwise).
    """
    half = 0.5 * np.asarray(size, dtype=float)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    corners = (signs * half) @ quat_to_matrix(quat).T + np.asarray(center, dtype=float)
    return _convex_hull(corners[:, :2])


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """Monotone-chain convex hull of 2-D points, counter-clockwise, without repeated vertices."""
    pts = np.unique(np.round(np.asarray(points, dtype=float), 12), axis=0)
    if len(pts) <= 2:
        return pts

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 1e-15:
            lower.pop()
        lower.append(p)
    for p in pts[::-1]:
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 1e-15:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1])


def _darker(color, factor: float = 0.6) -> tuple:
    c = np.asarray(color, dtype=float)
    return tuple(np.concatenate([np.clip(c[:3] * factor, 0.0, 1.0), [1.0]]))


def _top_z(center, size, quat) -> float:
    half = 0.5 * np.asarray(size, dtype=float)
    return float(np.asarray(center, dtype=float)[2] + np.abs(quat_to_matrix(quat)[2]) @ half)


# ------------------------------------------------------------------------------------------------------------------
# scene
# ------------------------------------------------------------------------------------------------------------------
def plot_scene_top(ax, scene, show_labels: bool = True, show_problems: bool = False):
    """Draw a scene seen from above.

    Obstacles are drawn as filled footprints in their own colours (lower boxes first, so things standing on
    furniture stay visible), targets as red-edged footprints with an arrow along their facing (+x) direction
    (a dot-in-circle when they face mostly up or down), goal regions as green circles of radius
    ``xy_tolerance`` with a heading tick, and the workspace as a dashed outline.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
    scene : psprm_core.scene.Scene
    show_labels : bool
        Write obstacle, target and goal names.
    show_problems : bool
        Also mark every problem's start (circle) and goal (square) base positions with a heading tick.

    Returns
    -------
    matplotlib.axes.Axes
        ``ax``, with equal aspect and limits covering the workspace and all boxes.
    """
    from matplotlib.patches import Circle, Polygon, Rectangle

    ws = np.asarray(scene.workspace, dtype=float)
    ax.add_patch(Rectangle((ws[0, 0], ws[1, 0]), ws[0, 1] - ws[0, 0], ws[1, 1] - ws[1, 0], fill=False,
                           linestyle="--", linewidth=1.0, edgecolor="0.35", zorder=0.5, label="workspace"))
    all_xy = [ws.T]

    # obstacles, lowest top first
    items = sorted(scene.obstacles, key=lambda b: _top_z(b.center, b.size, b.quat))
    for b in items:
        poly = box_footprint(b.center, b.size, b.quat)
        all_xy.append(poly)
        color = np.clip(np.asarray(b.color, dtype=float), 0.0, 1.0)
        ax.add_patch(Polygon(poly, closed=True, facecolor=color, edgecolor=_darker(color), linewidth=0.8,
                             zorder=1.0 + 0.01 * _top_z(b.center, b.size, b.quat)))
        if show_labels:
            ext = poly.max(axis=0) - poly.min(axis=0)
            if min(ext) >= 0.2:  # skip walls and other slivers: their names would only clutter the plot
                ax.text(b.center[0], b.center[1], b.name.replace("_", " "), ha="center", va="center",
                        fontsize=6, color="0.1", zorder=4, clip_on=True, bbox=_LABEL_BOX)

    # targets
    for t in scene.targets:
        poly = box_footprint(t.center, t.size, t.quat)
        all_xy.append(poly)
        ax.add_patch(Polygon(poly, closed=True, facecolor=(1.0, 0.85, 0.3, 0.9), edgecolor=TARGET_COLOR,
                             linewidth=1.2, zorder=5))
        facing = np.asarray(t.facing, dtype=float)
        horiz = float(np.hypot(facing[0], facing[1]))
        if horiz > 0.3:
            length = 0.45
            ax.annotate("", xy=(t.center[0] + length * facing[0] / horiz, t.center[1] + length * facing[1] / horiz),
                        xytext=(t.center[0], t.center[1]), zorder=6,
                        arrowprops=dict(arrowstyle="-|>", color=TARGET_COLOR, linewidth=1.5, shrinkA=0, shrinkB=0))
        else:  # faces (mostly) up or down: circle with a dot (up) or a cross (down)
            ax.plot([t.center[0]], [t.center[1]], marker="o", markersize=9, markerfacecolor="none",
                    markeredgecolor=TARGET_COLOR, zorder=6)
            ax.plot([t.center[0]], [t.center[1]], marker="." if facing[2] > 0 else "x", markersize=5,
                    color=TARGET_COLOR, zorder=6)
        if show_labels:
            text = t.name if t.name.replace("_", " ") == t.detector_class else f"{t.name} ({t.detector_class})"
            ax.annotate(text, xy=(t.center[0], t.center[1]), xytext=(5, -5), textcoords="offset points",
                        ha="left", va="top", fontsize=6, color=TARGET_COLOR, zorder=7, annotation_clip=True,
                        bbox=_LABEL_BOX)

    # goal regions
    for g in scene.goals:
        x, y, th = (float(v) for v in g.base)
        r = max(float(g.xy_tolerance), 0.05)
        ax.add_patch(Circle((x, y), r, facecolor=(0.1, 0.55, 0.15, 0.2), edgecolor=GOAL_COLOR, linewidth=1.2,
                            zorder=5))
        ax.plot([x, x + (r + 0.2) * math.cos(th)], [y, y + (r + 0.2) * math.sin(th)], color=GOAL_COLOR,
                linewidth=1.2, zorder=5)
        if show_labels:
            ax.annotate(g.name, xy=(x, y), xytext=(0, 8), textcoords="offset points", ha="center", va="bottom",
                        fontsize=6, color=GOAL_COLOR, zorder=7, bbox=_LABEL_BOX)

    if show_problems:
        plot_problems_top(ax, scene, show_labels=show_labels)

    pts = np.vstack(all_xy)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.05 * float(max(hi - lo))
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel(f"x [m] ({scene.frame})")
    ax.set_ylabel("y [m]")
    return ax


def plot_problems_top(ax, scene, names: Optional[Sequence[str]] = None, show_labels: bool = True):
    """Mark problem start (circle) and goal (square) base poses with a heading tick.

    Problems with goal regions only have no goal marker (the regions are drawn by :func:`plot_scene_top`).
    Base joints missing from a problem are skipped (they take the robot default, which this module does not know).

    Parameters
    ----------
    ax : matplotlib.axes.Axes
    scene : psprm_core.scene.Scene
    names : sequence of str, optional
        Problems to draw (default: all).
    show_labels : bool
        Number the markers ``S1``/``G1``... in problem order.
    """
    problems = scene.problems if names is None else [scene.problem(n) for n in names]
    seen = {}
    for i, p in enumerate(problems, start=1):
        for kind, joints, marker, color in (("S", p.start, "o", "tab:blue"), ("G", p.goal, "s", "tab:purple")):
            if "base_x" not in joints or "base_y" not in joints:
                continue
            x, y = joints["base_x"], joints["base_y"]
            th = joints.get("base_theta", 0.0)
            ax.plot([x], [y], marker=marker, markersize=5, color=color, zorder=8, linestyle="none")
            ax.plot([x, x + 0.3 * math.cos(th)], [y, y + 0.3 * math.sin(th)], color=color, linewidth=1.0,
                    zorder=8)
            if show_labels:
                key = (round(x, 3), round(y, 3))
                k = seen.get(key, 0)
                seen[key] = k + 1
                ax.annotate(f"{kind}{i}", xy=(x, y), xytext=(5, 3 + 7 * k), textcoords="offset points",
                            fontsize=5, color=color, zorder=9)
    return ax


# ------------------------------------------------------------------------------------------------------------------
# robots, roadmaps, paths
# ------------------------------------------------------------------------------------------------------------------
def plot_spheres_top(ax, centers, radii, **style):
    """Draw collision spheres as circles (their x-y cross-section at the centre height).

    Parameters
    ----------
    ax : matplotlib.axes.Axes
    centers : (S, 3) or (S, 2) array_like
        Sphere centres in the scene frame.
    radii : (S,) array_like or float
        Sphere radii.
    **style
        Passed to :class:`matplotlib.collections.PatchCollection` (defaults: blue edge, light blue fill).

    Returns
    -------
    matplotlib.collections.PatchCollection
    """
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

    c = np.asarray(centers, dtype=float).reshape(-1, np.shape(centers)[-1] if np.ndim(centers) > 1 else 3)
    r = np.broadcast_to(np.asarray(radii, dtype=float), (len(c),))
    if not np.all(np.isfinite(c[:, :2])) or not np.all(np.isfinite(r)):
        raise InputError("sphere centres and radii must be finite")
    kw = dict(facecolor=(0.12, 0.47, 0.71, 0.15), edgecolor=(0.12, 0.47, 0.71, 0.8), linewidth=0.6, zorder=9)
    kw.update(style)
    coll = PatchCollection([Circle((float(x), float(y)), float(rr)) for (x, y), rr in zip(c[:, :2], r)], **kw)
    ax.add_collection(coll)
    return coll


def plot_roadmap_top(ax, nodes_xy, edges, **style):
    """Draw a roadmap: edges as thin lines, nodes as small dots.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
    nodes_xy : (N, 2) array_like
        Node base positions.
    edges : (E, 2) array_like of int
        Index pairs into ``nodes_xy``.
    **style
        Passed to the edges' :class:`matplotlib.collections.LineCollection` (defaults: grey, thin). The keys
        ``node_size`` (default 2) and ``node_color`` (default the edge colour) style the nodes; ``node_size=0``
        hides them.

    Returns
    -------
    matplotlib.collections.LineCollection
    """
    from matplotlib.collections import LineCollection

    nodes = np.asarray(nodes_xy, dtype=float).reshape(-1, 2)
    e = np.asarray(edges, dtype=int).reshape(-1, 2)
    if len(e) and (e.min() < 0 or e.max() >= len(nodes)):
        raise InputError(f"edge indices must lie in [0, {len(nodes)}); got [{e.min()}, {e.max()}]")
    node_size = style.pop("node_size", 2.0)
    kw = dict(colors=[(0.45, 0.45, 0.45, 0.5)], linewidths=0.4, zorder=2.5)
    if "color" in style:
        style["colors"] = [style.pop("color")]
    kw.update(style)
    node_color = kw.pop("node_color", None)
    lc = LineCollection(nodes[e] if len(e) else np.zeros((0, 2, 2)), **kw)
    ax.add_collection(lc)
    if node_size and len(nodes):
        if node_color is None:
            node_color = lc.get_colors()[0] if len(lc.get_colors()) else "0.4"
        ax.scatter(nodes[:, 0], nodes[:, 1], s=node_size, color=node_color, zorder=kw.get("zorder", 2.5) + 0.1,
                   linewidths=0)
    return lc


def plot_path_top(ax, xy, scores=None, cmap: str = "viridis", colorbar: bool = True, label: Optional[str] = None,
                  linewidth: float = 2.5, vmin: Optional[float] = None, vmax: Optional[float] = None):
    """Draw a base path, coloured by perception score.

    Parameters
    ----------
    ax : matplotlib.axes.Axes
    xy : (M, 2) array_like
        Waypoint base positions.
    scores : (M,) array_like or None
        Perception score at each waypoint. Each segment takes the mean score of its two ends. ``None`` draws a
        plain black line.
    cmap : str
        Colormap for the scores.
    colorbar : bool
        Add a colour bar labelled "perception score" (only when ``scores`` is given).
    label : str, optional
        Legend label.
    linewidth : float
    vmin, vmax : float, optional
        Colour scale limits (default: [0, 1] widened to include all scores).

    Returns
    -------
    matplotlib.collections.LineCollection or matplotlib.lines.Line2D
    """
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize

    p = np.asarray(xy, dtype=float).reshape(-1, 2)
    if len(p) == 0:
        raise InputError("empty path")
    ends = dict(zorder=11, linestyle="none")
    if scores is None:
        (line,) = ax.plot(p[:, 0], p[:, 1], color="k", linewidth=linewidth, zorder=10, label=label)
        artist = line
    else:
        s = np.asarray(scores, dtype=float).reshape(-1)
        if len(s) != len(p):
            raise InputError(f"scores has {len(s)} entries for {len(p)} waypoints")
        if not np.all(np.isfinite(s)):
            raise InputError("scores must be finite")
        lo = min(0.0, float(s.min())) if vmin is None else vmin
        hi = max(1.0, float(s.max())) if vmax is None else vmax
        norm = Normalize(vmin=lo, vmax=hi)
        if len(p) >= 2:
            segs = np.stack([p[:-1], p[1:]], axis=1)
            seg_scores = 0.5 * (s[:-1] + s[1:])
        else:
            segs, seg_scores = np.zeros((0, 2, 2)), np.zeros(0)
        lc = LineCollection(segs, cmap=cmap, norm=norm, linewidths=linewidth, zorder=10, label=label,
                            capstyle="round")
        lc.set_array(seg_scores)
        ax.add_collection(lc)
        if colorbar:
            ax.figure.colorbar(lc, ax=ax, label="perception score", shrink=0.8)
        artist = lc
    ax.plot([p[0, 0]], [p[0, 1]], marker="o", markersize=6, color="tab:green", **ends)
    ax.plot([p[-1, 0]], [p[-1, 1]], marker="*", markersize=9, color="tab:red", **ends)
    return artist


# ------------------------------------------------------------------------------------------------------------------
# convenience
# ------------------------------------------------------------------------------------------------------------------
def new_figure(figsize=(8.0, 6.0), dpi: int = 150):
    """A pyplot-free ``Figure`` on an Agg canvas, with one ``Axes``.

    Returns
    -------
    (matplotlib.figure.Figure, matplotlib.axes.Axes)
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    return fig, ax


def save_scene_figure(scene, path, robot_spheres=None, title: Optional[str] = None, show_problems: bool = True,
                      dpi: int = 150) -> Path:
    """Write a top-view PNG of a scene.

    Parameters
    ----------
    scene : psprm_core.scene.Scene
    path : str or Path
        Output file (parent folders are created). PNG unless the suffix says otherwise.
    robot_spheres : tuple of ((S, 3) array_like, (S,) array_like), optional
        Collision sphere centres and radii of a robot configuration to overlay.
    title : str, optional
        Figure title (default: scene name and robot).
    show_problems : bool
        Mark the problems' start/goal base poses.
    dpi : int

    Returns
    -------
    Path
        The written file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ws = np.asarray(scene.workspace, dtype=float)
    w, h = ws[0, 1] - ws[0, 0], ws[1, 1] - ws[1, 0]
    figsize = (8.0, float(np.clip(8.0 * h / w, 3.0, 10.0)) + 0.6)
    fig, ax = new_figure(figsize=figsize, dpi=dpi)
    plot_scene_top(ax, scene, show_labels=True, show_problems=show_problems)
    if robot_spheres is not None:
        centers, radii = robot_spheres
        plot_spheres_top(ax, centers, radii)
    ax.set_title(title if title is not None else f"{scene.name} (robot: {scene.robot})", fontsize=10)
    ax.grid(True, linewidth=0.3, alpha=0.5)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    log.debug("wrote scene figure %s", path)
    return path
