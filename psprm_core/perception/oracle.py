"""The perception oracle (ground truth): render the camera's view and score it with a real pretrained detector.

``Oracle.score(camera_pose, target)`` renders the view with :class:`~psprm_core.perception.render.SceneRenderer`,
runs the detector for the target's class and returns the confidence of the best detection of that class whose box
matches the target's projected box (:func:`boxes_match`). The score is 0 when nothing matches, when the target's
box projects outside the image, or when it is behind the camera (those cases skip rendering altogether).

Detector-specific "detected" thresholds live in :data:`DETECTION_THRESHOLDS`; ``docs/detectors.md`` explains how they
were calibrated (``psprm calibrate-detectors`` reproduces the measurement).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Dict, Iterable, List, Mapping, Optional, Sequence, Union

import numpy as np

from ..camera import CameraIntrinsics
from ..scene import Scene
from .detectors import Detection, Detector, default_detector_name, make_detector
from .metrics import DEFAULT_THRESHOLD
from .render import SceneRenderer

log = logging.getLogger(__name__)

#: Confidence at or above which a target counts as "detected", per detector (optionally per ``"detector:class"``);
#: chosen by ``psprm calibrate-detectors`` (see docs/detectors.md).
DETECTION_THRESHOLDS: Dict[str, float] = {
    "centerface": 0.34,  # faces: 0-40 deg at 1-2.5 m score 0.67-0.92; 75-180 deg and 80 % occluded score 0
    "centernet": 0.14,  # pooled over tv + potted plant (TPR 0.90, FPR 0.18)
    "centernet:tv": 0.23,  # the screen's back still scores up to 0.21 (TPR 0.93, FPR 0)
    "centernet:potted plant": 0.10,  # floor value; plants look alike from every side (TPR 0.90)
    "centernet-tiled": 0.10,  # 8 cm cup at 0.6-1.5 m: floor value (TPR 0.45, FPR 0)
}

#: A *confident* detection, per detector (optionally per ``"detector:class"``): the median confidence of the
#: detector's positive calibration views (unoccluded, 0-40 deg off-axis, at the case's four distances; pooled like
#: :data:`DETECTION_THRESHOLDS`, ``psprm calibrate-detectors`` prints it as ``strict``), never below the calibrated
#: threshold. A view counted at the calibrated threshold may be a barely-detected one; at this one it scores like a
#: typical good view of the target. Detectors missing here use their calibrated threshold.
STRICT_THRESHOLDS: Dict[str, float] = {
    "centerface": 0.84,
    "centernet": 0.30,  # pooled over tv + potted plant
    "centernet:tv": 0.37,
    "centernet:potted plant": 0.16,
    "centernet-tiled": 0.10,  # the 8 cm cup's positives have a median of 0.09: no view is confident beyond the floor
}


@dataclass(frozen=True)
class MatchConfig:
    """When a detection box is taken to be the target.

    A detection of the target's class matches the target's projected box ``T`` if

    * ``IoU(det, T) >= iou``, or
    * ``area(det ∩ T) / area(det) >= containment`` (the detection lies mostly inside the target's box) and
      ``area(det) >= min_area_fraction * area(T)`` (it is not a tiny unrelated blob inside it).

    Containment matters because the target's box is the *whole* object's box (a head, a cup with saucer...) while
    detectors box only the part they recognise (the face, the cup's body).
    """

    iou: float = 0.3
    containment: float = 0.7
    min_area_fraction: float = 0.1


@dataclass
class OracleResult:
    """Outcome of one oracle query.

    Attributes
    ----------
    score : float
        Matched detection's confidence in [0, 1], 0 when not detected / not in view.
    detected : bool
        ``score >= threshold``.
    threshold : float
        The detector's calibrated threshold.
    detection : Detection or None
        The matched detection.
    projected_box : (4,) ndarray or None
        The target's projected box ``[x1, y1, x2, y2]`` (None when outside the view or behind the camera).
    image : (H, W, 3) uint8 ndarray or None
        The rendered view (None when not rendered or not kept).
    target : str
    detector_class : str
    detector : str
        Detector name.
    detections : list of Detection
        Everything the detector returned for this view.
    timings : dict
        Seconds spent in ``render`` and ``detect``.
    """

    score: float
    detected: bool
    threshold: float
    detection: Optional[Detection]
    projected_box: Optional[np.ndarray]
    image: Optional[np.ndarray]
    target: str
    detector_class: str
    detector: str
    detections: List[Detection] = field(default_factory=list)
    timings: Dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-friendly summary (no image)."""
        def box(b):
            return None if b is None else [round(float(v), 2) for v in b]

        return {
            "target": self.target, "class": self.detector_class, "detector": self.detector,
            "score": round(float(self.score), 4), "detected": bool(self.detected), "threshold": self.threshold,
            "detection_box": box(self.detection.box_xyxy) if self.detection else None,
            "projected_box": box(self.projected_box),
            "timings_ms": {k: round(1000 * v, 1) for k, v in self.timings.items()},
        }


def box_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two ``[x1, y1, x2, y2]`` boxes."""
    inter = _inter(a, b)
    union = _area(a) + _area(b) - inter
    return float(inter / union) if union > 0 else 0.0


def boxes_match(det: np.ndarray, target: np.ndarray, cfg: MatchConfig = MatchConfig()) -> bool:
    """Whether detection box ``det`` is the target with projected box ``target`` (see :class:`MatchConfig`)."""
    if box_iou(det, target) >= cfg.iou:
        return True
    a_det, a_t = _area(det), _area(target)
    if a_det <= 0 or a_t <= 0:
        return False
    return _inter(det, target) / a_det >= cfg.containment and a_det >= cfg.min_area_fraction * a_t


def _area(b) -> float:
    return max(0.0, float(b[2] - b[0])) * max(0.0, float(b[3] - b[1]))


def _inter(a, b) -> float:
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    return float(max(0.0, w) * max(0.0, h))


class Oracle:
    """Renderer + real detectors = ground-truth perception score of a camera pose for a target.

    Parameters
    ----------
    scene : Scene
    detectors : mapping or sequence of Detector, optional
        ``{class: detector}`` or a list of detectors (the first whose ``classes`` contains the target's class is
        used). Classes without a detector get the built-in one (CenterFace for ``face``, CenterNet for COCO classes),
        constructed the first time it is needed.
    intrinsics : CameraIntrinsics, optional
    renderer : SceneRenderer, optional
        Reuse an existing renderer of the same scene (the oracle then does not close it).
    match : MatchConfig, optional
    thresholds : mapping, optional
        Overrides of :data:`DETECTION_THRESHOLDS` by detector name.
    **renderer_kwargs
        Passed to :class:`SceneRenderer` when the oracle builds its own.
    """

    def __init__(self, scene: Scene, detectors: Union[Mapping[str, Detector], Sequence[Detector], None] = None, *,
                 intrinsics: Optional[CameraIntrinsics] = None, renderer: Optional[SceneRenderer] = None,
                 match: Optional[MatchConfig] = None, thresholds: Optional[Mapping[str, float]] = None,
                 **renderer_kwargs):
        self.scene = scene
        self._own_renderer = renderer is None
        self.renderer = renderer or SceneRenderer(scene, intrinsics, **renderer_kwargs)
        self.intrinsics = self.renderer.intrinsics
        self.match = match or MatchConfig()
        self.thresholds = dict(DETECTION_THRESHOLDS)
        self.thresholds.update(thresholds or {})
        self.strict_thresholds = dict(STRICT_THRESHOLDS)
        self._by_class: Dict[str, Detector] = {}
        self._pool: List[Detector] = []
        if isinstance(detectors, Mapping):
            self._by_class.update(detectors)
        elif detectors is not None:
            self._pool.extend(detectors)
        self._builtin: Dict[str, Detector] = {}

    # ---- lifetime ------------------------------------------------------------------------------------------------
    def close(self) -> None:
        if self._own_renderer:
            self.renderer.close()

    def __enter__(self) -> "Oracle":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- detectors -----------------------------------------------------------------------------------------------
    def detector_for(self, detector_class: str) -> Detector:
        """The detector used for a class (builds the built-in one on first use)."""
        if detector_class in self._by_class:
            return self._by_class[detector_class]
        for d in self._pool:
            if detector_class in d.classes:
                self._by_class[detector_class] = d
                return d
        name = default_detector_name(detector_class)
        if name not in self._builtin:
            t0 = time.perf_counter()
            self._builtin[name] = make_detector(name)
            log.info("loaded detector %s in %.2f s", name, time.perf_counter() - t0)
        self._by_class[detector_class] = self._builtin[name]
        return self._builtin[name]

    def threshold(self, detector: Detector, detector_class: str = "") -> float:
        """Calibrated "detected" threshold: ``"<detector>:<class>"`` entry, else ``"<detector>"``, else
        :data:`DEFAULT_THRESHOLD`."""
        key = f"{detector.name}:{detector_class}"
        if key in self.thresholds:
            return float(self.thresholds[key])
        return float(self.thresholds.get(detector.name, DEFAULT_THRESHOLD))

    def strict_threshold(self, target_name: str) -> float:
        """Confidence of a confident detection of ``target_name`` (:data:`STRICT_THRESHOLDS`), at least the
        detector's calibrated threshold."""
        cls = self.scene.target(target_name).detector_class
        det = self.detector_for(cls)
        thr = self.threshold(det, cls)
        v = self.strict_thresholds.get(f"{det.name}:{cls}", self.strict_thresholds.get(det.name, thr))
        return max(float(v), thr)

    # ---- scene updates -------------------------------------------------------------------------------------------
    def set_target_pose(self, name: str, center, quat=None) -> None:
        self.renderer.set_target_pose(name, center, quat)

    def set_obstacle_pose(self, name: str, center, quat=None) -> None:
        self.renderer.set_obstacle_pose(name, center, quat)

    # ---- scoring -------------------------------------------------------------------------------------------------
    def score(self, camera_pose: np.ndarray, target_name: str, keep_image: bool = True) -> OracleResult:
        """Ground-truth perception score of target ``target_name`` seen from ``camera_pose``.

        Parameters
        ----------
        camera_pose : (4, 4) array_like
            Optical frame (+z forward, +x right, +y down) in the scene frame.
        target_name : str
        keep_image : bool
            Keep the rendered image in the result.

        Returns
        -------
        OracleResult
        """
        target = self.renderer.target(target_name)
        det = self.detector_for(target.detector_class)
        thr = self.threshold(det, target.detector_class)
        T = np.asarray(camera_pose, float)
        proj = self.renderer.projected_box(T, target_name)
        base = dict(threshold=thr, target=target_name, detector_class=target.detector_class, detector=det.name)
        if proj is None:
            return OracleResult(score=0.0, detected=False, detection=None, projected_box=None, image=None, **base)
        t0 = time.perf_counter()
        rgb = self.renderer.render(T).rgb
        t1 = time.perf_counter()
        detections = det.detect(rgb)
        t2 = time.perf_counter()
        best: Optional[Detection] = None
        for d in detections:
            if d.label == target.detector_class and boxes_match(d.box_xyxy, proj, self.match):
                if best is None or d.score > best.score:
                    best = d
        score = float(np.clip(best.score, 0.0, 1.0)) if best else 0.0
        return OracleResult(score=score, detected=score >= thr, detection=best, projected_box=proj,
                            image=rgb if keep_image else None, detections=detections,
                            timings={"render": t1 - t0, "detect": t2 - t1}, **base)

    def score_many(self, camera_poses: Iterable[np.ndarray], target_name: str,
                   keep_images: bool = False) -> List[OracleResult]:
        """:meth:`score` for many camera poses (an (N, 4, 4) array or any iterable of 4x4 poses)."""
        return [self.score(T, target_name, keep_image=keep_images) for T in camera_poses]

    def scores(self, camera_poses: Iterable[np.ndarray], target_name: str) -> np.ndarray:
        """Just the scores (N,) of :meth:`score_many`."""
        return np.array([r.score for r in self.score_many(camera_poses, target_name)], dtype=float)
