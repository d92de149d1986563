"""PS-PRM planner: projection onto the visibility manifold, paths that are collision-free (pybullet's exact check),
executable by a differential drive and within the joint limits, perception better than a plain shortest-path
roadmap, clear failures for bad queries, save/load."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from psprm_core.errors import ConfigError
from psprm_core.evaluation.reference import PybulletWorld, sample_uniform
from psprm_core.paths import resolve_named
from psprm_core.perception.scoring import GeometricScorer
from psprm_core.planning.constraints import ProjectionSettings, VisibilityConstraint
from psprm_core.planning.factory import problem_configurations
from psprm_core.planning.psprm import PSPRM, PSPRMSettings
from psprm_core.planning.timing import check_base_segments
from psprm_core.scene import load_scene

from judges import limit_ratios, same_config  # noqa: E402

N_NODES = 700


@pytest.fixture(scope="module")
def home(home_tv_planner):
    scene, robot, planner, _, _, stats = home_tv_planner(**{"roadmap.n_nodes": N_NODES, "seed": 1})
    assert stats["success"] and stats["n_nodes"] == N_NODES
    return scene, robot, planner


@pytest.mark.parametrize("kind", ["line", "frustum"])
def test_projection_reaches_the_manifold(kind, load_robot):
    robot = load_robot("ur5_mobile")
    target = [2.0, 1.0, 0.9]
    c = VisibilityConstraint(robot, kind, target, margin=0.05)
    q = torch.as_tensor(sample_uniform(robot, 300, np.random.default_rng(0), base_box=np.array([[0, 4.0], [0, 3.0]])),
                        dtype=torch.float64)
    qp, ok = c.project(q, ProjectionSettings(tolerance=0.01))
    assert ok.float().mean() > 0.8
    assert (c.error(qp[ok]) < 0.01).all()
    lo, hi = torch.as_tensor(robot.lower), torch.as_tensor(robot.upper)
    assert ((qp >= lo - 1e-9) & (qp <= hi + 1e-9)).all()
    if kind == "line":  # the target is on the optical axis, in front of the camera
        pc = c.target_in_camera(qp[ok])
        assert (pc[:, 2] > 0.45).all() and (pc[:, :2].norm(dim=-1) < 0.011).all()


@pytest.mark.parametrize("robot_name", ["stretch2", "fetchlike", "ur5_mobile"])
@pytest.mark.parametrize("kind", ["line", "frustum"])
def test_analytic_jacobian_matches_finite_differences(kind, robot_name, load_robot):
    """The projection's analytic Jacobian of h_M (camera twists, Eq. of ``residual_jacobian``) equals central
    differences of h_M for every planning joint: base, revolute, prismatic (Stretch's lift, Fetch's torso), in
    float64, including frustum configurations with the target outside (active faces) and inside (flat)."""
    robot = load_robot(robot_name)
    c = VisibilityConstraint(robot, kind, [2.0, 1.0, 0.9], margin=0.05)
    q = torch.as_tensor(sample_uniform(robot, 200, np.random.default_rng(1), base_box=np.array([[0, 4.0], [0, 3.0]])),
                        dtype=torch.float64)
    cols = torch.arange(robot.dof)
    h, J = c.residual_jacobian(q, cols)
    assert torch.allclose(h, c.residual(q))
    eps, Jn = 1e-6, torch.zeros_like(J)
    for i in range(robot.dof):
        qp, qm = q.clone(), q.clone()
        qp[:, i] += eps
        qm[:, i] -= eps
        Jn[:, :, i] = (c.residual(qp) - c.residual(qm)) / (2 * eps)
    assert J.abs().max() > 0.5  # the camera really moves
    assert (J - Jn).abs().max() < 1e-5


def test_path_is_collision_free_drivable_and_timed(home):
    scene, robot, planner = home
    start, goals = problem_configurations(robot, scene, scene.problem("tv_west_to_southeast"))
    res = planner.plan(start, goals)
    assert res.success, res.reason
    assert np.allclose(res.waypoints[0], start, atol=1e-5) and np.allclose(res.waypoints[-1], goals[0], atol=1e-5)
    # every configuration along the executed path is free under pybullet's exact mesh check
    traj = res.trajectory
    world = PybulletWorld(robot, scene.collision_boxes())
    try:
        assert not world.in_collision(res.dense).any()
        assert not world.in_collision(traj.positions).any()  # smooth phases leave the straight pieces: free too
    finally:
        world.close()
    assert check_base_segments(res.waypoints, (0, 1, 2), 1e-5) == []  # rotate or drive straight, never sideways
    assert check_base_segments(traj.positions, (0, 1, 2), 1e-5) == []  # also between the knots
    over = {k: r for k, r in limit_ratios(traj, robot).items() if r > 1 + 1e-3}
    assert not over, f"limits exceeded (finite differences of the positions): {over}"
    assert np.all(np.diff(traj.times) > 0)
    # smooth timing: the robot stops where the base changes its motion, not at every re-aiming knot
    stops = int((np.abs(traj.velocities[1:-1]).max(1) <= 1e-9).sum())
    assert traj.off_segment_mask().any() and stops < len(res.waypoints) - 2
    assert 0.0 <= res.mean_score <= 1.0 and res.path_length > 0
    # the score report along the dense path equals the test's own scores: camera poses from pybullet's FK, scored by
    # a geometric scorer of the tv the test builds on the scene file
    expected = _own_scores(robot, res.dense)
    np.testing.assert_allclose(res.dense_scores, expected, atol=1e-5)
    assert res.mean_score == pytest.approx(float(expected.mean()), abs=1e-5) and expected.std() > 0


def test_every_problem_keeps_the_base_and_joint_limits_by_finite_differences(home):
    """Over every home problem, the executed trajectories keep the base's linear (norm of the world-frame x, y
    velocity) and angular limits and every joint's, speeds and accelerations alike, measured by finite differences of
    the positions sampled along time; and the base comes close to its top speed, so the check is not idle."""
    scene, robot, planner = home
    worst = {}
    for p in scene.problems:
        res = planner.plan(*problem_configurations(robot, scene, p))
        assert res.success, (p.name, res.reason)
        for k, r in limit_ratios(res.trajectory, robot).items():
            worst[k] = max(worst.get(k, 0.0), r)
    assert max(worst.values()) <= 1 + 1e-3, {k: round(r, 4) for k, r in worst.items() if r > 1 + 1e-3}
    assert worst["base_linear_velocity"] > 0.9 and worst["base_angular_velocity"] > 0.9


def _own_scores(robot, qs) -> np.ndarray:
    """The test's own perception of the tv at configurations ``qs``: camera poses from pybullet's FK, scored by a
    geometric scorer built on the home scene loaded afresh from its file."""
    fresh = load_scene(resolve_named("scene", "home"))
    world = PybulletWorld(robot)
    try:
        cams = torch.as_tensor(np.stack([world.camera_pose(q) for q in np.asarray(qs, float)]))
    finally:
        world.close()
    return GeometricScorer(fresh, "tv", robot.config.intrinsics).score(cams).double().numpy()


def test_perception_weighting_beats_shortest_path(home):
    """Same roadmap, same problems: alpha = 0.8 keeps the target better in view than alpha = 0 (Eq. 2), judged by the
    test's own perception of each path (pybullet FK, its own geometric scorer of the tv) along the dense path, never
    the planner's costs or score reports."""
    scene, robot, planner = home
    probs = [p for p in scene.problems if p.target == "tv"]
    assert len(probs) >= 2
    scores = {}
    for alpha in (0.0, 0.8):
        planner.set_alpha(alpha)
        vals = []
        for p in probs:
            start, goals = problem_configurations(robot, scene, p)
            res = planner.plan(start, goals, timing=False)
            assert res.success, res.reason
            assert same_config(res.dense[0], start) and any(same_config(res.dense[-1], g) for g in goals)
            vals.append(float(_own_scores(robot, res.dense).mean()))
        scores[alpha] = float(np.mean(vals))
    planner.set_alpha(0.8)
    assert scores[0.8] > scores[0.0] + 0.02, scores


