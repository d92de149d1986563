"""The robot's own description: a robot model built from URDF text (``RobotModel.load(name, urdf_text=...)``) and
the nodes' ``robot_description`` parameters (``psprm_ros.robots.robot_description``).

Judged by pybullet loaded with the very text the test gave the model (written by the test to a temporary file, the
meshes reachable next to it as pybullet looks them up), its link frames composed with the planar base pose and the
camera's roll by the test: the packaged URDF's text gives the packaged model's camera poses; a text in which the test
moved one joint origin by 2 cm (a unit's calibration) moves the camera by exactly that offset, carried by the
rotation pybullet gives the joint's parent link. A description missing what the config needs is refused with the
name of what is missing and the config field that asked for it, before anything is built. Over rclpy, in process:
a description published (transient local) before the node starts is the one the node's model is built from; ``auto``
without a publisher falls back to the packaged URDF within the timeout; a lifecycle node with an unusable description
stays unconfigured and says why."""

from __future__ import annotations

import re
import sys
import time
import uuid
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from psprm_core.errors import RobotModelError  # noqa: E402
from psprm_core.robot import RobotModel, load_robot_config  # noqa: E402

OFFSET = np.array([0.02, 0.0, 0.0])  # the test's calibration of joint_head_pan's origin (in its parent link's frame)


# ------------------------------------------------------------------------------------------------------------ reference
def _pose(pos, quat) -> np.ndarray:
    x, y, z, w = quat
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = pos
    return T


