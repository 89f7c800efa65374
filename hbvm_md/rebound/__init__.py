"""HBVM(k, s) inside REBOUND: an integrator registered with REBOUND's plug-in interface.

``import hbvm_md`` registers HBVM with REBOUND (``reb_integrator_register``) under the name
``"hbvm"``, once per process.  Then ``sim.integrator = "hbvm"`` works as for a built-in
integrator, with HBVM's defaults (adaptive steps, s = 6, the default epsilon of
:mod:`integrators.engine` and k for it), and :class:`HBVMIntegrator` ``(sim, s=..., k=...,
dt=..., ...)`` selects it with checked settings (and k measured on the scene for a fixed step).  REBOUND owns the run: time, exact finish
times, ``steps_done``, heartbeats, pre- and post-timestep callbacks, collisions (its search and
resolve functions run after each step), SIGINT, simulation archives, ``save_to_file``,
``copy`` and pickling.  This package holds the glue only; the step is :mod:`integrators.loop`.
``HBVMIntegrator(sim, method="equip", ...)`` (with EQUIP's own adaptive defaults, s = 8 at
epsilon 1e-4; or ``sim.integrator.method = "equip"``, a saved field like ``s`` and ``k``,
which keeps the s and epsilon set) runs EQUIP(k, s) (:class:`integrators.EQUIP`) in the same step:
the host passes its packed arrays (their shapes in the context block), sizes the work buffers
for its ``work_rows``, and keeps its alpha and slope (warm starts of the energy condition)
beside the reference energy in the saved state, so a copy, a file or an archive of an EQUIP run
continues bit for bit.

Modules: :mod:`~hbvm_md.rebound.layout` (every memory layout: HBVM's state, the step's context
block, REBOUND's offsets read from its ctypes structures), :mod:`~hbvm_md.rebound.cabi` (the
step REBOUND calls and the state's ``free``, compiled at registration),
:mod:`~hbvm_md.rebound.glue` (compiled with the step: one REBOUND step),
:mod:`~hbvm_md.rebound.host` (registration, the callbacks, the run's exceptions),
:mod:`~hbvm_md.rebound.checks` (what is refused) and :mod:`~hbvm_md.rebound.integrator`
(:class:`HBVMIntegrator`, the options and their checks).

How the design answers REBOUND's questions
------------------------------------------
Where the compiled step finds HBVM's per-simulation state
    REBOUND calls ``step(r, r->integrator.state)``.  The state is what our ``create`` returned:
    a block of 8-byte slots (:mod:`~hbvm_md.rebound.layout`) holding the settings, the counts,
    the C-allocated arrays of the double-double state (q, p and their compensations), the last
    step's coefficients gamma and the core's counters, and, not saved, the address of the
    compiled step and of a context block (the method's arrays, work buffers, the particles as
    last written, REBOUND's offsets).  Everything lives in C memory that the state's ``free``
    releases: nothing in Python has to outlive or track a simulation.

How a loaded, copied or new simulation gets its compiled step
    The registered step is a small compiled dispatcher (:func:`~hbvm_md.rebound.cabi.dispatch`)
    that does not depend on the force kernel.  When the state has no compiled step yet (a new,
    loaded, copied or unpickled simulation, in any process that imported ``hbvm_md``), or the
    step answers that the particles, G, N_active or the method are not what it last saw
    (particles added, removed, merged by a collision or edited by the user), it calls the
    host's ``prepare`` once, a Python ctypes callback: it checks the simulation, builds the
    N-body model and the compiled step (loaded from numba's cache) and the context block, and
    keeps the saved state when it is the particles' own (a continued run), else starts it
    afresh from them.  Then the step runs.  A normal step is two compiled calls, no Python.

How a failed step surfaces
    The core's step works on trial arrays: a failed step (no convergence, non-finite values,
    an energy change above ``energy_tol``, a fixed step's test particle whose own error
    estimate is out of bounds, an adaptive step below ``min_dt``) changes neither
    the particles nor ``t`` (REBOUND counts the attempt in ``steps_done``, as it counts IAS15's
    rejected steps).  The dispatcher then calls the host's ``fail`` callback, which builds the
    exception (ConvergenceError, UnresolvedStepError, StepSizeError, ... with their messages),
    naming the closest encounter at the step's start and the ways out,
    sets REBOUND's status to GENERIC_ERROR and queues the message with REBOUND's
    ``reb_simulation_error``, so REBOUND's own loop stops and a caller of the C library sees the
    error.  REBOUND's Python maps a run's status and messages to its own exceptions inside
    ``Simulation.integrate`` and ``Simulation.steps`` (a RuntimeError with our message); the
    least invasive way to raise our classes is to replace those two methods at registration by
    versions that, for a simulation whose integrator is HBVM only, make the same C call with
    the same argument conversions and raise the recorded exception in place of that
    RuntimeError (REBOUND's other statuses as REBOUND raises them); any other integrator goes
    to REBOUND's own methods unchanged.  Nothing is swallowed: without them the run still stops
    with a RuntimeError carrying our message.  Exceptions raised by ``prepare`` (a refused
    setting) travel the same way.

How a file refuses to run where ``hbvm_md`` is not imported
    REBOUND's binary names the integrator ("integrator.name" = "hbvm"); a process where it is
    not registered gets REBOUND's own refusal: a "binary file seems to be corrupted" warning at
    load and ``RuntimeError: Integrator not found.`` at the first ``integrate``.  Import
    ``hbvm_md`` before loading (``tests/test_rebound_host.py`` checks both).

How variational particles and MEGNO work
    REBOUND's first-order variational particles of the whole system (``sim.add_variation()``,
    ``sim.init_megno()``) are tangent vectors: each step carries them by the derivative of the
    step it took (:func:`integrators.tangent.tangent_map`, the linearised stage equations
    solved at the step's converged stages), committed with the step or not at all (a failed
    step leaves them unchanged).  With ``calculate_megno`` set the step hands REBOUND's
    ``reb_tools_megno_update`` the increment of its MEGNO integral as IAS15 does, so
    ``sim.megno()`` and ``sim.lyapunov()`` are REBOUND's own bookkeeping.  The tangents'
    previous coefficients (an initial guess only) are not saved: a loaded run starts them at
    zero.

What HBVM cannot honour
    Second-order variational particles, the variation of one particle (testparticle >= 0),
    softening, additional forces, non-direct gravity, boundaries, user
    ODEs and ``testparticle_type = 1`` are refused with the reason and the fix: at
    :class:`HBVMIntegrator`, or at the first step after ``sim.integrator = "hbvm"`` (REBOUND's
    ``create`` is not given the simulation).
"""
from hbvm_md.rebound.checks import check_particles, check_simulation, shortest_period
from hbvm_md.rebound.host import register
from hbvm_md.rebound.integrator import HBVMIntegrator

__all__ = ["HBVMIntegrator", "check_particles", "check_simulation", "register", "shortest_period"]
