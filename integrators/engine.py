"""The stepping engine: :class:`Stepper` owns time, state, counters and status; :func:`integrate`
runs many steps.  Both call the one step of :mod:`integrators.loop` (compiled for systems with
compiled kernels, executed as Python otherwise: the same code either way).

Like scipy's ``OdeSolver``: the public ``step`` owns time, counters and status; the step itself
(:func:`integrators.loop.advance`) changes nothing on failure.
"""
from __future__ import annotations

import functools
import math
import numbers
import os
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from .core import (C_ERR, C_ITER, C_NEWTON, C_NFEV, C_RUN_ERR, C_STEPS, DIVERGED, N_COUNTERS,
                   NOT_FINITE, NOT_RESOLVED, OK, RUN_ERROR_BOUND, velocity_work, work_sizes)
from .core import DIVERGED as FAILED_STEP
from .core import ERROR_BOUND, EREF_RUN, N_EREF, adapt_step, select_extrapolation
from .core import test_particle_control
from . import ccore
from .jit import entry_point
from .errors import (AccumulatedErrorWarning, EnergyDriftError, NonFiniteError, StepError,
                     StepSizeError, UnresolvedStepError, step_error)
from .protocol import _Adapted, adapt_system
from .records import Method, Newton, Options, Samples, State, System, Work
from .quadrature import gauss_rule01
from .specialise import specialise

SOLVERS = ("auto", "fixed_point", "newton")
#: The default energy check of every host (engine, ASE, REBOUND): a step of a method exact for H
#: (a polynomial H with k >= nu s / 2, iterated to round-off) that changes H by more than this,
#: relative to |T| + |V|, is refused (:class:`integrators.UnresolvedStepError`).  HBVM at such
#: k changes it by about 1e-16 a step; 1e-10 leaves room for the rounding of H itself.
DEFAULT_ENERGY_TOL = 1e-10
#: ... and of a method not exact for H, whose own energy error has no computable bound: a step
#: (s >= 2) that changes H by more than this fraction of |T| + |V| and by more than
#: :data:`integrators.core.FLOW_FRACTION` (1e-3; 1.5e-2 for s = 2) of the energy it moved between the terms of H
#: (:func:`integrators.core.energy_flow`) is refused: it flew past what it should have resolved
#: (Kepler e = 0.999, HBVM(8, 4) at 1000 steps a period took E from -0.5 to +441.9 in its first
#: step from pericentre, and "finished"), or converged to a spurious root (HBVM(6, 3) on Kepler
#: at h = 1e6: an escaping state 1.25 (|T| + |V|) off).  A step that resolves its path keeps
#: its quadrature error far below that fraction of the flow (Gauss s = 2 on Kepler e = 0.6 at
#: 50 steps a period: 1e-5 a step).  This floor only keeps the flow's cost off steps whose error
#: is at round-off or near it.
NOT_A_SOLUTION = 1e-6
#: ... and for s = 1 (a constant force polynomial, order 2), whose error at a coarse step is of
#: the order of the flow itself (the midpoint rule on Henon-Heiles at h = 0.5: 6e-3 of |T| + |V|,
#: above the energy its one stage moves): a change above this fraction that also exceeds all of
#: the flow is refused.
NOT_A_SOLUTION_S1 = 0.1
FORMS = ("auto", "full", "separable")
#: a compiled fixed-step run returns to the interpreter about this often (seconds), so that
#: Ctrl-C is honoured within it (:meth:`Stepper._run_chunks`); a chunk grows at most
#: CHUNK_GROWTH times over the last
CHUNK_SECONDS = 0.1
CHUNK_GROWTH = 8
MAX_ITER = {"fixed_point": 60, "newton": 30}
#: solver="auto" after a switch to Newton: fixed point is tried again after this many Newton
#: steps, the wait doubling after each try that fails, up to NEWTON_HOLD_MAX (a try that
#: fails costs at most one fixed-point iteration's max_iter sweeps; a problem that stays stiff
#: pays it once every NEWTON_HOLD_MAX steps)
NEWTON_HOLD, NEWTON_HOLD_MAX = 1, 64
_SWITCH_WHY = {DIVERGED: "the fixed-point iteration did not converge",
               NOT_FINITE: "the fixed-point iteration met non-finite values (nan or inf)"}


def _is_separable(system) -> bool:
    return all(hasattr(system, a) for a in ("masses", "forces", "potential"))


def check_state(system, y, name: str = "y0"):
    """(system, y): the system as the engine calls it (:func:`.protocol.adapt_system`) and a
    float copy of y, checked: a system instance (not its class), y real, of shape
    (2 * system.dim,) and finite."""
    if isinstance(system, type):
        raise TypeError(f"`system` must be a system instance, not the class {system.__name__}: "
                        f"pass {system.__name__}(...) (e.g. Kepler(e=0.6), not Kepler)")
    try:
        a = np.asarray(y)
    except (TypeError, ValueError):       # ragged nesting
        a = None
    if a is not None and a.dtype.kind == "c":
        raise ValueError(f"`{name}` must be real (got a complex array): a state (q, p) is real; "
                         f"pass its real part explicitly if that is what you mean")
    try:
        if a is None or a.dtype.kind in "USV":     # strings would be parsed as numbers
            raise TypeError
        y = np.array(a, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be an array of numbers (got {y!r})") from None
    if not np.all(np.isfinite(y)):
        bad = np.flatnonzero(~np.isfinite(y))
        raise ValueError(f"`{name}` must be finite (got {y.flat[bad[0]]} at index {bad[0]}, {bad.size} "
                         f"non-finite of {y.size}); check the initial state for nan or inf")
    system = adapt_system(system, y)
    dim = getattr(system, "dim", None)
    if isinstance(dim, bool) or not isinstance(dim, (int, np.integer)) or dim < 1:
        name_ = type(system._system if isinstance(system, _Adapted) else system).__name__
        raise ValueError(f"`dim` of {name_} must be a positive integer, the number of degrees "
                         f"of freedom (got dim={dim!r}); set it to len(q), half the length of "
                         f"the state (q, p), or leave it out to take len(y0) // 2")
    if y.shape != (2 * system.dim,):
        raise ValueError(f"`{name}` must have shape ({2 * system.dim},) = (q, p) of a system with "
                         f"{system.dim} degrees of freedom (got shape {y.shape})")
    return system, y


def check_method(method) -> None:
    """A TypeError naming ``method`` when it is not a method object (a string, the class)."""
    if isinstance(method, type) or not all(hasattr(method, a) for a in ("k", "s", "tau", "X")):
        got = (f"the class {method.__name__}" if isinstance(method, type)
               else f"{type(method).__name__} {method!r:.60}")
        raise TypeError(f"`method` must be a method object such as integrators.HBVM(4, 2) or "
                        f"EQUIP(4, 2) (got {got}); build it with HBVM(k, s)")


def check_fast(fast) -> None:
    """A ValueError naming ``fast`` unless it is True, False or None ("no" is not False)."""
    if fast is not None and not isinstance(fast, (bool, np.bool_)):
        raise ValueError(f"`fast` must be True (compiled kernels required), False (the Python "
                         f"step) or None (compiled when the system has kernels) (got "
                         f"fast={fast!r})")


#: a run's samples may take at most this fraction of the machine's memory
SAMPLES_MEMORY = 0.5


def check_samples(steps: int, sample_every: int, size: int) -> None:
    """A ValueError naming ``steps`` and ``sample_every`` when the samples of a run would not
    fit in memory (instead of numpy's MemoryError, or the out-of-memory killer later)."""
    nsamp = steps // sample_every + 1
    need = 8.0 * nsamp * (size + 2)
    try:
        have = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):       # (not on every platform)
        have = 2.0 ** 40
    if need > SAMPLES_MEMORY * have:
        every = int(math.ceil(8.0 * steps * (size + 2) / (0.01 * have)))
        raise ValueError(f"`steps`={steps} with sample_every={sample_every} keeps {nsamp} samples "
                         f"of {size + 2} numbers ({need / 2**30:.3g} GiB, more than "
                         f"{SAMPLES_MEMORY:g} of this machine's {have / 2**30:.3g} GiB); raise "
                         f"sample_every (e.g. sample_every={every} keeps 1 % of memory) or run "
                         f"in pieces")


