/* integrators._core: the compiled core's Python face.
 *
 * run(kernel, system, state, h, E, method, newton, opts, work, samples[, pyk, scratch,
 * follow]) takes the records of integrators.records (named tuples of numpy arrays, read by
 * position through the buffer protocol: no numpy headers at build time) and returns the step's
 * status, as integrators.loop.run does (follow: the N-body kernel's test particles solved as
 * followers); attempt(...) is integrators.loop.attempt's contract (hbvm_attempt). The arrays
 * are checked for their dtype, shape and contiguity: a record that does not fit is a TypeError
 * or ValueError naming the field, never a wrong read. The GIL is released while the steps
 * run. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "hbvm_core.h"

enum { KERNEL_PYTHON = 0, KERNEL_NBODY = 1, KERNEL_BUILTIN = 2 };

/* A kernel written in Python (a user's system, an ASE calculator): the step calls back into
 * the interpreter at each evaluation, through buffers the Python side owns: the stages go out
 * as rows Xr (n, m) (the layout of integrators.loop's kernels) and the forces come back from
 * Fr; the potential reads q.  The callbacks take no arguments (integrators.ccore binds them). */
typedef struct {
    PyObject *f_all, *f_one, *pot;
    double *Xr, *Fr, *X1, *F1, *q;
    int kmax, m;
} pyk_ctx;

static int pyk_force(void *c, const double *X, int m, int kp, int n, const double *params,
                     double *F)
{
    pyk_ctx *p = c;
    (void)params;
    if (n > p->kmax)
        return -1;
    double *Xr = n == 1 ? p->X1 : p->Xr, *Fr = n == 1 ? p->F1 : p->Fr;
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < m; ++j)
            Xr[i * m + j] = X[j * kp + i];
    PyObject *r = PyObject_CallNoArgs(n == 1 ? p->f_one : p->f_all);
    if (!r)
        return -1;
    Py_DECREF(r);
    for (int j = 0; j < m; ++j)
        for (int i = 0; i < kp; ++i)
            F[j * kp + i] = Fr[(i < n ? i : n - 1) * m + j];
    return 0;
}

static int pyk_potential(void *c, const double *q, const double *params, double *V)
{
    pyk_ctx *p = c;
    (void)params;
    memcpy(p->q, q, (size_t)p->m * sizeof(double));
    PyObject *r = PyObject_CallNoArgs(p->pot);
    if (!r)
        return -1;
    *V = PyFloat_AsDouble(r);
    Py_DECREF(r);
    return (*V == -1.0 && PyErr_Occurred()) ? -1 : 0;
}

#define MAX_BUFS 32

typedef struct {
    Py_buffer b[MAX_BUFS];
    int n;
} bufset;

static void release(bufset *bs)
{
    for (int i = 0; i < bs->n; ++i)
        PyBuffer_Release(&bs->b[i]);
    bs->n = 0;
}

/* a float64 C-contiguous array of ndim dimensions from obj; shape checked by the caller */
static double *get(bufset *bs, PyObject *obj, const char *name, int ndim, int writable,
                   Py_ssize_t *shape)
{
    if (bs->n >= MAX_BUFS) {
        PyErr_SetString(PyExc_RuntimeError, "hbvm-md core: too many arrays");
        return NULL;
    }
    Py_buffer *b = &bs->b[bs->n];
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, b, flags) != 0) {
        PyErr_Format(PyExc_TypeError,
                     "hbvm-md core: `%s` must be a C-contiguous%s float64 array", name,
                     writable ? " writable" : "");
        return NULL;
    }
    bs->n += 1;
    if (b->format == NULL || strcmp(b->format, "d") != 0 || b->itemsize != 8) {
        PyErr_Format(PyExc_TypeError, "hbvm-md core: `%s` must be float64 (got format %s)",
                     name, b->format ? b->format : "?");
        return NULL;
    }
    if (b->ndim != ndim) {
        PyErr_Format(PyExc_ValueError, "hbvm-md core: `%s` must have %d dimensions (got %d)",
                     name, ndim, b->ndim);
        return NULL;
    }
    for (int i = 0; i < ndim; ++i)
        shape[i] = b->shape[i];
    return (double *)b->buf;
}

static PyObject *item(PyObject *tup, Py_ssize_t i, const char *name)
{
    if (!PyTuple_Check(tup) || PyTuple_GET_SIZE(tup) <= i) {
        PyErr_Format(PyExc_TypeError, "hbvm-md core: `%s` must be a record (named tuple)", name);
        return NULL;
    }
    return PyTuple_GET_ITEM(tup, i);
}

