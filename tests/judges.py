"""Independent references the tests judge with: the poses a test sent (applied to its scene loaded afresh from the
file), collision checks built from that record (the planner's box model and pybullet's exact mesh check), and the
motion limits measured by finite differences of a trajectory's positions. Nothing here reads the state of the code
under test."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from psprm_core.collision import CollisionChecker
from psprm_core.evaluation.reference import PybulletWorld
from psprm_core.paths import resolve_named
from psprm_core.scene import load_scene


class SentPoses:
    """A test's own record of every pose it sent, applied to the scene loaded afresh from its file."""

    def __init__(self, scene_name: str):
        self.scene = load_scene(resolve_named("scene", scene_name))
        self.poses = {b.name: (b.center.copy(), b.quat.copy()) for b in self.scene.obstacles}
        self.poses.update({t.name: (t.center.copy(), t.quat.copy()) for t in self.scene.targets if t.obstacle})

    def sent(self, name: str, center, quat) -> None:
        q = np.asarray(quat, float)
        self.poses[name] = (np.asarray(center, float).copy(), q / np.linalg.norm(q))

    def boxes(self) -> list:
        """Every collision box (obstacles, and targets that are obstacles) at the pose last sent."""
        out = [dataclasses.replace(b, center=self.poses[b.name][0], quat=self.poses[b.name][1])
               for b in self.scene.obstacles]
        return out + [dataclasses.replace(t, center=self.poses[t.name][0], quat=self.poses[t.name][1]).as_box()
                      for t in self.scene.targets if t.obstacle]


class Judge:
    """Collision flags of configurations against a :class:`SentPoses` record: a collision checker built afresh from
    the record (the planner's conservative box model) or'ed with pybullet's exact mesh check on the same record."""

    def __init__(self, robot, sent: SentPoses):
        self.robot, self.sent = robot, sent
        self.world = PybulletWorld(robot, sent.boxes())
        self._bodies = {name: body for body, name in self.world.box_bodies.items()}

    def close(self) -> None:
        self.world.close()

    def colliding(self, qs: np.ndarray, exact_every: int = 1) -> np.ndarray:
        """(N,) flags; pybullet checks every ``exact_every``-th configuration (the box model checks all)."""
        qs = np.asarray(qs, float)
        boxes = self.sent.boxes()
        ch = CollisionChecker(self.robot, boxes, workspace=self.sent.scene.workspace)
        hit = ch.check(torch.as_tensor(qs, dtype=torch.float32)).numpy().copy()
        for b in boxes:
            self.world.p.resetBasePositionAndOrientation(self._bodies[b.name], list(b.center), list(b.quat),
                                                         physicsClientId=self.world.cid)
        idx = np.arange(0, len(qs), exact_every)
        hit[idx] |= self.world.in_collision(qs[idx])
        return hit


def wrap(q: np.ndarray) -> np.ndarray:
    """Configurations with the base heading (index 2) wrapped into [-pi, pi)."""
    q = np.array(q, float)
    q[..., 2] = (q[..., 2] + np.pi) % (2 * np.pi) - np.pi
    return q


def same_config(a: np.ndarray, b: np.ndarray, tol: float = 1e-4) -> bool:
    """Two configurations equal within ``tol``, the base heading modulo a turn."""
    d = np.asarray(a, float) - np.asarray(b, float)
    d[..., 2] = (d[..., 2] + np.pi) % (2 * np.pi) - np.pi
    return bool(np.abs(d).max() < tol)


def limit_ratios(traj, robot, dt: float = 2e-3) -> dict:
    """Largest speed and acceleration of a trajectory as fractions of the robot's limits, measured by finite
    differences of its positions sampled about every ``dt`` (never from the velocities the trajectory reports).

    A chord's speed never exceeds the largest speed along it, and a second difference over ``2 dt`` is an average
    of the acceleration, so a ratio above 1 is a real excess. Mobile robots: the base's (x, y) speed / acceleration
    (their norm) against the linear limits, its heading against the angular ones, every other joint against its
    own."""
    n = max(3, int(np.ceil(traj.duration / dt)) + 1)
    ts, h = np.linspace(0.0, traj.duration, n, retstep=True)
    x = traj.evaluate(ts)[0]
    v = np.diff(x, axis=0) / h
    a = np.diff(v, axis=0) / h
    out = {}
    vmax, amax = np.asarray(robot.velocity, float), np.asarray(robot.acceleration, float)
    first = 0
    if robot.mobile:
        b = robot.config.base
        out["base_linear_velocity"] = float(np.hypot(v[:, 0], v[:, 1]).max() / b.linear_velocity)
        out["base_angular_velocity"] = float(np.abs(v[:, 2]).max() / b.angular_velocity)
        out["base_linear_acceleration"] = float(np.hypot(a[:, 0], a[:, 1]).max() / b.linear_acceleration)
        out["base_angular_acceleration"] = float(np.abs(a[:, 2]).max() / b.angular_acceleration)
        first = 3
    for j in range(first, x.shape[1]):
        out[f"joint{j}_velocity"] = float(np.abs(v[:, j]).max() / vmax[j])
        out[f"joint{j}_acceleration"] = float(np.abs(a[:, j]).max() / amax[j])
    return out