def is_real(value) -> bool:
    """True for a real number: an int, a float, a numpy real scalar or 0-d array; False for a
    bool, a string, a complex number, None or a sequence."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, numbers.Real):
        return True
    return isinstance(value, np.ndarray) and value.ndim == 0 and value.dtype.kind in "iuf"


def check_real(name: str, value, accepted: str, ok=None, none: bool = False):
    """``float(value)``, or a ValueError naming ``name``, the value received and what is
    ``accepted`` (e.g. "a positive number or None") when it is not a finite real number for
    which ``ok(float(value))`` holds.  ``none=True`` lets None through (returned as None)."""
    if value is None and none:
        return None
    good = is_real(value)
    if good:
        try:
            x = float(value)
        except OverflowError:        # an int beyond the float range
            good = False
        else:
            good = math.isfinite(x) and (ok is None or ok(x))
    if not good:
        raise ValueError(f"`{name}` must be {accepted} (got {name}={value!r})")
    return x


def check_times(name: str, times, t0: float, t_end: float) -> list:
    """The floats of ``times`` (None: none) in the order the run from t0 to t_end meets them,
    or a ValueError naming ``name`` when it is not a sequence of finite real numbers between
    t0 and t_end (a single number, a nan, a time the run never reaches)."""
    if times is None:
        return []
    if is_real(times) or isinstance(times, (str, bytes)):
        raise ValueError(f"`{name}` must be a sequence of times between t0={t0!r} and "
                         f"t_end={t_end!r} (got {name}={times!r}); for one time write [{times!r}]")
    try:
        values = list(times)
    except TypeError:
        raise ValueError(f"`{name}` must be a sequence of times between t0={t0!r} and "
                         f"t_end={t_end!r} (got {name}={times!r})") from None
    lo, hi = min(t0, t_end), max(t0, t_end)
    for i, x in enumerate(values):
        if not is_real(x) or not (np.isfinite(float(x)) and lo <= float(x) <= hi):
            raise ValueError(f"`{name}` must hold finite times between t0={t0!r} and "
                             f"t_end={t_end!r} (got {name}[{i}]={x!r}): a sample the run never "
                             f"reaches would be missing from the result without a word")
    return sorted((float(x) for x in values), reverse=t_end < t0)


def check_count(name: str, value, minimum: int) -> int:
    """``value`` as an int, or ValueError naming ``name`` when it is not an integer >= minimum
    (a bool, a float such as 10.0, or a smaller number)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"`{name}` must be an integer >= {minimum} (got {name}={value!r})")
    return int(value)


def check_step(h, name: str = "h") -> float:
    """``float(h)``, or a ValueError naming ``name`` when h is not a nonzero finite real
    number (a string such as "1", None, a bool, nan, inf or 0)."""
    if type(h) is float and h != 0.0 and math.isfinite(h):    # (every Stepper.step: 60 ns)
        return h
    return check_real(name, h, "a nonzero finite number", lambda x: x != 0.0)


def energy_check(method, system, energy_tol="auto", tol=None, round_off_k: bool = False) -> float:
    """The step's energy check ``etol`` (:func:`integrators.loop.run`) for ``energy_tol``.

    ``"auto"`` (the default of every host): when the method conserves H exactly (``system.
    polynomial_degree`` nu known, k >= nu s / 2, the iteration to round-off: ``tol`` None),
    or when the host chose k for a round-off quadrature error (``round_off_k``: the REBOUND
    host's ``choose_k`` / ``adaptive_k``), +DEFAULT_ENERGY_TOL, a step changing H by more than
    round-off is refused (an unresolved close encounter, a spurious root); otherwise
    -NOT_A_SOLUTION, a change above that fraction of |T| + |V| is refused when it also exceeds
    ``core.FLOW_FRACTION`` of the energy the step moved between the terms of H
    (:func:`integrators.core.energy_flow`): a step that flew past a pericentre it did not
    resolve, or a state that is not a solution (the Kepler problem at h = 1e6 converges to a
    state 1.25 (|T| + |V|) off), where the method's own error passes (for s = 1,
    -NOT_A_SOLUTION_S1 against all of the flow).  A number: that tolerance,
    strictly.  None: 0, no check."""
    if energy_tol is None:
        return 0.0
    if isinstance(energy_tol, str) and energy_tol == "auto":
        nu = getattr(system, "polynomial_degree", None)
        if nu is not None and (isinstance(nu, bool) or not isinstance(nu, (int, np.integer))
                               or nu < 0):
            raise ValueError(f"`polynomial_degree` of {type(system).__name__} must be None (H "
                             f"is not a polynomial) or a non-negative integer, the degree of "
                             f"H in q and p (got polynomial_degree={nu!r})")
        exact = (nu is not None and tol is None
                 and method.k >= type(method).for_polynomial_degree(max(int(nu), 1), method.s,
                                                                     method.nodes).k)
        if exact or (round_off_k and tol is None):
            return DEFAULT_ENERGY_TOL
        return -NOT_A_SOLUTION if method.s > 1 else -NOT_A_SOLUTION_S1
    if (isinstance(energy_tol, (bool, str)) or not isinstance(energy_tol, (int, float, np.number))
            or not (np.isfinite(energy_tol) and energy_tol > 0)):
        raise ValueError(f"`energy_tol` must be 'auto', a positive number or None (got "
                         f"energy_tol={energy_tol!r}); None switches the energy check off")
    return float(energy_tol)


def error_check(error_bound="auto") -> float:
    """The bound on each step's own error estimate (:func:`integrators.core.resolution_error`,
    checked by :func:`integrators.loop.run`) for ``error_bound``: "auto" (the default of every
    host), :data:`integrators.core.ERROR_BOUND`; a number in (0, inf): that bound; None: 0, no
    check (a run that wants steps which do not resolve the motion: a stability study)."""
    if error_bound is None:
        return 0.0
    if isinstance(error_bound, str) and error_bound == "auto":
        return ERROR_BOUND
    if (isinstance(error_bound, (bool, str)) or not isinstance(error_bound, (int, float, np.number))
            or not (np.isfinite(error_bound) and error_bound > 0)):
        raise ValueError(f"`error_bound` must be 'auto', a positive number or None (got "
                         f"error_bound={error_bound!r}); None switches the step's own error "
                         "check off")
    return float(error_bound)


def body_size(system) -> int:
    """The coordinates of one body of a separable system (its ``body_dim``: 3 for N bodies and
    atoms), for the step's error estimate body by body; 0 (the state as one block) for a
    system that does not say."""
    dim = getattr(system, "body_dim", None)
    if isinstance(dim, (int, np.integer)) and not isinstance(dim, bool) and dim > 0:
        return int(dim)
    return 0


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
    return check_real("t0", t0, "a finite number")


_COEF_CACHE: dict = {}
#: the Stepper class :func:`integrate` builds for ``variational=``: registered by
#: :mod:`integrators.variational` when it is imported (the package imports it), so that this
#: module does not import it back
VARIATIONAL: list = [None]


def method_arrays(method) -> tuple:
    """(c1, c2) = ((tn, ts), (Wp, Cp)): the method's arrays packed as the step takes them,
    tn = [tau, tau_lo], ts = [X0, X0_lo], Wp = [W, W_lo], Cp = [C2, C2_lo, I, I_lo] (contiguous,
    read-only, so that every path compiles one signature; see :mod:`integrators.loop`)."""
    hit = _COEF_CACHE.get(method)
    if hit is None and hasattr(method, "step_arrays"):      # a method that packs its own (EQUIP)
        hit = _COEF_CACHE[method] = method.step_arrays
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
    far longer than the last).  The rule is ``core.select_extrapolation``'s, for the REBOUND
    step too; the compiled core has a copy of it (``integrators/csrc/pymodule.c``) until
    REBOUND's step moves there, chosen once for this object."""

    core = False        # (one pickled before the compiled core took the rule: numba's)

    def __init__(self, method):
        self.E1 = np.array(method.E, dtype=float, order="C")   # writable: one array type
        t, w = gauss_rule01(method.s)
        self.t, self.w = t.copy(), w.copy()                      # writable, like E1
        self.buf = np.empty_like(self.E1)
        self.zero = np.zeros_like(self.E1)
        # the compiled core's copy of the rule (the same numbers, nothing to compile), chosen
        # once, not at every step
        self.core = ccore.available()

    def __call__(self, h: float, h_prev: float | None) -> np.ndarray:
        hp = np.nan if h_prev is None else h_prev
        if self.core:
            return ccore._core.select_extrapolation(float(h), float(hp), self.E1, self.t,
                                                    self.w, self.buf, self.zero)
        return entry_point(select_extrapolation)(h, hp, self.E1, self.t, self.w, self.buf,
                                                 self.zero)