#define SHAPE_ERR(name, want)                                                                \
    do {                                                                                     \
        PyErr_Format(PyExc_ValueError, "hbvm-md core: `%s` has the wrong shape (want %s)",   \
                     name, want);                                                            \
        goto fail;                                                                           \
    } while (0)

static int kernel_of(long id, hbvm_kernel *kern)
{
    kern->ctx = NULL;
    if (id == KERNEL_NBODY) {
        kern->force = hbvm_nbody_force_k;
        kern->potential = hbvm_nbody_potential_k;
        return 0;
    }
    if (id == KERNEL_PYTHON) {
        kern->force = pyk_force;
        kern->potential = pyk_potential;
        return 0;
    }
    for (long i = 0; id >= KERNEL_BUILTIN && hbvm_builtins[i].name; ++i)
        if (i == id - KERNEL_BUILTIN) {
            kern->force = hbvm_builtins[i].force;
            kern->potential = hbvm_builtins[i].potential;
            return 0;
        }
    PyErr_Format(PyExc_ValueError, "hbvm-md core: unknown kernel %ld", id);
    return -1;
}

/* the Python kernel's callbacks and buffers: (f_all, f_one, pot, Xr (k, m), Fr (k, m),
 * X1 (1, m), F1 (1, m), q (m,)) */
static int python_kernel(bufset *bs, PyObject *pyk, int m, pyk_ctx *ctx)
{
    if (!PyTuple_Check(pyk) || PyTuple_GET_SIZE(pyk) != 8) {
        PyErr_SetString(PyExc_TypeError, "hbvm-md core: a Python kernel needs "
                                         "(f_all, f_one, pot, Xr, Fr, X1, F1, q)");
        return -1;
    }
    ctx->f_all = PyTuple_GET_ITEM(pyk, 0);
    ctx->f_one = PyTuple_GET_ITEM(pyk, 1);
    ctx->pot = PyTuple_GET_ITEM(pyk, 2);
    const char *names[] = {"Xr", "Fr", "X1", "F1", "q"};
    double **ptr[] = {&ctx->Xr, &ctx->Fr, &ctx->X1, &ctx->F1, &ctx->q};
    Py_ssize_t sh[2];
    for (int i = 0; i < 5; ++i) {
        if (!(*ptr[i] = get(bs, PyTuple_GET_ITEM(pyk, 3 + i), names[i], i < 4 ? 2 : 1, 1, sh)))
            return -1;
        if ((i < 4 && sh[1] != m) || (i == 4 && sh[0] != m) || (i >= 2 && i < 4 && sh[0] < 1)) {
            PyErr_Format(PyExc_ValueError, "hbvm-md core: the Python kernel's buffer %s has "
                                           "the wrong shape", names[i]);
            return -1;
        }
        if (i == 0)
            ctx->kmax = (int)sh[0];
    }
    ctx->m = m;
    return 0;
}

static int check_params(long id, int m, Py_ssize_t np, const double *params)
{
    if (id >= KERNEL_BUILTIN) {
        const hbvm_builtin *b = &hbvm_builtins[id - KERNEL_BUILTIN];
        if ((b->m != 0 && b->m != m) || np < b->nparams) {
            PyErr_Format(PyExc_ValueError, "hbvm-md core: the %s kernel takes %d coordinates "
                         "and %d parameters (got %d and %zd)", b->name, b->m, b->nparams, m, np);
            return -1;
        }
        return 0;
    }
    if (id == KERNEL_NBODY && hbvm_nbody_check(m, params, (long)np) != 0) {
        PyErr_Format(PyExc_ValueError,
                     "hbvm-md core: the N-body parameters do not describe %d coordinates "
                     "(systems.nbody.kernel_params: [G, N, masses, gravitating masses, links])",
                     m);
        return -1;
    }
    return 0;
}

/* a step's records, read and checked (py_run, py_attempt) */
typedef struct {
    hbvm_kernel kern;
    pyk_ctx pctx;
    int mctx;
    hbvm_system sys;
    hbvm_tableau tab;
    hbvm_state st;
    hbvm_options op;
    double *counters, *scratch;
    Py_ssize_t nscratch;
} step_args;

