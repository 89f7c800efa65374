/* One HBVM(k, s) step of the separable form, stage-fastest (hbvm_core.h), and many of them.
 *
 * The step of integrators/loop.py (its HBVM, separable, fixed-point branch: no stage
 * velocities, no Newton matrices; with or without followers) with its pieces from
 * integrators/core.py and integrators/followers.py, operation for operation: the extrapolated
 * start, the fixed point gamma <- P_s^T Omega f(stages), the stop rule (stop_action), the
 * compensated polish and commit, the followers (test particles) solved after the sources each
 * with its own stop rule, the step's own error estimate (resolution_error), the energy check
 * and the run's drift, the counters and the compensated clock. The docstrings of those Python
 * functions say why each piece is as it is; the comments here say only where this code
 * differs (the layout). */
#include <math.h>
#include <stdlib.h>
#include <stdint.h>
#include <string.h>

#include "hbvm_core.h"
#include "hbvm_vec.h"

#define L HBVM_LANES

static const double EPS = 2.220446049250313e-16;
static const double ROUNDOFF_ULPS = 64.0;
static const double LIPSCHITZ_ULPS = 4.0;
static const double STATE_ULPS = 16.0;
static const double STRONG_CONTRACTION = 1e-3;
static const double EXTRAPOLATED_ULPS = 1e-3;
static const double TOL_CONTRACTION = 0.25;
static const double RUNAWAY = 1e8;
static const double DRIFT_BOUND = 1e-3;
static const double DRIFT_PHASE = 1.5;
static const double FLOW_FRACTION[3] = {1.0, 1.5e-2, 1e-3};

enum { ITERATE = 0, POLISH = 1 };

/* the blocked sums take JB coordinates at a time: JB independent chains of additions, each
 * stage's (each coefficient's) sum still in its order */
#define JB 4

/* HBVM_PROFILE (setup.py: HBVM_MD_PROFILE=1): the step's pieces stay functions of their own, so
 * that a sampling profiler (perf) splits the step's time between them */
#ifdef HBVM_PROFILE
#define PIECE __attribute__((noinline)) static
#else
#define PIECE static
#endif

/* Python's max(a, b) (the first unless the second is larger), as the Python-side step takes it */
static inline double py_max(double a, double b) { return b > a ? b : a; }
static inline double py_min(double a, double b) { return b < a ? b : a; }

static inline void two_product(double a, double b, double *hi, double *lo)
{
    double p = a * b;
    *hi = p;
    *lo = fma(a, b, -p);
}

static inline void two_sum(double a, double b, double *s, double *e)
{
    double x = a + b;
    double bb = x - a;
    *s = x;
    *e = (a - (x - bb)) + (b - bb);
}

/* x[j] - c[j] (c holds minus the low part) += inc_hi + inc_lo */
static inline void dd_add(double *x, double *c, int j, double inc_hi, double inc_lo)
{
    double s, e;
    two_sum(x[j], inc_hi, &s, &e);
    double lo = (e + inc_lo) - c[j];
    double hi = s + lo;
    c[j] = -(lo - (hi - s));
    x[j] = hi;
}

static double legendre_at(int s, double c)
{
    double x = 2.0 * c - 1.0, lm = 0.0, l0 = 1.0;
    for (int j = 0; j < s; ++j) {
        double ln = ((2.0 * j + 1.0) * x * l0 - j * lm) / (j + 1.0);
        lm = l0;
        l0 = ln;
    }
    return sqrt(2.0 * s + 1.0) * l0;
}

static double weighted_kinetic(const double *p, const double *w, int m)
{
    double ke = 0.0;
    for (int i = 0; i < m; ++i)
        ke += 0.5 * p[i] * p[i] * w[i];
    return ke;
}

int hbvm_energy_parts(const hbvm_kernel *kernel, const hbvm_system *sys, const double *y,
                      double *T, double *V)
{
    *T = weighted_kinetic(y + sys->m, sys->kin_w, sys->m);
    return kernel->potential(kernel->ctx, y, kernel->params, V);
}

/* the step's work arrays, one allocation */
typedef struct {
    int k, kp, s, sp, m, mp;     /* mp: m rounded up to JB (the blocked sums' rows) */
    double *ht, *ht_lo;          /* (kp) h tau as exact pairs, padded with the last stage */
    double *C2T, *C2T_lo;        /* (s, kp) C2 transposed, padded with the last stage */
    double *WT, *WT_lo;          /* (k, sp) W transposed, rows padded with zeros */
    double *a;                   /* (m, sp) g / m */
    double *g;                   /* (m, sp) the iterate, each coordinate's coefficients
                                  * contiguous (gamma's transpose, padded with zeros) */
    double *X, *F, *Xp, *Fp;     /* (m, kp) stages, forces, the Lipschitz probe's copies */
    double *P, *Q;               /* (m, kp) the stages' parts fixed for a step: q0 + h tau v0 and
                                  * the rounding terms of h tau v0 and of the state's low part */
    double *X1, *F1;             /* (m, L) one point (the first guess, the endpoint defect) */
    double *ET;                  /* (s, sp) E transposed: the guess's rows as lanes */
    double *pw;                  /* (k) W[0, i] P_s(tau_i): the omitted coefficient's weights */
    double *yt, *cyt;            /* (2m) the trial state */
    double *dq, *dq_lo, *om;     /* (m) */
    double hist[5];
    void *block;
} work_t;

/* the work arrays' lengths (doubles) for k stages, s coefficients and m coordinates; each a
 * multiple of L long, so that each starts aligned.  lean: the whole state's arrays of a step
 * with followers, whose iteration runs on the sources' block (no stages, no a) */
#define N_WORK 23
static size_t work_sizes(int k, int s, int m, int lean, size_t *sizes)
{
    const size_t kp = hbvm_padded(k), sp = hbvm_padded(s), mp = (m + JB - 1) / JB * JB;
    const size_t mk = lean ? 0 : m * kp, mpk = lean ? 0 : mp * kp, mps = lean ? 0 : mp * sp;
    const size_t sz[N_WORK] = {kp, kp, s * kp, s * kp, k * sp, k * sp, mps, mp * sp,
                               mk, mpk, mk, mk, mk, mk, m * L, m * L,
                               s * sp, k, 2 * (size_t)m, 2 * (size_t)m, m, m, m};
    size_t total = 0;
    for (int i = 0; i < N_WORK; ++i) {
        sizes[i] = (sz[i] + L - 1) / L * L;
        total += sizes[i];
    }
    return total;
}

size_t hbvm_work_size(int k, int s, int m)
{
    size_t sizes[N_WORK];
    return work_sizes(k, s, m, 0, sizes) + L;     /* (+ L: room to align the start) */
}

/* the work arrays of w from p on (aligned; work_sizes(k, s, m, lean) doubles, zero when first
 * handed over: the padded rows and lanes must stay zero, and nothing writes them), and the
 * method's arrays in the lanes' layout; returns the end */
static double *work_carve(work_t *w, const hbvm_tableau *tab, int m, int lean, double *p)
{
    const int k = tab->k, s = tab->s;
    const int kp = hbvm_padded(k), sp = hbvm_padded(s);
    const int mp = (m + JB - 1) / JB * JB;
    w->k = k, w->kp = kp, w->s = s, w->sp = sp, w->m = m, w->mp = mp;
    size_t sizes[N_WORK];
    work_sizes(k, s, m, lean, sizes);
    double **ptrs[N_WORK] = {&w->ht, &w->ht_lo, &w->C2T, &w->C2T_lo, &w->WT, &w->WT_lo, &w->a,
                             &w->g, &w->X, &w->F, &w->Xp, &w->Fp, &w->P, &w->Q, &w->X1, &w->F1,
                             &w->ET, &w->pw, &w->yt, &w->cyt, &w->dq, &w->dq_lo, &w->om};
    w->block = NULL;
    for (int i = 0; i < N_WORK; ++i) {
        *ptrs[i] = p;
        p += sizes[i];
    }
    for (int l = 0; l < s; ++l)
        for (int i = 0; i < kp; ++i) {
            int ii = i < k ? i : k - 1;
            w->C2T[l * kp + i] = tab->C2[ii * s + l];
            w->C2T_lo[l * kp + i] = tab->C2_lo[ii * s + l];
        }
    for (int i = 0; i < k; ++i)
        for (int l = 0; l < sp; ++l) {
            w->WT[i * sp + l] = l < s ? tab->W[l * k + i] : 0.0;
            w->WT_lo[i * sp + l] = l < s ? tab->W_lo[l * k + i] : 0.0;
        }
    for (int i = 0; i < k; ++i)
        w->pw[i] = tab->W[i] * legendre_at(s, tab->tau[i]);
    return p;
}

