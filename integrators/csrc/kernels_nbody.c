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