/* a state record (y (2m), cy (2m), gamma (s, m), eref (>= 7), clock (>= 2)) named `what` */
static int get_state(bufset *bs, PyObject *state, const char *what, int m, int s,
                     hbvm_state *st)
{
    const char *fields[] = {"y", "cy", "gamma", "eref", "clock"};
    const int sdims[] = {1, 1, 2, 1, 1};
    double *sp[5];
    Py_ssize_t sh[2];
    char name[64];
    for (int i = 0; i < 5; ++i) {
        snprintf(name, sizeof name, "%s.%s", what, fields[i]);
        PyObject *o = item(state, i, name);
        if (!o)
            return -1;
        if (!(sp[i] = get(bs, o, name, sdims[i], 1, sh)))
            return -1;
        if ((i < 2 && sh[0] != 2 * m) || (i == 2 && (sh[0] != s || sh[1] != m))
            || (i == 3 && sh[0] < HBVM_N_EREF) || (i == 4 && sh[0] < 2)) {
            PyErr_Format(PyExc_ValueError, "hbvm-md core: `%s` has the wrong shape (want %s)",
                         name, i < 2 ? "(2m,)" : i == 2 ? "(s, m)" : i == 3 ? "(7,)" : "(2,)");
            return -1;
        }
    }
    st->y = sp[0], st->cy = sp[1], st->gamma = sp[2], st->eref = sp[3], st->clock = sp[4];
    return 0;
}

/* kernel id, system, state, method, newton, opts, work, the Python kernel, the scratch and the
 * followers flag into a (0, or -1 with the exception set) */
static int parse_step(bufset *bs, long kid, PyObject *system, PyObject *state, PyObject *method,
                      PyObject *newton, PyObject *opts, PyObject *wk, PyObject *pyk,
                      PyObject *scr, int follow, step_args *a)
{
    Py_ssize_t sh[3];
    PyObject *o;
    if (kernel_of(kid, &a->kern) != 0)
        return -1;
    /* system: (full, minv, kin_w, params) */
    if (!(o = item(system, 0, "system.full")))
        return -1;
    if (PyObject_IsTrue(o)) {
        PyErr_SetString(PyExc_ValueError, "hbvm-md core: the compiled core steps the separable "
                                          "form only (system.full is true)");
        return -1;
    }
    if (!(o = item(system, 1, "system.minv")))
        return -1;
    const double *minv = get(bs, o, "system.minv", 1, 0, sh);
    if (!minv)
        return -1;
    const int m = (int)sh[0];
    if (!(o = item(system, 2, "system.kin_w")))
        return -1;
    const double *kin_w = get(bs, o, "system.kin_w", 1, 0, sh);
    if (!kin_w)
        return -1;
    if (sh[0] != m)
        SHAPE_ERR("system.kin_w", "(m,) as minv");
    if (!(o = item(system, 3, "system.params")))
        return -1;
    const double *params = get(bs, o, "system.params", 1, 0, sh);
    if (!params)
        return -1;
    if (check_params(kid, m, sh[0], params) != 0)
        return -1;
    a->kern.params = params;
    /* the followers (test particles) of the N-body kernel: its followers block after the
     * kernel's own 3N + 3 parameters (systems.nbody.followers_block; none: nbody_followers
     * says -1, and the step is the whole system's) */
    const double *fblock = NULL;
    const long at = 3 * (long)(m / 3) + 3;
    if (follow && (kid != KERNEL_NBODY || sh[0] > at)) {
        if (kid != KERNEL_NBODY || hbvm_followers_check(m, params + at, (long)sh[0] - at) != 0) {
            PyErr_SetString(PyExc_ValueError,
                            "hbvm-md core: the followers need the N-body kernel's parameters "
                            "with their followers block (systems.nbody.followers_block: [P, 3, "
                            "3 Ns, 3 Ns + 3, source columns, test particles' first columns, "
                            "the sources' own parameters])");
            return -1;
        }
        fblock = params + at;
    }
    a->mctx = m;
    if (kid >= KERNEL_BUILTIN)
        a->kern.ctx = &a->mctx;
    if (kid == KERNEL_PYTHON) {
        if (python_kernel(bs, pyk, m, &a->pctx) != 0)
            return -1;
        a->kern.ctx = &a->pctx;
    }
    /* method: (tn (2, k), ts (2, s), Wp (2, s, k), Cp (4, k, s)) */
    if (!(o = item(method, 0, "method.tn")))
        return -1;
    const double *tn = get(bs, o, "method.tn", 2, 0, sh);
    if (!tn)
        return -1;
    if (sh[0] != 2)
        SHAPE_ERR("method.tn", "(2, k)");
    const int k = (int)sh[1];
    if (!(o = item(method, 1, "method.ts")))
        return -1;
    const double *ts = get(bs, o, "method.ts", 2, 0, sh);
    if (!ts)
        return -1;
    if (sh[0] != 2)
        SHAPE_ERR("method.ts", "(2, s)");
    const int s = (int)sh[1];
    if (s < 1 || k < s)
        SHAPE_ERR("method", "1 <= s <= k");
    if (!(o = item(method, 2, "method.Wp")))
        return -1;
    const double *Wp = get(bs, o, "method.Wp", 3, 0, sh);
    if (!Wp)
        return -1;
    if (sh[0] != 2 || sh[1] != s || sh[2] != k)
        SHAPE_ERR("method.Wp", "(2, s, k)");
    if (!(o = item(method, 3, "method.Cp")))
        return -1;
    const double *Cp = get(bs, o, "method.Cp", 3, 0, sh);
    if (!Cp)
        return -1;
    if (sh[0] != 4 || sh[1] != k || sh[2] != s) {
        PyErr_SetString(PyExc_ValueError,
                        "hbvm-md core: method.Cp must have shape (4, k, s): the compiled core "
                        "steps HBVM (EQUIP's packed arrays have more planes)");
        return -1;
    }
    a->tab = (hbvm_tableau){.k = k, .s = s, .tau = tn, .tau_lo = tn + k, .X0 = ts,
                            .X0_lo = ts + s, .W = Wp, .W_lo = Wp + s * k, .C2 = Cp,
                            .C2_lo = Cp + k * s, .I = Cp + 2 * k * s, .I_lo = Cp + 3 * k * s};
    if (get_state(bs, state, "state", m, s, &a->st) != 0)
        return -1;
    /* newton: (NV, NVinv, NM): the core iterates to a fixed point only */
    if (!(o = item(newton, 2, "newton.NM")))
        return -1;
    {
        PyObject *shape = PyObject_GetAttrString(o, "shape");
        if (!shape)
            return -1;
        PyObject *n0 = PyTuple_Check(shape) && PyTuple_GET_SIZE(shape) > 0
                           ? PyTuple_GET_ITEM(shape, 0) : NULL;
        long nm = n0 ? PyLong_AsLong(n0) : -1;
        Py_DECREF(shape);
        if (nm != 0) {
            PyErr_SetString(PyExc_ValueError, "hbvm-md core: the compiled core iterates to a "
                                              "fixed point (newton.NM must be empty)");
            return -1;
        }
    }
    /* opts: (max_iter, tol, etol, ebound, group) */
    {
        PyObject *f[5];
        for (int i = 0; i < 5; ++i)
            if (!(f[i] = item(opts, i, "opts")))
                return -1;
        a->op.max_iter = (int)PyLong_AsLong(f[0]);
        a->op.tol = PyFloat_AsDouble(f[1]);
        a->op.etol = PyFloat_AsDouble(f[2]);
        a->op.ebound = PyFloat_AsDouble(f[3]);
        a->op.group = (int)PyLong_AsLong(f[4]);
        if (PyErr_Occurred())
            return -1;
    }
    /* work: (work, cwork, counters): the core keeps its own scratch */
    if (!(o = item(wk, 2, "work.counters")))
        return -1;
    a->counters = get(bs, o, "work.counters", 1, 1, sh);
    if (!a->counters)
        return -1;
    if (sh[0] < N_COUNTERS)
        SHAPE_ERR("work.counters", "(10,)");
    a->sys = (hbvm_system){.m = m, .minv = minv, .kin_w = kin_w, .follow = fblock,
                           .field = fblock ? hbvm_nbody_field : NULL};
    a->scratch = NULL;
    a->nscratch = 0;
    if (scr != Py_None) {
        if (!(a->scratch = get(bs, scr, "scratch", 1, 1, &a->nscratch)))
            return -1;
    }
    if (kid == KERNEL_PYTHON && a->tab.k > a->pctx.kmax) {
        PyErr_SetString(PyExc_ValueError, "hbvm-md core: the Python kernel's buffers are "
                                          "shorter than the method's stages");
        return -1;
    }
    return 0;
fail:
    return -1;
}

