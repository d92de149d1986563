"""The device check: the tensor pipeline and the planner on a torch device against independent references
(:mod:`.check`), which are computed here or carried in a file (:mod:`.references`).

    python -m psprm_core.evaluation.device_check --device cuda
    python -m psprm_core.evaluation.device_check --device cuda --references psprm_core/data/device_check/references.npz
"""

from .check import TOLERANCES, check, main, run
from .references import DEFAULT_REFERENCES, References, record

__all__ = ["DEFAULT_REFERENCES", "TOLERANCES", "References", "check", "main", "record", "run"]
