"""Choosing k for HBVM(k, s): the smallest k that leaves no quadrature error in the energy.

One implementation for every caller: the REBOUND driver measures k when it attaches (on one
shortest orbital period, on the sources and the few test particles that decide k:
``hbvm_md.rebound.integrator.probe_scene``), the work-precision reports and the Brouwer
benchmark on a fixed number of test steps.

* Polynomial H of degree nu (``system.polynomial_degree``): k = max(s, ceil(nu s / 2)) conserves
  H exactly (:meth:`HBVM.for_polynomial_degree`); nothing is run.
* Otherwise the energy error of HBVM(k, s) is the quadrature error of the line integral,
  O(h^(2k)), oscillating with the motion, until it reaches round-off.  It is measured, not
  guessed: :func:`choose_k` runs the scene's first steps with k = s, s + 1, ... and keeps the
  first k whose maximum relative energy error is at most max(2 eps, 1.5 e_ref, 2 ulps of the
  energy's rounding), e_ref being the error of a reference k_ref on the round-off plateau, and
  returns k + 1 (at most k_ref) as a margin: long runs add round-off on top of what the test
  steps show.
* Adaptive steps have no single step to measure on: :func:`adaptive_k` derives k from the
  control's precision epsilon.
"""
from __future__ import annotations

import logging
import math
import numbers
from dataclasses import dataclass, field

import numpy as np

from .errors import StepError
from .tableau import HBVM

_LOG = logging.getLogger(__name__)

#: choose_k keeps k = s after one run when its energy error is within this many ulps of the
#: energy's rounding (see :func:`choose_k`)
EARLY_ULPS = 2.0
#: fewer test steps than this (left before a failure) measure nothing: k_ref is kept
MIN_STEPS = 8
#: a reference error above this many ulps of the energy's rounding is checked for being on the
#: round-off plateau (a larger k must not halve it), up to k = k_cap(s)
PLATEAU_ULPS = 8.0


def k_cap(s: int) -> int:
    """The largest k the plateau search of :func:`choose_k` goes to: 3 s + 12."""
    return 3 * s + 12


@dataclass
class KChoice:
    """The k chosen for HBVM(k, s) on one scene and step, and why.

    Attributes
    ----------
    k, s : int
    reason : str
        "exact for polynomial degree nu", "round-off quadrature error" or, when even the
        reference k failed on the test steps, "reference k (test steps failed)".
    trial_errors : dict
        k -> maximum relative energy error over the test steps, for each k run (inf: the run
        failed); empty for a polynomial H.
    steps : int
        Test steps asked of each trial run (0 for a polynomial H).
    """

    k: int
    s: int
    reason: str
    trial_errors: dict = field(default_factory=dict)
    steps: int = 0


def energy_rounding(system, y0) -> float:
    """eps (|T| + |V|) / |T + V| at y0: the relative rounding of evaluating the energy in double
    precision (0 when the system does not give T and V, or T + V is 0 or not finite)."""
    m = y0.shape[0] // 2
    try:
        if hasattr(system, "separable_kernels") and hasattr(system, "kinetic_weights"):
            _, potential, params = system.separable_kernels()      # compiled: 0.1 ms fewer
            p = y0[m:]
            T = 0.5 * float(np.dot(p * p, system.kinetic_weights))
            V = float(potential(np.ascontiguousarray(y0[:m]), params))
        else:
            T, V = float(system.kinetic(y0[m:])), float(system.potential(y0[:m]))
    except (AttributeError, TypeError, ValueError):
        return 0.0
    r = np.finfo(float).eps * (abs(T) + abs(V)) / abs(T + V) if T + V != 0.0 else 0.0
    return r if math.isfinite(r) else 0.0


def period_steps(period: float, h: float) -> int:
    """Test steps for :func:`choose_k`: one period of the fastest motion at step h (its
    error's amplitude shows over one period), at least MIN_STEPS and at most 400; MIN_STEPS
    when there is no finite period."""
    if not math.isfinite(period):
        return MIN_STEPS
    return int(min(400, max(MIN_STEPS, math.ceil(period / abs(h)))))


