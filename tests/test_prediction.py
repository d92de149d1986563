"""Target motion prediction (psprm_core.prediction), judged against the motion the test itself generated: a turn in
progress is extrapolated, a walk is extrapolated, a person turning back and forth is predicted, beyond a few
seconds, to look where they have been looking in the proportions they have (the test's own quantiles of its own
headings), a turn that repeats at a steady pace is predicted from one period earlier (the test's own formula) and
a turn that does not repeat is not, a standing target stays; bad input (NaN, time going back, jumps, gaps) is
discarded with a warning and the last good pose used; and the replanner's predicted path score changes with the
predicted poses, not with the instantaneous one alone."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from psprm_core.errors import InputError
from psprm_core.geometry import yaw_to_quat
from psprm_core.prediction import PredictionSettings, TargetPredictor, quat_yaw, turned


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _feed(pr, times, positions, yaws):
    for t, p, y in zip(times, positions, yaws):
        assert pr.add(t, p, yaw_to_quat(y))


def _mix_yaws(mix):
    return np.array([quat_yaw(q) for _, _, q in mix]), np.array([w for w, _, _ in mix])


def test_quaternion_turn_about_the_vertical():
    rng = np.random.default_rng(1)
    for _ in range(20):
        y, d = rng.uniform(-3, 3, 2)
        assert _wrap(quat_yaw(turned(yaw_to_quat(y), d)) - (y + d)) == pytest.approx(0.0, abs=1e-9)


def test_a_turn_in_progress_is_extrapolated():
    pr = TargetPredictor(PredictionSettings(components=1))
    t = np.arange(0.0, 2.0, 1 / 60)
    rate = 0.6  # rad/s, a person turning at a human pace
    _feed(pr, t, np.zeros((len(t), 3)), 0.2 + rate * t)
    truth = 0.2 + rate * (t[-1] + 0.3)
    (w, p, q), = pr.mixture(t[-1] + 0.3)
    held = 0.2 + rate * t[-1]
    # nearer the truth than holding the last pose, and within 0.05 rad of it
    assert abs(_wrap(quat_yaw(q) - truth)) < 0.05
    assert abs(_wrap(quat_yaw(q) - truth)) < 0.5 * abs(_wrap(held - truth))


def test_a_walk_is_extrapolated_and_a_standing_target_stays():
    pr = TargetPredictor(PredictionSettings())
    t = np.arange(0.0, 3.0, 1 / 60)
    v = np.array([0.8, -0.3, 0.0])
    P = np.array([1.0, 2.0, 1.6]) + t[:, None] * v
    _feed(pr, t, P, np.full(len(t), 0.4))
    for tau in (0.5, 1.0):
        truth = P[-1] + v * tau
        for w, p, q in pr.mixture(t[-1] + tau):
            assert np.linalg.norm(p - truth) < 0.25 * np.linalg.norm(v * tau)
            assert abs(_wrap(quat_yaw(q) - 0.4)) < 1e-6  # the heading never changed: every component keeps it
    # a person who stood looking elsewhere, then walks: looks where they go, not back where they looked
    walker = TargetPredictor(PredictionSettings())
    _feed(walker, t, np.tile([1.0, 2.0, 1.6], (len(t), 1)), np.full(len(t), 2.0))
    turn = np.arange(3.0, 4.0, 1 / 60)
    _feed(walker, turn, np.tile([1.0, 2.0, 1.6], (len(turn), 1)), np.linspace(2.0, 0.4, len(turn)))
    _feed(walker, t + 4.0, np.array([1.0, 2.0, 1.6]) + t[:, None] * v, np.full(len(t), 0.4))
    for w, p, q in walker.mixture(t[-1] + 4.0 + 5.0):
        assert abs(_wrap(quat_yaw(q) - 0.4)) < 1e-6
    still = TargetPredictor(PredictionSettings())
    _feed(still, t, np.tile([3.0, 1.0, 1.5], (len(t), 1)), np.full(len(t), -1.0))
    for w, p, q in still.mixture(t[-1] + 10.0):
        assert np.allclose(p, [3.0, 1.0, 1.5], atol=1e-9) and abs(_wrap(quat_yaw(q) + 1.0)) < 1e-6


def test_a_person_turning_back_and_forth_is_predicted_by_what_they_looked_at():
    s = PredictionSettings(history_s=20.0, components=4, period_window_s=0.0)  # the history's quantiles alone
    pr = TargetPredictor(s)
    t = np.arange(0.0, 30.0, 1 / 60)
    # dwelling at each side (the shipped recording's profile): -pi/2 -+ 1.3 rad
    yaw = -math.pi / 2 - 1.3 * np.tanh(1.5 * np.cos(2 * np.pi * t / 20.0)) / np.tanh(1.5)
    _feed(pr, t, np.zeros((len(t), 3)), yaw)
    # the test's own quantiles of the headings of the last 20 s
    recent = yaw[t >= t[-1] - 20.0]
    expected = np.quantile(recent, (np.arange(3) + 0.5) / 3)
    yaws, w = _mix_yaws(pr.mixture(t[-1] + 5 * s.revert_s))
    assert w.sum() == pytest.approx(1.0)
    assert w[0] < 0.01  # far ahead (five reversion times), the extrapolation has given way
    assert np.abs(_wrap(np.sort(yaws[1:]) - np.sort(expected))).max() < 0.05
    # the spread grows with the horizon, from nothing to the history's (the test's quantiles, equally weighted)
    spreads = [pr.expected_yaw_spread(t[-1] + tau) for tau in (0.0, 0.5, 20.0)]
    assert spreads[0] == pytest.approx(0.0, abs=1e-9) and spreads[1] > 0.1
    c = math.atan2(np.sin(expected).mean(), np.cos(expected).mean())
    assert spreads[2] == pytest.approx(math.sqrt(np.mean(_wrap(expected - c) ** 2)), abs=0.05)


@pytest.mark.parametrize("period", [7.3, 11.0, 16.5])
def test_a_turn_that_repeats_is_predicted_from_one_period_earlier(period):
    """A person scanning side to side at a steady pace (a sinusoid of the test's period, 45 s at 30 Hz) and, beside
    it, the same person with the periodic component off. The period found is the test's; the predicted mixture
    holds a component within 0.05 rad of the heading the test's own formula gives at each horizon, and the mixture's
    weighted heading error (against that formula) is lower than without the component from 2 s on."""
    t = np.arange(0.0, 45.0, 1 / 30)

    def truth(tt):
        return -math.pi / 2 + 1.1 * np.sin(2 * np.pi * tt / period + 0.4)

    pr, off = TargetPredictor(), TargetPredictor(PredictionSettings(period_window_s=0.0))
    for p in (pr, off):
        _feed(p, t, np.zeros((len(t), 3)), truth(t))
    P, c = pr.period()
    assert P == pytest.approx(period, abs=0.15) and c > 0.95
    assert off.period() is None
    for tau in (1.0, 2.0, 4.0, 8.0, 12.0):
        y_true = truth(t[-1] + tau)
        yaws, w = _mix_yaws(pr.mixture(t[-1] + tau))
        assert w.sum() == pytest.approx(1.0) and len(w) == 4
        assert np.abs(_wrap(yaws - y_true)).min() < 0.05, (tau, yaws, y_true)
        yaws_off, w_off = _mix_yaws(off.mixture(t[-1] + tau))
        err, err_off = (float(ww @ np.abs(_wrap(yy - y_true))) for yy, ww in ((yaws, w), (yaws_off, w_off)))
        if tau >= 2.0:
            assert err < 0.8 * err_off, (tau, err, err_off)
    # a gap in the stream (longer than max_gap_s) restarts the search: no period until it has seen one again
    t_gap = t[-1] + 2.0
    assert pr.add(t_gap, [0.0, 0.0, 0.0], yaw_to_quat(float(truth(t_gap))))
    assert pr.period() is None and len(pr.mixture(t_gap + 4.0)) == 3


@pytest.mark.parametrize("period", [9.0, 14.0])
def test_a_turn_that_dwells_at_each_side_is_found_at_its_own_period_not_a_multiple(period):
    """A person who dwells at each side of the turn (the shipped recording's shape: a squashed cosine) correlates
    with themselves as well two periods back as one; the period found is the turn's own (the test's), not twice it,
    so that the component needs no more history than one period does."""
    def truth(tt):
        return -math.pi / 2 - (math.pi / 2) * np.tanh(1.5 * np.cos(2 * np.pi * tt / period)) / math.tanh(1.5)

    pr, found = TargetPredictor(), []
    for t in np.arange(0.0, 68.0, 1 / 30):
        assert pr.add(t, np.zeros(3), yaw_to_quat(float(truth(t))))
        if t >= 45.0 and round(t * 30) % 30 == 0:  # once a second over the last 23 s
            found.append(pr.period())
    assert all(f is not None and f[1] > 0.95 for f in found)
    assert [round(f[0], 1) for f in found] == pytest.approx([period] * len(found), abs=0.15)


def test_a_turn_that_does_not_repeat_has_no_periodic_component():
    """Turns that do not repeat at a steady pace (dwell times drawn by the test between 2 and 9 s), a steady spin,
    a standing person with mocap noise, and too little history for one period: no period, and the mixture is the
    extrapolation and the history's quantiles."""
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 45.0, 1 / 30)
    switches = np.cumsum(rng.uniform(2.0, 9.0, 40))
    side = np.searchsorted(switches, t) % 2
    dwell = -math.pi / 2 + np.where(side == 1, 0.9, -0.9)
    # turns of 1.8 rad take 0.4 s (within the predictor's turn-rate limit)
    dwell = np.convolve(np.pad(dwell, (6, 6), mode="edge"), np.ones(13) / 13, mode="valid")
    cases = {"irregular": dwell, "spin": 0.3 * t, "standing": -1.0 + rng.normal(0.0, 0.01, len(t)),
             "short": -math.pi / 2 + 1.1 * np.sin(2 * np.pi * t / 20.0)}
    for name, yaw in cases.items():
        pr = TargetPredictor()
        n = len(t) if name != "short" else int(25.0 * 30)  # 25 s of a 20 s period
        _feed(pr, t[:n], np.zeros((n, 3)), yaw[:n])
        assert pr.period() is None, name
        assert len(pr.mixture(t[n - 1] + 5.0)) <= 3, name


