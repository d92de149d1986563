"""The dynamic benchmark (``psprm dynbench``, :mod:`psprm_core.evaluation.dynamic.dynamic_bench`) and the episode modes
of
:func:`psprm_core.evaluation.simulation.run_episode`, judged from records the code did not produce: the person's poses
computed here from the scenario's numbers, finite differences of the executed configurations against the robot's
velocity limits, the old trajectory's own ``evaluate``, pybullet's exact check (``judges.Judge``) on the poses computed
here, and the strict-JSON parser."""

from __future__ import annotations

import dataclasses
import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from psprm_core.errors import ConfigError
from psprm_core.evaluation.scenario_world import World
from psprm_core.evaluation.scenarios import draw_variation, load_scenario
from psprm_core.evaluation.simulation import run_episode
from psprm_core.geometry import yaw_to_quat
from psprm_core.paths import config_dir, resolve_named
from psprm_core.planning.factory import make_planner
from psprm_core.robot import RobotModel
from psprm_core.scene import load_scene

from judges import Judge, SentPoses  # noqa: E402

LATENCY = 0.3
MODES = ("motion", "motion_no_prediction", "from_rest", "static")


def _heading(q) -> float:
    x, y, z, w = (float(v) for v in q)
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def _expected_person(t: float, var: dict) -> dict:
    """The rotating_person scenario's person at time t, computed here from the scenario file's numbers and the
    episode's variation: yaw(t) = yaw0 + A a sin(2 pi t / (P p) + phase), the body turning about its centre by the
    face's change of heading, the face keeping its offset from the body's centre."""
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    face, body = scene.target("person_face"), scene.obstacle("person_body")
    A, P, yaw0 = 1.2, 14.0, -1.5708  # config/scenarios/rotating_person.yaml
    yaw = yaw0 + A * var["amplitude_scale"] * math.sin(2 * math.pi * t / (P * var["period_scale"]) + var["phase_rad"])
    d = yaw - _heading(face.quat)
    off = face.center - body.center
    c, s = math.cos(d), math.sin(d)
    face_c = body.center + np.array([c * off[0] - s * off[1], s * off[0] + c * off[1], off[2]])
    return {"face": (face_c, yaw), "body": (body.center.copy(), _heading(body.quat) + d)}


@pytest.fixture(scope="module")
def episodes():
    """rotating_person (600 nodes, 20 s) in every replanning mode and static, episode 0's variation, every mode from
    a copy of one saved roadmap. Every replan a trigger asks for is adopted (``keep_unless_better`` off: which replans
    replace the plan under way is judged in test_replanner.py), so that the modes' splices and stops happen."""
    from psprm_core.planning.replanner import ReplanSettings

    torch.set_num_threads(1)
    sc = load_scenario(resolve_named("scenario", "rotating_person"))
    sc = dataclasses.replace(sc, nodes=600, duration_s=20.0, camera_fps=1.0)
    scene = load_scene(resolve_named("scene", sc.scene))
    robot = RobotModel.load(scene.robot)

    def fresh():
        return make_planner(sc.planner, scene, list(sc.targets), robot=robot,
                            options={"roadmap.n_nodes": sc.nodes, "seed": sc.seed})

    p = fresh()
    assert p.build()["success"]
    var = draw_variation(sc, 0)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = p.save(Path(tmp) / "roadmap.npz")
        for mode in MODES:
            pl = fresh()
            pl.load(path)
            out[mode] = run_episode(sc, mode=mode, planner=pl, variation=var, latency_s=LATENCY,
                                    replan_settings=ReplanSettings(keep_unless_better=False))
    return sc, robot, var, out


def _speeds(times, executed, robot) -> np.ndarray:
    """Finite-difference speeds between consecutive executed configurations over the robot's limits (steps x
    [base linear, heading, joints...])."""
    dt = np.diff(times)
    d = np.diff(np.asarray(executed, float), axis=0)
    d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
    b = robot.config.base
    lin = np.hypot(d[:, 0], d[:, 1]) / dt / b.linear_velocity
    ang = np.abs(d[:, 2]) / dt / b.angular_velocity
    joints = np.abs(d[:, 3:]) / dt[:, None] / np.asarray(robot.velocity, float)[3:]
    return np.column_stack([lin, ang, joints])


