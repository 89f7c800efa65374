"""The stepping engine: :class:`Stepper` owns time, state, counters and status; :func:`integrate`
runs many steps.  Both call the one step of :mod:`integrators.loop` (compiled for systems with
compiled kernels, executed as Python otherwise: the same code either way).

Like scipy's ``OdeSolver``: the public ``step`` owns time, counters and status; the step itself
(:func:`integrators.loop.advance`) changes nothing on failure.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .core import (C_ITER, C_NEWTON, C_NFEV, C_STATUS, C_STEPS, DIVERGED, N_COUNTERS, NOT_FINITE,
                   OK, work_sizes)
from .core import next_step, select_extrapolation
from .core import step_error as error_estimate
from .jit import entry_point
from .errors import StepError, StepSizeError, step_error
from .protocol import adapt_system
from .tableau import gauss_rule01
from .specialise import specialise

SOLVERS = ("auto", "fixed_point", "newton")
FORMS = ("auto", "full", "separable")
MAX_ITER = {"fixed_point": 60, "newton": 30}


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


def check_count(name: str, value, minimum: int) -> int:
    """``value`` as an int, or ValueError naming ``name`` when it is not an integer >= minimum
    (a bool, a float such as 10.0, or a smaller number)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"`{name}` must be an integer >= {minimum} (got {name}={value!r})")
    return int(value)


def check_step(h) -> float:
    try:
        hf = float(h)
    except (TypeError, ValueError):
        raise ValueError(f"`h` must be a nonzero finite number (got h={h!r})") from None
    if isinstance(h, bool) or not np.isfinite(hf) or hf == 0.0:
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


_COEF_CACHE: dict = {}


def method_arrays(method) -> tuple:
    """(c1, c2) = ((tn, ts), (Wp, Cp)): the method's arrays packed as the step takes them,
    tn = [tau, tau_lo], ts = [X0, X0_lo], Wp = [W, W_lo], Cp = [C2, C2_lo, I, I_lo] (contiguous,
    read-only, so that every path compiles one signature; see :mod:`integrators.loop`)."""
    hit = _COEF_CACHE.get(method)
    if hit is None:
        def c(a):
            a = np.array(a, dtype=float, order="C")
            a.flags.writeable = False
            return a
        m = method
        hit = ((c([m.tau, m.tau_lo]), c([m.X[0], m.X_lo[0]])),
               (c([m.W, m.W_lo]), c([m.C2, m.C2_lo, m.I, m.I_lo])))
        _COEF_CACHE[method] = hit
    return hit


class Counted:
    """Read-only views of a caller's step counters (``self.counters``, the layout of
    :mod:`integrators.core`): they count the work of committed steps."""

    counters: np.ndarray

    @property
    def niter(self) -> int:
        """Iterations of the committed steps."""
        return int(self.counters[C_ITER])

    @property
    def nfev(self) -> int:
        """Right-hand-side evaluations (one stage configuration each) of the committed steps."""
        return int(self.counters[C_NFEV])

    @property
    def newton_steps(self) -> int:
        return int(self.counters[C_NEWTON])


class Extrapolation:
    """The initial guess's matrix E(h_new / h_old) (:meth:`HBVM.extrapolation_matrix`) for
    every caller of the step: the arrays the compiled ``core.select_extrapolation`` chooses
    from or fills (E(1) kept, any other ratio computed into a reused buffer, zero for a step
    far longer than the last; the rule is written there once, also for the REBOUND step)."""

    def __init__(self, method):
        self.E1 = np.array(method.E, dtype=float, order="C")   # writable: one array type
        t, w = gauss_rule01(method.s)
        self.t, self.w = t.copy(), w.copy()                      # writable, like E1
        self.buf = np.empty_like(self.E1)
        self.zero = np.zeros_like(self.E1)

    def __call__(self, h: float, h_prev: float | None) -> np.ndarray:
        return entry_point(select_extrapolation)(h, np.nan if h_prev is None else h_prev,
                                                 self.E1, self.t, self.w, self.buf, self.zero)


