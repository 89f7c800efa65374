"""REBOUND's compiled glue (``hbvm_md/rebound/csrc``, built by ``pip install`` as
``hbvm_md.rebound._glue`` against the installed REBOUND's ``rebound.h``): REBOUND's step and
free in C, and the plain N-body step on the compiled core (``integrators._core``).

:func:`available` says whether it serves this process: it was built, from the sources beside
it (an editable install whose C or ``layout.py`` changed and was not rebuilt is refused: its
slot numbers would be the old ones), with the core it was built for, and against a
``rebound.h`` whose layout is the running REBOUND's (the offsets of every field the step reads,
compared with REBOUND's own ctypes structures, which REBOUND checks against its library).
Otherwise the numba functions of :mod:`hbvm_md.rebound.cabi` and :mod:`hbvm_md.rebound.glue`
serve, as before, with one warning saying why.

:func:`plain_step` says whether a prepared simulation's step is the one the glue has in C
(:data:`COVERS`); every other case runs the numba step of :mod:`hbvm_md.rebound.glue`, which
the same C dispatch calls.
"""
from __future__ import annotations

import ctypes
import os
import warnings

#: what the compiled REBOUND step covers; the rest is numba's (hbvm_md.rebound.glue)
COVERS = ("HBVM (not EQUIP), the fixed-point iteration, Newtonian gravity among point masses, "
          "test particles among them (N_active below N, massless bodies), no variational "
          "particles, no REBOUND or REBOUNDx forces and no attached ODEs, kepler = 0")

try:
    from hbvm_md.rebound import _glue
except ImportError as _exc:     # (not built: no compiler, no REBOUND header, or no core)
    _glue = None
    _WHY = f"the compiled REBOUND glue is not built ({_exc})"
else:
    _WHY = None

_checked: list = []


def _why_not() -> str | None:
    """Why the built glue cannot serve (None: it can)."""
    if _glue is None:
        return _WHY
    from integrators import ccore
    from integrators._digest import glue_digest
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    digest = glue_digest(root)
    if digest is not None and digest != _glue.SOURCE_DIGEST:
        return ("the compiled REBOUND glue (hbvm_md/rebound/_glue) was built from other sources "
                "than hbvm_md/rebound/csrc and layout.py hold now: run `pip install -e .` again")
    import rebound
    S, P = rebound.Simulation, rebound.Particle
    lay = _glue.LAYOUT
    want = {"sizeof_simulation": ctypes.sizeof(S), "sizeof_particle": ctypes.sizeof(P),
            "last_step": -2}
    for f in ("t", "G", "dt", "dt_last_done", "N", "_particles", "_particles_var", "N_active",
              "_status", "integrator"):
        want[f] = getattr(S, f).offset
    for f in ("x", "y", "z", "vx", "vy", "vz", "m"):
        want[f] = getattr(P, f).offset
    bad = sorted(f for f, v in want.items() if lay.get(f) != v)
    if bad:
        return (f"the compiled REBOUND glue was built against REBOUND {_glue.REBOUND_VERSION}'s "
                f"rebound.h, whose layout differs from the running REBOUND {rebound.__version__} "
                f"({', '.join(bad)}): reinstall hbvm-md (pip install --force-reinstall --no-deps "
                "hbvm-md) against this REBOUND")
    return None


def built() -> bool:
    """True when the compiled glue can serve this process (module docstring): then REBOUND's
    step and free are its C ``dispatch`` and ``release`` (which call whatever step a state was
    prepared with: the C step, a numba step, or the Python one under ``NUMBA_DISABLE_JIT``)."""
    if not _checked:
        why = _why_not()
        _checked.append(why)
        if why is not None and _glue is not None:
            warnings.warn(f"hbvm-md: {why}; REBOUND's step is compiled by numba instead",
                          RuntimeWarning, stacklevel=3)
    return _checked[0] is None


def available() -> bool:
    """True when the compiled glue's C step serves REBOUND's plain scenes in this process: it is
    :func:`built` and the compiled core is in use (``HBVM_MD_CORE=numba`` and
    ``NUMBA_DISABLE_JIT=1`` turn both off: integrators.ccore.available)."""
    if not built():
        return False
    from integrators import ccore
    return ccore.available()


def addresses() -> tuple[int, int, int]:
    """(dispatch, release, the plain step): the C functions' addresses."""
    return int(_glue.DISPATCH), int(_glue.RELEASE), int(_glue.STEP)


def plain_step(method, nb, host_forces: bool, n_var: int) -> bool:
    """Does the compiled step cover this simulation (:data:`COVERS`)?  method: HBVM or
    EQUIP; nb: the N-body model (None on REBOUND's own accelerations)."""
    from integrators.tableau import HBVM
    return (available() and type(method) is HBVM and nb is not None and not host_forces
            and n_var == 0)
