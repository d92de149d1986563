"""Trajectory acceptance of the robot adapter: whether and how a planned trajectory is executed (no ROS).

:class:`TrajectoryAcceptance` takes a planned trajectory (planning joints, times and positions), the measured
configuration and velocity of the base, and the trajectory under way (:class:`UnderWay`), and decides:

* a splice: the new trajectory continues the one under way (each of its configurations over its first
  ``SPLICE_CHECK_S`` within ``SPLICE_TOL_M``, whole robot, of the trajectory under way near the robot's time along
  it); the base then goes on from where it is, and the robot's time along the splice is its time along the trajectory
  under way less where the splice began on it (:func:`psprm_ros.robots.commands.splice_progress`); a splice that
  begins ahead of the robot is joined along the trajectory under way (:func:`psprm_ros.robots.commands.join_along`);
* the robot's progress along a trajectory that is no splice (:func:`psprm_ros.robots.commands.progress_offset`):
  a replan starts from the robot's state when planning began, which the robot has passed by the time it executes;
* the start checks: the first point within each controller's ``start_tolerance`` (for a splice: of the measured
  joint or of the trajectory under way at the robot's time, which the splice continues) and the base's
  ``start_tolerance_m`` / ``_rad`` of the measured state; and the path tolerance: the robot, braking from where it
  is (:func:`psprm_ros.robots.commands.braking_configurations`), within ``path_tolerance_m`` of the trajectory's
  configurations near its start, or, for a splice, of the trajectory under way.

The answer is a :class:`Verdict`: accepted with the trajectory trimmed to the robot's progress, refused with the
reason, or a stop (the robot is already at the end of the new trajectory). :class:`RestWatch` says when a braking
base has come to rest (a held plan starts then, a replan is asked for then); :func:`path_check` is the path
tolerance at every control step.
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import numpy as np

from psprm_core.tracking import CheckedPath, displacement

from . import adapters as ad

REST_MPS, REST_RADPS = 0.01, 0.02  # a base slower than this on both axes ...
REST_S = 0.1  # ... for this long is at rest
REST_WAIT_S = 2.0  # a replan pending "at rest" is asked for this long after the stop at the latest
SPLICE_TOL_M = 0.01  # a new trajectory this close to the one executing (whole robot) ...
# how far back along the trajectory under way a splice may begin: a splice starts where the robot was when the
# replan began, which it may have passed by seconds when a replan is slow (the server withdraws a splice it has
# passed altogether, so this bounds the planning and delivery time a splice can take)
SPLICE_LOOKBACK_S = 6.0
SPLICE_CHECK_S = 0.3  # ... over its first this many seconds continues it: a splice


@dataclasses.dataclass
class UnderWay:
    """The trajectory the robot executes: ``checked`` its configurations on the follower's clock (the path
    tolerance's), ``received`` (a :class:`~psprm_core.tracking.CheckedPath` of it as received, before its start was
    trimmed to the robot's progress; the time on it at the follower's start), ``tau`` the robot's time along it on
    the follower's clock, ``following`` whether the follower still follows it."""

    checked: Optional[CheckedPath]
    received: Optional[tuple]
    tau: float
    following: bool


@dataclasses.dataclass
class Verdict:
    """What becomes of a trajectory. Accepted: ``times``, ``positions``, ``velocities`` from the robot's progress on
    (``progress`` s into the trajectory as received), started ``lead`` s from now; ``checked`` its configurations for
    the path tolerance (None when that is off), ``received`` what a later splice is recognised against. Refused:
    ``reason``. ``stop``: not executed, the robot stops (it is at the end of the new trajectory). ``spliced``: it was
    recognised as a continuation of the trajectory under way (counted whether or not it was accepted)."""

    accepted: bool
    reason: str = ""
    stop: str = ""
    times: Optional[np.ndarray] = None
    positions: Optional[np.ndarray] = None
    velocities: Optional[np.ndarray] = None
    lead: float = 0.0
    progress: float = 0.0
    checked: Optional[CheckedPath] = None
    received: Optional[tuple] = None
    spliced: bool = False


