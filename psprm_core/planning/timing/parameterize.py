"""TOPP-RA time parameterisation of a joint-space path (:func:`time_parameterize`, the package's docstring):
straight runs and smooth phases timed rest-to-rest, the :class:`Trajectory` they make, the per-run profile cache,
and the checks of a timed path (limits, deviation, base segments)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ...errors import InputError
from .profiles import _profile_curve, _profile_toppra, _split_phases
from .runs import _Run, _evaluate_runs, _profile_analytic, _run_limits, _split_runs

logger = logging.getLogger(__name__)

#: Runs shorter than this (joint-space arc length) use the analytic profile: TOPP-RA's solver is not reliable there.
_TOPPRA_MIN_LENGTH = 1e-6
#: A smooth phase that takes this many times longer than stopping at each of its waypoints is timed stop by stop.
SMOOTH_SLOWER_LIMIT = 1.25



@dataclass
class Trajectory:
    """Time-parameterised joint trajectory.

    Attributes
    ----------
    times : np.ndarray
        ``(m,)`` strictly increasing sample times, starting at 0.
    positions, velocities, accelerations : np.ndarray
        ``(m, dof)`` samples.  Accelerations are right-continuous at the switching instants (the value of the phase
        starting there); the final sample (at rest) reports zero acceleration.
    joint_names : list of str
        Names of the dof.
    waypoint_times : np.ndarray
        ``(n,)`` time at which each input waypoint is reached.
    waypoint_indices : np.ndarray
        ``(n,)`` index in ``times`` of each input waypoint sample.
    waypoints : np.ndarray
        ``(n, dof)`` the (unwrapped) waypoints the trajectory passes through.
    """

    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    accelerations: np.ndarray
    joint_names: list[str]
    waypoint_times: np.ndarray
    waypoint_indices: np.ndarray
    waypoints: np.ndarray
    _runs: list[_Run] = field(default_factory=list, repr=False)

    @property
    def duration(self) -> float:
        """Total duration (s)."""
        return float(self.times[-1]) if self.times.size else 0.0

    @property
    def dof(self) -> int:
        """Number of joints."""
        return int(self.positions.shape[1])

    def off_segment_mask(self) -> np.ndarray:
        """``(m,)`` bool: samples strictly inside a smooth phase, i.e. off the straight segments between waypoints
        (all False for ``smooth=False``). Those are the samples a caller must collision-check itself."""
        mask = np.zeros(self.times.shape[0], dtype=bool)
        for run in self._runs:
            if run.curve is not None:
                mask |= (self.times > run.t0) & (self.times < run.t0 + run.duration)
        return mask

    def evaluate(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, velocities and accelerations at arbitrary times (clamped to ``[0, duration]``).

        Returns
        -------
        tuple of np.ndarray
            Each ``(len(t), dof)``.
        """
        ts = np.atleast_1d(np.asarray(t, dtype=np.float64))
        return _evaluate_runs(self._runs, ts, self.waypoints[-1])


# ====================================================================== geometry helpers
def _unwrap(waypoints: np.ndarray, continuous: Sequence[int]) -> np.ndarray:
    """Unwrap the continuous-angle columns so consecutive differences lie in (-pi, pi]."""
    q = np.array(waypoints, dtype=np.float64, copy=True)
    for j in continuous:
        q[:, j] = np.unwrap(q[:, j])
    return q


