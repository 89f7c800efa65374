"""The compiled core (``integrators/csrc``, built by ``pip install`` as ``integrators._core``):
the separable HBVM step with its kernels in C, the stages in the vector lanes.

:func:`core_step` returns, for the kernels it knows and the variant it implements, an object
with the interface of :func:`integrators.specialise.specialise`'s (``run``, ``advance``,
``energy_parts``, ``kind``): the engine's :class:`~integrators.engine.Stepper` then runs
:func:`integrators.loop.run`'s contract in C, with no compilation at run time.  What it covers
so far: the N-body kernel (:mod:`systems.nbody`, sources only), HBVM (not EQUIP), the
separable form, the fixed-point iteration, no followers, no stage velocities, no tangents and
no recentring.  Every other variant runs the numba step of :mod:`integrators.loop`, as before.

``HBVM_MD_CORE=numba`` in the environment turns the compiled core off (every step then runs
on numba, for comparisons); a build without the core (no C compiler at install: setup.py) runs
numba too, with one log line saying so.
"""
from __future__ import annotations

import logging
import os

try:
    from . import _core
except ImportError:            # (installed without a compiler: the numba step serves)
    _core = None

_log = logging.getLogger("hbvm_md")
_warned = []

#: the kernels the core has, by the (module, name) of the numba kernels they replace
KERNELS = {}
if _core is not None:
    KERNELS[(("systems.nbody", "nbody_forces"), ("systems.nbody", "nbody_potential"))] = \
        _core.NBODY


def available() -> bool:
    """True when the compiled core was built and is not turned off (``HBVM_MD_CORE``)."""
    return _core is not None and os.environ.get("HBVM_MD_CORE", "").lower() != "numba"


def lanes() -> int:
    """The core's vector width in doubles (8 with AVX-512, 4 with AVX, 2 otherwise); 0 when
    there is no core."""
    return 0 if _core is None else int(_core.LANES)


class CoreStep:
    """The compiled core's step for one kernel: :func:`integrators.loop.run`'s interface."""

    kind = "compiled"
    core = True

    def __init__(self, kernel: int):
        self.kernel = kernel

    def run(self, system, state, h, E, method, newton, opts, wk, samples) -> int:
        return _core.run(self.kernel, system, state, float(h), E, method, newton, opts, wk,
                         samples)

    def energy_parts(self, full, y, kin_w, params):
        if full:
            raise ValueError("internal error: the compiled core has the separable form only")
        return _core.energy_parts(self.kernel, y, kin_w, params)

    def force(self, X, params, out) -> None:
        """The kernel at the rows of X (n, m) into out (n, m), through the lanes' layout."""
        _core.force(self.kernel, X, params, out)


def core_step(refs, *, full, equip, velocities, glue, jvp, follow, recentre):
    """The compiled core's step for kernels imported from ``refs`` ((module, name) of the force
    and the potential) in this variant, or None when the core does not cover it."""
    if (full is not False or equip is not False or velocities or glue is not None
            or jvp is not None or follow is not None or recentre is not None):
        return None
    kernel = KERNELS.get(tuple(refs))
    if kernel is None:
        return None
    if not available():
        if _core is None and not _warned:
            _warned.append(True)
            _log.info("hbvm-md: the compiled core was not built (no C compiler at install); "
                      "the step is compiled by numba instead")
        return None
    return CoreStep(kernel)
