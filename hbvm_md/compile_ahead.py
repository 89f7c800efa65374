"""Compile HBVM's steps ahead of a deployment: ``hbvm-md compile`` or :func:`precompile`.

numba compiles HBVM's step for a scene once and caches it on disk (``HBVM_MD_CACHE_DIR`` for
the generated step modules, ``NUMBA_CACHE_DIR`` for numba's compiled code; see
:mod:`integrators.specialise`).  The first run on a fresh machine pays that compile; a CI job,
a container image or a dask worker can pay it ahead instead, by running a tiny scene of each
kind it will use:

* ``"rebound"``: ``sim.integrator = "hbvm"`` on point masses (the step every REBOUND scene
  without test particles or variational particles runs, fixed or adaptive, any k and s);
* ``"test-particles"``: the same with test particles (``N_active`` < N, or massless bodies);
* ``"variational"``: the same with variational particles (``sim.add_variation()``, MEGNO);
* ``"equip"``: REBOUND with ``sim.integrator.method = "equip"``;
* ``"rebound-forces"``: REBOUND on its own accelerations (:mod:`hbvm_md.rebound.forces`: a
  scene with REBOUNDx forces, ``sim.additional_forces``, softening, semi-active particles or
  no gravity), forces of positions only;
* ``"rebound-forces-velocities"``: the same for forces that read the velocities
  (``sim.force_is_velocity_dependent``: REBOUNDx ``gr``, tides, drag);
* ``"kepler"``: ``sim.integrator.kepler = 1``, HBVM composed with the Keplerian flows (its own
  kernels and glue, :mod:`hbvm_md.rebound.kepler_glue`; planets and a test particle);
* ``"ase"``: :class:`hbvm_md.HBVMDynamics` (the compiled pieces its step calls).

The caches are then filled for every later process that uses the same folders, the same
hbvm-md, numba and Python versions.
"""
from __future__ import annotations

import time

#: what :func:`precompile` compiles when not told (the scenes most runs use)
DEFAULT_SCENES = ("rebound", "ase")


def _drag(reb_sim):
    """A weak drag on every particle: a force of the velocities (``"rebound-forces-velocities"``)."""
    sim = reb_sim.contents
    for p in sim.particles:
        p.ax -= 1e-6 * p.vx
        p.ay -= 1e-6 * p.vy
        p.az -= 1e-6 * p.vz


def _rebound(test_particles: bool = False, variational: bool = False, method: str = "hbvm",
             host_forces: str | None = None, kepler: bool = False):
    import importlib

    import rebound
    importlib.import_module("hbvm_md")      # registers "hbvm" with REBOUND
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, e=0.05)
    sim.add(m=1e-3, a=1.6, e=0.02, inc=0.1)
    if test_particles:
        sim.add(a=2.5, e=0.1)
        sim.N_active = 3
    if variational:
        sim.init_megno()
    if host_forces == "positions":       # (softening: REBOUND's own accelerations, of q only)
        sim.softening = 1e-4
    elif host_forces == "velocities":
        sim.additional_forces = _drag
        sim.force_is_velocity_dependent = 1
    sim.integrator = "hbvm"
    if method != "hbvm":
        sim.integrator.method = method
    if kepler:                           # (the composed step takes fixed steps only)
        sim.integrator.kepler = 1
        sim.integrator.epsilon = 0.0
    sim.dt = 0.05
    sim.steps(2)


def _ase():
    import numpy as np
    from ase import Atoms
    from ase.calculators.emt import EMT

    from hbvm_md.ase import HBVMDynamics
    atoms = Atoms("Cu2", positions=[[0.0, 0.0, 0.0], [2.6, 0.0, 0.0]])
    atoms.calc = EMT()
    atoms.set_momenta(np.array([[0.05, 0.0, 0.0], [-0.05, 0.0, 0.0]]))
    HBVMDynamics(atoms, 1.0).run(2)


SCENES = {
    "rebound": _rebound,
    "test-particles": lambda: _rebound(test_particles=True),
    "variational": lambda: _rebound(variational=True),
    "equip": lambda: _rebound(method="equip"),
    "rebound-forces": lambda: _rebound(host_forces="positions"),
    "rebound-forces-velocities": lambda: _rebound(host_forces="velocities"),
    "kepler": lambda: _rebound(test_particles=True, kepler=True),
    "ase": _ase,
}


def precompile(scenes=DEFAULT_SCENES) -> dict[str, float]:
    """Compile and cache HBVM's steps for these kinds of scene (see the module docstring);
    returns the seconds each took (about a second for one already cached).

    Parameters
    ----------
    scenes : iterable of str
        Any of ``"rebound"``, ``"test-particles"``, ``"variational"``, ``"equip"``,
        ``"rebound-forces"``, ``"rebound-forces-velocities"``, ``"kepler"``, ``"ase"``, or
        ``"all"``
        (default: ``("rebound", "ase")``).

    Examples
    --------
    In a dask worker's setup, or a CI step before the tests::

        import hbvm_md
        hbvm_md.precompile(["rebound", "test-particles"])
    """
    if isinstance(scenes, str):
        scenes = [scenes]
    names = []
    for name in scenes:
        if name == "all":
            names += [n for n in SCENES if n not in names]
        elif name in SCENES:
            if name not in names:
                names.append(name)
        else:
            raise ValueError(f"`scenes` must name scenes among {sorted(SCENES)} or 'all' "
                             f"(got {name!r})")
    took = {}
    for name in names:
        t0 = time.perf_counter()
        SCENES[name]()
        took[name] = time.perf_counter() - t0
    return took
