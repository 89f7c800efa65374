/* Newtonian N-body gravity, all stages at once (systems/nbody.py: the parameters
 * [G, N, w_0 .. w_{N-1}, g_0 .. g_{N-1}, f_0 .. f_N], w_i the mass in M, g_i the gravitating
 * mass, f_i the first source at or after i).
 *
 * For each pair of sources the kp stages of the separation go through the lanes together:
 * packed subtractions, square roots and divisions (the build's -fno-math-errno lets sqrt
 * vectorise). Each stage receives the operations of systems.nbody.nbody_forces on that row, in
 * the same order: the same numbers bit for bit. */
#include <math.h>

#include "hbvm_core.h"
#include "hbvm_vec.h"

#define L HBVM_LANES

int hbvm_nbody_check(int m, const double *params, long nparams)
{
    if (nparams < 3)
        return -1;
    double Nd = params[1];
    if (!(Nd >= 0) || Nd != (double)(long)Nd)
        return -1;
    long N = (long)Nd;
    if (3 * N != m || nparams < 3 * N + 3)
        return -1;
    return 0;
}

void hbvm_nbody_force(const double *restrict X, int m, int kp, const double *restrict params,
                      double *restrict F)
{
    const double G = params[0];
    const int N = (int)params[1];
    const double *w = params + 2, *gm = params + 2 + N, *next = params + 2 + 2 * N;
    const int first = (int)next[0];
    const vd vG = vsplat(G), zero = vsplat(0.0);
    for (int a = 0; a < m * kp; a += L)
        vstore(F + a, zero);
    for (int b = 0; b < kp; b += L) {
        for (int i = 0; i < N; ++i) {
            const double gi = gm[i];
            if (gi == 0.0)
                continue;
            const double wi = w[i];
            const double *xi = X + 3 * i * kp + b;
            double *fi = F + 3 * i * kp + b;
            const vd xi0 = vload(xi), xi1 = vload(xi + kp), xi2 = vload(xi + 2 * kp);
            vd fx = vload(fi), fy = vload(fi + kp), fz = vload(fi + 2 * kp);
            for (int j = i + 1; j < N; ++j) {
                const double gj = gm[j];
                if (gj == 0.0)
                    continue;
                const vd wg = vsplat(wi * gj), gw = vsplat(w[j] * gi);
                const double *xj = X + 3 * j * kp + b;
                double *fj = F + 3 * j * kp + b;
                const vd dx = vload(xj) - xi0;
                const vd dy = vload(xj + kp) - xi1;
                const vd dz = vload(xj + 2 * kp) - xi2;
                const vd s2 = dx * dx + dy * dy + dz * dz;
                const vd inv = vG / (s2 * vsqrt(s2));
                const vd ci = wg * inv, cj = gw * inv;
                fx += ci * dx;
                fy += ci * dy;
                fz += ci * dz;
                vstore(fj, vload(fj) - cj * dx);
                vstore(fj + kp, vload(fj + kp) - cj * dy);
                vstore(fj + 2 * kp, vload(fj + 2 * kp) - cj * dz);
            }
            vstore(fi, fx);
            vstore(fi + kp, fy);
            vstore(fi + 2 * kp, fz);
        }
        /* each test particle from every source, summed in registers (nbody_forces' order) */
        for (int t = 0; t < N; ++t) {
            if (gm[t] != 0.0)
                continue;
            const vd wt = vsplat(w[t]);
            const double *xt = X + 3 * t * kp + b;
            const vd xt0 = vload(xt), xt1 = vload(xt + kp), xt2 = vload(xt + 2 * kp);
            vd fx = zero, fy = zero, fz = zero;
            for (int k = first; k < N; k = (int)next[k + 1]) {
                const vd wg = wt * vsplat(gm[k]);
                const double *xk = X + 3 * k * kp + b;
                const vd dx = vload(xk) - xt0;
                const vd dy = vload(xk + kp) - xt1;
                const vd dz = vload(xk + 2 * kp) - xt2;
                const vd s2 = dx * dx + dy * dy + dz * dz;
                const vd c = wg * (vG / (s2 * vsqrt(s2)));
                fx += c * dx;
                fy += c * dy;
                fz += c * dz;
            }
            vstore(F + 3 * t * kp + b, fx);
            vstore(F + (3 * t + 1) * kp + b, fy);
            vstore(F + (3 * t + 2) * kp + b, fz);
        }
    }
}

