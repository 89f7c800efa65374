"""HBVM(k, s) as an integrator that REBOUND drives.

How it attaches
---------------
``sim.integrator = "none"`` makes REBOUND advance only the time (t += dt, dt_last_done = dt);
a post-timestep callback then advances the particles by ``sim.dt_last_done`` with one step of
the project's single step core (:mod:`integrators.loop`, compiled with the N-body kernel called
statically, see :mod:`integrators.specialise`).  Everything REBOUND
does around a step (``exact_finish_time``'s shrunken last step, heartbeats, ``steps_done``,
simulation archives, ``sim.energy()``) is REBOUND's own.

One step is one compiled call, :func:`hbvm_md.rebound_step.host_step`, compiled in the same
module as the core's step: have the particles changed? the core's step on trial arrays
(retried smaller when adaptive), then the commit of state, particles, time and bookkeeping.
It is called in one of two ways:

* **natively** (the default): for the time of one ``sim.integrate`` / ``sim.steps``, the
  post-timestep slot holds the C callback :func:`hbvm_md.rebound_step.host_cstep` and
  ``sim.extras`` the address of the driver's ``ctx`` (the arrays' addresses and sizes): no
  Python runs between steps.  A failed step puts ``sim.t`` back and stops REBOUND; the driver
  then raises, or, when the particles changed (a REBOUND-side change), re-reads them and goes
  on.  Measured on one planet at e = 0.9: 7.7 us a step against 16.8 with three compiled calls
  from a Python callback;
* **through the Python callback** when Python must run between steps: a heartbeat, a chained
  post-timestep callback, a pre-timestep callback, or ``sim.extras`` in use by someone else.
  The callback makes the same compiled call with one argument (``ctx``), the same numbers bit
  for bit.

This module holds host glue only; no numerics.

State between steps
-------------------
The driver keeps its own state: positions q with their Kahan compensation, momenta p = m v for
gravitating bodies (v for test particles, see :mod:`systems.nbody`) with theirs, and the previous
step's coefficients gamma (the initial guess of the next step by extrapolation).  Each step it
compares the particles REBOUND holds with what it wrote last time (a zero-copy numpy view over
REBOUND's particle array, no Python loop over particles); only when they differ (the user moved,
added or removed a particle, changed a mass or G) does it re-read the state, and the
compensations and gamma start afresh.  So REBOUND's doubles never throw away the compensated
bits, and p is not rebuilt from v every step.

Errors
------
ctypes prints and swallows an exception raised in a callback.  The callback therefore catches
it, restores the particles and ``sim.t`` to their values before the failed step, and calls
``sim.stop()``; the attached simulation's class is swapped for a subclass whose ``integrate``
and ``steps`` re-raise the stored exception after REBOUND returns.  (``sim.steps_done`` has
already counted the failed step: REBOUND increments it after the callback.)

An exception raised by a Python signal handler (SIGALRM, SIGTERM turned into SystemExit) lands
between any two bytecodes of the Python callback; in a native run, only after REBOUND returns.
The compiled step commits the state, the particles, sim.t and the bookkeeping in one call, so
the callback tells a committed step (sim.t is the time the step wrote) from one not taken
(REBOUND's t += h undone).  One raised on
entering the callback, before its ``try``, is handed by ctypes to ``sys.unraisablehook``; the
driver installs its own for the time of a run through the Python callback (a native run has no
Python callback).  The tests fire random SIGALRMs at both ways
of running a step (tests/test_rebound_workflows.py): all leave whole steps.

Copies and restarts
-------------------
``sim.copy()`` is driven by a new HBVMIntegrator with the same settings and state;
:meth:`HBVMIntegrator.save` and :meth:`HBVMIntegrator.load` write and read REBOUND's binary
plus HBVM's state (``path + ".hbvm.npz"``): both continue bit for bit like the original.
"""
from __future__ import annotations

import contextlib
import ctypes
import math
import numbers
import sys
import warnings
import weakref

import numpy as np
from numba import carray

from hbvm_md import rebound_step as glue
from hbvm_md.rebound_step import RESYNC
from integrators import HBVM, StepError
from integrators.core import C_ITER, C_NFEV, OK, N_COUNTERS, TOO_SMALL
from integrators.engine import DEFAULT_EPSILON, Binding, Counted, Extrapolation, check_adaptive
from integrators.errors import StepSizeError, step_error
from integrators.jit import entry_point, jit
from integrators.kchoice import adaptive_k, choose_k, period_steps
from integrators.pointers import call_int32_voidptr_double, int64_pointer
from systems.nbody import NBody, shortest_r3_over_m

_REGISTRY: "weakref.WeakValueDictionary[int, HBVMIntegrator]" = weakref.WeakValueDictionary()
# struct reb_simulation fields whose values _before_run checks (settings HBVM cannot honour,
# the integrator and callback it owns while attached)
_CONFIG_FIELDS = ("integrator", "_post_timestep_modifications", "softening", "_additional_forces",
                  "_collision", "N_var", "_gravity", "_boundary", "_N_odes", "testparticle_type",
                  "N_active", "N")
# and the fields :meth:`HBVMIntegrator._native` reads (the callbacks that need Python between
# steps, the particles' address): while all these bytes are unchanged its answer is too
_NATIVE_FIELDS = ("_heartbeat", "_pre_timestep_modifications", "extras", "_particles")
_CFG_IDX: dict = {}        # the byte indices of those fields, by Simulation class
_DOUBLES_PER_PARTICLE = glue.PARTICLE_DOUBLES       # sizeof(reb_particle) = 112 bytes


def _layout_is_known(rebound) -> bool:
    """Are the struct offsets :mod:`hbvm_md.rebound_step` was written for those of this
    REBOUND?"""
    S, P = rebound.Simulation, rebound.Particle
    at = {"t": glue.T_AT, "G": glue.G_AT, "dt": glue.DT_AT, "dt_last_done": glue.DTL_AT,
          "steps_done": glue.STEPS_AT,
          "N": glue.N_AT, "_particles": glue.PTR_AT, "N_active": glue.NA_AT}
    return (all(getattr(S, f).offset == 8 * i for f, i in at.items())
            and S._status.offset == glue.STATUS_BYTES and S.extras.offset == glue.EXTRAS_BYTES
            and ctypes.sizeof(P) == 8 * glue.PARTICLE_DOUBLES and P.m.offset == 72
            and P.x.offset == 0 and P.vx.offset == 24)


