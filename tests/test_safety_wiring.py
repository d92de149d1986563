"""Safety checks where they are used: each final check is disabled in turn AT ITS CALL SITE (the function or method
its caller uses, patched to pass everything, for that caller only) while an upstream fault makes a colliding result;
with the real check the collision never escapes, with the check disabled it does. Both halves are judged from the
test's own record (the scene file and the poses the test sent: a fresh box-model checker or'ed with pybullet, or
pybullet alone), never from the code's state. The second half shows that the test exercises the call site: a caller
that stopped calling its check (or a redesign that dropped it) fails the first half.

Call sites covered:

- the replanner's final dense collision check of a new plan (``Replanner._replan``: ``checker.check_unpadded`` on the
  dense path and the trajectory's positions), behind a planner whose output is driven through the table;
- the roadmap server's check of a trajectory before publishing it (``_unsafe`` as its plan step ``_plan`` calls it,
  on the server or on the planning loop it holds), behind a replanner whose output is driven through the person
  (ROS 2 in-process suite, as ``test_ros_safety``)."""

from __future__ import annotations

import contextlib
import sys
import time

import numpy as np
import pytest
import torch

from psprm_core.paths import resolve_named
from psprm_core.perception.scoring import GeometricScorer
from psprm_core.planning.factory import problem_configurations
from psprm_core.planning.psprm import PSPRM, PSPRMSettings
from psprm_core.planning.replanner import Replanner
from psprm_core.scene import load_scene

from judges import Judge, SentPoses  # noqa: E402


def _drive_through(P: np.ndarray, xy) -> np.ndarray:
    """Fault: configurations whose base x, y run straight from the first one to ``xy`` and as far beyond."""
    P = np.array(P, float)
    f = np.linspace(0.0, 1.0, len(P))[:, None]
    a = P[0, :2].copy()
    P[:, :2] = a + f * 2.0 * (np.asarray(xy, float) - a)
    return P


@contextlib.contextmanager
def _disabled_at(obj, method: str, caller: str, caller_file: str):
    """``obj.method`` answers "nothing collides" (all False) when called from function ``caller`` of a file ending
    in ``caller_file``, and runs as usual for every other caller."""
    real = getattr(obj, method)
    hits = []

    def patched(q, *a, **k):
        f = sys._getframe(1)
        if f.f_code.co_name == caller and f.f_code.co_filename.endswith(caller_file):
            hits.append(len(q))
            return torch.zeros(len(q), dtype=torch.bool)
        return real(q, *a, **k)

    setattr(obj, method, patched)
    try:
        yield hits
    finally:
        setattr(obj, method, real)


# ---------------------------------------------------------------------------------------------- the replanner
@pytest.fixture(scope="module")
def dynamic_world(load_robot):
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = load_robot("stretch2")
    scorer = GeometricScorer(scene, "person_face", robot.config.intrinsics)
    p = PSPRM(robot, scene, scorer, scene.target("person_face").center,
              PSPRMSettings().changed({"roadmap.n_nodes": 300, "seed": 3}))
    assert p.build()["success"]
    start, goals = problem_configurations(robot, scene, scene.problem("south_to_either"))
    return scene, robot, p, start, goals


def _replan_through_the_table(dynamic_world, final_check: bool):
    """A fresh replanner whose planner's plans are driven through the table (the fault); returns (replan result,
    the replanner's adopted plan or None, the test's judge flags of that plan, hits of the disabled check)."""
    scene, robot, p, start, goals = dynamic_world
    table_xy = scene.obstacle("table").center[:2]
    real_plan = p.plan
    faults = []

    def faulty_plan(*a, **k):
        res = real_plan(*a, **k)
        if res.success and res.dense is not None:
            faults.append(1)
            res.dense = _drive_through(res.dense, table_xy)
            res.trajectory.positions = _drive_through(res.trajectory.positions, table_xy)
        return res

    rp = Replanner(p, targets=["person_face"])
    rp.set_robot_state(start)
    rp.set_goals(goals)
    p.plan = faulty_plan
    try:
        with contextlib.ExitStack() as stack:
            hits = []
            if not final_check:
                hits = stack.enter_context(_disabled_at(p.checker, "check_unpadded", "_replan", "replanner.py"))
            res = rp.replan()
    finally:
        del p.plan  # back to the class's method
    assert faults, "the fault never ran: the planner found no plan"
    plan = rp.result
    flags = None
    if plan is not None and plan.dense is not None:
        sent = SentPoses("dynamic_person")  # nothing moved: the scene file's poses
        judge = Judge(robot, sent)
        try:
            flags = np.r_[judge.colliding(plan.dense), judge.colliding(plan.trajectory.positions)]
        finally:
            judge.close()
    return res, plan, flags, hits


