/* The compiled core of hbvm-md: one HBVM(k, s) step of the separable form, its kernels and its
 * control, built when the package is installed (setup.py).
 *
 * The stage index runs fastest everywhere in the step ("the stages in the lanes"): a stage
 * array X (m, kp) holds coordinate j's kp stage values at X[j * kp + i], kp being k padded up
 * to a multiple of HBVM_LANES with copies of the last stage, so that one vector register holds
 * HBVM_LANES stages of one coordinate, the kernel evaluates every stage at once on those
 * vectors, and the stage algebra runs on the same vectors.  Each stage's numbers are those of
 * a scalar loop (the same operations in the same order; no fused multiply-add where the
 * Python-side step has none: the build passes -ffp-contract=off).
 *
 * The implementer's contract of a kernel (docs/design/step.md, "The compiled core"):
 *   force(ctx, X, m, kp, n, params, F): F (m, kp) <- -grad V at each of the kp stages of
 *       X (m, kp), stage-fastest, every lane written (lanes n .. kp - 1 repeat stage n - 1:
 *       a kernel may compute them or copy lane n - 1); returns 0, or nonzero to abort the step
 *       (a Python kernel that raised);
 *   potential(ctx, q, params, V): *V <- V(q) at one point q (m,); returns 0 or nonzero.
 */
#ifndef HBVM_CORE_H
#define HBVM_CORE_H

#include <stddef.h>

#if defined(HBVM_LANES)
/* set by the build */
#elif defined(__AVX512F__)
#define HBVM_LANES 8
#elif defined(__AVX__)
#define HBVM_LANES 4
#else
#define HBVM_LANES 2
#endif

/* status codes: the same table as integrators.core (one map to exceptions there) */
enum {
    HBVM_OK = 0,
    HBVM_DIVERGED = 1,
    HBVM_NOT_FINITE = 2,
    HBVM_UNRESOLVED = 3,
    HBVM_TOO_SMALL = 4,
    HBVM_NOT_RESOLVED = 6,
    HBVM_DRIFTED = 7,
    HBVM_ABORTED = 101   /* a kernel asked to stop (a Python kernel raised): nothing committed */
};

/* counters: integrators.core's layout */
enum { C_STEPS, C_ITER, C_NFEV, C_LAST, C_NEWTON, C_CHANGE, C_LASTIT, C_ERR, C_WORST,
       C_RUN_ERR, N_COUNTERS };

/* eref: integrators.core's layout (the energy, EQUIP's two, the run's start, T's time mean over
 * the run, the run's time, T's largest) */
#define HBVM_EREF_RUN 3
#define HBVM_EREF_TMEAN 4
#define HBVM_EREF_TIME 5
#define HBVM_EREF_TMAX 6
#define HBVM_N_EREF 7

/* core.ERROR_BOUND (the step's own error estimate's bound, on with the energy check) and
 * core.TINY_RATIO (a step this much shorter than the previous one is a sliver) */
#define HBVM_ERROR_BOUND 1e-3
#define HBVM_TINY_RATIO 1e-3

typedef int (*hbvm_force_fn)(void *ctx, const double *X, int m, int kp, int n,
                             const double *params, double *F);
typedef int (*hbvm_potential_fn)(void *ctx, const double *q, const double *params, double *V);

/* a system's kernels and their parameters */
typedef struct {
    hbvm_force_fn force;
    hbvm_potential_fn potential;
    const double *params;
    void *ctx;
} hbvm_kernel;

/* the method's arrays at their natural (row-major) shapes, as integrators.engine packs them */
typedef struct {
    int k, s;
    const double *tau, *tau_lo;         /* (k,) the nodes on [0, 1] */
    const double *X0, *X0_lo;           /* (s,) the first row of X_s */
    const double *W, *W_lo;             /* (s, k) P_s^T Omega */
    const double *C2, *C2_lo;           /* (k, s) I_s X_s */
    const double *I, *I_lo;             /* (k, s) I_s */
} hbvm_tableau;

