"""The references of the device check (:mod:`.device_check`): what the device is judged against, computed here with
the project's full environment (pybullet, the CPU planner) and carried to a bare machine in one file.

    python -m psprm_core.evaluation.device_check --record psprm_core/data/device_check/references.npz

:class:`References` holds the configurations, pybullet's camera poses and collision flags of them, the float64 CPU
scores, the CPU planner's node scores, queries, path lengths and timings, and the robot model's planning description
(its URDF with each collision mesh replaced by the mesh's bounding box, :func:`planning_urdf`, which is all the robot
model takes from a mesh; :func:`carried_robot` builds the model from it and :func:`record` verifies that it equals
the packaged one).
"""

from __future__ import annotations

import json
import os
import platform
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ...errors import InputError
from ...paths import resolve_named

#: the shipped references (``--references`` without a value takes this file); regenerate with ``--record``
DEFAULT_REFERENCES = Path(__file__).resolve().parents[2] / "data" / "device_check" / "references.npz"
#: layout of the references file
FORMAT = 1
#: limits of the checks (``ok`` needs every one)
TOLERANCES = {"fk_position_m": 1e-3, "fk_rotation_rad": 1e-3, "missed_collisions": 0, "score_abs": 0.02,
              "node_score_abs": 0.02, "path_collisions": 0, "path_goal_error": 1e-3, "robot_model_m": 1e-9}
#: defaults of the sizes and problem
DEFAULTS = {"scene": "dynamic_person", "target": "person_face", "configs": 2000, "nodes": 600, "queries": 10,
            "replans": 5, "seed": 0}
FK_VIEWS = 500  # configurations whose camera poses and scores are compared
NODE_SCORES = 500  # roadmap nodes whose scores are compared


@dataclass
class References:
    """What the device is judged against (see the module docstring); arrays as stored in the references file."""

    header: dict
    configs: np.ndarray  # (N, dof) float64: uniform over the joint limits and the scene's workspace
    camera_poses: np.ndarray  # (M, 4, 4) pybullet's camera poses of configs[:M]
    collision: np.ndarray  # (N,) bool: pybullet's exact check of configs
    score_index: np.ndarray  # (K,) indices of the first free configs (of configs[:M]) scored
    scores: np.ndarray  # (K,) their neural scores on the CPU in float64, compiled paths off
    node_configs: np.ndarray  # (P, dof) the first nodes of the CPU planner's roadmap
    node_scores: np.ndarray  # (P,) the CPU planner's scores of them
    query_starts: np.ndarray  # (Q, dof)
    query_goals: np.ndarray  # (sum G, dof) the goals of every query, query after query
    query_goal_counts: np.ndarray  # (Q,) goals per query
    query_success: np.ndarray  # (Q,) bool: the CPU planner's
    query_path_length: np.ndarray  # (Q,) the CPU planner's path lengths (nan where it found none)
    query_ms: np.ndarray  # (Q,) the CPU planner's query times
    build_s: np.ndarray  # () the CPU planner's build time
    replan_start: np.ndarray  # (dof,) the scene's first problem
    replan_goals: np.ndarray  # (G, dof)
    replan_yaws: np.ndarray  # (R,) target turns, in order
    replan_success: np.ndarray  # (R,) bool: the CPU replanner's
    replan_ms: np.ndarray  # (R,) the CPU replanner's times
    robot_spheres: np.ndarray  # (S, 4) the packaged robot model's collision spheres (body-frame centre, radius)
    robot_urdf: np.ndarray  # (bytes,) uint8: the robot's planning URDF (collision meshes as their boxes), UTF-8

    def goals(self, i: int) -> np.ndarray:
        c = np.concatenate([[0], np.cumsum(self.query_goal_counts)])
        return self.query_goals[c[i]:c[i + 1]]

    def save(self, path: Path) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "header"}
        with open(path, "wb") as fh:  # a file object: numpy appends no ".npz" to the name
            np.savez_compressed(fh, header=np.array(json.dumps(self.header, sort_keys=True)), **arrays)

    @classmethod
    def load(cls, path: Path) -> "References":
        with np.load(Path(path), allow_pickle=False) as z:
            header = json.loads(str(z["header"]))
            if header.get("format") != FORMAT:
                raise InputError(f"{path}: references format {header.get('format')}, this check reads {FORMAT}: "
                                 "record them again (--record)")
            return cls(header=header, **{f.name: z[f.name] for f in fields(cls) if f.name != "header"})

    def prefix(self, configs: int | None, queries: int | None, replans: int | None) -> "References":
        """The first ``configs`` configurations, ``queries`` queries and ``replans`` target turns (None: all)."""
        h = self.header
        for name, n in (("configs", configs), ("queries", queries), ("replans", replans)):
            if n is not None and not 1 <= n <= h[name]:
                raise InputError(f"--{name} {n}: the references hold {h[name]}")
        n = h["configs"] if configs is None else configs
        q = h["queries"] if queries is None else queries
        r = h["replans"] if replans is None else replans
        m = min(FK_VIEWS, n)
        keep = self.score_index < m  # the free ones of the first m configurations
        g = int(np.sum(self.query_goal_counts[:q]))
        out = References(**{f.name: getattr(self, f.name) for f in fields(self)})
        out.header = dict(h, configs=n, queries=q, replans=r)
        out.configs, out.collision, out.camera_poses = self.configs[:n], self.collision[:n], self.camera_poses[:m]
        out.score_index, out.scores = self.score_index[keep], self.scores[keep]
        out.query_starts, out.query_goal_counts = self.query_starts[:q], self.query_goal_counts[:q]
        out.query_goals = self.query_goals[:g]
        out.query_success, out.query_path_length = self.query_success[:q], self.query_path_length[:q]
        out.query_ms = self.query_ms[:q]
        out.replan_yaws, out.replan_success, out.replan_ms = self.replan_yaws[:r], self.replan_success[:r], \
            self.replan_ms[:r]
        return out


