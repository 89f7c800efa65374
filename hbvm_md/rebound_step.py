"""REBOUND's host glue around the single step core, compiled with it in one module.

:mod:`integrators.specialise` appends this file's text to the step's (:mod:`integrators.loop`,
with the N-body kernel bound) and compiles :data:`GLUE_FUNCTIONS` and the C callback
:data:`GLUE_CFUNCS` there, so that one REBOUND step is one compiled call: have the particles
changed? the core's :func:`~integrators.loop.attempt` on trial arrays, then the commit (state,
particles, time, bookkeeping).  Nothing here is numerics; the driver
(:mod:`hbvm_md.rebound_driver`) keeps the Python side: models, errors, copies and restarts.

Two ways in, one step:

* :func:`host_step_arrays` takes the arrays: it is what runs as Python (``NUMBA_DISABLE_JIT``,
  or a kernel that is not compiled);
* :func:`host_step` takes one int64 array ``ctx`` of addresses and sizes (layout: the ``A_*``
  and ``D_*`` slots below), views the arrays with ``numba.carray`` and calls
  :func:`host_step_arrays`: a Python callback pays for one argument, not thirty;
* :func:`host_cstep` is a C callback (``void (*)(struct reb_simulation*)``) that REBOUND calls
  as its post-timestep function when no Python callback needs to run (no heartbeat, no other
  callback): it finds ``ctx`` through the simulation's ``extras`` pointer, which the driver
  sets for the time of one ``integrate``.  A step that cannot be committed puts ``sim.t`` back
  and stops REBOUND (status REB_STATUS_USER); the driver raises the error, or re-reads the
  particles (RESYNC) and goes on.

Struct offsets are REBOUND 5.x's (checked against ``rebound.Simulation``'s fields at attach).
"""
import numpy as np
from numba import carray

from integrators.pointers import (address_of, complex128_pointer, float64_pointer,
                                  int32_pointer, int64_pointer)
from integrators.core import N_COUNTERS, OK, TINY_RATIO, copy1, copy2

RESYNC = -1               # the particles are not what the driver wrote last: re-read them

# struct reb_simulation (REBOUND 5.x), in doubles (8 bytes) from its start
T_AT, G_AT, DT_AT, DTL_AT, STEPS_AT, N_AT, PTR_AT, NA_AT = 0, 1, 5, 6, 7, 9, 11, 18
SIM_HEAD = 19                # doubles viewed: t .. N_active
STATUS_BYTES = 216           # int status
EXTRAS_BYTES = 808           # void* extras
REB_STATUS_USER = 5          # what reb_simulation_stop sets: the run ends without an error
PARTICLE_DOUBLES = 14        # sizeof(struct reb_particle) / 8: x, y, z, vx, vy, vz at 0-5, m at 9

# ctx: addresses of the arrays, in host_step_arrays' order
(A_Y, A_CY, A_YT, A_CYT, A_GAMMA, A_GAMMAT, A_EREF, A_EREFT, A_WRITTEN, A_MINV, A_KINW,
 A_PARAMS, A_TN, A_TS, A_WP, A_CP, A_NV, A_NVINV, A_NM, A_COUNTERS, A_WORK, A_CWORK, A_CLOCK,
 A_E1, A_ET, A_EW, A_EBUF, A_EZERO, A_SCAL) = range(29)
# ... then sizes: state dimension 2m (m = 3N), s, k, N, kernel parameters, work buffers,
# the simulation's address, and the particle pointer and N the arrays were built for
D_S, D_K, D_M, D_N, D_P, D_NF, D_NC, D_SIM, D_PTR, D_NPART = range(29, 39)
N_CTX = 39

# scal: the driver's scalars (float64), read and written by the step
(S_H_PREV, S_T_WRITTEN, S_NSTEPS, S_REJECTED, S_EPSILON, S_MIN_DT, S_MAX_ITER, S_TOL, S_ETOL,
 S_G, S_NA, S_STATUS, S_H_FAIL, S_T_FAIL, S_CAUSE_ERR, S_CAUSE_STATUS, S_RES) = range(17)
