"""The planning loop's parameters, its constants and the live replan settings a running server changes (the planner's
settings are declared from their specs by the roadmap server, :func:`psprm_ros.planner_setup.server_setting_specs`)."""

from __future__ import annotations

import functools
from typing import Optional

import numpy as np

from psprm_core.paths import resolve_named
from psprm_core.planning.replanner import ReplanSettings

from .. import core

P = core.Param
#: a spliced trajectory reaches the robot this long after the loop is done with it (publication, the adapter's
#: checks) at most, on top of the age of the robot state the splice was measured from
SPLICE_DELIVERY_S = 0.25
#: the adapter starts a trajectory that does not continue the one under way this long after its publication (s)
ADAPTER_LEAD_S = 0.15
#: the parameters the loop reads (the roadmap server declares them; live ones are read at each use)
LOOP_PARAMS = {
    "plan_on_start": P(False, "plan to goal_regions as soon as the node is active"),
    "auto_replan": P(True, "ask the replanner's triggers after every state update", live=True),
    "trajectory_dt": P(0.1, "sample spacing of the published trajectory (s)", live=True, lo=0.01, hi=1.0),
    "robot_state_timeout_s": P(1.0, "plan only with a robot state (joints and base pose) at most this old", live=True,
                               lo=0.05),
    "publish_markers": P(True, "RViz markers of the scene, roadmap and path", live=True),
    "markers_period_s": P(5.0, "roadmap markers at most this often, built while the planner is idle", live=True,
                          lo=0.1),
    "path_camera_samples": P(200, "camera poses along the path sent to the perception scorer", live=True, lo=2),
    "robot_trigger_period_s": P(0.5, "re-evaluate the triggers on robot progress at most this often", live=True,
                                lo=0.0),
    "safety_step": P(0.05, "spacing (m / rad) of the final collision check along the published trajectory",
                     live=True, lo=0.005, hi=0.2),
    "stop_hold_s": P(0.25, "time_from_start of the stop trajectory's one point", live=True, lo=0.01),
    "stop_horizon_s": P(1.5, "the stop guard: an obstacle pose that collides with the next this-many seconds of the "
                             "trajectory being executed stops the robot at once, on the message's arrival, before the "
                             "replan (0 = off: the robot follows the old trajectory until a new one is planned)",
                        live=True, lo=0.0),
    "commit_horizon_min_s": P(0.25, "a replan of a robot in motion commits at least this far ahead (s): planning "
                                    "and delivery, measured from recent replans, clamped to [min, max]", live=True,
                              lo=0.0),
    "commit_horizon_max_s": P(1.5, "... and at most this far", live=True, lo=0.0),
    "progress_tolerance_m": P(0.025, "the robot counts as following the trajectory under way (and a replan starts "
                                     "from its committed state) while no point of its collision boxes is further "
                                     "than this from where the trajectory has it (m; below the adapter's path "
                                     "tolerance) and it moves when the trajectory does; otherwise a replan starts "
                                     "from where it is", live=True, lo=0.0),
    "start_tolerance_m": P(0.035, "a plan that starts from the robot's state (not spliced) is not published when the "
                                  "robot, braking from its newest state, has meanwhile come further than this from "
                                  "the trajectory's configurations near its start (m; below the adapter's path "
                                  "tolerance, which would refuse it and stop the robot): a replan from the newest "
                                  "state follows at once while the robot keeps what it executes (0 = off)",
                           live=True, lo=0.0),
    "start_joint_tolerance": P(0.1, "... and when a joint other than the base's lies further than this from the "
                                    "trajectory's sample nearest the robot (rad or m; below the adapter's "
                                    "controllers' start tolerances, 0.25 in the shipped configs; 0 = off)",
                               live=True, lo=0.0),
    "settle_timeout_s": P(1.5, "a plan from a base that moves with nothing under way for it (braking from a stop, "
                               "the adapter's included) waits until the base rests, so that it starts where the "
                               "robot stands and the adapter takes it; at most this long, then it starts from "
                               "where the base is predicted to rest (s; 0 = plan at once from that prediction)",
                          live=True, lo=0.0),
}
#: a base whose braking takes it at most this far from where it is counts as at rest (m)
SETTLED_M = 0.002
#: plans withdrawn in a row for a stale start before one is handed to the robot anyway (the adapter decides)
MAX_STALE_STARTS = 2


@functools.lru_cache(maxsize=None)
def live_replan() -> dict:
    """The replanner's settings a running server changes live, by name: the ``live`` fields of
    :class:`~psprm_core.planning.replanner.ReplanSettings` as their
    :class:`~psprm_core.planning.settings_groups.SettingSpec` (their defaults come from the replan settings file)."""
    return {spec.name: spec for spec in ReplanSettings.specs() if spec.live}


TRANSITIONS = ("configure", "activate", "deactivate", "cleanup", "shutdown")
REQUESTS = ("plan", "rebuild", "stop")


def default_params(replan_settings: str = "") -> dict:
    """Values of :data:`LOOP_PARAMS` and of the live replan settings (defaults from ``replan_settings``, a name in
    config/planners/ or a YAML path; '' = the ReplanSettings defaults)."""
    rs = ReplanSettings.from_yaml(resolve_named("planner", replan_settings)) if replan_settings else ReplanSettings()
    return {**{k: v.default for k, v in LOOP_PARAMS.items()}, **{k: getattr(rs, k) for k in live_replan()}}


def finite_or_none(x) -> Optional[float]:
    """A finite float, else None (JSON has no NaN)."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if np.isfinite(x) else None
