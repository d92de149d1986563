"""The grouped inputs of the compiled kernels (:mod:`psprm_core.kernels._fast_numba`): named tuples of arrays and
scalars, one per object whose data a kernel reads, each built by that object's class (``RobotModel.kernel_pack``,
``CollisionChecker.kernel_pack``, ``VisibilityConstraint.kernel_pack``, ``PerceptionSurrogate.kernel_layers``,
``OcclusionChecker.kernel_pack``, ``DiffDriveMotion.kernel_pack``) or by :mod:`psprm_core.kernels.fastpath` from a
call's arguments (:class:`SolverPack`, :class:`EdgeOpts`, :class:`ScorerPack`, the edge batches). numba passes named
tuples into compiled functions as typed structs; the kernels read their fields into locals once per call.

Also the joint type codes of :attr:`RobotPack.jtype`. Nothing here imports numba. The kernel modules import this one,
so that its source is part of their ``CALLEES_SHA256`` (a changed field order changes the cached kernels too).
"""

from collections import namedtuple

ROOT, REVOLUTE, PRISMATIC = 0, 1, 2  # RobotPack.jtype: the root body, a revolute joint, a prismatic joint

#: A robot's body tree and camera (RobotModel._poses, RobotModel._camera_from_body): the bodies in FK order (root
#: excluded), the camera chain's order, parent body (NB,), joint type (NB,), joint origin R_off (NB, 3, 3) and t_off
#: (NB, 3), joint axis (NB, 3), drive matrix D (dof, NB) and offset (NB,), whether the base is a diff-drive base, and
#: the camera's body with its offset (cam_R (3, 3), cam_t (3,)) in that body's frame. float64, int64.
RobotPack = namedtuple("RobotPack", "bodies chain parent jtype R_off t_off axis D off mobile cam_body cam_R cam_t")

#: Obstacle boxes (BoxTensors): centres (K, 3), rotations box -> world (K, 3, 3), half extents (K, 3), world bounds
#: (K, 6) = [min xyz, max xyz].
BoxPack = namedtuple("BoxPack", "c R h aabb")

#: A collision checker's model (CollisionChecker): joint limits (dof,), the bodies with elements, body spheres and
#: boxes (body frame), each body's elements (start, count into el_order), the element boxes and radii, the
#: self-collision element pairs (P, 2) and the elements in them, the separating-axis eps and the obstacle boxes
#: (:class:`BoxPack`).
CollisionPack = namedtuple("CollisionPack", "lower upper bodies body_c body_r body_box_c body_box_h el_start el_count "
                                            "el_order el_body el_c el_R el_h el_r pairs pair_els eps boxes")

#: The visibility residual h_M (VisibilityConstraint.residual_jacobian): target point (3,), line model (else frustum),
#: minimum distance, far plane, tangents of the half fields of view, frustum margin.
ViewPack = namedtuple("ViewPack", "target line min_distance far th tv margin")

#: The damped Gauss-Newton iteration (VisibilityConstraint.project): the joints it moves (k,), the bounds (dof,),
#: tolerance on |h|, step count, damping and step-norm cap.
SolverPack = namedtuple("SolverPack", "cols lo hi tol max_iters damping max_step")

#: The motion metric (DiffDriveMotion.distance): weight of the base rotations, diff-drive base or not.
MotionPack = namedtuple("MotionPack", "w_rot mobile")

#: A query's edges (PSPRM.edge_knots, Edges.knots_valid): the motion (:class:`MotionPack`), Eq. 1 samples per edge,
#: whether the camera joints re-aim, whether to round to float32 between stages, the dense check's resolution and
#: step cap, and the views per compiled MLP call.
EdgeOpts = namedtuple("EdgeOpts", "motion n_interp track r32 resolution max_steps mlp_rows")

#: The surrogate MLP of one class (PerceptionSurrogate with the feature normalisation and the class folded into the
#: first layer), float32: W1^T (F, H), b1 (H,), hidden W^T (L, H, H) and b (L, H), output weights (H,) and bias.
MlpPack = namedtuple("MlpPack", "w1 b1 ws bs wo bo")

#: Ray-cast occlusion (OcclusionChecker): the target's points (M, K, 3) and centre (K, 3) in every box frame, the boxes
#: grown by the points' radius (K, 3), box centres (K, 3), rotations (K, 3, 3), half extents (K, 3), whether a ray
#: starting inside a box counts, the direction eps.
OcclusionPack = namedtuple("OcclusionPack", "pts_local centre_local fat_half c R h count_inside eps")

#: A single-target neural scorer (NeuralScorer): target pose (4, 4), derived features or not, the MLP
#: (:class:`MlpPack`), whether occlusion applies, its :class:`OcclusionPack` and the threshold tau.
ScorerPack = namedtuple("ScorerPack", "tgt derived mlp has_occ occ tau")
