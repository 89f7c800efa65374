"""The Python side of HBVM in REBOUND: registration, the state's ``create``, the step's
``prepare`` and ``fail`` callbacks, and the map from a failed step to its exception in
``Simulation.integrate`` / ``steps``.  See :mod:`hbvm_md.rebound` for the design."""
from __future__ import annotations

import ctypes
import math
import os
import sys
import threading
import warnings

import numpy as np

from hbvm_md.rebound import cglue, layout as L
from hbvm_md.rebound import state as _state
from hbvm_md.rebound.state import (LIBC as _LIBC, RECORDS as _RECORDS, Record as _Record,
                                   array as _array, context as _context, masses_changed as
                                   _masses_changed, masses_digest, model_changed as
                                   _model_changed, record as _record, record_of_state,
                                   slots as _slots, user_stacklevel as _user_stacklevel)
from hbvm_md.rebound.memory import doubles, int64s
from hbvm_md.rebound.checks import _step_size, check_particles, check_simulation
from integrators import EQUIP, HBVM, ccore
from integrators.core import (C_LASTIT, C_WORST, ERROR_BOUND, N_COUNTERS, NOT_FINITE, NOT_RESOLVED,
                              OK, RUN_ERROR_BOUND, TOO_SMALL, test_particle_error)
from integrators.engine import (DEFAULT_EPSILON, Binding, check_adaptive,
                                energy_check)
from integrators.errors import (AccumulatedErrorWarning, ConvergenceError, NonFiniteError,
                                StepSizeError, UnresolvedStepError, step_error)
from integrators.kchoice import adaptive_k
from integrators.tangent import TANGENT_FAILED
from systems.nbody import NBody, nbody_force_jvp
from hbvm_md.rebound.forces import (P_NODES, P_ODES_HELD, ReboundScene, host_reasons,
                                    ode_signature, reboundx_forces)
from hbvm_md.rebound.glue import Host, Rebound
from hbvm_md.rebound.masses import masses_only
from integrators import records as R

NAME = "hbvm"
DEFAULTS = dict(method="hbvm", s=6, k=adaptive_k(6, DEFAULT_EPSILON), nodes="gauss", max_iter=60,
                adaptive=True, epsilon=DEFAULT_EPSILON, min_dt=0.0, tol=None)
# the engine's one default energy check, for k chosen for a round-off quadrature error (1e-10)
DEFAULTS["energy_tol"] = energy_check(HBVM(DEFAULTS["k"], DEFAULTS["s"]), None, "auto", None,
                                      round_off_k=True)
#: what to do about a failed fixed step, by its cause (after the closest encounter, _encounter)
_WAY_OUT = ("leave out `dt` (HBVMIntegrator(sim) takes adaptive steps, which shrink through "
            "encounters, test particles' too), or use a smaller sim.dt")
#: the same for the composed step (``sim.integrator.kepler = 1``: fixed steps only)
_WAY_OUT_KEPLER = ("use a smaller sim.dt, or sim.integrator.kepler = 0 with adaptive steps "
                   "(HBVMIntegrator(sim, kepler=False) without `dt`), which shrink through "
                   "encounters")
_HINTS = {"diverged": _WAY_OUT + ", or a larger max_iter",
          "not_finite": _WAY_OUT + "; check for particles at the same position",
          "unresolved": _WAY_OUT + ", or pass energy_tol=None to accept such steps"}
#: the way out of a run's drift (EnergyDriftError): not the step's size nor an encounter, but
#: the quadrature, which the default k makes exact to round-off
_DRIFTED_HINT = ("leave k unset (HBVMIntegrator(sim, s=...) then chooses k so that H is kept "
                 "to round-off) or give more nodes, k >= 2s")
_REB_GENERIC_ERROR = 1            # enum REB_STATUS
_PENDING: dict = {}               # simulation address -> the exception of its failed step
_REG = None                       # what registration keeps alive (see register)


def _rebound():
    import rebound
    return rebound


# -- registration ------------------------------------------------------------------------------
def register() -> None:
    """Register HBVM with REBOUND under the name "hbvm", once per process (``import hbvm_md``
    calls it).  REBOUND cannot register a name twice (its registry then loops), so a second call
    returns at once, and a name "hbvm" registered by someone else is an error."""
    global _REG
    rebound = _rebound()
    if _REG is not None:
        return
    mark = getattr(rebound.clibrebound, "_hbvm_md_registration", None)
    if mark is not None:           # hbvm_md imported again (a reload): keep the first one
        _state.REG.update(mark)
        _REG = _state.REG
        return
    L.check_version(rebound)
    lib = rebound.clibrebound
    lib.reb_integrators_registered.restype = ctypes.POINTER(ctypes.c_char_p)
    names = lib.reb_integrators_registered()
    i, known = 0, []
    while names[i]:
        known.append(names[i].decode())
        i += 1
    _LIBC.free(ctypes.cast(names, ctypes.c_void_p))
    if NAME in known:
        raise RuntimeError(f"an integrator named {NAME!r} is registered with REBOUND already, "
                           "not by hbvm_md; HBVM cannot register")
    from rebound.binarydata_field_descriptor import BinarydataFieldDescriptor, EnumDescriptor
    from rebound.integrator import Integrator
    from hbvm_md.rebound import cglue
    if cglue.built():           # (REBOUND's step and free in C: nothing compiled at run time)
        dispatch, release, _ = cglue.addresses()
    else:                       # (numba's, compiled once and cached on disk)
        from hbvm_md.rebound import cabi
        dispatch, release = cabi.dispatch.address, cabi.release.address
    enums = {}
    for field, names in L.ENUMS.items():
        enums[field] = (EnumDescriptor * (len(names) + 1))()
        for j, n in enumerate(names):
            enums[field][j].value, enums[field][j].name = j, n.encode()
    fds = (BinarydataFieldDescriptor * (len(L.SAVED) + 1))()
    docs = []
    for j, (name, slot, dtype, slot_n, doc) in enumerate(L.SAVED):
        docs.append(ctypes.create_string_buffer(doc.encode()))
        fd = fds[j]
        fd.documentation = ctypes.cast(docs[-1], ctypes.c_char_p)
        fd.dtype, fd.name, fd.offset = dtype, name.encode(), 8 * slot
        fd.offset_N = 8 * slot_n if slot_n is not None else 0
        fd.element_size = 8 if dtype == L._POINTER else 0
        if name in enums:
            fd.enum_descriptor_list = ctypes.cast(enums[name], type(fd.enum_descriptor_list))
    create = ctypes.CFUNCTYPE(ctypes.c_void_p)(_create)
    prepare = ctypes.CFUNCTYPE(ctypes.c_int32, ctypes.c_void_p, ctypes.c_void_p)(_prepare_cb)
    fail = ctypes.CFUNCTYPE(ctypes.c_int32, ctypes.c_void_p, ctypes.c_void_p)(_fail_cb)
    python_core = ctypes.CFUNCTYPE(ctypes.c_int32, ctypes.c_void_p, ctypes.c_void_p)(_python_core)
    forget = ctypes.CFUNCTYPE(ctypes.c_int32, ctypes.c_void_p, ctypes.c_void_p)(_forget_cb)
    doc = ctypes.create_string_buffer(
        b"HBVM(k, s) (Brugnano, Iavernaro, Trigiante: Hamiltonian Boundary Value Methods), "
        b"registered by the hbvm_md package: energy-conserving implicit Runge-Kutta steps of "
        b"order 2s, adaptive by default; with method = 'equip', EQUIP(k, s) (Brugnano, "
        b"Iavernaro, Trigiante: energy- and quadratic-invariants-preserving methods), which "
        b"keeps the angular momentum to round-off too.  Configure with "
        b"hbvm_md.HBVMIntegrator(sim, ...).")
    integ = Integrator()
    integ.documentation = ctypes.cast(doc, ctypes.c_char_p)
    integ.step = dispatch
    integ.create = ctypes.cast(create, ctypes.c_void_p).value
    integ.free = release
    integ.field_descriptor_list = ctypes.cast(fds, type(integ.field_descriptor_list))
    step_at, state_at = L.state_offset(rebound)
    reg = dict(keep=(enums, fds, docs, create, prepare, fail, python_core, forget, doc, integ),
               forget=ctypes.cast(forget, ctypes.c_void_p).value,
               dispatch=dispatch, prepare=ctypes.cast(prepare, ctypes.c_void_p).value,
               fail=ctypes.cast(fail, ctypes.c_void_p).value,
               python_core=ctypes.cast(python_core, ctypes.c_void_p).value,
               free=ctypes.cast(_LIBC.free, ctypes.c_void_p).value,
               step_at=step_at, state_at=state_at, offsets=L.rebound_offsets(rebound),
               config_words=L.config_words(rebound), **L.run_offsets(rebound),
               ax=rebound.Particle.ax.offset // 8,
               variational=L.variational_offsets(rebound),
               megno_update=ctypes.cast(lib.reb_tools_megno_update, ctypes.c_void_p).value)
    lib.reb_integrator_register.argtypes = [Integrator, ctypes.c_char_p]
    _state.REG.update(reg)
    _REG = _state.REG             # (create reads it)
    import atexit
    atexit.register(_finishing)
    lib.reb_integrator_register(integ, NAME.encode())
    rebound.clibrebound._hbvm_md_registration = reg
    _self_check(rebound)


#: False until the first HBVM simulation of the process (its state's ``create``): only then are
#: REBOUND's ``Simulation.integrate``, ``steps`` and ``__repr__`` of the integrator, and
#: REBOUNDx's ``Extras.add_operator``, replaced (a process that imports hbvm_md and REBOUND
#: without using HBVM keeps them as they are, and does not import REBOUNDx)
_INSTALLED = False
_CHECKING = []            # (register's self-check creates a state: it installs nothing)


def _install() -> None:
    """What an HBVM simulation needs of its host's Python, once per process."""
    global _INSTALLED
    _INSTALLED = True
    rebound = _rebound()
    _install_runs(rebound)
    _install_repr(rebound)
    _install_operators()


def _self_check(rebound) -> None:
    """REBOUND steps, saves and reads HBVM's state where this host put it (the ctypes layouts
    of ``struct reb_integrator`` and its field descriptors are REBOUND's Python's; this checks
    them against the C library once)."""
    _CHECKING.append(True)
    try:
        _self_check_states(rebound)
    finally:
        _CHECKING.pop()


