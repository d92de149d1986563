"""``psprm dataset``, ``psprm train``, ``psprm eval-surrogate``: the perception surrogate's pipeline."""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

from .bench import add_backend_arguments
from ..errors import InputError, PsprmError

log = logging.getLogger(__name__)

STUDIO_DATASET = "psprm_core/data/surrogate_dataset"
# the shipped surrogate's training data: the studio views and the oracle-labelled views of the scenes' roadmaps
# (dynamic_person is left out, to measure how the surrogate carries over to a scene it has not seen)
DEFAULT_DATASET = ",".join([STUDIO_DATASET] + [f"psprm_core/data/scene_views/{s}" for s in
                                               ("home", "nursing", "cup_table", "blind_spot_alley")])
DEFAULT_OCCLUDED = "psprm_core/data/surrogate_occluded"


def register(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser("dataset", help="render + score camera views of a scene's targets with the real-detector "
                                       "oracle (parallel, resumable)")
    d.add_argument("--scene", default="surrogate_studio", help="scene whose targets are viewed")
    d.add_argument("--targets", default=None, help="comma-separated target names (default: all)")
    d.add_argument("--samples", type=int, default=20000, help="total labelled views (split evenly over targets)")
    d.add_argument("--out", default=STUDIO_DATASET)
    d.add_argument("--seed", type=int, default=0)
    add_backend_arguments(d, "a task is one chunk; each worker builds its oracle once and keeps it", in_process=0)
    d.add_argument("--chunk", type=int, default=250, help="samples per chunk file (unit of resumption)")
    d.add_argument("--max-distance", type=float, default=4.0)
    d.add_argument("--source", choices=("studio", "roadmap"), default="studio",
                   help="studio: views sampled around each target (0.4 m to --max-distance); roadmap: camera poses of "
                        "the scene's PS-PRM roadmap nodes and Eq. 1 edge samples (the views the planner chooses "
                        "among), ray-cast-occluded ones dropped")
    d.add_argument("--planner", default="neural-psprm-line", help="roadmap source: PS-PRM variant whose roadmap is "
                                                                  "drawn from")
    d.add_argument("--nodes", type=int, default=3000, help="roadmap source: roadmap size")
    d.add_argument("--edge-fraction", type=float, default=0.5, help="roadmap source: share of Eq. 1 edge samples")
    d.set_defaults(func=_dataset)

    t = sub.add_parser("train", help="train the perception surrogate MLP on a dataset")
    t.add_argument("--dataset", default=DEFAULT_DATASET,
                   help="dataset directory, or several separated by commas (each is split by viewpoint on its own; "
                        "the splits are pooled)")
    t.add_argument("--out", default="psprm_core/data/surrogate.pt")
    t.add_argument("--epochs", type=int, default=200)
    t.add_argument("--lr", type=float, default=1e-4)
    t.add_argument("--batch", type=int, default=512)
    t.add_argument("--threads", type=int, default=2)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--loss", choices=("bce", "mse", "log-mse"), default="bce",
                   help="bce: cross-entropy with the soft labels; log-mse: squared error of log(score + "
                        "--log-offset), training on the logarithm of the confidence (the network still outputs the "
                        "confidence)")
    t.add_argument("--log-offset", type=float, default=0.05, help="offset of the log-mse loss")
    t.add_argument("--class-weight", default="", metavar="CLASS=W,...",
                   help="loss weight of the samples of each named class (others 1), e.g. 'cup=4'")
    t.add_argument("--schedule", choices=("constant", "cosine"), default="constant",
                   help="learning rate: --lr throughout (the paper), or cosine-annealed to 1 %% of it")
    t.add_argument("--patience", type=int, default=20,
                   help="stop after this many epochs without a better validation RMSE (0: never stop early)")
    t.add_argument("--weight-decay", type=float, default=0.0, help="Adam weight decay")
    t.add_argument("--allow-incomplete", action="store_true",
                   help="train on the chunks labelled so far (a dataset build that was stopped; resume it later)")
    t.set_defaults(func=_train)

    e = sub.add_parser("eval-surrogate", help="evaluate the shipped surrogate on its held-out test split")
    e.add_argument("--checkpoint", default="psprm_core/data/surrogate.pt")
    e.add_argument("--dataset", default=DEFAULT_DATASET, help="dataset directory, or several separated by commas "
                                                             "(as the checkpoint was trained on)")
    e.add_argument("--occluded", default=DEFAULT_OCCLUDED, help="dataset rendered in a cluttered scene "
                                                                 "(occluded views are evaluated with ray casting)")
    e.add_argument("--allow-incomplete", action="store_true", help="evaluate on a dataset whose build was stopped")
    e.add_argument("--threads", type=int, default=2, help="torch threads (the throughput measurement, "
                                                          "evals_per_s, included)")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=_eval)