double hbvm_nbody_potential(const double *q, const double *params)
{
    const double G = params[0];
    const int N = (int)params[1];
    const double *gm = params + 2 + N, *next = params + 2 + 2 * N;
    double v = 0.0;
    for (int i = (int)next[0]; i < N; i = (int)next[i + 1]) {
        const double gi = gm[i];
        for (int j = (int)next[i + 1]; j < N; j = (int)next[j + 1]) {
            const double gj = gm[j];
            const double dx = q[3 * j] - q[3 * i];
            const double dy = q[3 * j + 1] - q[3 * i + 1];
            const double dz = q[3 * j + 2] - q[3 * i + 2];
            v -= gi * gj / sqrt(dx * dx + dy * dy + dz * dz);
        }
    }
    return G * v;
}

int hbvm_nbody_force_k(void *ctx, const double *X, int m, int kp, int n, const double *params,
                       double *F)
{
    (void)ctx, (void)n;
    hbvm_nbody_force(X, m, kp, params, F);
    return 0;
}

int hbvm_nbody_potential_k(void *ctx, const double *q, const double *params, double *V)
{
    (void)ctx;
    *V = hbvm_nbody_potential(q, params);
    return 0;
}

/* The accelerations of nt test particles from the sources (systems.nbody.nbody_field): Xt
 * (3 nt, kp) the particles' stages, Xs (3 Ns, kp) the sources', F (3 nt, kp), all
 * stage-fastest; n stages, lanes n .. kp - 1 repeating stage n - 1; params the sources' own
 * kernel parameters [G, Ns, w, g, f].  Each particle sums over its sources in their order,
 * c = g_k (G / (d2 sqrt(d2))) on each stage, as nbody_field does on each row: the same numbers
 * bit for bit.  (A particle's three sums start from zero where nbody_field starts from its
 * stored zero: the same additions.)  The square roots and divisions are the kernel's cost: a
 * last vector holding at most half a vector of stages (HBVM(9, 8)'s ninth stage in a second
 * vector of 8) computes them in half a vector, or one stage at a time, and copies the last
 * stage into the padded lanes (a packed square root or division of half the width, or a scalar
 * one, takes half the time or less of a full one; the same operations on each stage). */
#if HBVM_LANES == 8 && defined(__AVX512F__)
typedef double vdh __attribute__((vector_size(4 * HBVM_LANES)));
static inline vdh vhsqrt(vdh x) { return (vdh)_mm256_sqrt_pd((__m256d)x); }
#define HAVE_HALF 1
#elif HBVM_LANES == 4 && defined(__AVX__)
typedef double vdh __attribute__((vector_size(4 * HBVM_LANES)));
static inline vdh vhsqrt(vdh x) { return (vdh)_mm_sqrt_pd((__m128d)x); }
#define HAVE_HALF 1
#else
#define HAVE_HALF 0
#endif

/* the followers' field for the stages b .. b + width of the test particle at xt (3 rows of
 * kp), from Ns sources at Xs, in vectors of type V (the full lanes, or half of them for a last
 * vector at most half full): the same operations at every width */
