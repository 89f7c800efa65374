"""What a larger k costs: :func:`k_cost`.

Choosing k itself is :func:`integrators.kchoice.choose_k` (one implementation for every host
and report).
"""
from __future__ import annotations

import time

from integrators import HBVM, integrate

__all__ = ["k_cost"]


def k_cost(s: int, k: int, system, y0, h: float, steps: int = 200, extra: int = 4) -> dict:
    """Time per step of HBVM(k, s) and HBVM(k + extra, s) measured back to back.

    Returns
    -------
    dict
        ``k``, ``k_larger``, ``us_per_step``, ``us_per_step_larger``, ``ratio`` (larger / chosen).
    """
    out = {"k": int(k), "k_larger": int(k + extra)}
    for key, kk in (("us_per_step", k), ("us_per_step_larger", k + extra)):
        m = HBVM(kk, s)
        integrate(m, system, y0, h, 2)       # compile / warm up outside the timing
        t0 = time.perf_counter()
        r = integrate(m, system, y0, h, int(steps), sample_every=max(int(steps), 1))
        out[key] = 1e6 * (time.perf_counter() - t0) / max(r.steps, 1)
    out["ratio"] = out["us_per_step_larger"] / out["us_per_step"]
    return out
