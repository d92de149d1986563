"""A client node for tests, the latency benchmark and the demo: publishes mocap poses and goals like a motion-capture
system and an operator would, and records everything the suite publishes (trajectories, plan info, statuses, scores)
with arrival times."""

from __future__ import annotations

import json
import threading
import time
from typing import Callable, Optional
from psprm_core.scene import load_scene


from .. import core
from ..interfaces import conversions as cv
from ..perception_scorer import PerceptionScorer
from ..replan_monitor import ReplanMonitor
from ..roadmap_server import RoadmapServer
from ..robot_adapter import RobotAdapter
from ..runner import start_lifecycles
from ..sim_robot import SimRobotNode
from ..spinning import NodeSpinner


_claimed: list = []  # open lock files: a claimed domain stays ours until this process ends


def claim_domain_id(lo: int = 1, hi: int = 200) -> int:
    """A ROS_DOMAIN_ID no other process of this machine that asks the same way is using: a random id whose lock file
    (``<tmp>/psprm-ros-domain-<id>.lock``, an exclusive non-blocking flock held until this process ends) could be
    taken. Test suites run side by side on one machine otherwise share a random domain now and then, and one suite's
    /odom or controller commands reach the other's nodes."""
    import fcntl
    import os
    import random
    import tempfile

    ids = list(range(lo, hi + 1))
    random.shuffle(ids)
    for i in ids:
        f = open(os.path.join(tempfile.gettempdir(), f"psprm-ros-domain-{i}.lock"), "a")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        _claimed.append(f)
        return i
    return random.randint(lo, hi)  # every id taken: fall back to chance