#define FIELD(NAME, V, LOAD, STORE, SPLAT, SQRT)                                                \
    static inline void NAME(const double *xt, const double *Xs, int kp, int b, int Ns,         \
                            const double *gm, double G, double *ft)                            \
    {                                                                                          \
        const V vG = SPLAT(G), zero = SPLAT(0.0);                                              \
        const V x0 = LOAD(xt + b), x1 = LOAD(xt + kp + b), x2 = LOAD(xt + 2 * kp + b);         \
        V fx = zero, fy = zero, fz = zero;                                                     \
        for (int k = 0; k < Ns; ++k) {                                                         \
            const double *xs = Xs + 3 * k * kp + b;                                            \
            const V dx = LOAD(xs) - x0;                                                        \
            const V dy = LOAD(xs + kp) - x1;                                                   \
            const V dz = LOAD(xs + 2 * kp) - x2;                                               \
            const V d2 = dx * dx + dy * dy + dz * dz;                                          \
            const V c = SPLAT(gm[k]) * (vG / (d2 * SQRT(d2)));                                 \
            fx += c * dx;                                                                      \
            fy += c * dy;                                                                      \
            fz += c * dz;                                                                      \
        }                                                                                      \
        STORE(ft + b, fx);                                                                     \
        STORE(ft + kp + b, fy);                                                                \
        STORE(ft + 2 * kp + b, fz);                                                            \
    }

FIELD(field_full, vd, vload, vstore, vsplat, vsqrt)

#if HAVE_HALF
static inline vdh hload(const double *p)
{
    return *(const vdh *)__builtin_assume_aligned(p, 4 * L);
}
static inline void hstore(double *p, vdh v) { *(vdh *)__builtin_assume_aligned(p, 4 * L) = v; }
static inline vdh hsplat(double x)
{
    vdh v;
    for (int i = 0; i < L / 2; ++i)
        v[i] = x;
    return v;
}

FIELD(field_half, vdh, hload, hstore, hsplat, vhsqrt)
#endif

static inline void field_scalar(const double *xt, const double *Xs, int kp, int i, int Ns,
                                const double *gm, double G, double *ft)
{
    const double x0 = xt[i], x1 = xt[kp + i], x2 = xt[2 * kp + i];
    double fx = 0.0, fy = 0.0, fz = 0.0;
    for (int k = 0; k < Ns; ++k) {
        const double *xs = Xs + 3 * k * kp + i;
        const double dx = xs[0] - x0;
        const double dy = xs[kp] - x1;
        const double dz = xs[2 * kp] - x2;
        const double d2 = dx * dx + dy * dy + dz * dz;
        const double c = gm[k] * (G / (d2 * sqrt(d2)));
        fx += c * dx;
        fy += c * dy;
        fz += c * dz;
    }
    ft[i] = fx;
    ft[kp + i] = fy;
    ft[2 * kp + i] = fz;
}

int hbvm_nbody_field(const double *restrict Xt, int nt, const double *restrict Xs, int kp,
                     int n, const double *restrict params, double *restrict F)
{
    const double G = params[0];
    const int Ns = (int)params[1];
    const double *gm = params + 2 + Ns;
    if (n < 1 || n > kp)
        n = kp;
    /* the last vector's stages, and the lanes computed of it (the rest copy stage n - 1) */
    const int b_last = (n - 1) / L * L, r = n - b_last;
    for (int t = 0; t < nt; ++t) {
        const double *xt = Xt + 3 * t * kp;
        double *ft = F + 3 * t * kp;
        for (int b = 0; b < b_last; b += L)
            field_full(xt, Xs, kp, b, Ns, gm, G, ft);
        int done;
        if (2 * r > L) {
            field_full(xt, Xs, kp, b_last, Ns, gm, G, ft);
            done = L;
        } else if (HAVE_HALF && 4 * r > L) {
#if HAVE_HALF
            field_half(xt, Xs, kp, b_last, Ns, gm, G, ft);
#endif
            done = L / 2;
        } else {
            for (int i = b_last; i < n; ++i)
                field_scalar(xt, Xs, kp, i, Ns, gm, G, ft);
            done = r;
        }
        for (int c = 0; c < 3; ++c)
            for (int i = b_last + done; i < b_last + L; ++i)
                ft[c * kp + i] = ft[c * kp + n - 1];
    }
    return 0;
}
