"""Static frame transforms for pose inputs: a pose in another frame than the scene's (vrpn_mocap's ``world``, a
robot's ``odom``) is mapped into the scene frame by a fixed transform given as parameters; a pose in a frame with no
transform is refused with a clear message.

Parameters (Nav2-style: a list of names, then one parameter group per name)::

    input_frames: ["world", "odom"]
    input_frame:
      world: {xyz: [0.0, 0.0, 0.0], quat: [0.0, 0.0, 0.0, 1.0]}   # pose of `world` in the scene frame
      odom:  {xyz: [4.0, 0.7, 0.0], quat: [0.0, 0.0, 0.7071, 0.7071]}

``xyz`` + ``quat`` (x, y, z, w) is the pose of the input frame expressed in the scene frame, i.e. the transform
``T_scene_input`` with ``p_scene = T_scene_input @ p_input`` (what ``ros2 run tf2_ros static_transform_publisher`` takes
with ``--frame-id <scene> --child-frame-id <input>``).

No ROS import here: the tables are numpy; :func:`declare_frame_params` takes a node.
"""

from __future__ import annotations

from typing import Dict, Optional, Sequence

import numpy as np

from psprm_core.errors import InputError
from psprm_core.geometry import quat_multiply

from .conversions import validated_pose


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vector ``v`` (3,) by the unit quaternion ``q`` xyzw."""
    u, w = np.asarray(q[:3], float), float(q[3])
    v = np.asarray(v, float)
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_conj(q: np.ndarray) -> np.ndarray:
    return np.array([-q[0], -q[1], -q[2], q[3]], float)


def compose_pose(a: tuple, b: tuple) -> tuple:
    """Pose ``a`` (p, q) composed with pose ``b`` expressed in ``a``'s frame: ``T_a @ T_b``."""
    pa, qa = a
    pb, qb = b
    return np.asarray(pa, float) + quat_rotate(qa, pb), _unit(quat_multiply(qa, qb))


def invert_pose(a: tuple) -> tuple:
    p, q = a
    qi = quat_conj(_unit(q))
    return -quat_rotate(qi, p), qi


def _unit(q) -> np.ndarray:
    q = np.asarray(q, float)
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or n < 1e-9:
        raise InputError(f"quaternion {q.tolist()} is not a rotation")
    return q / n


def _clean(frame_id: str) -> str:
    return (frame_id or "").strip().lstrip("/")


class FrameTable:
    """The scene frame plus fixed transforms of other input frames into it, and optionally the robot's tf tree.

    ``to_scene(frame_id, p, q)`` returns the pose in the scene frame: through the fixed transform when the table has
    one for the frame, else through ``tf`` (a :class:`psprm_ros.interfaces.tf_tree.TfTree`, when given) when tf links
    the frame to the scene frame; otherwise it raises :class:`InputError` (the message names the frames it knows and,
    with tf, the missing link).
    """

    def __init__(self, scene_frame: str, transforms: Optional[Dict[str, tuple]] = None, tf=None):
        self.scene_frame = _clean(scene_frame)
        self.tf = tf
        self.transforms: Dict[str, tuple] = {}
        for name, (xyz, quat) in (transforms or {}).items():
            self.add(name, xyz, quat)

    def add(self, frame: str, xyz: Sequence[float], quat: Sequence[float]) -> None:
        f = _clean(frame)
        xyz = np.asarray(xyz, float).reshape(-1)
        quat = np.asarray(quat, float).reshape(-1)
        if not f:
            raise InputError("input frame: empty frame name")
        if xyz.shape != (3,) or quat.shape != (4,) or not (np.isfinite(xyz).all() and np.isfinite(quat).all()):
            raise InputError(f"input frame '{f}': xyz must be 3 finite numbers and quat 4 (x, y, z, w), "
                             f"got {xyz.tolist()} / {quat.tolist()}")
        if f == self.scene_frame:
            raise InputError(f"input frame '{f}' is the scene frame itself (it needs no transform)")
        self.transforms[f] = (xyz, _unit(quat))

    @property
    def known(self) -> list:
        return [self.scene_frame] + sorted(self.transforms)

    def knows(self, frame_id: str) -> bool:
        f = _clean(frame_id)
        return f == self.scene_frame or f in self.transforms or (
            self.tf is not None and self.tf.find(self.scene_frame, f)[0] is not None)

    def to_scene(self, frame_id: str, p, q, what: str = "pose") -> tuple:
        f = _clean(frame_id)
        if f == self.scene_frame:
            return np.asarray(p, float), np.asarray(q, float)
        if f in self.transforms:
            return compose_pose(self.transforms[f], (p, q))
        why = ""
        if self.tf is not None and f:
            found, why = self.tf.find(self.scene_frame, f)
            if found is not None:
                return compose_pose((found.xyz, found.quat), (p, q))
            why = f"; tf: {why}"
        raise InputError(f"{what}: frame '{frame_id}' is neither the scene frame '{self.scene_frame}' nor an "
                         f"input frame with a transform (known: {', '.join(self.known)}){why}")


#: parameter names (see the module docstring)
FRAMES_PARAM = "input_frames"


def declare_frame_params(node, scene_frame: str) -> FrameTable:
    """Declare ``input_frames`` and, for every name in it, ``input_frame.<name>.xyz`` / ``.quat``; returns the table.
    Raises ValueError naming the parameter when a transform is malformed."""
    from rcl_interfaces.msg import ParameterDescriptor

    desc = ParameterDescriptor(description="frames whose poses are mapped into the scene frame by a fixed transform "
                                           "(input_frame.<name>.xyz / .quat: that frame's pose in the scene frame)",
                               read_only=True, dynamic_typing=True)
    names = node.get_parameter(FRAMES_PARAM).value if node.has_parameter(FRAMES_PARAM) else \
        node.declare_parameter(FRAMES_PARAM, [""], desc).value
    names = [str(n) for n in (names or []) if str(n).strip()]
    table = FrameTable(scene_frame)
    for n in names:
        vals = []
        for key, default in (("xyz", [0.0, 0.0, 0.0]), ("quat", [0.0, 0.0, 0.0, 1.0])):
            pname = f"input_frame.{n}.{key}"
            if node.has_parameter(pname):
                v = node.get_parameter(pname).value
            else:
                v = node.declare_parameter(pname, default, ParameterDescriptor(
                    description=f"{key} of frame '{n}' in the scene frame", read_only=True, dynamic_typing=True)).value
            vals.append([float(x) for x in v])
        try:
            table.add(n, vals[0], vals[1])
        except (ValueError, InputError) as exc:
            raise InputError(f"parameter input_frame.{n}: {exc}") from None
    return table


def validated_pose_in(msg, table: FrameTable, now_sec: Optional[float] = None, max_age_s: float = 0.0,
                      what: str = "pose") -> tuple:
    """``geometry_msgs/PoseStamped`` -> (position, unit quaternion) in the scene frame: refuses non-finite values, a
    zero quaternion, stale stamps (as :func:`psprm_ros.interfaces.conversions.validated_pose`) and a frame the table
    does not know; a known input frame is transformed into the scene frame."""
    frame = (msg.header.frame_id or "").strip().lstrip("/")
    if not frame:
        raise InputError(f"{what}: empty frame_id (the scene frame is '{table.scene_frame}')")
    if not table.knows(frame):
        table.to_scene(frame, None, None, what)  # raises with the known frames
    p, q = validated_pose(msg, msg.header.frame_id, now_sec, max_age_s, what)
    return table.to_scene(frame, p, q, what)
