"""The kinematic robot of ``sim_robot`` without ROS (:class:`SimModel`): trajectories accepted by the rules of
ros2_control's joint_trajectory_controller, the base's twist and a disturbance integrated within the robot config's
limits, and the joint states the robot reports."""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from .adapters import AdapterConfig, ControllerConfig


class _Active:
    """A joint trajectory being executed: planning indices, start time, knot times/positions (the robot's position at
    acceptance prepended at time 0 when the first point lies in the future)."""

    def __init__(self, idx, t_start, times, positions, scaled: bool = False):
        self.idx, self.t_start, self.times, self.positions = idx, t_start, times, positions
        self.scaled = scaled  # a scaled controller: its own clock ``tau`` advances at the speed scaling
        self.tau: Optional[float] = None

    def desired(self, t: float) -> np.ndarray:
        tau = t - self.t_start if self.tau is None else self.tau
        if tau <= self.times[0]:
            return self.positions[0]
        if tau >= self.times[-1]:
            return self.positions[-1]
        return np.array([np.interp(tau, self.times, self.positions[:, j]) for j in range(self.positions.shape[1])])


class SimModel:
    """The simulation without ROS: ``accept_trajectory``, ``set_twist``, ``step``."""

    def __init__(self, robot, adapter: AdapterConfig, q0: np.ndarray, cmd_vel_timeout_s: float = 0.5):
        self.robot, self.adapter = robot, adapter
        self.q = np.asarray(q0, float).copy()
        self.v = np.zeros(2)  # base (v, omega) now
        self.twist = np.zeros(2)
        self.twist_t = -math.inf
        self.cmd_vel_timeout_s = cmd_vel_timeout_s
        self.active: dict = {}
        self.accepted = {c.name: 0 for c in adapter.controllers}
        self.rejected = {c.name: 0 for c in adapter.controllers}
        self.twists = 0
        self.last_reject = ""
        self.disturbance = np.zeros(3)  # (vx, vy, omega) in the base frame, added to the commanded motion ...
        self.disturbance_until = -math.inf  # ... until this time
        self.speed_scaling = 1.0  # what scaled controllers (speed_scaling_topic) run at

    def accept_trajectory(self, ctrl: ControllerConfig, joint_names, stamp_sec: float, points, now: float) -> tuple:
        """(ok, reason). ``points``: list of (time_from_start, positions). The rules of ros2_control's
        joint_trajectory_controller with ``allow_partial_joints_goal: false``."""
        own = ctrl.robot_joints
        names = list(joint_names)
        if len(set(names)) != len(names) or set(names) != set(own):
            return self._reject(ctrl, f"joint set {names} is not the controller's {own}")
        idx_msg = [names.index(j) for j in own]
        if not points:  # Jazzy's joint_trajectory_controller discards an empty trajectory
            return self._reject(ctrl, "empty trajectory discarded")
        t = np.array([p[0] for p in points], float)
        try:
            P = np.array([[p[1][i] for i in idx_msg] for p in points], float)
        except (IndexError, TypeError):
            return self._reject(ctrl, "a point has fewer positions than joints")
        if not (np.isfinite(t).all() and np.isfinite(P).all()):
            return self._reject(ctrl, "non-finite values")
        if np.any(t < 0) or np.any(np.diff(t) <= 0):
            return self._reject(ctrl, f"time_from_start not strictly increasing: {t[:5].tolist()}")
        start = now if stamp_sec == 0.0 else stamp_sec
        if start + t[-1] < now:
            return self._reject(ctrl, f"trajectory ends {now - start - t[-1]:.3f} s in the past")
        pidx = [self.robot.joint_names.index(j) for j in ctrl.joints]
        if t[0] > 0:
            t = np.r_[0.0, t]
            P = np.vstack([self.q[pidx], P])
        # a start in the past (not ended): sampled from the current time on, as a JTC does
        a = _Active(pidx, start, t, P, scaled=bool(ctrl.speed_scaling_topic))
        if a.scaled:
            a.tau = now - start
        self.active[ctrl.name] = a
        self.accepted[ctrl.name] += 1
        return True, "ok"

    def _reject(self, ctrl, why: str) -> tuple:
        self.rejected[ctrl.name] += 1
        self.last_reject = f"{ctrl.name}: {why}"
        return False, why

    def hold(self, name: str) -> None:
        """The controller ``name`` holds where its joints are (a JTC after an aborted goal)."""
        a = self.active.get(name)
        if a is not None:
            q = self.q[a.idx].copy()
            self.active[name] = _Active(a.idx, -1e9, np.array([0.0]), q[None])

    def set_twist(self, v: float, w: float, now: float) -> None:
        if not (math.isfinite(v) and math.isfinite(w)):
            return
        self.twist = np.array([v, w], float)
        self.twist_t = now
        self.twists += 1

    def set_disturbance(self, vx: float, vy: float, w: float, until: float) -> None:
        """A motion the base makes on top of what it is commanded (body frame: forward, left, counter-clockwise)
        until ``until``: what a push or slipping wheels do to a real base, which no command produced."""
        d = np.array([vx, vy, w], float)
        if np.isfinite(d).all():
            self.disturbance, self.disturbance_until = d, float(until)

    def step(self, t: float, dt: float, base: bool = True) -> None:
        """Advance by ``dt``: the joint trajectories under way, and (``base``) the base from its twist input."""
        r = self.robot
        for a in list(self.active.values()):
            if a.scaled:
                a.tau += dt * self.speed_scaling
            want = a.desired(t)
            cur = self.q[a.idx]
            vmax = r.velocity[a.idx]
            self.q[a.idx] = np.clip(cur + np.clip(want - cur, -vmax * dt, vmax * dt), r.lower[a.idx], r.upper[a.idx])
        if r.mobile and base:
            b = r.config.base
            target = self.twist if t - self.twist_t <= self.cmd_vel_timeout_s else np.zeros(2)
            target = np.clip(target, [-b.linear_velocity, -b.angular_velocity], [b.linear_velocity, b.angular_velocity])
            amax = np.array([b.linear_acceleration, b.angular_acceleration]) * dt
            self.v = self.v + np.clip(target - self.v, -amax, amax)
            v, w = self.v
            th = self.q[2] + 0.5 * w * dt
            dx, dy, dw = self.disturbance if t <= self.disturbance_until else (0.0, 0.0, 0.0)
            c, s = math.cos(th), math.sin(th)
            self.q[0] += ((v + dx) * c - dy * s) * dt
            self.q[1] += ((v + dx) * s + dy * c) * dt
            self.q[2] += (w + dw) * dt

    def joint_state(self) -> tuple:
        """(names, positions) as the robot publishes them: controller joints by their robot names, plus the URDF
        joints they drive (e.g. Stretch's joint_arm_l0..l3)."""
        names, pos = [], []
        for c in self.adapter.controllers:
            for j in c.joints:
                names.append(c.robot_name(j))
                pos.append(float(self.q[self.robot.joint_names.index(j)]))
        vals = self.robot.urdf_joint_values(self.q)
        for uj in self.robot.urdf_drives:
            if uj not in names and uj not in self.robot.joint_names:
                names.append(uj)
                pos.append(float(vals[uj]))
        return names, pos
