"""The closed-loop demo's configuration from each shipped params file, and the shipped recordings replayed with them.

Judged from independent records: the params file and the scene file read here with ``yaml`` (the shared ``/**``
section, the node sections, the scene's problems and goal regions), and the recording's CSV read here with ``csv``
(speeds by finite differences of the recorded positions, boxes placed by the test's own quaternion maths, the robot
at its start and goals checked by the tests' :class:`~judges.Judge`: pybullet and a box model built afresh from the
poses the CSV holds). Nothing runs the closed loop (minutes); ``python -m psprm_ros.harness.demo --params ...`` does.
"""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from psprm_core.errors import InputError  # noqa: E402

from psprm_ros.harness.demo_analysis import adapter_stops, goal_switches, rest_arrival, strict_json  # noqa: E402
from psprm_ros.harness.demo_config import (POSE_GOAL_THETA_TOLERANCE_RAD, POSE_GOAL_XY_TOLERANCE_M,  # noqa: E402
                                           default_recording, demo_config)
from psprm_ros.interfaces.recordings import load_recording  # noqa: E402

#: params file -> the recording shipped for it (the test's own table)
SHIPPED = {
    "dynamic_person.yaml": "person_turning.csv",
    "fetchlike_nursing.yaml": "nurses_turning_walking.csv",
    "ur5_mobile_blind_spot_alley.yaml": "monitor_cart_rolling.csv",
}
#: what the recordings of people and of objects they push may do: a brisk walk, a quick whole-body turn
HUMAN_SPEED_M_S = 2.0
HUMAN_TURN_RAD_S = math.radians(250.0)


def _params(name: str) -> dict:
    """node -> parameters, the shared section overlaid by the node's own (read here)."""
    data = yaml.safe_load((ROOT / "config" / "ros" / name).read_text())
    shared = data["/**"]["ros__parameters"]
    nodes = ("roadmap_server", "perception_scorer", "replan_monitor", "robot_adapter", "sim_robot")
    return {n: {**shared, **(data.get(n) or {}).get("ros__parameters", {})} for n in nodes} | {"/**": shared}


def _scene_yaml(name: str) -> dict:
    return yaml.safe_load((ROOT / "config" / "scenes" / f"{name}.yaml").read_text())


def _quat_rotate(q, v) -> np.ndarray:
    """v (N, 3) rotated by unit quaternions q (N, 4) xyzw (or one)."""
    q = np.broadcast_to(np.asarray(q, float), (len(v), 4))
    u, w = q[:, :3], q[:, 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _quat_mul(a, b) -> np.ndarray:
    ax, ay, az, aw = np.moveaxis(np.broadcast_to(a, np.broadcast_shapes(np.shape(a), np.shape(b))), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.broadcast_to(b, np.broadcast_shapes(np.shape(a), np.shape(b))), -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz], -1)


def _yaw(q) -> np.ndarray:
    q = np.asarray(q, float)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def _read_csv(path: Path) -> dict:
    """body -> (frame, times (N,), positions (N, 3), quaternions (N, 4)), read with the csv module."""
    rows: dict = {}
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            rows.setdefault(r["body"], []).append(r)
    out = {}
    for body, rs in rows.items():
        frames = {r.get("frame") or "map" for r in rs}
        assert len(frames) == 1, f"{body}: several frames {frames}"
        t = np.array([float(r["time"]) for r in rs])
        order = np.argsort(t, kind="stable")
        P = np.array([[float(r[k]) for k in ("x", "y", "z")] for r in rs])[order]
        Q = np.array([[float(r[k]) for k in ("qx", "qy", "qz", "qw")] for r in rs])[order]
        out[body] = (frames.pop(), t[order], P, Q)
    return out


