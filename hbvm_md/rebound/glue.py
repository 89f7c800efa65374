"""REBOUND's step around the single step core, compiled in the same module as the core.

:mod:`integrators.specialise` appends this file's text to the step's (:mod:`integrators.loop`,
the N-body kernel bound) and compiles :data:`GLUE_FUNCTIONS` and the C function
:data:`GLUE_CFUNCS` there: one REBOUND step is one compiled call of :func:`core_step`, which
:func:`hbvm_md.rebound.cabi.dispatch` (or its C twin, :mod:`hbvm_md.rebound.cglue`) calls with REBOUND's simulation and HBVM's state.  It
reads the addresses, sizes and REBOUND's offsets from the context block the host built
(:mod:`hbvm_md.rebound.layout`), checks that G, N_active and the masses are those it wrote
(else RESYNC: the host reads them afresh) and reads positions and velocities changed since
its last commit itself (:func:`reread_particles`), takes the core's step on trial arrays (adaptive
steps retried smaller inside it) and commits state, particles, ``t`` (a compensated sum of
the steps, :func:`~hbvm_md.rebound.particles.step_end`), ``dt_last_done``, the proposed ``dt``
and the counts together.  A failed step changes nothing and records its step
size, start and cause in the state.  No numerics here.  HBVM and EQUIP differ only in the
method's packed arrays (their shapes in the context block's header) and in the length of eref
(the energy, EQUIP's alpha and slope: all of it committed with the step).

:func:`step_arrays` is the same step on arrays: the compiled :func:`core_step` views the memory
and calls it; with ``NUMBA_DISABLE_JIT`` the host calls it as Python.
"""
from collections import namedtuple
from typing import TYPE_CHECKING

import numpy as np
from numba import carray

from integrators.core import (C_ITER, C_NEWTON, C_NFEV, C_RUN_ERR, C_STEPS, EREF_RUN, ERROR_BOUND, OK, TINY_RATIO, copy1,
                              copy2, select_extrapolation, test_particle_error)
from integrators.tangent import TANGENT_FAILED
from integrators.pointers import address_of, complex128_pointer, float64_pointer, int64_pointer
from integrators.records import Adaptive, Options, System, Tangents
from hbvm_md.rebound.intrinsics import call_megno
from hbvm_md.rebound.layout import (A_HOST, A_KINW, A_MINV, A_PARAMS, A_WRITTEN, A_V, A_VT, A_DG,
                                    A_DGT, A_DGS, A_TW, A_TCW, A_TCOUNT, A_VIDX, D_NV, D_TGF, D_TGC,
                                    D_PVAR, D_MEGNO_FN, R_PVAR, R_MEGNO_ON, R_MEGNO_T0, D_HOST,
                                    A_TP, A_TO, BAD_DT, BAD_SETTINGS, D_M, D_N, D_P, D_PTR, D_S,
                                    N_HOST, N_RES, RESYNC, R_DT, R_DTL, R_G, R_M, R_NACTIVE,
                                    R_STRIDE, R_T, R_VX, R_X, SL_ADAPTIVE, SL_CAUSE_ERR,
                                    SL_CAUSE_STATUS, SL_ECHECK, SL_RUN_ERR, SL_EPSILON, SL_ETOL, SL_H_FAIL,
                                    SL_H_PREV, SL_MAX_DT, SL_MAX_ITER, SL_MIN_DT, SL_NSTEPS,
                                    SL_REJECTED, SL_RES, SL_RESYNCS, SL_TOL, SL_T_FAIL,
                                    TEST_PARTICLE)
from hbvm_md.rebound.forces import (CLOCK, O_COL, O_DERIV, O_LEN, O_ODE, O_PRE, O_SIGMA,
                                    O_WIDTH, O_Y, P_N, P_NODES, P_ODE_DERIV_AT, P_ODES_HELD,
                                    P_ODES_WORD, call_void2, odes_at, odes_set)
from hbvm_md.rebound.particles import (commit_clock, context_current, context_views,
                                       record_failure, ctx_1, ctx_2, ctx_3, delta2,
                                       particles_match, read_tangents, reread_particles,
                                       landing_step, restore_particles, settings_ok, step_end,
                                       step_records, var_rows, write_tangents)

