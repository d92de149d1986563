"""Closed-loop tracking of a planned differential-drive base path from the measured base pose.

The reference is the planned base trajectory (``base_x, base_y, base_theta`` against time, scene frame) started at a
known time, so the base stays in step with the other joints' controllers, which run the same trajectory on the same
clock. The control law is Kanayama et al.'s tracking controller ("A stable tracking control method for an autonomous
mobile robot", ICRA 1990) with the heading term kept for in-place rotations:

    e_x, e_y = R(theta)^T (p_ref - p),   e_theta = wrap(theta_ref - theta)
    v     = v_ref cos(e_theta) + k_x e_x
    omega = omega_ref + k_y v_ref e_y + k_theta sin(e_theta)

then clipped to the base's velocity limits and rate-limited to its acceleration limits. After the end of the path
the reference stays at the final pose; the feed-forward velocities are taken ``preview_s`` ahead (the delay from a
command to the wheels); the command is zero once the base is within the goal tolerances (or
``settle_s`` later). Pure numpy: the adapter node calls :meth:`BaseFollower.command` at its rate (>= 20 Hz).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

from psprm_core.errors import InputError
from psprm_core.geometry import wrap_angle


@dataclasses.dataclass(frozen=True)
class Limits:
    linear_velocity: float
    angular_velocity: float
    linear_acceleration: float
    angular_acceleration: float

    @classmethod
    def for_robot(cls, robot, base=None) -> "Limits":
        """The robot config's base limits, each replaced by the adapter's value when that is > 0."""
        b = robot.config.base

        def pick(name):
            v = getattr(base, name, 0.0) if base is not None else 0.0
            return float(v) if v and v > 0 else float(getattr(b, name))
        return cls(pick("linear_velocity"), pick("angular_velocity"), pick("linear_acceleration"),
                   pick("angular_acceleration"))


@dataclasses.dataclass(frozen=True)
class Gains:
    k_x: float = 1.5
    k_y: float = 6.0
    k_theta: float = 3.0


class BaseReference:
    """A base trajectory (times (M,), poses (M, 3)) sampled with linear interpolation; velocities per segment."""

    def __init__(self, times, poses):
        t = np.asarray(times, float).reshape(-1)
        P = np.asarray(poses, float).reshape(len(t), 3).copy()
        if len(t) == 0 or np.any(np.diff(t) <= 0) or not np.isfinite(P).all():
            raise InputError("base reference: times must be strictly increasing and poses finite")
        P[:, 2] = np.unwrap(P[:, 2])
        self.t, self.P = t - t[0], P
        if len(t) > 1:
            dt = np.diff(self.t)
            d = np.diff(P, axis=0)
            heading = P[:-1, 2] + 0.5 * np.diff(P[:, 2])
            # signed speed along the heading (a diff drive moves along it; backwards gives v < 0)
            self.v = (d[:, 0] * np.cos(heading) + d[:, 1] * np.sin(heading)) / dt
            self.w = d[:, 2] / dt
        else:
            self.v = self.w = np.zeros(0)

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def run_end(self, tau: float) -> tuple:
        """End of the motion the reference is in at ``tau``: (pose (3,), kind) where the current run of segments with
        the same kind (rotation or translation) and direction ends -- where the base must have stopped."""
        if len(self.t) == 1 or tau >= self.t[-1]:
            return self.P[-1].copy(), ""
        k = max(0, int(np.searchsorted(self.t, max(tau, 0.0), side="right") - 1))
        rot = abs(self.w[k]) > 1e-6 and abs(self.v[k]) < 1e-6
        sgn = np.sign(self.w[k] if rot else self.v[k])
        if sgn == 0:
            return self.P[k].copy(), ""
        j = k
        while j + 1 < len(self.v):
            nxt = self.w[j + 1] if rot else self.v[j + 1]
            if np.sign(nxt) != sgn or (rot and abs(self.v[j + 1]) > 1e-6):
                break
            j += 1
        return self.P[j + 1].copy(), "rotation" if rot else "translation"

    def sample(self, tau: float) -> tuple:
        """(pose (3,), v_ref, omega_ref) at ``tau`` seconds from the start (clamped to the ends; zero velocity
        outside)."""
        if len(self.t) == 1 or tau <= 0.0:
            return self.P[0].copy(), 0.0, 0.0
        if tau >= self.t[-1]:
            return self.P[-1].copy(), 0.0, 0.0
        k = int(np.searchsorted(self.t, tau, side="right") - 1)
        f = (tau - self.t[k]) / (self.t[k + 1] - self.t[k])
        pose = self.P[k] + f * (self.P[k + 1] - self.P[k])
        return pose, float(self.v[k]), float(self.w[k])


class BaseFollower:
    """Tracks a :class:`BaseReference` started at ``t0`` (the caller's clock)."""

    def __init__(self, limits: Limits, gains: Gains = Gains(), goal_tolerance_m: float = 0.02,
                 goal_tolerance_rad: float = 0.03, settle_s: float = 2.0, preview_s: float = 0.1):
        self.limits, self.gains, self.preview_s = limits, gains, preview_s
        self.goal_tolerance_m, self.goal_tolerance_rad, self.settle_s = goal_tolerance_m, goal_tolerance_rad, settle_s
        self.ref: Optional[BaseReference] = None
        self.t0 = 0.0
        self.cmd = np.zeros(2)  # last (v, omega) command
        self.last_t: Optional[float] = None
        self.done = True
        self.error = np.zeros(3)  # last (e_x, e_y, e_theta)
        self._periods: list = []  # recent control periods (the braking margin covers the longest of them)
        # the rate at which the caller's path clock runs (a controller's speed scaling): the reference velocities
        # are taken times this rate
        self.rate = 1.0

    def set_path(self, ref: BaseReference, t0: float) -> None:
        self.ref, self.t0, self.done = ref, float(t0), False

    def stop(self) -> None:
        """Drop the path; the next commands decelerate to zero (a stop sends the zero twist at once instead)."""
        self.ref, self.done = None, True
        self.cmd = np.zeros(2)

    def command(self, t: float, pose) -> tuple:
        """(v, omega) for the measured ``pose`` (x, y, theta) at time ``t``."""
        dt = 0.0 if self.last_t is None else max(0.0, min(t - self.last_t, 0.2))
        if self.last_t is not None:
            self._periods.append(max(0.0, t - self.last_t))
            del self._periods[:-60]
        self.last_t = t
        if self.ref is None or self.done:
            self.cmd = np.zeros(2)
            return 0.0, 0.0
        x, y, th = (float(v) for v in pose)
        tau = t - self.t0
        (xr, yr, thr), _, _ = self.ref.sample(tau)
        # feed-forward velocities a little ahead: the command reaches the wheels one control period and one
        # acceleration ramp later (without it the base lags the reference by that much at every speed change)
        _, vr, wr = self.ref.sample(tau + self.preview_s * self.rate)
        vr, wr = vr * self.rate, wr * self.rate
        c, s = math.cos(th), math.sin(th)
        ex = c * (xr - x) + s * (yr - y)
        ey = -s * (xr - x) + c * (yr - y)
        eth = wrap_angle(thr - th)
        self.error = np.array([ex, ey, eth])
        if tau >= self.ref.duration:
            near = math.hypot(xr - x, yr - y) <= self.goal_tolerance_m and abs(eth) <= self.goal_tolerance_rad
            if near or tau >= self.ref.duration + self.settle_s:
                self.done = True
                self.cmd = np.zeros(2)
                return 0.0, 0.0
        g, lim = self.gains, self.limits
        v = vr * math.cos(eth) + g.k_x * ex
        w = wr + g.k_y * vr * ey + g.k_theta * math.sin(eth)
        v = float(np.clip(v, -lim.linear_velocity, lim.linear_velocity))
        w = float(np.clip(w, -lim.angular_velocity, lim.angular_velocity))
        # never faster than the base can still stop at the end of the motion it is in, with the longest recent
        # control period as the reaction delay: a late or skipped control step must not carry the base past a
        # corner of the path
        end, kind = self.ref.run_end(tau)
        delay = max([self.preview_s] + self._periods[-30:])  # a loaded computer runs this loop late at times
        if kind == "rotation" and w != 0.0:
            rem = wrap_angle(end[2] - th) * np.sign(w)
            w = float(np.sign(w) * min(abs(w), _stoppable(rem, lim.angular_acceleration, delay)))
        elif kind == "translation" and v != 0.0:
            rem = ((end[0] - x) * c + (end[1] - y) * s) * np.sign(v)
            v = float(np.sign(v) * min(abs(v), _stoppable(rem, lim.linear_acceleration, delay)))
        if dt > 0:
            v = float(np.clip(v, self.cmd[0] - lim.linear_acceleration * dt, self.cmd[0] + lim.linear_acceleration * dt))
            w = float(np.clip(w, self.cmd[1] - lim.angular_acceleration * dt,
                              self.cmd[1] + lim.angular_acceleration * dt))
        self.cmd = np.array([v, w])
        return v, w


def _stoppable(remaining: float, accel: float, delay: float) -> float:
    """The largest speed from which a base that reacts ``delay`` late and brakes at ``accel`` stops within
    ``remaining`` (0 when nothing remains)."""
    if remaining <= 0.0:
        return 0.0
    return accel * (-delay + math.sqrt(delay * delay + 2.0 * remaining / accel))

