"""The replan monitor's input gate: every input is checked (finite, scene frame, age) and good ones are forwarded to
the server and the scorer on ``/psprm/state/...``; bad ones give a rate-limited warning on ``~/status`` and are
dropped. The mocap rigid bodies are relayed within a deadband (a pose that moved goes out at once, otherwise at most
``relay_keepalive_hz``); the base pose (mocap body, odometry or tf) and ``/joint_states`` make the robot state, which
is forwarded only while both are fresh; goal poses and goal regions become goal candidates, those in collision or
outside the workspace left out."""

from __future__ import annotations

import time

import numpy as np

from .. import core
from ..interfaces import conversions as cv
from ..interfaces.frames import validated_pose_in


class InputGate:
    """The input callbacks of :class:`~psprm_ros.replan_monitor.ReplanMonitor` (a base class of it: they read and
    write the node's state under its lock, and report through its ``status`` and ``warn_limited``)."""

    # ------------------------------------------------------------------------------------------------ inputs
    def _now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9

    def _pose_cb(self, kind: str, name: str):
        def cb(msg):
            if self.frames is None:  # released by a cleanup while this message was on its way
                return
            try:
                p, q = validated_pose_in(msg, self.frames, self._now(), self.p["max_pose_age_s"], f"{kind} {name}")
            except Exception as exc:
                with self._lock:
                    self.counts["refused"] += 1
                self.warn_limited(f"{kind} {name} {_kind_of(exc)}", f"ignored {exc}")
                return
            if not self.active:
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
        if self.tracker is None:  # released by a cleanup while this message was on its way
            return
        try:
            with self._lock:
                self.tracker.update_pose(msg, time.monotonic(), self._now(), self.p["max_pose_age_s"])
        except Exception as exc:
            self.warn_limited(f"base {_kind_of(exc)}", f"ignored {exc}")

    def _odom_cb(self, msg) -> None:
        if self.tracker is None:  # released by a cleanup while this message was on its way
            return
        try:
            with self._lock:
                self.tracker.update_odometry(msg, time.monotonic(), self._now(), self.p["max_pose_age_s"])
        except Exception as exc:
            self.warn_limited(f"odom {_kind_of(exc)}", f"ignored {exc}")
            return

    def _tf_cb(self, msg, static: bool) -> None:
        if self.tracker is None:  # released by a cleanup while this message was on its way
            return
        with self._lock:
            if self.tracker.tf is not None:
                dropped = self.tracker.update_tf(msg, static, time.monotonic())
            else:  # tf for the input frames only
                dropped = [str(d) for d in self.frames.tf.update(msg, static, time.monotonic())]
        for text in dropped:
            self.warn_limited(f"tf {text}", f"ignored {text}")

    def _joints_cb(self, msg) -> None:
        if self.tracker is None:  # released by a cleanup while this message was on its way
            return
        try:
            with self._lock:
                self.tracker.update_joints(msg, time.monotonic())
        except Exception as exc:
            self.warn_limited(f"joints {_kind_of(exc)}", f"ignored {exc}")
            return
        self._forward_robot_state(msg.header.stamp)

    def _forward_robot_state(self, stamp=None) -> None:
        """Forward the measured configuration when joints and base pose are fresh; otherwise report why not
        (nothing is planned then)."""
        with self._lock:
            if self.tracker is None:
                return
            q, why = self.tracker.state(time.monotonic())
            vel = None  # the base's measured velocity (odometry, tf) goes with its pose: the server's braking model
            if q is not None and self.tracker.robot.mobile and self.tracker.base_velocity_measured:
                vel = cv.base_world_rates(q, self.tracker.base_velocity, len(q))
            was = self.robot_state_problem
            self.robot_state_problem = "" if q is not None else why
            if q is not None:
                self.q = q
                self.counts["robot_states"] += 1
        if q is None:
            self.warn_limited("robot state", f"not forwarding the robot state: {why}")
            return
        if was:
            self.status("robot state live (joints and base pose)")
        if not self.active:
            return
        now = time.monotonic()
        hz = self.p["robot_state_rate_hz"]
        if hz > 0 and now - self._robot_fwd_t < 1.0 / hz:
            return
        self._robot_fwd_t = now
        self.pub_robot.publish(cv.planning_joint_state(q, self.names, stamp or self.node.get_clock().now().to_msg(),
                                                       velocity=vel))
        self._check_deviation(q)

    def _goal_cb(self, msg) -> None:
        try:
            p, q = validated_pose_in(msg, self.frames, None, 0.0, "goal")
            if not self._robot.mobile:
                raise cv.InputError("goal poses need a mobile base; use goal regions")
            vals = {"base_x": p[0], "base_y": p[1], "base_theta": cv.yaw_of(q)}
            G = self._robot.configuration(vals)[None]
            self._send_goals(G, f"goal ({p[0]:.2f}, {p[1]:.2f}, yaw {vals['base_theta']:.2f})")
        except Exception as exc:
            self.status(f"ignored {exc}", "warning")

    def _regions_cb(self, msg) -> None:
        try:
            names = [n.strip() for n in msg.data.split(",") if n.strip()]
            if not names:
                raise cv.InputError("goal regions: empty")
            try:
                G = core.goal_region_configurations(self._robot, self.scene, names)
            except KeyError as exc:
                raise cv.InputError(f"goal regions: {exc}") from None
            self._send_goals(G, f"goal regions {', '.join(names)}")
        except Exception as exc:
            self.status(f"ignored {exc}", "warning")

    def _send_goals(self, G: np.ndarray, what: str) -> None:
        import torch

        ws = self.scene.workspace
        if self._robot.mobile and not ((G[:, 0] >= ws[0, 0]) & (G[:, 0] <= ws[0, 1]) & (G[:, 1] >= ws[1, 0]) &
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


def _kind_of(exc) -> str:
    """A short key of an input error for rate-limited warnings (frame / non-finite / stale / other)."""
    t = str(exc)
    for k in ("frame", "non-finite", "stale", "quaternion"):
        if k in t:
            return k
    return type(exc).__name__
