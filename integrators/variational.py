"""Tangent vectors of a run and the MEGNO chaos indicator: :class:`VariationalStepper` and
``integrate(..., variational=V0)``.

The tangent vectors advance by the Jacobian of HBVM's own discrete step (the linearised stage
equations solved at the step's converged stages, :mod:`integrators.tangent`), so they are the
derivative of the computed map y_n = Phi_h^n(y_0), not of the exact flow: a central difference
of two runs converges to them as the increment goes to zero.

What a system provides (the derivative of its force kernel along a direction, row by row):

``separable_jvp()``
    Separable form: a compiled (numba) ``jvp(Q, dQ, params, out)`` writing (dF/dq)(Q_i) dQ_i
    for each row of Q (n, m) into out (n, m), F = -grad V, with the params of
    ``separable_kernels()`` (:class:`systems.Kepler`, :class:`systems.NBody`).
``full_jvp()``
    Full form: a compiled ``jvp(Y, dY, params, out)`` writing Hess H(Y_i) dY_i, params of
    ``full_kernels()``.
``force_jvp(Q, dQ)`` / ``gradient_jvp(Y, dY)``
    The same as Python methods returning the (n, m) / (n, 2m) array.
``hessian(y)``
    The Hessian of H at one state (:mod:`systems.base`): used row by row when nothing above is
    given.

A system with none of them is refused (TypeError naming what to add).  Compiled jvp and
compiled kernels give a compiled tangent map; anything else runs the same code as Python.

MEGNO (Cincotta and Simo, *Simple tools to study global dynamics in non-axisymmetric galactic
potentials - I*, A&AS 147, 2000): with delta the first tangent vector,

    Y(t) = (2 / t) int_0^t (delta'(t') . delta(t') / |delta(t')|^2) t' dt',
    <Y>(t) = (1 / t) int_0^t Y(t') dt',

t measured from the start; |delta| is the norm of (dq, dv) = (dq, M^-1 dp), the positions and
velocities REBOUND's variational particles hold (the full form: (dq, dp)).  <Y> tends to 2 on a
regular (quasi-periodic) orbit, where |delta| grows linearly, and grows like lambda t / 2 on a
chaotic one with Lyapunov exponent lambda.  The integral is accumulated from the tangent at the
step ends (:func:`integrators.tangent.megno_step`: the integrand is t' d ln|delta|, whose
increments the discrete tangent gives exactly).
"""
from __future__ import annotations

import time
from functools import partial

import numpy as np

from . import tangent
from .tangent import TANGENT_FAILED
from .core import DIVERGED, NOT_FINITE, OK
from . import engine as _engine
from .engine import MAX_ITER, Stepper, _attach, check_count, check_step
from .errors import ConvergenceError, NonFiniteError, StepError
from .jit import jit
from .records import Samples, Tangents, Variational
from .specialise import specialise
from .tableau import HBVM

MEGNO_STATE = 7          # length of the accumulator array (integrators.tangent.megno_step)
#: the iteration cap of the tangent map, whatever the step's ``max_iter``: the linear iteration
#: contracts as the step's did, but starts further (from the previous step's d gamma, or zero)
TANGENT_MAX_ITER = {solver: 2 * n for solver, n in MAX_ITER.items()}

_megno_step = jit(tangent.megno_step)


def check_tangents(V0, d: int, name: str = "variational") -> np.ndarray:
    """V0 as a float array (nv, d) (one vector of shape (d,) is taken as nv = 1), checked:
    finite, the first vector nonzero (MEGNO divides by its norm)."""
    try:
        V = np.array(V0, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be an array of tangent vectors of shape (d,) or "
                         f"(nv, d) with d = {d} (got {V0!r})") from None
    if V.ndim == 1:
        V = V[None, :]
    if V.ndim != 2 or V.shape[1] != d or V.shape[0] < 1:
        raise ValueError(f"`{name}` must have shape ({d},) or (nv, {d}) with nv >= 1, one "
                         f"tangent (dq, dp) per row like the state (got shape {np.shape(V0)})")
    if not np.all(np.isfinite(V)):
        raise ValueError(f"`{name}` must be finite (got non-finite entries)")
    if not np.any(V[0] != 0.0):
        raise ValueError(f"`{name}`: the first tangent vector is zero; it must be nonzero (its "
                         "growth is what MEGNO and the Lyapunov indicator measure), e.g. a "
                         "random unit vector")
    return np.ascontiguousarray(V)


