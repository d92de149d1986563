"""RViz ``visualization_msgs/MarkerArray`` of the scene, the roadmap and the current path, coloured by perception score.

Namespaces (one marker each, so RViz can toggle them): ``obstacles`` (cubes), ``targets`` (arrows along the facing
direction), ``roadmap_nodes`` (the nodes' camera positions, points coloured by score), ``roadmap_edges`` (base
positions, grey lines), ``path`` (base path, line strip coloured by the score along the path) and ``path_camera``
(camera positions along the path).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

# a compact viridis approximation (score 0 -> dark purple, 1 -> yellow), no matplotlib import in the nodes
_VIRIDIS = np.array([[0.267, 0.005, 0.329], [0.283, 0.141, 0.458], [0.254, 0.265, 0.530], [0.207, 0.372, 0.553],
                     [0.164, 0.471, 0.558], [0.128, 0.567, 0.551], [0.135, 0.659, 0.518], [0.267, 0.749, 0.441],
                     [0.478, 0.821, 0.318], [0.741, 0.873, 0.150], [0.993, 0.906, 0.144]])


def score_colors(scores, alpha: float = 1.0) -> np.ndarray:
    """Scores in [0, 1] (clipped; NaN -> 0) -> RGBA (N, 4)."""
    s = np.nan_to_num(np.clip(np.asarray(scores, float).reshape(-1), 0.0, 1.0))
    x = s * (len(_VIRIDIS) - 1)
    i = np.clip(np.floor(x).astype(int), 0, len(_VIRIDIS) - 2)
    f = (x - i)[:, None]
    rgb = _VIRIDIS[i] * (1 - f) + _VIRIDIS[i + 1] * f
    return np.concatenate([rgb, np.full((len(s), 1), alpha)], 1)


def _color(c):
    from std_msgs.msg import ColorRGBA

    return ColorRGBA(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=float(c[3]) if len(c) > 3 else 1.0)


def _points(xyz):
    from geometry_msgs.msg import Point

    return [Point(x=float(a), y=float(b), z=float(c)) for a, b, c in np.asarray(xyz, float).reshape(-1, 3)]


def _marker(ns: str, kind: int, frame: str, stamp, mid: int = 0):
    from visualization_msgs.msg import Marker

    m = Marker()
    m.header.frame_id = frame
    if stamp is not None:
        m.header.stamp = stamp
    m.ns, m.id, m.type, m.action = ns, mid, kind, Marker.ADD
    m.pose.orientation.w = 1.0
    return m


def scene_markers(scene, stamp=None) -> list:
    """Cubes of the obstacles and arrows of the targets at their current poses."""
    from visualization_msgs.msg import Marker

    out = []
    for i, b in enumerate(scene.obstacles):
        m = _marker("obstacles", Marker.CUBE, scene.frame, stamp, i)
        m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) for v in b.center)
        (m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
         m.pose.orientation.w) = (float(v) for v in b.quat)
        m.scale.x, m.scale.y, m.scale.z = (float(v) for v in b.size)
        c = np.array(b.color, float)
        c[3] = min(c[3], 0.6)
        m.color = _color(c)
        out.append(m)
    for i, t in enumerate(scene.targets):
        m = _marker("targets", Marker.ARROW, scene.frame, stamp, i)
        m.points = _points([t.center, np.asarray(t.center) + 0.4 * t.facing])
        m.scale.x, m.scale.y, m.scale.z = 0.03, 0.06, 0.08
        m.color = _color((1.0, 0.55, 0.1, 1.0))
        out.append(m)
    return out


def roadmap_markers(frame: str, camera_xyz: np.ndarray, node_scores: np.ndarray, base_xy: np.ndarray,
                    edges: Optional[np.ndarray], stamp=None, max_edges: int = 20000) -> list:
    """Points at the nodes' camera positions coloured by score, and the edges between the nodes' base positions."""
    from visualization_msgs.msg import Marker

    nodes = _marker("roadmap_nodes", Marker.POINTS, frame, stamp)
    nodes.scale.x = nodes.scale.y = 0.04
    nodes.points = _points(camera_xyz)
    nodes.colors = [_color(c) for c in score_colors(node_scores)]
    out = [nodes]
    e = _marker("roadmap_edges", Marker.LINE_LIST, frame, stamp)
    e.scale.x = 0.005
    e.color = _color((0.55, 0.55, 0.55, 0.35))
    if edges is not None and len(edges):
        ed = np.asarray(edges, int)
        if len(ed) > max_edges:  # an evenly spread subset (edge ids follow the sampling, not space: no hole)
            ed = ed[np.linspace(0, len(ed) - 1, max_edges).round().astype(int)]
        xy = np.asarray(base_xy, float)
        seg = np.stack([xy[ed[:, 0]], xy[ed[:, 1]]], 1).reshape(-1, 2)
        e.points = _points(np.c_[seg, np.full(len(seg), 0.01)])
    out.append(e)
    return out


def path_markers(frame: str, base_xy: np.ndarray, camera_xyz: Optional[np.ndarray], scores: np.ndarray,
                 stamp=None) -> list:
    """The path: base line strip (z = 5 cm) and camera line strip, both with per-vertex score colours."""
    from visualization_msgs.msg import Marker

    cols = [_color(c) for c in score_colors(scores)]
    base = _marker("path", Marker.LINE_STRIP, frame, stamp)
    base.scale.x = 0.04
    xy = np.asarray(base_xy, float).reshape(-1, 2)
    base.points = _points(np.c_[xy, np.full(len(xy), 0.05)])
    base.colors = cols[: len(xy)]
    out = [base]
    if camera_xyz is not None:
        cam = _marker("path_camera", Marker.LINE_STRIP, frame, stamp)
        cam.scale.x = 0.02
        cam.points = _points(camera_xyz)
        cam.colors = cols[: len(cam.points)]
        out.append(cam)
    return out


def marker_array(markers: list):
    from visualization_msgs.msg import MarkerArray

    return MarkerArray(markers=list(markers))