def _dataset(args) -> int:
    from ..executors import BackendSettings
    from ..paths import project_root, resolve_named
    from ..perception.dataset import OracleFactory, SamplingConfig, build_dataset
    from ..scene import load_scene

    path = resolve_named("scene", args.scene)
    scene = load_scene(path)
    try:  # record a project-relative scene path in the dataset's metadata, never a path of this machine
        path = path.resolve().relative_to(project_root())
    except ValueError:
        pass
    names = args.targets.split(",") if args.targets else scene.target_names
    targets = [scene.target(n) for n in names]
    backend = BackendSettings(backend=args.backend, workers=args.workers, address=args.address,
                              max_retries=args.max_retries)
    backend.validate()
    t0 = time.perf_counter()
    if args.source == "roadmap":
        from ..perception.scene_views import roadmap_view_source, roadmap_views
        from ..robot import RobotModel

        robot = RobotModel.load(scene.robot)
        per_target = max(1, args.samples // len(names))
        views = roadmap_views(scene, names, per_target, nodes=args.nodes, seed=args.seed, planner=args.planner,
                              edge_fraction=args.edge_fraction, robot=robot)
        stats = views.pop("stats")
        log.info("roadmap views: %s", stats)
        dist = (float(views["distance"].min()), float(views["distance"].max()))
        source = roadmap_view_source(args.scene, args.planner, args.nodes, args.seed, per_target,
                                     args.edge_fraction, dist)
        out = build_dataset(args.out, targets, OracleFactory(str(path), {"intrinsics": robot.config.intrinsics}),
                            seed=args.seed, chunk_size=args.chunk, samples=views, source=source, backend=backend)
        args.samples = len(views["camera_poses"])
    else:
        out = build_dataset(args.out, targets, OracleFactory(str(path)), n_samples=args.samples,
                            sampling=SamplingConfig(distance=(0.4, args.max_distance)), seed=args.seed,
                            chunk_size=args.chunk, backend=backend)
    print(json.dumps({"dataset": str(out), "samples": args.samples, "targets": names,
                      "seconds": round(time.perf_counter() - t0, 1)}))
    return 0


def _train(args) -> int:
    from ..perception.dataset import load_dataset
    from ..perception.training import TrainConfig, pool_datasets, train_surrogate

    weights = {}
    for item in (w for w in args.class_weight.split(",") if w.strip()):
        name, sep, value = item.rpartition("=")
        try:
            weights[name.strip()] = float(value)
        except ValueError:
            name = ""
        if not sep or not name.strip():
            raise InputError(f"--class-weight wants CLASS=WEIGHT items, got {item!r}")
    cfg = TrainConfig(epochs=args.epochs, lr=args.lr, batch_size=args.batch, seed=args.seed, threads=args.threads,
                      loss=args.loss, log_offset=args.log_offset, class_weights=weights, schedule=args.schedule,
                      patience=args.patience if args.patience > 0 else None, weight_decay=args.weight_decay)
    dss = [load_dataset(d, allow_incomplete=args.allow_incomplete) for d in args.dataset.split(",") if d]
    for d in dss:
        if not d.metadata.get("complete", True):
            log.warning("training on an incomplete dataset %s: %d samples", d.path, len(d))
    ds = pool_datasets(dss)
    t0 = time.perf_counter()
    _, report = train_surrogate(ds, out_path=args.out, config=cfg)
    report = {k: v for k, v in report.items() if k != "history"} if isinstance(report, dict) else report
    print(json.dumps({"checkpoint": args.out, "seconds": round(time.perf_counter() - t0, 1), "report": report},
                     default=str))
    return 0


def class_thresholds(classes) -> dict:
    """Calibrated "detected" threshold of the built-in detector of each class (oracle.DETECTION_THRESHOLDS)."""
    from ..perception.detectors import default_detector_name
    from ..perception.oracle import DEFAULT_THRESHOLD, DETECTION_THRESHOLDS

    out = {}
    for c in classes:
        det = default_detector_name(c)
        out[c] = float(DETECTION_THRESHOLDS.get(f"{det}:{c}", DETECTION_THRESHOLDS.get(det, DEFAULT_THRESHOLD)))
    return out


def line_of_sight_blocked(scene, ds):
    """Ground-truth occlusion as in the paper: pybullet ray from the camera to the target centroid hits an obstacle
    (a box other than the target itself)."""
    import numpy as np
    import pybullet as pb

    cid = pb.connect(pb.DIRECT)
    try:
        names = {}
        for box in scene.collision_boxes():
            shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=list(box.half_extents), physicsClientId=cid)
            names[pb.createMultiBody(0, shape, basePosition=list(box.center), baseOrientation=list(box.quat),
                                     physicsClientId=cid)] = box.name
        starts = ds.camera_poses[:, :3, 3]
        ends = np.stack([ds.targets[i].center for i in ds.target_index])
        blocked = np.zeros(len(ds), dtype=bool)
        for s0 in range(0, len(ds), 4000):
            hits = pb.rayTestBatch(starts[s0:s0 + 4000].tolist(), ends[s0:s0 + 4000].tolist(), physicsClientId=cid)
            for k, h in enumerate(hits):
                i = s0 + k
                blocked[i] = h[0] >= 0 and names.get(h[0]) != ds.targets[ds.target_index[i]].name
        return blocked
    finally:
        pb.disconnect(cid)


