"""REBOUND's step of HBVM composed with the Keplerian flows (``sim.integrator.kepler = 1``),
compiled in the same module as the one step, as :mod:`hbvm_md.rebound.glue` is for plain HBVM.

The mathematics is the engine's, not a copy: the state is :class:`systems.flow_composed.
FlowComposed`'s (X, tau, P, p_tau), its kernels (gradient, energy and the recentring hook) are
bound with the step by :mod:`integrators.specialise` exactly as the engine binds them, and
the step is :func:`integrators.loop.attempt` with a fixed step.  This glue only reads REBOUND's
side (``sim.dt``, ``sim.t``, the particles), checks that the particles are those the last
commit wrote (else RESYNC: the host reads them afresh), and after a step commits state and
particles together: the bodies from the state by :func:`systems.flow_composed.composed_bodies`
(the barycentre moving uniformly from the saved ``com``), ``t``, ``dt_last_done`` and the counts.
A failed step changes nothing and records its step size, start and cause, as the plain glue's.

What the host keeps (:mod:`hbvm_md.rebound.layout`): the saved array ``state`` holds y (2m),
its low parts cy (2m) and com (17: the barycentre's position at time com[6], its velocity,
com[6], the time the bodies were last written, com[7], and the force terms the state was
integrated with, com[8:17], FlowComposed's params block (c of the GR potential, the star's J2,
J4, R_eq and unit spin axis, its central force's A and gamma; 0 for an absent term): a copy or
a loaded file whose REBOUNDx ``gr_potential``, ``gravitational_harmonics`` or
``central_force`` differs starts afresh from its particles, as after a mass change);
``gamma`` holds the last step's coefficients (s, 2m), already carried into the recentred
variables by the hook; ``h_prev``, ``eref`` and the counts as for plain HBVM.  So a copy or a
loaded file continues bit for bit.
"""
from typing import TYPE_CHECKING

import numpy as np
from numba import carray

from integrators.core import C_RUN_ERR, ERROR_BOUND, NOT_FINITE, OK, copy1, copy2
from integrators.pointers import address_of, float64_pointer
from integrators.records import Adaptive, Options, System
from hbvm_md.rebound.layout import (SL_RUN_ERR, A_HOST, A_PARAMS, A_WRITTEN, BAD_DT, BAD_SETTINGS, D_M, D_N,
                                    D_P, D_PTR, N_HOST, N_RES, RESYNC, R_DT, R_DTL, R_G, R_M,
                                    R_NACTIVE, R_STRIDE, R_T, R_VX, R_X, SL_ADAPTIVE, SL_ECHECK,
                                    SL_EPSILON, SL_ETOL, SL_H_FAIL, SL_H_PREV, SL_MAX_ITER,
                                    SL_NSTEPS, SL_RES, SL_TOL, SL_Y)
from hbvm_md.rebound.particles import (commit_clock, context_current, context_views, ctx_1,
                                       landing_step, particles_match, record_failure, settings_ok,
                                       step_end, step_records)
from systems.flow_composed import composed_bodies

GLUE_FUNCTIONS = ("kepler_step_arrays",)
#: the fixed-point iteration only, as the plain glue (integrators.specialise, "Compile time")
GLUE_NEWTON = False
GLUE_CFUNCS = {"core_step": "int32(voidptr, voidptr)"}
GLUE_DEPENDS = ("integrators.pointers", "hbvm_md.rebound.layout", "hbvm_md.rebound.particles",
                "systems.flow_composed", "integrators.kepler_flow", "integrators.kepler_flow_dd",
                "integrators.double_double")
#: the width of the barycentre's record after y and cy in the saved state (module docstring)
N_COM = 17