def jvp_for(binding, system):
    """The kernel ``jvp(X, dX, params, out)`` for the binding's form (module docstring):
    the system's compiled one, else a Python one built from its methods.  TypeError when the
    system gives no derivative of its force."""
    full = binding.full
    name = type(system).__name__
    m = int(system.dim)
    if not full:
        if callable(getattr(system, "separable_jvp", None)) and hasattr(system, "separable_kernels"):
            return system.separable_jvp()
        if callable(getattr(system, "force_jvp", None)):
            def jvp(Q, dQ, params, out):
                out[...] = system.force_jvp(Q, dQ)
            return jvp
        if callable(getattr(system, "hessian", None)):
            def jvp(Q, dQ, params, out):
                y = np.zeros(2 * m)
                for i in range(Q.shape[0]):
                    y[:m] = Q[i]
                    out[i] = -(np.asarray(system.hessian(y))[:m, :m] @ dQ[i])
            return jvp
    else:
        if callable(getattr(system, "full_jvp", None)) and hasattr(system, "full_kernels"):
            return system.full_jvp()
        if callable(getattr(system, "gradient_jvp", None)):
            def jvp(Y, dY, params, out):
                out[...] = system.gradient_jvp(Y, dY)
            return jvp
        sep = None
        if hasattr(system, "masses"):
            if callable(getattr(system, "separable_jvp", None)) and hasattr(system, "separable_kernels"):
                kern, sparams = system.separable_jvp(), system.separable_kernels()[2]
                sep = lambda Q, dQ, out: kern(Q, dQ, sparams, out)      # noqa: E731
            elif callable(getattr(system, "force_jvp", None)):
                def sep(Q, dQ, out):
                    out[...] = system.force_jvp(Q, dQ)
        if sep is not None:          # H = T(p) + V(q): Hess H dY = (-dF/dq dq, M^-1 dp)
            minv = 1.0 / np.asarray(system.masses, dtype=float)

            def jvp(Y, dY, params, out):
                K = np.empty((Y.shape[0], m))
                sep(np.ascontiguousarray(Y[:, :m]), np.ascontiguousarray(dY[:, :m]), K)
                out[:, :m] = -K
                out[:, m:] = dY[:, m:] * minv
            return jvp
        if callable(getattr(system, "hessian", None)):
            def jvp(Y, dY, params, out):
                for i in range(Y.shape[0]):
                    out[i] = np.asarray(system.hessian(Y[i])) @ dY[i]
            return jvp
    what = ("`separable_jvp()` (compiled), `force_jvp(Q, dQ)` or `hessian(y)`" if not full else
            "`full_jvp()` (compiled), `gradient_jvp(Y, dY)` or `hessian(y)`")
    raise TypeError(f"tangent vectors need the derivative of the force of {name} "
                    f"({'full' if full else 'separable'} form): give it {what}; see "
                    "integrators.variational")


class Megno:
    """The MEGNO accumulator (module docstring), fed with a tangent vector at increasing times.

    Parameters
    ----------
    t0 : float
        Start time (t is measured from it).
    delta0 : ndarray (d,)
        The tangent vector at t0 (nonzero).
    weights : ndarray (d,)
        |delta|^2 = sum (weights delta)^2: 1 for positions, 1/m for momenta.
    """

    def __init__(self, t0: float, delta0, weights, state: np.ndarray | None = None):
        self.weights = np.ascontiguousarray(weights, dtype=float)
        self.state = np.zeros(MEGNO_STATE) if state is None else state
        lnd = 0.5 * np.log(np.sum((self.weights * np.asarray(delta0, dtype=float)) ** 2))
        if not np.isfinite(lnd):
            raise ValueError("MEGNO needs a nonzero, finite tangent vector at the start")
        self.state[:] = [t0, lnd, t0, lnd, 0.0, 0.0, 0.0]

    def update(self, t: float, delta) -> None:
        """Advance to time t with the tangent delta (d,) there."""
        _megno_step(self.state, float(t), np.ascontiguousarray(delta, dtype=float), self.weights)

    @property
    def elapsed(self) -> float:
        return float(self.state[2] - self.state[0])

    @property
    def mean(self) -> float:
        """<Y>(t), the MEGNO (nan at the start)."""
        return float(self.state[5] / self.elapsed) if self.elapsed != 0 else float("nan")

    @property
    def Y(self) -> float:
        """Y(t), the instantaneous (not averaged) indicator."""
        return float(self.state[6])

    @property
    def lyapunov(self) -> float:
        """The finite-time Lyapunov indicator ln(|delta(t)| / |delta(t0)|) / (t - t0)."""
        return float((self.state[3] - self.state[1]) / self.elapsed) if self.elapsed != 0 else float("nan")