def test_bad_queries_fail_cleanly(home):
    scene, robot, planner = home
    start, goals = problem_configurations(robot, scene, scene.problem("tv_west_to_southeast"))
    table = scene.obstacle("table")
    inside = start.copy()
    inside[:2] = table.center[:2]
    res = planner.plan(inside, goals)
    assert not res.success and "start" in res.reason and "environment" in res.reason
    res = planner.plan(start, inside)
    assert not res.success and "goal" in res.reason
    nan = start.copy()
    nan[0] = math.nan
    res = planner.plan(nan, goals)
    assert not res.success and "NaN" in res.reason
    outside = goals[0].copy()
    outside[:2] = [50.0, 50.0]
    assert not planner.plan(start, outside).success


def test_save_load_roundtrip(home, tmp_path):
    scene, robot, planner = home
    start, goals = problem_configurations(robot, scene, scene.problem("tv_west_to_southeast"))
    a = planner.plan(start, goals, timing=False)
    path = planner.save(tmp_path / "roadmap.npz")
    other = PSPRM(robot, scene, planner.scorer, planner.constraint.target.numpy(), planner.settings)
    other.load(path)
    b = other.plan(start, goals, timing=False)
    assert b.success and abs(a.cost - b.cost) < 1e-6
    moved = scene.with_obstacle_pose("table", scene.obstacle("table").center + np.array([0.5, 0, 0]))
    stale = PSPRM(robot, moved, planner.scorer, planner.constraint.target.numpy(), planner.settings)
    with pytest.raises(ConfigError, match="fingerprint"):
        stale.load(path)