def test_replanner_final_dense_check_refuses_a_colliding_plan(dynamic_world):
    """The planner's plan driven through the table: the replanner's own final dense check refuses it, and the
    replanner hands out no plan at all (the test's judge has nothing colliding to find)."""
    res, plan, flags, _ = _replan_through_the_table(dynamic_world, final_check=True)
    assert not res.success and "final collision check" in res.reason, res.reason
    assert plan is None or not flags.any()


def test_replanner_with_its_final_check_disabled_lets_the_collision_escape(dynamic_world):
    """The same fault with the final check disabled at its call site (``check_unpadded`` from ``_replan`` only): the
    colliding plan is adopted, and the test's judge (fresh box model or pybullet on the scene file) finds it
    colliding; so the test above fails when the replanner stops calling its check."""
    res, plan, flags, hits = _replan_through_the_table(dynamic_world, final_check=False)
    assert hits, "the final check was never called from _replan"
    assert res.success and plan is not None
    assert flags.any(), "the fault did not make the plan collide: the test above would not need the check"


# ---------------------------------------------------------------------------------------------- the roadmap server
def _server_publishes_through_the_person(load_robot, check_enabled: bool) -> tuple:
    """The ROS suite (server + monitor) with the replanner's results driven through the person (the fault of
    ``test_ros_safety``); with ``check_enabled`` False the server's ``_unsafe`` answers False when its plan step
    asks. Returns (infos after the fault was armed, colliding trajectories published after it, the fault's hits,
    calls of the disabled check)."""
    pytest.importorskip("rclpy")
    from test_ros_safety import PARAMS, Fault, Judge as RosJudge, densified

    from psprm_ros.harness.probe import InProcessSuite, claim_domain_id

    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = load_robot("stretch2")
    with InProcessSuite(PARAMS, domain_id=claim_domain_id(), nodes=("server", "monitor")) as s:
        assert s.server.ready.wait(180)
        assert s.probe.wait_subscribers("/mocap/person_body/pose")
        q = problem_configurations(robot, scene, scene.problem("south_to_either"))[0]
        state = s.probe.hold_robot_state(q, robot.joint_names)
        judge = RosJudge(robot, scene)
        try:
            face = scene.target("person_face")
            n0 = len(s.probe.trajectories)
            s.probe.publish_pose("person_face", face.center, face.quat)
            judge.sent(s.probe.publish_pose("person_body", *judge.log[0][1:]), *judge.log[0][1:])
            s.probe.publish_regions(["at_shelf", "at_cabinet"])
            assert s.probe.wait_trajectory(n0, 30) is not None  # a first, unfaulted plan went out
            fault = Fault(s.server, scene)
            holder = s.server.loop.worker  # the object whose plan step calls _unsafe
            real_unsafe = holder._unsafe
            calls = []

            def unsafe(P):
                f = sys._getframe(1)
                if f.f_code.co_name != "_plan":  # other callers (the monitoring of the path under way) as usual
                    return real_unsafe(P)
                calls.append(len(P))
                return False

            if not check_enabled:
                holder._unsafe = unsafe  # the plan step's check (the method it calls) passes everything
            try:
                fault.armed = True
                t0 = time.perf_counter()
                m0 = len(s.probe.infos)
                s.probe.publish_regions(["at_cabinet"])  # a new goal: a replan, whose output the fault corrupts
                s.probe.wait_for(lambda: [i for _, i in s.probe.infos[m0:] if fault.hits and (
                    "refused" in str(i.get("reason")) or i.get("published_stamp"))], 20)
                time.sleep(0.5)
            finally:
                fault.armed = False
                fault.remove()
                if not check_enabled:
                    del holder._unsafe  # back to the class's method
            with s.probe.cond:
                got = [(t, m) for t, m in s.probe.trajectories if t > t0]
            colliding = [m for t, m in got
                         if judge.collides(densified(m, robot.joint_names), judge.pose_known_at(t)).any()]
            infos = [i for _, i in s.probe.infos[m0:]]
            return infos, colliding, fault.hits, calls
        finally:
            state.stop()
            judge.close()


@pytest.mark.parametrize("check_enabled", [True, False], ids=["check", "check_disabled"])
def test_roadmap_server_check_before_publishing(load_robot, check_enabled):
    """The server's plan step checks every trajectory against the latest obstacle poses before publishing it: with
    the check, the faulted plan is refused and nothing colliding is published (pybullet on the poses the test sent);
    with ``_unsafe`` disabled where the plan step calls it, the colliding trajectory is published, so the first case
    fails when the server stops calling its check."""
    infos, colliding, hits, calls = _server_publishes_through_the_person(load_robot, check_enabled)
    assert hits >= 1, "the fault never ran"
    if check_enabled:
        assert any("planner output in collision" in str(i.get("reason")) for i in infos), infos
        assert not colliding, f"{len(colliding)} colliding trajectories published"
    else:
        assert calls, "the server's plan step never called its check"
        assert colliding, "the faulted trajectory was not published: the check's case would not need the check"
