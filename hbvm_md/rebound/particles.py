"""REBOUND's particles seen from the compiled step: the helpers of both REBOUND steps
(:mod:`hbvm_md.rebound.glue`, :mod:`hbvm_md.rebound.kepler_glue`) that do not depend on the
force kernel or the method (the views of HBVM's state, the context block and the simulation;
is the context block still the simulation's; the step's records; a failure's record; does the
simulation hold what the last step wrote, read it afresh, restore it, the settings' ranges,
the variational particles).

They are an ordinary compiled module, cached once: every generated step module (one per scene
variant, :mod:`integrators.specialise`) links the same compiled functions instead of compiling
its own copies (six REBOUND variants in the test suite compiled them six times).
"""
import numpy as np
from numba import carray

from integrators.core import N_COUNTERS, tick
from integrators.jit import jit
from integrators.pointers import complex128_pointer, float64_pointer, int64_pointer
from integrators.records import Extrapolation, Method, Newton, State, Work
from hbvm_md.rebound.layout import (A_CLOCK, A_CP, A_CWORK, A_CYT, A_E1, A_EBUF, A_EREFT, A_ET,
                                    A_EW, A_EZERO, A_GAMMAT, A_NM, A_NV, A_NVINV, A_TN, A_TS,
                                    A_WORK, A_WP, A_YT, C_VALUES, C_WORDS, D_CPP, D_K, D_KEPLER,
                                    D_KK, D_METHOD, D_N, D_NC, D_NF, D_NODES, D_PTR, D_S, D_TNC,
                                    D_TSR, D_WPP, N_CFG, N_EREF, N_HEADER, N_SLOTS, R_HEAD, R_N,
                                    R_STATUS, R_T, R_PARTICLES, SL_ADAPTIVE, SL_CAUSE_ERR, SL_CAUSE_STATUS, SL_CTX,
                                    SL_COUNTERS, SL_EPSILON, SL_EREF, SL_ETOL, SL_GAMMA, SL_H_FAIL,
                                    SL_K, SL_KEPLER, SL_MAX_DT, SL_MAX_ITER, SL_METHOD, SL_MIN_DT,
                                    SL_NODES, SL_S, SL_TOL, SL_T_COMP, SL_T_FAIL,
                                    SL_T_WRITTEN, SL_Y)

#: layout.py's digest (as cabi.LAYOUT_DIGEST): numba caches this module's compiled functions
#: with layout's slot numbers compiled in, keyed on this file alone, so a layout change must
#: change this file too (tests/test_rebound_host.py keeps it current); else a ``git pull`` of a
#: new layout over an old cache loads code that indexes the state with the old slots
LAYOUT_DIGEST = "e1008eefe6ce66b8"


@jit
def particles_match(view, written, ix, ivx, im):
    """Are REBOUND's particles (view: (N, stride) doubles over reb_particle, x, vx and m at
    columns ix, ivx, im) what the last commit wrote (written: x, y, z, vx, vy, vz, m)?"""
    N = view.shape[0]
    if written.shape[0] != N:
        return False
    for i in range(N):
        for c in range(3):
            if view[i, ix + c] != written[i, c] or view[i, ivx + c] != written[i, 3 + c]:
                return False
        if view[i, im] != written[i, 6]:
            return False
    return True


@jit
def reread_particles(view, written, ix, ivx, im, y, cy, minv):
    """The state y (2m,) <- REBOUND's particles whose positions or velocities were changed
    between two steps (by a REBOUNDx operator, a post-timestep callback, the user), with the
    same masses: q = x, p = v / minv (the momenta, or the velocities of the state on REBOUND's
    own accelerations, whose weights are 1), their compensations zeroed (the clock's
    coordinates, after the particles', are the glue's); ``written`` <- them.
    Returns False, changing nothing, when a mass changed or a value is not finite: the host
    then updates the masses in place (:mod:`hbvm_md.rebound.masses`, when nothing else
    changed) or prepares the step afresh (and names what is wrong)."""
    N = view.shape[0]
    for i in range(N):
        if view[i, im] != written[i, 6]:
            return False
        for c in range(3):
            if not (np.isfinite(view[i, ix + c]) and np.isfinite(view[i, ivx + c])):
                return False
    m = y.shape[0] // 2
    for i in range(N):
        for c in range(3):
            y[3 * i + c] = view[i, ix + c]
            cy[3 * i + c] = 0.0
            y[m + 3 * i + c] = view[i, ivx + c] / minv[3 * i + c]
            cy[m + 3 * i + c] = 0.0
            written[i, c] = view[i, ix + c]
            written[i, 3 + c] = view[i, ivx + c]
    return True