def _checked_result(method: str, system: str, r, given: tuple, expected: tuple) -> np.ndarray:
    """``r``, the result of ``method`` of a system (its class name ``system``) on a stack of
    shape ``given``, as a float array of shape ``expected``, or a ValueError naming the method
    and both shapes."""
    a = np.asarray(r)
    if a.shape != expected:
        raise ValueError(f"`{method}` of {system} must return shape {expected} for a stack of shape "
                         f"{given} (the k stages of a step, one row each) (got shape {a.shape}); "
                         f"index the last axis (x[..., i], not x[i]) and keep the stack axis")
    if a.dtype.kind not in "iuf":
        raise ValueError(f"`{method}` of {system} must return shape {expected} for a stack of shape "
                         f"{given}, real numbers (got dtype {a.dtype})")
    return a


def _checked_rows(method: str, system: str, fn, X: np.ndarray, r: np.ndarray) -> None:
    """Once, on the first stack of several rows: the first and the last row of ``r`` =
    ``fn(X)`` must equal ``fn`` of that row alone (to round-off), else a ValueError naming the
    method: a result of the right shape can still mix the rows (transposed when the stack is
    square, x[i] where x[..., i] was meant)."""
    for i in (0, X.shape[0] - 1):
        alone = np.asarray(fn(X[i:i + 1]), dtype=float).reshape(-1)
        if alone.shape == r[i].shape and not (np.all(np.isfinite(alone))
                                              and np.all(np.isfinite(r[i]))):
            # a force that is not finite there (nan, inf) is the step's to report
            # (NOT_FINITE: a switch to Newton, or NonFiniteError), as in any later step: one
            # policy from the first step on (issue 47, item 7)
            continue
        if alone.shape != r[i].shape or not np.all(np.abs(r[i] - alone)
                                                   <= 1e-9 * (np.max(np.abs(alone)) + 1e-300)):
            raise ValueError(f"`{method}` of {system} on a stack of shape {X.shape} returned a row "
                             f"{i} that differs from `{method}` of that row alone: it mixes the rows "
                             f"of the stack (a transposed result, or x[i] where x[..., i] was "
                             f"meant); return one row per row of the stack")


def _commit_seen(watch: list) -> None:
    """The Python kernels' note of a new committed step (see :meth:`Binding.watch`)."""
    watch[1] = watch[0][0]
    watch[2][:] = watch[3]