class TrajectoryAcceptance:
    """Decides on each trajectory for one robot (a :class:`~psprm_core.robot.RobotModel`) and adapter config.

    ``names`` are the planning joints (the columns of every trajectory), ``limits`` the base follower's
    (:class:`psprm_ros.robots.base_follower.Limits`, for the braking distance; mobile robots)."""

    def __init__(self, robot, cfg: ad.AdapterConfig, names: Optional[Sequence[str]] = None, limits=None):
        self.robot = robot
        self.cfg = cfg
        self.names = list(robot.joint_names if names is None else names)
        self.limits = limits

    def lead(self) -> float:
        """How long after sending a trajectory that is no splice starts: the longest lead time of the controllers
        and the base (0 in Stretch's trajectory mode: a goal starts when the driver receives it)."""
        if self.cfg.base.mode == "stretch_trajectory":
            return 0.0
        return max([c.lead_time_s for c in self.cfg.controllers] + [self.cfg.base.lead_time_s])

    def navigation_refusal(self, P: np.ndarray, q: np.ndarray) -> str:
        """Stretch's navigation mode, where the driver aborts arm and head goals: the refusal of a plan that moves
        a joint other than the base's by more than the smallest start tolerance; "" when it may run."""
        d = self.cfg.driver
        if not (d.kind == "stretch" and d.mode == "navigation"):
            return ""
        mobile = self.robot.mobile
        moved = np.abs(P[:, 3:] - q[None, 3:]).max(0) if mobile else np.abs(P - q[None]).max(0)
        k = int(np.argmax(moved))
        tol = min(c.start_tolerance for c in self.cfg.controllers)
        if moved[k] > tol:
            j = self.names[(3 if mobile else 0) + k]
            return (f"navigation mode moves the base only, the plan moves {j} by {moved[k]:.3f} "
                    f"(use the trajectory-mode adapter)")
        return ""

    def splice(self, t: np.ndarray, P: np.ndarray, q: np.ndarray, under_way: Optional[UnderWay],
               window_s: float) -> tuple:
        """(deviation, why not, time along it): when a new trajectory continues the one being executed (each of its
        configurations over its first ``SPLICE_CHECK_S`` within ``SPLICE_TOL_M``, whole robot, of the executing
        trajectory's configurations near the robot's time along it): the measured configuration's deviation from
        the executing trajectory there, "" and the robot's time along the new trajectory (its time along the
        executing one less the latest time the new one's start lies on it; None if it lies on it nowhere); else None,
        the reason and None. The roadmap server's replans of a robot in motion are such splices
        (psprm_core.planning.execution): the trajectory under way up to a rest instant at least the planning and
        delivery time ahead, then the new plan."""
        if under_way is None or under_way.received is None:
            return None, "no trajectory under way", None
        if not under_way.following:
            return None, "the trajectory under way has ended or was stopped", None
        cur, (ref_path, ref_offset), tau = under_way.checked, under_way.received, under_way.tau
        w = window_s
        ts = np.linspace(0.0, min(SPLICE_CHECK_S, float(t[-1])), 6)
        X = np.stack([np.interp(ts, t, P[:, j]) for j in range(P.shape[1])], 1)
        # the splice's start lies behind the robot by the replan's planning and delivery time (possibly before the
        # point where this adapter joined the trajectory under way): look for it on that trajectory as received,
        # from SPLICE_LOOKBACK_S back to 1 s ahead (the server's estimate of the robot's progress may lead this one)
        half = 0.5 * (SPLICE_LOOKBACK_S + 1.0)
        off = float(ref_path.path_distances(X, tau + ref_offset + ts + 1.0 - half, max(w, half)).max())
        if off > SPLICE_TOL_M:
            return None, f"its first {ts[-1]:.1f} s lie {off:.3f} m from it (splice tolerance {SPLICE_TOL_M:g} m)", None
        at = ad.splice_progress(ref_path, tau + ref_offset, t, P, SPLICE_LOOKBACK_S, SPLICE_TOL_M)
        d = cur.deviation(q, tau, w)[0] if cur is not None else ref_path.deviation(q, tau + ref_offset, w)[0]
        return d, "", at

    def decide(self, t: np.ndarray, P: np.ndarray, V: Optional[np.ndarray], q: np.ndarray, velocity,
               under_way: Optional[UnderWay], path_tolerance_m: float, path_window_s: float) -> Verdict:
        """The verdict on a trajectory (``t`` (M,), ``P`` (M, dof), ``V`` (M, dof) or None) for the measured
        configuration ``q`` and base ``velocity`` (v, omega; mobile robots) while ``under_way`` executes."""
        robot, cfg = self.robot, self.cfg
        lead = self.lead()
        # a splice (the new trajectory continues the one the robot executes): the base goes on from where it is
        # now, and only the controllers' goals start a lead time ahead (controller_command trims them there)
        if robot.mobile:
            splice_d, not_splice, splice_tau = self.splice(t, P, q, under_way, path_window_s)
        else:
            splice_d, not_splice, splice_tau = None, "", None
        base_lead = 0.0 if splice_d is not None else lead
        if splice_tau is not None:
            # the splice begins ahead of the robot on the trajectory under way (the server's estimate of the robot's
            # progress led this one, or the robot lags its trajectory's clock, as in a turn on the spot): the robot
            # goes on along the trajectory under way, which the server checked, from the configuration of it nearest
            # the robot to the splice's start, and the path tolerance measures it against that
            ref_path, ref_offset = under_way.received
            tau_r = under_way.tau + ref_offset
            s0 = tau_r - splice_tau
            s_robot = ref_path.deviation(q, tau_r, path_window_s)[1]
            if s0 > s_robot + 1e-6:
                t, P, V = ad.join_along(ref_path, s_robot, s0, t, P, V)
                splice_tau = 0.0
        received, tau0 = (np.asarray(t, float) - t[0], P.copy()), 0.0
        vel = None
        if robot.mobile:
            vel = np.asarray(velocity, float).copy()
            # the robot drove on since the plan started from its state: start at its progress, not back at the start
            tau0 = ad.progress_offset(t, P, q, vel, base_lead, velocity_limits=robot.velocity,
                                      horizon_s=SPLICE_LOOKBACK_S if splice_d is not None else 1.5)
            if splice_tau is not None:
                # a splice repeats the trajectory under way up to its commit instant: the robot's time along it is
                # its time along the trajectory under way, less where the splice began on it; taken unless the
                # nearest configuration lies more than the splice tolerance nearer the robot
                d_s, d_n = displacement(robot, q, ad.sample_at(t, P, [splice_tau, tau0]))
                if d_s <= d_n + SPLICE_TOL_M:
                    tau0 = splice_tau
            if tau0 > 0:
                t, P, V = ad.trim_from(t - t[0], P, V, tau0)
                if len(t) <= 1:
                    return Verdict(False, stop="the robot is already at the end of the new trajectory")
        # a splice continues what the controllers follow: a joint that lags the trajectory under way (a head slewing
        # at its velocity limit) lags the splice by as much, which the replacement does not change; the start
        # tolerance then also admits a first point within it of the trajectory under way at the robot's time
        commanded = None
        if splice_d is not None and under_way.checked is not None:
            cur = under_way.checked
            commanded = ad.sample_at(cur.ts, cur.Q, [min(max(under_way.tau, 0.0), cur.duration)])[0]
        for c in cfg.controllers:
            ok, joint, err = ad.check_start(c, self.names, P[0], q, commanded)
            if not ok:
                where = "measured" if commanded is None else "measured and the commanded"
                return Verdict(False, reason=f"first point {err:.3f} from the {where} {joint} ({c.name}: tolerance "
                                             f"{c.start_tolerance})")
        if robot.mobile:
            ok, what, err = ad.check_base_start(cfg.base, P[0, :3], q[:3])
            if not ok:
                return Verdict(False, reason=f"first point {err:.3f} from the measured {what}")
        checked, tol, spliced = None, path_tolerance_m, False
        if tol > 0 and robot.mobile:
            checked = CheckedPath(robot, t, P)
            d = splice_d
            if d is not None:
                # a splice: the robot keeps following the trajectory it executes, which the new one continues; only
                # its distance from that one counts (as at every control step)
                spliced = True
            else:
                # where the robot is and where it would brake to: a base still moving on its last command
                # overshoots a trajectory that starts behind it (planned from where it was when planning began) by
                # that much
                probe = np.vstack([q[None], ad.braking_configurations(q, vel, self.limits)])
                d = max(checked.deviation(x, 0.0, path_window_s)[0] for x in probe)
            if d > tol:
                return Verdict(False, spliced=spliced,
                               reason=f"the robot, braking from where it is, comes {d:.3f} m from the trajectory's "
                                      f"configurations near its start (path tolerance {tol:g} m; not a continuation "
                                      f"of the motion under way: {not_splice})")
        return Verdict(True, times=t, positions=P, velocities=V, lead=base_lead, progress=tau0, checked=checked,
                       received=(CheckedPath(robot, *received), tau0) if robot.mobile else None, spliced=spliced)