def _self_check_states(rebound) -> None:
    sim = rebound.Simulation()
    sim.integrator = NAME
    p = ctypes.c_void_p.from_address(ctypes.addressof(sim) + _REG["state_at"]).value
    st, sd = _slots(p) if p else (None, None)
    ok = (p == sim.integrator.state and st[L.SL_PREPARE] == _REG["prepare"]
          and int(sim.integrator.s) == DEFAULTS["s"] and str(sim.integrator.nodes) == "gauss"
          and str(sim.integrator.method) == DEFAULTS["method"]
          and float(sim.integrator.epsilon) == DEFAULTS["epsilon"]
          and ctypes.c_void_p.from_address(ctypes.addressof(sim) + _REG["step_at"]).value
          == _REG["dispatch"])
    copy = sim.copy() if ok else None
    if not ok or int(copy.integrator.k) != DEFAULTS["k"]:
        raise RuntimeError(f"REBOUND {rebound.__version__} does not keep HBVM's state where its "
                           f"own layout says; HBVM's REBOUND host supports {L.SUPPORTED}")


def _create() -> int:
    """REBOUND's ``create``: a new state with HBVM's defaults (REBOUND then reads saved fields
    into it when it loads or copies a simulation)."""
    if not _INSTALLED and not _CHECKING:
        try:
            _install()
        except BaseException as exc:  # noqa: BLE001 - a callback must not raise into REBOUND
            warnings.warn(f"hbvm-md: could not install its REBOUND hooks ({exc!r}); failed "
                          "steps then raise REBOUND's generic RuntimeError", RuntimeWarning)
    p = _LIBC.calloc(L.N_SLOTS, 8)
    if not p:
        return 0
    _RECORDS[p] = _Record()
    st, sd = _slots(p)
    d = DEFAULTS
    st[[L.SL_METHOD, L.SL_S, L.SL_K, L.SL_NODES, L.SL_MAX_ITER, L.SL_ADAPTIVE]] = (
        L.METHODS.index(d["method"]), d["s"], d["k"], L.NODES.index(d["nodes"]), d["max_iter"],
        int(d["adaptive"]))
    sd[[L.SL_EPSILON, L.SL_MIN_DT, L.SL_TOL, L.SL_ETOL, L.SL_H_PREV]] = (
        d["epsilon"], d["min_dt"], 0.0, d["energy_tol"], np.nan)
    sd[L.SL_EREF:L.SL_EREF + L.N_EREF] = np.nan      # energy, alpha, slope, run's start: unknown
    sd[L.SL_T_WRITTEN] = np.nan                        # (sim.t is then taken as it is)
    sd[L.SL_EREF_MASSES] = np.nan                      # (no masses yet: see masses_digest)
    st[[L.SL_PREPARE, L.SL_FAIL, L.SL_FREE, L.SL_FORGET]] = (
        _REG["prepare"], _REG["fail"], _REG["free"], _REG["forget"])
    return p


def _forget_cb(r: int, p: int) -> int:
    """REBOUND frees the state at p (its ``free``, before the memory goes): its record goes."""
    _RECORDS.pop(p, None)
    return 0


def _finishing() -> None:
    """At the interpreter's exit (atexit, before modules go): no state calls Python any more
    when REBOUND frees it later (a simulation collected at shutdown)."""
    for p in list(_RECORDS):
        int64s(p, L.N_SLOTS)[L.SL_FORGET] = 0
    _RECORDS.clear()


# -- the integrate and steps of rebound.Simulation ------------------------------------------------
# simulation address -> the thread of the run in progress: REBOUND's run loop releases the GIL,
# and two threads integrating one simulation step one state from two places (the step then finds
# the state changed under it)
_RUNNING: dict[int, int] = {}


def _install_runs(rebound) -> None:
    """``rebound.Simulation.integrate`` and ``steps`` raise a failed HBVM step's own exception.

    REBOUND's Python maps the C status of a run to its exceptions in these two methods, and an
    error message to a RuntimeError; our ``fail`` callback sets that status and message (so a
    caller of the C library sees the failure too).  For a simulation whose integrator is HBVM
    these methods make the same C call with the same arguments and the same exceptions for
    REBOUND's own statuses, and raise the recorded ConvergenceError, StepSizeError, ... in place
    of the RuntimeError; for any other integrator they are REBOUND's own, untouched."""
    S = rebound.Simulation
    if getattr(S.integrate, "_hbvm_md", False):
        return
    lib = rebound.clibrebound
    c_integrate = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_double)(
        ctypes.cast(lib.reb_simulation_integrate, ctypes.c_void_p).value)
    c_steps = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_size_t)(
        ctypes.cast(lib.reb_simulation_steps, ctypes.c_void_p).value)
    reb_integrate, reb_steps = S.integrate, S.steps
    step_at, dispatch, eft_at = _REG["step_at"], _REG["dispatch"], _REG["eft_at"]
    messages_at = _REG["messages_at"]
    auto_step_at = S.simulationarchive_auto_step.offset
    c_int, c_void_p, addressof = ctypes.c_int, ctypes.c_void_p, ctypes.addressof
    c_uint64 = ctypes.c_uint64
    c_double, c_size_t = ctypes.c_double, ctypes.c_size_t

    def integrate(self, tmax, exact_finish_time=1):
        addr = addressof(self)
        if c_void_p.from_address(addr + step_at).value != dispatch:
            return reb_integrate(self, tmax, exact_finish_time)
        _check_tmax(tmax)
        with _Run(addr, self) as run:
            _PENDING.pop(addr, None)
            if c_uint64.from_address(addr + auto_step_at).value:
                _warn_step_archive(addr)
            if _record(addr).host_path:
                _probe_run(self)
            _recheck_forces(self, addr)
            _forget_host_energy(addr, self)
            c_int.from_address(addr + eft_at).value = exact_finish_time  # a TypeError as REBOUND's
            _recheck_odes(self, addr)
            try:
                status = c_integrate(addr, c_double(tmax))
            finally:
                _release_odes(addr)
            _after_run(self, addr, status, messages_at, run.raised)  # (as REBOUND)
            _warn_run_error(self, addr)

    def steps(self, N_steps):
        addr = addressof(self)
        if c_void_p.from_address(addr + step_at).value != dispatch:
            return reb_steps(self, N_steps)
        with _Run(addr, self) as run:
            _PENDING.pop(addr, None)
            if c_uint64.from_address(addr + auto_step_at).value:
                _warn_step_archive(addr)
            if _record(addr).host_path:
                _probe_run(self)
            _recheck_forces(self, addr)
            _forget_host_energy(addr, self)
            _recheck_odes(self, addr)
            try:
                status = c_steps(addr, c_size_t(N_steps))
            finally:
                _release_odes(addr)
            _after_run(self, addr, status, messages_at, run.raised)
            _warn_run_error(self, addr)

    integrate.__doc__, steps.__doc__ = reb_integrate.__doc__, reb_steps.__doc__
    integrate._hbvm_md = steps._hbvm_md = True
    S.integrate, S.steps = integrate, steps


def _check_tmax(tmax) -> None:
    """Refuse ``sim.integrate(nan)``: REBOUND's run loop compares t with tmax, and a nan never
    compares, so the run would never end (IAS15's hangs).  Infinity is REBOUND's run until an
    exit condition (a collision, an escape, ``sim.exit_min_distance``): kept."""
    try:
        nan = math.isnan(tmax)
    except TypeError:
        return                      # (REBOUND's own TypeError, from c_double)
    if nan:
        raise ValueError(f"sim.integrate(tmax) needs a number for tmax (got tmax={tmax!r}, which "
                         "no time reaches: the run would never end); pass the time to integrate "
                         "to, or inf for a run that an exit condition stops")


def _install_repr(rebound) -> None:
    """``repr(sim.integrator)`` of HBVM shows the steps it takes: REBOUND's repr lists the
    saved fields, and ``sim.integrator.epsilon = 0`` (IAS15's idiom for fixed steps of sim.dt)
    leaves the field ``adaptive`` at 1 (it must: a later epsilon > 0 is adaptive again), so a
    fixed-step run showed ``adaptive=1``; it shows ``adaptive=0 (epsilon=0: fixed steps of
    sim.dt)`` instead.  Other integrators' repr is REBOUND's own."""
    C = rebound.integrator.IntegratorConfiguration
    if getattr(C.__repr__, "_hbvm_md", False):
        return
    reb_repr = C.__repr__

    def __repr__(self):
        text = reb_repr(self)
        try:
            ours = self.name.decode() == NAME
        except Exception:  # noqa: BLE001 - (a configuration without a name)
            ours = False
        if ours and ", adaptive=1," in text and ", epsilon=0.0," in text:
            text = text.replace(", adaptive=1,", ", adaptive=0 (epsilon=0: fixed steps of "
                                "sim.dt),", 1)
        return text

    __repr__._hbvm_md = True
    C.__repr__ = __repr__


def _warn_run_error(sim, addr: int) -> None:
    """After a run that returned: warn once a simulation (AccumulatedErrorWarning) when its run's
    accumulated error estimate (``sim.integrator.error_estimate``, integrators.core.C_RUN_ERR)
    has passed RUN_ERROR_BOUND."""
    p = ctypes.c_void_p.from_address(addr + _REG["state_at"]).value
    if not p:
        return
    st, sd = _slots(p)
    est = float(sd[L.SL_RUN_ERR])
    if est > RUN_ERROR_BOUND and not st[L.SL_RUN_WARNED]:
        st[L.SL_RUN_WARNED] = 1
        warnings.warn(AccumulatedErrorWarning(
            est, RUN_ERROR_BOUND, float(sim.t),
            "a smaller sim.dt (the estimate falls like dt^(2s)), a larger s, or adaptive steps "
            "(sim.integrator.epsilon)"), stacklevel=_user_stacklevel())


