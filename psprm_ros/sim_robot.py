"""``sim_robot``: a kinematic simulation of a robot config behind the interfaces a real robot offers.

    sim_robot --ros-args -p scene:=dynamic_person -p adapter:=stretch2 [-p start_problem:=south_to_either]
              [-p mocap_topic:=/mocap/robot/pose]

Subscribes to what the robot's controllers take, from its adapter config (``config/ros/adapters/<robot>.yaml``): one
``trajectory_msgs/JointTrajectory`` topic per controller (joint_trajectory_controller rules, :mod:`.robots.sim_model`)
and the base's cmd_vel (``Twist`` or ``TwistStamped`` per the adapter; zero after ``cmd_vel_timeout_s`` without a
command), integrated within the robot config's limits. Publishes ``/joint_states`` (the robot's own joint names,
plus the URDF joints they drive), ``/odom`` (frame ``odom``), with ``mocap_topic`` a motion-capture
``PoseStamped`` of a body on its base (frame ``mocap_frame``), and its URDF on ``robot_description`` (transient
local), as robot_state_publisher does. A ``Twist`` on ``~/disturbance`` (body frame, sideways too) is added to the
base's motion for ``disturbance_timeout_s`` after each message: a push or wheel slip. It never reads psprm's own
topics. Refused commands are counted and reported on ``~/status``.
"""

from __future__ import annotations

import threading
from typing import Optional

import numpy as np

from . import core
from .interfaces import conversions as cv
from .interfaces.frames import compose_pose, invert_pose
from .robots.adapters import ControllerConfig, import_follow_joint_trajectory, load_adapter
from .robots.robot_description import description_qos
from .robots.sim_model import SimModel
from .robots.sim_stretch import BASE_JOINT, StretchDriver
from .runner import run_nodes

SIM_PARAMS = {
    "adapter": "",  # adapter config name or path ("" = the robot's name)
    "start_problem": "",  # scene problem whose start is the initial configuration ("" = the first one)
    "initial_base": [0.0],  # (x, y, theta) overriding the problem's start base (one value = unset)
    "rate_hz": 50.0,
    "cmd_vel_timeout_s": 0.5,
    "disturbance_topic": "~/disturbance",  # geometry_msgs/Twist added to the base's motion (a push, wheel slip)
    "disturbance_timeout_s": 0.2,  # ... for this long after each message
    "joint_states_topic": "joint_states",
    "odom_topic": "odom",
    "odom_frame": "odom",
    "base_frame": "base_link",
    "odom_origin.xyz": [0.0, 0.0, 0.0],  # pose of the odom frame in the scene frame
    "odom_origin.quat": [0.0, 0.0, 0.0, 1.0],
    "mocap_topic": "",  # "" = no mocap pose of the base
    "mocap_frame": "world",
    "mocap_rate_hz": 100.0,
    "mocap_world.xyz": [0.0, 0.0, 0.0],  # pose of the mocap frame in the scene frame
    "mocap_world.quat": [0.0, 0.0, 0.0, 1.0],
    "mocap_body_offset.xyz": [0.0, 0.0, 0.0],  # pose of base_link in the mocap body's frame
    "mocap_body_offset.quat": [0.0, 0.0, 0.0, 1.0],
    "driver": "",  # "" = ros2_control JointTrajectory topics; "stretch" = Stretch 2's driver (robots.sim_stretch)
    "driver_mode": "position",  # the Stretch driver's mode at start-up (its own default: position)
    "runstop_service": "/runstop",  # std_srvs/SetBool of the Stretch driver
    "status_rate_hz": 10.0,  # /mode and /is_runstopped of the Stretch driver
    "speed_scaling": 100.0,  # percent: scaled controllers (speed_scaling_topic) run at this rate, published there
    "interface": "topic",  # the controllers as JointTrajectory topics, or as FollowJointTrajectory actions ("action")
    "path_tolerance": 0.2,  # action goals: a joint this far (rad or m) from its trajectory aborts the goal
    "goal_tolerance": 0.05,  # ... and this far from the last point when the trajectory ends
    "joint_disturbance_topic": "~/joint_disturbance",  # sensor_msgs/JointState: offsets added to joints (a push)
    "robot_description_topic": "robot_description",  # the robot model's URDF, latched ("" = none)
}


