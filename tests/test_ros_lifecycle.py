"""Lifecycle transitions and live parameters, driven through the nodes' standard ROS services from a client node
(lifecycle_msgs ChangeState / GetState, rcl_interfaces SetParameters), in process with real rclpy: configure builds
or loads the roadmap, activate starts planning and execution, deactivate stops the robot (zero twist, hold, stop
trajectory; the robot's reported base stops moving), cleanup drops the roadmap; a live parameter changes what the
node does, one that needs a rebuild is refused with the reason."""

from __future__ import annotations

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

from psprm_core.paths import resolve_named  # noqa: E402
from psprm_core.scene import load_scene  # noqa: E402
from psprm_ros import conversions as cv  # noqa: E402
from psprm_ros.probe import InProcessSuite, claim_domain_id  # noqa: E402

PARAMS = {"scene": "dynamic_person", "dynamic_obstacles": ["person_body"], "n_nodes": 500, "seed": 0,
          "stale_timeout_s": 60.0, "publish_markers": False, "input_frames": ["odom"], "interface": "topic",
          "adapter": "stretch2", "start_problem": "south_to_either"}


class Services:
    def __init__(self, node):
        self.node = node
        self.clients = {}

    def call(self, srv_type, name, request, timeout=60.0):
        if name not in self.clients:
            self.clients[name] = self.node.create_client(srv_type, name)
        cl = self.clients[name]
        assert cl.wait_for_service(timeout_sec=10.0), f"no service {name}"
        fut = cl.call_async(request)
        done = threading.Event()
        fut.add_done_callback(lambda f: done.set())
        assert done.wait(timeout), f"{name}: no answer"
        return fut.result()

    def state(self, node):
        from lifecycle_msgs.srv import GetState

        return self.call(GetState, f"/{node}/get_state", GetState.Request()).current_state.label

    def transition(self, node, tid):
        from lifecycle_msgs.srv import ChangeState

        req = ChangeState.Request()
        req.transition.id = tid
        return self.call(ChangeState, f"/{node}/change_state", req, timeout=300.0).success

    def set_params(self, node, **values):
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        req = SetParameters.Request()
        req.parameters = [Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]
        return self.call(SetParameters, f"/{node}/set_parameters", req).results


def _twists(node, topic="/stretch/cmd_vel"):
    from geometry_msgs.msg import Twist

    got = []
    sub = node.create_subscription(Twist, topic, lambda m: got.append((time.perf_counter(), m)), 50)
    return got, sub


def test_lifecycle_transitions_from_a_client(load_robot):
    from lifecycle_msgs.msg import Transition
    from trajectory_msgs.msg import JointTrajectory

    scene = load_scene(resolve_named("scene", "dynamic_person"))
    with InProcessSuite(PARAMS, domain_id=claim_domain_id(), nodes=("server", "monitor", "adapter", "sim"),
                        autostart=False) as s:
        srv = Services(s.probe.node)
        for n in ("roadmap_server", "replan_monitor", "robot_adapter"):
            assert srv.state(n) == "unconfigured"
        assert s.server.rp is None
        # configure builds or loads the roadmap; inactive nodes publish nothing
        assert srv.transition("roadmap_server", Transition.TRANSITION_CONFIGURE)
        assert srv.state("roadmap_server") == "inactive" and s.server.ready.is_set()
        assert s.server.planner.n_roadmap_nodes > 0
        for n in ("replan_monitor", "robot_adapter"):
            assert srv.transition(n, Transition.TRANSITION_CONFIGURE)
            assert srv.transition(n, Transition.TRANSITION_ACTIVATE)
        face = scene.target("person_face")
        n0 = len(s.probe.trajectories)
        s.probe.publish_pose("person_face", face.center, face.quat)
        s.probe.publish_regions(["at_cabinet"])
        time.sleep(1.5)
        assert len(s.probe.trajectories) == n0, "an inactive server published a trajectory"
        # activate: the plan comes and the robot moves
        assert srv.transition("roadmap_server", Transition.TRANSITION_ACTIVATE)
        assert srv.state("roadmap_server") == "active"
        msg = s.probe.wait_trajectory(n0, 30)
        assert msg is not None and len(msg.points) > 1
        q_start = s.sim.q
        assert s.probe.wait_for(lambda: np.linalg.norm(s.sim.q[:3] - q_start[:3]) > 0.05, 15), "the robot did not move"
        # deactivating the adapter stops the robot: zero twist, a hold on its controller, the base comes to rest
        got, sub = _twists(s.probe.node)
        holds = []
        hsub = s.probe.node.create_subscription(JointTrajectory, "/stretch_controller/joint_trajectory",
                                                holds.append, 10)
        time.sleep(0.3)
        assert srv.transition("robot_adapter", Transition.TRANSITION_DEACTIVATE)
        assert srv.state("robot_adapter") == "inactive"
        assert s.probe.wait_for(lambda: [m for _, m in got if m.linear.x == 0.0 and m.angular.z == 0.0], 5)
        assert s.probe.wait_for(lambda: [h for h in holds if len(h.points) == 1], 5), "no hold trajectory"
        time.sleep(1.0)  # decelerating within the acceleration limit
        a = s.sim.q[:3].copy()
        time.sleep(1.0)
        assert np.linalg.norm(s.sim.q[:2] - a[:2]) < 1e-3 and abs(s.sim.q[2] - a[2]) < 1e-3, "the base still moves"
        # deactivating the server publishes a stop trajectory
        n1 = len(s.probe.trajectories)
        assert srv.transition("roadmap_server", Transition.TRANSITION_DEACTIVATE)
        stops = s.probe.wait_for(lambda: [m for _, m in s.probe.trajectories[n1:] if len(m.points) == 1], 10)
        assert stops, "no stop trajectory on deactivation"
        n2 = len(s.probe.trajectories)
        s.probe.publish_regions(["at_shelf"])  # an inactive server does not plan
        time.sleep(1.0)
        assert len(s.probe.trajectories) == n2
        # cleanup drops the roadmap; a plan request is answered "not configured"
        assert srv.transition("roadmap_server", Transition.TRANSITION_CLEANUP)
        assert srv.state("roadmap_server") == "unconfigured" and s.server.rp is None
        from std_srvs.srv import Trigger

        r = srv.call(Trigger, "/roadmap_server/plan", Trigger.Request())
        assert not r.success and "not configured" in r.message
        s.probe.node.destroy_subscription(sub)
        s.probe.node.destroy_subscription(hsub)