def _in_scene_frame(params: dict, scene_frame: str, frame: str, P, Q) -> tuple:
    """Recorded poses mapped into the scene frame by the params file's input frame transform (read here)."""
    if frame == scene_frame:
        return P, Q
    shared = params["/**"]
    assert frame in shared["input_frames"], f"frame {frame} neither the scene frame nor an input frame"
    spec = shared["input_frame"][frame]
    qf = np.asarray(spec["quat"], float) / np.linalg.norm(spec["quat"])
    return _quat_rotate(qf, P) + np.asarray(spec["xyz"], float), _quat_mul(qf, Q)


def _box_of(scene: dict, name: str) -> dict:
    for b in scene.get("obstacles", []) + scene.get("targets", []):
        if b["name"] == name:
            return b
    raise AssertionError(f"scene {scene['name']} has no body {name}")


def _footprint(center, yaw, size) -> np.ndarray:
    """(4, 2) corners of a box's footprint."""
    c, s = math.cos(yaw), math.sin(yaw)
    hx, hy = size[0] / 2, size[1] / 2
    local = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
    return local @ np.array([[c, s], [-s, c]]) + np.asarray(center[:2])


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating-axis test of two convex polygons (corners in order)."""
    for poly in (a, b):
        for i in range(len(poly)):
            e = poly[(i + 1) % len(poly)] - poly[i]
            n = np.array([-e[1], e[0]])
            pa, pb = a @ n, b @ n
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True


def _static_yaw(b: dict) -> float:
    if "quat" in b:
        return float(_yaw(b["quat"]))
    return float(b.get("yaw", 0.0))


# ---------------------------------------------------------------------------------------------------- configuration
@pytest.mark.parametrize("params_file", sorted(SHIPPED))
def test_demo_configuration_is_the_params_files(params_file):
    """Scene, robot, adapter, targets, dynamic obstacles, start, goals and the bodies' topics, as the params file and
    its scene file say (read here)."""
    params = _params(params_file)
    shared, server, monitor, sim = params["/**"], params["roadmap_server"], params["replan_monitor"], params["sim_robot"]
    scene = _scene_yaml(shared["scene"])
    cfg = demo_config(ROOT / "config" / "ros" / params_file)
    assert cfg.scene.name == scene["name"] == shared["scene"]
    robot = shared.get("robot") or scene["robot"]
    assert cfg.robot.name == robot
    adapter = params["robot_adapter"].get("adapter") or robot
    assert cfg.adapter == adapter
    assert yaml.safe_load((ROOT / "config" / "ros" / "adapters" / f"{adapter}.yaml").read_text())["robot"] == robot
    assert cfg.targets == list(shared["targets"]) and cfg.targets
    assert cfg.dynamic_obstacles == list(shared["dynamic_obstacles"])
    # the start: where sim_robot starts (its start_problem)
    problems = {p["name"]: p for p in scene["problems"]}
    start = problems[sim["start_problem"]]["start"] if sim.get("start_problem") else scene["problems"][0]["start"]
    assert np.allclose(cfg.start[:3], [start["base_x"], start["base_y"], start["base_theta"]])
    # the goals: the server's goal regions, else its start problem's goal regions or goal pose
    regions = {g["name"]: g for g in scene.get("goals", [])}
    if server.get("goal_regions"):
        want_regions = list(server["goal_regions"])
    else:
        want_regions = list(problems[server["start_problem"]].get("goal_regions", []))
    assert cfg.goal_regions == want_regions
    if want_regions:
        assert [g.name for g in cfg.goals] == want_regions
        for g in cfg.goals:
            r = regions[g.name]
            assert np.allclose(g.base, r["base"]) and g.xy_tolerance == r["xy_tolerance"]
            assert g.theta_tolerance == r["theta_tolerance"]
    else:
        goal = problems[server["start_problem"]]["goal"]
        assert len(cfg.goals) == 1
        assert np.allclose(cfg.goals[0].base, [goal["base_x"], goal["base_y"], goal["base_theta"]])
        assert (cfg.goals[0].xy_tolerance, cfg.goals[0].theta_tolerance) == (POSE_GOAL_XY_TOLERANCE_M,
                                                                             POSE_GOAL_THETA_TOLERANCE_RAD)
    # the goal test: the goal's own base is at the goal; a base beyond the tolerance is not
    for g in cfg.goals:
        q = np.zeros(cfg.robot.dof)
        q[:3] = g.base
        assert cfg.at_goal(q) == g.name
        q[0] += g.xy_tolerance + 0.02
        assert cfg.at_goal(q) != g.name
    # every target and dynamic obstacle on the monitor's topic for it
    want = {}
    for names, key in ((shared["targets"], "target_topics"), (shared["dynamic_obstacles"], "obstacle_topics")):
        topics = monitor.get(key) or [f"{monitor.get('mocap_prefix', '/mocap')}/{n}/pose" for n in names]
        want.update(zip(names, topics))
    assert cfg.body_topics == want
    assert json.loads(json.dumps(cfg.describe()))["scene"] == scene["name"]
    # the server's arrival budget: its replan settings file's (read here), and the loop given that much time
    planners = yaml.safe_load((ROOT / "config" / "planners" / f"{server['replan_settings']}.yaml").read_text())
    budget = server.get("arrival_budget", planners["arrival_budget"])
    assert cfg.arrival_budget == budget > 0
    assert cfg.patience_s(100.0, 120.0) == pytest.approx((1 + budget) * 100.0 + 10.0)
    assert cfg.patience_s(40.0, 120.0) == 120.0


def test_the_loop_waits_as_long_as_a_params_files_own_arrival_budget(tmp_path):
    """A params file that sets the server's arrival budget gives the loop that budget's time; with no budget (0) the
    loop waits ``--timeout`` alone."""
    src = (ROOT / "config" / "ros" / "dynamic_person.yaml").read_text()
    for budget, want in ((1.0, 2.0 * 100.0 + 10.0), (0.0, 120.0)):
        data = yaml.safe_load(src)
        data["roadmap_server"]["ros__parameters"]["arrival_budget"] = budget
        f = tmp_path / f"b{budget}.yaml"
        f.write_text(yaml.safe_dump(data))
        cfg = demo_config(f)
        assert cfg.arrival_budget == budget
        assert cfg.patience_s(100.0, 120.0) == pytest.approx(want)


def test_a_recording_the_params_file_does_not_stream_is_refused(tmp_path):
    """Bodies that are no target or dynamic obstacle of the params file, or poses in a frame it does not map."""
    rec = tmp_path / "r.csv"
    rec.write_text("time,body,frame,x,y,z,qx,qy,qz,qw\n0.0,sofa,map,4,5.45,0.4,0,0,0,1\n")
    with pytest.raises(InputError, match="sofa"):
        demo_config(ROOT / "config" / "ros" / "dynamic_person.yaml", load_recording(rec))
    rec.write_text("time,body,frame,x,y,z,qx,qy,qz,qw\n0.0,person_body,vicon,4,3.2,0.75,0,0,0,1\n")
    with pytest.raises(InputError, match="vicon"):
        demo_config(ROOT / "config" / "ros" / "dynamic_person.yaml", load_recording(rec))


@pytest.mark.parametrize("params_file", sorted(SHIPPED))
def test_each_params_file_has_its_shipped_recording(params_file):
    path = default_recording(ROOT / "config" / "ros" / params_file)
    assert path is not None and Path(path).resolve() == (ROOT / "config" / "recordings" / SHIPPED[params_file])
    assert Path(path).is_file()


# ---------------------------------------------------------------------------------------------------- recordings
@pytest.mark.parametrize("params_file", sorted(SHIPPED))
def test_shipped_recording_bodies_exist_and_move_plausibly(params_file, load_robot):
    """Each recorded body is a target or dynamic obstacle of the params file and of its scene, in a frame the params
    file maps; it streams at mocap rate without gaps, stays in the room, clear of the static furniture, never faster
    than a person walks or turns (finite differences over 0.1 s), jumps nowhere (sample to sample, and across the
    loop's seam), and never touches the robot standing at its start or at a goal (pybullet and the box model on the
    recorded poses)."""
    from judges import Judge, SentPoses

    params = _params(params_file)
    shared, server = params["/**"], params["roadmap_server"]
    scene = _scene_yaml(shared["scene"])
    tracks = _read_csv(ROOT / "config" / "recordings" / SHIPPED[params_file])
    streamed = set(shared["targets"]) | set(shared["dynamic_obstacles"])
    assert set(tracks) <= streamed, set(tracks) - streamed
    assert set(shared["dynamic_obstacles"]) <= set(tracks)  # every tracked obstacle streams (else it never updates)
    ws = scene["workspace"]
    recorded = set(tracks)
    static = [b for b in scene["obstacles"] if b["name"] not in recorded]
    moved, turned = 0.0, 0.0
    scene_poses = {}
    for body, (frame, t, P, Q) in tracks.items():
        box = _box_of(scene, body)
        P, Q = _in_scene_frame(params, scene["frame"], frame, P, Q)
        scene_poses[body] = (t, P, Q)
        assert np.allclose(np.linalg.norm(Q, axis=1), 1.0, atol=1e-3)
        dt = np.diff(t)
        assert t[-1] - t[0] >= 30.0 and len(t) / (t[-1] - t[0]) >= 100.0  # a mocap stream (Hz)
        assert dt.min() > 0 and dt.max() < 0.1  # sorted, no gap a stale timeout (0.5 s) would notice
        # no teleport: sample to sample within a person's speed (plus 5 mm of mocap noise), and the looped replay's
        # seam (last sample -> first) no larger
        step = np.linalg.norm(np.diff(P, axis=0), axis=1)
        assert (step <= HUMAN_SPEED_M_S * dt + 0.005).all(), step.max()
        assert np.linalg.norm(P[-1] - P[0]) < 0.05
        seam = abs(math.remainder(float(_yaw(Q[-1]) - _yaw(Q[0])), 2 * math.pi))
        assert seam < math.radians(5)
        # speeds over 0.1 s bins (the mean pose of each bin: the noise averages out)
        bins = np.floor((t - t[0]) / 0.1).astype(int)
        n = bins.max() + 1
        cnt = np.bincount(bins, minlength=n)
        ok = cnt > 0
        Pm = np.stack([np.bincount(bins, P[:, k], minlength=n) for k in range(3)], -1)[ok] / cnt[ok, None]
        yaw = np.unwrap(_yaw(Q))
        ym = (np.bincount(bins, yaw, minlength=n)[ok] / cnt[ok])
        tm = np.bincount(bins, t, minlength=n)[ok] / cnt[ok]
        speed = np.linalg.norm(np.diff(Pm[:, :2], axis=0), axis=1) / np.diff(tm)
        turn = np.abs(np.diff(ym)) / np.diff(tm)
        assert speed.max() < HUMAN_SPEED_M_S, (body, speed.max())
        assert turn.max() < HUMAN_TURN_RAD_S, (body, math.degrees(turn.max()))
        assert np.abs(np.diff(Pm[:, 2])).max() / 0.1 < 1.0  # no body flies up or down
        moved = max(moved, float(np.ptp(P[:, 0]) + np.ptp(P[:, 1])))
        turned = max(turned, float(np.ptp(yaw)))
        # in the room: the footprint inside the workspace (1 cm for the mocap noise of a body parked against a
        # wall); clear of the furniture it shares heights with
        for i in range(0, len(t), 24):  # every 0.2 s
            fp = _footprint(P[i], float(_yaw(Q[i])), box["size"])
            assert (fp[:, 0] >= ws["x"][0] - 0.01).all() and (fp[:, 0] <= ws["x"][1] + 0.01).all(), body
            assert (fp[:, 1] >= ws["y"][0] - 0.01).all() and (fp[:, 1] <= ws["y"][1] + 0.01).all(), body
            z0, z1 = P[i, 2] - box["size"][2] / 2, P[i, 2] + box["size"][2] / 2
            for o in static:
                oz0, oz1 = o["center"][2] - o["size"][2] / 2, o["center"][2] + o["size"][2] / 2
                if z1 <= oz0 or oz1 <= z0:
                    continue
                assert not _overlap(fp, _footprint(o["center"], _static_yaw(o), o["size"])), \
                    f"{body} inside {o['name']} at t={t[i] - t[0]:.2f} s"
    assert moved > 0.5 or turned > math.radians(90)  # the recording moves something
    # the robot standing at its start and at every goal is touched by no recorded body
    robot = load_robot(shared.get("robot") or scene["robot"])
    problems = {p["name"]: p for p in scene["problems"]}
    sim_problem = params["sim_robot"].get("start_problem")
    starts = [robot.configuration(problems[sim_problem]["start"] if sim_problem else scene["problems"][0]["start"])]
    goal_problem = problems[server["start_problem"]]
    goals = [robot.configuration({"base_x": g["base"][0], "base_y": g["base"][1], "base_theta": g["base"][2]})
             for g in scene.get("goals", []) if g["name"] in goal_problem.get("goal_regions", [])]
    if goal_problem.get("goal"):
        goals.append(robot.configuration(goal_problem["goal"]))
    assert goals
    qs = np.array(starts + goals)
    sent = SentPoses(scene["name"])
    judge = Judge(robot, sent)
    try:
        assert not judge.colliding(qs).any()  # precondition: clear of the scene as it stands
        t_all = np.arange(0.0, min(tt[-1] - tt[0] for tt, _, _ in scene_poses.values()), 0.25)
        for tq in t_all:
            for body, (t, P, Q) in scene_poses.items():
                i = min(int(np.searchsorted(t - t[0], tq)), len(t) - 1)
                sent.sent(body, P[i], Q[i])
            hit = judge.colliding(qs)
            assert not hit.any(), f"t={tq:.2f} s: a recorded body touches the robot at its start or a goal"
    finally:
        judge.close()


def test_nursing_and_alley_recordings_move_the_way_their_scenes_need(tmp_path):
    """A nurse walks (about a metre) while both turn; the monitor rolls (metres), both back where they started."""
    nurses = _read_csv(ROOT / "config" / "recordings" / SHIPPED["fetchlike_nursing.yaml"])
    walk = {b: float(np.ptp(P[:, 1])) for b, (_, _, P, _) in nurses.items() if b.endswith("_body")}
    turns = {b: float(np.ptp(np.unwrap(_yaw(Q)))) for b, (_, _, _, Q) in nurses.items() if b.endswith("_face")}
    assert max(walk.values()) > 0.8 and min(turns.values()) > math.radians(150)
    cart = _read_csv(ROOT / "config" / "recordings" / SHIPPED["ur5_mobile_blind_spot_alley.yaml"])
    _, t, P, _ = cart["monitor"]
    assert np.ptp(P[:, 0]) > 1.5
    _, ts, S, _ = cart["monitor_stand"]
    S = np.c_[np.interp(t, ts, S[:, 0]), np.interp(t, ts, S[:, 1])]  # the stand at the monitor's samples
    assert np.linalg.norm(P[:, :2] - S - (P[0, :2] - S[0]), axis=1).max() < 0.05  # it rides on its stand


def test_shipped_recordings_are_what_their_generator_writes(tmp_path):
    """The CSVs are generated (``python -m psprm_ros.interfaces.recordings``), not edited by hand: regenerated, they are
    the same files."""
    from psprm_ros.interfaces import recordings

    for name, (_, path, params) in recordings.SHIPPED.items():
        assert SHIPPED[Path(params).name] == Path(path).name
        assert recordings.main([name, "--out", str(tmp_path / f"{name}.csv")]) == 0
        assert (tmp_path / f"{name}.csv").read_bytes() == (ROOT / path).read_bytes(), name


# ---------------------------------------------------------------------------------------------------- result helpers
def test_result_helpers_against_hand_computed_values():
    doc = strict_json({"a": float("nan"), "b": [np.float32(np.inf), 1.5, None], "c": {"d": np.float64(-np.inf)},
                       "e": np.int64(3), "f": np.bool_(True)})
    assert json.loads(json.dumps(doc, allow_nan=False)) == {"a": None, "b": [None, 1.5, None], "c": {"d": None},
                                                            "e": 3, "f": True}
    assert goal_switches([0, 0, 1, 1, None, 0, 0]) == 2 and goal_switches([1]) == 0 and goal_switches([]) == 0
    # the base moves until t = 2, then rests (a 1 mm wobble); heading given as pi and -pi (the same)
    T = np.arange(0.0, 5.0, 0.5)
    Q = np.zeros((len(T), 3))
    Q[:, 0] = np.minimum(T, 2.0)
    Q[:, 2] = np.where(np.arange(len(T)) % 2 == 0, math.pi, -math.pi)
    Q[-1, 1] = 0.001
    assert rest_arrival(T, Q) == 2.0 and rest_arrival(np.zeros(0), np.zeros((0, 3))) is None
    statuses = [(1.0, "robot_adapter", "warning: robot stopped: trajectory refused: first point 0.3 from ..."),
                (2.0, "robot_adapter", "warning: robot stopped: stop trajectory received"),
                (3.0, "robot_adapter", "warning: robot stopped: off the checked path by 0.05 m"),
                (4.0, "roadmap_server", "warning: robot stopped: not the adapter"),
                (9.0, "robot_adapter", "warning: robot stopped: shutting down")]
    assert adapter_stops(statuses, 0.5, 5.0) == {"trajectory refused": 1, "off the checked path by 0.05 m": 1}


def test_replayer_publishes_on_the_monitors_topics():
    """With the demo's topics, each recorded body goes out on the topic the params file gives the monitor."""
    pytest.importorskip("rclpy")
    import rclpy

    from psprm_ros.mocap_replay import Replayer
    from psprm_ros.harness.probe import claim_domain_id

    params = _params("fetchlike_nursing.yaml")
    monitor, shared = params["replan_monitor"], params["/**"]
    want = dict(zip(shared["targets"], monitor["target_topics"])) | dict(zip(shared["dynamic_obstacles"],
                                                                           monitor["obstacle_topics"]))
    rec = load_recording(ROOT / "config" / "recordings" / SHIPPED["fetchlike_nursing.yaml"])
    cfg = demo_config(ROOT / "config" / "ros" / "fetchlike_nursing.yaml", rec)
    ctx = rclpy.Context()
    ctx.init(domain_id=claim_domain_id())
    node = rclpy.create_node("replay", context=ctx)
    try:
        rp = Replayer(node, rec, topics=cfg.body_topics)
        assert {rec.bodies[i]: p.topic_name for i, p in rp.pubs.items()} == want
    finally:
        node.destroy_node()
        ctx.try_shutdown()


