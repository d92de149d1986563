"""Baseline 6, RL-based goal-conditioned active perception (``rl-ppo``; paper Sec. "Evaluated Methods").

A policy is trained with PPO (Schulman et al. 2017; the ``stable-baselines3`` implementation) on the
:class:`~psprm_core.baselines.rl_env.ActivePerceptionEnv` of the planner's scene, robot and targets: actor and critic
MLPs with hidden layers 256-256-128, learning rate 3e-4, rollouts of 512 steps, minibatches of 64, 1e5 environment
steps (:class:`PPOSettings`). The observation holds the configuration, the goal, the target position and the episode
progress; the reward is the geometric perception proxy, the motion cost, the goal progress, a collision penalty
for rejected (invalid) actions and a goal bonus (see :mod:`.rl_env`).

The shipped settings (``config/planners/baselines.yaml``) go beyond those base values where that was measured to
help (home, ``tv``, 50 bench problems, 1e5 steps: 42 % of the goals reached against 2-3 % with the base values): the 512-step rollout is split over 8 environments stepped in turn (64 steps each, more episodes
per update), the initial action standard deviation is 0.37, the observation carries a 16-beam range scan, whether the
last action was rejected and the goal's bearing, the goal progress counts 0.25 m per radian of heading error towards
the goal, a rejected action costs 0.1 and the final motion to the goal is tried from 0.4 m. Optional, off, and
without a measured gain: observation/reward normalisation (``VecNormalize``) and a distance curriculum (2-3e4-step
runs), the geodesic progress and a rejection counter (``streak_cap``) (1e5-step runs).

``prepare()`` trains the policy (its wall time is the planner's preprocessing time) or loads it from
``~/.cache/psprm/rl/`` (keyed by a hash of the scene geometry, targets, robot, settings and seed; the recorded
training time is reported again). ``plan()`` rolls the policy out deterministically for at most ``max_steps`` (200)
steps from the start towards the nearest valid goal and returns the executed motion; when the goal is not reached,
``success`` is False and the reason says how far the robot ended up.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..errors import InputError
from ..paths import cache_dir
from ..planning.results import Failure
from .base import PlanningContext, failure, resolve_settings
from .rl_env import ActivePerceptionEnv, ENV_VERSION
from .rl_settings import PPOSettings
from .trajopt import index_of_goal

log = logging.getLogger(__name__)


_NOT_TRAINING = ("timeout_s", "cache", "threads", "checkpoint_every")  # settings that do not change the trained policy


def _ProgressLog(total: int, checkpoint_every: int = 0, checkpoint_path: Optional[Path] = None):
    """An SB3 callback that logs the training progress after every rollout (timesteps, wall time, episodes) and,
    with ``checkpoint_every``, saves the policy so far (plus a JSON with its step count and wall time)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class ProgressLog(BaseCallback):
        def _on_training_start(self) -> None:
            self.t0 = time.perf_counter()
            self.episodes = self.successes = 0
            self.next_checkpoint = checkpoint_every

        def _on_step(self) -> bool:
            for done, info in zip(self.locals.get("dones", []), self.locals.get("infos", [])):
                if done:
                    self.episodes += 1
                    self.successes += bool(info.get("success"))
            return True

        def _on_rollout_end(self) -> None:
            el = time.perf_counter() - self.t0
            n = self.model.num_timesteps
            log.info("PPO %d/%d steps, %.0f s (%.1f ms/step), %d episodes, %d reached the goal", n, total, el,
                     1e3 * el / max(n, 1), self.episodes, self.successes)
            if checkpoint_every > 0 and checkpoint_path is not None and n >= self.next_checkpoint:
                self.model.save(str(checkpoint_path))
                checkpoint_path.with_suffix(".json").write_text(json.dumps({"train_s": el, "timesteps": n}))
                self.next_checkpoint = n + checkpoint_every

    return ProgressLog()


def _obs_stats_path(path: Path) -> Path:
    return path.with_name(path.stem + ".obs_stats.npz")


def _load_obs_stats(path: Path) -> dict:
    """The observation statistics saved next to a cached policy (``normalize_obs``); raises OSError if missing."""
    with np.load(_obs_stats_path(path)) as z:
        return {"mean": z["mean"].copy(), "var": z["var"].copy(), "clip": float(z["clip"]),
                "epsilon": float(z["epsilon"])}


def rl_cache_dir() -> Path:
    d = cache_dir() / "rl"
    d.mkdir(parents=True, exist_ok=True)
    return d