def test_retired_query_edges_never_change_results(home):
    """Query nodes/edges are retired lazily (blocked, removed in batches): repeated queries give the same costs
    whether or not the retired ones were compacted away, and the graph only grows until compaction."""
    scene, robot, planner = home
    probs = [problem_configurations(robot, scene, p) for p in scene.problems[:4]]
    first = [planner.plan(a, b, timing=False).cost for a, b in probs]
    grown = planner.graph.n_nodes
    again = [planner.plan(a, b, timing=False).cost for a, b in probs]
    assert planner.graph.n_nodes > grown  # retired nodes are kept until compaction
    planner.pipeline.rm.compact()
    compacted = [planner.plan(a, b, timing=False).cost for a, b in probs]
    assert np.allclose(first, again) and np.allclose(first, compacted)
    assert planner.graph.node_valid[planner.n_roadmap_nodes:].sum() == 2 * len(probs)  # only the last queries'


def test_eager_collision_checking_plans_free_paths(load_robot):
    """``lazy_collision: false``: every roadmap edge is checked densely at build and the query's connections are
    checked and scored in full before the search (no lazy verification); the paths are free and end where asked."""
    scene = load_scene(resolve_named("scene", "home"))
    robot = load_robot("stretch2")
    prob = scene.problem("tv_west_to_southeast")
    scorer = GeometricScorer(scene, prob.target, robot.config.intrinsics)
    planner = PSPRM(robot, scene, scorer, scene.target(prob.target).center,
                    PSPRMSettings().changed({"roadmap.n_nodes": 300, "seed": 2, "edges.lazy_collision": False}))
    planner.build(template=problem_configurations(robot, scene, prob)[0])
    assert (planner.graph.edge_attribute("checked")[planner.graph.valid_edge_ids()] == 1.0).all()
    solved = 0
    for p in scene.problems:
        start, goals = problem_configurations(robot, scene, p)
        res = planner.plan(start, goals, timing=False)
        if not res.success:
            continue
        solved += 1
        assert np.allclose(res.waypoints[0], start, atol=1e-5)
        off = res.waypoints[-1] - np.asarray(goals)
        off[:, 2] = (off[:, 2] + np.pi) % (2 * np.pi) - np.pi  # the base heading, modulo a turn
        assert (np.abs(off).max(1) < 1e-4).any()
        assert bool(planner.checker.valid(torch.as_tensor(res.dense, dtype=planner.dtype)).all())
    assert solved >= len(scene.problems) // 2


