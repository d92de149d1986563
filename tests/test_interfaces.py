"""The control_msgs and tf2_msgs interfaces that scripts/build_interfaces.sh generates into the venv (they are not on
PyPI): the generated types against the published Jazzy definitions written out here (control_msgs 5.8.0's
FollowJointTrajectory, JointTolerance, JointComponentTolerance; tf2_msgs 0.36.4's TFMessage), not against the copies
the build read; then in one process with real rclpy, a FollowJointTrajectory ActionServer aborting a goal of an
ActionClient, and a TFMessage going from a publisher to a subscription, judged from what the test itself sent."""

from __future__ import annotations

import threading
import time

import pytest

pytest.importorskip("rclpy")

# The published definitions, as rosidl's Python bindings name the types (field order as in the files).
FOLLOW_JOINT_TRAJECTORY_GOAL = [
    ("trajectory", "trajectory_msgs/JointTrajectory"),
    ("multi_dof_trajectory", "trajectory_msgs/MultiDOFJointTrajectory"),
    ("path_tolerance", "sequence<control_msgs/JointTolerance>"),
    ("component_path_tolerance", "sequence<control_msgs/JointComponentTolerance>"),
    ("goal_tolerance", "sequence<control_msgs/JointTolerance>"),
    ("component_goal_tolerance", "sequence<control_msgs/JointComponentTolerance>"),
    ("goal_time_tolerance", "builtin_interfaces/Duration"),
]
FOLLOW_JOINT_TRAJECTORY_RESULT = [("error_code", "int32"), ("error_string", "string")]
FOLLOW_JOINT_TRAJECTORY_RESULT_CODES = {"SUCCESSFUL": 0, "INVALID_GOAL": -1, "INVALID_JOINTS": -2,
                                        "OLD_HEADER_TIMESTAMP": -3, "PATH_TOLERANCE_VIOLATED": -4,
                                        "GOAL_TOLERANCE_VIOLATED": -5}
FOLLOW_JOINT_TRAJECTORY_FEEDBACK = [
    ("header", "std_msgs/Header"),
    ("joint_names", "sequence<string>"),
    ("desired", "trajectory_msgs/JointTrajectoryPoint"),
    ("actual", "trajectory_msgs/JointTrajectoryPoint"),
    ("error", "trajectory_msgs/JointTrajectoryPoint"),
    ("multi_dof_joint_names", "sequence<string>"),
    ("multi_dof_desired", "trajectory_msgs/MultiDOFJointTrajectoryPoint"),
    ("multi_dof_actual", "trajectory_msgs/MultiDOFJointTrajectoryPoint"),
    ("multi_dof_error", "trajectory_msgs/MultiDOFJointTrajectoryPoint"),
]
JOINT_TOLERANCE = [("name", "string"), ("position", "double"), ("velocity", "double"), ("acceleration", "double")]
JOINT_COMPONENT_TOLERANCE = [("joint_name", "string"), ("component", "uint16"), ("position", "double"),
                             ("velocity", "double"), ("acceleration", "double")]
JOINT_COMPONENT_TOLERANCE_CODES = {"X_AXIS": 1, "Y_AXIS": 2, "Z_AXIS": 3, "TRANSLATION": 4, "ROTATION": 5}
TF_MESSAGE = [("transforms", "sequence<geometry_msgs/TransformStamped>")]

STATUS_ABORTED = 6  # action_msgs/msg/GoalStatus


def _fields(cls) -> list:
    return list(cls.get_fields_and_field_types().items())


def _constants(cls, names) -> dict:
    return {n: getattr(cls, n) for n in names if hasattr(cls, n)}


def test_generated_types_match_the_published_definitions():
    from control_msgs.action import FollowJointTrajectory
    from control_msgs.msg import JointComponentTolerance, JointTolerance
    from tf2_msgs.msg import TFMessage

    assert _fields(FollowJointTrajectory.Goal) == FOLLOW_JOINT_TRAJECTORY_GOAL
    assert _fields(FollowJointTrajectory.Result) == FOLLOW_JOINT_TRAJECTORY_RESULT
    assert _constants(FollowJointTrajectory.Result, FOLLOW_JOINT_TRAJECTORY_RESULT_CODES) == \
        FOLLOW_JOINT_TRAJECTORY_RESULT_CODES
    assert _fields(FollowJointTrajectory.Feedback) == FOLLOW_JOINT_TRAJECTORY_FEEDBACK
    assert _fields(JointTolerance) == JOINT_TOLERANCE
    assert _fields(JointComponentTolerance) == JOINT_COMPONENT_TOLERANCE
    assert _constants(JointComponentTolerance, JOINT_COMPONENT_TOLERANCE_CODES) == JOINT_COMPONENT_TOLERANCE_CODES
    assert _fields(TFMessage) == TF_MESSAGE
    # the names a ROS graph shows for them
    assert FollowJointTrajectory.Goal.__module__.startswith("control_msgs.action")
    assert TFMessage.__module__.startswith("tf2_msgs.msg")


@pytest.fixture
def ros():
    """A context of its own (a free domain id), an executor spinning in a thread, and a factory of nodes on it."""
    import rclpy
    from rclpy.executors import MultiThreadedExecutor

    from psprm_ros.harness.probe import claim_domain_id

    ctx = rclpy.Context()
    ctx.init(domain_id=claim_domain_id())
    ex = MultiThreadedExecutor(num_threads=4, context=ctx)
    nodes = []

    def node(name):
        n = rclpy.create_node(name, context=ctx)
        ex.add_node(n)
        nodes.append(n)
        return n

    stop = threading.Event()

    def spin():
        while not stop.is_set() and ctx.ok():
            ex.spin_once(timeout_sec=0.05)

    th = threading.Thread(target=spin, daemon=True)
    th.start()
    try:
        yield node
    finally:
        stop.set()
        th.join(timeout=5.0)
        ex.shutdown()
        for n in nodes:
            n.destroy_node()
        ctx.try_shutdown()


