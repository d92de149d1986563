"""What the ``soak`` (:mod:`psprm_ros.harness.soak`) reports of a run: the executed configurations against the bodies'
poses at that instant (each collision attributed to the robot's or the person's closing in, with the trajectory the
robot followed), how closely the robot tracked the trajectories it executed, the record of the run, and the summary
JSON (plans, refusals, latencies, memory, restarts)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import numpy as np

from psprm_core.collision import CollisionChecker
from psprm_core.tracking import CheckedPath

from ..interfaces import conversions as cv
from ..robots.acceptance import SPLICE_LOOKBACK_S, SPLICE_TOL_M  # the adapter's splice rule
from .demo_analysis import _scene_with, goal_triggered, published_plan


CLOSING_WINDOW_S = 0.25  # the motion before a collision over which the closing speeds are measured
CLOSING_MPS = 0.02  # a robot closing in faster than this counts the collision as the robot's (else the person's)


def _followed(t: float, q: np.ndarray, trajs: list, names: list, checker) -> Optional[dict]:
    """The trajectory the robot was following at ``t`` (the last one received before it) and how far the executed
    configuration ``q`` is from its path: the base distance to the nearest of its points, that point's heading and
    joint differences, whether that point itself collides with the boxes ``checker`` holds now, and how many of the
    trajectory's points do. Tells a collision of the plan from one of the tracking. None before any trajectory."""
    import torch

    prev = [(tt, m) for tt, m in trajs if tt <= t]
    if not prev:
        return None
    t_m, m = prev[-1]
    try:
        idx = [list(m.joint_names).index(n) for n in names]
    except ValueError:
        return {"received_s_before": round(t - t_m, 2), "joint_names": list(m.joint_names)}
    P = np.array([np.asarray(p.positions, float)[idx] for p in m.points])
    i = int(np.argmin(np.hypot(P[:, 0] - q[0], P[:, 1] - q[1])))
    bad = checker.check(torch.as_tensor(P, dtype=torch.float32)).cpu().numpy()
    return {"received_s_before": round(t - t_m, 2), "points": len(P),
            "base_off_m": round(float(np.hypot(*(P[i, :2] - q[:2]))), 3),
            "heading_off_rad": round(abs(float((q[2] - P[i, 2] + np.pi) % (2 * np.pi) - np.pi)), 3),
            "joints_off_max": round(float(np.abs(P[i, 3:] - q[3:]).max()), 3) if P.shape[1] > 3 else 0.0,
            "nearest_point_collides": bool(bad[i]), "points_in_collision": int(bad.sum())}


def _closing_speeds(t: float, q: np.ndarray, ex: list, ex_t: np.ndarray, body_tp: list, body_t: np.ndarray) -> tuple:
    """(robot, person) closing speeds (m/s) at an executed configuration ``q`` at time ``t`` in collision with the
    person: how fast the robot's base motion alone, and the person's walk alone, shrank the distance between the base
    and the body over the preceding :data:`CLOSING_WINDOW_S`."""
    t_b = t - CLOSING_WINDOW_S
    i = int(np.clip(np.searchsorted(ex_t, t_b), 0, len(ex_t) - 1))
    j0 = int(np.clip(np.searchsorted(body_t, ex_t[i], side="right") - 1, 0, len(body_t) - 1))
    j1 = int(np.clip(np.searchsorted(body_t, t, side="right") - 1, 0, len(body_t) - 1))
    r0, r1 = np.asarray(ex[i][1][:2], float), np.asarray(q[:2], float)
    p0, p1 = np.asarray(body_tp[j0][1][:2], float), np.asarray(body_tp[j1][1][:2], float)
    dt = max(t - ex_t[i], 1e-3)
    d0 = np.linalg.norm(r0 - p0)
    return (d0 - np.linalg.norm(r1 - p0)) / dt, (d0 - np.linalg.norm(r0 - p1)) / dt


TRACK_WINDOW_S = 3.0
JOIN_S = 1.5  # how long after a splice arrives the robot may still be on the trajectory it joins it along


