"""Settings of the RL baseline (``rl_ppo:`` in ``config/planners/baselines.yaml``), shared by the PPO trainer
(:mod:`.rl_ppo`) and its environment (:mod:`.rl_env`)."""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import ConfigError


@dataclass(frozen=True)
class PPOSettings:
    """Settings of the RL baseline (section ``rl_ppo:`` of ``config/planners/baselines.yaml``)."""

    # PPO (stable-baselines3)
    total_timesteps: int = 100_000
    learning_rate: float = 3e-4
    n_steps: int = 512  # rollout length per update (transitions, over all n_envs environments)
    n_envs: int = 1  # environments stepped in turn (one process); each contributes n_steps / n_envs per rollout
    batch_size: int = 64
    n_epochs: int = 10
    gamma: float = 0.99
    gae_lambda: float = 0.95
    ent_coef: float = 0.0
    net_arch: str = "256-256-128"  # hidden layers of both the actor and the critic
    log_std_init: float = 0.0  # initial log standard deviation of the Gaussian actions (sb3 default 0: std 1)
    threads: int = 1  # torch threads while training
    cache: bool = True  # save / load the trained policy under ~/.cache/psprm/rl
    checkpoint_every: int = 0  # > 0: also save the policy so far every this many steps (``<cache>.partial.zip``)
    normalize_obs: bool = False  # running mean/std observation normalisation (sb3 VecNormalize), saved with the policy
    normalize_reward: bool = False  # VecNormalize's return-based reward scaling while training
    # environment
    max_steps: int = 200  # episode length in training and the rollout limit of plan()
    step_forward: float = 0.1  # metres of base travel per step at |action| = 1
    step_turn: float = 0.3  # radians of base rotation per step at |action| = 1
    step_joint: float = 0.15  # camera joint change per step at |action| = 1
    goal_tolerance: float = 0.2  # base distance (m) from which the final motion to the goal is attempted
    goal_bearing: bool = False  # extend the observation by the goal's bearing (sin, cos) and distance from the base
    scan_beams: int = 0  # > 0: extend the observation by a range scan with this many beams + "last action rejected"
    scan_range: float = 3.0  # m
    streak_cap: int = 0  # > 0: the scan's last feature counts consecutive rejected actions (/ streak_cap, <= 1)
    scan_height: float = 0.2  # m above the floor
    w_perception: float = 0.05  # x geometric perception score in [0, 1], per step
    perception_offset: float = 0.0  # subtracted from the score (1.0: the paper's perception cost -(1 - p) per step)
    w_motion: float = 0.05  # x motion cost of the step
    w_progress: float = 1.0  # x decrease of the base's distance to the goal (m)
    progress_metric: str = "euclidean"  # that distance: "euclidean" (straight line) or "geodesic" (around furniture)
    geodesic_cell: float = 0.1  # m, grid cell of the geodesic distance
    w_heading: float = 0.0  # m per rad of heading error towards the goal added to that distance (0: off)
    collision_penalty: float = 0.5  # rejected (invalid) action
    goal_bonus: float = 10.0
    problems: int = 256  # random (start, goal) pairs episodes are drawn from
    curriculum_steps: int = 0  # > 0: start-goal distance of training episodes capped, the cap growing over these steps
    curriculum_start: float = 1.0  # m, the cap at the first step
    min_problem_distance: float = 1.0
    resolution: float = 0.05  # collision-check spacing along a step (motion-cost units)
    timeout_s: float = 60.0
    seed: int = 0

    def layers(self) -> list:
        try:
            out = [int(x) for x in self.net_arch.replace(",", "-").split("-") if x.strip()]
        except ValueError:
            out = []
        if not out or min(out) < 1:
            raise ConfigError("rl_ppo settings", "net_arch",
                              f"expected sizes like '256-256-128', got '{self.net_arch}'")
        return out

    def validate(self, source: str = "rl_ppo settings") -> None:
        self.layers()
        if self.n_steps < 2 or self.batch_size < 2 or self.total_timesteps < 1 or self.max_steps < 1:
            raise ConfigError(source, "n_steps", "n_steps, batch_size >= 2, total_timesteps, max_steps >= 1")
        if self.n_envs < 1 or self.n_steps % self.n_envs or self.n_steps // self.n_envs < 2:
            raise ConfigError(source, "n_envs", f"n_envs >= 1 must divide n_steps ({self.n_steps}) into rollouts of >= 2")
        if self.progress_metric not in ("euclidean", "geodesic"):
            raise ConfigError(source, "progress_metric",
                              f"expected 'euclidean' or 'geodesic', got '{self.progress_metric}'")
        if self.curriculum_steps < 0 or not self.curriculum_start > 0:
            raise ConfigError(source, "curriculum_steps", "curriculum_steps >= 0 and curriculum_start > 0")
        if not self.geodesic_cell > 0:
            raise ConfigError(source, "geodesic_cell", f"must be > 0, got {self.geodesic_cell}")
