"""A small transform tree fed from ``tf2_msgs/TFMessage`` (``/tf`` and ``/tf_static``): the latest transform of
every parent -> child link, composed through the tree on request.

A localised robot says where it is through tf: ``map -> odom`` from its localisation, ``odom -> base_link`` from its
base controller, fixed links (``base_link -> camera_link``) on ``/tf_static``. :class:`TfTree` keeps the newest
transform of each link with its header stamp and the caller's receipt time; :meth:`TfTree.lookup` composes the
links between two frames through their common ancestor, as ``tf2_ros.Buffer.lookup_transform(target, source,
Time())`` does (no interpolation in time: each link's latest transform). A message's bad transforms (non-finite
values, a quaternion whose norm is off 1 by more than :data:`QUAT_NORM_TOLERANCE`, an empty frame id, a link to
itself, a second parent for a frame, a link closing a loop) are discarded with a reason the caller reports;
:meth:`TfTree.update` never raises for message content.

Frame ids are taken without a leading ``/`` (``/map`` is ``map``). No ROS import at module level: the update takes
message objects and reads their fields; :func:`subscribe_tf` imports rclpy and tf2_msgs when called.
"""

from __future__ import annotations

import math
from typing import Dict, List, NamedTuple, Optional, Tuple

import numpy as np

from psprm_core.errors import InputError

from .frames import compose_pose, invert_pose

#: a rotation whose quaternion norm differs from 1 by more than this is discarded (tf2's own check is on the
#: squared norm, 1e-2); accepted ones are normalised
QUAT_NORM_TOLERANCE = 5e-3

#: topics, relative so that a node's namespace moves them (a robot with namespaced tf remaps them)
TF_TOPIC = "tf"
TF_STATIC_TOPIC = "tf_static"

_IDENTITY = (np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))


class Link(NamedTuple):
    """The latest transform of one link: the pose of ``child`` in ``parent`` (``p_parent = T @ p_child``)."""

    parent: str
    child: str
    xyz: np.ndarray
    quat: np.ndarray
    stamp: float  # header stamp, s
    received: float  # the caller's receipt time
    static: bool


class Discarded(NamedTuple):
    """A transform :meth:`TfTree.update` did not take, and why."""

    parent: str
    child: str
    reason: str

    def __str__(self) -> str:
        return f"transform {self.parent or '?'} -> {self.child or '?'} discarded: {self.reason}"


class TfPose(NamedTuple):
    """Result of :meth:`TfTree.lookup`: the pose of the source frame in the target frame, and how fresh the links
    that gave it are."""

    xyz: np.ndarray
    quat: np.ndarray
    links: Tuple[Link, ...]  # the links composed (source side, then target side)

    @property
    def dynamic(self) -> Tuple[Link, ...]:
        return tuple(lk for lk in self.links if not lk.static)

    @property
    def stamp(self) -> Optional[float]:
        """Header stamp of the newest dynamic link (None when every link is static)."""
        d = self.dynamic
        return max(lk.stamp for lk in d) if d else None

    @property
    def received(self) -> Optional[float]:
        """Receipt time of the newest dynamic link (None when every link is static)."""
        d = self.dynamic
        return max(lk.received for lk in d) if d else None

    @property
    def oldest_received(self) -> Optional[float]:
        """Receipt time of the oldest dynamic link (None when every link is static)."""
        d = self.dynamic
        return min(lk.received for lk in d) if d else None

    def age(self, now: float) -> float:
        """Seconds since the newest dynamic link arrived (0 for a chain of static links)."""
        r = self.received
        return 0.0 if r is None else now - r


class TfLookupError(InputError):
    """No transform between two frames; the message names the missing link."""


def clean_frame(frame_id) -> str:
    """A frame id as the tree keys it: stripped, no leading ``/``."""
    return str(frame_id or "").strip().lstrip("/")