/* the followers of a step (integrators/followers.py): the block's layout (hbvm_system.follow)
 * and their work arrays, the stage index fastest as in the step (a follower's three
 * coordinates are three rows of kp stage values, contiguous) */
#define FOLLOWER_GROUP 128              /* core.FOLLOWER_GROUP */
typedef struct {
    int P, us, nown, nmax;              /* followers, the sources' columns, their own params'
                                         * length, the followers of a group */
    const double *cols, *first, *own;   /* (us) the sources' columns, (P) each follower's first
                                         * column, the sources' own kernel parameters */
    double *yb, *cyb, *mb;              /* (2us, 2us, us) the sources' state and 1 / m */
    double *P0, *Q0;                    /* (3 nmax, kp) a group's stage_base */
    double *X, *F, *Xp, *Fp;            /* (3 nmax, kp) its stages, fields, the probe's copies */
    double *g, *a;                      /* (3 nmax, sp) its coefficients, (3, sp) g / m */
    double *mv;                         /* (3 nmax) 1 / m */
    double *hist;                       /* (nmax, 5) each follower's stop rule's history */
    double *lip, *xmax, *ymax, *active; /* (nmax) its Lipschitz estimate, max |X|, max |y|; the
                                         * followers still iterating, in their order */
    double *smask;                      /* (sp) all ones in the lanes l < s, zero past them */
} follow_t;

#define N_FOLLOW 17
static size_t follow_sizes(int k, int s, int us, int P, size_t *sizes)
{
    const size_t kp = hbvm_padded(k), sp = hbvm_padded(s);
    const size_t nmax = P < FOLLOWER_GROUP ? P : FOLLOWER_GROUP, r = 3 * nmax;
    const size_t sz[N_FOLLOW] = {2 * (size_t)us, 2 * (size_t)us, us, r * kp, r * kp, r * kp,
                                 r * kp, r * kp, r * kp, r * sp, 3 * sp, r, 5 * nmax, nmax,
                                 nmax, nmax, nmax};
    size_t total = 0;
    for (int i = 0; i < N_FOLLOW; ++i) {
        sizes[i] = (sz[i] + L - 1) / L * L;
        total += sizes[i];
    }
    return total + (sp + L - 1) / L * L;
}

/* the whole state's lean arrays, the sources' block and the followers' arrays */
static size_t followers_total(int k, int s, int m, int us, int P)
{
    size_t sw[N_WORK], sf[N_FOLLOW];
    return work_sizes(k, s, m, 1, sw) + work_sizes(k, s, us, 0, sw) + follow_sizes(k, s, us, P, sf);
}

size_t hbvm_work_size_followers(int k, int s, int m, int us, int P)
{
    return followers_total(k, s, m, us, P) + L;
}

int hbvm_followers_check(int m, const double *f, long nblock)
{
    if (nblock < 4)
        return -1;
    for (int i = 0; i < 4; ++i)
        if (!(f[i] >= 0.0 && f[i] <= 1e9) || f[i] != (double)(long)f[i])
            return -1;
    const long P = (long)f[0], w = (long)f[1], us = (long)f[2], np = (long)f[3];
    if (P < 1 || w != 3 || us < 3 || us % 3 != 0 || nblock < 4 + us + P + np)
        return -1;
    for (long i = 0; i < us + P; ++i) {
        const double c = f[4 + i];
        if (!(c >= 0.0 && c < m) || c != (double)(long)c || (i >= us && c + 3 > m))
            return -1;
    }
    return hbvm_nbody_check((int)us, f + 4 + us + P, np);
}

/* the followers' arrays from p on (follow_sizes) */
static double *follow_carve(follow_t *f, const double *blk, int k, int s, double *p)
{
    f->P = (int)blk[0];
    f->us = (int)blk[2];
    f->nown = (int)blk[3];
    f->nmax = f->P < FOLLOWER_GROUP ? f->P : FOLLOWER_GROUP;
    f->cols = blk + 4;
    f->first = blk + 4 + f->us;
    f->own = blk + 4 + f->us + f->P;
    size_t sizes[N_FOLLOW];
    follow_sizes(k, s, f->us, f->P, sizes);
    double **ptrs[N_FOLLOW] = {&f->yb, &f->cyb, &f->mb, &f->P0, &f->Q0, &f->X, &f->F, &f->Xp,
                               &f->Fp, &f->g, &f->a, &f->mv, &f->hist, &f->lip, &f->xmax,
                               &f->ymax, &f->active};
    for (int i = 0; i < N_FOLLOW; ++i) {
        *ptrs[i] = p;
        p += sizes[i];
    }
    const int sp = hbvm_padded(s);
    f->smask = p;
    for (int l = 0; l < sp; ++l) {
        const uint64_t bits = l < s ? ~(uint64_t)0 : 0;
        memcpy(f->smask + l, &bits, sizeof bits);
    }
    return p + (sp + L - 1) / L * L;
}

/* the step's work arrays in `scratch` (hbvm_work_size or hbvm_work_size_followers doubles,
 * zeroed when first handed over), or in a block of their own when scratch is NULL or short:
 * w the whole state's; with followers (blk not NULL) w lean, wb the sources' block and f the
 * followers' */
static int work_alloc(work_t *w, work_t *wb, follow_t *f, const hbvm_tableau *tab, int m,
                      const double *blk, double *scratch, size_t nscratch)
{
    size_t sizes[N_WORK];
    const int us = blk ? (int)blk[2] : 0, P = blk ? (int)blk[0] : 0;
    const size_t total = blk ? followers_total(tab->k, tab->s, m, us, P)
                             : work_sizes(tab->k, tab->s, m, 0, sizes);
    double *p;
    void *block = NULL;
    if (scratch != NULL && nscratch >= total + L) {
        p = (double *)(((uintptr_t)scratch + 8 * L - 1) / (8 * L) * (8 * L));
    } else {
        block = aligned_alloc(8 * L, (total > 0 ? total : L) * sizeof(double));
        if (!block)
            return -1;
        memset(block, 0, total * sizeof(double));
        p = block;
    }
    p = work_carve(w, tab, m, blk != NULL, p);
    w->block = block;
    if (blk) {
        p = work_carve(wb, tab, us, 0, p);
        follow_carve(f, blk, tab->k, tab->s, p);
    }
    return 0;
}

/* h tau_i as exact pairs into ht, ht_lo (padded); returns h h as an exact pair */
PIECE void step_constants(work_t *w, const hbvm_tableau *tab, double h, double *h2,
                           double *h2_lo)
{
    for (int i = 0; i < w->kp; ++i) {
        int ii = i < w->k ? i : w->k - 1;
        double lo;
        two_product(h, tab->tau[ii], &w->ht[i], &lo);
        w->ht_lo[i] = lo + h * tab->tau_lo[ii];
    }
    two_product(h, h, h2, h2_lo);
}

/* X <- q0 + h tau v0 + h^2 (I_s X_s) M^{-1} gamma (core.stage_positions), every coordinate's kp
 * stages as vectors; exact: with C2's low parts.  JB coordinates at a time, their sums in
 * registers (one chain of additions per coordinate waits on each addition's latency: JB
 * chains keep the units busy); each stage's sum runs over l in order (the same numbers). */
/* the parts of the stages a step's iterations share (stage_positions' first terms, the same
 * operations as the whole expression: the same numbers) */
PIECE void stage_base(work_t *w, const double *y, const double *cy, const double *minv)
{
    const int m = w->m, kp = w->kp;
    for (int j = 0; j < m; ++j) {
        const double yj = y[j], vj = y[m + j] * minv[j], cyj = cy[j];
        const double cpj = cy[m + j], mj = minv[j];
        for (int b = 0; b < kp; b += L) {
            const vd ht = vload(w->ht + b), ht_lo = vload(w->ht_lo + b);
            vstore(w->P + j * kp + b, yj + ht * vj);
            vstore(w->Q + j * kp + b, (ht_lo * vj - cyj) - ht * cpj * mj);
        }
    }
}

static inline void put_stage(work_t *w, int j, int b, vd A, vd A_lo, double h2, double h2_lo)
{
    if (j >= w->m)
        return;
    const int o = j * w->kp + b;
    vstore(w->X + o, vload(w->P + o) + ((vload(w->Q + o) + h2 * (A + A_lo)) + h2_lo * A));
}

