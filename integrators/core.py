"""The compiled pieces of one HBVM step that call no force kernel (numba).

:mod:`integrators.loop` assembles them into the step, once, for both forms of the method:

* the **separable** form, H = p^T M^{-1} p / 2 + V(q): only the momentum coefficients gamma_p
  (s, m) are unknown, because P_s^T Omega I_s = X_s when the quadrature is exact to degree
  2s - 1 (Brugnano-Iavernaro-Trigiante, proof of Theorem 1); the stage positions are
  Q = q0 + h tau v0 + h^2 (I_s X_s) M^{-1} gamma_p, and q1 = q0 + h v0 + h^2 M^{-1}
  (X_s gamma_p)_1, p1 = p0 + h gamma_p1;
* the **full** form, any Hamiltonian: gamma (s, 2m), stages Y = y0 + h I_s gamma,
  gamma <- P_s^T Omega f(Y), y1 = y0 + h gamma_1 (eqs. (expan), (orth)).

Round-off is kept unbiased and small, so that the energy error is a random walk (Brouwer's law)
rather than a drift:

* products of two constants are never rounded once and reused: h tau_i and h h are carried as
  exact (hi, lo) pairs in the stage positions, and h^2 xg is formed as h (h xg).  Left as plain
  products they perturb the method itself by one ulp and the energy drifts linearly (measured:
  3e-14 over 1000 Jupiter years of the outer solar system);
* the state is a double-double number (y - cy); the increments are formed without rounding
  (two_product, two_sum) and added exactly, and the low parts enter the stage values;
* once the iteration has converged, one more evaluation projects the stage forces with a
  compensated dot product (Dot2, with the remainders W_lo) rounded once.

Every function here is compiled with :func:`integrators.jit.jit` (cached on disk when possible)
and runs as plain Python under ``NUMBA_DISABLE_JIT=1``.
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir as llvm_ir
from numba import types
from numba.extending import intrinsic, overload

from .jit import jit
from .pointers import view, view1

EPS = np.finfo(float).eps
ROUNDOFF_ULPS = 64.0     # a stalled increment within this many ulps of its round-off is converged
LIPSCHITZ_ULPS = 4.0     # ... within this many ulps of the stage values' rounding times L
STATE_ULPS = 16.0        # ... and so is one that moves the new state by at most this many ulps
STRONG_CONTRACTION = 1e-3  # a contraction at least this strong is extrapolated (stop_action) ...
EXTRAPOLATED_ULPS = 1e-3   # ... to an iterate predicted within this many ulps of the fixed point
TOL_CONTRACTION = 0.25    # with a tolerance: a contraction this strong estimates the error (stop_action)
RUNAWAY = 1e8             # coefficients that would move the state this many times farther than
                          # the first iterate and the state itself: the iteration runs away

# status codes of a step (one table maps them to exceptions: integrators.errors.step_error);
# TOO_SMALL: an adaptive step was not accepted down to min_dt (loop.attempt)
OK, DIVERGED, NOT_FINITE, UNRESOLVED, TOO_SMALL = 0, 1, 2, 3, 4
# NOT_RESOLVED: a converged step whose own error estimate (resolution_error) exceeds the bound
# (6: after integrators.equip_core.NO_ENERGY_ROOT, 5)
NOT_RESOLVED = 6
# DRIFTED: a converged step of a method not exact for H after which the run's energy stands more
# than DRIFT_BOUND away from its start (the energy check, integrators.loop.energy_check); not
# retried by the controller: a shorter step does not undo the run's past
DRIFTED = 7
NARROW = 8                # from this many columns the sums run column-innermost (vectorised),
                          # below it entry by entry (fewer than 3 bodies), measured
BLOCK = 512               # ... in blocks of this many columns (their partial sums stay in cache)
FOLLOWER_GROUP = 128       # followers iterated together (integrators.loop.follow), measured
TINY_RATIO = 1e-3         # a step this much shorter than the previous one is a sliver
MAX_EXTRAPOLATION = 4.0   # the longest h_new / h_old the previous polynomial is extrapolated over
# A step of a method not exact for H whose energy error exceeds FLOW_FRACTION[min(s, 3) - 1] of
# the energy it moved between the terms of H (energy_flow) does not resolve its path (the check
# of integrators.loop.run).  Measured on Kepler e = 0.6 .. 0.999, HBVM(k, s), s = 2 .. 8, 30 to
# 1e4 steps a period (tests/test_eccentric_steps.py): a step that flies past a pericentre (its
# force polynomial misses the pericentre's force) errs by 3e-3 to 800 times its flow at s >= 3
# and 2.8e-2 to 800 at s = 2 (in the runs whose energy ends off by more than 1); runs that
# resolve it stay below 6.3e-4 (s >= 3) and, at s = 2 (order 4, a larger error for the same
# resolution), 1.5e-3 on Kepler and up to 7.6e-3 on the benchmark scenes (a quartic cluster with
# Hookean springs at 10 fs: benchmarks/bench_energy_check.py --scenes).  Each fraction sits near
# the geometric middle of its gap (1e-3 between 6.3e-4 and 3e-3; 1.5e-2 between 7.6e-3 and
# 2.8e-2).  s = 1, a constant force polynomial, errs by about its flow at a coarse step (the
# midpoint rule crossing a potential's minimum), and is refused only beyond all of it.
FLOW_FRACTION = (1.0, 1.5e-2, 1e-3)
# what the iteration does next (stop_action)
ITERATE, POLISH = 0, 1
# counters: one float64 array, the same layout on every path
# C_ERR, C_WORST: the last step's own error estimate (resolution_error) and the body it names
# (of the last committed step, or of the refused one)
# C_RUN_ERR: the run's accumulated error estimate, the sum over its committed steps of each
# step's own estimate, plus DRIFT_PHASE times the run's drift for a method not exact for H,
# times the share of its body's motion the step turns (run_error_share);
# like C_STEPS it counts committed steps only, and it rides with the counters wherever they go
# (a Stepper's calls, REBOUND's saved counters: copies and archives)
C_STEPS, C_ITER, C_NFEV, C_LAST, C_NEWTON, C_CHANGE, C_LASTIT, C_ERR, C_WORST, C_RUN_ERR = range(10)
N_COUNTERS = 10
# A step is a solution when its own estimate of its relative local error (resolution_error) is
# at most ERROR_BOUND: three correct digits a step.  The derivation and the measurements are in
# docs/design/step.md, "A step judged by its own error".
ERROR_BOUND = 1e-3
# A run of a method not exact for H (energy_tol "auto" negative: k = s, the Gauss method, or k
# too small for H's quadrature) is refused when its energy stands more than DRIFT_BOUND of the
# run's kinetic scale, max(T, <T> sqrt(<T> / Tmax)), away from the energy at its start: T the
# kinetic energy after the step, <T> its time mean and Tmax its largest over the run so far.
# None moves with the potential's zero (a constant added to V changes no force, no step, no T).
# Why: for a bound Kepler orbit the virial theorem gives <T> = -H = |H| (H's zero at infinity),
# and a relative offset delta = dH / <T> shifts the mean motion by 1.5 delta: the phase lags by
# 3 pi delta a period, and the position by that times the fastest speed over the mean one,
# sqrt(Tmax / <T>) (at pericentre: sqrt((1 + e) / (1 - e))), so dH / (<T> sqrt(<T> / Tmax)) at
# most 1e-3 keeps the position within 1e-2 of the orbit's size a period, the standard
# ERROR_BOUND sets for one step.  And along a path dv / v = dH / (2 T) at the same place: a
# transient offset (a symmetric method's bump inside a pericentre passage, which it gives back
# after it) is judged against the T of the moment.  The larger of the two: a lasting offset is
# met where T is small (every orbit has such a part), a turning point (T = 0) is judged against
# the mean.  No single step can see this: a run that starts inside a passage keeps half of the
# bump as a lasting offset, with the same steps and estimates as a run that does not
# (docs/design/step.md, "What it cannot see", derived and measured there).
DRIFT_BOUND = ERROR_BOUND
# the step's eref, carried between steps by every host: [the energy after the last step, EQUIP's
# alpha and dE/dalpha (integrators.equip_core.EREF_EQUIP), the energy at the run's start (the
# anchor of DRIFT_BOUND's rule), the time mean of T over the run so far, the run's elapsed
# time (|h| summed) and T's largest value (the scale of DRIFT_BOUND's rule)]; nan: not known yet (a host that changes
# the Hamiltonian or the state sets all of them to nan, so a run starts again from there: the
# run's start, its mean T, its time and its largest T start together, when EREF_RUN is nan)
EREF_RUN = 3
EREF_TMEAN = 4
EREF_TIME = 5
EREF_TMAX = 6
N_EREF = 7
# A run whose accumulated error estimate (C_RUN_ERR) passes RUN_ERROR_BOUND is warned about
# (integrators.errors.AccumulatedErrorWarning) by the engine and REBOUND: a hundredth of the
# motion's scale (docs/design/step.md, "The run's accumulated error")
RUN_ERROR_BOUND = 1e-2
# ... and a method not exact for H adds, each step, DRIFT_PHASE times its run's drift (the
# energy's offset from the run's start over DRIFT_BOUND's scale) times the step's share of its
# motion: an offset delta moves a Kepler orbit's mean motion by 1.5 delta, so the phase it
# lags over the step is 1.5 delta times the phase the step advances
DRIFT_PHASE = 1.5


def two_product(a, b):
    """a * b = hi + lo exactly.  As Python (``NUMBA_DISABLE_JIT``): Dekker's product with
    Veltkamp splitting; compiled: lo = fma(a, b, -hi) (:func:`_two_product_fma`).  Both give
    the exact error of the rounded product, so the same numbers (barring overflow in the
    splitting, |a|, |b| > 2^995); the fused form costs 2 operations instead of 17 (the
    compensated projection of every step: measured 800 -> 475 ns, HBVM(8, 6), outer solar
    system)."""
    p = a * b
    c = 134217729.0 * a
    ah = c - (c - a)
    al = a - ah
    c = 134217729.0 * b
    bh = c - (c - b)
    bl = b - bh
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


@intrinsic
def _fma(typingctx, a, b, c):
    """a * b + c rounded once (LLVM's llvm.fma: the FMA instruction, or libm's exact fma on a
    machine without one)."""
    if not all(isinstance(x, (types.Float, types.Integer)) for x in (a, b, c)):
        return None
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        d = llvm_ir.DoubleType()
        fn = builder.module.declare_intrinsic("llvm.fma", [d], llvm_ir.FunctionType(d, [d, d, d]))
        return builder.call(fn, args)
    return sig, codegen


@overload(two_product)
def _two_product_fma(a, b):
    def impl(a, b):
        p = a * b
        return p, _fma(a, b, -p)
    return impl


@jit
def two_sum(a, b):
    """a + b = s + e exactly (Knuth)."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


