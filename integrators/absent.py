"""Compiled stand-ins for the parts of the step a scene does not use.

:mod:`integrators.specialise` compiles the step of :mod:`integrators.loop` once per scene
variant: the followers (test particles) only when the system has any, the full form or the
separable form only as the binding uses, EQUIP only for EQUIP, the tangent map only when
variational particles ask for it, the simplified Newton update only for a host that uses it.
The step's code is the same for every variant.  The variant is declared by module globals of
the generated step (``_FULL``, ``_EQUIP``, ``_FOLLOWERS``, ``_NEWTON``, ``_TANGENTS``) that
numba reads as constants: the branches they decide are pruned before typing, so the parts a
variant leaves out are not compiled at all (measured on REBOUND's three-body scene with empty
caches: 12 % less compile time than compiling these stand-ins in their place).
The names a variant leaves out are still bound to the functions here, as guards: a stand-in is
never reached, and if it ever were (a binding that does not match its system or method) it
raises instead of computing something else.

The EQUIP stand-ins are bound as the step's ``eq`` (the names of
:mod:`integrators.equip_core`): its constants and ``carve`` (the empty views an HBVM step
carves) are EQUIP's own, its steps raise.
"""
import numpy as np

from integrators.core import OK
from integrators.equip_core import (  # (the names the step reads through ``eq``, __all__)
    CONVERGED, CP_B1, CP_B2, CP_PATH_C2, CP_PATH_C2_LO, CP_PATH_I, CP_PATH_I_LO, CP_PATH_S, CP_PS,
    CP_VEC, CP_X, CP_X_LO, EREF_EQUIP, FAILED, NO_ENERGY_ROOT, REITERATE, TS_PSE1, TS_S0, UPDATED,
    WP_PATH, WP_PATH_LO, carve)
from integrators.jit import jit

__all__ = ["CONVERGED", "CP_B1", "CP_B2", "CP_PATH_C2", "CP_PATH_C2_LO", "CP_PATH_I",
           "CP_PATH_I_LO", "CP_PATH_S", "CP_PS", "CP_VEC", "CP_X", "CP_X_LO", "EREF_EQUIP",
           "FAILED", "NO_ENERGY_ROOT", "REITERATE", "TS_PSE1", "TS_S0", "UPDATED", "WP_PATH",
           "WP_PATH_LO", "carve",
           "follow", "full_stages", "full_stages_narrow", "symplectic", "commit_full",
           "tangent_map", "read_tangents", "write_tangents", "delta2", "start", "finish",
           "stage_correction", "path_correction", "energy_residual", "update_alpha",
           "commit_correction", "newton_update", "recentre"]


@jit
def _not_compiled():
    raise RuntimeError("hbvm-md: internal error: the step was compiled without this part "
                       "(integrators.absent); its binding does not match the system or method")


# -- the followers (integrators.loop.follow), for a system without test particles ----------
@jit
def follow(y, cy, minv, g, Xs, params, at, sc, tab, opts, R, fb):
    _not_compiled()
    return OK, 0, 0.0


# -- the recentring hook (integrators.loop._recentre), for a system without one -------------
@jit
def recentre(y, cy, gamma, h, params):
    _not_compiled()
    return 0


# -- the full form (integrators.core), for a separable binding ----------------------------
@jit
def full_stages(y, cy, g, I, I_lo, h, Y, R, exact):
    _not_compiled()


@jit
def full_stages_narrow(y, cy, g, I, I_lo, h, Y, exact):
    _not_compiled()


@jit
def symplectic(G, F):
    _not_compiled()


@jit
def commit_full(y, cy, h, g):
    _not_compiled()


# -- the tangent map (integrators.tangent), for a host step without variational particles --
@jit
def tangent_map(system, y0, cy0, gamma, h, E, method, newton, max_iter, tan):
    if tan.V.shape[0] > 0:
        _not_compiled()
    return OK               # no tangents: nothing to map


# -- REBOUND's tangents (hbvm_md.rebound.glue), likewise ----------------------------------
@jit
def read_tangents(pv, vidx, N, ix, ivx, im, minv, V, DG, na, params, TP, TO):
    if V.shape[0] > 0:
        _not_compiled()


@jit
def write_tangents(pv, vidx, N, ix, ivx, minv, V):
    if V.shape[0] > 0:
        _not_compiled()


@jit
def delta2(pv, N, ix, ivx):
    _not_compiled()
    return 1.0


# -- EQUIP (integrators.equip_core, bound as the step's ``eq``), for an HBVM binding -------
@jit
def start(es, eref):
    _not_compiled()


@jit
def finish(es, eref):
    _not_compiled()


@jit
def stage_correction(full, y, minv, g, a, sc, alpha, method, X):
    _not_compiled()


@jit
def path_correction(g, minv, h2, alpha, IkS, Xk):
    _not_compiled()


@jit
def energy_residual(full, y, minv, kin_w, g, rho, h, alpha, X, X_lo, S0):
    _not_compiled()
    return np.nan, np.nan, np.nan


@jit
def update_alpha(es, E, scale, floor):
    _not_compiled()
    return FAILED


@jit
def commit_correction(yt, cyt, minv, h, g, alpha, S0):
    _not_compiled()


# -- the simplified Newton update (integrators.core), for a host without Newton (REBOUND) ---
@jit
def newton_update(g, pg, NV, NVinv, NM, Rt, Z):
    _not_compiled()
    return 0.0, 0.0