def test_a_collision_detail_names_the_box_pybullet_finds_the_robot_in(load_robot):
    """The main job's report of an executed configuration in collision (``_collision_detail``) names the kind and
    the boxes; judged by pybullet with each of the scene's boxes alone, on configurations the test places: the base
    driven into the person's body, and one clear of everything. The base speed is the test's finite difference."""
    import torch

    from psprm_core.collision import CollisionChecker
    from psprm_core.evaluation.reference import PybulletWorld
    from psprm_core.paths import resolve_named
    from psprm_core.scene import load_scene
    from psprm_ros.harness.demo_analysis import _collision_detail

    robot = load_robot("stretch2")
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    boxes = scene.collision_boxes()
    from psprm_core.planning.factory import problem_configurations

    body = next(b for b in boxes if b.name == "person_body")
    q_clear = np.asarray(problem_configurations(robot, scene, scene.problems[0])[0], float)  # the scene's start
    q_in = q_clear.copy()
    q_in[:2] = body.center[:2] + np.array([0.05, 0.0])  # the base centre inside the body's box
    T = np.arange(6) * 0.02
    Q = np.repeat(q_clear[None], 6, 0)
    Q[:, 0] += 0.01 * np.arange(6)  # 0.5 m/s along x
    Q[-1] = q_in
    Q[-2, :2] = q_in[:2] - [0.01, 0.0]  # the last step: 0.01 m in 0.02 s
    checker = CollisionChecker(robot, boxes, workspace=scene.workspace)
    d_in = _collision_detail(checker, boxes, T, Q, 5, 0.0)
    d_clear = _collision_detail(checker, boxes, T, Q, 3, 0.0)
    ref = {}
    for b in boxes:
        world = PybulletWorld(robot, [b])
        try:
            ref[b.name] = world.in_collision(np.stack([q_in, q_clear]))
        finally:
            world.close()
    assert ref["person_body"][0] and not any(v[1] for v in ref.values())
    assert d_in["kinds"] == ["environment"]
    assert set(d_in["boxes"]) == {n for n, v in ref.items() if v[0]}
    assert d_clear["kinds"] == [] and d_clear["boxes"] == []
    assert d_in["t"] == 0.1 and d_in["base"][:2] == [round(float(v), 3) for v in q_in[:2]]
    assert abs(d_clear["base_speed_mps"] - 0.5) < 1e-6
    # the checker holds the scene's boxes again afterwards
    assert bool(checker.check(torch.as_tensor(q_in[None], dtype=torch.float32))[0])