GLUE_FUNCTIONS = ("step_arrays", "_step", "moved_anchor", "odes_release", "odes_read",
                  "odes_replaced")
#: the REBOUND step iterates to a fixed point only (its Newton record is empty): the step is
#: built without the simplified Newton iteration (integrators.specialise, "Compile time")
GLUE_NEWTON = False
GLUE_CFUNCS = {"core_step": "int32(voidptr, voidptr)"}
GLUE_DEPENDS = ("integrators.pointers", "hbvm_md.rebound.layout", "hbvm_md.rebound.intrinsics",
                "hbvm_md.rebound.forces", "hbvm_md.rebound.particles")

#: A fixed step (with the energy check on) refuses a test particle whose own error estimate
#: (``core.test_particle_error``) exceeds max(TP_FLOOR, TP_FACTOR x the sources' estimate); the
#: gravitating bodies are judged by the step's own estimate (``core.resolution_error``).
#: Measured (s = 6, k = 7, no check): the adaptive tests' comet (past the Sun, then Jupiter)
#: ends 1e-11 AU from IAS15 at a largest estimate of 7e-3, 1e-7 AU off at 0.19, 0.1 AU off at
#: 27; the outer solar system's sources at a step of 200 days reach 1.5e-4, test particles at
#: 7 to 60 AU 4e-4 (1e-12 AU off), an asteroid at 2.5 AU 2e-2 (4e-8 AU off).
#: False in a step built without the tangent map (no variational particles): numba reads it as a
#: constant and leaves the tangents' branches out of the compiled step (integrators.specialise)
_TANGENTS = True
TP_FLOOR = 1e-2
TP_FACTOR = 10.0

#: REBOUND's side of a step: the simulation's head as float64 and int64 words (simd, simi), its
#: particles (view: (N, stride) doubles over reb_particle), the context block's header (ctx,
#: :mod:`hbvm_md.rebound.layout`), the simulation's address (r) and its variational particles
#: (pv: (N_var, stride) doubles over ``particles_var``)
Rebound = namedtuple("Rebound", ["simd", "simi", "view", "ctx", "r", "pv"])
#: HBVM's side kept in the host's state block: its int64 and float64 slots (st, sd), the attempt's
#: result (res), the particles as the last commit wrote them (written: x, v, m), G and N_active as
#: the host wrote them (host), the variational sets' first rows in ``particles_var`` and their
#: particle (vidx (nv, 2): -1 for a set of the whole system, i for REBOUND's
#: ``add_variation(testparticle=i)``) and a sliver step's
#: scratch for the tangents' coefficients (DGs)
Host = namedtuple("Host", ["st", "sd", "res", "written", "host", "vidx", "DGs"])