def _dedupe(q: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Drop consecutive duplicate waypoints; returns the kept points and, per input waypoint, its kept index."""
    keep = [0]
    owner = np.zeros(q.shape[0], dtype=np.int64)
    for i in range(1, q.shape[0]):
        if np.linalg.norm(q[i] - q[keep[-1]]) > tol:
            keep.append(i)
        owner[i] = len(keep) - 1
    return q[keep], owner


def check_base_segments(
    waypoints: np.ndarray,
    base_indices: tuple[int, int, int],
    tol: float = 1e-6,
    allow_reverse: bool = True,
) -> list[str]:
    """Check the differential-drive guarantee: each segment is a pure rotation or a translation along the heading.

    Parameters
    ----------
    waypoints : np.ndarray
        ``(n, dof)`` joint-space waypoints.
    base_indices : tuple of int
        Columns of ``(x, y, theta)``.
    tol : float
        Tolerance on the lateral displacement (m) and on the heading change during a translation (rad).
    allow_reverse : bool
        Accept translations against the heading (driving backwards).

    Returns
    -------
    list of str
        One message per violating segment (empty when the path is valid).
    """
    ix, iy, it = base_indices
    q = np.asarray(waypoints, dtype=np.float64)
    problems: list[str] = []
    for i in range(q.shape[0] - 1):
        dx, dy = q[i + 1, ix] - q[i, ix], q[i + 1, iy] - q[i, iy]
        dth = q[i + 1, it] - q[i, it]
        dist = math.hypot(dx, dy)
        if dist <= tol:
            continue  # pure rotation (or no base motion)
        if abs(dth) > tol:
            problems.append(f"segment {i}: base translates {dist:.3g} m and rotates {dth:.3g} rad at once")
            continue
        c, s = math.cos(q[i, it]), math.sin(q[i, it])
        lateral = abs(-s * dx + c * dy)
        forward = c * dx + s * dy
        if lateral > tol:
            problems.append(f"segment {i}: base translation is {lateral:.3g} m off the heading")
        elif forward < 0 and not allow_reverse:
            problems.append(f"segment {i}: base drives backwards")
    return problems


def _knot_times(s: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """Times of the profile knots for constant path acceleration between knots: dt = 2 ds / (sd_i + sd_i+1)."""
    ds = np.diff(s)
    denom = sd[:-1] + sd[1:]
    if np.any((denom <= 0) & (ds > 0)):
        raise RuntimeError("path speed is zero on both ends of a grid interval: cannot move")
    with np.errstate(divide="ignore", invalid="ignore"):
        dt = np.where(ds > 0, 2.0 * ds / denom, 0.0)
    return np.concatenate([[0.0], np.cumsum(dt)])


# ====================================================================== public API
class ProfileCache:
    """The TOPP-RA profiles of smooth phases already timed, by the phase's exact waypoints and limits (least recently
    used first out, at most ``size``), with the choice made for each (smooth, or stop by stop when that was faster).
    Consecutive plans of a replanner share most of their route, hence most of their phases; a phase found here gets
    the profile TOPP-RA gave it before (the same arrays) and the same choice."""

    def __init__(self, size: int = 256):
        from collections import OrderedDict

        self.size = int(size)
        self._data: "OrderedDict[bytes, tuple]" = OrderedDict()
        self.hits = self.misses = 0

    @staticmethod
    def key(points: np.ndarray, v: np.ndarray, a: np.ndarray, n_grid: int) -> bytes:
        p = np.ascontiguousarray(points, dtype=np.float64)
        return b"".join([np.asarray(p.shape, np.int64).tobytes(), p.tobytes(), np.asarray(v, np.float64).tobytes(),
                         np.asarray(a, np.float64).tobytes(), np.int64(n_grid).tobytes()])

    def get(self, key: bytes):
        got = self._data.get(key)
        if got is None:
            self.misses += 1
            return None
        self._data.move_to_end(key)
        self.hits += 1
        return got[0].copy(), got[1].copy(), got[2]

    def put(self, key: bytes, s_knots: np.ndarray, sd_knots: np.ndarray, smooth_kept: bool) -> None:
        """Keep a phase's profile and whether it was kept smooth (else timed stop by stop)."""
        self._data[key] = (np.array(s_knots, dtype=np.float64), np.array(sd_knots, dtype=np.float64),
                           bool(smooth_kept))
        self._data.move_to_end(key)
        while len(self._data) > self.size:
            self._data.popitem(last=False)


