/* The small built-in systems' kernels, all stages at once (systems/kepler.py, henon_heiles.py,
 * fpu.py, pendulum.py): each lane receives the operations of the numba kernel's row, in the
 * same order (the same numbers bit for bit). */
#include <math.h>

#include "hbvm_core.h"

/* Kepler in the plane: F = -mu q / |q|^3 (params [mu]) */
static int kepler_force(void *ctx, const double *X, int m, int kp, int n, const double *p,
                        double *F)
{
    (void)ctx, (void)m, (void)n;
    const double mu = p[0];
    for (int i = 0; i < kp; ++i) {
        const double x = X[i], y = X[kp + i];
        const double r2 = x * x + y * y;
        const double f = -mu / (r2 * sqrt(r2));
        F[i] = f * x;
        F[kp + i] = f * y;
    }
    return 0;
}

static int kepler_potential(void *ctx, const double *q, const double *p, double *V)
{
    (void)ctx;
    *V = -p[0] / sqrt(q[0] * q[0] + q[1] * q[1]);
    return 0;
}

/* Henon-Heiles */
static int hh_force(void *ctx, const double *X, int m, int kp, int n, const double *p,
                    double *F)
{
    (void)ctx, (void)m, (void)n, (void)p;
    for (int i = 0; i < kp; ++i) {
        const double x = X[i], y = X[kp + i];
        F[i] = -x - 2.0 * x * y;
        F[kp + i] = -y - x * x + y * y;
    }
    return 0;
}

static int hh_potential(void *ctx, const double *q, const double *p, double *V)
{
    (void)ctx, (void)p;
    const double x = q[0], y = q[1];
    *V = 0.5 * (x * x + y * y) + x * x * y - y * y * y / 3.0;
    return 0;
}

/* Fermi-Pasta-Ulam: soft cubic-force springs between q_{2i} and q_{2i+1}, walls, stiff linear
 * springs between q_{2i-1} and q_{2i} (params [omega]) */
static int fpu_force(void *ctx, const double *X, int m, int kp, int n, const double *p,
                     double *F)
{
    (void)ctx, (void)n;
    const double w2 = p[0] * p[0];
    for (int a = 0; a < m * kp; ++a)
        F[a] = 0.0;
    for (int i = 0; i < m / 2 + 1; ++i)
        for (int r = 0; r < kp; ++r) {
            const double left = i > 0 ? X[(2 * i - 1) * kp + r] : 0.0;
            const double right = 2 * i < m ? X[2 * i * kp + r] : 0.0;
            const double d = right - left;
            const double f = 4.0 * d * d * d;
            if (i > 0)
                F[(2 * i - 1) * kp + r] += f;
            if (2 * i < m)
                F[2 * i * kp + r] -= f;
        }
    for (int i = 0; i < m / 2; ++i)
        for (int r = 0; r < kp; ++r) {
            const double d = X[(2 * i + 1) * kp + r] - X[2 * i * kp + r];
            const double f = 0.5 * w2 * d;
            F[2 * i * kp + r] += f;
            F[(2 * i + 1) * kp + r] -= f;
        }
    return 0;
}

/* the FPU potential needs m: the core passes it through the kernel's context */
static int fpu_potential(void *ctx, const double *q, const double *p, double *V)
{
    const int m = *(const int *)ctx;
    const double w2 = p[0] * p[0];
    double v = 0.0;
    for (int i = 0; i < m / 2; ++i) {
        const double d = q[2 * i + 1] - q[2 * i];
        v += 0.25 * w2 * d * d;
    }
    for (int i = 0; i < m / 2 + 1; ++i) {
        const double left = i > 0 ? q[2 * i - 1] : 0.0;
        const double right = 2 * i < m ? q[2 * i] : 0.0;
        const double d = right - left;
        v += d * d * d * d;
    }
    *V = v;
    return 0;
}

/* the pendulum: F = -omega0^2 sin q (params [omega0^2]) */
static int pendulum_force(void *ctx, const double *X, int m, int kp, int n, const double *p,
                          double *F)
{
    (void)ctx, (void)m, (void)n;
    for (int i = 0; i < kp; ++i)
        F[i] = -p[0] * sin(X[i]);
    return 0;
}

static int pendulum_potential(void *ctx, const double *q, const double *p, double *V)
{
    (void)ctx;
    *V = -p[0] * cos(q[0]);
    return 0;
}

/* the Morse oscillator (params [D, a]) */
static int morse_force(void *ctx, const double *X, int m, int kp, int n, const double *p,
                       double *F)
{
    (void)ctx, (void)m, (void)n;
    const double D = p[0], a = p[1];
    for (int i = 0; i < kp; ++i) {
        const double e = exp(-a * X[i]);
        F[i] = -2.0 * D * a * (e - e * e);
    }
    return 0;
}

static int morse_potential(void *ctx, const double *q, const double *p, double *V)
{
    (void)ctx;
    const double e = 1.0 - exp(-p[1] * q[0]);
    *V = p[0] * e * e;
    return 0;
}

/* the table the Python face reads: name, force, potential, coordinates (0: any), parameters */
const hbvm_builtin hbvm_builtins[] = {
    {"kepler", kepler_force, kepler_potential, 2, 1},
    {"henon_heiles", hh_force, hh_potential, 2, 0},
    {"fpu", fpu_force, fpu_potential, 0, 1},
    {"pendulum", pendulum_force, pendulum_potential, 1, 1},
    {"morse", morse_force, morse_potential, 1, 2},
    {0, 0, 0, 0, 0}};
