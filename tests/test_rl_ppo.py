"""RL baseline: the gymnasium environment passes both env checkers, rejects invalid actions without changing the
state, its reward terms have the right signs; a tiny stable-baselines3 PPO training runs, is cached, reloads and
rolls out deterministically within 200 steps."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from psprm_core.baselines import rl_ppo
from psprm_core.baselines.rl_ppo import PPOPlanner
from psprm_core.paths import resolve_named
from psprm_core.scene import load_scene

TINY = {"total_timesteps": 512, "n_epochs": 1, "problems": 32}  # one rollout of 512 steps


@pytest.fixture(scope="module")
def planner(load_robot):
    scene = load_scene(resolve_named("scene", "home"))
    return PPOPlanner("rl-ppo", scene, ["cup"], robot=load_robot("stretch2"), **TINY)


@pytest.fixture()
def env(planner):
    return planner.make_env()


def _config(p, x, y, th):
    q = p.robot.configuration({"base_x": x, "base_y": y, "base_theta": th})
    return p.ctx.aim(q[None])[0][0]


def test_env_passes_the_checkers(env):
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    sb3_check(env, warn=True)
    gym_check(env, skip_render_check=True)
    obs, _ = env.reset(seed=3)
    assert env.observation_space.contains(obs)
    assert env.action_space.shape == (4,)  # forward, turn, head pan, head tilt


def test_optional_range_scan(planner):
    from psprm_core.baselines.rl_env import ActivePerceptionEnv
    from stable_baselines3.common.env_checker import check_env

    settings = dataclasses.replace(planner.settings, scan_beams=8)
    env = ActivePerceptionEnv(planner.scene, planner.targets, settings=settings, context=planner.ctx)
    no_scan = ActivePerceptionEnv(planner.scene, planner.targets, context=planner.ctx,
                                  settings=dataclasses.replace(planner.settings, scan_beams=0))
    q = planner.robot.configuration({"base_x": 1.0, "base_y": 1.0, "base_theta": 0.0})
    r = env.scan(q)  # beams every 45 deg from the heading (east)
    assert r[4] == pytest.approx(1.0) and r[6] == pytest.approx(1.0)  # west and south walls
    assert r[2] == pytest.approx(3.625 - 1.0)  # the shelf to the north
    assert r[0] == settings.scan_range  # nothing within range to the east
    check_env(env)
    assert env.observation_space.shape[0] == no_scan.observation_space.shape[0] + 9


def test_invalid_action_is_rejected_and_leaves_the_state_unchanged(planner, env):
    start = _config(planner, 0.6, 3.0, np.pi)  # facing the west wall, 0.6 m from it
    goal = _config(planner, 2.0, 1.0, 0.0)
    env.reset(options={"start": start, "goal": goal})
    forward = np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32)
    for _ in range(10):
        before, n = env.q.copy(), len(env.path)
        obs, reward, terminated, truncated, info = env.step(forward)
        if info["rejected"]:
            break
    assert info["rejected"], "driving into the wall was never rejected"
    assert np.array_equal(env.q, before) and len(env.path) == n
    assert info["terms"]["collision"] < 0 and reward < 0 and not terminated
    assert env.observation_space.contains(obs)



def test_rejection_streak_in_the_observation(planner):
    """With streak_cap the scan's last feature counts consecutive rejected actions (a bool without it)."""
    from psprm_core.baselines.rl_env import ActivePerceptionEnv

    start, goal = _config(planner, 0.6, 3.0, np.pi), _config(planner, 2.0, 1.0, 0.0)
    forward = np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32)
    seen = {}
    for cap in (0, 4):
        env = ActivePerceptionEnv(planner.scene, planner.targets, context=planner.ctx,
                                  settings=dataclasses.replace(planner.settings, scan_beams=8, streak_cap=cap))
        env.reset(options={"start": start, "goal": goal})
        flags = []
        for _ in range(20):
            obs, _, _, _, info = env.step(forward)
            if info["rejected"]:
                flags.append(float(obs[-1]))
        seen[cap] = flags
    assert len(seen[0]) >= 6 and set(seen[0]) == {1.0}
    assert seen[4][:5] == pytest.approx([0.25, 0.5, 0.75, 1.0, 1.0])
    env.step(np.array([-1.0, 0.0, 0.0, 0.0], dtype=np.float32))  # backing off is accepted: the count restarts
    assert env.rejected_streak == 0 and env._obs()[-1] == 0.0