PIECE void stage_positions(work_t *w, const double *minv, double h2, double h2_lo, int exact)
{
    const int m = w->m, s = w->s, kp = w->kp, sp = w->sp;
    for (int j = 0; j < m; ++j)
        for (int b = 0; b < sp; b += L)
            vstore(w->a + j * sp + b, vload(w->g + j * sp + b) * minv[j]);
    const vd zero = vsplat(0.0);
    for (int j0 = 0; j0 < m; j0 += JB) {
        const double *a0 = w->a + j0 * sp, *a1 = a0 + sp, *a2 = a1 + sp, *a3 = a2 + sp;
        for (int b = 0; b < kp; b += L) {
            vd c0 = zero, c1 = zero, c2 = zero, c3 = zero;
            vd d0 = zero, d1 = zero, d2 = zero, d3 = zero;
            if (exact) {
                for (int l = 0; l < s; ++l) {
                    const vd c = vload(w->C2T + l * kp + b), cl = vload(w->C2T_lo + l * kp + b);
                    c0 += c * a0[l];
                    c1 += c * a1[l];
                    c2 += c * a2[l];
                    c3 += c * a3[l];
                    d0 += cl * a0[l];
                    d1 += cl * a1[l];
                    d2 += cl * a2[l];
                    d3 += cl * a3[l];
                }
            } else {
                for (int l = 0; l < s; ++l) {
                    const vd c = vload(w->C2T + l * kp + b);
                    c0 += c * a0[l];
                    c1 += c * a1[l];
                    c2 += c * a2[l];
                    c3 += c * a3[l];
                }
            }
            put_stage(w, j0, b, c0, d0, h2, h2_lo);
            put_stage(w, j0 + 1, b, c1, d1, h2, h2_lo);
            put_stage(w, j0 + 2, b, c2, d2, h2, h2_lo);
            put_stage(w, j0 + 3, b, c3, d3, h2, h2_lo);
        }
    }
}

/* g <- W F (core.project): each coordinate's s coefficients as vectors, summed over the
 * stages in order, JB coordinates at a time; returns max |increment| (nan first) and max |g| */
PIECE void project(work_t *w, double *delta_out, double *scale_out)
{
    const int m = w->m, sp = w->sp, k = w->k, kp = w->kp;
    const vd zero = vsplat(0.0);
    vd dmax = zero, smax = zero;
    for (int j0 = 0; j0 < m; j0 += JB) {
        const double *f0 = w->F + j0 * kp, *f1 = f0 + kp, *f2 = f1 + kp, *f3 = f2 + kp;
        for (int b = 0; b < sp; b += L) {
            vd g0 = zero, g1 = zero, g2 = zero, g3 = zero;
            for (int i = 0; i < k; ++i) {
                const vd wt = vload(w->WT + i * sp + b);
                g0 += wt * f0[i];
                g1 += wt * f1[i];
                g2 += wt * f2[i];
                g3 += wt * f3[i];
            }
            const vd gs[JB] = {g0, g1, g2, g3};
            for (int r = 0; r < JB && j0 + r < m; ++r) {
                double *old = w->g + (j0 + r) * sp + b;
                dmax = vmax_nan(dmax, vabs(gs[r] - vload(old)));
                smax = vmax(smax, vabs(gs[r]));
                vstore(old, gs[r]);
            }
        }
    }
    *delta_out = hmax_nan(0.0, dmax);
    *scale_out = hmax(0.0, smax);
}

/* one term of the compensated sum (Dot2): (acc, lo) += w f */
static inline void dot2_step(vd *acc, vd *lo, vd wt, vd wt_lo, double fs)
{
    const vd f = vsplat(fs);
    const vd ph = wt * f;
    const vd pl = vfma(wt, f, -ph);
    const vd hi = *acc + ph;
    const vd bb = hi - *acc;
    const vd e = (*acc - (hi - bb)) + (ph - bb);
    *acc = hi;
    *lo += (e + pl) + wt_lo * f;
}

/* g <- W F as if in twice the working precision (Dot2), rounded once (core.project_compensated),
 * JB coordinates at a time */
PIECE void project_compensated(work_t *w)
{
    const int m = w->m, sp = w->sp, k = w->k, kp = w->kp;
    const vd zero = vsplat(0.0);
    for (int j0 = 0; j0 < m; j0 += JB) {
        const double *f0 = w->F + j0 * kp, *f1 = f0 + kp, *f2 = f1 + kp, *f3 = f2 + kp;
        for (int b = 0; b < sp; b += L) {
            vd a0 = zero, a1 = zero, a2 = zero, a3 = zero;
            vd l0 = zero, l1 = zero, l2 = zero, l3 = zero;
            for (int i = 0; i < k; ++i) {
                const vd wt = vload(w->WT + i * sp + b), wt_lo = vload(w->WT_lo + i * sp + b);
                dot2_step(&a0, &l0, wt, wt_lo, f0[i]);
                dot2_step(&a1, &l1, wt, wt_lo, f1[i]);
                dot2_step(&a2, &l2, wt, wt_lo, f2[i]);
                dot2_step(&a3, &l3, wt, wt_lo, f3[i]);
            }
            const vd gs[JB] = {a0 + l0, a1 + l1, a2 + l2, a3 + l3};
            for (int r = 0; r < JB && j0 + r < m; ++r)
                vstore(w->g + (j0 + r) * sp + b, gs[r]);
        }
    }
}

/* g <- E gamma (core.guess): the previous polynomial over the new step, the sums over l in
 * order, outermost */
PIECE void guess(work_t *w, const double *E, const double *gamma)
{
    const int m = w->m, s = w->s, sp = w->sp;
    for (int l = 0; l < s; ++l)
        for (int i = 0; i < sp; ++i)
            w->ET[l * sp + i] = i < s ? E[i * s + l] : 0.0;
    const vd zero = vsplat(0.0);
    for (int a = 0; a < m * sp; a += L)
        vstore(w->g + a, zero);
    for (int l = 0; l < s; ++l)
        for (int j = 0; j < m; ++j) {
            const double c = gamma[l * m + j];
            for (int b = 0; b < sp; b += L)
                vstore(w->g + j * sp + b, vload(w->g + j * sp + b) + vload(w->ET + l * sp + b) * c);
        }
}

/* lip <- max(lip, max|F - Fp| / max|X - Xp|) when the stages moved by more than round-off, then
 * (X, F) kept in (Xp, Fp); returns max |X| in *xmax (core.lipschitz_probe) */
PIECE double lipschitz_probe(work_t *w, double lip, double *xmax_out)
{
    const int n = w->m * w->kp;
    const vd zero = vsplat(0.0);
    vd dx = zero, df = zero, xm = zero;
    for (int a = 0; a < n; a += L) {
        const vd x = vload(w->X + a), f = vload(w->F + a);
        dx = vmax(dx, vabs(x - vload(w->Xp + a)));
        xm = vmax(xm, vabs(x));
        df = vmax(df, vabs(f - vload(w->Fp + a)));
        vstore(w->Xp + a, x);
        vstore(w->Fp + a, f);
    }
    const double ddx = hmax(0.0, dx), ddf = hmax(0.0, df), xmax = hmax(0.0, xm);
    if (ddx > 1024.0 * EPS * xmax && ddf / ddx > lip)
        lip = ddf / ddx;
    *xmax_out = xmax;
    return lip;
}

/* max |F| over the n stage values at F (a multiple of L), nan when an entry is nan
 * (core.max_abs2) */
PIECE double max_abs_forces(const double *F, int n)
{
    vd v = vsplat(0.0);
    for (int a = 0; a < n; a += L)
        v = vmax_nan(v, vabs(vload(F + a)));
    return hmax_nan(0.0, v);
}

/* the stopping rule (core.stop_action) with its history hist (5) and the stage forces F (nF
 * values: the block's, or one follower's); returns ITERATE, POLISH or -status */
