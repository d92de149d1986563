"""Dynamic scenarios: a scene whose people, obstacles and goals move on a timeline (``config/scenarios/<name>.yaml``),
the seeded variation of the people's motion that makes the episodes of a benchmark differ, and the world the
scenario describes at any instant (:class:`World`).

Scenario files::

    name: rotating_person
    scene: dynamic_person
    planner: neural-psprm-line        # any PS-PRM variant
    nodes: 3000
    seed: 0
    target: person_face               # or targets: [nurse_1_face, nurse_2_face] (kept in view together)
    start: {base_x: 4.0, base_y: 0.7, base_theta: 1.5708}   # planning-joint values (others: robot default)
    goals: [at_shelf, at_cabinet]     # goal-region names, or {base: [x, y, theta]} entries
    duration_s: 60                    # give up after this much simulated time
    control_dt: 0.1                   # robot state / trigger period (s)
    camera_fps: 4                     # oracle frames per simulated second
    person:                           # one moving person (or `people:`, a list of such entries)
      target: person_face
      body: person_body               # obstacle that moves and turns with the face (optional)
      amplitude_rad: 1.2              # yaw(t) = heading(t) + amplitude * sin(2 pi t / period + phase)
      period_s: 12
      keyframes:                      # optional: heading(t) and where the body stands, linearly interpolated
        - {t: 0, xy: [4.0, 3.2], yaw: -1.5708}
        - {t: 3, yaw: 0.0}            # a field left out is held from the keyframe before
        - {t: 6, xy: [5.2, 4.2]}      # walks there from t = 3 to t = 6
      loop_s: 20                      # optional: the keyframes repeat every loop_s (back to the first at loop_s)
    variation: {phase_rad: 6.2832, period: 0.2, amplitude: 0.15, speed: 0.2}   # the episodes' variation (defaults)
    obstacles:                        # keyframes per obstacle, linearly interpolated (held before/after)
      cabinet: [{t: 0, center: [7.75, 3.2, 0.5]}, {t: 6, center: [7.75, 2.0, 0.5], yaw: 0.0}]
    goal_changes:                     # the goal set changes at time t
      - {t: 6, goals: [{base: [6.9, 2.0, 0.0]}]}
    recording:                        # bodies replayed from a motion-capture recording (CSV or rosbag2), looped
      file: ../recordings/person_turning.csv   # relative to the scenario file
      bodies: [person_face, person_body]        # scene targets or obstacles (default: every body recorded)
      frame: {name: world, xyz: [0, 0, 0], quat: [0, 0, 0, 1]}   # optional: a recorded frame's pose in the scene's

A person (:class:`PersonMotion`) is a target, optionally with a body obstacle: the pair turns about the body's
vertical axis (the face keeps its offset from the body's centre) and walks with the body's centre on the keyframes'
positions. Headings are used as written (unwrapped): from -1.5708 to -4.7124 turns through west. ``person:`` turns by
``amplitude_rad`` (default 1.0) when no amplitude is given; entries of ``people:`` do not (default 0).

Episode variation (:func:`draw_variation`, :func:`vary`): per person, a phase offset drawn in ``[0, phase_rad)`` (added
to the turn's phase; with ``loop_s`` the keyframed timeline also starts that fraction of a loop later), a scale of the
turn's period and of the standing stretches' durations (1 +- ``period``), of the turn's amplitude and of the keyframed
turns (the headings' deviations from the first keyframe's; 1 +- ``amplitude``) and of the walking speed (the walking
stretches' durations divided by 1 +- ``speed``); a recording's replay starts a drawn fraction (the phase over
``2 pi``) into its loop, drawn after the people's. The draw depends on the scenario's seed, the benchmark's seed and the
episode alone, so every mode of an episode sees the same motion.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..errors import ConfigError
from ..prediction import turned
from ..recording import Recording, load_recording
from ..yamlio import Fields, load_yaml


@dataclass(frozen=True)
class PoseKeyframe:
    """A person at time ``t``: the body's centre (or, without a body, the target's centre) at ``xy`` and the target
    facing ``yaw`` (rad, unwrapped). None: held from the keyframe before (the scene's pose before the first)."""

    t: float
    xy: Optional[tuple] = None
    yaw: Optional[float] = None


@dataclass(frozen=True)
class PersonMotion:
    """A moving person (or any target on a moving body, e.g. a monitor on a cart).

    ``yaw(t) = heading(t) + amplitude_rad * sin(2 pi t / period_s + phase_rad)``, ``heading`` interpolated linearly
    between the ``keyframes`` (``yaw0``, else the scene's heading of the target, without keyframes); the body's centre
    follows the keyframes' ``xy`` (the scene's position without them). With ``loop_s`` the keyframes repeat every
    ``loop_s`` seconds, interpolated from the last keyframe back to the first (its heading taken by whole turns
    nearest the last's) at ``loop_s``; ``time_shift_s`` moves the keyframed timeline (an episode's phase)."""

    target: str
    body: Optional[str] = None
    amplitude_rad: float = 1.0
    period_s: float = 12.0
    phase_rad: float = 0.0
    yaw0: Optional[float] = None  # default: the scene's initial yaw of the target
    keyframes: tuple = ()  # PoseKeyframe, increasing t
    loop_s: Optional[float] = None
    time_shift_s: float = 0.0


@dataclass(frozen=True)
class Keyframe:
    """An obstacle's pose at time ``t`` (yaw None: held)."""

    t: float
    center: np.ndarray
    yaw: Optional[float] = None


@dataclass(frozen=True)
class VariationRanges:
    """How much the episodes vary a person's motion (module docstring): the phase offset's range (rad) and the
    relative spreads of the period, the amplitude and the walking speed (uniform in 1 +- spread)."""

    phase_rad: float = 2.0 * math.pi
    period: float = 0.2
    amplitude: float = 0.15
    speed: float = 0.2


@dataclass(frozen=True)
class MotionVariation:
    """One episode's variation of one person's motion (:func:`vary`)."""

    phase_rad: float = 0.0
    period_scale: float = 1.0
    amplitude_scale: float = 1.0
    speed_scale: float = 1.0

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class RecordingSpec:
    """Bodies replayed from a recording (:mod:`psprm_core.recording`): the file, the bodies (() = every one) and,
    for bodies recorded in another frame than the scene's, that frame's name and pose in the scene frame."""

    file: str
    bodies: tuple = ()
    frame_name: str = ""
    frame_xyz: tuple = (0.0, 0.0, 0.0)
    frame_quat: tuple = (0.0, 0.0, 0.0, 1.0)

    @cached_property
    def recording(self) -> Recording:
        """The file's samples, read once per spec (every episode's :class:`~.scenario_world.World` replays them)."""
        return load_recording(self.file)


RECORDING_KEY = "<recording>"  # the variation entry of a scenario's recording (no target has this name)


@dataclass(frozen=True)
class Scenario:
    name: str
    scene: str
    targets: tuple
    start: dict
    goals: tuple
    planner: str = "neural-psprm-line"
    nodes: int = 3000
    seed: int = 0
    duration_s: float = 60.0
    control_dt: float = 0.1
    camera_fps: float = 4.0
    goal_tolerance: float = 0.1  # m (base) / rad (heading) to count as arrived
    people: tuple = ()  # PersonMotion
    obstacles: dict = field(default_factory=dict)  # name -> tuple of Keyframe
    goal_changes: tuple = ()  # ((t, goals), ...)
    variation: VariationRanges = field(default_factory=VariationRanges)
    description: str = ""
    source: str = ""
    recording: Optional[RecordingSpec] = None

    @property
    def target(self) -> str:
        """The first target kept in view (the only one of a single-target scenario)."""
        return self.targets[0]

    @property
    def person(self) -> Optional[PersonMotion]:
        """The first moving person, or None."""
        return self.people[0] if self.people else None


# ---- loading ------------------------------------------------------------------------------------------------------
def _list(f: Fields, key: str) -> list:
    v = f.raw(key, [])
    if not isinstance(v, list):
        raise f.error(key, "expected a list")
    return v


def _goal_spec(f: Fields, item, where: str):
    if isinstance(item, str):
        return item
    if isinstance(item, dict) and "base" in item:
        b = item["base"]
        if not (isinstance(b, list) and len(b) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                             and math.isfinite(x) for x in b)):
            raise ConfigError(f.source, where, "goal 'base' must be [x, y, theta] (finite numbers)")
        return tuple(float(x) for x in b)
    raise ConfigError(f.source, where, "a goal is a goal-region name or {base: [x, y, theta]}")


