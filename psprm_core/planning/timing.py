"""Time parameterisation of a PS-PRM joint-space path (waypoints of the A* path over the roadmap, Eqs. 2-6).

The planner returns a piecewise-linear path in joint space: consecutive roadmap nodes joined by straight edges (the
edges whose perception cost Eq. 1 was evaluated on interpolated configurations).  :func:`time_parameterize` turns it
into a :class:`Trajectory` that respects per-joint velocity and acceleration limits while following that path
**exactly**:

* no corner blending: at a corner the path direction is discontinuous, so finite accelerations require the robot to
  be at rest there; every corner is therefore a stop, and each straight *run* between corners is time-parameterised
  rest-to-rest.  Consecutive segments that are collinear and point the same way (within ``collinear_tol``) are merged
  into one run, so intermediate waypoints on a straight line are passed without stopping.
* along a run, TOPP-RA (``toppra``, ``method="toppra"``) solves the time-optimal path parameterisation with the joint
  velocity and acceleration constraints on a grid of path positions; since the run is a straight line
  (:math:`q'' = 0`) the constant-acceleration interpolation between grid points satisfies the limits everywhere and
  keeps every sample on the line.  ``method="analytic"`` uses the closed-form time-optimal trapezoidal / triangular
  profile of a straight rest-to-rest run (identical constraints; it is also the fallback when ``toppra`` is missing).
* mobile base: three dof ``(x, y, theta)`` of a differential drive.  The caller guarantees that between consecutive
  waypoints the base either rotates in place or translates along its heading; linear interpolation in joint space
  keeps exactly that geometry (theta constant during translations, x/y constant during rotations), and since every
  sample lies on the joint-space segment the base never leaves it.  :func:`check_base_segments` verifies the
  guarantee (``validate_base=True``).  An optional linear speed / acceleration limit of the base (norm of the (x, y)
  velocity) is enforced exactly by folding it, per straight run, into the x/y joint limits.
* ``smooth=True`` (what the planner uses on mobile robots): consecutive segments in which the base keeps one motion
  (drives along one line in one direction, turns one way, or stands still) form one *phase*, timed rest-to-rest as a
  whole: the joints follow a shape-preserving cubic (PCHIP) through the phase's waypoints, parameterised by the base's
  progress (so the base still moves exactly along its line or turns in place), and TOPP-RA times it. The robot then
  stops only where the base changes its motion (the drive corners), not at every re-aiming knot. Between two waypoints
  a PCHIP joint stays within the two waypoint values (no overshoot) but the configuration leaves the straight
  segment: the caller must collision-check the samples (the planner does, and falls back to ``smooth=False``).
  Samples between TOPP-RA's grid points are checked against the limits and the phase is slowed down uniformly when a
  limit is exceeded.
* continuous (unbounded angle) joints are unwrapped (``np.unwrap``) before timing, so they take the short way; the
  output keeps the unwrapped values (start equals the input start, later values may differ by multiples of
  :math:`2\\pi`).
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from ..errors import InputError

logger = logging.getLogger(__name__)

#: Runs shorter than this (joint-space arc length) use the analytic profile: TOPP-RA's solver is not reliable there.
_TOPPRA_MIN_LENGTH = 1e-6
#: A smooth phase is slowed down to this fraction of its limits where its dense samples reach them (the limits hold
#: exactly at TOPP-RA's grid points; between samples the cubic terms can exceed the sampled maximum by ~1e-4).
_CURVE_MARGIN = 0.995
#: A smooth phase that takes this many times longer than stopping at each of its waypoints is timed stop by stop.
SMOOTH_SLOWER_LIMIT = 1.25

__all__ = [
    "Trajectory",
    "check_base_segments",
    "max_limit_violation",
    "path_deviation",
    "time_parameterize",
]


# ====================================================================== data
@dataclass
class _Run:
    """A straight, rest-to-rest run of the path, parameterised by joint-space arc length ``s``."""

    points: np.ndarray  # (k, dof) waypoints of the run (collinear), first/last are the run ends
    s_breaks: np.ndarray  # (k,) arc length of each waypoint along the run
    dirs: np.ndarray  # (k-1, dof) unit direction dq/ds of each piece
    s_knots: np.ndarray = field(default_factory=lambda: np.zeros(0))  # profile knots in s
    sd_knots: np.ndarray = field(default_factory=lambda: np.zeros(0))  # path speed at the knots
    t_knots: np.ndarray = field(default_factory=lambda: np.zeros(0))  # times of the knots (relative to run start)
    t0: float = 0.0  # absolute start time
    curve: Any = None  # smooth phase: _CurvePath q(s) through ``points`` at ``s_breaks`` (None: straight pieces)

    @property
    def length(self) -> float:
        return float(self.s_breaks[-1])

    @property
    def duration(self) -> float:
        return float(self.t_knots[-1])


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


def _split_runs(q: np.ndarray, collinear_tol: float) -> list[_Run]:
    """Split a piecewise-linear path into straight runs (stops at every non-collinear corner)."""
    seg = np.diff(q, axis=0)
    lengths = np.linalg.norm(seg, axis=1)
    dirs = seg / lengths[:, None]
    runs: list[_Run] = []
    start = 0
    for i in range(1, seg.shape[0] + 1):
        corner = i == seg.shape[0] or float(dirs[i] @ dirs[i - 1]) < 1.0 - collinear_tol
        if corner:
            s = np.concatenate([[0.0], np.cumsum(lengths[start:i])])
            runs.append(_Run(points=q[start : i + 1], s_breaks=s, dirs=dirs[start:i]))
            start = i
    return runs


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


# ====================================================================== limits of a run
def _run_limits(
    run: _Run,
    vmax: np.ndarray,
    amax: np.ndarray,
    base_indices: tuple[int, int, int] | None,
    base_linear_limits: tuple[float, float] | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-joint limits for a run; the base linear (x, y)-norm limits are folded into the x/y joint limits.

    Along a straight run the (x, y) direction is fixed, so ``||(x', y')|| sd <= v_lin`` is equivalent to
    ``|x'| sd <= v_lin |x'| / ||(x', y')||`` (and the same for y and for the acceleration).
    """
    v = vmax.astype(np.float64).copy()
    a = amax.astype(np.float64).copy()
    if base_indices is not None and base_linear_limits is not None:
        ix, iy, _ = base_indices
        d = run.dirs[0]
        nxy = math.hypot(d[ix], d[iy])
        if nxy > 1e-12:
            v_lin, a_lin = base_linear_limits
            for j in (ix, iy):
                frac = abs(d[j]) / nxy
                if frac > 1e-12:  # a negligible component keeps its own limit (denormal folds stall TOPP-RA)
                    v[j] = min(v[j], v_lin * frac)
                    a[j] = min(a[j], a_lin * frac)
    return v, a