/* the followers' field kernel: F (3 nt, kp) <- the accelerations of nt test particles at
 * their stages Xt (3 nt, kp) from the sources at theirs, Xs (us, kp), both stage-fastest, with
 * the sources' own parameters (systems.nbody.nbody_field's operations on each stage; lanes
 * n .. kp - 1 repeat stage n - 1); returns 0 */
typedef int (*hbvm_field_fn)(const double *Xt, int nt, const double *Xs, int kp, int n,
                             const double *params, double *F);

/* the separable system: m positions, 1 / m per coordinate and the kinetic energy's weights;
 * with followers (test particles solved after the sources: integrators/followers.py), `follow`
 * points at the followers block of the kernel's parameters (systems.nbody.followers_block:
 * [P, 3, us, np, the sources' columns (us), each follower's first column (P), the sources' own
 * kernel parameters (np)]) and `field` is their field kernel; follow NULL: none (the fields
 * a host leaves out of its initialiser are zero) */
typedef struct {
    int m;
    const double *minv, *kin_w;
    const double *follow;
    hbvm_field_fn field;
} hbvm_system;

/* the state a step reads and commits: the double-double pair (y, cy) (2m,), the previous step's
 * coefficients gamma (s, m), the energies eref (HBVM_N_EREF,) and the compensated clock (2,) */
typedef struct {
    double *y, *cy, *gamma, *eref, *clock;
} hbvm_state;

typedef struct {
    int max_iter;
    double tol, etol, ebound;
    int group;
} hbvm_options;

/* samples of (t, y, H) at steps 0, every, 2 every, ... (every = 0: none) */
typedef struct {
    long nsteps, every;
    double *t, *y, *e;
} hbvm_samples;

/* nsteps steps of size h, each committed when it succeeds; returns HBVM_OK or the first failed
 * step's status, everything as after the last committed step (integrators.loop.run's
 * contract). E (s, s): the initial guess's extrapolation matrix. */
int hbvm_run(const hbvm_kernel *kernel, const hbvm_system *sys, hbvm_state *st, double h,
             const double *E, const hbvm_tableau *tab, const hbvm_options *opts,
             double *counters, hbvm_samples *samples, double *scratch, size_t nscratch);

/* the scratch hbvm_run works in (doubles) for k stages, s coefficients, m coordinates: handed
 * over zeroed and kept between calls (scratch NULL: the run allocates its own) */
size_t hbvm_work_size(int k, int s, int m);

/* ... and for a system with P followers besides sources of us coordinates */
size_t hbvm_work_size_followers(int k, int s, int m, int us, int P);

/* the followers block at `follow` (hbvm_system) checked against m coordinates and the block's
 * length nblock: 0 when usable, else -1 */
int hbvm_followers_check(int m, const double *follow, long nblock);

/* the adaptive control's estimate with the test particles (core.test_particle_control):
 * gamma (s, m) row-major, the weights w = 1 / m and kin_w (0 for a test particle) */
double hbvm_test_particle_control(const double *gamma, int s, int m, const double *w,
                                  const double *kin_w, double err_sources);

/* a fixed step's check of its test particles (core.test_particle_error without the sources'
 * floor): the worst test particle (kin_w 0) whose own estimate exceeds max(floor, factor x the
 * sources'), or -1; its estimate in *worst_err */
int hbvm_test_particle_error(const double *gamma, int s, int m, const double *w,
                             const double *kin_w, double floor, double factor,
                             double *worst_err);

/* the kinetic and potential energies at y (2m,) */
int hbvm_energy_parts(const hbvm_kernel *kernel, const hbvm_system *sys, const double *y,
                      double *T, double *V);

/* E (s, s) <- the extrapolation of the previous step's polynomial over a step r times as long
 * (core.extrapolation_matrix); c: scratch of 4 s doubles */
void hbvm_extrapolation_matrix(double r, const double *t, const double *w, int s, double *E,
                               double *c);

