"""Named errors of the integrators package."""
from __future__ import annotations


class ConvergenceError(RuntimeError):
    """The nonlinear system of an HBVM step did not converge.

    The caller's state is exactly as it was before the step.

    Attributes
    ----------
    h : float
        The step size that was attempted.
    residual : float
        The last increment of the iteration (max norm).
    iterations : int
        Iterations done before giving up.
    solver : str
        The solver that failed: "fixed_point", "newton", or "auto" when the fixed point
        iteration and then Newton both failed (the hint then suggests a smaller step only).
    t : float or None
        Time at the start of the failed step, when known.
    """

    def __init__(self, h: float, residual: float, iterations: int, solver: str,
                 t: float | None = None, hint: str | None = None):
        self.h, self.residual, self.iterations, self.solver, self.t = h, residual, iterations, solver, t
        if hint is None:
            # "auto" (fixed point, then Newton) has tried Newton already: do not suggest it
            hint = ("try a smaller step size h" if solver in ("newton", "auto") else
                    "try a smaller step size h, or solver='newton' for a stiff problem")
        where = "" if t is None else f" at t={t:.17g}"
        super().__init__(
            f"HBVM step of size h={h:.6g}{where} did not converge: {solver} iteration stopped after "
            f"{iterations} iterations with increment {residual:.3e}; {hint}")


class UnresolvedStepError(ConvergenceError):
    """An HBVM step converged but changed the energy by more than the caller's tolerance.

    HBVM conserves H up to the quadrature error of the line integral; a step that changes H
    visibly does not resolve the motion (a close encounter passed within a fraction of a step,
    or the iteration found a spurious root of the nonlinear system).  Nothing was committed.

    Attributes
    ----------
    h, t : float
        The step size and the time at the start of the step.
    change : float
        |H(y1) - H(y0)| relative to the size of the energy terms (|T| + |V|).
    tolerance : float
        The tolerance it exceeded.
    """

    def __init__(self, h: float, change: float, tolerance: float, iterations: int,
                 t: float | None = None, hint: str | None = None):
        RuntimeError.__init__(
            self, f"HBVM step of size h={h:.6g}" + ("" if t is None else f" at t={t:.17g}")
            + f" changed the energy by {change:.3e} (relative), more than energy_tol="
            f"{tolerance:.1e}: the step does not resolve the motion; "
            + (hint or "use a smaller step"))
        self.h, self.residual, self.iterations, self.solver, self.t = h, change, iterations, "fixed_point", t
        self.change, self.tolerance = change, tolerance