class TfTree:
    """The latest transform of every link of ``/tf`` and ``/tf_static`` (see the module docstring)."""

    def __init__(self):
        self.links: Dict[str, Link] = {}  # child -> its link to its parent

    # ------------------------------------------------------------------------------------------------ input
    def update(self, msg, static: bool, now: float) -> List[Discarded]:
        """Take the transforms of a ``tf2_msgs/TFMessage`` (``static``: it came on ``/tf_static``), received at
        ``now`` (the caller's clock). Returns the transforms discarded, each with its reason; raises nothing for
        message content."""
        out: List[Discarded] = []
        try:
            transforms = list(msg.transforms)
        except Exception as exc:  # not a TFMessage
            return [Discarded("", "", f"not a TFMessage ({type(msg).__name__}: {exc})")]
        for tr in transforms:
            try:
                bad = self._take(tr, bool(static), float(now))
            except Exception as exc:  # a field of the wrong kind: discarded like any other bad transform
                bad = Discarded(_frame_of(tr, "header"), _frame_of(tr, "child"), f"unreadable ({exc})")
            if bad is not None:
                out.append(bad)
        return out

    def _take(self, tr, static: bool, now: float) -> Optional[Discarded]:
        parent = clean_frame(tr.header.frame_id)
        child = clean_frame(tr.child_frame_id)
        if not parent or not child:
            return Discarded(parent, child, "empty frame id")
        if parent == child:
            return Discarded(parent, child, "a frame linked to itself")
        t, r = tr.transform.translation, tr.transform.rotation
        xyz = np.array([t.x, t.y, t.z], float)
        quat = np.array([r.x, r.y, r.z, r.w], float)
        stamp = float(tr.header.stamp.sec) + 1e-9 * float(tr.header.stamp.nanosec)
        if not (np.isfinite(xyz).all() and np.isfinite(quat).all() and math.isfinite(stamp)):
            return Discarded(parent, child, f"non-finite values (translation {xyz.tolist()}, rotation "
                                            f"{quat.tolist()})")
        n = float(np.linalg.norm(quat))
        if abs(n - 1.0) > QUAT_NORM_TOLERANCE:
            return Discarded(parent, child, f"rotation {quat.tolist()} is not a unit quaternion (norm {n:.6g}, "
                                            f"tolerance {QUAT_NORM_TOLERANCE:g})")
        held = self.links.get(child)
        if held is not None and held.parent != parent:
            return Discarded(parent, child, f"'{child}' already has the parent '{held.parent}' (a frame has one "
                                            "parent)")
        f = parent
        while f in self.links:  # the new link must not close a loop: the child may not be above the parent
            f = self.links[f].parent
            if f == child:
                return Discarded(parent, child, f"'{child}' is above '{parent}' in the tree (the link would close "
                                                "a loop)")
        self.links[child] = Link(parent, child, xyz, quat / n, stamp, now, static)
        return None

    # ------------------------------------------------------------------------------------------------ queries
    @property
    def frames(self) -> List[str]:
        """Every frame some link names."""
        return sorted(set(self.links) | {lk.parent for lk in self.links.values()})

    def knows(self, frame_id: str) -> bool:
        f = clean_frame(frame_id)
        return f in self.links or any(lk.parent == f for lk in self.links.values())

    def chain_up(self, frame_id: str) -> List[str]:
        """``frame``, its parent, ..., the root of its tree."""
        f = clean_frame(frame_id)
        out = [f]
        while f in self.links:
            f = self.links[f].parent
            out.append(f)
        return out

    def find(self, target_frame: str, source_frame: str) -> Tuple[Optional[TfPose], str]:
        """(pose of ``source_frame`` in ``target_frame``, "") or (None, the reason there is none)."""
        try:
            return self.lookup(target_frame, source_frame), ""
        except TfLookupError as exc:
            return None, str(exc)

    def lookup(self, target_frame: str, source_frame: str) -> TfPose:
        """The pose of ``source_frame`` in ``target_frame`` (``p_target = T @ p_source``, as tf2's
        ``lookup_transform(target, source)``), composed from the latest transform of each link between them.
        Raises :class:`TfLookupError` naming the missing link."""
        target, source = clean_frame(target_frame), clean_frame(source_frame)
        what = f"no transform from {target or '?'} to {source or '?'}"
        if not target or not source:
            raise TfLookupError(f"{what}: empty frame id")
        up_s, up_t = self.chain_up(source), self.chain_up(target)
        on_t = set(up_t)
        common = next((f for f in up_s if f in on_t), None)
        if common is None:
            raise TfLookupError(f"{what}: {self._missing(target, up_t, source, up_s)}")
        links_s = [self.links[f] for f in up_s[:up_s.index(common)]]
        links_t = [self.links[f] for f in up_t[:up_t.index(common)]]
        T_cs = _down(links_s)  # common ancestor -> source
        T_ct = _down(links_t)  # common ancestor -> target
        p, q = compose_pose(invert_pose(T_ct), T_cs)
        return TfPose(np.asarray(p, float), np.asarray(q, float), tuple(links_s) + tuple(links_t))

    def _missing(self, target: str, up_t: list, source: str, up_s: list) -> str:
        """Why two frames are not connected: which frame has no link to a parent, in words."""
        root_s, root_t = up_s[-1], up_t[-1]
        if not self.links:
            return "no transform received yet"
        if not self.knows(source):
            guess = self._leaf_of(root_t) if self.knows(target) else ""
            link = f"{guess} -> {source}" if guess else f"the link into {source}"
            return f"{link} missing (no transform names '{source}')"
        if not self.knows(target):
            return (f"{target} -> {root_s} missing (no transform names '{target}'; '{source}' is in the tree of "
                    f"'{root_s}')")
        guess = self._leaf_of(root_t)  # the source's tree has a root of its own: its link upward is missing
        link = f"{guess} -> {root_s}" if guess else f"the link into {root_s}"
        return f"{link} missing ('{root_s}' has no parent; '{target}' is in the tree of '{root_t}')"

    def _leaf_of(self, root: str) -> str:
        """The deepest frame below ``root`` when the tree under it is a single chain (``map -> odom``: ``odom``),
        else ""."""
        f = root
        while True:
            kids = [lk.child for lk in self.links.values() if lk.parent == f]
            if not kids:
                return f
            if len(kids) > 1:
                return ""
            f = kids[0]


