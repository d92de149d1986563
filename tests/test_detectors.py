"""Detector interface and the two built-in detectors on the photos shipped with scikit-image."""

from __future__ import annotations

import numpy as np
import pytest

from psprm_core.geometry import yaw_to_quat
from psprm_core.perception.appearance import crop_to_aspect, get_appearance, list_appearances
from psprm_core.perception.detectors import (Detection, Detector, DetectorUnavailableError, default_detector_name,
                                             make_detector, nms)
from psprm_core.perception.oracle import Oracle, boxes_match
from psprm_core.perception.render import look_at_pose
from psprm_core.scene import Scene, Target

skdata = pytest.importorskip("skimage.data")


def _make(name):
    try:
        return make_detector(name)
    except DetectorUnavailableError as exc:  # pragma: no cover - set-up problem
        pytest.skip(f"{exc}; run scripts/install_detectors.sh")


@pytest.fixture(scope="module")
def centerface():
    return _make("centerface")


@pytest.fixture(scope="module")
def centernet():
    return _make("centernet")


def test_centerface_finds_the_astronauts_face(centerface):
    dets = centerface.detect(skdata.astronaut())
    assert dets and dets[0].label == "face" and dets[0].score > 0.8
    x1, y1, x2, y2 = dets[0].box_xyxy
    assert 150 < x1 < x2 < 300 and 30 < y1 < y2 < 220  # her face, not the flag or the suit
    assert all(d.score <= dets[0].score for d in dets)


def test_centerface_handles_sizes_not_multiple_of_32(centerface):
    img = skdata.astronaut()[:500, :450]
    dets = centerface.detect(img)
    assert dets and dets[0].score > 0.7
    assert dets[0].box_xyxy[2] <= 450 and dets[0].box_xyxy[3] <= 500


def test_centernet_finds_the_cup_in_the_coffee_photo(centernet):
    dets = centernet.detect(skdata.coffee())
    cups = [d for d in dets if d.label == "cup"]
    assert cups and cups[0].score > 0.3
    x1, y1, x2, y2 = cups[0].box_xyxy
    assert 100 < 0.5 * (x1 + x2) < 450 and y2 < 350
    assert "cup" in centernet.classes and len(centernet.classes) == 80


def test_nothing_on_a_blank_image(centerface, centernet):
    blank = np.full((480, 640, 3), 200, np.uint8)
    assert not [d for d in centerface.detect(blank) if d.score > 0.3]
    assert not [d for d in centernet.detect(blank) if d.score > 0.3]


def test_default_detectors_and_errors():
    assert default_detector_name("face") == "centerface"
    assert default_detector_name("tv") == "centernet"
    with pytest.raises(DetectorUnavailableError):
        default_detector_name("unicorn")
    with pytest.raises(DetectorUnavailableError):
        make_detector("no-such-detector")


def test_nms_keeps_best_of_overlapping_boxes():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [50, 50, 60, 60]], float)
    keep = nms(boxes, np.array([0.5, 0.9, 0.3]), 0.5)
    assert list(keep) == [1, 2]


class _FixedDetector(Detector):
    """A user-supplied detector: always reports one box in the image centre."""

    name = "fixed"
    classes = frozenset({"face"})

    def __init__(self):
        self.calls = 0

    def detect(self, rgb):
        self.calls += 1
        h, w = rgb.shape[:2]
        return [Detection(np.array([w / 2 - 40, h / 2 - 50, w / 2 + 40, h / 2 + 50]), 0.66, "face"),
                Detection(np.array([0, 0, 20, 20]), 0.99, "face")]  # elsewhere: must not match


def test_user_detector_plugs_into_the_oracle():
    t = Target(name="head", detector_class="face", center=np.array([0.0, 0.0, 1.5]), size=np.array([0.2, 0.18, 0.24]),
               quat=yaw_to_quat(0.0), appearance="plain")
    scene = Scene(name="s", robot="", frame="map", workspace=np.array([[-2.0, 2.0], [-2.0, 2.0]]), obstacles=(),
                  targets=(t,))
    det = _FixedDetector()
    with Oracle(scene, detectors=[det], thresholds={"fixed": 0.6}) as oracle:
        r = oracle.score(look_at_pose([1.5, 0.0, 1.5], [0.0, 0.0, 1.5]), "head")
    assert det.calls == 1
    assert r.detector == "fixed" and r.score == pytest.approx(0.66) and r.detected and r.threshold == 0.6


def test_box_matching_rules():
    target = np.array([100, 100, 200, 220], float)
    assert boxes_match(np.array([110, 105, 195, 215]), target)        # IoU
    assert boxes_match(np.array([120, 110, 170, 160]), target)        # contained, big enough
    assert not boxes_match(np.array([120, 110, 125, 115]), target)    # contained but tiny
    assert not boxes_match(np.array([300, 300, 400, 400]), target)    # elsewhere