/* a step's status for Python: the status, or the exception of a step that could not run (out
 * of memory; a kernel that stopped it, whose own exception is kept when it set one) */
static PyObject *status_result(int status)
{
    if (status < 0)
        return PyErr_NoMemory();
    if (status == HBVM_ABORTED) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_RuntimeError, "hbvm-md core: a kernel stopped the step");
        return NULL;
    }
    return PyLong_FromLong(status);
}

static PyObject *py_run(PyObject *self, PyObject *args)
{
    long kid;
    PyObject *system, *state, *Eo, *method, *newton, *opts, *wk, *samples, *pyk = Py_None;
    PyObject *scr = Py_None;
    double h;
    int follow = 0;
    if (!PyArg_ParseTuple(args, "lOOdOOOOOO|OOp", &kid, &system, &state, &h, &Eo, &method,
                          &newton, &opts, &wk, &samples, &pyk, &scr, &follow))
        return NULL;
    bufset bs = {.n = 0};
    Py_ssize_t sh[3];
    PyObject *o;
    step_args a;
    if (parse_step(&bs, kid, system, state, method, newton, opts, wk, pyk, scr, follow, &a) != 0)
        goto fail;
    const int m = a.sys.m, s = a.tab.s;
    const double *E = get(&bs, Eo, "E", 2, 0, sh);
    if (!E)
        goto fail;
    if (sh[0] != s || sh[1] != s)
        SHAPE_ERR("E", "(s, s)");
    /* samples: (nsteps, every, t (n,), y (n, 2m), e (n,)) */
    hbvm_samples smp;
    {
        PyObject *a0 = item(samples, 0, "samples.nsteps"), *a1 = item(samples, 1, "samples.every");
        if (!a0 || !a1)
            goto fail;
        smp.nsteps = PyLong_AsLong(a0);
        smp.every = PyLong_AsLong(a1);
        if (PyErr_Occurred())
            goto fail;
        smp.t = smp.y = smp.e = NULL;
        if (smp.every > 0) {
            Py_ssize_t nt, ny[2], ne;
            if (!(o = item(samples, 2, "samples.t")) || !(smp.t = get(&bs, o, "samples.t", 1, 1, &nt)))
                goto fail;
            if (!(o = item(samples, 3, "samples.y")) || !(smp.y = get(&bs, o, "samples.y", 2, 1, ny)))
                goto fail;
            if (!(o = item(samples, 4, "samples.e")) || !(smp.e = get(&bs, o, "samples.e", 1, 1, &ne)))
                goto fail;
            const long need = smp.nsteps / smp.every + 1;
            if (nt < need || ne < need || ny[0] < need || ny[1] != 2 * m)
                SHAPE_ERR("samples", "(nsteps / every + 1) rows of t, y (2m), e");
        }
    }
    /* the GIL released for compiled kernels (a Python kernel calls the interpreter: kept) */
    PyThreadState *ts = kid == KERNEL_PYTHON ? NULL : PyEval_SaveThread();
    const int status = hbvm_run(&a.kern, &a.sys, &a.st, h, E, &a.tab, &a.op, a.counters, &smp,
                                a.scratch, (size_t)a.nscratch);
    if (ts)
        PyEval_RestoreThread(ts);
    release(&bs);
    return status_result(status);
fail:
    release(&bs);
    return NULL;
}

