"""HBVM(k, s) inside REBOUND: an integrator registered with REBOUND's plug-in interface.

``import hbvm_md`` registers HBVM with REBOUND (``reb_integrator_register``) under the name
``"hbvm"``, once per process (when REBOUND is imported: at once if it already is, else by an
import hook, ``hbvm_md._RegisterOnImport``; importing this module registers too).  Then ``sim.integrator = "hbvm"`` works as for a built-in
integrator, with HBVM's defaults (adaptive steps, s = 6, the default epsilon of
:mod:`integrators.engine` and k for it), and :class:`HBVMIntegrator` ``(sim, s=..., k=...,
dt=..., method="hbvm" | "equip", ...)`` selects it with checked settings.  REBOUND owns the run
(time, callbacks, collisions, SIGINT, archives, ``save_to_file``, ``copy``, pickling); this
package holds the glue only, and the step is the compiled core's (``integrators/csrc``)
or :mod:`integrators.loop`'s.  ``method="equip"`` takes
EQUIP's own adaptive defaults, s = 8 at epsilon 1e-17 (``sim.integrator.method = "equip"`` on an
existing integrator keeps the s and epsilon set).  ``kepler=True`` (the saved field
``sim.integrator.kepler = 1``) composes HBVM with the Keplerian flows about particle 0
(:class:`systems.flow_composed.FlowComposed`, fixed steps only; not the default: not faster).

Modules: ``csrc/hbvm_state.h`` and :mod:`~hbvm_md.rebound.layout` (HBVM's state and the
step's context as named C structs, and every other memory layout),
:mod:`~hbvm_md.rebound.state` (the host's record of each state, the state's views, arrays and
context block), ``csrc/glue.c`` and :mod:`~hbvm_md.rebound.cglue` (REBOUND's step, ``free``
and the plain N-body step in C, on the compiled core), :mod:`~hbvm_md.rebound.cabi` and
:mod:`~hbvm_md.rebound.glue` (their numba twins, and the numba step of every other case),
:mod:`~hbvm_md.rebound.host` (registration, the callbacks, preparing a step, the run's
exceptions), :mod:`~hbvm_md.rebound.forces` (REBOUND's own accelerations at the stages, for
scenes beyond point masses), :mod:`~hbvm_md.rebound.checks` (what is refused) and
:mod:`~hbvm_md.rebound.integrator` (:class:`HBVMIntegrator`, the options and their checks),
:mod:`~hbvm_md.rebound.kepler_glue` and :mod:`~hbvm_md.rebound.composed` (the composed step's
glue and preparation, which builds on :mod:`~hbvm_md.rebound.state`, not on the host).

How the design answers REBOUND's questions (where the state lives, how a loaded or copied
simulation gets its compiled step, how a failed step surfaces, what a process without
``hbvm_md`` does with a file, variational particles and MEGNO, which scenes take REBOUND's own
accelerations, energy there, REBOUNDx operators, what HBVM cannot honour): the
documentation's design page "The REBOUND host: how the plug-in is built"
(``docs/design/rebound_host.md``); for users, ``docs/guide/rebound.md``.
"""
from hbvm_md.rebound.checks import check_particles, check_simulation, shortest_period
from hbvm_md.rebound.host import register
from hbvm_md.rebound.integrator import HBVMIntegrator

__all__ = ["HBVMIntegrator", "check_particles", "check_simulation", "register", "shortest_period"]