def path_check(checked: CheckedPath, q: np.ndarray, tau: float, tolerance_m: float, window_s: float) -> tuple:
    """(deviation, why): the path tolerance at a control step, the measured configuration ``q`` against the
    trajectory's configurations within ``window_s`` of ``tau`` (:meth:`psprm_core.tracking.CheckedPath.deviation`);
    ``why`` is "" within ``tolerance_m`` (or with the tolerance off, 0), else the reason to stop."""
    d, _ = checked.deviation(q, tau, window_s)
    if tolerance_m > 0 and d > tolerance_m:
        return d, (f"off the checked path: {d:.3f} m from the trajectory's configurations "
                   f"(path tolerance {tolerance_m:g} m)")
    return d, ""


class RestWatch:
    """When a base that was stopped has come to rest: a replan pending "at rest" (``pending``, its reason) is asked
    for once the measured base velocity has stayed near zero for ``REST_S`` (or ``REST_WAIT_S`` after the stop, for
    a base that does not settle), so that the new plan starts where the robot stands, not where it was while braking.
    A plan that arrives while the base brakes is held until it rests (at most ``REST_WAIT_S``)."""

    def __init__(self):
        self.pending = ""
        self.stop_t: Optional[float] = None
        self.still_since: Optional[float] = None

    @staticmethod
    def moving(velocity) -> bool:
        """The measured base velocity (v, omega) is not that of a base at rest."""
        v, w = (abs(float(x)) for x in velocity)
        return v >= REST_MPS or w >= REST_RADPS

    def due(self, now: float, velocity) -> bool:
        """Whether the pending replan is to be asked for now (the base at rest, or ``REST_WAIT_S`` passed)."""
        v, w = (abs(float(x)) for x in velocity)
        if self.stop_t is None:
            self.stop_t = now
        if v < REST_MPS and w < REST_RADPS:
            self.still_since = now if self.still_since is None else self.still_since
        else:
            self.still_since = None
        return (self.still_since is not None and now - self.still_since >= REST_S) or now - self.stop_t >= REST_WAIT_S

    def clear(self) -> None:
        """Nothing pending (a replan was asked for, or a new plan came)."""
        self.pending, self.stop_t, self.still_since = "", None, None