def test_rebuilt_roadmap_connects_queries_to_its_own_nodes(load_robot):
    """A second build (same node count, so the same node ids) must not connect queries to the first roadmap's
    configurations: the executed path passes through every node of the new roadmap that it visits."""
    scene = load_scene(resolve_named("scene", "home"))
    robot = load_robot("stretch2")
    prob = scene.problem("tv_west_to_southeast")
    scorer = GeometricScorer(scene, prob.target, robot.config.intrinsics)
    start, goals = problem_configurations(robot, scene, prob)
    planner = PSPRM(robot, scene, scorer, scene.target(prob.target).center,
                    PSPRMSettings().changed({"roadmap.n_nodes": 300, "seed": 3}))
    planner.build(template=start)
    assert planner.plan(start, goals, timing=False).success
    planner.update_settings(planner.settings.__class__(**{**planner.settings.__dict__, "seed": 4}))
    planner.build(template=start)
    res = planner.plan(start, goals, timing=False)
    assert res.success, res.reason
    W = res.waypoints
    for node in res.path_nodes[1:-1]:
        q = planner.graph.configs[node]
        off = np.abs(W - q)
        off[:, 2] = np.abs((W[:, 2] - q[2] + np.pi) % (2 * np.pi) - np.pi)
        assert (off.max(1) < 1e-4).any(), f"the path does not pass through its node {node}"


def test_perception_preserving_shortcuts(home):
    """``shortcut``: the same queries give paths that are no longer, still collision-free under pybullet, drivable
    (rotate or drive straight), start and end where asked, and see as well along the dense path (the planner's
    scorer on every configuration); at least one path gets shorter."""
    import dataclasses

    scene, robot, planner = home
    saved = planner.settings
    world = PybulletWorld(robot, scene.collision_boxes())
    shorter = 0
    try:
        for p in (p for p in scene.problems if p.target == "tv"):
            start, goals = problem_configurations(robot, scene, p)
            out = {}
            for sc in (False, True):
                planner.update_settings(saved.changed({"scoring.objective": "motion", "query.shortcut": sc}))
                planner.reweight(alpha=0.8, objective="motion")
                out[sc] = planner.plan(start, goals, timing=True)
                assert out[sc].success, out[sc].reason
            a, b = out[False], out[True]
            assert b.path_length <= a.path_length + 1e-9
            shorter += b.path_length < a.path_length - 1e-3
            for q, want in ((b.waypoints[0], start), (b.waypoints[-1], goals[0])):
                d = q - want
                d[2] = (d[2] + math.pi) % (2 * math.pi) - math.pi  # the base heading wraps
                assert np.abs(d).max() < 1e-5
            assert not world.in_collision(b.dense).any() and not world.in_collision(b.trajectory.positions).any()
            assert check_base_segments(b.waypoints, (0, 1, 2), 1e-5) == []
            assert b.mean_score >= a.mean_score - 0.03, (a.mean_score, b.mean_score)
    finally:
        world.close()
        planner.update_settings(saved)
        planner.reweight(alpha=saved.scoring.alpha, objective=saved.scoring.objective)
    assert shorter >= 1


def test_motion_objective_reweights_and_validates(home):
    """``reweight(objective="motion")``: every edge weighs c_m ((1 - alpha) + alpha (1 - c_p)) from its stored
    Eq. 1 score and motion cost; the paper's form comes back; unknown forms are a ConfigError."""
    scene, robot, planner = home
    g = planner.graph
    ids = g.valid_edge_ids()
    before = np.asarray(g.weights)[ids].copy()
    cp, cm = g.edge_attribute("c_p")[ids], g.edge_attribute("c_m")[ids]
    try:
        planner.reweight(alpha=0.9, objective="motion")
        np.testing.assert_allclose(np.asarray(g.weights)[ids], cm * (0.1 + 0.9 * (1 - cp)), rtol=1e-12)
        assert planner.heuristic_name == "distance"
        start, goals = problem_configurations(robot, scene, scene.problem("tv_west_to_southeast"))
        assert planner.plan(start, goals, timing=False).success
        with pytest.raises(ConfigError, match="objective"):
            planner.reweight(objective="hops")
    finally:
        planner.reweight(alpha=0.8, objective="eq2")  # the fixture's settings
    # the build weighed in float32; the re-weighting in float64 from the stored c_p and c_m
    np.testing.assert_allclose(np.asarray(g.weights)[ids], before, rtol=1e-6)