def _rebound():
    import rebound
    return rebound


def _make_class():
    rebound = _rebound()

    class HBVMSimulation(rebound.Simulation):
        """A ``rebound.Simulation`` driven by :class:`HBVMIntegrator` (same memory layout).

        ``integrate`` and ``steps`` check the simulation before running and re-raise an
        exception raised inside the HBVM step.
        """

        __slots__ = ()

        def integrate(self, tmax, exact_finish_time=1):
            drv = _REGISTRY.get(ctypes.addressof(self))
            if drv is None:
                return super().integrate(tmax, exact_finish_time)
            drv._run(None, tmax, exact_finish_time)      # REBOUND's integrate

        def steps(self, N_steps):
            drv = _REGISTRY.get(ctypes.addressof(self))
            if drv is None:
                return super().steps(N_steps)
            drv._run(_steps, N_steps)

        def copy(self):
            """A deep copy driven by its own :class:`HBVMIntegrator` with the same settings and
            state (compensations and coefficients included): both continue bit for bit alike.
            Like REBOUND's ``copy``, the user's callbacks (heartbeat, a chained
            post-timestep callback) are not carried over; get the copy's driver with
            :meth:`HBVMIntegrator.of`."""
            with _pointers_are_reset():
                new = super().copy()
            drv = _REGISTRY.get(ctypes.addressof(self))
            if drv is not None:
                drv._clone_onto(new)
            return new

    # what HBVMIntegrator._run calls for sim.steps: REBOUND's own method, ``done`` steps taken
    # already (a function made once and its arguments, not a lambda and super() at each call:
    # 0.3 us); sim.integrate calls HBVMIntegrator._reb_integrate
    base = rebound.Simulation

    def _steps(sim, done, N_steps):
        base.steps(sim, N_steps - done)

    return HBVMSimulation


_REB_INTEGRATE = None
# what reb_simulation_integrate's return value means (REBOUND's enum REB_STATUS): the exception
# rebound.Simulation.integrate raises for it; it raises none for 0 (success), 5 (REB_STATUS_USER,
# a stop asked for) and any other value, and neither does HBVMIntegrator
_REB_ERRORS = {1: ("GenericError", "An error occurred during the integration."),
               2: ("NoParticles", "No more particles left in simulation."),
               3: ("Encounter", "Two particles had a close encounter (d<exit_min_distance)."),
               4: ("Escape", "A particle escaped (r>exit_max_distance)."),
               7: ("Collision", "Two particles collided (d < r1+r2)")}


def _reb_integrate_fn():
    """REBOUND's C ``reb_simulation_integrate(struct reb_simulation*, double)`` as a ctypes
    function of our own (the address and a float in, the status out), made once."""
    global _REB_INTEGRATE
    if _REB_INTEGRATE is None:
        lib = _rebound().clibrebound
        proto = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_double)
        _REB_INTEGRATE = proto(ctypes.cast(lib.reb_simulation_integrate, ctypes.c_void_p).value)
    return _REB_INTEGRATE


@jit(nogil=True)
def _integrate_native(a, tmax):
    """A native run as one compiled call: REBOUND's post-timestep slot and ``extras`` set to the
    compiled step and its ``ctx``, ``reb_simulation_integrate(sim, tmax)``, the slots set back
    to the Python callback; returns REBOUND's status.  a (int64): the function's address, the
    simulation's, the two slots' addresses, their values for the run, then after it.  No Python
    bytecode runs between the three (a signal's exception lands after them), and the GIL is
    released for the run, as ctypes released it.  It replaces a numpy assignment, a ctypes call
    and a second assignment, and with them about 1.3 us of a ``sim.integrate`` call."""
    slot_a = carray(int64_pointer(a[2]), 1)
    slot_b = carray(int64_pointer(a[3]), 1)
    slot_a[0] = a[4]
    slot_b[0] = a[5]
    status = call_int32_voidptr_double(a[0], a[1], tmax)
    slot_a[0] = a[6]
    slot_b[0] = a[7]
    return status


_NATIVE_CALL = _UNSET = object()


def _integrate_native_fn():
    """:func:`_integrate_native`'s compiled entry point (its one signature compiled, or loaded
    from the cache, on first use), or None when nothing is compiled (NUMBA_DISABLE_JIT: then
    :meth:`HBVMIntegrator._native` says no native run)."""
    global _NATIVE_CALL
    if _NATIVE_CALL is _UNSET:
        _NATIVE_CALL = None
        if hasattr(_integrate_native, "compile"):
            _integrate_native.compile("int32(int64[::1], float64)")
            _NATIVE_CALL = entry_point(_integrate_native)
    return _NATIVE_CALL


def _reb_status_error(sim, status: int) -> BaseException:
    """The exception ``rebound.Simulation.integrate`` raises for the C call's ``status``."""
    if status == 6:                       # REB_STATUS_SIGINT
        return KeyboardInterrupt()
    rebound = _rebound()
    if status == 1:
        sim.process_messages()            # an error message of REBOUND's is raised from there
    if status == 2 and sim._N_odes > 0:
        return rebound.NoParticles("No particles found. Will exit. Use BS integrator to "
                                   "integrate user-defined ODEs without any particles present.")
    name, message = _REB_ERRORS[status]
    return getattr(rebound, name)(message)


_SIM_CLASS = None
_ENTRIES: dict = {}        # compiled entry points, once known (see _entry)
_HINTS = {"diverged": "try a smaller sim.dt or a larger max_iter",
          "not_finite": "try a smaller sim.dt, and check for particles at the same position",
          "unresolved": "use a smaller sim.dt (or IAS15 for close encounters), or pass "
                        "energy_tol=None to accept such steps"}


def _entry(dispatcher):
    """The compiled entry point of a step function once it has been compiled: later calls skip
    numba's argument typing (several microseconds with this many arguments) and its Python code
    (where an exception raised by a signal handler would be turned into another one)."""
    fn = _ENTRIES.get(dispatcher)
    if fn is None:
        fn = entry_point(dispatcher)
        if fn is not dispatcher:
            _ENTRIES[dispatcher] = fn
    return fn