def test_bad_input_is_discarded_and_the_last_good_pose_used(caplog):
    s = PredictionSettings(max_rejects=5)
    pr = TargetPredictor(s, "face")
    t = np.arange(0.0, 1.0, 0.02)
    _feed(pr, t, np.tile([1.0, 1.0, 1.5], (len(t), 1)), np.zeros(len(t)))
    caplog.set_level(logging.WARNING, logger="psprm_core.prediction")
    assert not pr.add(1.0, [np.nan, 1.0, 1.5], yaw_to_quat(0.0))
    assert not pr.add(0.5, [1.0, 1.0, 1.5], yaw_to_quat(0.0))  # time going back
    assert not pr.add(1.01, [3.0, 1.0, 1.5], yaw_to_quat(0.0))  # 2 m in 20 ms
    assert pr.discarded == 3 and "discarded" in caplog.text
    (w, p, q), *_ = pr.mixture(2.0)
    assert np.allclose(p, [1.0, 1.0, 1.5], atol=1e-6)
    # a target that really was moved (the same jump, again and again) is taken after max_rejects samples
    results = [pr.add(1.02 + 0.02 * k, [3.0, 1.0, 1.5], yaw_to_quat(0.0)) for k in range(5)]
    assert results == [False, False, False, True, True]  # with the first jump: 5 in a row, then accepted
    (w, p, q), *_ = pr.mixture(2.0)
    assert np.allclose(p, [3.0, 1.0, 1.5], atol=1e-6)
    # a gap restarts the rates: no extrapolation from the stale ones
    turning = TargetPredictor(PredictionSettings(components=1))
    tt = np.arange(0.0, 1.0, 0.02)
    _feed(turning, tt, np.zeros((len(tt), 3)), 1.0 * tt)
    assert turning.yaw_rate == pytest.approx(1.0, rel=0.05)
    assert turning.add(5.0, [0.0, 0.0, 0.0], yaw_to_quat(1.0))
    assert turning.yaw_rate == 0.0