def test_perception_biased_sampling(load_robot):
    """``biased_share``: half the nodes are drawn where the scorer predicts good views. Re-scored by a scorer built
    here, the biased roadmap's nodes see the target clearly better than a uniform one's, and every node still lies on
    the manifold and is collision-free under pybullet."""
    scene = load_scene(resolve_named("scene", "home"))
    robot = load_robot("stretch2")
    judge = GeometricScorer(scene, "tv", robot.config.intrinsics)
    means = {}
    for share in (0.0, 0.5):
        scorer = GeometricScorer(scene, "tv", robot.config.intrinsics)
        p = PSPRM(robot, scene, scorer, scene.target("tv").center,
                  PSPRMSettings().changed({"roadmap.n_nodes": 400, "seed": 2, "roadmap.biased_share": share}))
        stats = p.build()
        assert stats["success"] and stats["n_nodes"] == 400
        assert stats.get("biased_nodes", 0) == int(round(400 * share))
        Q = torch.as_tensor(p.graph.configs[p.roadmap_node_ids()], dtype=torch.float64)
        means[share] = float(judge.score(robot.camera_poses(Q)).mean())
        assert (p.constraint.error(Q) < p.settings.projection.tolerance + 1e-6).all()
        world = PybulletWorld(robot, scene.collision_boxes())
        try:
            assert not world.in_collision(Q.numpy()).any()
        finally:
            world.close()
    assert means[0.5] > means[0.0] + 0.03, means
    with pytest.raises(ConfigError, match="biased_share"):
        PSPRMSettings().changed({"roadmap.biased_share": 1.5}).validate()


def test_make_planner_applies_overrides_and_the_shipped_settings(load_robot):
    """Overrides of any setting reach the planner (biased_share included); the shipped YAML's objective picks the
    alpha of DEFAULT_ALPHA unless alpha is given; oracle variants never bias their nodes; the mobile UR5 keeps
    uniform nodes (its per-robot section)."""
    import yaml

    from psprm_core.paths import config_dir, resolve_named
    from psprm_core.planning.factory import DEFAULT_ALPHA, make_planner
    from psprm_core.scene import load_scene

    shipped = yaml.safe_load((config_dir() / "planners" / "psprm.yaml").read_text())
    scene = load_scene(resolve_named("scene", "home"))
    robot = load_robot("stretch2")
    p = make_planner("neural-psprm-line", scene, ["tv"], robot=robot,
                     options={"roadmap.n_nodes": 50, "roadmap.biased_share": 0.3, "scoring.objective": "eq2"})
    assert p.settings.roadmap.biased_share == 0.3 and p.settings.scoring.objective == "eq2"
    assert p.settings.scoring.alpha == DEFAULT_ALPHA[("eq2", "neural")] == 0.8
    p = make_planner("neural-psprm-line", scene, ["tv"], robot=robot, options={"roadmap.n_nodes": 50})
    assert p.settings.scoring.objective == shipped["scoring"]["objective"]
    assert p.settings.query.shortcut == shipped["query"]["shortcut"]
    assert p.settings.roadmap.biased_share == shipped["roadmap"]["biased_share"]
    assert p.settings.scoring.alpha == DEFAULT_ALPHA[(shipped["scoring"]["objective"], "neural")]
    p = make_planner("neural-psprm-line", scene, ["tv"], robot=robot,
                     options={"roadmap.n_nodes": 50, "scoring.alpha": 0.5})
    assert p.settings.scoring.alpha == 0.5
    p = make_planner("psprm-line", scene, ["tv"], robot=robot,
                     options={"roadmap.n_nodes": 50, "roadmap.biased_share": 0.5})
    assert p.settings.roadmap.biased_share == 0.0
    alley = load_scene(resolve_named("scene", "blind_spot_alley"))
    p = make_planner("neural-psprm-line", alley, [alley.target_names[0]], robot=load_robot("ur5_mobile"),
                     options={"roadmap.n_nodes": 50})
    assert p.settings.roadmap.biased_share == shipped["robots"]["ur5_mobile"]["roadmap"]["biased_share"] == 0.0
    # the rest of the group keeps the shared values
    assert p.settings.roadmap.n_nodes == 50 and p.settings.roadmap.k_long == shipped["roadmap"]["k_long"]