def _warn_step_archive(addr: int) -> None:
    """An archive saved every N steps (``sim.save_to_file(f, step=N)``) of a run with adaptive
    steps holds snapshots unevenly spaced in time, which a user written for fixed steps (a
    frequency analysis, REBOUND's FrequencyAnalysis notebook) takes as evenly spaced: warn at
    the run's start, naming ``interval=`` (REBOUND's docs tell IAS15's users the same)."""
    p = ctypes.c_void_p.from_address(addr + _REG["state_at"]).value
    if not p:
        return
    st, sd = _slots(p)
    if not st[L.SL_ADAPTIVE] or sd[L.SL_EPSILON] == 0.0:
        return
    sim = _rebound().Simulation.from_address(addr)
    warnings.warn(
        f"sim.save_to_file(..., step={sim.simulationarchive_auto_step}) saves a snapshot every "
        f"{sim.simulationarchive_auto_step} steps, and HBVM's adaptive steps vary in length (as "
        "IAS15's), so the snapshots are unevenly spaced in time (a frequency analysis of them is "
        "wrong); save at even times with sim.save_to_file(filename, interval=...), or take "
        "fixed steps of sim.dt with sim.integrator.epsilon = 0", RuntimeWarning,
        stacklevel=_user_stacklevel())


def _prepared(addr: int):
    """(st, sd, ctx) of the simulation at ``addr``: HBVM's state slots and its context header
    (:mod:`hbvm_md.rebound.layout`), or None before its step was first prepared."""
    p = ctypes.c_void_p.from_address(addr + _REG["state_at"]).value
    if not p:
        return None
    st, sd = _slots(p)
    if not st[L.SL_CTX]:
        return None
    return st, sd, int64s(int(st[L.SL_CTX]), L.N_HEADER)


#: this thread's HBVM run (a _Run), if any: where the unraisable hook records a raise
_RUN = threading.local()


class _Run:
    """One HBVM run (``integrate`` or ``steps``) of the simulation at ``addr``, in this thread.

    *One thread at a time.*  A second thread that integrates the same simulation while a run is
    in progress is refused by name (``_RUNNING``: a dict's setdefault and del are atomic under
    the GIL, so no lock is needed; a run nested in the same thread, as from a heartbeat, is
    allowed and the outermost one releases the simulation).

    *Python callbacks that raise.*  A Python callback that raises inside REBOUND
    (``sim.additional_forces``, a heartbeat, a REBOUNDx Python effect) is called through ctypes,
    which prints the exception and returns to C as if nothing happened: IAS15 then goes on with
    the forces the function left, a silent wrong answer.  During an HBVM run the first such
    exception is recorded here (:func:`_unraisable`), and on REBOUND's own accelerations the
    particles' accelerations are set to nan, so that the step whose forces raised fails (nothing
    committed) and the run stops; :func:`_after_run` then raises the user's exception in place
    of the step's NonFiniteError or StepSizeError.  Outside a step the nan accelerations are
    harmless (each stage computes them afresh).

    One object for both, entered once per ``sim.integrate`` call, which a run with an output
    every step pays on every step: with the two context managers and the lock it replaces, a
    ``sim.integrate`` call that takes no step cost 4.5 us, now 3.0 us (REBOUND's own for WHFast:
    3.3 us), and one that takes one step of the outer solar system 24 us, now 22 us."""

    __slots__ = ("addr", "sim", "raised", "outer", "owner")

    def __init__(self, addr: int, sim=None):
        # (sim: the user's Python object, which holds the Python callbacks: messages name them)
        self.addr, self.sim, self.raised = addr, sim, None

    def __enter__(self):
        # the hook is chained in front of whatever hook is in place when a run starts (not at
        # import: importing hbvm_md changes no process-wide setting), and passes everything
        # outside HBVM's runs on to it
        if not getattr(sys.unraisablehook, "_hbvm_md", False):
            sys.unraisablehook = _unraisable(sys.unraisablehook)
        me = threading.get_ident()
        if _RUNNING.setdefault(self.addr, me) != me:
            raise RuntimeError("this REBOUND simulation is being integrated by another "
                               "thread (sim.integrator = 'hbvm'): a simulation holds one "
                               "state and is stepped by one thread at a time; give each "
                               "thread its own simulation (sim.copy()), or serialise the "
                               "integrate calls with a lock")
        outer = self.outer = getattr(_RUN, "run", None)
        # the outermost run of this simulation in this thread releases it
        while outer is not None and outer.addr != self.addr:
            outer = outer.outer
        self.owner = outer is None
        _RUN.run = self
        return self

    def __exit__(self, *exc):
        _RUN.run = self.outer
        if self.owner:
            del _RUNNING[self.addr]


def _unraisable(previous):
    """``sys.unraisablehook``: an exception of a ctypes callback during this thread's HBVM run
    is recorded (the first) and poisons the accelerations (:class:`_Run`); any other goes
    to ``previous``."""
    def hook(u):
        run = getattr(_RUN, "run", None)
        if run is None or "ctypes callback" not in (u.err_msg or ""):
            return previous(u)
        if run.raised is None:
            run.raised = u.exc_value if u.exc_value is not None else u.exc_type()
        try:
            prepared = _prepared(run.addr)
            if prepared is not None and prepared[2][L.D_HOST]:
                sim = _rebound().Simulation.from_address(run.addr)
                ptr = ctypes.cast(sim._particles, ctypes.c_void_p).value
                stride = _REG["offsets"][L.R_STRIDE - L.R_T]
                if ptr and sim.N:
                    ax = _REG["ax"]
                    doubles(ptr, sim.N * stride).reshape(sim.N, stride)[:, ax:ax + 3] = np.nan
        except BaseException as exc:  # noqa: BLE001 - a hook must not raise
            previous(type(u)((type(exc), exc, exc.__traceback__, None, None)))
    hook._hbvm_md = True
    return hook


def _recheck_forces(sim, addr: int) -> None:
    """A REBOUNDx force added or removed between runs changes no word of ``reb_simulation``
    that the compiled step checks (REBOUNDx keeps one ``additional_forces`` function for all its
    forces), yet it changes the model: the potentials of the H the energy check guards, whether
    the scene has an H at all.  So ``integrate`` and ``steps`` compare the attached forces with
    those the step was prepared with, and on a difference mark the step's context stale (its
    copy of the ``additional_forces`` word is changed): the step answers RESYNC and the host
    prepares it again, as for any setting it checks."""
    rec = _record(addr)
    seen = rec.forces
    if seen is None or (not seen and not sim.extras):
        return
    if tuple(reboundx_forces(sim) or ()) == seen and (
            rec.kepler_terms is None or _kepler_terms_unchanged(sim, rec.kepler_terms)):
        return
    prepared = _prepared(addr)
    if prepared is not None:
        prepared[2][L.C_VALUES + L.CONFIG_FIELDS.index("_additional_forces")] ^= 1
    rec.forces = None


def _kepler_terms_unchanged(sim, terms) -> bool:
    from hbvm_md.rebound.composed import force_terms
    try:
        return force_terms(sim) == terms
    except ValueError:
        return False            # (the preparation names what is wrong)


def _host_params(addr: int):
    """The parameters of the step on REBOUND's own accelerations (hbvm_md.rebound.forces), as
    an array over the context block, or None (not prepared, or the N-body kernel's step)."""
    prepared = _prepared(addr)
    if prepared is None or not prepared[2][L.D_HOST]:
        return None
    ctx = prepared[2]
    return doubles(int(ctx[L.A_PARAMS]), int(ctx[L.D_P]))


def _release_odes(addr: int) -> None:
    """Give the simulation its attached ODEs back: the compiled step hides them from REBOUND
    (``sim->N_odes = 0``) after each step, so that REBOUND does not step them again with its BS
    integrator (:func:`hbvm_md.rebound.glue.step_arrays`); the next step puts them back
    itself, and the end of a run (or the step's preparation) here."""
    # Only a step on REBOUND's own accelerations hides ODEs, and every preparation releases
    # them first (_prepare) and then sets the record's host_path: a state without it holds
    # none, and
    # the set lookup spares the kernel's runs the context's views (2 us of a 6 us call)
    if not _record(addr).host_path:
        return
    params = _host_params(addr)
    if params is None or params[P_NODES] == 0 or params[P_ODES_HELD] == 0.0:
        return
    sim = _rebound().Simulation.from_address(addr)
    sim._N_odes = int(params[P_ODES_HELD])
    params[P_ODES_HELD] = 0.0


def _recheck_odes(sim, addr: int) -> None:
    """An ODE attached or removed between runs (or its functions replaced) changes no word of
    ``reb_simulation`` that the compiled step checks, as a REBOUNDx force does not
    (:func:`_recheck_forces`): the step's context is then marked stale, and prepared again."""
    rec = _record(addr)
    seen = rec.odes
    if not seen and not sim._N_odes:
        # none attached now, and none (or never prepared) then: their signatures would be
        # equal, () == (); one test instead of building it on every call
        return
    if seen is not None and ode_signature(sim) == seen:
        return
    prepared = _prepared(addr)
    if prepared is not None:
        # its own word (a force changed too flips _additional_forces'), set to differ from the
        # simulation's count as it is now (a flip of the old count may equal the new one)
        sim_words = int64s(addr, int(prepared[2][L.R_HEAD]))
        j = L.CONFIG_FIELDS.index("_N_odes")
        prepared[2][L.C_VALUES + j] = sim_words[prepared[2][L.C_WORDS + j]] ^ 1
    rec.odes = None


def _forget_host_energy(addr: int, sim) -> None:
    """On REBOUND's own accelerations the H the energy check guards holds the added forces'
    potentials, whose parameters (REBOUNDx ``gr_potential``'s ``c``, ``J2``, ``Acentral``: in
    ``params`` of a force or a particle) a user may change between runs without changing a word
    the compiled step checks.  The reference energy carried from the last step would then
    belong to the old H, and the first step of the run would be refused as unresolved (adaptive
    steps shrank to a StepSizeError blaming an encounter).  So each run on this path starts its
    reference afresh from its first step's start: the same number as the one carried when
    nothing changed (the same state through the same function)."""
    if not _record(addr).host_path:
        return
    prepared = _prepared(addr)
    if prepared is not None and prepared[2][L.D_HOST]:
        prepared[1][L.SL_EREF] = np.nan
        if sim._additional_forces:
            # (H may have changed: the run's start too; attached ODEs alone change nothing of
            # the bodies' H, so their run's drift check goes on across calls)
            prepared[1][L.SL_EREF_RUN] = np.nan