PIECE int stop_action(double *hist, const double *F, int nF, double delta, double scale,
                       double floor, double hstate, double hmove, double ymax, int it,
                       double tol)
{
    if (!isfinite(delta))
        return -HBVM_NOT_FINITE;
    if (it == 1)
        hist[4] = ymax + hmove;
    else if (hmove > RUNAWAY * hist[4])
        return -HBVM_DIVERGED;
    if (delta <= 2.0 * EPS * scale || delta <= tol * scale)
        return POLISH;
    if (tol > 0.0 && delta < hist[0]) {
        double theta = py_max(delta / hist[0], hist[2]);
        if (theta <= TOL_CONTRACTION && theta * delta <= (1.0 - theta) * tol * scale)
            return POLISH;
    }
    if (delta >= hist[0]) {
        if (delta <= ROUNDOFF_ULPS * EPS * py_max(scale, max_abs_forces(F, nF))
            || delta <= floor || hstate <= STATE_ULPS)
            return POLISH;
        hist[1] += 1.0;
        if (hist[1] >= 2.0)
            return -HBVM_DIVERGED;
    } else {
        double theta = py_max(hist[2], hist[3]);
        if (theta <= STRONG_CONTRACTION
            && theta * theta * hist[0] <= EXTRAPOLATED_ULPS * EPS * scale
            && (delta <= floor || hstate <= STATE_ULPS
                || delta <= ROUNDOFF_ULPS * EPS * py_max(scale, max_abs_forces(F, nF))))
            return POLISH;
    }
    hist[3] = hist[2];
    hist[2] = isfinite(hist[0]) ? delta / hist[0] : INFINITY;
    hist[0] = delta;
    return ITERATE;
}

/* y1 from the converged coefficients, added exactly to the double-double state
 * (core.commit_separable) */
PIECE void commit_separable(work_t *w, double *y, double *cy, const double *minv, double h,
                             const hbvm_tableau *tab)
{
    const int m = w->m, s = w->s, sp = w->sp;
    const double *g = w->g;
    for (int j = 0; j < m; ++j) {
        double xg = 0.0;
        for (int l = 0; l < s; ++l)
            xg += tab->X0[l] * g[j * sp + l] + tab->X0_lo[l] * g[j * sp + l];
        double v_hi, v_lo, a_hi, a_lo, i_hi, i_lo;
        two_product(y[m + j], minv[j], &v_hi, &v_lo);
        v_lo -= cy[m + j] * minv[j];
        two_product(h, v_hi, &a_hi, &a_lo);
        a_lo += h * v_lo;
        double b = h * (h * xg) * minv[j];
        two_sum(a_hi, b, &i_hi, &i_lo);
        w->dq[j] = i_hi;
        w->dq_lo[j] = a_lo + i_lo;
    }
    for (int j = 0; j < m; ++j)
        dd_add(y, cy, j, w->dq[j], w->dq_lo[j]);
    for (int j = 0; j < m; ++j) {
        double d_hi, d_lo;
        two_product(h, g[j * sp], &d_hi, &d_lo);
        dd_add(y, cy, m + j, d_hi, d_lo);
    }
}

/* the force at one point q (m,) into f (m,) (every lane the same point) */
PIECE int force_at_point(const hbvm_kernel *kernel, work_t *w, const double *q, double *f)
{
    const int m = w->m;
    for (int j = 0; j < m; ++j)
        for (int v = 0; v < L; ++v)
            w->X1[j * L + v] = q[j];
    if (kernel->force(kernel->ctx, w->X1, m, L, 1, kernel->params, w->F1) != 0)
        return -1;
    for (int j = 0; j < m; ++j)
        f[j] = w->F1[j * L];
    return 0;
}

/* max(|v0|, |v1|) + |h gamma_0 / m| over the coordinates j0 .. j1 - 1 (core.body_motion) */
static double body_motion(const double *y, const double *minv, const double *g, int gs,
                          double h, int m, int j0, int j1)
{
    double v0 = 0.0, v1 = 0.0, a0 = 0.0;
    for (int j = j0; j < j1; ++j) {
        double v = y[m + j] * minv[j];
        double dv = h * g[j * gs] * minv[j];
        v0 += v * v;
        v1 += (v + dv) * (v + dv);
        a0 += dv * dv;
    }
    return sqrt(v0 > v1 ? v0 : v1) + sqrt(a0);
}

/* the bodies' mean motion over the step (bodies of w coordinates; a last shorter one a body) */
static double mean_motion(const double *y, const double *minv, const double *g, int gs,
                          double h, int m, int w)
{
    double mean = 0.0;
    int nbody = 0;
    for (int j0 = 0; j0 < m; j0 += w) {
        mean += body_motion(y, minv, g, gs, h, m, j0, j0 + w < m ? j0 + w : m);
        nbody += 1;
    }
    return nbody > 0 ? mean / nbody : 0.0;
}

/* the step's own estimate of its relative local error (core.resolution_error, separable) */
PIECE double resolution_error(const double *y, const double *minv, const double *g, int gs,
                               const double *om, double h, int m, int s, int group, int *worst)
{
    const int wdt = group > 0 ? group : m;
    const double mean = mean_motion(y, minv, g, gs, h, m, wdt);
    double err = 0.0;
    int b = 0;
    *worst = -1;
    for (int j0 = 0; j0 < m; j0 += wdt) {
        const int j1 = j0 + wdt < m ? j0 + wdt : m;
        double num = 0.0;
        for (int j = j0; j < j1; ++j) {
            double x = h * om[j] * minv[j];
            num += x * x;
        }
        if (num > 0.0) {
            double den = py_max(body_motion(y, minv, g, gs, h, m, j0, j1), mean);
            double e = den > 0.0 ? sqrt(num) / den : INFINITY;
            if (e > err || *worst < 0) {
                err = e;
                *worst = b;
            }
        }
        b += 1;
    }
    return pow(err, (2.0 * s + 1.0) / (s + 1.0));
}

/* the energy the step moves between the terms of H (core.energy_flow, separable) */
PIECE double energy_flow(const double *y, const double *kin_w, double h, const double *g,
                          int gs, const hbvm_tableau *tab, int m)
{
    const int s = tab->s, n = tab->k;
    double flow = 0.0;
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < m; ++j) {
            double vel = 0.0, acc = 0.0;
            for (int l = 0; l < s; ++l) {
                vel += tab->I[i * s + l] * g[j * gs + l];
                acc += tab->W[l * n + i] * g[j * gs + l];
            }
            flow += fabs((y[m + j] + h * vel) * kin_w[j] * acc);
        }
    return fabs(h) * flow;
}

/* the energy check (integrators.loop.energy_check, separable); returns a status and the change */
PIECE int energy_check(const hbvm_kernel *kernel, const hbvm_system *sys, const double *y,
                        const double *yt, const hbvm_options *opts, double *eref, double h,
                        const double *g, int gs, const hbvm_tableau *tab, double *change_out)
{
    const int m = sys->m;
    const double etol = opts->etol;
    if (!isfinite(eref[0])) {
        double t0, v0;
        if (hbvm_energy_parts(kernel, sys, y, &t0, &v0) != 0)
            return HBVM_ABORTED;
        eref[0] = t0 + v0;
    }
    double t1, v1;
    if (hbvm_energy_parts(kernel, sys, yt, &t1, &v1) != 0)
        return HBVM_ABORTED;
    const double scale = fabs(t1) + fabs(v1);
    double change = fabs(t1 + v1 - eref[0]);
    if (scale > 0.0)
        change = change / scale;
    int refuse = !(change <= fabs(etol));
    if (refuse && etol < 0.0) {
        const int si = (tab->s < 3 ? tab->s : 3) - 1;
        const double moved = fabs(t1 + v1 - eref[0]) / FLOW_FRACTION[si];
        refuse = !((moved <= fabs(t1 - weighted_kinetic(y + m, sys->kin_w, m)))
                   || moved <= energy_flow(y, sys->kin_w, h, g, gs, tab, m));
    }
    if (refuse) {
        *change_out = change;
        return HBVM_UNRESOLVED;
    }
    if (etol < 0.0) {
        /* the run's energy against its start, on the run's kinetic scale
         * max(T1, <T> sqrt(<T> / Tmax)) (integrators.loop.energy_check, core.DRIFT_BOUND) */
        double *e = eref;
        if (!(isfinite(e[HBVM_EREF_RUN]) && isfinite(e[HBVM_EREF_TMEAN])
              && isfinite(e[HBVM_EREF_TIME]) && isfinite(e[HBVM_EREF_TMAX]))) {
            e[HBVM_EREF_RUN] = e[0];
            e[HBVM_EREF_TMEAN] = 0.0;
            e[HBVM_EREF_TIME] = 0.0;
            e[HBVM_EREF_TMAX] = 0.0;
        }
        const double run_time = e[HBVM_EREF_TIME] + fabs(h);
        const double tmean = e[HBVM_EREF_TMEAN]
                             + (fabs(t1) - e[HBVM_EREF_TMEAN]) * (fabs(h) / run_time);
        const double tmax = py_max(e[HBVM_EREF_TMAX], fabs(t1));
        double drift = fabs(t1 + v1 - e[HBVM_EREF_RUN]);
        double kscale = fabs(t1);
        if (tmax > 0.0)
            kscale = py_max(kscale, tmean * sqrt(tmean / tmax));
        if (kscale > 0.0)
            drift = drift / kscale;
        if (!(drift <= DRIFT_BOUND)) {
            *change_out = drift;
            return HBVM_DRIFTED;
        }
        e[HBVM_EREF_TMEAN] = tmean;
        e[HBVM_EREF_TIME] = run_time;
        e[HBVM_EREF_TMAX] = tmax;
        e[0] = t1 + v1;
        *change_out = drift;
        return HBVM_OK;
    }
    eref[0] = t1 + v1;
    *change_out = 0.0;
    return HBVM_OK;
}