@contextlib.contextmanager
def _pointers_are_reset():
    # REBOUND warns that a copied or loaded simulation needs its function pointers set again:
    # HBVMIntegrator sets its own, so the warning would only mislead
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="You have to reset function pointers",
                                category=RuntimeWarning)
        yield


def _sim_class():
    global _SIM_CLASS
    if _SIM_CLASS is None:
        _SIM_CLASS = _make_class()
    return _SIM_CLASS


def check_simulation(sim) -> None:
    """Raise ValueError if ``sim`` uses something HBVMIntegrator cannot honour."""
    problems = []
    if sim.softening != 0.0:
        problems.append(f"softening={sim.softening!r} (HBVM integrates plain Newtonian gravity; "
                        "set sim.softening = 0)")
    if bool(sim._additional_forces):
        problems.append("additional_forces is set (not part of the separable Hamiltonian; "
                        "remove it or use a REBOUND integrator)")
    if sim.collision != "none":
        problems.append(f"collision={sim.collision!r} (set sim.collision = 'none')")
    if sim.N_var > 0:
        problems.append(f"{sim.N_var} variational particles (not supported; remove them or use "
                        "WHFast/IAS15)")
    if sim.gravity not in ("basic", "compensated"):
        problems.append(f"gravity={sim.gravity!r} (only direct summation 'basic' or "
                        "'compensated' is honoured)")
    if sim.boundary != "none":
        problems.append(f"boundary={sim.boundary!r} (set sim.boundary = 'none')")
    if sim._N_odes > 0:
        problems.append(f"{sim._N_odes} user ODEs attached (integrated by BS only)")
    N, na = sim.N, sim.N_active
    if sim.testparticle_type != 0 and 0 <= na < N:
        problems.append("testparticle_type=1 (massive test particles acting on active bodies "
                        "are not a Hamiltonian system; use testparticle_type = 0)")
    if problems:
        raise ValueError("HBVMIntegrator cannot honour this simulation: " + "; ".join(problems))