def _install_operators() -> None:
    """REBOUNDx's ``Extras.add_operator`` applies an operator with HBVM as with IAS15.

    REBOUNDx chooses an operator's timing from the integrator's name when it is added
    (``rebx_add_operator`` in its ``core.c``): IAS15 and BS get the whole step after the
    integrator's step, because they choose their own step size; an integrator whose name it does
    not know gets nothing (the operator is silently never applied).  HBVM chooses its step size
    too, so for a simulation integrated by HBVM an operator added without ``dtfraction`` is
    added as REBOUNDx adds it for IAS15: ``dtfraction = 1``, ``timing = "post"``.  Any other
    call (another integrator, an explicit ``dtfraction``) is REBOUNDx's own, untouched.
    Without REBOUNDx installed there is nothing to do."""
    try:
        import reboundx
    except ImportError:
        return
    Extras = reboundx.extras.Extras
    if getattr(Extras.add_operator, "_hbvm_md", False):
        return
    rebx_add_operator = Extras.add_operator
    step_at, dispatch = _REG["step_at"], _REG["dispatch"]

    def add_operator(self, operator, dtfraction=None, timing="post"):
        sim = self._sim
        if not (sim and ctypes.c_void_p.from_address(
                ctypes.addressof(sim.contents) + step_at).value == dispatch):
            return rebx_add_operator(self, operator, dtfraction, timing)
        if dtfraction is None:
            rebx_add_operator(self, operator, 1.0, "post")   # (IAS15's choice)
        else:
            rebx_add_operator(self, operator, dtfraction, timing)
        # (before the first run the step's preparation warns, for operators added to another
        # integrator too)
        if _prepared(ctypes.addressof(sim.contents)) is not None:
            _warn_operators(sim.contents, [operator])

    add_operator.__doc__ = rebx_add_operator.__doc__
    add_operator._hbvm_md = True
    Extras.add_operator = add_operator


def _operators(sim) -> list:
    """REBOUNDx's operators attached to ``sim`` (before and after the step), [] without."""
    if not sim.extras:
        return []
    try:
        import reboundx
    except ImportError:
        return []
    extras = reboundx.extras.Extras.from_address(sim.extras)
    out = []
    for node in (extras._pre_timestep_modifications, extras._post_timestep_modifications):
        while node:
            # a rebx_step: the operator's address, then its dt fraction
            op = ctypes.c_void_p.from_address(node.contents.object).value
            if op:
                out.append(reboundx.extras.Operator.from_address(op))
            node = node.contents.next
    return out


def _warn_operators(sim, operators) -> None:
    """REBOUNDx warns IAS15's users that an operator that changes the particles, applied once
    per adaptive step, can give spurious results.  At HBVM's longer steps the splitting error is
    larger (REBOUNDx's operator notebooks: 2.5 to 10 times IAS15's), so the same warning, with
    HBVM's ways out: a bound on the step (``max_dt``), or fixed steps of a small ``sim.dt``.
    Not when the user chose the steps (fixed steps, or ``max_dt`` set)."""
    p = ctypes.c_void_p.from_address(ctypes.addressof(sim) + _REG["state_at"]).value
    if not p:
        return
    st, sd = _slots(p)
    if not st[L.SL_ADAPTIVE] or sd[L.SL_EPSILON] == 0.0 or sd[L.SL_MAX_DT] > 0.0:
        return
    for op in operators:
        if op._operator_type == 2:          # a recorder (REBOUNDx's REBX_OPERATOR_TYPE)
            continue
        name = op.name.decode() if op.name else "?"
        warnings.warn(
            f"REBOUNDx operator '{name}' is applied once per HBVM step, after it (as REBOUNDx "
            "applies it for IAS15, which warns too): a splitting error that grows with the step, "
            "and HBVM's adaptive steps are longer than IAS15's (REBOUNDx's operator notebooks: "
            "2.5 to 10 times IAS15's error); bound the step with sim.integrator.max_dt (IAS15's "
            "step on the scene gives about IAS15's error), take fixed steps of a small sim.dt "
            "(sim.integrator.epsilon = 0), or use a REBOUNDx force in place of the operator",
            RuntimeWarning, stacklevel=_user_stacklevel())


def _after_run(sim, addr: int, status: int, messages_at: int, raised=None) -> None:
    """What ``rebound.Simulation.integrate`` does with the C status, with a failed HBVM step's
    exception in place of REBOUND's RuntimeError; a Python callback's exception that made the
    step fail (``raised``, :class:`_Run`) in place of that."""
    err = _PENDING.pop(addr, None)
    if err is not None:
        _drop_messages(sim, _message(err))
        if raised is not None and isinstance(err, (NonFiniteError, StepSizeError)):
            raise RuntimeError(
                f"a Python callback of the simulation (sim.additional_forces, an ODE's "
                f"derivatives or another) raised {type(raised).__name__}: {raised}; HBVM's step at "
                f"t={sim.t!r} evaluated "
                "REBOUND's accelerations through it and was not taken (the particles and sim.t "
                "are as before that step)") from raised
        raise err
    if raised is not None:      # (a callback outside the step, e.g. a heartbeat: as REBOUND,
        warnings.warn(          # which prints it and goes on)
            f"a Python callback of the simulation raised {type(raised).__name__}: {raised} "
            "(REBOUND ignores such exceptions; the run went on)", RuntimeWarning,
            stacklevel=_user_stacklevel())
    if status == 0:
        if ctypes.c_void_p.from_address(addr + messages_at).value:
            sim.process_messages()
        return
    rebound = _rebound()
    if status == 1:
        sim.process_messages()
        raise rebound.GenericError("An error occurred during the integration.")
    if status == 2:
        if sim._N_odes > 0:
            raise rebound.NoParticles("No particles found. Will exit. Use BS integrator to "
                                      "integrate user-defined ODEs without any particles present.")
        raise rebound.NoParticles("No more particles left in simulation.")
    if status == 3:
        raise rebound.Encounter("Two particles had a close encounter (d<exit_min_distance).")
    if status == 4:
        raise rebound.Escape("A particle escaped (r>exit_max_distance).")
    if status == 6:
        raise KeyboardInterrupt
    if status == 7:
        raise rebound.Collision("Two particles collided (d < r1+r2)")
    if ctypes.c_void_p.from_address(addr + messages_at).value:
        sim.process_messages()


def _drop_messages(sim, ours: str) -> None:
    """Show REBOUND's queued messages as ``process_messages`` does, except the error message
    our ``fail`` queued (its exception is raised instead)."""
    while True:
        try:
            sim.process_messages()
            return
        except RuntimeError as exc:
            if not (str(exc) and ours.startswith(str(exc))):
                warnings.warn(f"REBOUND: {exc}", RuntimeWarning, stacklevel=_user_stacklevel())


# -- the callbacks the compiled step calls --------------------------------------------------------
def _prepare_cb(r: int, p: int) -> int:
    try:
        if not masses_only(r, p):                  # (a change of masses only: in place)
            _prepare(_rebound().Simulation.from_address(r), p)
        return OK
    except BaseException as exc:  # noqa: BLE001 - ctypes would print and swallow it
        _PENDING[r] = exc
        return L.PREPARE_FAILED


def _fail_cb(r: int, p: int) -> int:
    """A step failed (nothing changed): record its exception, set REBOUND's error status and
    queue the message (so that REBOUND's own run loop stops, and a C caller sees it)."""
    try:
        st, sd = _slots(p)
        if int(st[L.SL_STATUS]) != L.PREPARE_FAILED or r not in _PENDING:
            try:
                _PENDING[r] = _step_failure(st, sd, _rebound().Simulation.from_address(r))
            except BaseException as exc:  # noqa: BLE001 - the run must stop with it
                _PENDING[r] = exc
        msg = _message(_PENDING[r])
        _rebound().clibrebound.reb_simulation_error(ctypes.c_void_p(r), msg.encode())
    finally:
        ctypes.c_int.from_address(r + _REG["status_at"]).value = _REB_GENERIC_ERROR
    return 0


def _message(err: BaseException) -> str:
    """The error message REBOUND queues for a failed HBVM step (REBOUND keeps its start)."""
    return f"{type(err).__name__}: {err}"


def _name(sim, i: int) -> str:
    """"particle i", with its name when it has one (REBOUND 5's ``name``, its hash before)."""
    name = sim.particles[i].name
    return f"particle {i}" + (f" ({name!r})" if name else "")


def _encounter(sim, only: int | None = None, s: int = 6) -> dict | None:
    """The closest encounter in ``sim`` as it is (the start of a failed step): of the pairs
    with a gravitating body (test particles do not meet each other), or of particle ``only``'s
    pairs, the one that weighs most in a step's error estimate: the largest (s-1)-th
    derivative of their pull, G (|m_i| + |m_j|) / d^2 / tau^(s-1) with the pair's time scale
    tau = min(d / v, sqrt(d^3 / (G (|m_i| + |m_j|)))) (a fast pass of a light body weighs
    little).
    dict(i, j, distance, speed, time) (j gravitates), or None when there is no such pair."""
    N = sim.N
    x, v, m = np.empty((N, 3)), np.empty((N, 3)), np.empty(N)
    sim.serialize_particle_data(xyz=x, vxvyvz=v, m=m)
    na = sim.N_active if 0 <= sim.N_active < N else N
    src = np.flatnonzero((np.arange(N) < na) & (m != 0))
    rows = np.arange(N) if only is None else np.array([only])
    best = None
    for a in range(0, rows.size, 256):                  # O(N N_sources) in blocks, no N^2 array
        i = rows[a:a + 256, None]
        d = np.linalg.norm(x[i] - x[src][None], axis=2)
        u = np.linalg.norm(v[i] - v[src][None], axis=2)
        with np.errstate(divide="ignore", invalid="ignore"):
            # (|m|: a negative mass moves its partner as fast as a positive one)
            gm = sim.G * (np.abs(m[i]) + np.abs(m[src])[None, :])
            tau = np.fmin(d / u, np.sqrt(d ** 3 / gm))
            weight = gm / d ** 2 / tau ** (s - 1)
        weight[(i == src[None, :]) | np.isnan(weight)] = -1.0
        k = np.unravel_index(np.argmax(weight), weight.shape)
        if weight[k] >= 0 and (best is None or weight[k] > best["weight"]):
            best = dict(i=int(i[k[0], 0]), j=int(src[k[1]]), distance=float(d[k]),
                        speed=float(u[k]), time=float(tau[k]), weight=float(weight[k]))
    return best