class Probe:
    def __init__(self, frame: str = "map", mocap_prefix: str = "/mocap", node_name: str = "psprm_probe",
                 **node_kwargs):
        from rclpy.node import Node
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from std_msgs.msg import Float32, String
        from trajectory_msgs.msg import JointTrajectory

        self.node = node = Node(node_name, **node_kwargs)
        self.frame, self.prefix = frame, mocap_prefix
        self.cond = threading.Condition()
        self.trajectories: list = []  # (t_arrival perf_counter, msg)
        self.infos: list = []  # (t, dict)
        self.statuses: list = []  # (t, node, text)
        self.path_scores: list = []
        self.server_state: list = []  # (t, text) from the latched /psprm/server_state
        self._pose_pubs: dict = {}
        self._sensor = qos_profile_sensor_data
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node.create_subscription(JointTrajectory, core.TRAJECTORY_TOPIC, self._rec(self.trajectories), latched)
        node.create_subscription(String, core.PLAN_INFO_TOPIC,
                                 self._rec(self.infos, lambda m: json.loads(m.data)), 50)
        node.create_subscription(Float32, core.PATH_SCORE_TOPIC, self._rec(self.path_scores, lambda m: m.data), 10)
        node.create_subscription(String, core.SERVER_STATE_TOPIC, self._rec(self.server_state, lambda m: m.data),
                                 latched)
        for n in ("roadmap_server", "perception_scorer", "replan_monitor", "robot_adapter", "sim_robot"):
            node.create_subscription(String, f"{n}/status", self._status_cb(n), 50)
        from geometry_msgs.msg import PoseStamped

        self.pub_goal = node.create_publisher(PoseStamped, "psprm/goal", 10)
        self.pub_regions = node.create_publisher(String, "psprm/goal_regions", 10)

    # ---------------------------------------------------------------------------------------------- recording
    def _rec(self, store: list, conv: Optional[Callable] = None):
        def cb(msg):
            t = time.perf_counter()
            with self.cond:
                store.append((t, conv(msg) if conv else msg))
                self.cond.notify_all()
        return cb

    def _status_cb(self, name: str):
        def cb(msg):
            with self.cond:
                self.statuses.append((time.perf_counter(), name, msg.data))
                self.cond.notify_all()
        return cb

    def wait_for(self, predicate: Callable[[], object], timeout: float = 30.0):
        """Wait until ``predicate()`` (called under the lock) returns something truthy; returns it (None on
        timeout)."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                r = predicate()
                if r:
                    return r
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self.cond.wait(min(left, 0.1))

    def wait_trajectory(self, after: int, timeout: float = 30.0):
        """The first trajectory message with index >= ``after`` (None on timeout)."""
        r = self.wait_for(lambda: len(self.trajectories) > after, timeout)
        return self.trajectories[after][1] if r else None

    def wait_ready(self, timeout: float = 600.0):
        """Wait for the server's latched state "ready: ..." (returns the text; None on timeout or error)."""
        def pred():
            for _, text in self.server_state:
                if text.startswith("ready") or text.startswith("error"):
                    return text
            return None
        r = self.wait_for(pred, timeout)
        return r if r and r.startswith("ready") else None

    def wait_status(self, needle: str, after_t: float = 0.0, timeout: float = 10.0, level: str = ""):
        def pred():
            for t, n, text in self.statuses:
                if t >= after_t and needle in text and (not level or text.startswith(level)):
                    return (n, text)
            return None
        return self.wait_for(pred, timeout)

    # ---------------------------------------------------------------------------------------------- publishing
    def pose_publisher(self, body: str, topic: Optional[str] = None):
        from geometry_msgs.msg import PoseStamped

        topic = topic or f"{self.prefix}/{body}/pose"
        if topic not in self._pose_pubs:
            self._pose_pubs[topic] = self.node.create_publisher(PoseStamped, topic, self._sensor)
        return self._pose_pubs[topic]

    def publish_pose(self, body: str, position, quat_xyzw, frame: Optional[str] = None, topic: Optional[str] = None,
                     stamp=None):
        stamp = stamp if stamp is not None else self.node.get_clock().now().to_msg()
        msg = cv.pose_stamped(position, quat_xyzw, self.frame if frame is None else frame, stamp)
        self.pose_publisher(body, topic).publish(msg)
        return time.perf_counter()

    def publish_goal(self, x: float, y: float, yaw: float, frame: Optional[str] = None):
        msg = cv.pose_stamped([x, y, 0.0], cv.yaw_quat(yaw), self.frame if frame is None else frame,
                              self.node.get_clock().now().to_msg())
        self.pub_goal.publish(msg)

    def publish_regions(self, names):
        from std_msgs.msg import String

        self.pub_regions.publish(String(data=",".join(names)))

    def wait_subscribers(self, topic: str, count: int = 1, timeout: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.node.count_subscribers(topic) >= count:
                return True
            time.sleep(0.05)
        return False

    def hold_robot_state(self, q, names, rate_hz: float = 20.0, odom_frame: str = "odom"):
        """Publish a standing robot's measured state from a thread: ``/joint_states`` (the non-base planning joints)
        and ``/odom`` (the base ``q[:3]``; frame ``odom_frame``) at ``rate_hz``. Returns the
        :class:`StatePublisher` (``.q`` may be changed, ``.stop()`` ends it)."""
        return StatePublisher(self.node, q, names, rate_hz, odom_frame).start()

    def destroy(self) -> None:
        self.node.destroy_node()


class StatePublisher:
    """What a robot standing at ``q`` publishes: /joint_states and /odom (see :meth:`Probe.hold_robot_state`)."""

    def __init__(self, node, q, names, rate_hz: float = 20.0, odom_frame: str = "odom"):
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import JointState

        self.node, self.names, self.rate, self.odom_frame = node, list(names), rate_hz, odom_frame
        self.q = list(map(float, q))
        self.twist = (0.0, 0.0)  # the odometry's (v, omega)
        self.mobile = self.names[:3] == ["base_x", "base_y", "base_theta"]
        self.pub_js = node.create_publisher(JointState, "joint_states", 10)
        self.pub_odom = node.create_publisher(Odometry, "odom", 10)
        self._stop = threading.Event()
        self.published = 0

    def start(self) -> "StatePublisher":
        self._thread = threading.Thread(target=self._run, daemon=True, name="state-publisher")
        self._thread.start()
        return self

    def publish_once(self) -> None:
        from nav_msgs.msg import Odometry

        stamp = self.node.get_clock().now().to_msg()
        q = list(self.q)
        k = 3 if self.mobile else 0
        self.pub_js.publish(cv.planning_joint_state(q[k:], self.names[k:], stamp))
        if self.mobile:
            od = Odometry()
            od.header.stamp = stamp
            od.header.frame_id = self.odom_frame
            od.child_frame_id = "base_link"
            cv.numpy_to_pose([q[0], q[1], 0.0], cv.yaw_quat(q[2]), od.pose.pose)
            od.twist.twist.linear.x, od.twist.twist.angular.z = (float(x) for x in self.twist)
            self.pub_odom.publish(od)
        self.published += 1

    def _run(self) -> None:
        while not self._stop.wait(1.0 / self.rate):
            try:
                self.publish_once()
            except Exception:  # context shutting down
                return

    def stop(self) -> None:
        self._stop.set()
        if getattr(self, "_thread", None):
            self._thread.join(2.0)


def scene_frame(scene_name: str) -> str:
    """The frame a scene's poses are in (the nodes load the scene at configure; the probe needs its frame first)."""
    return load_scene(core.resolve_scene(scene_name)).frame


class InProcessSuite:
    """The three nodes (or any subset) plus a :class:`Probe` in one rclpy context, each node on its own
    single-threaded executor (:class:`~psprm_ros.spinning.NodeSpinner`): ``with InProcessSuite(params) as s:
    s.probe.publish_pose(...)``."""

    def __init__(self, params: dict, domain_id: Optional[int] = None, nodes=("server", "scorer", "monitor"),
                 params_file: Optional[str] = None, autostart: bool = True, namespace: str = ""):
        self.params, self.domain_id, self.which = params, domain_id, nodes
        self.params_file, self.autostart, self.namespace = params_file, autostart, namespace

    def __enter__(self) -> "InProcessSuite":
        import rclpy
        from rclpy.parameter import Parameter

        self.context = rclpy.Context()
        args = ["--ros-args", "--params-file", self.params_file] if self.params_file else None
        self.context.init(args=args, domain_id=self.domain_id)
        overrides = [Parameter(k, value=v) for k, v in self.params.items()]
        kw = {"context": self.context, "parameter_overrides": overrides}
        if self.namespace:
            kw["namespace"] = self.namespace

        self.executor = NodeSpinner(self.context)
        self.nodes = []

        make = {"server": RoadmapServer, "scorer": PerceptionScorer, "monitor": ReplanMonitor,
                "adapter": RobotAdapter, "sim": SimRobotNode}
        self.server = self.scorer = self.monitor = self.adapter = self.sim = None
        try:
            for w in self.which:
                n = make[w](**kw)
                setattr(self, w, n)
                self.nodes.append(n)
                self.executor.add(n.node)
            frame = scene_frame(self.server.p["scene"]) if self.server else "map"
            self.probe = Probe(frame=frame, context=self.context,
                               **({"namespace": self.namespace} if self.namespace else {}))
            self.executor.add(self.probe.node)
        except Exception:
            self.__exit__(None, None, None)
            raise
        self.executor.start()
        if self.autostart:
            start_lifecycles(self.nodes)
        return self

    def __exit__(self, *exc) -> None:
        # stop spinning before destroying: a callback still running on the spin thread would otherwise hit a node
        # being destroyed ("cannot use Destroyable because destruction was requested", printed at exit)
        if getattr(self, "executor", None):
            self.executor.shutdown(timeout_sec=2.0)
        for n in reversed(getattr(self, "nodes", [])):
            try:
                n.destroy()
            except Exception:
                pass
        if getattr(self, "probe", None):
            self.probe.destroy()
        self.context.try_shutdown()
