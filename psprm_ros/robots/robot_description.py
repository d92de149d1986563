"""The robot's own description: a node's robot model from the URDF the robot publishes, or from the packaged one.

A real robot is calibrated per unit and publishes its URDF on ``robot_description`` (std_msgs/String, transient
local, reliable: robot_state_publisher). The node parameters (declared with :func:`psprm_ros.core.common_params`):

* ``robot_description``: ``package`` (default: the URDF the robot config names), ``topic`` (wait for the robot's
  URDF at start-up; none within the timeout is an error) or ``auto`` (the topic's URDF when one arrives within the
  timeout, else the packaged one, with a logged info);
* ``robot_description_topic``: ``robot_description`` (relative: a namespace moves it);
* ``robot_description_timeout_s``: the longest wait (10 s).

The URDF text is checked against the robot config and built into the same :class:`~psprm_core.robot.RobotModel`
(:meth:`~psprm_core.robot.RobotModel.from_description`). When that fails (no description, one that does not match
the config), a lifecycle node is still built, around the packaged model, but refuses every configure with the
reason (``~/status`` "error: configure failed: ..."), so it never activates; a plain node gets the
:class:`~psprm_core.errors.RobotModelError` (the process entry reports it in one line).

Nothing here runs at import time; rclpy is imported inside the functions.
"""

from __future__ import annotations

import threading
import time
from typing import Optional

from psprm_core.errors import PsprmError, RobotModelError
from psprm_core.robot import RobotModel

MODES = ("package", "topic", "auto")
DEFAULT_TOPIC = "robot_description"


def description_qos():
    """The QoS robot_state_publisher publishes ``robot_description`` with: depth 1, reliable, transient local (a late
    subscriber gets the last description)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def wait_for_robot_description(node, topic: str = DEFAULT_TOPIC, timeout_s: float = 10.0) -> Optional[str]:
    """The URDF text on ``topic`` (resolved by ``node``: its namespace and remappings), or None when none arrives
    within ``timeout_s``.

    The subscription (:func:`description_qos`) lives on a private helper node in ``node``'s context, spun by a
    private single-threaded executor on the calling thread until the message arrives: ``node`` itself and the
    executor it may be spinning in are not touched, so this works in a node's constructor and in its callbacks
    alike. A description published before the call is received (transient local)."""
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.node import Node
    from std_msgs.msg import String

    name = node.resolve_topic_name(topic)
    got: list = []
    arrived = threading.Event()

    def cb(msg) -> None:
        got.append(msg.data)
        arrived.set()

    helper = Node(f"{node.get_name()}_robot_description", namespace=node.get_namespace(), context=node.context,
                  use_global_arguments=False, start_parameter_services=False, enable_rosout=False)
    executor = SingleThreadedExecutor(context=node.context)
    try:
        helper.create_subscription(String, name, cb, description_qos())
        executor.add_node(helper)
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        while not arrived.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                break
            executor.spin_once(timeout_sec=min(left, 0.1))
    except ExternalShutdownException:  # the context is shutting down
        pass
    finally:
        executor.shutdown(timeout_sec=1.0)
        helper.destroy_node()
    return got[-1] if got else None


def robot_from_params(node, p: dict, scene):
    """The robot model of the node's robot (``p["robot"]``, or ``scene``'s robot) from the URDF its
    ``robot_description`` parameters name (``p``: the node's declared parameter values; module docstring).

    A description that cannot be used (none within the timeout with ``topic``, or one that does not match the robot
    config) makes a lifecycle node refuse to configure (the packaged model is returned, to build the node around)
    and raises :class:`~psprm_core.errors.RobotModelError` for any other node."""
    name = p.get("robot") or scene.robot
    mode = str(p.get("robot_description", "package") or "package").strip().lower()
    log = node.get_logger()
    if mode == "package":
        return RobotModel.load(name)
    if mode not in MODES:
        return _refuse(node, name, f"parameter robot_description: '{mode}' is not one of {', '.join(MODES)}")
    topic = str(p.get("robot_description_topic") or DEFAULT_TOPIC)
    timeout_s = float(p.get("robot_description_timeout_s", 10.0))
    resolved = node.resolve_topic_name(topic)
    text = wait_for_robot_description(node, topic, timeout_s)
    if text is None:
        if mode == "auto":
            log.info(f"no robot description on {resolved} within {timeout_s:g} s: robot '{name}' from its packaged "
                     f"URDF")
            return RobotModel.load(name)
        return _refuse(node, name, f"no robot description on {resolved} within {timeout_s:g} s "
                                   f"(robot_description: topic)")
    try:
        robot = RobotModel.load(name, urdf_text=text, origin=f"the robot description on {resolved}")
    except PsprmError as exc:
        return _refuse(node, name, str(exc))
    log.info(f"robot '{name}' built from the robot description on {resolved} ({len(text)} characters, "
             f"{robot.urdf.path.name})")
    return robot


def _refuse(node, name: str, reason: str):
    """A lifecycle node refuses to configure with ``reason`` and is built around the packaged model; another node
    raises it."""
    refuse = getattr(node, "refuse_configure", None)
    if refuse is None:
        raise RobotModelError(reason)
    node.get_logger().error(f"{reason}; the node will not configure")
    refuse(reason)
    return RobotModel.load(name)
