/* hbvm_md.rebound._glue: HBVM's step inside REBOUND, compiled when the package is installed,
 * against the installed REBOUND's rebound.h (as REBOUNDx builds against it).
 *
 * Three C functions are registered with REBOUND or called through HBVM's state:
 *   dispatch(r, p)  REBOUND's step: the step at the state's SL_CORE, the host's prepare (a
 *                   Python callback) first when there is none or the step answers RESYNC, the
 *                   host's fail (a Python callback) when it failed;
 *   release(p)      REBOUND's free: the arrays of the state and the state;
 *   step(r, p)      the plain N-body step (hbvm_md.rebound.glue.step_arrays' contract for its
 *                   default case: HBVM, the fixed-point iteration, gravity among bodies that
 *                   are all sources, no test particles, no variational particles, no REBOUND
 *                   forces or attached ODEs, no Kepler composition), calling the compiled
 *                   core's one retry loop (integrators._core's API capsule: one binary of the
 *                   step) with the N-body kernel.  Every other case keeps the numba step of
 *                   hbvm_md.rebound.glue, which dispatch calls the same way.
 *
 * REBOUND's simulation is read by name (struct reb_simulation, struct reb_particle); HBVM's
 * state and its context block by the slot numbers of hbvm_md/rebound/layout.py, which setup.py
 * writes into hbvm_layout.h when it builds this file (one table for Python, numba and C).  The
 * module checks at import that the rebound.h it was built with is the running REBOUND's
 * layout (hbvm_md.rebound.cglue compares the offsets exported here with REBOUND's ctypes
 * structures). */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "rebound.h"
#include "hbvm_core.h"
#include "hbvm_layout.h"

static const hbvm_api *core;

typedef int (*status_fn)(struct reb_simulation *, void *);

#define ST(p) ((int64_t *)(p))
#define SD(p) ((double *)(p))
#define CTXP(ctx, a) ((double *)(intptr_t)(ctx)[a])

/* REBOUND's step */
static void dispatch(struct reb_simulation *r, void *p)
{
    int64_t *st = ST(p);
    int status = RB_RESYNC;
    if (st[RB_SL_CORE] != 0)
        status = ((status_fn)(intptr_t)st[RB_SL_CORE])(r, p);
    if (status == RB_RESYNC) {
        status = ((status_fn)(intptr_t)st[RB_SL_PREPARE])(r, p);
        if (status == RB_OK)
            status = ((status_fn)(intptr_t)st[RB_SL_CORE])(r, p);
    }
    if (status != RB_OK) {
        st[RB_SL_STATUS] = status;
        ((status_fn)(intptr_t)st[RB_SL_FAIL])(r, p);
    }
}

/* REBOUND's free: the arrays REBOUND or the host allocated (with this process's C library),
 * then the state */
static void release(void *p)
{
    int64_t *st = ST(p);
    const int slots[] = {RB_SL_Y, RB_SL_GAMMA, RB_SL_COUNTERS, RB_SL_CTX};
    for (int i = 0; i < 4; ++i)
        if (st[slots[i]] != 0)
            free((void *)(intptr_t)st[slots[i]]);
    free(p);
}

/* particles.context_current: is the context block still the simulation's? */
static int context_current(const struct reb_simulation *r, const int64_t *st, const int64_t *ctx)
{
    if ((int64_t)(intptr_t)r->particles != ctx[RB_D_PTR] || (int64_t)r->N != ctx[RB_D_N])
        return 0;
    if (st[RB_SL_S] != ctx[RB_D_S] || st[RB_SL_K] != ctx[RB_D_K]
        || st[RB_SL_NODES] != ctx[RB_D_NODES] || st[RB_SL_METHOD] != ctx[RB_D_METHOD]
        || st[RB_SL_KEPLER] != ctx[RB_D_KEPLER])
        return 0;
    const int64_t *simi = (const int64_t *)r;
    for (int i = 0; i < RB_N_CFG; ++i)
        if (simi[ctx[RB_C_WORDS + i]] != ctx[RB_C_VALUES + i])
            return 0;
    return (int64_t)(intptr_t)r->particles_var == ctx[RB_D_PVAR];
}

