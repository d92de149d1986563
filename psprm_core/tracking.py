"""How far an executed configuration is from the configurations its trajectory was checked at.

A planner that keeps a clearance ``padding`` from every obstacle (:class:`psprm_core.collision.CollisionChecker`
with ``padding``: every box grown by it on every face) checks its path against the grown boxes. A point outside a
box grown by ``padding`` is more than ``padding`` from the box itself, so an executed configuration none of whose
points lies more than ``padding`` from where that point was in one checked configuration touches no obstacle,
whatever the tracking error that put it there. The robot's collision geometry is oriented boxes fixed to its bodies
(:attr:`psprm_core.robot.RobotModel.elements`); between two configurations a point of such a box moves by
``|(R_a - R_b) p + (t_a - t_b)|``, a convex function of ``p``, so the largest move over the box is at one of its
eight corners. :func:`displacement` is that largest move over every box; :class:`CheckedPath` holds the corners
along a trajectory (sampled every ``step_s``) and answers, for a measured configuration at a time, the smallest such
displacement over the trajectory's configurations within a window of that time (:meth:`CheckedPath.deviation`).
Sampling is conservative: a minimum over samples is never below the minimum over the continuous path.

The robot adapter stops the robot and asks for a new plan when the deviation exceeds its path tolerance (ros2_control's
joint_trajectory_controller likewise aborts a goal whose path tolerance is violated), so that what the robot
executes stays within the clearance of what was checked.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError


def displacement(robot, q, Q) -> np.ndarray:
    """The largest distance (M,) by which any point of the robot's collision boxes lies apart between configuration
    ``q`` (dof,) and each configuration of ``Q`` (M, dof)."""
    a = robot.element_corners(np.asarray(q, float)[None])[0]
    b = robot.element_corners(Q)
    return np.linalg.norm(b - a[None], axis=2).max(axis=1)


class CheckedPath:
    """A trajectory (``times`` (M,), ``positions`` (M, dof), linear between points, as the server checked it) with
    the corners of the robot's collision boxes sampled every ``step_s`` along it, computed in blocks of ``block``
    samples when a query first needs them (a long trajectory costs its first query only its first blocks)."""

    def __init__(self, robot, times, positions, step_s: float = 0.05, block: int = 32):
        t = np.asarray(times, float).reshape(-1)
        P = np.asarray(positions, float).reshape(len(t), robot.dof)
        if len(t) == 0 or np.any(np.diff(t) <= 0) or not np.isfinite(P).all():
            raise InputError("checked path: times must be strictly increasing and positions finite")
        if not step_s > 0:
            raise InputError(f"checked path: step_s must be > 0, got {step_s}")
        self.robot, self.block = robot, int(block)
        t = t - t[0]
        self.duration = float(t[-1])
        n = int(np.ceil(self.duration / step_s)) + 1
        # the points themselves too: a corner of the path (a stop between a rotation and a drive) is sampled exactly
        self.ts = np.union1d(np.linspace(0.0, self.duration, max(n, 1)), t)
        self.Q = np.stack([np.interp(self.ts, t, P[:, j]) for j in range(P.shape[1])], axis=1)
        self._blocks: dict = {}  # block index -> corners (block, 8E, 3) float32

    def corners(self, lo: int, hi: int) -> np.ndarray:
        """Corners (hi - lo, 8E, 3) of the sampled configurations ``lo:hi``."""
        b0, b1 = lo // self.block, (hi - 1) // self.block
        for b in range(b0, b1 + 1):
            if b not in self._blocks:
                Qb = self.Q[b * self.block:(b + 1) * self.block]
                self._blocks[b] = self.robot.element_corners(Qb).astype(np.float32)
        allc = np.concatenate([self._blocks[b] for b in range(b0, b1 + 1)])
        return allc[lo - b0 * self.block:hi - b0 * self.block]

    def _windows(self, taus, window_s: float) -> tuple:
        """Sample index ranges [lo, hi) (N,) within ``window_s`` of each time in ``taus`` (clamped to the path)."""
        taus = np.clip(np.asarray(taus, float).reshape(-1), 0.0, self.duration)
        lo = np.minimum(np.searchsorted(self.ts, taus - window_s, side="left"), len(self.ts) - 1)
        hi = np.minimum(np.maximum(np.searchsorted(self.ts, taus + window_s, side="left"), lo + 1), len(self.ts))
        return lo, hi

    def deviations(self, Q, taus, window_s: float = 2.0) -> np.ndarray:
        """:meth:`deviation` distances (N,) of configurations ``Q`` (N, dof) at times ``taus`` (N,), their forward
        kinematics in one batch."""
        A = self.robot.element_corners(Q).astype(np.float32)
        lo, hi = self._windows(taus, window_s)
        return np.array([np.linalg.norm(self.corners(lo[i], hi[i]) - A[i][None], axis=2).max(axis=1).min()
                         for i in range(len(A))])

    def path_distances(self, Q, taus, window_s: float = 2.0, refine: int = 16) -> np.ndarray:
        """Distances (N,) of configurations ``Q`` (N, dof) from the path itself, linear between its sampled
        configurations, within ``window_s`` of the times ``taus``: the nearest sample (as :meth:`deviations`), then
        the two segments beside it, each sampled ``refine`` times. Not conservative, unlike :meth:`deviations`: for
        recognising a trajectory that continues this one, where the sample spacing (a few cm at speed) would hide a
        match."""
        Q = np.asarray(Q, float).reshape(-1, self.robot.dof)
        A = self.robot.element_corners(Q).astype(np.float32)
        lo, hi = self._windows(taus, window_s)
        f = np.linspace(0.0, 1.0, int(refine) + 1)[:, None]
        out = np.empty(len(Q))
        for i in range(len(Q)):
            d = np.linalg.norm(self.corners(lo[i], hi[i]) - A[i][None], axis=2).max(axis=1)
            k = lo[i] + int(np.argmin(d))
            a, b = max(k - 1, 0), min(k + 1, len(self.ts) - 1)
            seg = np.concatenate([self.Q[a] + f * (self.Q[k] - self.Q[a]), self.Q[k] + f * (self.Q[b] - self.Q[k])])
            out[i] = min(float(d.min()), float(displacement(self.robot, Q[i], seg).min()))
        return out

    def deviation(self, q, tau: float, window_s: float = 2.0) -> tuple:
        """(distance, time): the smallest displacement (:func:`displacement`) of the configuration ``q`` from the
        path's sampled configurations within ``window_s`` of time ``tau`` (clamped to the path), and the time of
        the nearest one."""
        (lo,), (hi,) = self._windows([tau], window_s)
        a = self.robot.element_corners(np.asarray(q, float)[None])[0].astype(np.float32)
        d = np.linalg.norm(self.corners(lo, hi) - a[None], axis=2).max(axis=1)
        k = int(np.argmin(d))
        return float(d[k]), float(self.ts[lo + k])

    def latest_time_of(self, q, before: float, lookback_s: float, tol: float, refine: int = 8):
        """The latest time, within ``lookback_s`` before ``before`` (clamped to the path), at which the path (linear
        between its sampled configurations) passes within ``tol`` (:func:`displacement`) of configuration ``q``;
        None when it does not. Of several passes (a turn that comes back on itself) the latest is taken: the one
        the robot left most recently. Each sampled pass is refined to the nearest of ``refine`` points on the two
        segments beside it."""
        lo = int(np.searchsorted(self.ts, before - lookback_s, side="left"))
        hi = int(np.searchsorted(self.ts, before, side="right"))
        lo, hi = min(lo, len(self.ts) - 1), max(min(hi, len(self.ts)), min(lo, len(self.ts) - 1) + 1)
        q = np.asarray(q, float)
        a = self.robot.element_corners(q[None])[0].astype(np.float32)
        d = np.linalg.norm(self.corners(lo, hi) - a[None], axis=2).max(axis=1)
        near = np.nonzero(d <= 2.0 * tol)[0]
        if len(near) == 0:
            return None
        # the last run of samples near q, and its best sample
        runs = np.split(near, np.nonzero(np.diff(near) > 1)[0] + 1)
        for run in reversed(runs):
            k = lo + int(run[np.argmin(d[run])])
            a_, b_ = max(k - 1, 0), min(k + 1, len(self.ts) - 1)
            f = np.linspace(0.0, 1.0, int(refine) + 1)[:, None]
            seg = np.concatenate([self.Q[a_] + f * (self.Q[k] - self.Q[a_]), self.Q[k] + f * (self.Q[b_] - self.Q[k])])
            ts = np.concatenate([self.ts[a_] + f[:, 0] * (self.ts[k] - self.ts[a_]),
                                 self.ts[k] + f[:, 0] * (self.ts[b_] - self.ts[k])])
            dist = displacement(self.robot, q, seg)
            j = int(np.argmin(dist))
            if dist[j] <= tol:
                return float(ts[j])
        return None
