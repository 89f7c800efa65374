"""Named errors of a failed HBVM step, and the one table from status codes to them.

A failed step changes nothing: the caller's state, time and coefficients are as before it.
When :func:`integrators.integrate` fails, the exception's ``result`` holds what was computed up
to the last committed step (like scipy's ``solve_ivp``).
"""
from __future__ import annotations

import re

from .core import DIVERGED, DRIFTED, NOT_FINITE, NOT_RESOLVED, UNRESOLVED
from .equip_core import ALPHA_LIMIT, NO_ENERGY_ROOT


def _rebuild(cls, args, state):
    err = cls.__new__(cls)
    RuntimeError.__init__(err, *args)
    err.__dict__.update(state)
    return err


class StepError(RuntimeError):
    """Base class: an HBVM step was not taken.

    Attributes
    ----------
    h : float
        The step size that was attempted (in the caller's time unit).
    t : float or None
        Time at the start of the failed step, when known.
    iterations : int
        Iterations the failed step did.
    solver : str
        The solver that failed: "fixed_point", "newton", or "auto" when the fixed-point
        iteration and then Newton both failed (the hint then suggests a smaller step only).
    result : IntegrationResult or None
        Set by :func:`integrators.integrate`: the samples up to the last committed step, with
        ``status`` "failed" and ``message``.
    """

    result = None
    method = "HBVM"     # the method's name in the message (errors.step_error sets EQUIP's)

    def __reduce__(self):
        # the subclasses' __init__ take other arguments than args: copy and pickle (dask sends
        # errors between processes) rebuild from the message and the attributes
        return _rebuild, (type(self), self.args, self.__dict__)

    def _where(self) -> str:
        return (f"{self.method} step of size h={self.h:.6g}"
                + ("" if self.t is None else f" at t={self.t:.17g}"))


class ConvergenceError(StepError):
    """The nonlinear system of an HBVM step did not converge to round-off (or to ``tol``).

    Attributes (besides :class:`StepError`'s): ``residual``, the last increment (max norm).
    """

    def __init__(self, h: float, residual: float, iterations: int, solver: str,
                 t: float | None = None, hint: str | None = None):
        self.h, self.residual, self.iterations, self.solver, self.t = h, residual, iterations, solver, t
        if hint is None:
            # "auto" (fixed point, then Newton) has tried Newton already: do not suggest it
            hint = ("try a smaller step size h" if solver in ("newton", "auto") else
                    "try a smaller step size h, or solver='newton' for a stiff problem")
        self.hint = hint
        what = ("fixed_point iteration failed, then the newton iteration stopped" if solver == "auto"
                else f"{solver} iteration stopped")
        super().__init__(f"{self._where()} did not converge: {what} after {iterations} "
                         f"iterations with increment {residual:.3e}; {hint}")


class EnergyConditionError(ConvergenceError):
    """An EQUIP step whose energy condition has no root near the last step's alpha: its Gauss
    iteration converged for every alpha tried, but H(y1(alpha)) - H(y0) kept one sign over
    |alpha - alpha_last| <= :data:`integrators.equip_core.ALPHA_LIMIT`
    (:func:`integrators.equip_core.update_alpha`; the derivation is in
    :mod:`integrators.equip`).  Nothing was committed.  A subclass of ConvergenceError: the
    step's nonlinear system (stages and alpha together) has no solution there."""

    def __init__(self, h: float, residual: float, iterations: int, solver: str,
                 t: float | None = None, hint: str | None = None, method: str = "EQUIP"):
        self.h, self.residual, self.iterations, self.solver, self.t = h, residual, iterations, solver, t
        self.method = method
        self.hint = hint or ("use a smaller step (the energy condition's root moves towards "
                             "alpha = 0 as h^(2s-2)), or HBVM(k, s), which conserves the energy "
                             "without alpha")
        RuntimeError.__init__(self, f"{self._where()} did not converge: no alpha (the "
                                    f"perturbation of the Gauss method) within {ALPHA_LIMIT:g} "
                                    f"of the secant's last conserves the energy (E(alpha) keeps "
                                    f"one sign there: dE/dalpha, whose leading term is -xi_1^2 "
                                    f"h^3 H'''(y)(f, f, f), passes through zero near this "
                                    f"state); {self.hint}")