/* the share of its motion the step's worst body turns over the step (core.run_error_share,
 * separable), for the run's accumulated estimate */
PIECE double run_error_share(const double *y, const double *minv, const double *g, int gs,
                             double h, double err, int worst, int m, int s, int group)
{
    if (!(err > 0.0))
        return 0.0;
    if (!(err < INFINITY))
        return 1.0;
    if (worst < 0)
        return py_min(1.0, pow(err, 1.0 / (2.0 * s + 1.0)));
    const int w = group > 0 ? group : m;
    const double mean = mean_motion(y, minv, g, gs, h, m, w);
    const int j0 = worst * w;
    if (j0 >= m)
        return 1.0;
    const int j1 = j0 + w < m ? j0 + w : m;
    double dv = 0.0;
    for (int j = j0; j < j1; ++j) {
        const double x = h * g[j * gs] * minv[j];
        dv += x * x;
    }
    const double den = py_max(body_motion(y, minv, g, gs, h, m, j0, j1), mean);
    return den > 0.0 ? py_min(1.0, sqrt(dv) / den) : 1.0;
}

static int all_zero(const double *a, int n)
{
    for (int i = 0; i < n; ++i)
        if (a[i] != 0.0)
            return 0;
    return 1;
}

static int fail(double *counters, int status, double it0, double nfev0, double newton0)
{
    counters[C_ITER] = it0;
    counters[C_NFEV] = nfev0;
    counters[C_NEWTON] = newton0;
    return status;
}

static int sample(const hbvm_kernel *kernel, const hbvm_system *sys, hbvm_samples *smp,
                  long i, double t, const double *y)
{
    double T, V;
    smp->t[i] = t;
    memcpy(smp->y + i * 2 * sys->m, y, 2 * sys->m * sizeof(double));
    if (hbvm_energy_parts(kernel, sys, y, &T, &V) != 0)
        return -1;
    smp->e[i] = T + V;
    return 0;
}

/* ---- the followers (integrators/followers.py): each follower's three coordinates are three
 * rows of the group's arrays, their kp stage values contiguous; a follower that has converged
 * stays where it is (its coefficients final) and leaves the list of those still iterating,
 * which keeps their order: the same numbers as the numba step's compaction, which moves the
 * others up (no follower's numbers depend on another's) ---- */

/* follower j's stage_base (the parts of its stages fixed for the step), from its state at
 * columns c0 .. c0 + 2 of the whole state */
PIECE void follower_base(const work_t *B, follow_t *f, int j, int c0, const double *y,
                          const double *cy, const double *minv, int m)
{
    const int kp = B->kp;
    for (int c = 0; c < 3; ++c) {
        const int col = c0 + c, r = 3 * j + c;
        const double yj = y[col], vj = y[m + col] * minv[col], cyj = cy[col];
        const double cpj = cy[m + col], mj = minv[col];
        for (int b = 0; b < kp; b += L) {
            const vd ht = vload(B->ht + b), ht_lo = vload(B->ht_lo + b);
            vstore(f->P0 + r * kp + b, yj + ht * vj);
            vstore(f->Q0 + r * kp + b, (ht_lo * vj - cyj) - ht * cpj * mj);
        }
    }
}

/* follower j's stage positions from its coefficients (stage_positions' operations, its three
 * coordinates' sums in registers); exact: with C2's low parts (the polish) */
PIECE void follower_stages(const work_t *B, follow_t *f, int j, double h2, double h2_lo,
                           int exact)
{
    const int s = B->s, kp = B->kp, sp = B->sp;
    double *a0 = f->a, *a1 = a0 + sp, *a2 = a1 + sp;
    for (int c = 0; c < 3; ++c) {
        const int r = 3 * j + c;
        for (int l = 0; l < s; ++l)
            f->a[c * sp + l] = f->g[r * sp + l] * f->mv[r];
    }
    const vd zero = vsplat(0.0);
    for (int b = 0; b < kp; b += L) {
        vd c0 = zero, c1 = zero, c2 = zero, d0 = zero, d1 = zero, d2 = zero;
        if (exact) {
            for (int l = 0; l < s; ++l) {
                const vd c = vload(B->C2T + l * kp + b), cl = vload(B->C2T_lo + l * kp + b);
                c0 += c * a0[l];
                c1 += c * a1[l];
                c2 += c * a2[l];
                d0 += cl * a0[l];
                d1 += cl * a1[l];
                d2 += cl * a2[l];
            }
        } else {
            for (int l = 0; l < s; ++l) {
                const vd c = vload(B->C2T + l * kp + b);
                c0 += c * a0[l];
                c1 += c * a1[l];
                c2 += c * a2[l];
            }
        }
        const vd cs[3] = {c0, c1, c2}, ds[3] = {d0, d1, d2};
        for (int c = 0; c < 3; ++c) {
            const int o = (3 * j + c) * kp + b;
            vstore(f->X + o, vload(f->P0 + o) + ((vload(f->Q0 + o) + h2 * (cs[c] + ds[c]))
                                                 + h2_lo * cs[c]));
        }
    }
}

/* core.lipschitz_slots for follower j: its estimate and max |X| updated, (X, F) kept */
PIECE void follower_lipschitz(follow_t *f, int j, int kp)
{
    const vd zero = vsplat(0.0);
    vd dx = zero, df = zero, xm = zero;
    for (int a = 3 * j * kp; a < 3 * (j + 1) * kp; a += L) {
        const vd x = vload(f->X + a), fv = vload(f->F + a);
        dx = vmax(dx, vabs(x - vload(f->Xp + a)));
        df = vmax(df, vabs(fv - vload(f->Fp + a)));
        xm = vmax(xm, vabs(x));
        vstore(f->Xp + a, x);
        vstore(f->Fp + a, fv);
    }
    const double ddx = hmax(0.0, dx), ddf = hmax(0.0, df), xmax = hmax(0.0, xm);
    if (ddx > 1024.0 * EPS * xmax && ddf / ddx > f->lip[j])
        f->lip[j] = ddf / ddx;
    f->xmax[j] = xmax;
}

/* follower j's g <- W F (core.project_each's sums; its three coordinates' chains of additions
 * together); its largest increment (nan first) and coefficient over the lanes l < s */
PIECE void follower_project(const work_t *B, follow_t *f, int j, double *delta_out,
                            double *scale_out)
{
    const int k = B->k, kp = B->kp, sp = B->sp;
    const vd zero = vsplat(0.0);
    vd dmax = zero, smax = zero;
    const double *f0 = f->F + 3 * j * kp, *f1 = f0 + kp, *f2 = f1 + kp;
    double *g0 = f->g + 3 * j * sp;
    for (int b = 0; b < sp; b += L) {
        vd a0 = zero, a1 = zero, a2 = zero;
        for (int i = 0; i < k; ++i) {
            const vd wt = vload(B->WT + i * sp + b);
            a0 += wt * f0[i];
            a1 += wt * f1[i];
            a2 += wt * f2[i];
        }
        const vl mask = (vl)vload(f->smask + b);
        const vd as[3] = {a0, a1, a2};
        for (int c = 0; c < 3; ++c) {
            double *old = g0 + c * sp + b;
            dmax = vmax_nan(dmax, (vd)((vl)vabs(as[c] - vload(old)) & mask));
            smax = vmax(smax, (vd)((vl)vabs(as[c]) & mask));
            vstore(old, as[c]);
        }
    }
    *delta_out = hmax_nan(0.0, dmax);
    *scale_out = hmax(0.0, smax);
}