def _person(pf: Fields, default_amplitude: float) -> PersonMotion:
    pf.check_keys(["target", "body", "amplitude_rad", "period_s", "phase_rad", "yaw0", "keyframes", "loop_s"])
    frames = []
    for kf in pf.sub_list("keyframes", []):
        kf.check_keys(["t", "xy", "yaw"])
        t = kf.float("t", lo=0.0)
        if frames and t <= frames[-1].t:
            raise kf.error("t", f"keyframe times must increase (after {frames[-1].t:g})")
        frames.append(PoseKeyframe(t, kf.vec("xy", 2) if kf.has("xy") else None,
                                   kf.float("yaw") if kf.has("yaw") else None))
    loop = pf.float("loop_s", lo=1e-3) if pf.has("loop_s") else None
    if loop is not None:
        if not frames:
            raise pf.error("loop_s", "repeats keyframes: give 'keyframes' too")
        if loop <= frames[-1].t:
            raise pf.error("loop_s", f"must be after the last keyframe ({frames[-1].t:g} s)")
    return PersonMotion(target=pf.str("target"), body=pf.str("body") if pf.has("body") else None,
                        amplitude_rad=pf.float("amplitude_rad", default_amplitude),
                        period_s=pf.float("period_s", 12.0, lo=1e-3), phase_rad=pf.float("phase_rad", 0.0),
                        yaw0=pf.float("yaw0") if pf.has("yaw0") else None, keyframes=tuple(frames), loop_s=loop)


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario YAML (errors name the file and the field). Names of the scene (targets,
    obstacles, goal regions) are checked when the scenario meets its scene (:class:`World`)."""
    f = Fields(load_yaml(path), str(path))
    f.check_keys(["name", "description", "scene", "planner", "nodes", "seed", "target", "targets", "start", "goals",
                  "duration_s", "control_dt", "camera_fps", "goal_tolerance", "person", "people", "variation",
                  "obstacles", "goal_changes", "recording"])
    goals = _list(f, "goals")
    if not goals:
        raise ConfigError(str(path), "goals", "at least one goal is needed")
    if f.has("target") == f.has("targets"):
        raise ConfigError(str(path), "target", "give either 'target' (one name) or 'targets' (a list of names)")
    if f.has("target"):
        targets = (f.str("target"),)
    else:
        raw = _list(f, "targets")
        if not raw or not all(isinstance(t, str) for t in raw) or len(set(raw)) != len(raw):
            raise ConfigError(str(path), "targets", "expected a list of distinct target names")
        targets = tuple(raw)
    people = []
    if f.has("person"):
        people.append(_person(f.sub("person"), 1.0))
    for pf in f.sub_list("people", []):
        people.append(_person(pf, 0.0))
    names = [p.target for p in people] + [p.body for p in people if p.body]
    if len(set(names)) != len(names):
        raise ConfigError(str(path), "people", "a target or body moves with one person only")
    variation = VariationRanges()
    if f.has("variation"):
        vf = f.sub("variation")
        vf.check_keys(["phase_rad", "period", "amplitude", "speed"])
        variation = VariationRanges(phase_rad=vf.float("phase_rad", variation.phase_rad, lo=0.0, hi=2 * math.pi),
                                    period=vf.float("period", variation.period, lo=0.0, hi=0.9),
                                    amplitude=vf.float("amplitude", variation.amplitude, lo=0.0, hi=0.9),
                                    speed=vf.float("speed", variation.speed, lo=0.0, hi=0.9))
    obstacles = {}
    if f.has("obstacles"):
        of = f.sub("obstacles")
        for name in of.data:
            if name in names:
                raise ConfigError(str(path), f"obstacles.{name}", "moves with a person already")
            frames = []
            for i, kf in enumerate(_list(of, name)):
                where = f"obstacles.{name}[{i}]"
                if not isinstance(kf, dict) or "t" not in kf or "center" not in kf:
                    raise ConfigError(str(path), where, "a keyframe needs 't' and 'center'")
                c = np.asarray(kf["center"], dtype=float)
                if c.shape != (3,) or not np.isfinite(c).all():
                    raise ConfigError(str(path), where + ".center", "must be 3 finite numbers")
                frames.append(Keyframe(float(kf["t"]), c, None if kf.get("yaw") is None else float(kf["yaw"])))
            if not frames:
                raise ConfigError(str(path), f"obstacles.{name}", "at least one keyframe is needed")
            obstacles[name] = tuple(sorted(frames, key=lambda k: k.t))
    changes = []
    for i, ch in enumerate(_list(f, "goal_changes")):
        if not isinstance(ch, dict) or "t" not in ch or "goals" not in ch:
            raise ConfigError(str(path), f"goal_changes[{i}]", "needs 't' and 'goals'")
        if not isinstance(ch["goals"], list) or not ch["goals"]:
            raise ConfigError(str(path), f"goal_changes[{i}].goals", "expected a non-empty list of goals")
        changes.append((float(ch["t"]), tuple(_goal_spec(f, g, f"goal_changes[{i}].goals") for g in ch["goals"])))
    recording = None
    if f.has("recording"):
        rf = f.sub("recording")
        rf.check_keys(["file", "bodies", "frame"])
        bodies = _list(rf, "bodies")
        if not all(isinstance(b, str) for b in bodies) or len(set(bodies)) != len(bodies):
            raise rf.error("bodies", "expected a list of distinct body names")
        if set(bodies) & set(names):
            raise rf.error("bodies", "a recorded body cannot also move with a person")
        file = Path(rf.str("file"))
        if not file.is_absolute():
            file = Path(path).parent / file
        frame = {}
        if rf.has("frame"):
            ff = rf.sub("frame")
            ff.check_keys(["name", "xyz", "quat"])
            quat = ff.vec("quat", 4, (0.0, 0.0, 0.0, 1.0))
            if not np.linalg.norm(quat) > 1e-9:
                raise ff.error("quat", "must be a non-zero quaternion (x, y, z, w)")
            frame = {"frame_name": ff.str("name").strip("/"), "frame_xyz": ff.vec("xyz", 3, (0.0, 0.0, 0.0)),
                     "frame_quat": quat}
        recording = RecordingSpec(str(file), tuple(bodies), **frame)
    start = f.data.get("start")
    if not isinstance(start, dict):
        raise ConfigError(str(path), "start", "expected a mapping of planning-joint values")
    return Scenario(
        name=f.str("name"), scene=f.str("scene"), targets=targets, start=dict(start),
        goals=tuple(_goal_spec(f, g, f"goals[{i}]") for i, g in enumerate(goals)),
        planner=f.str("planner", "neural-psprm-line"), nodes=f.int("nodes", 3000, lo=2), seed=f.int("seed", 0),
        duration_s=f.float("duration_s", 60.0, lo=0.1), control_dt=f.float("control_dt", 0.1, lo=1e-3),
        camera_fps=f.float("camera_fps", 4.0, lo=0.01), goal_tolerance=f.float("goal_tolerance", 0.1, lo=1e-4),
        people=tuple(people), obstacles=obstacles, goal_changes=tuple(sorted(changes, key=lambda c: c[0])),
        variation=variation, description=f.str("description", ""), source=str(path), recording=recording)


# ---- episode variation ----------------------------------------------------------------------------------------------
def draw_variation(scenario: Scenario, episode: int, seed: int = 0) -> dict:
    """``{target: MotionVariation}`` of episode ``episode`` (module docstring): drawn from the scenario's name and
    seed, ``seed`` (the benchmark's) and the episode alone, person by person in the scenario's order, then the
    recording's start (:data:`RECORDING_KEY`)."""
    ss = np.random.SeedSequence([int(scenario.seed), int(seed), int(episode), zlib.crc32(scenario.name.encode())])
    rng = np.random.default_rng(ss)
    r = scenario.variation
    out = {}
    for p in scenario.people:
        out[p.target] = MotionVariation(phase_rad=float(rng.uniform(0.0, r.phase_rad)),
                                        period_scale=float(rng.uniform(1 - r.period, 1 + r.period)),
                                        amplitude_scale=float(rng.uniform(1 - r.amplitude, 1 + r.amplitude)),
                                        speed_scale=float(rng.uniform(1 - r.speed, 1 + r.speed)))
    if scenario.recording is not None:
        out[RECORDING_KEY] = MotionVariation(phase_rad=float(rng.uniform(0.0, r.phase_rad)))
    return out


def vary(motion: PersonMotion, v: MotionVariation, scene) -> PersonMotion:
    """``motion`` as one episode's variation ``v`` changes it (module docstring): the turn's phase, period and
    amplitude; the keyframes retimed (walking stretches, where the position changes, divided by the speed scale;
    the others multiplied by the period scale), their headings' deviations from the first keyframe's scaled by the
    amplitude scale; a looped timeline shifted by the phase's share of a loop."""
    frames = _resolved_keyframes(motion, scene)
    out = dataclasses.replace(motion, amplitude_rad=motion.amplitude_rad * v.amplitude_scale,
                              period_s=motion.period_s * v.period_scale, phase_rad=motion.phase_rad + v.phase_rad)
    if not motion.keyframes:
        return out

    def stretch(a: PoseKeyframe, b: PoseKeyframe, dt: float) -> float:
        walking = np.linalg.norm(np.subtract(b.xy, a.xy)) > 1e-9
        return dt / v.speed_scale if walking else dt * v.period_scale

    times = [frames[0].t * v.period_scale]
    for a, b in zip(frames[:-1], frames[1:]):
        times.append(times[-1] + stretch(a, b, b.t - a.t))
    yaw_ref = frames[0].yaw
    new = tuple(PoseKeyframe(t, k.xy, yaw_ref + v.amplitude_scale * (k.yaw - yaw_ref)) for t, k in zip(times, frames))
    loop = None
    if motion.loop_s is not None:
        loop = times[-1] + stretch(frames[-1], frames[0], motion.loop_s - frames[-1].t)
    shift = (v.phase_rad / (2 * math.pi)) * loop if loop is not None else 0.0
    return dataclasses.replace(out, keyframes=new, loop_s=loop, time_shift_s=motion.time_shift_s + shift)


# ---- world timeline -------------------------------------------------------------------------------------------------
def _heading(rotation: np.ndarray) -> float:
    return math.atan2(rotation[1, 0], rotation[0, 0])


def _pivot(scene, motion: PersonMotion) -> np.ndarray:
    """The point a person turns about and walks with: the body's centre, else the target's."""
    return (scene.obstacle(motion.body) if motion.body else scene.target(motion.target)).center


def _resolved_keyframes(motion: PersonMotion, scene) -> tuple:
    """The keyframes with every field filled in (held from the one before; the scene's pose, or ``yaw0``, before the
    first)."""
    xy = tuple(float(x) for x in _pivot(scene, motion)[:2])
    yaw = motion.yaw0 if motion.yaw0 is not None else _heading(scene.target(motion.target).rotation)
    out = []
    for k in motion.keyframes:
        xy = tuple(k.xy) if k.xy is not None else xy
        yaw = float(k.yaw) if k.yaw is not None else yaw
        out.append(PoseKeyframe(float(k.t), xy, yaw))
    return tuple(out)


def keyframed_pose(motion: PersonMotion, scene, t: float) -> tuple:
    """(xy (2,), heading) of ``motion``'s keyframed timeline at time ``t`` (without the sinusoidal turn)."""
    frames = _resolved_keyframes(motion, scene)
    if not frames:
        return _pivot(scene, motion)[:2].copy(), (motion.yaw0 if motion.yaw0 is not None
                                                  else _heading(scene.target(motion.target).rotation))
    tau = t + motion.time_shift_s
    T = np.array([k.t for k in frames])
    XY = np.array([k.xy for k in frames], float)
    Y = np.array([k.yaw for k in frames], float)
    if motion.loop_s is not None:
        first = Y[0] + 2 * math.pi * round((Y[-1] - Y[0]) / (2 * math.pi))  # the first heading nearest the last's
        T = np.append(T, motion.loop_s)
        XY = np.vstack([XY, XY[:1]])
        Y = np.append(Y, first)
        # the timeline repeats every loop_s; a loop that ends whole turns away from where it began carries them
        # into the next loop, so the heading stays continuous
        k = math.floor(tau / motion.loop_s)
        tau -= k * motion.loop_s
        base = k * (Y[-1] - Y[0])
    else:
        base = 0.0
    xy = np.array([np.interp(tau, T, XY[:, 0]), np.interp(tau, T, XY[:, 1])])
    return xy, float(np.interp(tau, T, Y)) + base


def person_pose(scene, motion: PersonMotion, yaw: float, xy: Optional[Sequence[float]] = None) -> dict:
    """Poses of the person's target (and body obstacle) turned to heading ``yaw`` about the body's vertical axis, the
    body's centre (the target's without a body) moved to ``xy`` (default: where the scene has it).

    The target keeps its offset from the body centre (rotated with the body) and its roll and pitch. Returns
    ``{"target": (center, quat), "body": (center, quat) or None}``."""
    face0 = scene.target(motion.target)
    body0 = scene.obstacle(motion.body) if motion.body else None
    pivot0 = body0.center if body0 is not None else face0.center
    pivot = pivot0.copy() if xy is None else np.array([float(xy[0]), float(xy[1]), pivot0[2]])
    d = yaw - _heading(face0.rotation)
    c, s = math.cos(d), math.sin(d)
    off = face0.center - pivot0
    face_c = pivot + np.array([c * off[0] - s * off[1], s * off[0] + c * off[1], off[2]])
    out = {"target": (face_c, turned(face0.quat, d)), "body": None}
    if body0 is not None:
        out["body"] = (pivot, turned(body0.quat, d))
    return out
