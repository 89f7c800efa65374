/* hbvm_md.rebound._glue: HBVM's step inside REBOUND, compiled when the package is installed,
 * against the installed REBOUND's rebound.h (as REBOUNDx builds against it).
 *
 * Three C functions are registered with REBOUND or called through HBVM's state:
 *   dispatch(r, p)  REBOUND's step: the step at the state's SL_CORE, the host's prepare (a
 *                   Python callback) first when there is none or the step answers RESYNC, the
 *                   host's fail (a Python callback) when it failed;
 *   release(p)      REBOUND's free: the arrays of the state and the state;
 *   step(r, p)      the plain N-body step (hbvm_md.rebound.glue.step_arrays' contract for its
 *                   default case: HBVM, the fixed-point iteration, Newtonian gravity, test
 *                   particles solved after the sources, no variational particles, no REBOUND
 *                   forces or attached ODEs, no Kepler composition), calling the compiled
 *                   core's one retry loop (integrators._core's API capsule: one binary of the
 *                   step) with the N-body kernel.  Every other case keeps the numba step of
 *                   hbvm_md.rebound.glue, which dispatch calls the same way.
 *
 * REBOUND's simulation is read by name (struct reb_simulation, struct reb_particle), and so
 * are HBVM's state and its context block (struct hbvm_rb_state, struct hbvm_rb_context of
 * hbvm_state.h, which hbvm_md/rebound/layout.py reads for the Python host and the numba step;
 * setup.py writes the statuses into hbvm_layout.h and a static assertion of every member's
 * offset as layout.py read it into hbvm_layout_check.h).  The
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
#include "hbvm_state.h"
#include "hbvm_layout_check.h"

/* (setup.py defines both: the digest of the sources built, the REBOUND whose header they saw) */
#ifndef HBVM_SOURCE_DIGEST
#define HBVM_SOURCE_DIGEST ""
#endif
#ifndef HBVM_REBOUND_VERSION
#define HBVM_REBOUND_VERSION ""
#endif

static const hbvm_api *core;

typedef struct hbvm_rb_state state_t;
typedef struct hbvm_rb_context context_t;

/* a context block's array at the address of member a */
#define ARR(ctx, a) ((double *)(intptr_t)(ctx)->a)

_Static_assert(sizeof(state_t) == 8 * RB_N_SLOTS, "hbvm_state.h: every member 8 bytes");
_Static_assert(sizeof(context_t) == 8 * RB_N_HEADER, "hbvm_state.h: every member 8 bytes");
_Static_assert(offsetof(state_t, tmax_run) == offsetof(state_t, eref) + 8 * (HBVM_N_EREF - 1),
               "hbvm_state.h: eref .. tmax_run are the step's eref, consecutive");

/* REBOUND's step */
static void dispatch(struct reb_simulation *r, void *p)
{
    state_t *st = p;
    int status = RB_RESYNC;
    if (st->core)
        status = st->core(r, p);
    if (status == RB_RESYNC) {
        status = st->prepare(r, p);
        if (status == RB_OK)
            status = st->core(r, p);
    }
    if (status != RB_OK) {
        st->status = status;
        st->fail(r, p);
    }
}

/* REBOUND's free: the arrays REBOUND or the host allocated (with this process's C library),
 * then the state */
static void release(void *p)
{
    state_t *st = p;
    if (st->forget)
        st->forget(NULL, p);
    free(st->y);
    free(st->gamma);
    free(st->counters);
    free((void *)(intptr_t)st->ctx);
    free(p);
}

/* particles.context_current: is the context block still the simulation's? */
static int context_current(const struct reb_simulation *r, const state_t *st,
                           const context_t *ctx)
{
    if ((int64_t)(intptr_t)r->particles != ctx->d_ptr || (int64_t)r->N != ctx->d_n)
        return 0;
    if (st->s != ctx->d_s || st->k != ctx->d_k || st->nodes != ctx->d_nodes
        || st->method != ctx->d_method || st->kepler != ctx->d_kepler)
        return 0;
    const int64_t *simi = (const int64_t *)r;
    for (int i = 0; i < RB_N_CFG; ++i)
        if (simi[ctx->c_words[i]] != ctx->c_values[i])
            return 0;
    return (int64_t)(intptr_t)r->particles_var == ctx->d_pvar;
}

