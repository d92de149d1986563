"""The roadmap server's planning loop, without ROS: :class:`PlanningLoop` (the worker and every decision about what
the robot is sent), its inputs, outputs, parameters, checks, the robot's measured motion and the views it publishes.
The ``roadmap_server`` node only converts messages; tests drive the loop directly."""

from .loop import PlanningLoop
from .outputs import Outputs, TrajectorySamples
from .params import LOOP_PARAMS, default_params, live_replan

__all__ = ["PlanningLoop", "Outputs", "TrajectorySamples", "LOOP_PARAMS", "default_params", "live_replan"]
