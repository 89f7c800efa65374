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
        The solver that failed ("fixed_point" or "newton").
    t : float or None
        Time at the start of the failed step, when known.
    """

    def __init__(self, h: float, residual: float, iterations: int, solver: str,
                 t: float | None = None, hint: str | None = None):
        self.h, self.residual, self.iterations, self.solver, self.t = h, residual, iterations, solver, t
        if hint is None:
            hint = ("try a smaller step size h" if solver == "newton" else
                    "try a smaller step size h, or solver='newton' for a stiff problem")
        where = "" if t is None else f" at t={t:.17g}"
        super().__init__(
            f"HBVM step of size h={h:.6g}{where} did not converge: {solver} iteration stopped after "
            f"{iterations} iterations with increment {residual:.3e}; {hint}")
