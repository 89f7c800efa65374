"""The compiled core (``integrators/csrc``, built by ``pip install`` as ``integrators._core``):
the separable HBVM step in C, the stages in the vector lanes.

:func:`core_step` returns, for the kernels and the variant the core covers, an object with the
interface of :func:`integrators.specialise.specialise`'s (``run``, ``attempt``,
``energy_parts``, ``kind``): the engine's :class:`~integrators.engine.Stepper` (and so
``HBVMDynamics``) then runs :func:`integrators.loop.run`'s contract in C, with nothing
compiled at run time and the same numbers bit for bit (the same operations in the same order).
What it covers so far:

* the kernels: the N-body kernel of :mod:`systems.nbody` and the small systems' (Kepler,
  Henon-Heiles, FPU, the pendulum, Morse: :data:`KERNELS`) in C, and any kernel written in
  Python (a user's system, an ASE calculator), which the core calls back at each evaluation
  through buffers of the loop's row layout;
* the variant: HBVM (not EQUIP), the separable form, the fixed-point iteration (a step handed
  Newton matrices runs the numba step, built then), no stage velocities, no tangents, no
  recentring, no host glue;
* the followers (test particles: an :class:`systems.nbody.NBody` with ``n_active`` < N or
  massless bodies, :data:`FOLLOWERS`) with the N-body kernel: the sources' stage equations
  solved as if alone, then each test particle's in their field with its own stop rule, in
  groups of ``core.FOLLOWER_GROUP`` (:mod:`integrators.followers`), each follower's stage
  values contiguous in the lanes as the sources' are; ``attempt`` (:func:`integrators.loop.
  attempt` in C, ``hbvm_attempt``) adds their term to the adaptive control
  (``core.test_particle_control``, whose C copy the engine's adaptive steps call on the core).

Every other variant runs the numba step of :mod:`integrators.loop`, as before.
``HBVM_MD_CORE=numba`` in the environment turns the compiled core off (every step then runs on
numba, for comparisons), and so does ``NUMBA_DISABLE_JIT=1`` (the Python of the loop); a build without the core (no C compiler at install: setup.py) runs
numba too, with one log line saying so.
"""
from __future__ import annotations

import logging
import os

import numpy as np

try:
    from . import _core
except ImportError:            # (installed without a compiler: the numba step serves)
    _core = None

from ._digest import source_digest  # noqa: E402