class VariationalStepper(Stepper):
    """A :class:`integrators.Stepper` that carries tangent vectors through every step, and the
    MEGNO of the first one.

    Parameters
    ----------
    variational : array_like, shape (d,) or (nv, d)
        The initial tangent vectors (dq, dp), d = 2m as the state; the first must be nonzero.
    others
        As for :class:`integrators.Stepper`.

    Attributes
    ----------
    tangents : ndarray (nv, d)
        The current tangent vectors (a copy).
    megno : Megno
        The accumulator of the first tangent (``megno.mean`` is <Y>, ``megno.lyapunov`` the
        finite-time Lyapunov indicator).
    tangent_iterations, jvp_evaluations : int
        Work of the tangent map over the committed steps (iterations summed over the vectors;
        stage evaluations of the force's derivative).

    A step whose tangent map fails raises like a failed step and is taken back: state, time,
    counters and tangents as before it.  Adaptive steps (:meth:`step_adaptive`) map the
    tangents once, with the accepted step.
    """

    def __init__(self, method, system, y0, t0: float = 0.0, solver: str = "auto",
                 tol: float | None = None, max_iter: int | None = None, form: str = "auto",
                 fast: bool | None = None, energy_tol: float | None = None, *, variational,
                 error_bound: float | str | None = "auto"):
        if not isinstance(method, HBVM):
            raise TypeError(f"tangent vectors need an HBVM(k, s) method (got {method!r}): the "
                            "tangent map is the derivative of the HBVM step, and EQUIP's step "
                            "adds a correction whose derivative it does not take")
        super().__init__(method, system, y0, t0, solver, tol, max_iter, form, fast, energy_tol,
                         error_bound=error_bound)
        b = self.binding
        d = self._y.size
        self._V = check_tangents(variational, d)
        jvp = jvp_for(b, self.system)
        # the step rebound with the jvp: one module holds the step and its tangent map
        b.step_code = specialise(b.force, b.potential, python=b.kind == "python", jvp=jvp,
                                 follow=b.follow, full=b.full, equip=b.equip)
        b.kind = b.step_code.kind
        b.name = f"{b.kind}-{'full' if b.full else 'separable'}"
        nv, s, u = self._V.shape[0], method.s, b.u
        self._DG = np.zeros((nv, s, u))
        self._Vt, self._DGt = np.empty_like(self._V), np.empty_like(self._DG)
        nf, nc = tangent.tangent_sizes(method.n_stages, s, u, b.minv.shape[0], d)
        self._tw, self._tcw = np.empty(nf), np.empty(nc, dtype=complex)
        self._tcount = np.zeros(3)
        self._no_params = np.zeros((nv, 0))         # (Tangents.P: the system's params)
        self._orders = np.zeros((nv, 3))            # (Tangents.O: all first-order)
        self._wv = np.ones(d) if b.full else np.concatenate([np.ones(d // 2), b.minv])
        self.megno = Megno(self.t, self._V[0], self._wv)
        # scratch of run_variational (the state before a step, to take it back)
        self._y0, self._cy0 = np.empty(d), np.empty(d)
        self._gsave, self._snap = np.empty_like(self._gamma), np.empty_like(self.counters)
        self._deferred = False
        self._record = None

    # -- public ------------------------------------------------------------------------
    @property
    def tangents(self) -> np.ndarray:
        return self._V.copy()

    @property
    def tangent_iterations(self) -> int:
        return int(self._tcount[0])

    @property
    def jvp_evaluations(self) -> int:
        return int(self._tcount[1])

    def step(self, h: float) -> np.ndarray:
        """One step (:meth:`integrators.Stepper.step`) and the tangent map of it."""
        if self._deferred:                 # an attempt of step_adaptive: mapped once accepted
            return super().step(h)
        before = self.save_state()
        super().step(h)
        self._map(before, float(h))
        return self._y.copy()

    def step_adaptive(self, h: float, epsilon: float, min_dt: float) -> tuple[float, float]:
        """:meth:`integrators.Stepper.step_adaptive`, then the tangent map of the accepted step
        (rejected attempts never touch the tangents)."""
        if self._record is not None:
            self._flush()
        before = self.save_state()
        self._deferred = True
        try:
            taken, proposed = super().step_adaptive(h, epsilon, min_dt)
        finally:
            self._deferred = False
        self._map(before, taken)
        if self._record is not None:
            self._accepted += 1
            entry = (self._V.copy(), self.megno.mean)
            if self._accepted % self._every == 0:
                self._record.append(entry)
            else:
                self._pending = entry
        return taken, proposed

    def run(self, h: float, steps: int, sample_every: int = 1):
        """:meth:`integrators.Stepper.run` with the tangents: the result's ``extra`` holds
        ``variational`` (n_samples, nv, d), the tangents at the samples, ``megno`` (n_samples,)
        <Y> there (nan at the start), ``lyapunov`` (the finite-time indicator at the end),
        ``tangent_iterations`` and ``jvp_evaluations``.  Fixed-point steps run in one call of
        the compiled loop (:func:`integrators.tangent.run_variational`)."""
        h = check_step(h)
        steps = check_count("steps", steps, 0)
        sample_every = check_count("sample_every", sample_every, 1)
        b = self.binding
        nv, d = self._V.shape
        nsamp = steps // sample_every + 1
        out_t, out_y, out_e = np.empty(nsamp), np.empty((nsamp, d)), np.empty(nsamp)
        out_v, out_m = np.empty((nsamp, nv, d)), np.empty(nsamp)
        out_t[0], out_y[0], out_e[0], out_v[0], out_m[0] = (self.t, self._y, b.energy(self._y),
                                                           self._V, self.megno.mean)
        k, done = 1, 0
        t_start = time.perf_counter()
        try:
            if self._solver == "fixed_point" and steps > 0:
                start = self.nsteps
                status = b.step_code.run_variational(
                    b.system_record, self._state_record(), h,
                    self._extrapolation(h, self._h_prev), b.method_record, b.no_newton,
                    self._options("fixed_point"), b.work_record(self.counters),
                    self._tangents(),
                    Variational(TANGENT_MAX_ITER["fixed_point"], self._y0, self._cy0,
                                self._gsave, self._snap, self.megno.state, self._wv,
                                out_v[1:], out_m[1:]),
                    Samples(steps, sample_every, out_t[1:], out_y[1:], out_e[1:]))
                done = self.nsteps - start
                if done > 0:
                    self._h_prev = h
                k = done // sample_every + 1
                if status >= TANGENT_FAILED:
                    self._tangent_fail(status - TANGENT_FAILED, h, "fixed_point")
                if status != OK:
                    if self.solver_option == "auto" and status in (DIVERGED, NOT_FINITE):
                        self._switch_to_newton(self.t, h, status)   # as step() does
                    else:
                        self._fail(status, h, self.solver_option)
            for i in range(done, steps):
                self.step(h)
                if (i + 1) % sample_every == 0:
                    out_t[k], out_y[k], out_e[k], out_v[k], out_m[k] = (
                        self.t, self._y, b.energy(self._y), self._V, self.megno.mean)
                    k += 1
        except StepError as err:
            err.result = self._with_tangents(self._result(out_t[:k], out_y[:k], out_e[:k], h, t_start,
                                                          "failed", str(err)), out_v[:k], out_m[:k])
            raise
        except BaseException as err:        # the system's own function, numpy, Ctrl-C
            self._stopped(err)
            _attach(err, self._with_tangents(self._result(out_t[:k], out_y[:k], out_e[:k], h,
                                                          t_start, self.status,
                                                          f"{type(err).__name__}: {err}"),
                                             out_v[:k], out_m[:k]))
            raise
        return self._with_tangents(self._result(out_t, out_y, out_e, h, t_start, "finished", ""),
                                   out_v, out_m)

    def run_adaptive(self, h: float, t_end: float, epsilon: float, min_dt: float,
                     sample_every: int = 1, sample_times=None):
        """:meth:`integrators.Stepper.run_adaptive` with the tangents at the samples in the
        result's ``extra`` (as :meth:`run`)."""
        # the run samples after every sample_every-th accepted step and after a step that lands on
        # one of the marks (sample_times, t_end): the tangents are kept after those steps only
        self._record = [(self._V.copy(), self.megno.mean)]
        self._every, self._accepted, self._pending = check_count("sample_every", sample_every, 1), 0, None
        self._marks = {float(x) for x in (sample_times if sample_times is not None else ())}
        self._marks.add(float(t_end))
        try:
            try:
                res = super().run_adaptive(h, t_end, epsilon, min_dt, sample_every, sample_times)
            except StepError as err:
                if err.result is not None:
                    self._flush()
                    self._pick(err.result)
                raise
            self._flush()
            return self._pick(res)
        finally:
            self._record = self._pending = None

    # -- private -----------------------------------------------------------------------
    def _map(self, before: tuple, h: float) -> None:
        """The tangent map of the step just committed from the state ``before``
        (:meth:`save_state`; the step's size h), and the MEGNO update; when it fails or raises
        (a Python jvp's own error, Ctrl-C) the step is taken back and the error raised."""
        b = self.binding
        y0, cy0, h_prev = before[0], before[1], before[6]
        try:
            newton = (b.newton_matrices(y0, h, self.counters) if self._solver == "newton"
                      else b.no_newton)
            status = b.step_code.tangent_map(
                b.system_record, y0, cy0, self._gamma, h, self._extrapolation(h, h_prev),
                b.method_record, newton, TANGENT_MAX_ITER[self._solver],
                self._tangents())
        except BaseException:
            self.restore_state(before)
            raise
        if status != OK:
            self.restore_state(before)
            self._tangent_fail(status, h, self._solver)
        b.step_code.megno_step(self.megno.state, self._clock[0], self._V[0], self._wv)

    def _tangents(self) -> Tangents:
        """The tangent map's arrays (:class:`integrators.records.Tangents`)."""
        return Tangents(self._V, self._DG, self._Vt, self._DGt, self._tw, self._tcw,
                        self._tcount, self._no_params, self._orders)

    def _tangent_fail(self, status: int, h: float, solver: str) -> None:
        self.status = "failed"
        it = int(self._tcount[2])
        if status == NOT_FINITE:
            raise NonFiniteError(h, it, solver, self.t, hint=(
                "the tangent vectors overflowed or met a singular force: the step itself "
                "converged and was taken back with them; renormalise the tangents, or check "
                "the state"))
        raise ConvergenceError(h, float("nan"), it, solver, self.t, hint=(
            "this is the tangent map's linear iteration (the step itself converged and was "
            "taken back with it); try a smaller step size h or solver='newton'"))

    def _with_tangents(self, res, out_v, out_m):
        res.extra.update(variational=np.array(out_v), megno=np.array(out_m),
                         lyapunov=self.megno.lyapunov, tangent_iterations=self.tangent_iterations,
                         jvp_evaluations=self.jvp_evaluations)
        return res

    def _flush(self) -> None:
        """Keep the last step's tangents when the run has set its clock onto a mark (a sample)."""
        if self._pending is not None and self.t in self._marks:
            self._record.append(self._pending)
        self._pending = None

    def _pick(self, res):
        """The kept tangents, one per sample of the adaptive run (checked)."""
        if len(self._record) != len(res.t):
            raise RuntimeError(f"internal error: {len(self._record)} tangents kept for "
                               f"{len(res.t)} samples of the adaptive run (its sampling rule "
                               "changed: see VariationalStepper.run_adaptive)")
        return self._with_tangents(res, np.array([r[0] for r in self._record]),
                                   np.array([r[1] for r in self._record]))


def variational_stepper(variational):
    """The Stepper class :func:`integrators.integrate` builds with ``variational=`` given."""
    return partial(VariationalStepper, variational=variational)


_engine.VARIATIONAL[0] = variational_stepper