/* particles.settings_ok */
static int settings_ok(const int64_t *st, const double *sd)
{
    if (st[RB_SL_MAX_ITER] < 1 || !(0.0 <= sd[RB_SL_TOL] && sd[RB_SL_TOL] < 1.0)
        || !(-1.0 < sd[RB_SL_ETOL] && sd[RB_SL_ETOL] < INFINITY))
        return 0;
    if (!(0.0 <= sd[RB_SL_MAX_DT] && sd[RB_SL_MAX_DT] < INFINITY))
        return 0;
    return st[RB_SL_ADAPTIVE] == 0 || sd[RB_SL_EPSILON] == 0.0
           || (0.0 < sd[RB_SL_EPSILON] && sd[RB_SL_EPSILON] < 1.0 && 0.0 <= sd[RB_SL_MIN_DT]
               && sd[RB_SL_MIN_DT] < INFINITY);
}

/* particles.particles_match: the particles as the last commit wrote them (x, v, m)? */
static int particles_match(const struct reb_particle *ps, size_t N, const double *written)
{
    for (size_t i = 0; i < N; ++i) {
        const struct reb_particle *q = ps + i;
        const double *w = written + 7 * i;
        if (q->x != w[0] || q->y != w[1] || q->z != w[2] || q->vx != w[3] || q->vy != w[4]
            || q->vz != w[5] || q->m != w[6])
            return 0;
    }
    return 1;
}

/* particles.reread_particles: the state from particles moved between two steps (same masses,
 * finite values): q = x, p = v / minv, compensations zeroed; 0 (nothing changed) otherwise */
static int reread_particles(const struct reb_particle *ps, size_t N, double *written, double *y,
                            double *cy, const double *minv, int m)
{
    for (size_t i = 0; i < N; ++i) {
        const struct reb_particle *q = ps + i;
        if (q->m != written[7 * i + 6])
            return 0;
        if (!(isfinite(q->x) && isfinite(q->vx) && isfinite(q->y) && isfinite(q->vy)
              && isfinite(q->z) && isfinite(q->vz)))
            return 0;
    }
    for (size_t i = 0; i < N; ++i) {
        const struct reb_particle *q = ps + i;
        const double x[3] = {q->x, q->y, q->z}, v[3] = {q->vx, q->vy, q->vz};
        for (int c = 0; c < 3; ++c) {
            const size_t j = 3 * i + c;
            y[j] = x[c];
            cy[j] = 0.0;
            y[m + j] = v[c] / minv[j];
            cy[m + j] = 0.0;
            written[7 * i + c] = x[c];
            written[7 * i + 3 + c] = v[c];
        }
    }
    return 1;
}

/* particles.clock_comp */
static double clock_comp(const double *sd, double t_start)
{
    return t_start == sd[RB_SL_T_WRITTEN] ? sd[RB_SL_T_COMP] : 0.0;
}

/* particles.landing_step: exact_finish_time's last step ends at tmax on the compensated clock */
static double landing_step(const struct reb_simulation *r, const double *sd, double t_start,
                           double h)
{
    if (r->status != REB_STATUS_LAST_STEP)
        return h;
    return h + clock_comp(sd, t_start);
}

