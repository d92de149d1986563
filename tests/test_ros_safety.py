"""The node suite's safety gate, judged from the test's own record: pybullet (mesh collision, the project's reference
model) holds the obstacle poses this test published; every trajectory the server publishes is checked against the
latest pose the test had sent 50 ms before the trajectory arrived. A planner result forced to collide (a fault
injected into the core replanner's output) must be refused by the server, never published; randomized episodes move
the person into and out of the path, with forced faults among them."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

pytest.importorskip("rclpy")
pytest.importorskip("pybullet")

from psprm_core.evaluation.reference import PybulletWorld  # noqa: E402
from psprm_core.paths import resolve_named  # noqa: E402
from psprm_core.scene import load_scene  # noqa: E402
from psprm_ros.interfaces import conversions as cv  # noqa: E402
from psprm_ros.harness.probe import InProcessSuite, claim_domain_id  # noqa: E402

PARAMS = {"scene": "dynamic_person", "dynamic_obstacles": ["person_body"], "roadmap.n_nodes": 500, "seed": 0,
          "stale_timeout_s": 60.0, "publish_markers": False, "input_frames": ["odom"], "deviation_tolerance": 1000.0,
          "relay_deadband_m": 0.0, "relay_deadband_rad": 0.0}
MARGIN_S = 0.05  # a pose counts as known to the server 50 ms after the test published it


class Judge:
    """pybullet world of the scene with the poses the test sent (its own log, with send times)."""

    def __init__(self, robot, scene):
        self.robot, self.scene = robot, scene
        self.world = PybulletWorld(robot, scene.collision_boxes())
        self.ids = {name: bid for bid, name in self.world.box_bodies.items()}
        b = scene.obstacle("person_body")
        self.log = [(-1e9, b.center.copy(), b.quat.copy())]  # (perf_counter send time, position, quaternion)

    def sent(self, t, p, q):
        self.log.append((t, np.asarray(p, float), np.asarray(q, float)))

    def pose_known_at(self, t):
        known = [e for e in self.log if e[0] <= t - MARGIN_S]
        return known[-1]

    def collides(self, P, pose) -> np.ndarray:
        _, p, q = pose
        self.world.p.resetBasePositionAndOrientation(self.ids["person_body"], list(p), list(q),
                                                     physicsClientId=self.world.cid)
        return self.world.in_collision(P)

    def close(self):
        self.world.close()


def densified(msg, names):
    P = cv.joint_trajectory_positions(msg, names)
    return cv.densify_linear(P, 0.05) if len(P) > 1 else P


def _through_the_person(res, person_xy):
    """Fault: the result's trajectory driven straight through the person (base x, y replaced)."""
    tr = res.trajectory
    if tr is None:
        return res
    P = np.array(tr.positions, float)
    f = np.linspace(0.0, 1.0, len(P))[:, None]
    a = P[0, :2]
    P[:, :2] = a + f * 2.0 * (np.asarray(person_xy) - a)  # to the person and as far beyond
    tr.positions = P
    return res


@pytest.fixture(scope="module")
def world(load_robot):
    return load_scene(resolve_named("scene", "dynamic_person")), load_robot("stretch2")


@pytest.fixture(scope="module")
def suite(world):
    scene, robot = world
    from psprm_core.planning.factory import problem_configurations

    with InProcessSuite(PARAMS, domain_id=claim_domain_id(), nodes=("server", "monitor")) as s:
        assert s.server.ready.wait(180)
        assert s.probe.wait_subscribers("/mocap/person_body/pose")
        q = problem_configurations(robot, scene, scene.problem("south_to_either"))[0]
        s.state = s.probe.hold_robot_state(q, robot.joint_names)
        s.judge = Judge(robot, scene)
        face = scene.target("person_face")
        n0 = len(s.probe.trajectories)
        s.probe.publish_pose("person_face", face.center, face.quat)
        s.judge.sent(s.probe.publish_pose("person_body", *s.judge.log[0][1:]), *s.judge.log[0][1:])
        s.probe.publish_regions(["at_shelf", "at_cabinet"])
        assert s.probe.wait_trajectory(n0, 30) is not None
        yield s
        s.state.stop()
        s.judge.close()