class NonFiniteError(ConvergenceError):
    """A force, an energy or the new state of an HBVM step is not finite (nan or inf): two
    bodies at the same place, a step far too large, or a model that breaks down there."""

    def __init__(self, h: float, iterations: int, solver: str, t: float | None = None,
                 hint: str | None = None):
        self.h, self.residual, self.iterations, self.solver, self.t = h, float("nan"), iterations, solver, t
        self.hint = hint or "try a smaller step size h, and check the state for coincident particles"
        RuntimeError.__init__(self, f"{self._where()} produced non-finite values (nan or inf) "
                                    f"after {iterations} iterations; {self.hint}")


class UnresolvedStepError(StepError):
    """An HBVM step converged but changed the energy by more than the caller's tolerance.

    HBVM conserves H up to the quadrature error of the line integral; a step that changes H
    visibly does not resolve the motion (a close encounter passed within a fraction of a step,
    or the iteration found a spurious root of the nonlinear system).  Nothing was committed.

    Attributes (besides :class:`StepError`'s): ``change``, |H(y1) - H(y0)| relative to the size
    of the energy terms (|T| + |V|); ``tolerance``, the tolerance it exceeded; ``flow``, True
    when the check was that of a method not exact for H (``energy_tol="auto"``): the change
    exceeded both the tolerance and far more of the energy the step moved between the terms of
    H than the method's own error at a step that resolves its path
    (:data:`integrators.core.FLOW_FRACTION`).
    """

    def __init__(self, h: float, change: float, tolerance: float, iterations: int,
                 t: float | None = None, hint: str | None = None, solver: str = "fixed_point",
                 flow: bool = False):
        self.h, self.t, self.iterations, self.solver = h, t, iterations, solver
        self.change, self.tolerance, self.residual, self.flow = change, tolerance, change, flow
        self.hint = hint or ("use a smaller step (one that resolves the encounter: several "
                             "steps over its closest approach), or adaptive steps" if flow else
                             "use a smaller step")
        what = (f"more than energy_tol={tolerance:.1e} and far more than its own error allows "
                f"against the energy it moved between the terms of H: the state is not a "
                f"solution of the step (a step too large for the close encounter or pericentre "
                f"it crosses, or a spurious root)" if flow else
                f"more than energy_tol={tolerance:.1e}: the step does not resolve the motion")
        super().__init__(f"{self._where()} changed the energy by {change:.3e} (relative), "
                         f"{what}; {self.hint}")


class EnergyDriftError(UnresolvedStepError):
    """A step of a method not exact for H (k = s, the Gauss method, or k too small for H's
    quadrature) converged and passed its own checks, but the run's energy now stands more than
    :data:`integrators.core.DRIFT_BOUND` of the run's kinetic scale, max(T, <T> sqrt(<T> /
    Tmax)) (T after the step, <T> its time mean and Tmax its largest over the run), away from
    its start: the orbit's size and period are off by about as much, its phase by ten times that
    a period, and its position by that times the fastest speed over the mean one.  No shorter step in
    its place can undo the run's past, so adaptive steps do not retry it.  Nothing was committed.

    Attributes (besides :class:`UnresolvedStepError`'s): ``drift``, the energy's distance from
    its start relative to that scale (also ``change``), and ``bound``, the bound it exceeded.
    The message names no step size: the drift found here is the first to pass the bound, and a
    run's drift can still grow after it (a pericentre passage's offset is set over the whole
    passage), so a step computed from it would not be a way out that works.
    """

    def __init__(self, h: float, drift: float, bound: float, iterations: int, s: int,
                 t: float | None = None, hint: str | None = None, solver: str = "fixed_point"):
        way = hint or (f"give the line integral more quadrature nodes: integrators.kchoice."
                       f"choose_k(system, y0, {s}, h, steps) finds the fewest that keep H to "
                       f"round-off at this step (HBVM({2 * s}, {s}) is often enough)")
        hint = (f"{way}; or a smaller step (the drift of HBVM with too few nodes falls like "
                f"h^{2 * s}); or energy_tol=None to accept the drift")
        super().__init__(h, drift, bound, iterations, t, hint, solver)
        RuntimeError.__init__(self, (
            f"{self._where()} leaves the run's energy {drift:.3e} (relative to its kinetic "
            f"energy, max(T, <T> sqrt(<T> / Tmax)) over the run) away "
            f"from its start, more than {bound:.1e}: HBVM with this many quadrature nodes does "
            f"not keep this H, and an energy this far off puts the orbit off too (its size and "
            f"period by about as much, its phase by ten times that a period), although every "
            f"step passed its own checks; {hint}"))
        self.drift, self.bound = drift, bound


