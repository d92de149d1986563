"""Labelling workers of the perception datasets (:mod:`psprm_core.perception.dataset` re-exports them): the
picklable factory of the rendering oracle (:class:`OracleFactory`) and the executor's task that labels one chunk of
views with the worker's scorer (:func:`label_task`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np

from ..paths import project_root
from ..scene import load_scene
from .oracle import Oracle


# ------------------------------------------------------------------------------------------------------------------
# Labelling workers
# ------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class OracleFactory:
    """Picklable factory building the rendering oracle (:class:`psprm_core.perception.oracle.Oracle`) in a worker.

    Parameters
    ----------
    scene_path : str
        Scene YAML file (loaded in the worker; a relative path that is not found from the worker's directory is
        taken from the project's root, as the dataset's metadata records it).
    oracle_kwargs : dict
        Keyword arguments for ``Oracle(scene, **oracle_kwargs)`` (must be picklable).
    """

    scene_path: str
    oracle_kwargs: dict = field(default_factory=dict)

    @property
    def description(self) -> str:
        extra = f", {self.oracle_kwargs}" if self.oracle_kwargs else ""
        return f"Oracle(scene={self.scene_path}{extra})"

    def __call__(self) -> Any:
        path = Path(self.scene_path)
        if not path.is_absolute() and not path.is_file():  # a project-relative path, on a worker started elsewhere
            path = project_root() / path
        return Oracle(load_scene(path), **self.oracle_kwargs)


def _score_fn(scorer: Any) -> Callable[[np.ndarray, str], float]:
    if hasattr(scorer, "score"):
        return scorer.score
    if callable(scorer):
        return scorer
    raise TypeError(f"scorer {scorer!r} has neither a score(pose, target_name) method nor is callable")


def _label_chunk(score: Callable, poses: np.ndarray, names: Sequence[str], report: Optional[Callable[[int], None]],
                 every: int) -> np.ndarray:
    out = np.empty(len(poses))
    pending = 0
    for i, (pose, name) in enumerate(zip(poses, names)):
        result = score(pose, name)
        out[i] = float(getattr(result, "score", result))  # a float, or a result object such as OracleResult
        pending += 1
        if report is not None and pending >= every:
            report(pending)
            pending = 0
    if report is not None and pending:
        report(pending)
    return out


def _close_scorer(scorer: Any) -> None:
    close = getattr(scorer, "close", None)
    if callable(close):
        close()


def _factory_key(factory: Callable[[], Any]) -> Any:
    """What identifies a scorer factory in a worker's cache: its pickle (equal factories share a scorer)."""
    import pickle

    try:
        return pickle.dumps(factory)
    except Exception:  # noqa: BLE001 - an in-process factory that cannot be pickled (a lambda): itself
        return ("object", id(factory))


def label_task(cache, factory: Callable[[], Any], poses: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """The executor's task (:mod:`psprm_core.executors`): label one chunk's views with the worker's scorer (built by
    ``factory()`` on the worker's first chunk and kept); progress is reported every 10 views."""
    scorer = cache.get("scorer", _factory_key(factory), factory, close=_close_scorer)
    return _label_chunk(_score_fn(scorer), poses, names, cache.report, 10)