class Binding:
    """A system bound to the step: the form, the kernels (compiled or Python), their parameters
    and the arrays the step works in.  Built once per Stepper (and per REBOUND resync).

    Parameters
    ----------
    method : HBVM
    system : a system following :mod:`systems.base`
    form : {"auto", "full", "separable"}
    fast : bool or None
        True: the system's compiled kernels (``separable_kernels()`` or ``full_kernels()``) are
        required and the step is compiled; False: the step runs as Python code (calling the
        compiled kernels when the system has them, else its numpy methods); None: compiled when
        the system has kernels.
    glue : str, optional
        A host's glue module compiled with the step (:func:`integrators.specialise.specialise`).
    """

    def __init__(self, method, system, form: str = "auto", fast: bool | None = None,
                 glue: str | None = None):
        if form == "separable" and not _is_separable(system):
            raise ValueError("`form='separable'` needs a system with `masses`, `forces` and "
                             "`potential`; use form='full'")
        self.full = not (form == "separable" or (form == "auto" and _is_separable(system)))
        self.method, self.system = method, system
        d = 2 * int(system.dim)
        m = d // 2
        kernels_attr = "full_kernels" if self.full else "separable_kernels"
        has_kernels = hasattr(system, kernels_attr)
        if fast and not has_kernels:
            raise ValueError(f"`fast=True` needs a system with `{kernels_attr}()` (compiled "
                             f"kernels for the {'full' if self.full else 'separable'} form); "
                             f"{type(system).__name__} has none: use fast=None or fast=False")
        if has_kernels:
            force, potential, params = getattr(system, kernels_attr)()
        else:
            force, potential, params = self._python_kernels(system)
        self.params = np.ascontiguousarray(params, dtype=float)
        # fast=False runs the step as Python code: with the system's compiled kernels when it
        # has them (then the numbers and counters equal the compiled run's bit for bit)
        self.step_code = specialise(force, potential, python=fast is False, glue=glue)
        self.force = force
        self.kind = self.step_code.kind
        self.name = f"{self.kind}-{'full' if self.full else 'separable'}"
        if self.full:
            self.minv = np.zeros(0)
            self.kin_w = np.zeros(0)
        else:
            masses = np.asarray(system.masses, dtype=float)
            if masses.shape != (m,):
                raise ValueError(f"`masses` of the system must have shape ({m},) "
                                 f"(got {masses.shape})")
            self.minv = 1.0 / masses
            self.kin_w = np.ascontiguousarray(getattr(system, "kinetic_weights", self.minv),
                                              dtype=float)
        self.c1, self.c2 = method_arrays(method)
        u = d if self.full else m
        s = method.s
        self.u = u
        self.no_newton = (np.zeros((s, s), dtype=complex), np.zeros((s, s), dtype=complex),
                          np.zeros((0, u, u), dtype=complex))
        nf, nc = work_sizes(method.n_stages, s, u, self.minv.shape[0], d)
        self.work, self.cwork = np.empty(nf), np.empty(nc, dtype=complex)
        self._eig = None

    def _python_kernels(self, system):
        """Kernels that call the system's own (numpy) methods: the Python path."""
        if self.full:
            def force(Y, params, out):
                out[...] = system.gradient(Y)

            def potential(y, params):
                return float(system.energy(y))
        else:
            if callable(getattr(system, "forces_into", None)):
                def force(Q, params, out):        # writes out itself (no copy of the result)
                    system.forces_into(Q, out)
            else:
                def force(Q, params, out):
                    out[...] = system.forces(Q)

            def potential(q, params):
                return float(system.potential(q))
        return force, potential, np.zeros(1)

    def energy(self, y: np.ndarray) -> float:
        t, v = self.step_code.energy_parts(self.full, y, self.kin_w, self.params)
        return float(t + v)

    def rhs(self, X: np.ndarray) -> np.ndarray:
        """The kernel's output (forces, or grad H for the full form) at a stack of rows X."""
        out = np.empty_like(X)
        self.force(np.ascontiguousarray(X), self.params, out)
        return out

    def newton_matrices(self, y: np.ndarray, h: float, counters: np.ndarray) -> tuple:
        """(NV, NVinv, NM): the simplified-Newton matrices of the Gauss method, I - h X_s (x) J0
        (full form) or I - h^2 X_s^2 (x) dF/dq M^{-1} (separable), split through X_s's
        eigenvalues (by the isospectral property they are Gauss's whatever k is).  J0 comes
        from the system's ``hessian`` or from central differences of the kernel (2u
        evaluations, counted)."""
        system, u, d = self.system, self.u, int(self.system.dim)
        if hasattr(system, "hessian"):
            Hs = np.asarray(system.hessian(y), dtype=float)
            if Hs.shape != (2 * d, 2 * d):
                raise ValueError(f"`hessian(y)` of {type(system).__name__} must return shape "
                                 f"({2 * d}, {2 * d}) (got {Hs.shape})")
            L = np.concatenate([Hs[d:], -Hs[:d]]) if self.full else -Hs[:d, :d] * self.minv[None, :]
        else:
            x = y if self.full else y[:d]
            e = 2.0 ** -26 * np.maximum(1.0, np.abs(x))
            vals = self.rhs(np.concatenate([x + np.diag(e), x - np.diag(e)]))
            counters[C_NFEV] += 2 * u
            jac = ((vals[:u] - vals[u:]) / (2 * e[:, None])).T
            L = np.concatenate([jac[d:], -jac[:d]]) if self.full else jac * self.minv[None, :]
        if self._eig is None:
            lam, V = np.linalg.eig(self.method.X)
            self._eig = (lam, np.ascontiguousarray(V, dtype=complex),
                         np.ascontiguousarray(np.linalg.inv(V), dtype=complex))
        lam, V, Vinv = self._eig
        mu = (h * lam) ** (1 if self.full else 2)
        eye = np.eye(u)
        NM = np.empty((lam.size, u, u), dtype=complex)
        for i, m_i in enumerate(mu):
            j = next((j for j in range(i) if abs(mu[j] - np.conj(m_i)) <= 1e-14 * (1 + abs(m_i))), None)
            NM[i] = np.conj(NM[j]) if j is not None else np.linalg.inv(eye - m_i * L)
        return V, Vinv, NM