class AccumulatedErrorWarning(UserWarning):
    """A run's accumulated error estimate passed :data:`integrators.core.RUN_ERROR_BOUND`
    (1e-2): the sum over its steps of each step's own error estimate (plus the phase its
    energy drift makes, for a method that does not keep H) times the share of its body's motion
    the step turns (:func:`integrators.core.run_error_share`), the error relative
    to the motion's own scale (an orbit's radius) that the steps' errors make when they add, as
    the phase error of a periodic orbit does (a lower bound for a chaotic one, whose errors
    grow faster).  Every step passed its own checks; the run as a whole keeps less than two
    digits of its path.  Warned once a run (the engine, REBOUND); ASE reports the estimate and
    never warns.  Make it an error with ``warnings.simplefilter("error",
    AccumulatedErrorWarning)``.

    Attributes: ``estimate`` (the run's accumulated estimate), ``bound``, ``t`` (the time it
    was found at, the end of the call that passed it)."""

    def __init__(self, estimate: float, bound: float, t: float | None = None,
                 way_out: str = "a smaller step (the estimate falls like h^(2s)) or a larger s"):
        where = f" at t={t!r}" if t is not None else ""
        super().__init__(
            f"the run's accumulated error estimate is {estimate:.3g}{where}, above {bound:g} "
            f"of the motion's scale (an orbit's radius): each step kept its own error below its "
            f"bound, but their sum over the run, the error of a periodic orbit's phase (a lower "
            f"bound for a chaotic one), leaves fewer than two correct digits of the path; use "
            f"{way_out}.  warnings.simplefilter('error', AccumulatedErrorWarning) makes this an "
            f"error")
        self.estimate, self.bound, self.t = estimate, bound, t


def unresolved_by_estimate(h: float, estimate: float, bound: float, body: int, s: int,
                           iterations: int, t: float | None, solver: str = "fixed_point",
                           hints: dict | None = None) -> "UnresolvedStepError":
    """The UnresolvedStepError of a step refused by its own error estimate (status
    NOT_RESOLVED, :func:`integrators.core.resolution_error`): it names the body (``hints
    ["body"]``, a format with ``{i}``: "atom {i}", "particle {i}"; "body {i}" by default), the
    estimate, the bound and a step that would pass (:func:`integrators.core.suggested_step`);
    ``hints["resolution"]``: a host's own way out, after the step size; ``hints["switch_off"]``:
    the host's switch for the check ("error_bound=None" by default)."""
    from .core import suggested_step
    hints = hints or {}
    h_ok = suggested_step(abs(h), estimate, bound, s)
    who = hints.get("body", "body {i}").format(i=body) if body >= 0 else "the state"
    way = hints.get("resolution", "or adaptive steps (adaptive=True), which shrink through it")
    off = hints.get("switch_off", "error_bound=None")
    hint = (f"use a smaller step (h={h_ok:.3g} or less here: the estimate falls like "
            f"h^{s + 1} or faster), {way}; or {off} to accept such steps")
    exc = UnresolvedStepError(h, estimate, bound, iterations, t, hint, solver)
    where = exc._where()
    RuntimeError.__init__(exc, (
        f"{where} does not resolve the motion of {who}: its own estimate of its local error, "
        f"{estimate:.3e} of {who}'s motion over the step (from the first Legendre term the "
        f"step leaves out of its velocity), exceeds error_bound={bound:.3g}, so the state it "
        f"reached is not a solution (the energy cannot tell: HBVM keeps it whether or not the "
        f"step followed the motion); {hint}"))
    exc.estimate, exc.bound, exc.body, exc.suggested_h = estimate, bound, body, h_ok
    return exc


