"""Robot models: configuration (YAML), URDF sources, batched forward kinematics and collision spheres.

A robot's *planning configuration* ``q`` is ``[base_x, base_y, base_theta, j_1 ... j_n]`` for a mobile base
(``base.type: diff_drive``) or ``[j_1 ... j_n]`` for a fixed base. A planning joint may drive several URDF joints
(Stretch's four telescoping arm joints are one ``arm_extension``). URDF joints that are not planned are held at fixed
values (wheels, fingers).

Forward kinematics works on *bodies*: maximal groups of links rigidly attached to each other. FK only walks the
driven joints, so a (B, dof) batch costs one small matrix product per driven joint.

The model is :mod:`~psprm_core.robot.model`; the configuration (YAML) and URDF sources are in
:mod:`~psprm_core.robot.config`; both re-exported here.
"""

from .bodies import ElementModel, SphereModel
from .config import (BASE_JOINTS, BaseConfig, CollisionConfig, PlanningJoint, RobotConfig, check_description,
                     description_urdf, image_roll, load_robot_config, urdf_path_for)
from .model import RobotModel, add_base_twists, load_acm
from .urdf import Urdf, parse_urdf

__all__ = ["BASE_JOINTS", "BaseConfig", "CollisionConfig", "ElementModel", "PlanningJoint", "RobotConfig",
           "RobotModel", "SphereModel", "Urdf", "add_base_twists", "check_description", "description_urdf",
           "image_roll", "load_acm", "load_robot_config", "parse_urdf", "urdf_path_for"]