@jit
def dd_add(x, c, j, inc_hi, inc_lo):
    """x[j] - c[j] (a double-double: c holds minus the low part) += inc_hi + inc_lo."""
    s, e = two_sum(x[j], inc_hi)
    lo = (e + inc_lo) - c[j]
    hi = s + lo
    c[j] = -(lo - (hi - s))
    x[j] = hi


@jit
def all_zero(a):
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            if a[i, j] != 0.0:
                return False
    return True


@jit
def copy1(dst, src):
    """dst[:] = src for 1-d arrays (an explicit loop: numba's slice assignment costs about
    0.1 microsecond, which counts on a one-microsecond step)."""
    for j in range(src.shape[0]):
        dst[j] = src[j]


@jit
def copy2(dst, src):
    """dst[:, :] = src for 2-d arrays."""
    for i in range(src.shape[0]):
        for j in range(src.shape[1]):
            dst[i, j] = src[i, j]


@jit
def lipschitz_probe(X, F, Xp, Fp, lip):
    """Update the estimate lip = max over calls of max|F - Fp| / max|X - Xp| (the force's
    Lipschitz constant seen between two iterations, when the stage values moved by more than
    round-off), then keep X, F in Xp, Fp; returns max |X|."""
    dx = 0.0
    df = 0.0
    xmax = 0.0
    for i in range(X.shape[0]):
        for j in range(X.shape[1]):
            d = abs(X[i, j] - Xp[i, j])
            if d > dx:
                dx = d
            if abs(X[i, j]) > xmax:
                xmax = abs(X[i, j])
            Xp[i, j] = X[i, j]
        # (F may be narrower than X: the stage velocities' step hands the kernel (q, v))
        for j in range(F.shape[1]):
            d = abs(F[i, j] - Fp[i, j])
            if d > df:
                df = d
            Fp[i, j] = F[i, j]
    if dx > 1024.0 * EPS * xmax and df / dx > lip:
        lip = df / dx
    return lip, xmax


