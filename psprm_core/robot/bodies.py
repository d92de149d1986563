"""A robot body's collision geometry as the robot model builds it: the spheres that cover each link's collision
elements (:class:`SphereModel`) and the oriented boxes of those elements (:class:`ElementModel`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError, RobotModelError


def _grid_spheres(lo: np.ndarray, hi: np.ndarray, r_max: float, pad: float) -> tuple:
    """Cover the box [lo, hi] with the circumscribed spheres of a grid of cells (conservative).

    Cells are refined greedily along their longest side until every sphere radius is <= ``r_max``.
    """
    ext = np.maximum(hi - lo, 1e-6)
    n = np.ones(3, dtype=int)
    while 0.5 * np.linalg.norm(ext / n) > r_max:
        n[np.argmax(ext / n)] += 1
    cell = ext / n
    r = 0.5 * np.linalg.norm(cell) + pad
    ii = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    centers = lo + (ii + 0.5) * cell
    return centers, np.full(len(centers), r)


def _geom_local_box(geom) -> tuple:
    """Axis-aligned bounds of a collision element in its own (origin) frame."""
    if geom.kind == "box":
        return -geom.size / 2, geom.size / 2
    if geom.kind == "cylinder":
        h = np.array([geom.radius, geom.radius, geom.length / 2])
        return -h, h
    if geom.kind == "mesh":
        import trimesh

        try:
            mesh = trimesh.load(str(geom.mesh), force="mesh")
        except Exception as exc:  # trimesh raises many types
            raise RobotModelError(f"cannot load collision mesh {geom.mesh}: {exc}") from None
        v = np.asarray(mesh.vertices) * geom.scale
        return v.min(0), v.max(0)
    raise InputError(geom.kind)


# ------------------------------------------------------------------------------------------------------------------
# Robot model
# ------------------------------------------------------------------------------------------------------------------
@dataclass
class SphereModel:
    """Collision spheres in body frames, grouped by link (for broad-phase bounds and allowed pairs)."""

    link_names: list  # collision links
    link_body: np.ndarray  # (L,) body index of each collision link
    centers: np.ndarray  # (S, 3) in the body frame
    radii: np.ndarray  # (S,)
    sphere_link: np.ndarray  # (S,) index into link_names


@dataclass
class ElementModel:
    """Collision elements as oriented bounding boxes in body frames (conservative: each mesh lies inside its box)."""

    link_names: list  # collision links
    element_link: np.ndarray  # (E,) index into link_names
    element_body: np.ndarray  # (E,) body index
    center: np.ndarray  # (E, 3) box centre in the body frame
    rotation: np.ndarray  # (E, 3, 3) box axes in the body frame
    half: np.ndarray  # (E, 3) half extents (padding included)