/* attempt(kernel, system, state, trial, h, h_prev, t_start, ext, method, newton, opts, work,
 * adaptive[, scratch, follow]) -> status: integrators.loop.attempt's contract in C
 * (hbvm_attempt: the one retry loop and controller, with the followers' term of the adaptive
 * control); trial shares state's clock; a compiled kernel only */
static PyObject *py_attempt(PyObject *self, PyObject *args)
{
    long kid;
    PyObject *system, *state, *trial, *exto, *method, *newton, *opts, *wk, *ado;
    PyObject *scr = Py_None;
    double h, h_prev, t_start;
    int follow = 0;
    if (!PyArg_ParseTuple(args, "lOOOdddOOOOOO|Op", &kid, &system, &state, &trial, &h, &h_prev,
                          &t_start, &exto, &method, &newton, &opts, &wk, &ado, &scr, &follow))
        return NULL;
    if (kid == KERNEL_PYTHON) {
        PyErr_SetString(PyExc_ValueError, "hbvm-md core: attempt() is for compiled kernels");
        return NULL;
    }
    bufset bs = {.n = 0};
    Py_ssize_t sh[2];
    PyObject *o;
    step_args a;
    if (parse_step(&bs, kid, system, state, method, newton, opts, wk, Py_None, scr, follow,
                   &a) != 0)
        goto fail;
    const int m = a.sys.m, s = a.tab.s;
    hbvm_state tr;
    if (get_state(&bs, trial, "trial", m, s, &tr) != 0)
        goto fail;
    /* ext: (E1, t, w, buf, zero) */
    const char *enames[] = {"ext.E1", "ext.t", "ext.w", "ext.buf", "ext.zero"};
    double *ep[5];
    for (int i = 0; i < 5; ++i) {
        const int nd = (i == 1 || i == 2) ? 1 : 2;
        if (!(o = item(exto, i, enames[i])) || !(ep[i] = get(&bs, o, enames[i], nd, i == 3, sh)))
            goto fail;
        if (sh[0] != s || (nd == 2 && sh[1] != s))
            SHAPE_ERR(enames[i], "(s, s), or (s,) for the rule");
    }
    hbvm_extrapolation ext = {.E1 = ep[0], .t = ep[1], .w = ep[2], .buf = ep[3], .zero = ep[4]};
    /* adaptive: (epsilon, min_dt, res (5,)) */
    PyObject *e0 = item(ado, 0, "adaptive.epsilon"), *e1 = item(ado, 1, "adaptive.min_dt");
    if (!e0 || !e1)
        goto fail;
    const double epsilon = PyFloat_AsDouble(e0), min_dt = PyFloat_AsDouble(e1);
    if (PyErr_Occurred())
        goto fail;
    double *res;
    if (!(o = item(ado, 2, "adaptive.res")) || !(res = get(&bs, o, "adaptive.res", 1, 1, sh)))
        goto fail;
    if (sh[0] < 5)
        SHAPE_ERR("adaptive.res", "(5,)");
    int status;
    Py_BEGIN_ALLOW_THREADS
    status = hbvm_attempt(&a.kern, &a.sys, &a.st, &tr, h, h_prev, t_start, &ext, &a.tab, &a.op,
                          a.counters, epsilon, min_dt, res, a.scratch, (size_t)a.nscratch);
    Py_END_ALLOW_THREADS
    release(&bs);
    return status_result(status);
fail:
    release(&bs);
    return NULL;
}

