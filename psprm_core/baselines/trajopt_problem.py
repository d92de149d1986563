"""The optimisation problem of the TrajOpt baseline (:class:`TrajOptProblem`): the path's free waypoints as the
variables, the analytic residuals and Jacobian of the motion, collision and view terms with their penalty weights,
and the differential-drive arcs between waypoints (:func:`arc_segments`)."""

from __future__ import annotations

import numpy as np
import torch

from ..errors import InputError
from ..geometry import wrap_angle



def arc_segments(qa: np.ndarray, qb: np.ndarray, w_rot: float) -> dict:
    """Decompose base segments qa -> qb (E, dof) into constant-curvature arcs.

    Returns ``dtheta`` (wrapped heading change), ``forward`` and ``lateral`` (displacement along / across the mean
    heading), ``arc`` (signed arc length, ``forward * (dth/2) / sin(dth/2)``) and ``cost`` (motion cost
    ``w_rot |dth| + |arc| + ||d joints||``), each (E,).
    """
    qa, qb = np.atleast_2d(qa), np.atleast_2d(qb)
    dth = wrap_angle(qb[:, 2] - qa[:, 2])
    thm = qa[:, 2] + 0.5 * dth
    dx, dy = qb[:, 0] - qa[:, 0], qb[:, 1] - qa[:, 1]
    fwd = np.cos(thm) * dx + np.sin(thm) * dy
    lat = -np.sin(thm) * dx + np.cos(thm) * dy
    arc = fwd / np.sinc(dth / (2 * np.pi))  # np.sinc(x) = sin(pi x) / (pi x)
    cost = w_rot * np.abs(dth) + np.abs(arc) + np.linalg.norm(qb[:, 3:] - qa[:, 3:], axis=1)
    return {"dtheta": dth, "forward": fwd, "lateral": lat, "arc": arc, "cost": cost}