N_SCAL = S_RES + 5           # res of loop.attempt: h taken, next h, rejections, cause, status

GLUE_FUNCTIONS = ("particles_match", "step_start", "undo_time", "host_step_arrays", "host_step")
GLUE_CFUNCS = {"host_cstep": "void(voidptr)"}
GLUE_DEPENDS = ("integrators.pointers",)        # in the generated module's hash


def particles_match(view, written):
    """Are REBOUND's particles (view, (N, 14) over reb_particle) what the last commit wrote
    (written: x, y, z, vx, vy, vz, m)?"""
    N = view.shape[0]
    if written.shape[0] != N:
        return False
    for i in range(N):
        for c in range(6):
            if view[i, c] != written[i, c]:
                return False
        if view[i, 9] != written[i, 6]:
            return False
    return True


def step_start(simd, scal):
    """sim.t before REBOUND's "none" integrator did t += dt_last_done (exact when the driver
    wrote it)."""
    t = simd[T_AT]
    h = simd[DTL_AT]
    tw = scal[S_T_WRITTEN]
    if not np.isnan(tw) and tw + h == t:
        return tw
    return t - h


def undo_time(simd, scal):
    """Undo REBOUND's t += dt of a step that was not committed."""
    t0 = step_start(simd, scal)
    simd[T_AT] = t0
    scal[S_T_WRITTEN] = t0


def host_step_arrays(simd, simi, view, y, cy, yt, cyt, gamma, gammat, eref, ereft, written, minv,
                     kin_w, params, tn, ts, Wp, Cp, NV, NVinv, NM, counters, work, cwork, clock,
                     E1, Et, Ew, Ebuf, Ezero, scal):
    """One REBOUND step: RESYNC when the particles, G or N_active changed (nothing done);
    otherwise the core's step of REBOUND's dt_last_done (adaptive when scal[S_EPSILON] > 0:
    tried smaller until accepted, and sim.t, dt_last_done and dt then say the step taken and
    the next one proposed), committed into the state (y, cy, gamma, eref), the particles and
    the bookkeeping (scal) together.  Returns the status; a failed step commits nothing and
    records its step size, start time and cause in scal."""
    if simd[G_AT] != scal[S_G] or float(simi[NA_AT]) != scal[S_NA]:
        return RESYNC
    if not particles_match(view, written):
        return RESYNC
    h = simd[DTL_AT]
    t_start = step_start(simd, scal)
    res = scal[S_RES:]
    res[2] = 0.0
    status = attempt(False, y, cy, gamma, eref, yt, cyt, gammat, ereft, minv, kin_w,  # noqa: F821
                     params, h, scal[S_H_PREV], E1, Et, Ew, Ebuf, Ezero, (tn, ts), (Wp, Cp),
                     NV, NVinv, NM, int(scal[S_MAX_ITER]), scal[S_TOL], scal[S_ETOL], counters,
                     work, cwork, clock, scal[S_EPSILON], scal[S_MIN_DT], t_start, res)
    scal[S_REJECTED] += res[2]
    scal[S_STATUS] = status
    if status != OK:
        scal[S_H_FAIL] = res[0]
        scal[S_T_FAIL] = t_start
        scal[S_CAUSE_ERR] = res[3]
        scal[S_CAUSE_STATUS] = res[4]
        return status
    h_done = res[0]
    hp = scal[S_H_PREV]
    # exact_finish_time's sliver of a step (1e-16): the next step extrapolates from the last
    # regular one, whose gamma is kept
    sliver = not np.isnan(hp) and abs(h_done) < TINY_RATIO * abs(hp)
    copy1(y, yt)
    copy1(cy, cyt)
    if not sliver:
        copy2(gamma, gammat)
    eref[0] = ereft[0]
    m = minv.shape[0]
    for i in range(view.shape[0]):
        for c in range(3):
            view[i, c] = y[3 * i + c]
            view[i, 3 + c] = y[m + 3 * i + c] * minv[3 * i + c]
            written[i, c] = view[i, c]
            written[i, 3 + c] = view[i, 3 + c]
    if h_done != h:                     # what REBOUND records as done
        simd[DTL_AT] = h_done
        simd[T_AT] = t_start + h_done
    if scal[S_EPSILON] > 0.0:
        simd[DT_AT] = res[1]            # the next step proposed
    if not sliver:
        scal[S_H_PREV] = h_done
    scal[S_T_WRITTEN] = simd[T_AT]
    scal[S_NSTEPS] += 1.0
    return OK