/* the plain N-body step (the module's docstring) */
static int step(struct reb_simulation *r, void *p)
{
    int64_t *st = ST(p);
    double *sd = SD(p);
    const int64_t *ctx = (const int64_t *)(intptr_t)st[RB_SL_CTX];
    if (!ctx || !context_current(r, st, ctx))
        return RB_RESYNC;
    const double *host = CTXP(ctx, RB_A_HOST);
    if (r->G != host[0] || (double)(int64_t)r->N_active != host[1])
        return RB_RESYNC;
    const int s = (int)ctx[RB_D_S], m = (int)ctx[RB_D_M], k = (int)ctx[RB_D_K];
    const size_t N = r->N;
    const double *minv = CTXP(ctx, RB_A_MINV), *kin_w = CTXP(ctx, RB_A_KINW);
    double *written = CTXP(ctx, RB_A_WRITTEN);
    double *y = (double *)(intptr_t)st[RB_SL_Y], *cy = y + 2 * m;
    double *gamma = (double *)(intptr_t)st[RB_SL_GAMMA];
    double *eref = sd + RB_SL_EREF;
    double *counters = (double *)(intptr_t)st[RB_SL_COUNTERS];
    double *res = sd + RB_SL_RES;
    double *yt = CTXP(ctx, RB_A_YT), *cyt = CTXP(ctx, RB_A_CYT);
    double *gammat = CTXP(ctx, RB_A_GAMMAT), *ereft = CTXP(ctx, RB_A_EREFT);
    double *clock = CTXP(ctx, RB_A_CLOCK);
    const double *params = CTXP(ctx, RB_A_PARAMS);
    hbvm_kernel kern = {.force = core->nbody_force, .potential = core->nbody_potential,
                        .params = params, .ctx = NULL};
    hbvm_system sys = {.m = m, .minv = minv, .kin_w = kin_w};
    if (!settings_ok(st, sd))
        return RB_BAD_SETTINGS;
    if (!particles_match(r->particles, N, written)) {
        /* moved between steps (an operator after every step): the previous coefficients stay
         * the initial guess, the reference energy starts afresh */
        const double e_old = eref[0], anchor = eref[HBVM_EREF_RUN];
        if (!reread_particles(r->particles, N, written, y, cy, minv, m))
            return RB_RESYNC;
        /* glue.moved_anchor: the run's start moves by the energy the move changed */
        double T, V;
        if (isfinite(e_old) && isfinite(anchor)
            && core->energy_parts(&kern, &sys, y, &T, &V) == 0) {
            eref[HBVM_EREF_RUN] = anchor + ((T + V) - e_old);
            for (int i = 0; i < HBVM_EREF_RUN; ++i)
                eref[i] = NAN;
        } else {
            for (int i = 0; i < RB_N_EREF; ++i)
                eref[i] = NAN;
        }
        st[RB_SL_RESYNCS] += 1;
    }
    double h = r->dt;
    if (!(fabs(h) < INFINITY && h != 0.0)) {
        sd[RB_SL_H_FAIL] = h;
        return RB_BAD_DT;
    }
    const double t_start = r->t;
    /* epsilon = 0: fixed steps of sim.dt, as IAS15 takes them (REBOUND's idiom) */
    const int adaptive = st[RB_SL_ADAPTIVE] != 0 && sd[RB_SL_EPSILON] != 0.0;
    const double epsilon = adaptive ? sd[RB_SL_EPSILON] : 0.0;
    const double max_dt = adaptive ? sd[RB_SL_MAX_DT] : 0.0;
    if (max_dt > 0.0 && fabs(h) > max_dt)
        h = h > 0.0 ? max_dt : -max_dt;
    else
        h = landing_step(r, sd, t_start, h);
    const double etol = st[RB_SL_ECHECK] > 0 ? sd[RB_SL_ETOL] : 0.0;
    /* the step's own error estimate, on with the energy check (core.ERROR_BOUND) */
    const double ebound = sd[RB_SL_ETOL] != 0.0 ? HBVM_ERROR_BOUND : 0.0;
    res[2] = 0.0;
    hbvm_state state = {.y = y, .cy = cy, .gamma = gamma, .eref = eref, .clock = clock};
    hbvm_state trial = {.y = yt, .cy = cyt, .gamma = gammat, .eref = ereft, .clock = clock};
    /* the method's packed arrays (integrators.engine.method_arrays, HBVM's planes) */
    const double *tn = CTXP(ctx, RB_A_TN), *ts = CTXP(ctx, RB_A_TS);
    const double *Wp = CTXP(ctx, RB_A_WP), *Cp = CTXP(ctx, RB_A_CP);
    hbvm_tableau tab = {.k = k, .s = s, .tau = tn, .tau_lo = tn + k, .X0 = ts, .X0_lo = ts + s,
                        .W = Wp, .W_lo = Wp + s * k, .C2 = Cp, .C2_lo = Cp + k * s,
                        .I = Cp + 2 * k * s, .I_lo = Cp + 3 * k * s};
    hbvm_extrapolation ext = {.E1 = CTXP(ctx, RB_A_E1), .t = CTXP(ctx, RB_A_ET),
                              .w = CTXP(ctx, RB_A_EW), .buf = CTXP(ctx, RB_A_EBUF),
                              .zero = CTXP(ctx, RB_A_EZERO)};
    hbvm_options op = {.max_iter = (int)st[RB_SL_MAX_ITER], .tol = sd[RB_SL_TOL], .etol = etol,
                       .ebound = ebound, .group = 3};
    int status = core->attempt(&kern, &sys, &state, &trial, h, sd[RB_SL_H_PREV], t_start, &ext,
                               &tab, &op, counters, epsilon, sd[RB_SL_MIN_DT], res,
                               CTXP(ctx, RB_A_WORK), (size_t)ctx[RB_D_NF]);
    st[RB_SL_REJECTED] += (int64_t)res[2];
    if (status < 0)
        status = RB_OUT_OF_MEMORY;
    if (status != RB_OK) {
        /* particles.record_failure */
        sd[RB_SL_H_FAIL] = res[0];
        sd[RB_SL_T_FAIL] = t_start;
        sd[RB_SL_CAUSE_ERR] = res[3];
        sd[RB_SL_CAUSE_STATUS] = res[4];
        return status;
    }
    const double h_done = res[0], hp = sd[RB_SL_H_PREV];
    /* exact_finish_time's sliver of a step (1e-16): the next step extrapolates from the last
     * regular one, whose gamma is kept (core.TINY_RATIO) */
    const int sliver = !isnan(hp) && fabs(h_done) < HBVM_TINY_RATIO * fabs(hp);
    memcpy(y, yt, 2 * (size_t)m * sizeof(double));
    memcpy(cy, cyt, 2 * (size_t)m * sizeof(double));
    if (!sliver) {
        memcpy(gamma, gammat, (size_t)s * m * sizeof(double));
        sd[RB_SL_H_PREV] = h_done;
    }
    eref[0] = ereft[0];
    if (!sliver)
        for (int i = 1; i < HBVM_EREF_RUN; ++i)
            eref[i] = ereft[i];
    for (int i = HBVM_EREF_RUN; i < RB_N_EREF; ++i)
        eref[i] = ereft[i];
    sd[RB_SL_RUN_ERR] = counters[C_RUN_ERR];
    for (size_t i = 0; i < N; ++i) {
        struct reb_particle *q = r->particles + i;
        double *w = written + 7 * i;
        const size_t j = 3 * i;
        q->x = y[j];
        q->y = y[j + 1];
        q->z = y[j + 2];
        q->vx = y[m + j] * minv[j];
        q->vy = y[m + j + 1] * minv[j + 1];
        q->vz = y[m + j + 2] * minv[j + 2];
        w[0] = q->x, w[1] = q->y, w[2] = q->z, w[3] = q->vx, w[4] = q->vy, w[5] = q->vz;
    }
    /* REBOUND's time, compensated (core.tick), so that sim.t stays n dt to an ulp */
    const double ct0 = clock_comp(sd, t_start);
    const double yk = h_done - ct0, t_end = t_start + yk, ct = (t_end - t_start) - yk;
    r->t = t_end;
    sd[RB_SL_T_COMP] = ct;
    sd[RB_SL_T_WRITTEN] = t_end;
    r->dt_last_done = h_done;
    if (adaptive) {
        double h_next = res[1];
        if (max_dt > 0.0 && fabs(h_next) > max_dt)
            h_next = h_next > 0.0 ? max_dt : -max_dt;
        r->dt = h_next;
    }
    st[RB_SL_NSTEPS] += 1;
    return RB_OK;
}