def test_live_parameters_change_behaviour_and_rebuild_parameters_are_refused(load_robot):
    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = load_robot("stretch2")
    # the robot stands still: no deviation trigger from the monitor
    with InProcessSuite(dict(PARAMS, relay_deadband_m=0.0, relay_deadband_rad=0.0, deviation_tolerance=1000.0),
                        domain_id=claim_domain_id(),
                        nodes=("server", "monitor")) as s:
        assert s.server.ready.wait(180)
        srv = Services(s.probe.node)
        from psprm_core.planning.factory import problem_configurations

        state = s.probe.hold_robot_state(problem_configurations(robot, scene, scene.problem("south_to_either"))[0],
                                         robot.joint_names)
        try:
            face, body = scene.target("person_face"), scene.obstacle("person_body")
            assert s.probe.wait_subscribers("/mocap/person_face/pose")
            n0 = len(s.probe.trajectories)
            s.probe.publish_pose("person_face", face.center, face.quat)
            s.probe.publish_regions(["at_shelf", "at_cabinet"])
            assert s.probe.wait_trajectory(n0, 30) is not None
            time.sleep(0.5)

            def turn_face(yaw):
                c = body.center[:2] + 0.06 * np.array([np.cos(yaw), np.sin(yaw)])
                return s.probe.publish_pose("person_face", np.r_[c, face.center[2]], cv.yaw_quat(yaw))

            # a large move threshold: turning the face by 0.5 rad no longer replans
            r = srv.set_params("roadmap_server", target_turn_rad=2.0, target_move_m=1.0)
            assert all(x.successful for x in r), [x.reason for x in r]
            time.sleep(0.3)
            n1 = len(s.probe.trajectories)
            turn_face(2.3)
            time.sleep(2.0)
            assert len(s.probe.trajectories) == n1, "replanned although the threshold was raised"
            # back to a small threshold: the same kind of turn replans
            r = srv.set_params("roadmap_server", target_turn_rad=0.1, target_move_m=0.03)
            assert all(x.successful for x in r)
            time.sleep(0.3)
            n2 = len(s.probe.trajectories)
            turn_face(2.0)
            assert s.probe.wait_trajectory(n2, 20) is not None, "no replan after lowering the threshold"
            # alpha (Eq. 2) applied to the roadmap's edge weights
            # (the roadmap's own edges: re-weighting also gives the retired query edges' slots back)
            ids = s.server.planner.roadmap_edge_ids()
            w_before = np.asarray(s.server.planner.graph.weights)[ids].copy()
            r = srv.set_params("roadmap_server", alpha=0.3)
            assert r[0].successful
            assert s.probe.wait_for(lambda: abs(s.server.planner.settings.scoring.alpha - 0.3) < 1e-9, 5)
            assert not np.allclose(w_before, np.asarray(s.server.planner.graph.weights)[ids])
            # refused, with reasons
            r = srv.set_params("roadmap_server", n_nodes=800)
            assert not r[0].successful and "read-only" in r[0].reason
            r = srv.set_params("roadmap_server", trajectory_dt=5.0)
            assert not r[0].successful and "range" in r[0].reason.lower()
            r = srv.set_params("roadmap_server", alpha=float("nan"))
            assert not r[0].successful
            r = srv.set_params("replan_monitor", mocap_prefix="/other")
            assert not r[0].successful and "configured" in r[0].reason
            r = srv.set_params("replan_monitor", robot_state_timeout_s=0.8)
            assert r[0].successful and s.monitor.tracker.timeout_s == pytest.approx(0.8)
            assert s.server.planner.n_roadmap_nodes == 500
        finally:
            state.stop()