static PyObject *py_energy_parts(PyObject *self, PyObject *args)
{
    long kid;
    PyObject *yo, *wo, *po;
    if (!PyArg_ParseTuple(args, "lOOO", &kid, &yo, &wo, &po))
        return NULL;
    if (kid == KERNEL_PYTHON) {
        PyErr_SetString(PyExc_ValueError, "hbvm-md core: a Python kernel's energy is Python's");
        return NULL;
    }
    hbvm_kernel kern;
    if (kernel_of(kid, &kern) != 0)
        return NULL;
    bufset bs = {.n = 0};
    Py_ssize_t sh[2], np;
    const double *y = get(&bs, yo, "y", 1, 0, sh);
    if (!y)
        goto fail;
    const int m = (int)(sh[0] / 2);
    const double *kin_w = get(&bs, wo, "kin_w", 1, 0, sh);
    if (!kin_w)
        goto fail;
    if (sh[0] != m)
        SHAPE_ERR("kin_w", "(m,) for y of shape (2m,)");
    const double *params = get(&bs, po, "params", 1, 0, &np);
    if (!params || check_params(kid, m, np, params) != 0)
        goto fail;
    kern.params = params;
    int mctx = m;
    if (kid >= KERNEL_BUILTIN)
        kern.ctx = &mctx;
    hbvm_system sys = {.m = m, .minv = NULL, .kin_w = kin_w};
    double T, V;
    hbvm_energy_parts(&kern, &sys, y, &T, &V);   /* (a compiled kernel: cannot fail) */
    release(&bs);
    return Py_BuildValue("dd", T, V);
fail:
    release(&bs);
    return NULL;
}

/* force(kernel, X (n, m), params, out (n, m)): the kernel on rows of X (the Python kernels'
 * layout), through the stage-fastest layout */
static PyObject *py_force(PyObject *self, PyObject *args)
{
    long kid;
    PyObject *xo, *po, *oo;
    if (!PyArg_ParseTuple(args, "lOOO", &kid, &xo, &po, &oo))
        return NULL;
    hbvm_kernel kern;
    if (kernel_of(kid, &kern) != 0)
        return NULL;
    if (kid == KERNEL_PYTHON) {
        PyErr_SetString(PyExc_ValueError, "hbvm-md core: force() is for compiled kernels");
        return NULL;
    }
    bufset bs = {.n = 0};
    Py_ssize_t sx[2], so[2], np;
    const double *X = get(&bs, xo, "X", 2, 0, sx);
    if (!X)
        goto fail;
    double *out = get(&bs, oo, "out", 2, 1, so);
    if (!out)
        goto fail;
    if (so[0] != sx[0] || so[1] != sx[1])
        SHAPE_ERR("out", "X's");
    const int n = (int)sx[0], m = (int)sx[1];
    const double *params = get(&bs, po, "params", 1, 0, &np);
    if (!params || check_params(kid, m, np, params) != 0)
        goto fail;
    int mctx = m;
    if (kid >= KERNEL_BUILTIN)
        kern.ctx = &mctx;
    const int kp = hbvm_padded(n > 0 ? n : 1);
    double *Xt = aligned_alloc(8 * HBVM_LANES, (size_t)m * kp * sizeof(double) + 8 * HBVM_LANES);
    double *Ft = aligned_alloc(8 * HBVM_LANES, (size_t)m * kp * sizeof(double) + 8 * HBVM_LANES);
    if (!Xt || !Ft) {
        free(Xt);
        free(Ft);
        release(&bs);
        return PyErr_NoMemory();
    }
    for (int j = 0; j < m; ++j)
        for (int i = 0; i < kp; ++i)
            Xt[j * kp + i] = n > 0 ? X[(i < n ? i : n - 1) * m + j] : 0.0;
    kern.force(kern.ctx, Xt, m, kp, n > 0 ? n : 1, params, Ft);
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < m; ++j)
            out[i * m + j] = Ft[j * kp + i];
    free(Xt);
    free(Ft);
    release(&bs);
    Py_RETURN_NONE;
