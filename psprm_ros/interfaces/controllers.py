"""The robot adapter's links to the robot: its controllers, its base's cmd_vel and the Stretch driver's services.

:class:`ControllerLinks` owns, on a node, what an adapter config (:mod:`psprm_ros.robots.adapters`) names: a
``trajectory_msgs/JointTrajectory`` publisher per topic controller, a ``control_msgs/FollowJointTrajectory`` action
client per action controller, a ``Twist`` / ``TwistStamped`` publisher on the base's cmd_vel; each controller's goal
gate (at most one goal per ``min_goal_interval_s``, the newest one pending) and the goal bookkeeping: every goal sent
to a controller gets the next sequence number, and only a rejection or an abort of its newest goal is a failure (a
goal that a newer one or a stop replaced ends without one). :class:`DriverLink` holds the Stretch driver's mode and
runstop subscriptions and its std_srvs/Trigger clients (mode switches, stop).

No ROS import at module level: the message, action and service types are imported when the links are made.
"""

from __future__ import annotations

import time
from typing import Callable, Optional, Sequence

import numpy as np

from ..robots import adapters as ad
from ..robots import stretch
from .conversions import duration_msg


def retrieve(fut) -> None:
    """Take a finished service call's result or exception (an unanswered call is cut off at shutdown)."""
    try:
        fut.result()
    except Exception:
        pass