def test_reward_terms_have_the_right_signs(planner, env):
    start, goal = _config(planner, 1.0, 1.0, 0.0), _config(planner, 2.5, 1.0, 0.0)
    env.reset(options={"start": start, "goal": goal})
    _, r_fwd, _, _, info = env.step(np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32))  # towards the goal
    t = info["terms"]
    assert not info["rejected"]
    assert t["progress"] > 0.09 and t["motion"] < 0 and t["perception"] >= 0
    assert r_fwd == pytest.approx(sum(t.values()))
    env.reset(options={"start": start, "goal": goal})
    _, r_back, _, _, info = env.step(np.array([-1.0, 0.0, 0.0, 0.0], dtype=np.float32))  # away from it
    assert info["terms"]["progress"] < 0 and r_back < r_fwd
    # as a perception cost (offset 1) the term is <= 0 and still grows with the score
    from psprm_core.baselines.rl_env import ActivePerceptionEnv

    cost_env = ActivePerceptionEnv(planner.scene, planner.targets, context=planner.ctx,
                                   settings=dataclasses.replace(planner.settings, perception_offset=1.0))
    cost_env.reset(options={"start": start, "goal": goal})
    _, _, _, _, info = cost_env.step(np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32))
    assert info["terms"]["perception"] == pytest.approx(t["perception"] - planner.settings.w_perception)
    # looking at the cup is worth more than looking away from it
    look_away = start.copy()
    look_away[planner.robot.index("joint_head_pan")] += 1.5
    assert env.score(start) > env.score(look_away)
    # reaching the goal ends the episode with the bonus, exactly at the goal configuration
    near = _config(planner, 2.35, 1.0, 0.0)
    env.reset(options={"start": near, "goal": goal})
    _, r, terminated, _, info = env.step(np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32))
    assert terminated and info["success"] and info["terms"]["goal"] > 0 and r > 1.0
    assert np.array_equal(env.q, goal)


def test_tiny_training_saves_reloads_and_rolls_out(planner, tmp_path, monkeypatch):
    monkeypatch.setattr(rl_ppo, "rl_cache_dir", lambda: tmp_path)
    t0 = time.perf_counter()
    info = planner.prepare()
    wall = time.perf_counter() - t0
    assert not info["cached"] and info["timesteps"] >= TINY["total_timesteps"]
    assert 0.5 * wall <= info["preprocess_s"] <= wall  # the training is the preparation's time, on this clock
    assert planner.cache_path().is_file()
    m = planner.model
    assert (m.n_steps * m.n_envs, m.batch_size, m.learning_rate) == (512, 64, 3e-4)  # rollout 512 in all
    assert [l.out_features for l in m.policy.mlp_extractor.policy_net if hasattr(l, "out_features")] == [256, 256, 128]
    again = PPOPlanner("rl-ppo", planner.scene, planner.targets, robot=planner.robot, **TINY)
    info2 = again.prepare()
    assert info2["cached"] and info2["preprocess_s"] == pytest.approx(info["preprocess_s"])
    obs = planner.make_env().reset(seed=1)[0]
    a1, a2 = planner.model.predict(obs, deterministic=True)[0], again.model.predict(obs, deterministic=True)[0]
    assert np.allclose(a1, a2)
    start, goal = _config(planner, 1.0, 1.0, 0.0), _config(planner, 2.5, 1.4, 0.5)
    res = again.plan(start, goal, timeout_s=300)
    env = again._env
    assert env.t <= 200 and len(env.path) <= 202
    if res.success:
        assert np.allclose(res.dense[0], start) and np.allclose(res.dense[-1], goal)
        assert again.ctx.valid(res.dense).all()
    else:
        assert "did not reach the goal within" in res.reason
    assert np.isfinite(res.query_ms)
    # bad problems are failures, not exceptions
    bad = goal.copy()
    bad[:2] = [3.0, 3.0]
    assert not again.plan(start, bad).success
    assert "not trained" in PPOPlanner("rl-ppo", planner.scene, ["cup"], robot=planner.robot).plan(start, goal).reason