@jit
def lipschitz_slots(X, F, Xp, Fp, w, lip, xmax):
    """:func:`lipschitz_probe` for each slot of w adjacent columns on its own (lip, xmax:
    (columns / w,), the slots' estimates updated and their max |X|), in one pass."""
    n, u = X.shape
    for j in range(u // w):
        dx = 0.0
        df = 0.0
        xm = 0.0
        for i in range(n):
            for c in range(w * j, w * j + w):
                d = abs(X[i, c] - Xp[i, c])
                if d > dx:
                    dx = d
                d = abs(F[i, c] - Fp[i, c])
                if d > df:
                    df = d
                if abs(X[i, c]) > xm:
                    xm = abs(X[i, c])
                Xp[i, c] = X[i, c]
                Fp[i, c] = F[i, c]
        if dx > 1024.0 * EPS * xm and df / dx > lip[j]:
            lip[j] = df / dx
        xmax[j] = xm


@jit
def all_finite(a):
    for j in range(a.shape[0]):
        if not np.isfinite(a[j]):
            return False
    return True


@jit
def max_abs2(a):
    """max |a| of a 2-d array, nan when an entry is nan."""
    v = 0.0
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            x = abs(a[i, j])
            if x > v or x != x:
                v = x
    return v


@jit
def max_abs(a):
    v = 0.0
    for j in range(a.shape[0]):
        if abs(a[j]) > v:
            v = abs(a[j])
    return v


@jit
def weighted_kinetic(p, w):
    """sum_i w_i p_i^2 / 2 (w = 1 / m_i, or 0 for a degree of freedom left out)."""
    ke = 0.0
    for i in range(p.shape[0]):
        ke += 0.5 * p[i] * p[i] * w[i]
    return ke


@jit
def energy_flow(full, y, minv, h, g, W, I, G):
    """The energy the step moves into and out of a term of H along its polynomial path sigma,
    |h| sum_i |b_i dH/dy sigma'(c_i)| taken coordinate by coordinate in absolute value.

    Separable form: the kinetic term, |h| sum_i sum_j |v_ij b_i sigma_p'(c_i)_j| with v =
    (p0 + h I_s gamma) w the stage velocities of the degrees of freedom the kinetic energy
    counts (``minv``: the kinetic weights, 1 / m or 0 for a test particle, which carries no
    energy and moves none) and b_i sigma_p'(c_i) = sum_l W[l, i]
    gamma_l (W = P_s^T Omega); the k-point rule integrates v . sigma_p' (degree 2s - 1)
    exactly, so this is at least |T(p1) - T(p0)|.  Full form: half of |h| sum_i sum_j |G_ij
    b_i sigma'(c_i)_j| with G (k, 2m) = grad H at the stages (each unit of energy leaves one
    term and enters another).  A resolved step's energy error, the quadrature error of the
    line integral of grad H along sigma (Brugnano-Iavernaro-Trigiante), is far smaller than
    this flow; a converged state whose error exceeds it is not a solution of the step
    (:func:`integrators.loop.run`)."""
    s, u = g.shape
    n = W.shape[1]
    flow = 0.0
    if full:
        for i in range(n):
            for j in range(u):
                acc = 0.0
                for l in range(s):
                    acc += W[l, i] * g[l, j]
                flow += abs(G[i, j] * acc)
        return 0.5 * abs(h) * flow
    m = minv.shape[0]
    for i in range(n):
        for j in range(m):
            vel = 0.0
            acc = 0.0
            for l in range(s):
                vel += I[i, l] * g[l, j]
                acc += W[l, i] * g[l, j]
            flow += abs((y[m + j] + h * vel) * minv[j] * acc)
    return abs(h) * flow


@jit
def step_constants(h, tau, tau_lo, ht, ht_lo):
    """h * tau_i as exact pairs (ht, ht_lo) and h * h as an exact pair, returned."""
    for i in range(tau.shape[0]):
        ht[i], lo = two_product(h, tau[i])
        ht_lo[i] = lo + h * tau_lo[i]
    return two_product(h, h)


@jit
def guess(E, gamma, g):
    """g = E gamma: the previous step's polynomial extrapolated over the new step, the sums
    column-innermost (vectorised; 276 -> 168 ns for the outer solar system, s = 6);
    :func:`guess_narrow` gives the same numbers entry by entry, faster below NARROW columns."""
    s, m = g.shape
    mu = np.uint64(m)
    for i in range(s):
        for j in range(mu):
            g[i, j] = 0.0
        for l in range(s):
            c = E[i, l]
            for j in range(mu):
                g[i, j] += c * gamma[l, j]


@jit
def guess_narrow(E, gamma, g):
    """:func:`guess` entry by entry (for few columns)."""
    s, m = g.shape
    for i in range(s):
        for j in range(m):
            acc = 0.0
            for l in range(s):
                acc += E[i, l] * gamma[l, j]
            g[i, j] = acc


@jit
def stage_positions(y, cy, minv, g, C2, C2_lo, sc, a, Q, R, exact):
    """Separable form: Q = q0 + h tau v0 + h^2 (I_s X_s) M^{-1} gamma_p, y = (q, p); sc: the
    step's constants (h tau and h^2 as exact pairs, :class:`integrators.records.StepConstants`).

    ``exact``: also the low parts C2_lo of the coefficients (the step's last evaluation, whose
    rounding the step keeps); the iterations before it only have to reach the fixed point to
    round-off, and C2_lo a is below the rounding of the sum itself (see :func:`project`).

    R (2, >= min(m, BLOCK)) is scratch: the sums over l run with the column j innermost, in
    blocks of BLOCK columns, so that the columns' sums are independent (vectorised) rather than
    one chain of dependent additions each, and their partial sums stay in cache however many
    columns there are.  Column indices are unsigned: numba then drops its negative-index
    wraparound, which otherwise keeps these loops from vectorising (measured 2x).  The block
    loop is written out here, in :func:`full_stages` and in the projections: as one shared
    helper it is not inlined into the step (measured 9.1 -> 11.4 us a step, outer solar system).
    :func:`stage_positions_narrow` gives the same numbers (every Q[i, j] is the same sum in the
    same order) and is faster below NARROW columns; the step picks one of the two where it
    calls them, which keeps each small enough to be inlined there (one function holding both
    loops is not inlined: measured 1.3 us more a step of the outer solar system)."""
    s, m = g.shape
    ht, ht_lo, h2, h2_lo = sc.ht, sc.ht_lo, sc.h2, sc.h2_lo
    acc = R[0]
    acc_lo = R[1]
    mu = np.uint64(m)
    for i in range(s):
        for j in range(m):
            a[i, j] = g[i, j] * minv[j]
    for j0 in range(0, m, BLOCK):
        nb = np.uint64(min(BLOCK, m - j0))
        ju = np.uint64(j0)
        for i in range(Q.shape[0]):
            for jj in range(nb):
                acc[jj] = 0.0
                acc_lo[jj] = 0.0
            if exact:
                for l in range(s):
                    c = C2[i, l]
                    c_lo = C2_lo[i, l]
                    for jj in range(nb):
                        acc[jj] += c * a[l, ju + jj]
                        acc_lo[jj] += c_lo * a[l, ju + jj]
            else:
                for l in range(s):
                    c = C2[i, l]
                    for jj in range(nb):
                        acc[jj] += c * a[l, ju + jj]
            hti = ht[i]
            hti_lo = ht_lo[i]
            for jj in range(nb):
                j = ju + jj
                vj = y[mu + j] * minv[j]
                Q[i, j] = y[j] + hti * vj + ((hti_lo * vj - cy[j]) - hti * cy[mu + j] * minv[j]
                                             + h2 * (acc[jj] + acc_lo[jj]) + h2_lo * acc[jj])

@jit
def stage_positions_narrow(y, cy, minv, g, C2, C2_lo, sc, a, Q, exact):
    """:func:`stage_positions` entry by entry (for few columns)."""
    s, m = g.shape
    ht, ht_lo, h2, h2_lo = sc.ht, sc.ht_lo, sc.h2, sc.h2_lo
    for i in range(s):
        for j in range(m):
            a[i, j] = g[i, j] * minv[j]
    for i in range(Q.shape[0]):
        for j in range(m):
            acc = 0.0
            acc_lo = 0.0
            for l in range(s):
                acc += C2[i, l] * a[l, j]
            if exact:
                for l in range(s):
                    acc_lo += C2_lo[i, l] * a[l, j]
            vj = y[m + j] * minv[j]
            Q[i, j] = y[j] + ht[i] * vj + ((ht_lo[i] * vj - cy[j]) - ht[i] * cy[m + j] * minv[j]
                                           + h2 * (acc + acc_lo) + h2_lo * acc)


@jit
def full_stages(y, cy, g, I, I_lo, h, Y, R, exact):
    """Full form: Y = y0 + h I_s gamma at the stages, y0 the double-double y - cy (R: scratch
    (2, >= min(d, BLOCK)), the sums column-innermost in blocks as in :func:`stage_positions`;
    below NARROW columns :func:`full_stages_narrow`; I_lo only when ``exact``, as there).

    The low part h I_lo gamma (below half an ulp of h I_s gamma) joins -cy, not the rounded
    sum: added to the rounded sum it is rounded away, the same way on every step (a stage
    moved by -h I_lo[i, 0] f, as if the nodes were rounded), and the energy of a polynomial H
    drifted by h^2 (2.8e-18 a step of the 7.8e-18 of Henon-Heiles, HBVM(12, 6), h = 0.5);
    with -cy (the state's low part: random bits below the state's ulp) the two roundings that
    follow keep it on average."""
    n = Y.shape[0]
    s, d = g.shape
    acc = R[0]
    acc_lo = R[1]
    for j0 in range(0, d, BLOCK):
        nb = np.uint64(min(BLOCK, d - j0))
        ju = np.uint64(j0)
        for i in range(n):
            for jj in range(nb):
                acc[jj] = 0.0
                acc_lo[jj] = 0.0
            if exact:
                for l in range(s):
                    c = I[i, l]
                    c_lo = I_lo[i, l]
                    for jj in range(nb):
                        acc[jj] += c * g[l, ju + jj]
                        acc_lo[jj] += c_lo * g[l, ju + jj]
            else:
                for l in range(s):
                    c = I[i, l]
                    for jj in range(nb):
                        acc[jj] += c * g[l, ju + jj]
            for jj in range(nb):
                j = ju + jj
                Y[i, j] = y[j] + (h * acc[jj] + (h * acc_lo[jj] - cy[j]))

@jit
def full_stages_narrow(y, cy, g, I, I_lo, h, Y, exact):
    """:func:`full_stages` entry by entry (for few columns)."""
    n = Y.shape[0]
    s, d = g.shape
    for i in range(n):
        for j in range(d):
            acc = 0.0
            acc_lo = 0.0
            for l in range(s):
                acc += I[i, l] * g[l, j]
            if exact:
                for l in range(s):
                    acc_lo += I_lo[i, l] * g[l, j]
            Y[i, j] = y[j] + (h * acc + (h * acc_lo - cy[j]))


@jit
def stage_velocities(y, cy, minv, g, I, I_lo, h, Z, exact):
    """Separable form with stage velocities: Z[:, m:] = (p0 + h I_s gamma_p) M^{-1}, the
    velocities at the stages, beside the positions Z[:, :m] that :func:`stage_positions`
    writes (Z (n, 2m), y = (q, p) the double-double state less cy).  These are the Runge-Kutta
    stages of the first-order system (q, p)' = (M^{-1} p, f(t, q, M^{-1} p)) whose position
    stages are the separable step's Q (Brugnano-Iavernaro-Trigiante: HBVM(k, s) is a k-stage
    Runge-Kutta method with A = I_s P_s^T Omega, and P_s^T Omega I_s = X_s), so the step stays
    of order 2s for a force that reads velocities.  The momenta's stages are the full form's
    (:func:`full_stages_narrow` on p: the same sums and roundings, I_lo only when ``exact``),
    then scaled by M^{-1}."""
    m = g.shape[1]
    V = Z[:, m:]
    full_stages_narrow(y[m:], cy[m:], g, I, I_lo, h, V, exact)
    for i in range(V.shape[0]):
        for j in range(m):
            V[i, j] *= minv[j]


@jit
def velocity_work(n, m, on):
    """The float work a step with stage velocities adds after :func:`work_sizes`'s (``on``
    False: none): the stages (q, v) and their previous iterate, (n, 2m) each."""
    return 4 * n * m if on else 0


@jit
def carve_velocities(work, o, n, m, on):
    """The stage velocities' work arrays (:func:`velocity_work`) at offset o of ``work``:
    Z, Zp (n, 2m) (empty when not ``on``)."""
    w = 2 * m if on else 0
    if work.shape[0] < o + 2 * n * w:
        raise ValueError("internal error: the step's work buffer is too short for its stage "
                         "velocities (core.velocity_work)")
    return view(work, o, n, w), view(work, o + n * w, n, w)


@jit
def symplectic(G, F):
    """F = J G with J = [[0, I], [-I, 0]]: (dH/dp, -dH/dq) from G = grad H, row by row."""
    m = G.shape[1] // 2
    for i in range(G.shape[0]):
        for j in range(m):
            F[i, j] = G[i, m + j]
            F[i, m + j] = -G[i, j]


@jit
def project_narrow(W, F, g):
    """:func:`project` for few columns (entry by entry: the same numbers)."""
    s, m = g.shape
    n = F.shape[0]
    delta = 0.0
    scale = 0.0
    for i in range(s):
        for j in range(m):
            v = 0.0
            for l in range(n):
                v += W[i, l] * F[l, j]
            d = abs(v - g[i, j])
            if d > delta or d != d:
                delta = d
            if abs(v) > scale:
                scale = abs(v)
            g[i, j] = v
    return delta, scale


@jit
def project(W, F, g, R):
    """g <- W F (plain sums); returns (max |increment|, max |g|), the first nan when an
    increment is nan (max |g| skips nan).  A non-finite force makes an increment non-finite:
    row 0 of W holds the quadrature weights, all positive.  For the iterations before the
    step's last evaluation: they only have to reach the fixed point to round-off, and the low
    parts W_lo of the weights (below half an ulp of W) move the sum by less than its own
    rounding, so they are left to :func:`project_compensated`.  R (5, >= min(m, BLOCK)) is
    scratch: the sums and maxima run column-innermost in blocks (see :func:`stage_positions`),
    then across the columns; :func:`project_narrow` gives the same numbers, faster below
    NARROW columns.  max |F| is not taken here: the stop rule needs it only when the increment
    stalls (:func:`stop_action`), and taking it on every iteration cost 75 ns of 430
    (HBVM(8, 6), outer solar system)."""
    s, m = g.shape
    n = F.shape[0]
    acc = R[0]
    dcol = R[3]
    scol = R[4]
    delta = 0.0
    scale = 0.0
    for j0 in range(0, m, BLOCK):
        nb = np.uint64(min(BLOCK, m - j0))
        ju = np.uint64(j0)
        for jj in range(nb):
            dcol[jj] = 0.0
            scol[jj] = 0.0
        for i in range(s):
            for jj in range(nb):
                acc[jj] = 0.0
            for l in range(n):
                w = W[i, l]
                for jj in range(nb):
                    acc[jj] += w * F[l, ju + jj]
            for jj in range(nb):
                j = ju + jj
                v = acc[jj]
                d = abs(v - g[i, j])
                c = dcol[jj]
                dcol[jj] = d if (d > c or d != d) else c
                x = abs(v)
                c = scol[jj]
                scol[jj] = x if x > c else c
                g[i, j] = v
        for jj in range(nb):
            if dcol[jj] > delta or dcol[jj] != dcol[jj]:
                delta = dcol[jj]
            if scol[jj] > scale:
                scale = scol[jj]
    return delta, scale

@jit
def project_each(W, F, g, R, dcol, scol):
    """g <- W F as :func:`project` computes it (the same numbers), but the increment and the
    size kept column by column: dcol[j] = max_i |increment_ij| (nan when one is nan), scol[j] =
    max_i |g_ij|, (u,) each; for blocks of columns that stop on their own (the followers of
    :mod:`integrators.loop`).  Not one function with :func:`project` (an argument saying where
    the column maxima go): that made a step of the outer solar system 2 % slower (HBVM(9, 8)
    through REBOUND, 13.83 -> 14.15 us, medians of 5 alternated runs)."""
    s, m = g.shape
    n = F.shape[0]
    acc = R[0]
    for j in range(m):
        dcol[j] = 0.0
        scol[j] = 0.0
    for j0 in range(0, m, BLOCK):
        nb = np.uint64(min(BLOCK, m - j0))
        ju = np.uint64(j0)
        for i in range(s):
            for jj in range(nb):
                acc[jj] = 0.0
            for l in range(n):
                w = W[i, l]
                for jj in range(nb):
                    acc[jj] += w * F[l, ju + jj]
            for jj in range(nb):
                j = ju + jj
                v = acc[jj]
                d = abs(v - g[i, j])
                c = dcol[j]
                dcol[j] = d if (d > c or d != d) else c
                x = abs(v)
                c = scol[j]
                scol[j] = x if x > c else c
                g[i, j] = v


@jit
def compact_slots(buf, off, rows, width, na, keep, nk):
    """In place: the (rows, na width) array at buf[off:] becomes the (rows, nk width) array of
    the slots keep[0 .. nk) (increasing; a slot is ``width`` adjacent columns).  Every entry
    moves to a lower or equal index, and in increasing order, so nothing is overwritten
    before it is read."""
    ou = na * width
    nu = nk * width
    for r in range(rows):
        for j in range(nk):
            src = off + r * ou + width * int(keep[j])
            dst = off + r * nu + width * j
            for c in range(width):
                buf[dst + c] = buf[src + c]


@jit
def no_followers(params):
    """The followers hook of a system without them (:mod:`integrators.loop`): none."""
    return -1


@jit
def no_field(Xt, Xs, params, out):
    """The field hook of a system without followers: never called."""
    return None


@jit
def project_compensated(W, W_lo, F, g, R):
    """g <- W F as if in twice the working precision (Dot2), rounded once (R: scratch, the
    sums column-innermost in blocks)."""
    s, m = g.shape
    n = F.shape[0]
    acc = R[0]
    acc_lo = R[1]
    for j0 in range(0, m, BLOCK):
        nb = np.uint64(min(BLOCK, m - j0))
        ju = np.uint64(j0)
        for i in range(s):
            for jj in range(nb):
                acc[jj] = 0.0
                acc_lo[jj] = 0.0
            for l in range(n):
                w = W[i, l]
                w_lo = W_lo[i, l]
                for jj in range(nb):
                    f = F[l, ju + jj]
                    ph, pl = two_product(w, f)
                    hi, e = two_sum(acc[jj], ph)
                    acc[jj] = hi
                    acc_lo[jj] += (e + pl) + w_lo * f
            for jj in range(nb):
                g[i, ju + jj] = acc[jj] + acc_lo[jj]

@jit
def newton_update(g, pg, NV, NVinv, NM, Rt, Z):
    """Simplified Newton: g <- g - (I - X_s^p (x) L)^{-1} (g - pg), pg = phi(g).

    The Gauss matrix is split through X_s = V Lambda V^{-1} into s systems (I - mu_i L) whose
    inverses NM (s, u, u) were formed once for the step (by the isospectral property they are
    Gauss's whatever k is).  Returns (max |correction|, max |g|)."""
    s, u = g.shape
    for i in range(s):
        for j in range(u):
            acc = 0.0 + 0.0j
            for l in range(s):
                acc += NVinv[i, l] * (g[l, j] - pg[l, j])
            Rt[i, j] = acc
    for i in range(s):
        for j in range(u):
            acc = 0.0 + 0.0j
            for l in range(u):
                acc += NM[i, j, l] * Rt[i, l]
            Z[i, j] = acc
    delta = 0.0
    scale = 0.0
    for i in range(s):
        for j in range(u):
            acc = 0.0 + 0.0j
            for l in range(s):
                acc += NV[i, l] * Z[l, j]
            c = acc.real
            v = g[i, j] - c
            if abs(c) > delta or c != c:
                delta = abs(c)
            if abs(v) > scale:
                scale = abs(v)
            g[i, j] = v
    return delta, scale


@jit
def stop_action(delta, scale, F, floor, hstate, hmove, ymax, it, hist, tol):
    """The stopping rule, one increment at a time (HLW Sec. VIII.6: iterate until the increment
    vanishes or stops decreasing at round-off level).

    Converged (POLISH) when the increment is within two ulps of the coefficients, below
    ``tol * scale`` (when a tolerance is given: tol > 0), when the iterate's error estimated
    from the contraction is (with a tolerance, see below), or when it stopped decreasing at its round-off
    level: within ROUNDOFF_ULPS ulps of the larger of the coefficients and the stage forces F
    (the rounding of W F; max |F| is taken only then), below ``floor`` (the stage values'
    rounding propagated through the force, LIPSCHITZ_ULPS eps max|stage| L with L the force's
    Lipschitz constant measured on the first iterations: eps |q| omega^2 for a stiff spring,
    which no scale of gamma shows), or moving the new state by at most STATE_ULPS of its
    largest component (``hstate`` = |h| delta / (eps max |y|)).  An increment that stops
    decreasing above those levels is not round-off: the second such stall is a failure
    (DIVERGED), never an accepted step.

    One more case is converged without waiting for the stall, when the iteration contracts
    strongly (the increments of a soft-sphere fluid shrink by 1e-5 an iteration): the increment
    is at one of the round-off levels above, and the last two ratios of increments before it,
    theta (the larger), are at most STRONG_CONTRACTION and put this iterate within
    EXTRAPOLATED_ULPS ulps of the fixed point, theta^2 delta_prev <= EXTRAPOLATED_ULPS eps scale
    (the contraction estimate of Hairer and Wanner, Solving ODEs II, Sec. IV.8, from increments
    above round-off, which this one, at round-off, is not).  The polish then lands theta times
    closer still, within 1e-6 ulp.  Without it, the max norm of the increments of 1e5 atoms
    sits at its round-off level, tens of ulps of the coefficients, for two iterations before it
    stalls (a 1e3-atom fluid reaches two ulps one iteration earlier): a quarter of the step.
    A weaker contraction never takes this exit, so planetary and Kepler runs (theta 0.005 to
    0.2) iterate as before: an estimate of theta from ratios near 0.1 let the polish's error,
    which has the same sign step after step, build a phase error on Kepler (an earlier rule,
    measured and reverted).
    An iteration that runs away is a failure (DIVERGED) at once, before any of the round-off
    levels above, which grow with the iterates and would take it as converged (a step of
    h = 10 on H = p^2 / 2 + 1e6 q^4 ran to 1e100 in three iterations and was accepted by the
    Lipschitz floor): the coefficients would move the state, by ``hmove`` = |h| max|gamma|,
    more than RUNAWAY times what the first iterate moved it plus the state's own size ``ymax``
    (max |y|).  A converging iteration moves it by about as much as its first iterate does.

    With a tolerance (tol > 0; the iteration to round-off, tol = 0, never takes this exit) the
    iterate is also converged when its error, estimated from the contraction as theta delta /
    (1 - theta) (Hairer and Wanner, Solving ODEs II, Sec. IV.8), is at most
    ``tol * scale``, theta being the larger of the last two ratios of increments and at most
    TOL_CONTRACTION (two ratios, so that a single small ratio does not pass for a contraction).
    The polish then lands theta times closer.  On EMT copper with ``HBVMDynamics``' tol of
    1e-12 (HBVM(3, 2) at 5 fs, theta about 7e-3) this stops one sweep before the increment
    itself is below tol: 22.1 -> 19.2 force evaluations a step, the same energy error.

    hist = [previous increment, stalls, the last two increment ratios, the first iterate's
    move plus ymax]; returns ITERATE, POLISH or -status.
    """
    if not np.isfinite(delta):        # also when a force is not finite (see project)
        return -NOT_FINITE
    if it == 1:
        hist[4] = ymax + hmove
    elif hmove > RUNAWAY * hist[4]:
        return -DIVERGED
    if delta <= 2.0 * EPS * scale or delta <= tol * scale:
        return POLISH
    if tol > 0.0 and delta < hist[0]:
        theta = max(delta / hist[0], hist[2])      # hist[2]: inf until two ratios are known
        if theta <= TOL_CONTRACTION and theta * delta <= (1.0 - theta) * tol * scale:
            return POLISH
    if delta >= hist[0]:
        if (delta <= ROUNDOFF_ULPS * EPS * max(scale, max_abs2(F)) or delta <= floor
                or hstate <= STATE_ULPS):
            return POLISH
        hist[1] += 1.0
        if hist[1] >= 2.0:
            return -DIVERGED
    else:
        theta = max(hist[2], hist[3])
        if (theta <= STRONG_CONTRACTION
                and theta * theta * hist[0] <= EXTRAPOLATED_ULPS * EPS * scale
                and (delta <= floor or hstate <= STATE_ULPS
                     or delta <= ROUNDOFF_ULPS * EPS * max(scale, max_abs2(F)))):
            return POLISH
    hist[3] = hist[2]
    hist[2] = delta / hist[0] if np.isfinite(hist[0]) else np.inf
    hist[0] = delta
    return ITERATE


@jit
def commit_separable(y, cy, minv, h, g, X0, X0_lo, dq, dq_lo):
    """y1 from the converged coefficients, added exactly to the double-double state:
    q += h v + h (h xg) / m with v = (p - cp) / m and xg = (X_s gamma_p)_1; p += h gamma_1."""
    s, m = g.shape
    for j in range(m):
        xg = 0.0
        for l in range(s):
            xg += X0[l] * g[l, j] + X0_lo[l] * g[l, j]
        v_hi, v_lo = two_product(y[m + j], minv[j])
        v_lo -= cy[m + j] * minv[j]
        a_hi, a_lo = two_product(h, v_hi)
        a_lo += h * v_lo
        b = h * (h * xg) * minv[j]
        i_hi, i_lo = two_sum(a_hi, b)
        dq[j] = i_hi
        dq_lo[j] = a_lo + i_lo
    for j in range(m):
        dd_add(y, cy, j, dq[j], dq_lo[j])
    for j in range(m):
        d_hi, d_lo = two_product(h, g[0, j])
        dd_add(y, cy, m + j, d_hi, d_lo)


@jit
def commit_full(y, cy, h, g):
    """y1 = y0 + h gamma_1, added exactly to the double-double state."""
    for j in range(g.shape[1]):
        d_hi, d_lo = two_product(h, g[0, j])
        dd_add(y, cy, j, d_hi, d_lo)


@jit
def work_sizes(n, s, u, m, d):
    """(float, complex) lengths of the work buffers :func:`carve` cuts for k = n stages, s
    coefficient blocks of width u, m masses and a state of length d."""
    return 4 * n + 5 + 2 * m + 3 * s * u + 5 * n * u + 2 * d + 5 * min(u, BLOCK), 2 * s * u


@jit
def follower_size(n, s, us, w, P):
    """The length of the float buffer of a step with P followers of w columns each
    (:mod:`integrators.loop`): the sources' block (us columns: state, masses, coefficients,
    stage values and forces and their previous iterates) and one group of followers (at most
    FOLLOWER_GROUP of them: the same plus their final coefficients, the columns' increments and
    sizes, and ten numbers each for their own stop rule)."""
    g = min(P, FOLLOWER_GROUP)
    up = w * g
    return 5 * us + 2 * s * us + 4 * n * us + 7 * up + 3 * s * up + 4 * n * up + 10 * g


@jit
def carve(work, cwork, n, s, u, m, d):
    """The step's work arrays as views of two buffers (one array argument each instead of
    eighteen, which a host calling one step at a time pays for: about 0.1 microsecond each to
    unbox, or to allocate): ht, ht_lo (n), hist (5), dq, dq_lo (m), a, pg, g (s, u), X, F, G,
    Xp, Fp (n, u), yt, cyt (d), R (5, min(u, BLOCK)) (scratch of the column sums), Rt, Z (s, u)
    complex.  The views are :func:`integrators.pointers.view`'s (no reference counts, no call:
    about 1 ns for all, against 0.7 microsecond with slices and reshapes); a buffer shorter than
    :func:`work_sizes` says is refused, since a view past its end would not be."""
    nf, nc = work_sizes(n, s, u, m, d)
    if work.shape[0] < nf or cwork.shape[0] < nc:
        raise ValueError("internal error: the step's work buffers are shorter than "
                         "core.work_sizes says")
    ht = view1(work, 0, n)
    ht_lo = view1(work, n, n)
    o = 2 * n
    hist = view1(work, o, 5)
    dq = view1(work, o + 5, m)
    dq_lo = view1(work, o + 5 + m, m)
    o += 5 + 2 * m
    yt = view1(work, o, d)
    cyt = view1(work, o + d, d)
    o += 2 * d
    a = view(work, o, s, u)
    pg = view(work, o + s * u, s, u)
    g = view(work, o + 2 * s * u, s, u)
    o += 3 * s * u
    X = view(work, o, n, u)
    F = view(work, o + n * u, n, u)
    G = view(work, o + 2 * n * u, n, u)
    Xp = view(work, o + 3 * n * u, n, u)
    Fp = view(work, o + 4 * n * u, n, u)
    o += 5 * n * u
    R = view(work, o, 5, min(u, BLOCK))
    Rt = view(cwork, 0, s, u)
    Z = view(cwork, s * u, s, u)
    return ht, ht_lo, hist, dq, dq_lo, a, pg, g, X, F, G, Xp, Fp, yt, cyt, R, Rt, Z


@jit
def fail(counters, status, work_iter, work_nfev, work_newton):
    """Take a failed step's work back out of the counters (they count committed steps; the
    failure's iterations stay in counters[C_LASTIT] for the error) and return its status (the
    status travels as the return value, never in the counters)."""
    counters[C_ITER] = work_iter
    counters[C_NFEV] = work_nfev
    counters[C_NEWTON] = work_newton
    return status


@jit
def monomial_weight(j):
    """c_j = int_0^1 P_j(x) x^j dx = (j!)^2 sqrt(2j + 1) / (2j + 1)!, P_j the orthonormal shifted
    Legendre polynomial: the Legendre coefficient of a polynomial's (t / h)^j term (its highest)."""
    c = 1.0
    for i in range(1, j + 1):
        c *= i * i / ((2.0 * i) * (2.0 * i + 1.0))
    return c * np.sqrt(2.0 * j + 1.0)


@jit
def step_error(gamma, w):
    """The size of the highest term of a step's force polynomial from its own coefficients, at
    no extra evaluation: max |w gamma_{s-1}| / (c_{s-1} max |w gamma_0|), a^(s-1) h^(s-1) /
    (s-1)! relative to the force over the step (the kind of quantity IAS15 makes its step
    from: its last coefficient b6 against the acceleration, for a polynomial of degree 7 where
    this one has degree s - 1).  gamma_j = int_0^1 P_j(x) f(y(xh)) dx starts with
    c_j a^(j) h^j / j! (:func:`monomial_weight`), so it grows like h^(s-1), and the step's own
    error, O(h^(2s+1)), is about its power 2s / (s-1) times the motion over the step: one bound
    on it asks for different accuracies at different s, so the adaptive control no longer uses
    it (until issue 58 it did; :func:`adapt_step` controls :func:`resolution_error`); the test
    particles' checks (:func:`test_particle_error`, :func:`test_particle_control`) compare it
    between bodies of one step.
    For the separable form w = 1/m turns the forces into accelerations, so that light bodies
    count as much as heavy ones (a planetesimal's encounter is invisible in its tiny forces),
    and test particles (w = 1) are part of it; with w empty (the full form) the coefficients
    are taken as they are.  Both maxima run over every coordinate of the state.  0 when gamma_0
    vanishes."""
    s, u = gamma.shape
    weighted = w.shape[0] == u
    top = 0.0
    low = 0.0
    for j in range(u):
        c = w[j] if weighted else 1.0
        if abs(c * gamma[s - 1, j]) > top:
            top = abs(c * gamma[s - 1, j])
        if abs(c * gamma[0, j]) > low:
            low = abs(c * gamma[0, j])
    if low == 0.0:
        return 0.0
    return top / (monomial_weight(s - 1) * low)


@jit
def sources_terms(gamma, w, kin_w):
    """(max |w gamma_{s-1}|, max |w gamma_0|) over the gravitating coordinates (kin_w != 0):
    the highest and the first force coefficient of the sources, as accelerations."""
    s, u = gamma.shape
    top = 0.0
    low = 0.0
    for j in range(u):
        if kin_w[j] != 0.0:
            if abs(w[j] * gamma[s - 1, j]) > top:
                top = abs(w[j] * gamma[s - 1, j])
            if abs(w[j] * gamma[0, j]) > low:
                low = abs(w[j] * gamma[0, j])
    return top, low


@jit
def particle_terms(gamma, i):
    """(max |gamma_{s-1}|, max |gamma_0|) over particle i's three coordinates: its highest and
    its first force coefficient (a test particle's are accelerations)."""
    s = gamma.shape[0]
    t = 0.0
    lo = 0.0
    for c in range(3 * i, 3 * i + 3):
        if abs(gamma[s - 1, c]) > t:
            t = abs(gamma[s - 1, c])
        if abs(gamma[0, c]) > lo:
            lo = abs(gamma[0, c])
    return t, lo


@jit
def test_particle_error(gamma, w, kin_w, floor, factor, source_floor=0.0):
    """A fixed step's check of its test particles, from its own coefficients (no evaluation).

    Each test particle's own estimate, :func:`step_error` over its three coordinates (its
    accelerations: a comet's encounter is invisible against the sources' maxima), against
    ``max(floor, factor * e)``, e the sources' :func:`step_error` (weights w) of the same step:
    a test particle resolved far worse than the bodies it moves among.  ``source_floor`` > 0:
    each gravitating body too, against ``source_floor`` (for a step whose energy check cannot
    see an unresolved encounter: a smooth potential, which HBVM conserves at any step, or no H
    at all).  gamma: (s, 3N); w, kin_w: (3N,), kin_w 0 for the test particles.  Returns (the
    worst offending particle's index, or -1, its estimate, the bound it exceeds)."""
    s, u = gamma.shape
    cw = monomial_weight(s - 1)
    top, low = sources_terms(gamma, w, kin_w)
    bound = floor
    if low > 0.0 and factor * top / (cw * low) > bound:
        bound = factor * top / (cw * low)
    worst = -1
    worst_err = 0.0
    worst_bound = bound
    for i in range(u // 3):
        b = bound
        if kin_w[3 * i] != 0.0:
            if source_floor <= 0.0:
                continue
            b = source_floor
        t, lo = particle_terms(gamma, i)
        err = t / (cw * lo) if lo > 0.0 else (np.inf if t > 0.0 else 0.0)
        if err > b and err > worst_err:
            worst = i
            worst_err = err
            worst_bound = b
    return worst, worst_err, worst_bound


@jit
def test_particle_control(gamma, w, kin_w, err_sources):
    """The adaptive control's estimate (:func:`adapt_step`) for the test particles (kin_w 0),
    which the step solves as followers and whose omitted Legendre term it does not compute:
    each test particle's ratio r_i of its highest force coefficient to its force
    (:func:`step_error` over its three coordinates) against the sources' r, taken to the power
    of the local error, err_sources (r_i / r)^((2s+1)/(s-1)): r goes like (omega h)^(s-1) and
    the local error like (omega h)^(2s+1) for the same step h, so a comet in an encounter
    (omega large) counts as its own motion would.  Returns the largest of err_sources and the
    test particles' values; err_sources for s = 1 (r is then 1) or no test particle."""
    s, u = gamma.shape
    if s < 2:
        return err_sources
    cw = monomial_weight(s - 1)
    top, low = sources_terms(gamma, w, kin_w)
    if not (low > 0.0 and top > 0.0):
        return err_sources
    r = top / (cw * low)
    p = (2.0 * s + 1.0) / (s - 1.0)
    out = err_sources
    for i in range(u // 3):
        if kin_w[3 * i] != 0.0:
            continue
        t, lo = particle_terms(gamma, i)
        if lo > 0.0:
            e = err_sources * (t / (cw * lo) / r) ** p
            if e > out:
                out = e
    return out


@jit
def extrapolation_matrix(r, t, w, E):
    """E_ij = int_0^1 P_i(x) P_j(1 + r x) dx by the s-point Gauss rule (t, w) on [0, 1], exact
    for these degrees: the previous step's polynomial continued over a step r times as long.
    P_j = sqrt(2j + 1) L_j(2x - 1), the orthonormal shifted Legendre polynomials, by Bonnet's
    recurrence on L_j; the factors sqrt(2j + 1) and the recurrence's divisions are taken once,
    not at every node (an adaptive run computes E at every step: 1.2 -> 0.6 us for s = 6)."""
    s = E.shape[0]
    c = np.empty((4, s))        # Bonnet's coefficients, then L_j at x and at 1 + r x
    for j in range(s):
        c[0, j] = (2.0 * j + 1.0) / (j + 1.0)
        c[1, j] = j / (j + 1.0)
    for i in range(s):
        for j in range(s):
            E[i, j] = 0.0
    for q in range(t.shape[0]):
        z0 = 2.0 * t[q] - 1.0
        z1 = 2.0 * (1.0 + r * t[q]) - 1.0
        m0, l0, m1, l1 = 0.0, 1.0, 0.0, 1.0
        for j in range(s):
            c[2, j] = l0
            c[3, j] = l1
            m0, l0 = l0, c[0, j] * z0 * l0 - c[1, j] * m0
            m1, l1 = l1, c[0, j] * z1 * l1 - c[1, j] * m1
        for i in range(s):
            wa = w[q] * c[2, i]
            for j in range(s):
                E[i, j] += wa * c[3, j]
    for i in range(s):
        c[2, i] = np.sqrt(2.0 * i + 1.0)
    for i in range(s):
        for j in range(s):
            E[i, j] *= c[2, i] * c[2, j]


@jit
def next_step(h, err, epsilon, s, safety=0.7, shrink=0.2, grow=2.0):
    """The step size a controller proposes after a step of size h whose estimated local error
    (:func:`resolution_error`, relative to the motion over the step) is err:
    h (epsilon / err)^(1 / (2s + 1)) times ``safety``, limited to [shrink h, grow h].  The
    exponent is the local error's own: a step of order 2s errs like (omega h)^(2s+1) (omega the
    motion's local frequency), so this is the step whose error lands at epsilon; it is defined
    for every s >= 1 (s = 1, the midpoint rule and HBVM(k, 1): 1/3)."""
    if not err > 0.0:
        return h * grow
    f = safety * (epsilon / err) ** (1.0 / (2.0 * s + 1.0))
    return h * min(grow, max(shrink, f))


FAILURE_SHRINK = 0.25      # a step whose iteration or a check failed is tried again this much shorter


@jit
def adapt_step(h, status, err, epsilon, s, t, min_dt):
    """The one step-size controller of every host (the engine's adaptive runs, REBOUND's and
    ASE's steps through :func:`integrators.loop.attempt`), called once per attempted step:
    (accept, the next step to try, too small).

    err is the step's own estimate of its local error relative to the motion over the step
    (:func:`resolution_error`, the quantity the step's resolution check bounds by
    :data:`ERROR_BOUND`), so that epsilon asks for the same accuracy whatever s is: each step
    keeps its own motion to about epsilon.  A converged step (status OK) is accepted when err
    is at most epsilon, and the next step is :func:`next_step`'s, h (epsilon / err)^(1/(2s+1))
    times 0.7, as the local error of an order-2s step goes like h^(2s+1).  A step refused by
    its own resolution check (NOT_RESOLVED, err known and above the bound) is retried at
    :func:`next_step`'s shorter step; any other failure (its iteration, the energy check) is
    retried FAILURE_SHRINK times as long.  (The shape of diffrax's ``adapt_step_size``, an
    error-per-step controller; IAS15 instead takes its step from the ratio of its last
    coefficient b6 to the acceleration to the power 1/7, and its ``predict_next_step``
    predicts the next step's coefficients, not its size.)  ``too small``: the step to try
    next would fall below min_dt or no longer change t (steps shrinking into a collision)."""
    if status == OK:
        h_new = next_step(h, err, epsilon, s)
        if err <= epsilon:
            return True, h_new, False
    elif status == NOT_RESOLVED and err > 0.0 and err < np.inf:
        h_new = next_step(h, err, epsilon, s)
    else:
        h_new = FAILURE_SHRINK * h
    return False, h_new, abs(h_new) < min_dt or h_new == 0.0 or t + h_new == t


@jit
def select_extrapolation(h, h_prev, E1, t, w, buf, zero):
    """The initial guess's matrix E(h / h_prev) for every caller of the step (h_prev nan: no
    previous step): E1 = E(1) when the step is unchanged; a sliver of a step (exact finish
    times, |r| < TINY_RATIO) takes the previous polynomial's end value (r = 0); a step more than
    MAX_EXTRAPOLATION times longer starts from zero (``zero``); any other ratio is computed into
    ``buf``.  (t, w): the s-point Gauss rule on [0, 1]."""
    if np.isnan(h_prev) or h == h_prev:
        return E1
    r = h / h_prev
    if abs(r) > MAX_EXTRAPOLATION:
        return zero
    if abs(r) < TINY_RATIO:
        r = 0.0
    extrapolation_matrix(r, t, w, buf)
    return buf


@jit
def tick(t, ct, h):
    """Compensated t += h; returns (t, ct)."""
    yk = h - ct
    tn = t + yk
    return tn, (tn - t) - yk


@jit
def legendre_at(s, c):
    """P_s(c), the orthonormal shifted Legendre polynomial of degree s on [0, 1] (Bonnet's
    recurrence on L_j(2c - 1))."""
    x = 2.0 * c - 1.0
    lm, l0 = 0.0, 1.0
    for j in range(s):
        lm, l0 = l0, ((2.0 * j + 1.0) * x * l0 - j * lm) / (j + 1.0)
    return np.sqrt(2.0 * s + 1.0) * l0


@jit
def omitted_coefficient(W, tau, F, om):
    """om <- the first Legendre coefficient the step leaves out of its right-hand side,
    int_0^1 P_s(c) f(sigma(ch)) dc, by the step's own k-point rule on its stage values F (k, u)
    (k > s: the rule (b_i = W[0, i], c_i = tau_i) integrates P_s times the interpolant of the
    stage values exactly; at k = s the Gauss nodes are the zeros of P_s and this is 0, so the
    step uses :func:`endpoint_defect` instead).  No evaluation: O(k u)."""
    s = W.shape[0]
    n, u = F.shape
    for j in range(u):
        om[j] = 0.0
    for i in range(n):
        w = W[0, i] * legendre_at(s, tau[i])
        for j in range(u):
            om[j] += w * F[i, j]


@jit
def endpoint_defect(g, f1, om):
    """om <- (f(y1) - sigma'(h)) / sqrt(2s + 1) from f1 = f(y1), the right-hand side at the
    step's end (one evaluation): sigma'(h) = sum_j P_j(1) gamma_j with P_j(1) = sqrt(2j + 1),
    and the defect f(sigma) - sigma' = sum_{j >= s} P_j gamma_j^true is led at c = 1 by
    sqrt(2s + 1) gamma_s^true: the same first omitted coefficient as
    :func:`omitted_coefficient`, for the k = s steps (Gauss, EQUIP), whose nodes cannot see it."""
    s, u = g.shape
    r = 1.0 / np.sqrt(2.0 * s + 1.0)
    for j in range(u):
        acc = 0.0
        for l in range(s):
            acc += np.sqrt(2.0 * l + 1.0) * g[l, j]
        om[j] = (f1[j] - acc) * r


@jit
def body_motion(y, minv, g, h, j0, j1):
    """max(|v0|, |v1|) + |h gamma_0 / m| over coordinates j0 .. j1 - 1 (one body) of the
    separable form: the velocity a step keeps, for :func:`resolution_error`."""
    m = minv.shape[0]
    v0 = 0.0
    v1 = 0.0
    a0 = 0.0
    for j in range(j0, j1):
        v = y[m + j] * minv[j]
        dv = h * g[0, j] * minv[j]
        v0 += v * v
        v1 += (v + dv) * (v + dv)
        a0 += dv * dv
    return np.sqrt(max(v0, v1)) + np.sqrt(a0)


@jit
def mean_motion(y, minv, g, h, w):
    """The bodies' mean :func:`body_motion` (bodies of w coordinates; a last shorter group a
    body), 0 without bodies."""
    m = minv.shape[0]
    mean = 0.0
    nbody = 0
    for j0 in range(0, m, w):
        mean += body_motion(y, minv, g, h, j0, min(j0 + w, m))
        nbody += 1
    return mean / nbody if nbody > 0 else 0.0


@jit
def full_blocks_error(g, om, group):
    """:func:`resolution_error` of the full form for a state made of bodies (``group`` > 0
    coordinates each, in q and in p alike; a last shorter group is a block too): each body's
    block of q and of p judged by itself, d = max over the blocks of |om_b| / max_j |gamma_j,b|,
    so that a block whose terms are small beside the others' (a planet's momenta beside its
    positions, both beside a clock whose rate is 1: :mod:`systems.flow_composed`) is still
    seen.  A block whose coefficients are below eps times the largest anywhere is judged
    against that (round-off, not motion).  Returns (d^((2s+1)/s), the worst block's body)."""
    s, u = g.shape
    m = u // 2
    keep_all = 0.0
    for j in range(u):
        for l in range(s):
            if abs(g[l, j]) > keep_all:
                keep_all = abs(g[l, j])
    floor = EPS * keep_all
    d = 0.0
    worst = -1
    for half in range(2):
        b = 0
        for j0 in range(half * m, (half + 1) * m, group):
            top = 0.0
            keep = floor
            for j in range(j0, min(j0 + group, (half + 1) * m)):
                if abs(om[j]) > top:
                    top = abs(om[j])
                for l in range(s):
                    if abs(g[l, j]) > keep:
                        keep = abs(g[l, j])
            if top > 0.0:
                e = top / keep if keep > 0.0 else np.inf
                if e > d or worst < 0:
                    d = e
                    worst = b
            b += 1
    return d ** ((2.0 * s + 1.0) / s), worst


@jit
def resolution_error(full, y, minv, g, om, h, group):
    """The step's own estimate of its relative local error, from its coefficients g (s, u) and
    the first omitted one om (:func:`omitted_coefficient`, :func:`endpoint_defect`); returns
    (estimate, worst body).

    The defect d of the step's path: separable form, body by body (``group`` coordinates each;
    a last shorter group is a body too), d = |h om / m| / (max(|v0|, |v1|) + |h gamma_0 / m|),
    Euclidean norms over the body's coordinates, v0 = p0 / m, v1 = v0 + h gamma_0 / m: the
    first Legendre term the step leaves out of the body's velocity over the step (h times its
    acceleration's) against the velocity it keeps (:func:`body_motion`, or the bodies' mean
    when larger: a body nearly at rest is judged against the motion around it); dimensionless,
    independent of the energy, and not fooled by a force that passes through zero (an atom
    crossing its equilibrium: its velocity is largest there).  Full form (no bodies):
    d = max |om| / max |gamma_j| over the whole state, the first omitted term of y' against
    the largest kept (with ``group`` > 0, body by body: :func:`full_blocks_error`).  0 for a
    body at rest
    in no force.  With omega the motion's local frequency, d ~ (omega h)^(s+1) (full form:
    (omega h)^s, y' itself keeps s terms) while the step's local error (order 2s) is
    ~ (omega h)^(2s+1): the estimate returned is d^((2s+1)/(s+1)) (full form: d^((2s+1)/s)),
    the local error relative to the motion over the step, in the same units for every s (so
    one bound, :data:`ERROR_BOUND`, serves every method)."""
    s, u = g.shape
    worst = -1
    if full and group > 0:
        return full_blocks_error(g, om, group)
    if full:
        top = 0.0
        keep = 0.0
        for j in range(u):
            if abs(om[j]) > top:
                top = abs(om[j])
            for l in range(s):
                if abs(g[l, j]) > keep:
                    keep = abs(g[l, j])
        if top == 0.0:
            return 0.0, -1
        if keep == 0.0:
            return np.inf, 0
        # (y' keeps s terms, so its first omitted one goes like (omega h)^s, a power less than
        # the separable form's velocity term: the local error is d^((2s+1)/s))
        return (top / keep) ** ((2.0 * s + 1.0) / s), 0
    m = minv.shape[0]
    w = group if group > 0 else m
    # the bodies' motion over the step, and its mean: a body nearly at rest (an atom of a
    # relaxed slab, a particle released from rest in no force) is judged against the mean
    # motion of the bodies, not its own vanishing one, whose ratio to round-off-sized terms
    # means nothing
    mean = mean_motion(y, minv, g, h, w)
    err = 0.0
    b = 0
    for j0 in range(0, m, w):
        num = 0.0
        for j in range(j0, min(j0 + w, m)):
            x = h * om[j] * minv[j]
            num += x * x
        if num > 0.0:
            den = max(body_motion(y, minv, g, h, j0, min(j0 + w, m)), mean)
            e = np.sqrt(num) / den if den > 0.0 else np.inf
            if e > err or worst < 0:
                err = e
                worst = b
        b += 1
    return err ** ((2.0 * s + 1.0) / (s + 1.0)), worst


@jit
def run_error_share(full, y, minv, g, h, err, worst, group, s):
    """The share of its motion the step's worst body (:func:`resolution_error`'s ``worst``)
    turns over the step, w in [0, 1]: |h gamma_0 / m| / (max(|v0|, |v1|) + |h gamma_0 / m|)
    (:func:`body_motion`, against the bodies' mean when larger, as the estimate is), about
    omega h for a body on a path of local frequency omega.  The run's accumulated error adds
    err * w a step (C_RUN_ERR): a step's estimate is its local error relative to the motion over
    the step (|v| h), and |v| h / (|v| / omega) = omega h, so err * w is the step's error
    relative to the motion's own scale (|v| / omega: an orbit's radius, an oscillation's
    amplitude), and the sum over steps that scale's relative error when the steps' errors add
    (the phase of a periodic orbit).  A body at rest in no force turns nothing (w = 0).  Full
    form: (err^(s / (2s + 1)))^(1 / s), d^(1/s) ~ omega h from the defect d ~ (omega h)^s,
    at most 1."""
    if not err > 0.0:
        return 0.0
    if not err < np.inf:
        return 1.0
    if full or worst < 0:
        return min(1.0, err ** (1.0 / (2.0 * s + 1.0)))
    m = minv.shape[0]
    w = group if group > 0 else m
    mean = mean_motion(y, minv, g, h, w)
    j0 = worst * w
    if j0 >= m:
        return 1.0
    j1 = min(j0 + w, m)
    dv = 0.0
    for j in range(j0, j1):
        x = h * g[0, j] * minv[j]
        dv += x * x
    den = max(body_motion(y, minv, g, h, j0, j1), mean)
    return min(1.0, np.sqrt(dv) / den) if den > 0.0 else 1.0


@jit
def suggested_step(h, err, bound, s):
    """A step whose estimate (:func:`resolution_error`) would meet ``bound``, taken safely: the
    estimate falls like h^(2s+1) once the step resolves the motion but only like h^(s+1) or
    slower from a step far too long (measured: HBVM(3, 2) at e = 0.99, a third of the step
    took the estimate from 3.4e-2 to 1.4e-3, a slope of 3, not 5), so
    0.5 h (bound / err)^(1 / (s + 1))."""
    if not err > 0.0:
        return h
    return 0.5 * h * (bound / err) ** (1.0 / (s + 1.0))