class ControllerLinks:
    """The controllers and the base of adapter config ``cfg`` on ``node``. ``counts`` (the node's counters:
    goals_sent, goals_deferred, goals_rejected, twists) is updated in place; ``on_failed(controller, why)`` hears of
    a failed newest goal, ``status(text, level)`` of anything else. ``fjt`` is the FollowJointTrajectory action type
    (None without action controllers); ``lock`` guards the goal handles."""

    def __init__(self, node, cfg: ad.AdapterConfig, mobile: bool, fjt, callback_group, lock, counts: dict,
                 on_failed: Callable[[str, str], None], status: Callable[..., None]):
        from geometry_msgs.msg import Twist, TwistStamped
        from trajectory_msgs.msg import JointTrajectory

        self.node, self.cfg, self.fjt, self.counts = node, cfg, fjt, counts
        self._lock, self._on_failed, self._status = lock, on_failed, status
        self.pubs: dict = {}  # controller -> JointTrajectory publisher
        self.clients: dict = {}  # controller -> ActionClient
        self.goal_handles: dict = {}  # controller -> active ClientGoalHandle
        self.gates: dict = {}
        self.pending: dict = {}  # controller -> (t, P, V, start_at) waiting for its goal interval
        self.goal_seq: dict = {}  # controller -> sequence number of the newest goal sent
        self.twist_pub = None
        for c in cfg.controllers:
            self.gates[c.name] = ad.GoalGate(c.min_goal_interval_s)
            if c.interface == "topic":
                self.pubs[c.name] = node.create_publisher(JointTrajectory, c.topic, 10)
            else:
                from rclpy.action import ActionClient

                self.clients[c.name] = ActionClient(node, fjt, c.action, callback_group=callback_group)
        b = cfg.base
        if mobile and b.mode == "cmd_vel":
            self.twist_pub = node.create_publisher(TwistStamped if b.stamped else Twist, b.topic, 10)

    # ------------------------------------------------------------------------------------------------ goals
    def offer(self, c: ad.ControllerConfig, item: tuple, now: float) -> Optional[tuple]:
        """``item`` (t, P, V, start_at) for controller ``c`` through its goal gate: what to send now, or None (kept
        pending until :meth:`due` releases it)."""
        out = self.gates[c.name].offer(item, now)
        if out is None:
            self.pending[c.name] = item
            self.counts["goals_deferred"] += 1
        else:
            self.pending.pop(c.name, None)
        return out

    def due(self, now: float) -> list:
        """(controller, item) for every pending goal its gate releases now."""
        out = []
        for c in self.cfg.controllers:
            item = self.gates[c.name].due(now) if c.name in self.pending else None
            if item is not None:
                self.pending.pop(c.name, None)
                out.append((c, item))
        return out

    def send(self, c: ad.ControllerConfig, cmd: ad.Command) -> None:
        """A command on ``c``'s topic, or as a FollowJointTrajectory goal on its action."""
        if c.interface == "topic":
            self.pubs[c.name].publish(ad.to_joint_trajectory(cmd))
        else:
            cl = self.clients[c.name]
            if not cl.server_is_ready():
                self._on_failed(c.name, f"action server {c.action} not available")
                return
            goal = ad.fill_goal(self.fjt.Goal(), ad.action_goal_fields(cmd, c.goal_time_tolerance_s))
            self._dispatch(c, cl, goal)
            return
        self.counts["goals_sent"] += 1

    def send_goal(self, c: ad.ControllerConfig, goal) -> None:
        """A trajectory-mode goal (:class:`psprm_ros.robots.stretch.TrajectoryModeGoal`: the joints and the base) on
        ``c``'s action."""
        cl = self.clients[c.name]
        if not cl.server_is_ready():
            self._on_failed(c.name, f"action server {c.action} not available")
            return
        jt, mt = stretch.goal_messages(goal)
        g = self.fjt.Goal()
        ad.fill_goal(g, {"trajectory": jt, "multi_dof_trajectory": mt,
                         "goal_time_tolerance": duration_msg(c.goal_time_tolerance_s)})
        self._dispatch(c, cl, g)

    def _dispatch(self, c, cl, goal) -> None:
        seq = self.goal_seq.get(c.name, 0) + 1
        self.goal_seq[c.name] = seq
        fut = cl.send_goal_async(goal)
        fut.add_done_callback(lambda f, name=c.name, n=seq: self._goal_response(name, f, n))
        self.counts["goals_sent"] += 1

    def _goal_response(self, name: str, fut, seq: int) -> None:
        try:
            gh = fut.result()
        except Exception as exc:
            self._status(f"{name}: goal failed: {exc}", "warning")
            return
        if not gh.accepted:
            self.counts["goals_rejected"] += 1
            if seq == self.goal_seq.get(name):
                self._on_failed(name, "goal rejected by the controller")
            return
        with self._lock:
            self.goal_handles[name] = gh
        gh.get_result_async().add_done_callback(lambda f: self._goal_result(name, f, seq))

    def _goal_result(self, name: str, fut, seq: int) -> None:
        """The controller's verdict on a goal: an abort of the newest goal (a tolerance violated, a runstop, a goal
        the driver could not start) is a failure; aborts of goals that a newer one replaced are the controllers' way
        of preempting and say nothing."""
        from action_msgs.msg import GoalStatus

        try:
            r = fut.result()
        except Exception as exc:
            self._status(f"{name}: no result: {exc}", "warning")
            return
        if r is None or seq != self.goal_seq.get(name):
            return
        code, text = int(getattr(r.result, "error_code", 0)), str(getattr(r.result, "error_string", ""))
        if r.status == GoalStatus.STATUS_ABORTED or code != 0:
            self._on_failed(name, f"goal aborted (error_code {code}{': ' + text if text else ''})")

    # ------------------------------------------------------------------------------------------------ stop, base
    def halt(self, names: Sequence[str], q: Optional[np.ndarray], now: float) -> None:
        """Drop the pending goals; a hold at ``q`` (planning joints ``names``; none when None) on every topic
        controller, past its goal gate; cancel every active action goal (what ends now is no failure)."""
        self.pending.clear()
        for c in self.cfg.controllers:
            if c.interface == "topic":
                if q is not None:
                    self.pubs[c.name].publish(ad.to_joint_trajectory(ad.hold_command(c, names, q)))
                    self.gates[c.name].offer(None, now, urgent=True)
            else:
                self.goal_seq[c.name] = self.goal_seq.get(c.name, 0) + 1
                gh = self.goal_handles.pop(c.name, None)
                if gh is not None:
                    gh.cancel_goal_async()

    def publish_twist(self, v: float, w: float) -> None:
        """(v, omega) on the base's cmd_vel (nothing without one)."""
        if self.twist_pub is None:
            return
        from geometry_msgs.msg import Twist, TwistStamped

        if self.cfg.base.stamped:
            m = TwistStamped()
            m.header.stamp = self.node.get_clock().now().to_msg()
            m.header.frame_id = self.cfg.base.frame_id
            tw = m.twist
        else:
            m = tw = Twist()
        tw.linear.x, tw.angular.z = float(v), float(w)
        self.twist_pub.publish(m)
        self.counts["twists"] += 1

    def missing(self) -> list:
        """What cannot take a command now: a JointTrajectory topic no controller subscribes to, an action server
        that is not there, the base's cmd_vel without a subscriber."""
        out = []
        for c in self.cfg.controllers:
            if self.cfg.driver.mode == "navigation":
                continue  # nothing is sent to them
            if c.interface == "topic" and self.pubs[c.name].get_subscription_count() == 0:
                out.append(f"no controller listens on {c.topic} ({c.name})")
            if c.interface == "action" and not self.clients[c.name].server_is_ready():
                out.append(f"action server {c.action} not available ({c.name})")
        if self.twist_pub is not None and self.twist_pub.get_subscription_count() == 0:
            out.append(f"no base controller listens on {self.cfg.base.topic}")
        return out

    def wait_acked(self, timeout_s: float = 1.0) -> bool:
        """Wait (at most ``timeout_s``) until the subscribers acknowledged what the command publishers sent."""
        from rclpy.duration import Duration

        pubs = list(self.pubs.values()) + ([self.twist_pub] if self.twist_pub is not None else [])
        deadline = time.monotonic() + timeout_s
        ok = True
        for pub in pubs:
            left = max(0.0, deadline - time.monotonic())
            ok = pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))) and ok
        return ok

    def destroy(self) -> None:
        """Destroy the publishers and action clients."""
        for pub in self.pubs.values():
            self.node.destroy_publisher(pub)
        for cl in self.clients.values():
            cl.destroy()
        if self.twist_pub is not None:
            self.node.destroy_publisher(self.twist_pub)
        self.pubs, self.clients, self.gates, self.pending = {}, {}, {}, {}
        self.twist_pub = None