def _encounter_text(sim, enc: dict | None, h: float) -> str:
    if enc is None:
        return ""
    # (a pair at rest relative to each other: no d / v, which raised ZeroDivisionError in
    # place of the step's own error)
    speed = (f"at relative speed {enc['speed']:.3g} (d / v = "
             f"{enc['distance'] / enc['speed'] / abs(h):.3g} steps)" if enc['speed'] > 0 else
             "at rest relative to each other")
    return (f"the closest encounter at the step's start: {_name(sim, enc['i'])} and "
            f"{_name(sim, enc['j'])}, {enc['distance']:.3g} apart {speed}; ")


def _test_particle_failure(sim, st, sd, h: float, t: float, counters) -> UnresolvedStepError:
    """A fixed step refused for its test particle (the glue's check, layout.TEST_PARTICLE; the
    gravitating bodies are judged by the step's own estimate, status NOT_RESOLVED)."""
    from hbvm_md.rebound.glue import TP_FACTOR, TP_FLOOR
    i, err, s = int(sd[L.SL_CAUSE_STATUS]), float(sd[L.SL_CAUSE_ERR]), int(st[L.SL_S])
    ctx = int64s(int(st[L.SL_CTX]), L.N_HEADER)
    m = int(ctx[L.D_M])
    gammat = doubles(int(ctx[L.A_GAMMAT]), s * m).reshape(s, m)
    minv, kin_w = doubles(int(ctx[L.A_MINV]), m), doubles(int(ctx[L.A_KINW]), m)
    _, _, bound = test_particle_error(gammat, minv, kin_w, TP_FLOOR, TP_FACTOR, 0.0)
    # the estimate grows like h^(s-1): the step at which it would meet the bound, with a margin
    h_ok = 0.5 * abs(h) * (bound / err) ** (1.0 / (s - 1)) if err > 0 else abs(h)
    if i >= sim.N:
        # a group of three of the attached ODEs' components (they follow the particles in the
        # state, hbvm_md.rebound.forces, "Attached ODEs"), checked as a test particle is
        j = 3 * (i - sim.N)
        exc = UnresolvedStepError(h, err, bound, int(counters[C_LASTIT]), t, "")
        RuntimeError.__init__(exc, (
            f"HBVM step of size h={h:.6g} at t={t:.17g} does not resolve the attached ODEs: "
            f"their components {j} to {j + 2} (counted over sim._odes in order) have an error "
            f"estimate {err:.3e} (the weight of the last Legendre coefficient of their "
            f"derivative over the step) above {bound:.3g} (the larger of {TP_FLOOR:g} and "
            f"{TP_FACTOR:g} times the gravitating bodies' estimate): leave out `dt` "
            "(HBVMIntegrator(sim) takes adaptive steps), or use a smaller sim.dt (about "
            f"{h_ok:.2g} or less here), or pass energy_tol=None to accept such steps"))
        exc.particle, exc.encounter = None, None
        return exc
    enc = _encounter(sim, only=i, s=s)
    where = (f"passes {_name(sim, enc['j'])} {enc['distance']:.3g} away at relative speed "
             f"{enc['speed']:.3g} (d / v = {enc['distance'] / enc['speed'] / abs(h):.3g} "
             "steps); " if enc else "")
    through = "the test particles' encounters too"
    hint = (f"{where}leave out `dt` (HBVMIntegrator(sim) takes adaptive steps, which shrink "
            f"through {through}), or "
            f"use a smaller sim.dt (about {h_ok:.2g} or less here), or pass energy_tol=None to "
            "accept such steps")
    exc = UnresolvedStepError(h, err, bound, int(counters[C_LASTIT]), t, hint)
    where_t = f"HBVM step of size h={h:.6g} at t={t:.17g}"
    rule = (f"the larger of {TP_FLOOR:g} and {TP_FACTOR:g} times the gravitating bodies' "
            "estimate")
    RuntimeError.__init__(exc, (
        f"{where_t} does not resolve test {_name(sim, i)}: its own error "
        f"estimate {err:.3e} (the weight of the last Legendre coefficient of its acceleration "
        f"over the step) exceeds {bound:.3g} ({rule}), so its orbit leaves the run's "
        f"accuracy; it {hint}"))
    exc.particle, exc.encounter = i, enc
    return exc


def _step_failure(st: np.ndarray, sd: np.ndarray, sim=None):
    """The exception of a failed step, from what the compiled step recorded (``sim``: the
    simulation, as before the step: the particles a message names)."""
    status = int(st[L.SL_STATUS])
    if status == L.OUT_OF_MEMORY:
        return MemoryError("HBVM: the compiled step could not allocate its work arrays "
                           "(nothing was changed)")
    if status == L.BAD_DT:
        return ValueError(f"`sim.dt` must be a nonzero finite step size (got sim.dt="
                          f"{float(sd[L.SL_H_FAIL])!r}); set it to the step you want, e.g. a "
                          "fraction "
                          "of the shortest period")
    if status == L.BAD_SETTINGS:
        check_settings(st, sd)
    if status in (L.RESYNC, L.BAD_SETTINGS):
        raise RuntimeError("HBVM: the step refused the state its host had just prepared (an "
                           "internal inconsistency; please report it)")
    counters = doubles(int(st[L.SL_COUNTERS]), N_COUNTERS)
    h, t = float(sd[L.SL_H_FAIL]), float(sd[L.SL_T_FAIL])
    etol = float(sd[L.SL_ETOL])
    if status > TANGENT_FAILED:
        it = int(sd[L.SL_CAUSE_ERR])
        hint = ("the step of the particles converged but the tangent map of the variational "
                "particles did not; nothing was changed: try a smaller sim.dt or epsilon")
        if status - TANGENT_FAILED == NOT_FINITE:
            return NonFiniteError(h, it, "tangent map", t, hint)
        return ConvergenceError(h, math.nan, it, "tangent map", t, hint)
    if status == L.TEST_PARTICLE:
        return _test_particle_failure(sim, st, sd, h, t, counters)
    nonfinite = status == NOT_FINITE or (status == TOO_SMALL
                                         and int(sd[L.SL_CAUSE_STATUS]) == NOT_FINITE)
    # (the step hides its ODEs from REBOUND, sim.N_odes = 0, until the run ends: the ones it
    # was prepared with)
    odes = _record(ctypes.addressof(sim)).odes if sim is not None else None
    if nonfinite and odes:
        culprit = _ode_culprit(sim, odes)
        if culprit is not None:        # the attached ODE, not an encounter or the step size
            exc = NonFiniteError(h, int(counters[C_LASTIT]), "fixed_point", t, culprit)
            exc.encounter = None
            return exc
    if nonfinite and sim is not None and _record(ctypes.addressof(sim)).host_path:
        culprit = _force_culprit(sim)
        if culprit is not None:      # REBOUND's accelerations, not an encounter or the step
            # (the step asked for: an adaptive run shrank it to nothing before stopping)
            exc = NonFiniteError(float(sim.dt), int(counters[C_LASTIT]), "fixed_point", t,
                                 culprit)
            exc.encounter = None
            return exc
    enc = _encounter(sim, s=int(st[L.SL_S])) if sim is not None else None
    near = _encounter_text(sim, enc, h)
    which = int(st[L.SL_METHOD])                       # the message names the method run
    name = L.METHODS[which].upper() if 0 <= which < len(L.METHODS) else None
    if status == TOO_SMALL:
        cause_status = int(sd[L.SL_CAUSE_STATUS])
        cause = (f"error estimate {sd[L.SL_CAUSE_ERR]:.3e} > epsilon={sd[L.SL_EPSILON]:.3e}"
                 if cause_status == OK else
                 str(step_error(cause_status, h, t, counters, "fixed_point", energy_tol=etol,
                                hints={k: "a smaller step" for k in _HINTS}, method=name,
                                error_bound=ERROR_BOUND, s=int(st[L.SL_S]))))
        exc = StepSizeError(h, float(sd[L.SL_MIN_DT]), t, near + cause)
    else:
        kepler = bool(st[L.SL_KEPLER])
        # (the composed step takes fixed steps only: adaptive ones are plain HBVM's)
        way_out = (_WAY_OUT_KEPLER if kepler else
                   "or leave out `dt` (HBVMIntegrator(sim) takes adaptive steps, which shrink "
                   "through encounters)")
        hints = {k: near + (v.replace(_WAY_OUT, _WAY_OUT_KEPLER) if kepler else v)
                 for k, v in _HINTS.items()}
        hints["drifted"] = _DRIFTED_HINT
        if status == NOT_RESOLVED and sim is not None:
            body = int(counters[C_WORST])
            if kepler:
                # the composed state's blocks are the planets 1 .. N-1, then the clock
                # (tau, p_tau: the perturbation's rate, systems.flow_composed)
                who = (_name(sim, body + 1) if 0 <= body < sim.N - 1 else
                       "the perturbation p_tau")
                hints["body"] = who.replace("{", "{{").replace("}", "}}")
            elif 0 <= body < sim.N:
                hints["body"] = _name(sim, body).replace("{", "{{").replace("}", "}}")
            hints["resolution"] = near + way_out
            hints["switch_off"] = "energy_tol=None"
        exc = step_error(status, h, t, counters, "fixed_point", energy_tol=etol,
                         hints=hints, method=name, error_bound=ERROR_BOUND,
                         s=int(st[L.SL_S]))
    exc.encounter = enc
    return exc


#: what yDot holds before an ODE's derivatives is called here: a nan no arithmetic makes
_UNWRITTEN = np.array([0x7FF8DEAD0000BEEF], dtype=np.int64).view(np.float64)[0]


def _ode_culprit(sim, odes) -> str | None:
    """Why an attached ODE makes the step non-finite, or None: each ODE of ``odes``
    (:func:`hbvm_md.rebound.forces.ode_signature` as prepared) has its ``derivatives``
    called once at the step's start (sim as before the step, its own ``y``, sim.t) into a
    yDot marked unwritten; the first component left unwritten (REBOUND's BS keeps what yDot
    held, zero at first) or not finite is named, with the way out."""
    call = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                            ctypes.c_double)
    t = float(sim.t)
    for j, (a, n, y, deriv, _pre, _post, _ydot) in enumerate(odes):
        if not (deriv and y and n):
            continue
        yd = np.full(n, _UNWRITTEN)
        call(deriv)(a, yd.ctypes.data, y, t)
        unwritten = yd.view(np.int64) == _UNWRITTEN.view(np.int64)
        bad = ~np.isfinite(yd) & ~unwritten
        which = f"the attached ODE sim._odes[{j}] (length {n})"
        if unwritten.any():
            i = int(np.flatnonzero(unwritten)[0])
            return (f"{which} leaves yDot[{i}] unwritten in its derivatives (at the step's "
                    f"start, t={t!r}; {int(unwritten.sum())} of {n} components): HBVM takes no "
                    "stale value for it (REBOUND's BS keeps whatever yDot held); write every "
                    f"component, yDot[{i}] = 0.0 for a constant one (a Python derivatives "
                    "function that raised leaves them unwritten too: its traceback is printed "
                    "above)")
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            return (f"{which} returns yDot[{i}] = {float(yd[i])!r} from its derivatives at the step's "
                    f"start (t={t!r}, y[{i}] = "
                    f"{float(np.ctypeslib.as_array((ctypes.c_double * n).from_address(y))[i])!r}"
                    "): no step size helps; check the ODE's derivatives function there")
    return None