class Stepper(Counted):
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
    fast : bool or None
        Compiled kernels: required (True), never (False), when the system has them (None).
    energy_tol : float, optional
        Refuse a converged step whose energy change exceeds this, relative to |T| + |V|
        (:class:`integrators.UnresolvedStepError`); None: no check.

    Attributes
    ----------
    t, y : current time and state (copies; the state is kept as a double-double number).
    nsteps, nfev, niter, newton_steps, solver_switches : counters.
    status : "running", or "failed" after a step raised.
    """

    def __init__(self, method, system, y0, t0: float = 0.0, solver: str = "auto",
                 tol: float | None = None, max_iter: int | None = None, form: str = "auto",
                 fast: bool | None = None, energy_tol: float | None = None):
        t0 = check_options(solver, form, tol, max_iter, t0)
        if energy_tol is not None and not (np.isfinite(energy_tol) and energy_tol > 0):
            raise ValueError(f"`energy_tol` must be a positive number or None (got "
                             f"energy_tol={energy_tol!r})")
        system, self._y = check_state(system, y0)
        self.method, self.system = method, system
        self.binding = Binding(method, system, form, fast)
        self.form = self.binding
        self._cy = np.zeros_like(self._y)
        self._clock = np.array([t0, 0.0])
        self._gamma = np.zeros((method.s, self.binding.u))
        self._h_prev = None
        self._extrapolation = Extrapolation(method)
        self._eref = np.full(1, np.nan)
        self.counters = np.zeros(N_COUNTERS)
        self.solver_option = solver
        self._solver = "newton" if solver == "newton" else "fixed_point"
        self.tol, self.max_iter, self.energy_tol = tol, max_iter, energy_tol
        self.solver_switches = 0
        self.rejected = 0
        self.status = "running"

    # -- public ------------------------------------------------------------------------
    @property
    def y(self) -> np.ndarray:
        return self._y.copy()

    @property
    def t(self) -> float:
        return float(self._clock[0])

    @property
    def nsteps(self) -> int:
        return int(self.counters[C_STEPS])

    @property
    def solver(self) -> str:
        """The solver the next step will use."""
        return self._solver

    def step(self, h: float) -> np.ndarray:
        """Advance by one step of size h and return (a copy of) the new state.

        Raises a :class:`integrators.StepError` (ConvergenceError, NonFiniteError,
        UnresolvedStepError) with the state, time and coefficients unchanged when the step
        fails, also after the automatic switch to Newton."""
        h = check_step(h)
        status = self._advance(h, self._solver)
        if status in (DIVERGED, NOT_FINITE) and self.solver_option == "auto" and self._solver == "fixed_point":
            status = self._advance(h, "newton")
            if status == OK:
                self._solver = "newton"
                self.solver_switches += 1
            else:
                self._fail(status, h, "auto")
        elif status != OK:
            self._fail(status, h, self.solver_option)
        self._after_step(h)
        return self._y.copy()

    def run(self, h: float, steps: int, sample_every: int = 1) -> "IntegrationResult":
        """``steps`` steps of size h with samples every ``sample_every`` steps (and at step 0).

        Fixed-point steps run in one call of the step loop (compiled when the kernels are);
        on failure with solver="auto" the run goes on with Newton.  A failure raises with the
        samples so far in the exception's ``result``."""
        h = check_step(h)
        steps = check_count("steps", steps, 0)
        sample_every = check_count("sample_every", sample_every, 1)
        b = self.binding
        nsamp = steps // sample_every + 1
        out_t, out_y, out_e = np.empty(nsamp), np.empty((nsamp, self._y.size)), np.empty(nsamp)
        start = self.nsteps
        t_start = time.perf_counter()
        if self._solver == "fixed_point":
            E = self._extrapolation(h, self._h_prev)
            b.step_code.run(b.full, self._y, self._cy, b.minv, b.kin_w,
                            b.params, h, E, self._gamma, b.c1, b.c2, *b.no_newton,
                            self._max_iter("fixed_point"), float(self.tol or 0.0),
                            float(self.energy_tol or 0.0), self._eref,
                            self.counters, b.work, b.cwork, steps, sample_every, self._clock, out_t, out_y, out_e)
            done = self.nsteps - start
            if done > 0:
                self._h_prev = h
            k = done // sample_every + 1
            status = int(self.counters[C_STATUS])
            if done < steps and status == OK:     # the step loop's contract, checked
                raise RuntimeError(f"internal error: the step loop stopped after {done} of "
                                   f"{steps} steps without a failure status")
            if done < steps and status != OK:
                if self.solver_option == "auto" and status in (DIVERGED, NOT_FINITE):
                    self._solver = "newton"          # for the rest of the run, as step() does
                    self.solver_switches += 1
                else:
                    try:
                        self._fail(status, h, self.solver_option)
                    except StepError as err:
                        err.result = self._result(out_t[:k], out_y[:k], out_e[:k], h, t_start,
                                                  "failed", str(err))
                        raise
        else:
            out_t[0], out_y[0], out_e[0] = self.t, self._y, b.energy(self._y)
            done, k = 0, 1
        try:
            for i in range(done, steps):
                self.step(h)
                if (i + 1) % sample_every == 0:
                    out_t[k], out_y[k], out_e[k] = self.t, self._y, b.energy(self._y)
                    k += 1
        except StepError as err:
            err.result = self._result(out_t[:k], out_y[:k], out_e[:k], h, t_start,
                                      "failed", str(err))
            raise
        return self._result(out_t, out_y, out_e, h, t_start, "finished", "")

    def step_adaptive(self, h: float, epsilon: float, min_dt: float) -> tuple[float, float]:
        """One adaptive step: try h, and on rejection (the error estimate from the step's own
        coefficients above ``epsilon``, a failed iteration or energy check) retry smaller.
        Returns (the step taken, the next step proposed).  A rejected attempt leaves no trace
        in the state, the time or the counters.  Raises :class:`integrators.StepSizeError`
        when no step down to ``min_dt`` is accepted."""
        s = self.method.s
        while True:
            snap = (self._y.copy(), self._cy.copy(), self._gamma.copy(), self._eref.copy(),
                    self._clock.copy(), self.counters.copy(), self._h_prev, self._solver,
                    self.solver_switches)
            try:
                self.step(h)
            except StepError as err:
                cause = f"{type(err).__name__}: {err}"
                h_new = 0.25 * h
            else:
                err_est = error_estimate(self._gamma, self.binding.minv)
                if err_est <= epsilon:
                    return h, next_step(h, err_est, epsilon, s)
                (self._y[:], self._cy[:], self._gamma[:], self._eref[:], self._clock[:],
                 self.counters[:]) = snap[:6]
                self._h_prev, self._solver, self.solver_switches = snap[6:]
                cause = f"error estimate {err_est:.3e} > epsilon={epsilon:.3e}"
                h_new = next_step(h, err_est, epsilon, s)
            self.rejected += 1
            self.status = "running"
            if abs(h_new) < min_dt:
                self.status = "failed"
                raise StepSizeError(h, min_dt, self.t, cause)
            h = h_new

    def run_adaptive(self, h: float, t_end: float, epsilon: float, min_dt: float,
                     sample_every: int = 1, sample_times=None) -> "IntegrationResult":
        """Adaptive steps from t to t_end, h the first step tried: samples every
        ``sample_every`` accepted steps, and at each of ``sample_times`` (the steps are
        shortened to land on them exactly, and on t_end)."""
        sample_every = check_count("sample_every", sample_every, 1)
        t_start = time.perf_counter()
        marks = sorted(float(x) for x in (sample_times if sample_times is not None else ()))
        marks = [x for x in marks if (x - self.t) * (t_end - self.t) > 0 and abs(x) <= abs(t_end)]
        marks.append(float(t_end))
        ts, ys, es = [self.t], [self._y.copy()], [self.binding.energy(self._y)]
        hs = []
        n = 0
        sign = 1.0 if t_end >= self.t else -1.0
        h = abs(h) * sign
        try:
            for mark in marks:
                while (mark - self.t) * sign > 0:
                    remaining = (mark - self._clock[0]) + self._clock[1]
                    last = abs(h) >= abs(remaining)
                    done, h_next = self.step_adaptive(remaining if last else h, epsilon, min_dt)
                    hs.append(done)
                    if last and done == remaining:
                        self._clock[:] = mark, 0.0          # exactly on the requested time
                    else:                                   # (else keep h for what follows)
                        h = h_next
                    n += 1
                    if n % sample_every == 0 or self.t == mark:
                        ts.append(self.t)
                        ys.append(self._y.copy())
                        es.append(self.binding.energy(self._y))
        except StepError as err:
            err.result = self._result(ts, ys, es, h, t_start, "failed", str(err))
            raise
        res = self._result(ts, ys, es, h, t_start, "finished", "")
        res.extra.update(adaptive=True, epsilon=epsilon, rejected=self.rejected,
                         h_min=float(np.min(np.abs(hs))) if hs else float("nan"),
                         h_max=float(np.max(np.abs(hs))) if hs else float("nan"))
        return res

    # -- private -----------------------------------------------------------------------
    def _max_iter(self, solver: str) -> int:
        return int(self.max_iter or MAX_ITER[solver])

    def _advance(self, h: float, solver: str) -> int:
        b = self.binding
        newton = (b.newton_matrices(self._y, h, self.counters) if solver == "newton"
                  else b.no_newton)
        return b.step_code.advance(b.full, self._y, self._cy, b.minv,
                                   b.kin_w, b.params, h, self._extrapolation(h, self._h_prev), self._gamma, b.c1, b.c2,
                                   *newton, self._max_iter(solver), float(self.tol or 0.0),
                                   float(self.energy_tol or 0.0), self._eref,
                                   self.counters, b.work, b.cwork, self._clock)

    def _after_step(self, h: float) -> None:
        self._h_prev = h          # the step itself advanced the compensated clock

    def _fail(self, status: int, h: float, solver: str) -> None:
        self.counters[C_STATUS] = status
        self.status = "failed"
        raise step_error(status, h, self.t, self.counters, solver, energy_tol=self.energy_tol)

    def _result(self, t, y, e, h, t_start, status, message) -> "IntegrationResult":
        self.status = "running" if status == "finished" else status
        return IntegrationResult(np.array(t), np.array(y), np.array(e), self.method, h,
                                 self.nsteps, self.nfev, self.niter, self.binding.name,
                                 time.perf_counter() - t_start, self.newton_steps,
                                 self.solver_switches, status=status, message=message)


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
        "compiled-separable", "compiled-full", "python-separable" or "python-full": which
        binding of the one step ran (:mod:`integrators.specialise`).
    wall_time : float
        Seconds spent in the integration loop.
    status, message : str
        "finished", or "failed" with the error's message (a failed :func:`integrate` raises
        and carries this result in the exception's ``result``).
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
    status: str = "finished"
    message: str = ""
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


