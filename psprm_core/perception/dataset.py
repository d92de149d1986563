"""Perception-score datasets for training the neural surrogate (Sec. "Neural Surrogate Perception Score Models").

The paper samples 50,000 camera transforms "where the object or human are in the field of view uniformly at
random", renders each view and labels it with the perception model's score. This module does the sampling, runs a
labelling function (the rendering oracle, or any ``score(pose_4x4, target_name) -> float``) on parallel workers (one
task per chunk on local worker processes or a Ray cluster, :mod:`psprm_core.executors`; each worker builds its scorer
once), and stores the result in resumable chunks.

Sampling (:func:`sample_camera_poses`), per target, in the target's frame:

* distance camera -> target centroid uniform in ``distance`` (default [0.4, 4.0] m);
* azimuth around the target uniform in ``azimuth`` relative to the target's facing direction (default all around,
  0 = in front of the target, +-pi = behind it);
* camera height uniform in ``camera_height`` (default [0.3, 1.6] m, what a mobile robot's camera reaches),
  restricted for each distance to the heights that distance can reach (and to elevations below 85 degrees);
* orientation: a roll-free pan/tilt camera (image x axis horizontal) aimed so that the target centroid lands on a
  pixel drawn uniformly over the image (minus ``image_margin`` on each side; redrawn in the rare steep views where
  no pan/tilt achieves it), then rolled by a uniform angle within ``+-roll_deg`` about the line of sight (which
  keeps the centroid on that pixel). The target centroid is therefore always inside the field of view, but not
  always centred.

All samples come from one ``numpy.random.default_rng(seed)`` in a fixed order (targets in the given order), so a
dataset is a pure function of (targets, n_samples, sampling config, seed); chunks are contiguous index ranges.

On-disk layout (``out_dir``)::

    metadata.json           # format, seed, sampling ranges, targets, classes, counts, scorer description, chunks done
    chunk_00000.npz         # index, camera_poses (n,4,4), target_index, scores, distance, azimuth, height, u, v, roll
    chunk_00001.npz
    ...

Re-running :func:`build_dataset` on the same directory with the same configuration labels only the missing chunks
(chunks already on disk are verified against the regenerated poses). :func:`split_by_viewpoint` makes
train/val/test splits in which whole viewpoint cells (azimuth x distance) go to one split.

The sampling is in :mod:`~psprm_core.perception.dataset_sampling`, the labelling workers in
:mod:`~psprm_core.perception.dataset_labelling`; their names are re-exported here.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence, Union

import numpy as np

from ..executors import BackendSettings, Executor, Task
from ..scene import Target
from ..errors import ConfigError, InputError
from .dataset_labelling import OracleFactory, _close_scorer, _factory_key, _label_chunk, _score_fn, label_task
from .dataset_sampling import (_MAX_ELEVATION, SamplingConfig, _aim_with_pixel, _pan_tilt_for_pixel, _pan_tilt_matrix,
                               _per_target_counts, _pixel_rays, _rodrigues, generate_samples, sample_camera_poses,
                               target_in_fov, view_parameters)
from .surrogate import target_pose_matrix

log = logging.getLogger(__name__)

DATASET_FORMAT = "psprm-perception-dataset"
DATASET_VERSION = 1
METADATA_FILE = "metadata.json"


# ------------------------------------------------------------------------------------------------------------------
# Chunked, resumable dataset
# ------------------------------------------------------------------------------------------------------------------
def _target_dict(t: Target) -> dict:
    return {"name": t.name, "class": t.detector_class, "center": [float(v) for v in t.center],
            "size": [float(v) for v in t.size], "quat": [float(v) for v in t.quat]}


def _target_from_dict(d: dict) -> Target:
    return Target(name=d["name"], detector_class=d["class"], center=np.array(d["center"]), size=np.array(d["size"]),
                  quat=np.array(d["quat"]))


def _chunk_path(out_dir: Path, i: int) -> Path:
    return out_dir / f"chunk_{i:05d}.npz"


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True))
    os.replace(tmp, path)


def _write_chunk(path: Path, arrays: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)


def _chunk_arrays(samples: dict, lo: int, hi: int, scores: np.ndarray) -> dict:
    arrays = {k: v[lo:hi] for k, v in samples.items()}
    arrays["index"] = np.arange(lo, hi, dtype=np.int64)
    arrays["scores"] = np.asarray(scores, float)
    return arrays


def _chunk_valid(path: Path, samples: dict, lo: int, hi: int) -> bool:
    try:
        with np.load(path) as z:
            ok = (z["index"].shape == (hi - lo,) and int(z["index"][0]) == lo
                  and np.allclose(z["camera_poses"], samples["camera_poses"][lo:hi], atol=1e-9)
                  and np.array_equal(z["target_index"], samples["target_index"][lo:hi])
                  and np.all(np.isfinite(z["scores"])))
    except Exception as exc:  # noqa: BLE001 - a corrupt chunk is relabelled
        log.warning("chunk %s is unreadable (%s); it will be relabelled", path.name, exc)
        return False
    if not ok:
        log.warning("chunk %s does not match the dataset configuration; it will be relabelled", path.name)
    return ok


def _describe(factory: Any, description: Optional[str]) -> str:
    if description:
        return description
    desc = getattr(factory, "description", None)
    if callable(desc):
        desc = desc()
    return str(desc) if desc else repr(factory)


def build_dataset(out_dir: Union[str, Path], targets: Sequence[Target], scorer_factory: Callable[[], Any],
                  n_samples: int = 50_000, sampling: Optional[SamplingConfig] = None, seed: int = 0,
                  chunk_size: int = 500, workers: int = 2, scorer_description: Optional[str] = None,
                  progress: bool = True, max_chunks: Optional[int] = None, start_method: str = "spawn",
                  worker_timeout: Optional[float] = None, samples: Optional[dict] = None,
                  source: Optional[dict] = None, backend=None,
                  on_start: Optional[Callable[[int, str], None]] = None) -> Path:
    """Sample camera poses around the targets (or take given ones), label them with a scorer, and write a resumable
    chunked dataset.

    Parameters
    ----------
    out_dir : path
        Dataset directory (created). If it already holds a dataset with the same configuration, only missing
        chunks are labelled (resume); a different configuration raises ``ValueError``.
    targets : sequence of Target
        Targets to view; their ``detector_class`` values define the classes. ``n_samples`` is split evenly.
    scorer_factory : picklable callable returning a scorer
        Each worker process calls it once to build its own scorer: an object with ``score(pose_4x4, target_name)``
        (e.g. the rendering oracle, see :class:`OracleFactory`) or such a callable, returning a float or an object
        with a ``score`` attribute (``OracleResult``). If the scorer has ``close()``, it is called at
        the end. A ``description`` attribute/method (or ``scorer_description``) is recorded in the metadata.
    n_samples : int
        Total number of labelled camera poses (paper: 50,000).
    sampling : SamplingConfig
        Pose sampling ranges (defaults: distance 0.4-4 m, height 0.3-1.6 m, all azimuths).
    seed : int
        Seed of the pose sampler.
    chunk_size : int
        Samples per chunk file (the unit of resumption and of work distribution).
    workers : int
        Worker processes; ``0`` labels in this process (no multiprocessing). Each worker builds its own scorer, so
        a scorer's own thread pools (torch, onnxruntime) should be sized for ``cores / workers``.
    progress : bool
        Show a tqdm progress bar (per sample).
    max_chunks : int, optional
        Label at most this many missing chunks in this call, then return (incremental builds).
    start_method : {"spawn", "forkserver"}
        Multiprocessing start method (never ``fork``: scorers may hold GPU/GL contexts or torch threads).
    worker_timeout : float, optional
        Abort if no worker reports anything (a result or progress) for this many seconds.
    samples : dict, optional
        Views to label instead of sampled ones: ``camera_poses`` (N, 4, 4), ``target_index`` (N,) into ``targets``,
        and the parameters of :func:`view_parameters`. ``n_samples`` and ``sampling`` are then ignored; the dataset
        has N samples.
    source : dict, optional
        With ``samples``: how they were made (JSON-serialisable), recorded in the metadata as ``sampling`` (it
        identifies the configuration when resuming). A ``distance`` range there sets the viewpoint split's cells.
    backend : psprm_core.executors.BackendSettings, optional
        Where the chunks are labelled (one task per chunk; each worker builds its scorer once): local worker processes
        or actors on a Ray cluster. Default: ``workers`` local processes with ``start_method``. A chunk whose worker
        dies is labelled again (``max_retries``); a chunk that cannot be labelled is reported and the others go on
        (``RuntimeError`` at the end, naming the chunks; the written ones stay).
    on_start : callable, optional
        ``on_start(chunk_id, worker)`` when a chunk is sent to a worker (``pid@host``, or ``inline``).

    Returns
    -------
    Path
        ``out_dir``. ``metadata.json`` records seed, ranges, targets, classes, counts, the scorer description and
        whether the dataset is complete.
    """
    if not targets:
        raise InputError("build_dataset needs at least one target")
    names = [t.name for t in targets]
    if len(set(names)) != len(names):
        raise InputError(f"duplicate target names: {names}")
    if n_samples < 1 or chunk_size < 1:
        raise InputError("n_samples and chunk_size must be positive")
    if start_method == "fork":
        raise InputError("start_method 'fork' is not supported; use 'spawn' or 'forkserver'")
    if samples is not None:
        n_samples = int(len(samples["camera_poses"]))
        if n_samples < 1:
            raise InputError("samples holds no views")
        counts = [int(c) for c in np.bincount(samples["target_index"], minlength=len(targets))]
        sampling_dict = dict(source or {"source": "given poses"})
    else:
        sampling = sampling or SamplingConfig()
        counts = _per_target_counts(n_samples, len(targets))
        sampling_dict = sampling.to_dict()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    classes = sorted({t.detector_class for t in targets})
    n_chunks = math.ceil(n_samples / chunk_size)
    config = {"format": DATASET_FORMAT, "version": DATASET_VERSION, "seed": int(seed), "n_samples": int(n_samples),
              "chunk_size": int(chunk_size), "n_chunks": n_chunks, "sampling": sampling_dict,
              "targets": [_target_dict(t) for t in targets]}
    meta_path = out_dir / METADATA_FILE
    if meta_path.exists():
        old = json.loads(meta_path.read_text())
        old_cfg = {k: old.get(k) for k in config}
        if old_cfg != json.loads(json.dumps(config)):
            diff = sorted(k for k in config if old_cfg.get(k) != json.loads(json.dumps(config[k])))
            raise InputError(f"{out_dir} holds a dataset with a different configuration (differs in: "
                             f"{', '.join(diff)}); use another directory")
    description = _describe(scorer_factory, scorer_description)
    if meta_path.exists() and old.get("scorer") not in (None, description):
        log.warning("dataset %s was labelled by '%s'; resuming with '%s'", out_dir, old.get("scorer"), description)
    meta = dict(config)
    meta.update({"classes": classes, "scorer": description,
                 "counts": {"per_target": dict(zip(names, counts)),
                            "per_class": {c: sum(k for t, k in zip(targets, counts) if t.detector_class == c)
                                          for c in classes}}})

    if samples is None:
        samples = generate_samples(targets, n_samples, sampling, seed)
    bounds = [(i, i * chunk_size, min(n_samples, (i + 1) * chunk_size)) for i in range(n_chunks)]
    missing = [(i, lo, hi) for i, lo, hi in bounds
               if not (_chunk_path(out_dir, i).exists() and _chunk_valid(_chunk_path(out_dir, i), samples, lo, hi))]
    done_before = n_chunks - len(missing)
    todo = missing if max_chunks is None else missing[:max(0, int(max_chunks))]
    meta.update({"chunks_done": done_before, "complete": done_before == n_chunks})
    _write_json(meta_path, meta)
    log.info("dataset %s: %d samples in %d chunks, %d already labelled, %d to label now", out_dir, n_samples,
             n_chunks, done_before, len(todo))
    if not todo:
        return out_dir

    target_names = np.array(names, dtype=object)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=n_samples, initial=n_samples - sum(hi - lo for _, lo, hi in missing), unit="view",
                   desc="labelling", dynamic_ncols=True)
    written = 0

    def finish(chunk_id: int, scores: np.ndarray) -> None:
        nonlocal written
        _, lo, hi = bounds[chunk_id]
        _write_chunk(_chunk_path(out_dir, chunk_id), _chunk_arrays(samples, lo, hi, scores))
        written += 1
        meta["chunks_done"] = done_before + written
        meta["complete"] = meta["chunks_done"] == n_chunks
        _write_json(meta_path, meta)

    if backend is None:
        backend = BackendSettings(workers=max(0, int(workers)), start_method=start_method)
    tasks = [Task(chunk_id, label_task, (scorer_factory, samples["camera_poses"][lo:hi],
                                         list(target_names[samples["target_index"][lo:hi]])), weight=hi - lo)
             for chunk_id, lo, hi in todo]
    failed = {}
    try:
        with Executor(backend) as ex:
            for out in ex.run(tasks, on_progress=bar.update if bar is not None else None, on_start=on_start,
                              idle_timeout=worker_timeout):
                if out.ok:
                    finish(out.key, out.value)
                else:  # reported, and the other chunks go on; a later run labels it again
                    failed[out.key] = out.error
                    log.error("chunk %d could not be labelled (%d attempt(s)): %s", out.key, out.attempts,
                              out.error.strip().splitlines()[-1] if out.error.strip() else "")
    finally:
        if bar is not None:
            bar.close()
    if failed:
        first = min(failed)
        raise RuntimeError(f"{len(failed)} of {len(todo)} chunks could not be labelled (chunks "
                           f"{sorted(failed)}; the {len(todo) - len(failed)} others are written, and a new run "
                           f"labels only the missing ones); chunk {first}:\n{failed[first]}")
    log.info("dataset %s: %d/%d chunks labelled", out_dir, meta["chunks_done"], n_chunks)
    return out_dir


# ------------------------------------------------------------------------------------------------------------------
# Loading and splitting
# ------------------------------------------------------------------------------------------------------------------
@dataclass
class PerceptionDataset:
    """A labelled dataset in memory (see :func:`load_dataset`).

    Attributes
    ----------
    camera_poses : (N, 4, 4) ndarray
    target_index : (N,) int ndarray
        Index into ``targets``.
    scores : (N,) ndarray
        Labels in [0, 1].
    params : dict of (N,) ndarrays
        Sampling parameters (``distance``, ``azimuth``, ``height``, ``u``, ``v``, ``roll``).
    targets : list of Target
    classes : list of str
        Sorted class names.
    metadata : dict
        Content of ``metadata.json``.
    path : str
        Directory it was loaded from ("" if built in memory).
    """

    camera_poses: np.ndarray
    target_index: np.ndarray
    scores: np.ndarray
    params: dict
    targets: list
    classes: list
    metadata: dict = field(default_factory=dict)
    path: str = ""

    def __len__(self) -> int:
        return int(self.scores.shape[0])

    @property
    def target_poses(self) -> np.ndarray:
        """(N, 4, 4) pose of each sample's target."""
        per_target = np.stack([target_pose_matrix(t) for t in self.targets])
        return per_target[self.target_index]

    @property
    def class_index(self) -> np.ndarray:
        """(N,) index of each sample's class in ``classes``."""
        lut = np.array([self.classes.index(t.detector_class) for t in self.targets])
        return lut[self.target_index]

    @property
    def target_names(self) -> np.ndarray:
        return np.array([t.name for t in self.targets], dtype=object)[self.target_index]

    def subset(self, idx: np.ndarray) -> "PerceptionDataset":
        idx = np.asarray(idx)
        return PerceptionDataset(self.camera_poses[idx], self.target_index[idx], self.scores[idx],
                                 {k: v[idx] for k, v in self.params.items()}, self.targets, self.classes, self.metadata,
                                 self.path)

    def content_hash(self) -> str:
        """SHA-256 (hex, first 16 chars) of poses, target indices and scores (identifies the training data)."""
        return dataset_hash(self)