/* follower j's g <- W F compensated (core.project_compensated's sums) */
PIECE void follower_project_compensated(const work_t *B, follow_t *f, int j)
{
    const int k = B->k, kp = B->kp, sp = B->sp;
    const vd zero = vsplat(0.0);
    const double *f0 = f->F + 3 * j * kp, *f1 = f0 + kp, *f2 = f1 + kp;
    double *g0 = f->g + 3 * j * sp;
    for (int b = 0; b < sp; b += L) {
        vd a0 = zero, a1 = zero, a2 = zero, l0 = zero, l1 = zero, l2 = zero;
        for (int i = 0; i < k; ++i) {
            const vd wt = vload(B->WT + i * sp + b), wt_lo = vload(B->WT_lo + i * sp + b);
            dot2_step(&a0, &l0, wt, wt_lo, f0[i]);
            dot2_step(&a1, &l1, wt, wt_lo, f1[i]);
            dot2_step(&a2, &l2, wt, wt_lo, f2[i]);
        }
        vstore(g0 + b, a0 + l0);
        vstore(g0 + sp + b, a1 + l1);
        vstore(g0 + 2 * sp + b, a2 + l2);
    }
}

/* The followers' stage equations after the sources' (integrators.followers.follow): in groups
 * of FOLLOWER_GROUP, each follower iterated in the sources' field at their stage values B->X
 * with its own stop rule until it converges, then the group's compensated polish; gw (m, sp):
 * the whole state's coefficients (the followers' rows hold their initial guess, overwritten
 * with the result).  Returns the status; *it_out the iterations of the slowest follower, the
 * polish included (of the failing group when one fails), *last_out the failing follower's
 * last increment (after max_iter: the largest of those still iterating), 0 when none. */
PIECE int follow(const hbvm_system *sys, const work_t *B, follow_t *f, const double *y,
                  const double *cy, const double *minv, double *gw, double h, double h2,
                  double h2_lo, const hbvm_options *opts, int *it_out, double *last_out)
{
    const int m = sys->m, k = B->k, kp = B->kp, sp = B->sp, P = f->P, nmax = f->nmax;
    int itmax = 0;
    for (int j0 = 0; j0 < P; j0 += nmax) {
        const int pc = nmax < P - j0 ? nmax : P - j0;
        for (int j = 0; j < pc; ++j) {
            const int c0 = (int)f->first[j0 + j];
            double ym = 0.0;
            for (int c = 0; c < 3; ++c) {
                const double q = fabs(y[c0 + c]), p = fabs(y[m + c0 + c]);
                if (q > ym)
                    ym = q;
                if (p > ym)
                    ym = p;
                f->mv[3 * j + c] = minv[c0 + c];
                memcpy(f->g + (3 * j + c) * sp, gw + (size_t)(c0 + c) * sp, sp * sizeof(double));
            }
            follower_base(B, f, j, c0, y, cy, minv, m);
            double *hist = f->hist + 5 * j;
            hist[0] = INFINITY;
            hist[1] = 0.0;
            hist[2] = INFINITY;
            hist[3] = INFINITY;
            hist[4] = 0.0;
            f->lip[j] = 0.0;
            f->xmax[j] = 0.0;
            f->ymax[j] = ym;
            f->active[j] = j;
        }
        int na = pc, it = 0;
        double worst = 0.0;       /* the largest increment of those still iterating */
        while (na > 0) {
            if (it >= opts->max_iter) {
                *it_out = it;
                *last_out = worst;
                return HBVM_DIVERGED;
            }
            it += 1;
            worst = 0.0;
            int nk = 0;
            for (int q = 0; q < na; ++q) {
                const int j = (int)f->active[q];
                double *Xj = f->X + 3 * j * kp, *Fj = f->F + 3 * j * kp;
                follower_stages(B, f, j, h2, h2_lo, 0);
                if (sys->field(Xj, 1, B->X, kp, k, f->own, Fj) != 0) {
                    *it_out = it;
                    *last_out = 0.0;
                    return HBVM_ABORTED;
                }
                if (it <= 3) {
                    if (it > 1) {
                        follower_lipschitz(f, j, kp);
                    } else {
                        memcpy(f->Xp + 3 * j * kp, Xj, 3 * (size_t)kp * sizeof(double));
                        memcpy(f->Fp + 3 * j * kp, Fj, 3 * (size_t)kp * sizeof(double));
                    }
                }
                double delta, scale;
                follower_project(B, f, j, &delta, &scale);
                const double ym = f->ymax[j];
                const double hstate = ym > 0.0 ? fabs(h) * delta / (EPS * ym) : INFINITY;
                const int action = stop_action(f->hist + 5 * j, Fj, 3 * kp, delta, scale,
                                               LIPSCHITZ_ULPS * EPS * f->xmax[j] * f->lip[j],
                                               hstate, fabs(h) * scale, ym, it, opts->tol);
                if (action == ITERATE) {
                    f->active[nk++] = j;
                    worst = py_max(worst, delta);
                } else if (action != POLISH) {
                    *it_out = it;
                    *last_out = delta;
                    return -action;
                }
            }
            na = nk;
        }
        if (it + 1 > itmax)
            itmax = it + 1;
        /* the polish, the group at once */
        for (int j = 0; j < pc; ++j) {
            const int c0 = (int)f->first[j0 + j];
            follower_stages(B, f, j, h2, h2_lo, 1);
            if (sys->field(f->X + 3 * j * kp, 1, B->X, kp, k, f->own, f->F + 3 * j * kp) != 0) {
                *it_out = it;
                *last_out = 0.0;
                return HBVM_ABORTED;
            }
            follower_project_compensated(B, f, j);
            memcpy(gw + (size_t)c0 * sp, f->g + 3 * j * sp, 3 * (size_t)sp * sizeof(double));
        }
    }
    *it_out = itmax;
    *last_out = 0.0;
    return HBVM_OK;
}