#: adaptive steps: the bound on the relative size of the force polynomial's highest term over a
#: step (core.step_error); measured (benchmarks/bench_defaults.py): IAS15's energy and position
#: accuracy on the outer solar system in about 0.6 of its time
DEFAULT_EPSILON = 1e-3


def check_adaptive(epsilon, min_dt, s: int) -> tuple[float, float]:
    """(epsilon, min_dt) checked for an adaptive run of a method with s blocks."""
    if isinstance(epsilon, bool) or not isinstance(epsilon, (int, float, np.number)) \
            or not (np.isfinite(epsilon) and 0 < epsilon < 1):
        raise ValueError(f"`epsilon` must be a number in (0, 1) (got epsilon={epsilon!r}); "
                         f"it bounds the relative size of the force polynomial's highest term "
                         f"over a step, like IAS15's; the default is {DEFAULT_EPSILON:g}")
    if min_dt is None:
        min_dt = 0.0
    if isinstance(min_dt, bool) or not isinstance(min_dt, (int, float, np.number)) \
            or not (np.isfinite(min_dt) and min_dt >= 0):
        raise ValueError(f"`min_dt` must be a finite number >= 0 (got min_dt={min_dt!r})")
    if s < 2:
        raise ValueError(f"adaptive steps need s >= 2 (got s={s}): the error estimate is the "
                         "weight of gamma_(s-1) against gamma_0")
    return float(epsilon), float(min_dt)