class TrajOptProblem:
    """Residuals and Jacobian of one start/goal pair of ``planner`` (:class:`~.trajopt.TrajOptPlanner`: its robot,
    settings, checker and view terms).

    The variables are the free waypoints' values of the optimised joints ``cols`` (n_free, nc), flattened; the other
    joints stay at the start's values (the start and goal agree on them).
    """

    def __init__(self, planner, start: np.ndarray, goal: np.ndarray, dt: float, cols: np.ndarray):
        self.p = planner
        r = planner.robot
        s = planner.settings
        self.dof = r.dof
        self.N = s.n_waypoints
        self.n_free = self.N - 1
        self.mobile = r.mobile
        self.cols = np.asarray(cols)
        self.nc = len(self.cols)
        if self.mobile and not np.array_equal(self.cols[:3], [0, 1, 2]):
            raise InputError("the base joints must be optimised")
        self.start, self.goal = np.asarray(start, float), np.asarray(goal, float)
        c = self.cols
        w = np.ones(r.dof)
        if r.mobile:
            w[2] = planner.w_rot
        self.wsm = w[c]
        self.lo = np.where(np.isfinite(planner.lo), planner.lo, -1e9)[c]
        self.hi = np.where(np.isfinite(planner.hi), planner.hi, 1e9)[c]
        self.bounded = np.nonzero(np.isfinite(planner.lo[c]) | np.isfinite(planner.hi[c]))[0]
        self.vmax = (r.velocity * dt)[c]
        self.penalty = np.ones(4)
        # evaluation points of the per-configuration terms: the free waypoints, then substeps of every segment
        K = s.collision_substeps
        rows = [(i, 1.0, i, 0.0) for i in range(1, self.N)]
        for i in range(self.N - 1):
            for k in range(1, K + 1):
                f = k / (K + 1)
                rows.append((i, 1 - f, i + 1, f))
        rows = np.array(rows)
        A = np.zeros((len(rows), self.N))
        np.add.at(A, (np.arange(len(rows)), rows[:, 0].astype(int)), rows[:, 1])
        np.add.at(A, (np.arange(len(rows)), rows[:, 2].astype(int)), rows[:, 3])
        self.A = A  # evaluation points = A @ Q
        self.A_free = A[:, 1:]

    def set_penalty_scale(self, scale) -> None:
        self.penalty = np.asarray(scale, float)

    def _weights(self):
        s = self.p.settings
        pl, pc, pn, pg = self.penalty
        return (s.w_goal * pg, s.w_smooth, s.w_limits * pl, s.w_velocity, s.w_collision * pc, s.w_view,
                s.w_nonholonomic * pn)

    def full_path(self, x: np.ndarray) -> np.ndarray:
        """All N waypoints (N, dof) for the variables ``x``."""
        Q = np.tile(self.start, (self.N, 1))
        Q[1:, self.cols] = x.reshape(self.n_free, self.nc)
        return Q

    # ---- analytic blocks: goal, smoothness, limits, velocity, nonholonomic ------------------------------------------
    def _analytic(self, x: np.ndarray, jacobian: bool):
        wg, ws, wl, wv, _, _, wn = self._weights()
        nf, nc = self.n_free, self.nc
        n = nf * nc
        X = x.reshape(nf, nc)
        Q = np.vstack([self.start[self.cols][None], X])  # (N, nc), Q[i + 1] = variable block i
        dQ = Q[1:] - Q[:-1]  # segment i: block i minus block i - 1
        res, jac = [], []

        def seg_rows(d1: np.ndarray, j1: np.ndarray) -> np.ndarray:
            """Rows of per-segment scalars with derivatives d1 (S, nc) wrt the segment's end (d0 = -d1 wrt its start
            unless given through ``j1`` = per-column sign pattern)."""
            J = np.zeros((nf, nf, nc))
            J[np.arange(nf), np.arange(nf)] = d1
            J[np.arange(1, nf), np.arange(nf - 1)] = j1[1:]
            return J.reshape(nf, n)

        # goal
        res.append(wg * (X[-1] - self.goal[self.cols]))
        if jacobian:
            Jg = np.zeros((nc, n))
            Jg[:, (nf - 1) * nc:] = wg * np.eye(nc)
            jac.append(Jg)
        # smoothness (first differences, weighted like the motion cost)
        res.append((ws * dQ * self.wsm).reshape(-1))
        if jacobian:
            Js = np.zeros((nf, nc, nf, nc))
            ii, cc = np.meshgrid(np.arange(nf), np.arange(nc), indexing="ij")
            Js[ii, cc, ii, cc] = ws * self.wsm[cc]
            Js[ii[1:], cc[1:], ii[1:] - 1, cc[1:]] = -ws * self.wsm[cc[1:]]
            jac.append(Js.reshape(nf * nc, n))
        # joint limits (bounded columns)
        b = self.bounded
        over, under = X[:, b] - self.hi[b], self.lo[b] - X[:, b]
        res.append((wl * (np.maximum(over, 0) + np.maximum(under, 0))).reshape(-1))
        if jacobian:
            Jl = np.zeros((nf, len(b), nf, nc))
            ii, bb = np.meshgrid(np.arange(nf), np.arange(len(b)), indexing="ij")
            Jl[ii, bb, ii, b[bb]] = wl * ((over > 0).astype(float) - (under > 0))
            jac.append(Jl.reshape(nf * len(b), n))
        # velocity limits and the nonholonomic constraint
        j0 = 3 if self.mobile else 0
        dj = dQ[:, j0:]
        vj = dj.__abs__() - self.vmax[j0:]
        if self.mobile:
            thm = Q[:-1, 2] + 0.5 * dQ[:, 2]
            c, s_ = np.cos(thm), np.sin(thm)
            fwd = c * dQ[:, 0] + s_ * dQ[:, 1]
            lat = -s_ * dQ[:, 0] + c * dQ[:, 1]
            vf = np.abs(fwd) - self.vmax[0]
            vt = np.abs(dQ[:, 2]) - self.vmax[2]
            res.append(wv * np.maximum(vf, 0))
            res.append(wv * np.maximum(vt, 0))
            res.append((wv * np.maximum(vj, 0)).reshape(-1))
            res.append(wn * lat)
            if jacobian:
                z = np.zeros((nf, nc))
                # d fwd / d(end): (c, s, lat / 2); d fwd / d(start): (-c, -s, lat / 2)
                d1, d0 = z.copy(), z.copy()
                d1[:, 0], d1[:, 1], d1[:, 2] = c, s_, 0.5 * lat
                d0[:, 0], d0[:, 1], d0[:, 2] = -c, -s_, 0.5 * lat
                act = wv * (vf > 0) * np.sign(fwd)
                jac.append(seg_rows(d1 * act[:, None], d0 * act[:, None]))
                d1, d0 = z.copy(), z.copy()
                act = wv * (vt > 0) * np.sign(dQ[:, 2])
                d1[:, 2], d0[:, 2] = act, -act
                jac.append(seg_rows(d1, d0))
                nj = nc - 3
                Jv = np.zeros((nf, nj, nf, nc))
                ii, kk = np.meshgrid(np.arange(nf), np.arange(nj), indexing="ij")
                act = wv * (vj > 0) * np.sign(dj)
                Jv[ii, kk, ii, 3 + kk] = act
                Jv[ii[1:], kk[1:], ii[1:] - 1, 3 + kk[1:]] = -act[1:]
                jac.append(Jv.reshape(nf * nj, n))
                # d lat / d(end): (-s, c, -fwd / 2); d lat / d(start): (s, -c, -fwd / 2)
                d1, d0 = z.copy(), z.copy()
                d1[:, 0], d1[:, 1], d1[:, 2] = -s_, c, -0.5 * fwd
                d0[:, 0], d0[:, 1], d0[:, 2] = s_, -c, -0.5 * fwd
                jac.append(seg_rows(wn * d1, wn * d0))
        else:
            res.append((wv * np.maximum(vj, 0)).reshape(-1))
            if jacobian:
                Jv = np.zeros((nf, nc, nf, nc))
                ii, kk = np.meshgrid(np.arange(nf), np.arange(nc), indexing="ij")
                act = wv * (vj > 0) * np.sign(dj)
                Jv[ii, kk, ii, kk] = act
                Jv[ii[1:], kk[1:], ii[1:] - 1, kk[1:]] = -act[1:]
                jac.append(Jv.reshape(nf * nc, n))
        r = np.concatenate(res)
        return (r, np.vstack(jac)) if jacobian else r

    # ---- per-configuration blocks: collision, view ------------------------------------------------------------------
    def _eval_points(self, x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(self.A @ self.full_path(x))

    def _config_weights(self, k: int) -> tuple:
        _, _, _, _, wc, wview, _ = self._weights()
        w = np.full((len(self.A), k), wc)
        w[:, k - 1] = wview
        keep = np.ones((len(self.A), k), dtype=bool)
        keep[self.n_free:, k - 1] = False  # view residuals only at the free waypoints (the first n_free points)
        # no collision term at the final waypoint: it should be the goal, which is valid but may lie within the
        # clearance margin of an obstacle (the exact check judges it)
        w[self.n_free - 1, : k - 1] = 0.0
        return w, keep

    def fun(self, x: np.ndarray) -> np.ndarray:
        ra = self._analytic(x, False)
        with torch.no_grad():
            f0 = self.p.config_terms(self._eval_points(x)).numpy()
        w, keep = self._config_weights(f0.shape[1])
        return np.concatenate([ra, (f0 * w)[keep]])

    def jac(self, x: np.ndarray) -> np.ndarray:
        _, Ja = self._analytic(x, True)
        with torch.no_grad():
            f0, J = self.p.config_terms(self._eval_points(x), jacobian=True, eps=self.p.settings.fd_eps,
                                        cols=self.cols)
        f0, J = f0.numpy(), J.numpy()  # J: (E, nc, k)
        w, keep = self._config_weights(f0.shape[1])
        # d r_{e,k} / d X_{i,j} = A_free[e, i] * J[e, j, k] * w_{e,k}
        Jc = np.einsum("ei,ejk->ekij", self.A_free, J * w[:, None, :])  # (E, k, n_free, nc)
        Jc = Jc[keep].reshape(-1, self.n_free * self.nc)
        return np.vstack([Ja, Jc])

    def violations(self, x: np.ndarray) -> dict:
        """Unweighted constraint violations: max collision hinge norm, max |lateral| (m), max limit violation."""
        X = x.reshape(self.n_free, self.nc)
        Q = self.full_path(x)
        with torch.no_grad():
            f0 = self.p.config_terms(self._eval_points(x)).numpy()
        b = self.bounded
        lim = np.maximum(X[:, b] - self.hi[b], 0) + np.maximum(self.lo[b] - X[:, b], 0)
        lat = np.abs(arc_segments(Q[:-1], Q[1:], 1.0)["lateral"]).max() if self.mobile else 0.0
        return {"collision": float(f0[:, :-1].max()) if f0.shape[1] > 1 else 0.0, "lateral": float(lat),
                "limits": float(lim.max()) if lim.size else 0.0,
                "goal": float(np.abs(Q[-1, self.cols] - self.goal[self.cols]).max())}