class Fault:
    """Wraps the server's replanner: while armed, each result's trajectory is driven through the person."""

    def __init__(self, server, scene):
        self.server, self.armed, self.hits = server, False, 0
        self._orig = server.rp.replan
        self.person_xy = scene.obstacle("person_body").center[:2]
        server.rp.replan = self.replan

    def replan(self, *a, **k):
        res = self._orig(*a, **k)
        if self.armed and res.success:
            self.hits += 1
            return _through_the_person(res, self.person_xy)
        return res

    def remove(self):
        self.server.rp.replan = self._orig


def check_all(s, robot, since: float) -> int:
    """Judge every trajectory received after ``since``; returns how many were judged."""
    with s.probe.cond:
        got = [(t, m) for t, m in s.probe.trajectories if t > since]
    for t, m in got:
        pose = s.judge.pose_known_at(t)
        bad = s.judge.collides(densified(m, robot.joint_names), pose)
        assert not bad.any(), (f"a published trajectory ({len(m.points)} points) collides with the person at "
                               f"{pose[1][:2]} at {int(bad.sum())} configurations")
    return len(got)


def test_a_planner_result_forced_to_collide_is_refused(suite, world):
    scene, robot = world
    fault = Fault(suite.server, scene)
    try:
        fault.armed = True
        t0 = time.perf_counter()
        n0 = len(suite.probe.infos)
        suite.probe.publish_regions(["at_cabinet"])  # a new goal: a replan, whose output the fault corrupts
        info = suite.probe.wait_for(lambda: [i for _, i in suite.probe.infos[n0:] if "refused" in str(i.get("reason"))],
                                    20)
        assert info, f"no refusal; infos: {[i for _, i in suite.probe.infos[n0:]]}"
        assert fault.hits >= 1
        assert "planner output in collision" in info[0]["reason"]
        assert suite.probe.wait_status("planning failed", t0, timeout=5, level="warning")
        time.sleep(0.5)
        check_all(suite, robot, t0)
    finally:
        fault.remove()


def test_randomized_episodes_never_publish_a_colliding_trajectory(suite, world):
    scene, robot = world
    rng = np.random.default_rng(7)
    box = scene.obstacle("person_body")
    fault = Fault(suite.server, scene)
    t_start = time.perf_counter()
    refused = judged_steps = 0
    try:
        for step in range(10):
            with suite.probe.cond:
                last = [m for _, m in suite.probe.trajectories if len(m.points) > 1]
            P = cv.joint_trajectory_positions(last[-1], robot.joint_names) if last else None
            kind = rng.choice(["into", "out", "home"], p=[0.5, 0.3, 0.2])
            if kind == "into" and P is not None and len(P) > 10:
                k = int(rng.integers(len(P) // 4, 3 * len(P) // 4))
                xy = P[k, :2] + rng.normal(0, 0.05, 2)
            elif kind == "out":
                xy = np.array([rng.uniform(1.5, 6.5), rng.uniform(4.4, 4.8)])  # in front of the sofa, off the way
            else:
                xy = box.center[:2]
            yaw = rng.uniform(-np.pi, np.pi)
            pos, quat = np.r_[xy, box.center[2]], cv.yaw_quat(yaw)
            fault.armed = bool(rng.random() < 0.35)
            n_info = len(suite.probe.infos)
            t = suite.probe.publish_pose("person_body", pos, quat)
            suite.judge.sent(t, pos, quat)
            # the plan (or refusal / stop) answering this pose
            suite.probe.wait_for(lambda: len(suite.probe.infos) > n_info, 8)
            time.sleep(0.6)
            refused += sum("refused" in str(i.get("reason")) for _, i in suite.probe.infos[n_info:])
            judged_steps += 1
            # keep the stream alive between steps (the last pose, as a mocap system repeats it)
            suite.judge.sent(suite.probe.publish_pose("person_body", pos, quat), pos, quat)
        fault.armed = False
        time.sleep(0.5)
        n = check_all(suite, robot, t_start)
        assert n >= 5, f"only {n} trajectories published in 10 steps"
        assert fault.hits == 0 or refused >= 1
    finally:
        fault.remove()
        suite.judge.sent(suite.probe.publish_pose("person_body", box.center, box.quat), box.center, box.quat)