def executed_trajectories(trajs: list, commands: list) -> list:
    """The server's trajectories the robot adapter executed, as (t, msg, t_hold): those followed by a controller
    command of more than one point (a refused trajectory is followed by a hold instead), and when the first hold
    after it stopped the robot (inf if none did), judged from the messages on the controller's topic
    (``commands``: (t, number of points))."""
    t_tr = np.array([t for t, _ in trajs])
    out, seen = [], set()
    for tc, n in commands:
        j = int(np.searchsorted(t_tr, tc, side="right") - 1)
        if n == 1 and out and out[-1][2] == np.inf:
            out[-1] = (*out[-1][:2], tc)
        elif n > 1 and j >= 0 and j not in seen:
            seen.add(j)
            out.append((*trajs[j], np.inf))
    return out


def tracking_report(ex: list, trajs: list, robot, checker, static_boxes: list) -> dict:
    """How closely the robot executed the trajectories it was sent, judged from the record alone: for every executed
    configuration, the trajectory it was following (the last of ``trajs``, those executed, (t, msg) or (t, msg,
    t_hold), received before it; the motion after a hold at ``t_hold`` counts against where it stopped), the
    base's distance to that trajectory's base path (point to segment), and the deviation of the whole robot
    (:class:`psprm_core.tracking.CheckedPath`: how far a point of its collision boxes is from where it was in the
    nearest of the trajectory's configurations within ``TRACK_WINDOW_S`` of the time since it was received; over the
    first ``JOIN_S`` of a splice, whose first configuration lies on the trajectory followed before it, the nearer of
    the two: the adapter joins a splice that begins ahead of the robot along the trajectory under way, and
    ``joined_configurations`` counts those nearer to that one by more than the splice tolerance);
    percentiles of both, and how often the deviation exceeded the padding, which is the clearance the plan kept.
    Then the executed configurations inside the collision padding of the static boxes
    (``checker`` pads them), split by whether the nearest point of the followed trajectory is inside it too (the plan
    itself came that close, e.g. from a start inside the padding) or clear of it (the tracking error carried the
    robot in)."""
    import torch

    names = list(robot.joint_names)
    if not ex or not trajs:
        return {}
    t_tr = np.array([tr[0] for tr in trajs])
    paths = []
    for tr in trajs:
        m = tr[1]
        try:
            paths.append(cv.joint_trajectory_positions(m, names))
        except Exception:
            paths.append(np.zeros((0, len(names))))
    ex_t = np.array([t for t, _ in ex])
    Q = np.array([q for _, q in ex], float)
    which = np.searchsorted(t_tr, ex_t, side="right") - 1
    base_off = np.full(len(Q), np.nan)
    nearest = np.full((len(Q), len(names)), np.nan)
    deviation = np.full(len(Q), np.nan)
    prev, joined = None, 0  # (CheckedPath, index) of the trajectory followed before; configurations nearer to it
    for j in np.unique(which[which >= 0]):
        P = paths[j]
        if len(P) < 2:  # a stop: the robot holds, nothing to follow
            prev = None
            continue
        sel = np.nonzero(which == j)[0]
        m = trajs[j][1]
        T = np.array([cv.duration_to_sec(p.time_from_start) for p in m.points])
        if np.all(np.diff(T) > 0):
            # the robot's collision boxes against the trajectory's configurations within TRACK_WINDOW_S of the time
            # since it was received (the adapter starts it a lead time later, spliced up to 1.5 s in)
            path = CheckedPath(robot, T, P)
            # after a hold the robot is no longer following: it is measured against where it was stopped
            t_hold = trajs[j][2] if len(trajs[j]) > 2 else np.inf
            deviation[sel] = path.deviations(Q[sel], np.minimum(ex_t[sel], t_hold) - t_tr[j], TRACK_WINDOW_S)
            # a splice that begins ahead of the robot is joined along the trajectory under way: for its first
            # JOIN_S the robot may still be on that one (also checked and published), measured against it there
            early = sel[ex_t[sel] - t_tr[j] <= JOIN_S]
            if len(early) and prev is not None:
                path_p, j_p = prev
                held = trajs[j_p][2] if len(trajs[j_p]) > 2 else np.inf
                # it was still followed when this one came, and this one continues it (a splice: its first
                # configuration lies on it)
                if not np.isfinite(held) and path_p.path_distances(P[:1], [t_tr[j] - t_tr[j_p]], SPLICE_LOOKBACK_S)[0] \
                        <= SPLICE_TOL_M:
                    d_prev = path_p.deviations(Q[early], ex_t[early] - t_tr[j_p], TRACK_WINDOW_S)
                    joined += int(np.sum(d_prev + SPLICE_TOL_M < deviation[early]))
                    deviation[early] = np.minimum(deviation[early], d_prev)
            prev = (path, j)
        else:
            prev = None
        a, b = P[:-1, :2], P[1:, :2]  # base path segments
        d = b - a
        L2 = np.maximum((d * d).sum(1), 1e-12)
        x = Q[sel, None, :2]
        f = np.clip(((x - a) * d).sum(2) / L2, 0.0, 1.0)  # (n, segments)
        dist = np.linalg.norm(a + f[..., None] * d - x, axis=2)
        k = np.argmin(dist, axis=1)
        fk = f[np.arange(len(sel)), k][:, None]
        near = P[k] + fk * (P[k + 1] - P[k])
        nearest[sel] = near
        base_off[sel] = dist[np.arange(len(sel)), k]
    ok = np.isfinite(base_off)
    if not ok.any():
        return {}
    bt = checker.box_tensors(static_boxes)
    inside = np.zeros(len(Q), bool)
    near_inside = np.zeros(len(Q), bool)
    for s in range(0, len(Q), 4096):
        qt = torch.as_tensor(Q[s:s + 4096], dtype=torch.float32)
        inside[s:s + 4096] = checker.env_hits(qt, bt).cpu().numpy()
    idx = np.nonzero(inside & ok)[0]
    if len(idx):
        near_inside[idx] = checker.env_hits(torch.as_tensor(nearest[idx], dtype=torch.float32), bt).cpu().numpy()
    pct = (lambda v, p: round(float(np.percentile(v[ok], p)), 3))
    return {
        "configurations_following": int(ok.sum()),
        "base_off_m": {f"p{p}": pct(base_off, p) for p in (50, 95, 99)} | {"max": round(float(base_off[ok].max()), 3)},
        # psprm_core.tracking: how far a point of the robot's boxes is from where it was in the nearest
        # configuration of the followed trajectory (within TRACK_WINDOW_S of its receipt time)
        "deviation_m": {f"p{p}": round(float(np.nanpercentile(deviation[ok], p)), 3) for p in (50, 95, 99)}
        | {"max": round(float(np.nanmax(deviation[ok])), 3),
           "over_padding": int(np.sum(deviation[ok] > checker.padding)),
           "trajectories_over_padding": int(len(np.unique(which[ok & (deviation > checker.padding)]))),
           "joined_configurations": joined},
        "padding_m": float(checker.padding),
        "inside_static_padding": int((inside & ok).sum()),
        "inside_static_padding_plan_too": int((inside & near_inside).sum()),
        "inside_static_padding_by_tracking": int((inside & ok & ~near_inside).sum()),
        "base_off_when_inside_m_max": round(float(base_off[inside & ok].max()), 3) if (inside & ok).any() else None,
    }