def _real(name: str, value) -> float:
    """``value`` as a float, or TypeError naming ``name`` (bools and strings are not numbers)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"`{name}` must be a real number (got {name}={value!r})")
    return float(value)


def _step_size(name: str, value) -> float:
    h = _real(name, value)
    if not (math.isfinite(h) and h != 0.0):
        raise ValueError(f"`{name}` must be a nonzero finite step size (got {name}={value!r}); "
                         "set it to the step you want, e.g. a fraction of the shortest period")
    return h


def check_particles(y: np.ndarray, model: NBody) -> None:
    """Raise ValueError when the state y = (q, p) of ``model`` is not finite, or when two
    particles of which one gravitates share a position (their force is infinite); the
    message names the particles by their index in ``sim.particles``."""
    if not np.all(np.isfinite(y)):
        raise ValueError("the simulation holds non-finite positions or velocities")
    x = np.asarray(y[: model.dim]).reshape(-1, 3)
    order = np.lexsort(x.T[::-1])
    xs = x[order]
    same = np.all(xs[1:] == xs[:-1], axis=1)        # sorted neighbours that coincide
    for i in np.flatnonzero(same):
        members = np.flatnonzero(np.all(x == xs[i], axis=1))
        if np.any(model.is_source[members]):
            raise ValueError(
                f"particles {', '.join(map(str, members))} are at the same position "
                f"{tuple(map(float, xs[i]))}: the force between them is infinite; remove one "
                "of them or move it")


def shortest_period(sim) -> float:
    """The shortest two-body orbital period 2 pi sqrt(r^3 / (G M)) over pairs with a
    gravitating member, from the current positions (a crude time scale of the scene).
    ``sim``: a ``rebound.Simulation`` or the :class:`systems.NBody` read from one."""
    nb = sim if isinstance(sim, NBody) else NBody.from_rebound(sim)
    g = np.where(nb.is_source, nb.body_masses, 0.0)
    return 2 * math.pi * math.sqrt(shortest_r3_over_m(np.ascontiguousarray(nb.positions), g) / nb.G)


class HBVMIntegrator(Counted):
    """Attach HBVM(k, s) to a ``rebound.Simulation`` so that REBOUND drives it.

    Parameters
    ----------
    sim : rebound.Simulation
        Plain Newtonian gravity (no softening, additional forces, collisions, variational
        particles; gravity 'basic' or 'compensated'); test particles (``N_active``,
        ``testparticle_type = 0``) are honoured.
    s : int
        Degree of the method (order 2s).
    k : int, optional
        Quadrature nodes (k >= s).  None: measured on the scene at attach time for ``sim.dt``
        (:func:`integrators.kchoice.choose_k` over one shortest orbital period) with
        a fixed step, :func:`integrators.kchoice.adaptive_k` (9 for the defaults) with adaptive
        steps.
    dt : float, optional
        Sets ``sim.dt`` (the nominal step; REBOUND may shrink the last one).
    max_iter : int
        Fixed-point iterations allowed per step.
    tol : float, optional
        Relative tolerance of the iteration; None iterates to round-off.
    nodes : {"gauss", "lobatto"}
        Quadrature of the line integral.
    adaptive : bool or None
        Step-size control (None, the default: adaptive unless ``dt`` is given, as with IAS15).
        Each step's error estimate, the weight of its last Legendre coefficient
        max|gamma_(s-1)| / max|gamma_0| (no extra force evaluation), is kept below ``epsilon``;
        a step whose estimate, iteration or energy check fails is retried smaller within the
        same REBOUND step, which then records the step taken (``sim.t``,
        ``sim.dt_last_done``); ``sim.dt`` shows the next step proposed.  HBVM conserves the
        energy at any step size, so changing it costs nothing in energy.
    epsilon : float
        Precision of the adaptive control (dimensionless, like IAS15's); the default gives
        round-off energy error on the scenes of the README.
    min_dt : float
        Smallest step the adaptive control may take; below it a step that cannot be resolved
        raises :class:`integrators.StepSizeError`.
    energy_tol : float or None
        A step that changes the energy of the gravitating bodies by more than this, relative to
        |T| + |V|, is refused with :class:`integrators.UnresolvedStepError` (nothing committed).
        HBVM at round-off k changes it by about 1e-16 a step; a step that does not resolve the
        motion (two bodies passing within a fraction of a step, or a spurious root of the
        nonlinear system found after many iterations) changes it visibly, and would otherwise
        pass silently.  The check costs one potential evaluation a step.  None disables it.

    Attributes
    ----------
    method : HBVM
    nsteps, nfev, niter : int
        Steps, force evaluations (stages) and fixed-point iterations done by this driver.
    resyncs : int
        How often the state was re-read from REBOUND (1 at the first step).
    last_run_native : bool
        Whether the last ``sim.integrate`` / ``sim.steps`` ran the step as a C callback (no
        Python between steps): the default; a heartbeat, a chained post-timestep callback, a
        pre-timestep callback or ``sim.extras`` in use make the run go through the Python
        callback instead (about 5 us more a step; the same numbers bit for bit).

    Notes
    -----
    After attaching, use ``sim.integrate(t)``, ``sim.steps(n)`` and the rest of REBOUND as
    usual.  An exception in a step (``ConvergenceError``, non-finite state, a refused setting)
    stops the run, leaves the particles and ``sim.t`` as before that step and is raised by
    ``sim.integrate``; so does an exception raised by a signal handler, with the particles and
    ``sim.t`` at a whole number of committed steps.  :meth:`detach` restores the previous
    integrator and callback.  ``sim.copy()`` carries its own HBVMIntegrator (:meth:`of`);
    :meth:`save` / :meth:`load` restart a run bit for bit.  A scene with at most one
    gravitating body, at rest (the restricted problem with a star at rest), has no energy to
    check: ``energy_tol`` is then ignored with a RuntimeWarning.
    """

    def __init__(self, sim, s: int = 6, k: int | None = None, dt: float | None = None,
                 max_iter: int = 60, tol: float | None = None, nodes: str = "gauss",
                 energy_tol: float | None = 1e-10, adaptive: bool | None = None,
                 epsilon: float = DEFAULT_EPSILON, min_dt: float = 0.0):
        # Everything is checked before anything is changed: a failed attach leaves sim as it was.
        rebound = _rebound()
        if not isinstance(sim, rebound.Simulation):
            raise TypeError(f"`sim` must be a rebound.Simulation (got {type(sim).__name__})")
        if not rebound.__version__.startswith("5.") or not _layout_is_known(rebound):
            raise RuntimeError(f"HBVMIntegrator supports REBOUND 5.x (its particle layout) only; got rebound {rebound.__version__}: pip install 'rebound>=5.0,<6'")
        if ctypes.addressof(sim) in _REGISTRY:
            raise ValueError("an HBVMIntegrator is already attached to this simulation; call "
                             "its detach() first")
        method = HBVM(s if k is None else k, s, nodes=nodes)    # checks s, k and nodes
        if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
            raise ValueError(f"`max_iter` must be a positive integer (got max_iter={max_iter!r})")
        if tol is not None and not 0 < _real("tol", tol) < 1:
            raise ValueError(f"`tol` must be None (round-off) or in (0, 1) (got tol={tol!r})")
        if energy_tol is not None and not 0 < _real("energy_tol", energy_tol) < math.inf:
            raise ValueError(f"`energy_tol` must be a positive number or None (got "
                             f"energy_tol={energy_tol!r}); None switches the energy check off")
        if adaptive is None:
            adaptive = dt is None      # like IAS15: no step to choose unless one is given
        if not isinstance(adaptive, (bool, np.bool_)):
            raise TypeError(f"`adaptive` must be True, False or None (got adaptive={adaptive!r})")
        epsilon, min_dt = check_adaptive(epsilon, min_dt, method.s) if adaptive else (epsilon, min_dt)
        check_simulation(sim)
        if dt is not None:
            h = _step_size("dt", dt)
        elif adaptive:
            # the first step tried: the controller takes it from there
            period = shortest_period(sim) if sim.N > 1 else math.inf
            h = period / 50 if math.isfinite(period) else _step_size("sim.dt", sim.dt)
            h = math.copysign(h, sim.dt) if sim.dt != 0 else h
        else:
            h = _step_size("sim.dt", sim.dt)
        nb = None
        if k is None and adaptive:
            # the steps vary (pericentres, encounters): no single step to probe k on
            method = HBVM(adaptive_k(method.s, epsilon), method.s, nodes=nodes)
        elif k is None and sim.N > 1:
            nb = NBody.from_rebound(sim)
            y0 = nb.initial_state()
            check_particles(y0, nb)
            steps = period_steps(shortest_period(nb), h)
            method = HBVM(choose_k(nb, y0, method.s, h, steps, solver="fixed_point").k,
                          method.s, nodes=nodes)
        self._attach(sim, method, h, int(max_iter), tol, energy_tol)
        self._set_control(bool(adaptive), epsilon, min_dt)
        self._premodel = nb     # the first run's model, while the particles are still these

    def _attach(self, sim, method: HBVM, h: float, max_iter: int, tol, energy_tol) -> None:
        self.method = method
        self.sim = sim
        # the scalars the compiled step reads and writes (layout: rebound_step.S_*)
        self._scal = np.zeros(glue.N_SCAL)
        self._scal[[glue.S_H_PREV, glue.S_T_WRITTEN]] = np.nan
        self._energy_check = True
        self.max_iter, self.tol = max_iter, tol
        self.energy_tol = energy_tol
        self._eref = np.full(1, np.nan)    # energy after the last committed step (nan: unknown)
        m = self.method
        self._extrapolation = Extrapolation(m)
        self.counters = np.zeros(N_COUNTERS)   # the core's counters, over the driver's life
        self._clock = np.zeros(2)               # the core ticks it; REBOUND keeps the time
        self.resyncs = 0
        self.last_run_native = False
        self._allow_native = True       # False: always the Python callback (tests, debugging)
        self._error = None
        self._hook_prev = None
        self._addr = ctypes.addressof(sim)
        # the head of struct reb_simulation (t .. N_active) as doubles and as int64
        head = (ctypes.c_double * glue.SIM_HEAD).from_address(self._addr)
        self._simd = np.frombuffer(head, dtype=np.float64)
        self._simi = np.frombuffer(head, dtype=np.int64)
        self._steps_done = ctypes.c_int64.from_address(self._addr + 8 * glue.STEPS_AT)
        S = type(sim)
        self._extras_c = ctypes.c_void_p.from_address(self._addr + S.extras.offset)
        self._exact_finish = ctypes.c_int.from_address(self._addr + S.exact_finish_time.offset)
        self._messages = ctypes.c_void_p.from_address(self._addr + S.messages.offset)
        self._reb_call = _reb_integrate_fn()
        self._native_call = _integrate_native_fn()
        # the bytes of the settings _before_run checks (integrator, callbacks, gravity, ...):
        # while they are those of the last run that passed, the checks are not read again
        # field by field (about 8 us a sim.integrate call, which 200 outputs pay 200 times)
        self._cfg_idx = _CFG_IDX.get(S)
        if self._cfg_idx is None:
            self._cfg_idx = _CFG_IDX[S] = np.concatenate(
                [np.arange(getattr(S, f).offset, getattr(S, f).offset + getattr(S, f).size)
                 for f in _CONFIG_FIELDS + _NATIVE_FIELDS])
        self._cfg_bytes = np.frombuffer((ctypes.c_uint8 * ctypes.sizeof(S)).from_address(self._addr),
                                        dtype=np.uint8)
        self._cfg_ok = None
        self._native_key = None     # (config, ctx, allow_native) of the last _native() answer
        self._native_last = False
        self._view_key = None
        self._view = None
        self._gamma = None
        self._ctx = None            # addresses and sizes for the compiled step (rebound_step)
        self._written = None        # (N, 7): x, y, z, vx, vy, vz, m as written last step
        self._premodel = None       # see __init__ and _model
        # remember what to restore on detach
        self._prev_integrator = str(sim.integrator)
        # A ctypes function-pointer field read from the struct shares the struct's memory, so
        # keep the pointer's value (and a fresh callable built from it), not the field object.
        self._ptm_slot = ctypes.c_void_p.from_address(
            self._addr + type(sim)._post_timestep_modifications.offset)
        self._prev_ptm = self._ptm_slot.value
        self._prev_ref = getattr(sim, "_posttmp", None)
        self._prev_class = type(sim)
        self._chain = (type(sim._post_timestep_modifications)(self._prev_ptm)
                       if self._prev_ptm else None)
        # the post-timestep callback slot and the extras pointer, set together around a native
        # run with no Python bytecode between them: inside one compiled call for sim.integrate
        # (_integrate_native), by one numpy assignment for sim.steps (see _run)
        first = type(sim)._post_timestep_modifications.offset
        n = (type(sim).extras.offset - first) // 8 + 1
        self._slots = np.frombuffer((ctypes.c_int64 * n).from_address(self._addr + first),
                                    dtype=np.int64)
        self._slot_idx = np.array([0, n - 1])
        sim.dt = h
        sim.integrator = "none"
        sim.post_timestep_modifications = self._callback
        self._cb_ptr = ctypes.cast(sim._post_timestep_modifications, ctypes.c_void_p).value
        # _integrate_native's arguments: REBOUND's integrate, the simulation, the two slots,
        # their values during a native run (set with ctx, see _arrays) and after it; a native
        # sim.steps sets the slots from the same two pairs (views)
        self._nat = np.array([ctypes.cast(self._reb_call, ctypes.c_void_p).value, self._addr,
                              self._addr + first, self._addr + first + 8 * (n - 1), 0, 0,
                              self._cb_ptr, 0], dtype=np.int64)
        self._native_slots, self._python_slots = self._nat[4:6], self._nat[6:8]
        sim.__class__ = _sim_class()
        _REGISTRY[self._addr] = self
        self.attached = True

    # the bookkeeping lives in the scalars the compiled step updates
    @property
    def nsteps(self) -> int:
        """Steps committed by this driver."""
        return int(self._scal[glue.S_NSTEPS])

    @property
    def rejected(self) -> int:
        """Adaptive trial steps rejected (and retried smaller)."""
        return int(self._scal[glue.S_REJECTED])

    @property
    def adaptive(self) -> bool:
        return bool(self._scal[glue.S_EPSILON] > 0.0)

    @property
    def epsilon(self) -> float:
        return self._epsilon

    @property
    def max_iter(self) -> int:
        """Fixed-point iterations allowed per step (settable between runs)."""
        return int(self._scal[glue.S_MAX_ITER])

    @max_iter.setter
    def max_iter(self, value: int) -> None:
        self._scal[glue.S_MAX_ITER] = int(value)

    @property
    def tol(self) -> float:
        """Relative tolerance of the iteration (0: round-off)."""
        return float(self._scal[glue.S_TOL])

    @tol.setter
    def tol(self, value: float) -> None:
        self._scal[glue.S_TOL] = float(value or 0.0)

    @property
    def energy_tol(self) -> float | None:
        """The energy check's tolerance (None: off); settable between runs."""
        return self._energy_tol

    @energy_tol.setter
    def energy_tol(self, value: float | None) -> None:
        self._energy_tol = value
        self._scal[glue.S_ETOL] = (value or 0.0) if self._energy_check else 0.0

    def _set_control(self, adaptive: bool, epsilon: float, min_dt: float) -> None:
        self._epsilon, self.min_dt = float(epsilon), float(min_dt)
        self._scal[glue.S_EPSILON] = self._epsilon if adaptive else 0.0
        self._scal[glue.S_MIN_DT] = self.min_dt

    def __repr__(self) -> str:
        return f"HBVMIntegrator({self.method!r}, attached={self.attached}, nsteps={self.nsteps})"

    # -- public ------------------------------------------------------------------------
    def integrate(self, tmax: float, exact_finish_time: int = 1) -> None:
        """``sim.integrate(tmax, exact_finish_time)``."""
        self.sim.integrate(tmax, exact_finish_time)

    def detach(self) -> None:
        """Give the simulation back: previous integrator, post-timestep callback and class."""
        if not self.attached:
            return
        sim = self.sim
        _REGISTRY.pop(self._addr, None)
        sim.__class__ = self._prev_class
        sim.integrator = self._prev_integrator
        self._ptm_slot.value = self._prev_ptm          # the user's callback, or NULL
        if self._prev_ref is not None:
            sim._posttmp = self._prev_ref              # keeps the user's callback alive
        self.attached = False
        self._view = None

    @staticmethod
    def of(sim) -> "HBVMIntegrator | None":
        """The HBVMIntegrator attached to ``sim`` (for instance a ``sim.copy()``), or None."""
        return _REGISTRY.get(ctypes.addressof(sim))

    @staticmethod
    def state_path(path) -> str:
        """Where :meth:`save` puts HBVM's state next to REBOUND's file ``path``."""
        return f"{path}.hbvm.npz"

    def save(self, path) -> None:
        """Save the simulation for a restart that continues bit for bit.

        REBOUND's binary goes to ``path`` (one snapshot: an existing file is replaced), and
        what HBVM carries between steps (settings, the compensated state q, p and their
        compensations, the coefficients gamma of the last step, the previous step size, the
        reference energy, the counters) to :meth:`state_path` (``path + ".hbvm.npz"``).
        Continue with :meth:`load`.  ``rebound.Simulation(path)`` alone gives a simulation
        with integrator "none" and no callback, whose particles do not move.
        """
        sim = self.sim
        state = self._state()
        sim.save_to_file(str(path), delete_file=True)
        np.savez(self.state_path(path), t=sim.t, N=sim.N, **state)

    @classmethod
    def load(cls, path) -> tuple:
        """``(sim, integrator)`` from the files :meth:`save` wrote: the simulation at the time
        it was saved, driven by HBVM exactly as before (an uninterrupted run and a saved and
        loaded one give identical particles)."""
        rebound = _rebound()
        side = cls.state_path(path)
        try:
            data = dict(np.load(side, allow_pickle=False))
        except FileNotFoundError:
            raise FileNotFoundError(f"{side} not found: HBVMIntegrator.load(path) reads the "
                                    "REBOUND file and the state file that "
                                    "HBVMIntegrator.save(path) wrote") from None
        with _pointers_are_reset():
            sim = rebound.Simulation(str(path))
        if sim.t != data["t"] or sim.N != data["N"]:
            raise ValueError(f"{path} holds t={sim.t!r}, N={sim.N} but {side} was saved at "
                             f"t={float(data['t'])!r}, N={int(data['N'])}: save both with "
                             "HBVMIntegrator.save(path)")
        return sim, cls._rebuild(sim, data)

    # -- copies and restarts -------------------------------------------------------------
    def _state(self) -> dict:
        """Settings and the state between steps, as arrays (the .npz of :meth:`save`)."""
        nan = float("nan")
        d = dict(s=self.method.s, k=self.method.k, nodes=self.method.nodes,
                 max_iter=self.max_iter, tol=self.tol,
                 energy_tol=nan if self.energy_tol is None else self.energy_tol,
                 adaptive=self.adaptive, epsilon=self.epsilon, min_dt=self.min_dt,
                 rejected=self.rejected,
                 prev_integrator=self._prev_integrator, stepped=self._written is not None,
                 counts=np.array([self.nsteps, self.nfev, self.niter, self.resyncs]))
        if self._written is not None:
            d.update(S=self._S, gamma=self._gamma, written=self._written, eref=self._eref[0],
                     h_prev=float(self._scal[glue.S_H_PREV]),          # nan: none
                     t_written=float(self._scal[glue.S_T_WRITTEN]))
        return d

    @classmethod
    def _rebuild(cls, sim, d: dict) -> "HBVMIntegrator":
        """Attach to ``sim`` with the settings and state ``d`` of :meth:`_state` (no k probe)."""
        energy_tol = float(d["energy_tol"])
        drv = cls.__new__(cls)
        drv._attach(sim, HBVM(int(d["k"]), int(d["s"]), nodes=str(d["nodes"])), sim.dt,
                    int(d["max_iter"]), float(d["tol"]) or None,
                    None if math.isnan(energy_tol) else energy_tol)
        drv._set_control(bool(d["adaptive"]), float(d["epsilon"]), float(d["min_dt"]))
        drv._scal[glue.S_REJECTED] = int(d["rejected"])
        drv._prev_integrator = str(d["prev_integrator"])
        nsteps, nfev, niter, drv.resyncs = (int(c) for c in d["counts"])
        drv._scal[glue.S_NSTEPS] = nsteps
        drv.counters[C_NFEV], drv.counters[C_ITER] = nfev, niter
        if bool(d["stepped"]):
            drv._set_state(d)
        return drv

    def _clone_onto(self, sim) -> "HBVMIntegrator":
        return self._rebuild(sim, self._state())

    def _set_state(self, d: dict) -> None:
        view = self._particle_view()
        w = np.asarray(d["written"], dtype=float)
        if w.shape != (view.shape[0], 7) or not (np.array_equal(view[:, :6], w[:, :6])
                                                 and np.array_equal(view[:, 9], w[:, 6])):
            raise ValueError("the saved HBVM state does not belong to these particles; load "
                             "the simulation and the state that HBVMIntegrator.save wrote together")
        self._model(view)
        self._arrays(np.array(d["S"], dtype=float), np.array(d["gamma"], dtype=float), view, w)
        self._eref[0] = float(d["eref"])
        self._scal[glue.S_H_PREV] = float(d["h_prev"])
        self._scal[glue.S_T_WRITTEN] = float(d["t_written"])

    # -- called by the wrapped Simulation ----------------------------------------------
    def _reb_integrate(self, sim, done, tmax, exact_finish_time) -> None:
        """``rebound.Simulation.integrate(sim, tmax, exact_finish_time)``: the same C call, the
        same exceptions, without the wrapper's per-call work (the field set through
        ``Simulation.__setattr__``, a message buffer made whether or not there are messages:
        4.1 -> 1.3 us a call that takes no step, which 200 output times pay 200 times)."""
        self._exact_finish.value = exact_finish_time        # a TypeError as REBOUND's c_int
        self._reb_done(sim, self._reb_call(self._addr, ctypes.c_double(tmax)))

    def _reb_done(self, sim, status: int) -> None:
        """What rebound.Simulation.integrate does with the C call's status: its exceptions,
        and the messages REBOUND left."""
        if status == 6 or status in _REB_ERRORS:
            raise _reb_status_error(sim, status)
        if self._messages.value:
            sim.process_messages()

    def _run(self, go, *args) -> None:
        """Run REBOUND (``go(sim, done, *args)``: its steps minus the ``done`` ones; None: its
        integrate, args (tmax, exact_finish_time)) with the step in C when nothing in Python
        has to run between steps (:meth:`_native`), else through the Python callback; re-raise
        an exception of a step afterwards."""
        native = self._before_run()
        try:
            steps_done = self._steps_done
            slots, idx = self._slots, self._slot_idx
            done = 0
            while True:
                self.last_run_native = native
                if not native:
                    self._hook_on()
                    (go or self._reb_integrate)(self.sim, done, *args)
                    break
                before = steps_done.value
                scal = self._scal
                scal[glue.S_STATUS] = OK
                if go is None:
                    tmax, eft = args
                    self._exact_finish.value = eft       # a TypeError as REBOUND's c_int
                    if type(tmax) is not float:
                        tmax = ctypes.c_double(tmax).value    # and as its c_double
                    self._reb_done(self.sim, self._native_call(self._nat, tmax))
                else:
                    try:
                        slots[idx] = self._native_slots
                        go(self.sim, done, *args)
                    finally:
                        slots[idx] = self._python_slots
                status = scal[glue.S_STATUS]
                if status == OK:
                    break
                done += steps_done.value - before
                if status == RESYNC:      # the C step stopped the run: re-read, go on
                    self._resync(self._particle_view())
                    native = self._native()
                    continue
                self._error = self._step_failure(int(status))
                break
        finally:
            self._after_run()

    def _native(self) -> bool:
        """Can REBOUND call the compiled step directly (no Python between steps)?  Yes when
        the step is compiled, its state is current, and the simulation has no heartbeat, no
        other callback and no ``extras`` of its own."""
        if (self._cstep is None or self._native_call is None or self._chain is not None
                or self._ctx is None or not self._allow_native):
            return False
        sim = self.sim
        if sim._heartbeat or sim._pre_timestep_modifications or self._extras_c.value:
            return False
        key = (self._simi[glue.PTR_AT], self._simi[glue.N_AT])
        if key != (self._ctx[glue.D_PTR], self._ctx[glue.D_NPART]):
            self._resync(self._particle_view())
        return True

    def _before_run(self) -> bool:
        """Check the simulation before a run; returns :meth:`_native`'s answer, asked again
        only when the bytes it reads, the step's arrays or ``_allow_native`` changed (asking
        costs about 1 us a ``sim.integrate`` call, which 200 output times pay 200 times)."""
        self._error = None
        sim = self.sim
        config = self._cfg_bytes[self._cfg_idx].tobytes()
        if config != self._cfg_ok:
            name = str(sim.integrator)
            if name != "none":
                raise ValueError(f"sim.integrator was changed to '{name}' while HBVMIntegrator is "
                                 "attached; call detach() first (it restores the integrator you had)")
            if ctypes.cast(sim._post_timestep_modifications, ctypes.c_void_p).value != self._cb_ptr:
                raise ValueError("sim.post_timestep_modifications was replaced while HBVMIntegrator "
                                 "is attached; set your callback before attaching (it is chained)")
            check_simulation(sim)
            self._cfg_ok = config
        h = self._simd[glue.DT_AT]
        if not (math.isfinite(h) and h != 0.0):
            _step_size("sim.dt", sim.dt)
        if self._ctx is None and self._simi[glue.N_AT] > 0:
            self._resync(self._particle_view())
        key = self._native_key
        if (key is None or key[0] != config or key[1] is not self._ctx
                or key[2] != self._allow_native):
            self._native_last = self._native()
            self._native_key = (config, self._ctx, self._allow_native)
        return self._native_last

    def _hook_on(self) -> None:
        """Before a run through the Python callback: ctypes hands an exception raised on
        entering the callback (before its try: a signal handler's) to sys.unraisablehook and
        goes on, so catch it there for the time of the run.  A native run has no Python
        callback (a signal's exception is raised after REBOUND returns) and skips this."""
        if self._hook_prev is None:
            self._hook_prev = sys.unraisablehook
            sys.unraisablehook = self._unraisable

    def _after_run(self) -> None:
        if self._hook_prev is not None:
            if sys.unraisablehook == self._unraisable:
                sys.unraisablehook = self._hook_prev
            self._hook_prev = None
        err, self._error = self._error, None
        if err is not None:
            raise err

    def _unraisable(self, unraisable) -> None:
        if getattr(unraisable.object, "__self__", None) is self:
            self._fail(unraisable.exc_value)
        else:
            (self._hook_prev or sys.__unraisablehook__)(unraisable)

    # -- the step ----------------------------------------------------------------------
    def _callback(self, simp) -> None:
        try:
            self._step()
        except BaseException as exc:  # noqa: BLE001 - ctypes would swallow it
            self._fail(exc)
            return
        try:
            if self._chain is not None:
                self._chain(simp)
        except BaseException as exc:  # noqa: BLE001
            self._fail(exc)

    def _fail(self, exc: BaseException) -> None:
        """Stop the run on ``exc`` (``sim.integrate`` raises it) with the particles and sim.t at
        a whole number of committed steps.

        An exception can land between any two bytecodes (a signal handler's), also after the
        compiled step committed (it then wrote sim.t as the state's time: nothing to undo);
        otherwise REBOUND's t += h is undone."""
        if self._scal[glue.S_T_WRITTEN] != self._simd[glue.T_AT]:
            glue.undo_time(self._simd, self._scal)
        if self._error is None:
            self._error = exc
        self.sim.stop()

    def _step_failure(self, status: int) -> StepError:
        """The exception of a failed step, from what the compiled step recorded."""
        sc = self._scal
        h, t = float(sc[glue.S_H_FAIL]), float(sc[glue.S_T_FAIL])
        if status == TOO_SMALL:
            cause_status = int(sc[glue.S_CAUSE_STATUS])
            cause = (f"error estimate {sc[glue.S_CAUSE_ERR]:.3e} > epsilon={self.epsilon:.3e}"
                     if cause_status == OK else
                     str(step_error(cause_status, h, t, self.counters, "fixed_point",
                                    energy_tol=self.energy_tol, hints=_HINTS)))
            return StepSizeError(h, self.min_dt, t, cause)
        return step_error(status, h, t, self.counters, "fixed_point", energy_tol=self.energy_tol,
                          hints=_HINTS)

    def _particle_view(self) -> np.ndarray:
        key = (self._simi[glue.PTR_AT], self._simi[glue.N_AT])
        if key != self._view_key:
            N = int(key[1])
            if N == 0 or key[0] == 0:
                raise ValueError("the simulation has no particles")
            buf = (ctypes.c_double * (_DOUBLES_PER_PARTICLE * N)).from_address(int(key[0]))
            self._view = np.frombuffer(buf, dtype=np.float64).reshape(N, _DOUBLES_PER_PARTICLE)
            self._view_key = key
            self._written = None
        return self._view

    def _model(self, view: np.ndarray) -> np.ndarray:
        """Build and check the N-body model of REBOUND's particles (masses, G, N_active);
        returns their state y = (q, p)."""
        sim = self.sim
        check_simulation(sim)
        N = view.shape[0]
        na = sim.N_active
        n_active = None if na < 0 or na >= N else na
        nb, self._premodel = self._premodel, None
        if (nb is not None and nb.N == N and nb.G == sim.G
                and nb.n_active == (N if n_active is None else n_active)
                and np.array_equal(nb.positions, view[:, :3])
                and np.array_equal(nb.velocities, view[:, 3:6])
                and np.array_equal(nb.body_masses, view[:, 9])):
            # the model the k probe ran on, built and checked at attach from these particles:
            # the same numbers as building and checking it again (about 0.1 ms of a first run)
            y = nb.initial_state()
        else:
            nb = NBody(view[:, 9].copy(), G=sim.G, n_active=n_active)
            y = np.concatenate([view[:, :3].reshape(-1), nb.momenta_from_velocities(view[:, 3:6])])
            check_particles(y, nb)
        self._system = nb
        self._binding = Binding(self.method, nb, form="separable", fast=True,
                                glue="hbvm_md.rebound_step")
        code = self._binding.step_code
        compiled = code.kind == "compiled"
        self._host = _entry(code.host_step) if compiled else code.host_step_arrays
        self._cstep = code.host_cstep.address if compiled else None
        # |T| + |V| of the gravitating bodies is the energy check's scale.  It is zero only for
        # at most one gravitating body, at rest (the restricted problem with a star at rest):
        # then it stays zero, there is nothing to check, and test particles are not checked.
        self._energy_check = bool(np.count_nonzero(nb.is_source) >= 2 or nb.kinetic(y[nb.dim:]) > 0)
        if not self._energy_check and self.energy_tol is not None:
            warnings.warn("HBVMIntegrator: the gravitating bodies have no energy (a single body "
                          "at rest), so energy_tol checks nothing here; test particles' steps "
                          "are not checked", RuntimeWarning, stacklevel=2)
        self.energy_tol = self.energy_tol          # the check's tolerance into the scalars
        sc = self._scal
        sc[glue.S_G] = self._simd[glue.G_AT]
        sc[glue.S_NA] = float(self._simi[glue.NA_AT])
        return y

    def _resync(self, view: np.ndarray) -> None:
        y = self._model(view)
        dim = self._system.dim
        # S rows: q, p, and their compensations (minus the low parts of the double-double state)
        S = np.zeros((4, dim))
        S[0] = y[:dim]
        S[1] = y[dim:]
        w = np.empty((view.shape[0], 7))
        w[:, :6] = view[:, :6]
        w[:, 6] = view[:, 9]
        self._arrays(S, np.zeros((self.method.s, dim)), view, w)
        self._scal[glue.S_H_PREV] = np.nan
        self._eref[0] = np.nan
        self.resyncs += 1

    def _arrays(self, S: np.ndarray, gamma: np.ndarray, view: np.ndarray,
                written: np.ndarray) -> None:
        """The state (S, gamma), the trial arrays the core's step works on, and ``ctx``, their
        addresses and sizes for the compiled step (:mod:`hbvm_md.rebound_step`)."""
        self._S, self._gamma = S, gamma
        self._S1, self._gamma1 = np.empty_like(S), np.empty_like(gamma)
        self._eref1 = np.empty(1)
        self._written = np.array(written, dtype=float)
        b, ex = self._binding, self._extrapolation
        (tn, ts), (Wp, Cp) = b.c1, b.c2
        NV, NVinv, NM = b.no_newton
        self._args = (S[:2].reshape(-1), S[2:].reshape(-1), self._S1[:2].reshape(-1),
                      self._S1[2:].reshape(-1), gamma, self._gamma1, self._eref, self._eref1,
                      self._written, b.minv, b.kin_w, b.params, tn, ts, Wp, Cp, NV, NVinv, NM,
                      self.counters, b.work, b.cwork, self._clock, ex.E1, ex.t, ex.w, ex.buf,
                      ex.zero, self._scal)
        ctx = np.zeros(glue.N_CTX, dtype=np.int64)
        for i, a in enumerate(self._args):
            if not (a.flags.c_contiguous and a.dtype in (np.float64, np.complex128)):
                raise AssertionError(f"rebound_step argument {i} is not a contiguous array")
            # the address through the buffer protocol (0.6 us) rather than a.ctypes (1.9 us),
            # where it is writable and not empty
            ctx[i] = (ctypes.addressof(ctypes.c_char.from_buffer(a))
                      if a.flags.writeable and a.size else a.ctypes.data)
        ctx[[glue.D_S, glue.D_K, glue.D_M, glue.D_N, glue.D_P, glue.D_NF, glue.D_NC]] = (
            self.method.s, self.method.n_stages, b.minv.shape[0], view.shape[0],
            b.params.shape[0], b.work.shape[0], b.cwork.shape[0])
        ctx[[glue.D_SIM, glue.D_PTR, glue.D_NPART]] = (self._addr, self._simi[glue.PTR_AT],
                                                      self._simi[glue.N_AT])
        self._ctx = ctx
        if self._cstep is not None:   # the two slots' values during a native run (see _run)
            self._native_slots[:] = (self._cstep, ctx.ctypes.data)

    def _step(self) -> None:
        """One REBOUND step through the Python callback: one compiled call (the step and its
        commit), or two when the particles changed since the last one."""
        if self._ctx is None:
            self._resync(self._particle_view())
        status = self._call_host()
        if status == RESYNC:
            # the user changed the particles: rebuild the model (masses, params, arrays)
            self._resync(self._particle_view())
            status = self._call_host()
        if status != OK:
            raise self._step_failure(status)

    def _call_host(self) -> int:
        if self._cstep is not None:
            return self._host(self._ctx)
        view = self._particle_view()      # a Python step: views made here, RESYNC if moved
        if self._written is None:
            return RESYNC
        return self._host(self._simd, self._simi, view, *self._args)