def _count(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"`{name}` must be an integer >= {minimum} (got {name}={value!r})")
    return int(value)


def choose_k(system, y0, s: int, h: float, steps: int, k_max: int | None = None,
             solver: str = "auto") -> KChoice:
    """The smallest k for which HBVM(k, s) conserves the energy of ``system`` to round-off.

    Parameters
    ----------
    system : a system of :mod:`systems` (or any the engine accepts)
    y0 : array_like (2m,)
        The state the run will start from.
    s : int
        Degree of the method.
    h : float
        The step size the run will use.
    steps : int
        Test steps of each trial run: :func:`period_steps`, one period of the fastest motion,
        shows the error's amplitude (the REBOUND driver and the reports take it).
    k_max : int, optional
        The reference k_ref, and no larger k is returned.  Default max(2 s, s + 8), raised
        (up to :func:`k_cap`, 3 s + 12) while a larger k still halves its error.
    solver : str
        The engine's solver for the trial runs ("fixed_point" for a host that runs nothing
        else).

    Returns
    -------
    KChoice

    Notes
    -----
    One run usually settles it: k = s + 1 is returned without the reference run when HBVM(s, s)'s
    error is within EARLY_ULPS ulps of the energy's own rounding, eps (|T| + |V|) / |T + V| at y0
    (what evaluating T + V in double precision leaves, which the reference, measured with the
    same energy, does not go below).  Measured on the scenes and steps of
    ``benchmarks/bench_rebound.py`` (15 settings x 9 starts): HBVM(s, s) at round-off shows
    0.97-3.11 such ulps and exits early in 89 of the 135 starts; with a visible quadrature
    error (outer solar system, s = 6, dt = 300 d) it shows 6.5-8.7 and never does.  Where it
    exits early, the full measurement picks the same k, except in 5 starts where its k = s and
    reference draws differed by more than 1.5x by chance and it took 8, 10, 11, 13 or 14 for
    s + 1 (the noise of comparing two round-off draws, which the early exit does not have);
    so an error within EARLY_ULPS ulps of the rounding passes for every k, whatever the
    reference drew.

    The reference must be on the round-off plateau itself: when its error is above PLATEAU_ULPS
    ulps of the energy's rounding, k_ref grows (by max(2, s // 2), up to 3 s + 12) while each
    step halves its error, and when no k below it is at round-off the margin is k_ref + 1.
    Kepler e = 0.6 at 25 steps a period needs it: over one period HBVM(10, 2) leaves 1.3e-13
    (7e-12 over 100 periods), HBVM(12, 2) 1.8e-15, and k = 13 is returned (7e-15 over 100
    periods).  On the planetary scenes of ``benchmarks/bench_rebound.py`` the reference is at
    the rounding and nothing more is run.  The test steps see one period: at such coarse steps
    an error that grows over many periods can still escape them (Kepler, s = 3, 25 steps a
    period: HBVM(11, 3) 4e-15 over one period, 8e-13 over 100; the k = 12 returned 4e-14).

    When even k_ref fails on the test steps (an encounter ahead that a step of size h does not
    resolve, or a step too large for the iteration), the measurement is repeated on the steps
    before the failure, or k_ref is returned when fewer than MIN_STEPS remain; either is logged,
    and the run itself then reports the step it cannot take.
    """
    from integrators import integrate      # looked up at call time (tests count the runs)

    s = _count("s", s, 1)
    nu = getattr(system, "polynomial_degree", None)
    if nu is not None:
        return KChoice(HBVM.for_polynomial_degree(nu, s).k, s, f"exact for polynomial degree {nu}")
    steps = _count("steps", steps, 1)
    k_ref = max(2 * s, s + 8) if k_max is None else _count("k_max", k_max, s)
    y0 = np.asarray(y0, dtype=float)
    if y0.ndim != 1 or y0.size == 0 or y0.size % 2:
        raise ValueError(f"`y0` must be one state (q, p) of shape (2m,) (got shape {y0.shape}); "
                         "pass the state the run starts from, not a stack of states")
    if not np.all(np.isfinite(y0)):
        raise ValueError("`y0` has non-finite entries: k is measured by running from it; pass "
                         "a finite state")
    errors: dict = {}

    def err(k):
        if k not in errors:
            try:
                res = integrate(HBVM(k, s), system, y0, h, steps, solver=solver)
                errors[k] = res.max_energy_error
            except StepError:
                errors[k] = math.inf
                raise
        return errors[k]

    def done(k, reason="round-off quadrature error"):
        return KChoice(int(k), s, reason, dict(errors), steps)

    early = energy_rounding(system, y0)
    if early > 0.0:
        try:
            if err(s) <= EARLY_ULPS * early:
                return done(min(s + 1, k_ref))
        except StepError:
            pass                  # the full measurement below says what to do
    try:
        e_ref = err(k_ref)
    except StepError as exc:
        ran = int(round((exc.t or 0.0) / abs(h)))
        if ran < MIN_STEPS:
            _LOG.warning("k probe: HBVM(%d, %d) failed after %d steps of h=%.6g (%s); using "
                         "k=%d", k_ref, s, ran, h, exc, k_ref)
            return done(k_ref, "reference k (test steps failed)")
        _LOG.warning("k probe: HBVM(%d, %d) failed after %d steps of h=%.6g; probing k on "
                     "those %d steps only", k_ref, s, ran, h, ran)
        steps = ran
        errors.clear()
        try:
            e_ref = err(k_ref)
        except StepError:
            return done(k_ref, "reference k (test steps failed)")
    if k_max is None:
        # k_ref must itself be on the round-off plateau (see the notes): unless its error is at
        # the energy's rounding, k_ref grows while each larger k halves the error.
        while e_ref > PLATEAU_ULPS * early and k_ref < k_cap(s):
            k_next = min(k_cap(s), k_ref + max(2, s // 2))
            try:
                e_next = err(k_next)
            except StepError:
                break
            if e_next > 0.5 * e_ref:
                break
            k_ref, e_ref = k_next, e_next
    # an error within EARLY_ULPS of the energy's rounding is round-off whatever the reference
    # drew (two round-off draws differ by more than 1.5x by chance)
    bound = max(2 * np.finfo(float).eps, 1.5 * e_ref, EARLY_ULPS * early)
    for k in range(s, k_ref):
        try:
            if err(k) <= bound:
                return done(min(k + 1, k_ref))
        except StepError:
            continue
    # k_ref is the first at round-off: the margin is one above it, unless k_max forbids
    return done(k_ref if k_max is not None else min(k_ref + 1, k_cap(s)))


def adaptive_k(s: int, epsilon: float) -> int:
    """k for adaptive steps: the smallest k > s with epsilon^(2k / (2s + 1)) <= 1e-16.

    The control keeps each step's estimated local error (:func:`integrators.core.
    resolution_error`, relative to the motion over the step) near epsilon; that error goes
    like (omega h)^(2s+1), omega the motion's local frequency, so the steps it takes have
    omega h about epsilon^(1 / (2s + 1)), and the quadrature error of HBVM(k, s) in the energy,
    about (omega h)^(2k), stays at round-off on every step the control takes.  For REBOUND's
    default s = 6, epsilon = 3e-15 (:data:`integrators.engine.DEFAULT_EPSILON`) it gives
    k = 8; measured (`python benchmarks/bench_defaults.py --variant`, REBOUND's outer solar
    system over 1000 Jupiter years, 5 starts): HBVM(8, 6) at epsilon 1e-13 keeps the energy at
    4.1e-15 (IAS15 2.7e-15); at 1e-10, where this gives k = 11, HBVM(8, 6) leaves it at 6e-13."""
    need = 16.0 * (2 * s + 1) / (2.0 * -math.log10(epsilon))
    return int(min(128, max(s + 1, math.ceil(need - 1e-9))))
