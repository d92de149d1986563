"""The shipped surrogate (``psprm_core/data/surrogate.pt``) against the real detector, per class, on the planner's own
roadmap views: the views of a small neural PS-PRM roadmap per scene target (fixed seeds) are rendered and scored by
the oracle (render + real detector); the surrogate must rank them like the detector, agree with its confidences, and
agree with them better given the target's own class than given any other class."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import spearmanr

from psprm_core.paths import resolve_named
from psprm_core.perception.occlusion import OcclusionChecker
from psprm_core.perception.oracle import Oracle
from psprm_core.perception.scoring import NeuralScorer
from psprm_core.perception.surrogate import load_surrogate, target_pose_matrix
from psprm_core.planning.factory import default_checkpoint, make_planner
from psprm_core.scene import load_scene

#: (scene, target, views): one target per class of the shipped surrogate; the cup's tiled detector costs ~3x a view.
CASES = [("dynamic_person", "person_face", 12), ("home", "tv", 12), ("home", "potted_plant", 12), ("home", "cup", 8)]
#: The shipped checkpoint measures Spearman 0.84-1.0 and a mean absolute error of 0.016-0.057 on these views, and
#: 0.40-0.46 of the error under the nearest other class for the tv and the cup (0.08-0.13 for the face and plant).
MIN_SPEARMAN = 0.5
MAX_MAE = 0.1


@pytest.fixture(scope="module")
def views(load_robot):
    """Per class: the scene, the camera poses of ``views`` roadmap nodes and the oracle's scores of them."""
    out = {}
    for scene_name, target, k in CASES:
        scene = load_scene(resolve_named("scene", scene_name))
        robot = load_robot(scene.robot)
        p = make_planner("neural-psprm-line", scene, [target], robot=robot, options={"roadmap.n_nodes": 150, "seed": 0})
        assert p.build()["success"]
        ids = np.random.default_rng(0).choice(p.roadmap_node_ids(), k, replace=False)
        cams = robot.camera_poses(torch.as_tensor(p.graph.configs[ids], dtype=torch.float64))
        with Oracle(scene, intrinsics=robot.config.intrinsics) as oracle:
            labels = np.array([oracle.score(T, target, keep_image=False).score for T in cams.numpy()])
        out[scene.target(target).detector_class] = (scene, target, cams, labels)
    return out


@pytest.fixture(scope="module")
def surrogate():
    return load_surrogate(default_checkpoint())


def test_every_class_of_the_surrogate_is_judged(views, surrogate):
    assert sorted(views) == sorted(surrogate.classes)
    for cls, (_, _, _, labels) in views.items():
        # the views span seen and unseen targets, so a ranking is meaningful
        assert (labels > 0.1).sum() >= 2 and (labels < 0.05).sum() >= 1, (cls, labels.round(2))


@pytest.mark.parametrize("cls", ["face", "tv", "potted plant", "cup"])
def test_surrogate_ranks_roadmap_views_like_the_detector(cls, views, surrogate):
    scene, target, cams, labels = views[cls]
    pred = NeuralScorer(surrogate, scene, target).score(cams).double().numpy()  # what the planners optimise
    rho = spearmanr(pred, labels).statistic
    mae = float(np.abs(pred - labels).mean())
    assert rho >= MIN_SPEARMAN, f"{cls}: Spearman {rho:.2f} (oracle {labels.round(2)}, surrogate {pred.round(2)})"
    assert mae <= MAX_MAE, f"{cls}: mean absolute error {mae:.3f}"


@pytest.mark.parametrize("cls", ["face", "tv", "potted plant", "cup"])
def test_the_class_input_selects_the_detector_behaviour_of_that_class(cls, views, surrogate):
    """Given any other class instead of the target's, the same poses (zeroed where ray casting finds the target
    occluded, as in the planners) agree far worse with the detector."""
    scene, target, cams, labels = views[cls]
    tp = target_pose_matrix(scene.target(target))
    occ = OcclusionChecker.from_scene(scene, target)
    err = {c: float(np.abs(occ.apply(surrogate.predict(cams, tp, c), cams).double().numpy() - labels).mean())
           for c in surrogate.classes}
    others = {c: e for c, e in err.items() if c != cls}
    assert err[cls] < 0.7 * min(others.values()), err
