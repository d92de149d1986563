"""``perception_scorer``: the perception surrogate (+ ray-cast occlusion) as a node.

Subscribes to the target (and dynamic obstacle) poses ``/psprm/state/...`` and to the camera poses the roadmap server
publishes (``/psprm/roadmap/camera_poses``: every roadmap node; ``/psprm/path/camera_poses``: along the current
path). Re-scores them whenever the target moves (at most ``rescore_rate_hz``) and publishes
``/psprm/roadmap/scores`` (std_msgs/Float32MultiArray, one score per roadmap node), ``/psprm/path/score``
(std_msgs/Float32, mean predicted score of the current path), ``~/path_scores`` (Float32MultiArray along the path) and
``~/status``.
"""

from __future__ import annotations

import threading
import time
from typing import Optional

import numpy as np
from psprm_core.planning.factory import make_scorer

from . import core
from .interfaces import conversions as cv
from .runner import run_nodes

P = core.Param
SCORER_PARAMS = {
    "scorer": P("neural", "neural (surrogate + occlusion) | geometric (closed-form proxy)", rebuild=True),
    "checkpoint": P("", "surrogate checkpoint ('' = the shipped one)", rebuild=True),
    "rescore_rate_hz": P(5.0, "path score updates per second (while the target moves)", lo=0.1),
    "roadmap_rescore_period_s": P(2.0, "roadmap scores (marker colours) at most this often", live=True, lo=0.1),
    "max_pose_age_s": P(1.0, "refuse poses older than this (0 = no check)", live=True, lo=0.0),
}


