"""The stepping engine: one public :class:`Stepper` that owns time, state and counters, and
:func:`integrate`, which runs a Stepper (or the compiled fast path) over many steps.

Like scipy's ``OdeSolver``: the public ``step`` owns time, counters and status; the private
``_solve`` does the nonlinear solve of one step and changes nothing on failure.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .errors import ConvergenceError
from .forms import FullForm, SeparableForm
from .protocol import adapt_system
from .solvers import SimplifiedNewton, StopRule, fixed_point, newton

SOLVERS = ("auto", "fixed_point", "newton")
FORMS = ("auto", "full", "separable")


def _is_separable(system) -> bool:
    return all(hasattr(system, a) for a in ("masses", "forces", "potential"))


def check_state(system, y, name: str = "y0"):
    """(system, y): the system as the engine calls it (:func:`.protocol.adapt_system`) and a
    float copy of y, checked: shape (2 * system.dim,) and finite."""
    try:
        y = np.array(y, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be an array of numbers (got {y!r})") from None
    if not np.all(np.isfinite(y)):
        bad = np.flatnonzero(~np.isfinite(y))
        raise ValueError(f"`{name}` must be finite (got {y.flat[bad[0]]} at index {bad[0]}, {bad.size} "
                         f"non-finite of {y.size}); check the initial state for nan or inf")
    system = adapt_system(system, y)
    if y.shape != (2 * system.dim,):
        raise ValueError(f"`{name}` must have shape ({2 * system.dim},) = (q, p) of a system with "
                         f"{system.dim} degrees of freedom (got shape {y.shape})")
    return system, y


def check_step(h) -> float:
    try:
        hf = float(h)
    except (TypeError, ValueError):
        raise ValueError(f"`h` must be a nonzero finite number (got h={h!r})") from None
    if not np.isfinite(hf) or hf == 0.0:
        raise ValueError(f"`h` must be a nonzero finite number (got h={h!r})")
    return hf


def check_options(solver, form, tol, max_iter, t0) -> float:
    """Check the options shared by :class:`Stepper` and :func:`integrate`; returns float(t0)."""
    if not isinstance(solver, str) or solver not in SOLVERS:
        raise ValueError(f"`solver` must be one of {SOLVERS} (got solver={solver!r})")
    if not isinstance(form, str) or form not in FORMS:
        raise ValueError(f"`form` must be 'auto', 'full' or 'separable' (got form={form!r})")
    if tol is not None and (isinstance(tol, bool) or not isinstance(tol, (int, float, np.number))
                            or not (np.isfinite(tol) and 0 < tol < 1)):
        raise ValueError(f"`tol` must be None (round-off) or a number in (0, 1) (got tol={tol!r})")
    if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer))
                                 or max_iter < 1):
        raise ValueError(f"`max_iter` must be a positive integer (got max_iter={max_iter!r})")
    try:
        t0f = float(t0)
    except (TypeError, ValueError):
        raise ValueError(f"`t0` must be a finite number (got t0={t0!r})") from None
    if not np.isfinite(t0f):
        raise ValueError(f"`t0` must be a finite number (got t0={t0!r})")
    return t0f


class Stepper:
    """Integrates a Hamiltonian system with HBVM(k, s), one step at a time.

    Parameters
    ----------
    method : HBVM
    system : object following the protocol of :mod:`systems.base`
    y0 : array_like, shape (2m,)
    t0 : float
    solver : {"auto", "fixed_point", "newton"}
        ``"fixed_point"``: gamma <- P_s^T Omega f(stages(gamma)).  ``"newton"``: simplified Newton
        with the Gauss matrix I - h X_s (x) J0, J0 refreshed every step.  ``"auto"`` (default):
        fixed point, switching to Newton for the rest of the run when a fixed-point iteration
        fails (a stiff problem or a large step).
    tol : float, optional
        Relative tolerance of the iteration; default None iterates to round-off.
    max_iter : int, optional
        Iteration cap per step (default 60 for fixed point, 30 for Newton).
    form : {"auto", "full", "separable"}
        ``"separable"`` iterates on the momentum coefficients only (needs ``masses``,
        ``forces``, ``potential``); ``"auto"`` uses it when the system offers them.

    Attributes
    ----------
    t, y : current time and state (y is the rounded value; a Kahan compensation is kept).
    nsteps, nfev, niter, newton_steps, solver_switches : counters.
    """

    def __init__(self, method, system, y0, t0: float = 0.0, solver: str = "auto",
                 tol: float | None = None, max_iter: int | None = None, form: str = "auto"):
        t0 = check_options(solver, form, tol, max_iter, t0)
        system, self.y = check_state(system, y0)
        self.method, self.system = method, system
        self.t = t0
        if form == "separable" and not _is_separable(system):
            raise ValueError("`form='separable'` needs a system with `masses`, `forces` and "
                             "`potential`; use form='full'")
        use_sep = form == "separable" or (form == "auto" and _is_separable(system))
        self.form = SeparableForm(method, system) if use_sep else FullForm(method, system)
        self.solver_option = solver
        self._solver = "newton" if solver == "newton" else "fixed_point"
        self.tol, self.max_iter = tol, max_iter
        self._yc = np.zeros_like(self.y)   # Kahan compensation of y
        self._tc = 0.0                     # and of t
        self._gamma = None                 # previous step's coefficients (initial guesses)
        self._h_prev = None
        self.nsteps = self.nfev = self.niter = self.newton_steps = self.solver_switches = 0
        self.status = "running"

    # -- public ------------------------------------------------------------------------
    def step(self, h: float) -> np.ndarray:
        """Advance by one step of size h and return the new state.

        Raises ConvergenceError (with the state, time and counters unchanged) when the
        nonlinear iteration fails, also after the automatic switch to Newton.
        """
        h = check_step(h)
        gamma, it, fev, solver_used = self._solve(h)
        inc = self.form.increment(self.y, gamma, h)
        if not np.all(np.isfinite(inc)):
            raise ConvergenceError(h, float("nan"), it, solver_used, self.t,
                                   hint="the new state is not finite; try a smaller step size h")
        # commit: compensated sums of y and t (Brouwer's law for the round-off)
        yk = inc - self._yc
        ynew = self.y + yk
        self._yc = (ynew - self.y) - yk
        self.y = ynew
        tk = h - self._tc
        tnew = self.t + tk
        self._tc = (tnew - self.t) - tk
        self.t = tnew
        self._gamma, self._h_prev = gamma, h
        self.nsteps += 1
        self.niter += it
        self.nfev += fev
        if solver_used == "newton":
            self.newton_steps += 1
        return self.y

    @property
    def solver(self) -> str:
        """The solver the next step will use."""
        return self._solver

    # -- private -----------------------------------------------------------------------
    def _guess(self, h: float) -> np.ndarray:
        if self._gamma is None:
            return self.form.start(self.y)
        return self.method.extrapolation_matrix(h / self._h_prev) @ self._gamma

    def _solve(self, h: float):
        y0 = self.y
        start_fev = 0 if self._gamma is not None else 1
        g0 = self._guess(h)
        phi = self.form.phi(y0, h)
        n = self.form.stage_count()
        if self._solver == "fixed_point":
            rule = StopRule(self.max_iter or 60, self.tol)
            try:
                g, it = fixed_point(phi, g0, rule, h, self.t)
                return g, it, start_fev + it * n, "fixed_point"
            except ConvergenceError as err:
                if self.solver_option != "auto":
                    raise
                first_failure = err
            self._solver = "newton"
            self.solver_switches += 1
            try:
                return self._newton(phi, g0, y0, h, n, start_fev)
            except ConvergenceError:
                self._solver = "fixed_point"
                self.solver_switches -= 1
                raise first_failure from None
        return self._newton(phi, g0, y0, h, n, start_fev)

    def _newton(self, phi, g0, y0, h, n, start_fev):
        L, power = self.form.linear_part(y0, h)
        lin = SimplifiedNewton(self.method.X, L, h, power)
        rule = StopRule(self.max_iter or 30, self.tol)
        g, it = newton(phi, g0, rule, h, lin, self.t)
        return g, it, start_fev + it * n + (2 * L.shape[0] if not hasattr(self.system, "hessian") else 0), "newton"


@dataclass
class IntegrationResult:
    """Samples and counters of a run.

    Attributes
    ----------
    t : ndarray (n_samples,)
    y : ndarray (n_samples, 2m)
    energy : ndarray (n_samples,)
    steps, nfev, iterations, newton_steps, solver_switches : int
    path : str
        "compiled" (numba fast path), "separable" or "full" (numpy).
    wall_time : float
        Seconds spent in the integration loop.
    """

    t: np.ndarray
    y: np.ndarray
    energy: np.ndarray
    method: object
    h: float
    steps: int
    nfev: int
    iterations: int
    path: str
    wall_time: float
    newton_steps: int = 0
    solver_switches: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def energy_error(self) -> np.ndarray:
        """|H(y_n) - H(y_0)| / |H(y_0)| (absolute when H(y_0) = 0)."""
        e0 = self.energy[0]
        return np.abs(self.energy - e0) / (abs(e0) if e0 != 0 else 1.0)

    @property
    def max_energy_error(self) -> float:
        return float(np.max(self.energy_error))

    @property
    def iterations_per_step(self) -> float:
        return self.iterations / max(self.steps, 1)

    def drift_slope(self) -> float:
        """Slope of a least-squares line through the relative energy error against time."""
        return float(np.polyfit(self.t - self.t[0], self.energy_error, 1)[0]) if len(self.t) > 2 else 0.0


def _fast_kind(system, solver, fast, form="auto") -> str | None:
    """Which compiled loop to run: "separable" (``separable_kernels``), "full" (``full_kernels``,
    any Hamiltonian) or None (the numpy engine)."""
    sep = hasattr(system, "separable_kernels") and _is_separable(system)
    full = hasattr(system, "full_kernels")
    if fast is None:
        if solver not in ("auto", "fixed_point"):
            return None
        if sep and form != "full":
            return "separable"
        # an explicit form='separable' asks for the numpy separable engine
        return "full" if full and form != "separable" else None
    if fast and not (sep or full):
        raise ValueError("`fast=True` needs a system with `separable_kernels()` (compiled force "
                         "and potential) or `full_kernels()` (compiled gradient and energy); use "
                         "fast=False for the numpy path")
    if fast and solver == "newton":
        raise ValueError("the compiled fast path iterates by fixed point; use fast=False with "
                         "solver='newton'")
    if fast and form == "full" and not full:
        raise ValueError("the compiled fast path iterates on the separable form; use fast=False "
                         "with form='full'")
    if not fast:
        return None
    return "separable" if sep and form != "full" else "full"


def integrate(method, system, y0, h: float, steps: int, t0: float = 0.0, solver: str = "auto",
              sample_every: int = 1, fast: bool | None = None, tol: float | None = None,
              max_iter: int | None = None, form: str = "auto") -> IntegrationResult:
    """Integrate ``steps`` steps of size h with HBVM ``method`` from y0.

    Parameters
    ----------
    sample_every : int
        Keep t, y and H every this many steps (and at step 0).
    fast : bool or None
        Use a compiled loop: the separable form for systems with ``separable_kernels``, the full
        form for systems with ``full_kernels`` (see :mod:`systems.base`).  None: when available
        and the solver is not "newton".  With solver="auto" a compiled loop falls back to the
        numpy engine (and its Newton switch) from a step where fixed point fails.
    Other parameters as for :class:`Stepper`.
    """
    h = check_step(h)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise ValueError(f"`steps` must be an integer >= 0 (got steps={steps!r})")
    if isinstance(sample_every, bool) or not isinstance(sample_every, (int, np.integer)) or sample_every < 1:
        raise ValueError(f"`sample_every` must be an integer >= 1 (got sample_every={sample_every!r})")
    t0 = check_options(solver, form, tol, max_iter, t0)
    system, y0 = check_state(system, y0)
    kind = _fast_kind(system, solver, fast, form)
    if kind == "separable":
        return _integrate_fast(method, system, y0, h, int(steps), t0, solver, int(sample_every), tol, max_iter)
    if kind == "full":
        return _integrate_full(method, system, y0, h, int(steps), t0, solver, int(sample_every), tol, max_iter)
    st = Stepper(method, system, y0, t0, solver, tol, max_iter, form)
    return _run_stepper(st, h, int(steps), int(sample_every))


def _run_stepper(st: Stepper, h, steps, sample_every, offset=0, ts=None, ys=None, wall0=0.0):
    """Run ``steps`` steps, sampling when the global step count (offset + i) is a multiple."""
    ts = [st.t] if ts is None else ts
    ys = [st.y.copy()] if ys is None else ys
    t_start = time.perf_counter()
    for i in range(steps):
        st.step(h)
        if (offset + i + 1) % sample_every == 0:
            ts.append(st.t)
            ys.append(st.y.copy())
    wall = wall0 + time.perf_counter() - t_start
    Y = np.array(ys)
    energy = np.asarray(st.system.energy(Y), dtype=float)
    return IntegrationResult(np.array(ts), Y, energy, st.method, h, st.nsteps, st.nfev, st.niter,
                             st.form.name, wall, st.newton_steps, st.solver_switches)


def _integrate_fast(method, system, y0, h, steps, t0, solver, sample_every, tol, max_iter):
    """The compiled separable form (``system.separable_kernels()``)."""
    from .fast import coefficients, integrate_separable
    force, potential, params = system.separable_kernels()
    d = system.dim
    q, p = y0[:d].copy(), y0[d:].copy()
    cq, cp = np.zeros(d), np.zeros(d)
    minv = 1.0 / np.asarray(system.masses, dtype=float)
    nsamp = steps // sample_every + 1
    out_t, out_q, out_p, out_e = np.empty(nsamp), np.empty((nsamp, d)), np.empty((nsamp, d)), np.empty(nsamp)
    counters = np.zeros(5)
    gamma = np.zeros((method.s, d))
    t_start = time.perf_counter()
    integrate_separable(force, potential, np.ascontiguousarray(params, dtype=float), q, p, cq, cp,
                        minv, h, steps, sample_every, float(t0), *coefficients(method),
                        int(max_iter or 60), 2.0 ** -40, float(tol or 0.0), out_t, out_q, out_p,
                        out_e, counters, gamma)
    wall = time.perf_counter() - t_start
    return _finish_compiled(method, system, h, steps, t0, solver, sample_every, tol, max_iter,
                            "separable", counters, np.concatenate([q, p]), np.concatenate([cq, cp]),
                            gamma, out_t, np.concatenate([out_q, out_p], axis=1), out_e, wall)


def _integrate_full(method, system, y0, h, steps, t0, solver, sample_every, tol, max_iter):
    """The compiled full form (``system.full_kernels()``)."""
    from .fast import integrate_full
    gradient, energy, params = system.full_kernels()
    d = y0.size
    y, cy = y0.copy(), np.zeros(d)
    nsamp = steps // sample_every + 1
    out_t, out_y, out_e = np.empty(nsamp), np.empty((nsamp, d)), np.empty(nsamp)
    counters = np.zeros(5)
    gamma = np.zeros((method.s, d))
    m = method
    c = np.ascontiguousarray
    t_start = time.perf_counter()
    integrate_full(gradient, energy, c(params, dtype=float), y, cy, h, steps, sample_every,
                   float(t0), c(m.W), c(m.W_lo), c(m.I), c(m.I_lo), c(m.E), int(max_iter or 60),
                   2.0 ** -40, float(tol or 0.0), out_t, out_y, out_e, counters, gamma)
    wall = time.perf_counter() - t_start
    return _finish_compiled(method, system, h, steps, t0, solver, sample_every, tol, max_iter,
                            "full", counters, y, cy, gamma, out_t, out_y, out_e, wall)


def _finish_compiled(method, system, h, steps, t0, solver, sample_every, tol, max_iter, form,
                     counters, y, yc, gamma, out_t, out_y, out_e, wall) -> IntegrationResult:
    """The result of a compiled loop; on a failed step with solver="auto" the numpy engine (with
    its switch to Newton) goes on from the last good step, keeping its coefficients and the
    compensation of the state."""
    from .fast import OK
    done, iters, nfev, status = (int(counters[0]), int(counters[1]), int(counters[2]),
                                 int(counters[3]))
    path = "compiled" if form == "separable" else "compiled-full"
    if status == OK:
        return IntegrationResult(out_t, out_y, out_e, method, h, done, nfev, iters, path, wall)
    t_fail = t0 + done * h
    if solver != "auto":
        raise ConvergenceError(h, float(counters[4]), int(max_iter or 60), "fixed_point", t_fail)
    st = Stepper(method, system, y, t_fail, solver, tol, max_iter, form)
    st._yc = yc.copy()
    st.nsteps, st.niter, st.nfev = done, iters, nfev
    if done > 0:   # the compiled loop keeps the last good step's coefficients in gamma
        st._gamma, st._h_prev = gamma.copy(), h
    k = done // sample_every + 1
    res = _run_stepper(st, h, steps - done, sample_every, done, list(out_t[:k]), list(out_y[:k]), wall)
    res.path = f"compiled+{form}"
    return res