def test_the_post_mortem_record_holds_what_the_test_gave_it(tmp_path, load_robot):
    """``save_record`` (the soak's record, and the main job's when it misses its goal or collides) writes the
    executed motion, each trajectory message's positions and times and the replayed poses; read back with numpy
    against the values the test built the messages from."""
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    from psprm_ros.harness.soak_report import save_record

    robot = load_robot("stretch2")
    names = list(robot.joint_names)
    rng = np.random.default_rng(3)
    ex = [(10.0 + 0.02 * i, rng.normal(size=len(names))) for i in range(5)]
    P = rng.normal(size=(3, len(names)))
    msg = JointTrajectory(joint_names=names[::-1])  # another joint order than the robot's
    for k in range(3):
        msg.points.append(JointTrajectoryPoint(positions=[float(v) for v in P[k][::-1]],
                                               time_from_start=Duration(sec=k, nanosec=500_000_000)))
    poses = [(10.01, "person_body", np.array([4.0, 3.2, 0.75]), np.array([0.0, 0.0, 0.1, 0.995])),
             (10.03, "person_face", np.array([3.9, 3.2, 1.6]), np.array([0.0, 0.0, 0.0, 1.0]))]
    path = tmp_path / "r.npz"
    save_record(path, ex, [(10.05, msg)], names, poses=poses)
    d = np.load(path)
    assert np.allclose(d["executed_t"], [0.02 * i for i in range(5)])
    assert np.allclose(d["executed_q"], np.array([q for _, q in ex]))
    assert np.allclose(d["trajectory_t"], [0.05]) and list(d["trajectory_offsets"]) == [0, 3]
    assert np.allclose(d["trajectory_q"], P) and np.allclose(d["trajectory_time_from_start"], [0.5, 1.5, 2.5])
    assert np.allclose(d["pose_t"], [0.01, 0.03]) and list(d["pose_body"]) == ["person_body", "person_face"]
    assert np.allclose(d["pose_p"][1], [3.9, 3.2, 1.6]) and np.allclose(d["pose_q"][0], [0.0, 0.0, 0.1, 0.995])