@jit
def restore_particles(view, written, ix, ivx):
    """REBOUND's particles' x and v <- what the last commit wrote (a step on REBOUND's own
    accelerations leaves its last stage in them)."""
    for i in range(view.shape[0]):
        for c in range(3):
            view[i, ix + c] = written[i, c]
            view[i, ivx + c] = written[i, 3 + c]


@jit
def context_views(ra, pa):
    """(st, sd, ctx, simd, simi): HBVM's state at address ``pa`` as int64 and float64 slots, its
    context block's header, and REBOUND's simulation at ``ra`` as words of both kinds (as far
    as the header's R_HEAD reaches): what both REBOUND steps read first."""
    st = carray(int64_pointer(pa), N_SLOTS)
    sd = carray(float64_pointer(pa), N_SLOTS)
    ctx = carray(int64_pointer(st[SL_CTX]), N_HEADER)
    return (st, sd, ctx, carray(float64_pointer(ra), ctx[R_HEAD]),
            carray(int64_pointer(ra), ctx[R_HEAD]))


@jit
def ctx_1(ctx, slot, n):
    """The context block's array at header word ``slot``, n doubles."""
    return carray(float64_pointer(ctx[slot]), n)


@jit
def ctx_2(ctx, slot, a, b):
    """... (a, b) doubles."""
    return carray(float64_pointer(ctx[slot]), (a, b))


@jit
def ctx_3(ctx, slot, a, b, c):
    """... (a, b, c) doubles."""
    return carray(float64_pointer(ctx[slot]), (a, b, c))


@jit
def ctx_z2(ctx, slot, a, b):
    """... (a, b) complex numbers."""
    return carray(complex128_pointer(ctx[slot]), (a, b))


@jit
def record_failure(sd, res, t_start):
    """What a failed step leaves for the host's error (:func:`hbvm_md.rebound.host.
    _step_failure`): its size, its start, and its cause's estimate and status (``res``:
    loop.attempt's)."""
    sd[SL_H_FAIL] = res[0]
    sd[SL_T_FAIL] = t_start
    sd[SL_CAUSE_ERR] = res[3]
    sd[SL_CAUSE_STATUS] = res[4]


@jit
def clock_comp(sd, t_start):
    """The compensation of the clock at sim.t = ``t_start`` (the exact time is t_start minus
    it): the saved one (layout.SL_T_COMP) while sim.t is what the last step wrote, else 0 (the
    user set sim.t: it is taken as exact)."""
    return sd[SL_T_COMP] if t_start == sd[SL_T_WRITTEN] else 0.0


@jit
def step_end(sd, t_start, h):
    """The step's end time and the clock's compensation after it (as the engine's Stepper
    keeps its clock, :func:`integrators.core.tick`): ``t_start`` + ``h`` with the compensation
    of the sum of steps so far (:func:`clock_comp`).  Nothing is stored: :func:`commit_clock`
    does, with the step."""
    return tick(t_start, clock_comp(sd, t_start), h)


#: REBOUND's REB_STATUS_LAST_STEP (-2) as the low 32 bits of its word
LAST_STEP_BITS = 0xFFFFFFFE


