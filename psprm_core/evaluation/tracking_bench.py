"""The path tolerance's measure (:mod:`psprm_core.tracking`) timed with the compiled corner kernel and with torch's FK
(``psprm perf tracking``)."""

from __future__ import annotations

import time

import numpy as np
import torch

from ..kernels.compute import Compute
from ..robot import RobotModel
from ..tracking import CheckedPath


def tracking_benchmark(robot_name: str, rounds: int = 20, seed: int = 0, threads: int = 1) -> dict:
    """The path tolerance's measure (:mod:`psprm_core.tracking`) with the compiled corner kernel against torch's FK,
    the same inputs, alternating: per round a 10 s trajectory (the base driving at 0.3 m/s while the other joints
    move between random configurations, points every 0.1 s) and the work of one splice check (a
    :class:`~psprm_core.tracking.CheckedPath` of it, the distances of 6 configurations from it over a 7 s window,
    the latest time one of them lies on it, 5 deviations) and of one control step (a deviation). Medians in ms, the
    ratio, and the largest difference of the distances (m) between the two."""
    torch.set_num_threads(threads)
    fast = RobotModel.load(robot_name)
    if not fast.compute.compiled:
        raise RuntimeError("the compiled kernels are not available here (numba)")
    ref = fast.using(Compute.make("cpu", kernels="torch"))
    rng = np.random.default_rng(seed)
    lo, hi = fast.lower.copy(), fast.upper.copy()
    if fast.mobile:
        lo[:3], hi[:3] = -1.0, 1.0

    def work(robot, t, P, X) -> tuple:
        t0 = time.perf_counter()
        path = CheckedPath(robot, t, P)
        d = path.path_distances(X, np.full(len(X), 3.5), 3.5)
        path.latest_time_of(X[0], 4.0, 4.0, 0.01)
        d = np.concatenate([d, [path.deviation(x, 3.5, 2.0)[0] for x in X[:5]]])
        t1 = time.perf_counter()
        path.deviation(X[5], 3.5, 2.0)
        return (t1 - t0) * 1e3, (time.perf_counter() - t1) * 1e3, d

    # compile and load each path once
    t, P = np.array([0.0, 1.0]), np.stack([fast.default_configuration()] * 2).astype(float)
    work(fast, t, P, P[:1].repeat(6, 0)), work(ref, t, P, P[:1].repeat(6, 0))
    out = {"fast": [], "torch": [], "fast_step": [], "torch_step": [], "max_abs_diff_m": 0.0}
    for _ in range(rounds):
        t = np.arange(0.0, 10.0 + 1e-9, 0.1)
        keys = rng.uniform(lo, hi, size=(6, fast.dof))
        P = np.stack([np.interp(t, np.linspace(0.0, 10.0, 6), keys[:, j]) for j in range(fast.dof)], 1)
        if fast.mobile:
            P[:, 0], P[:, 1], P[:, 2] = 0.3 * t, 0.0, 0.0
        X = P[30:36] + rng.normal(scale=0.01, size=(6, fast.dof))
        a, b = work(fast, t, P, X), work(ref, t, P, X)
        out["fast"].append(a[0]), out["torch"].append(b[0])
        out["fast_step"].append(a[1]), out["torch_step"].append(b[1])
        out["max_abs_diff_m"] = max(out["max_abs_diff_m"], float(np.abs(a[2] - b[2]).max()))
    res = {"robot": robot_name, "rounds": rounds}
    for k in ("fast", "torch", "fast_step", "torch_step"):
        res[f"{k}_ms"] = float(np.median(out[k]))
    res["speedup"] = res["torch_ms"] / res["fast_ms"]
    res["step_speedup"] = res["torch_step_ms"] / res["fast_step_ms"]
    res["max_abs_diff_m"] = out["max_abs_diff_m"]
    return res