def _checked_number(method: str, system: str, v, given: tuple) -> float:
    """``v``, the result of ``method`` (energy or potential) for one state of shape ``given``,
    as a float, or a ValueError naming the method and the shape received."""
    a = np.asarray(v)
    if a.size != 1 or a.dtype.kind not in "iuf":
        raise ValueError(f"`{method}` of {system} must return one real number for one state of "
                         f"shape {given} (got {'shape ' + str(a.shape) if a.size != 1 else repr(v)})")
    return float(a.reshape(()))


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
    jvp : callable, optional
        The force kernel's derivative ``jvp(X, dX, params, out)``: the tangent map is bound
        with the step (:mod:`integrators.variational`), for a glue that calls it.
    velocities : bool
        The separable step hands the force kernel the stage velocities too (X of shape
        (n, 2m): positions, then velocities M^{-1} p; :func:`integrators.core.stage_velocities`):
        for a force that reads velocities.  HBVM only, no followers, no tangent map.
    """

    def __init__(self, method, system, form: str = "auto", fast: bool | None = None,
                 glue: str | None = None, jvp=None, velocities: bool = False):
        if form == "separable" and not _is_separable(system):
            raise ValueError("`form='separable'` needs a system with `masses`, `forces` and "
                             "`potential`; use form='full'")
        check_fast(fast)
        self.full = not (form == "separable" or (form == "auto" and _is_separable(system)))
        self.method, self.system = method, system
        self._watch = None
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
        # test particles (followers) solved after the sources, with the system's kernels
        self.follow = (system.separable_followers()
                       if has_kernels and not self.full
                       and callable(getattr(system, "separable_followers", None))
                       else None)
        # (the form and the method are fixed for a binding: the step leaves the others out)
        self.equip = hasattr(method, "step_arrays")         # EQUIP packs its own arrays
        self.velocities = bool(velocities)
        if self.velocities and (self.full or self.equip or self.follow is not None
                                or jvp is not None):
            raise ValueError("`velocities=True` (stage velocities for a force that reads them) "
                             "needs the separable form, method HBVM, no test particles and no "
                             f"tangent map (got form={'full' if self.full else 'separable'}, "
                             f"{type(method).__name__}); use form='full' for such a system")
        # a system whose variables are re-expressed after each committed step (the Keplerian
        # flows' recentring of systems.flow_composed): its kernel is bound with the step
        self.recentre = (system.recentre_kernel()
                         if has_kernels and self.full
                         and callable(getattr(system, "recentre_kernel", None)) else None)
        self.step_code = specialise(force, potential, python=fast is False, glue=glue, jvp=jvp,
                                    follow=self.follow, full=self.full, equip=self.equip,
                                    velocities=self.velocities, recentre=self.recentre)
        self.force, self.potential = force, potential    # (the tangent map rebinds them)
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
            # (a negative mass is a mass: an N-body source of negative mass, whose p / m is
            # its velocity; only a zero has no velocity)
            if not np.all(np.isfinite(masses) & (masses != 0)):
                bad = int(np.flatnonzero(~(np.isfinite(masses) & (masses != 0)))[0])
                raise ValueError(f"`masses` of {type(system).__name__} must be nonzero and "
                                 f"finite, one per coordinate (got masses[{bad}]={float(masses[bad])!r}): "
                                 f"a coordinate of zero mass has no velocity p / m; give it a "
                                 f"mass (NBody gives a massless test particle 1 per coordinate) "
                                 f"or use the full form (form='full', gradient and energy)")
            self.minv = 1.0 / masses
            self.kin_w = np.ascontiguousarray(getattr(system, "kinetic_weights", self.minv),
                                              dtype=float)
        self.c1, self.c2 = method_arrays(method)
        # the method's packed arrays as the step takes them (integrators.records.Method)
        self.method_record = Method(*self.c1, *self.c2)
        u = d if self.full else m
        s = method.s
        self.u = u
        self.no_newton = Newton(np.zeros((s, s), dtype=complex), np.zeros((s, s), dtype=complex),
                                np.zeros((0, u, u), dtype=complex))
        n = getattr(method, "work_rows", method.n_stages)
        # (the sizes' arithmetic as Python: compiling it costs a first run more than it saves)
        nf, nc = getattr(work_sizes, "py_func", work_sizes)(n, s, u, self.minv.shape[0], d)
        nf += getattr(velocity_work, "py_func", velocity_work)(n, m, self.velocities)
        self.work, self.cwork = np.empty(nf), np.empty(nc, dtype=complex)
        self._eig = None

    @property
    def system_record(self) -> System:
        """The step's :class:`integrators.records.System` (built at each call: a host may
        replace the binding's arrays)."""
        return System(self.full, self.minv, self.kin_w, self.params)

    def work_record(self, counters: np.ndarray) -> Work:
        """The step's work buffers and the caller's counters (:class:`integrators.records.Work`)."""
        return Work(self.work, self.cwork, counters)

    def _python_kernels(self, system):
        """Kernels that call the system's own (numpy) methods: the Python path.

        Every result is checked against the shape the step needs, whatever the system's class
        (a :class:`systems.base.SeparableSystem` subclass is not probed by
        :mod:`.protocol`): numpy would broadcast a result of shape (n, 1), or one summed over
        the stack, into the step's array and the run would finish with a wrong answer.  The
        first call of each checks fully (shape, real numbers); later calls compare the shape
        only (a tuple comparison), so that a method whose result changes shape mid-run is
        refused at that call.  The kernels also keep the counters of the last committed step
        (:meth:`watch`)."""
        name = type(system._system if isinstance(system, _Adapted) else system).__name__
        if self.full:
            rhs, rhs_name, one, one_name = system.gradient, "gradient", system.energy, "energy"
        else:
            rhs, rhs_name, one, one_name = system.forces, "forces", system.potential, "potential"
        # watch: [the counters' C_STEPS as a memoryview (None: not watched), the value seen,
        # a copy of the counters at the first kernel call after a commit, the counters]
        self._watch = watch = [None, -1.0, None, None]
        into = None if self.full else getattr(system, "forces_into", None)
        if callable(into):
            def force(X, params, out):        # writes out itself (no copy of the result)
                w = watch[0]
                if w is not None and w[0] != watch[1]:
                    _commit_seen(watch)
                into(X, out)
        else:
            # until the first call and the first stack of several rows (a system declaring
            # rows_independent = True, the ASE adapter's, is not probed row by row)
            unchecked = [True]
            rows = not getattr(system, "rows_independent", False)

            def force(X, params, out):
                w = watch[0]
                if w is not None and w[0] != watch[1]:
                    _commit_seen(watch)
                r = rhs(X)
                if unchecked[0] or getattr(r, "shape", None) != out.shape:
                    r = _checked_result(rhs_name, name, r, X.shape, out.shape)
                    if X.shape[0] > 1:
                        if rows:
                            _checked_rows(rhs_name, name, rhs, X, r)
                        unchecked[0] = False
                out[...] = r

        def potential(x, params):
            w = watch[0]
            if w is not None and w[0] != watch[1]:
                _commit_seen(watch)
            v = one(x)
            return float(v) if isinstance(v, float) else _checked_number(one_name, name, v, x.shape)
        return force, potential, np.zeros(1)

    def watch(self, counters: np.ndarray) -> None:
        """Let the Python kernels keep a copy of ``counters`` as of the last committed step:
        taken at their first call after a commit (a step calls them before it changes
        anything), so that :meth:`restore` can undo the work counted by a step that the
        system's own function (or Ctrl-C) stopped midway.  Compiled kernels never raise.
        (A memoryview reads the step counter as a Python float: half the cost of numpy's
        scalar, on every kernel call of the Python path.)"""
        if getattr(self, "_watch", None) is not None:
            self._watch[:] = [memoryview(counters)[C_STEPS:C_STEPS + 1], -1.0, counters.copy(),
                              counters]

    def restore(self, counters: np.ndarray) -> None:
        """``counters`` back to the last committed step's (see :meth:`watch`), when the copy
        is of that step (no step committed since the kernels were last called)."""
        w = getattr(self, "_watch", None)
        if w is not None and w[3] is counters and w[2][C_STEPS] == counters[C_STEPS]:
            counters[:] = w[2]

    def energy(self, y: np.ndarray) -> float:
        t, v = self.step_code.energy_parts(self.full, y, self.kin_w, self.params)
        return float(t + v)

    def rhs(self, X: np.ndarray) -> np.ndarray:
        """The kernel's output (forces, or grad H for the full form) at a stack of rows X."""
        out = np.empty_like(X)
        self.force(np.ascontiguousarray(X), self.params, out)
        return out

    def newton_matrices(self, y: np.ndarray, h: float, counters: np.ndarray) -> "Newton | None":
        """Newton(NV, NVinv, NM) (:class:`integrators.records.Newton`): the simplified-Newton
        matrices of the Gauss method, I - h X_s (x) J0 (full form) or I - h^2 X_s^2 (x) dF/dq
        M^{-1} (separable), split through X_s's eigenvalues (by the isospectral property they
        are Gauss's whatever k is); None when h is at an eigenvalue of the Jacobian.  J0 comes
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
        if not np.all(np.isfinite(L)):
            return None           # (the caller fails the step as NonFiniteError)
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
            try:
                NM[i] = np.conj(NM[j]) if j is not None else np.linalg.inv(eye - m_i * L)
            except np.linalg.LinAlgError:   # h at an eigenvalue of the Jacobian: no Newton step
                return None
        return Newton(V, Vinv, NM)


#: the hint of an adaptive step's NonFiniteError when the forces at its start are not finite
NONFINITE_AT_START = ("the forces at the state the step starts from are not finite (nan or "
                      "inf), so no shorter step helps; check the model there (two bodies on "
                      "top of each other, a force that breaks down)")


def _caller_stacklevel() -> int:
    """The stacklevel of warnings.warn, called here, that names the first frame outside this
    package (the user's call of integrate or Stepper.run, not the engine's own lines)."""
    here = os.path.dirname(os.path.abspath(__file__))
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.dirname(os.path.abspath(frame.f_code.co_filename)) == here:
        frame, level = frame.f_back, level + 1
    return level


def _attach(err: BaseException, result) -> None:
    """Give an exception that stopped a run (not a StepError: those carry ``result`` by
    construction) the samples up to the last committed step, and say so in its notes."""
    try:
        err.result = result
    except AttributeError:       # (an exception class with __slots__ and no __dict__)
        return
    if hasattr(err, "add_note"):             # Python >= 3.11
        end = f" (t = {float(result.t[-1])!r})" if len(result.t) else ""
        err.add_note(f"hbvm-md: the run stopped after {result.steps} committed steps{end}; "
                     f"their samples are in this exception's `.result`")


def _one_thread(fn):
    """A Stepper method that refuses a second thread while another one runs it: a Stepper
    holds one state, and two threads stepping it at once would mix their iterations in its
    work arrays (and fail with a misleading hint, or not at all)."""
    @functools.wraps(fn)
    def guarded(self, *args, **kwargs):
        busy = self.__dict__.get("_busy") or self.__dict__.setdefault("_busy", threading.RLock())
        if not busy.acquire(blocking=False):
            raise RuntimeError(f"this Stepper is already running `{fn.__name__}` in another "
                               f"thread: a Stepper holds one state and steps it in one thread "
                               f"at a time; give each thread its own Stepper (or integrate "
                               f"call), or serialise the calls with a lock")
        try:
            return fn(self, *args, **kwargs)
        finally:
            busy.release()
    return guarded


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
        fixed point; a step whose fixed-point iteration fails (a stiff problem, a large step,
        one bad force) is done with Newton, and fixed point is tried again after NEWTON_HOLD
        Newton steps, the wait doubling after each try that fails (up to NEWTON_HOLD_MAX):
        one transient failure costs one Newton step, a stiff problem stays with Newton.
    tol : float, optional
        Relative tolerance of the iteration; default None iterates to round-off.
    max_iter : int, optional
        Iteration cap per step (default 60 for fixed point, 30 for Newton).
    form : {"auto", "full", "separable"}
        ``"separable"`` iterates on the momentum coefficients only (needs ``masses``,
        ``forces``, ``potential``); ``"auto"`` uses it when the system offers them.
    fast : bool or None
        Compiled kernels: required (True), never (False), when the system has them (None).
    energy_tol : "auto", float or None
        Refuse a converged step whose energy change, relative to |T| + |V|, exceeds this
        (:class:`integrators.UnresolvedStepError`, nothing committed); None: no check.
        "auto" (default, :func:`energy_check`): DEFAULT_ENERGY_TOL (1e-10) for a method exact
        for the system's polynomial H; for any other, a change above NOT_A_SOLUTION (1e-6) that
        also exceeds 1e-3 (s = 2: 1.5e-2) of the energy the step moved between the terms of H is refused (a
        step too large for the encounter it crosses, a state that is not a solution), and the
        method's own quadrature error passes (s = 1: above 0.1 and all of that energy).

    error_bound : "auto", float or None (keyword-only)
        Refuse a converged step whose own estimate of its relative local error exceeds this
        (:class:`integrators.UnresolvedStepError` naming the body, its estimate and a step that
        would pass; nothing committed): from the first Legendre term the step leaves out of a
        body's velocity over the step against the velocity it keeps
        (:func:`integrators.core.resolution_error`), taken from the step's own stage values
        (k > s) or one evaluation at its end (k = s), independent of the energy, which an
        energy-conserving step keeps whether or not it followed the solution.  "auto"
        (default): :data:`integrators.core.ERROR_BOUND` (1e-3: three correct digits a step);
        None: no check.

    Attributes
    ----------
    t, y : current time and state (copies; the state is kept as a double-double number).
    nsteps, nfev, niter, newton_steps, solver_switches : counters (``solver_switches``: the
        switches from fixed point to Newton under solver="auto").
    last_switch : dict or None
        The last switch to Newton: ``t`` and ``h`` of the step, ``why`` (the fixed-point
        failure, in words); None before any.
    solver_returns : int
        The times solver="auto" went back to fixed point after Newton.
    status : "running" after a step succeeded; "failed" after a step raised (a StepError or
        an exception from the system's own function), "interrupted" after KeyboardInterrupt or
        SystemExit; the state and time are those of the last committed step.
    """

    def __init__(self, method, system, y0, t0: float = 0.0, solver: str = "auto",
                 tol: float | None = None, max_iter: int | None = None, form: str = "auto",
                 fast: bool | None = None, energy_tol: float | str | None = "auto", *,
                 error_bound: float | str | None = "auto"):
        check_method(method)
        self.error_bound = error_bound
        t0 = check_options(solver, form, tol, max_iter, t0)
        energy_check(method, None, energy_tol, tol)        # checks the argument first
        system, self._y = check_state(system, y0)
        self.method, self.system = method, system
        self.binding = Binding(method, system, form, fast)
        self.form = self.binding
        self._group = body_size(system)
        # a host's own words in its errors (errors.step_error's ``hints``: "body": how a body is
        # named, "atom {i}"; "resolution": its way out of an unresolved step)
        self.hints = {}
        self._cy = np.zeros_like(self._y)
        self._clock = np.array([t0, 0.0])
        self._gamma = np.zeros((method.s, self.binding.u))
        self._h_prev = None
        self._extrapolation = Extrapolation(method)
        # [energy, EQUIP's alpha, slope, the run's start, its mean T, its time] (core.N_EREF)
        self._eref = np.full(N_EREF, np.nan)
        self.counters = np.zeros(N_COUNTERS)
        self.binding.watch(self.counters)
        # one step is run() of one step without samples (loop.advance, which compiled callers
        # inline): the same entry point as the runs', so that a first step() does not compile
        # a second one (numba optimises the linked step again for each entry point)
        self._one_step = Samples(1, 0, np.empty(0), np.empty((0, self._y.shape[0])), np.empty(0))
        self.solver_option = solver
        self._solver = "newton" if solver == "newton" else "fixed_point"
        self.tol, self.max_iter = tol, max_iter
        self.energy_tol = energy_tol
        self.solver_switches = 0
        self.solver_returns = 0
        self.last_switch = None
        # solver="auto" under Newton: steps done since the switch, and the wait before fixed
        # point is tried again
        self._newton_run, self._newton_hold = 0, NEWTON_HOLD
        self.rejected = 0
        # a host's way through a step the energy check refused whatever its size (ASE: a
        # calculator's jump, hbvm_md.ase.discontinuity): called by step_adaptive as
        # through_refusal(err, h) at the first such refusal of a step; True when it took the
        # step itself (committed, t advanced by h), False to shrink as usual
        self.through_refusal = None
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
    def error_estimate(self) -> float:
        """The run's accumulated error estimate (:data:`integrators.core.C_RUN_ERR`): the sum
        over the committed steps of each step's own error estimate (plus 1.5 times the run's
        energy drift, for a method that does not keep H: the phase an energy offset makes,
        :data:`integrators.core.DRIFT_PHASE`) times the share of its body's motion the step
        turned (:func:`integrators.core.run_error_share`), an estimate
        of the run's error relative to the motion's own scale (an orbit's radius) when the
        steps' errors add, as a periodic orbit's phase error does; a lower bound for a chaotic
        orbit, whose errors grow faster.  Carried by this Stepper across its calls (and
        pickles); a new Stepper starts at 0.  Steps taken with ``error_bound=None`` (no
        estimate) add nothing.  :meth:`run` and :meth:`run_adaptive` warn once
        (:class:`integrators.AccumulatedErrorWarning`) when it passes
        :data:`integrators.core.RUN_ERROR_BOUND` (1e-2)."""
        return float(self.counters[C_RUN_ERR])

    @property
    def energy_tol(self):
        """The energy check as given ("auto", a number or None); setting it re-derives what
        the step checks (:func:`energy_check`)."""
        return self._energy_tol

    @energy_tol.setter
    def energy_tol(self, value) -> None:
        self._etol = energy_check(self.method, self.system, value, self.tol)
        self._energy_tol = value

    @property
    def error_bound(self):
        """The bound on each step's own error estimate as given ("auto", a number or None);
        setting it re-derives what the step checks (:func:`error_check`)."""
        return self._error_bound

    @error_bound.setter
    def error_bound(self, value) -> None:
        self._ebound = error_check(value)
        self._error_bound = value

    @property
    def solver(self) -> str:
        """The solver the next step will use."""
        return self._solver

    @property
    def energy_reference(self) -> float:
        """H at the end of the last committed step, as the next step's energy check compares
        it (nan before the first step): a host compares it with H at the state it hands back
        to see a Hamiltonian changed between steps (ASE's calculator set in place)."""
        return float(self._eref[0])

    def accept_energy_jump(self, jump: float) -> None:
        """Move the run's starting energy by ``jump``, a change of H on the last step that the
        host knows is not the step's (a calculator's own discontinuity, accepted with a warning
        by ASE's host): the drift rule (:data:`integrators.core.DRIFT_BOUND`) then goes on
        judging what the steps did, not the calculator's jumps."""
        if math.isfinite(jump):
            self._eref[EREF_RUN] += jump

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state.pop("_busy", None)          # (a lock does not pickle; a copy gets its own)
        return state

    def __setstate__(self, state: dict) -> None:
        eref = state.get("_eref")
        if eref is not None and eref.shape[0] < N_EREF:
            # a Stepper pickled before the run's start (and its mean T) joined eref
            # (core.N_EREF): the compiled step indexes eref unchecked, so the array is padded;
            # nan starts the run's drift afresh from the next step
            eref = np.concatenate([eref, np.full(N_EREF - eref.shape[0], np.nan)])
            eref[EREF_RUN] = np.nan
            state["_eref"] = eref
        counters = state.get("counters")
        if counters is not None and counters.shape[0] < N_COUNTERS:
            # (pickled before the run's accumulated estimate joined the counters: from 0)
            state["counters"] = np.concatenate([counters,
                                                np.zeros(N_COUNTERS - counters.shape[0])])
        self.__dict__.update(state)

    @_one_thread
    def step(self, h: float) -> np.ndarray:
        """Advance by one step of size h and return (a copy of) the new state.

        Raises a :class:`integrators.StepError` (ConvergenceError, NonFiniteError,
        UnresolvedStepError) with the state, time and coefficients unchanged when the step
        fails, also after the automatic switch to Newton."""
        h = check_step(h)
        auto = self.solver_option == "auto"
        # solver="auto" under Newton tries fixed point again once it has waited its hold
        retry = auto and self._solver == "newton" and self._newton_run >= self._newton_hold
        first = "fixed_point" if retry else self._solver
        t0 = self.t
        try:
            status = self._advance(h, first)
            switch = status in (DIVERGED, NOT_FINITE) and auto and first == "fixed_point"
            why = status
            if switch:
                status = self._advance(h, "newton")
        except BaseException as err:        # the system's own function, numpy, Ctrl-C
            self._stopped(err)
            raise
        if switch:
            if status != OK:
                self._fail(status, h, "auto")
            self._switch_to_newton(t0, h, why, retry)
        elif status != OK:
            self._fail(status, h, self.solver_option)
        elif retry:                 # fixed point converges again: back to it
            self._solver = "fixed_point"
            self._newton_hold = NEWTON_HOLD
            self.solver_returns += 1
        if self._solver == "newton":
            self._newton_run += 1
        self._after_step(h)
        self.status = "running"
        return self._y.copy()

    def _switch_to_newton(self, t: float, h: float, why: int, retry: bool = False) -> None:
        """solver="auto": from now on simplified Newton, after the fixed-point iteration of the
        step of size h at t failed with status ``why`` (DIVERGED or NOT_FINITE); written once,
        for :meth:`step`, :meth:`run` and the variational run.  A first switch is counted and
        reported (``solver_switches``, ``last_switch``); a ``retry`` of fixed point that failed
        again (still stiff) doubles the wait before the next try instead (up to
        NEWTON_HOLD_MAX)."""
        if retry:
            self._newton_hold = min(2 * self._newton_hold, NEWTON_HOLD_MAX)
        else:
            self.solver_switches += 1
            self.last_switch = {"t": t, "h": h, "why": _SWITCH_WHY[why]}
            self._newton_hold = NEWTON_HOLD
        self._solver = "newton"
        self._newton_run = 0

    def save_state(self) -> tuple:
        """Everything a step changes (state, coefficients, energy reference, clock, counters,
        solver, status), copied: :meth:`restore_state` puts it back, for a host whose own part
        of a step failed after the engine's succeeded (ASE's forces at the new positions)."""
        return (self._y.copy(), self._cy.copy(), self._gamma.copy(), self._eref.copy(),
                self._clock.copy(), self.counters.copy(), self._h_prev, self._solver,
                self.solver_switches, self.rejected, self.status, self.solver_returns,
                self.last_switch, self._newton_run, self._newton_hold)

    def restore_state(self, saved: tuple) -> None:
        """Back to a :meth:`save_state` exactly (in place: the arrays keep their identity)."""
        for mine, kept in zip((self._y, self._cy, self._gamma, self._eref, self._clock,
                               self.counters), saved[:6]):
            mine[...] = kept
        (self._h_prev, self._solver, self.solver_switches, self.rejected, self.status,
         self.solver_returns, self.last_switch, self._newton_run, self._newton_hold) = saved[6:]

    @_one_thread
    def run(self, h: float, steps: int, sample_every: int = 1) -> "IntegrationResult":
        """``steps`` steps of size h with samples every ``sample_every`` steps (and at step 0).

        Fixed-point steps run in calls of the step loop (compiled when the kernels are) of
        about CHUNK_SECONDS each, so that Ctrl-C stops the run within that time with the
        committed steps in the exception's ``result`` (the numbers are those of one call);
        on failure with solver="auto" the run goes on with Newton.  A failure raises with the
        samples so far in the exception's ``result``."""
        h = check_step(h)
        steps = check_count("steps", steps, 0)
        sample_every = check_count("sample_every", sample_every, 1)
        check_samples(steps, sample_every, self._y.size)
        nsamp = steps // sample_every + 1
        # t and H start as nan: a run stopped by an exception keeps the samples written
        out_t, out_y, out_e = np.full(nsamp, np.nan), np.empty((nsamp, self._y.size)), np.full(nsamp, np.nan)
        start = self.nsteps
        t_start = time.perf_counter()
        try:
            return self._run(h, steps, sample_every, start, t_start, out_t, out_y, out_e)
        except StepError:
            raise
        except BaseException as err:        # the system's own function, numpy, Ctrl-C
            self._stopped(err)
            k = (self.nsteps - start) // sample_every + 1
            while k > 0 and np.isnan(out_e[k - 1]):    # a sample whose energy was not written
                k -= 1
            _attach(err, self._result(out_t[:k], out_y[:k], out_e[:k], h, t_start, self.status,
                                      f"{type(err).__name__}: {err}"))
            raise

    def _run(self, h, steps, sample_every, start, t_start, out_t, out_y, out_e):
        b = self.binding
        if self._solver == "fixed_point":
            status = self._run_chunks(h, steps, sample_every, start, out_t, out_y, out_e)
            done = self.nsteps - start
            k = done // sample_every + 1
            if done < steps and status == OK:     # the step loop's contract, checked
                raise RuntimeError(f"internal error: the step loop stopped after {done} of "
                                   f"{steps} steps without a failure status")
            if done < steps and status != OK:
                if self.solver_option == "auto" and status in (DIVERGED, NOT_FINITE):
                    # the failed step again with Newton, then as step() does
                    self._switch_to_newton(self.t, h, status)
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
        return self._warn_run_error(self._result(out_t, out_y, out_e, h, t_start, "finished",
                                                 ""))

    def _run_chunks(self, h, steps, sample_every, start, out_t, out_y, out_e) -> int:
        """The fixed-point steps of :meth:`run` through the step loop, in chunks of about
        CHUNK_SECONDS each: between two calls the interpreter runs its signal handlers, so
        that Ctrl-C stops a compiled run within a chunk (a compiled loop never returns to
        it), with every committed step kept.  The numbers are those of one call bit for bit:
        each chunk continues from the state, coefficients, energy reference and clock the last
        left (the same E throughout, as one call uses), and a chunk starting on a sample writes
        that sample again, the same numbers; a chunk that starts between two samples (a chunk
        shorter than ``sample_every``) ends at the next one, which is written here with the
        loop's own energy function.  Stops at the first failed step; returns its status (OK
        when every step was committed)."""
        b = self.binding
        E = self._extrapolation(h, self._h_prev)
        args = (b.system_record, self._state_record(), h, E, b.method_record, b.no_newton,
                self._options("fixed_point"), b.work_record(self.counters))
        # the Python step (a user's system, fast=False) returns to the interpreter all the
        # time: one call, so that its kernels see the calls of one run (no sample written
        # twice)
        done, chunk = 0, (1 if b.kind == "compiled" else max(steps, 1))
        while True:
            end = min(steps, done + chunk)
            aligned = done % sample_every == 0
            if not aligned:
                end = min(end, (done // sample_every + 1) * sample_every)
            i = done // sample_every if aligned else 0
            every, n_out = (sample_every, out_t.shape[0]) if aligned else (0, 0)
            t0 = time.perf_counter()
            status = b.step_code.run(*args, Samples(end - done, every, out_t[i:i + n_out],
                                           out_y[i:i + n_out], out_e[i:i + n_out]))
            took = time.perf_counter() - t0
            if self.nsteps > start:
                self._h_prev = h
            if self.nsteps - start < end:          # a failed step
                return int(status)
            if not aligned and end % sample_every == 0:
                j = end // sample_every
                out_t[j], out_y[j] = self.t, self._y
                out_e[j] = b.energy(self._y)
            done = end
            if done >= steps:
                return OK
            # the next chunk aims at CHUNK_SECONDS, growing at most CHUNK_GROWTH times (the
            # first is one step: a step of 1e5 atoms can take a fifth of a second)
            chunk = max(1, min(CHUNK_GROWTH * chunk, int(chunk * CHUNK_SECONDS / max(took, 1e-9))))

    def step_adaptive(self, h: float, epsilon: float, min_dt: float) -> tuple[float, float]:
        """One adaptive step: try h, and on rejection (the error estimate from the step's own
        coefficients above ``epsilon``, a failed iteration or energy check) retry smaller.
        Returns (the step taken, the next step proposed).  A rejected attempt leaves no trace
        in the state, the time or the counters.  Raises :class:`integrators.StepSizeError`
        when no step down to ``min_dt``, or down to the smallest step that still changes t, is
        accepted."""
        s = self.method.s
        why = getattr(self.system, "fixed_steps_only", None)
        if why:        # (a system whose coefficients the controller's estimate cannot read)
            raise ValueError(f"adaptive steps are not available for {type(self.system).__name__}: "
                             f"{why}")
        # the controller reads each step's own error estimate (core.resolution_error): with
        # the check off (error_bound=None) it is computed at an infinite bound, never refused
        ebound = self._ebound
        if not ebound > 0.0:
            self._ebound = math.inf
        hook = self.through_refusal
        try:
            while True:
                snap = self.save_state()
                try:
                    self.step(h)
                except EnergyDriftError:
                    raise           # the run's past: no shorter step in its place undoes it
                except StepError as err:
                    if type(err) is NonFiniteError and not self._finite_forces_at_start():
                        # a force that is not finite where every step starts: no shorter step
                        # helps (it would halve down to the smallest step first)
                        self.status = "failed"
                        raise NonFiniteError(err.h, err.iterations, err.solver, err.t,
                                             hint=NONFINITE_AT_START) from None
                    # (the cause quoted without advising adaptive steps to a run that has them)
                    cause = (f"{type(err).__name__}: {err}"
                             .replace(", or adaptive steps (adaptive=True), which shrink through "
                                      "it", "").replace(", or adaptive steps", ""))
                    status, err_est = FAILED_STEP, math.nan
                    if getattr(err, "suggested_h", None) is not None:    # its own estimate
                        status, err_est = NOT_RESOLVED, float(err.estimate)
                    elif hook is not None and isinstance(err, UnresolvedStepError):
                        h_hook, hook = h, None          # (once a step: the host's test costs)
                        self._ebound = ebound
                        try:
                            taken = self.through_refusal(err, h_hook)
                        finally:
                            self._ebound = ebound if ebound > 0.0 else math.inf
                        if taken:
                            return h_hook, h_hook
                else:
                    status, err_est = OK, float(self.counters[C_ERR])
                    b = self.binding
                    if b.follow is not None and b.kin_w.shape[0] == self._gamma.shape[1]:
                        # the test particles, solved apart (core.test_particle_control; the
                        # compiled core's copy on its step: the same numbers, nothing compiled)
                        tpc = (ccore._core.test_particle_control
                               if getattr(b.step_code, "core", False) else test_particle_control)
                        err_est = float(tpc(self._gamma, b.minv, b.kin_w, err_est))
                    cause = f"error estimate {err_est:.3e} > epsilon={epsilon:.3e}"
                # the one controller (core.adapt_step, as loop.attempt calls it)
                accept, h_new, too_small = adapt_step(h, status, err_est, epsilon, s, self.t,
                                                      min_dt)
                if accept:
                    return h, h_new
                if status == OK:
                    self.restore_state(snap)
                self.rejected += 1
                self.status = "running"
                if too_small:
                    self.status = "failed"
                    raise StepSizeError(h, min_dt, self.t, cause)
                h = h_new
        finally:
            self._ebound = ebound

    def _finite_forces_at_start(self) -> bool:
        """The forces (grad H in the full form) at the current state are finite: one
        evaluation, for an adaptive step that failed with non-finite values."""
        b = self.binding
        x = self._y if b.full else self._y[: self._y.size // 2]
        with np.errstate(all="ignore"):
            f = b.rhs(np.array(x, dtype=float)[None])
        return bool(np.all(np.isfinite(f)))

    def step_toward(self, mark: float, h: float, epsilon: float,
                    min_dt: float) -> tuple[float, float]:
        """One adaptive step (:meth:`step_adaptive`) of at most h toward the time ``mark``,
        shortened to land on it exactly (its clock set to ``mark``); returns (the step taken,
        the step to try next: the controller's proposal, or h again after a landing, which
        was shortened by the mark and not by the motion).  Raises
        :class:`integrators.StepSizeError` when h no longer changes t (steps shrinking into a
        singularity).  The one landing rule of :meth:`run_adaptive` and of a host that
        advances by a fixed outer step made of adaptive inner ones (ASE's
        ``HBVMDynamics(adaptive=True)``, as IAS15 with ``exact_finish_time``)."""
        remaining = (mark - self._clock[0]) + self._clock[1]
        last = abs(h) >= abs(remaining)
        if not last and self.t + h == self.t:    # steps shrinking into a singularity
            self.status = "failed"
            raise StepSizeError(h, min_dt, self.t, f"the step proposed, h={h:.3g}, "
                                f"no longer changes t={self.t!r}")
        done, h_next = self.step_adaptive(remaining if last else h, epsilon, min_dt)
        if last and done == remaining:
            self._clock[:] = mark, 0.0          # exactly on the requested time
            return done, h
        return done, h_next

    @_one_thread
    def run_adaptive(self, h: float, t_end: float, epsilon: float, min_dt: float,
                     sample_every: int = 1, sample_times=None) -> "IntegrationResult":
        """Adaptive steps from t to t_end, h the first step tried: samples every
        ``sample_every`` accepted steps, and at each of ``sample_times`` (times between t and
        t_end; the steps are shortened to land on them exactly, and on t_end).  Raises
        :class:`integrators.StepSizeError` when the step proposed no longer changes t (steps
        shrinking into a collision).  Whatever stops the run, the exception carries the
        samples so far in ``result``."""
        sample_every = check_count("sample_every", sample_every, 1)
        t_end = check_real("t_end", t_end, f"a finite time other than t={self.t!r}",
                           lambda x: x != self.t)
        marks = [x for x in check_times("sample_times", sample_times, self.t, t_end)
                 if x != self.t and x != t_end]     # (the run samples its start and its end)
        marks.append(t_end)
        t_start = time.perf_counter()
        ts, ys, es = [], [], []
        hs = []
        n = 0
        sign = 1.0 if t_end >= self.t else -1.0
        h = abs(h) * sign
        try:
            ts.append(self.t)
            ys.append(self._y.copy())
            es.append(self.binding.energy(self._y))
            for mark in marks:
                while (mark - self.t) * sign > 0:
                    done, h = self.step_toward(mark, h, epsilon, min_dt)
                    hs.append(done)
                    n += 1
                    if n % sample_every == 0 or self.t == mark:
                        ts.append(self.t)
                        ys.append(self._y.copy())
                        es.append(self.binding.energy(self._y))
        except StepError as err:
            err.result = self._result(ts, ys, es, h, t_start, "failed", str(err))
            raise
        except BaseException as err:        # the system's own function, numpy, Ctrl-C
            self._stopped(err)
            n = min(len(ts), len(ys), len(es))     # (stopped between the appends of a sample)
            _attach(err, self._result(ts[:n], ys[:n], es[:n], h, t_start, self.status,
                                      f"{type(err).__name__}: {err}"))
            raise
        res = self._result(ts, ys, es, h, t_start, "finished", "")
        res.extra.update(adaptive=True, epsilon=epsilon, rejected=self.rejected,
                         h_min=float(np.min(np.abs(hs))) if hs else float("nan"),
                         h_max=float(np.max(np.abs(hs))) if hs else float("nan"))
        return self._warn_run_error(res)

    # -- private -----------------------------------------------------------------------
    def _warn_run_error(self, res: "IntegrationResult") -> "IntegrationResult":
        """Warn once (AccumulatedErrorWarning) when the run's accumulated estimate has passed
        RUN_ERROR_BOUND; as an error (a warnings filter), it carries ``res`` in ``result``."""
        est = self.error_estimate
        if est > RUN_ERROR_BOUND and not getattr(self, "_run_error_warned", False):
            self._run_error_warned = True
            w = AccumulatedErrorWarning(est, RUN_ERROR_BOUND, self.t)
            w.result = res
            warnings.warn(w, stacklevel=_caller_stacklevel())
        return res

    def _max_iter(self, solver: str) -> int:
        return int(self.max_iter or MAX_ITER[solver])

    def _options(self, solver: str) -> Options:
        """The iteration's options for ``solver`` (:class:`integrators.records.Options`)."""
        return Options(self._max_iter(solver), float(self.tol or 0.0), float(self._etol),
                       self._ebound, self._group)

    def _state_record(self) -> State:
        """The state the step reads and commits (:class:`integrators.records.State`)."""
        return State(self._y, self._cy, self._gamma, self._eref, self._clock)

    def _advance(self, h: float, solver: str) -> int:
        b = self.binding
        if solver == "newton":
            nfev = self.counters[C_NFEV]
            newton = b.newton_matrices(self._y, h, self.counters)
            if newton is None:
                self.counters[C_NFEV] = nfev
                return NOT_FINITE
        else:
            newton = b.no_newton
        status = b.step_code.run(b.system_record, self._state_record(), h,
                                 self._extrapolation(h, self._h_prev), b.method_record,
                                 newton, self._options(solver),
                                 b.work_record(self.counters), self._one_step)
        if status != OK and solver == "newton":
            self.counters[C_NFEV] = nfev     # the Jacobian's evaluations were the failed step's too
        return status

    def _after_step(self, h: float) -> None:
        self._h_prev = h          # the step itself advanced the compensated clock

    def _stopped(self, err: BaseException) -> None:
        """After an exception that is not a :class:`StepError` (the system's own function
        raised, a numpy error, Ctrl-C): the counters back at the last committed step (the
        state and the time are: a step writes them only when it commits) and the status
        "interrupted" (KeyboardInterrupt, SystemExit) or "failed"."""
        self.binding.restore(self.counters)
        self.status = "interrupted" if isinstance(err, (KeyboardInterrupt, SystemExit)) else "failed"

    def _fail(self, status: int, h: float, solver: str) -> None:
        self.status = "failed"
        raise step_error(status, h, self.t, self.counters, solver, energy_tol=self._etol,
                         method=type(self.method).__name__, error_bound=self._ebound,
                         s=self.method.s, hints=self.hints)

    def _result(self, t, y, e, h, t_start, status, message) -> "IntegrationResult":
        self.status = "running" if status == "finished" else status
        y = np.array(y, dtype=float).reshape(len(t), self._y.size)
        return IntegrationResult(np.array(t, dtype=float), y, np.array(e, dtype=float), self.method, h,
                                 self.nsteps, self.nfev, self.niter, self.binding.name,
                                 time.perf_counter() - t_start, self.newton_steps,
                                 self.solver_switches, status=status, message=message,
                                 error_estimate=self.error_estimate)


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
        "finished"; or "failed" (a failed step, or an exception from the system's own
        function) or "interrupted" (KeyboardInterrupt, SystemExit), with the exception's
        message: a stopped :func:`integrate` raises that exception and carries this result,
        the samples up to the last committed step, in its ``result``.
    error_estimate : float
        The run's accumulated error estimate at its end (:attr:`Stepper.error_estimate`): the
        steps' own estimates (and the phase the energy's drift makes, for a method that does
        not keep H), each times the share of its body's motion the step turned, summed; the error relative to the motion's scale (an orbit's radius) of a run whose
        steps' errors add (a periodic orbit's phase), a lower bound for a chaotic one.  A run
        that ends above :data:`integrators.core.RUN_ERROR_BOUND` (1e-2) is warned about once
        (:class:`integrators.AccumulatedErrorWarning`).
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
    error_estimate: float = float("nan")

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


#: adaptive steps: the bound on each step's estimated local error relative to the motion over
#: the step (core.resolution_error, the quantity core.adapt_step controls); measured
#: (benchmarks/bench_defaults.py, 9 starts): with s = 6 (k = 8 from kchoice.adaptive_k) REBOUND's
#: outer solar system over 1000 Jupiter years at 1.1x IAS15's energy error (3.1e-15) in 17959
#: steps; 1e-14 took 16307 steps to 1.6x (4.5e-15), the bar being 1.5x; HLW's over 1e6 days
#: at 2x IAS15's position error (1e-14: 2.1x)
DEFAULT_EPSILON = 3e-15


def check_adaptive(epsilon, min_dt, s: int) -> tuple[float, float]:
    """(epsilon, min_dt) checked for an adaptive run of a method with s blocks."""
    if isinstance(epsilon, bool) or not isinstance(epsilon, (int, float, np.number)) \
            or not (np.isfinite(epsilon) and 0 < epsilon < 1):
        raise ValueError(f"`epsilon` must be a number in (0, 1) (got epsilon={epsilon!r}); "
                         f"it bounds each adaptive step's estimated local error relative to the "
                         f"motion over the step; the default is {DEFAULT_EPSILON:g}")
    if min_dt is None:
        min_dt = 0.0
    if isinstance(min_dt, bool) or not isinstance(min_dt, (int, float, np.number)) \
            or not (np.isfinite(min_dt) and min_dt >= 0):
        raise ValueError(f"`min_dt` must be a finite number >= 0 (got min_dt={min_dt!r})")
    return float(epsilon), float(min_dt)


def integrate(method, system, y0, h: float, steps: int | None = None, *, t0: float = 0.0,
              solver: str = "auto", sample_every: int = 1, fast: bool | None = None,
              tol: float | None = None, max_iter: int | None = None, form: str = "auto",
              energy_tol: float | str | None = "auto",
              error_bound: float | str | None = "auto", adaptive: bool = False,
              t_end: float | None = None, epsilon: float | None = None,
              min_dt: float | None = None, sample_times=None, variational=None) -> IntegrationResult:
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
        (default 0) and while t + h != t (else :class:`integrators.StepSizeError`).
    epsilon : float
        The precision of adaptive steps, in (0, 1): a bound on each step's own estimate of its
        local error relative to the motion over the step (:func:`integrators.core.
        resolution_error`, the estimate the step's resolution check bounds by
        ``error_bound``; no extra evaluation for k > s, one for k = s), the same accuracy
        whatever s is.  A step is accepted when its estimate is at most epsilon; the next one
        is proposed at 0.7 of the step that would reach epsilon, h (epsilon / err)^(1/(2s+1))
        (:func:`integrators.core.next_step`: an order-2s step errs like h^(2s+1)).  Over a
        fixed time the error of the solution (positions, phases) is about epsilon times the
        number of steps or less (measured on Kepler e = 0.6 over one period: s = 1 at 1e-9,
        5828 steps, 4.8e-6; s = 6, 20 steps, 6.3e-11; ``benchmarks/bench_adaptive_steps.py``
        compares each s with the fewest fixed steps that reach its error).  The energy stays
        at round-off whatever the steps (HBVM conserves H at any step size once k is large
        enough: :func:`integrators.kchoice.adaptive_k`).  The default, 3e-15 for s = 6 (k = 8),
        gives IAS15's energy error (1.1x) and 2x its position error on the outer solar system
        in about 0.6-0.7 of its time (``benchmarks/bench_defaults.py``).  (Until issue 58 epsilon
        bounded the highest force coefficient, IAS15's quantity, whose meaning changed with s:
        epsilon = 1e-3 at s = 6 took about the steps 3e-15 takes now.)
        The default (None) is DEFAULT_EPSILON.
    t_end, sample_times
        Adaptive runs end exactly at t_end and also land exactly on each of sample_times.
        A fixed-step run (``adaptive=False``) takes ``steps`` and ``sample_every`` instead:
        ``t_end``, ``sample_times``, ``epsilon`` and ``min_dt`` given to it are refused with
        a ValueError naming the argument (they would be ignored).
    variational : array_like, shape (2m,) or (nv, 2m), optional
        Initial tangent vectors, carried by the Jacobian of each step; the result's ``extra``
        then holds them at the samples and the MEGNO (:mod:`integrators.variational`).
    others
        As for :class:`Stepper`.

    Raises
    ------
    StepError
        A step failed; ``err.result`` holds the samples up to the last committed step.
        (:class:`integrators.StepSizeError` when adaptive steps shrink below ``min_dt`` or
        below what the time can resolve.)
    Exception, KeyboardInterrupt
        Raised by the system's own functions, numpy, or Ctrl-C: it reaches the caller as
        itself, with ``err.result`` holding the samples up to the last committed step
        (``status`` "failed", or "interrupted" for KeyboardInterrupt and SystemExit).
    """
    h = check_step(h)
    check_method(method)
    if variational is not None:
        Stepper_ = VARIATIONAL[0](variational)
    else:
        Stepper_ = Stepper
    if adaptive:
        if steps is not None:
            raise ValueError("give `t_end` (not `steps`) with adaptive=True: the number of "
                             "steps is what the control chooses")
        t0f = check_real("t0", t0, "a finite number")
        t_end = check_real("t_end", t_end, "a finite time other than t0 with adaptive=True",
                           lambda x: x != t0f)
        epsilon, min_dt = check_adaptive(DEFAULT_EPSILON if epsilon is None else epsilon,
                                         min_dt, method.s)
        sample_every = check_count("sample_every", sample_every, 1)
        st = Stepper_(method, system, y0, t0, solver, tol, max_iter, form, fast, energy_tol,
                      error_bound=error_bound)
        return st.run_adaptive(h, t_end, epsilon, min_dt, sample_every, sample_times)
    for name, value, fix in (
            ("t_end", t_end, "give steps = round((t_end - t0) / h), or adaptive=True to end "
                             "exactly at t_end"),
            ("sample_times", sample_times, "give sample_every (samples every that many "
                                           "steps), or adaptive=True to land on each time"),
            ("epsilon", epsilon, "it sets the precision of adaptive steps: pass adaptive=True, "
                                 "or leave it out for fixed steps of size h"),
            ("min_dt", min_dt, "it bounds adaptive steps: pass adaptive=True, or leave it out "
                               "for fixed steps of size h")):
        if value is not None:
            raise ValueError(f"`{name}` is an option of adaptive runs; a fixed-step run "
                             f"(adaptive=False) would ignore it (got {name}={value!r}): {fix}")
    if steps is None:
        raise ValueError("`steps` is required without adaptive=True")
    steps = check_count("steps", steps, 0)
    sample_every = check_count("sample_every", sample_every, 1)
    st = Stepper_(method, system, y0, t0, solver, tol, max_iter, form, fast, energy_tol,
                  error_bound=error_bound)
    return st.run(h, steps, sample_every)