def step_arrays(rb, hb, system, state, trial, method, newton, wk, ext, tan):
    """One REBOUND step of sim.dt (rb: REBOUND's side, :data:`Rebound`; hb: HBVM's state block,
    :data:`Host`; the rest: the records of :mod:`integrators.records` over the context block's
    arrays, :mod:`hbvm_md.rebound.layout`; tan: the tangents, empty without variational
    particles).  Returns OK, RESYNC (nothing done) or a failure status (nothing done, cause
    recorded).

    On REBOUND's own accelerations (the context's D_HOST, :mod:`hbvm_md.rebound.forces`) the
    state is (q, clock, v, CLOCK): its clock is set to ``sim.t`` before the step, and the
    stages' positions, velocities and times that the kernel wrote into the particles and
    ``sim.t`` are replaced by the committed state, or restored when the step fails.  With
    attached ODEs (:mod:`hbvm_md.rebound.forces`, "Attached ODEs") the state's ODE block is
    synced from each ODE's ``y`` before the step (:func:`odes_read`) and written back after it
    (the committed state, or the state before a failed step), and the ODEs are hidden from
    REBOUND's own stepping of them until the next call (:func:`odes_release`).

    With variational particles the tangents advance by the derivative of the step taken
    (:func:`integrators.tangent.tangent_map` from the state before the step, with its accepted
    coefficients and size), committed with the state or not at all; when REBOUND computes
    MEGNO the step hands it dY = 2 int t' d ln|delta| over the step (t' from
    ``megno_initial_t``), as IAS15 does (its dt_done sum_i w_i t_i (delta'.delta/delta^2)(t_i)
    is a quadrature of the same integral): here the discrete tangent gives ln|delta| exactly
    at both ends, and the integral is taken as (t'_0 + t'_1) / 2 (ln|delta_1| - ln|delta_0|)."""
    simd, simi, ctx = rb.simd, rb.simi, rb.ctx
    host = hb.host
    params = system.params
    nodes = int(params[P_NODES]) if ctx[D_HOST] != 0 else 0
    if nodes > 0:
        odes_release(simi, params)
    if simd[ctx[R_G]] != host[0] or float(simi[ctx[R_NACTIVE]]) != host[1]:
        return RESYNC
    status = _step(rb, hb, system, state, trial, method, newton, wk, ext, tan)
    if nodes > 0 and status != RESYNC:
        # REBOUND steps the attached ODEs with its BS integrator after any other integrator's
        # step (from t - dt_last_done, with the bodies at the step's end): HBVM has stepped
        # them with the bodies, so the simulation shows no ODE until the step's next call or
        # the end of the run puts them back (odes_release; hbvm_md.rebound.host)
        params[P_ODES_HELD] = simi[int(params[P_ODES_WORD])]
        simi[int(params[P_ODES_WORD])] = 0
    return status


def odes_release(simi, params):
    """``sim->N_odes`` as it was before the last step hid the ODEs from REBOUND (above)."""
    if params[P_NODES] > 0 and params[P_ODES_HELD] != 0.0:
        simi[int(params[P_ODES_WORD])] = int(params[P_ODES_HELD])
        params[P_ODES_HELD] = 0.0


def odes_replaced(params):
    """Has an ODE's ``derivatives`` been replaced since the step was prepared (in a heartbeat,
    during a run: the step would call the old function, which Python may have freed)?"""
    o0 = odes_at(params)
    for e in range(int(params[P_NODES])):
        at = o0 + O_WIDTH * e
        word = carray(int64_pointer(int(params[at + O_ODE]) + int(params[P_ODE_DERIV_AT])), 1)
        if word[0] != int(params[at + O_DERIV]):
            return True
    return False


def odes_read(params, y, cy, eref, st):
    """The attached ODEs' state before a step: each ODE's ``pre_timestep`` (REBOUNDx's spins
    from the particles' "Omega"), then, where ``y`` differs from what the last step wrote (a
    user's change between runs), the state's ODE block reread from it, as moved particles are
    (compensations zeroed, the reference energy afresh).  The ODE block's positions (nothing
    reads them: module docstring of hbvm_md.rebound.forces) are set to 0, so that they never
    grow into the iteration's scale."""
    N = int(params[P_N])
    m = y.shape[0] // 2
    o0 = odes_at(params)
    moved = False
    for e in range(int(params[P_NODES])):
        at = o0 + O_WIDTH * e
        n, col, sig = int(params[at + O_LEN]), int(params[at + O_COL]), params[at + O_SIGMA]
        if params[at + O_PRE] != 0.0:
            call_void2(int(params[at + O_PRE]), int(params[at + O_ODE]), int(params[at + O_Y]))
        z = carray(float64_pointer(int(params[at + O_Y])), n)
        for i in range(n):
            j = m + 3 * N + col + i
            if z[i] != y[j] / sig:
                y[j] = z[i] * sig
                cy[j] = 0.0
                moved = True
            y[3 * N + col + i] = 0.0
            cy[3 * N + col + i] = 0.0
    if moved:
        for i in range(eref.shape[0]):
            eref[i] = np.nan
        st[SL_RESYNCS] += 1
    return moved


