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
from psprm_ros.interfaces import conversions as cv  # noqa: E402
from psprm_ros.harness.probe import InProcessSuite, claim_domain_id  # noqa: E402

PARAMS = {"scene": "dynamic_person", "dynamic_obstacles": ["person_body"], "roadmap.n_nodes": 500, "seed": 0,
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
            r = srv.set_params("roadmap_server", **{"scoring.alpha": 0.3})
            assert r[0].successful
            assert s.probe.wait_for(lambda: abs(s.server.planner.settings.scoring.alpha - 0.3) < 1e-9, 5)
            assert not np.allclose(w_before, np.asarray(s.server.planner.graph.weights)[ids])
            # refused, with reasons
            r = srv.set_params("roadmap_server", **{"roadmap.n_nodes": 800})
            assert not r[0].successful and "read-only" in r[0].reason
            r = srv.set_params("roadmap_server", trajectory_dt=5.0)
            assert not r[0].successful and "range" in r[0].reason.lower()
            r = srv.set_params("roadmap_server", **{"scoring.alpha": float("nan")})
            assert not r[0].successful
            r = srv.set_params("replan_monitor", mocap_prefix="/other")
            assert not r[0].successful and "configured" in r[0].reason
            r = srv.set_params("replan_monitor", robot_state_timeout_s=0.8)
            assert r[0].successful and s.monitor.tracker.timeout_s == pytest.approx(0.8)
            assert s.server.planner.n_roadmap_nodes == 500
        finally:
            state.stop()


# ---------------------------------------------------------------------------------------------------------------------
# the monitor and the scorer set up in configure and release in cleanup (as Nav2's lifecycle nodes do)
class _Loads:
    """Counts what the process loads: scenes, robot models, perception scorers (the surrogate's weights)."""

    def __init__(self, monkeypatch):
        import psprm_core.planning.factory as factory
        import psprm_core.scene as scene_mod
        from psprm_core.robot import RobotModel

        self.counts = {"scene": 0, "robot": 0, "scorer": 0}

        def counted(kind, fn):
            def wrapper(*a, **kw):
                self.counts[kind] += 1
                return fn(*a, **kw)
            return wrapper

        def everywhere(name, kind, fn):
            # the function and every module's name bound to it (a module imports it by name at its top)
            wrapped = counted(kind, fn)
            for mod in list(sys.modules.values()):
                if getattr(mod, "__name__", "").startswith(("psprm_core", "psprm_ros")) \
                        and getattr(mod, name, None) is fn:
                    monkeypatch.setattr(mod, name, wrapped)

        everywhere("load_scene", "scene", scene_mod.load_scene)
        monkeypatch.setattr(RobotModel, "load", staticmethod(counted("robot", RobotModel.load)))
        everywhere("make_scorer", "scorer", factory.make_scorer)

    def total(self) -> int:
        return sum(self.counts.values())


class _Lone:
    """One lifecycle node (``factory``: the monitor or the scorer, parameters ``params``) and an observer node in a
    context of their own: the observer calls the node's lifecycle and parameter services, records its ``~/status`` and
    reads the ROS graph."""

    def __init__(self, factory, name: str, params: dict):
        import rclpy
        from rclpy.parameter import Parameter
        from std_msgs.msg import String

        from psprm_ros.spinning import NodeSpinner

        self.name = name
        self.ctx = rclpy.Context()
        self.ctx.init(domain_id=claim_domain_id())
        self.owner = factory(context=self.ctx, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        self.obs = rclpy.create_node("lifecycle_observer", context=self.ctx)
        self.statuses: list = []  # (perf_counter, text)
        self._lock = threading.Lock()

        def on_status(msg):
            with self._lock:
                self.statuses.append((time.perf_counter(), msg.data))

        self.obs.create_subscription(String, f"/{name}/status", on_status, 50)
        self.spinner = NodeSpinner(self.ctx)
        self.spinner.add(self.owner.node)
        self.spinner.add(self.obs)
        self.spinner.start()
        self.srv = Services(self.obs)

    def close(self) -> None:
        self.spinner.shutdown(timeout_sec=2.0)
        self.owner.destroy()
        self.obs.destroy_node()
        self.ctx.try_shutdown()

    # graph
    def subscribers(self, topic: str) -> set:
        """Names of the nodes with a subscription on ``topic`` (as the observer's graph sees it)."""
        return {i.node_name for i in self.obs.get_subscriptions_info_by_topic(topic)}

    def node_subscriptions(self) -> set:
        """The topics the node subscribes to (empty until the observer has discovered it)."""
        try:
            return {t for t, _ in self.obs.get_subscriber_names_and_types_by_node(self.name, "/")}
        except Exception:  # not discovered yet
            return set()

    def node_publishers(self) -> set:
        try:
            return {t for t, _ in self.obs.get_publisher_names_and_types_by_node(self.name, "/")}
        except Exception:
            return set()

    def wait(self, predicate, timeout: float = 10.0):
        deadline = time.monotonic() + timeout
        while True:
            r = predicate()
            if r or time.monotonic() > deadline:
                return r
            time.sleep(0.05)

    def status_after(self, t0: float, needle: str, timeout: float = 10.0):
        def find():
            with self._lock:
                return next((s for t, s in self.statuses if t >= t0 and needle in s), None)
        return self.wait(find, timeout)

    def transition(self, tid) -> bool:
        return self.srv.transition(self.name, tid)

    def state(self) -> str:
        return self.srv.state(self.name)

    def set_params(self, **values):
        return self.srv.set_params(self.name, **values)


#: what the nodes may subscribe to before configure: nothing of the suite
_BASE_TOPICS = {"/parameter_events", "/clock"}


def _unconfigured_and_idle(lone: _Lone, loads: _Loads) -> None:
    """(a) built, not configured: the node is on the graph with its ~/status and subscribes to no input topic;
    nothing (scene, robot model, scorer) was loaded."""
    assert lone.wait(lambda: f"/{lone.name}/status" in lone.node_publishers()), lone.node_publishers()
    time.sleep(0.5)  # entities made with the status publisher would be discovered with it
    assert lone.node_subscriptions() <= _BASE_TOPICS, lone.node_subscriptions()
    assert lone.state() == "unconfigured"
    assert loads.total() == 0, loads.counts


def _configured(lone: _Lone, status: str, inputs: set) -> None:
    """(b) configure: the status says so and the node subscribes to ``inputs``."""
    from lifecycle_msgs.msg import Transition

    t0 = time.perf_counter()
    assert lone.transition(Transition.TRANSITION_CONFIGURE)
    assert lone.status_after(t0, status), lone.statuses[-3:]
    assert lone.wait(lambda: inputs <= lone.node_subscriptions()), lone.node_subscriptions()


def _reconfigured(lone: _Lone, params: dict, want: set, gone: set) -> None:
    """Unconfigured: ``params`` are taken; configure again: the node subscribes to ``want`` and not to ``gone``."""
    from lifecycle_msgs.msg import Transition

    r = lone.set_params(**params)
    assert all(x.successful for x in r), [x.reason for x in r]
    assert lone.transition(Transition.TRANSITION_CONFIGURE)
    assert lone.wait(lambda: want <= lone.node_subscriptions()), lone.node_subscriptions()
    time.sleep(0.3)
    subs = lone.node_subscriptions()
    assert not gone & subs, subs


def test_monitor_sets_up_in_configure_and_releases_in_cleanup(monkeypatch):
    """The monitor built: no subscription, nothing loaded. Configure: the mocap, robot state and goal subscriptions
    appear; cleanup: they are gone; configure again after changing the targets and their topics (refused while
    configured, taken while unconfigured): the subscriptions follow; active, a pose on the new topic is forwarded."""
    from lifecycle_msgs.msg import Transition
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import qos_profile_sensor_data

    from psprm_ros.replan_monitor import ReplanMonitor

    loads = _Loads(monkeypatch)
    lone = _Lone(ReplanMonitor, "replan_monitor", {"scene": "home", "targets": ["tv"], "adapter": "stretch2"})
    try:
        _unconfigured_and_idle(lone, loads)
        inputs = {"/mocap/tv/pose", "/joint_states", "/odom", "/psprm/goal", "/psprm/goal_regions"}
        # (b) configure: the subscriptions exist, the models are loaded
        _configured(lone, "configured: scene home", inputs)
        assert "replan_monitor" in lone.subscribers("/mocap/tv/pose")
        assert loads.counts["scene"] >= 1 and loads.counts["robot"] >= 1
        # configured: the targets' topics are read at configure, a change is refused with the reason
        r = lone.set_params(targets=["cup"], target_topics=["/elsewhere/cup"])
        assert not r[0].successful and "configure" in r[0].reason, r[0].reason
        # cleanup: every input subscription is gone
        t0 = time.perf_counter()
        assert lone.transition(Transition.TRANSITION_CLEANUP)
        assert lone.state() == "unconfigured"
        assert lone.status_after(t0, "unconfigured")
        assert lone.wait(lambda: lone.node_subscriptions() <= _BASE_TOPICS, 10), lone.node_subscriptions()
        assert not lone.subscribers("/mocap/tv/pose")
        # unconfigured: the change is taken, and the next configure follows it
        _reconfigured(lone, {"targets": ["cup"], "target_topics": ["/elsewhere/cup"], "odom_topic": "odom_2"},
                      {"/elsewhere/cup", "/odom_2", "/joint_states"}, {"/mocap/tv/pose", "/mocap/cup/pose", "/odom"})
        # active: a pose on the new topic is forwarded as the cup's state (behaviour while active unchanged)
        assert lone.transition(Transition.TRANSITION_ACTIVATE) and lone.state() == "active"
        got = []
        lone.obs.create_subscription(PoseStamped, "/psprm/state/targets/cup", got.append, qos_profile_sensor_data)
        pub = lone.obs.create_publisher(PoseStamped, "/elsewhere/cup", qos_profile_sensor_data)
        assert lone.wait(lambda: pub.get_subscription_count() >= 1)

        def forwarded():
            pub.publish(cv.pose_stamped([1.0, 2.0, 0.8], [0.0, 0.0, 0.0, 1.0], "map",
                                        lone.obs.get_clock().now().to_msg()))
            return got
        assert lone.wait(forwarded, 10), "the pose on the reconfigured topic was not forwarded"
        assert np.allclose(cv.pose_to_numpy(got[-1].pose)[0], [1.0, 2.0, 0.8])
        # deactivate then cleanup from active use releases too
        assert lone.transition(Transition.TRANSITION_DEACTIVATE)
        assert lone.transition(Transition.TRANSITION_CLEANUP)
        assert lone.wait(lambda: lone.node_subscriptions() <= _BASE_TOPICS, 10), lone.node_subscriptions()
    finally:
        lone.close()


def test_scorer_sets_up_in_configure_and_releases_in_cleanup(monkeypatch):
    """The scorer built: no subscription, no scene, robot or surrogate loaded. Configure: it subscribes to its
    targets' states and the camera poses and loads the surrogate; cleanup: all gone; configure again with other
    targets and an obstacle: the subscriptions follow."""
    from lifecycle_msgs.msg import Transition

    from psprm_ros.perception_scorer import PerceptionScorer

    loads = _Loads(monkeypatch)
    lone = _Lone(PerceptionScorer, "perception_scorer", {"scene": "home", "targets": ["tv"], "scorer": "neural"})
    try:
        _unconfigured_and_idle(lone, loads)
        inputs = {"/psprm/state/targets/tv", "/psprm/roadmap/camera_poses", "/psprm/path/camera_poses"}
        _configured(lone, "configured: scene home", inputs)
        assert lone.wait(lambda: "/psprm/roadmap/scores" in lone.node_publishers())
        assert loads.counts["scorer"] == 1 and loads.counts["robot"] >= 1
        r = lone.set_params(targets=["cup"])
        assert not r[0].successful, "a rebuild parameter changed while configured"
        assert lone.transition(Transition.TRANSITION_CLEANUP)
        assert lone.wait(lambda: lone.node_subscriptions() <= _BASE_TOPICS, 10), lone.node_subscriptions()
        assert lone.wait(lambda: "/psprm/roadmap/scores" not in lone.node_publishers())
        assert not lone.subscribers("/psprm/state/targets/tv")
        _reconfigured(lone, {"targets": ["cup"], "dynamic_obstacles": ["sofa"]},
                      {"/psprm/state/targets/cup", "/psprm/state/obstacles/sofa", "/psprm/roadmap/camera_poses"},
                      {"/psprm/state/targets/tv"})
        assert loads.counts["scorer"] == 2
        assert lone.transition(Transition.TRANSITION_ACTIVATE) and lone.state() == "active"
    finally:
        lone.close()


def _planner_threads() -> int:
    return sum(1 for t in threading.enumerate() if t.name == "psprm-planner" and t.is_alive())


def test_server_sets_up_in_configure_and_releases_in_cleanup(monkeypatch):
    """The server built: no input subscription, no scene or robot model loaded, no planner thread; a plan request is
    answered "not configured". Configure: the target, obstacle, robot state and goal subscriptions appear and a
    roadmap is ready; cleanup: the subscriptions and the planner thread are gone; configure again: back, and it
    activates."""
    from lifecycle_msgs.msg import Transition
    from std_srvs.srv import Trigger

    from psprm_ros.roadmap_server import RoadmapServer

    loads = _Loads(monkeypatch)
    threads0 = _planner_threads()
    lone = _Lone(RoadmapServer, "roadmap_server", {"scene": "dynamic_person", "dynamic_obstacles": ["person_body"],
                                                   "roadmap.n_nodes": 300, "seed": 0, "publish_markers": False})

    def plan():
        return lone.srv.call(Trigger, "/roadmap_server/plan", Trigger.Request())
    try:
        _unconfigured_and_idle(lone, loads)
        assert _planner_threads() == threads0
        r = plan()
        assert not r.success and "not configured" in r.message, r.message
        inputs = {"/psprm/state/targets/person_face", "/psprm/state/obstacles/person_body", "/psprm/state/robot",
                  "/psprm/state/goals"}
        assert lone.transition(Transition.TRANSITION_CONFIGURE)
        assert lone.wait(lambda: inputs <= lone.node_subscriptions()), lone.node_subscriptions()
        assert loads.counts["scene"] >= 1 and loads.counts["robot"] >= 1
        assert lone.owner.ready.is_set() and _planner_threads() == threads0 + 1
        t0 = time.perf_counter()
        assert lone.transition(Transition.TRANSITION_CLEANUP)
        assert lone.state() == "unconfigured" and lone.status_after(t0, "unconfigured")
        assert lone.wait(lambda: lone.node_subscriptions() <= _BASE_TOPICS, 10), lone.node_subscriptions()
        assert lone.wait(lambda: _planner_threads() == threads0, 10)
        assert not lone.owner.ready.is_set()
        r = plan()
        assert not r.success and "not configured" in r.message, r.message
        assert lone.transition(Transition.TRANSITION_CONFIGURE)
        assert lone.wait(lambda: inputs <= lone.node_subscriptions()), lone.node_subscriptions()
        assert lone.owner.ready.is_set()
        assert lone.transition(Transition.TRANSITION_ACTIVATE) and lone.state() == "active"
    finally:
        lone.close()


@pytest.mark.parametrize("bad, needle", [({"targets": ["no_such_face"]}, "no target 'no_such_face'"),
                                         ({"checkpoint": "/nonexistent/surrogate.pt"}, "surrogate.pt")])
def test_server_configure_that_fails_leaves_nothing_made_and_says_why(bad, needle):
    """A server whose target the scene lacks (configure fails before the planning loop exists), or whose surrogate
    checkpoint is missing (the loop's roadmap build fails): built (no process dies on it), every configure fails with
    the reason on ``~/status`` and the latched server state, and leaves no subscription and no planner thread."""
    from lifecycle_msgs.msg import Transition
    from std_msgs.msg import String
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from psprm_ros.roadmap_server import RoadmapServer

    threads0 = _planner_threads()
    lone = _Lone(RoadmapServer, "roadmap_server", {"scene": "dynamic_person", "roadmap.n_nodes": 300,
                                                   "roadmap_file": "none", "publish_markers": False, **bad})
    states = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    lone.obs.create_subscription(String, "/psprm/server_state", lambda m: states.append(m.data), latched)
    try:
        assert lone.wait(lambda: "/roadmap_server/status" in lone.node_publishers())
        time.sleep(0.3)
        for _ in range(2):
            t0 = time.perf_counter()
            assert not lone.transition(Transition.TRANSITION_CONFIGURE)
            msg = lone.status_after(t0, needle)
            assert msg is not None and msg.startswith("error:"), lone.statuses[-3:]
            assert lone.state() == "unconfigured"
            assert lone.wait(lambda: any(x.startswith("error:") and needle in x for x in states)), states
            time.sleep(0.3)
            assert lone.node_subscriptions() <= _BASE_TOPICS, lone.node_subscriptions()
            assert _planner_threads() == threads0
            assert not lone.owner.ready.is_set()
    finally:
        lone.close()


def test_adapter_sets_up_in_configure_and_releases_in_cleanup(monkeypatch):
    """The adapter built: no subscription, nothing loaded. Configure: the trajectory, joint state and odometry
    subscriptions and the controller's command topics appear; cleanup: they are gone; configure again with another
    odometry topic and the base pose from mocap (refused while configured, taken while unconfigured): the
    subscriptions follow."""
    from lifecycle_msgs.msg import Transition

    from psprm_ros.robot_adapter import RobotAdapter

    loads = _Loads(monkeypatch)
    lone = _Lone(RobotAdapter, "robot_adapter", {"scene": "dynamic_person", "interface": "topic"})
    try:
        _unconfigured_and_idle(lone, loads)
        inputs = {"/psprm/trajectory", "/joint_states", "/odom"}
        _configured(lone, "configured: scene dynamic_person, robot stretch2", inputs)
        assert lone.wait(lambda: "/stretch/cmd_vel" in lone.node_publishers()), lone.node_publishers()
        assert loads.counts["scene"] >= 1 and loads.counts["robot"] >= 1
        r = lone.set_params(odom_topic="odom_2")
        assert not r[0].successful and "configure" in r[0].reason, r[0].reason
        t0 = time.perf_counter()
        assert lone.transition(Transition.TRANSITION_CLEANUP)
        assert lone.state() == "unconfigured" and lone.status_after(t0, "unconfigured")
        assert lone.wait(lambda: lone.node_subscriptions() <= _BASE_TOPICS, 10), lone.node_subscriptions()
        assert lone.wait(lambda: "/stretch/cmd_vel" not in lone.node_publishers()), lone.node_publishers()
        assert not lone.subscribers("/psprm/trajectory")
        _reconfigured(lone, {"base_pose_source": "pose", "robot_pose_topic": "/mocap/stretch/pose"},
                      {"/psprm/trajectory", "/joint_states", "/mocap/stretch/pose"}, {"/odom"})
        assert lone.transition(Transition.TRANSITION_ACTIVATE) and lone.state() == "active"
        assert lone.transition(Transition.TRANSITION_DEACTIVATE)
        assert lone.transition(Transition.TRANSITION_CLEANUP)
        assert lone.wait(lambda: lone.node_subscriptions() <= _BASE_TOPICS, 10), lone.node_subscriptions()
    finally:
        lone.close()


@pytest.mark.parametrize("which", ["monitor", "scorer", "adapter"])
def test_configure_with_a_bad_parameter_fails_and_the_node_lives_on(which):
    """An unknown scene (monitor), robot (scorer) or adapter config (adapter): the node is built, configure fails with
    the reason on ``~/status`` and subscribes to nothing; it stays unconfigured, takes the fixed parameter and then
    configures."""
    from lifecycle_msgs.msg import Transition

    if which == "monitor":
        from psprm_ros.replan_monitor import ReplanMonitor as factory

        name, bad, needle, fix = "replan_monitor", {"scene": "no_such_scene"}, "unknown scene 'no_such_scene'", \
            {"scene": "dynamic_person"}
        topic = "/mocap/person_face/pose"
    elif which == "adapter":
        from psprm_ros.robot_adapter import RobotAdapter as factory

        name, bad, needle, fix = "robot_adapter", {"adapter": "no_such_adapter", "interface": "topic"}, \
            "no_such_adapter", {"adapter": ""}
        topic = "/psprm/trajectory"
    else:
        from psprm_ros.perception_scorer import PerceptionScorer as factory

        name, bad, needle, fix = "perception_scorer", {"robot": "no_such_robot"}, "unknown robot 'no_such_robot'", \
            {"robot": ""}
        topic = "/psprm/state/targets/person_face"
    lone = _Lone(factory, name, {"scene": "dynamic_person", **bad})
    try:
        assert lone.wait(lambda: f"/{name}/status" in lone.node_publishers())
        time.sleep(0.3)  # the observer's status subscription is matched
        t0 = time.perf_counter()
        assert not lone.transition(Transition.TRANSITION_CONFIGURE)
        msg = lone.status_after(t0, needle)
        assert msg is not None and msg.startswith("error: configure failed"), lone.statuses[-3:]
        assert lone.state() == "unconfigured"
        time.sleep(0.3)
        assert lone.node_subscriptions() <= _BASE_TOPICS, lone.node_subscriptions()
        # a second try with the same parameter fails the same way: the node is not stuck, nor half configured
        t1 = time.perf_counter()
        assert not lone.transition(Transition.TRANSITION_CONFIGURE)
        assert lone.status_after(t1, needle)
        r = lone.set_params(**fix)
        assert all(x.successful for x in r), [x.reason for x in r]
        t2 = time.perf_counter()
        assert lone.transition(Transition.TRANSITION_CONFIGURE)
        assert lone.status_after(t2, "configured: scene dynamic_person"), lone.statuses[-3:]
        assert lone.wait(lambda: topic in lone.node_subscriptions()), lone.node_subscriptions()
        assert lone.transition(Transition.TRANSITION_ACTIVATE) and lone.state() == "active"
    finally:
        lone.close()