def _force_culprit(sim) -> str | None:
    """Why REBOUND's own accelerations make the step non-finite, or None: they are computed
    once at the step's start (sim as before the step; ``reb_simulation_update_acceleration``:
    gravity, ``sim.additional_forces``, REBOUNDx's forces) and the first particle whose
    acceleration is not finite is named, with the way out.  The particles' positions and
    velocities are left as they were (the accelerations are scratch: each stage computes
    them)."""
    N = int(sim.N)
    stride = ctypes.sizeof(_rebound().Particle) // 8
    ptr = ctypes.cast(sim._particles, ctypes.c_void_p).value
    if not N or not ptr:
        return None
    view = doubles(ptr, N * stride).reshape(N, stride)
    keep = view.copy()
    ax = _REG["ax"]
    try:
        _rebound().clibrebound.reb_simulation_update_acceleration(
            ctypes.c_void_p(ctypes.addressof(sim)))
        acc = view[:, ax:ax + 3].copy()
    finally:
        view[:] = keep
    bad = np.flatnonzero(~np.all(np.isfinite(acc), axis=1))
    if bad.size == 0:
        return None
    i = int(bad[0])
    return (f"REBOUND's accelerations are not finite at the step's start (t={float(sim.t)!r}): "
            f"{_name(sim, i)} has a = {tuple(float(a) for a in acc[i])!r} "
            f"({bad.size} of {N} particles), from {_force_name(sim)}: no step size helps; "
            "check that force there")


def _python_core(r: int, p: int) -> int:
    """The step as Python (``NUMBA_DISABLE_JIT``): the glue's :func:`step_arrays` on numpy
    views of the same memory the compiled :func:`core_step` views."""
    try:
        return record_of_state(p).python_step(r, p)
    except BaseException as exc:  # noqa: BLE001
        _PENDING[r] = exc
        return L.PREPARE_FAILED


# -- prepare: the model, the compiled step and the context block from the particles ----------------
def method_of(st: np.ndarray) -> HBVM | EQUIP:
    """The HBVM(k, s) or EQUIP(k, s) a state's settings name (ValueError naming a bad one)."""
    nodes, which = int(st[L.SL_NODES]), int(st[L.SL_METHOD])
    if not 0 <= which < len(L.METHODS):
        raise ValueError(f"`sim.integrator.method` must be one of {L.METHODS} (got {which}): "
                         "'hbvm' conserves the energy, 'equip' the energy and the angular momentum")
    if not 0 <= nodes < len(L.NODES):
        raise ValueError(f"`sim.integrator.nodes` must be 'gauss' or 'lobatto' (got {nodes})")
    if L.METHODS[which] == "equip":
        if L.NODES[nodes] != "gauss":
            raise ValueError(f"`sim.integrator.nodes` must be 'gauss' with method='equip' (got "
                             f"{L.NODES[nodes]!r}): EQUIP perturbs the Gauss method")
        return EQUIP(int(st[L.SL_K]), int(st[L.SL_S]))
    return HBVM(int(st[L.SL_K]), int(st[L.SL_S]), nodes=L.NODES[nodes])


def check_settings(st: np.ndarray, sd: np.ndarray) -> HBVM | EQUIP:
    """Check the settings in ``sim.integrator`` (a user may change them between runs; the
    compiled step checks the same ranges, ``particles.settings_ok``); returns the method."""
    method = method_of(st)
    bad = [(n, v, want) for n, v, want in (
        ("max_iter", int(st[L.SL_MAX_ITER]), "a positive integer"),
        ("tol", float(sd[L.SL_TOL]), "in [0, 1) (0: round-off)"),
        ("energy_tol", float(sd[L.SL_ETOL]), "a finite number >= 0 (0: no check), or in "
         "(-1, 0) for the not-a-solution rule"),
        ("max_dt", float(sd[L.SL_MAX_DT]), "a finite number >= 0 (0: no bound on the adaptive "
         "step)"))
        if not (v >= 1 if n == "max_iter" else
                0 <= v < 1 if n == "tol" else
                0 <= v < math.inf if n == "max_dt" else -1 < v < math.inf)]
    if bad:
        n, v, want = bad[0]
        raise ValueError(f"`sim.integrator.{n}` must be {want} (got {v!r})")
    if st[L.SL_KEPLER] not in (0, 1):
        raise ValueError(f"`sim.integrator.kepler` must be 0 (plain HBVM) or 1 (HBVM composed "
                         f"with the Keplerian flows) (got {int(st[L.SL_KEPLER])})")
    if st[L.SL_KEPLER] and st[L.SL_ADAPTIVE] and sd[L.SL_EPSILON] != 0.0:
        raise ValueError(
            "sim.integrator.kepler = 1 takes fixed steps of sim.dt only (the composed step's "
            "clock row hides the planets from the step-size controller's estimate, as in "
            "systems.flow_composed); set sim.integrator.epsilon = 0 (fixed steps of sim.dt, as "
            "with IAS15), or attach with HBVMIntegrator(sim, kepler=True, dt=...); for adaptive "
            "steps use sim.integrator.kepler = 0")
    if st[L.SL_KEPLER] and isinstance(method, EQUIP):
        raise ValueError("sim.integrator.kepler = 1 composes HBVM with the Keplerian flows; "
                         "method='equip' is not composed: use method='hbvm', or kepler = 0")
    if st[L.SL_ADAPTIVE] and sd[L.SL_EPSILON] != 0.0:   # (0: fixed steps, as IAS15's)
        try:
            check_adaptive(float(sd[L.SL_EPSILON]), float(sd[L.SL_MIN_DT]), method.s)
        except ValueError as exc:
            raise ValueError(f"sim.integrator: {exc}; sim.integrator.epsilon = 0 takes fixed "
                             "steps of sim.dt, as with IAS15") from None
    return method


