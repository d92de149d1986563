"""A scenario's world over time (:class:`World`, :mod:`.scenarios`): the moving targets' and obstacles' poses and
the goal set at each instant of an episode, and the goals' configurations and arrival."""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from ..errors import ConfigError, InputError
from ..geometry import yaw_to_quat
from ..recording import RecordedTrack
from .scenarios import RECORDING_KEY, Scenario, _heading, keyframed_pose, person_pose, vary


class World:
    """The scenario's time-varying scene: ``poses(t)`` gives the moving targets' and obstacles' poses (the people,
    the keyframed obstacles and the recorded bodies), ``goal_specs(t)`` the goal set at time t. ``variation``:
    ``{target: MotionVariation}`` of an episode (:func:`draw_variation`); None: the motion as written."""

    def __init__(self, scenario: Scenario, scene, robot=None, variation: Optional[dict] = None):
        self.sc, self.scene0, self.robot = scenario, scene, robot
        for name in scenario.targets:
            scene.target(name)  # clear errors for unknown names
        for name in scenario.obstacles:
            scene.obstacle(name)
        lo, hi = np.asarray(scene.workspace, float)[:, 0], np.asarray(scene.workspace, float)[:, 1]
        for i, p in enumerate(scenario.people):
            scene.target(p.target)
            if p.body:
                scene.obstacle(p.body)
            for k in p.keyframes:
                if k.xy is not None and not ((np.asarray(k.xy) >= lo).all() and (np.asarray(k.xy) <= hi).all()):
                    raise ConfigError(scenario.source, f"people[{i}].keyframes", f"position {list(k.xy)} at t = "
                                      f"{k.t:g} s lies outside the scene's workspace")
        for specs in [scenario.goals] + [g for _, g in scenario.goal_changes]:
            for g in specs:
                if isinstance(g, str):
                    scene.goal(g)
        self.variation = dict(variation or {})
        self.people = tuple(vary(p, self.variation[p.target], scene) if p.target in self.variation else p
                            for p in scenario.people)
        p = self.people[0] if self.people else None
        if p is not None:
            self.yaw0 = p.yaw0 if p.yaw0 is not None else _heading(scene.target(p.target).rotation)
        self.recorded = self._recorded_tracks(scenario, scene)

    def _recorded_tracks(self, scenario: Scenario, scene) -> dict:
        """``{body: (kind, RecordedTrack)}`` of the scenario's recording, each replay started the episode's drawn
        fraction into the recording's loop; kind "target" or "obstacle" as the scene has the body."""
        spec = scenario.recording
        if spec is None:
            return {}
        try:
            rec = spec.recording
        except (OSError, InputError) as exc:
            raise ConfigError(scenario.source, "recording.file", str(exc)) from None
        out = {}
        for body in spec.bodies or tuple(rec.bodies):
            if body not in rec.bodies:
                raise ConfigError(scenario.source, "recording.bodies", f"'{body}' is not in {spec.file} (it has "
                                  f"{', '.join(rec.bodies)})")
            frame = rec.frames[rec.bodies.index(body)].strip("/")
            frame_pose = None
            if frame != scene.frame:
                if frame != spec.frame_name:
                    raise ConfigError(scenario.source, "recording.frame", f"'{body}' is recorded in frame '{frame}', "
                                      f"the scene's frame is '{scene.frame}': give that frame's pose in it")
                frame_pose = (spec.frame_xyz, spec.frame_quat)
            kind = "target" if body in scene.target_names else "obstacle"
            if kind == "obstacle":
                scene.obstacle(body)  # a clear error for a body the scene does not have
            if body in scenario.obstacles or any(body in (q.target, q.body) for q in scenario.people):
                raise ConfigError(scenario.source, "recording.bodies", f"'{body}' moves by the scenario already")
            track = RecordedTrack(rec, body, frame_pose=frame_pose)
            v = self.variation.get(RECORDING_KEY)
            track.offset_s = (v.phase_rad / (2 * math.pi)) * track.loop_s if v is not None else 0.0
            out[body] = (kind, track)
        return out

    def person_yaw(self, t: float, i: int = 0) -> float:
        """Heading of person ``i``'s target at time t."""
        p = self.people[i]
        _, heading = keyframed_pose(p, self.scene0, t)
        return heading + p.amplitude_rad * math.sin(2 * math.pi * t / p.period_s + p.phase_rad)

    def obstacle_pose(self, name: str, t: float) -> tuple:
        frames = self.sc.obstacles[name]
        b = self.scene0.obstacle(name)
        yaw_init = _heading(b.rotation)
        if t <= frames[0].t:
            k = frames[0]
            return k.center, yaw_to_quat(k.yaw if k.yaw is not None else yaw_init)
        for a, bk in zip(frames[:-1], frames[1:]):
            if a.t <= t <= bk.t:
                w = (t - a.t) / max(bk.t - a.t, 1e-9)
                ya = a.yaw if a.yaw is not None else yaw_init
                yb = bk.yaw if bk.yaw is not None else ya
                return (1 - w) * a.center + w * bk.center, yaw_to_quat((1 - w) * ya + w * yb)
        k = frames[-1]
        return k.center, yaw_to_quat(k.yaw if k.yaw is not None else yaw_init)

    def goal_specs(self, t: float) -> tuple:
        specs = self.sc.goals
        for tc, g in self.sc.goal_changes:
            if t >= tc:
                specs = g
        return specs

    def all_goal_specs(self) -> tuple:
        """Every goal the scenario names at some time (in order of appearance, without repeats)."""
        out = []
        for g in [self.sc.goals] + [g for _, g in self.sc.goal_changes]:
            out += [s for s in g if s not in out]
        return tuple(out)

    def poses(self, t: float) -> dict:
        """``{"targets": {name: (c, q)}, "obstacles": {name: (c, q)}}`` of everything the scenario moves."""
        out = {"targets": {}, "obstacles": {}}
        for i, p in enumerate(self.people):
            xy, _ = keyframed_pose(p, self.scene0, t)
            pp = person_pose(self.scene0, p, self.person_yaw(t, i), xy if p.keyframes else None)
            out["targets"][p.target] = pp["target"]
            if pp["body"] is not None:
                out["obstacles"][p.body] = pp["body"]
        for name in self.sc.obstacles:
            out["obstacles"][name] = self.obstacle_pose(name, t)
        for name, (kind, track) in self.recorded.items():
            out["targets" if kind == "target" else "obstacles"][name] = track.pose(t)
        return out

    def scene_at(self, t: float, scene=None):
        """``scene`` (default: the scenario's scene as loaded) with everything moved to its pose at time t."""
        scene = self.scene0 if scene is None else scene
        poses = self.poses(t)
        for name, (c, q) in poses["targets"].items():
            scene = scene.with_target_pose(name, c, q)
        for name, (c, q) in poses["obstacles"].items():
            scene = scene.with_obstacle_pose(name, c, q)
        return scene


