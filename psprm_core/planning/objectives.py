"""Edge weights of the roadmap (Eqs. 1-2) and the motion-weighted objective.

* Eq. 1, :func:`edge_perception`: :math:`c_p(q_u, q_v) = (c_p(q_u) + c_p(q_v) + \\sum_{i=1}^N c_p(q_i)) / (N + 2)`.
* Eq. 2, :func:`combined_weight`: :math:`c(q_u, q_v) = 1 - \\alpha c_p(q_u, q_v) + (1 - \\alpha) c_m(q_u, q_v)`.
* Beside Eq. 2, :func:`motion_weighted` charges the perception loss per unit of motion,
  :math:`c = c_m ((1 - \\alpha) + \\alpha (1 - c_p))`, with the consistent heuristic :func:`motion_heuristic`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InputError

ArrayLike = Any  # numpy array, torch tensor or Python float
#: Relative shrink of :math:`c^{\min}` in Eq. 3 so that floating-point rounding cannot break Eqs. 5-6.
_CMIN_SAFETY = 1.0 - 1e-12


def edge_perception(scores_u: ArrayLike, scores_v: ArrayLike, interior: ArrayLike | None = None) -> ArrayLike:
    """Normalised perception score of edges, Eq. 1.

    .. math:: c_p(q_u, q_v) = \\frac{c_p(q_u) + c_p(q_v) + \\sum_{i=1}^{N} c_p(q_i)}{N + 2}

    Parameters
    ----------
    scores_u, scores_v : array-like, shape (E,)
        Normalised perception scores :math:`c_p \\in [0, 1]` of the edge endpoints (numpy or torch).
    interior : array-like, shape (E, N), optional
        Scores of the :math:`N` interpolated intermediate configurations of each edge (``N`` may be 0);
        same library as the endpoint scores.

    Returns
    -------
    array-like, shape (E,)
        :math:`c_p(q_u, q_v)`, same type (numpy / torch) as the inputs.
    """
    if interior is None:
        return (scores_u + scores_v) / 2.0
    n_interior = interior.shape[-1]
    return (scores_u + scores_v + interior.sum(-1)) / float(n_interior + 2)


def combined_weight(p_edge: ArrayLike, c_motion: ArrayLike, alpha: float) -> ArrayLike:
    """Combined PS-PRM edge weight, Eq. 2: :math:`c = 1 - \\alpha c_p + (1 - \\alpha) c_m`.

    Parameters
    ----------
    p_edge : array-like
        Normalised edge perception score :math:`c_p(q_u, q_v) \\in [0, 1]` (Eq. 1); numpy, torch or float.
    c_motion : array-like
        Normalised motion cost :math:`c_m(q_u, q_v) \\in [0, 1]`.
    alpha : float
        Trade-off :math:`\\alpha \\in [0, 1]` (1 = perception only, 0 = motion only).

    Returns
    -------
    array-like
        Edge weight in :math:`[0, 2]` (non-negative as required by the consistency proof, Eqs. 5-6).
    """
    if not 0.0 <= float(alpha) <= 1.0:
        raise InputError(f"alpha must lie in [0, 1], got {alpha}")
    return 1.0 - alpha * p_edge + (1.0 - alpha) * c_motion


#: Edge-weight forms: ``eq2`` (the paper's Eq. 2) and ``motion`` (perception loss per unit of motion).
OBJECTIVES = ("eq2", "motion")


def motion_weighted(p_edge: ArrayLike, c_motion: ArrayLike, alpha: float) -> ArrayLike:
    """Motion-weighted edge weight: :math:`c = c_m \\left((1 - \\alpha) + \\alpha (1 - c_p)\\right)`.

    The perception loss :math:`1 - c_p` (Eq. 1) is charged per unit of motion, so a path's cost is
    :math:`(1 - \\alpha) L + \\alpha U` with :math:`L` its motion length and :math:`U` the length along which the
    target is not seen (both in units of the roadmap's longest edge). Unlike Eq. 2 it charges nothing per edge: the
    cost does not grow with the hop count, and a long edge pays for every part of it that sees poorly. Every weight
    is at least
    :math:`(1 - \\alpha) c_m`, which makes a lower bound of the motion to the goal an admissible, consistent heuristic
    (:func:`motion_heuristic`).
    """
    if not 0.0 <= float(alpha) <= 1.0:
        raise InputError(f"alpha must lie in [0, 1], got {alpha}")
    return c_motion * ((1.0 - alpha) + alpha * (1.0 - p_edge))


def edge_weight(p_edge: ArrayLike, c_motion: ArrayLike, alpha: float, objective: str = "eq2") -> ArrayLike:
    """Edge weight of the objective form ``objective`` (:data:`OBJECTIVES`): :func:`combined_weight` (Eq. 2) or
    :func:`motion_weighted`."""
    if objective == "eq2":
        return combined_weight(p_edge, c_motion, alpha)
    if objective == "motion":
        return motion_weighted(p_edge, c_motion, alpha)
    raise InputError(f"unknown objective {objective!r} (one of {', '.join(OBJECTIVES)})")


def motion_heuristic(lower_bound: np.ndarray, alpha: float, scale: float) -> np.ndarray:
    """Consistent A* heuristic of the :func:`motion_weighted` form: :math:`h(q) = (1 - \\alpha) d(q) / s`.

    ``lower_bound`` (n,): for each node a lower bound :math:`d(q)` of the motion cost of any path from it to the goal
    set, which is a metric's distance to the nearest goal (so :math:`d(q_u) \\le m(q_u, q_v) + d(q_v)` on every edge
    whose motion cost is :math:`m`); ``scale`` the motion cost that :math:`c_m = 1` stands for. Every edge weighs at
    least :math:`(1 - \\alpha) m / s`, hence :math:`h(q_u) \\le c(q_u, q_v) + h(q_v)` (Eqs. 5-6). ``inf`` stays
    ``inf``. Shrunk by a relative 1e-12 against rounding, like Eq. 3."""
    return np.asarray(lower_bound, dtype=np.float64) * ((1.0 - float(alpha)) / float(scale) * _CMIN_SAFETY)