def kepler_step_arrays(simd, simi, view, ctx, st, sd, res, written, host, com, system, state,
                       trial, method, newton, wk, ext):
    """One REBOUND step of sim.dt of the composed method (module docstring).  Returns OK,
    RESYNC (nothing done) or a failure status (nothing done, cause recorded)."""
    if simd[ctx[R_G]] != host[0] or float(simi[ctx[R_NACTIVE]]) != host[1]:
        return RESYNC
    if not settings_ok(st, sd):
        return BAD_SETTINGS
    if st[SL_ADAPTIVE] != 0 and sd[SL_EPSILON] != 0.0:
        return BAD_SETTINGS                  # (fixed steps only: host.check_settings names it)
    ix, ivx = ctx[R_X], ctx[R_VX]
    if not particles_match(view, written, ix, ivx, ctx[R_M]):
        return RESYNC                        # moved between steps: the host reads them afresh
    t_start = simd[ctx[R_T]]
    if t_start != com[7]:
        # sim.t set by the user: the barycentre's position, written from its uniform motion
        # since com[6], would jump with it; the host reads the particles afresh at this time
        return RESYNC
    h = simd[ctx[R_DT]]
    if not (abs(h) < np.inf and h != 0.0):
        sd[SL_H_FAIL] = h
        return BAD_DT
    h = landing_step(simi, ctx, sd, t_start, h)     # (exact_finish_time's last step: tmax)
    etol = sd[SL_ETOL] if st[SL_ECHECK] > 0 else 0.0
    # the step's own error estimate per body block (integrators.core.resolution_error), on
    # with the energy check as in the plain glue (energy_tol=None switches both off)
    ebound = ERROR_BOUND if sd[SL_ETOL] != 0.0 else 0.0
    res[2] = 0.0
    status = attempt(system, state, trial, h, sd[SL_H_PREV], t_start, ext, method, newton,
                     Options(st[SL_MAX_ITER], sd[SL_TOL], etol, ebound, 3), wk,
                     Adaptive(0.0, 0.0, res))
    yt = trial.y
    N = view.shape[0]
    out = np.empty((N, 6))
    # the step's end on the compensated clock (particles.step_end): the barycentre moves
    # uniformly to it, and sim.t shows it
    t_end, ct = step_end(sd, t_start, res[0])
    if status == OK:
        if composed_bodies(yt, system.params, com, t_end, out) != 0:
            status = NOT_FINITE     # (a flow that did not converge: nothing committed)
    if status != OK:
        record_failure(sd, res, t_start)
        return status
    h_done = res[0]
    y, cy, gamma, eref, _ = state
    copy1(y, yt)
    copy1(cy, trial.cy)
    copy2(gamma, trial.gamma)
    sd[SL_H_PREV] = h_done
    eref[0] = trial.eref[0]
    for i in range(N):
        for c in range(3):
            view[i, ix + c] = out[i, c]
            view[i, ivx + c] = out[i, 3 + c]
            written[i, c] = out[i, c]
            written[i, 3 + c] = out[i, 3 + c]
    commit_clock(simd, ctx, sd, t_end, ct)     # REBOUND's time is the step's to advance
    com[7] = t_end
    simd[ctx[R_DTL]] = h_done
    st[SL_NSTEPS] += 1
    sd[SL_RUN_ERR] = wk.counters[C_RUN_ERR]       # (sim.integrator.error_estimate)
    return OK


def core_step(r, p):
    """:func:`kepler_step_arrays` on REBOUND's simulation ``r`` and HBVM's state ``p``; RESYNC
    also when the particle array moved or changed size, or a setting changed."""
    ra, pa = address_of(r), address_of(p)
    st, sd, ctx, simd, simi = context_views(ra, pa)
    N = ctx[D_N]
    if not context_current(simi, st, ctx):
        return RESYNC
    m = ctx[D_M]
    u = 2 * m                                      # the coefficients' width (full form)
    view = carray(float64_pointer(ctx[D_PTR]), (N, ctx[R_STRIDE]))
    empty = carray(float64_pointer(ctx[A_PARAMS]), 0)
    state, trial, method, newton, work, ext = step_records(ctx, st, pa, m, u)
    return kepler_step_arrays(
        simd, simi, view, ctx, st, sd, carray(float64_pointer(pa + 8 * SL_RES), N_RES),
        carray(float64_pointer(ctx[A_WRITTEN]), (N, 7)), ctx_1(ctx, A_HOST, N_HOST),
        carray(float64_pointer(st[SL_Y] + 32 * m), N_COM),
        System(True, empty, empty, ctx_1(ctx, A_PARAMS, ctx[D_P])),
        state, trial, method, newton, work, ext)


if TYPE_CHECKING:
    # integrators.specialise compiles this text after the step's (integrators.loop), where
    # these are the step's own, bound to systems.flow_composed's kernels (imported here for
    # readers and linters only)
    from integrators.loop import attempt
