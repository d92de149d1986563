"""What numba's dispatch costs per call for a kernel's arguments given one by one, as one tuple or as one named
tuple: ``python -m psprm_core.evaluation.dispatch_cost`` prints microseconds per call (fastest of 15 runs of
20,000 calls) as one JSON object. Why the compiled kernels take long positional argument lists."""

from __future__ import annotations

import json
import time
from collections import namedtuple


def dispatch_cost(n_arrays: int = 12, calls: int = 20_000, runs: int = 15) -> dict:
    import numpy as np
    from numba import njit

    arrs = [np.zeros((5, 3)) for _ in range(n_arrays)]
    names = [f"a{i}" for i in range(n_arrays)]
    group = namedtuple("Group", names)(*arrs)
    plain = tuple(arrs)
    ns: dict = {"njit": njit}
    exec(f"@njit(nogil=True)\ndef positional({', '.join(names)}):\n    return a0[0, 0] + a{n_arrays - 1}[0, 0]\n", ns)
    first_last = (lambda t: t[0][0, 0] + t[-1][0, 0])
    one_plain, one_named = njit(nogil=True)(first_last), njit(nogil=True)(first_last)  # one signature each
    cases = {"positional": lambda: ns["positional"](*arrs), "tuple": lambda: one_plain(plain),
             "named_tuple": lambda: one_named(group)}
    out = {"arrays": n_arrays}
    for name, fn in cases.items():
        fn()  # compile
        best = float("inf")
        for _ in range(runs):
            t0 = time.perf_counter()
            for _ in range(calls):
                fn()
            best = min(best, (time.perf_counter() - t0) / calls * 1e6)
        out[f"{name}_us"] = round(best, 2)
    return out


if __name__ == "__main__":
    print(json.dumps(dispatch_cost()))
