"""Time parameterisation of a PS-PRM joint-space path (waypoints of the A* path over the roadmap, Eqs. 2-6).

The planner returns a piecewise-linear path in joint space: consecutive roadmap nodes joined by straight edges (the
edges whose perception cost Eq. 1 was evaluated on interpolated configurations).  :func:`time_parameterize` turns it
into a :class:`Trajectory` that respects per-joint velocity and acceleration limits while following that path
**exactly**:

* no corner blending: at a corner the path direction is discontinuous, so finite accelerations require the robot to
  be at rest there; every corner is therefore a stop, and each straight *run* between corners is time-parameterised
  rest-to-rest.  Consecutive segments that are collinear and point the same way (within ``collinear_tol``) are merged
  into one run, so intermediate waypoints on a straight line are passed without stopping.
* along a run, TOPP-RA (``toppra``, ``method="toppra"``) solves the time-optimal path parameterisation with the joint
  velocity and acceleration constraints on a grid of path positions; since the run is a straight line
  (:math:`q'' = 0`) the constant-acceleration interpolation between grid points satisfies the limits everywhere and
  keeps every sample on the line.  ``method="analytic"`` uses the closed-form time-optimal trapezoidal / triangular
  profile of a straight rest-to-rest run (identical constraints; it is also the fallback when ``toppra`` is missing).
* mobile base: three dof ``(x, y, theta)`` of a differential drive.  The caller guarantees that between consecutive
  waypoints the base either rotates in place or translates along its heading; linear interpolation in joint space
  keeps exactly that geometry (theta constant during translations, x/y constant during rotations), and since every
  sample lies on the joint-space segment the base never leaves it.  :func:`check_base_segments` verifies the
  guarantee (``validate_base=True``).  An optional linear speed / acceleration limit of the base (norm of the (x, y)
  velocity) is enforced exactly by folding it, per straight run, into the x/y joint limits.
* ``smooth=True`` (what the planner uses on mobile robots): consecutive segments in which the base keeps one motion
  (drives along one line in one direction, turns one way, or stands still) form one *phase*, timed rest-to-rest as a
  whole: the joints follow a shape-preserving cubic (PCHIP) through the phase's waypoints, parameterised by the base's
  progress (so the base still moves exactly along its line or turns in place), and TOPP-RA times it. The robot then
  stops only where the base changes its motion (the drive corners), not at every re-aiming knot. Between two waypoints
  a PCHIP joint stays within the two waypoint values (no overshoot) but the configuration leaves the straight
  segment: the caller must collision-check the samples (the planner does, and falls back to ``smooth=False``).
  Samples between TOPP-RA's grid points are checked against the limits and the phase is slowed down uniformly when a
  limit is exceeded.
* continuous (unbounded angle) joints are unwrapped (``np.unwrap``) before timing, so they take the short way; the
  output keeps the unwrapped values (start equals the input start, later values may differ by multiples of
  :math:`2\\pi`).
"""

from .parameterize import (ProfileCache, SMOOTH_SLOWER_LIMIT, Trajectory, check_base_segments, max_limit_violation,
                           path_deviation, time_parameterize)

__all__ = [
    "ProfileCache",
    "SMOOTH_SLOWER_LIMIT",
    "Trajectory",
    "check_base_segments",
    "max_limit_violation",
    "path_deviation",
    "time_parameterize",
]
