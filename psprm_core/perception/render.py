"""Render what the robot camera sees with pybullet's CPU renderer (``ER_TINY_RENDERER``).

:class:`SceneRenderer` builds one pybullet ``DIRECT`` client from a :class:`~psprm_core.scene.Scene` (obstacles as
coloured boxes, targets with their :mod:`appearance <psprm_core.perception.appearance>` on the facing side, a floor)
and is then reused for many frames; target and obstacle poses can be moved without rebuilding anything.

Camera convention (shared with :mod:`psprm_core.camera`): a camera pose is the 4x4 transform of the *optical* frame in
the scene frame, +z forward, +x right, +y down. Intrinsics are a :class:`~psprm_core.camera.CameraIntrinsics`.

Nothing heavy happens at import time: pybullet is connected only when a renderer is constructed.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..camera import CameraIntrinsics
from ..geometry import matrix_to_quat, quat_to_matrix
from ..scene import Box, Scene, Target
from .appearance import Appearance, Part, get_appearance
from ..errors import InputError

log = logging.getLogger(__name__)

#: Box edges as pairs of corner indices, for corners ordered like :meth:`Box.corners` (x slowest, z fastest).
_BOX_EDGES = ((0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7))
_UNIT_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)


# ------------------------------------------------------------------------------------------------------------------
# Projection helpers (pure numpy, no pybullet)
# ------------------------------------------------------------------------------------------------------------------
def box_corners(center, size, quat) -> np.ndarray:
    """The 8 corners (8, 3) of an oriented box, ordered like :meth:`psprm_core.scene.Box.corners`."""
    return (_UNIT_CORNERS * 0.5 * np.asarray(size, float)) @ quat_to_matrix(quat).T + np.asarray(center, float)


def project_box(corners_world: np.ndarray, camera_pose: np.ndarray,
                intrinsics: CameraIntrinsics) -> Optional[np.ndarray]:
    """Axis-aligned 2-D bounding box of a convex box's projection, clipped to the near plane and the image.

    The 12 box edges are clipped against the camera's near plane (so a box that straddles the camera is handled
    exactly), the surviving edge end points are projected with the pinhole model and their extent is clipped to the
    image rectangle.

    Parameters
    ----------
    corners_world : (8, 3) ndarray
        Box corners in the scene frame, ordered like :meth:`psprm_core.scene.Box.corners`.
    camera_pose : (4, 4) ndarray
        Optical frame in the scene frame.
    intrinsics : CameraIntrinsics

    Returns
    -------
    (4,) ndarray or None
        ``[x1, y1, x2, y2]`` in pixels (x right, y down, image corner at (0, 0)); ``None`` when the box is entirely
        behind the near plane or its projection misses the image.
    """
    T = np.asarray(camera_pose, float)
    R, t = T[:3, :3], T[:3, 3]
    pc = (np.asarray(corners_world, float) - t) @ R  # world -> optical: R^T (p - t)
    near = intrinsics.near
    pts = [pc[i] for i in range(8) if pc[i, 2] >= near]
    for a, b in _BOX_EDGES:
        za, zb = pc[a, 2], pc[b, 2]
        if (za - near) * (zb - near) < 0:  # edge crosses the near plane
            s = (near - za) / (zb - za)
            pts.append(pc[a] + s * (pc[b] - pc[a]))
    if not pts:
        return None
    uv = intrinsics.project(np.array(pts))
    x1, y1 = uv.min(axis=0)
    x2, y2 = uv.max(axis=0)
    x1, x2 = np.clip([x1, x2], 0, intrinsics.width)
    y1, y2 = np.clip([y1, y2], 0, intrinsics.height)
    if x2 - x1 <= 0 or y2 - y1 <= 0:
        return None
    return np.array([x1, y1, x2, y2], dtype=float)


def mask_box(mask: np.ndarray) -> Optional[np.ndarray]:
    """Tight ``[x1, y1, x2, y2]`` box (pixel edges, so ``x2`` is exclusive) of a boolean mask, or ``None``."""
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return None
    return np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=float)


def view_matrix(camera_pose: np.ndarray) -> list:
    """pybullet (OpenGL, column-major) view matrix of an optical-frame camera pose."""
    T = np.asarray(camera_pose, float)
    r_gl = T[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # optical (z fwd, y down) -> OpenGL (-z fwd, y up)
    v = np.eye(4)
    v[:3, :3] = r_gl.T
    v[:3, 3] = -r_gl.T @ T[:3, 3]
    return v.T.reshape(-1).tolist()


# ------------------------------------------------------------------------------------------------------------------
# Renderer
# ------------------------------------------------------------------------------------------------------------------
@dataclass
class RenderResult:
    """One rendered frame.

    Attributes
    ----------
    rgb : (H, W, 3) uint8 ndarray
    segmentation : (H, W) int32 ndarray or None
        pybullet body id per pixel (-1 for background); use :meth:`SceneRenderer.target_mask` to get a target's mask.
    camera_pose : (4, 4) ndarray
    """

    rgb: np.ndarray
    segmentation: Optional[np.ndarray]
    camera_pose: np.ndarray


@dataclass
class _Item:
    """Bodies making up one scene element, with each body's fixed pose in the element's frame."""

    kind: str  # "target" | "obstacle"
    name: str
    bodies: list = field(default_factory=list)  # (body_id, (4, 4) local transform)


class SceneRenderer:
    """Reusable CPU renderer of a scene's camera views.

    Parameters
    ----------
    scene : Scene
        Obstacles become coloured boxes (a box's optional ``mesh`` is not drawn); targets get their appearance (see
        :func:`psprm_core.perception.appearance.get_appearance`) on the side they face (+x of the target frame).
    intrinsics : CameraIntrinsics, optional
        Defaults to the paper's camera (640x480, 42.5 deg vertical FOV, near 0.3 m, far 10 m).
    renderer : {"tiny", "egl", "auto"}
        ``"tiny"`` (default) uses ``ER_TINY_RENDERER`` on the CPU. ``"egl"`` loads pybullet's EGL plugin and renders
        with OpenGL on a GPU; ``"auto"`` does so only when an NVIDIA/DRI device node exists and falls back to
        ``"tiny"`` when the plugin fails.
    floor : bool
        Add a floor plane (top face at z = 0).
    floor_color : sequence of 4 floats
    light_direction : sequence of 3 floats
        Direction *towards* the light in the scene frame.
    ambient, diffuse, specular : float
        TinyRenderer lighting coefficients (no shadows; walls-free lighting).

    Notes
    -----
    The renderer owns a pybullet client and a temporary directory for texture files; call :meth:`close` (or use it as
    a context manager) to free them.
    """

    def __init__(self, scene: Scene, intrinsics: Optional[CameraIntrinsics] = None, *, renderer: str = "tiny",
                 floor: bool = True, floor_color: Sequence[float] = (0.78, 0.76, 0.72, 1.0),
                 light_direction: Sequence[float] = (0.4, 0.3, 1.0), ambient: float = 0.6, diffuse: float = 0.45,
                 specular: float = 0.05):
        import pybullet as p  # imported here so that importing this module stays cheap

        self._p = p
        self.scene = scene
        self.intrinsics = intrinsics or CameraIntrinsics()
        self._light = dict(lightDirection=list(map(float, light_direction)), lightAmbientCoeff=float(ambient),
                           lightDiffuseCoeff=float(diffuse), lightSpecularCoeff=float(specular), shadow=0)
        self._client = p.connect(p.DIRECT)
        self._tmp = tempfile.TemporaryDirectory(prefix="psprm-render-")
        self._textures: dict = {}
        self._items: dict = {}
        self._owner: dict = {}
        self._targets: dict = {t.name: t for t in scene.targets}
        self._obstacles: dict = {b.name: b for b in scene.obstacles}
        self._renderer_flag = p.ER_TINY_RENDERER
        self.renderer_name = "tiny"
        if renderer not in ("tiny", "egl", "auto"):
            raise InputError(f"renderer must be 'tiny', 'egl' or 'auto', not {renderer!r}")
        if renderer == "egl" or (renderer == "auto" and _gpu_device_present()):
            self._try_egl(required=renderer == "egl")
        a = self.intrinsics
        self._proj = p.computeProjectionMatrixFOV(fov=a.vfov_deg, aspect=a.width / a.height, nearVal=a.near,
                                                  farVal=a.far, physicsClientId=self._client)
        if floor:
            self._floor = self._box_body(np.array([0.0, 0.0, -0.005]), np.array([60.0, 60.0, 0.01]),
                                         np.array([0, 0, 0, 1.0]), floor_color)
        for b in scene.obstacles:
            self._add_obstacle(b)
        for t in scene.targets:
            self._add_target(t)
        log.debug("SceneRenderer for scene '%s': %d obstacles, %d targets, renderer=%s", scene.name,
                  len(scene.obstacles), len(scene.targets), self.renderer_name)

    # ---- lifetime ------------------------------------------------------------------------------------------------
    def close(self) -> None:
        """Disconnect the pybullet client and delete temporary texture files (idempotent)."""
        if getattr(self, "_client", None) is not None:
            try:
                self._p.disconnect(physicsClientId=self._client)
            except Exception:  # pragma: no cover - already disconnected
                pass
            self._client = None
        if getattr(self, "_tmp", None) is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> "SceneRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    # ---- building ------------------------------------------------------------------------------------------------
    def _try_egl(self, required: bool) -> None:
        p = self._p
        try:
            import importlib.util

            spec = importlib.util.find_spec("eglRenderer")  # shipped with pybullet
            plugin = p.loadPlugin(spec.origin, "_eglRendererPlugin", physicsClientId=self._client) \
                if spec is not None and spec.origin else -1
            if plugin < 0:
                raise RuntimeError("pybullet EGL renderer plugin could not be loaded")
            self._renderer_flag = p.ER_BULLET_HARDWARE_OPENGL
            self.renderer_name = "egl"
        except Exception as exc:
            if required:
                raise
            log.info("EGL rendering unavailable (%s); using TinyRenderer", exc)

    def _box_body(self, center, size, quat, rgba, texture: Optional[int] = None) -> int:
        p = self._p
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=(0.5 * np.asarray(size, float)).tolist(),
                                  rgbaColor=list(map(float, rgba)), physicsClientId=self._client)
        body = p.createMultiBody(baseMass=0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=vis,
                                 basePosition=list(map(float, center)), baseOrientation=list(map(float, quat)),
                                 physicsClientId=self._client)
        if texture is not None:
            p.changeVisualShape(body, -1, textureUniqueId=texture, physicsClientId=self._client)
        return body

    def _quad_body(self, width: float, height: float, texture: int, pose: np.ndarray) -> int:
        """A textured rectangle in the local y-z plane facing +x (visible from the front only)."""
        p = self._p
        hw, hh = 0.5 * width, 0.5 * height
        # counter-clockwise as seen from +x (viewer's right is +y): bottom-left, bottom-right, top-right, top-left
        verts = [[0, -hw, -hh], [0, hw, -hh], [0, hw, hh], [0, -hw, hh]]
        uvs = [[0, 0], [1, 0], [1, 1], [0, 1]]
        vis = p.createVisualShape(p.GEOM_MESH, vertices=verts, indices=[0, 1, 2, 0, 2, 3], uvs=uvs,
                                  normals=[[1, 0, 0]] * 4, rgbaColor=[1, 1, 1, 1], physicsClientId=self._client)
        body = p.createMultiBody(baseMass=0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=vis,
                                 basePosition=pose[:3, 3].tolist(), baseOrientation=matrix_to_quat(pose[:3, :3]).tolist(),
                                 physicsClientId=self._client)
        p.changeVisualShape(body, -1, textureUniqueId=texture, rgbaColor=[1, 1, 1, 1], physicsClientId=self._client)
        return body

    def _texture(self, key: str, make_image) -> int:
        if key not in self._textures:
            from PIL import Image

            path = Path(self._tmp.name) / f"tex{len(self._textures)}.png"
            img = np.ascontiguousarray(np.asarray(make_image())[..., :3].astype(np.uint8))
            Image.fromarray(img).save(path)
            self._textures[key] = self._p.loadTexture(str(path), physicsClientId=self._client)
        return self._textures[key]

    def _register(self, item: _Item, world: np.ndarray) -> None:
        self._items[(item.kind, item.name)] = item
        for body, _ in item.bodies:
            self._owner[body] = (item.kind, item.name)
        self._place(item, world)

    def _add_obstacle(self, b: Box) -> None:
        item = _Item("obstacle", b.name)
        body = self._box_body(np.zeros(3), b.size, np.array([0, 0, 0, 1.0]), b.color)
        item.bodies.append((body, np.eye(4)))
        self._register(item, _pose(b.center, b.quat))

    def _add_target(self, t: Target) -> None:
        item = _Item("target", t.name)
        app: Appearance = get_appearance(t.appearance, t.detector_class)
        size = np.asarray(t.size, float)
        for part in app.parts_for(size):
            item.bodies.append(self._part_body(app, part, size))
        self._register(item, _pose(t.center, t.quat))

    def _part_body(self, app: Appearance, part: Part, size: np.ndarray) -> tuple:
        center = np.asarray(part.center, float) * size
        psize = np.maximum(np.asarray(part.size, float) * size, 1e-4)
        local = np.eye(4)
        local[:3, :3] = quat_to_matrix(part.quat)
        local[:3, 3] = center
        if part.image is not None:
            aspect = float(psize[1] / psize[2])
            key = f"{app.name}:{part.image}:{aspect:.3f}"
            tex = self._texture(key, lambda: app.texture(part.image, aspect))
            if part.kind == "quad":
                return self._quad_body(psize[1], psize[2], tex, local), local
            body = self._box_body(np.zeros(3), psize, np.array([0, 0, 0, 1.0]), (1, 1, 1, 1), texture=tex)
            return body, local
        if part.kind == "cylinder":  # axis along the part's z; radius from the smaller of its x/y extents
            p = self._p
            vis = p.createVisualShape(p.GEOM_CYLINDER, radius=float(0.5 * min(psize[0], psize[1])),
                                      length=float(psize[2]), rgbaColor=list(map(float, part.color)),
                                      physicsClientId=self._client)
            body = p.createMultiBody(baseMass=0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=vis,
                                     physicsClientId=self._client)
            return body, local
        body = self._box_body(np.zeros(3), psize, np.array([0, 0, 0, 1.0]), part.color)
        return body, local

    def _place(self, item: _Item, world: np.ndarray) -> None:
        p = self._p
        for body, local in item.bodies:
            T = world @ local
            p.resetBasePositionAndOrientation(body, T[:3, 3].tolist(), matrix_to_quat(T[:3, :3]).tolist(),
                                              physicsClientId=self._client)

    # ---- updates -------------------------------------------------------------------------------------------------
    def set_target_pose(self, name: str, center, quat=None) -> None:
        """Move a target (all its parts) to a new pose; ``quat`` (x, y, z, w) defaults to the current one."""
        t = self._targets[name] if name in self._targets else self.scene.target(name)
        q = t.quat if quat is None else np.asarray(quat, float)
        self._targets[name] = _replace(t, center=np.asarray(center, float), quat=q)
        self._place(self._items[("target", name)], _pose(center, q))

    def set_obstacle_pose(self, name: str, center, quat=None) -> None:
        """Move an obstacle box to a new pose; ``quat`` (x, y, z, w) defaults to the current one."""
        b = self._obstacles[name] if name in self._obstacles else self.scene.obstacle(name)
        q = b.quat if quat is None else np.asarray(quat, float)
        self._obstacles[name] = _replace(b, center=np.asarray(center, float), quat=q)
        self._place(self._items[("obstacle", name)], _pose(center, q))

    def target(self, name: str) -> Target:
        """The target with its *current* pose (after :meth:`set_target_pose`)."""
        if name not in self._targets:
            self.scene.target(name)  # raises a KeyError listing the targets
        return self._targets[name]

    # ---- rendering -----------------------------------------------------------------------------------------------
    def render(self, camera_pose: np.ndarray, segmentation: bool = False) -> RenderResult:
        """Render the view of an optical-frame camera pose (4x4, scene frame).

        Parameters
        ----------
        camera_pose : (4, 4) array_like
        segmentation : bool
            Also return the per-pixel body ids.

        Returns
        -------
        RenderResult
        """
        p = self._p
        T = np.asarray(camera_pose, float)
        a = self.intrinsics
        flags = 0 if segmentation else p.ER_NO_SEGMENTATION_MASK
        kwargs = dict(self._light) if self._renderer_flag == p.ER_TINY_RENDERER else {}
        _, _, rgba, _, seg = p.getCameraImage(a.width, a.height, viewMatrix=view_matrix(T),
                                              projectionMatrix=self._proj, renderer=self._renderer_flag, flags=flags,
                                              physicsClientId=self._client, **kwargs)
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(a.height, a.width, 4)[..., :3].copy()
        seg_arr = np.asarray(seg, dtype=np.int32).reshape(a.height, a.width) if segmentation else None
        return RenderResult(rgb=rgb, segmentation=seg_arr, camera_pose=T)

    def target_mask(self, segmentation: np.ndarray, name: str) -> np.ndarray:
        """Boolean mask of the pixels showing target ``name`` in a segmentation image from :meth:`render`."""
        ids = [b for b, _ in self._items[("target", name)].bodies]
        return np.isin(segmentation, ids)

    def owner(self, body_id: int) -> Optional[tuple]:
        """``("target" | "obstacle", name)`` of a body id found in a segmentation image, or ``None`` (floor)."""
        return self._owner.get(int(body_id))

    def target_corners(self, name: str) -> np.ndarray:
        """The 8 corners (8, 3) of target ``name``'s box at its current pose."""
        t = self.target(name)
        return box_corners(t.center, t.size, t.quat)

    def projected_box(self, camera_pose: np.ndarray, name: str) -> Optional[np.ndarray]:
        """Target ``name``'s projected 2-D box ``[x1, y1, x2, y2]`` (see :func:`project_box`), or ``None``."""
        return project_box(self.target_corners(name), camera_pose, self.intrinsics)


# ------------------------------------------------------------------------------------------------------------------
def _pose(center, quat) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(quat)
    T[:3, 3] = np.asarray(center, float)
    return T


def _replace(obj, **kw):
    return dataclasses.replace(obj, **kw)


def _gpu_device_present() -> bool:
    return any(os.path.exists(d) for d in ("/dev/nvidia0", "/dev/dri/renderD128"))


def look_at_pose(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Optical-frame camera pose at ``eye`` looking at ``target`` (image "up" as close to ``up`` as possible).

    Parameters
    ----------
    eye, target : sequence of 3 floats
    up : sequence of 3 floats

    Returns
    -------
    (4, 4) ndarray
    """
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up, float)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight along ``up``
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T