class PPOPlanner:
    """Goal-conditioned active-perception policy trained with PPO (see the module docstring).

    Parameters
    ----------
    name, scene, targets, robot, seed : as for every benchmark planner.
    settings : PPOSettings, optional
        Default: sections ``common`` and ``rl_ppo`` of ``config/planners/baselines.yaml``.
    **overrides : :class:`PPOSettings` fields (``total_timesteps=...``) applied on top.
    """

    section = "rl_ppo"

    def __init__(self, name: str = "rl-ppo", scene=None, targets: Sequence[str] = (), robot=None, seed: int = 0,
                 settings: Optional[PPOSettings] = None, **overrides):
        if scene is None or not targets:
            raise InputError("PPOPlanner needs a scene and at least one target")
        self.name = name
        self.settings = settings = resolve_settings(PPOSettings, self.section, settings, seed=seed, **overrides)
        self.ctx = PlanningContext(scene, targets, robot=robot, resolution=settings.resolution)
        self.scene, self.targets, self.robot = scene, list(targets), self.ctx.robot
        self.model = None
        self.obs_stats: Optional[dict] = None  # observation mean / var of VecNormalize (``normalize_obs``)
        self.info: dict = {}
        self._env = None

    # ---- environment and cache ----------------------------------------------------------------------------------
    def make_env(self, problems: Optional[list] = None, seed_offset: int = 0):
        """A fresh :class:`~psprm_core.baselines.rl_env.ActivePerceptionEnv` for this planner (episode seed
        ``settings.seed + seed_offset``)."""
        return ActivePerceptionEnv(self.scene, self.targets, settings=self.settings, problems=problems,
                                   seed=self.settings.seed + seed_offset, context=self.ctx)

    def training_env(self):
        """The (vectorised) training environment: ``n_envs`` environments on one problem pool (generated here,
        part of the preprocessing), wrapped in ``VecNormalize`` with ``normalize_obs`` / ``normalize_reward``."""
        from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

        s = self.settings
        first = self.make_env()
        envs = [first] + [self.make_env(problems=first.problems, seed_offset=1000 * i) for i in range(1, s.n_envs)]
        if s.progress_metric == "geodesic":
            for e in envs[1:]:
                e._grid_cache = first._grid()  # one free-space grid for all
        venv = DummyVecEnv([lambda e=e: e for e in envs])
        if s.normalize_obs or s.normalize_reward:
            venv = VecNormalize(venv, norm_obs=s.normalize_obs, norm_reward=s.normalize_reward, clip_obs=10.0,
                                gamma=s.gamma)
        return venv

    def fingerprint(self) -> str:
        """Hash of what the policy depends on: robot, scene geometry, targets, settings, seed, library versions and the
        environment version (:data:`~psprm_core.baselines.rl_env.ENV_VERSION`)."""
        import stable_baselines3

        h = hashlib.sha256(self.robot.hash().encode())
        h.update(f"env{ENV_VERSION}".encode())
        for b in self.scene.collision_boxes():
            h.update(np.concatenate([b.center, b.size, b.quat]).astype(np.float64).tobytes())
        h.update(np.asarray(self.scene.workspace, float).tobytes())
        for t in self.targets:
            tg = self.scene.target(t)
            h.update(t.encode())
            h.update(np.concatenate([tg.center, tg.quat, tg.size]).astype(np.float64).tobytes())
        trained = {k: v for k, v in dataclasses.asdict(self.settings).items() if k not in _NOT_TRAINING}
        h.update(json.dumps(trained, sort_keys=True).encode())
        h.update(stable_baselines3.__version__.encode())
        return h.hexdigest()[:20]

    def cache_path(self) -> Path:
        return rl_cache_dir() / f"ppo_{self.scene.name}_{self.fingerprint()}.zip"

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        """The policy's input for an environment observation: with ``normalize_obs``, standardised by the running
        statistics of training (as ``VecNormalize.normalize_obs``), else unchanged."""
        st = self.obs_stats
        if st is None:
            return obs
        z = (obs - st["mean"]) / np.sqrt(st["var"] + st["epsilon"])
        return np.clip(z, -st["clip"], st["clip"]).astype(np.float32)

    # ---- interface ------------------------------------------------------------------------------------------------
    def prepare(self) -> dict:
        """Train the policy (or load the cached one). Returns ``preprocess_s`` (the training wall time, also when
        the policy comes from the cache), ``cached``, ``load_s``, ``timesteps`` and ``path``."""
        from stable_baselines3 import PPO

        s = self.settings
        path = self.cache_path()
        meta_path = path.with_suffix(".json")
        if s.cache and path.is_file() and meta_path.is_file():
            t0 = time.perf_counter()
            try:
                self.model = PPO.load(str(path), device="cpu")
                meta = json.loads(meta_path.read_text())
                self.obs_stats = _load_obs_stats(path) if s.normalize_obs else None
                self.info = {"preprocess_s": float(meta["train_s"]), "cached": True,
                             "load_s": time.perf_counter() - t0, "timesteps": int(meta["timesteps"]),
                             "path": str(path)}
                log.info("loaded PPO policy %s (trained %.1f s)", path, meta["train_s"])
                return dict(self.info)
            except (OSError, ValueError, KeyError, RuntimeError) as exc:  # unreadable cache: train again
                log.warning("cannot load cached PPO policy %s (%s); training a new one", path, exc)
                self.model = None
        threads = torch.get_num_threads()
        torch.set_num_threads(max(1, s.threads))
        try:
            t0 = time.perf_counter()
            venv = self.training_env()
            layers = s.layers()
            self.model = PPO("MlpPolicy", venv, learning_rate=s.learning_rate, n_steps=s.n_steps // s.n_envs,
                             batch_size=s.batch_size, n_epochs=s.n_epochs, gamma=s.gamma, gae_lambda=s.gae_lambda,
                             ent_coef=s.ent_coef, policy_kwargs={"net_arch": {"pi": layers, "vf": layers},
                                                             "log_std_init": s.log_std_init},
                             seed=s.seed, device="cpu", verbose=0)
            partial = path.with_name(path.stem + ".partial.zip")
            self.model.learn(total_timesteps=s.total_timesteps,
                             callback=_ProgressLog(s.total_timesteps, s.checkpoint_every, partial))
            train_s = time.perf_counter() - t0
            self.obs_stats = None
            if s.normalize_obs:
                self.obs_stats = {"mean": np.asarray(venv.obs_rms.mean, float).copy(),
                                  "var": np.asarray(venv.obs_rms.var, float).copy(),
                                  "clip": float(venv.clip_obs), "epsilon": float(venv.epsilon)}
        finally:
            torch.set_num_threads(threads)
        self.info = {"preprocess_s": train_s, "cached": False, "load_s": 0.0,
                     "timesteps": int(self.model.num_timesteps), "path": str(path) if s.cache else None}
        if s.cache:
            self.model.save(str(path))
            if self.obs_stats is not None:
                np.savez(_obs_stats_path(path), **self.obs_stats)
            meta_path.write_text(json.dumps({"train_s": train_s, "timesteps": int(self.model.num_timesteps),
                                             "settings": dataclasses.asdict(s), "scene": self.scene.name,
                                             "targets": self.targets, "robot": self.robot.name}, indent=1))
        log.info("trained PPO for %d steps in %.1f s", self.model.num_timesteps, train_s)
        return dict(self.info)

    def plan(self, start: np.ndarray, goals: np.ndarray, timeout_s: Optional[float] = None):
        """Roll the policy out deterministically (at most ``max_steps`` steps) towards the nearest valid goal.

        ``dense`` is the executed motion (every step's differential-drive motion, densified and collision-checked
        again by :meth:`PlanningContext.execute`).
        """
        t0 = time.perf_counter()
        if self.model is None:
            return failure("policy not trained (call prepare() first)", t0, Failure.NOT_BUILT)
        timeout_s = self.settings.timeout_s if timeout_s is None else float(timeout_s)
        given = goals
        start, goals, fail = self.ctx.check_problem(start, goals)
        if fail is not None:
            return fail
        gi = int(np.argmin(np.linalg.norm(goals[:, :2] - start[:2], axis=1)))
        goal = goals[gi]
        if self._env is None:
            self._env = self.make_env(problems=[])
        env = self._env
        obs, _ = env.reset(options={"start": start, "goal": goal})
        rejected, steps = 0, 0
        for _ in range(self.settings.max_steps):
            if time.perf_counter() - t0 > timeout_s:
                return failure(f"timeout after {steps} policy steps", t0, Failure.TIMEOUT)
            action, _ = self.model.predict(self.normalize(obs), deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            steps += 1
            rejected += info["rejected"]
            if terminated or truncated:
                break
        path = np.asarray(env.path)
        if not env.reached:
            return failure(f"policy did not reach the goal within {steps} steps (base {env.goal_distance(env.q):.2f} m "
                           f"from the goal, {rejected} actions rejected)", t0)
        res = self.ctx.execute(path, t0=t0)
        if not res.success:
            res.reason = f"executed policy motion rejected: {res.reason}"
            return res
        res.goal_index = index_of_goal(given, goal)
        self.last_rollout = {"steps": steps, "rejected": rejected}
        return res