def _scalar_limits(run: _Run, v: np.ndarray, a: np.ndarray) -> tuple[float, float]:
    """Path-speed / path-acceleration bounds of a straight run: min_j v_j / |dq_j/ds| over its pieces."""
    absd = np.abs(run.dirs)
    with np.errstate(divide="ignore", over="ignore"):
        sv = np.where(absd > 0, v[None, :] / absd, np.inf).min()
        sa = np.where(absd > 0, a[None, :] / absd, np.inf).min()
    return float(sv), float(sa)


# ====================================================================== profiles along a run
def _profile_analytic(run: _Run, v: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form time-optimal rest-to-rest profile (trapezoid or triangle) of a straight run."""
    length = run.length
    sv, sa = _scalar_limits(run, v, a)
    d_acc = sv * sv / (2.0 * sa)
    if 2.0 * d_acc < length:
        return np.array([0.0, d_acc, length - d_acc, length]), np.array([0.0, sv, sv, 0.0])
    peak = math.sqrt(length * sa)
    return np.array([0.0, 0.5 * length, length]), np.array([0.0, peak, 0.0])


class _LinearRunPath:
    """Straight run as a ``toppra`` geometric path q(s), s in [0, L] (arc length); q'' = 0."""

    def __init__(self, run: _Run) -> None:
        self._run = run

    def __call__(self, s: float | np.ndarray, order: int = 0) -> np.ndarray:
        ss = np.atleast_1d(np.asarray(s, dtype=np.float64))
        out = _positions_on_run(self._run, ss) if order == 0 else (
            _dirs_on_run(self._run, ss) if order == 1 else np.zeros((ss.shape[0], self.dof))
        )
        return out[0] if np.ndim(s) == 0 else out

    @property
    def dof(self) -> int:
        return int(self._run.points.shape[1])

    @property
    def path_interval(self) -> np.ndarray:
        return np.array([0.0, self._run.length])

    @property
    def waypoints(self) -> tuple[np.ndarray, np.ndarray]:
        return self._run.s_breaks, self._run.points


def _pchip_slopes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Fritsch-Carlson slopes of the monotone cubic (PCHIP) through (x, y (n, d)): the weighted harmonic mean of the
    neighbouring secants where they agree in sign, 0 at local extrema; shape-preserving one-sided end slopes. The
    same slopes as ``scipy.interpolate.PchipInterpolator`` (the tests compare them)."""
    h = np.diff(x)[:, None]
    delta = np.diff(y, axis=0) / h
    m = np.zeros_like(y)
    if y.shape[0] == 2:
        m[:] = delta[0]
        return m
    w1, w2 = 2.0 * h[1:] + h[:-1], h[1:] + 2.0 * h[:-1]
    d0, d1 = delta[:-1], delta[1:]
    agree = (np.sign(d0) * np.sign(d1)) > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        m[1:-1] = np.where(agree, (w1 + w2) / (w1 / d0 + w2 / d1), 0.0)

    def edge(h0, h1, m0, m1):
        d = ((2.0 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
        d = np.where(np.sign(d) != np.sign(m0), 0.0, d)
        return np.where((np.sign(m0) != np.sign(m1)) & (np.abs(d) > 3.0 * np.abs(m0)), 3.0 * m0, d)

    m[0] = edge(h[0], h[1], delta[0], delta[1])
    m[-1] = edge(h[-1], h[-2], delta[-1], delta[-2])
    return m


class _CurvePath:
    """A smooth phase as a ``toppra`` geometric path: PCHIP through the phase's waypoints at ``s_breaks``
    (cubic Hermite pieces with :func:`_pchip_slopes`; evaluated with its first and second derivatives)."""

    def __init__(self, s_breaks: np.ndarray, points: np.ndarray) -> None:
        self._s = np.asarray(s_breaks, dtype=np.float64)
        self._points = np.asarray(points, dtype=np.float64)
        self._m = _pchip_slopes(self._s, self._points)

    def __call__(self, s: float | np.ndarray, order: int = 0) -> np.ndarray:
        scalar = np.ndim(s) == 0
        ss = np.clip(np.atleast_1d(np.asarray(s, dtype=np.float64)), self._s[0], self._s[-1])
        k = np.clip(np.searchsorted(self._s, ss, side="right") - 1, 0, self._s.shape[0] - 2)
        h = (self._s[k + 1] - self._s[k])[:, None]
        t = ((ss - self._s[k])[:, None]) / h
        y0, y1 = self._points[k], self._points[k + 1]
        m0, m1 = self._m[k] * h, self._m[k + 1] * h  # slopes in the unit parameter t
        if order == 0:
            t2, t3 = t * t, t * t * t
            out = (2 * t3 - 3 * t2 + 1) * y0 + (t3 - 2 * t2 + t) * m0 + (-2 * t3 + 3 * t2) * y1 + (t3 - t2) * m1
        elif order == 1:
            t2 = t * t
            out = ((6 * t2 - 6 * t) * y0 + (3 * t2 - 4 * t + 1) * m0 + (-6 * t2 + 6 * t) * y1 + (3 * t2 - 2 * t) * m1) / h
        else:
            out = ((12 * t - 6) * y0 + (6 * t - 4) * m0 + (-12 * t + 6) * y1 + (6 * t - 2) * m1) / (h * h)
        return out[0] if scalar else out

    @property
    def dof(self) -> int:
        return int(self._points.shape[1])

    @property
    def path_interval(self) -> np.ndarray:
        return np.array([self._s[0], self._s[-1]])

    @property
    def waypoints(self) -> tuple[np.ndarray, np.ndarray]:
        return self._s, self._points


def _base_signature(seg: np.ndarray, start: np.ndarray, base_indices: tuple[int, int, int] | None,
                    tol: float) -> tuple:
    """What the base does on a segment: ("T", heading, direction) drive, ("R", direction) turn, ("S",) stand."""
    if base_indices is None:
        return ("S",)
    ix, iy, it = base_indices
    if math.hypot(seg[ix], seg[iy]) > tol:
        fwd = math.cos(start[it]) * seg[ix] + math.sin(start[it]) * seg[iy]
        return ("T", float(start[it]), fwd > 0)
    if abs(seg[it]) > tol:
        return ("R", seg[it] > 0)
    return ("S",)


def _same_phase(a: tuple, b: tuple, tol: float) -> bool:
    if a[0] != b[0]:
        return False
    if a[0] == "T":
        return abs(a[1] - b[1]) <= tol and a[2] == b[2]
    return a == b


def _split_phases(q: np.ndarray, base_indices: tuple[int, int, int] | None, collinear_tol: float,
                  tol: float) -> list[_Run]:
    """Straight runs (collinear segments) and smooth phases (segments of one base motion, see the module notes)."""
    seg = np.diff(q, axis=0)
    sigs = [_base_signature(seg[i], q[i], base_indices, tol) for i in range(seg.shape[0])]
    runs: list[_Run] = []
    start = 0
    for i in range(1, seg.shape[0] + 1):
        if i < seg.shape[0] and _same_phase(sigs[i], sigs[i - 1], tol):
            continue
        pts = q[start : i + 1]
        straight = _split_runs(pts, collinear_tol)
        if len(straight) == 1:
            runs.extend(straight)
        else:
            kind = sigs[start][0]
            d = np.diff(pts, axis=0)
            if kind == "T":
                ix, iy, _ = base_indices  # type: ignore[misc]
                steps = np.hypot(d[:, ix], d[:, iy])
            elif kind == "R":
                steps = np.abs(d[:, base_indices[2]])  # type: ignore[index]
            else:
                steps = np.linalg.norm(d, axis=1)
            sb = np.concatenate([[0.0], np.cumsum(steps)])
            dirs = d / np.linalg.norm(d, axis=1)[:, None]
            runs.append(_Run(points=pts, s_breaks=sb, dirs=dirs, curve=_CurvePath(sb, pts)))
        start = i
    return runs


def _curve_limit_ratio(run: _Run, v: np.ndarray, a: np.ndarray, per_interval: int = 8) -> float:
    """max over dense samples of a smooth phase of max(|q'| sd / v, sqrt(|q'' sd^2 + q' sdd| / a)).

    Each grid interval is sampled at both ends (the left end from inside: q'' of a PCHIP piece is linear and jumps at
    the waypoints, so the acceleration peaks at interval ends) and ``per_interval`` - 1 points between."""
    S, SD = run.s_knots, run.sd_knots
    f = np.linspace(0.0, 1.0, per_interval + 1)
    f[-1] = 1.0 - 1e-9
    k = f.shape[0]
    ds = np.diff(S)
    s = (S[:-1, None] + f[None, :] * ds[:, None]).reshape(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(ds > 0, (SD[1:] ** 2 - SD[:-1] ** 2) / (2.0 * ds), 0.0)
    u = np.repeat(u, k)
    sd2 = np.maximum(np.repeat(SD[:-1] ** 2, k) + 2.0 * u * (s - np.repeat(S[:-1], k)), 0.0)
    d1, d2 = run.curve(s, 1), run.curve(s, 2)
    vel = np.abs(d1) * np.sqrt(sd2)[:, None] / v
    acc = np.abs(d2 * sd2[:, None] + d1 * u[:, None]) / a
    return float(max(vel.max(initial=0.0), math.sqrt(acc.max(initial=0.0))))


@functools.lru_cache(maxsize=1)
def _memoize_solver_lookup() -> None:
    """toppra's TOPP-RA constructor asks importlib for its optional solver packages (qpOASES, cvxpy) on every call,
    whichever solver it is given: about 3 ms per replan of 10 phases. Their presence does not change while the
    process runs, so the answer is looked up once and ``toppra.solverwrapper.available_solvers`` returns it from then
    on (a process-wide change of toppra's module; the same answer)."""
    import toppra.solverwrapper as sw

    found = sw.available_solvers(output_msg=False)
    sw.available_solvers = lambda output_msg=True: found


@functools.lru_cache(maxsize=1)
def _quiet_constraints() -> tuple[type, type]:
    """toppra's joint velocity / acceleration constraints without the log string their constructors build from
    the limit arrays (numpy array printing, ~1 ms per pair: as long as the TOPP-RA solve of a short phase).
    Limits are validated by :func:`time_parameterize` (positive, finite)."""
    import toppra.constraint as ta_con

    class QuietVelocity(ta_con.JointVelocityConstraint):
        def _assert_valid_limits(self) -> None:
            if self.vlim.shape[1] != 2 or np.any(self.vlim[:, 0] >= self.vlim[:, 1]):
                raise InputError("bad velocity limits")
            self._format_string = "    Velocity limit (psprm)\n"

    class QuietAcceleration(ta_con.JointAccelerationConstraint):
        def __init__(self, alim: np.ndarray) -> None:  # pylint: disable=super-init-not-called
            ta_con.LinearConstraint.__init__(self)
            self.alim = np.array(alim, dtype=float)
            if self.alim.ndim != 2 or self.alim.shape[1] != 2 or np.any(self.alim[:, 0] >= self.alim[:, 1]):
                raise InputError("bad acceleration limits")
            self.dof = self.alim.shape[0]
            self.set_discretization_type(ta_con.DiscretizationType.Interpolation)
            self._format_string = "    Acceleration limit (psprm)\n"
            self.identical = True

    return QuietVelocity, QuietAcceleration


def _profile_curve(run: _Run, v: np.ndarray, a: np.ndarray, n_grid: int,
                   cache: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """TOPP-RA rest-to-rest profile of a smooth phase, slowed down uniformly if a sample between grid points
    exceeds a limit (TOPP-RA enforces them at the grid points). ``cache`` keeps the constraint objects per limit
    vector (their constructors format the limits into log strings: ~2 ms each)."""
    import toppra.algorithm as ta_algo

    _memoize_solver_lookup()
    sb = run.s_breaks  # uniform points, the waypoints and 2 points inside every PCHIP piece
    inner = (sb[:-1, None] + np.diff(sb)[:, None] * np.array([1.0 / 3.0, 2.0 / 3.0])[None, :]).reshape(-1)
    grid = np.unique(np.concatenate([np.linspace(0.0, run.length, n_grid), sb, inner]))
    key = (v.tobytes(), a.tobytes())
    constraints = None if cache is None else cache.get(key)
    if constraints is None:
        vel_cls, acc_cls = _quiet_constraints()
        constraints = [vel_cls(np.stack([-v, v], axis=1)), acc_cls(np.stack([-a, a], axis=1))]
        if cache is not None:
            cache[key] = constraints
    instance = ta_algo.TOPPRA(constraints, run.curve, gridpoints=grid, solver_wrapper="seidel")
    _, sd, _, _ = instance.compute_parameterization(0.0, 0.0, return_data=True)
    if sd is None or np.any(~np.isfinite(sd)):
        raise RuntimeError("toppra failed to parameterise a smooth phase (numerical failure)")
    sd = np.maximum(np.asarray(sd, dtype=np.float64), 0.0)
    sd[0] = sd[-1] = 0.0
    run.s_knots, run.sd_knots = grid, sd
    ratio = _curve_limit_ratio(run, v, a)
    if ratio > _CURVE_MARGIN:  # sd / r scales velocities by 1 / r and accelerations by 1 / r^2
        sd = sd * (_CURVE_MARGIN / ratio)
    return grid, sd


def _profile_toppra(run: _Run, v: np.ndarray, a: np.ndarray, n_grid: int) -> tuple[np.ndarray, np.ndarray]:
    """TOPP-RA rest-to-rest profile of a straight run on ``n_grid`` + breakpoint grid points."""
    import toppra.algorithm as ta_algo
    import toppra.constraint as ta_con

    _memoize_solver_lookup()
    moving = np.any(np.abs(run.dirs) > 0, axis=0)
    v = np.where(moving, v, np.maximum(v, 1.0))  # joints that do not move: any finite limit
    a = np.where(moving, a, np.maximum(a, 1.0))
    path = _LinearRunPath(run)
    # Grid: uniform points, the run's waypoints and the switching points of the time-optimal bang-coast-bang
    # profile (TOPP-RA keeps the path acceleration constant between grid points, so without these the accelerating
    # phase would be smeared over a whole grid interval and the result would be a few % slower than optimal).
    switch, _ = _profile_analytic(run, v, a)
    grid = np.unique(np.concatenate([np.linspace(0.0, run.length, n_grid), run.s_breaks, switch]))
    grid[0], grid[-1] = 0.0, run.length
    constraints = [
        ta_con.JointVelocityConstraint(np.stack([-v, v], axis=1)),
        ta_con.JointAccelerationConstraint(np.stack([-a, a], axis=1)),
    ]
    instance = ta_algo.TOPPRA(constraints, path, gridpoints=grid, solver_wrapper="seidel")
    _, sd, _, _ = instance.compute_parameterization(0.0, 0.0, return_data=True)
    if sd is None or np.any(~np.isfinite(sd)):
        raise RuntimeError("toppra failed to parameterise a straight run (numerical failure)")
    sd = np.maximum(np.asarray(sd, dtype=np.float64), 0.0)
    sd[0] = sd[-1] = 0.0
    return grid, sd


def _knot_times(s: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """Times of the profile knots for constant path acceleration between knots: dt = 2 ds / (sd_i + sd_i+1)."""
    ds = np.diff(s)
    denom = sd[:-1] + sd[1:]
    if np.any((denom <= 0) & (ds > 0)):
        raise RuntimeError("path speed is zero on both ends of a grid interval: cannot move")
    with np.errstate(divide="ignore", invalid="ignore"):
        dt = np.where(ds > 0, 2.0 * ds / denom, 0.0)
    return np.concatenate([[0.0], np.cumsum(dt)])


# ====================================================================== evaluation
def _positions_on_run(run: _Run, s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, run.length)
    k = np.clip(np.searchsorted(run.s_breaks, s, side="right") - 1, 0, run.dirs.shape[0] - 1)
    return run.points[k] + (s - run.s_breaks[k])[:, None] * run.dirs[k]


def _dirs_on_run(run: _Run, s: np.ndarray) -> np.ndarray:
    k = np.clip(np.searchsorted(run.s_breaks, s, side="right") - 1, 0, run.dirs.shape[0] - 1)
    return run.dirs[k]


def _evaluate_runs(
    runs: list[_Run], t: np.ndarray, last: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, velocities and accelerations at times ``t`` (after the end: ``last`` at rest).

    Vectorised over all runs: the runs' profile knots are laid end to end in time and in a global arc length
    (run offset + s), so one ``searchsorted`` finds every sample's profile interval and one more its path piece.
    At a run boundary both runs contribute a knot at the same instant and position; a sample at that instant falls
    in the later run (as its first interval), like a sample at a run's local time 0.
    """
    dof = last.shape[0]
    pos = np.tile(last, (t.shape[0], 1))
    vel = np.zeros((t.shape[0], dof))
    acc = np.zeros((t.shape[0], dof))
    if not runs:
        return pos, vel, acc
    if any(r.curve is not None for r in runs):
        return _evaluate_runs_loop(runs, t, pos, vel, acc)
    off = np.concatenate([[0.0], np.cumsum([r.length for r in runs])[:-1]])
    T = np.concatenate([r.t0 + r.t_knots for r in runs])
    S = np.concatenate([o + r.s_knots for o, r in zip(off, runs)])
    SD = np.concatenate([r.sd_knots for r in runs])
    B = np.concatenate([o + r.s_breaks[:-1] for o, r in zip(off, runs)])
    P = np.concatenate([r.points[:-1] for r in runs])
    D = np.concatenate([r.dirs for r in runs])
    end = runs[-1].t0 + runs[-1].duration
    m = t < end
    s, sd, u = _profile_at(T, S, SD, t[m])
    k = np.clip(np.searchsorted(B, s, side="right") - 1, 0, B.shape[0] - 1)
    pos[m] = P[k] + (s - B[k])[:, None] * D[k]
    vel[m] = D[k] * sd[:, None]
    acc[m] = D[k] * u[:, None]
    return pos, vel, acc


def _profile_at(T: np.ndarray, S: np.ndarray, SD: np.ndarray, tau: np.ndarray) -> tuple:
    """Path position, speed and acceleration (s, sd, sdd) at times ``tau`` of a profile with knots (T, S, SD) and
    constant path acceleration between knots."""
    i = np.clip(np.searchsorted(T, tau, side="right") - 1, 0, T.shape[0] - 2)
    ds = S[i + 1] - S[i]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(ds > 0, (SD[i + 1] ** 2 - SD[i] ** 2) / (2.0 * ds), 0.0)
    dt = np.clip(tau - T[i], 0.0, T[i + 1] - T[i])
    s = np.minimum(S[i] + SD[i] * dt + 0.5 * u * dt * dt, S[i + 1])
    return s, np.maximum(SD[i] + u * dt, 0.0), u


def _evaluate_runs_loop(runs: list[_Run], t: np.ndarray, pos: np.ndarray, vel: np.ndarray,
                        acc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_evaluate_runs` run by run (smooth phases evaluate their curve and its derivatives)."""
    for k, r in enumerate(runs):
        end = r.t0 + r.duration
        m = (t >= r.t0) & (t < end) if k else t < end
        if not m.any():
            continue
        s, sd, u = _profile_at(r.t_knots, r.s_knots, r.sd_knots, t[m] - r.t0)
        if r.curve is None:
            d = _dirs_on_run(r, s)
            pos[m], vel[m], acc[m] = _positions_on_run(r, s), d * sd[:, None], d * u[:, None]
        else:
            d1 = r.curve(s, 1)
            pos[m] = r.curve(s, 0)
            vel[m] = d1 * sd[:, None]
            acc[m] = r.curve(s, 2) * (sd * sd)[:, None] + d1 * u[:, None]
    return pos, vel, acc


# ====================================================================== public API
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
        straight = _split_runs(run.points, collinear_tol)
        for r in straight:
            r.s_knots, r.sd_knots = _profile_analytic(r, *_run_limits(r, vmax_a, amax_a, base_indices,
                                                                      base_linear_limits))
        try:
            run.s_knots, run.sd_knots = _profile_curve(run, v, a, max(4, n_grid // 8), constraint_cache)
        except Exception as exc:  # toppra reports numerical failures in several ways
            logger.warning("toppra failed on a smooth phase (%s): timed straight, stop by stop", exc)
            timed.extend(straight)
            continue
        t_curve = float(_knot_times(run.s_knots, run.sd_knots)[-1])
        t_stops = sum(float(_knot_times(r.s_knots, r.sd_knots)[-1]) for r in straight)
        if t_curve > SMOOTH_SLOWER_LIMIT * t_stops:  # sharp turns of the joints: stopping is faster
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
