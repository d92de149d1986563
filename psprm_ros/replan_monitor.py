"""``replan_monitor``: the input gate and supervisor of the node suite.

Subscribes to the mocap rigid bodies (geometry_msgs/PoseStamped, one topic per target/obstacle named in its
parameters, sensor-data QoS: best effort, keep last 1), to ``/joint_states`` (+ the robot's own mocap pose for the
base), and to the goal (``/psprm/goal`` PoseStamped base pose, or ``/psprm/goal_regions`` std_msgs/String with goal
region names of the scene). Every message is checked (finite, scene frame, age); good ones are forwarded to the
server and the scorer on ``/psprm/state/...``, bad ones produce a warning on ``~/status`` and are dropped.

Triggers applied here (the geometric triggers of the core ReplanSettings run inside the server on every forwarded
state): a new goal, a predicted path score (``/psprm/path/score`` from the perception scorer) below
``min_path_score_ratio`` x its value at plan time, the robot deviating from the trajectory by more than
``deviation_tolerance`` m, a periodic replan (``replan_period_s``), and stale inputs: an obstacle silent for
``stale_timeout_s`` makes the server stop (``~/stop``), a silent target only warns (the last plan stays safe).
It reports a JSON summary on ``~/status`` once per second (plans, stops, latencies, stale bodies).
"""

from __future__ import annotations

import json
import threading
import time
from typing import Optional

import numpy as np

from . import conversions as cv
from . import core

MONITOR_PARAMS = {
    "mocap_prefix": "/mocap",  # default topic of a rigid body: <prefix>/<name>/pose
    "target_topics": [],  # one per target (same order); [] = defaults from mocap_prefix
    "obstacle_topics": [],  # one per dynamic obstacle (same order)
    "robot_pose_topic": "",  # the robot's own rigid body (base x, y, yaw); "" = base from /joint_states or fixed
    "joint_states_topic": "/joint_states",
    "goal_topic": "/psprm/goal",
    "goal_regions_topic": "/psprm/goal_regions",
    "max_pose_age_s": 1.0,
    # forwarding of the mocap stream: a pose that moved more than the deadband since the last forwarded one goes out
    # at once; otherwise at most relay_keepalive_hz (keeps the downstream nodes' CPU for planning; the core's move
    # thresholds are 3-5 cm / 0.1-0.15 rad, so nothing that matters is held back). 0 / 0 = forward everything.
    "relay_deadband_m": 0.01,
    "relay_deadband_rad": 0.02,
    "relay_keepalive_hz": 10.0,
    "stale_timeout_s": 0.5,
    "stop_on_stale_obstacle": True,
    "check_rate_hz": 10.0,
    "min_path_score_ratio": 0.5,
    "deviation_tolerance": 0.3,
    "replan_period_s": 0.0,
    "min_request_interval_s": 1.0,
    "start_problem": "",
}


