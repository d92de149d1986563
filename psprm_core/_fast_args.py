"""Named tuples of the arrays and settings the compiled kernels take (re-exported by :mod:`psprm_core._fast_numba`,
built and cached by :mod:`psprm_core.fastpath`): the arrays that always travel together reach a kernel as one
argument each, whose fields the kernels read by name.

numba compiles a kernel for the layout of the tuples it was called with but keys its disk cache on their class
only, so the kernel modules import the tuples they take from here: this file is then part of their recorded
``CALLEES_SHA256``, and a change to a tuple's fields changes the files of the kernels compiled for it.
"""

from collections import namedtuple

#: Joint type codes of ``RobotArrays.jtype``.
ROOT, REVOLUTE, PRISMATIC = 0, 1, 2

#: The body tree and camera of a robot (RobotModel): ``order`` every body but the root in FK order, ``chain`` the
#: camera chain's bodies but the root in FK order (both int64); per body ``parent`` (NB,) int64, joint type ``jtype``
#: (NB,) int64 (ROOT, REVOLUTE, PRISMATIC), joint origin ``R_off`` (NB, 3, 3) / ``t_off`` (NB, 3), joint ``axis``
#: (NB, 3); the drive matrix ``D`` (dof, NB) and offsets ``off`` (NB,) (joint value = q D + off); ``mobile`` (a
#: planar base in q[:3]); the camera's body ``cam_body`` and optical-frame offset ``cam_R`` (3, 3) / ``cam_t`` (3,).
RobotArrays = namedtuple("RobotArrays", "order chain parent jtype R_off t_off axis D off mobile cam_body cam_R cam_t")

#: What a collision check tests against (CollisionChecker): joint limits ``lower`` / ``upper`` (dof,); the bodies
#: with elements ``bodies``, per body the bounding sphere ``body_c`` / ``body_r`` and box ``body_box_c`` /
#: ``body_box_h``, its elements ``el_order[el_start[b]:el_start[b] + el_count[b]]``; per element its body
#: ``el_body``, box (``el_c``, ``el_R``, ``el_h``) and sphere radius ``el_r``; the self-collision element ``pairs``
#: (P, 2) and the elements they use ``pair_els``; the obstacle boxes ``box_c`` (K, 3), ``box_R`` (K, 3, 3),
#: ``box_h`` (K, 3) and their bounds ``box_aabb`` (K, 6); the separating-axis tolerance ``eps``.
CollisionArrays = namedtuple("CollisionArrays", "lower upper bodies body_c body_r body_box_c body_box_h el_start "
                                                "el_count el_order el_body el_c el_R el_h el_r pairs pair_els box_c "
                                                "box_R box_h box_aabb eps")

#: A projection onto the visibility manifold (VisibilityConstraint.project with ProjectionSettings): the world
#: ``target`` (3,), the planning joints ``cols`` (k,) int64, the model (``line``: the line model, else the frustum)
#: with its ``min_distance``, ``far``, the half-angle tangents ``th`` / ``tv`` and the frustum ``margin``; the
#: bounds ``lo`` / ``hi`` (dof,) of the result; the stopping tolerance ``tol`` on |h|, at most ``max_iters``
#: steps, the Gauss-Newton ``damping`` and step cap ``max_step``.
ProjectionArgs = namedtuple("ProjectionArgs", "target cols line min_distance far th tv margin lo hi tol max_iters "
                                              "damping max_step")

#: The surrogate MLP of one class, float32 (PerceptionSurrogate with its feature normalisation and the class's
#: one-hot column folded into the first layer): first layer ``w1`` (F, H) / ``b1`` (H,), hidden layers ``ws``
#: (L, H, H) / ``bs`` (L, H), output ``wo`` (H,) / ``bo`` (a float32).
MlpArrays = namedtuple("MlpArrays", "w1 b1 ws bs wo bo")

#: The occluders of a target (OcclusionChecker): the target's M sample points ``pts_local`` (M, K, 3) and their
#: centre ``centre_local`` (K, 3) in every box frame, the boxes inflated by the points' radius ``fat_half`` (K, 3),
#: the boxes (``box_c`` (K, 3), ``box_R`` (K, 3, 3), ``box_h`` (K, 3)), whether a ray starting inside a box counts
#: as blocked (``count_inside``) and the smallest ray direction component ``eps``.
OcclusionArrays = namedtuple("OcclusionArrays", "pts_local centre_local fat_half box_c box_R box_h count_inside eps")

#: A single-target neural scorer (NeuralScorer): the target pose ``target_pose`` (4, 4), whether the pose features
#: include the derived ones (``derived``), the class's MLP ``mlp`` (:data:`MlpArrays`), whether occlusion applies
#: (``has_occ``) and the occluders ``occ`` (:data:`OcclusionArrays`; empty placeholders without it), and the
#: occlusion threshold ``tau`` above which a view scores zero.
ScorerArgs = namedtuple("ScorerArgs", "target_pose derived mlp has_occ occ tau")

#: How a query's edges are built and verified: the Eq. 1 samples per edge ``n_interp``, the motion metric
#: (``w_rot``, ``mobile``: DiffDriveMotion), whether the interior knots' camera joints re-aim (``track``), whether
#: values are rounded to float32 between stages (``r32``: the float32 torch path), the dense check's ``resolution``
#: and step cap ``max_steps``, and the views per compiled MLP call ``mlp_rows``. Building knots alone
#: (:func:`~psprm_core._fast_query.query_knots`) reads the first five.
EdgeArgs = namedtuple("EdgeArgs", "n_interp w_rot mobile track r32 resolution max_steps mlp_rows")
