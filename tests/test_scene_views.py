"""Roadmap views for fine-tuning the surrogate: camera poses of a scene's PS-PRM roadmap, occluded ones dropped."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from psprm_core.paths import resolve_named
from psprm_core.perception.dataset import target_in_fov
from psprm_core.perception.occlusion import OcclusionChecker
from psprm_core.perception.scene_views import roadmap_views
from psprm_core.scene import load_scene


def test_roadmap_views_see_the_target_unoccluded(load_robot):
    scene = load_scene(resolve_named("scene", "cup_table"))
    robot = load_robot(scene.robot)
    v = roadmap_views(scene, ["cup"], 60, nodes=300, seed=3, edge_fraction=0.5, robot=robot)
    n = len(v["camera_poses"])
    st = v["stats"]["cup"]
    assert n == st["views"] and 30 <= n <= 60 and st["drawn"] >= n
    assert set(np.unique(v["origin"])) == {0, 1}  # both roadmap nodes and Eq. 1 edge samples
    cams = torch.as_tensor(v["camera_poses"])
    assert not OcclusionChecker.from_scene(scene, "cup").occluded(cams).any()
    cup = scene.target("cup")
    # the line-of-sight manifold puts the cup on the optical axis: inside the image, in front of the camera
    assert target_in_fov(v["camera_poses"], cup.center, robot.config.intrinsics).mean() > 0.9
    assert np.allclose(v["distance"], np.linalg.norm(v["camera_poses"][:, :3, 3] - cup.center, axis=1))
    again = roadmap_views(scene, ["cup"], 60, nodes=300, seed=3, edge_fraction=0.5, robot=robot)
    assert np.allclose(again["camera_poses"], v["camera_poses"])  # seeded
    with pytest.raises(ValueError, match="edge_fraction"):
        roadmap_views(scene, ["cup"], 10, edge_fraction=1.5, robot=robot)