def test_appearance_catalogue():
    names = list_appearances()
    for n in ("astronaut", "grace_hopper", "coffee", "monitor", "potted_plant", "suitcase", "fork", "plain"):
        assert n in names
    assert get_appearance("", "tv").name == "monitor"
    assert get_appearance("nurse", "face").name == "astronaut"
    assert get_appearance("typo", "cup").name == "coffee"
    img = crop_to_aspect(np.zeros((100, 200, 3), np.uint8), 0.5, focus=(90, 40, 110, 60))
    assert abs(img.shape[1] / img.shape[0] - 0.5) < 0.05


def test_calibration_thresholds_pooled_over_detectable_cases(monkeypatch, tmp_path, capsys):
    """``psprm calibrate-detectors``: a threshold per case (Youden's J) and one pooled per detector over the
    detectable cases only; unknown cases are a clear error. Measurements are stood in (the real ones render)."""
    import json

    from psprm_core import cli
    from psprm_core.perception.detectors import calibration

    fake = {"grace_hopper": ([0.8, 0.9], [0.1, 0.85]), "astronaut": ([0.3, 0.35, 0.4], [0.05, 0.2]),
            "monitor": ([0.6, 0.7], [0.1, 0.5]), "suitcase": ([0.0, 0.0], [0.0])}

    def measure(case):
        pos, neg = fake[case.appearance]
        return {"pos": pos, "neg": neg, "views": {"d1_yaw0": pos[0]}, "ms_render": 1.0, "ms_detect": 2.0}

    monkeypatch.setattr(calibration, "measure_case", measure)
    res = calibration.calibrate(["astronaut", "grace_hopper", "monitor", "suitcase"])
    assert res["astronaut"]["threshold"] == pytest.approx(0.25) and res["astronaut"]["tpr"] == 1.0
    assert res["monitor"]["threshold"] == pytest.approx(0.55) and res["monitor"]["fpr"] == 0.0
    faces = res["pooled:centerface"]  # both faces pooled: one threshold for the detector
    assert (faces["n_pos"], faces["n_neg"]) == (5, 4)
    assert faces["threshold"] == pytest.approx(0.25) and faces["tpr"] == 1.0 and faces["fpr"] == 0.25
    # the undetectable suitcase is measured but kept out of CenterNet's pooled threshold
    assert "suitcase" in res and res["pooled:centernet"]["n_pos"] == 2
    assert "pooled:centernet:suitcase" not in res and res["pooled:centernet:tv"]["threshold"] == pytest.approx(0.55)
    assert cli.main(["calibrate-detectors", "--cases", "astronaut", "monitor", "--json", str(tmp_path / "c.json")]) == 0
    out = capsys.readouterr().out
    assert "POOLED centernet: threshold 0.55" in out and "own threshold 0.25" in out
    assert json.loads((tmp_path / "c.json").read_text())["monitor"]["threshold"] == pytest.approx(0.55)
    assert cli.main(["calibrate-detectors", "--cases", "mug"]) == 2
    assert "unknown calibration case(s) mug" in capsys.readouterr().err


def test_shipped_thresholds_are_what_calibration_measures_on_real_renders():
    """Every "detected" threshold the oracle ships, and every strict one, is the one ``calibrate()`` chooses on real
    renders with the real detectors (the detectable cases of :data:`DEFAULT_CASES`, pooled per detector and per
    detector:class)."""
    from psprm_core.perception.detectors import calibration
    from psprm_core.perception.oracle import DETECTION_THRESHOLDS, STRICT_THRESHOLDS

    res = calibration.calibrate([c.appearance for c in calibration.DEFAULT_CASES if c.detectable])
    measured = {k[len("pooled:"):]: r["threshold"] for k, r in res.items() if k.startswith("pooled:")}
    assert set(DETECTION_THRESHOLDS) <= set(measured), sorted(measured)
    shipped = {k: pytest.approx(v, abs=1e-9) for k, v in DETECTION_THRESHOLDS.items()}
    assert {k: measured[k] for k in DETECTION_THRESHOLDS} == shipped
    strict = {k[len("pooled:"):]: r["strict"] for k, r in res.items() if k.startswith("pooled:")}
    assert {k: strict[k] for k in STRICT_THRESHOLDS} == {k: pytest.approx(v, abs=1e-9)
                                                         for k, v in STRICT_THRESHOLDS.items()}
    # the measurement separates: each detectable case's positives are mostly at or above its shipped threshold
    for c in calibration.DEFAULT_CASES:
        if c.detectable:
            r = res[c.appearance]
            assert r["tpr"] >= 0.45 and r["fpr"] <= 0.2, (c.appearance, r["tpr"], r["fpr"])