/* the rebound.h layout this module was built with, for the import's check against the running
 * REBOUND (hbvm_md.rebound.cglue) */
static PyObject *layout(void)
{
    return Py_BuildValue(
        "{s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n,s:n}",
        "sizeof_simulation", (Py_ssize_t)sizeof(struct reb_simulation),
        "sizeof_particle", (Py_ssize_t)sizeof(struct reb_particle),
        "t", (Py_ssize_t)offsetof(struct reb_simulation, t),
        "G", (Py_ssize_t)offsetof(struct reb_simulation, G),
        "dt", (Py_ssize_t)offsetof(struct reb_simulation, dt),
        "dt_last_done", (Py_ssize_t)offsetof(struct reb_simulation, dt_last_done),
        "N", (Py_ssize_t)offsetof(struct reb_simulation, N),
        "_particles", (Py_ssize_t)offsetof(struct reb_simulation, particles),
        "_particles_var", (Py_ssize_t)offsetof(struct reb_simulation, particles_var),
        "N_active", (Py_ssize_t)offsetof(struct reb_simulation, N_active),
        "_status", (Py_ssize_t)offsetof(struct reb_simulation, status),
        "integrator", (Py_ssize_t)offsetof(struct reb_simulation, integrator),
        "x", (Py_ssize_t)offsetof(struct reb_particle, x),
        "y", (Py_ssize_t)offsetof(struct reb_particle, y),
        "z", (Py_ssize_t)offsetof(struct reb_particle, z),
        "vx", (Py_ssize_t)offsetof(struct reb_particle, vx),
        "vy", (Py_ssize_t)offsetof(struct reb_particle, vy),
        "vz", (Py_ssize_t)offsetof(struct reb_particle, vz),
        "m", (Py_ssize_t)offsetof(struct reb_particle, m),
        "last_step", (Py_ssize_t)REB_STATUS_LAST_STEP);
}

