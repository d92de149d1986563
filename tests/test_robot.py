"""Robot configs and models: the three shipped robots load; bad input gives errors that name file and field."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import torch

from psprm_core.errors import ConfigError, PsprmError, RobotModelError
from psprm_core.paths import config_dir
from psprm_core.robot import RobotModel, load_robot_config, urdf_path_for

ROBOTS = {"stretch2": (8, "camera_color_optical_frame"), "fetchlike": (13, "xtion_rgb_optical_frame"),
          "ur5_mobile": (9, "wrist_camera_optical_frame")}


@pytest.mark.parametrize("name", sorted(ROBOTS))
def test_shipped_robot_loads(name, load_robot):
    r = load_robot(name)
    dof, cam = ROBOTS[name]
    assert r.dof == dof and r.joint_names[:3] == ["base_x", "base_y", "base_theta"]
    assert r.config.camera_link == cam
    q = torch.as_tensor(np.stack([r.default_configuration()] * 4), dtype=torch.float32)
    T = r.camera_poses(q)
    assert T.shape == (4, 4, 4)
    R = T[0, :3, :3]
    assert torch.allclose(R @ R.T, torch.eye(3), atol=1e-5)
    assert 0.3 < float(T[0, 2, 3]) < 2.0  # a camera above the floor, below the ceiling
    centers = r.sphere_centers(q)
    assert centers.shape == (4, len(r.spheres.radii), 3)


def test_stretch_arm_extension_drives_four_joints(load_robot):
    r = load_robot("stretch2")
    q = r.configuration({"arm_extension": 0.4})
    vals = r.urdf_joint_values(q)
    assert [round(vals[f"joint_arm_l{i}"], 6) for i in range(4)] == [0.1] * 4
    # the camera does not move with the arm; the gripper does
    q0 = torch.as_tensor(np.stack([r.configuration({"arm_extension": 0.0}), q]), dtype=torch.float64)
    cam = r.camera_poses(q0)
    assert torch.allclose(cam[0], cam[1])
    grip = r.link_poses(q0, ["link_gripper"])
    assert abs(float((grip[1, 0, :3, 3] - grip[0, 0, :3, 3]).norm()) - 0.4) < 1e-6


def test_base_pose_moves_camera_rigidly(load_robot):
    r = load_robot("fetchlike")
    q = np.stack([r.default_configuration()] * 2)
    q[1, :3] = [1.0, -2.0, np.pi / 2]
    T = r.camera_poses(torch.as_tensor(q, dtype=torch.float64))
    Rz = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(T[1, :3, :3], Rz @ T[0, :3, :3], atol=1e-9)
    assert torch.allclose(T[1, :3, 3], Rz @ T[0, :3, 3] + torch.tensor([1.0, -2.0, 0], dtype=torch.float64))


@pytest.mark.parametrize("name", ["fetchlike", "stretch2"])
def test_head_camera_images_are_upright(name, load_robot):
    """Renders and detectors see gravity-upright images: image x horizontal, image "up" (-y) towards the sky, for
    any base pose and the head's pan/tilt. Stretch's portrait-mounted D435i needs its configured roll for this."""
    r = load_robot(name)
    rng = np.random.default_rng(3)
    q = np.stack([r.default_configuration()] * 32)
    q[:, :3] = rng.uniform([-2, -2, -np.pi], [2, 2, np.pi], size=(32, 3))
    for joint, lim in (("joint_head_pan", 1.2), ("joint_head_tilt", 0.5), ("head_1_joint", 1.2),
                       ("head_2_joint", 0.5)):
        if joint in r.joint_names:
            q[:, r.index(joint)] = rng.uniform(-lim, lim, 32)
    T = r.camera_poses(torch.as_tensor(q, dtype=torch.float64)).numpy()
    assert np.all(np.abs(T[:, 2, 0]) < 0.01)  # image x axis horizontal (URDF mounts are level within 0.05 deg)
    assert np.all(-T[:, 2, 1] > 0.3)  # image up points upwards


def test_camera_roll_turns_the_image_about_the_optical_axis(tmp_path, load_robot):
    """``camera.roll_deg`` turns the image frame about the optical axis and nothing else."""
    from psprm_core.robot import image_roll
    from psprm_core.robot.urdf import parse_urdf

    r = load_robot("stretch2")
    text = Path(r.config.source).read_text()
    assert "roll_deg: -90.0" in text
    p = tmp_path / "stretch_sideways.yaml"
    p.write_text(text.replace("roll_deg: -90.0", "roll_deg: 0.0"))
    cfg = load_robot_config(str(p))
    raw = RobotModel(cfg, parse_urdf(urdf_path_for(cfg)))
    q = torch.as_tensor(np.stack([r.default_configuration()] * 3), dtype=torch.float64)
    q[1, 3:] = torch.tensor([0.9, 0.3, 1.0, -1.0, -0.6], dtype=torch.float64)
    a, b = r.camera_poses(q).numpy(), raw.camera_poses(q).numpy()
    assert np.allclose(a[:, :3, 3], b[:, :3, 3]) and np.allclose(a[:, :3, 2], b[:, :3, 2])  # same eye, same axis
    assert np.allclose(a, b @ image_roll(-90.0), atol=1e-12)
    assert np.allclose(a[:, :3, 0], -b[:, :3, 1], atol=1e-12)  # the sideways image's "up" is now its x axis
    with pytest.raises(ConfigError, match=r"field 'camera\.roll_deg'"):
        p.write_text(text.replace("roll_deg: -90.0", "roll_deg: sideways"))
        load_robot_config(str(p))


def test_ur5_mobile_urdf_is_generated_with_camera(load_robot):
    r = load_robot("ur5_mobile")
    root = ET.parse(r.urdf.path).getroot()
    links = {l.get("name") for l in root.findall("link")}
    assert "world" not in links and "mobile_base_link" in links and "wrist_camera_optical_frame" in links
    assert r.urdf.root == "mobile_base_link"
    for mesh in root.iter("mesh"):
        assert Path(mesh.get("filename")).is_file()


def _write_robot(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "robot.yaml"
    p.write_text(text)
    return p


BASE = (config_dir() / "robots" / "ur5_mobile.yaml").read_text()


def test_malformed_yaml_names_file(tmp_path):
    p = _write_robot(tmp_path, "name: x\njoints: [\n")
    with pytest.raises(ConfigError, match=r"robot.yaml.*malformed YAML"):
        load_robot_config(str(p))


def test_unknown_robot_name():
    with pytest.raises(ConfigError, match=r"unknown robot 'nope'.*stretch2"):
        load_robot_config("nope")


def test_unknown_urdf_joint_in_drives(tmp_path):
    from psprm_core.robot.urdf import parse_urdf

    p = _write_robot(tmp_path, BASE.replace("name: shoulder_pan_joint,", "name: shoulder_pan_joint, drives: {no_such_joint: 1.0},"))
    with pytest.raises(ConfigError, match=r"field 'joints\[0\]\.drives'.*no_such_joint"):
        RobotModel(load_robot_config(str(p)), parse_urdf(urdf_path_for(load_robot_config(str(p)))))


def test_missing_camera_link(tmp_path):
    p = _write_robot(tmp_path, BASE.replace("  link: wrist_camera_optical_frame", "  link: no_camera_here"))
    cfg = load_robot_config(str(p))
    from psprm_core.robot.urdf import parse_urdf

    with pytest.raises(RobotModelError, match=r"camera\.link.*no link 'no_camera_here'"):
        RobotModel(cfg, parse_urdf(urdf_path_for(cfg)))


def test_nan_limit_rejected(tmp_path):
    p = _write_robot(tmp_path, BASE.replace("limits: [-3.14159265, 0.0]", "limits: [.nan, 0.0]"))
    with pytest.raises(ConfigError, match=r"field 'joints\[1\]\.limits'.*finite"):
        load_robot_config(str(p))


def test_unknown_field_rejected(tmp_path):
    p = _write_robot(tmp_path, BASE + "\nspeed_of_light: 3\n")
    with pytest.raises(PsprmError, match="speed_of_light"):
        load_robot_config(str(p))


def test_unknown_joint_in_configuration(load_robot):
    r = load_robot("stretch2")
    with pytest.raises(KeyError, match="no planning joint 'elbow'"):
        r.configuration({"elbow": 1.0})