def _wait(future, timeout):
    deadline = time.monotonic() + timeout
    while not future.done() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert future.done(), f"no answer within {timeout} s"
    return future.result()


def test_follow_joint_trajectory_goal_aborted_by_a_real_action_server(ros):
    from builtin_interfaces.msg import Duration
    from control_msgs.action import FollowJointTrajectory
    from control_msgs.msg import JointTolerance
    from rclpy.action import ActionClient, ActionServer
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    joints = ["joint_lift", "wrist_extension", "joint_head_pan"]
    points = [([0.50, 0.10, 0.00], 1, 0), ([0.62, 0.15, -0.40], 2, 500_000_000), ([0.71, 0.20, -0.75], 4, 0)]
    error_string = "joint_lift: position error 0.0731 m > path tolerance 0.05 m at t = 1.25 s"
    received, feedbacks = [], []

    def execute(goal_handle):
        received.append(goal_handle.request)
        fb = FollowJointTrajectory.Feedback()
        fb.joint_names = list(goal_handle.request.trajectory.joint_names)
        fb.desired.positions = list(goal_handle.request.trajectory.points[0].positions)
        goal_handle.publish_feedback(fb)
        time.sleep(0.2)  # the feedback goes out before the result
        goal_handle.abort()
        return FollowJointTrajectory.Result(error_code=FollowJointTrajectory.Result.PATH_TOLERANCE_VIOLATED,
                                            error_string=error_string)

    server_node = ros("fjt_server")
    server = ActionServer(server_node, FollowJointTrajectory, "/arm_controller/follow_joint_trajectory", execute)
    client_node = ros("fjt_client")
    client = ActionClient(client_node, FollowJointTrajectory, "/arm_controller/follow_joint_trajectory")
    try:
        assert client.wait_for_server(timeout_sec=20.0), "the action server was not discovered"
        goal = FollowJointTrajectory.Goal()
        goal.trajectory = JointTrajectory(joint_names=joints, points=[
            JointTrajectoryPoint(positions=p, time_from_start=Duration(sec=s, nanosec=ns)) for p, s, ns in points])
        goal.path_tolerance = [JointTolerance(name="joint_lift", position=0.05)]
        goal.goal_time_tolerance = Duration(sec=0, nanosec=250_000_000)
        handle = _wait(client.send_goal_async(goal, feedback_callback=lambda m: feedbacks.append(m.feedback)), 20.0)
        assert handle.accepted
        answer = _wait(handle.get_result_async(), 20.0)
    finally:
        client.destroy()
        server.destroy()

    # the client gets exactly the server's verdict
    assert answer.status == STATUS_ABORTED
    assert answer.result.error_code == -4
    assert answer.result.error_string == error_string
    # the server got exactly the goal the test sent
    assert len(received) == 1
    got = received[0]
    assert list(got.trajectory.joint_names) == joints
    assert [(list(p.positions), p.time_from_start.sec, p.time_from_start.nanosec) for p in got.trajectory.points] \
        == [(p, s, ns) for p, s, ns in points]
    assert [(t.name, t.position, t.velocity, t.acceleration) for t in got.path_tolerance] == \
        [("joint_lift", 0.05, 0.0, 0.0)]
    assert (got.goal_time_tolerance.sec, got.goal_time_tolerance.nanosec) == (0, 250_000_000)
    # and the feedback came back to the client
    assert [(list(f.joint_names), list(f.desired.positions)) for f in feedbacks] == [(joints, points[0][0])]


def test_tf_message_reaches_a_subscriber(ros):
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    sent = [  # (parent, child, stamp sec, nanosec, translation, rotation xyzw)
        ("map", "odom", 12, 345_000_000, (1.25, -0.5, 0.0), (0.0, 0.0, 0.3826834323650898, 0.9238795325112867)),
        ("base_link", "camera_link", 12, 400_000_000, (0.1, 0.02, 1.3), (0.5, -0.5, 0.5, -0.5)),
    ]
    msg = TFMessage()
    for parent, child, sec, ns, t, q in sent:
        tr = TransformStamped()
        tr.header.frame_id, tr.child_frame_id = parent, child
        tr.header.stamp.sec, tr.header.stamp.nanosec = sec, ns
        tr.transform.translation.x, tr.transform.translation.y, tr.transform.translation.z = t
        (tr.transform.rotation.x, tr.transform.rotation.y, tr.transform.rotation.z,
         tr.transform.rotation.w) = q
        msg.transforms.append(tr)

    got = []
    ros("tf_listener").create_subscription(TFMessage, "/tf_test", got.append, 10)
    pub = ros("tf_broadcaster").create_publisher(TFMessage, "/tf_test", 10)
    deadline = time.monotonic() + 20.0
    while not got and time.monotonic() < deadline:  # until discovery has matched the two
        pub.publish(msg)
        time.sleep(0.1)
    assert got, "no TFMessage received"
    for m in got:
        assert [(tr.header.frame_id, tr.child_frame_id, tr.header.stamp.sec, tr.header.stamp.nanosec,
                 (tr.transform.translation.x, tr.transform.translation.y, tr.transform.translation.z),
                 (tr.transform.rotation.x, tr.transform.rotation.y, tr.transform.rotation.z, tr.transform.rotation.w))
                for tr in m.transforms] == sent