#: the phases of a pose-triggered plan in the server's plan info (ms): the pose's age at the server's receipt, the
#: cycle's application of the inputs and its triggers, the replan, the message and the final check
PHASES = ("input_age_ms", "apply_ms", "triggers_ms", "replan_ms", "msg_ms", "check_ms")


def latency_samples(infos: list) -> list:
    """The pose -> trajectory latencies of the published plans a pose triggered (plan infos of the server, in order):
    one dict each, ``total`` (the pose's stamp to the trajectory's publication, ms), the :data:`PHASES` and ``wait``,
    what the phases leave of the total: the pose waiting for the worker to finish the cycle under way (a replan for
    goal spam, a wait for a braking base)."""
    out = []
    for info in infos:
        if not published_plan(info) or goal_triggered(info.get("reasons")) or not info.get("published_stamp"):
            continue
        x = {"total": (info["published_stamp"] - info["input_stamp"]) * 1e3}
        for k in PHASES:
            v = info.get(k)
            x[k] = float(v) if isinstance(v, (int, float)) and np.isfinite(v) else 0.0
        x["wait"] = x["total"] - sum(x[k] for k in PHASES)
        out.append(x)
    return out


def latency_phases(samples: list) -> dict:
    """Where the latency goes (:func:`latency_samples`): the median of each phase over all samples and over the
    slowest tenth (at least one), in ms."""
    if not samples:
        return {}
    slow = sorted(samples, key=lambda x: x["total"])[-max(1, len(samples) // 10):]
    keys = ("total", "wait") + PHASES
    return {group: {k: round(float(np.median([x[k] for x in xs])), 1) for k in keys} | {"samples": len(xs)}
            for group, xs in (("all", samples), ("slowest_tenth", slow))}


def _params_padding(params_file: str) -> float:
    """The roadmap server's ``edges.collision_padding`` in the params file, as a dotted key or nested (0 when it sets
    none)."""
    import yaml

    data = yaml.safe_load(Path(params_file).read_text()) or {}
    params = (data.get("roadmap_server") or {}).get("ros__parameters") or {}
    if "edges.collision_padding" in params:
        return float(params["edges.collision_padding"])
    return float((params.get("edges") or {}).get("collision_padding", 0.0))


def save_record(path: Path, ex: list, trajs: list, names: list, commands: list = (), poses: list = ()) -> None:
    """The soak's record for a replay: executed configurations (t, q), every trajectory received (t, times from its
    start, positions in the robot's joint order), the controller commands (t, number of points) and the bodies'
    poses (t, body, position, quaternion: ``pose_t``, ``pose_body``, ``pose_p``, ``pose_q``), times in seconds from
    the first executed configuration."""
    t_ref = ex[0][0] if ex else 0.0
    tt, off, P, T = [], [0], [], []
    for t, m in trajs:
        try:
            pos = cv.joint_trajectory_positions(m, names)
        except Exception:
            continue
        tt.append(t - t_ref)
        P.append(pos)
        T.append([cv.duration_to_sec(p.time_from_start) for p in m.points])
        off.append(off[-1] + len(pos))
    np.savez_compressed(path, joint_names=np.array(names), executed_t=np.array([t - t_ref for t, _ in ex]),
                        executed_q=np.array([q for _, q in ex]).reshape(-1, len(names)),
                        trajectory_t=np.array(tt), trajectory_offsets=np.array(off),
                        trajectory_q=np.vstack(P) if P else np.zeros((0, len(names))),
                        trajectory_time_from_start=np.concatenate(T) if T else np.zeros(0),
                        command_t=np.array([t - t_ref for t, _ in commands]),
                        command_points=np.array([n for _, n in commands], int),
                        pose_t=np.array([t - t_ref for t, *_ in poses]),
                        pose_body=np.array([str(b) for _, b, _, _ in poses]),
                        pose_p=np.array([p for _, _, p, _ in poses], float).reshape(-1, 3),
                        pose_q=np.array([q for _, _, _, q in poses], float).reshape(-1, 4))


def report(a, scene, robot, probe, record, procs, exits, mem, stream, n_spam, reached, diags, t0, t_end,
           wall_minus_perf, commands: list, commands_lock) -> dict:
    import torch

    with probe.cond:
        trajs = [(t, m) for t, m in probe.trajectories if t0 <= t <= t_end]
        infos = [(t, i) for t, i in probe.infos if t0 <= t <= t_end]
        statuses = [(t, n, s) for t, n, s in probe.statuses if t0 <= t <= t_end]
    samples = latency_samples([i for _, i in infos])
    lat = np.array([x["total"] for x in samples], float)
    with record.lock:
        ex = [(t, q) for t, q in record.executed if t0 <= t <= t_end]
        poses = list(record.poses)
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    collided, k, cur = 0, 0, {}
    version, checked_version = 0, -1
    events = []
    # who closed the gap at each collision with the person: the robot's own motion or the person's walk
    ex_t = np.array([t for t, _ in ex]) if ex else np.zeros(0)
    body_tp = [(t, p) for t, b, p, _ in poses if b == "person_body"]
    body_t = np.array([t for t, _ in body_tp]) if body_tp else np.zeros(0)
    by = {"robot_closing": 0, "person_closing": 0, "static_obstacle": 0}
    for t, q in ex:
        while k < len(poses) and poses[k][0] <= t:
            cur[poses[k][1]] = (poses[k][2], poses[k][3])
            k += 1
            version += 1
        if version != checked_version:
            checker.set_boxes(_scene_with(scene, cur).collision_boxes())
            checked_version = version
        qt = torch.as_tensor(q[None], dtype=torch.float32)
        hit = bool(checker.check(qt)[0])
        collided += int(hit)
        closing = None
        if hit:
            hit_boxes = [b.name for b in _scene_with(scene, cur).collision_boxes()
                         if bool(checker.env_hits(qt, [b])[0])]  # the boxes this configuration touches
            if "person_body" in hit_boxes and len(body_t):
                closing = _closing_speeds(t, q, ex, ex_t, body_tp, body_t)
                by["robot_closing" if closing[0] > CLOSING_MPS else "person_closing"] += 1
            else:
                by["static_obstacle"] += 1
        if hit and len(events) < 10:
            body = cur.get("person_body", (np.full(3, np.nan), None))[0]
            det = checker.check_detailed(qt)
            events.append({"t": round(t - t0, 2), "base": [round(float(v), 3) for v in q[:3]],
                           "person": [round(float(v), 3) for v in body[:2]],
                           "q": [round(float(v), 4) for v in q],  # the whole configuration, for a replay
                           "why": [k for k in ("limits", "environment", "self") if bool(det[k][0])],
                           "boxes": hit_boxes,
                           # m/s by which the robot's motion / the person's walk shrank their distance over the last
                           # CLOSING_WINDOW_S
                           "closing_mps": None if closing is None else [round(float(c), 3) for c in closing],
                           # the trajectory the robot was following, and how far off it the robot was
                           "followed": _followed(t, q, trajs, list(robot.joint_names), checker)})
    moving = {b for _, b, _, _ in poses}
    padded = CollisionChecker(robot, workspace=scene.workspace, padding=_params_padding(a.params))
    with commands_lock:
        cmds = [(t, n) for t, n in commands if t0 <= t <= t_end]
    tracking = tracking_report(ex, executed_trajectories(trajs, cmds), robot, padded,
                               [b for b in scene.collision_boxes() if b.name not in moving])
    save_record(Path(a.out) / "soak_record.npz", ex, trajs, list(robot.joint_names), cmds)
    growth = {}
    for n, m in mem.items():
        v = [x for _, x in m if np.isfinite(x)]
        if len(v) >= 4:
            first = float(np.median(v[: max(2, len(v) // 6)]))
            last = float(np.median(v[-max(2, len(v) // 6):]))
            growth[n] = {"first_mb": round(first, 1), "last_mb": round(last, 1), "growth_mb": round(last - first, 1),
                         "max_mb": round(max(v), 1),
                         # one sample a minute (s, MB): whether the memory levels off over a long run
                         "series": [[round(t), round(x, 1)] for t, x in m[::6] if np.isfinite(x)]}
    left_active = sum(1 for _, n, s in statuses if "inactive" in s or "configure failed" in s)
    errors = [s for _, n, s in statuses if s.startswith("error")]
    pct = (lambda p: round(float(np.percentile(lat, p)), 1) if len(lat) else None)
    return {
        "duration_s": round(t_end - t0, 1), "trajectories_published": len(trajs),
        "plans_ok": sum(1 for _, i in infos if i.get("success") and not i.get("stop") and not i.get("kept")),
        "kept": sum(1 for _, i in infos if i.get("kept")),
        "stops": sum(1 for _, i in infos if i.get("stop")), "failed": sum(1 for _, i in infos if not i.get("success")),
        "refused_unsafe": sum(1 for _, i in infos if "refused" in str(i.get("reason"))),
        "late_splices": sum(1 for _, i in infos if i.get("failure") == "late_splice"),
        "stale_starts": sum(1 for _, i in infos if i.get("failure") == "stale_start"),
        "goals_reached": len(reached), "executed_configurations": len(ex), "executed_collisions": int(collided),
        "executed_collisions_by": by, "collision_events": events, "tracking": tracking,
        "latency_ms_p50": pct(50), "latency_ms_p90": pct(90), "latency_ms_p95": pct(95), "latency_ms_p99": pct(99),
        "latency_ms_max": round(float(lat.max()), 1) if len(lat) else None, "latency_samples": int(len(lat)),
        "latency_phases_ms": latency_phases(samples),
        "suite": a.suite, "memory": growth, "restarts": len(exits) + left_active, "process_exits": exits,
        "error_statuses": len(errors),
        "first_errors": errors[:5], "stream": stream.counts, "goal_spam_messages": n_spam,
        "adapter_refusals": sum(1 for _, n, s in statuses if n == "robot_adapter" and "refused" in s),
        "adapter_refusal_examples": [s for _, n, s in statuses if n == "robot_adapter" and "refused" in s][:5],
        "controller_refusals": sum(1 for _, n, s in statuses if n == "sim_robot" and "refused" in s),
        "load_avg_1min": round(os.getloadavg()[0], 2), "cpus": os.cpu_count(),
    }