def _prepare(sim, p: int) -> None:
    """Build (again) what the compiled step needs: check the simulation and the settings, the
    N-body model of the particles, the compiled step and the context block; keep the saved state
    (compensations, gamma) when it is the particles' (a loaded or copied run), else start it
    afresh from the particles."""
    st, sd = _slots(p)
    _release_odes(ctypes.addressof(sim))     # (hidden by the last step, when a run resyncs)
    if not st[L.SL_CTX] and st[L.SL_CONTROL] != L.CONTROL:
        if st[L.SL_NSTEPS] > 0:            # (a file saved before the field existed)
            _adopt_old_epsilon(st, sd)
        st[L.SL_CONTROL] = L.CONTROL
    method = check_settings(st, sd)
    check_simulation(sim)
    if st[L.SL_KEPLER]:
        from hbvm_md.rebound.composed import prepare_composed
        prepare_composed(sim, p, method)
        return
    h = sim.dt
    if not (math.isfinite(h) and h != 0.0):
        _step_size("sim.dt", h)
    N = sim.N
    offsets = _REG["offsets"]
    stride = offsets[L.R_STRIDE - L.R_T]
    ix, ivx, im = (offsets[i - L.R_T] for i in (L.R_X, L.R_VX, L.R_M))
    ptr = ctypes.cast(sim._particles, ctypes.c_void_p).value
    if N == 0 or not ptr:
        n_odes = int(sim._N_odes)
        if n_odes:
            raise ValueError(
                f"the simulation has no particles, only {n_odes} attached ODE"
                f"{'s' if n_odes > 1 else ''}: HBVM integrates attached ODEs together with the "
                "particles (at the bodies' stages) and refuses a scene without bodies; integrate "
                "ODEs alone with sim.integrator = 'BS' (REBOUND's integrator for ODEs, as its "
                "test_bs does), or add the particles they belong to")
        raise ValueError("the simulation has no particles; add them (sim.add(...)) before "
                         "integrating")
    view = doubles(ptr, N * stride).reshape(N, stride)
    na = sim.N_active
    x, v = view[:, ix:ix + 3], view[:, ivx:ivx + 3]
    s = method.s
    if isinstance(method, EQUIP) and sim.N_var > 0:
        raise ValueError(f"{sim.N_var} variational particles with method='equip': the tangent "
                         "map is the derivative of the HBVM step, and EQUIP's step adds a "
                         "correction whose derivative it does not take; use method='hbvm'")
    reasons = host_reasons(sim)
    model_changed = _model_changed(st, sim, bool(reasons))
    if reasons:
        # REBOUND's own accelerations at the stages (hbvm_md.rebound.forces), in the separable
        # form: the state (q, clock, v, CLOCK), with the stage velocities for a force that reads
        # them
        _check_host_path(sim, method, reasons)
        _clear_gravity_ignore(sim)
        if sim._additional_forces:
            _probe_velocities(sim, view, ix, ivx, reasons)
        scene = ReboundScene(sim, (stride, ix, ivx, _REG["ax"], offsets[0]), ptr)
        nb = None
        c_step = False
        # (variational particles are refused on this path: no tangent map is compiled)
        binding = Binding(method, scene, form="separable", fast=None,
                          glue="hbvm_md.rebound.glue", velocities=scene.velocities)
        dim = scene.dim
        u, vw = dim, binding.minv[:3 * N]                  # (1: the state holds v)
    else:
        nb = NBody(view[:, im].copy(), G=sim.G, n_active=None if na < 0 or na >= N else na)
        # the tangent map is compiled only for a simulation with variational particles (a
        # change of N_var moves particles_var: the compiled step asks for a resync, and this
        # builds it again).  The plain case runs the C step of hbvm_md.rebound.csrc on the
        # compiled core (cglue.COVERS): its binding is the engine's, nothing compiled
        c_step = cglue.plain_step(method, nb, False, sim.N_var)
        binding = Binding(method, nb, form="separable", fast=None,
                          glue=None if c_step else "hbvm_md.rebound.glue",
                          jvp=nbody_force_jvp if sim.N_var > 0 else None)
        if c_step and not getattr(binding.step_code, "core", False):
            c_step = False          # (the core refused the kernel: the numba glue serves)
            binding = Binding(method, nb, form="separable", fast=None,
                              glue="hbvm_md.rebound.glue")
        dim = nb.dim
        u, vw = dim, binding.minv
    y, g, c = (doubles(int(st[a]), int(st[n])) for a, n in
               ((L.SL_Y, L.SL_NY), (L.SL_GAMMA, L.SL_NGAMMA), (L.SL_COUNTERS, L.SL_NCOUNTERS)))
    same = not model_changed and y.size == 4 * dim and g.size == s * u
    keep = (same and np.array_equal(y[:3 * N], x.reshape(-1))
            and np.array_equal(y[dim:dim + 3 * N] * vw, v.reshape(-1)))
    if (same and not keep and np.isfinite(sd[L.SL_H_PREV]) and np.all(np.isfinite(x))
            and np.all(np.isfinite(v))):
        # a saved or copied run whose particles were moved after its last step (a REBOUNDx
        # operator, a post-timestep callback): read them as the compiled step reads particles
        # moved between two steps (particles.reread_particles: q = x, p = v / minv, the
        # compensations zeroed, the previous coefficients and step kept as the next step's
        # initial guess), so that the continued run is the uninterrupted one bit for bit (it
        # started afresh here: restarts with integrate_force differed by 1e-14 to 6e-11).
        # Only after a step (h_prev known): before any, the fresh start below (p = m v) is the
        # uninterrupted run's, also when a signal stopped the first preparation halfway.
        if nb is not None:
            y0 = np.concatenate([x.reshape(-1), v.reshape(-1) / vw])
            check_particles(y0, nb)
        else:                   # (v / 1: the state of REBOUND's own accelerations holds v)
            y0 = scene.state(x, v, sim.t)
        y[:] = 0.0
        y[:2 * dim] = y0
        sd[L.SL_EREF:L.SL_EREF + L.N_EREF] = np.nan
        st[L.SL_RESYNCS] += 1
        keep = True
    if keep and nb is not None and _masses_changed(st, sim):
        # a mass changed between runs on a body at rest (p = 0 = m v whatever m): the state is
        # kept, but the reference energy is the old masses' and would refuse the next step
        # (a jump of the potential, not the step's error); the check starts afresh from it
        sd[L.SL_EREF:L.SL_EREF + L.N_EREF] = np.nan
    elif keep and nb is not None and not st[L.SL_CTX]:
        # a loaded or copied run kept: no record of the masses its reference energy was
        # computed with (a mass changed after loading, on a body at rest, was refused as
        # above).  The energy alone starts afresh: the check computes it from the kept state
        # by the same function that computed the saved one at the last commit (loop.
        # energy_check), so an unchanged run continues bit for bit; EQUIP's alpha and slope
        # (an initial guess and its slope) stay.  The run's start (the drift check's anchor,
        # core.DRIFT_BOUND), its mean T and time stay when the masses are those they were
        # taken with (SL_EREF_MASSES, saved): the continued run refuses or passes as the
        # uninterrupted one; with other masses (changed after loading) they start afresh,
        # since measured from the saved start a mass change would read as the run's drift
        sd[L.SL_EREF] = np.nan
    if not keep:
        if nb is not None:
            q0 = x.reshape(-1).copy()
            y0 = np.concatenate([q0, nb.momenta_from_velocities(v.copy())])
            check_particles(y0, nb)
        else:
            y0 = scene.state(x, v, sim.t)
            if not np.all(np.isfinite(y0)):
                raise ValueError("the simulation holds non-finite positions or velocities")
        y = _array(st, L.SL_Y, L.SL_NY, 4 * dim)
        y[:] = 0.0
        y[:2 * dim] = y0
        _array(st, L.SL_GAMMA, L.SL_NGAMMA, s * u)[:] = 0.0
        sd[L.SL_H_PREV] = np.nan
        sd[L.SL_EREF:L.SL_EREF + L.N_EREF] = np.nan    # energy, EQUIP's alpha, slope, run's start
        st[L.SL_RESYNCS] += 1
    if keep and not st[L.SL_CTX] and sd[L.SL_EREF_MASSES] != masses_digest(sim):
        sd[L.SL_EREF_RUN] = np.nan          # (a loaded or copied run with other masses)
    sd[L.SL_EREF_MASSES] = masses_digest(sim)
    if nb is None:       # (a loaded or copied run's reference: as _forget_host_energy)
        sd[L.SL_EREF] = np.nan
    if nb is None and scene.nz:
        y = doubles(int(st[L.SL_Y]), 4 * dim)
        zq = slice(3 * N, 3 * N + scene.nz)
        zp = slice(dim + 3 * N, dim + 3 * N + scene.nz)
        if not (keep and scene.adopt_sigma(y[zp].copy())):
            # the ODEs' block from their y at the scene's sigma, their positions 0 (nothing
            # reads them), their coefficients afresh (the initial guess only); with the sigma
            # of a kept state (a resync, or a loaded or copied run with its ODEs attached
            # again) the compiled step rereads an ODE's y only where it changed, and the run
            # goes on as the uninterrupted one
            y[zq] = y[2 * dim:][zq] = 0.0
            y[zp], y[2 * dim:][zp] = scene.ode_state(), 0.0
            doubles(int(st[L.SL_GAMMA]), s * u).reshape(s, u)[:, zq] = 0.0
        binding.params[:] = scene.params       # (the sigma taken: one array when not copied)
    if c.size != N_COUNTERS:
        _array(st, L.SL_COUNTERS, L.SL_NCOUNTERS, N_COUNTERS)[:] = 0.0
    # |T| + |V| of the gravitating bodies is the energy check's scale.  It is zero only for at
    # most one gravitating body, at rest (the restricted problem with a star at rest): then it
    # stays zero and there is nothing to check (the test particles' own check, glue.TP_FLOOR,
    # still runs on a fixed step).
    # On REBOUND's own accelerations the check guards the H of hbvm_md.rebound.forces when the
    # added forces have one, and is off otherwise (the step control carries the run).
    if nb is None:
        check = scene.hamiltonian
    else:
        check = bool(np.count_nonzero(nb.is_source) >= 2 or nb.kinetic(y[dim:2 * dim]) != 0)
    if not check and nb is not None and sd[L.SL_ETOL] > 0 and not st[L.SL_ECHECK] == -1:
        warnings.warn("HBVM: the gravitating bodies have no energy (a single body at rest), so "
                      "energy_tol's energy check checks nothing here; test particles are checked "
                      "by their own error estimates (fixed steps) or the step control (adaptive)",
                      RuntimeWarning, stacklevel=_user_stacklevel())
    st[L.SL_ECHECK] = 1 if check else -1
    _context(st, binding, method, nb, view, ptr, sim, ix, ivx, im, host_forces=nb is None,
             work=np.zeros(ccore.work_size(method.k, s, binding.minv.shape[0],
                                           binding.params if binding.follow else None))
             if c_step else None, follow=c_step and binding.follow is not None)
    code = binding.step_code
    if code.kind != "compiled" and sim.N_var > 0 and sim._calculate_megno:
        raise ValueError("HBVM hands MEGNO to REBOUND from its compiled step only; unset "
                         "NUMBA_DISABLE_JIT to compute MEGNO with HBVM")
    if c_step:
        st[L.SL_CORE] = cglue.addresses()[2]
    elif code.kind == "compiled":
        st[L.SL_CORE] = code.core_step.address
    else:
        record_of_state(p).python_step = _python_step(code, st)
        st[L.SL_CORE] = _REG["python_core"]
    rec = record_of_state(p)
    rec.forces = tuple(reboundx_forces(sim) or ())
    rec.kepler_terms = None
    rec.odes = ode_signature(sim)
    if sim.extras:
        _warn_operators(sim, _operators(sim))
    rec.host_path = nb is None


def _adopt_old_epsilon(st: np.ndarray, sd: np.ndarray) -> None:
    """A simulation saved by hbvm-md before 2026-12-08 (no ``controller`` field): its epsilon
    meant the former controller's, whose default 1e-3 kept the energy at round-off; epsilon
    now bounds each step's own local error estimate relative to its motion, and 1e-3 would take
    steps some 20 times longer, far from round-off.  The former default becomes today's
    (DEFAULT_EPSILON: the continued run keeps the accuracy it had), with a warning; another
    value is kept, with a warning saying what it now means and what to set."""
    if not (st[L.SL_ADAPTIVE] and sd[L.SL_EPSILON] > 0.0):
        return
    eps = float(sd[L.SL_EPSILON])
    if eps == L.OLD_DEFAULT_EPSILON:
        sd[L.SL_EPSILON] = DEFAULT_EPSILON
        msg = (f"HBVM: this simulation was saved by hbvm-md before 2026-12-08 with the default "
               f"epsilon={eps:g} of the step control of that time; epsilon now bounds each "
               f"step's own local error estimate (relative to its motion), whose default is "
               f"{DEFAULT_EPSILON:g}: sim.integrator.epsilon is set to that, so that the "
               "continued run keeps the accuracy it had")
    else:
        msg = (f"HBVM: this simulation was saved by hbvm-md before 2026-12-08 with "
               f"epsilon={eps:g} for the step control of that time; epsilon now bounds each "
               f"step's own local error estimate (relative to its motion) and {eps:g} means a "
               f"far looser run than it did. Set sim.integrator.epsilon again: "
               f"{DEFAULT_EPSILON:g}, the default, keeps the energy at round-off")
    warnings.warn(msg, RuntimeWarning, stacklevel=_user_stacklevel())


