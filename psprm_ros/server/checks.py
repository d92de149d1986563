"""The planning loop's collision checks of what the robot executes: the final check of a trajectory before it is
published (against the newest obstacle poses the loop has), and the stop guard's check of a body's new pose against
the robot and the next seconds of its trajectory."""

from __future__ import annotations

import dataclasses
import numpy as np
import torch

from psprm_core.collision import CollisionChecker

from ..interfaces import conversions as cv

#: how a heading or joint difference (per rad / m) counts against base distance (m) in finding where along a
#: published trajectory the robot is
TURN_M_PER_RAD = 0.3


def remaining(robot, positions: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The part of a published trajectory ``positions`` the robot has not traversed yet: from its sample nearest to
    the robot state ``q``. For a mobile base the nearness counts the heading and the joints too
    (:data:`TURN_M_PER_RAD`): a turn on the spot keeps the base where it is, and by position alone its first sample
    would be the nearest however far the turn has gone."""
    Q = np.asarray(positions)
    if len(Q) <= 1:
        return Q
    if robot.mobile:
        turn = np.abs((Q[:, 2] - q[2] + np.pi) % (2 * np.pi) - np.pi)
        d = (np.linalg.norm(Q[:, :2] - q[:2], axis=1) + TURN_M_PER_RAD * turn
             + TURN_M_PER_RAD * np.abs(Q[:, 3:] - q[3:]).max(axis=1, initial=0.0))
    else:
        d = np.linalg.norm(Q - q, axis=1)
    return Q[int(np.argmin(d)):]


class FinalCheck:
    """The scene with the newest obstacle and target poses the loop has, and a collision checker of it: a trajectory
    is published only when every configuration along it (densified to ``step``, as a controller interpolating
    linearly between its points moves) is free (:meth:`unsafe`)."""

    def __init__(self, robot, scene):
        self.robot, self.scene = robot, scene
        self.checker = CollisionChecker(robot, scene.collision_boxes(), workspace=scene.workspace)

    def with_poses(self, obstacles: dict, targets: dict) -> list:
        """Apply poses (name -> (position, quaternion)) of obstacles and of targets (only those that are obstacles
        count); returns the (kind, name, error) of the ones the scene refused."""
        refused, changed = [], False
        for name, (p, q) in obstacles.items():
            try:
                self.scene = self.scene.with_obstacle_pose(name, p, q)
                changed = True
            except (KeyError, ValueError) as exc:
                refused.append(("obstacle", name, exc))
        for name, (p, q) in targets.items():
            try:
                self.scene = self.scene.with_target_pose(name, p, q)
                changed |= self.scene.target(name).obstacle
            except (KeyError, ValueError) as exc:
                refused.append(("target", name, exc))
        if changed:
            self.checker.set_boxes(self.scene.collision_boxes())
        return refused

    def unsafe(self, positions: np.ndarray, step: float) -> bool:
        """True when any configuration along ``positions`` (densified to ``step``) collides with the newest obstacle
        poses, or leaves the joint limits or the workspace; a non-finite position counts as a collision."""
        Q = np.asarray(positions, float).reshape(-1, self.robot.dof)
        if len(Q) == 0:
            return False
        if not np.isfinite(Q).all():
            return True
        Q = cv.densify_linear(Q, step)
        return bool(self.checker.check(torch.as_tensor(Q, dtype=torch.float32)).any())


class StopGuard:
    """The stop guard's check, run on the thread that delivers a body's pose: does the body at its new pose collide
    with the robot's newest configuration or the next seconds of its trajectory? Its own checker (it runs beside the
    worker's final check)."""

    def __init__(self, robot, scene):
        self.robot, self.scene = robot, scene
        self.checker = CollisionChecker(robot, workspace=scene.workspace)

    def body(self, kind: str, name: str, p: np.ndarray, q: np.ndarray):
        """The box of body ``name`` (``kind`` obstacle or target) at a new pose; None for a target that is not an
        obstacle."""
        if kind == "target":
            t = self.scene.target(name)
            return dataclasses.replace(t.as_box(), center=p, quat=q) if t.obstacle else None
        return dataclasses.replace(self.scene.obstacle(name), center=p, quat=q)

    def hits(self, box, q_now: np.ndarray, positions: np.ndarray, horizon_s: float, dt: float,
             step: float) -> bool:
        """Whether ``box`` collides with the robot at ``q_now`` (a robot that lags its trajectory or has left it
        stands where no sample of it lies) or along the next ``horizon_s`` of the trajectory ``positions`` (samples
        ``dt`` apart) from its sample nearest ``q_now`` (densified to ``step``)."""
        ahead = remaining(self.robot, positions, q_now)[: int(np.ceil(horizon_s / dt)) + 1]
        D = np.vstack([np.asarray(q_now, float)[None], cv.densify_linear(ahead, step)])
        return bool(self.checker.env_hits(torch.as_tensor(D, dtype=torch.float32), [box]).any())