# ----------------------------------------------------------------------------------------------------------------------
# The robot model's planning description
# ----------------------------------------------------------------------------------------------------------------------
def planning_urdf(robot) -> str:
    """The robot's URDF with what the robot model takes from it only: links, joints and collision elements, each
    collision mesh replaced by a box of the mesh's bounds (scaled) about the same frame. Visual, inertial, gazebo and
    transmission elements are left out. Reads the meshes (trimesh): the record step's work."""
    from ...robot.bodies import _geom_local_box

    tree = ET.parse(robot.urdf.path)
    root = tree.getroot()
    for tag in ("gazebo", "transmission"):
        for el in list(root.findall(tag)):
            root.remove(el)
    for link in root.findall("link"):
        for tag in ("visual", "inertial"):
            for el in list(link.findall(tag)):
                link.remove(el)
        geoms = iter(robot.urdf.links.get(link.get("name"), []))
        for col in link.findall("collision"):
            g = col.find("geometry")
            if g is None or len(g) == 0:
                continue
            geom = next(geoms)
            if g[0].tag != "mesh":
                continue
            lo, hi = _geom_local_box(geom)
            centre = geom.origin[:3, :3] @ (0.5 * (lo + hi)) + geom.origin[:3, 3]
            g.remove(g[0])
            ET.SubElement(g, "box", size=" ".join(repr(float(v)) for v in hi - lo))
            origin = col.find("origin")
            if origin is None:
                origin = ET.SubElement(col, "origin", rpy="0 0 0")
            origin.set("xyz", " ".join(repr(float(v)) for v in centre))
    return ET.tostring(root, encoding="unicode")


def sphere_table(robot) -> np.ndarray:
    sm = robot.spheres
    return np.concatenate([sm.centers, sm.radii[:, None]], axis=1)


def model_difference(a, b) -> float:
    """Largest difference (m, and rotation entries) between two robot models' collision spheres and boxes."""
    ea, eb = a.elements, b.elements
    if sphere_table(a).shape != sphere_table(b).shape or ea.center.shape != eb.center.shape:
        return float("inf")
    return float(max(np.abs(sphere_table(a) - sphere_table(b)).max(), np.abs(ea.center - eb.center).max(),
                     np.abs(ea.half - eb.half).max(), np.abs(ea.rotation - eb.rotation).max()))


def carried_robot(refs: References, scene, folder: Path):
    """The robot model of ``scene`` built from the references' planning URDF (written into ``folder``, which must
    outlive the model: its hash reads the file), with nothing but this package's URDF reader."""
    from ...robot import RobotModel
    from ...robot.config import load_robot_config
    from ...robot.urdf import parse_urdf

    path = Path(folder) / f"{refs.header['robot']}_planning.urdf"
    path.write_bytes(refs.robot_urdf.tobytes())
    return RobotModel(load_robot_config(scene.robot), parse_urdf(path))


# ----------------------------------------------------------------------------------------------------------------------
# References
# ----------------------------------------------------------------------------------------------------------------------
def planner_options(nodes: int, seed: int) -> dict:
    """Settings of both planners: trajectories timed by the analytic profile, stopping at every knot (the smooth
    timing needs toppra, which a bare machine lacks; the build's warm-up times one trajectory)."""
    return {"roadmap.n_nodes": nodes, "seed": seed, "query.smooth_timing": False}


def replan_settings():
    from ...planning.replanner import ReplanSettings

    return ReplanSettings(smooth_timing=False)  # as the planners: the same timing with or without toppra