int hbvm_run(const hbvm_kernel *kernel, const hbvm_system *sys, hbvm_state *st, double h,
             const double *E, const hbvm_tableau *tab, const hbvm_options *opts,
             double *counters, hbvm_samples *smp, double *scratch, size_t nscratch)
{
    const int m = sys->m, d = 2 * m, k = tab->k, s = tab->s;
    const double *minv = sys->minv;
    double *y = st->y, *cy = st->cy, *gamma = st->gamma, *eref = st->eref;
    double t = st->clock[0], ct = st->clock[1];
    /* with followers (integrators.loop, "Followers"): the sources' stage equations are solved
     * as if alone, on their own copies (the block B, with the sources' own kernel parameters),
     * then each follower's in their field (follow); without, the block is the whole system */
    const double *blk = sys->follow != NULL && sys->field != NULL ? sys->follow : NULL;
    work_t w, wb;
    follow_t fo;
    if (work_alloc(&w, &wb, &fo, tab, m, blk, scratch, nscratch) != 0)
        return -1;
    work_t *B = blk ? &wb : &w;
    hbvm_kernel kb = *kernel;
    double *yb = y, *cyb = cy;
    const double *mb = minv;
    if (blk) {
        kb.params = fo.own;
        yb = fo.yb;
        cyb = fo.cyb;
        for (int c = 0; c < fo.us; ++c)
            fo.mb[c] = minv[(int)fo.cols[c]];
        mb = fo.mb;
    }
    const int mbk = B->m, sp = w.sp;
    double *g = w.g, *gb = B->g;
    long isample = 0;
    if (smp->every > 0) {
        if (sample(kernel, sys, smp, 0, t, y) != 0) {
            free(w.block);
            return HBVM_ABORTED;
        }
        isample = 1;
    }
    int result = HBVM_OK;
    for (long istep = 0; istep < smp->nsteps; ++istep) {
        const double it0 = counters[C_ITER], nfev0 = counters[C_NFEV];
        const double newton0 = counters[C_NEWTON];
        double h2, h2_lo;
        step_constants(B, tab, h, &h2, &h2_lo);
        if (blk)                 /* the sources' state (loop.gather_sources) */
            for (int c = 0; c < mbk; ++c) {
                const int col = (int)fo.cols[c];
                yb[c] = y[col];
                yb[mbk + c] = y[m + col];
                cyb[c] = cy[col];
                cyb[mbk + c] = cy[m + col];
            }
        stage_base(B, yb, cyb, mb);
        /* the first guess (of the whole state): the previous polynomial extrapolated, or the
         * force at y0 */
        if (all_zero(gamma, s * m)) {
            if (force_at_point(kernel, &w, y, w.dq) != 0) {
                result = fail(counters, HBVM_ABORTED, it0, nfev0, newton0);
                break;
            }
            for (int i = 0; i < sp; ++i)
                for (int j = 0; j < m; ++j)
                    g[j * sp + i] = i == 0 ? w.dq[j] : 0.0;
            counters[C_NFEV] += 1;
        } else {
            guess(&w, E, gamma);
        }
        if (blk)                 /* ... and the sources' part of it into their block */
            for (int c = 0; c < mbk; ++c)
                memcpy(gb + c * sp, g + (size_t)fo.cols[c] * sp, sp * sizeof(double));
        B->hist[0] = INFINITY;
        B->hist[1] = 0.0;
        B->hist[2] = INFINITY;
        B->hist[3] = INFINITY;
        double ymax = 0.0;
        for (int j = 0; j < 2 * mbk; ++j)
            if (fabs(yb[j]) > ymax)
                ymax = fabs(yb[j]);
        const double yscale = EPS * ymax;
        double lip = 0.0, xmax = 0.0;
        int polish = 0, status = HBVM_DIVERGED, it = 0;
        while (polish || it < opts->max_iter) {
            it += 1;
            stage_positions(B, mb, h2, h2_lo, polish);
            if (kb.force(kb.ctx, B->X, mbk, B->kp, k, kb.params, B->F) != 0) {
                status = HBVM_ABORTED;
                break;
            }
            counters[C_NFEV] += k;
            if (it <= 3) {
                if (it > 1) {
                    lip = lipschitz_probe(B, lip, &xmax);
                } else {
                    memcpy(B->Xp, B->X, (size_t)mbk * B->kp * sizeof(double));
                    memcpy(B->Fp, B->F, (size_t)mbk * B->kp * sizeof(double));
                }
            }
            if (polish) {
                project_compensated(B);
                status = HBVM_OK;
                break;
            }
            double delta, scale;
            project(B, &delta, &scale);
            counters[C_LAST] = delta;
            const double hstate = yscale > 0.0 ? fabs(h) * delta / yscale : INFINITY;
            const int action = stop_action(B->hist, B->F, mbk * B->kp, delta, scale,
                                           LIPSCHITZ_ULPS * EPS * xmax * lip, hstate,
                                           fabs(h) * scale, ymax, it, opts->tol);
            if (action == POLISH)
                polish = 1;
            else if (action != ITERATE) {
                status = -action;
                break;
            }
        }
        if (blk && status == HBVM_OK) {
            /* the sources' coefficients back into the whole state's, then the followers
             * (loop.solve_followers); the counts are the longest block's (the step's depth) */
            for (int c = 0; c < mbk; ++c)
                memcpy(g + (size_t)fo.cols[c] * sp, gb + c * sp, sp * sizeof(double));
            int itf;
            double dlast;
            status = follow(sys, B, &fo, y, cy, minv, g, h, h2, h2_lo, opts, &itf, &dlast);
            if (status != HBVM_OK)
                counters[C_LAST] = dlast;
            if (itf > it) {
                counters[C_NFEV] += (double)k * (itf - it);
                it = itf;
            }
        }
        counters[C_ITER] += it;
        counters[C_LASTIT] = it;
        if (status != HBVM_OK) {
            result = fail(counters, status, it0, nfev0, newton0);
            break;
        }
        memcpy(w.yt, y, d * sizeof(double));
        memcpy(w.cyt, cy, d * sizeof(double));
        commit_separable(&w, w.yt, w.cyt, minv, h, tab);
        int finite = 1;
        for (int j = 0; j < d; ++j)
            if (!isfinite(w.yt[j]))
                finite = 0;
        if (!finite) {
            result = fail(counters, HBVM_NOT_FINITE, it0, nfev0, newton0);
            break;
        }
        double err = 0.0, share = 0.0, drift = 0.0;
        if (opts->ebound > 0.0) {
            /* the first Legendre coefficient the step leaves out, of the block (the sources
             * with followers): from the stages (k > s), else from one evaluation at the
             * step's end (core.omitted_coefficient, endpoint_defect) */
            if (k > s) {
                for (int j = 0; j < mbk; ++j)
                    B->om[j] = 0.0;
                for (int i = 0; i < k; ++i) {
                    const double wi = B->pw[i];
                    for (int j = 0; j < mbk; ++j)
                        B->om[j] += wi * B->F[j * B->kp + i];
                }
            } else {
                for (int j = 0; j < mbk; ++j) {
                    const int col = blk ? (int)fo.cols[j] : j;
                    B->dq[j] = w.yt[col] - w.cyt[col];
                }
                if (force_at_point(&kb, B, B->dq, B->dq_lo) != 0) {
                    result = fail(counters, HBVM_ABORTED, it0, nfev0, newton0);
                    break;
                }
                const double r = 1.0 / sqrt(2.0 * s + 1.0);
                for (int j = 0; j < mbk; ++j) {
                    double acc = 0.0;
                    for (int l = 0; l < s; ++l)
                        acc += sqrt(2.0 * l + 1.0) * gb[j * sp + l];
                    B->om[j] = (B->dq_lo[j] - acc) * r;
                }
                counters[C_NFEV] += 1;
            }
            int worst;
            err = resolution_error(yb, mb, gb, sp, B->om, h, mbk, s, opts->group, &worst);
            share = run_error_share(yb, mb, gb, sp, h, err, worst, mbk, s, opts->group);
            if (blk && worst >= 0 && opts->group > 0)     /* (the whole state's body) */
                worst = (int)fo.cols[worst * opts->group] / opts->group;
            counters[C_ERR] = err;
            counters[C_WORST] = worst;
            if (!(err <= opts->ebound)) {
                result = fail(counters, HBVM_NOT_RESOLVED, it0, nfev0, newton0);
                break;
            }
        }
        if (opts->etol != 0.0) {
            double change = 0.0;
            const int checked = energy_check(kernel, sys, y, w.yt, opts, eref, h, g, sp, tab,
                                             &change);
            if (checked != HBVM_OK) {
                counters[C_CHANGE] = change;
                result = fail(counters, checked, it0, nfev0, newton0);
                break;
            }
            drift = change;
        }
        if (opts->ebound > 0.0)      /* (committed: the run's accumulated estimate) */
            counters[C_RUN_ERR] += (err + DRIFT_PHASE * drift) * share;
        memcpy(y, w.yt, d * sizeof(double));
        memcpy(cy, w.cyt, d * sizeof(double));
        for (int l = 0; l < s; ++l)
            for (int j = 0; j < m; ++j)
                gamma[l * m + j] = g[j * sp + l];
        counters[C_STEPS] += 1;
        const double yk = h - ct;
        const double tn = t + yk;
        ct = (tn - t) - yk;
        t = tn;
        st->clock[0] = t;
        st->clock[1] = ct;
        if (smp->every > 0 && (istep + 1) % smp->every == 0) {
            if (sample(kernel, sys, smp, isample, t, y) != 0) {
                result = HBVM_ABORTED;
                break;
            }
            isample += 1;
        }
    }
    free(w.block);
    return result;
}

/* E_ij = int_0^1 P_i(x) P_j(1 + r x) dx by the s-point Gauss rule (t, w) on [0, 1]
 * (core.extrapolation_matrix, operation for operation): the previous step's polynomial
 * continued over a step r times as long. E (s, s); c: scratch (4 s). */
void hbvm_extrapolation_matrix(double r, const double *t, const double *w, int s, double *E,
                               double *c)
{
    double *b0 = c, *b1 = c + s, *l0v = c + 2 * s, *l1v = c + 3 * s;
    for (int j = 0; j < s; ++j) {
        b0[j] = (2.0 * j + 1.0) / (j + 1.0);
        b1[j] = j / (j + 1.0);
    }
    for (int i = 0; i < s * s; ++i)
        E[i] = 0.0;
    for (int q = 0; q < s; ++q) {
        const double z0 = 2.0 * t[q] - 1.0;
        const double z1 = 2.0 * (1.0 + r * t[q]) - 1.0;
        double m0 = 0.0, l0 = 1.0, m1 = 0.0, l1 = 1.0;
        for (int j = 0; j < s; ++j) {
            l0v[j] = l0;
            l1v[j] = l1;
            const double n0 = b0[j] * z0 * l0 - b1[j] * m0;
            const double n1 = b0[j] * z1 * l1 - b1[j] * m1;
            m0 = l0;
            l0 = n0;
            m1 = l1;
            l1 = n1;
        }
        for (int i = 0; i < s; ++i) {
            const double wa = w[q] * l0v[i];
            for (int j = 0; j < s; ++j)
                E[i * s + j] += wa * l1v[j];
        }
    }
    for (int i = 0; i < s; ++i)
        l0v[i] = sqrt(2.0 * i + 1.0);
    for (int i = 0; i < s; ++i)
        for (int j = 0; j < s; ++j)
            E[i * s + j] *= l0v[i] * l0v[j];
}