def test_settings_are_validated():
    with pytest.raises(InputError):
        PredictionSettings(history_s=0.0)
    with pytest.raises(InputError):
        PredictionSettings(components=0)
    with pytest.raises(InputError):
        PredictionSettings(period_window_s=-1.0)
    with pytest.raises(InputError):
        PredictionSettings(period_min_corr=0.0)
    with pytest.raises(InputError):
        TargetPredictor().mixture(0.0)  # no pose yet


def _person_planner(load_robot):
    """A 500-node PS-PRM of Stretch in dynamic_person with a geometric scorer of the face, and the start and goals
    of its problem south_to_either: (scene, robot, planner, start, goals)."""
    from psprm_core.paths import resolve_named
    from psprm_core.perception.scoring import GeometricScorer
    from psprm_core.planning.factory import problem_configurations
    from psprm_core.planning.psprm import PSPRM, PSPRMSettings
    from psprm_core.scene import load_scene

    scene = load_scene(resolve_named("scene", "dynamic_person"))
    robot = load_robot("stretch2")
    scorer = GeometricScorer(scene, "person_face", robot.config.intrinsics)
    p = PSPRM(robot, scene, scorer, scene.target("person_face").center,
              PSPRMSettings().changed({"roadmap.n_nodes": 500, "seed": 2}))
    assert p.build()["success"]
    start, goals = problem_configurations(robot, scene, scene.problem("south_to_either"))
    return scene, robot, p, start, goals