/* particles.settings_ok */
static int settings_ok(const state_t *st)
{
    if (st->max_iter < 1 || !(0.0 <= st->tol && st->tol < 1.0)
        || !(-1.0 < st->etol && st->etol < INFINITY))
        return 0;
    if (!(0.0 <= st->max_dt && st->max_dt < INFINITY))
        return 0;
    return st->adaptive == 0 || st->epsilon == 0.0
           || (0.0 < st->epsilon && st->epsilon < 1.0 && 0.0 <= st->min_dt
               && st->min_dt < INFINITY);
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
static double clock_comp(const state_t *st, double t_start)
{
    return t_start == st->t_written ? st->t_comp : 0.0;
}

/* particles.landing_step: exact_finish_time's last step ends at tmax on the compensated clock */
static double landing_step(const struct reb_simulation *r, const state_t *st, double t_start,
                           double h)
{
    if (r->status != REB_STATUS_LAST_STEP)
        return h;
    return h + clock_comp(st, t_start);
}

/* glue.TP_FLOOR, glue.TP_FACTOR: a fixed step refuses a test particle whose own estimate
 * exceeds max(TP_FLOOR, TP_FACTOR x the sources') */
static const double TP_FLOOR = 1e-2, TP_FACTOR = 10.0;

/* the plain N-body step (the module's docstring) */
static int step(struct reb_simulation *r, void *p)
{
    state_t *st = p;
    const context_t *ctx = (const context_t *)(intptr_t)st->ctx;
    if (!ctx || !context_current(r, st, ctx))
        return RB_RESYNC;
    const double *host = ARR(ctx, a_host);
    if (r->G != host[0] || (double)(int64_t)r->N_active != host[1])
        return RB_RESYNC;
    const int s = (int)ctx->d_s, m = (int)ctx->d_m, k = (int)ctx->d_k;
    const size_t N = r->N;
    const double *minv = ARR(ctx, a_minv), *kin_w = ARR(ctx, a_kinw);
    double *written = ARR(ctx, a_written);
    double *y = st->y, *cy = y + 2 * m, *gamma = st->gamma, *counters = st->counters;
    double *eref = &st->eref;             /* (eref .. tmax_run: consecutive, HBVM_N_EREF) */
    double *res = st->res;
    double *yt = ARR(ctx, a_yt), *cyt = ARR(ctx, a_cyt);
    double *gammat = ARR(ctx, a_gammat), *ereft = ARR(ctx, a_ereft);
    double *clock = ARR(ctx, a_clock);
    const double *params = ARR(ctx, a_params);
    hbvm_kernel kern = {.force = core->nbody_force, .potential = core->nbody_potential,
                        .params = params, .ctx = NULL};
    /* test particles: solved after the sources in their field (the followers block of the
     * N-body kernel's parameters, systems.nbody.followers_block) */
    const double *follow = ctx->d_follow ? params + m + 3 : NULL;
    hbvm_system sys = {.m = m, .minv = minv, .kin_w = kin_w, .follow = follow,
                       .field = follow ? core->nbody_field : NULL};
    if (!settings_ok(st))
        return RB_BAD_SETTINGS;
    if (!particles_match(r->particles, N, written)) {
        /* moved between steps (an operator after every step): the previous coefficients stay
         * the initial guess; the energy starts afresh, and the run's start moves by the energy
         * the move changed (glue.moved_anchor) */
        const double e_old = eref[0], anchor = eref[HBVM_EREF_RUN];
        if (!reread_particles(r->particles, N, written, y, cy, minv, m))
            return RB_RESYNC;
        double T, V;
        if (isfinite(e_old) && isfinite(anchor)
            && core->energy_parts(&kern, &sys, y, &T, &V) == 0) {
            eref[HBVM_EREF_RUN] = anchor + ((T + V) - e_old);
            for (int i = 0; i < HBVM_EREF_RUN; ++i)
                eref[i] = NAN;
        } else {
            for (int i = 0; i < HBVM_N_EREF; ++i)
                eref[i] = NAN;
        }
        st->resyncs += 1;
    }
    double h = r->dt;
    if (!(fabs(h) < INFINITY && h != 0.0)) {
        st->h_fail = h;
        return RB_BAD_DT;
    }
    const double t_start = r->t;
    /* epsilon = 0: fixed steps of sim.dt, as IAS15 takes them (REBOUND's idiom) */
    const int adaptive = st->adaptive != 0 && st->epsilon != 0.0;
    const double epsilon = adaptive ? st->epsilon : 0.0;
    const double max_dt = adaptive ? st->max_dt : 0.0;
    if (max_dt > 0.0 && fabs(h) > max_dt)
        h = h > 0.0 ? max_dt : -max_dt;
    else
        h = landing_step(r, st, t_start, h);
    const double etol = st->echeck > 0 ? st->etol : 0.0;
    /* the step's own error estimate, on with the energy check (core.ERROR_BOUND) */
    const double ebound = st->etol != 0.0 ? HBVM_ERROR_BOUND : 0.0;
    res[2] = 0.0;
    hbvm_state state = {.y = y, .cy = cy, .gamma = gamma, .eref = eref, .clock = clock};
    hbvm_state trial = {.y = yt, .cy = cyt, .gamma = gammat, .eref = ereft, .clock = clock};
    /* the method's packed arrays (integrators.engine.method_arrays, HBVM's planes) */
    const double *tn = ARR(ctx, a_tn), *ts = ARR(ctx, a_ts);
    const double *Wp = ARR(ctx, a_wp), *Cp = ARR(ctx, a_cp);
    hbvm_tableau tab = {.k = k, .s = s, .tau = tn, .tau_lo = tn + k, .X0 = ts, .X0_lo = ts + s,
                        .W = Wp, .W_lo = Wp + s * k, .C2 = Cp, .C2_lo = Cp + k * s,
                        .I = Cp + 2 * k * s, .I_lo = Cp + 3 * k * s};
    hbvm_extrapolation ext = {.E1 = ARR(ctx, a_e1), .t = ARR(ctx, a_et), .w = ARR(ctx, a_ew),
                              .buf = ARR(ctx, a_ebuf), .zero = ARR(ctx, a_ezero)};
    hbvm_options op = {.max_iter = (int)st->max_iter, .tol = st->tol, .etol = etol,
                       .ebound = ebound, .group = 3};
    /* a fixed step's test-particle check may refuse a converged step: its work then comes out
     * of the counters and the clock, as the core takes a failed step's out */
    const double c_iter = counters[C_ITER], c_nfev = counters[C_NFEV];
    const double c_newton = counters[C_NEWTON], clock0 = clock[0], clock1 = clock[1];
    int status = core->attempt(&kern, &sys, &state, &trial, h, st->h_prev, t_start, &ext, &tab,
                               &op, counters, epsilon, st->min_dt, res, ARR(ctx, a_work),
                               (size_t)ctx->d_nf);
    st->rejected += (int64_t)res[2];
    if (status < 0)
        status = RB_OUT_OF_MEMORY;
    if (status == RB_OK && !adaptive && st->etol != 0.0) {
        /* the test particles against the bodies they move among (glue.step_arrays) */
        double err;
        const int worst = core->test_particle_error(gammat, s, m, minv, kin_w, TP_FLOOR,
                                                    TP_FACTOR, &err);
        if (worst >= 0) {
            counters[C_ITER] = c_iter;
            counters[C_NFEV] = c_nfev;
            counters[C_NEWTON] = c_newton;
            counters[C_STEPS] -= 1;
            clock[0] = clock0;
            clock[1] = clock1;
            res[3] = err;
            res[4] = worst;
            status = RB_TEST_PARTICLE;
        }
    }
    if (status != RB_OK) {
        /* particles.record_failure */
        st->h_fail = res[0];
        st->t_fail = t_start;
        st->cause_err = res[3];
        st->cause_status = res[4];
        return status;
    }
    const double h_done = res[0], hp = st->h_prev;
    /* exact_finish_time's sliver of a step (1e-16): the next step extrapolates from the last
     * regular one, whose gamma is kept (core.TINY_RATIO) */
    const int sliver = !isnan(hp) && fabs(h_done) < HBVM_TINY_RATIO * fabs(hp);
    memcpy(y, yt, 2 * (size_t)m * sizeof(double));
    memcpy(cy, cyt, 2 * (size_t)m * sizeof(double));
    if (!sliver) {
        memcpy(gamma, gammat, (size_t)s * m * sizeof(double));
        st->h_prev = h_done;
    }
    eref[0] = ereft[0];
    if (!sliver)
        for (int i = 1; i < HBVM_EREF_RUN; ++i)
            eref[i] = ereft[i];
    for (int i = HBVM_EREF_RUN; i < HBVM_N_EREF; ++i)
        eref[i] = ereft[i];
    st->run_err = counters[C_RUN_ERR];
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
    const double ct0 = clock_comp(st, t_start);
    const double yk = h_done - ct0, t_end = t_start + yk, ct = (t_end - t_start) - yk;
    r->t = t_end;
    st->t_comp = ct;
    st->t_written = t_end;
    r->dt_last_done = h_done;
    if (adaptive) {
        double h_next = res[1];
        if (max_dt > 0.0 && fabs(h_next) > max_dt)
            h_next = h_next > 0.0 ? max_dt : -max_dt;
        r->dt = h_next;
    }
    st->nsteps += 1;
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
    PyModule_AddStringConstant(mod, "SOURCE_DIGEST", HBVM_SOURCE_DIGEST);
    PyModule_AddStringConstant(mod, "REBOUND_VERSION", HBVM_REBOUND_VERSION);
    return mod;
}
