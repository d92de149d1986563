"""ament_python package of the psprm ROS 2 nodes.

The sources live in the repository's top-level ``psprm_ros/`` folder; ``psprm_ros``, ``config`` and ``scenes`` here
are symlinks to it, to ``config/ros`` and to ``config/scenes``, so colcon builds the same code the tests run.
Executables are installed under ``lib/psprm_ros/`` (setup.cfg), where ``ros2 run psprm_ros <executable>`` finds them;
params files, adapter configs, the RViz config and the scenes under ``share/psprm_ros/``, where the nodes look for
them by name (``ament_index_python``) before the repository's folders.
"""

from glob import glob

from setuptools import setup

package_name = "psprm_ros"
executables = ["roadmap_server", "perception_scorer", "replan_monitor", "robot_adapter", "sim_robot", "all_in_one",
               "mocap_replay"]
harness = ["latency_bench", "soak", "demo"]  # clients that drive the suite (psprm_ros/harness/)

setup(
    name=package_name,
    version="0.1.0",
    packages=[package_name] + [f"{package_name}.{sub}"
                               for sub in ("harness", "interfaces", "monitor", "robots", "server")],
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", sorted(glob("config/*.yaml")) + sorted(glob("config/*.rviz"))),
        ("share/" + package_name + "/config/adapters", sorted(glob("config/adapters/*.yaml"))),
        ("share/" + package_name + "/scenes", sorted(glob("scenes/*.yaml"))),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="psprm developers",
    maintainer_email="psprm@example.org",
    description="ROS 2 node suite around psprm_core (PS-PRM perception-aware motion planning)",
    license="BSD-3-Clause",
    entry_points={"console_scripts": [f"{e} = {package_name}.{e}:main" for e in executables]
                                     + [f"{e} = {package_name}.harness.{e}:main" for e in harness]},
)