def test_the_replanners_path_score_uses_the_predicted_poses(load_robot):
    """The same remaining path, the same latest pose: a person who has been looking at the robot's route for 20 s
    and just turned away scores higher, predicted, than one who has always looked away (the history says they turn
    back); with prediction off both score alike (the instantaneous view)."""
    from psprm_core.planning.replanner import Replanner, ReplanSettings

    scene, robot, p, start, goals = _person_planner(load_robot)
    face = scene.target("person_face")
    south = -math.pi / 2
    away = math.pi / 2

    def score(history_yaw, enabled=True):
        rp = Replanner(p, ReplanSettings(prediction=PredictionSettings(enabled=enabled)), targets=["person_face"])
        for k in range(600):  # 20 s at 30 Hz, then turned away for the last 0.2 s
            y = history_yaw if k < 594 else away
            rp.update_target("person_face", face.center, yaw_to_quat(y), stamp=k / 30)
        rp.set_robot_state(start)
        rp.set_goals(goals[:1])
        res = rp.replan(now=0.0)
        assert res.success
        return rp.predicted_score(res.trajectory)

    looked_at_robot, always_away = score(south), score(away)
    assert looked_at_robot > always_away + 0.05
    assert score(south, enabled=False) == pytest.approx(score(away, enabled=False), abs=1e-9)


def test_a_person_who_turned_away_is_planned_for_where_they_looked_before(load_robot):
    """A person has looked one way for 20 s and has just turned away (over 1 s); they turn back. The replan's route,
    judged by the test's own measure against the person looking where they looked before (a geometric scorer of that
    scene on the trajectory every 50 ms, normalised with the roadmap's scale; motion cost by the diff-drive metric;
    the motion-weighted objective L ((1 - alpha) + alpha (1 - P)) with the planner's alpha), is never worse with the
    routes of the predicted headings than with the search of the extrapolated pose alone, and better by more than
    10 % in at least two of the four cases."""
    import torch

    from psprm_core.perception.scoring import GeometricScorer
    from psprm_core.planning.replanner import Replanner, ReplanSettings

    scene, robot, p, start, goals = _person_planner(load_robot)
    face = scene.target("person_face")
    alpha = float(p.settings.scoring.alpha)

    def judged(traj, yaw):
        q = torch.as_tensor(traj.evaluate(np.arange(0.0, traj.duration, 0.05))[0], dtype=torch.float64)
        looking = scene.with_target_pose("person_face", face.center, yaw_to_quat(yaw))
        sc = GeometricScorer(looking, "person_face", robot.config.intrinsics).score(robot.camera_poses(q)).numpy()
        P = float(np.clip(sc * p.score_scale, 0.0, 1.0).mean())
        L = float(p.motion.distance(q[:-1], q[1:]).sum())
        return L * ((1.0 - alpha) + alpha * (1.0 - P))

    def plan(history_yaw, away, routes):
        rp = Replanner(p, ReplanSettings(predicted_routes=routes), targets=["person_face"])
        turn = float(_wrap(away - history_yaw))
        for k in range(600):  # 30 Hz; the turn over the last second
            y = history_yaw + min(1.0, max(0.0, (k - 570) / 29)) * turn
            rp.update_target("person_face", face.center, yaw_to_quat(y), stamp=k / 30)
        rp.set_robot_state(start)
        rp.set_goals(goals)
        res = rp.replan(now=0.0)
        assert res.success, res.reason
        return judged(res.trajectory, history_yaw)

    better = 0
    for history_yaw, away in ((0.0, math.pi / 2), (0.0, math.pi), (math.pi, math.pi / 2), (math.pi, 0.0)):
        alone, with_routes = plan(history_yaw, away, False), plan(history_yaw, away, True)
        assert with_routes <= alone * 1.001, (history_yaw, away, with_routes, alone)
        better += with_routes < 0.9 * alone
    assert better >= 2