class ReplanMonitor:
    def __init__(self, node_name: str = "replan_monitor", **node_kwargs):
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from rclpy.node import Node
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float32, String
        from std_srvs.srv import Trigger
        from trajectory_msgs.msg import JointTrajectory

        from psprm_core.collision import CollisionChecker

        self.node = node = Node(node_name, **node_kwargs)
        self.log = node.get_logger()
        self.p = core.declare_params(node, {**core.COMMON_PARAMS, **MONITOR_PARAMS})
        self.scene, self.robot = core.load_scene_and_robot(self.p["scene"], self.p["robot"])
        self.frame = self.scene.frame
        self.targets = core.scene_targets(self.scene, self.p["targets"])
        self.obstacles = list(self.p["dynamic_obstacles"])
        for o in self.obstacles:
            self.scene.obstacle(o)
        self.names = list(self.robot.joint_names)
        self.checker = CollisionChecker(self.robot, self.scene.collision_boxes(), workspace=self.scene.workspace)
        self.q = core.start_configuration(self.robot, self.scene, self.p["start_problem"])
        self.base: Optional[np.ndarray] = None
        self._lock = threading.Lock()
        self.last_seen: dict = {}  # body -> monotonic time of the last good pose
        self.stale: set = set()
        self.counts = {"forwarded": 0, "refused": 0, "plans": 0, "stops": 0, "failed": 0, "requests": 0}
        self.latencies: list = []
        self.plan_score: Optional[float] = None
        self.path_score: Optional[float] = None
        self.traj: Optional[dict] = None
        self.last_plan_t = time.monotonic()
        self.last_request_t = 0.0
        self.last_warning = ""

        sensor = qos_profile_sensor_data
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_status = node.create_publisher(String, "~/status", 10)
        self.pub_goals = node.create_publisher(JointTrajectory, core.GOALS_TOPIC, latched)
        self.pub_robot = node.create_publisher(JointState, core.ROBOT_STATE_TOPIC, sensor)
        self.relay = {}
        self._last_fwd: dict = {}  # (kind, name) -> (monotonic t, p, q) of the last forwarded pose
        cb = MutuallyExclusiveCallbackGroup()
        pairs = self._topics("target", self.targets, self.p["target_topics"]) + \
            self._topics("obstacle", self.obstacles, self.p["obstacle_topics"])
        for kind, name, topic in pairs:
            out = core.target_topic(name) if kind == "target" else core.obstacle_topic(name)
            self.relay[(kind, name)] = node.create_publisher(PoseStamped, out, sensor)
            node.create_subscription(PoseStamped, topic, self._pose_cb(kind, name), sensor, callback_group=cb)
        self.topics = {f"{k}:{n}": t for k, n, t in pairs}
        if self.p["robot_pose_topic"]:
            node.create_subscription(PoseStamped, self.p["robot_pose_topic"], self._base_cb, sensor, callback_group=cb)
        node.create_subscription(JointState, self.p["joint_states_topic"], self._joints_cb, sensor, callback_group=cb)
        node.create_subscription(PoseStamped, self.p["goal_topic"], self._goal_cb, 10, callback_group=cb)
        node.create_subscription(String, self.p["goal_regions_topic"], self._regions_cb, 10, callback_group=cb)
        node.create_subscription(String, core.PLAN_INFO_TOPIC, self._info_cb, 10, callback_group=cb)
        node.create_subscription(Float32, core.PATH_SCORE_TOPIC, self._score_cb, 10, callback_group=cb)
        node.create_subscription(JointTrajectory, core.TRAJECTORY_TOPIC, self._traj_cb, latched, callback_group=cb)
        srv_cb = MutuallyExclusiveCallbackGroup()
        self.cli_plan = node.create_client(Trigger, f"/{core.SERVER_NAME}/plan", callback_group=srv_cb)
        self.cli_stop = node.create_client(Trigger, f"/{core.SERVER_NAME}/stop", callback_group=srv_cb)
        node.create_timer(1.0 / max(0.5, self.p["check_rate_hz"]), self._check,
                          callback_group=MutuallyExclusiveCallbackGroup())
        node.create_timer(1.0, self._report, callback_group=MutuallyExclusiveCallbackGroup())

    def _topics(self, kind, names, topics) -> list:
        if topics and len(topics) != len(names):
            raise ValueError(f"{kind}_topics has {len(topics)} entries for {len(names)} {kind}s")
        return [(kind, n, topics[i] if topics else f"{self.p['mocap_prefix']}/{n}/pose") for i, n in enumerate(names)]

    # ------------------------------------------------------------------------------------------------ reporting
    def status(self, text: str, level: str = "info") -> None:
        if level == "warning":
            self.last_warning = text
        core.report(self.log, self.pub_status, text, level)

    def summary(self) -> dict:
        with self._lock:
            lat = np.array(self.latencies[-200:], float)
            return {**self.counts, "stale": sorted(self.stale), "plan_score": self.plan_score,
                    "path_score": self.path_score,
                    "latency_ms_median": float(np.median(lat)) if len(lat) else None,
                    "last_warning": self.last_warning}

    def _report(self) -> None:
        from std_msgs.msg import String

        self.pub_status.publish(String(data="summary: " + json.dumps(self.summary())))

    # ------------------------------------------------------------------------------------------------ inputs
    def _now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9

    def _pose_cb(self, kind: str, name: str):
        def cb(msg):
            try:
                p, q = cv.validated_pose(msg, self.frame, self._now(), self.p["max_pose_age_s"], f"{kind} {name}")
            except Exception as exc:
                with self._lock:
                    self.counts["refused"] += 1
                self.status(f"ignored {exc}", "warning")
                return
            now = time.monotonic()
            with self._lock:
                self.last_seen[(kind, name)] = now
                if not self._should_forward((kind, name), now, p, q):
                    return
                self._last_fwd[(kind, name)] = (now, p, q)
                self.counts["forwarded"] += 1
                if kind == "obstacle":
                    self.scene = self.scene.with_obstacle_pose(name, p, q)
                else:
                    self.scene = self.scene.with_target_pose(name, p, q)
            out = cv.pose_stamped(p, q, self.frame, msg.header.stamp)
            self.relay[(kind, name)].publish(out)
        return cb

    def _should_forward(self, key, now: float, p: np.ndarray, q: np.ndarray) -> bool:
        last = self._last_fwd.get(key)
        if last is None:
            return True
        t, lp, lq = last
        dm, dr = self.p["relay_deadband_m"], self.p["relay_deadband_rad"]
        if dm <= 0 and dr <= 0:
            return True
        if np.linalg.norm(p - lp) > dm or 2.0 * np.arccos(min(1.0, abs(float(np.dot(q, lq))))) > dr:
            return True
        hz = self.p["relay_keepalive_hz"]
        return hz > 0 and now - t >= 1.0 / hz

    def _base_cb(self, msg) -> None:
        try:
            p, q = cv.validated_pose(msg, self.frame, self._now(), self.p["max_pose_age_s"], "robot pose")
        except Exception as exc:
            self.status(f"ignored {exc}", "warning")
            return
        with self._lock:
            self.base = np.array([p[0], p[1], cv.yaw_of(q)])
            self.last_seen[("robot", "base")] = time.monotonic()

    def _joints_cb(self, msg) -> None:
        try:
            with self._lock:
                base = self.base
            q, found = cv.joint_state_to_planning(msg, self.robot, base=base, template=self.q)
            if self.robot.mobile and base is None and not {"base_x", "base_y", "base_theta"} <= set(found):
                pass  # base stays at the start configuration until a base pose arrives
        except Exception as exc:
            self.status(f"ignored {exc}", "warning")
            return
        with self._lock:
            self.q = q
        self.pub_robot.publish(cv.planning_joint_state(q, self.names, msg.header.stamp))
        self._check_deviation(q)

    def _goal_cb(self, msg) -> None:
        try:
            p, q = cv.validated_pose(msg, self.frame, None, 0.0, "goal")
            if not self.robot.mobile:
                raise cv.InputError("goal poses need a mobile base; use goal regions")
            vals = {"base_x": p[0], "base_y": p[1], "base_theta": cv.yaw_of(q)}
            G = self.robot.configuration(vals)[None]
            self._send_goals(G, f"goal ({p[0]:.2f}, {p[1]:.2f}, yaw {vals['base_theta']:.2f})")
        except Exception as exc:
            self.status(f"ignored {exc}", "warning")

    def _regions_cb(self, msg) -> None:
        try:
            names = [n.strip() for n in msg.data.split(",") if n.strip()]
            if not names:
                raise cv.InputError("goal regions: empty")
            try:
                G = core.goal_region_configurations(self.robot, self.scene, names)
            except KeyError as exc:
                raise cv.InputError(f"goal regions: {exc}") from None
            self._send_goals(G, f"goal regions {', '.join(names)}")
        except Exception as exc:
            self.status(f"ignored {exc}", "warning")

    def _send_goals(self, G: np.ndarray, what: str) -> None:
        import torch

        ws = self.scene.workspace
        if self.robot.mobile and not ((G[:, 0] >= ws[0, 0]) & (G[:, 0] <= ws[0, 1]) & (G[:, 1] >= ws[1, 0]) &
                                      (G[:, 1] <= ws[1, 1])).any():
            raise cv.InputError(f"{what}: outside the workspace {ws.tolist()}")
        with self._lock:
            self.checker.set_boxes(self.scene.collision_boxes())
            bad = self.checker.check(torch.as_tensor(G, dtype=torch.float32)).numpy()
        if bad.all():
            raise cv.InputError(f"{what}: in collision; keeping the current plan")
        G = G[~bad]
        self.pub_goals.publish(cv.configs_to_joint_trajectory(G, self.names, self.frame,
                                                              self.node.get_clock().now().to_msg()))
        self.status(f"forwarded {what} ({len(G)} candidate(s))")

    # ------------------------------------------------------------------------------------------------ server outputs
    def _info_cb(self, msg) -> None:
        try:
            info = json.loads(msg.data)
        except ValueError:
            return
        with self._lock:
            if info.get("stop"):
                self.counts["stops"] += 1
            elif info.get("success"):
                self.counts["plans"] += 1
                self.plan_score = info.get("mean_score")
                self.path_score = None
                self.last_plan_t = time.monotonic()
                if info.get("latency_ms") is not None:
                    self.latencies.append(float(info["latency_ms"]))
            else:
                self.counts["failed"] += 1

    def _score_cb(self, msg) -> None:
        with self._lock:
            self.path_score = float(msg.data)

    def _traj_cb(self, msg) -> None:
        try:
            P = cv.joint_trajectory_positions(msg, self.names)
            t = np.array([cv.duration_to_sec(p.time_from_start) for p in msg.points])
        except Exception as exc:
            self.status(f"ignored trajectory: {exc}", "warning")
            return
        with self._lock:
            self.traj = {"P": P, "t": t, "t0": time.monotonic()} if len(P) > 1 else None

    # ------------------------------------------------------------------------------------------------ triggers
    def _check_deviation(self, q: np.ndarray) -> None:
        with self._lock:
            tr = self.traj
        if tr is None or not self.robot.mobile:
            return
        el = min(time.monotonic() - tr["t0"], tr["t"][-1])
        expect = np.array([np.interp(el, tr["t"], tr["P"][:, j]) for j in (0, 1)])
        dev = float(np.linalg.norm(q[:2] - expect))
        if dev > self.p["deviation_tolerance"]:
            self._request("plan", f"robot {dev:.2f} m off the trajectory")

    def _check(self) -> None:
        now = time.monotonic()
        with self._lock:
            seen = dict(self.last_seen)
            plan_score, path_score = self.plan_score, self.path_score
        newly = []
        for key, t in seen.items():
            label = f"{key[0]} {key[1]}"
            if now - t > self.p["stale_timeout_s"]:
                if label not in self.stale:
                    self.stale.add(label)
                    newly.append(key)
            elif label in self.stale:
                self.stale.discard(label)
                self.status(f"{label} is live again")
                if key[0] == "obstacle" and self.p["stop_on_stale_obstacle"]:
                    self._request("plan", f"{label} live again", force=True)
        for kind, name in newly:
            if kind == "obstacle" and self.p["stop_on_stale_obstacle"]:
                self.status(f"obstacle {name} stale (no pose for {self.p['stale_timeout_s']:.1f} s): stopping",
                            "warning")
                self._request("stop", f"obstacle {name} stale", force=True)
            else:
                self.status(f"{kind} {name} stale (no pose for {self.p['stale_timeout_s']:.1f} s): "
                            "keeping the last plan", "warning")
        settled = now - self.last_plan_t > self.p["min_request_interval_s"]  # the scorer has seen the new path
        if settled and plan_score and path_score is not None and \
                path_score < self.p["min_path_score_ratio"] * plan_score:
            self._request("plan", f"predicted path score {path_score:.3f} < "
                                  f"{self.p['min_path_score_ratio']:.2f} x {plan_score:.3f}")
        if self.p["replan_period_s"] > 0 and now - self.last_plan_t > self.p["replan_period_s"]:
            self._request("plan", "periodic replan")

    def _request(self, kind: str, why: str, force: bool = False) -> None:
        from std_srvs.srv import Trigger

        now = time.monotonic()
        if not force and now - self.last_request_t < self.p["min_request_interval_s"]:
            return
        cli = self.cli_plan if kind == "plan" else self.cli_stop
        if not cli.service_is_ready():
            self.status(f"cannot request {kind} ({why}): server not available", "warning")
            return
        self.last_request_t = now
        with self._lock:
            self.counts["requests"] += 1
            if kind == "plan":
                self.path_score = None
                self.last_plan_t = now
        self.status(f"requesting {kind}: {why}")
        fut = cli.call_async(Trigger.Request())
        fut.add_done_callback(lambda f: self._done(kind, f))

    def _done(self, kind, fut) -> None:
        try:
            r = fut.result()
            if not r.success:
                self.status(f"{kind} request failed: {r.message}", "warning")
        except Exception as exc:
            self.status(f"{kind} request error: {exc}", "warning")

    def destroy(self) -> None:
        self.node.destroy_node()


def main(args=None) -> int:
    from .runner import run_nodes

    return run_nodes([ReplanMonitor], args, description=__doc__, prog="replan_monitor")


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