def integrate(method, system, y0, h: float, steps: int | None = None, t0: float = 0.0,
              solver: str = "auto", sample_every: int = 1, fast: bool | None = None,
              tol: float | None = None, max_iter: int | None = None, form: str = "auto",
              energy_tol: float | None = None, *, adaptive: bool = False,
              t_end: float | None = None, epsilon: float = DEFAULT_EPSILON,
              min_dt: float | None = None, sample_times=None) -> IntegrationResult:
    """Integrate ``steps`` steps of size h with HBVM ``method`` from y0, or with
    ``adaptive=True`` from t0 to ``t_end`` with h the first step.

    Parameters
    ----------
    sample_every : int
        Keep t, y and H every this many (accepted) steps, and at the start.
    fast : bool or None
        Compiled kernels required (True), never (False), or when the system has them (None).
    adaptive : bool
        Step-size control from each step's own coefficients (:meth:`Stepper.step_adaptive`); a
        step that fails its iteration or energy check is retried smaller, down to ``min_dt``
        (default 0).
    epsilon : float
        The precision of adaptive steps, in (0, 1), with the meaning of IAS15's ``epsilon``: a
        bound on the relative size of the highest term of the force polynomial over a step,
        |a^(s-1)| h^(s-1) / (s-1)! against |a| (max over the coordinates, accelerations for
        the separable form: :func:`integrators.core.step_error`), from the step's own Legendre
        coefficients (no extra evaluation).  A step is accepted when its estimate is at most
        epsilon; the next one is proposed at 0.7 of the step that would reach epsilon
        (:func:`integrators.core.next_step`), so smooth motion runs near 0.7^(s-1) epsilon,
        epsilon / 6 for s = 6.  IAS15 bounds the same quantity for its degree-7
        polynomial; here the degree is s - 1, so the same step gives a larger number (the
        circular orbit at omega h = 0.2: 2.7e-6 for s = 6, 2.5e-9 for IAS15's degree 7).
        The step's own error is O(h^(2s+1)), so the solution's accuracy (positions, phases),
        not only the energy, follows epsilon: the position error over a fixed time goes like
        epsilon^(2s / (s - 1)) (measured 2.7 for s = 6, predicted 2.4).  The energy stays at
        round-off whatever the steps (HBVM conserves H at any step size once k is large
        enough: :func:`integrators.kchoice.adaptive_k`).  The
        default, 1e-3 for s = 6, gives IAS15's energy and position error on the outer solar
        system in about 0.6 of its time (``benchmarks/bench_defaults.py``).
    t_end, sample_times
        Adaptive runs end exactly at t_end and also land exactly on each of sample_times.
    Other parameters as for :class:`Stepper`.

    Raises
    ------
    StepError
        A step failed; ``err.result`` holds the samples up to the last committed step.
    """
    h = check_step(h)
    if adaptive:
        if steps is not None:
            raise ValueError("give `t_end` (not `steps`) with adaptive=True: the number of "
                             "steps is what the control chooses")
        if t_end is None or not np.isfinite(float(t_end)) or float(t_end) == float(t0):
            raise ValueError(f"`t_end` must be a finite time other than t0 with adaptive=True "
                             f"(got t_end={t_end!r})")
        epsilon, min_dt = check_adaptive(epsilon, min_dt, method.s)
        sample_every = check_count("sample_every", sample_every, 1)
        st = Stepper(method, system, y0, t0, solver, tol, max_iter, form, fast, energy_tol)
        return st.run_adaptive(h, float(t_end), epsilon, min_dt, sample_every, sample_times)
    if steps is None:
        raise ValueError("`steps` is required without adaptive=True")
    steps = check_count("steps", steps, 0)
    sample_every = check_count("sample_every", sample_every, 1)
    st = Stepper(method, system, y0, t0, solver, tol, max_iter, form, fast, energy_tol)
    return st.run(h, steps, sample_every)
