"""Replanning a robot in motion: where a new plan may start, and the trajectory that carries the robot there.

A replan takes time (planning, then delivery to the controllers), and the robot drives on meanwhile. Starting the
new plan where the robot was when planning began makes it start behind the robot, from rest: the controller either
pulls the robot back or stops it. Here a replan starts from the *committed state* instead:

* the executing trajectory is kept up to the first instant, at or after ``now + horizon`` (planning and delivery),
  at which it is at rest anyway (:func:`rest_times`: the ends of its rest-to-rest runs, :mod:`.timing`; with a
  differential-drive base these are the drive corners, where the base turns in place);
* the new plan starts there, from rest, and :func:`splice` joins the two: the result is the executing trajectory up
  to that instant, then the new plan. Position and velocity are continuous (both are at rest at the joint), so a
  replan never makes the robot brake where its trajectory would not have, and the new plan's first motion may be a
  turn in place.

A committed prefix is motion the controllers already execute: the replanner re-checks it against the latest obstacle
poses (an obstacle that moved into it stops the robot) and the spliced trajectory is checked as a whole before it is
handed out, so what runs is what was checked.

:func:`progress_time` finds where along a trajectory a measured configuration lies (the nodes measure the robot, not
the trajectory's clock).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from ..errors import InputError

#: Two rest instants closer than this (s) are one.
_REST_TOL = 1e-6


@dataclass(frozen=True)
class Execution:
    """Where the robot is along the current plan's trajectory when a replan starts.

    ``t``: the trajectory's own time (s from its start) the robot has reached; ``horizon_s``: the time planning and
    delivery are expected to take. The new plan starts at the first rest instant of the trajectory at or after
    ``t + horizon_s``."""

    t: float
    horizon_s: float = 0.3

    def __post_init__(self):
        if not (math.isfinite(self.t) and math.isfinite(self.horizon_s) and self.horizon_s >= 0):
            raise InputError(f"execution time and horizon must be finite (horizon >= 0), got {self.t}, "
                             f"{self.horizon_s}")


def rest_times(traj) -> np.ndarray:
    """Sorted instants (s) at which ``traj`` is at rest: the start and end of each rest-to-rest run of a timed
    trajectory (:class:`~.timing.Trajectory`) or a :class:`SplicedTrajectory`, and its end."""
    own = getattr(traj, "rest", None)
    if own is not None:
        return np.asarray(own, float)
    runs = getattr(traj, "_runs", None) or []
    t = [0.0, float(traj.duration)] + [r.t0 for r in runs] + [r.t0 + r.duration for r in runs]
    t = np.unique(np.round(np.asarray(t, float), 9))
    return t[(t >= 0) & (t <= float(traj.duration) + _REST_TOL)]


def commit_time(traj, t_from: float, horizon_s: float) -> float:
    """The first rest instant of ``traj`` at or after ``t_from + horizon_s`` (its end when none comes before)."""
    r = rest_times(traj)
    later = r[r >= t_from + horizon_s - _REST_TOL]
    return float(later[0]) if len(later) else float(traj.duration)


def progress_time(traj, q: np.ndarray, t_guess: float, window_s: float = 2.0, scale: Optional[np.ndarray] = None,
                  angle_cols: Sequence[int] = (), dt: float = 0.02, tie: float = 0.0) -> float:
    """The time along ``traj`` whose configuration is nearest the measured ``q``, searched within ``window_s`` of
    ``t_guess`` (the time the trajectory's clock says). Nearness: the largest joint difference divided by ``scale``
    (e.g. the velocity limits, so that the distance reads as time); ``angle_cols`` are compared on the circle. With
    ``tie`` > 0, of the passes (local minima of the nearness) within ``tie`` of the nearest one, the one nearest
    ``t_guess``: a trajectory that comes back on itself (forward and back within the window) passes ``q`` twice, and
    the pass the clock points to is the robot's."""
    lo = max(0.0, t_guess - window_s)
    hi = min(float(traj.duration), t_guess + window_s)
    if hi <= lo:
        return float(min(max(t_guess, 0.0), traj.duration))
    ts = np.arange(lo, hi + dt, dt)
    ts = ts[ts <= hi + 1e-12]
    P = traj.evaluate(ts)[0]
    d = np.abs(P - np.asarray(q, float))
    for c in angle_cols:
        d[:, c] = np.abs(np.remainder(d[:, c] + math.pi, 2 * math.pi) - math.pi)
    if scale is not None:
        d = d / np.maximum(np.asarray(scale, float), 1e-9)
    near = d.max(1)
    if tie > 0 and len(near) > 2:
        # the passes: local minima of the nearness; of those within ``tie`` of the nearest, the one nearest the clock
        pad = np.concatenate([[np.inf], near, [np.inf]])
        passes = np.nonzero((near <= pad[:-2]) & (near <= pad[2:]) & (near <= near.min() + tie))[0]
        return float(ts[passes[int(np.argmin(np.abs(ts[passes] - t_guess)))]])
    return float(ts[int(np.argmin(near))])


class SplicedTrajectory:
    """The executing trajectory from ``t_from`` to ``t_commit``, then a new trajectory that starts there at rest.

    It reads like a :class:`~.timing.Trajectory` (``times``, ``positions``, ``velocities``, ``accelerations``,
    ``joint_names``, ``waypoint_indices``, ``duration``, :meth:`evaluate`), its time 0 being ``t_from`` of the
    executing one; ``rest`` holds its rest instants so that it can itself be spliced again. ``offset`` (dof,) is
    added to the new trajectory's positions (whole turns of a continuous joint: the new plan starts at the wrapped
    angle, the executing trajectory at its unwrapped one)."""

    def __init__(self, current, t_from: float, t_commit: float, new, offset: Optional[np.ndarray] = None,
                 dt: float = 0.05):
        if not (0.0 <= t_from <= t_commit <= float(current.duration) + _REST_TOL):
            raise InputError(f"splice times must satisfy 0 <= {t_from:.3f} <= {t_commit:.3f} <= "
                             f"{float(current.duration):.3f}")
        self.current, self.new = current, new
        self.t_from, self.t_commit = float(t_from), float(t_commit)
        self.shift = self.t_commit - self.t_from
        dof = int(np.asarray(current.positions).shape[1])
        self.offset = np.zeros(dof) if offset is None else np.asarray(offset, float).reshape(dof)
        self.joint_names = list(current.joint_names)
        n_pre = max(1, int(math.ceil(self.shift / dt)))
        t_pre = np.linspace(self.t_from, self.t_commit, n_pre + 1)[:-1] if self.shift > 0 else np.zeros(0)
        pre = current.evaluate(t_pre) if len(t_pre) else (np.zeros((0, dof)),) * 3
        nt = np.asarray(new.times, float)
        npos = np.asarray(new.positions, float) + self.offset
        nacc = new.accelerations if new.accelerations is not None else np.zeros_like(npos)
        self.times = np.concatenate([t_pre - self.t_from, nt + self.shift])
        self.positions = np.vstack([pre[0], npos])
        self.velocities = np.vstack([pre[1], np.asarray(new.velocities, float)])
        self.accelerations = np.vstack([pre[2], np.asarray(nacc, float)])
        wi = np.asarray(getattr(new, "waypoint_indices", []), dtype=np.int64)
        self.waypoint_indices = np.concatenate([[0], wi + len(t_pre)]) if len(t_pre) else wi
        r_cur = rest_times(current)
        r_cur = r_cur[(r_cur >= self.t_from - _REST_TOL) & (r_cur <= self.t_commit + _REST_TOL)] - self.t_from
        self.rest = np.unique(np.round(np.concatenate([np.clip(r_cur, 0, None), rest_times(new) + self.shift]), 9))
        self.waypoints = np.asarray(getattr(new, "waypoints", npos[[0, -1]]), float) + self.offset

    @property
    def duration(self) -> float:
        return self.shift + float(self.new.duration)

    @property
    def dof(self) -> int:
        return int(self.positions.shape[1])

    def evaluate(self, t) -> tuple:
        """Positions, velocities and accelerations at times ``t`` (clamped to ``[0, duration]``)."""
        ts = np.clip(np.atleast_1d(np.asarray(t, dtype=np.float64)), 0.0, self.duration)
        dof = self.dof
        out = [np.zeros((len(ts), dof)) for _ in range(3)]
        pre = ts < self.shift
        if pre.any():
            for o, v in zip(out, self.current.evaluate(ts[pre] + self.t_from)):
                o[pre] = v
        if (~pre).any():
            vals = self.new.evaluate(ts[~pre] - self.shift)
            out[0][~pre] = vals[0] + self.offset
            out[1][~pre], out[2][~pre] = vals[1], vals[2]
        return tuple(out)

    def off_segment_mask(self) -> np.ndarray:
        """Samples strictly inside a smooth phase (:meth:`.timing.Trajectory.off_segment_mask`) of either part."""
        m = np.zeros(len(self.times), dtype=bool)
        k = len(self.times) - len(self.new.times)
        f = getattr(self.new, "off_segment_mask", None)
        if f is not None:
            m[k:] = f()
        return m


def splice(current, t_from: float, t_commit: float, new, continuous: Sequence[int] = ()) -> SplicedTrajectory:
    """The executing trajectory ``current`` from ``t_from`` to ``t_commit`` (a rest instant of it), then ``new``,
    which starts at rest where ``current`` is at ``t_commit``. ``continuous``: joint columns that wrap (the new
    plan's positions are moved by whole turns onto the executing trajectory's branch). Raises
    :class:`~psprm_core.errors.InputError` when ``new`` does not start there at rest."""
    q_c, v_c, _ = (a[0] for a in current.evaluate(np.array([t_commit])))
    n0 = np.asarray(new.positions, float)[0]
    offset = np.zeros_like(q_c)
    for c in continuous:
        offset[c] = 2 * math.pi * round((q_c[c] - n0[c]) / (2 * math.pi))
    gap = np.abs(n0 + offset - q_c)
    if gap.max() > 1e-4:
        raise InputError(f"the new trajectory starts {gap.max():.4f} from the committed state (joint {int(gap.argmax())})")
    if np.abs(v_c).max() > 1e-3 or np.abs(np.asarray(new.velocities, float)[0]).max() > 1e-3:
        raise InputError("a splice joins two trajectories at rest")
    return SplicedTrajectory(current, t_from, t_commit, new, offset)