fail:
    release(&bs);
    return NULL;
}

static PyObject *py_kinetic(PyObject *self, PyObject *args)
{
    PyObject *po, *wo;
    if (!PyArg_ParseTuple(args, "OO", &po, &wo))
        return NULL;
    bufset bs = {.n = 0};
    Py_ssize_t sp[1], sw[1];
    const double *p = get(&bs, po, "p", 1, 0, sp);
    if (!p)
        goto fail;
    const double *w = get(&bs, wo, "kin_w", 1, 0, sw);
    if (!w)
        goto fail;
    if (sp[0] != sw[0])
        SHAPE_ERR("kin_w", "p's");
    double ke = 0.0;
    for (Py_ssize_t i = 0; i < sp[0]; ++i)
        ke += 0.5 * p[i] * p[i] * w[i];
    release(&bs);
    return PyFloat_FromDouble(ke);
fail:
    release(&bs);
    return NULL;
}

/* select_extrapolation(h, h_prev, E1, t, w, buf, zero): core.select_extrapolation's rule (the
 * initial guess's matrix for a step h after one of h_prev, nan: none), returning the array it
 * chose: E1 (the same step), zero (a step more than MAX_EXTRAPOLATION times longer), or buf
 * filled with E(h / h_prev) (a sliver, |r| < TINY_RATIO, takes r = 0) */
static PyObject *py_select_extrapolation(PyObject *self, PyObject *args)
{
    double h, hp;
    PyObject *E1, *to, *wo, *bo, *zo;
    if (!PyArg_ParseTuple(args, "ddOOOOO", &h, &hp, &E1, &to, &wo, &bo, &zo))
        return NULL;
    bufset bs = {.n = 0};
    Py_ssize_t st[1], sw[1], sb[2], s1[2], sz[2];
    const double *t = get(&bs, to, "t", 1, 0, st);
    if (!t)
        goto fail;
    const double *w = get(&bs, wo, "w", 1, 0, sw);
    if (!w)
        goto fail;
    double *buf = get(&bs, bo, "buf", 2, 1, sb);
    if (!buf)
        goto fail;
    const double *e1 = get(&bs, E1, "E1", 2, 0, s1);
    if (!e1)
        goto fail;
    const double *zero = get(&bs, zo, "zero", 2, 0, sz);
    if (!zero)
        goto fail;
    const int s = (int)st[0];
    if (sw[0] != s || sb[0] != s || sb[1] != s || s1[0] != s || s1[1] != s || sz[0] != s
        || sz[1] != s)
        SHAPE_ERR("E1, buf, zero", "(s, s) for the s-point rule (t, w)");
    hbvm_extrapolation ext = {.E1 = e1, .t = t, .w = w, .buf = buf, .zero = zero};
    const double *E = hbvm_select_extrapolation(h, hp, &ext, s);
    release(&bs);
    if (!E)
        return PyErr_NoMemory();
    PyObject *out = E == e1 ? E1 : E == zero ? zo : bo;
    Py_INCREF(out);
    return out;
fail:
    release(&bs);
    return NULL;
}

static PyObject *py_work_size(PyObject *self, PyObject *args)
{
    int k, s, m, us = 0, P = 0;
    if (!PyArg_ParseTuple(args, "iii|ii", &k, &s, &m, &us, &P))
        return NULL;
    if (P > 0)
        return PyLong_FromSize_t(hbvm_work_size_followers(k, s, m, us, P));
    return PyLong_FromSize_t(hbvm_work_size(k, s, m));
}

/* test_particle_control(gamma (s, m), w (m,), kin_w (m,), err) -> core.test_particle_control */
static PyObject *py_test_particle_control(PyObject *self, PyObject *args)
{
    PyObject *go, *wo, *ko;
    double err;
    if (!PyArg_ParseTuple(args, "OOOd", &go, &wo, &ko, &err))
        return NULL;
    bufset bs = {.n = 0};
    Py_ssize_t sg[2], sw[1], sk[1];
    const double *g = get(&bs, go, "gamma", 2, 0, sg);
    if (!g)
        goto fail;
    const double *w = get(&bs, wo, "w", 1, 0, sw);
    if (!w)
        goto fail;
    const double *kw = get(&bs, ko, "kin_w", 1, 0, sk);
    if (!kw)
        goto fail;
    if (sw[0] != sg[1] || sk[0] != sg[1] || sg[0] < 1)
        SHAPE_ERR("w, kin_w", "(m,) for gamma of shape (s, m)");
    const double out = hbvm_test_particle_control(g, (int)sg[0], (int)sg[1], w, kw, err);
    release(&bs);
    return PyFloat_FromDouble(out);
fail:
    release(&bs);
    return NULL;
}

