"""Kernel inputs as arrays: the conversions the owners of the kernel packs (:mod:`._fast_packs`) use to build them."""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch


def as_f64(x) -> np.ndarray:
    """A C-contiguous float64 array of ``x`` (a tensor, detached and on the CPU, or array-like): a kernel input."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().double().numpy()
    return np.ascontiguousarray(np.asarray(x, dtype=np.float64))


def as_i64(x) -> np.ndarray:
    """A C-contiguous int64 array of ``x`` (a tensor, detached and on the CPU, or array-like): a kernel input."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.ascontiguousarray(np.asarray(x, dtype=np.int64))


def const_f64(t: torch.Tensor, dtype: Optional[torch.dtype] = None) -> np.ndarray:
    """float64 copy of a constant tensor (limits, target point), first rounded to ``dtype`` if given (as the torch
    path casts it); kept on the tensor until it changes in place."""
    cache = getattr(t, "_fast_f64", None)
    if cache is None:
        cache = t._fast_f64 = {}
    got = cache.get(dtype)
    key = (t._version, t.data_ptr())  # in-place changes; a copied tensor (and its copied attributes) has new storage
    if got is None or got[0] != key:
        got = cache[dtype] = (key, as_f64(t if dtype is None else t.to(dtype)))
    return got[1]