def test_circular_crps_matches_hand_computed_values():
    """The heading score of ``psprm perf prediction``: a single heading scores its error the shorter way round; two
    equally weighted headings at +-a score a/2 at their middle (E|Y - y| = a, E|Y - Y'| = a); a mixture that does not
    sum to 1 is refused."""
    from psprm_core.evaluation.dynamic.prediction_score import circular_crps

    assert circular_crps([1.0], [0.3], -0.2) == pytest.approx(0.5)
    assert circular_crps([1.0], [3.0], -3.0) == pytest.approx(2 * math.pi - 6.0)
    assert circular_crps([0.5, 0.5], [0.4, -0.4], 0.0) == pytest.approx(0.2)
    assert circular_crps([0.5, 0.5], [0.4, -0.4], 1.0) == pytest.approx(1.0 - 0.2)  # 0.6 and 1.4, less 0.4
    with pytest.raises(ValueError):
        circular_crps([0.5, 0.4], [0.0, 1.0], 0.0)


def test_prediction_scores_of_the_latest_pose_are_the_targets_own_change_over_the_horizon():
    """With prediction off the forecast is the latest pose, so its heading score is the mean absolute heading change
    over the horizon and its position error the distance walked: both computed here from the scenario's world at the
    same instants. The shipped predictor, fed the same stream, gives other (finite) figures."""
    from psprm_core.evaluation.dynamic.prediction_score import prediction_scores
    from psprm_core.evaluation.scenario_world import World
    from psprm_core.evaluation.scenarios import draw_variation, load_scenario
    from psprm_core.paths import resolve_named
    from psprm_core.scene import load_scene

    h, T = 2.0, 20.0
    res = prediction_scores({"off": PredictionSettings(enabled=False), "on": PredictionSettings()},
                            ["walking_person"], [3], [h], max_duration_s=T)
    sc = load_scenario(resolve_named("scenario", "walking_person"))
    world = World(sc, load_scene(resolve_named("scene", sc.scene)), None, draw_variation(sc, 3, 0))
    tgt = sc.people[0].target
    dyaw, dxy = [], []
    for k, t in enumerate(np.arange(0.0, T, 1 / 30)):
        if k % 15 or t < 2.0 or t + h > T:
            continue
        (p0, q0), (p1, q1) = world.poses(float(t))["targets"][tgt], world.poses(float(t + h))["targets"][tgt]
        d = quat_yaw(np.asarray(q1)) - quat_yaw(np.asarray(q0))
        dyaw.append(abs((d + math.pi) % (2 * math.pi) - math.pi))
        dxy.append(float(np.linalg.norm(np.asarray(p1)[:2] - np.asarray(p0)[:2])))
    off = res["variants"]["off"]["scenarios"]["walking_person"]
    assert off["forecasts"] == len(dyaw) > 20
    assert off["yaw_crps_rad"][0] == pytest.approx(np.mean(dyaw), abs=1e-9)
    assert off["position_error_m"][0] == pytest.approx(np.mean(dxy), abs=1e-9)
    assert np.mean(dxy) > 0.2  # the person walks
    on = res["variants"]["on"]["scenarios"]["walking_person"]
    assert np.isfinite(on["yaw_crps_rad"][0]) and on["position_error_m"][0] != pytest.approx(off["position_error_m"][0])