def _force_name(sim, reasons=None) -> str:
    """The added forces by name: REBOUNDx's, or the user's Python function (held by the user's
    Simulation object of the run in progress, :class:`_Run`)."""
    reasons = host_reasons(sim) if reasons is None else reasons
    if any(r.startswith("REBOUNDx") for r in reasons):
        return ", ".join(r for r in reasons if r.startswith("REBOUNDx"))
    run = getattr(_RUN, "run", None)
    while run is not None and run.addr != ctypes.addressof(sim):
        run = run.outer
    try:
        import gc
        afp = run.sim._afp               # (REBOUND's ctypes wrapper of the user's function)
        fn = next(r for r in gc.get_referents(afp) if callable(r) and not isinstance(r, type))
        return f"sim.additional_forces ({getattr(fn, '__qualname__', fn)!r})"
    except Exception:  # noqa: BLE001 - a C function, or another Python than CPython
        return "sim.additional_forces"


def _probe_run(sim) -> None:
    """:func:`_probe_velocities` at the start of a run on REBOUND's own accelerations (the
    step's preparation probes the first run): a force may start reading the velocities later
    (a drag switched on at some time)."""
    if not sim._additional_forces:
        return
    ptr = ctypes.cast(sim._particles, ctypes.c_void_p).value
    N = sim.N
    if not ptr or N == 0:
        return
    offsets = _REG["offsets"]
    ix, ivx = (offsets[i - L.R_T] for i in (L.R_X, L.R_VX))
    view = doubles(ptr, N * offsets[L.R_STRIDE - L.R_T]).reshape(N, -1)
    _probe_velocities(sim, view, ix, ivx)


def _probe_velocities(sim, view, ix, ivx, reasons=None) -> None:
    """A force that reads the velocities without ``sim.force_is_velocity_dependent`` would see
    the step's initial velocities at every stage (as IAS15's substeps then do): integrated to
    first order only, in silence (a drag ended 1.1 off, 30 times IAS15's error under the same
    mistake).  So the forces are evaluated once more with the velocities moved: when the
    accelerations move with them, the flag is set (the stages then hand the force their own
    velocities, order 2s) and a warning names the force and the flag.  The particles' positions
    and velocities are as before; the accelerations are scratch (each stage computes them).
    Done when the step is prepared and at the start of every later run (:func:`_probe_run`):
    two evaluations of the forces a run.  A force that writes the particles' velocities or
    positions (a kick in the force) is warned about: the stages drop what it writes there."""
    lib = _rebound().clibrebound
    ax = _REG["ax"]
    v0 = view[:, ivx:ivx + 3].copy()
    x0 = view[:, ix:ix + 3].copy()
    scale = float(np.max(np.abs(v0))) or 1.0
    # every component moved, by different amounts, so that no symmetry of a force hides it
    dv = 1e-3 * scale * (1.0 + np.arange(v0.size).reshape(v0.shape) / v0.size)
    flagged = bool(sim.force_is_velocity_dependent)
    try:
        lib.reb_simulation_update_acceleration(ctypes.c_void_p(ctypes.addressof(sim)))
        a0 = view[:, ax:ax + 3].copy()
        wrote = {name for name, part, was in (("velocities", view[:, ivx:ivx + 3], v0),
                                              ("positions", view[:, ix:ix + 3], x0))
                 if not np.array_equal(part, was)}
        view[:, ix:ix + 3] = x0
        view[:, ivx:ivx + 3] = v0 + dv
        lib.reb_simulation_update_acceleration(ctypes.c_void_p(ctypes.addressof(sim)))
        a1 = view[:, ax:ax + 3].copy()
        wrote |= {name for name, part, was in (("velocities", view[:, ivx:ivx + 3], v0 + dv),
                                               ("positions", view[:, ix:ix + 3], x0))
                  if not np.array_equal(part, was)}
        wrote = sorted(wrote, reverse=True)         # (velocities, then positions)
    finally:
        view[:, ivx:ivx + 3] = v0
        view[:, ix:ix + 3] = x0
    if wrote:
        warnings.warn(
            f"{_force_name(sim, reasons)} writes the particles' {' and '.join(wrote)}: HBVM's "
            "stages take only the accelerations it writes (each stage sets the positions and "
            "velocities of its own state before calling it, as IAS15's substeps do), so what it "
            "writes there is dropped. Write the effect as an acceleration (a drag: "
            "p.ax -= gamma * p.vx, with sim.force_is_velocity_dependent = 1), or change the "
            "particles between steps (sim.post_timestep_modifications, a REBOUNDx operator)",
            RuntimeWarning, stacklevel=_user_stacklevel())
    if flagged or np.array_equal(a0, a1) or not (np.all(np.isfinite(a0))
                                                 and np.all(np.isfinite(a1))):
        return
    sim.force_is_velocity_dependent = 1
    warnings.warn(
        f"{_force_name(sim, reasons)} changes the accelerations when the velocities change, but "
        "sim.force_is_velocity_dependent was 0: its stages would have seen the step's initial "
        "velocities (a first-order error, as IAS15's substeps under the same setting); HBVM "
        "set sim.force_is_velocity_dependent = 1 (each stage hands the force its own "
        "velocities: order 2s). Set it yourself after setting the force to silence this warning",
        RuntimeWarning, stacklevel=_user_stacklevel())


def _check_host_path(sim, method, reasons) -> None:
    """What the step on REBOUND's own accelerations cannot do, refused with the reason."""
    why = ", ".join(reasons)
    if isinstance(method, EQUIP):
        raise ValueError(f"method='equip' needs the separable N-body step; this scene has {why} "
                         "and runs on REBOUND's own accelerations: use method='hbvm'")
    if sim.N_var > 0:
        raise ValueError(f"variational particles with {why}: HBVM's tangent map differentiates "
                         "its own N-body kernel, not REBOUND's forces; use IAS15")
    import numba
    if numba.config.DISABLE_JIT:
        raise ValueError(f"this scene ({why}) runs on REBOUND's own accelerations, called from "
                         "compiled code only; unset NUMBA_DISABLE_JIT")


def _clear_gravity_ignore(sim) -> None:
    """REBOUND's gravity skips the terms WHFast or MERCURIUS left flagged in
    ``gravity_ignore``; a direct step needs every term (IAS15 clears it at each step too)."""
    f = type(sim).gravity_ignore
    (ctypes.c_int if f.size == 4 else ctypes.c_int64).from_address(
        ctypes.addressof(sim) + f.offset).value = 0


def _python_step(code, st):
    """The glue's step_arrays run as Python on views of the state and context block."""
    def step(r: int, p: int) -> int:
        st_, sd = _slots(p)
        ctx = int64s(int(st_[L.SL_CTX]), L.N_HEADER)
        head = int(ctx[L.R_HEAD])
        simi = int64s(r, head)
        simd = simi.view(np.float64)
        N = int(ctx[L.D_N])
        if simi[ctx[L.R_PARTICLES]] != ctx[L.D_PTR] or simi[ctx[L.R_N]] != N or any(
                st_[a] != ctx[b] for a, b in ((L.SL_S, L.D_S), (L.SL_K, L.D_K),
                                               (L.SL_NODES, L.D_NODES),
                                               (L.SL_METHOD, L.D_METHOD),
                                               (L.SL_KEPLER, L.D_KEPLER))):
            return L.RESYNC
        s, m = (int(ctx[i]) for i in (L.D_S, L.D_M))
        u = m
        nv = int(ctx[L.D_NV])
        tnc, tsr, wpp, cpp, kk = (int(ctx[i]) for i in (L.D_TNC, L.D_TSR, L.D_WPP, L.D_CPP,
                                                         L.D_KK))

        def f(slot, shape, dtype=np.float64):
            n = int(np.prod(shape))
            size = n * np.dtype(dtype).itemsize
            if size == 0:
                return np.zeros(shape, dtype)
            return np.frombuffer((ctypes.c_char * size).from_address(int(ctx[slot])),
                                 dtype).reshape(shape)
        y = doubles(int(st_[L.SL_Y]), 4 * m)
        view = doubles(int(ctx[L.D_PTR]), N * int(ctx[L.R_STRIDE])).reshape(N, -1)
        vidx = f(L.A_VIDX, (nv, 2))
        rows = max(int(v0) + (1 if tp >= 0 else N) for v0, tp in vidx) if nv else 0
        pv = f(L.D_PVAR, (rows, int(ctx[L.R_STRIDE]))) if nv else np.zeros((0, 1))
        return int(code.step_arrays(
            Rebound(simd, simi, view, ctx, r, pv),
            Host(st_, sd, sd[L.SL_RES:L.SL_RES + L.N_RES], f(L.A_WRITTEN, (N, 7)),
                   f(L.A_HOST, L.N_HOST), vidx, f(L.A_DGS, (nv, s, m))),
            R.System(False, f(L.A_MINV, u), f(L.A_KINW, m),
                     f(L.A_PARAMS, int(ctx[L.D_P]))),
            R.State(y[:2 * m], y[2 * m:], doubles(int(st_[L.SL_GAMMA]), s * u).reshape(s, u),
                    sd[L.SL_EREF:L.SL_EREF + L.N_EREF], f(L.A_CLOCK, 2)),
            R.State(f(L.A_YT, 2 * m), f(L.A_CYT, 2 * m), f(L.A_GAMMAT, (s, u)),
                    f(L.A_EREFT, L.N_EREF), f(L.A_CLOCK, 2)),
            R.Method(f(L.A_TN, (2, tnc)), f(L.A_TS, (tsr, s)), f(L.A_WP, (wpp, s, kk)),
                     f(L.A_CP, (cpp, kk, s))),
            R.Newton(f(L.A_NV, (s, s), complex), f(L.A_NVINV, (s, s), complex),
                     f(L.A_NM, (0, m, m), complex)),
            R.Work(f(L.A_WORK, int(ctx[L.D_NF])), f(L.A_CWORK, int(ctx[L.D_NC]), complex),
                   doubles(int(st_[L.SL_COUNTERS]), N_COUNTERS)),
            R.Extrapolation(f(L.A_E1, (s, s)), f(L.A_ET, s), f(L.A_EW, s), f(L.A_EBUF, (s, s)),
                            f(L.A_EZERO, (s, s))),
            R.Tangents(f(L.A_V, (nv, 2 * m)), f(L.A_DG, (nv, s, m)), f(L.A_VT, (nv, 2 * m)),
                       f(L.A_DGT, (nv, s, m)), f(L.A_TW, int(ctx[L.D_TGF])),
                       f(L.A_TCW, int(ctx[L.D_TGC]), complex), f(L.A_TCOUNT, 3),
                       f(L.A_TP, (nv, 6 * N + 3)), f(L.A_TO, (nv, 3)))))
    return step