static struct PyModuleDef moddef = {PyModuleDef_HEAD_INIT, "_glue",
                                    "HBVM's compiled step inside REBOUND "
                                    "(hbvm_md/rebound/csrc).", -1, NULL};

PyMODINIT_FUNC PyInit__glue(void)
{
    core = PyCapsule_Import("integrators._core.API", 0);
    if (!core)
        return NULL;
    if (core->version != HBVM_API_VERSION || core->n_counters != N_COUNTERS
        || core->n_eref != RB_N_EREF) {
        PyErr_SetString(PyExc_ImportError, "hbvm_md.rebound._glue was built for another "
                                           "integrators._core: run `pip install -e .` again");
        return NULL;
    }
    PyObject *mod = PyModule_Create(&moddef);
    if (!mod)
        return NULL;
    PyModule_AddObject(mod, "DISPATCH", PyLong_FromVoidPtr((void *)(intptr_t)&dispatch));
    PyModule_AddObject(mod, "RELEASE", PyLong_FromVoidPtr((void *)(intptr_t)&release));
    PyModule_AddObject(mod, "STEP", PyLong_FromVoidPtr((void *)(intptr_t)&step));
    PyModule_AddObject(mod, "LAYOUT", layout());
#ifdef HBVM_SOURCE_DIGEST
    PyModule_AddStringConstant(mod, "SOURCE_DIGEST", HBVM_SOURCE_DIGEST);
#else
    PyModule_AddStringConstant(mod, "SOURCE_DIGEST", "");
#endif
#ifdef HBVM_REBOUND_VERSION
    PyModule_AddStringConstant(mod, "REBOUND_VERSION", HBVM_REBOUND_VERSION);
#else
    PyModule_AddStringConstant(mod, "REBOUND_VERSION", "");
#endif
    return mod;
}