def _down(links: List[Link]) -> tuple:
    """Pose of the first link's child in the last link's parent (``links`` ordered from the bottom up)."""
    T = _IDENTITY
    for lk in links:
        T = compose_pose((lk.xyz, lk.quat), T)
    return T


def _frame_of(tr, which: str) -> str:
    try:
        return clean_frame(tr.header.frame_id if which == "header" else tr.child_frame_id)
    except Exception:
        return ""


# ---------------------------------------------------------------------------------------------------------- ROS side
def import_tf_message():
    """``tf2_msgs.msg.TFMessage``, or an :class:`InputError` that names the missing package."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError as exc:
        raise InputError(f"base_pose_source 'tf' needs the ROS package tf2_msgs (TFMessage), which is not "
                         f"importable ({exc}): on a robot apt install ros-jazzy-tf2-msgs; in this repository's "
                         f"virtual environment run bash scripts/build_interfaces.sh") from None
    return TFMessage


def subscribe_tf(node, callback, callback_group=None) -> list:
    """Subscribe ``callback(msg, static)`` to ``tf`` (keep last 100, reliable, volatile) and ``tf_static`` (keep
    last 100, reliable, transient local), relative names: the node's namespace applies. Returns the subscriptions.
    Publishes nothing."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    TFMessage = import_tf_message()
    dynamic = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
    static = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return [node.create_subscription(TFMessage, TF_TOPIC, lambda m: callback(m, False), dynamic,
                                     callback_group=callback_group),
            node.create_subscription(TFMessage, TF_STATIC_TOPIC, lambda m: callback(m, True), static,
                                     callback_group=callback_group)]
