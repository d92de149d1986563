"""What the planning loop hands out: trajectory samples, and the :class:`Outputs` a node (or a test) implements."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class TrajectorySamples(NamedTuple):
    """A trajectory as published: one row per point, times from its start (s); the last point at rest."""

    times: np.ndarray  # (M,)
    positions: np.ndarray  # (M, dof), planning joint order
    velocities: np.ndarray  # (M, dof)
    accelerations: np.ndarray  # (M, dof)


class Outputs:
    """Where the loop's results go; every method does nothing here. The roadmap server's implementation builds and
    publishes the messages, a test records the calls. Methods run on the worker thread, except :meth:`stop` (also
    on the thread that delivered an obstacle pose, for the stop guard), :meth:`status` (any thread) and
    :meth:`roadmap_markers`, :meth:`path`, :meth:`base_path` (the loop's side thread, while the planner is idle)."""

    def trajectory(self, samples: TrajectorySamples) -> None:
        """Publish these samples as the robot's trajectory (called only after the final check passed them)."""

    def stop(self, q: np.ndarray, hold_s: float) -> None:
        """Publish a trajectory that holds ``q`` at rest for ``hold_s`` seconds."""

    def info(self, info: dict) -> None:
        """Publish one plan's record (JSON-serialisable: floats, ints, strings, lists, None)."""

    def status(self, text: str, level: str = "info") -> None:
        """Report a line (level info, warning or error)."""

    def state(self, text: str) -> None:
        """The server's state ("building", "ready: ...", "inactive: ...", "unconfigured", "error: ...")."""

    def roadmap_cameras(self, cameras: np.ndarray) -> None:
        """Camera poses (N, 4, 4) of every roadmap node slot, in slot order (the perception scorer's order)."""

    def roadmap_markers(self, scene, cam_xyz: np.ndarray, scores: np.ndarray, base_xy: np.ndarray,
                        edges: np.ndarray) -> None:
        """The roadmap drawn in ``scene``: valid nodes' camera positions (N, 3), normalised scores (N,), base
        positions (N, 2) and edges (E, 2) as row indices into them."""

    def path(self, cameras: np.ndarray, base_xy: np.ndarray, scores: np.ndarray, scene) -> None:
        """Camera poses (K, 4, 4) along the planned path, its base positions (K, 2) and normalised scores (K,)."""

    def base_path(self, positions: np.ndarray) -> None:
        """The base route of a published trajectory (its positions (M, dof))."""