def host_step(ctx):
    """:func:`host_step_arrays` on the arrays whose addresses and sizes ``ctx`` holds; RESYNC
    also when REBOUND's particle array moved or changed size."""
    simd = carray(float64_pointer(ctx[D_SIM]), SIM_HEAD)
    simi = carray(int64_pointer(ctx[D_SIM]), SIM_HEAD)
    N = ctx[D_NPART]
    if simi[PTR_AT] != ctx[D_PTR] or simi[N_AT] != N:
        return RESYNC
    s, k, m, P = ctx[D_S], ctx[D_K], ctx[D_M], ctx[D_P]
    d = 2 * m

    def f(slot, n):
        return carray(float64_pointer(ctx[slot]), n)

    def f2(slot, r, c):
        return carray(float64_pointer(ctx[slot]), (r, c))

    def f3(slot, a, b, c):
        return carray(float64_pointer(ctx[slot]), (a, b, c))

    def z2(slot, r, c):
        return carray(complex128_pointer(ctx[slot]), (r, c))

    view = carray(float64_pointer(simi[PTR_AT]), (N, PARTICLE_DOUBLES))
    return host_step_arrays(
        simd, simi, view, f(A_Y, d), f(A_CY, d), f(A_YT, d), f(A_CYT, d), f2(A_GAMMA, s, m),
        f2(A_GAMMAT, s, m), f(A_EREF, 1), f(A_EREFT, 1), f2(A_WRITTEN, N, 7), f(A_MINV, m),
        f(A_KINW, m), f(A_PARAMS, P), f2(A_TN, 2, k), f2(A_TS, 2, s), f3(A_WP, 2, s, k),
        f3(A_CP, 4, k, s), z2(A_NV, s, s), z2(A_NVINV, s, s),
        carray(complex128_pointer(ctx[A_NM]), (0, m, m)), f(A_COUNTERS, N_COUNTERS), f(A_WORK, ctx[D_NF]),
        carray(complex128_pointer(ctx[A_CWORK]), ctx[D_NC]), f(A_CLOCK, 2), f2(A_E1, s, s),
        f(A_ET, s), f(A_EW, s), f2(A_EBUF, s, s), f2(A_EZERO, s, s), f(A_SCAL, N_SCAL))


def host_cstep(r):
    """REBOUND's post-timestep callback in C: :func:`host_step` on the ``ctx`` that the
    simulation's ``extras`` points to; a step not committed (a failure, or RESYNC) puts sim.t
    back and stops the run (the driver takes it from there)."""
    a = address_of(r)
    ctx = carray(int64_pointer(carray(int64_pointer(a + EXTRAS_BYTES), 1)[0]), N_CTX)
    status = host_step(ctx)
    if status != OK:
        scal = carray(float64_pointer(ctx[A_SCAL]), N_SCAL)
        scal[S_STATUS] = status
        undo_time(carray(float64_pointer(a), SIM_HEAD), scal)
        if status == RESYNC:     # not a step: REBOUND counts it after this callback
            carray(int64_pointer(a), SIM_HEAD)[STEPS_AT] -= 1
        carray(int32_pointer(a + STATUS_BYTES), 1)[0] = REB_STATUS_USER