def test_compiled_step_matches_the_torch_path(planner, env):
    """The step's compiled work (motion points, collision check, motion cost, geometric score with occlusion) gives
    the values of the torch path (PlanningContext.densify, CollisionChecker, DiffDriveMotion, GeometricScorer)."""
    from psprm_core.baselines.base import PlanningContext
    from psprm_core.kernels.compute import Compute
    from psprm_core.baselines.rl_env import ActivePerceptionEnv

    assert env.ctx.motion.compute.compiled and env.ctx.checker.compute.compiled  # precondition: numba here
    torch_robot = planner.robot.using(Compute.make("cpu", kernels="torch"))
    ref = ActivePerceptionEnv(planner.scene, planner.targets, settings=planner.settings,
                              context=PlanningContext(planner.scene, planner.targets, robot=torch_robot,
                                                      resolution=planner.settings.resolution))
    assert not (ref.ctx.motion.compute.compiled or ref.ctx.checker.compute.compiled or ref.scorer.occ.compute.compiled)
    rng = np.random.default_rng(5)
    seen = {"valid": 0, "rejected": 0, "scored": 0}
    for i in range(120):
        a, _ = env.problems[i % len(env.problems)]
        q = a.copy()
        q[:2] += rng.normal(0.0, 0.3, 2)
        qn = env.propose(q, rng.uniform(-1.0, 1.0, env.action_space.shape))
        fast = (env.motion_points(q, qn), env.motion_valid(q, qn), env.step_cost(q, qn), env.score(qn))
        env._cam_key = None
        slow = (ref.motion_points(q, qn), ref.motion_valid(q, qn), ref.step_cost(q, qn), ref.score(qn))
        assert fast[0].shape == slow[0].shape and np.allclose(fast[0], slow[0], atol=1e-9)
        assert fast[1] == slow[1]
        assert fast[2] == pytest.approx(slow[2], abs=1e-9) and fast[3] == pytest.approx(slow[3], abs=1e-6)
        seen["valid" if fast[1] else "rejected"] += 1
        seen["scored"] += fast[3] > 0
    assert min(seen.values()) > 0, seen  # both outcomes and non-zero scores were compared


def test_geodesic_progress_goes_around_the_furniture(planner):
    """The geodesic goal distance is 0 at the goal, never shorter than the straight line, and longer than it
    when the table stands between the robot and the goal."""
    from psprm_core.baselines.rl_env import ActivePerceptionEnv

    settings = dataclasses.replace(planner.settings, progress_metric="geodesic", w_heading=0.0)
    env = ActivePerceptionEnv(planner.scene, planner.targets, settings=settings, context=planner.ctx)
    goal = _config(planner, 3.0, 4.0, 0.0)  # north of the table (x 2.3-3.7, y 2.6-3.4)
    env.reset(options={"start": _config(planner, 3.0, 1.2, 0.0), "goal": goal})
    assert env.progress_distance(goal) == pytest.approx(0.0)
    behind = env.q.copy()
    behind[:2] = [3.5, 2.0]  # south of the table, next to the chair (x 2.75-3.25, y 1.8-2.3)
    assert env.progress_distance(behind) > env.goal_distance(behind) + 0.5
    rng = np.random.default_rng(0)
    for xy in rng.uniform([0.3, 0.3], [7.7, 5.7], (50, 2)):
        q = env.q.copy()
        q[:2] = xy
        assert env.progress_distance(q) >= env.goal_distance(q) - 1e-9
    # the progress term uses it: a step towards the table (straight at the goal) earns less than the straight metric
    env.reset(options={"start": _config(planner, 3.0, 1.4, np.pi / 2), "goal": goal})  # the chair ahead
    q0 = env.q.copy()
    _, _, _, _, info = env.step(np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32))
    straight = env.goal_distance(q0) - env.goal_distance(env.q)
    assert not info["rejected"] and straight > 0.09 and info["terms"]["progress"] < straight - 0.02


def test_curriculum_starts_near_the_goal_first(planner):
    from psprm_core.baselines.rl_env import ActivePerceptionEnv

    settings = dataclasses.replace(planner.settings, curriculum_steps=1000, curriculum_start=1.2)
    env = ActivePerceptionEnv(planner.scene, planner.targets, settings=settings, context=planner.ctx)
    env.reset(seed=0)
    first = [env.reset()[1]["goal_distance"] for _ in range(40)]
    assert max(first) <= 1.2 and np.mean(first) > 0.3
    assert all(env.ctx.valid(env.q[None]))
    env.total_steps = 500  # half way: the cap grows towards the workspace diagonal
    assert env.curriculum_distance() == pytest.approx(1.2 + 0.5 * (10.0 - 1.2))
    env.total_steps = 1000  # after the curriculum: the pool's problems as they are
    later = [env.reset()[1]["goal_distance"] for _ in range(40)]
    assert min(later) >= settings.min_problem_distance - 1e-9 and max(later) > 3.0


