"""Two node suites in two namespaces of one ROS domain, each planning for its own robot: every topic and service of a
suite lies under its namespace (read from the ROS graph), each suite's trajectories start where its own robot stands
(the state the test published in that namespace) and none reaches the other suite. The mocap stream of the target
is shared, as one motion-capture system serves both robots."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

pytest.importorskip("rclpy")

from psprm_core.paths import resolve_named  # noqa: E402
from psprm_core.planning.factory import problem_configurations  # noqa: E402
from psprm_core.scene import load_scene  # noqa: E402
from psprm_ros.interfaces import conversions as cv  # noqa: E402
from psprm_ros.harness.probe import InProcessSuite, claim_domain_id  # noqa: E402

PARAMS = {"scene": "dynamic_person", "roadmap.n_nodes": 400, "seed": 0, "stale_timeout_s": 60.0,
          "input_frames": ["odom"]}


def test_two_suites_in_two_namespaces_plan_for_their_own_robots(load_robot):
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = load_robot("stretch2")
    starts = {"/robot1": problem_configurations(robot, scene, scene.problem("south_to_either"))[0],
              "/robot2": problem_configurations(robot, scene, scene.problem("north_west_to_either"))[0]}
    assert np.hypot(*(starts["/robot1"][:2] - starts["/robot2"][:2])) > 1.0
    domain = claim_domain_id()
    with InProcessSuite(PARAMS, domain_id=domain, nodes=("server", "monitor"), namespace="/robot1") as a, \
            InProcessSuite(PARAMS, domain_id=domain, nodes=("server", "monitor"), namespace="/robot2") as b:
        suites = {"/robot1": a, "/robot2": b}
        states = []
        for ns, s in suites.items():
            assert s.server.ready.wait(180), f"{ns}: roadmap not ready"
            states.append(s.probe.hold_robot_state(starts[ns], robot.joint_names))
        try:
            # the graph: each suite's topics and services under its namespace
            names = {n for n, _ in a.probe.node.get_topic_names_and_types()}
            services = {n for n, _ in a.probe.node.get_service_names_and_types()}
            for ns in suites:
                assert f"{ns}/psprm/trajectory" in names and f"{ns}/psprm/goal_regions" in names, sorted(names)
                assert f"{ns}/roadmap_server/plan" in services, sorted(services)
            assert "/psprm/trajectory" not in names and "/roadmap_server/plan" not in services
            face = scene.target("person_face")
            assert a.probe.wait_subscribers("/mocap/person_face/pose", count=2)
            a.probe.publish_pose("person_face", face.center, face.quat)
            n0 = {ns: len(s.probe.trajectories) for ns, s in suites.items()}
            for ns, s in suites.items():
                assert s.probe.wait_subscribers("psprm/goal_regions")
                s.probe.publish_regions(["at_shelf", "at_cabinet"])
            for ns, s in suites.items():
                msg = s.probe.wait_trajectory(n0[ns], 90)
                assert msg is not None, (ns, [x[2] for x in s.probe.statuses[-6:]])
            for ns, s in suites.items():
                other = starts["/robot2" if ns == "/robot1" else "/robot1"]
                with s.probe.cond:
                    got = [m for _, m in s.probe.trajectories[n0[ns]:]]
                for m in got:
                    P = cv.joint_trajectory_positions(m, robot.joint_names)
                    if len(P) <= 1:
                        continue
                    # its own robot's start, never the other's
                    assert np.hypot(*(P[0, :2] - starts[ns][:2])) < 0.05, (ns, P[0, :3], starts[ns][:3])
                    assert np.hypot(*(P[0, :2] - other[:2])) > 1.0
        finally:
            for st in states:
                st.stop()