def test_settings_files_are_read_by_one_typed_reader(tmp_path):
    """PSPRMSettings and ReplanSettings YAML: values typed by each field's default, the file and field named in the
    error; negative values only where a field is signed; unknown keys refused; the groups nested, a setting given
    outside its group refused with the group named; settings named by their own name or dotted path."""
    from psprm_core.planning.replanner import ReplanSettings

    good = tmp_path / "p.yaml"
    good.write_text("roadmap:\n  n_nodes: 120\nedges:\n  edge_view_slack: -1.0\nquery:\n  shortcut: true\n"
                    "projection:\n  max_iters: 7\n  tolerance: 0.01\n")
    s = PSPRMSettings.from_yaml(good)
    assert (s.roadmap.n_nodes, s.edges.edge_view_slack, s.query.shortcut) == (120, -1.0, True)
    assert (s.projection.max_iters, s.projection.tolerance) == (7, 0.01)
    assert s.roadmap.k_long == PSPRMSettings().roadmap.k_long  # a group given in part keeps its other defaults
    t = s.changed({"scoring.alpha": 0.3, "projection.max_iters": 9})
    assert (t.scoring.alpha, t.projection.max_iters, t.value("scoring.alpha"), s.scoring.alpha) == (0.3, 9, 0.3, None)
    with pytest.raises(ConfigError, match="no_such"):
        s.changed({"no_such": 1})
    for text, field in (("roadmap:\n  n_nodes: many\n", "roadmap.n_nodes"),
                        ("roadmap:\n  max_edge_length: -2.0\n", "roadmap.max_edge_length"),
                        ("no_such_setting: 1\n", "no_such_setting"), ("projection:\n  max_iters: 0\n", "max_iters"),
                        ("alpha: 0.5\n", "'alpha'.*'scoring' group"), ("scoring:\n  alpha: 1.5\n", "scoring.alpha"),
                        ("robots:\n  stretch2:\n    n_nodes: 5\n", "robots.stretch2.n_nodes.*'roadmap' group")):
        bad = tmp_path / "bad.yaml"
        bad.write_text(text)
        with pytest.raises(ConfigError, match=field) as e:
            PSPRMSettings.from_yaml(bad)
        assert "bad.yaml" in str(e.value)
    r = tmp_path / "r.yaml"
    r.write_text("goal_commit_s: 3.5\nreplan_on_move: true\n")
    rs = ReplanSettings.from_yaml(r)
    assert (rs.goal_commit_s, rs.replan_on_move) == (3.5, True)
    r.write_text("goal_commit_s: yes please\n")
    with pytest.raises(ConfigError, match="goal_commit_s"):
        ReplanSettings.from_yaml(r)


def test_update_settings_refuses_the_visibility_model_and_remakes_changed_knots(home):
    """The visibility model is fixed when a planner is made; a change of N (Eq. 1's interior samples) drops the
    stored knots, so the path that runs has knots made with the new N, and pybullet finds it free."""
    scene, robot, planner = home
    saved = planner.settings
    with pytest.raises(ConfigError, match="constraint"):
        planner.update_settings(**{"visibility.constraint": "frustum" if saved.visibility.constraint == "line"
                                   else "line"})
    assert planner.settings == saved
    world = PybulletWorld(robot, scene.collision_boxes())
    try:
        planner.update_settings(**{"edges.n_interp": saved.edges.n_interp + 2})
        start, goals = problem_configurations(robot, scene, scene.problem("tv_west_to_southeast"))
        res = planner.plan(start, goals, timing=False)
        assert res.success, res.reason
        eids = planner.graph.edge_ids_of_path(res.path_nodes)
        knots, interior = planner.stored_knots(eids)
        assert interior.shape[1] == saved.edges.n_interp + 2
        assert not world.in_collision(res.dense).any()
        # Eq. 1 of every edge that runs, from its knots, by this test's own FK and scorer: the weights the search
        # used were made with the new N at the knots that run, not kept from the old ones
        pts = torch.cat([knots[:, :1], torch.gather(knots, 1, interior.unsqueeze(-1).expand(-1, -1, robot.dof)),
                         knots[:, -1:]], 1)
        raw = planner.scorer.score(robot.camera_poses(pts.reshape(-1, robot.dof))).reshape(len(eids), -1)
        eq1 = (raw.double() * planner.score_scale).clamp(0, 1).mean(1).numpy()
        np.testing.assert_allclose(planner.graph.edge_attribute("c_p")[eids], eq1, atol=1e-4)
    finally:
        world.close()
        planner.update_settings(saved)
    assert planner.plan(start, goals, timing=False).success