def dataset_hash(ds: PerceptionDataset) -> str:
    """Content hash of a dataset (see :meth:`PerceptionDataset.content_hash`)."""
    h = hashlib.sha256()
    for a in (ds.camera_poses.astype(np.float64), ds.target_index.astype(np.int64), ds.scores.astype(np.float64)):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(json.dumps([_target_dict(t) for t in ds.targets], sort_keys=True).encode())
    return h.hexdigest()[:16]


def load_dataset(path: Union[str, Path], allow_incomplete: bool = False) -> PerceptionDataset:
    """Load a dataset written by :func:`build_dataset` (all chunks, in index order).

    Raises
    ------
    ConfigError
        No ``metadata.json`` in ``path``.
    InputError
        Chunks are missing and ``allow_incomplete`` is false.
    """
    path = Path(path)
    meta_path = path / METADATA_FILE
    if not meta_path.exists():
        raise ConfigError(str(path), "", f"no {METADATA_FILE} in {path}: not a perception dataset")
    meta = json.loads(meta_path.read_text())
    if meta.get("format") != DATASET_FORMAT:
        raise InputError(f"{meta_path}: not a perception dataset (format={meta.get('format')!r})")
    parts, missing = [], []
    for i in range(meta["n_chunks"]):
        p = _chunk_path(path, i)
        if not p.exists():
            missing.append(i)
            continue
        with np.load(p) as z:
            parts.append({k: z[k] for k in z.files})
    if missing and not allow_incomplete:
        raise InputError(f"dataset {path} is incomplete: {len(missing)} of {meta['n_chunks']} chunks missing "
                         f"(re-run the build to resume, or pass allow_incomplete=True)")
    if not parts:
        raise InputError(f"dataset {path} has no labelled chunks")
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    param_keys = ("distance", "azimuth", "height", "u", "v", "roll")
    return PerceptionDataset(camera_poses=cat["camera_poses"], target_index=cat["target_index"].astype(np.int64),
                             scores=cat["scores"], params={k: cat[k] for k in param_keys if k in cat},
                             targets=[_target_from_dict(t) for t in meta["targets"]], classes=list(meta["classes"]),
                             metadata=meta, path=str(path))