def compute_references(scene, robot, target: str, configs: int, nodes: int, queries: int, replans: int, seed: int,
                       world) -> References:
    """The references of the module docstring, computed here: ``world`` (a
    :class:`~psprm_core.evaluation.reference.PybulletWorld` of ``robot`` and the scene's boxes) for FK and collision,
    the CPU in float64 for the scores, the CPU planner (compiled kernels) for the planning figures."""
    import torch

    from ...collision import CollisionChecker
    from ...kernels.compute import Compute
    from ...perception.scoring import NeuralScorer
    from ...perception.surrogate import load_surrogate
    from ...planning.factory import default_checkpoint, make_planner, problem_configurations
    from ...planning.replanner import Replanner
    from ...problems import random_problems
    from ..reference import sample_uniform

    qs = sample_uniform(robot, configs, np.random.default_rng(seed), base_box=scene.workspace)
    m = min(FK_VIEWS, configs)
    camera = np.stack([world.camera_pose(x) for x in qs[:m]])
    flags = world.in_collision(qs)
    score_index = np.flatnonzero(~flags[:m])
    scorer = NeuralScorer(load_surrogate(default_checkpoint()), scene, target)
    torch_only = Compute.make("cpu", kernels="torch")  # float64 reference scores: the torch code on the CPU
    free = torch.as_tensor(qs[score_index], dtype=torch.float64)
    scores = scorer.using(torch_only).score(robot.using(torch_only).camera_poses(free)).double().cpu().numpy()

    p = make_planner("neural-psprm-line", scene, [target], robot=robot, device="cpu",
                     options=planner_options(nodes, seed))
    t0 = time.perf_counter()
    p.build()
    build_s = time.perf_counter() - t0
    checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)
    probs = random_problems(robot, scene, checker, queries, np.random.default_rng(seed + 1),
                            robot.default_configuration(), scene.target(target).center, aimed_only=True,
                            aim_restarts=8)
    success, length, q_ms = [], [], []
    for a, b in probs:
        t0 = time.perf_counter()
        r = p.plan(a, b, timing=False)
        q_ms.append((time.perf_counter() - t0) * 1e3)
        success.append(bool(r.success))
        length.append(float(r.path_length) if r.success else float("nan"))
    node_configs = np.asarray(p.graph.configs[:NODE_SCORES])
    node_scores = p.score_configs(torch.as_tensor(node_configs, dtype=torch.float32)).double().cpu().numpy()

    start, goals = problem_configurations(robot, scene, scene.problems[0])
    yaws = np.random.default_rng(seed + 7).uniform(-1.0, 1.0, replans)
    tgt = scene.target(target)
    rp = Replanner(p, replan_settings(), targets=[target])
    rp.set_robot_state(start)
    rp.set_goals(goals)
    rp.replan()
    r_ok, r_ms = [], []
    for yaw in yaws:
        t0 = time.perf_counter()
        rp.update_target(target, tgt.center, np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)]))
        r_ok.append(bool(rp.replan().success))
        r_ms.append((time.perf_counter() - t0) * 1e3)

    header = {"format": FORMAT, "scene": scene.name, "target": target, "robot": robot.name, "configs": configs,
              "nodes": nodes, "queries": len(probs), "replans": replans, "seed": seed, "torch": torch.__version__,
              "numpy": np.__version__, "python": platform.python_version(),
              "cpu": {"machine": platform.machine(), "cores": os.cpu_count(), "torch_threads": torch.get_num_threads()}}
    return References(
        header=header, configs=qs, camera_poses=camera, collision=flags, score_index=score_index, scores=scores,
        node_configs=node_configs, node_scores=node_scores,
        query_starts=np.stack([np.asarray(a, float) for a, _ in probs]),
        query_goals=np.concatenate([np.atleast_2d(np.asarray(b, float)) for _, b in probs]),
        query_goal_counts=np.array([len(np.atleast_2d(b)) for _, b in probs]),
        query_success=np.array(success), query_path_length=np.array(length), query_ms=np.array(q_ms),
        build_s=np.array(build_s), replan_start=np.asarray(start, float), replan_goals=np.atleast_2d(goals),
        replan_yaws=yaws, replan_success=np.array(r_ok), replan_ms=np.array(r_ms),
        robot_spheres=sphere_table(robot), robot_urdf=np.frombuffer(planning_urdf(robot).encode(), dtype=np.uint8))


def record(path: Path, scene_name: str = DEFAULTS["scene"], target: str = DEFAULTS["target"],
           configs: int = DEFAULTS["configs"], nodes: int = DEFAULTS["nodes"], queries: int = DEFAULTS["queries"],
           replans: int = DEFAULTS["replans"], seed: int = DEFAULTS["seed"]) -> dict:
    """Compute the references in this (full) environment and write them to ``path``; verifies first that the robot
    model built from the carried planning URDF equals the packaged one. Returns the header and the file's size."""
    from ...robot import RobotModel
    from ...scene import load_scene
    from ..reference import PybulletWorld

    scene = load_scene(resolve_named("scene", scene_name))
    robot = RobotModel.load(scene.robot)
    world = PybulletWorld(robot, scene.collision_boxes())
    try:
        refs = compute_references(scene, robot, target, configs, nodes, queries, replans, seed, world)
    finally:
        world.close()
    with tempfile.TemporaryDirectory() as tmp:
        diff = model_difference(carried_robot(refs, scene, Path(tmp)), robot)
    if not diff <= TOLERANCES["robot_model_m"]:
        raise RuntimeError(f"the planning URDF's robot model differs from the packaged one by {diff}")
    refs.header["robot_model_difference_m"] = diff
    refs.save(path)
    return {"recorded": str(path), "bytes": Path(path).stat().st_size, **refs.header}


# ----------------------------------------------------------------------------------------------------------------------
# The check
# ----------------------------------------------------------------------------------------------------------------------