/* the initial guess's extrapolation arrays (integrators.records.Extrapolation): E(1), the
 * s-point Gauss rule (t, w) on [0, 1], a buffer for another ratio and the zero matrix */
typedef struct {
    const double *E1, *t, *w;
    double *buf;
    const double *zero;
} hbvm_extrapolation;

/* the initial guess's matrix for a step h after a step h_prev (nan: none): core.
 * select_extrapolation's rule (E1 for the same step, the end value for a sliver, zero past
 * MAX_EXTRAPOLATION, else computed into ext->buf) */
const double *hbvm_select_extrapolation(double h, double h_prev, const hbvm_extrapolation *ext,
                                        int s);

/* One step from state into trial (integrators.loop.attempt's contract: the one retry loop of
 * every host, around the one controller core.adapt_step); the state is not changed.  trial
 * shares state's clock.  epsilon = 0: a fixed step, its status returned.  epsilon > 0: a step
 * whose own error estimate exceeds epsilon, or that failed, is tried again smaller, leaving no
 * trace in the counters; HBVM_TOO_SMALL below min_dt.  res (5,): h taken (or last tried), next
 * h proposed, rejections (added), the last rejection's estimate, its status. */
int hbvm_attempt(const hbvm_kernel *kernel, const hbvm_system *sys, hbvm_state *state,
                 hbvm_state *trial, double h, double h_prev, double t_start,
                 const hbvm_extrapolation *ext, const hbvm_tableau *tab,
                 const hbvm_options *opts, double *counters, double epsilon, double min_dt,
                 double *res, double *scratch, size_t nscratch);

/* the core's functions for the hosts' compiled glue (hbvm_md/rebound/csrc), handed over in
 * the capsule integrators._core.API: one binary of the step */
#define HBVM_API_VERSION 5
typedef struct {
    int version, lanes, n_counters, n_eref;
    int (*attempt)(const hbvm_kernel *, const hbvm_system *, hbvm_state *, hbvm_state *,
                   double, double, double, const hbvm_extrapolation *, const hbvm_tableau *,
                   const hbvm_options *, double *, double, double, double *, double *, size_t);
    size_t (*work_size)(int, int, int);
    int (*energy_parts)(const hbvm_kernel *, const hbvm_system *, const double *, double *,
                        double *);
    hbvm_force_fn nbody_force;
    hbvm_potential_fn nbody_potential;
    int (*nbody_check)(int, const double *, long);
    hbvm_field_fn nbody_field;          /* the test particles' field (followers) */
    int (*test_particle_error)(const double *, int, int, const double *, const double *,
                               double, double, double *);
} hbvm_api;

/* the padded stage count for k stages */
static inline int hbvm_padded(int k) { return (k + HBVM_LANES - 1) / HBVM_LANES * HBVM_LANES; }

/* a built-in kernel of a small system (kernels_simple.c): m coordinates (0: any) and the
 * number of parameters it reads; its ctx points to the int m */
typedef struct {
    const char *name;
    hbvm_force_fn force;
    hbvm_potential_fn potential;
    int m, nparams;
} hbvm_builtin;
extern const hbvm_builtin hbvm_builtins[];

/* built-in kernels (kernels_*.c) */
void hbvm_nbody_force(const double *X, int m, int kp, const double *params, double *F);
double hbvm_nbody_potential(const double *q, const double *params);
int hbvm_nbody_force_k(void *ctx, const double *X, int m, int kp, int n, const double *params,
                       double *F);
int hbvm_nbody_potential_k(void *ctx, const double *q, const double *params, double *V);
/* the parameters' consistency with m coordinates: 0 when usable, else -1 */
int hbvm_nbody_check(int m, const double *params, long nparams);
/* the followers' field of the N-body kernel (hbvm_field_fn; systems.nbody.nbody_field) */
int hbvm_nbody_field(const double *Xt, int nt, const double *Xs, int kp, int n,
                     const double *params, double *F);

#endif