def viewpoint_cells(azimuth: np.ndarray, distance: np.ndarray, n_azimuth_cells: int = 24, n_distance_cells: int = 6,
                    distance_range: Optional[tuple] = None) -> np.ndarray:
    """Coarse viewpoint cell id of each sample (azimuth x distance grid)."""
    az = np.mod(np.asarray(azimuth, float) + math.pi, 2 * math.pi)
    ai = np.minimum((az / (2 * math.pi) * n_azimuth_cells).astype(np.int64), n_azimuth_cells - 1)
    d = np.asarray(distance, float)
    d0, d1 = distance_range if distance_range is not None else (d.min(), d.max())
    di = np.clip(((d - d0) / max(d1 - d0, 1e-12) * n_distance_cells).astype(np.int64), 0, n_distance_cells - 1)
    return ai * n_distance_cells + di


def split_by_viewpoint(azimuth: np.ndarray, distance: np.ndarray, fractions: Sequence[float] = (0.8, 0.1, 0.1),
                       n_azimuth_cells: int = 24, n_distance_cells: int = 6, seed: int = 0,
                       distance_range: Optional[tuple] = None) -> dict:
    """Train/val/test split in which each viewpoint cell (azimuth x distance) goes to exactly one split.

    Cells are shuffled with ``seed`` and assigned one by one to the split furthest below its target share of samples,
    so nearby viewpoints (same cell) never straddle splits and the split sizes approximate ``fractions``.

    Returns
    -------
    dict
        ``{"train": idx, "val": idx, "test": idx}`` with sorted index arrays (a split may be empty if its fraction is
        0 or there are fewer cells than splits).
    """
    fr = np.asarray(fractions, float)
    if fr.shape != (3,) or np.any(fr < 0) or fr.sum() <= 0:
        raise InputError(f"fractions must be three non-negative numbers, got {fractions}")
    fr = fr / fr.sum()
    cells = viewpoint_cells(azimuth, distance, n_azimuth_cells, n_distance_cells, distance_range)
    ids, counts = np.unique(cells, return_counts=True)
    order = np.random.default_rng(seed).permutation(len(ids))
    n = len(cells)
    filled = np.zeros(3)
    assign = {}
    for j in order:
        deficit = fr * n - filled
        k = int(np.argmax(deficit))
        assign[int(ids[j])] = k
        filled[k] += counts[j]
    split_of = np.array([assign[int(c)] for c in ids])[np.searchsorted(ids, cells)]
    return {name: np.flatnonzero(split_of == k) for k, name in enumerate(("train", "val", "test"))}


def split_dataset(ds: PerceptionDataset, fractions: Sequence[float] = (0.8, 0.1, 0.1), n_azimuth_cells: int = 24,
                  n_distance_cells: int = 6, seed: int = 0) -> dict:
    """:func:`split_by_viewpoint` on a dataset (distance cells span the configured distance range)."""
    rng = ds.metadata.get("sampling", {}).get("distance")
    return split_by_viewpoint(ds.params["azimuth"], ds.params["distance"], fractions, n_azimuth_cells,
                              n_distance_cells, seed, tuple(rng) if rng else None)