#: why the built core is not used (None: it is)
STALE = None
if _core is not None:
    _sources = source_digest(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    if _sources is not None and _sources != _core.SOURCE_DIGEST:
        STALE = ("the compiled core (integrators/_core) was built from other sources than "
                 "integrators/csrc holds now (an editable install whose C changed, or whose "
                 "rebuild failed): run `pip install -e .` again; the numba step serves until then")
        _core = None

_log = logging.getLogger("hbvm_md")
_warned = []

#: the kernels the core has in C, by the (module, name) of the numba kernels they replace
KERNELS = {}
if _core is not None:
    KERNELS[(("systems.nbody", "nbody_forces"), ("systems.nbody", "nbody_potential"))] = \
        _core.NBODY
    for _module, _force, _potential, _name in (
            ("systems.kepler", "_kepler_force", "_kepler_potential", "kepler"),
            ("systems.henon_heiles", "_hh_force", "_hh_potential", "henon_heiles"),
            ("systems.fpu", "_fpu_force", "_fpu_potential", "fpu"),
            ("systems.pendulum", "_pendulum_force", "_pendulum_potential", "pendulum"),
            ("systems.pendulum", "_morse_force", "_morse_potential", "morse")):
        KERNELS[((_module, _force), (_module, _potential))] = _core.BUILTINS[_name]


#: the followers hooks the core has in C (``follow`` of :func:`core_step`: the (module, name) of
#: the numba hooks it replaces), and the kernels they go with
FOLLOWERS = {}
if _core is not None:
    FOLLOWERS[(("systems.nbody", "nbody_followers"), ("systems.nbody", "nbody_field"))] = \
        (_core.NBODY,)


def _ref(fn):
    """(module, name) of a compiled function (its ``py_func``'s), or None."""
    f = getattr(fn, "py_func", None)
    mod, name = getattr(f, "__module__", None), getattr(f, "__qualname__", None)
    return None if mod is None or name is None else (mod, name)


def available() -> bool:
    """True when the compiled core was built and is not turned off (``HBVM_MD_CORE=numba``,
    or ``NUMBA_DISABLE_JIT=1``: every step then runs as the Python of integrators.loop, for
    debugging it)."""
    if os.environ.get("NUMBA_DISABLE_JIT", "0").strip() not in ("", "0"):
        return False
    if _core is None:
        if not _warned:
            _warned.append(True)
            if STALE:
                import warnings
                warnings.warn("hbvm-md: " + STALE, RuntimeWarning, stacklevel=3)
            else:
                _log.info("hbvm-md: the compiled core was not built (no C compiler at "
                          "install); the step is compiled by numba instead")
        return False
    return os.environ.get("HBVM_MD_CORE", "").lower() != "numba"


def work_size(k: int, s: int, m: int, params=None) -> int:
    """The doubles of scratch the core's step works in for k stages, s coefficients and m
    coordinates (handed over zeroed, kept between calls); with the N-body kernel's params
    holding a followers block (test particles), for them too."""
    at = m + 3              # (systems.nbody.nbody_followers: after [G, N, w, g, f])
    if params is not None and params.shape[0] > at + 3:
        return int(_core.work_size(int(k), int(s), int(m), int(params[at + 2]),
                                   int(params[at])))
    return int(_core.work_size(int(k), int(s), int(m)))


def lanes() -> int:
    """The core's vector width in doubles (8 with AVX-512, 4 with AVX, 2 otherwise); 0 when
    there is no core."""
    return 0 if _core is None else int(_core.LANES)


class CoreStep:
    """The compiled core's step for one compiled kernel: :func:`integrators.loop.run`'s
    interface.  ``fallback()`` builds the numba step, for the Newton iteration."""

    kind = "compiled"
    core = True
    follow = False      # (one pickled before the core took the followers: none)

    def __init__(self, kernel: int, fallback, follow: bool = False):
        self.kernel = kernel
        self._fallback = fallback
        self._numba = None
        self._scratch = np.zeros(0)
        self.follow = bool(follow)

    def scratch(self, method, m: int, params=None) -> np.ndarray:
        """The core's work arrays for this method and m coordinates (and the followers of the
        kernel's params, with followers), kept between calls (a call that allocated and zeroed
        its own paid for it at every step of a host that calls one step at a time: 10 MB for
        4096 atoms)."""
        n = work_size(method.tn.shape[1], method.ts.shape[1], m,
                      params if self.follow else None)
        if self._scratch.shape[0] != n:
            self._scratch = np.zeros(n)
        return self._scratch

    def __getstate__(self) -> dict:
        # (a pickled Stepper: the work arrays and the numba step are rebuilt where it lands)
        state = self.__dict__.copy()
        state.update(_numba=None, _scratch=np.zeros(0))
        if "_kern" in state:
            state["_kern"] = None
        return state

    def numba_step(self):
        if self._numba is None:
            self._numba = self._fallback()
        return self._numba

    def run(self, system, state, h, E, method, newton, opts, wk, samples) -> int:
        if newton.NM.shape[0] > 0:
            return self.numba_step().run(system, state, h, E, method, newton, opts, wk,
                                         samples)
        return _core.run(self.kernel, system, state, float(h), E, method, newton, opts, wk,
                         samples, None, self.scratch(method, system.minv.shape[0],
                                                     system.params), self.follow)

    def attempt(self, system, state, trial, h, h_prev, t_start, ext, method, newton, opts, wk,
                adaptive) -> int:
        """:func:`integrators.loop.attempt` on the core (``hbvm_attempt``: the one retry loop
        and controller, with the test particles' term of the adaptive control)."""
        if newton.NM.shape[0] > 0:
            return self.numba_step().attempt(system, state, trial, h, h_prev, t_start, ext,
                                             method, newton, opts, wk, adaptive)
        return _core.attempt(self.kernel, system, state, trial, float(h), float(h_prev),
                             float(t_start), ext, method, newton, opts, wk, adaptive,
                             self.scratch(method, system.minv.shape[0], system.params),
                             self.follow)

    def energy_parts(self, full, y, kin_w, params):
        if full:
            raise ValueError("internal error: the compiled core has the separable form only")
        return _core.energy_parts(self.kernel, y, kin_w, params)

    def force(self, X, params, out) -> None:
        """The kernel at the rows of X (n, m) into out (n, m), through the lanes' layout."""
        _core.force(self.kernel, X, params, out)


class PythonCoreStep(CoreStep):
    """The compiled core's step around kernels written in Python (``force(X, params, out)``
    on rows X (n, m), ``potential(x, params)``: :mod:`integrators.loop`'s contract), called
    back at each evaluation.  ``kind`` is "python": the host calls it as it calls a Python
    step (one call for a run, no chunks)."""

    kind = "python"

    def __init__(self, force, potential, fallback):
        super().__init__(_core.PYTHON, fallback)
        self._force, self._potential = force, potential
        self._kern = None

    def _kernel(self, k: int, m: int, params):
        """The callbacks and their row buffers for k stages of m coordinates (built again when
        the method, the size or the parameters' array change)."""
        kern = self._kern
        if kern is None or kern[3].shape != (k, m) or kern[-1] is not params:
            Xr, Fr = np.zeros((k, m)), np.zeros((k, m))
            X1, F1, q = np.zeros((1, m)), np.zeros((1, m)), np.zeros(m)
            force, potential = self._force, self._potential
            kern = ((lambda: force(Xr, params, Fr)), (lambda: force(X1, params, F1)),
                    (lambda: potential(q, params)), Xr, Fr, X1, F1, q, params)
            self._kern = kern
        return kern[:8]

    def run(self, system, state, h, E, method, newton, opts, wk, samples) -> int:
        if newton.NM.shape[0] > 0:
            return self.numba_step().run(system, state, h, E, method, newton, opts, wk,
                                         samples)
        kern = self._kernel(method.tn.shape[1], system.minv.shape[0], system.params)
        return _core.run(_core.PYTHON, system, state, float(h), E, method, newton, opts, wk,
                         samples, kern, self.scratch(method, system.minv.shape[0]))

    def attempt(self, *args) -> int:
        """(the Python step's: the core's attempt takes compiled kernels)"""
        return self.numba_step().attempt(*args)

    def energy_parts(self, full, y, kin_w, params):
        if full:
            raise ValueError("internal error: the compiled core has the separable form only")
        m = kin_w.shape[0]
        return _core.kinetic(y[m:], kin_w), self._potential(y[:m], params)


def core_step(force, potential, refs, *, full, equip, velocities, glue, jvp, follow, recentre,
              fallback):
    """The compiled core's step for these kernels in this variant, or None when the core does
    not cover it.  ``refs``: the (module, name) of compiled kernels (None for Python ones);
    ``follow``: the followers hooks (:data:`FOLLOWERS`: the N-body kernel's; None: none);
    ``fallback()``: the numba step of the same binding (built only if a step needs Newton)."""
    if (full is not False or equip is not False or velocities or glue is not None
            or jvp is not None or recentre is not None):
        return None
    if not available():
        return None
    if refs is None:
        return None if follow is not None else PythonCoreStep(force, potential, fallback)
    kernel = KERNELS.get(tuple(refs))
    if kernel is None:
        return None
    if follow is not None:
        hooks = tuple(_ref(f) for f in follow)
        if kernel not in FOLLOWERS.get(hooks, ()):
            return None
    return CoreStep(kernel, fallback, follow=follow is not None)