@jit
def landing_step(simi, ctx, sd, t_start, h):
    """The step to take for REBOUND's sim.dt ``h``: ``h`` itself, except on the last step of an
    ``exact_finish_time`` run (REBOUND's status REB_STATUS_LAST_STEP, its dt set to tmax -
    sim.t), where the compensated clock's time is sim.t - ct (:func:`step_end`): there the step
    is h + ct, so that the bodies end at tmax itself and sim.t shows tmax exactly, as REBOUND's
    own integrators leave it (a run's output times are where the user asked).  ct is below an
    ulp of t, and 0 while every step so far summed exactly (dt = 500 days: the same numbers)."""
    w = ctx[R_STATUS]
    if (simi[w // 8] >> (8 * (w % 8))) & 0xFFFFFFFF != LAST_STEP_BITS:
        return h
    return h + clock_comp(sd, t_start)


@jit
def commit_clock(simd, ctx, sd, t_end, ct):
    """sim.t <- the step's end (:func:`step_end`), and the compensation and the t written kept
    in HBVM's saved state; sim.dt_last_done is the caller's (the step's size)."""
    simd[ctx[R_T]] = t_end
    sd[SL_T_COMP] = ct
    sd[SL_T_WRITTEN] = t_end


@jit
def context_current(simi, st, ctx):
    """Is the context block still the simulation's?  False (the step answers RESYNC, and the
    host prepares afresh) when REBOUND's particle array moved or changed size, or the method
    or a setting HBVM checks changed between runs: the one test of both REBOUND steps (plain,
    :mod:`~hbvm_md.rebound.glue`, and composed, :mod:`~hbvm_md.rebound.kepler_glue`)."""
    if simi[ctx[R_PARTICLES]] != ctx[D_PTR] or simi[ctx[R_N]] != ctx[D_N]:
        return False
    if (st[SL_S] != ctx[D_S] or st[SL_K] != ctx[D_K] or st[SL_NODES] != ctx[D_NODES]
            or st[SL_METHOD] != ctx[D_METHOD] or st[SL_KEPLER] != ctx[D_KEPLER]):
        return False
    for i in range(N_CFG):
        if simi[ctx[C_WORDS + i]] != ctx[C_VALUES + i]:
            return False
    return True


@jit
def step_records(ctx, st, pa, m, u):
    """The step's records (:mod:`integrators.records`) over HBVM's state in REBOUND (``pa``:
    its address; the double-double state y, cy at slot SL_Y, gamma (s, u) at SL_GAMMA, eref)
    and the context block ``ctx``: (state, trial state, method, Newton, work, extrapolation),
    for a state of 2m components whose coefficients are u wide (u = m in the separable form,
    2m in the full form).  Both REBOUND steps bind them so."""
    s, kk = ctx[D_S], ctx[D_KK]
    ys = st[SL_Y]
    state = State(carray(float64_pointer(ys), 2 * m), carray(float64_pointer(ys + 16 * m), 2 * m),
                  carray(float64_pointer(st[SL_GAMMA]), (s, u)),
                  carray(float64_pointer(pa + 8 * SL_EREF), N_EREF), ctx_1(ctx, A_CLOCK, 2))
    trial = State(ctx_1(ctx, A_YT, 2 * m), ctx_1(ctx, A_CYT, 2 * m), ctx_2(ctx, A_GAMMAT, s, u),
                  ctx_1(ctx, A_EREFT, N_EREF), ctx_1(ctx, A_CLOCK, 2))
    method = Method(ctx_2(ctx, A_TN, 2, ctx[D_TNC]), ctx_2(ctx, A_TS, ctx[D_TSR], s),
                    ctx_3(ctx, A_WP, ctx[D_WPP], s, kk), ctx_3(ctx, A_CP, ctx[D_CPP], kk, s))
    newton = Newton(ctx_z2(ctx, A_NV, s, s), ctx_z2(ctx, A_NVINV, s, s),
                    carray(complex128_pointer(ctx[A_NM]), (0, u, u)))
    work = Work(ctx_1(ctx, A_WORK, ctx[D_NF]), carray(complex128_pointer(ctx[A_CWORK]), ctx[D_NC]),
                carray(float64_pointer(st[SL_COUNTERS]), N_COUNTERS))
    ext = Extrapolation(ctx_2(ctx, A_E1, s, s), ctx_1(ctx, A_ET, s), ctx_1(ctx, A_EW, s),
                        ctx_2(ctx, A_EBUF, s, s), ctx_2(ctx, A_EZERO, s, s))
    return state, trial, method, newton, work, ext


@jit
def settings_ok(st, sd):
    """The ranges :func:`hbvm_md.rebound.host.check_settings` checks (and names), for the
    settings a user may change in ``sim.integrator`` between runs."""
    if st[SL_MAX_ITER] < 1 or not 0.0 <= sd[SL_TOL] < 1.0 or not -1.0 < sd[SL_ETOL] < np.inf:
        return False
    if not 0.0 <= sd[SL_MAX_DT] < np.inf:
        return False
    # epsilon = 0 is IAS15's idiom for fixed steps of sim.dt (glue.step_arrays)
    return st[SL_ADAPTIVE] == 0 or sd[SL_EPSILON] == 0.0 or (
        0.0 < sd[SL_EPSILON] < 1.0 and 0.0 <= sd[SL_MIN_DT] < np.inf)


@jit
def read_tangents(pv, vidx, N, ix, ivx, im, minv, V, DG, na, params, TP, TO):
    """V (nv, 2u) <- REBOUND's first-order variational particles (pv: (N_var, stride) doubles
    over ``particles_var``; set v's rows start at vidx[v, 0]): dq = dx and dp = dv / minv
    (the momenta's variation: m dv for a gravitating body, dv for a test particle).

    A set of the whole system (vidx[v, 1] < 0) has N rows.  A set of one particle i =
    vidx[v, 1] (REBOUND's ``add_variation(testparticle=i)``) has one row, the variation of
    particle i with every other particle's variation zero: V[v] holds it at i's entries and
    zeros elsewhere.

    TP (nv, 6N + 3) <- each set's params of the force's derivative: the N-body kernel's first
    3N + 3 ``params`` with N given as -N, then the set's variation of the masses, its
    particles' m (column im), of the gravitating particles (index below na, or all when
    na < 0) as REBOUND's variational equations count them
    (:func:`systems.nbody.nbody_force_jvp`), then for a second-order set (TO (nv, 3): order,
    first-order sets a and b, :func:`hbvm_md.rebound.state.orders`) a's and b's variations of
    the masses (its forcing's, :func:`systems.nbody._second_jvp`; zeros for a first-order set).
    A second-order set's own m is the second variation of the masses.  With the momenta's variation
    taken as m dv (fixed m), a mass varied enters the linearised step through the force only.
    A set of one particle i varies no mass and sees i's gravitating mass as zero: REBOUND
    moves it as a test particle in the field of the others (its variational equations leave
    out i's pull on them and any mass variation), and with i's pull gone the others'
    variations stay exactly zero through the step.

    V holds the tangents as the last step wrote them: a set that differs (edited by the user,
    rescaled by REBOUND) gets its previous coefficients DG[v] (the tangent map's initial
    guess, which belongs to the tangent it was computed for) zeroed."""
    m = minv.shape[0]
    for v in range(V.shape[0]):
        i0 = int(vidx[v, 0])
        tp = int(vidx[v, 1])
        same = True
        for i in range(N):
            if tp >= 0 and i != tp:
                for c in range(3):
                    if V[v, 3 * i + c] != 0.0 or V[v, m + 3 * i + c] != 0.0:
                        same = False
                    V[v, 3 * i + c] = 0.0
                    V[v, m + 3 * i + c] = 0.0
                continue
            row = i0 + (0 if tp >= 0 else i)
            for c in range(3):
                dx, dv = pv[row, ix + c], pv[row, ivx + c]
                # (as write_tangents wrote them)
                if dx != V[v, 3 * i + c] or dv != V[v, m + 3 * i + c] * minv[3 * i + c]:
                    same = False
                V[v, 3 * i + c] = dx
                V[v, m + 3 * i + c] = dv / minv[3 * i + c]
        if not same:
            for j in range(DG.shape[1]):
                for u in range(DG.shape[2]):
                    DG[v, j, u] = 0.0
    P = 3 * N + 3
    for v in range(V.shape[0]):
        i0 = int(vidx[v, 0])
        tp = int(vidx[v, 1])
        for a in range(P):
            TP[v, a] = params[a]
        TP[v, 1] = -N
        if tp >= 0:
            TP[v, 2 + N + tp] = 0.0
        for i in range(N):
            TP[v, P + i] = pv[i0 + i, im] if (tp < 0 and (na < 0 or i < na)) else 0.0
        ia, ib = int(TO[v, 1]), int(TO[v, 2])
        for i in range(N):
            # (sets a and b come before: their columns are already read)
            TP[v, P + N + i] = TP[ia, P + i] if TO[v, 0] == 2 else 0.0
            TP[v, P + 2 * N + i] = TP[ib, P + i] if TO[v, 0] == 2 else 0.0


@jit
def write_tangents(pv, vidx, N, ix, ivx, minv, V):
    """REBOUND's variational particles <- V (the inverse of :func:`read_tangents`; a set of
    one particle gets that particle's entries)."""
    m = minv.shape[0]
    for v in range(V.shape[0]):
        i0 = int(vidx[v, 0])
        tp = int(vidx[v, 1])
        for i in range(N):
            if tp >= 0 and i != tp:
                continue
            row = i0 + (0 if tp >= 0 else i)
            for c in range(3):
                pv[row, ix + c] = V[v, 3 * i + c]
                pv[row, ivx + c] = V[v, m + 3 * i + c] * minv[3 * i + c]


@jit
def var_rows(vidx, N):
    """The rows of ``particles_var`` the sets in vidx span (:func:`read_tangents`)."""
    rows = 0
    for v in range(vidx.shape[0]):
        end = int(vidx[v, 0]) + (1 if vidx[v, 1] >= 0 else N)
        if end > rows:
            rows = end
    return rows


@jit
def delta2(pv, N, ix, ivx):
    """|delta|^2 = sum of dx^2 + dv^2 over variational particles 0 .. N-1: the tangent whose
    growth REBOUND's MEGNO measures (``reb_tools_megno_deltad_delta`` reads these rows)."""
    acc = 0.0
    for i in range(N):
        for c in range(3):
            acc += pv[i, ix + c] * pv[i, ix + c] + pv[i, ivx + c] * pv[i, ivx + c]
    return acc