def test_observation_normalisation_is_saved_with_the_policy(planner, tmp_path, monkeypatch):
    """Also: with n_envs the rollout of n_steps transitions is split over that many environments."""
    from psprm_core.errors import ConfigError

    monkeypatch.setattr(rl_ppo, "rl_cache_dir", lambda: tmp_path)
    kw = dict(TINY, normalize_obs=True, n_envs=2)
    p = PPOPlanner("rl-ppo", planner.scene, planner.targets, robot=planner.robot, **kw)
    assert p.fingerprint() != planner.fingerprint()
    assert not p.prepare()["cached"]
    assert (p.model.n_envs, p.model.n_steps, p.model.rollout_buffer.buffer_size) == (2, 256, 256)
    with pytest.raises(ConfigError):
        dataclasses.replace(p.settings, n_envs=3).validate()
    st = p.obs_stats
    assert st["mean"].shape == p.make_env().observation_space.shape and (st["var"] > 0).all()
    obs = p.make_env().reset(seed=2)[0]
    z = p.normalize(obs)
    assert np.allclose(z, np.clip((obs - st["mean"]) / np.sqrt(st["var"] + st["epsilon"]), -10, 10), atol=1e-5)
    assert not np.allclose(z, obs)
    again = PPOPlanner("rl-ppo", planner.scene, planner.targets, robot=planner.robot, **kw)
    assert again.prepare()["cached"]
    assert np.allclose(again.obs_stats["mean"], st["mean"]) and np.allclose(again.obs_stats["var"], st["var"])
    assert np.allclose(again.model.predict(again.normalize(obs), deterministic=True)[0],
                       p.model.predict(z, deterministic=True)[0])
    assert planner.normalize(obs) is obs  # without the setting the observation goes in unchanged


def test_goal_bearing_and_heading_progress(planner):
    """goal_bearing adds (sin, cos) of the goal's bearing and its distance; with w_heading a turn towards the goal
    earns progress and a turn away from it costs."""
    from psprm_core.baselines.rl_env import ActivePerceptionEnv

    settings = dataclasses.replace(planner.settings, goal_bearing=True, w_heading=0.25, progress_metric="euclidean")
    env = ActivePerceptionEnv(planner.scene, planner.targets, settings=settings, context=planner.ctx)
    plain = ActivePerceptionEnv(planner.scene, planner.targets, context=planner.ctx,
                                settings=dataclasses.replace(settings, goal_bearing=False))
    assert env.observation_space.shape[0] == plain.observation_space.shape[0] + 3
    start, goal = _config(planner, 4.5, 4.0, 0.0), _config(planner, 4.5, 2.0, 0.0)  # the goal 2 m to the right
    n = plain.observation_space.shape[0] - (settings.scan_beams + 1 if settings.scan_beams > 0 else 0)
    # the bearing's (sin, cos) and a distance feature proportional to the goal's distance (1 m ahead, 2 m right)
    ahead, _ = env.reset(options={"start": start, "goal": _config(planner, 5.5, 4.0, 0.0)})
    obs, _ = env.reset(options={"start": start, "goal": goal})
    assert ahead[n:n + 2] == pytest.approx([0.0, 1.0], abs=1e-5)
    assert obs[n:n + 2] == pytest.approx([-1.0, 0.0], abs=1e-5)
    assert 0 < ahead[n + 2] < 2.0 and obs[n + 2] == pytest.approx(2.0 * ahead[n + 2], rel=1e-5)
    assert env.progress_distance(start) == pytest.approx(2.0 + 0.25 * np.pi / 2)

    def heading_error(q):
        return abs((np.arctan2(goal[1] - q[1], goal[0] - q[0]) - q[2] + np.pi) % (2 * np.pi) - np.pi)

    _, _, _, _, info = env.step(np.array([0.0, -1.0, 0.0, 0.0], dtype=np.float32))  # turn right, on the spot
    turned = start[2] - env.q[2]
    assert not info["rejected"] and turned > 0.1 and np.allclose(env.q[:2], start[:2])
    expected = 0.25 * (heading_error(start) - heading_error(env.q))  # the heading error fell by the turn
    assert info["terms"]["progress"] == pytest.approx(expected, abs=1e-6) and expected == pytest.approx(0.25 * turned)
    env.reset(options={"start": start, "goal": goal})
    _, _, _, _, info = env.step(np.array([0.0, 1.0, 0.0, 0.0], dtype=np.float32))  # turn left, away
    assert info["terms"]["progress"] == pytest.approx(-0.25 * 0.3, abs=1e-6)


def test_environment_scores_views_of_several_targets():
    """With several targets (nursing: both faces) the environment's perception proxy is the multi-target scorer's,
    one view at a time, the same as its batched score."""
    import torch

    from psprm_core.baselines.rl_env import ActivePerceptionEnv

    scene = load_scene(resolve_named("scene", "nursing"))
    targets = scene.target_names[:2]
    env = ActivePerceptionEnv(scene, targets, settings=rl_ppo.PPOSettings(problems=4, scan_beams=0))
    env.reset(seed=0)
    q = env.q.copy()
    cam = env.camera(q)
    batch = float(env.scorer.score(torch.as_tensor(cam[None]))[0])
    assert env.score(q) == pytest.approx(batch, abs=1e-9)