class SimRobotNode:
    def __init__(self, node_name: str = "sim_robot", **node_kwargs):
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from rclpy.node import Node
        from rclpy.qos import qos_profile_sensor_data
        from geometry_msgs.msg import PoseStamped, Twist, TwistStamped
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String
        from trajectory_msgs.msg import JointTrajectory

        self.node = node = Node(node_name, **node_kwargs)
        self.log = node.get_logger()
        self.p = core.declare_params(node, {**core.COMMON_PARAMS, **SIM_PARAMS})
        self.scene, self.robot = core.load_scene_and_robot(self.p["scene"], self.p["robot"])
        adapter = load_adapter(self.p["adapter"] or self.robot.name, self.robot)
        self.driver = None
        if self.p["driver"] not in ("", "stretch"):
            raise ValueError(f"driver must be '' or 'stretch', got '{self.p['driver']}'")
        if self.p["interface"] not in ("topic", "action"):
            raise ValueError(f"interface must be 'topic' or 'action', got '{self.p['interface']}'")
        self.adapter = adapter if self.p["driver"] == "stretch" else adapter.with_interface(self.p["interface"])
        q0 = core.start_configuration(self.robot, self.scene, self.p["start_problem"])
        if len(self.p["initial_base"]) == 3:
            q0[:3] = self.p["initial_base"]
        self.model = SimModel(self.robot, self.adapter, q0, self.p["cmd_vel_timeout_s"])
        self._lock = threading.Lock()
        self.odom_origin = (np.array(self.p["odom_origin.xyz"], float), _unit(self.p["odom_origin.quat"]))
        self.mocap_world = (np.array(self.p["mocap_world.xyz"], float), _unit(self.p["mocap_world.quat"]))
        self.mocap_offset = (np.array(self.p["mocap_body_offset.xyz"], float),
                             _unit(self.p["mocap_body_offset.quat"]))
        cb = MutuallyExclusiveCallbackGroup()
        self._goal_futures: dict = {}
        if self.p["driver"] == "stretch":
            self.driver = StretchDriver(self.model, self.p["driver_mode"])
            self._stretch_interfaces(cb)
        elif self.p["interface"] == "action":
            self._jtc_actions()
        else:
            for c in self.adapter.controllers:
                node.create_subscription(JointTrajectory, c.topic, self._traj_cb(c), 10, callback_group=cb)
        node.create_subscription(JointState, self.p["joint_disturbance_topic"], self._joint_disturbance_cb, 10,
                                 callback_group=cb)
        b = self.adapter.base
        if self.robot.mobile and b.mode == "cmd_vel" and self.driver is None:
            node.create_subscription(TwistStamped if b.stamped else Twist, b.topic, self._twist_cb(b.stamped), 10,
                                     callback_group=cb)
            node.create_subscription(Twist, self.p["disturbance_topic"], self._disturbance_cb, 10, callback_group=cb)
        self.pub_js = node.create_publisher(JointState, self.p["joint_states_topic"], 10)
        self.pub_odom = node.create_publisher(Odometry, self.p["odom_topic"], 10)
        self.pub_status = node.create_publisher(String, "~/status", 10)
        self.pub_description = None
        if self.p["robot_description_topic"]:
            self.pub_description = node.create_publisher(String, self.p["robot_description_topic"], description_qos())
            self.pub_description.publish(String(data=self.robot.urdf.path.read_text()))
        self.pub_mocap = None
        if self.p["mocap_topic"]:
            self.pub_mocap = node.create_publisher(PoseStamped, self.p["mocap_topic"], qos_profile_sensor_data)
            node.create_timer(1.0 / max(1.0, self.p["mocap_rate_hz"]), self._mocap,
                              callback_group=MutuallyExclusiveCallbackGroup())
        self._last_t: Optional[float] = None
        self.model.speed_scaling = min(max(self.p["speed_scaling"], 0.0), 100.0) / 100.0
        self.pub_scaling = []
        for topic in sorted({c.speed_scaling_topic for c in self.adapter.controllers if c.speed_scaling_topic}):
            from std_msgs.msg import Float64

            self.pub_scaling.append(node.create_publisher(Float64, topic, 10))
        node.create_timer(1.0 / max(1.0, self.p["rate_hz"]), self._step, callback_group=cb)

    def _now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9

    def status(self, text: str, level: str = "info") -> None:
        core.report(self.log, self.pub_status, text, level)

    # ------------------------------------------------------------------------------------------------ JTC actions
    def _jtc_actions(self) -> None:
        """FollowJointTrajectory servers as ros2_control's joint_trajectory_controller offers them: a goal whose
        joint set or times break the topic rules is rejected; an accepted goal replaces the one under way (which
        ends canceled); a joint further than ``path_tolerance`` from its trajectory aborts the goal with
        PATH_TOLERANCE_VIOLATED (the controller then holds where the robot is), one further than
        ``goal_tolerance`` from the last point when the trajectory ends with GOAL_TOLERANCE_VIOLATED; a cancel
        holds."""
        from rclpy.action import ActionServer
        from rclpy.callback_groups import ReentrantCallbackGroup

        fjt = import_follow_joint_trajectory()
        if fjt is None:
            raise RuntimeError("interface action needs control_msgs (scripts/build_interfaces.sh)")
        self._fjt = fjt
        self._jtc_goals: dict = {}  # controller -> [goal id, outcome or None]
        self._jtc_next = 0
        self._action_servers = []
        for c in self.adapter.controllers:
            self._action_servers.append(ActionServer(
                self.node, fjt, c.action, execute_callback=self._jtc_execute(c),
                goal_callback=self._jtc_goal_request(c), cancel_callback=lambda gh: _accept_cancel(),
                callback_group=ReentrantCallbackGroup()))

    def _jtc_goal_request(self, ctrl):
        from rclpy.action import GoalResponse

        def cb(request):
            names = list(request.trajectory.joint_names)
            own = ctrl.robot_joints
            ok = len(set(names)) == len(names) and set(names) == set(own) and len(request.trajectory.points) > 0
            if not ok:
                self.status(f"{ctrl.name}: goal rejected: joint set {names} is not {own}", "warning")
            return GoalResponse.ACCEPT if ok else GoalResponse.REJECT
        return cb

    def _jtc_execute(self, ctrl):
        from rclpy.task import Future

        async def execute(goal_handle):
            tr = goal_handle.request.trajectory
            pts = [(cv.duration_to_sec(p.time_from_start), list(p.positions)) for p in tr.points]
            res = self._fjt.Result()
            with self._lock:
                ok, why = self.model.accept_trajectory(ctrl, tr.joint_names, cv.stamp_to_sec(tr.header.stamp), pts,
                                                       self._now())
                self._jtc_next += 1
                rec = [self._jtc_next, None if ok else ("aborted", -1, why)]
                prev = self._jtc_goals.get(ctrl.name)
                if ok and prev is not None and prev[1] is None:
                    prev[1] = ("canceled", 0, "replaced by a newer goal")
                if ok:
                    self._jtc_goals[ctrl.name] = rec
                fut = Future()
                rec += [fut, goal_handle]
            if rec[1] is None:
                await fut
            state, code, text = rec[1]
            res.error_code, res.error_string = int(code), text
            if state == "succeeded":
                goal_handle.succeed()
            elif state == "canceled":
                goal_handle.canceled() if goal_handle.is_cancel_requested else goal_handle.abort()
            else:
                goal_handle.abort()
            return res
        return execute

    def _jtc_check(self, t: float) -> None:
        """Tolerances of the action goals under way (after each step), as the JTC checks them."""
        ended = []
        with self._lock:
            for c in self.adapter.controllers:
                rec = self._jtc_goals.get(c.name)
                if rec is None or rec[1] is not None:
                    continue
                a = self.model.active.get(c.name)
                if rec[3].is_cancel_requested:
                    self.model.hold(c.name)
                    rec[1] = ("canceled", 0, "canceled: holding")
                    ended.append(rec)
                    continue
                if a is None:
                    rec[1] = ("canceled", 0, "held")
                    ended.append(rec)
                    continue
                err = np.abs(self.model.q[a.idx] - a.desired(t))
                k = int(np.argmax(err))
                if err[k] > self.p["path_tolerance"]:
                    rec[1] = ("aborted", -4, f"State tolerances failed for joint {c.robot_joints[k]}: position "
                                             f"error {err[k]:.4f}, tolerance {self.p['path_tolerance']:g}")
                    self.model.hold(c.name)
                    ended.append(rec)
                elif t - a.t_start >= a.times[-1]:
                    end_err = np.abs(self.model.q[a.idx] - a.positions[-1])
                    if end_err.max() <= self.p["goal_tolerance"]:
                        rec[1] = ("succeeded", 0, "Goal successfully reached!")
                        ended.append(rec)
                    elif t - a.t_start >= a.times[-1] + 1.0:  # goal_time_tolerance
                        rec[1] = ("aborted", -5, f"goal tolerance failed by {end_err.max():.4f}")
                        ended.append(rec)
        for rec in ended:
            if rec[1][0] == "aborted":
                self.status(f"goal aborted: {rec[1][2]}", "warning")
            if len(rec) > 2 and not rec[2].done():
                rec[2].set_result(True)

    def _joint_disturbance_cb(self, msg) -> None:
        """A push: each named joint moved by the given offset at once."""
        with self._lock:
            names = self.robot.joint_names
            rmap = {}
            for c in self.adapter.controllers:
                for j in c.joints:
                    rmap[c.robot_name(j)] = j
            for n, d in zip(msg.name, msg.position):
                j = rmap.get(n, n)
                if j in names and np.isfinite(d):
                    i = names.index(j)
                    self.model.q[i] = float(np.clip(self.model.q[i] + d, self.robot.lower[i], self.robot.upper[i]))

    # ------------------------------------------------------------------------------------------------ Stretch driver
    def _stretch_interfaces(self, cb) -> None:
        """The Stretch driver's ROS interfaces (names from the adapter's ``driver`` section and action)."""
        from rclpy.action import ActionServer
        from rclpy.callback_groups import ReentrantCallbackGroup
        from geometry_msgs.msg import Twist
        from std_msgs.msg import Bool, String
        from std_srvs.srv import SetBool, Trigger

        fjt = import_follow_joint_trajectory()
        if fjt is None:
            raise RuntimeError("the Stretch driver profile needs control_msgs (scripts/build_interfaces.sh)")
        self._fjt = fjt
        node, d = self.node, self.adapter.driver
        action = next(c.action for c in self.adapter.controllers if c.action)
        self._action_server = ActionServer(node, fjt, action, execute_callback=self._execute_goal,
                                           goal_callback=self._goal_request, cancel_callback=self._cancel_request,
                                           callback_group=ReentrantCallbackGroup())
        for m in ("navigation", "position", "trajectory"):
            node.create_service(Trigger, d.switch_name(m), self._switch_cb(m), callback_group=cb)
        node.create_service(Trigger, d.stop_service, self._stop_cb, callback_group=cb)
        node.create_service(SetBool, self.p["runstop_service"], self._runstop_cb, callback_group=cb)
        self.pub_mode = node.create_publisher(String, d.mode_topic, 1)
        self.pub_runstop = node.create_publisher(Bool, d.runstop_topic, 1)
        self.pub_driver = node.create_publisher(String, "~/driver", 10)  # the driver's counts (JSON), for tests
        if self.robot.mobile:
            node.create_subscription(Twist, self.adapter.base.topic, self._stretch_twist_cb, 10, callback_group=cb)
        node.create_timer(1.0 / max(1.0, self.p["status_rate_hz"]), self._driver_status, callback_group=cb)

    def _driver_status(self) -> None:
        from std_msgs.msg import Bool, String

        import json

        with self._lock:
            mode, rs = self.driver.mode, self.driver.runstopped
            rec = {"mode": mode, **self.driver.counts, "aborts": [list(a) for a in self.driver.aborts[-20:]]}
        self.pub_mode.publish(String(data=mode))
        self.pub_runstop.publish(Bool(data=rs))
        self.pub_driver.publish(String(data=json.dumps(rec)))

    def _switch_cb(self, mode: str):
        def cb(req, resp):
            with self._lock:
                resp.success, resp.message = self.driver.switch_mode(mode, self._now())
            self._wake_goals()
            return resp
        return cb

    def _stop_cb(self, req, resp):
        with self._lock:
            self.driver.stop_the_robot(self._now())
        resp.success, resp.message = True, "Stopped the robot."
        return resp

    def _runstop_cb(self, req, resp):
        with self._lock:
            self.driver.set_runstop(bool(req.data), self._now())
        self._wake_goals()
        resp.success, resp.message = True, f"is_runstopped: {bool(req.data)}"
        return resp

    def _stretch_twist_cb(self, msg) -> None:
        with self._lock:
            ok = self.driver.cmd_vel(float(msg.linear.x), float(msg.angular.z), self._now())
        if not ok and self.driver.counts["cmd_vel_dropped"] in (1, 10, 100, 1000):
            self.status(f"cmd_vel dropped: the driver must be in navigation mode (mode = {self.driver.mode})",
                        "error")

    def _goal_request(self, request):
        from rclpy.action import GoalResponse

        with self._lock:
            ok = self.driver.goal_request(self._now())
        if not ok:
            self.status("goal rejected: another goal is active and the last one came less than 0.2 s ago",
                        "warning")
        return GoalResponse.ACCEPT if ok else GoalResponse.REJECT

    def _cancel_request(self, goal_handle):
        from rclpy.action import CancelResponse

        with self._lock:
            self.driver.cancel(self._now())
        return CancelResponse.ACCEPT

    async def _execute_goal(self, goal_handle):
        from rclpy.task import Future

        goal = goal_handle.request
        tr, mt = goal.trajectory, goal.multi_dof_trajectory
        pts = [(cv.duration_to_sec(p.time_from_start), list(p.positions), list(p.velocities)) for p in tr.points]
        bpts = []
        if BASE_JOINT in mt.joint_names:
            i = list(mt.joint_names).index(BASE_JOINT)
            for p in mt.points:
                tf = p.transforms[i]
                yaw = cv.yaw_of([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w])
                vel = (p.velocities[i].linear.x, p.velocities[i].angular.z) if len(p.velocities) > i else None
                bpts.append((cv.duration_to_sec(p.time_from_start), (tf.translation.x, tf.translation.y, yaw), vel))
        with self._lock:
            g = self.driver.execute(cv.stamp_to_sec(tr.header.stamp), list(tr.joint_names), pts,
                                    list(mt.joint_names), bpts, self._now())
            fut = Future()
            if g.outcome is None:
                self._goal_futures[g.id] = (g, fut)
        if g.outcome is None:
            await fut
        state, code, text = g.outcome
        if state == "aborted" and code != 0:
            self.status(f"goal aborted: {text}", "warning")
        res = self._fjt.Result()
        res.error_code, res.error_string = int(code), text
        if state == "succeeded":
            goal_handle.succeed()
        elif state == "canceled":
            goal_handle.canceled()
        else:
            goal_handle.abort()
        return res

    def _wake_goals(self) -> None:
        """Complete the futures of goals that ended (the step and the services call this)."""
        with self._lock:
            done = [k for k, (g, f) in self._goal_futures.items() if g.outcome is not None]
            futs = [self._goal_futures.pop(k)[1] for k in done]
        for f in futs:
            if not f.done():
                f.set_result(True)

    def _traj_cb(self, ctrl: ControllerConfig):
        def cb(msg):
            try:
                pts = [(cv.duration_to_sec(p.time_from_start), list(p.positions)) for p in msg.points]
                with self._lock:
                    ok, why = self.model.accept_trajectory(ctrl, msg.joint_names, cv.stamp_to_sec(msg.header.stamp),
                                                           pts, self._now())
            except Exception as exc:  # never die on a message
                ok, why = False, f"malformed trajectory: {exc}"
            if not ok:
                self.status(f"{ctrl.name} refused a trajectory: {why}", "warning")
        return cb

    def _twist_cb(self, stamped: bool):
        def cb(msg):
            tw = msg.twist if stamped else msg
            with self._lock:
                self.model.set_twist(float(tw.linear.x), float(tw.angular.z), self._now())
        return cb

    def _disturbance_cb(self, msg) -> None:
        with self._lock:
            self.model.set_disturbance(msg.linear.x, msg.linear.y, msg.angular.z,
                                       self._now() + self.p["disturbance_timeout_s"])

    def _step(self) -> None:
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import JointState

        t = self._now()
        with self._lock:
            dt = 0.0 if self._last_t is None else min(max(t - self._last_t, 0.0), 0.2)
            self._last_t = t
            if self.driver is not None:
                self.driver.step(t, dt)
                self.model.step(t, dt, base=self.driver.mode == "navigation")
            else:
                self.model.step(t, dt)
            q = self.model.q.copy()
            v = self.model.v.copy()
            names, pos = self.model.joint_state()
        if self._goal_futures:
            self._wake_goals()
        if getattr(self, "_jtc_goals", None):
            self._jtc_check(t)
        if self.pub_scaling:
            from std_msgs.msg import Float64

            for pub in self.pub_scaling:
                pub.publish(Float64(data=100.0 * self.model.speed_scaling))
        stamp = self.node.get_clock().now().to_msg()
        js = JointState()
        js.header.stamp = stamp
        js.name, js.position = names, pos
        self.pub_js.publish(js)
        if self.robot.mobile:
            p, qq = compose_pose(invert_pose(self.odom_origin), (np.array([q[0], q[1], 0.0]), cv.yaw_quat(q[2])))
            od = Odometry()
            od.header.stamp = stamp
            od.header.frame_id = self.p["odom_frame"]
            od.child_frame_id = self.p["base_frame"]
            cv.numpy_to_pose(p, qq, od.pose.pose)
            od.twist.twist.linear.x, od.twist.twist.angular.z = float(v[0]), float(v[1])
            self.pub_odom.publish(od)

    def _mocap(self) -> None:
        with self._lock:
            q = self.model.q.copy()
        base = (np.array([q[0], q[1], 0.0]), cv.yaw_quat(q[2]))
        body = compose_pose(base, invert_pose(self.mocap_offset))
        p, qq = compose_pose(invert_pose(self.mocap_world), body)
        self.pub_mocap.publish(cv.pose_stamped(p, qq, self.p["mocap_frame"], self.node.get_clock().now().to_msg()))

    @property
    def q(self) -> np.ndarray:
        with self._lock:
            return self.model.q.copy()

    def destroy(self) -> None:
        self.node.destroy_node()


def _accept_cancel():
    from rclpy.action import CancelResponse

    return CancelResponse.ACCEPT


def _unit(q) -> np.ndarray:
    q = np.asarray(q, float)
    return q / np.linalg.norm(q)


def main(args=None) -> int:
    return run_nodes([SimRobotNode], args, description=__doc__, prog="sim_robot")


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
