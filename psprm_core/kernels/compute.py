"""Where and how batched work runs: :class:`Compute`, a frozen value built once and handed to every object that
computes (robot FK, collision checks, the visibility projection, the motion metric, the surrogate, ray casting, the
planner's stage backend).

A ``Compute`` names the torch device and dtype, which kernels serve CPU batches (``"numba"``: the compiled kernels of
:mod:`psprm_core.kernels.fastpath` for the batch sizes they serve, torch otherwise; ``"torch"``: torch operators
only, the path a GPU runs) and the batch policy (how many rows a call may have for the compiled path). Its ``ops``
is the implementation of the kernels protocol (:mod:`.ops`) those choices select, and every object calls its batched
verbs through it (``self.compute.ops.camera_poses(self, q)``). The choice is data: an object built with
``Compute.make("cpu", kernels="torch")`` runs its torch code on the CPU, one built with ``Compute.make("cuda")`` runs
on the GPU, and nothing switches kernels process-wide. ``obj.using(compute)`` gives a
copy of a domain object that computes with another ``Compute`` (the equivalence tests run both).

:func:`~.runtime.bulk` is the one scoped policy: inside it (a roadmap build, re-scoring, repair growth) CPU batches
of any size take the compiled kernels, their rows split over a few threads. It is a
:class:`contextvars.ContextVar`, so it holds for the thread (or task) that entered it and for no other: a query on
another thread keeps its small-batch rules.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
from typing import Iterator, Optional, TypeVar

import torch

from ..errors import ConfigError
from .fastpath import NumbaKernels
from .ops import Kernels, TorchKernels
from .runtime import _BULK_WORKERS, bulk, bulk_workers, numba_importable

__all__ = ["Compute", "Computing", "bulk", "bulk_workers", "compute_for", "default_compute", "numba_importable"]

KERNELS = ("numba", "torch")
_IMPLEMENTATIONS = {"numba": NumbaKernels, "torch": TorchKernels}
T = TypeVar("T", bound="Computing")


@dataclasses.dataclass(frozen=True)
class Compute:
    """Device, dtype, kernels and batch policy of an object's batched work.

    ``kernels``: ``"numba"`` (CPU only: compiled kernels for batches up to ``max_batch`` rows, the motion metric up
    to ``motion_max_batch``, the surrogate MLP up to ``mlp_max_rows``; any size inside :func:`bulk`, in chunks of at
    least ``bulk_chunk`` rows) or ``"torch"`` (torch operators on ``device`` at every size). Build it with
    :meth:`make`, which resolves ``"auto"`` and checks the values."""

    device: torch.device = torch.device("cpu")
    dtype: torch.dtype = torch.float32
    kernels: str = "torch"
    max_batch: int = 1024
    motion_max_batch: int = 1 << 16
    mlp_max_rows: int = 32
    bulk_chunk: int = 2048
    ops: Kernels = dataclasses.field(init=False, repr=False, compare=False)

    def __post_init__(self):
        impl = _IMPLEMENTATIONS.get(self.kernels)
        if impl is None:
            raise ConfigError("compute", "kernels", f"must be one of {KERNELS}, got {self.kernels!r}")
        object.__setattr__(self, "ops", impl(self))  # the kernels protocol's implementation (:mod:`.ops`)

    @classmethod
    def make(cls, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32, kernels: str = "auto",
             **policy) -> "Compute":
        """A checked ``Compute``: ``kernels="auto"`` is ``"numba"`` on a CPU where numba imports, else ``"torch"``;
        ``"numba"`` on another device, an unknown kernels name or a batch limit below 1 raise :class:`ConfigError`."""
        dev = torch.device(device)
        if kernels == "auto":
            kernels = "numba" if dev.type == "cpu" and numba_importable() else "torch"
        if kernels not in KERNELS:
            raise ConfigError("compute", "kernels", f"must be one of {KERNELS} or 'auto', got {kernels!r}")
        if kernels == "numba" and dev.type != "cpu":
            raise ConfigError("compute", "kernels", f"the numba kernels run on the CPU only, not on {dev}")
        if kernels == "numba" and not numba_importable():
            raise ConfigError("compute", "kernels", "'numba' asked for, but numba cannot be imported")
        unknown = set(policy) - {f.name for f in dataclasses.fields(cls)} - {"device", "dtype", "kernels"}
        if unknown:
            raise ConfigError("compute", "", f"unknown batch policy {sorted(unknown)}")
        out = cls(dev, dtype, kernels, **policy)
        for name in ("max_batch", "motion_max_batch", "mlp_max_rows", "bulk_chunk"):
            if int(getattr(out, name)) < 1:
                raise ConfigError("compute", name, f"must be at least 1, got {getattr(out, name)!r}")
        return out

    @property
    def compiled(self) -> bool:
        """Whether the compiled CPU kernels serve the batches they fit."""
        return self.kernels == "numba"

    def torch_only(self) -> "Compute":
        """The same device, dtype and limits with torch operators at every size."""
        return dataclasses.replace(self, kernels="torch")

    def fits(self, rows: int, max_batch: Optional[int] = None) -> bool:
        """Whether a call over ``rows`` rows is small enough for the compiled path (any size inside :func:`bulk`)."""
        limit = self.max_batch if max_batch is None else max_batch
        return 0 < rows and (rows <= limit or _BULK_WORKERS.get() > 0)

    def takes(self, x: torch.Tensor, max_batch: Optional[int] = None, bulk_ok: bool = True) -> bool:
        """Whether a batch ``x`` (B, ...) runs compiled: compiled kernels chosen, a CPU tensor of 1..``max_batch``
        rows (any number inside :func:`bulk`, unless ``bulk_ok`` is false: callers whose torch path is faster on large
        batches) that needs no gradient."""
        if not self.compiled or x.device.type != "cpu" or (x.requires_grad and torch.is_grad_enabled()):
            return False
        limit = self.max_batch if max_batch is None else max_batch
        return self.fits(x.shape[0], limit) if bulk_ok else 0 < x.shape[0] <= limit

    def pair_takes(self, qa: torch.Tensor, qb: torch.Tensor) -> bool:
        """Whether a pair of batches (E, dof) runs the compiled motion kernels (same shape and dtype, CPU, see
        :meth:`takes` with ``motion_max_batch``)."""
        return (qa.dim() == 2 and qa.shape == qb.shape and qa.dtype == qb.dtype and qb.device.type == "cpu"
                and not (qb.requires_grad and torch.is_grad_enabled()) and self.takes(qa, self.motion_max_batch))

    @contextlib.contextmanager
    def one_thread(self) -> Iterator[None]:
        """Run a block of small CPU batches (a query, a replan) with torch's intra-op parallelism off, restoring the
        thread count after it (a CUDA device, or one thread already: nothing changes).

        With 2 threads even a reduction over a few hundred numbers can open a parallel region; on a machine whose
        other core is busy that region waits for its second thread to be scheduled, up to a scheduler time slice
        (4-6 ms). With another process busy on the other core, the home query's median was 21 ms with 2 threads and
        8.5 ms with one. The thread count is process-wide: torch work in other threads during the block runs
        single-threaded too."""
        n = torch.get_num_threads()
        if n == 1 or self.device.type != "cpu":
            yield
            return
        torch.set_num_threads(1)
        try:
            yield
        finally:
            torch.set_num_threads(n)


@functools.lru_cache(maxsize=8)
def default_compute(device: str = "cpu", dtype: torch.dtype = torch.float32) -> Compute:
    """``Compute.make(device, dtype)``: what an object built without a ``Compute`` uses (compiled on a CPU with
    numba). A frozen value, the same object for the same arguments."""
    return Compute.make(device, dtype)


def compute_for(device: torch.device | str, dtype: torch.dtype = torch.float32) -> Compute:
    """:func:`default_compute` of a device given as a string or a ``torch.device``."""
    return default_compute(str(torch.device(device)), dtype)


class Computing:
    """An object whose batched methods follow a :class:`Compute`: the one it was built with (``_compute``), else
    the default of :meth:`default_device` (:func:`compute_for`). :meth:`using` gives a copy that computes with
    another; the copy shares the object's tensors and state."""

    _compute: Optional[Compute] = None

    @property
    def compute(self) -> Compute:
        """The :class:`Compute` this object's batched methods follow."""
        c = self._compute
        if c is not None:
            return c
        dev = self.default_device()
        c = self.__dict__.get("_default_compute")
        if c is None or c.device != dev:  # kept per object; looked up again when its device changes
            c = self.__dict__["_default_compute"] = compute_for(dev)
        return c

    def default_device(self) -> torch.device:
        """The device of the default :class:`Compute` (the object's own device where it keeps tensors)."""
        return getattr(self, "device", torch.device("cpu"))

    def using(self: T, compute: Compute) -> T:
        """A shallow copy of this object that computes with ``compute`` (this object unchanged)."""
        if not isinstance(compute, Compute):
            raise ConfigError("compute", "", f"expected a Compute, got {type(compute).__name__}")
        out = copy.copy(self)
        out._compute = compute
        return out