def _eval(args) -> int:
    import numpy as np
    import torch

    from ..paths import resolve_named
    from ..perception.dataset import load_dataset
    from ..perception.occlusion import OcclusionChecker
    from ..perception.surrogate import load_surrogate
    from ..perception.training import _splits, TrainConfig, evals_per_s, perception_metrics, pool_datasets
    from ..scene import load_scene

    torch.set_num_threads(max(1, int(args.threads)))
    ck = Path(args.checkpoint)
    if not ck.is_file():
        raise PsprmError(f"checkpoint not found: {ck}")
    model = load_surrogate(ck)

    def predict(ds):
        pred = np.zeros(len(ds))
        for ti, t in enumerate(ds.targets):
            sel = ds.target_index == ti
            if sel.any():
                pose = np.eye(4)
                pose[:3, :3], pose[:3, 3] = t.rotation, t.center
                pred[sel] = model.predict(torch.as_tensor(ds.camera_poses[sel]), torch.as_tensor(pose),
                                          t.detector_class).double().numpy()
        return pred

    def thresholds(ds):
        thr = class_thresholds({t.detector_class for t in ds.targets})
        return np.array([thr[ds.targets[i].detector_class] for i in ds.target_index])

    full = pool_datasets([load_dataset(d, allow_incomplete=args.allow_incomplete)
                          for d in args.dataset.split(",") if d])
    test_idx = _splits(full, TrainConfig.from_dict(model.metadata.get("training", {})))["test"]
    test = full.subset(test_idx)
    pred = predict(test)
    out = perception_metrics(pred, test.scores, thresholds(test))
    for src in full.metadata.get("pooled", []):
        sel = (test_idx >= src["start"]) & (test_idx < src["stop"])
        if sel.any():
            out.setdefault("per_source", {})[src["dir"]] = perception_metrics(pred[sel], test.scores[sel],
                                                                             thresholds(test)[sel])
    out["thresholds"] = class_thresholds(sorted({t.detector_class for t in test.targets}))
    out["per_class"] = {}
    for c in sorted({t.detector_class for t in test.targets}):
        sel = np.array([test.targets[i].detector_class == c for i in test.target_index])
        out["per_class"][c] = perception_metrics(pred[sel], test.scores[sel], out["thresholds"][c])
    occ_dir = Path(args.occluded)
    if occ_dir.is_dir():
        occ = load_dataset(occ_dir)
        scene = load_scene(resolve_named("scene", _scene_from_meta(occ.metadata)))
        blocked = line_of_sight_blocked(scene, occ)
        rc = np.zeros(len(occ), dtype=bool)
        for ti, t in enumerate(occ.targets):
            sel = occ.target_index == ti
            if sel.any():
                rc[sel] = OcclusionChecker.from_scene(scene, t.name).occluded(
                    torch.as_tensor(occ.camera_poses[sel])).numpy()
        p_raw = predict(occ)
        p_zero = np.where(rc, 0.0, p_raw)  # Alg. 2: zero when the ray-cast occlusion score exceeds tau
        thr = thresholds(occ)
        # views a robot camera can have: inside the workspace, not inside any obstacle (TinyRenderer culls back
        # faces, so a camera inside a wall box would see through it)
        from ..perception.occlusion import boxes_to_tensors

        cam = torch.as_tensor(occ.camera_poses[:, :3, 3])
        inside = boxes_to_tensors(scene.collision_boxes(), dtype=torch.float64).contains(cam, margin=0.05).any(-1)
        ws = scene.workspace
        valid = ((cam[:, 0] >= ws[0, 0]) & (cam[:, 0] <= ws[0, 1]) & (cam[:, 1] >= ws[1, 0]) &
                 (cam[:, 1] <= ws[1, 1]) & ~inside).numpy()
        sub = blocked & valid
        out["occluded_rmse_raycast_incl_invalid_views"] = perception_metrics(p_zero[blocked], occ.scores[blocked],
                                                                             thr[blocked])["rmse"]
        out["valid_views"] = int(valid.sum())
        out["occluded_scene"] = scene.name
        out["occluded_views"] = int(sub.sum())
        out["occluded_fraction"] = float(sub.sum() / max(1, valid.sum()))
        out["occluded_rmse_surrogate"] = perception_metrics(p_raw[sub], occ.scores[sub], thr[sub])["rmse"]
        out["occluded_rmse_raycast"] = perception_metrics(p_zero[sub], occ.scores[sub], thr[sub])["rmse"]
        out["occluded_mean_error_surrogate"] = float(np.mean(p_raw[sub] - occ.scores[sub])) if sub.any() else None
        out["raycast_agreement_with_line_of_sight"] = float(np.mean(rc == blocked))
        out["cluttered_scene_rmse_surrogate"] = perception_metrics(p_raw[valid], occ.scores[valid], thr[valid])["rmse"]
        out["cluttered_scene_rmse_raycast"] = perception_metrics(p_zero[valid], occ.scores[valid], thr[valid])["rmse"]
    out["evals_per_s"] = evals_per_s(model, threads=args.threads)
    print(json.dumps(out, default=float) if args.json else json.dumps(out, indent=2, default=float))
    return 0


def _scene_from_meta(meta: dict) -> str:
    desc = str(meta.get("scorer_description") or meta.get("scorer") or "")
    if "scene=" in desc:
        return Path(desc.split("scene=")[1].split(",")[0].rstrip(")")).stem  # resolved by name in config/scenes
    raise InputError("dataset metadata does not name its scene")
