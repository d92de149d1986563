"""Settings of online replanning (:class:`ReplanSettings`, ``config/planners/replan.yaml``): triggers, the keep
decision, goal hysteresis, repair, timing of the replanned trajectories, commitment and target prediction."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..prediction import PredictionSettings
from ..yamlio import Fields, dataclass_kwargs, load_yaml
from .settings_groups import field_specs, setting

HEURISTICS = ("exact", "hop", "planner")


@dataclass(frozen=True)
class ReplanSettings:
    """Replanning triggers and repair (``config/planners/replan.yaml``). Each field carries its metadata
    (:func:`~.settings_groups.setting`: description, range or choices; ``live``: a running server changes it through its
    parameter of the field's name), listed by :meth:`specs`."""

    target_move_m: float = setting(0.05, "target translation that counts as a move (m; re-score, replan)", live=True)
    target_turn_rad: float = setting(0.15, "target rotation that counts as a move (rad)", live=True)
    obstacle_move_m: float = setting(0.03, "obstacle translation that counts as a move (m; re-check, replan)",
                                     live=True)
    obstacle_turn_rad: float = setting(0.1, "obstacle rotation that counts as a move (rad)", live=True)
    turning_hull: bool = setting(True, "an obstacle seen turning in place about its vertical axis by more than "
                                       "obstacle_turn_rad (a person's body) is planned against at every heading it "
                                       "can take (scene.Box.swept); its real box stays what a path must not touch")
    turning_hold_s: float = setting(10.0, "... until it has not turned for this long (s)", range=(0.0, None))
    turning_in_place_m: float = setting(0.15, "... a turn counts when the centre stays within this of where the turn "
                                              "began (m; a walking person or a carried chair does not turn in place)",
                                        range=(0.0, None))
    focus_move_m: float = setting(0.25, "the visibility focus follows a target that moved further than this (m)")
    replan_on_move: bool = setting(False, "a target/obstacle move alone triggers a replan (else it triggers the "
                                          "score and collision checks, and those decide)", live=True)
    score_min: float = setting(0.1, "replan when the predicted normalised score along the remaining path falls below "
                                    "this (and, for a plan made below it, whenever the target moved)", live=True)
    score_drop: float = setting(0.15, "... or drops by more than this since the plan (scores normalised as in "
                                      "Eq. 1)", live=True)
    goal_switch_margin: float = setting(0.2, "goal hysteresis: switch to another goal only when it is cheaper by "
                                             "this fraction of the current plan's cost", live=True)
    final_approach_m: float = setting(1.0, "no score-triggered replan within this base path length of the goal (m); "
                                           "a collision or a new goal still replans", live=True)
    goal_commit_s: float = setting(10.0, "keep a chosen goal this long (s) unless no path reaches it (0: off)",
                                   live=True)
    goal_commit_growth: float = setting(2.0, "each goal switch multiplies the next commitment by this (1: constant); "
                                             "a new goal set starts again at goal_commit_s", range=(1.0, None),
                                        live=True)
    keep_unless_better: bool = setting(True, "a replan the view alone triggered replaces the trajectory only when it "
                                             "sees more or is shorter (else the robot keeps driving it)", live=True)
    keep_score_margin: float = setting(0.05, "normalised mean score along the path a new plan must add to replace "
                                             "the current", live=True)
    keep_length_margin: float = setting(0.1, "fraction of the remaining path's motion cost a new plan must save to "
                                             "replace the current (predicted to see no less)", live=True)
    keep_length_min_score: float = setting(0.0, "a shorter plan replaces the current only when it is predicted to see "
                                                "at least this (normalised mean score): two routes both predicted to "
                                                "see nothing are not told apart by the views", live=True)
    arrival_budget: float = setting(0.5, "a replan the view alone triggered may delay the arrival to at most the first "
                                         "plan's duration times (1 + this) after the plan for the goals was made, or "
                                         "else arrive no later than the current plan (0: no bound)",
                                    range=(0.0, None), live=True)
    arrival_reference: str = setting("fastest", "the duration the arrival budget multiplies: fastest (the route of "
                                                "least motion over the roadmap to the goals, from where the first plan "
                                                "for them started) | plan (that first plan's own duration)",
                                     choices=("fastest", "plan"), live=True)
    min_interval_s: float = setting(1.0, "at most one score/move-triggered replan per interval (s)", live=True)
    score_samples: int = setting(200, "configurations of the remaining path scored for the score trigger",
                                 range=(1, None))
    repair_rounds: int = setting(2, "roadmap repair attempts when no goal is reachable")
    repair_nodes: int = setting(150, "nodes sampled per repair round")
    repair_radius_m: float = setting(1.5, "repair nodes around the moved obstacles and the start within this (m)")
    repair_budget_nodes: int = setting(1500, "at most this many nodes added by repair over the replanner's life")
    heuristic: str = setting("exact", "A* heuristic of the replans: exact (cost-to-go from one compiled Dijkstra over "
                                      "the current weights) | hop (Eq. 3) | planner (the planner's query.heuristic)",
                             choices=HEURISTICS)
    smooth_timing: bool = setting(True, "replanned trajectories pass the knots of a base phase without stopping "
                                        "(about a third shorter to execute, about +25 ms per replan)")
    shortcut: bool = setting(False, "perception-preserving shortcuts of replanned paths (query.shortcut; tens of ms "
                                    "per replan)")
    route_selection: bool = setting(False, "the planner's route selection (query.route_searches) in replans (each "
                                           "extra search adds a search's time)")
    commit: bool = setting(True, "a robot in motion replans from its committed state: the trajectory under way is "
                                 "kept to its first rest instant after planning and delivery, the new plan is spliced "
                                 "on there", live=True)
    commit_horizon_s: float = setting(0.3, "planning and delivery time when the caller gives none (s)")
    predict_lead_s: float = setting(1.5, "the roadmap is scored against the target pose extrapolated this far ahead "
                                         "(s)")
    score_bins: int = setting(4, "a path's predicted score: its duration split into this many stretches, each scored "
                                 "against the targets' predicted poses at its middle", range=(1, None))
    predict_samples: int = setting(48, "... at this many configurations of the path, evenly in time",
                                   range=(1, None))
    predicted_routes: bool = setting(False, "a replan also searches the roadmap scored against each other heading of "
                                           "the targets' predicted mixture and keeps the route of the best predicted "
                                           "objective (a re-scoring and a search per heading)", live=True)
    predicted_route_turn_rad: float = setting(0.5, "... the headings that differ by more than this (rad) from the "
                                                   "extrapolated one and from each other", range=(0.0, None),
                                              live=True)
    prediction: PredictionSettings = field(default_factory=PredictionSettings)

    def __post_init__(self):
        for spec in self.specs():
            spec.check(getattr(self, spec.name), "replan settings")

    @staticmethod
    def specs() -> tuple:
        """Every field but ``prediction`` as a :class:`~.settings.SettingSpec` (named by the field's name)."""
        return field_specs(ReplanSettings)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "ReplanSettings":
        return cls(**dataclass_kwargs(cls, Fields(load_yaml(path), str(path))))