def time_parameterize(
    waypoints: np.ndarray,
    vmax: np.ndarray | Sequence[float],
    amax: np.ndarray | Sequence[float],
    dt: float = 0.02,
    joint_names: Sequence[str] | None = None,
    continuous_joints: Sequence[int] = (),
    base_indices: tuple[int, int, int] | None = None,
    base_linear_limits: tuple[float, float] | None = None,
    validate_base: bool = True,
    base_tol: float = 1e-6,
    method: str = "toppra",
    n_grid: int = 60,
    collinear_tol: float = 1e-9,
    duplicate_tol: float = 1e-12,
    smooth: bool = False,
    profile_cache: "ProfileCache | None" = None,
) -> Trajectory:
    """Time-parameterise a piecewise-linear joint path exactly (stop at corners, time-optimal straight runs), or with
    ``smooth`` through the waypoints of each base phase (stops only where the base changes its motion).

    Parameters
    ----------
    waypoints : np.ndarray
        ``(n, dof)`` configurations (e.g. the node configurations of the A* path over the PS-PRM roadmap).
    vmax, amax : array-like
        ``(dof,)`` positive velocity and acceleration limits.
    dt : float
        Sampling period of the output (the waypoint instants and the final time are always sampled too).
    joint_names : sequence of str, optional
        Names of the dof (default ``q0, q1, ...``).
    continuous_joints : sequence of int
        Columns holding unbounded angles; unwrapped before timing.  The base theta (``base_indices[2]``) is always
        treated as continuous.
    base_indices : tuple of int, optional
        Columns ``(x, y, theta)`` of a differential-drive base.
    base_linear_limits : tuple of float, optional
        ``(v_lin, a_lin)`` limits on the norm of the base (x, y) velocity / acceleration (in addition to the per-joint
        limits of x and y).
    validate_base : bool
        Raise ``ValueError`` when a segment is neither a pure rotation nor a translation along the heading
        (see :func:`check_base_segments`).
    base_tol : float
        Tolerance of that check.
    method : {"toppra", "analytic"}
        Profile of each straight run.  ``"toppra"`` falls back to ``"analytic"`` (with a warning) when ``toppra`` is
        not installed or fails on a run, and for runs shorter than 1e-6.  Both give the same time-optimal profile up
        to TOPP-RA's solver tolerance (the analytic switching points are added to the TOPP-RA grid); ``"analytic"``
        is ~100x faster and avoids importing toppra (which imports matplotlib, ~2 s).
    n_grid : int
        TOPP-RA grid points per run.
    collinear_tol : float
        Consecutive segments whose unit directions satisfy ``d_i . d_i+1 >= 1 - collinear_tol`` form one run
        (passed without stopping).
    duplicate_tol : float
        Consecutive waypoints closer than this are merged.
    smooth : bool
        Smooth phases (module notes): the joints pass the waypoints of a base phase without stopping, on a PCHIP
        curve timed by TOPP-RA (``toppra`` required). A phase where it fails, or whose smooth timing takes more than
        ``SMOOTH_SLOWER_LIMIT`` times as long as stopping at its waypoints, is timed straight, stop by stop. The
        samples leave the straight segments between waypoints: collision-check them.

    Returns
    -------
    Trajectory
    """
    q_in = np.asarray(waypoints, dtype=np.float64)
    if q_in.ndim != 2 or q_in.shape[0] < 1:
        raise InputError("waypoints must be an (n, dof) array with n >= 1")
    n, dof = q_in.shape
    vmax_a = np.broadcast_to(np.asarray(vmax, dtype=np.float64), (dof,)).copy()
    amax_a = np.broadcast_to(np.asarray(amax, dtype=np.float64), (dof,)).copy()
    if np.any(~(vmax_a > 0)) or np.any(~(amax_a > 0)) or not (np.all(np.isfinite(vmax_a))
                                                             and np.all(np.isfinite(amax_a))):
        raise InputError("vmax and amax must be positive and finite")
    if not dt > 0:
        raise InputError("dt must be positive")
    names = list(joint_names) if joint_names is not None else [f"q{j}" for j in range(dof)]
    if len(names) != dof:
        raise InputError("joint_names must have one name per dof")
    continuous = set(int(j) for j in continuous_joints)
    if base_indices is not None:
        continuous.add(int(base_indices[2]))
    q = _unwrap(q_in, sorted(continuous))
    if base_indices is not None and validate_base:
        problems = check_base_segments(q, base_indices, tol=base_tol)
        if problems:
            raise InputError("base path is not differential-drive feasible: " + "; ".join(problems[:5]))
    if method == "toppra":
        try:
            import toppra  # noqa: F401
        except ImportError:
            logger.warning("toppra is not installed: using the analytic time-optimal profile")
            method = "analytic"
    if method not in ("toppra", "analytic"):
        raise InputError(f"unknown method {method!r}")

    qk, owner = _dedupe(q, duplicate_tol)
    q = qk[owner]  # waypoints merged as duplicates (closer than duplicate_tol) take their kept value exactly
    if smooth and qk.shape[0] > 2:
        try:
            import toppra  # noqa: F401
        except ImportError:
            logger.warning("toppra is not installed: smooth timing unavailable, stopping at every corner")
            smooth = False
    if qk.shape[0] <= 1:
        runs = []
    elif smooth:
        runs = _split_phases(qk, base_indices, collinear_tol, base_tol)
    else:
        runs = _split_runs(qk, collinear_tol)
    timed: list[_Run] = []
    constraint_cache: dict = {}
    for run in runs:
        if run.curve is None:
            timed.append(run)
            continue
        v, a = _run_limits(run, vmax_a, amax_a, base_indices, base_linear_limits)
        key = None if profile_cache is None else profile_cache.key(run.points, v, a, max(4, n_grid // 8))
        hit = None if key is None else profile_cache.get(key)
        if hit is not None and hit[2]:  # timed before, and kept smooth
            run.s_knots, run.sd_knots = hit[0], hit[1]
            timed.append(run)
            continue
        straight = _split_runs(run.points, collinear_tol)
        for r in straight:
            r.s_knots, r.sd_knots = _profile_analytic(r, *_run_limits(r, vmax_a, amax_a, base_indices,
                                                                      base_linear_limits))
        if hit is not None:  # timed before: stopping at its waypoints was faster
            timed.extend(straight)
            continue
        try:
            run.s_knots, run.sd_knots = _profile_curve(run, v, a, max(4, n_grid // 8), constraint_cache)
        except Exception as exc:  # toppra reports numerical failures in several ways
            logger.warning("toppra failed on a smooth phase (%s): timed straight, stop by stop", exc)
            timed.extend(straight)
            continue
        t_curve = float(_knot_times(run.s_knots, run.sd_knots)[-1])
        t_stops = sum(float(_knot_times(r.s_knots, r.sd_knots)[-1]) for r in straight)
        smooth_kept = not t_curve > SMOOTH_SLOWER_LIMIT * t_stops
        if key is not None:
            profile_cache.put(key, run.s_knots, run.sd_knots, smooth_kept)
        if not smooth_kept:  # sharp turns of the joints: stopping is faster
            logger.debug("smooth phase %.2f s vs %.2f s stopping at its waypoints: stops kept", t_curve, t_stops)
            timed.extend(straight)
        else:
            timed.append(run)
    runs = timed
    t0 = 0.0
    for run in runs:
        if run.curve is not None or len(run.s_knots):  # profiled above
            run.t_knots = _knot_times(run.s_knots, run.sd_knots)
            run.t0 = t0
            t0 += run.duration
            continue
        v, a = _run_limits(run, vmax_a, amax_a, base_indices, base_linear_limits)
        if method == "toppra" and run.length > _TOPPRA_MIN_LENGTH:
            try:
                run.s_knots, run.sd_knots = _profile_toppra(run, v, a, n_grid)
            except Exception as exc:  # toppra reports numerical failures in several ways
                logger.warning("toppra failed on a run of length %.3g (%s): analytic profile used", run.length, exc)
                run.s_knots, run.sd_knots = _profile_analytic(run, v, a)
        else:
            run.s_knots, run.sd_knots = _profile_analytic(run, v, a)
        run.t_knots = _knot_times(run.s_knots, run.sd_knots)
        run.t0 = t0
        t0 += run.duration
    logger.debug("timed %d waypoints as %d straight runs, duration %.3f s (%s)", n, len(runs), t0, method)

    # Time of every kept waypoint: run boundaries, plus interior (collinear) waypoints found on the profile.
    kept_times = _waypoint_times(runs)
    wp_times = kept_times[owner]
    grid = np.arange(0.0, t0, dt) if t0 > 0 else np.zeros(0)
    times = np.union1d(np.concatenate([grid, [t0]]), kept_times)
    times = _merge_close(times, kept_times, tol=1e-9)
    pos, vel, acc = _evaluate_runs(runs, times, qk[-1])
    wp_idx = np.searchsorted(times, wp_times)
    wp_idx = np.minimum(wp_idx, times.shape[0] - 1)
    pos[wp_idx] = q  # exact waypoint values at their instants
    return Trajectory(
        times=times, positions=pos, velocities=vel, accelerations=acc, joint_names=names,
        waypoint_times=wp_times, waypoint_indices=wp_idx, waypoints=q, _runs=runs,
    )


def _waypoint_times(runs: list[_Run]) -> np.ndarray:
    """Absolute time at which each kept waypoint is reached (inverse of s(t) at the run breakpoints)."""
    if not runs:
        return np.zeros(1)
    out = [0.0]
    for run in runs:
        for s_target in run.s_breaks[1:]:
            out.append(run.t0 + _time_at_s(run, float(s_target)))
    return np.asarray(out)


def _time_at_s(run: _Run, s_target: float) -> float:
    """Invert s(t) on a run (constant acceleration between knots)."""
    if s_target >= run.length:
        return run.duration
    sk, sdk, tk = run.s_knots, run.sd_knots, run.t_knots
    i = int(np.clip(np.searchsorted(sk, s_target, side="right") - 1, 0, sk.shape[0] - 2))
    ds = sk[i + 1] - sk[i]
    u = (sdk[i + 1] ** 2 - sdk[i] ** 2) / (2.0 * ds) if ds > 0 else 0.0
    rem = s_target - sk[i]
    if abs(u) < 1e-15:
        return float(tk[i] + (rem / sdk[i] if sdk[i] > 0 else 0.0))
    disc = max(sdk[i] ** 2 + 2.0 * u * rem, 0.0)
    return float(tk[i] + (math.sqrt(disc) - sdk[i]) / u)


def _merge_close(times: np.ndarray, keep: np.ndarray, tol: float) -> np.ndarray:
    """Drop grid samples closer than ``tol`` to a kept (waypoint) time, so times are strictly increasing."""
    out = [times[0]]
    keep_set = set(np.round(keep / tol).astype(np.int64).tolist())
    for t in times[1:]:
        if t - out[-1] > tol:
            out.append(t)
        elif int(round(t / tol)) in keep_set:
            out[-1] = t  # prefer the exact waypoint time
    return np.asarray(out)


def max_limit_violation(
    traj: Trajectory,
    vmax: np.ndarray | Sequence[float],
    amax: np.ndarray | Sequence[float],
    base_indices: tuple[int, int, int] | None = None,
    base_linear_limits: tuple[float, float] | None = None,
) -> float:
    """Largest relative limit excess over all samples: ``max(|v_j| / vmax_j, |a_j| / amax_j) - 1``, clipped at 0.

    With ``base_indices`` and ``base_linear_limits`` the norm of the base (x, y) velocity / acceleration is checked
    against ``(v_lin, a_lin)`` too.  0 means every sample is within the limits.
    """
    v = np.asarray(vmax, dtype=np.float64)
    a = np.asarray(amax, dtype=np.float64)
    ratios = [np.abs(traj.velocities) / v, np.abs(traj.accelerations) / a]
    if base_indices is not None and base_linear_limits is not None:
        ix, iy, _ = base_indices
        ratios.append(np.hypot(traj.velocities[:, ix], traj.velocities[:, iy])[:, None] / base_linear_limits[0])
        ratios.append(np.hypot(traj.accelerations[:, ix], traj.accelerations[:, iy])[:, None] / base_linear_limits[1])
    worst = max(float(r.max()) if r.size else 0.0 for r in ratios)
    return max(worst - 1.0, 0.0)


def path_deviation(traj: Trajectory) -> float:
    """Largest distance of a position sample from the piecewise-linear path through ``traj.waypoints``.

    Each sample is compared with the segment of the waypoint interval it falls in (by time), i.e. this measures that
    the trajectory follows the path segment by segment, not merely that it stays near it.
    """
    q = traj.waypoints
    if q.shape[0] < 2:
        return float(np.abs(traj.positions - q[0]).max())
    k = np.clip(np.searchsorted(traj.waypoint_times, traj.times, side="right") - 1, 0, q.shape[0] - 2)
    a, b = q[k], q[k + 1]
    ab = b - a
    denom = np.einsum("ij,ij->i", ab, ab)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.where(denom > 0, np.einsum("ij,ij->i", traj.positions - a, ab) / denom, 0.0)
    lam = np.clip(lam, 0.0, 1.0)
    closest = a + lam[:, None] * ab
    return float(np.linalg.norm(traj.positions - closest, axis=1).max())
