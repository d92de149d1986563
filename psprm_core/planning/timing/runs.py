"""Straight rest-to-rest runs of a timed path (:func:`~.timing.time_parameterize`): their limits, the analytic
speed profile, and the evaluation of positions and velocities along them."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np


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


def _positions_on_run(run: _Run, s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, run.length)
    k = np.clip(np.searchsorted(run.s_breaks, s, side="right") - 1, 0, run.dirs.shape[0] - 1)
    return run.points[k] + (s - run.s_breaks[k])[:, None] * run.dirs[k]


def _dirs_on_run(run: _Run, s: np.ndarray) -> np.ndarray:
    k = np.clip(np.searchsorted(run.s_breaks, s, side="right") - 1, 0, run.dirs.shape[0] - 1)
    return run.dirs[k]


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


def _run_limits(
    run: _Run,
    vmax: np.ndarray,
    amax: np.ndarray,
    base_indices: tuple[int, int, int] | None,
    base_linear_limits: tuple[float, float] | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-joint limits for a run; the base linear (x, y)-norm limits are folded into the x/y joint limits.

    Along a straight run the (x, y) direction is fixed, so ``||(x', y')|| sd <= v_lin`` is equivalent to
    ``|x'| sd <= v_lin |x'| / ||(x', y')||`` (and the same for y and for the acceleration). Either component's bound
    alone is that equivalence, so only the larger one is folded: the other would get a limit as small as its share of
    the motion (a heading of 1e-11 rad gave y a limit of 1e-11 m/s, and TOPP-RA failed on it).
    """
    v = vmax.astype(np.float64).copy()
    a = amax.astype(np.float64).copy()
    if base_indices is not None and base_linear_limits is not None:
        ix, iy, _ = base_indices
        d = run.dirs[0]
        nxy = math.hypot(d[ix], d[iy])
        if nxy > 1e-12:
            v_lin, a_lin = base_linear_limits
            j = ix if abs(d[ix]) >= abs(d[iy]) else iy
            frac = abs(d[j]) / nxy  # >= 1 / sqrt(2)
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


def _profile_analytic(run: _Run, v: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form time-optimal rest-to-rest profile (trapezoid or triangle) of a straight run."""
    length = run.length
    sv, sa = _scalar_limits(run, v, a)
    d_acc = sv * sv / (2.0 * sa)
    if 2.0 * d_acc < length:
        return np.array([0.0, d_acc, length - d_acc, length]), np.array([0.0, sv, sv, 0.0])
    peak = math.sqrt(length * sa)
    return np.array([0.0, 0.5 * length, length]), np.array([0.0, peak, 0.0])
