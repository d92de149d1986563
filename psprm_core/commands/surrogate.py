"""``psprm dataset``, ``psprm train``, ``psprm eval-surrogate``: the perception surrogate's pipeline."""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

log = logging.getLogger(__name__)

DEFAULT_DATASET = "psprm_core/data/surrogate_dataset"
DEFAULT_OCCLUDED = "psprm_core/data/surrogate_occluded"


def register(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser("dataset", help="render + score camera views of a scene's targets with the real-detector "
                                       "oracle (parallel, resumable)")
    d.add_argument("--scene", default="surrogate_studio", help="scene whose targets are viewed")
    d.add_argument("--targets", default=None, help="comma-separated target names (default: all)")
    d.add_argument("--samples", type=int, default=20000, help="total labelled views (split evenly over targets)")
    d.add_argument("--out", default=DEFAULT_DATASET)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--workers", type=int, default=2)
    d.add_argument("--chunk", type=int, default=250, help="samples per chunk file (unit of resumption)")
    d.add_argument("--max-distance", type=float, default=4.0)
    d.set_defaults(func=_dataset)

    t = sub.add_parser("train", help="train the perception surrogate MLP on a dataset")
    t.add_argument("--dataset", default=DEFAULT_DATASET)
    t.add_argument("--out", default="psprm_core/data/surrogate.pt")
    t.add_argument("--epochs", type=int, default=200)
    t.add_argument("--lr", type=float, default=1e-4)
    t.add_argument("--batch", type=int, default=512)
    t.add_argument("--threads", type=int, default=2)
    t.add_argument("--seed", type=int, default=0)
    t.set_defaults(func=_train)

    e = sub.add_parser("eval-surrogate", help="evaluate the shipped surrogate on its held-out test split")
    e.add_argument("--checkpoint", default="psprm_core/data/surrogate.pt")
    e.add_argument("--dataset", default=DEFAULT_DATASET)
    e.add_argument("--occluded", default=DEFAULT_OCCLUDED, help="dataset rendered in a cluttered scene "
                                                                 "(occluded views are evaluated with ray casting)")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=_eval)


def _dataset(args) -> int:
    from ..paths import resolve_named
    from ..perception.dataset import OracleFactory, SamplingConfig, build_dataset
    from ..scene import load_scene

    path = resolve_named("scene", args.scene)
    scene = load_scene(path)
    names = args.targets.split(",") if args.targets else scene.target_names
    targets = [scene.target(n) for n in names]
    t0 = time.perf_counter()
    out = build_dataset(args.out, targets, OracleFactory(str(path)), n_samples=args.samples,
                        sampling=SamplingConfig(distance=(0.4, args.max_distance)), seed=args.seed,
                        chunk_size=args.chunk, workers=args.workers)
    print(json.dumps({"dataset": str(out), "samples": args.samples, "targets": names,
                      "seconds": round(time.perf_counter() - t0, 1)}))
    return 0


def _train(args) -> int:
    from ..perception.training import TrainConfig, train_surrogate

    cfg = TrainConfig(epochs=args.epochs, lr=args.lr, batch_size=args.batch, seed=args.seed, threads=args.threads)
    t0 = time.perf_counter()
    _, report = train_surrogate(args.dataset, out_path=args.out, config=cfg)
    report = {k: v for k, v in report.items() if k != "history"} if isinstance(report, dict) else report
    print(json.dumps({"checkpoint": args.out, "seconds": round(time.perf_counter() - t0, 1), "report": report},
                     default=str))
    return 0


def _eval(args) -> int:
    from ..errors import PsprmError
    from ..paths import resolve_named
    from ..perception.surrogate import load_surrogate
    from ..perception.training import evals_per_s, evaluate_surrogate
    from ..scene import load_scene

    ck = Path(args.checkpoint)
    if not ck.is_file():
        raise PsprmError(f"checkpoint not found: {ck}")
    model = load_surrogate(ck)
    res = evaluate_surrogate(model, args.dataset, split="test")
    out = {k: res[k] for k in ("rmse", "mae", "spearman", "accuracy", "precision", "recall", "f1") if k in res}
    out["n_test"] = res.get("n", res.get("count"))
    occ_dir = Path(args.occluded)
    if occ_dir.is_dir():
        meta = json.loads((occ_dir / "metadata.json").read_text())
        scene = load_scene(resolve_named("scene", _scene_from_meta(meta)))
        occ = evaluate_surrogate(model, args.occluded, split="all", scene=scene)
        out["occluded_fraction"] = occ.get("occluded_fraction")
        out["occluded_rmse_surrogate"] = occ.get("occluded_rmse_surrogate", occ.get("occluded", {}).get("rmse"))
        out["occluded_rmse_raycast"] = occ.get("occluded_rmse_raycast", occ.get("occluded_raycast", {}).get("rmse"))
        out["occluded_details"] = {k: v for k, v in occ.items() if k.startswith("occluded")}
    out["evals_per_s"] = evals_per_s(model, threads=2)
    print(json.dumps(out, default=float) if args.json else "\n".join(f"{k:28s} {v}" for k, v in out.items()))
    return 0


def _scene_from_meta(meta: dict) -> str:
    desc = str(meta.get("scorer_description") or meta.get("scorer") or "")
    if "scene=" in desc:
        return desc.split("scene=")[1].split(",")[0].rstrip(")")
    raise ValueError("dataset metadata does not name its scene")