def test_motion_mode_executes_continuously_across_spliced_replans(episodes):
    sc, robot, _, eps = episodes
    ep = eps["motion"]
    spliced = [a for a in ep["adoptions"] if a["spliced"]]
    assert spliced, "precondition: the motion mode adopted a replan in motion"
    t, x = np.asarray(ep["times"]), np.asarray(ep["executed"])
    assert np.allclose(np.diff(t), sc.control_dt)
    v = _speeds(t, x, robot)
    assert v.max() <= 1.0 + 1e-6, f"a step faster than the limits: {v.max():.3f} x at t = {t[1 + v.max(1).argmax()]}"
    # the robot moved on after each adoption (the check above is not about a robot at rest)
    for a in spliced:
        after = (t > a["t"]) & (t <= a["t"] + 2.0)
        assert np.abs(np.diff(x[after], axis=0)).max() > 1e-4


def test_spliced_trajectory_reproduces_the_old_one_up_to_the_commit(episodes):
    sc, robot, _, eps = episodes
    ep = eps["motion"]
    spliced = [a for a in ep["adoptions"] if a["spliced"]]
    assert spliced, "precondition: the motion mode adopted a replan in motion"
    t, x = np.asarray(ep["times"]), np.asarray(ep["executed"])
    for a in spliced:
        old, new = a["old"], a["new"]
        assert a["committed_s"] >= LATENCY - 1e-9  # the commit lies at least the latency ahead
        ts = np.linspace(0.0, a["committed_s"], 60)
        q_new = new.evaluate(ts)[0]
        q_old = old.evaluate(ts + a["start_offset_s"])[0]
        assert np.abs(q_new - q_old).max() < 1e-6
        # its time 0 is where the robot was on the old trajectory when it replanned (the executed record)
        i = int(np.argmin(np.abs(t - a["t"])))
        q_robot = x[i]
        q_there = old.evaluate(a["t"] - a["old_t0"])[0][0]
        d = q_there - q_robot
        d[2] = (d[2] + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(d).max() < 1e-6
        assert abs(a["start_offset_s"] - (a["t"] - a["old_t0"])) < 1e-9


def test_from_rest_mode_stops_and_waits_the_latency(episodes):
    sc, robot, _, eps = episodes
    ep = eps["from_rest"]
    assert ep["stops"] >= 1, "precondition: a replan was adopted while the robot moved"
    t, x = np.asarray(ep["times"]), np.asarray(ep["executed"])
    v = _speeds(t, x, robot)
    checked = 0
    for a in ep["adoptions"]:
        i = int(np.argmin(np.abs(t - a["t"])))
        if i == 0 or v[i - 1].max() < 1e-3:
            continue  # it was at rest already
        wait = (t >= a["t"] - 1e-9) & (t <= a["t"] + LATENCY + 1e-9)
        assert wait.sum() >= int(round(LATENCY / sc.control_dt)) + 1
        # at rest (the new plan starts at the robot's configuration as the planner's float32 holds it: < 1e-6)
        assert np.abs(np.diff(x[wait], axis=0)).max() < 1e-6, f"moved during the wait after t = {a['t']}"
        assert np.abs(x[i - 1] - x[i]).max() > 1e-4  # and it was moving just before
        checked += 1
    assert checked >= 1
    assert v.max() <= 1.0 + 1e-6  # no jump either (the stop is where the robot was)


def test_every_mode_executes_collision_free_against_the_moving_person(episodes, load_robot):
    sc, robot, var, eps = episodes
    v = var["person_face"].as_dict()
    sent = SentPoses("dynamic_person")
    judge = Judge(robot, sent)
    try:
        # the judge can fail: the robot standing where the person stands collides
        q_bad = np.asarray(eps["static"]["executed"][0], float).copy()
        q_bad[:2] = sent.scene.obstacle("person_body").center[:2]
        assert judge.colliding(q_bad[None])[0]
        for mode, ep in eps.items():
            hits = 0
            for t, q in zip(ep["times"], ep["executed"]):
                pp = _expected_person(float(t), v)
                sent.sent("person_face", pp["face"][0], yaw_to_quat(pp["face"][1]))
                sent.sent("person_body", pp["body"][0], yaw_to_quat(pp["body"][1]))
                hits += int(judge.colliding(np.asarray(q)[None])[0])
            assert hits == 0, f"{mode}: {hits} executed configurations in collision"
            assert ep["collision_steps"] == 0
    finally:
        judge.close()


def test_every_mode_sees_the_same_varied_person(episodes):
    sc, robot, var, eps = episodes
    v = var["person_face"].as_dict()
    assert 0.8 <= v["period_scale"] <= 1.2 and 0.85 <= v["amplitude_scale"] <= 1.15
    assert abs(v["period_scale"] - 1) > 1e-3 and abs(v["amplitude_scale"] - 1) > 1e-3  # it varies
    ref = None
    for mode, ep in eps.items():
        assert ep["variation"]["person_face"] == v
        k = int(round(1.0 / (sc.camera_fps * sc.control_dt)))
        ts = np.asarray(ep["times"])[::k]
        assert len(ep["frames_scene"]) == len(ts)
        for t, poses in zip(ts, ep["frames_scene"]):
            c, q = poses["targets"]["person_face"]
            pp = _expected_person(float(t), v)
            assert np.allclose(c, pp["face"][0], atol=1e-6)
            dyaw = (_heading(q) - pp["face"][1] + np.pi) % (2 * np.pi) - np.pi
            assert abs(dyaw) < 1e-6
            bc, bq = poses["obstacles"]["person_body"]
            assert np.allclose(bc, pp["body"][0], atol=1e-6)
        seen = {round(float(t), 6): poses["targets"]["person_face"][1] for t, poses in zip(ts, ep["frames_scene"])}
        if ref is not None:
            common = set(seen) & set(ref)
            assert len(common) >= 5
            assert all(np.allclose(seen[t], ref[t]) for t in common)
        ref = seen if ref is None else ref
    # another episode's person differs
    other = draw_variation(sc, 1)["person_face"].as_dict()
    assert other != v


def test_keyframed_walk_interpolates_and_the_body_follows():
    sc = load_scenario(resolve_named("scenario", "walking_person"))
    scene = load_scene(resolve_named("scene", sc.scene))
    world = World(sc, scene)
    body0, face0 = scene.obstacle("person_body"), scene.target("person_face")
    # halfway through the walk from (4.0, 3.2) at 3 s to (2.6, 4.3) at 6 s, heading held at -3.808
    poses = world.poses(4.5)
    bc, bq = poses["obstacles"]["person_body"]
    assert np.allclose(bc[:2], [3.3, 3.75], atol=1e-9) and abs(bc[2] - body0.center[2]) < 1e-12
    fc, fq = poses["targets"]["person_face"]
    dyaw = -3.808 - _heading(face0.quat)
    off = face0.center - body0.center
    want = bc + np.array([math.cos(dyaw) * off[0] - math.sin(dyaw) * off[1],
                          math.sin(dyaw) * off[0] + math.cos(dyaw) * off[1], off[2]])
    assert np.allclose(fc, want, atol=1e-9)
    assert abs((_heading(fq) + 3.808 + np.pi) % (2 * np.pi) - np.pi) < 1e-9
    # a turn in place: 1.5 -> 3 s from -1.5708 to -3.808, standing at the start
    _, q = world.poses(2.25)["targets"]["person_face"]
    assert abs((_heading(q) - 0.5 * (-1.5708 - 3.808) + np.pi) % (2 * np.pi) - np.pi) < 1e-9
    # the loop: 30 s later it is where it was
    a, b = world.poses(4.5), world.poses(34.5)
    assert np.allclose(a["obstacles"]["person_body"][0], b["obstacles"]["person_body"][0], atol=1e-9)
    # an episode's variation retimes the walk (speed) but keeps its places
    var = draw_variation(sc, 3)
    w2 = World(sc, scene, variation=var)
    s = var["person_face"].speed_scale
    assert abs(s - 1) > 1e-3
    xs = [w2.poses(t)["obstacles"]["person_body"][0][:2] for t in np.arange(0, 60, 0.05)]
    d = np.linalg.norm(np.diff(xs, axis=0), axis=1) / 0.05
    fastest = max(math.hypot(1.4, 1.1) / 3.0, 2.8 / 3.5, math.hypot(1.4, 1.1) / 2.0)  # the file's three walks
    assert s * fastest * 0.95 <= d.max() <= s * fastest * 1.001 + 1e-9  # at the varied speed
    assert any(np.allclose(x, [2.6, 4.3], atol=1e-6) for x in xs)


def test_shipped_scenarios_meet_their_scenes_and_bad_ones_name_the_field(tmp_path):
    for f in sorted((config_dir() / "scenarios").glob("*.yaml")):
        sc = load_scenario(f)
        World(sc, load_scene(resolve_named("scene", sc.scene)))
    nursing = load_scenario(resolve_named("scenario", "nursing_turning_walking"))
    assert nursing.targets == ("nurse_1_face", "nurse_2_face") and len(nursing.people) == 2
    base = ("name: x\nscene: dynamic_person\ntarget: person_face\nstart: {base_x: 1}\ngoals: [at_shelf]\n")
    bad = {"people: [{target: person_face, keyframes: [{t: 2, yaw: 0}, {t: 1, yaw: 1}]}]\n":
           r"people\[0\]\.keyframes\[1\]\.t",
           "people: [{target: person_face, keyframes: [{t: 0, xy: [1, 2, 3]}]}]\n": r"keyframes\[0\]\.xy",
           "people: [{target: person_face, keyframes: [{t: 5, yaw: 0}], loop_s: 3}]\n": r"people\[0\]\.loop_s",
           "people: [{target: person_face, walk: 1}]\n": r"people\[0\]\.walk",
           "targets: [person_face]\n": "either 'target'",
           "variation: {speed: 2}\n": r"variation\.speed"}
    for extra, msg in bad.items():
        (tmp_path / "bad.yaml").write_text(base + extra)
        with pytest.raises(ConfigError, match=msg):
            load_scenario(tmp_path / "bad.yaml")
    (tmp_path / "far.yaml").write_text(base + "people: [{target: person_face, keyframes: [{t: 0, xy: [40, 2]}]}]\n")
    with pytest.raises(ConfigError, match="outside the scene's workspace"):
        World(load_scenario(tmp_path / "far.yaml"), load_scene(resolve_named("scene", "dynamic_person")))


def _strict(text: str):
    def no_constant(c):
        raise AssertionError(f"not strict JSON: {c}")

    return json.loads(text, parse_constant=no_constant)


def test_dynbench_command_prints_strict_json(tmp_path, capsys):
    from psprm_core.cli import main

    out = tmp_path / "dyn.json"
    assert main(["dynbench", "--scenarios", "rotating_person", "--episodes", "1", "--nodes", "600", "--duration",
                 "4", "--camera-fps", "0.5", "--modes", "motion,static,hindsight", "--workers", "1", "--no-progress",
                 "--json", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    res = _strict(printed)
    assert _strict(out.read_text()) == res
    s = res["scenarios"]["rotating_person"]
    ep = s["episodes"][0]
    assert set(ep["modes"]) == {"motion", "static", "hindsight"}
    # 4 s is too short to arrive: the numbers that do not exist are null (NaN before)
    assert ep["modes"]["motion"]["reached"] is False and ep["modes"]["motion"]["time_ratio"] is None
    assert s["summary"]["modes"]["motion"]["time_ratio"] is None
    assert ep["modes"]["motion"]["frames"] == 3  # t = 0, 2, 4 s
    assert ep["modes"]["motion"]["det_rate"] is not None


def test_dynbench_applies_a_nested_replan_setting(tmp_path, capsys):
    """``--replan prediction.enabled=false`` reaches the episodes' replanner: mode ``motion`` with prediction off
    replays exactly what mode ``motion_no_prediction`` (prediction off by its mode) does in the same episode, and
    no episode fails."""
    from psprm_core.cli import main

    assert main(["dynbench", "--scenarios", "rotating_person", "--episodes", "1", "--nodes", "600", "--duration",
                 "8", "--camera-fps", "1", "--modes", "motion,motion_no_prediction", "--workers", "1",
                 "--no-progress", "--replan", "prediction.enabled=false", "--json"]) == 0
    s = _strict(capsys.readouterr().out)["scenarios"]["rotating_person"]
    assert s["summary"]["failed_episodes"] == 0
    modes = s["episodes"][0]["modes"]
    keys = ("det_rate", "adopted", "declined", "frames", "goal_switches", "stops")
    assert {k: modes["motion"][k] for k in keys} == {k: modes["motion_no_prediction"][k] for k in keys}
    assert modes["motion"]["adopted"] + modes["motion"]["declined"] > 0  # it replanned


def test_simulate_json_is_strict(tmp_path, capsys):
    from psprm_core.cli import main

    assert main(["simulate", "--scenario", "rotating_person", "--nodes", "600", "--duration", "1", "--threads", "1",
                 "--json", "--plot", str(tmp_path / "sim.png")]) == 0
    res = _strict(capsys.readouterr().out)
    assert res["static"]["replan_ms_median"] is None  # the static plan never replans: null, not NaN
    assert res["reached_goal"] is False and res["time_ratio"] is None


def test_a_frame_judge_starts_from_the_scene_file_whatever_the_oracle_judged_before(load_robot):
    """A worker keeps one oracle per scene: the chair moved by one scenario's episode must be back where the scene
    file has it in the next scenario's frames (read from the renderer's pybullet bodies)."""
    from psprm_core.evaluation.dynamic.episodes import FrameJudge
    from psprm_core.perception.oracle import Oracle

    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = load_robot("stretch2")
    moving = World(load_scenario(resolve_named("scenario", "moving_obstacle_and_goal")), scene, robot)
    still = World(load_scenario(resolve_named("scenario", "rotating_person")), scene, robot)
    oracle = Oracle(scene, intrinsics=robot.config.intrinsics)
    r = oracle.renderer

    def chair_at() -> np.ndarray:
        (body, local), = r._items[("obstacle", "chair")].bodies
        return np.asarray(r._p.getBasePositionAndOrientation(body, physicsClientId=r._client)[0])

    try:
        file_chair = load_scene(resolve_named("scene", "dynamic_person")).obstacle("chair").center
        q = robot.configuration({"base_x": 4.0, "base_y": 0.7, "base_theta": 1.5708})
        FrameJudge(oracle, robot, moving, ["person_face"]).judge(np.array([10.0]), q[None])
        moved = moving.poses(10.0)["obstacles"]["chair"][0]
        assert np.linalg.norm(moved - file_chair) > 0.5 and np.allclose(chair_at(), moved, atol=1e-6)
        FrameJudge(oracle, robot, still, ["person_face"])
        assert np.allclose(chair_at(), file_chair, atol=1e-6)
    finally:
        oracle.close()


def test_scenario_summary_ratios_and_headroom_share_from_hand_made_episodes():
    """The summary's means, ratios and share of the dynamic headroom written out by hand for three episodes (one
    without a hindsight reference, which the share leaves out)."""
    from psprm_core.evaluation.dynamic.dynamic_bench import summarize_scenario

    def row(det, reached=True, collisions=0, stops=0, time_ratio=1.0, switches=0):
        return {"det_rate": det, "det_rate_any": det, "reached": reached, "collisions": collisions, "stops": stops,
                "adopted": stops, "declined": 2 * stops, "declined_late": stops, "goal_switches": switches,
                "time_ratio": time_ratio if reached else None}

    det = {"motion": [0.6, 0.5, 0.4], "motion_no_prediction": [0.5, 0.5, 0.2], "from_rest": [0.4, 0.3, 0.3],
           "static": [0.4, 0.4, 0.3], "hindsight": [0.7, 0.6, None]}
    eps = [{"episode": i, "modes": {m: row(det[m][i], reached=not (m == "static" and i == 2),
                                           collisions=5 if (m == "static" and i == 2) else 0,
                                           stops=2 if m == "from_rest" else 0,
                                           time_ratio=1.5 if m == "motion" else 1.0)
                                    for m in det}} for i in range(3)]
    eps.append({"episode": 3, "error": "worker died"})
    s = summarize_scenario(eps, list(det))
    assert s["episodes"] == 3 and s["failed_episodes"] == 1
    m = s["modes"]
    assert m["motion"]["det_rate"] == pytest.approx(0.5) and m["static"]["det_rate"] == pytest.approx(1.1 / 3)
    assert m["hindsight"]["det_rate"] == pytest.approx(0.65)
    assert m["static"]["reached_pct"] == pytest.approx(200 / 3) and m["static"]["collisions"] == 5
    assert m["from_rest"]["stops"] == 6 and m["motion"]["time_ratio"] == pytest.approx(1.5)
    assert m["from_rest"]["declined_mean"] == pytest.approx(4.0) and m["from_rest"]["declined_late_mean"] == 2.0
    r = s["ratios"]
    assert r["motion_over_static"] == pytest.approx(0.5 / (1.1 / 3))
    assert r["motion_over_no_prediction"] == pytest.approx(0.5 / 0.4)
    assert r["motion_over_hindsight"] == pytest.approx(0.55 / 0.65) and r["motion_over_hindsight_episodes"] == 2
    # share over the two episodes with a reference: a = 0.55, d = 0.4, e = 0.65
    assert r["headroom_share"] == pytest.approx((0.55 - 0.4) / (0.65 - 0.4)) and r["headroom_share_episodes"] == 2
    # no headroom (hindsight no better than static): no share
    for e in eps[:3]:
        e["modes"]["hindsight"]["det_rate"] = e["modes"]["static"]["det_rate"]
    assert summarize_scenario(eps, list(det))["ratios"]["headroom_share"] is None


def _write_recording(path: Path, n: int = 41, dt: float = 0.1, frame: str = "map") -> tuple:
    """A recording written here: the dynamic_person scene's face and body, the face turning at a constant rate
    (heading -1.5708 + 0.3 t) and both drifting east (x + 0.05 t), sampled every ``dt`` s. Returns the numbers it
    was written from, (times, face positions, face headings)."""
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    face, body = scene.target("person_face"), scene.obstacle("person_body")
    ts = np.arange(n) * dt
    rows = ["time,body,frame,x,y,z,qx,qy,qz,qw"]
    fc, fyaw = [], []
    for t in ts:
        yaw = -1.5708 + 0.3 * t
        shift = np.array([0.05 * t, 0.0, 0.0])
        for name, c in (("person_face", face.center + shift), ("person_body", body.center + shift)):
            q = yaw_to_quat(yaw)
            rows.append(f"{t + 100.0:.6f},{name},{frame}," + ",".join(f"{v:.9f}" for v in (*c, *q)))
        fc.append(face.center + shift)
        fyaw.append(yaw)
    path.write_text("\n".join(rows) + "\n")
    return ts, np.array(fc), np.array(fyaw)


def _recorded_scenario(tmp_path: Path, extra: str = "", bodies: str = "[person_face, person_body]") -> Path:
    f = tmp_path / "rec_scenario.yaml"
    f.write_text("name: rec\nscene: dynamic_person\ntarget: person_face\n"
                 "start: {base_x: 4.0, base_y: 0.7, base_theta: 1.5708}\ngoals: [at_shelf]\n"
                 f"recording: {{file: rec.csv, bodies: {bodies}}}\n" + extra)
    return f


def test_a_recorded_scenario_replays_the_recording_looped_from_the_drawn_moment(tmp_path):
    ts, fc, fyaw = _write_recording(tmp_path / "rec.csv")
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    sc = load_scenario(_recorded_scenario(tmp_path))
    world = World(sc, scene)
    loop = 4.0 + 0.1  # 41 samples 0.1 s apart; the first follows the last one period later
    for t, c, yaw in zip(ts, fc, fyaw):  # the samples as written (recorded time 100 s = replay time 0)
        for tt in (t, t + loop, t + 3 * loop):
            got = world.poses(float(tt))["targets"]["person_face"]
            assert np.allclose(got[0], c, atol=1e-8)
            assert abs(_heading(got[1]) - yaw) < 1e-6
    mid = world.poses(1.25)  # halfway between the samples at 1.2 and 1.3 s
    assert np.allclose(mid["targets"]["person_face"][0], 0.5 * (fc[12] + fc[13]), atol=1e-8)
    assert abs(_heading(mid["targets"]["person_face"][1]) - (-1.5708 + 0.3 * 1.25)) < 1e-6
    assert np.allclose(mid["obstacles"]["person_body"][0][0],
                       scene.obstacle("person_body").center[0] + 0.05 * 1.25, atol=1e-8)
    wrap = world.poses(4.05)  # halfway from the last sample back to the first
    assert np.allclose(wrap["targets"]["person_face"][0], 0.5 * (fc[-1] + fc[0]), atol=1e-8)
    # an episode starts its replay a drawn fraction into the loop; the people's draws come first, unchanged
    starts = set()
    for e in range(3):
        var = draw_variation(sc, e)
        frac = var["<recording>"].phase_rad / (2 * math.pi)
        assert 0.0 <= frac < 1.0
        starts.add(round(frac, 6))
        w = World(sc, scene, variation=var)
        for t in (0.0, 0.7, 2.0):
            tau = (t + frac * loop) % loop
            if tau <= ts[-1]:
                want_c = np.array([np.interp(tau, ts, fc[:, k]) for k in range(3)])
                want_yaw = np.interp(tau, ts, fyaw)
            else:  # on the stretch back to the first sample
                w8 = (tau - ts[-1]) / 0.1
                want_c, want_yaw = (1 - w8) * fc[-1] + w8 * fc[0], None
            c, q = w.poses(t)["targets"]["person_face"]
            assert np.allclose(c, want_c, atol=1e-8)
            if want_yaw is not None:
                assert abs(_heading(q) - want_yaw) < 1e-6
    assert len(starts) == 3
    rot = load_scenario(resolve_named("scenario", "rotating_person"))
    both = dataclasses.replace(rot, recording=dataclasses.replace(sc.recording, bodies=("person_face",)))
    assert draw_variation(both, 2)["person_face"] == draw_variation(rot, 2)["person_face"]


def test_bad_recordings_in_a_scenario_name_the_field(tmp_path):
    _write_recording(tmp_path / "rec.csv")
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    with pytest.raises(ConfigError, match=r"recording\.bodies.*not in"):
        World(load_scenario(_recorded_scenario(tmp_path, bodies="[person_face, nurse_body]")), scene)
    missing = tmp_path / "missing.yaml"
    missing.write_text(_recorded_scenario(tmp_path).read_text().replace("rec.csv", "absent.csv"))
    with pytest.raises(ConfigError, match=r"recording\.file"):
        World(load_scenario(missing), scene)
    with pytest.raises(ConfigError, match=r"recording\.bodies"):
        load_scenario(_recorded_scenario(tmp_path, extra="person: {target: person_face}\n"))
    _write_recording(tmp_path / "rec.csv", frame="world")
    with pytest.raises(ConfigError, match=r"recording\.frame.*frame 'world'"):
        World(load_scenario(_recorded_scenario(tmp_path)), scene)


def test_a_recorded_episode_judges_its_frames_against_the_recording(tmp_path):
    """A static episode of a recorded scenario: every camera frame's person is the recording's at that instant of
    the replay, as interpolated here from the file's numbers."""
    ts, fc, fyaw = _write_recording(tmp_path / "rec.csv")
    sc = dataclasses.replace(load_scenario(_recorded_scenario(tmp_path)), nodes=400, duration_s=8.0)
    var = draw_variation(sc, 1)
    ep = run_episode(sc, mode="static", variation=var)
    frac, loop = var["<recording>"].phase_rad / (2 * math.pi), 4.1
    k = int(round(1.0 / (sc.camera_fps * sc.control_dt)))
    times = np.asarray(ep["times"])[::k]
    assert len(times) >= 5 and len(ep["frames_scene"]) == len(times)
    checked = 0
    for t, poses in zip(times, ep["frames_scene"]):
        tau = (float(t) + frac * loop) % loop
        if tau > ts[-1]:
            continue
        c, q = poses["targets"]["person_face"]
        assert np.allclose(c, [np.interp(tau, ts, fc[:, j]) for j in range(3)], atol=1e-8)
        assert abs(_heading(q) - np.interp(tau, ts, fyaw)) < 1e-6
        checked += 1
    assert checked >= 4


def test_a_history_reaches_the_replanner_before_the_first_plan(tmp_path, monkeypatch):
    """``history_s``: the replanner is given the recorded person's poses, one per control step from -history_s on,
    before it makes the first plan (recorded here by wrapping the real replanner's calls; the poses judged against the
    test's own CSV)."""
    from psprm_core.errors import PsprmError
    from psprm_core.planning.replanner import Replanner

    ts, fc, fyaw = _write_recording(tmp_path / "rec.csv")
    sc = dataclasses.replace(load_scenario(_recorded_scenario(tmp_path)), nodes=400, duration_s=2.0)
    calls = []
    update, replan = Replanner.update_target, Replanner.replan

    def spy_update(self, name, c, q, stamp=None):
        calls.append(("pose", name, stamp, np.array(c), np.array(q)))
        return update(self, name, c, q, stamp=stamp)

    def spy_replan(self, *a, **k):
        calls.append(("replan",))
        return replan(self, *a, **k)

    monkeypatch.setattr(Replanner, "update_target", spy_update)
    monkeypatch.setattr(Replanner, "replan", spy_replan)
    run_episode(sc, mode="static", history_s=1.5)
    first = next(i for i, c in enumerate(calls) if c[0] == "replan")
    before = [c for c in calls[:first] if c[1] == "person_face"]
    assert [round(c[2], 6) for c in before] == [round(-1.5 + 0.1 * k, 6) for k in range(16)]
    loop = 4.1
    for _, _, t, c, q in before:
        tau = t % loop
        if tau <= ts[-1]:
            assert np.allclose(c, [np.interp(tau, ts, fc[:, j]) for j in range(3)], atol=1e-8)
            assert abs(_heading(q) - np.interp(tau, ts, fyaw)) < 1e-6
    calls.clear()
    run_episode(sc, mode="static")  # no history: the first pose is the one at t = 0
    first = next(i for i, c in enumerate(calls) if c[0] == "replan")
    assert [c[2] for c in calls[:first] if c[1] == "person_face"] == [0.0]
    with pytest.raises(PsprmError, match="history"):
        run_episode(sc, mode="static", history_s=float("nan"))


def test_a_recording_in_another_frame_is_replayed_in_the_scene_frame(tmp_path):
    """Samples recorded in ``world``, a frame whose pose in the scene's ``map`` the scenario gives (turned 0.5 rad about
    z and 0.2 rad about x, moved by (1, -2, 0.1)): the test writes the world coordinates of its own map-frame poses
    (the face also pitched 0.3 rad), computed with scipy's rotations, and the replay gives the map-frame poses back."""
    from scipy.spatial.transform import Rotation

    ts, fc, fyaw = _write_recording(tmp_path / "map.csv")
    t_w = np.array([1.0, -2.0, 0.1])
    R_w = Rotation.from_euler("ZX", [0.5, 0.2])  # the pose of world in map
    lines = (tmp_path / "map.csv").read_text().splitlines()
    out, want = [lines[0]], {}
    for line in lines[1:]:
        t, body, _, *v = line.split(",")
        x, y, z, w = (float(a) for a in v[3:])
        yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        R_map = Rotation.from_euler("ZY", [yaw, 0.3])
        p = R_w.inv().apply(np.array(v[:3], float) - t_w)
        out.append(f"{t},{body},world," + ",".join(f"{a:.12f}" for a in (*p, *(R_w.inv() * R_map).as_quat())))
        want[(round(float(t) - 100.0, 6), body)] = (np.array(v[:3], float), R_map)
    (tmp_path / "rec.csv").write_text("\n".join(out) + "\n")
    qx, qy, qz, qw = R_w.as_quat()
    frame = f"  frame: {{name: world, xyz: [1.0, -2.0, 0.1], quat: [{qx:.12f}, {qy:.12f}, {qz:.12f}, {qw:.12f}]}}\n"
    f = _recorded_scenario(tmp_path)
    f.write_text(f.read_text().replace("recording: {file: rec.csv, bodies: [person_face, person_body]}\n",
                                       "recording:\n  file: rec.csv\n  bodies: [person_face, person_body]\n" + frame))
    world = World(load_scenario(f), load_scene(resolve_named("scene", "dynamic_person")))
    for k in (0, 7, 23, 40):
        c, q = world.poses(float(ts[k]))["targets"]["person_face"]
        wc, wr = want[(round(float(ts[k]), 6), "person_face")]
        assert np.allclose(c, wc, atol=1e-7)
        assert (Rotation.from_quat(q) * wr.inv()).magnitude() < 1e-6
    f.write_text(f.read_text().replace("name: world", "name: mocap"))
    with pytest.raises(ConfigError, match=r"recording\.frame.*frame 'world'"):
        World(load_scenario(f), load_scene(resolve_named("scene", "dynamic_person")))