def test_the_scores_by_heading_are_the_scores_of_the_person_at_each_heading(load_robot):
    """A person has looked south for 10 s, turned east over 1 s and looked east since: the predicted mixture is the
    extrapolation (east, no turn under way) and the history's two headings (south, east). The remaining path's score
    under each component alone is the score a replanner without prediction gives the same trajectory with the
    person standing at that heading; the mixture's mean lies between them."""
    from psprm_core.planning.replanner import Replanner, ReplanSettings

    scene, robot, p, start, goals = _person_planner(load_robot)
    face = scene.target("person_face")
    south, east = -math.pi / 2, 0.0
    rp = Replanner(p, ReplanSettings(), targets=["person_face"])
    for k in range(631):
        y = south if k < 300 else east if k >= 330 else south + (east - south) * (k - 300) / 30
        rp.update_target("person_face", face.center, yaw_to_quat(y), stamp=k / 30)
    rp.set_robot_state(start)
    rp.set_goals(goals[:1])
    res = rp.replan(now=0.0)
    assert res.success, res.reason
    mean, by_heading = rp.predicted_score(res.trajectory, per_component=True)

    def alone(yaw):
        ref = Replanner(p, ReplanSettings(prediction=PredictionSettings(enabled=False)), targets=["person_face"])
        ref.update_target("person_face", face.center, yaw_to_quat(yaw), stamp=0.0)
        return ref.predicted_score(res.trajectory)

    s_south, s_east = alone(south), alone(east)
    assert abs(s_south - s_east) > 0.05, (s_south, s_east)  # the headings see the route differently
    assert by_heading == pytest.approx([s_east, s_south, s_east], abs=1e-4)
    assert min(s_south, s_east) - 1e-6 <= mean <= max(s_south, s_east) + 1e-6


def test_prediction_scores_cover_a_recorded_person():
    """A scenario whose person is replayed from a recording (``recorded_person``) is scored too: with prediction off
    the heading score is the mean absolute heading change over the horizon, computed here from the CSV itself (read
    with the csv module, the replay started the episode's drawn fraction into the body's loop)."""
    import csv

    from psprm_core.evaluation.dynamic.prediction_score import prediction_scores
    from psprm_core.evaluation.scenarios import draw_variation, load_scenario
    from psprm_core.paths import config_dir, resolve_named

    h, T = 4.0, 24.0
    res = prediction_scores({"off": PredictionSettings(enabled=False)}, ["recorded_person"], [3], [h],
                            max_duration_s=T)
    ts, yaws = [], []
    with open(config_dir() / "recordings" / "person_turning.csv", newline="") as f:
        for row in csv.DictReader(f):
            if row["body"] == "person_face":
                x, y, z, w = (float(row[k]) for k in ("qx", "qy", "qz", "qw"))
                ts.append(float(row["time"]))
                yaws.append(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
    ts, yaws = np.array(ts) - ts[0], np.unwrap(yaws)
    loop = ts[-1] + ts[-1] / (len(ts) - 1)
    sc = load_scenario(resolve_named("scenario", "recorded_person"))
    offset = draw_variation(sc, 3, 0)["<recording>"].phase_rad / (2 * math.pi) * loop

    def yaw_at(t):
        tau = (t + offset) % loop
        assert tau <= ts[-1]  # (the stretch back to the first sample is not among this test's instants)
        return float(np.interp(tau, ts, yaws))

    dyaw = []
    for k, t in enumerate(np.arange(0.0, T, 1 / 30)):
        if k % 15 or t < 2.0 or t + h > T:
            continue
        d = yaw_at(float(t + h)) - yaw_at(float(t))
        dyaw.append(abs((d + math.pi) % (2 * math.pi) - math.pi))
    off = res["variants"]["off"]["scenarios"]["recorded_person"]
    assert off["forecasts"] == len(dyaw) > 20
    assert off["yaw_crps_rad"][0] == pytest.approx(np.mean(dyaw), abs=1e-4)
    assert np.mean(dyaw) > 0.5  # the person turns
