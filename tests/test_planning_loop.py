"""The roadmap server's planning loop driven directly (no ROS): inputs as values, outputs recorded by the test.

Every judgement comes from the test's own record: the robot states and poses it sent, the samples it received (the
exact arrays a node turns into the JointTrajectory message), and pybullet (the project's reference collision model)
holding the scene loaded afresh from its file with the poses the test sent. The loop's own state is never read to
judge; its replanner is only wrapped to make a replan slow (fault injection).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent
for _p in (ROOT, TESTS):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

pytest.importorskip("pybullet")

from judges import SentPoses, same_config  # noqa: E402
from psprm_core.evaluation.reference import PybulletWorld  # noqa: E402
from psprm_core.paths import resolve_named  # noqa: E402
from psprm_core.planning.factory import problem_configurations  # noqa: E402
from psprm_core.scene import load_scene  # noqa: E402
from psprm_ros.interfaces import conversions as cv  # noqa: E402
from psprm_ros import planner_setup  # noqa: E402
from psprm_ros.server import Outputs, PlanningLoop, TrajectorySamples  # noqa: E402

SCENE = "dynamic_person"
STEP = 0.05  # spacing (m / rad) of the configurations the test checks along a trajectory's polyline
#: quiet, deterministic loops: replans only on a goal, a request or a trajectory the scene invalidated
PARAMS = {"publish_markers": False, "auto_replan": False, "robot_state_timeout_s": 600.0}


class Record(Outputs):
    """Every output the loop produced, as copies, with the test's perf_counter time of receipt."""

    def __init__(self):
        self.events: list = []  # (time, kind, payload)
        self.cond = threading.Condition()

    def _add(self, kind: str, payload) -> None:
        with self.cond:
            self.events.append((time.perf_counter(), kind, payload))
            self.cond.notify_all()

    def trajectory(self, samples) -> None:
        self._add("trajectory", TrajectorySamples(*(np.array(a, float) for a in samples)))

    def stop(self, q, hold_s) -> None:
        self._add("stop", (np.array(q, float), float(hold_s)))

    def info(self, info) -> None:
        self._add("info", dict(info))

    def status(self, text, level="info") -> None:
        self._add("status", (level, text))

    def since(self, t: float, kinds=("trajectory", "stop", "info")) -> list:
        with self.cond:
            return [e for e in self.events if e[0] >= t and e[1] in kinds]

    def wait(self, t: float, kinds, timeout: float):
        """The first event of ``kinds`` received at or after ``t`` (waits at most ``timeout`` s), else None."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                got = [e for e in self.events if e[0] >= t and e[1] in kinds]
                if got:
                    return got[0]
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self.cond.wait(left)


class World:
    """pybullet with the scene loaded afresh and the poses the test sent."""

    def __init__(self, robot):
        self.sent = SentPoses(SCENE)
        self.world = PybulletWorld(robot, self.sent.boxes())
        self.bodies = {name: body for body, name in self.world.box_bodies.items()}

    def send(self, loop: PlanningLoop, name: str, p, q) -> float:
        """Record the pose, hand it to the loop; returns the time just before the hand-over."""
        self.sent.sent(name, p, q)
        t = time.perf_counter()
        loop.obstacle_pose(name, np.asarray(p, float), np.asarray(q, float) / np.linalg.norm(q), stamp=time.time())
        return t

    def colliding(self, positions: np.ndarray) -> np.ndarray:
        """Collision flags of the configurations along the polyline through ``positions`` (every ``STEP``)."""
        for b in self.sent.boxes():
            self.world.p.resetBasePositionAndOrientation(self.bodies[b.name], list(b.center), list(b.quat),
                                                         physicsClientId=self.world.cid)
        return self.world.in_collision(cv.densify_linear(np.asarray(positions, float), STEP))

    def close(self) -> None:
        self.world.close()


def at_time(s: TrajectorySamples, t: float) -> np.ndarray:
    """The configuration of received samples at time ``t``, interpolated linearly (as a controller does)."""
    t = float(np.clip(t, s.times[0], s.times[-1]))
    return np.array([np.interp(t, s.times, s.positions[:, j]) for j in range(s.positions.shape[1])])


def time_on(s: TrajectorySamples, q: np.ndarray) -> tuple:
    """(distance from ``q`` to the polyline of ``s``, the time of the nearest point on it)."""
    A, B = s.positions[:-1], s.positions[1:]
    AB = B - A
    f = np.clip(np.einsum("ij,ij->i", q - A, AB) / np.maximum(np.einsum("ij,ij->i", AB, AB), 1e-18), 0.0, 1.0)
    d = np.linalg.norm(A + f[:, None] * AB - q, axis=1)
    k = int(np.argmin(d))
    return float(d[k]), float(s.times[k] + f[k] * (s.times[k + 1] - s.times[k]))


@pytest.fixture(scope="module")
def world_models(load_robot):
    scene = load_scene(resolve_named("scene", SCENE))
    robot = load_robot("stretch2")
    start, goals = problem_configurations(robot, scene, scene.problem("south_to_either"))
    return robot, start, goals


@pytest.fixture(scope="module")
def roadmap_file(tmp_path_factory):
    return str(tmp_path_factory.mktemp("roadmap") / "dynamic_person_400.npz")


@pytest.fixture
def make_loop(world_models, roadmap_file):
    """Factory: a configured, active loop (the roadmap built once per module, then loaded) and its Record."""
    robot, start, _ = world_models
    made = []

    def make(**params):
        rec = Record()
        spec = planner_setup.PlannerSpec(settings={"roadmap.n_nodes": 400, "seed": 0}, roadmap_file=roadmap_file)
        loop = PlanningLoop(load_scene(resolve_named("scene", SCENE)), robot, ["person_face"], spec, rec,
                            obstacles=["person_body"], q0=start, params={**PARAMS, **params})
        made.append(loop)
        assert loop.transition("configure", timeout=300), [e for e in rec.events if e[1] == "status"]
        assert loop.transition("activate")
        return loop, rec

    yield make
    for loop in made:
        loop.close()


@pytest.fixture
def world(world_models):
    w = World(world_models[0])
    yield w
    w.close()


def _first_trajectory(loop, rec, q, goals, timeout=60.0, base_velocity=None) -> TrajectorySamples:
    t0 = time.perf_counter()
    loop.robot_state(q, base_velocity)
    loop.goals(goals)
    ev = rec.wait(t0, ("trajectory", "stop"), timeout)
    assert ev is not None and ev[1] == "trajectory", f"no trajectory: {rec.since(t0)}"
    return ev[2]


def test_goals_and_a_robot_state_give_one_trajectory_from_that_state_free_in_pybullet(make_loop, world,
                                                                                       world_models):
    robot, start, goals = world_models
    loop, rec = make_loop()
    q = start.copy()  # a state the roadmap was not templated on: moved base, head turned away
    q[0] += 0.1
    q[robot.index("joint_head_pan")] += 0.6
    assert not world.colliding(q[None]).any()  # precondition: a free state
    t0 = time.perf_counter()
    s = _first_trajectory(loop, rec, q, goals)
    time.sleep(1.0)
    assert len(rec.since(t0, ("trajectory", "stop"))) == 1  # one output for one goal
    assert same_config(s.positions[0], q, 1e-5), (s.positions[0], q)  # (float32 planner values)
    assert s.times[0] == 0.0 and np.all(np.diff(s.times) > 0)
    assert len(s.times) == len(s.positions) == len(s.velocities) == len(s.accelerations)
    assert not np.any(s.velocities[-1]) and not np.any(s.accelerations[-1])  # ends at rest
    assert min(np.hypot(*(s.positions[-1, :2] - g[:2])) for g in goals) < 0.05  # reaches one of the goals
    bad = world.colliding(s.positions)
    assert not bad.any(), f"{int(bad.sum())} configurations along the trajectory collide in pybullet"


def test_an_obstacle_moved_into_the_path_never_gets_a_colliding_trajectory(make_loop, world, world_models):
    robot, start, goals = world_models
    loop, rec = make_loop()
    s = _first_trajectory(loop, rec, start, goals)
    # the person stepping onto the path, several seconds ahead of the robot (beyond the stop guard's horizon)
    k = int(np.searchsorted(s.times, 0.55 * s.times[-1]))
    assert s.times[k] > 3.0, "precondition: a path longer than the guard's horizon"
    body = world.sent.scene.obstacle("person_body")
    p, q = np.r_[s.positions[k, :2], body.center[2]], body.quat
    world.sent.sent("person_body", p, q)
    assert world.colliding(s.positions).any(), "precondition: the pose blocks the published path"
    t0 = world.send(loop, "person_body", p, q)
    ev = rec.wait(t0, ("trajectory", "stop"), 60.0)
    assert ev is not None, f"neither a trajectory nor a stop: {rec.since(t0)}"
    time.sleep(1.0)
    for _, kind, out in rec.since(t0, ("trajectory",)):
        bad = world.colliding(out.positions)
        assert not bad.any(), f"a trajectory through the person: {int(bad.sum())} configurations collide"
    if ev[1] == "stop":
        assert same_config(ev[2][0], start, 1e-9)  # held where the robot is


def test_a_late_splice_is_withdrawn_and_the_next_replan_starts_on_the_published_trajectory(make_loop,
                                                                                           world_models):
    robot, start, goals = world_models
    loop, rec = make_loop(robot_state_timeout_s=1.0)
    s1 = _first_trajectory(loop, rec, start, goals)
    t_rx = rec.since(0.0, ("trajectory",))[0][0]
    lead = 0.15  # the robot starts the trajectory this long after receiving it
    running = threading.Event()
    running.set()
    sent: list = []  # (perf_counter, time along s1, q): the robot's states as the test sent them

    def follow():  # the robot drives the received samples, reporting its state at 20 Hz
        while running.is_set():
            now = time.perf_counter()
            tau = max(0.0, now - t_rx - lead)
            q = at_time(s1, tau)
            sent.append((now, tau, q))
            loop.robot_state(q)
            time.sleep(0.05)

    th = threading.Thread(target=follow, daemon=True)
    th.start()
    try:
        assert s1.times[-1] > 8.0, "precondition: a trajectory long enough to replan along"
        while not sent or sent[-1][1] < 1.0:  # well under way
            time.sleep(0.05)
        orig = loop.rp.replan
        slept: list = []

        def slow(*a, **k):  # a replan that takes longer than its commitment: ready after the splice instant
            res = orig(*a, **k)
            if res.success and res.committed_s > 0:
                slept.append(res.committed_s + 0.3)
                time.sleep(res.committed_s + 0.3)
            return res

        loop.rp.replan = slow
        t0 = time.perf_counter()
        ok, message = loop.request("plan", 60.0)
        loop.rp.replan = orig
        assert slept, "precondition: the replan was spliced (the robot followed the trajectory)"
        late = [out for _, kind, out in rec.since(t0, ("info",)) if out.get("failure") == "late_splice"]
        assert not ok and late, f"no late splice: {message}"
        assert not rec.since(t0, ("trajectory", "stop")), "a late splice reached the robot"

        t1 = time.perf_counter()
        tau_robot = [e[1] for e in sent if e[0] <= t1][-1]
        ok, message = loop.request("plan", 60.0)
        ev = rec.wait(t1, ("trajectory", "stop"), 5.0)
        assert ok and ev is not None and ev[1] == "trajectory", message
        s2 = ev[2]
        d, tau = time_on(s1, s2.positions[0])
        assert d < 1e-3, f"the replan starts {d:.4f} off the published trajectory"
        assert abs(tau - tau_robot) < 0.5, f"it starts at {tau:.2f} s along it, the robot was at {tau_robot:.2f} s"
        # and repeats it at least to the shortest commitment (commit_horizon_min_s) before it turns off
        on = [time_on(s1, q) for q in s2.positions[s2.times <= 0.25]]
        assert len(on) >= 2 and max(x[0] for x in on) < 1e-3, on
        assert np.all(np.diff([x[1] for x in on]) >= 0), on
    finally:
        running.clear()
        th.join(2.0)


def test_a_plan_right_after_an_adopted_splice_is_spliced_too_without_a_new_robot_state(make_loop, world_models):
    """A burst of goals: the robot drives its trajectory (its states at 20 Hz, then none for a moment), a replan is
    published, and another one is made before the next state arrives. It too continues the trajectory the robot
    follows (judged from the published samples: its first configurations lie on the previous trajectory), instead of
    starting a moving robot from its state."""
    robot, start, goals = world_models
    loop, rec = make_loop(robot_state_timeout_s=5.0)
    s1 = _first_trajectory(loop, rec, start, goals)
    t_rx = rec.since(0.0, ("trajectory",))[0][0]
    reporting, running = threading.Event(), threading.Event()
    reporting.set()
    running.set()

    def follow():  # the robot drives the received samples; reports its state at 20 Hz while ``reporting``
        while running.is_set():
            if reporting.is_set():
                loop.robot_state(at_time(s1, max(0.0, time.perf_counter() - t_rx - 0.15)))
            time.sleep(0.05)

    th = threading.Thread(target=follow, daemon=True)
    th.start()
    try:
        assert s1.times[-1] > 8.0, "precondition: a trajectory long enough to replan along"
        time.sleep(2.0)  # well under way
        reporting.clear()
        time.sleep(0.1)
        t0 = time.perf_counter()
        ok, message = loop.request("plan", 60.0)
        ev = rec.wait(t0, ("trajectory", "stop"), 5.0)
        assert ok and ev is not None and ev[1] == "trajectory", message
        s2 = ev[2]
        assert json.loads(message)["spliced"], "precondition: the first replan of the moving robot is spliced"
        t1 = time.perf_counter()
        ok, message = loop.request("plan", 60.0)  # no robot state since the first replan
        ev = rec.wait(t1, ("trajectory", "stop"), 5.0)
        assert ok and ev is not None and ev[1] == "trajectory", message
        s3 = ev[2]
        assert json.loads(message)["spliced"], f"planned from the robot's state: {message}"
        on = [time_on(s2, q)[0] for q in s3.positions[s3.times <= 0.25]]
        assert len(on) >= 2 and max(on) < 1e-3, on
    finally:
        running.clear()
        th.join(2.0)


def test_the_stop_guard_stops_at_once_for_a_pose_inside_the_next_second(make_loop, world, world_models):
    robot, start, goals = world_models
    loop, rec = make_loop()
    s = _first_trajectory(loop, rec, start, goals)
    time.sleep(0.5)
    body = world.sent.scene.obstacle("person_body")
    # a pose off the path first: no stop (the guard stops only for what blocks the path)
    assert not world.colliding(s.positions).any()
    t_off = world.send(loop, "person_body", body.center, body.quat)
    assert not rec.since(t_off, ("stop",))
    # then onto the path within its next second (the robot stands at the start: the first second from time 0)
    first = s.times <= 1.0
    k = int(np.argmax(np.where(first, np.hypot(*(s.positions[:, :2] - start[:2]).T), -1.0)))
    p = np.r_[s.positions[k, :2] + 0.25 * np.array([np.cos(s.positions[k, 2]), np.sin(s.positions[k, 2])]),
              body.center[2]]
    world.sent.sent("person_body", p, body.quat)
    assert world.colliding(s.positions[first]).any(), "precondition: the pose blocks the next second of the path"
    t0 = world.send(loop, "person_body", p, body.quat)
    got = rec.since(t0)  # what the loop had output when obstacle_pose returned
    assert got and got[0][1] == "stop", f"no stop at once: {got}"
    assert same_config(got[0][2][0], start, 1e-9)  # held where the robot is
    assert not [e for e in got if e[1] == "trajectory"]


def test_a_plan_for_a_braking_base_starts_where_it_comes_to_rest(make_loop, world_models):
    """Robot states of a base that drove straight at 0.3 m/s and brakes (no trajectory under way, as after a stop),
    then no more states (so no wait for the rest, ``settle_timeout_s`` 0): the plan starts where the test's own
    uniform-deceleration kinematics bring it to rest, within 1 cm."""
    robot, start, goals = world_models
    loop, rec = make_loop(settle_timeout_s=0.0)
    a = float(robot.config.base.linear_acceleration)
    v0, t_brake, t_end, dt = 0.3, 0.2, 0.38, 0.02
    heading = np.array([np.cos(start[2]), np.sin(start[2])])

    def travelled(t: float) -> float:
        if t <= t_brake:
            return v0 * t
        tb = min(t - t_brake, v0 / a)
        return v0 * t_brake + v0 * tb - 0.5 * a * tb * tb

    t_run = time.monotonic()
    for k in range(int(round(t_end / dt)) + 1):  # the states at the times the test sends them
        time.sleep(max(0.0, t_run + k * dt - time.monotonic()))
        q = start.copy()
        q[:2] += travelled(time.monotonic() - t_run) * heading
        loop.robot_state(q)
    t_last = time.monotonic() - t_run
    v_last = v0 - a * (t_last - t_brake)
    assert 0.1 < v_last < v0  # precondition: still braking at the last state
    rest = start[:2] + (travelled(t_last) + v_last ** 2 / (2 * a)) * heading
    s = _first_trajectory(loop, rec, q, goals)
    err = float(np.hypot(*(s.positions[0, :2] - rest)))
    assert err < 0.01, (s.positions[0, :2], rest, err)


def test_a_braking_base_whose_states_arrive_irregularly_rests_where_its_measured_velocity_says(make_loop,
                                                                                                  world_models):
    """Robot states of a base braking from 0.3 m/s, each taken every 20 ms of the robot's time but received
    irregularly (5 and 35 ms apart in turn, as on a busy machine), each with the velocity the robot measured
    (odometry): the plan starts where the test's own uniform-deceleration kinematics bring the base to rest, within
    5 mm. The estimate from receipt times, which the loop falls back to without a measured velocity, is 1.6 cm
    off on these states (no wait for the rest: ``settle_timeout_s`` 0)."""
    robot, start, goals = world_models
    loop, rec = make_loop(settle_timeout_s=0.0)
    a = float(robot.config.base.linear_acceleration)
    v0, dt, n = 0.3, 0.02, 8
    heading = np.array([np.cos(start[2]), np.sin(start[2])])
    gaps = [0.005 if k % 2 else 0.035 for k in range(n)]
    t_run = time.monotonic()
    for k in range(n):  # the robot's time k * dt; received after the gaps
        time.sleep(max(0.0, t_run + sum(gaps[:k]) - time.monotonic()))
        t = k * dt
        q = start.copy()
        q[:2] += (v0 * t - 0.5 * a * t * t) * heading
        loop.robot_state(q, np.array([v0 - a * t, 0.0]))
    t_last = (n - 1) * dt
    v_last = v0 - a * t_last
    assert 0.1 < v_last < v0  # precondition: still braking at the last state
    rest = start[:2] + (v0 * t_last - 0.5 * a * t_last ** 2 + v_last ** 2 / (2 * a)) * heading
    s = _first_trajectory(loop, rec, q, goals, base_velocity=np.array([v_last, 0.0]))
    err = float(np.hypot(*(s.positions[0, :2] - rest)))
    assert err < 0.005, (s.positions[0, :2], rest, err)


def test_a_base_braking_slower_than_its_config_says_gets_a_plan_from_where_it_rests(make_loop, world, world_models):
    """A base brakes from 0.3 m/s at a third of the deceleration its robot config gives (a driver's own braking
    ramp), with nothing under way and a goal arriving as braking begins; states at 50 Hz until 0.5 s after it
    rests. The trajectory handed over starts within 1 cm of where the test's own kinematics bring the base to rest,
    and not before the base is within 1 cm of it. Planned at once from the rest the config predicts (with
    ``settle_timeout_s`` 0), it starts 17 cm off: the adapter would refuse it and stop the robot again."""
    robot, start, goals = world_models
    loop, rec = make_loop()
    a = float(robot.config.base.linear_acceleration) / 3.0
    v0, dt = 0.3, 0.02
    t_rest = v0 / a
    heading = np.array([np.cos(start[2]), np.sin(start[2])])
    rest = start.copy()
    rest[:2] += v0 ** 2 / (2 * a) * heading
    assert not world.colliding(np.stack([start + f * (rest - start) for f in np.linspace(0, 1, 11)])).any()

    def at(t: float) -> np.ndarray:
        tb = min(t, t_rest)
        q = start.copy()
        q[:2] += (v0 * tb - 0.5 * a * tb * tb) * heading
        return q

    sent: list = []

    def brake():  # the robot's states at 50 Hz, each with its measured velocity
        for k in range(int((t_rest + 0.5) / dt) + 1):
            time.sleep(max(0.0, t_run + k * dt - time.monotonic()))
            t = time.monotonic() - t_run
            loop.robot_state(at(t), np.array([max(0.0, v0 - a * t), 0.0]))
            sent.append((time.perf_counter(), t))

    t0 = time.perf_counter()
    t_run = time.monotonic()
    loop.robot_state(at(0.0), np.array([v0, 0.0]))
    th = threading.Thread(target=brake, daemon=True)
    th.start()
    loop.goals(goals)
    ev = rec.wait(t0, ("trajectory", "stop"), 60.0)
    th.join()
    assert ev is not None and ev[1] == "trajectory", f"no trajectory: {rec.since(t0)}"
    err = float(np.hypot(*(ev[2].positions[0, :2] - rest[:2])))
    assert err < 0.01, f"the trajectory starts {err:.3f} m from where the base rests"
    t_robot = max(t for tp, t in sent if tp <= ev[0])  # the robot's time at the newest state sent before it
    left = float(np.hypot(*(rest[:2] - at(t_robot)[:2])))
    assert left < 0.01, f"handed over while the base had {left:.3f} m left to brake"
    assert not rec.since(t0, ("stop",)), "the robot was stopped"


def test_a_robot_resting_at_the_end_of_its_trajectory_takes_the_next_goal(make_loop, world, world_models):
    """A robot that has driven its trajectory to the end and rests there: a new goal gives a trajectory from where it
    rests (the commitment, at most the rest of the old trajectory, is never "too late" for a robot that waits at its
    end), judged from the states the test sent and the samples it received."""
    robot, start, goals = world_models
    loop, rec = make_loop(robot_state_timeout_s=1.0)
    near = start.copy()
    near[:2] += 0.5 * np.array([np.cos(start[2]), np.sin(start[2])])
    assert not world.colliding(np.stack([start, near])).any()  # precondition: a short free drive
    s1 = _first_trajectory(loop, rec, start, near[None])
    t_rx = rec.since(0.0, ("trajectory",))[0][0]
    T = float(s1.times[-1])
    assert T < 8.0, "precondition: a short trajectory"
    running = threading.Event()
    running.set()
    sent: list = []

    def follow():  # the robot drives the received samples and rests at their end, reporting at 20 Hz
        while running.is_set():
            tau = max(0.0, time.perf_counter() - t_rx - 0.15)
            q = at_time(s1, tau)
            sent.append((tau, q))
            loop.robot_state(q)
            time.sleep(0.05)

    th = threading.Thread(target=follow, daemon=True)
    th.start()
    try:
        while not sent or sent[-1][0] < T + 0.5:
            time.sleep(0.05)
        t0 = time.perf_counter()
        loop.goals(goals)
        ev = rec.wait(t0, ("trajectory", "stop"), 15.0)
        late = [out for _, kind, out in rec.since(t0, ("info",)) if out.get("failure") == "late_splice"]
        assert ev is not None and ev[1] == "trajectory", f"no trajectory for the next goal ({len(late)} late splices)"
        s2 = ev[2]
        assert same_config(s2.positions[0], s1.positions[-1], 1e-3), (s2.positions[0], s1.positions[-1])
        assert min(np.hypot(*(s2.positions[-1, :2] - g[:2])) for g in goals) < 0.05
    finally:
        running.clear()
        th.join(2.0)


def _plan_while_the_robot_moves(loop, rec, start: np.ndarray, end: np.ndarray, move_s: float, rest_s: float):
    """Request a plan from ``start`` (the robot stopped there) while, during the replan, the robot moves to ``end``
    over ``move_s`` and rests ``rest_s`` (states at 50 Hz, sent from inside the wrapped replan: fault injection of a
    slow query). Returns (the first trajectory or stop after the request, its time; None if none came)."""
    orig = loop.rp.replan
    moved: list = []
    n_move, n = max(1, int(round(move_s / 0.02))), int(round((move_s + rest_s) / 0.02)) + 1

    def moving_while_planning(*a, **k):
        res = orig(*a, **k)
        if not moved:
            moved.append(time.perf_counter())
            for i in range(n):
                loop.robot_state(start + min(i / n_move, 1.0) * (end - start))
                time.sleep(0.02)
        return res

    loop.rp.replan = moving_while_planning
    try:
        t0 = time.perf_counter()
        loop.robot_state(start)
        loop.request("plan", 60.0)
        ev = rec.wait(t0, ("trajectory", "stop"), 30.0)
    finally:
        loop.rp.replan = orig
    assert moved, "precondition: a replan ran"
    assert ev is not None and ev[1] == "trajectory", f"no trajectory: {rec.since(t0)}"
    assert not rec.since(t0, ("stop",)), "the robot was stopped"
    return ev


def test_a_plan_from_a_state_the_robot_left_while_planning_is_replaced_by_one_from_its_newest_state(
        make_loop, world, world_models):
    """The robot is pushed 0.2 m along its heading while a plan from where it stood is being made (as a slow query
    or a stop in between leave a plan's start behind the robot): the loop hands the robot no trajectory starting
    where it stood (the adapter would refuse it and stop the robot), and no stop, but a trajectory from the state the
    test sent last."""
    robot, start, goals = world_models
    loop, rec = make_loop()
    moved = start.copy()
    moved[:2] += 0.2 * np.array([np.cos(start[2]), np.sin(start[2])])
    assert not world.colliding(np.stack([start, moved])).any()  # precondition: a free push
    _first_trajectory(loop, rec, start, goals)
    ok, _ = loop.request("stop", 30.0)  # stopped at the start: the next plan starts from its state, not spliced
    assert ok
    ev = _plan_while_the_robot_moves(loop, rec, start, moved, 1.0, 0.4)  # pushed 0.2 m over 1 s, at rest 0.4 s
    d = float(np.hypot(*(ev[2].positions[0, :2] - moved[:2])))
    assert d < 0.01, f"the trajectory handed to the robot starts {d:.3f} m from the robot's newest state"


def test_a_plan_from_a_head_pan_the_robot_left_while_planning_is_replaced(make_loop, world, world_models):
    """The head is panned 0.3 rad while a plan from where it pointed is being made (the base stays): no trajectory
    whose head pan starts more than the adapter's 0.25 rad from the last state the test sent is handed over, and no
    stop. Without the joint check (``start_joint_tolerance`` 0) the plan goes out 0.3 rad off: the head's collision
    boxes move less than the 3.5 cm start tolerance."""
    robot, start, goals = world_models
    loop, rec = make_loop()
    j = robot.joint_names.index("joint_head_pan")
    turned = start.copy()
    turned[j] += 0.3 if start[j] + 0.3 <= robot.upper[j] else -0.3
    assert not world.colliding(np.stack([start, turned])).any()  # precondition: a free turn
    _first_trajectory(loop, rec, start, goals)
    ok, _ = loop.request("stop", 30.0)  # stopped at the start: the next plan starts from its state, not spliced
    assert ok
    ev = _plan_while_the_robot_moves(loop, rec, start, turned, 0.5, 0.3)  # the head turns over 0.5 s, rests 0.3 s
    err = abs(float(ev[2].positions[0, j] - turned[j]))
    assert err < 0.25, f"the trajectory's head pan starts {err:.3f} rad from the robot's newest state"


def test_the_stop_guard_stops_for_a_body_stepping_onto_a_robot_standing_off_its_trajectory(make_loop, world,
                                                                                          world_models):
    """The robot stands 0.3 m beside the start of its trajectory (pushed, or lagging a turn on the spot): a body
    pose touching the robot where it stands, clear of the trajectory's next 1.5 s, stops it at once; the same body
    0.6 m further out does not."""
    robot, start, goals = world_models
    loop, rec = make_loop()
    s = _first_trajectory(loop, rec, start, goals)
    side = np.array([-np.sin(start[2]), np.cos(start[2])])
    body = world.sent.scene.obstacle("person_body")
    first = s.positions[s.times <= 1.5]
    for sign in (1.0, -1.0):  # the free side
        off = start.copy()
        off[:2] += sign * 0.3 * side
        if not world.colliding(off[None]).any():
            break
    assert not world.colliding(off[None]).any(), "precondition: a free place beside the start"
    loop.robot_state(off)
    time.sleep(0.3)
    touching = None
    for d in np.arange(0.15, 0.6, 0.02):  # the nearest body position that touches the robot where it stands
        p = np.r_[off[:2] + sign * d * side, body.center[2]]
        world.sent.sent("person_body", p, body.quat)
        if world.colliding(off[None]).any() and not world.colliding(first).any():
            touching = p
            break
    assert touching is not None, "precondition: a body pose touching the standing robot, clear of the trajectory"
    far = np.r_[touching[:2] + sign * 0.6 * side, body.center[2]]
    world.sent.sent("person_body", far, body.quat)
    assert not world.colliding(np.vstack([off[None], first])).any()  # precondition: clear of both
    t_far = world.send(loop, "person_body", far, body.quat)
    assert not rec.since(t_far, ("stop",)), "a stop for a body clear of the robot and its trajectory"
    world.sent.sent("person_body", touching, body.quat)
    t0 = world.send(loop, "person_body", touching, body.quat)
    got = rec.since(t0, ("stop", "trajectory"))
    assert got and got[0][1] == "stop", f"no stop at once: {got}"


def test_the_stop_guard_checks_what_lies_ahead_of_a_robot_turning_on_the_spot(make_loop, world, world_models):
    """The robot is 40 % through a turn on the spot of its trajectory (its base where the turn began): a body pose
    that collides with the trajectory 0.6-1.4 s ahead of the robot, and with nothing the robot has turned through
    or turns through in the next 0.55 s, stops it at once."""
    robot, start, goals = world_models
    loop, rec = make_loop()
    s = _first_trajectory(loop, rec, start, goals)
    xy = s.positions[:, :2]
    step = np.r_[0.0, np.hypot(*np.diff(xy, axis=0).T)]
    dth = np.r_[0.0, np.abs(np.diff(s.positions[:, 2]))]
    spot = (step < 1e-4) & (dth > 1e-3)  # samples turning on the spot
    runs, k = [], 0
    while k < len(spot):
        if spot[k]:
            j = k
            while j + 1 < len(spot) and spot[j + 1]:
                j += 1
            runs.append((k, j))
            k = j + 1
        else:
            k += 1
    turns = [(a, b) for a, b in runs if s.times[b] - s.times[a] > 2.5 and s.times[a] > 1.0]
    assert turns, "precondition: the trajectory turns on the spot for more than 2.5 s after its first second"
    a, b = turns[0]
    t_r = s.times[a] + 0.4 * (s.times[b] - s.times[a])
    q_r = at_time(s, t_r)
    ahead = s.positions[(s.times >= t_r + 0.6) & (s.times <= t_r + 1.4)]
    # clear of what the robot turned through and of the next 0.55 s (a guard that looked from where the turn began
    # would check only the first 1.5 s of the turn, which ends before t_r + 0.55)
    behind = s.positions[(s.times >= s.times[a] - 1.0) & (s.times <= t_r + 0.55)]
    assert s.times[a] + 1.5 < t_r + 0.55, "precondition: the turn's first 1.5 s end before the clear stretch does"
    body = world.sent.scene.obstacle("person_body")
    place = None
    for r in np.arange(0.2, 1.0, 0.04):
        for ang in np.linspace(-np.pi, np.pi, 48, endpoint=False):
            p = np.r_[q_r[:2] + r * np.array([np.cos(ang), np.sin(ang)]), body.center[2]]
            world.sent.sent("person_body", p, body.quat)
            if world.colliding(ahead).any() and not world.colliding(np.vstack([q_r[None], behind])).any():
                place = p
                break
        if place is not None:
            break
    assert place is not None, "precondition: a body pose touching only the turn still ahead"
    # the robot's states at 50 Hz along its turn up to t_r
    for tau in np.arange(max(0.0, t_r - 0.4), t_r + 1e-9, 0.02):
        loop.robot_state(at_time(s, tau))
        time.sleep(0.02)
    world.sent.sent("person_body", place, body.quat)
    t0 = world.send(loop, "person_body", place, body.quat)
    got = rec.since(t0, ("stop", "trajectory"))
    assert got and got[0][1] == "stop", f"no stop at once: {got}"
