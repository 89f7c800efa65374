"""Choosing HBVM's k: as small as the scene allows.

* Polynomial H of degree nu: k = max(s, ceil(nu s / 2)) conserves H exactly (BIT 2010, eq. (knu)).
* Otherwise the energy error is the quadrature error of the line integral, which falls as k
  grows until it reaches round-off; :func:`choose_k` increases k until the energy error of a
  few test steps stops improving, and :func:`k_cost` measures what a larger k would cost.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from integrators import HBVM, ConvergenceError, StepError, integrate


@dataclass
class KChoice:
    """The k chosen for HBVM(k, s) on one scene and why.

    Attributes
    ----------
    k, s : int
    reason : str
        "exact for polynomial degree nu" or "round-off quadrature error".
    trial_errors : dict
        k -> max relative energy error over the test steps (empty for polynomial H).
    """

    k: int
    s: int
    reason: str
    trial_errors: dict = field(default_factory=dict)

    @property
    def method(self) -> HBVM:
        return HBVM(self.k, self.s)


def _check_s(s) -> int:
    if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 1:
        raise ValueError(f"`s` must be an integer >= 1 (got s={s!r})")
    return int(s)


def choose_k(s: int, system, y0, h: float, test_steps: int = 20, k_max: int | None = None) -> KChoice:
    """The smallest k for which HBVM(k, s) conserves the energy of ``system`` to round-off.

    Parameters
    ----------
    s : int
        Degree of the method.
    system : HamiltonianSystem
    y0 : array_like (2m,)
    h : float
        The step size that will be used.
    test_steps : int
        Steps of each trial run (non-polynomial H only).
    k_max : int, optional
        Largest k tried (default 3 s + 12).

    Returns
    -------
    KChoice

    Notes
    -----
    For a non-polynomial H, k runs from s upwards; the trial error of each k is the largest
    relative energy error over ``test_steps`` steps.  The search stops when two k in a row
    fail to halve the best error (the round-off plateau), and the smallest k within a factor 2
    of the best error is returned.  A trial whose iteration does not converge counts as an
    infinite error.
    """
    s = _check_s(s)
    nu = getattr(system, "polynomial_degree", None)
    if nu is not None:
        k = max(s, -(-int(nu) * s // 2))
        return KChoice(k, s, f"exact for polynomial degree {nu}")
    if isinstance(test_steps, bool) or not isinstance(test_steps, (int, np.integer)) or test_steps < 1:
        raise ValueError(f"`test_steps` must be an integer >= 1 (got test_steps={test_steps!r})")
    k_max = 3 * s + 12 if k_max is None else int(k_max)
    if k_max < s:
        raise ValueError(f"`k_max` must be >= s (got k_max={k_max}, s={s})")
    errors: dict[int, float] = {}
    best = np.inf
    stalls = 0
    for k in range(s, k_max + 1):
        try:
            r = integrate(HBVM(k, s), system, y0, h, int(test_steps))
            err = r.max_energy_error
        except StepError:
            err = np.inf
        errors[k] = err
        if err < 0.5 * best:
            stalls = 0
        else:
            stalls += 1
        best = min(best, err)
        if stalls >= 2:
            break
    if not np.isfinite(best):
        raise ConvergenceError(h, float("inf"), 0, "fixed_point", None,
                               hint=f"no k in [{s}, {k_max}] converged; try a smaller step size h")
    k = min(kk for kk, e in errors.items() if e <= 2 * best)
    return KChoice(k, s, "round-off quadrature error", errors)


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