class PerceptionScorer:
    """The scorer as a lifecycle node. Construction declares the parameters and makes ``~/status``; configure reads
    the parameters, loads the scene, the robot model and the scorer (the surrogate's weights), and makes the pose and
    camera subscriptions, the score publishers and the rescoring timer; activate/deactivate gate scoring; cleanup
    destroys what configure made and drops the models, so a configure after it follows changed parameters. Until
    configure, ``scene``, ``robot`` and ``scorer`` are None."""

    def __init__(self, node_name: str = "perception_scorer", **node_kwargs):
        from std_msgs.msg import String

        self.node = node = core.lifecycle_node(self, node_name, **node_kwargs)
        self.log = node.get_logger()
        self.spec = {**core.common_params(), **SCORER_PARAMS}
        self.active = False
        self._lock = threading.Lock()
        # made at configure, dropped at cleanup
        self.scene = self.robot = self.scorer = None
        self.frame: Optional[str] = None
        self.targets: list = []
        self.obstacles: list = []
        self.pub_scores = self.pub_path = self.pub_path_scores = None
        self._made = core.ConfigureScope(node)  # what configure makes, released by cleanup
        self._scene_dirty = False
        self._roadmap: Optional[np.ndarray] = None
        self._path: Optional[np.ndarray] = None
        self._rm_dirty = self._path_dirty = False
        self._last_rm = 0.0
        self.p = core.declare_reconfigurable_params(node, self.spec, lambda k, v: None)
        self.pub_status = node.create_publisher(String, "~/status", 10)

    # ------------------------------------------------------------------------------------------------ lifecycle
    def on_configure(self, state) -> bool:
        """Read the parameters, load the scene, robot model and scorer, make the subscriptions, publishers and
        timer. A bad parameter or a missing file raises: the configure fails with the reason on ``~/status``, the
        node stays unconfigured with nothing made, and can be configured again."""
        return self._made.configure(self._configure, self._release)

    def _configure(self) -> None:
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from geometry_msgs.msg import PoseArray, PoseStamped
        from std_msgs.msg import Float32, Float32MultiArray
        import torch

        node, p = self.node, dict(self.p)
        torch.set_num_threads(max(1, p["torch_threads"]))
        scene, robot = core.load_configured_scene_and_robot(node, p)
        targets = core.scene_targets(scene, p["targets"])
        obstacles = list(p["dynamic_obstacles"])
        for o in obstacles:
            scene.obstacle(o)
        scorer = make_scorer(p["scorer"], scene, targets, robot.config.intrinsics, p["checkpoint"] or None)
        with self._lock:
            self.scene, self.robot, self.scorer, self.frame = scene, robot, scorer, scene.frame
            self.targets, self.obstacles = targets, obstacles
            self._scene_dirty = False
            self._roadmap = self._path = None
            self._rm_dirty = self._path_dirty = False
            self._last_rm = 0.0
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_scores = self._made.publisher(Float32MultiArray, core.ROADMAP_SCORES_TOPIC, latched)
        self.pub_path = self._made.publisher(Float32, core.PATH_SCORE_TOPIC, 10)
        self.pub_path_scores = self._made.publisher(Float32MultiArray, "~/path_scores", 10)
        cb = MutuallyExclusiveCallbackGroup()
        sub = self._made.subscription
        for t in targets:
            sub(PoseStamped, core.target_topic(t), self._pose_cb("target", t), qos_profile_sensor_data,
                callback_group=cb)
        for o in obstacles:
            sub(PoseStamped, core.obstacle_topic(o), self._pose_cb("obstacle", o), qos_profile_sensor_data,
                callback_group=cb)
        sub(PoseArray, core.ROADMAP_CAMERAS_TOPIC, self._cams_cb("roadmap"), latched, callback_group=cb)
        sub(PoseArray, core.PATH_CAMERAS_TOPIC, self._cams_cb("path"), latched, callback_group=cb)
        period = 1.0 / max(0.1, p["rescore_rate_hz"])
        self._made.timer(period, self._tick, callback_group=MutuallyExclusiveCallbackGroup())
        self.status(f"configured: scene {scene.name}, robot {robot.name}, {p['scorer']} scorer of "
                    f"{', '.join(targets)}" + (f"; obstacles {', '.join(obstacles)}" if obstacles else ""))

    def _release(self) -> None:
        """Destroy the subscriptions, publishers and timer configure made and drop the models."""
        self._made.release()
        with self._lock:
            self.pub_scores = self.pub_path = self.pub_path_scores = None
            self.scene = self.robot = self.scorer = self.frame = None
            self.targets, self.obstacles = [], []
            self._roadmap = self._path = None
            self._scene_dirty = self._rm_dirty = self._path_dirty = False

    def on_activate(self, state) -> bool:
        self.active = True
        with self._lock:
            self._rm_dirty = self._path_dirty = True
        return True

    def on_deactivate(self, state) -> bool:
        self.active = False
        return True

    def on_cleanup(self, state) -> bool:
        self._release()
        self.status("unconfigured: subscriptions, publishers and models released")
        return True

    def on_shutdown(self, state) -> bool:
        self.active = False
        self._release()
        return True

    def status(self, text: str, level: str = "info") -> None:
        core.report(self.log, self.pub_status, text, level)

    def _pose_cb(self, kind: str, name: str):
        def cb(msg):
            try:
                now = self.node.get_clock().now().nanoseconds * 1e-9
                p, q = cv.validated_pose(msg, self.frame, now, self.p["max_pose_age_s"], f"{kind} {name}")
                with self._lock:
                    if kind == "target":
                        self.scene = self.scene.with_target_pose(name, p, q)
                    else:
                        self.scene = self.scene.with_obstacle_pose(name, p, q)
                    self._scene_dirty = True
            except Exception as exc:
                self.status(f"ignored {exc}", "warning")
        return cb

    def _cams_cb(self, which: str):
        def cb(msg):
            try:
                cv.check_frame(msg.header.frame_id, self.frame, f"{which} camera poses")
                T = cv.pose_array_to_matrices(msg)
            except Exception as exc:
                self.status(f"ignored {exc}", "warning")
                return
            with self._lock:
                if which == "roadmap":
                    self._roadmap, self._rm_dirty = T, True
                else:
                    self._path, self._path_dirty = T, True
            self._tick(force=True)
        return cb

    def score(self, T: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            return self.scorer.score(torch.as_tensor(T, dtype=torch.float32)).double().numpy()

    def _tick(self, force: bool = False) -> None:
        from std_msgs.msg import Float32

        if not self.active:
            return
        try:
            with self._lock:
                if self._scene_dirty:
                    self.scorer.set_scene(self.scene)
                    self._scene_dirty = False
                    self._rm_dirty = self._path_dirty = True
                rm, path = self._roadmap, self._path
                now = time.monotonic()
                do_rm = self._rm_dirty and rm is not None and (
                    force or now - self._last_rm >= self.p["roadmap_rescore_period_s"])
                do_path = self._path_dirty and path is not None
                if do_rm:
                    self._last_rm = now
                self._rm_dirty &= not do_rm
                self._path_dirty &= not do_path
                if do_rm:
                    self.pub_scores.publish(cv.float_array(self.score(rm)))
                if do_path and len(path):
                    s = self.score(path)
                    self.pub_path_scores.publish(cv.float_array(s))
                    self.pub_path.publish(Float32(data=float(s.mean())))
        except Exception as exc:
            self.status(f"scoring failed: {exc}", "warning")

    def destroy(self) -> None:
        self.node.destroy_node()


def main(args=None) -> int:
    return run_nodes([PerceptionScorer], args, description=__doc__, prog="perception_scorer")


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
