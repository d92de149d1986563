"""``psprm score``: render one camera view of a scene and print the oracle's perception score for a target;
``psprm calibrate-detectors``: choose each detector's "detected" threshold on rendered views.

Example::

    psprm score --scene home --target tv --camera 5.5 3.22 1.15  -0.7348 0 0 0.6783 --save-image view.png --json

The camera pose is the *optical* frame (+z forward, +x right, +y down) in the scene frame: position then quaternion
(x, y, z, w).
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
from typing import Optional

import numpy as np

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    """Add the ``score`` subcommand."""
    p = subparsers.add_parser(
        "score", help="render a camera view and score a target with the real-detector oracle",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", required=True, help="scene name (config/scenes/NAME.yaml) or path to a YAML file")
    p.add_argument("--target", required=True, help="target name in the scene")
    p.add_argument("--camera", required=True, nargs=7, type=float, metavar=("X", "Y", "Z", "QX", "QY", "QZ", "QW"),
                   help="optical-frame camera pose in the scene frame")
    p.add_argument("--save-image", metavar="PNG", help="write the rendered view (projected target box in green, "
                                                       "matched detection in red)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--renderer", choices=("tiny", "egl", "auto"), default="tiny", help="pybullet renderer")
    p.add_argument("--surrogate", metavar="CKPT", help="also print the neural surrogate's score (saved model file)")
    p.set_defaults(func=run)
    c = subparsers.add_parser(
        "calibrate-detectors", help="measure each detector's confidence on rendered views of the shipped "
                                    "appearances and choose its 'detected' threshold (Youden's J; docs/detectors.md)")
    c.add_argument("--cases", nargs="*", help="appearance names to measure (default: all)")
    c.add_argument("--json", metavar="FILE", help="also write the raw measurements to this file")
    c.set_defaults(func=_calibrate)


def _calibrate(args) -> int:
    from ..errors import PsprmError
    from ..perception.detectors.calibration import calibrate, report_lines

    try:
        results = calibrate(args.cases)
    except ValueError as exc:
        raise PsprmError(str(exc)) from None
    for line in report_lines(results):
        print(line)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)
    return 0


def camera_pose_from_args(values) -> np.ndarray:
    """4x4 pose from ``[x, y, z, qx, qy, qz, qw]``."""
    from ..errors import PsprmError
    from ..geometry import quat_to_matrix

    v = np.asarray(values, float)
    if not np.all(np.isfinite(v)) or np.linalg.norm(v[3:]) < 1e-9:
        raise PsprmError("--camera needs a finite position and a non-zero quaternion")
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(v[3:])
    T[:3, 3] = v[:3]
    return T


def _optional_module(name: str):
    """``psprm_core.perception.<name>`` if that module exists, else ``None``."""
    full = f"psprm_core.perception.{name}"
    try:
        return importlib.import_module(full)
    except ModuleNotFoundError as exc:
        if exc.name == full:
            return None
        raise


# ---- HOOKS: scores built by other modules, reported next to the oracle's when those modules are present ----------
def occlusion_hook(scene, target: str, pose: np.ndarray) -> Optional[float]:
    """Ray-cast occlusion score (fraction of blocked rays) from ``psprm_core.perception.occlusion``, if present.

    Uses ``OcclusionChecker.from_scene(scene, target).score(poses)``, or a module-level
    ``cli_score(scene, target, camera_pose)`` when the checker is not there.
    """
    mod = _optional_module("occlusion")
    if mod is None:
        return None
    if hasattr(mod, "OcclusionChecker"):
        import torch

        checker = mod.OcclusionChecker.from_scene(scene, target)
        return float(checker.score(torch.as_tensor(pose, dtype=torch.float64)[None])[0])
    if hasattr(mod, "cli_score"):
        return float(mod.cli_score(scene, target, pose))
    return None


def surrogate_hook(scene, target: str, pose: np.ndarray, checkpoint: Optional[str]) -> Optional[float]:
    """Neural surrogate score from ``psprm_core.perception.surrogate`` for a saved model ``checkpoint``, if given."""
    if not checkpoint:
        return None
    mod = _optional_module("surrogate")
    if mod is None or not hasattr(mod, "load_surrogate"):
        log.warning("--surrogate given but psprm_core.perception.surrogate provides no load_surrogate()")
        return None
    model = mod.load_surrogate(checkpoint)
    t = scene.target(target)
    out = model.predict(np.asarray(pose, float)[None], mod.target_pose_matrix(t), t.detector_class)
    return float(np.asarray(out.detach().cpu() if hasattr(out, "detach") else out).reshape(-1)[0])


def save_annotated(path: str, image: np.ndarray, projected_box, detection_box) -> None:
    """Write ``image`` with the projected target box (green) and the matched detection (red)."""
    from PIL import Image, ImageDraw

    img = Image.fromarray(image)
    draw = ImageDraw.Draw(img)
    if projected_box is not None:
        draw.rectangle([float(v) for v in projected_box], outline=(0, 200, 0), width=2)
    if detection_box is not None:
        draw.rectangle([float(v) for v in detection_box], outline=(220, 0, 0), width=2)
    img.save(path)


def run(args) -> int:
    from ..errors import PsprmError
    from ..paths import resolve_named
    from ..perception.oracle import Oracle
    from ..scene import load_scene

    scene = load_scene(resolve_named("scene", args.scene))
    if args.target not in scene.target_names:
        raise PsprmError(f"scene '{scene.name}' has no target '{args.target}' "
                         f"(targets: {', '.join(scene.target_names) or 'none'})")
    pose = camera_pose_from_args(args.camera)
    from ..perception.render import SceneRenderer

    with SceneRenderer(scene, renderer=args.renderer) as renderer:
        oracle = Oracle(scene, renderer=renderer)
        result = oracle.score(pose, args.target)
        image = result.image
        if image is None and args.save_image:  # target out of view: still save what the camera sees
            image = renderer.render(pose).rgb
    out = result.to_dict()
    # ---- HOOKS: surrogate / occlusion scores (other modules; reported only when available) ----------------------
    try:
        occ = occlusion_hook(scene, args.target, pose)
    except Exception as exc:  # another module's failure must not hide the oracle's answer
        log.warning("occlusion score unavailable: %s", exc)
        occ = None
    if occ is not None:
        out["occlusion_score"] = round(occ, 4)
    if args.surrogate:  # explicitly requested: failures are errors
        try:
            sur = surrogate_hook(scene, args.target, pose, args.surrogate)
        except (OSError, KeyError, ValueError, RuntimeError) as exc:
            raise PsprmError(f"--surrogate {args.surrogate}: {exc}") from exc
        if sur is not None:
            out["surrogate_score"] = round(sur, 4)
    if args.save_image:
        save_annotated(args.save_image, image, result.projected_box,
                       result.detection.box_xyxy if result.detection else None)
        out["image"] = args.save_image
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"{args.target} ({out['class']}, {out['detector']}): score {out['score']:.3f} "
              f"({'detected' if out['detected'] else 'not detected'}, threshold {out['threshold']:.2f})")
        for key in ("occlusion_score", "surrogate_score"):
            if key in out:
                print(f"  {key.replace('_', ' ')}: {out[key]:.3f}")
        if args.save_image:
            print(f"  image: {args.save_image}")
    return 0