/* ---- the one retry loop and its controller (integrators.loop.attempt, core.adapt_step) ---- */

static const double TINY_RATIO = HBVM_TINY_RATIO;
static const double MAX_EXTRAPOLATION = 4.0;    /* core.MAX_EXTRAPOLATION */
static const double FAILURE_SHRINK = 0.25;      /* core.FAILURE_SHRINK */

const double *hbvm_select_extrapolation(double h, double h_prev, const hbvm_extrapolation *ext,
                                        int s)
{
    if (isnan(h_prev) || h == h_prev)
        return ext->E1;
    double r = h / h_prev;
    if (fabs(r) > MAX_EXTRAPOLATION)
        return ext->zero;
    if (fabs(r) < TINY_RATIO)
        r = 0.0;
    double c[4 * 64];
    double *cc = s <= 64 ? c : malloc(4 * (size_t)s * sizeof(double));
    if (!cc)
        return NULL;
    hbvm_extrapolation_matrix(r, ext->t, ext->w, s, ext->buf, cc);
    if (cc != c)
        free(cc);
    return ext->buf;
}

/* c_j = int_0^1 P_j(x) x^j dx (core.monomial_weight) */
static double monomial_weight(int j)
{
    double c = 1.0;
    for (int i = 1; i <= j; ++i)
        c *= (double)(i * i) / ((2.0 * i) * (2.0 * i + 1.0));
    return c * sqrt(2.0 * j + 1.0);
}

/* core.sources_terms: (max |w gamma_{s-1}|, max |w gamma_0|) over the gravitating
 * coordinates (kin_w != 0) of gamma (s, m) row-major */
static void sources_terms(const double *gamma, int s, int m, const double *w,
                          const double *kin_w, double *top, double *low)
{
    const double *top_row = gamma + (size_t)(s - 1) * m;
    *top = 0.0;
    *low = 0.0;
    for (int j = 0; j < m; ++j)
        if (kin_w[j] != 0.0) {
            if (fabs(w[j] * top_row[j]) > *top)
                *top = fabs(w[j] * top_row[j]);
            if (fabs(w[j] * gamma[j]) > *low)
                *low = fabs(w[j] * gamma[j]);
        }
}

/* core.particle_terms: (max |gamma_{s-1}|, max |gamma_0|) over particle i's coordinates */
static void particle_terms(const double *gamma, int s, int m, int i, double *t, double *lo)
{
    const double *top_row = gamma + (size_t)(s - 1) * m;
    *t = 0.0;
    *lo = 0.0;
    for (int c = 3 * i; c < 3 * i + 3; ++c) {
        if (fabs(top_row[c]) > *t)
            *t = fabs(top_row[c]);
        if (fabs(gamma[c]) > *lo)
            *lo = fabs(gamma[c]);
    }
}

double hbvm_test_particle_control(const double *gamma, int s, int m, const double *w,
                                  const double *kin_w, double err_sources)
{
    if (s < 2)
        return err_sources;
    const double cw = monomial_weight(s - 1);
    double top, low;
    sources_terms(gamma, s, m, w, kin_w, &top, &low);
    if (!(low > 0.0 && top > 0.0))
        return err_sources;
    const double r = top / (cw * low);
    const double p = (2.0 * s + 1.0) / (s - 1.0);
    double out = err_sources;
    for (int i = 0; i < m / 3; ++i) {
        if (kin_w[3 * i] != 0.0)
            continue;
        double tt, lo;
        particle_terms(gamma, s, m, i, &tt, &lo);
        if (lo > 0.0) {
            const double e = err_sources * pow(tt / (cw * lo) / r, p);
            if (e > out)
                out = e;
        }
    }
    return out;
}

int hbvm_test_particle_error(const double *gamma, int s, int m, const double *w,
                             const double *kin_w, double floor, double factor,
                             double *worst_err)
{
    const double cw = monomial_weight(s - 1);
    double top, low;
    sources_terms(gamma, s, m, w, kin_w, &top, &low);
    double bound = floor;
    if (low > 0.0 && factor * top / (cw * low) > bound)
        bound = factor * top / (cw * low);
    int worst = -1;
    *worst_err = 0.0;
    for (int i = 0; i < m / 3; ++i) {
        if (kin_w[3 * i] != 0.0)
            continue;
        double t, lo;
        particle_terms(gamma, s, m, i, &t, &lo);
        const double err = lo > 0.0 ? t / (cw * lo) : (t > 0.0 ? INFINITY : 0.0);
        if (err > bound && err > *worst_err) {
            worst = i;
            *worst_err = err;
        }
    }
    return worst;
}

/* core.next_step: h (epsilon / err)^(1 / (2s + 1)) x 0.7, within [0.2 h, 2 h] */
static double next_step(double h, double err, double epsilon, int s)
{
    if (!(err > 0.0))
        return h * 2.0;
    const double f = 0.7 * pow(epsilon / err, 1.0 / (2.0 * s + 1.0));
    return h * py_min(2.0, py_max(0.2, f));
}

/* core.adapt_step: accept?, the next step to try, too small? */
static int adapt_step(double h, int status, double err, double epsilon, int s, double t,
                      double min_dt, double *h_new, int *too_small)
{
    if (status == HBVM_OK) {
        *h_new = next_step(h, err, epsilon, s);
        if (err <= epsilon) {
            *too_small = 0;
            return 1;
        }
    } else if (status == HBVM_NOT_RESOLVED && err > 0.0 && err < INFINITY) {
        *h_new = next_step(h, err, epsilon, s);
    } else {
        *h_new = FAILURE_SHRINK * h;
    }
    *too_small = fabs(*h_new) < min_dt || *h_new == 0.0 || t + *h_new == t;
    return 0;
}

int hbvm_attempt(const hbvm_kernel *kernel, const hbvm_system *sys, hbvm_state *state,
                 hbvm_state *trial, double h, double h_prev, double t_start,
                 const hbvm_extrapolation *ext, const hbvm_tableau *tab,
                 const hbvm_options *opts, double *counters, double epsilon, double min_dt,
                 double *res, double *scratch, size_t nscratch)
{
    const int m = sys->m, s = tab->s;
    double snap[N_COUNTERS];
    double *clock = state->clock;
    const double clock0 = clock[0], clock1 = clock[1];
    hbvm_options op = *opts;
    if (epsilon > 0.0 && !(op.ebound > 0.0))
        op.ebound = INFINITY;    /* (the controller reads the estimate: computed, never refused) */
    hbvm_samples one = {.nsteps = 1, .every = 0, .t = NULL, .y = NULL, .e = NULL};
    for (;;) {
        memcpy(trial->y, state->y, 2 * (size_t)m * sizeof(double));
        memcpy(trial->cy, state->cy, 2 * (size_t)m * sizeof(double));
        memcpy(trial->gamma, state->gamma, (size_t)s * m * sizeof(double));
        memcpy(trial->eref, state->eref, HBVM_N_EREF * sizeof(double));
        clock[0] = clock0;
        clock[1] = clock1;
        memcpy(snap, counters, sizeof snap);
        const double *E = hbvm_select_extrapolation(h, h_prev, ext, s);
        if (!E)
            return -1;
        hbvm_state tr = *trial;
        tr.clock = clock;
        const int status = hbvm_run(kernel, sys, &tr, h, E, tab, &op, counters, &one, scratch,
                                    nscratch);
        if (status < 0 || status == HBVM_ABORTED)
            return status;
        res[0] = h;
        res[1] = h;
        if (epsilon <= 0.0 || status == HBVM_DRIFTED)   /* (no shorter step undoes the past) */
            return status;
        double err = (status == HBVM_OK || status == HBVM_NOT_RESOLVED) ? counters[C_ERR] : NAN;
        if (sys->follow != NULL && sys->field != NULL && status == HBVM_OK)
            /* (the test particles, solved apart: core.test_particle_control) */
            err = hbvm_test_particle_control(trial->gamma, s, m, sys->minv, sys->kin_w, err);
        double h_new;
        int too_small;
        if (adapt_step(h, status, err, epsilon, s, t_start, min_dt, &h_new, &too_small)) {
            res[1] = h_new;
            return HBVM_OK;
        }
        if (status == HBVM_OK)
            memcpy(counters, snap, sizeof snap);         /* a rejected step leaves no trace */
        res[3] = err;
        res[4] = status;
        res[2] += 1.0;
        if (too_small)
            return HBVM_TOO_SMALL;
        h = h_new;
    }
}