class DriverLink:
    """The Stretch driver (adapter config ``driver``, a :class:`~psprm_ros.robots.adapters.DriverConfig`) on
    ``node``: ``on_mode(msg)`` and ``on_runstop(msg)`` hear its mode and runstop topics; :meth:`call` triggers its
    mode switches and its stop."""

    def __init__(self, node, d: ad.DriverConfig, on_mode, on_runstop, callback_group, status: Callable[..., None]):
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from std_msgs.msg import Bool, String
        from std_srvs.srv import Trigger

        self._status, self.node = status, node
        self.subscriptions = [
            node.create_subscription(String, d.mode_topic, on_mode, 10, callback_group=callback_group),
            node.create_subscription(Bool, d.runstop_topic, on_runstop, 10, callback_group=callback_group)]
        grp = MutuallyExclusiveCallbackGroup()
        self.clients: dict = {}  # service name -> Trigger client
        for name in [d.switch_name(m) for m in ("navigation", "position", "trajectory")] + [d.stop_service]:
            self.clients[name] = node.create_client(Trigger, name, callback_group=grp)

    def call(self, name: str):
        """Call the Trigger service ``name``: its future, or None (reported) when it is not available."""
        from std_srvs.srv import Trigger

        cl = self.clients.get(name)
        if cl is None or not cl.service_is_ready():
            self._status(f"driver service {name} not available", "error")
            return None
        fut = cl.call_async(Trigger.Request())
        fut.add_done_callback(retrieve)
        return fut

    def destroy(self) -> None:
        """Destroy the mode and runstop subscriptions and the service clients."""
        for s in self.subscriptions:
            self.node.destroy_subscription(s)
        for cl in self.clients.values():
            self.node.destroy_client(cl)
        self.subscriptions, self.clients = [], {}