class ConstraintError(StepError):
    """A step with holonomic constraints (rigid bonds, :mod:`integrators.holonomic`) could not
    keep them: the bond lengths after the step (or after moving a start onto them) are off by
    more than the tolerance.  Nothing was committed.

    Attributes (besides :class:`StepError`'s): ``violation``, the largest |r - d| found (in the
    positions' unit).
    """

    def __init__(self, h: float, t: float | None, violation: float, hint: str):
        self.h, self.t, self.iterations, self.solver = h, t, 0, "fixed_point"
        self.violation, self.residual, self.hint = violation, violation, hint
        super().__init__(f"{self._where()} did not keep the constraints (largest bond-length "
                         f"error {violation:.3e}): {hint}")


class StepSizeError(StepError):
    """An adaptive step could not be resolved even at the smallest step allowed (``min_dt``, or
    the smallest step that still changes t): its error estimate stayed above ``epsilon``, or
    its iteration or energy check failed (steps shrinking into a collision)."""

    def __init__(self, h: float, min_dt: float, t: float | None, cause: str):
        self.h, self.t, self.iterations, self.solver, self.min_dt = h, t, 0, "fixed_point", min_dt
        self.hint = ("lower min_dt, raise epsilon, or check the state (two bodies on top of each "
                     "other, a singular force)")
        # (with min_dt = 0 the floor is the smallest step that still changes t)
        floor = f"min_dt={min_dt:.6g}" if min_dt > 0 else "the smallest step that changes t"
        super().__init__(f"{self._where()}: the adaptive step fell below {floor} "
                         f"without being resolved ({cause}); {self.hint}")


def step_error(status: int, h: float, t: float | None, counters, solver: str, *,
               energy_tol: float | None = None, hints: dict | None = None,
               method: str | None = None, error_bound: float = 0.0, s: int = 1) -> StepError:
    """The exception for a failed step's status code (the one table of the project).

    ``counters`` is the step's counter array (layout in :mod:`integrators.core`); ``solver``
    the solver that failed, or "auto" when the automatic switch to Newton failed too; ``hints``
    maps "diverged", "not_finite" and "unresolved" to a host's own advice (REBOUND's sim.dt,
    ASE's timestep).  ``energy_tol`` is the check the step ran (:func:`integrators.engine.
    energy_check`: negative for the energy-flow check of a method not exact for H).
    ``method``: the name the message gives the step ("HBVM", "EQUIP"; None: the error's own,
    HBVM but for EQUIP's energy condition); ``error_bound`` and ``s``: the bound a step's own
    error estimate exceeded (NOT_RESOLVED) and the method's s (for the step that would pass)."""
    exc = _step_error(status, h, t, counters, solver, energy_tol, hints or {}, error_bound, s)
    if method is not None and method != exc.method:
        exc.method = method
        exc.args = (re.sub(r"^\w+ step", f"{method} step", str(exc), count=1),)
    return exc


def _step_error(status, h, t, counters, solver, energy_tol, hints, error_bound, s):
    from .core import C_CHANGE, C_ERR, C_LAST, C_LASTIT, C_WORST
    it = int(counters[C_LASTIT])
    if status == NOT_RESOLVED:
        return unresolved_by_estimate(h, float(counters[C_ERR]), error_bound,
                                      int(counters[C_WORST]), s, it, t, solver, hints)
    if status == NO_ENERGY_ROOT:
        return EnergyConditionError(h, float(counters[C_LAST]), it, solver, t,
                                    hints.get("energy_condition"))
    if status == DIVERGED:
        return ConvergenceError(h, float(counters[C_LAST]), it, solver, t, hints.get("diverged"))
    if status == NOT_FINITE:
        return NonFiniteError(h, it, solver, t, hints.get("not_finite"))
    if status == DRIFTED:
        from .core import DRIFT_BOUND
        return EnergyDriftError(h, float(counters[C_CHANGE]), DRIFT_BOUND, it, s, t,
                                hints.get("drifted"), solver)
    if status == UNRESOLVED:
        etol = float(energy_tol or 0.0)
        return UnresolvedStepError(h, float(counters[C_CHANGE]), abs(etol), it, t,
                                   hints.get("unresolved"), solver, flow=etol < 0)
    raise ValueError(f"unknown step status {status!r}")