def _rz(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def _urdf_values(cfg, q: np.ndarray, base_dof: int) -> dict:
    """URDF joint values of a planning configuration, from the robot config's own text: each planning joint's drive
    coefficients, the fixed joints at their configured values."""
    vals = dict(cfg.fixed_joints)
    for i, pj in enumerate(cfg.joints):
        for uj, c in pj.drives:
            vals[uj] = c * q[base_dof + i]
    return vals


def pybullet_link_poses(text: str, packaged: Path, cfg, qs: np.ndarray, links: list, tmp_path: Path) -> dict:
    """World poses (N, 4, 4) of ``links`` for planning configurations ``qs``, by pybullet from ``text`` written to a
    temporary file: pybullet's URDF link frames relative to the root link's frame, placed by the planar base pose
    ``Trans(x, y, 0) Rz(theta)`` (for a mobile base)."""
    import pybullet as p

    d = tmp_path / f"pb_{uuid.uuid4().hex[:8]}"
    d.mkdir()
    for entry in packaged.parent.iterdir():  # relative mesh paths, as the packaged URDF's folder has them
        if not entry.name.endswith(".urdf"):
            (d / entry.name).symlink_to(entry)
    for pkg in set(re.findall(r'package://([^/"]+)/', text)):  # pybullet looks for package://pkg/... in ./pkg
        for parent in packaged.resolve().parents:
            if parent.name == pkg and not (d / pkg).exists():
                (d / pkg).symlink_to(parent)
    f = d / "robot.urdf"
    f.write_text(text)
    mobile = cfg.base.type == "diff_drive"
    base_dof = 3 if mobile else 0
    cid = p.connect(p.DIRECT)
    try:
        body = p.loadURDF(str(f), useFixedBase=True, physicsClientId=cid)
        joint_index, link_index = {}, {}
        for i in range(p.getNumJoints(body, physicsClientId=cid)):
            info = p.getJointInfo(body, i, physicsClientId=cid)
            joint_index[info[1].decode()] = i
            link_index[info[12].decode()] = i
        inertial = p.getDynamicsInfo(body, -1, physicsClientId=cid)
        out = {name: [] for name in links}
        for q in qs:
            for name, v in _urdf_values(cfg, q, base_dof).items():
                p.resetJointState(body, joint_index[name], float(v), physicsClientId=cid)
            com = _pose(*p.getBasePositionAndOrientation(body, physicsClientId=cid))
            root = com @ np.linalg.inv(_pose(inertial[3], inertial[4]))
            place = (np.array([[1, 0, 0, q[0]], [0, 1, 0, q[1]], [0, 0, 1, 0], [0, 0, 0, 1.0]]) @ _rz(q[2])
                     if mobile else np.eye(4))
            for name in links:
                st = p.getLinkState(body, link_index[name], computeForwardKinematics=True, physicsClientId=cid)
                out[name].append(place @ np.linalg.inv(root) @ _pose(st[4], st[5]))
    finally:
        p.disconnect(cid)
    return {k: np.array(v) for k, v in out.items()}


def pybullet_cameras(text, packaged, cfg, qs, tmp_path) -> np.ndarray:
    """Camera optical-frame poses: the camera link's pybullet pose turned by the config's roll about its z axis."""
    return pybullet_link_poses(text, packaged, cfg, qs, [cfg.camera_link], tmp_path)[cfg.camera_link] @ \
        _rz(np.radians(cfg.camera_roll_deg))


def random_configurations(robot, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = np.zeros((n, robot.dof))
    for i in range(robot.dof):
        lo, hi = robot.lower[i], robot.upper[i]
        if i < robot.base_dof:
            lo, hi = ((-2.0, 2.0) if i < 2 else (-np.pi, np.pi))
        q[:, i] = rng.uniform(lo, hi, n)
    return q


def cameras(robot, qs) -> np.ndarray:
    return robot.camera_poses(torch.as_tensor(qs, dtype=torch.float64)).numpy()


def calibrated(text: str, joint: str = "joint_head_pan", offset=OFFSET) -> str:
    """``text`` with ``joint``'s origin moved by ``offset`` (in its parent link's frame)."""
    root = ET.fromstring(text)
    (el,) = [j for j in root.findall("joint") if j.get("name") == joint]
    o = el.find("origin")
    xyz = np.array([float(v) for v in o.get("xyz").split()]) + offset
    o.set("xyz", " ".join(repr(float(v)) for v in xyz))
    return ET.tostring(root, encoding="unicode")


def without(text: str, links=(), joints=(), collisions_of=()) -> str:
    root = ET.fromstring(text)
    for el in list(root):
        if (el.tag == "link" and el.get("name") in links) or (el.tag == "joint" and el.get("name") in joints):
            root.remove(el)
        if el.tag == "link" and el.get("name") in collisions_of:
            for c in el.findall("collision"):
                el.remove(c)
    return ET.tostring(root, encoding="unicode")


# ------------------------------------------------------------------------------------------------------------ core
@pytest.mark.parametrize("name", ["stretch2", "fetchlike", "ur5_mobile"])
def test_packaged_text_gives_the_packaged_model(name, load_robot, tmp_path):
    packaged_model = load_robot(name)
    packaged = packaged_model.urdf.path
    text = packaged.read_text()
    cfg = load_robot_config(name)
    model = RobotModel.load(name, urdf_text=text)
    qs = random_configurations(packaged_model, 48, seed=1)
    ref = pybullet_cameras(text, packaged, cfg, qs, tmp_path)
    assert np.abs(cameras(model, qs) - ref).max() < 1e-6
    assert np.abs(cameras(packaged_model, qs) - ref).max() < 1e-6
    # the same collision boxes (its meshes found from the packaged URDF's folder)
    a, b = model.elements, packaged_model.elements
    assert a.link_names == b.link_names
    assert np.allclose(a.half, b.half, atol=1e-12) and np.allclose(a.center, b.center, atol=1e-12)


def test_calibrated_joint_origin_moves_the_camera_by_that_offset(load_robot, tmp_path):
    packaged_model = load_robot("stretch2")
    packaged = packaged_model.urdf.path
    text = packaged.read_text()
    cal = calibrated(text)
    cfg = load_robot_config("stretch2")
    model = RobotModel.load("stretch2", urdf_text=cal, origin="calibrated unit")
    qs = random_configurations(packaged_model, 48, seed=2)
    parent = [j for j in ET.fromstring(text).findall("joint") if j.get("name") == "joint_head_pan"][0] \
        .find("parent").get("link")
    ref = pybullet_link_poses(text, packaged, cfg, qs, [cfg.camera_link, parent], tmp_path)
    ref_cal = pybullet_cameras(cal, packaged, cfg, qs, tmp_path)
    got, got_packaged = cameras(model, qs), cameras(packaged_model, qs)
    assert np.abs(got - ref_cal).max() < 1e-6
    # the offset in the world: the parent link's rotation (pybullet's) applied to it
    expected = ref[parent][:, :3, :3] @ OFFSET
    assert np.allclose(np.linalg.norm(expected, axis=1), 0.02)
    assert np.abs((got[:, :3, 3] - got_packaged[:, :3, 3]) - expected).max() < 1e-6
    assert np.abs(got[:, :3, :3] - got_packaged[:, :3, :3]).max() < 1e-9
    assert np.abs((ref_cal[:, :3, 3] - ref[cfg.camera_link][:, :3, 3]) - expected).max() < 1e-6


def test_missing_camera_link_planning_joint_or_collision_link_is_named(load_robot, tmp_path, monkeypatch):
    monkeypatch.setenv("PSPRM_CACHE_DIR", str(tmp_path / "cache"))
    text = load_robot("stretch2").urdf.path.read_text()
    src = re.escape(str(load_robot_config("stretch2").source))
    cam = "camera_color_optical_frame"
    with pytest.raises(RobotModelError, match=src + r".*no link 'camera_color_optical_frame' \(field 'camera\.link'\)"):
        RobotModel.load("stretch2", urdf_text=without(text, links=[cam], joints=["camera_color_optical_frame_joint"]))
    with pytest.raises(RobotModelError, match=r"no joint 'joint_head_tilt' \(driven by planning joint "
                                              r"'joint_head_tilt', field 'joints\[4\]'\)"):
        RobotModel.load("stretch2", urdf_text=text.replace('"joint_head_tilt"', '"joint_head_tilt_renamed"'))
    with pytest.raises(RobotModelError, match=r"no joint 'joint_arm_l2' \(driven by planning joint 'arm_extension', "
                                              r"field 'joints\[1\]'\)"):
        RobotModel.load("stretch2", urdf_text=text.replace('"joint_arm_l2"', '"joint_arm_l2x"'))
    with pytest.raises(RobotModelError, match=r"link 'link_lift' has no collision geometry \(used by the collision "
                                              r"model"):
        RobotModel.load("stretch2", urdf_text=without(text, collisions_of=["link_lift"]))
    with pytest.raises(RobotModelError, match=r"no joint 'joint_left_wheel' \(field 'fixed_joints\.joint_left_wheel'\)"):
        RobotModel.load("stretch2", urdf_text=text.replace('"joint_left_wheel"', '"wheel_l"'))
    # checked before anything is built: no description file was written
    assert not list((tmp_path / "cache").rglob("*_description_*"))
    # every missing item at once
    with pytest.raises(RobotModelError) as e:
        RobotModel.load("stretch2", urdf_text=without(text.replace('"joint_head_tilt"', '"jt"'), links=[cam],
                                                      joints=["camera_color_optical_frame_joint"]))
    assert "'joint_head_tilt'" in str(e.value) and f"'{cam}'" in str(e.value)


def test_root_link_extra_collision_links_and_malformed_text_are_refused(load_robot):
    text = load_robot("stretch2").urdf.path.read_text()
    root = ET.fromstring(text)
    root.insert(0, ET.fromstring('<link name="base_footprint"/>'))
    root.append(ET.fromstring('<joint name="footprint_joint" type="fixed"><parent link="base_footprint"/>'
                              '<child link="base_link"/><origin xyz="0 0 0.05"/></joint>'))
    with pytest.raises(RobotModelError, match=r"root link 'base_footprint' instead of 'base_link'"):
        RobotModel.load("stretch2", urdf_text=ET.tostring(root, encoding="unicode"))
    # TIAGo with its hand against the hand-less config: the hand's collision links are not in its collision model
    tiago = load_robot("fetchlike").urdf.path.parent / "tiago.urdf"
    assert tiago.is_file()
    with pytest.raises(RobotModelError, match=r"collision geometry on links that tiago_no_hand\.urdf has none on: "
                                              r".*'hand_palm_link'.*collision\.ignore_links"):
        RobotModel.load("fetchlike", urdf_text=tiago.read_text())
    for bad, why in (("", "empty URDF"), ("<robot name='x'><link", "cannot parse"), ("<sdf/>", "not a URDF")):
        with pytest.raises(RobotModelError, match=why):
            RobotModel.load("stretch2", urdf_text=bad, origin="/robot_description")


def test_robot_mesh_uris(load_robot, tmp_path):
    """A robot's own ``package://stretch_description/meshes/...`` URIs are found among the packaged meshes; a visual
    mesh found nowhere is left out; a collision mesh found nowhere is an error naming link and URI."""
    packaged_model = load_robot("stretch2")
    packaged = packaged_model.urdf.path
    text = packaged.read_text()
    assert '"./meshes/' in text
    robot_text = text.replace('"./meshes/', '"package://stretch_description/meshes/')
    model = RobotModel.load("stretch2", urdf_text=robot_text)
    a, b = model.elements, packaged_model.elements
    assert a.link_names == b.link_names and np.allclose(a.half, b.half) and np.allclose(a.center, b.center)
    for m in ET.parse(model.urdf.path).getroot().iter("mesh"):
        assert Path(m.get("filename")).is_file()
    # visual meshes nowhere to be found: left out, the model builds (pybullet on the test's copy with the meshes)
    root = ET.fromstring(robot_text)
    for v in root.iter("visual"):
        for m in v.iter("mesh"):
            m.set("filename", "package://stretch_description/meshes/not_here_" + m.get("filename").rsplit("/")[-1])
    model = RobotModel.load("stretch2", urdf_text=ET.tostring(root, encoding="unicode"))
    cfg = load_robot_config("stretch2")
    qs = random_configurations(packaged_model, 16, seed=3)
    assert np.abs(cameras(model, qs) - pybullet_cameras(text, packaged, cfg, qs, tmp_path)).max() < 1e-6
    assert not [m for m in ET.parse(model.urdf.path).getroot().iter("mesh") if "not_here_" in m.get("filename")]
    # a collision mesh nowhere to be found
    root = ET.fromstring(robot_text)
    (lift,) = [el for el in root.findall("link") if el.get("name") == "link_lift"]
    lift.find("collision").find("geometry").find("mesh").set("filename", "package://lift_pkg/meshes/lift_v9.STL")
    with pytest.raises(RobotModelError, match=r"collision mesh files not found \(link 'link_lift': "
                                              r"'package://lift_pkg/meshes/lift_v9\.STL'\).*needs the files"):
        RobotModel.load("stretch2", urdf_text=ET.tostring(root, encoding="unicode"))


# ------------------------------------------------------------------------------------------------------------ rclpy
@pytest.fixture
def ros_context():
    pytest.importorskip("rclpy")
    import rclpy

    from psprm_ros.harness.probe import claim_domain_id

    ctx = rclpy.Context()
    domain = claim_domain_id()
    ctx.init(domain_id=domain)
    ctx.domain = domain
    yield ctx
    ctx.try_shutdown()


def _publisher(ctx, text: str, namespace: str = "", topic: str = "robot_description"):
    """A robot_state_publisher stand-in: publishes ``text`` once, transient local and reliable, spun on its own."""
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    from psprm_ros.spinning import NodeSpinner

    node = Node(f"rsp_{uuid.uuid4().hex[:6]}", context=ctx, **({"namespace": namespace} if namespace else {}))
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = node.create_publisher(String, topic, qos)
    pub.publish(String(data=text))
    spinner = NodeSpinner(ctx)
    spinner.add(node)
    spinner.start()
    return node, spinner


def _node(ctx, namespace: str, **params):
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from psprm_ros import core

    node = Node("roadmap_server", namespace=namespace, context=ctx,
                parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    return node, core.declare_params(node, core.common_params())


def test_topic_description_published_before_the_node_starts(ros_context, load_robot, tmp_path):
    from psprm_core.paths import resolve_named
    from psprm_core.scene import load_scene
    from psprm_ros.robots.robot_description import robot_from_params, wait_for_robot_description

    packaged_model = load_robot("stretch2")
    text = packaged_model.urdf.path.read_text()
    cal = calibrated(text)
    pub, spinner = _publisher(ros_context, cal, namespace="/unit7")
    try:
        time.sleep(0.5)  # published before the node exists
        scene = load_scene(resolve_named("scene", "dynamic_person"))
        node, p = _node(ros_context, "/unit7", robot_description="topic", robot_description_timeout_s=30.0)
        try:
            assert p["robot_description"] == "topic" and p["robot_description_topic"] == "robot_description"
            robot = robot_from_params(node, p, scene)
            assert wait_for_robot_description(node, "robot_description", 30.0) == cal
        finally:
            node.destroy_node()
    finally:
        spinner.shutdown()
        pub.destroy_node()
    cfg = load_robot_config("stretch2")
    qs = random_configurations(packaged_model, 24, seed=4)
    ref_cal = pybullet_cameras(cal, packaged_model.urdf.path, cfg, qs, tmp_path)
    ref = pybullet_cameras(text, packaged_model.urdf.path, cfg, qs, tmp_path)
    assert np.abs(ref_cal[:, :3, 3] - ref[:, :3, 3]).max() > 0.015  # the calibration shows
    assert np.abs(cameras(robot, qs) - ref_cal).max() < 1e-6


def test_auto_without_a_publisher_falls_back_within_the_timeout(ros_context, load_robot, tmp_path):
    from psprm_core.paths import resolve_named
    from psprm_core.scene import load_scene
    from psprm_ros.robots.robot_description import robot_from_params

    packaged_model = load_robot("stretch2")
    text = packaged_model.urdf.path.read_text()
    # a calibrated robot in another namespace: not this node's description
    pub, spinner = _publisher(ros_context, calibrated(text), namespace="/unit7")
    try:
        scene = load_scene(resolve_named("scene", "dynamic_person"))
        node, p = _node(ros_context, "/unit8", robot_description="auto", robot_description_timeout_s=1.0)
        try:
            t0 = time.monotonic()
            robot = robot_from_params(node, p, scene)
            took = time.monotonic() - t0
            node2, p2 = _node(ros_context, "/unit9", robot_description="topic", robot_description_timeout_s=0.5)
            with pytest.raises(RobotModelError, match=r"no robot description on /unit9/robot_description within "
                                                      r"0\.5 s"):
                robot_from_params(node2, p2, scene)
            node2.destroy_node()
        finally:
            node.destroy_node()
    finally:
        spinner.shutdown()
        pub.destroy_node()
    assert 1.0 <= took < 4.0, took
    cfg = load_robot_config("stretch2")
    qs = random_configurations(packaged_model, 16, seed=5)
    assert np.abs(cameras(robot, qs) - pybullet_cameras(text, packaged_model.urdf.path, cfg, qs, tmp_path)).max() \
        < 1e-6


def test_lifecycle_nodes_with_a_mismatching_description_stay_unconfigured(ros_context, load_robot):
    """The server and the scorer, given a description without the camera link: both are built, every configure fails
    with the reason on ``~/status`` (and the server's latched state), both stay unconfigured."""
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState

    from psprm_ros.harness.probe import InProcessSuite

    text = load_robot("stretch2").urdf.path.read_text()
    bad = without(text, links=["camera_color_optical_frame"], joints=["camera_color_optical_frame_joint"])
    pub, spinner = _publisher(ros_context, bad)  # /robot_description, another participant of the same domain
    params = {"scene": "dynamic_person", "n_nodes": 300, "publish_markers": False, "robot_description": "topic",
              "robot_description_timeout_s": 30.0}
    try:
        with InProcessSuite(params, domain_id=ros_context.domain, nodes=("server", "scorer"), autostart=False) as s:
            probe = s.probe
            clients = {}

            def call(srv_type, name, req):
                cl = clients.setdefault(name, probe.node.create_client(srv_type, name))
                assert cl.wait_for_service(timeout_sec=10.0), name
                fut = cl.call_async(req)
                assert probe.wait_for(lambda: fut.done(), 30), name
                return fut.result()

            for n in ("roadmap_server", "perception_scorer"):
                assert probe.wait_for(lambda: probe.node.count_publishers(f"/{n}/status") >= 1, 10)
                t0 = time.perf_counter()
                req = ChangeState.Request()
                req.transition.id = Transition.TRANSITION_CONFIGURE
                assert not call(ChangeState, f"/{n}/change_state", req).success
                got = probe.wait_status("no link 'camera_color_optical_frame' (field 'camera.link')", after_t=t0,
                                        timeout=10, level="error")
                assert got is not None and got[0] == n, [x[1:] for x in probe.statuses]
                assert "configure failed" in got[1]
                assert call(GetState, f"/{n}/get_state", GetState.Request()).current_state.label == "unconfigured"
            assert probe.wait_for(lambda: [t for _, t in probe.server_state
                                           if t.startswith("error:") and "camera.link" in t], 10)
            assert not [t for _, t in probe.server_state if t.startswith("ready")]
    finally:
        spinner.shutdown()
        pub.destroy_node()


def test_sim_robot_publishes_its_urdf_as_the_robot_description(ros_context, load_robot):
    """sim_robot publishes its robot's URDF on robot_description (transient local) as robot_state_publisher does:
    a node started after it with ``robot_description: topic`` receives the packaged file's text (the test reads the
    file itself) and builds its model from it."""
    from rclpy.parameter import Parameter

    from psprm_core.paths import resolve_named
    from psprm_core.scene import load_scene
    from psprm_ros.robots.robot_description import robot_from_params, wait_for_robot_description
    from psprm_ros.sim_robot import SimRobotNode
    from psprm_ros.spinning import NodeSpinner

    packaged = load_robot("stretch2").urdf.path
    sim = SimRobotNode(context=ros_context, namespace="/unit9",
                       parameter_overrides=[Parameter("scene", value="dynamic_person"),
                                            Parameter("adapter", value="stretch2")])
    spinner = NodeSpinner(ros_context)
    spinner.add(sim.node)
    spinner.start()
    try:
        node, p = _node(ros_context, "/unit9", robot_description="topic", robot_description_timeout_s=30.0)
        try:
            assert wait_for_robot_description(node, "robot_description", 30.0) == packaged.read_text()
            robot = robot_from_params(node, p, load_scene(resolve_named("scene", "dynamic_person")))
            assert robot.joint_names == load_robot("stretch2").joint_names
        finally:
            node.destroy_node()
    finally:
        spinner.shutdown()
        sim.node.destroy_node()
