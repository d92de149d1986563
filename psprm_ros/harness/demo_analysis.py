"""What the closed-loop ``demo`` (:mod:`psprm_ros.harness.demo`) reports of a run: plans and latencies, the
executed motion against the replayed bodies, arrival at a goal, the adapter's stops, and the oracle's verdict along
the executed motion and along the first plan alone (with the run's figure). The soak uses the same helpers."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Optional

import numpy as np

from psprm_core.collision import CollisionChecker
from psprm_core.evaluation import viz

from ..interfaces import conversions as cv


def at_goal(scene, q) -> str:
    """Name of the scene goal region whose tolerances contain the base of ``q`` ("" = none)."""
    for g in scene.goals:
        if math.hypot(q[0] - g.base[0], q[1] - g.base[1]) <= g.xy_tolerance and \
                abs(math.remainder(q[2] - g.base[2], 2 * math.pi)) <= g.theta_tolerance:
            return g.name
    return ""


def rest_arrival(T: np.ndarray, Q: np.ndarray, eps: float = 5e-3) -> Optional[float]:
    """The earliest time since which the base (``Q[:, :3]``, heading modulo a turn) has stayed within ``eps`` of its
    last pose: when the robot came to rest where it ended (None without samples)."""
    if not len(T):
        return None
    d = np.abs(np.asarray(Q, float)[:, :3] - np.asarray(Q, float)[-1, :3])
    d[:, 2] = np.abs(np.remainder(d[:, 2] + np.pi, 2 * np.pi) - np.pi)
    moved = np.nonzero(d.max(axis=1) >= eps)[0]
    return float(T[moved[-1] + 1]) if len(moved) else float(T[0])


def strict_json(value):
    """``value`` with every non-finite float (NaN, inf) replaced by None, recursively: strict JSON."""
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def goal_switches(goal_indices) -> int:
    """Changes of the goal between successive adopted plans (``goal_indices`` in plan order; None entries skipped)."""
    seq = [g for g in goal_indices if g is not None]
    return int(sum(1 for a, b in zip(seq, seq[1:]) if a != b))


def adapter_stops(statuses, t0: float, t1: float) -> dict:
    """The robot adapter's stops reported on its ``~/status`` between ``t0`` and ``t1`` (perf_counter), by reason,
    except the execution of the server's stop trajectory (counted as the server's stop)."""
    out: dict = {}
    for t, node, text in statuses:
        if node != "robot_adapter" or not t0 <= t <= t1 or "robot stopped: " not in text:
            continue
        why = text.split("robot stopped: ", 1)[1]
        if why.startswith("stop trajectory received"):
            continue
        key = why.split(":", 1)[0].strip()
        out[key] = out.get(key, 0) + 1
    return out


GOAL_REASONS = ("goal_received", "goal_changed", "no_plan", "plan requested")


def goal_triggered(reasons) -> bool:
    """Whether a plan was made for a goal (or on request) rather than triggered by a pose, from its trigger reasons."""
    return any(r in GOAL_REASONS for r in (reasons or []))


def published_plan(info: dict) -> bool:
    """Whether a plan info of the server is of a new trajectory it published for a stamped input: a success, not a
    stop, not the last plan kept or a replan declined. With :func:`goal_triggered` false, its latency is pose ->
    trajectory (the demo's and the soak's latency samples)."""
    return bool(info.get("input_stamp") and info.get("success")) and not (
        info.get("stop") or info.get("kept_last") or info.get("kept"))


def _scene_with(scene, poses: dict):
    """``scene`` with each body of ``poses`` (name -> (p, q)) moved there."""
    s = scene
    for b, (p, q) in poses.items():
        s = s.with_target_pose(b, p, q) if b in scene.target_names else s.with_obstacle_pose(b, p, q)
    return s


def _collision_detail(checker, boxes, T: np.ndarray, Q: np.ndarray, i: int, t0: float) -> dict:
    """What the executed configuration ``Q[i]`` collides with (``checker`` holds ``boxes``): the kinds (limits,
    environment, self), the boxes it touches, the base pose and its speed there (t from the replay's start)."""
    import torch

    q = torch.as_tensor(Q[i:i + 1], dtype=torch.float32)
    det = checker.check_detailed(q)
    kinds = [k for k, v in det.items() if bool(v[0])]
    hit = []
    if "environment" in kinds:
        for b in boxes:
            checker.set_boxes([b])
            if bool(checker.check_detailed(q)["environment"][0]):
                hit.append(b.name)
        checker.set_boxes(boxes)
    j = max(0, i - 5)
    dt = max(1e-6, float(T[i] - T[j])) if i > j else 1.0
    speed = float(np.hypot(*(Q[i, :2] - Q[j, :2]))) / dt if i > j else 0.0
    turn = float(abs(np.remainder(Q[i, 2] - Q[j, 2] + np.pi, 2 * np.pi) - np.pi)) / dt if i > j else 0.0
    return {"t": round(float(T[i] - t0), 3), "kinds": kinds, "boxes": hit,
            "base": [round(float(v), 3) for v in Q[i, :3]], "base_speed_mps": round(speed, 3),
            "base_turn_radps": round(turn, 3), "configuration": [round(float(v), 4) for v in Q[i]]}


def bodies_at(record, t: float) -> dict:
    """The latest replayed pose (scene frame) of each body at time ``t`` (perf_counter) in ``record`` (the demo's
    :class:`~.demo.Record`)."""
    out = {}
    with record.lock:
        for tt, b, p, q in record.poses:
            if tt > t:
                break
            out[b] = (p, q)
    return out


def analyse(a, cfg, probe, record, first, t_first, t_replay, t_end, wall_minus_perf, say) -> dict:
    """Plans, latencies, the executed motion against the replayed bodies, and the oracle's verdict on every target
    of the params file along the executed motion and along the first plan alone; writes the figure."""
    import torch

    scene, robot = cfg.scene, cfg.robot
    with probe.cond:
        infos = list(probe.infos)
        trajs = list(probe.trajectories)
    rows = []
    for t, info in infos:
        if t < t_replay - 1.0 or t > t_end:
            continue
        rx = [tt for tt, _ in trajs if tt <= t + 1e-6]
        e2e = at_client = None
        if published_plan(info) and rx:
            # the suite's latency: the pose message's stamp to the trajectory's publication (the server's clock,
            # the same wall clock); and as this client received it (its own callbacks and the replay add to it)
            if info.get("published_stamp"):
                e2e = (info["published_stamp"] - info["input_stamp"]) * 1e3
            at_client = (rx[-1] + wall_minus_perf - info["input_stamp"]) * 1e3
        rows.append({"t": round(t - t_replay, 2), "reasons": info.get("reasons"), "success": info.get("success"),
                     "stop": bool(info.get("stop")), "kept": bool(info.get("kept")),
                     "kept_because": info.get("kept_because"), "goal_index": info.get("goal_index"),
                     "pose_to_trajectory_ms": None if e2e is None else round(e2e, 1),
                     "at_client_ms": None if at_client is None else round(at_client, 1),
                     "server_ms": info.get("latency_ms"), "replan_ms": info.get("replan_ms"),
                     "apply_ms": info.get("apply_ms"), "msg_ms": info.get("msg_ms"), "check_ms": info.get("check_ms"),
                     "input_age_ms": info.get("input_age_ms"), "triggers_ms": info.get("triggers_ms"),
                     "path_score": info.get("mean_score"), "reason": info.get("reason"),
                     "route": info.get("route", ""), "adopted_because": info.get("adopted_because"),
                     "judgement": info.get("judgement") or ""})
    goal_names = cfg.goal_names
    say("[demo] plans (t = seconds since the replay started):")
    for r in rows:
        what = "STOP" if r["stop"] else ("kept" if r["kept"] else "plan" if r["success"] else "FAILED")
        gi = r["goal_index"]
        goal = goal_names[gi] if r["success"] and gi is not None and 0 <= gi < len(goal_names) else "-"
        lat = "" if r["pose_to_trajectory_ms"] is None else f", pose->trajectory {r['pose_to_trajectory_ms']:.0f} ms"
        rp = "" if r["replan_ms"] is None else f", replan {r['replan_ms']:.0f} ms"
        sc = "" if r["path_score"] is None else f", path score {r['path_score']:.3f}"
        route = f", route: {r['route']}" if r["route"] else ""
        because = r["kept_because"] if r["kept"] else r["adopted_because"] if what == "plan" else None
        because = f" [{because}]" if because else ""
        say(f"  t={r['t']:6.2f}  {what:6s} -> {goal:10s} triggers: {', '.join(r['reasons'] or [])}{lat}{rp}{sc}{route}"
            f"{because}")
        judged = r["reason"] if r["kept"] else r["judgement"] if what == "plan" else ""
        if judged:
            say(f"{'':16s}{judged}")
    # pose -> trajectory: plans a pose triggered (a move, a score or collision trigger after it); plans for a new
    # goal or on request are goal -> trajectory (their first input is the goal, not a pose)
    lat = np.array([r["pose_to_trajectory_ms"] for r in rows if r["pose_to_trajectory_ms"] is not None
                    and not goal_triggered(r["reasons"])], float)
    goal_lat = [r["pose_to_trajectory_ms"] for r in rows if r["pose_to_trajectory_ms"] is not None
                and goal_triggered(r["reasons"])]
    client = np.array([r["at_client_ms"] for r in rows if r["at_client_ms"] is not None
                       and not goal_triggered(r["reasons"])], float)
    # the executed motion against the replayed bodies at each instant
    with record.lock:
        ex = [(t, q) for t, q in record.executed if t_replay <= t <= t_end]
    T = np.array([t for t, _ in ex])
    Q = np.array([q for _, q in ex]).reshape(-1, robot.dof)
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    collided, idx_bad, bad_details = 0, [], []
    with record.lock:
        poses = list(record.poses)
    k = 0
    cur: dict = {}
    for i, t in enumerate(T):
        while k < len(poses) and poses[k][0] <= t:
            cur[poses[k][1]] = (poses[k][2], poses[k][3])
            k += 1
        boxes = _scene_with(scene, cur).collision_boxes()
        checker.set_boxes(boxes)
        if bool(checker.check(torch.as_tensor(Q[i:i + 1], dtype=torch.float32))[0]):
            collided += 1
            idx_bad.append(i)
            if len(bad_details) < 20:
                bad_details.append(_collision_detail(checker, boxes, T, Q, i, t_replay))
    dist = float(np.sum(np.hypot(*np.diff(Q[:, :2], axis=0).T))) if len(Q) > 1 else 0.0
    if len(Q):
        say(f"[demo] executed motion: {len(Q)} configurations over {T[-1] - T[0]:.1f} s (reported at "
            f"{len(Q) / max(1e-9, T[-1] - T[0]):.0f} Hz), base drove {dist:.2f} m from ({Q[0, 0]:.2f}, {Q[0, 1]:.2f}) "
            f"to ({Q[-1, 0]:.2f}, {Q[-1, 1]:.2f}, yaw {Q[-1, 2]:.2f}); {collided} configurations in collision with "
            f"the replayed bodies ({', '.join(cfg.recorded_bodies)})")
    for d in bad_details:
        say(f"[demo]   in collision at t={d['t']:.2f} s: {', '.join(d['kinds'])}"
            f"{' with ' + ', '.join(d['boxes']) if d['boxes'] else ''}; base at ({d['base'][0]:.2f}, {d['base'][1]:.2f}, "
            f"yaw {d['base'][2]:.2f}) moving {d['base_speed_mps']:.2f} m/s, {d['base_turn_radps']:.2f} rad/s")
    # oracle along the executed motion
    ts = np.arange(T[0], T[-1] + 1e-9, a.oracle_every) if len(T) else np.zeros(0)
    Qs = np.array([Q[min(np.searchsorted(T, t), len(T) - 1)] for t in ts]).reshape(-1, robot.dof)
    seen = [bodies_at(record, t) for t in ts]
    # first plan only: where the robot would have been, had it executed the first trajectory without replanning,
    # judged against the same replayed bodies at the same instants
    ts0, Q0 = first_plan_samples(first, robot, t_first, a.oracle_every)
    seen0 = [bodies_at(record, t) for t in ts0]
    targets = list(cfg.targets)
    oracle = {n: [] for n in targets}  # target -> scores along the executed motion
    detected = {n: [] for n in targets}
    oracle0 = {n: [] for n in targets}  # ... along the first plan alone
    detected0 = {n: [] for n in targets}
    if not a.no_oracle and len(ts):
        try:
            from psprm_core.perception.oracle import Oracle

            t0 = time.perf_counter()
            with Oracle(scene, intrinsics=robot.config.intrinsics) as orc:
                for views, who, score, det in ((Qs, seen, oracle, detected), (Q0, seen0, oracle0, detected0)):
                    with torch.no_grad():
                        cams = robot.camera_poses(torch.as_tensor(views, dtype=torch.float32)).double().numpy()
                    for i in range(len(views)):
                        for b, (p, q) in who[i].items():
                            (orc.set_target_pose if b in scene.target_names else orc.set_obstacle_pose)(b, p, q)
                        for n in targets:
                            r = orc.score(cams[i], n, keep_image=False)
                            score[n].append(float(r.score))
                            det[n].append(bool(r.detected))
            say(f"[demo] oracle: {len(ts)} rendered views along the executed motion and {len(ts0)} along the first "
                f"plan alone (no replanning), each scored for {', '.join(targets)} by the real detector in "
                f"{time.perf_counter() - t0:.1f} s: " + "; ".join(
                    f"{n} detected in {_share(detected[n])} / {_share(detected0[n])} of them, mean score "
                    f"{_mean(oracle[n], 3)} / {_mean(oracle0[n], 3)}" for n in targets))
        except Exception as exc:  # detectors not installed: report and continue without
            say(f"[demo] oracle evaluation skipped: {exc}")
    adopted = [r for r in rows if r["success"] and not r["stop"] and not r["kept"]]
    n_ok = len(adopted)
    summary = {
        "plans_ok": n_ok, "replans": max(0, n_ok - 1), "kept": sum(r["kept"] for r in rows),
        "adopted_replans": max(0, n_ok - 1), "declined_replans": sum(r["kept"] for r in rows),
        "declined_late_replans": sum(r.get("kept_because") == "late" for r in rows),
        "goal_switches": goal_switches(r["goal_index"] for r in adopted),
        "adopted_goals": [goal_names[r["goal_index"]] if r["goal_index"] is not None and
                          0 <= r["goal_index"] < len(goal_names) else None for r in adopted],
        "stops": sum(r["stop"] for r in rows),
        "failed": sum(1 for r in rows if not r["success"] and not r["stop"]),
        "pose_to_trajectory_ms_median": round(float(np.median(lat)), 1) if len(lat) else None,
        "pose_to_trajectory_ms_p95": round(float(np.percentile(lat, 95)), 1) if len(lat) else None,
        "pose_to_trajectory_ms_max": round(float(lat.max()), 1) if len(lat) else None,
        "latency_samples": int(len(lat)),
        "pose_to_trajectory_at_client_ms_median": round(float(np.median(client)), 1) if len(client) else None,
        "pose_to_trajectory_at_client_ms_p95": round(float(np.percentile(client, 95)), 1) if len(client) else None,
        "goal_to_trajectory_ms": [round(float(v), 1) for v in goal_lat],
        **{f"{k}_median": (round(float(np.median(v)), 1) if v else None) for k, v in
           ((k, [r[k] for r in rows if r.get(k) is not None]) for k in ("server_ms", "replan_ms", "apply_ms",
                                                                        "msg_ms", "check_ms", "input_age_ms", "triggers_ms"))},
        "executed_configurations": int(len(Q)), "executed_collisions": int(collided),
        "executed_collision_details": bad_details,
        "executed_distance_m": round(dist, 3),
        "final_base": [round(float(v), 3) for v in Q[-1, :3]] if len(Q) else None,
        # every target of the params file in every view: the share of (view, target) pairs detected (one target:
        # the share of views), then per target, and the share of views that saw all of them at once
        "oracle_detected_fraction": _pooled(detected), "oracle_mean": _pooled(oracle, 4),
        "oracle_views": len(ts) if any(oracle.values()) else 0,
        "oracle_detected_fraction_by_target": {n: _mean(detected[n], 3) for n in targets},
        "oracle_all_detected_fraction": _all(detected),
        "first_plan_only_detected_fraction": _pooled(detected0), "first_plan_only_oracle_mean": _pooled(oracle0, 4),
        "first_plan_only_views": len(ts0) if any(oracle0.values()) else 0,
        "first_plan_only_detected_fraction_by_target": {n: _mean(detected0[n], 3) for n in targets},
        "first_plan_only_all_detected_fraction": _all(detected0),
    }
    say(f"[demo] {n_ok} plans ({summary['adopted_replans']} replans adopted, {summary['goal_switches']} goal "
        f"switches), {summary['declined_replans']} replans not adopted ({summary['declined_late_replans']} would have "
        f"arrived beyond the arrival budget, the rest were no better than the trajectory under way or it already ended "
        f"at the best goal), "
        f"{summary['stops']} stops by the server, {summary['failed']} failed; "
        f"pose->trajectory latency median {summary['pose_to_trajectory_ms_median']} ms, p95 "
        f"{summary['pose_to_trajectory_ms_p95']} ms, max {summary['pose_to_trajectory_ms_max']} ms "
        f"({len(lat)} plans triggered by a pose; goal -> trajectory {summary['goal_to_trajectory_ms']} ms); as "
        f"received by this client: median {summary['pose_to_trajectory_at_client_ms_median']} ms, p95 "
        f"{summary['pose_to_trajectory_at_client_ms_p95']} ms")
    try:
        _figure(Path(a.out) / "ros_demo.png", cfg, record, first, Q, ts, oracle, rows, t_replay)
    except Exception as exc:  # the figure is a report, never a reason to lose the result
        say(f"[demo] figure failed: {exc}")
    scored = any(oracle.values())
    return {**summary, "plans": rows,
            # per view: the mean score over the targets (one target: its score), and each target's
            "oracle": np.mean([oracle[n] for n in targets], axis=0).round(4).tolist() if scored else [],
            "oracle_by_target": oracle, "oracle_t": (ts - t_replay).round(2).tolist() if scored else []}


def _mean(values, digits: int = 3) -> Optional[float]:
    return round(float(np.mean(values)), digits) if len(values) else None


def _share(flags) -> str:
    return f"{np.mean(flags):.0%}" if len(flags) else "-"


def _pooled(by_target: dict, digits: int = 3) -> Optional[float]:
    """Mean over every (view, target) pair (None without any)."""
    vals = [v for vs in by_target.values() for v in vs]
    return _mean(vals, digits)


def _all(detected: dict) -> Optional[float]:
    """Share of the views in which every target was detected (None without views)."""
    cols = [np.asarray(v, bool) for v in detected.values()]
    if not cols or not len(cols[0]):
        return None
    return round(float(np.mean(np.logical_and.reduce(cols))), 3)


def first_plan_samples(first, robot, t_first: float, every: float) -> tuple:
    """Instants (perf_counter, every ``every`` s from ``t_first`` to the end of the first trajectory) and the
    configurations (K, dof) the first trajectory holds then (linear between its points): the motion of a robot that
    executes its first plan and never replans."""
    P = cv.joint_trajectory_positions(first, robot.joint_names)
    tp = np.array([cv.duration_to_sec(p.time_from_start) for p in first.points], float)
    tau = np.arange(0.0, tp[-1] + 1e-9, every) if len(tp) else np.zeros(0)
    Q = np.stack([np.interp(tau, tp, P[:, j]) for j in range(P.shape[1])], -1) if len(tau) else P[:0]
    if robot.mobile and len(tau):  # the heading the short way between points
        Q[:, 2] = np.interp(tau, tp, np.unwrap(P[:, 2]))
    return t_first + tau, Q


def _figure(path, cfg, record, first, Q, ts, oracle, rows, t_replay) -> None:
    """Top view (scene, first plan, executed motion, the recorded targets' headings) and, over time, each target's
    heading and distance from its first pose, the oracle's scores and the plans."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    scene, robot = cfg.scene, cfg.robot
    fig = Figure(figsize=(14, 5.5), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2, 1)
    viz.plot_scene_top(ax, scene, show_labels=True)
    P0 = cv.joint_trajectory_positions(first, robot.joint_names)
    ax.plot(P0[:, 0], P0[:, 1], "--", color="0.4", lw=1.2, label="first plan")
    if len(Q):
        ax.plot(Q[:, 0], Q[:, 1], color="k", lw=1.5, label="executed (sim_robot /odom)")
    for g in cfg.goals:
        ax.plot(g.base[0], g.base[1], "*", color="tab:green", ms=10)
    with record.lock:
        poses = list(record.poses)
    recorded_targets = [n for n in cfg.targets if n in cfg.recorded_bodies]
    colours = ["tab:orange", "tab:purple", "tab:brown", "tab:pink"]
    tracks = {n: [(t, p, q) for t, b, p, q in poses if b == n] for n in recorded_targets}
    for c, (n, tr) in zip(colours * 4, tracks.items()):
        for t, p, q in tr[::240]:
            yaw = cv.yaw_of(q)
            ax.arrow(p[0], p[1], 0.35 * np.cos(yaw), 0.35 * np.sin(yaw), width=0.01, color=c, alpha=0.5)
    ax.set_title(f"{scene.name}: closed loop ({robot.name}, adapter {cfg.adapter} + sim_robot)\n"
                 f"replayed: {', '.join(cfg.recorded_bodies)}", fontsize=9)
    ax.legend(loc="lower right", fontsize=7)
    ax2 = fig.add_subplot(1, 2, 2)
    for c, (n, tr) in zip(colours * 4, tracks.items()):
        if not tr:
            continue
        tf = np.array([t for t, _, _ in tr]) - t_replay
        ax2.plot(tf, np.unwrap([cv.yaw_of(q) for _, _, q in tr]), color=c, lw=1, label=f"{n} yaw (rad)")
        P = np.array([p for _, p, _ in tr])
        ax2.plot(tf, np.linalg.norm(P[:, :2] - P[0, :2], axis=1), color=c, lw=1, ls="--",
                 label=f"{n} moved (m)")
    ax2.set_xlabel("time since the replay started (s)")
    ax2.set_ylabel("target yaw (rad) / distance moved (m)")
    for r in rows:
        ax2.axvline(r["t"], color="red" if r["stop"] else "0.6", lw=0.8, ls=":" if r["success"] else "-")
    ax2.legend(fontsize=7, loc="upper left")
    if any(oracle.values()):
        ax3 = ax2.twinx()
        for c, (n, sc) in zip(["tab:blue", "tab:cyan", "tab:olive", "tab:gray"] * 4, oracle.items()):
            ax3.plot(ts[:len(sc)] - t_replay, sc, color=c, label=f"oracle score of {n} along the executed motion")
        ax3.set_ylim(0, 1.05)
        ax3.set_ylabel("oracle score")
        ax3.legend(fontsize=7, loc="upper right")
    ax2.set_title("targets as replayed; dotted lines = plans/replans, red = stops", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