def goal_configurations(robot, scene, specs, template: np.ndarray, aim=None) -> np.ndarray:
    """Goal configurations (G, dof) from goal-region names or explicit base poses; camera joints aimed with ``aim``
    (a callable (G, dof) -> (G, dof), e.g. the planner's line-of-sight projection of the non-base joints)."""
    qs = []
    for g in specs:
        q = template.copy()
        if isinstance(g, str):
            gr = scene.goal(g)
            vals = dict(gr.joints)
            vals.update(base_x=gr.base[0], base_y=gr.base[1], base_theta=gr.base[2])
            q = robot.configuration(vals)
        else:
            q[:3] = g
        qs.append(q)
    Q = np.stack(qs)
    return aim(Q) if aim is not None else Q


def goal_base(scene, spec) -> np.ndarray:
    """The base pose (x, y, theta) of a goal spec (a goal-region name or an explicit base pose)."""
    if isinstance(spec, str):
        return np.asarray(scene.goal(spec).base, float)
    return np.asarray(spec, float)


def at_goal(q: np.ndarray, scene, specs, tolerance: float) -> bool:
    """The base of configuration ``q`` within ``tolerance`` (m, and rad of heading) of one of the goals ``specs``."""
    for g in specs:
        b = goal_base(scene, g)
        dth = abs((q[2] - b[2] + math.pi) % (2 * math.pi) - math.pi)
        if np.hypot(q[0] - b[0], q[1] - b[1]) <= tolerance and dth <= tolerance:
            return True
    return False