def moved_anchor(host_forces, y, kin_w, params, eref, e_old, anchor):
    """eref after particles were moved between two steps (an operator, a post-timestep
    callback: :func:`reread_particles`): the energy and EQUIP's warm starts start afresh, and
    the run's start (the drift check's anchor, core.DRIFT_BOUND) moves by the energy the move
    changed, H(moved) - H(last commit), so that the check goes on judging the steps' own drift
    over the run (a dissipating operator's energy is not the step's); T's mean, the run's time
    and T's largest stay.  Without a known energy and start, or on REBOUND's own accelerations,
    the run's terms start afresh (as before 2026-12-08 for every move)."""
    if not host_forces and np.isfinite(e_old) and np.isfinite(anchor):
        t, v = energy_parts(False, y, kin_w, params)
        eref[EREF_RUN] = anchor + ((t + v) - e_old)
        for i in range(EREF_RUN):
            eref[i] = np.nan
    else:
        for i in range(eref.shape[0]):
            eref[i] = np.nan


def _step(rb, hb, system, state, trial, method, newton, wk, ext, tan):
    """:func:`step_arrays` past its first checks."""
    simd, simi, view, ctx, r, pv = rb
    st, sd, res, written, host, vidx, DGs = hb
    _, minv, kin_w, params = system
    host_forces = ctx[D_HOST] != 0
    y, cy, gamma, eref, clock = state
    yt, cyt, gammat, ereft, _ = trial
    counters = wk.counters
    V, DG, Vt, DGt, tw, tcw, tcount, TP, TO = tan
    nodes = int(params[P_NODES]) if host_forces else 0
    if nodes > 0 and odes_replaced(params):
        return RESYNC
    ix, ivx = ctx[R_X], ctx[R_VX]
    if not settings_ok(st, sd):
        return BAD_SETTINGS
    if not particles_match(view, written, ix, ivx, ctx[R_M]):
        # moved between steps (an operator after every step): read in compiled code; the
        # previous coefficients stay the initial guess, the reference energy starts afresh
        e_old, anchor = eref[0], eref[EREF_RUN]
        if not reread_particles(view, written, ix, ivx, ctx[R_M], y, cy, minv):
            return RESYNC
        moved_anchor(host_forces, y, kin_w, params, eref, e_old, anchor)
        st[SL_RESYNCS] += 1
    h = simd[ctx[R_DT]]
    if not (abs(h) < np.inf and h != 0.0):
        sd[SL_H_FAIL] = h
        return BAD_DT
    t_start = simd[ctx[R_T]]
    # epsilon = 0: fixed steps of sim.dt, as IAS15 takes them (REBOUND's idiom)
    adaptive = st[SL_ADAPTIVE] != 0 and sd[SL_EPSILON] != 0.0
    epsilon = sd[SL_EPSILON] if adaptive else 0.0
    max_dt = sd[SL_MAX_DT] if adaptive else 0.0
    if max_dt > 0.0 and abs(h) > max_dt:       # (the user's bound, e.g. for an operator)
        h = max_dt if h > 0.0 else -max_dt
    else:       # (exact_finish_time's last step ends at tmax on the compensated clock)
        h = landing_step(simi, ctx, sd, t_start, h)
    etol = sd[SL_ETOL] if st[SL_ECHECK] > 0 else 0.0
    # the step's own error estimate (integrators.core.resolution_error, every body of three
    # coordinates), on with the energy check (energy_tol=None switches both off)
    ebound = ERROR_BOUND if sd[SL_ETOL] != 0.0 else 0.0
    N = view.shape[0]
    nv = V.shape[0]
    m = y.shape[0] // 2
    if host_forces:
        y[m - 1] = t_start * CLOCK                 # (exact: CLOCK is a power of two)
        cy[m - 1] = 0.0
    if nodes > 0:
        odes_read(params, y, cy, eref, st)
    if _TANGENTS and nv > 0:
        read_tangents(pv, vidx, N, ix, ivx, ctx[R_M], minv, V, DG, host[1], params, TP, TO)
    res[2] = 0.0
    # a fixed step's test-particle check may refuse a converged step: its work then comes out
    # of the counters and the clock, as the core takes a failed step's out
    c_iter, c_nfev, c_newton = counters[C_ITER], counters[C_NFEV], counters[C_NEWTON]
    clock0, clock1 = clock[0], clock[1]
    status = attempt(system, state, trial, h, sd[SL_H_PREV], t_start, ext, method, newton,
                     Options(st[SL_MAX_ITER], sd[SL_TOL], etol, ebound, 3), wk,
                     Adaptive(epsilon, sd[SL_MIN_DT], res))
    st[SL_REJECTED] += int(res[2])
    if status == OK and not adaptive and sd[SL_ETOL] != 0.0:
        # the test particles against the bodies they move among (the gravitating bodies, and
        # the test particles on REBOUND's own accelerations, are judged by the step's own
        # estimate, integrators.core.resolution_error, inside the step)
        worst, err, _ = test_particle_error(gammat, minv, kin_w, TP_FLOOR, TP_FACTOR, 0.0)
        if worst >= 0:
            counters[C_ITER], counters[C_NFEV], counters[C_NEWTON] = c_iter, c_nfev, c_newton
            counters[C_STEPS] -= 1
            clock[0], clock[1] = clock0, clock1
            res[3], res[4] = err, worst
            status = TEST_PARTICLE
    if status != OK:
        if host_forces:
            restore_particles(view, written, ix, ivx)
            simd[ctx[R_T]] = t_start
        if nodes > 0:       # (each ODE's y, and what its post_timestep writes, as before)
            odes_set(params, y[m + 3 * int(params[P_N]):], cy, False)
        record_failure(sd, res, t_start)
        return status
    h_done = res[0]
    hp = sd[SL_H_PREV]
    # exact_finish_time's sliver of a step (1e-16): the next step extrapolates from the last
    # regular one, whose gamma is kept
    sliver = not np.isnan(hp) and abs(h_done) < TINY_RATIO * abs(hp)
    d2_0 = 0.0
    megno = False
    if _TANGENTS and nv > 0:
        megno = (simi[ctx[R_MEGNO_ON] // 8] >> (8 * (ctx[R_MEGNO_ON] % 8))) & 0xFFFFFFFF != 0
        # the previous d gamma extrapolated as the step's gamma was (a sliver's are not kept)
        E = select_extrapolation(h_done, hp, ext.E1, ext.t, ext.w, ext.buf, ext.zero)
        dg = DG
        if sliver:
            for v in range(nv):
                copy2(DGs[v], DG[v])
            dg = DGs
        tstatus = tangent_map(System(False, minv, kin_w, params), y, cy, gammat, h_done, E,
                              method, newton, 2 * st[SL_MAX_ITER],
                              Tangents(V, dg, Vt, DGt, tw, tcw, tcount, TP, TO))
        if tstatus != OK:
            sd[SL_H_FAIL] = h_done
            sd[SL_T_FAIL] = t_start
            sd[SL_CAUSE_ERR] = tcount[2]
            sd[SL_CAUSE_STATUS] = tstatus
            return TANGENT_FAILED + tstatus
        if megno:      # (MEGNO's set is the whole system's, REBOUND's first N rows)
            d2_0 = delta2(pv, N, ix, ivx)
    copy1(y, yt)
    copy1(cy, cyt)
    if not sliver:
        copy2(gamma, gammat)
        sd[SL_H_PREV] = h_done
    eref[0] = ereft[0]
    if not sliver:
        # EQUIP's alpha and dE/dalpha (warm starts of its energy condition), as gamma: a
        # sliver's slope, of the order of its h, would misguide the next regular step
        for i in range(1, EREF_RUN):
            eref[i] = ereft[i]
    for i in range(EREF_RUN, eref.shape[0]):      # the run's start, mean T and time: any step's
        eref[i] = ereft[i]
    sd[SL_RUN_ERR] = counters[C_RUN_ERR]          # (sim.integrator.error_estimate)
    for i in range(view.shape[0]):
        for c in range(3):
            view[i, ix + c] = y[3 * i + c]
            view[i, ivx + c] = y[m + 3 * i + c] * minv[3 * i + c]
            written[i, c] = view[i, ix + c]
            written[i, 3 + c] = view[i, ivx + c]
    if nodes > 0:
        odes_set(params, y[m + 3 * int(params[P_N]):], cy, False)
    # REBOUND's time is the step's to advance: compensated, so that sim.t (and the forces that
    # read it at the next step) stays n dt to an ulp after any number of steps
    t_end, ct = step_end(sd, t_start, h_done)
    commit_clock(simd, ctx, sd, t_end, ct)
    simd[ctx[R_DTL]] = h_done
    if adaptive:
        h_next = res[1]                        # the next step proposed
        if max_dt > 0.0 and abs(h_next) > max_dt:
            h_next = max_dt if h_next > 0.0 else -max_dt
        simd[ctx[R_DT]] = h_next
    if _TANGENTS and nv > 0:
        write_tangents(pv, vidx, N, ix, ivx, minv, V)
        if megno:
            t0 = simd[ctx[R_MEGNO_T0]]
            dY = (t_start - t0 + (t_end - t0)) * 0.5 * (
                np.log(delta2(pv, N, ix, ivx)) - np.log(d2_0))
            call_megno(ctx[D_MEGNO_FN], r, dY, h_done)
    st[SL_NSTEPS] += 1
    return OK


def core_step(r, p):
    """:func:`step_arrays` on REBOUND's simulation ``r`` and HBVM's state ``p`` (the context
    block's addresses in ``p``'s slot SL_CTX); RESYNC also when the particle array moved or
    changed size."""
    ra, pa = address_of(r), address_of(p)
    st, sd, ctx, simd, simi = context_views(ra, pa)
    N = ctx[D_N]
    if ctx[D_HOST] != 0:        # (N_odes is a word the checks below compare)
        odes_release(simi, carray(float64_pointer(ctx[A_PARAMS]), ctx[D_P]))
    if not context_current(simi, st, ctx):
        return RESYNC
    s, m = ctx[D_S], ctx[D_M]
    u = m                                          # the coefficients' width (separable)
    if simi[ctx[R_PVAR]] != ctx[D_PVAR]:
        return RESYNC                              # the variational particles moved
    view = carray(float64_pointer(ctx[D_PTR]), (N, ctx[R_STRIDE]))
    nv = ctx[D_NV]
    vidx = ctx_2(ctx, A_VIDX, nv, 2)
    pv = carray(float64_pointer(ctx[D_PVAR]), (var_rows(vidx, N), ctx[R_STRIDE]))
    state, trial, method, newton, work, ext = step_records(ctx, st, pa, m, u)
    return step_arrays(
        Rebound(simd, simi, view, ctx, ra, pv),
        Host(st, sd, carray(float64_pointer(pa + 8 * SL_RES), N_RES),
             ctx_2(ctx, A_WRITTEN, N, 7), ctx_1(ctx, A_HOST, N_HOST), vidx,
             ctx_3(ctx, A_DGS, nv, s, m)),
        System(False, ctx_1(ctx, A_MINV, u), ctx_1(ctx, A_KINW, m),
               ctx_1(ctx, A_PARAMS, ctx[D_P])),
        state, trial, method, newton, work, ext,
        Tangents(ctx_2(ctx, A_V, nv, 2 * m), ctx_3(ctx, A_DG, nv, s, m),
                 ctx_2(ctx, A_VT, nv, 2 * m), ctx_3(ctx, A_DGT, nv, s, m),
                 ctx_1(ctx, A_TW, ctx[D_TGF]), carray(complex128_pointer(ctx[A_TCW]), ctx[D_TGC]),
                 ctx_1(ctx, A_TCOUNT, 3), ctx_2(ctx, A_TP, nv, 6 * N + 3),
                 ctx_2(ctx, A_TO, nv, 3)))


if TYPE_CHECKING:
    # integrators.specialise compiles this text after the step's (integrators.loop, and
    # integrators.tangent or its stand-in in integrators.absent), where these are the step's
    # own, bound to the N-body kernel (imported here for readers and linters only)
    from integrators.loop import attempt, energy_parts
    from integrators.tangent import tangent_map
