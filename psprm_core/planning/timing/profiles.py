"""Speed profiles of the timed path's runs beyond the analytic one: TOPP-RA on straight runs, and smooth base phases
(a monotone cubic through a phase's knots, timed by TOPP-RA within the limits)."""

from __future__ import annotations

import functools
import logging
import math

import numpy as np

from ...errors import InputError

from .runs import _Run, _dirs_on_run, _positions_on_run, _profile_analytic, _split_runs

logger = logging.getLogger(__name__)


#: A smooth phase is slowed down to this fraction of its limits where its dense samples reach them (the limits hold
#: exactly at TOPP-RA's grid points; between samples the cubic terms can exceed the sampled maximum by ~1e-4).
_CURVE_MARGIN = 0.995


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
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # masked where the secants disagree
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
            out = ((6 * t2 - 6 * t) * y0 + (3 * t2 - 4 * t + 1) * m0 + (-6 * t2 + 6 * t) * y1
                   + (3 * t2 - 2 * t) * m1) / h
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
