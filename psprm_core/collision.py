"""Batched collision checking in torch: robot collision elements against oriented scene boxes, self-collision,
joint limits.

Every collision element of the robot (mesh, box, cylinder, sphere) is represented by its oriented bounding box in
its own frame, which contains the element; so the check never misses a collision that the exact mesh check finds
(it may report a few false positives where a mesh is much smaller than its box). The robot's collision *spheres*
(:meth:`RobotModel.spheres`, which cover those boxes) are used where distances are needed (optimisation baselines,
plots); the checker itself uses the boxes because they are both tighter and cheaper.

Hierarchy (every level batched, each only on the survivors of the previous one):

1. body bounds: one bounding sphere per rigid body, against every scene box (sphere/box distance);
2. element bounds: one bounding sphere per element of the candidate bodies, against the candidate box;
3. exact oriented-box overlap by the separating-axis theorem (15 axes; Gottschalk et al., OBBTree, 1996).

Self-collision runs levels 2-3 on the element pairs of link pairs that the allowed-collision matrix leaves checked.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Iterable, Optional

import numpy as np
import torch

from .errors import InputError
from .geometry import obb_overlap
from .kernels._fast_packs import BoxPack, CollisionPack
from .kernels.arrays import as_f64, as_i64, const_f64
from .kernels.compute import Compute, Computing
from .robot import RobotModel, load_acm

log = logging.getLogger(__name__)


@dataclass
class BoxTensors:
    """Oriented boxes as tensors: centres (K,3), rotations (K,3,3) box->world (columns = axes), half extents (K,3)."""

    center: torch.Tensor
    rotation: torch.Tensor
    half: torch.Tensor
    names: list

    @classmethod
    def from_boxes(cls, boxes: Iterable, device="cpu", dtype=torch.float32) -> "BoxTensors":
        boxes = list(boxes)
        if not boxes:
            z = torch.zeros(0, 3, device=device, dtype=dtype)
            return cls(z, torch.zeros(0, 3, 3, device=device, dtype=dtype), z.clone(), [])
        return cls(
            torch.as_tensor(np.stack([b.center for b in boxes]), device=device, dtype=dtype),
            torch.as_tensor(np.stack([b.rotation for b in boxes]), device=device, dtype=dtype),
            torch.as_tensor(np.stack([b.half_extents for b in boxes]), device=device, dtype=dtype),
            [b.name for b in boxes],
        )

    def __len__(self) -> int:
        return self.center.shape[0]

    @property
    def radius(self) -> torch.Tensor:
        return self.half.norm(dim=-1)

    def aabb(self) -> torch.Tensor:
        """World axis-aligned bounds (K, 6) = [min xyz, max xyz] of the boxes (|R| times the half extents)."""
        ext = (self.rotation.abs() * self.half.unsqueeze(-2)).sum(-1)
        return torch.cat([self.center - ext, self.center + ext], -1)

    def kernel_pack(self):
        """The boxes as the compiled kernels take them (:mod:`psprm_core.kernels.fastpath`): a
        :class:`~psprm_core.kernels._fast_packs.BoxPack` of centres, rotations, half extents and :meth:`aabb`,
        float64."""
        f64 = as_f64
        return BoxPack(f64(self.center).reshape(-1, 3), f64(self.rotation).reshape(-1, 3, 3),
                       f64(self.half).reshape(-1, 3), f64(self.aabb()).reshape(-1, 6))

    def padded(self, padding: float) -> "BoxTensors":
        """The boxes grown by ``padding`` (m) on every face. A grown box contains every point within ``padding`` of
        the box, so a robot that misses the grown boxes keeps at least that clearance from the real ones."""
        if padding == 0.0:
            return self
        return BoxTensors(self.center, self.rotation, self.half + padding, list(self.names))


def point_box_sqdist(points: torch.Tensor, box_center: torch.Tensor, box_rot: torch.Tensor,
                     box_half: torch.Tensor) -> torch.Tensor:
    """Squared distance from points (n, 3) to paired boxes (n, 3), (n, 3, 3), (n, 3) -> (n,)."""
    local = ((points - box_center).unsqueeze(-1) * box_rot).sum(-2)
    d = local - torch.maximum(torch.minimum(local, box_half), -box_half)
    return (d * d).sum(-1)


class CollisionChecker(Computing):
    """Batched validity checker for one robot in one scene.

    Parameters
    ----------
    robot : RobotModel
    boxes : iterable of Box
        Obstacles (use ``scene.collision_boxes()``).
    allowed_pairs : set of frozenset, optional
        Allowed self-collision link pairs; default: the robot's ACM file.
    workspace : (2, 2) array, optional
        Base position bounds [[xmin, xmax], [ymin, ymax]] (mobile robots).
    device, dtype : torch device and dtype of all tensors.
    chunk : int
        Configurations processed per batch (bounds peak memory).
    kinematics : object with ``body_poses(q)``, optional
        The body poses of the torch path, in the format of :meth:`RobotModel.body_poses`: the robot model itself
        (default) or e.g. :class:`~psprm_core.robot.kinematics_pk.PKBodyKinematics`. The compiled small-batch CPU path
        (:mod:`~psprm_core.kernels.fastpath`) runs the robot model's own FK either way.
    compute : Compute, optional
        Which kernels serve its checks (default: the robot model's on the robot's device, else the device's
        default; :mod:`~psprm_core.kernels.compute`).
    padding : float
        Clearance (m) kept from every obstacle box: the environment checks run against the boxes grown by this much
        on every face (:meth:`BoxTensors.padded`); :attr:`true_boxes` keeps the boxes as given, for
        :meth:`check_unpadded`. Self-collision and the limits are not padded. A planner plans with a padding so that
        a robot tracking its path a few centimetres off stays clear of the real obstacles.
    """

    def __init__(self, robot: RobotModel, boxes: Iterable = (), allowed_pairs: Optional[set] = None,
                 workspace: Optional[np.ndarray] = None, device="cpu", dtype=torch.float32, chunk: int = 16384,
                 kinematics=None, padding: float = 0.0, compute: Optional[Compute] = None):
        if not (np.isfinite(padding) and padding >= 0):
            raise InputError(f"collision padding must be a finite distance >= 0 m, got {padding}")
        self.padding = float(padding)

        self.robot = robot
        self.kin = robot if kinematics is None else kinematics
        self.device = torch.device(device)
        self.dtype = dtype
        self.chunk = chunk
        self._compute = compute if compute is not None else (robot.compute if robot.compute.device == self.device
                                                             else None)
        em = robot.elements
        t = lambda a: torch.as_tensor(np.asarray(a), device=self.device, dtype=dtype)  # noqa: E731
        ti = lambda a: torch.as_tensor(np.asarray(a, dtype=np.int64), device=self.device)  # noqa: E731
        E = len(em.element_link)
        self.el_c, self.el_R, self.el_h = t(em.center), t(em.rotation), t(em.half)
        self.el_body, self.el_r = ti(em.element_body), t(np.linalg.norm(em.half, axis=1))
        # body bounding spheres (body frame) over their elements' boxes
        NB = len(robot.bodies)
        bc, br = np.zeros((NB, 3)), np.zeros(NB)
        self.body_elements = []
        for b in range(NB):
            idx = np.nonzero(em.element_body == b)[0]
            self.body_elements.append(idx)
            if len(idx):
                lo = (em.center[idx] - np.linalg.norm(em.half[idx], axis=1)[:, None]).min(0)
                hi = (em.center[idx] + np.linalg.norm(em.half[idx], axis=1)[:, None]).max(0)
                bc[b] = 0.5 * (lo + hi)
                br[b] = (np.linalg.norm(em.center[idx] - bc[b], axis=1) + np.linalg.norm(em.half[idx], axis=1)).max()
        self.bodies_with_elements = ti([b for b in range(NB) if len(self.body_elements[b])])
        # body boxes (body frame, axis-aligned) enclosing each body's element boxes: a tighter test than the body
        # sphere for long bodies (Stretch's base with its mast) before their elements are tested one by one
        box_c, box_h = np.zeros((NB, 3)), np.zeros((NB, 3))
        for b in range(NB):
            idx = self.body_elements[b]
            if len(idx):
                ext = np.einsum("kij,kj->ki", np.abs(em.rotation[idx]), em.half[idx])
                lo, hi = (em.center[idx] - ext).min(0), (em.center[idx] + ext).max(0)
                box_c[b], box_h[b] = 0.5 * (lo + hi), 0.5 * (hi - lo)
        self.body_box_c, self.body_box_h = t(box_c), t(box_h)
        self.body_c, self.body_r = t(bc), t(br)
        counts = np.array([len(self.body_elements[b]) for b in range(NB)])
        order = np.concatenate([self.body_elements[b] for b in range(NB)]) if E else np.zeros(0, int)
        self.body_el_count = ti(counts)
        self.body_el_start = ti(np.concatenate([[0], np.cumsum(counts)[:-1]]))
        self.body_el_order = ti(order)
        # self-collision element pairs (link pair not allowed, different bodies)
        allowed = load_acm(robot) if allowed_pairs is None else allowed_pairs
        pairs = []
        for a in range(E):
            for b in range(a + 1, E):
                if em.element_body[a] == em.element_body[b]:
                    continue
                la, lb = em.link_names[em.element_link[a]], em.link_names[em.element_link[b]]
                if frozenset((la, lb)) in allowed:
                    continue
                pairs.append((a, b))
        self.self_pairs = ti(np.array(pairs, dtype=np.int64).reshape(-1, 2))
        # planning joints each self pair's relative pose depends on: the joints of the bodies on the tree path
        # between the two bodies (below their common ancestor), mapped through the drive matrix (mimic joints)
        dep = np.zeros((len(pairs), robot.dof), dtype=bool)
        drives = np.abs(np.asarray(robot.drive_matrix)) > 0  # (dof, NB)
        for i, (a, b) in enumerate(pairs):
            for body in _tree_path(robot.parent_body, int(em.element_body[a]), int(em.element_body[b])):
                dep[i] |= drives[:, body]
        self.pair_joints = torch.as_tensor(dep, device=self.device)
        self.lower = t(np.where(np.isfinite(robot.lower), robot.lower, -1e9))
        self.upper = t(np.where(np.isfinite(robot.upper), robot.upper, 1e9))
        if workspace is not None and robot.mobile:
            self.lower[:2] = t(np.asarray(workspace)[:, 0])
            self.upper[:2] = t(np.asarray(workspace)[:, 1])
        self.set_boxes(boxes)
        log.debug("collision model %s: %d elements, %d self pairs", robot.name, E, len(pairs))

    def set_boxes(self, boxes: Iterable) -> None:
        """Replace the obstacle set (e.g. after an obstacle moved). :attr:`boxes` are the ones checked (a turning box
        as :meth:`~psprm_core.scene.Box.swept`, grown by the padding), :attr:`true_boxes` the ones given."""
        boxes = list(boxes)
        self.true_boxes = BoxTensors.from_boxes(boxes, self.device, self.dtype)
        self.boxes = (self.box_tensors(boxes) if any(b.turning for b in boxes)
                      else self.true_boxes.padded(self.padding))

    @property
    def keeps_margin(self) -> bool:
        """The boxes checked are larger than the real ones (a padding, or a turning box's sweep): a configuration
        may be inside that margin without touching an obstacle (:meth:`check_unpadded`)."""
        return self.boxes is not self.true_boxes

    def kernel_pack(self):
        """The checker as the compiled kernels take it (:mod:`psprm_core.kernels.fastpath`): a
        :class:`~psprm_core.kernels._fast_packs.CollisionPack` of the joint limits, the collision model (bodies with
        elements, body spheres and boxes, element boxes, self-collision pairs; float64, int64), the separating-axis
        eps of :func:`obb_overlap` and the obstacle boxes :attr:`boxes` (:meth:`BoxTensors.kernel_pack`). Kept on
        the checker; the limits are read again when they change (in place, or by new storage), the boxes when
        :meth:`set_boxes` replaces them."""
        f64, i64 = as_f64, as_i64
        cache = self.__dict__.get("_kernel_pack")
        if cache is None:
            model = (i64(self.bodies_with_elements), f64(self.body_c), f64(self.body_r), f64(self.body_box_c),
                     f64(self.body_box_h), i64(self.body_el_start), i64(self.body_el_count), i64(self.body_el_order),
                     i64(self.el_body), f64(self.el_c), f64(self.el_R), f64(self.el_h), f64(self.el_r),
                     i64(self.self_pairs).reshape(-1, 2), np.unique(i64(self.self_pairs)), 1e-6)
            cache = self._kernel_pack = {"model": model, "boxes_of": None, "pack": None}
        lower, upper = const_f64(self.lower), const_f64(self.upper)
        bx = self.boxes
        pack = cache["pack"]
        if cache["boxes_of"] is not bx or pack.lower is not lower or pack.upper is not upper:
            pack = cache["pack"] = CollisionPack(lower, upper, *cache["model"],
                                                 bx.kernel_pack() if cache["boxes_of"] is not bx else pack.boxes)
            cache["boxes_of"] = bx
        return pack

    def box_tensors(self, boxes: Iterable) -> "BoxTensors":
        """``boxes`` as this checker tests them (tensors on its device, a turning box swept through every heading,
        grown by its padding)."""
        return BoxTensors.from_boxes([b.planned() for b in boxes], self.device, self.dtype).padded(self.padding)

    def check_unpadded(self, q: torch.Tensor) -> torch.Tensor:
        """In-collision flags (B,) against the boxes as given (:attr:`true_boxes`: no padding, a turning box at its
        heading), the limits and self-collision: whether a configuration touches the real obstacles, not the
        clearance kept from them."""
        q = q.to(self.device, self.dtype)
        if self.boxes is self.true_boxes:
            return self.check(q)
        det = self.check_detailed(q)
        return det["limits"] | det["self"] | self.env_hits(q, self.true_boxes)

    # ---- checks ----------------------------------------------------------------------------------------------------
    def check(self, q: torch.Tensor) -> torch.Tensor:
        """In-collision flags (B,) for configurations (B, dof): limits, environment or self-collision."""
        return self.compute.ops.check(self, q)

    def check_torch(self, q: torch.Tensor) -> torch.Tensor:
        """:meth:`check` in torch on the checker's device."""
        q = q.to(self.device, self.dtype)
        if q.shape[0] == 0:
            return torch.zeros(0, dtype=torch.bool, device=self.device)
        return torch.cat([self._check_chunk(q[s:s + self.chunk]) for s in range(0, q.shape[0], self.chunk)])

    def valid(self, q: torch.Tensor) -> torch.Tensor:
        return ~self.check(q)

    def check_detailed(self, q: torch.Tensor) -> dict:
        """Separate flags: ``limits``, ``environment``, ``self`` (each (B,) bool)."""
        return self.compute.ops.check_detailed(self, q)

    def check_detailed_torch(self, q: torch.Tensor) -> dict:
        """:meth:`check_detailed` in torch on the checker's device."""
        q = q.to(self.device, self.dtype)
        poses = self.kin.body_poses(q)
        return {"limits": self.limits_violated(q), "environment": self._env(poses), "self": self._self(poses)}

    def env_hits(self, q: torch.Tensor, boxes, return_aabb: bool = False):
        """Environment-collision flags (B,) against ``boxes`` only (a list of boxes or :class:`BoxTensors`): no
        limits, no self-collision, no other obstacles. What an obstacle move can change for configurations that were
        valid before. A list of boxes is grown by the padding (:meth:`box_tensors`); :class:`BoxTensors` are tested as
        they are. ``return_aabb``: also return the robot's world bounds (B, 6) at each configuration
        (:meth:`robot_aabb`), from the same forward kinematics."""
        q = q.to(self.device, self.dtype)
        bt = boxes if isinstance(boxes, BoxTensors) else self.box_tensors(boxes)
        return self.compute.ops.env_hits(self, q, bt, return_aabb)

    def env_hits_torch(self, q: torch.Tensor, bt: "BoxTensors", return_aabb: bool):
        """:meth:`env_hits` against :class:`BoxTensors`, in torch on the checker's device."""
        saved = self.boxes
        hits, boxes_out = [], []
        try:
            self.boxes = bt
            for s in range(0, q.shape[0], self.chunk):
                poses = self.kin.body_poses(q[s:s + self.chunk])
                hits.append(self._env(poses))
                if return_aabb:
                    boxes_out.append(self._aabb(poses))
        finally:
            self.boxes = saved
        hit = torch.cat(hits) if hits else torch.zeros(0, dtype=torch.bool, device=self.device)
        if not return_aabb:
            return hit
        return hit, (torch.cat(boxes_out) if boxes_out else torch.zeros(0, 6, dtype=self.dtype, device=self.device))

    def robot_aabb(self, q: torch.Tensor) -> torch.Tensor:
        """World axis-aligned bounds (B, 6) = [min xyz, max xyz] enclosing every collision element of the robot at
        configurations (B, dof) (the union of the element boxes' world bounds). A configuration whose bounds
        miss a box's bounds (:meth:`BoxTensors.aabb`) cannot touch it."""
        return self.compute.ops.robot_aabb(self, q)

    def robot_aabb_torch(self, q: torch.Tensor) -> torch.Tensor:
        """:meth:`robot_aabb` in torch on the checker's device."""
        q = q.to(self.device, self.dtype)
        return torch.cat([self._aabb(self.kin.body_poses(q[s:s + self.chunk]))
                          for s in range(0, q.shape[0], self.chunk)]) if q.shape[0] else \
            torch.zeros(0, 6, dtype=self.dtype, device=self.device)

    def _aabb(self, poses) -> torch.Tensor:
        R, t = poses
        body = self.el_body
        Rb = R[:, body]  # (B, E, 3, 3)
        c = (Rb * self.el_c.unsqueeze(-2)).sum(-1) + t[:, body]  # element centres (B, E, 3)
        ext = ((Rb @ self.el_R).abs() * self.el_h.unsqueeze(-2)).sum(-1)  # world half extents of the element boxes
        return torch.cat([(c - ext).amin(1), (c + ext).amax(1)], -1)

    def limits_violated(self, q: torch.Tensor) -> torch.Tensor:
        return ((q < self.lower) | (q > self.upper)).any(-1) | ~torch.isfinite(q).all(-1)

    def _check_chunk(self, q: torch.Tensor) -> torch.Tensor:
        bad = self.limits_violated(q)
        poses = self.kin.body_poses(q)
        return bad | self._env(poses) | self._self(poses, q)

    def _element_world(self, poses, b_idx: torch.Tensor, e_idx: torch.Tensor) -> tuple:
        R, t = poses
        body = self.el_body[e_idx]
        Rb = R[b_idx, body]
        c = (Rb * self.el_c[e_idx].unsqueeze(-2)).sum(-1) + t[b_idx, body]
        return c, Rb @ self.el_R[e_idx]

    def _env(self, poses) -> torch.Tensor:
        R, t = poses
        B = R.shape[0]
        hit = torch.zeros(B, dtype=torch.bool, device=self.device)
        if len(self.boxes) == 0:
            return hit
        bx = self.boxes
        # level 0: the bounds of the robot's body spheres vs the boxes' world bounds, (B, K)
        bodies = self.bodies_with_elements
        bc = (R[:, bodies] * self.body_c[bodies].unsqueeze(-2)).sum(-1) + t[:, bodies]  # (B, NBe, 3)
        rad = self.body_r[bodies].unsqueeze(-1)
        lo, hi = (bc - rad).amin(1), (bc + rad).amax(1)  # (B, 3)
        bb = bx.aabb()  # (K, 6)
        near = ((lo.unsqueeze(1) <= bb[:, 3:]) & (hi.unsqueeze(1) >= bb[:, :3])).all(-1)  # (B, K)
        c_b, c_k = torch.nonzero(near, as_tuple=True)
        if len(c_b) == 0:
            return hit
        # level 1: body bounding spheres vs the candidate boxes, (C, NBe)
        nbe = len(bodies)
        pts = bc[c_b].reshape(-1, 3)
        kk = c_k.repeat_interleave(nbe)
        d2 = point_box_sqdist(pts, bx.center[kk], bx.rotation[kk], bx.half[kk]).reshape(-1, nbe)
        c_i, nb_i = torch.nonzero(d2 < self.body_r[bodies] ** 2, as_tuple=True)
        if len(c_i) == 0:
            return hit
        b_i, k_i = c_b[c_i], c_k[c_i]
        body = bodies[nb_i]
        # level 1b: the body's box vs the candidate box (exact OBB test, conservative for the elements inside)
        Rbd = R[b_i, body]
        cbd = (Rbd * self.body_box_c[body].unsqueeze(-2)).sum(-1) + t[b_i, body]
        m = obb_overlap(cbd, Rbd, self.body_box_h[body], bx.center[k_i], bx.rotation[k_i], bx.half[k_i])
        b_i, k_i, body = b_i[m], k_i[m], body[m]
        if len(b_i) == 0:
            return hit
        # level 2: the candidate bodies' elements (bounding spheres) vs the candidate box
        counts = self.body_el_count[body]
        rows = torch.repeat_interleave(torch.arange(len(body), device=self.device), counts)
        off = torch.arange(len(rows), device=self.device) - torch.repeat_interleave(torch.cumsum(counts, 0) - counts,
                                                                                    counts)
        e = self.body_el_order[self.body_el_start[body][rows] + off]
        b2, k2 = b_i[rows], k_i[rows]
        body_e = self.el_body[e]
        Rb = R[b2, body_e]
        c = (Rb * self.el_c[e].unsqueeze(-2)).sum(-1) + t[b2, body_e]
        m = point_box_sqdist(c, bx.center[k2], bx.rotation[k2], bx.half[k2]) < self.el_r[e] ** 2
        b2, k2, e, c = b2[m], k2[m], e[m], c[m]
        if len(b2) == 0:
            return hit
        Re = Rb[m] @ self.el_R[e]  # element orientations only for the survivors
        # level 3: exact OBB overlap
        ov = obb_overlap(c, Re, self.el_h[e], bx.center[k2], bx.rotation[k2], bx.half[k2])
        hit[b2[ov]] = True
        return hit

    def _self(self, poses, q: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Self-collision flags (B,). With ``q``, pairs whose relative pose depends only on joints that hold one
        value over the whole batch (e.g. an arm kept at its template while the base and head move) are tested on
        the first configuration only: their answer is the same for every row."""
        R, t = poses
        B = R.shape[0]
        hit = torch.zeros(B, dtype=torch.bool, device=self.device)
        P = self.self_pairs.shape[0]
        if P == 0:
            return hit
        ea, eb = self.self_pairs[:, 0], self.self_pairs[:, 1]
        if q is not None and B > 1:
            varying = (q != q[:1]).any(0)  # (dof,)
            moving = (self.pair_joints & varying).any(-1)  # (P,) pairs whose relative pose changes in the batch
            if not bool(moving.all()):
                const = ~moving
                first = (R[:1], t[:1])
                if bool(self._pairs_overlap(first, ea[const], eb[const]).any()):
                    hit[:] = True
                    return hit
                ea, eb = ea[moving], eb[moving]
        return self._pairs_overlap(poses, ea, eb)

    def _pairs_overlap(self, poses, ea: torch.Tensor, eb: torch.Tensor) -> torch.Tensor:
        """Overlap flags (B,) over the element pairs (ea, eb) for every configuration of ``poses``."""
        B = poses[0].shape[0]
        hit = torch.zeros(B, dtype=torch.bool, device=self.device)
        if len(ea):
            b_i, ov = self._pairs_hits(poses, ea, eb)
            hit[b_i[ov]] = True
        return hit

    def _pairs_hits(self, poses, ea: torch.Tensor, eb: torch.Tensor) -> tuple:
        """Rows ``b_i`` of the (configuration, pair) candidates whose element bounding spheres meet, and their exact
        OBB overlap flags."""
        R, t = poses
        # centres of the elements involved for all configurations (B, E', 3) once, then pair distances (B, P)
        els, inv = torch.unique(torch.cat([ea, eb]), return_inverse=True)
        body = self.el_body[els]
        c = (R[:, body] * self.el_c[els].unsqueeze(-2)).sum(-1) + t[:, body]
        d2 = ((c[:, inv[:len(ea)]] - c[:, inv[len(ea):]]) ** 2).sum(-1)
        b_i, p_i = torch.nonzero(d2 < (self.el_r[ea] + self.el_r[eb]) ** 2, as_tuple=True)
        if len(b_i) == 0:
            return b_i, torch.zeros(0, dtype=torch.bool, device=self.device)
        a, b = ea[p_i], eb[p_i]
        ca, Ra = self._element_world(poses, b_i, a)
        cb, Rb = self._element_world(poses, b_i, b)
        return b_i, obb_overlap(ca, Ra, self.el_h[a], cb, Rb, self.el_h[b])


def _tree_path(parent: list, a: int, b: int) -> list:
    """Bodies on the kinematic-tree path between bodies ``a`` and ``b``, their common ancestor excluded: the
    bodies whose joints change the relative pose of ``a`` and ``b``."""
    up_a = [a]
    while parent[up_a[-1]] >= 0:
        up_a.append(parent[up_a[-1]])
    up_b = [b]
    while parent[up_b[-1]] >= 0:
        up_b.append(parent[up_b[-1]])
    common = set(up_a) & set(up_b)
    return [x for x in up_a if x not in common] + [x for x in up_b if x not in common]