static PyMethodDef methods[] = {
    {"work_size", py_work_size, METH_VARARGS,
     "work_size(k, s, m[, us, P]) -> the doubles of scratch run() works in (zeroed, kept "
     "between calls); with P followers besides sources of us coordinates"},
    {"test_particle_control", py_test_particle_control, METH_VARARGS,
     "test_particle_control(gamma, w, kin_w, err) -> core.test_particle_control's estimate"},
    {"select_extrapolation", py_select_extrapolation, METH_VARARGS,
     "select_extrapolation(h, h_prev, E1, t, w, buf, zero) -> the initial guess's matrix "
     "(core.select_extrapolation's rule)"},
    {"kinetic", py_kinetic, METH_VARARGS,
     "kinetic(p, kin_w) -> sum_i kin_w_i p_i^2 / 2, summed in order (core.weighted_kinetic)"},
    {"run", py_run, METH_VARARGS,
     "run(kernel, system, state, h, E, method, newton, opts, work, samples[, pyk, scratch, "
     "follow]) -> status: integrators.loop.run's steps for the separable HBVM form, compiled; "
     "follow: the N-body kernel's test particles solved after the sources (followers)."},
    {"attempt", py_attempt, METH_VARARGS,
     "attempt(kernel, system, state, trial, h, h_prev, t_start, ext, method, newton, opts, "
     "work, adaptive[, scratch, follow]) -> status: integrators.loop.attempt's contract, "
     "compiled (hbvm_attempt)"},
    {"energy_parts", py_energy_parts, METH_VARARGS,
     "energy_parts(kernel, y, kin_w, params) -> (T, V)"},
    {"force", py_force, METH_VARARGS,
     "force(kernel, X, params, out): the kernel at the rows of X (n, m) into out (n, m)"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef moddef = {PyModuleDef_HEAD_INIT, "_core",
                                    "The compiled core of hbvm-md (integrators/csrc).", -1,
                                    methods};

PyMODINIT_FUNC PyInit__core(void)
{
    PyObject *mod = PyModule_Create(&moddef);
    if (!mod)
        return NULL;
    PyModule_AddIntConstant(mod, "LANES", HBVM_LANES);
    static const hbvm_api api = {.version = HBVM_API_VERSION, .lanes = HBVM_LANES,
                                 .n_counters = N_COUNTERS, .n_eref = HBVM_N_EREF,
                                 .attempt = hbvm_attempt, .work_size = hbvm_work_size,
                                 .energy_parts = hbvm_energy_parts,
                                 .nbody_force = hbvm_nbody_force_k,
                                 .nbody_potential = hbvm_nbody_potential_k,
                                 .nbody_check = hbvm_nbody_check,
                                 .nbody_field = hbvm_nbody_field,
                                 .test_particle_error = hbvm_test_particle_error};
    PyObject *cap = PyCapsule_New((void *)&api, "integrators._core.API", NULL);
    if (!cap || PyModule_AddObject(mod, "API", cap) != 0)
        return NULL;
    PyModule_AddIntConstant(mod, "NBODY", KERNEL_NBODY);
    PyModule_AddIntConstant(mod, "PYTHON", KERNEL_PYTHON);
    PyObject *builtins = PyDict_New();
    if (!builtins)
        return NULL;
    for (long i = 0; hbvm_builtins[i].name; ++i) {
        PyObject *v = PyLong_FromLong(KERNEL_BUILTIN + i);
        if (!v || PyDict_SetItemString(builtins, hbvm_builtins[i].name, v) != 0)
            return NULL;
        Py_DECREF(v);
    }
    PyModule_AddObject(mod, "BUILTINS", builtins);
#ifdef HBVM_SOURCE_DIGEST
    PyModule_AddStringConstant(mod, "SOURCE_DIGEST", HBVM_SOURCE_DIGEST);
#else
    PyModule_AddStringConstant(mod, "SOURCE_DIGEST", "");
#endif
#ifdef HBVM_BUILD_FLAGS
    PyModule_AddStringConstant(mod, "BUILD_FLAGS", HBVM_BUILD_FLAGS);
#else
    PyModule_AddStringConstant(mod, "BUILD_FLAGS", "");
#endif
    return mod;
}
