"""The ROS 2 suite as users run it: the colcon workspace builds and installs runnable executables under
lib/psprm_ros/, and the nodes started by the shell scripts (separately and all-in-one) answer poses published from
another process with trajectories, then stop cleanly on SIGTERM."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

pytest.importorskip("rclpy")

from psprm_ros.harness.probe import Probe, claim_domain_id  # noqa: E402

PARAMS_FILE = ROOT / "config" / "ros" / "dynamic_person.yaml"
N_NODES = 500  # same small roadmap as tests/test_ros_nodes.py (cached after the first build)


def test_colcon_workspace_builds_and_installs_runnable_executables(tmp_path):
    env = dict(os.environ, PATH=f"{ROOT / '.venv' / 'bin'}:{os.environ.get('PATH', '')}")
    r = subprocess.run(["bash", str(ROOT / "scripts" / "build_ros2_ws.sh"), str(tmp_path / "ws")], env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    install = tmp_path / "ws" / "install"
    lib = install / "psprm_ros" / "lib" / "psprm_ros"
    exes = {"roadmap_server", "perception_scorer", "replan_monitor", "robot_adapter", "sim_robot", "all_in_one",
            "mocap_replay", "latency_bench", "soak", "demo"}
    assert exes <= {p.name for p in lib.iterdir()}
    assert (install / "psprm_ros" / "share" / "ament_index" / "resource_index" / "packages" / "psprm_ros").is_file()
    share = install / "psprm_ros" / "share" / "psprm_ros"
    for robot, f in (("stretch2", "dynamic_person.yaml"), ("fetchlike", "fetchlike_nursing.yaml"),
                     ("ur5_mobile", "ur5_mobile_blind_spot_alley.yaml")):
        assert (share / "config" / f).is_file() and (share / "config" / "adapters" / f"{robot}.yaml").is_file()
    assert (share / "config" / "psprm.rviz").is_file() and (share / "scenes" / "dynamic_person.yaml").is_file()
    site = next((install / "psprm_ros" / "lib").glob("python3*/site-packages"))
    # what `source install/setup.bash; ros2 run psprm_ros all_in_one --self-check` does: PYTHONPATH from the hook
    run_env = dict(os.environ, PYTHONPATH=str(site))
    r = subprocess.run([str(lib / "all_in_one"), "--self-check"], env=run_env, capture_output=True, text=True,
                       timeout=120, cwd=str(tmp_path))
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["ok"] and out["psprm_ros"].startswith(str(site))  # the installed copy, not the source tree
    # the installed adapter configs are the ones found by name (share/ before the repository)
    r = subprocess.run([sys.executable, "-c", "import json; from psprm_ros.robots.adapters import resolve_adapter; "
                        "print(json.dumps(str(resolve_adapter('stretch2'))))"],
                       env=dict(run_env, AMENT_PREFIX_PATH=str(install / "psprm_ros")), capture_output=True,
                       text=True, timeout=60, cwd=str(tmp_path))
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stdout.strip().splitlines()[-1]).startswith(str(share))
    r = subprocess.run([str(lib / "roadmap_server"), "--help"], env=run_env, capture_output=True, text=True,
                       timeout=60, cwd=str(tmp_path))
    assert r.returncode == 0 and "--ros-args" in r.stdout


def _start(script: str, domain: int):
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), RMW_IMPLEMENTATION="rmw_fastrtps_cpp", PYTHONUNBUFFERED="1")
    # node-specific overrides: a plain "-p name:=value" does not beat the params file's per-node sections
    cmd = ["bash", str(ROOT / "scripts" / script), str(PARAMS_FILE), "-p", f"roadmap_server:roadmap.n_nodes:={N_NODES}",
           "-p", "replan_monitor:stale_timeout_s:=60.0", "-p", "roadmap_server:publish_markers:=false",
           "-p", "robot_adapter:interface:=topic"]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    # the suite's log is read as it comes: a pipe nobody reads fills (64 KiB) and blocks the nodes in their logging
    proc.lines = []
    proc.reader = threading.Thread(target=lambda: proc.lines.extend(proc.stdout), daemon=True)
    proc.reader.start()
    return proc


def _stop(proc) -> tuple:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    proc.reader.join(timeout=5.0)
    return proc.returncode, "".join(proc.lines)


@pytest.mark.parametrize("script", ["run_all_in_one.sh", "run_nodes.sh"])
def test_script_started_nodes_answer_poses_from_another_process(script, load_robot):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from psprm_core.paths import resolve_named
    from psprm_core.scene import load_scene
    from psprm_ros.interfaces import conversions as cv

    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = load_robot("stretch2")
    domain = claim_domain_id()
    proc = _start(script, domain)
    ctx = rclpy.Context()
    ctx.init(domain_id=domain)
    ex = SingleThreadedExecutor(context=ctx)
    probe = Probe(context=ctx)
    ex.add_node(probe.node)
    from trajectory_msgs.msg import JointTrajectory

    from geometry_msgs.msg import Twist

    cmds, twists = [], []
    probe.node.create_subscription(JointTrajectory, "/stretch_controller/joint_trajectory", cmds.append, 10)
    probe.node.create_subscription(Twist, "/stretch/cmd_vel", lambda m: twists.append((time.perf_counter(), m)), 50)
    stop = threading.Event()
    th = threading.Thread(target=_spin, args=(ex, stop), daemon=True)
    th.start()
    try:
        # ready = the monitor subscribes to the mocap topic and the server publishes "ready"
        ready = probe.wait_ready(timeout=240)
        assert ready, f"suite not ready; output:\n{_tail(proc)}"
        assert f"{N_NODES} nodes" in ready  # the command-line override reached the server
        assert probe.wait_subscribers("/mocap/person_face/pose", timeout=30)
        face = scene.target("person_face")
        probe.wait_subscribers("/psprm/goal_regions", timeout=10)
        from psprm_core.planning.factory import problem_configurations

        state = probe.hold_robot_state(problem_configurations(robot, scene, scene.problem("south_to_either"))[0],
                                       robot.joint_names)  # the robot's /joint_states and /odom
        deadline = time.monotonic() + 90
        n0 = len(probe.trajectories)
        while time.monotonic() < deadline and len(probe.trajectories) <= n0:
            probe.publish_pose("person_face", face.center, face.quat)
            if not probe.wait_status("forwarded goal regions", timeout=0.01):
                probe.publish_regions(["at_shelf", "at_cabinet"])
            time.sleep(0.5)
        msg = probe.wait_trajectory(n0, 1)
        assert msg is not None, f"no trajectory; statuses {[s[2] for s in probe.statuses[-6:]]}"
        assert list(msg.joint_names) == robot.joint_names and len(msg.points) > 10
        # a second pose (the person turned) gives a replanned trajectory across processes
        n1 = len(probe.trajectories)
        yaw = 0.3
        body = scene.obstacle("person_body")
        p = np.r_[body.center[:2] + 0.06 * np.array([np.cos(yaw), np.sin(yaw)]), face.center[2]]
        probe.publish_pose("person_face", p, cv.yaw_quat(yaw))
        assert probe.wait_trajectory(n1, 60) is not None
        # the adapter process turned the plan into the robot's controller command (its JointTrajectory topic; it
        # takes the trajectory when this process does, and may hold a goal back for the controller's goal interval)
        deadline = time.monotonic() + 10
        while not cmds and time.monotonic() < deadline:
            time.sleep(0.1)
        assert cmds, "robot_adapter sent nothing to the stretch_controller topic"
        assert set(cmds[-1].joint_names) == {"joint_lift", "wrist_extension", "joint_wrist_yaw", "joint_head_pan",
                                             "joint_head_tilt"}
        # stop on shutdown: after SIGTERM the adapter sends a zero twist and a hold before the process ends
        n_cmds, t_term = len(cmds), time.perf_counter()
        os.killpg(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.1)
        wait = time.monotonic() + 5.0  # what the adapter sent on its way out may still be in transit

        def zero_twist():
            return [m for t, m in twists if t >= t_term and m.linear.x == 0.0 and m.angular.z == 0.0]

        def hold():
            return [m for m in cmds[n_cmds:] if len(m.points) == 1]

        while time.monotonic() < wait and not (zero_twist() and hold()):
            time.sleep(0.1)
        assert zero_twist(), f"no zero twist at shutdown; output:\n{_tail(proc)}"
        assert hold(), "no hold trajectory at shutdown"
        state.stop()
    finally:
        stop.set()  # the spin thread leaves before the executor, node and context go (no shutdown race)
        th.join(timeout=5.0)
        ex.shutdown(timeout_sec=1.0)
        probe.destroy()
        ctx.try_shutdown()
        code, out = _stop(proc)
    assert code in (0, -signal.SIGTERM, 128 + signal.SIGTERM), out[-3000:]
    assert "Traceback" not in out, out[-3000:]


def test_package_declares_every_ros_package_its_nodes_import():
    """Every ROS interface package imported by psprm_ros (``from X.msg|srv|action import``, rclpy, ament_index_python)
    is an exec_depend of ros2_ws/src/psprm_ros/package.xml."""
    import re
    import xml.etree.ElementTree as ET

    deps = {e.text for e in ET.parse(ROOT / "ros2_ws" / "src" / "psprm_ros" / "package.xml").getroot()
            if e.tag == "exec_depend"}
    used = set()
    for f in (ROOT / "psprm_ros").rglob("*.py"):
        text = f.read_text()
        used |= set(re.findall(r"^\s*from (\w+)\.(?:msg|srv|action) import", text, re.M))
        used |= {m for m in ("rclpy", "ament_index_python") if re.search(rf"^\s*(from|import) {m}\b", text, re.M)}
    assert used, "no imports found"
    assert used <= deps, f"imported but not declared: {sorted(used - deps)}"


def _spin(ex, stop) -> None:
    while not stop.is_set():
        try:
            ex.spin_once(timeout_sec=0.1)
        except Exception:  # a callback error must not end the probe's spinning; shutdown ends the loop
            if stop.is_set():
                break
            time.sleep(0.01)


def _tail(proc) -> str:
    return "".join(proc.lines)[-3000:]


def test_soak_tells_who_closed_the_gap_at_a_collision():
    """The soak's closing speeds, from positions made here: a robot driving at 0.3 m/s into a standing person, and a
    person walking at 0.5 m/s into a standing robot."""
    from psprm_ros.harness.soak_report import _closing_speeds

    ts = np.arange(0.0, 1.0, 0.02)
    robot = [(t, np.array([0.3 * t, 0.0, 0.0])) for t in ts]  # drives +x
    person = [(t, np.array([2.0, 0.0, 1.0])) for t in ts]
    r, p = _closing_speeds(ts[-1], robot[-1][1], robot, ts, person, ts)
    assert abs(r - 0.3) < 0.02 and abs(p) < 1e-9
    robot = [(t, np.array([0.0, 0.0, 0.0])) for t in ts]
    person = [(t, np.array([2.0 - 0.5 * t, 0.0, 1.0])) for t in ts]  # walks -x, towards the robot
    r, p = _closing_speeds(ts[-1], robot[-1][1], robot, ts, person, ts)
    assert abs(r) < 1e-9 and abs(p - 0.5) < 0.03


def test_soak_reports_how_far_off_its_trajectory_a_colliding_robot_was(load_robot):
    """For a collision the soak names the trajectory the robot was following and how far off it the robot was.
    Made here: a straight base path past a box, a trajectory received 1 s before; a robot 0.12 m and 0.2 rad off
    its nearest point, then the same path moved onto the box."""
    from psprm_core.collision import CollisionChecker
    from psprm_core.scene import Box
    from psprm_ros.interfaces import conversions as cv
    from psprm_ros.harness.soak_report import _followed

    robot = load_robot("stretch2")
    names = list(robot.joint_names)
    q0 = np.array([0.0, 0.0, 0.0, 0.5, 0.0, 3.0, -1.12, 0.17])  # lift up, arm and wrist stowed, head turned
    P = np.repeat(q0[None], 11, 0)
    P[:, 0] = np.linspace(0.0, 2.0, 11)  # drives +x along y = 0
    box = Box(name="crate", center=np.array([1.0, 1.5, 0.4]), size=np.array([0.4, 0.4, 0.8]),
              quat=np.array([0.0, 0.0, 0.0, 1.0]))
    checker = CollisionChecker(robot, [box])

    def msg_of(path):
        from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

        m = JointTrajectory()
        m.joint_names = names[::-1]  # any order: matched by name
        for k, p in enumerate(path):
            pt = JointTrajectoryPoint()
            pt.positions = [float(v) for v in p[::-1]]
            pt.time_from_start = cv.duration_msg(0.5 * k)
            m.points.append(pt)
        return m

    q = P[5].copy()
    q[1] += 0.12
    q[2] += 0.2
    f = _followed(10.0, q, [(8.0, msg_of(P[::-1])), (9.0, msg_of(P))], names, checker)
    assert f["received_s_before"] == 1.0 and f["points"] == 11
    assert abs(f["base_off_m"] - 0.12) < 1e-3 and abs(f["heading_off_rad"] - 0.2) < 1e-3 and f["joints_off_max"] == 0
    assert not f["nearest_point_collides"] and f["points_in_collision"] == 0
    onto = P.copy()
    onto[:, 1] = 1.5  # through the crate
    f = _followed(10.0, onto[5], [(9.5, msg_of(onto))], names, checker)
    assert f["nearest_point_collides"] and f["points_in_collision"] > 0
    assert _followed(10.0, q, [(11.0, msg_of(P))], names, checker) is None  # nothing received before


def test_soak_tracking_counts_the_trajectories_executed_and_how_far_off_the_robot_was(load_robot):
    """The soak's tracking report, on a record made here: a straight drive along x received at 9 s and executed (the
    controller then got 11 points), a second trajectory at 12 s that was refused (the controller got a hold). The
    robot drove the first path 3 cm to its side until 13 s, then 8 cm: judged against the executed trajectory only,
    the base is 3 and 8 cm off it (the shift is a translation, so the whole robot is as far off), the deviation
    exceeds the 5 cm padding for the later configurations alone, and a box next to the path is reached only by them."""
    from psprm_core.collision import CollisionChecker
    from psprm_core.scene import Box
    from psprm_ros.interfaces import conversions as cv
    from psprm_ros.harness.soak_report import executed_trajectories, tracking_report

    robot = load_robot("stretch2")
    names = list(robot.joint_names)
    q0 = np.array([0.0, 0.0, 0.0, 0.5, 0.0, 3.0, -1.12, 0.17])
    P = np.repeat(q0[None], 11, 0)
    P[:, 0] = np.linspace(0.0, 2.0, 11)  # 2 m along +x in 10 s

    def msg_of(path):
        from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

        m = JointTrajectory()
        m.joint_names = names
        for k, p in enumerate(path):
            pt = JointTrajectoryPoint(positions=[float(v) for v in p], time_from_start=cv.duration_msg(1.0 * k))
            m.points.append(pt)
        return m

    away = P.copy()
    away[:, 1] = 3.0  # the refused one: far from where the robot drives
    trajs = [(9.0, msg_of(P)), (12.0, msg_of(away))]
    ran = executed_trajectories(trajs, [(9.01, 11), (12.01, 1)])
    assert len(ran) == 1 and ran[0][0] == 9.0 and ran[0][2] == 12.01  # executed, then held by the refusal
    ran = [(9.0, ran[0][1], np.inf)]  # here the robot drives on (a hold that did not stop it)
    ex = []
    for k in range(100):
        t = 9.0 + 0.1 * k
        q = q0.copy()
        q[0] = 0.2 * (t - 9.0)
        q[1] = 0.03 if t < 13.0 else 0.08
        ex.append((t, q))
    # a box beside the path whose near face is 9 cm beyond the robot's side when the robot is on the path: 6 cm from
    # it when 3 cm off (outside the 5 cm padding), 1 cm when 8 cm off (inside it, not touching)
    import torch

    side = float(CollisionChecker(robot).robot_aabb(torch.as_tensor(q0[None], dtype=torch.float32))[0, 4])
    box = Box(name="crate", center=np.array([1.5, side + 0.09 + 0.2, 0.4]), size=np.array([0.4, 0.4, 0.8]),
              quat=np.array([0.0, 0.0, 0.0, 1.0]))
    r = tracking_report(ex, ran, robot, CollisionChecker(robot, padding=0.05), [box])
    assert r["configurations_following"] == 100
    assert abs(r["base_off_m"]["p50"] - 0.08) < 1e-3 and abs(r["base_off_m"]["max"] - 0.08) < 1e-3
    assert abs(r["deviation_m"]["max"] - 0.08) < 1e-3
    assert r["deviation_m"]["over_padding"] == 60 and r["deviation_m"]["trajectories_over_padding"] == 1
    assert r["inside_static_padding"] > 0
    assert r["inside_static_padding"] == r["inside_static_padding_by_tracking"]
    assert not CollisionChecker(robot, [box]).check(torch.as_tensor(np.array([q for _, q in ex]),
                                                                    dtype=torch.float32)).any()
    with_refused = tracking_report(ex, trajs, robot, CollisionChecker(robot, padding=0.05), [box])
    assert with_refused["deviation_m"]["over_padding"] > 60  # the refused trajectory would have counted too
    # stopped by a hold at 11 s where it stood 3 cm off: measured against the path where it stopped, not against the
    # reference moving on without it
    rest = [(t, ex[20][1] if t >= 11.0 else q) for t, q in ex]
    held = tracking_report(rest, [(9.0, ran[0][1], 11.0)], robot, CollisionChecker(robot, padding=0.05), [box])
    assert abs(held["deviation_m"]["max"] - 0.03) < 1e-3 and held["deviation_m"]["over_padding"] == 0


def test_soak_tracking_measures_a_joined_splice_against_the_trajectory_it_joins(load_robot):
    """A drive along x at 0.2 m/s received at 9 s; at 12 s a splice that begins where that drive is at 12.3 s (6 cm
    ahead of the robot) and goes on along it. The robot, on the first drive throughout, reaches the splice's start at
    12.3 s: its configurations before that are measured against the drive it is on (three of them, nearer to it), not
    6 cm off against the splice. A trajectory at 12 s that does not continue the drive gets no such allowance."""
    from psprm_core.collision import CollisionChecker
    from psprm_ros.interfaces import conversions as cv
    from psprm_ros.harness.soak_report import tracking_report

    robot = load_robot("stretch2")
    names = list(robot.joint_names)
    q0 = np.array([0.0, 0.0, 0.0, 0.5, 0.0, 3.0, -1.12, 0.17])

    def msg_of(ts, path):
        from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

        m = JointTrajectory()
        m.joint_names = names
        for t, p in zip(ts, path):
            m.points.append(JointTrajectoryPoint(positions=[float(v) for v in p], time_from_start=cv.duration_msg(t)))
        return m

    def drive(t_from, t_to):  # the drive's configurations from its time t_from to t_to, times from 0
        ts = np.arange(0.0, t_to - t_from + 1e-9, 0.1)
        P = np.repeat(q0[None], len(ts), 0)
        P[:, 0] = 0.2 * (ts + t_from)
        return ts, P

    a = msg_of(*drive(0.0, 10.0))
    ex = []
    for k in range(50):
        t = 9.0 + 0.1 * k
        q = q0.copy()
        q[0] = 0.2 * (t - 9.0)
        ex.append((t, q))
    checker = CollisionChecker(robot, padding=0.05)
    b = msg_of(*drive(3.3, 8.0))  # the drive from its 3.3 s on: where the robot is at 12.3 s
    r = tracking_report(ex, [(9.0, a, np.inf), (12.0, b, np.inf)], robot, checker, [])
    assert r["deviation_m"]["joined_configurations"] == 3
    assert r["deviation_m"]["max"] < 0.01 and r["deviation_m"]["over_padding"] == 0
    # against the splice alone the robot at 12.0 s is 6 cm off: the trajectory it was on is what makes the difference
    ts_b, P_side = drive(3.3, 8.0)
    P_side[:, 1] += 3.0  # 3 m to the side: no continuation of the drive
    other = tracking_report(ex, [(9.0, a, np.inf), (12.0, msg_of(ts_b, P_side), np.inf)], robot, checker, [])
    assert other["deviation_m"]["joined_configurations"] == 0 and other["deviation_m"]["over_padding"] > 0


def test_soak_walk_yields_to_the_robot_then_walks_on():
    """The soak's person walks at 0.5 m/s, never steps within 1 m of the robot's base (closer to it) for up to 20 s
    of waiting, then walks on; judged from the positions stepped here."""
    from psprm_ros.harness.soak import Stream

    st = Stream(None, None, None, np.random.default_rng(0), None, 40.0)
    st.home = np.array([0.0, 0.0])
    st.walk = {"phase": "back", "home": np.zeros(2), "to": np.array([4.0, 0.0]), "hold": 0.0, "waited": 0.0,
               "until": 0.0}
    st.offset = np.array([4.0, 0.0])
    st.robot_xy = np.array([2.0, 0.0])  # standing on the way home
    t, track = 0.0, []
    st.t_last = t
    while st.walk is not None and t < 60.0:
        t += 1 / 120
        st.offset = st._walk_offset(t)
        track.append((t, st.offset.copy()))
    T = np.array([x for x, _ in track])
    P = np.array([p for _, p in track])
    d = np.linalg.norm(P - st.robot_xy, axis=1)
    speed = np.linalg.norm(np.diff(P, axis=0), axis=1) * 120
    assert speed.max() <= 0.5 + 1e-6
    t_close = T[np.argmax(d < 1.0 - 1e-6)]  # it comes closer than 1 m only after waiting 20 s at 1 m
    wait = T[(d >= 1.0 - 1e-3) & (d <= 1.0 + 1e-3)]
    assert wait.max() - wait.min() >= 19.5 and t_close >= 20.0 + 2.0
    assert st.walk is None and np.allclose(P[-1], 0.0)  # then home


def test_soak_latency_phases_split_each_pose_triggered_plan_into_its_wait_and_the_servers_phases():
    """The soak's latency attribution, from plan infos the test wrote: only published plans a pose triggered count
    (not a goal's, a kept plan, a stop, a failure); each sample's wait is its total less the server's phases; the
    slowest tenth is reported apart."""
    from psprm_ros.harness.soak_report import latency_phases, latency_samples

    def info(total_ms, wait_ms, replan_ms, **kw):
        phases = {"input_age_ms": 5.0, "apply_ms": 1.0, "triggers_ms": 2.0, "replan_ms": replan_ms, "msg_ms": 3.0,
                  "check_ms": 4.0}
        assert abs(total_ms - wait_ms - sum(phases.values())) < 1e-9
        return {"input_stamp": 100.0, "published_stamp": 100.0 + total_ms / 1e3, "success": True,
                "reasons": ["view"], **phases, **kw}

    rows = [info(115.0, 0.0, 100.0) for _ in range(18)] + [info(1015.0, 900.0, 100.0), info(2015.0, 1800.0, 200.0)]
    rows += [info(5015.0, 0.0, 5000.0, reasons=["goal_received"]), info(9015.0, 0.0, 9000.0, kept=True),
             info(9015.0, 0.0, 9000.0, stop=True), info(9015.0, 0.0, 9000.0, success=False),
             {**info(115.0, 0.0, 100.0), "published_stamp": None}]
    samples = latency_samples(rows)
    assert len(samples) == 20
    assert sorted(round(x["wait"], 6) for x in samples)[-2:] == [900.0, 1800.0]
    ph = latency_phases(samples)
    assert ph["all"]["samples"] == 20 and ph["all"]["total"] == 115.0 and ph["all"]["wait"] == 0.0
    assert ph["slowest_tenth"]["samples"] == 2
    assert ph["slowest_tenth"]["total"] == 1515.0 and ph["slowest_tenth"]["wait"] == 1350.0
    assert ph["slowest_tenth"]["replan_ms"] == 150.0
    assert latency_phases([]) == {}
