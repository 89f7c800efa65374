/* The lanes: a vector of HBVM_LANES doubles (GCC's and Clang's vector extensions), with the few
 * operations the language leaves out (sqrt, fma) from the instruction set the build targets. */
#ifndef HBVM_VEC_H
#define HBVM_VEC_H

#include <math.h>

#include "hbvm_core.h"

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#endif

typedef double vd __attribute__((vector_size(8 * HBVM_LANES)));

static inline vd vload(const double *p) { return *(const vd *)__builtin_assume_aligned(p, 8 * HBVM_LANES); }
static inline void vstore(double *p, vd v) { *(vd *)__builtin_assume_aligned(p, 8 * HBVM_LANES) = v; }
static inline vd vsplat(double x)
{
#if HBVM_LANES == 8 && defined(__AVX512F__)
    return (vd)_mm512_set1_pd(x);
#elif HBVM_LANES == 4 && defined(__AVX__)
    return (vd)_mm256_set1_pd(x);
#elif HBVM_LANES == 2 && defined(__SSE2__)
    return (vd)_mm_set1_pd(x);
#else
    vd v;
    for (int i = 0; i < HBVM_LANES; ++i)
        v[i] = x;
    return v;
#endif
}

/* correctly rounded square roots, lane by lane */
static inline vd vsqrt(vd x)
{
#if HBVM_LANES == 8 && defined(__AVX512F__)
    return (vd)_mm512_sqrt_pd((__m512d)x);
#elif HBVM_LANES == 4 && defined(__AVX__)
    return (vd)_mm256_sqrt_pd((__m256d)x);
#elif HBVM_LANES == 2 && defined(__SSE2__)
    return (vd)_mm_sqrt_pd((__m128d)x);
#else
    vd r;
    for (int i = 0; i < HBVM_LANES; ++i)
        r[i] = sqrt(x[i]);
    return r;
#endif
}

/* a b + c rounded once, lane by lane */
static inline vd vfma(vd a, vd b, vd c)
{
#if HBVM_LANES == 8 && defined(__AVX512F__)
    return (vd)_mm512_fmadd_pd((__m512d)a, (__m512d)b, (__m512d)c);
#elif HBVM_LANES == 4 && defined(__FMA__)
    return (vd)_mm256_fmadd_pd((__m256d)a, (__m256d)b, (__m256d)c);
#elif HBVM_LANES == 2 && defined(__FMA__)
    return (vd)_mm_fmadd_pd((__m128d)a, (__m128d)b, (__m128d)c);
#else
    vd r;
    for (int i = 0; i < HBVM_LANES; ++i)
        r[i] = fma(a[i], b[i], c[i]);
    return r;
#endif
}

typedef long long vl __attribute__((vector_size(8 * HBVM_LANES)));

static inline vd vabs(vd x) { return (vd)((vl)x & ~(vl)vsplat(-0.0)); }

/* lane by lane b > a ? b : a (Python's max(a, b): a nan b is not taken) */
static inline vd vmax(vd a, vd b)
{
    vl mask = b > a;
    return (vd)(((vl)b & mask) | ((vl)a & ~mask));
}

/* lane by lane (b > a or b is nan) ? b : a: a nan, once taken, stays */
static inline vd vmax_nan(vd a, vd b)
{
    vl mask = (b > a) | (b != b);
    return (vd)(((vl)b & mask) | ((vl)a & ~mask));
}

/* the lanes' maximum with the same rule, lane 0 first (as the scalar loop over the stages) */
static inline double hmax(double acc, vd v)
{
    for (int i = 0; i < HBVM_LANES; ++i)
        if (v[i] > acc)
            acc = v[i];
    return acc;
}

static inline double hmax_nan(double acc, vd v)
{
    for (int i = 0; i < HBVM_LANES; ++i)
        if (v[i] > acc || v[i] != v[i])
            acc = v[i];
    return acc;
}

#endif
