"""Compiled fast path for separable Hamiltonians (numba, ``cache=True``).

The whole integration loop of :class:`integrators.forms.SeparableForm` with fixed-point
iteration runs in one compiled function.  The force and potential are numba ``cfunc`` kernels
(signatures in :mod:`systems.base`), passed as first-class function values: the compiled loop is
typed by the kernels' signature, not their identity, so it is compiled once and cached on disk
for every system.
"""
from __future__ import annotations

import numpy as np
from numba import njit

EPS = np.finfo(float).eps
DECREASE = 2.0 ** -30   # same stopping rule as integrators.solvers.StopRule

# status codes of the compiled loop
OK, DIVERGED, NOT_FINITE = 0, 1, 2


def coefficients(method) -> tuple:
    """The method's arrays in the order :func:`integrate_separable` takes them:
    (tau, tau_lo, W, W_lo, C2, C2_lo, X0, X0_lo, E), contiguous float64."""
    c = np.ascontiguousarray
    return (c(method.tau), c(method.tau_lo), c(method.W), c(method.W_lo), c(method.C2),
            c(method.C2_lo), c(method.X[0]), c(method.X_lo[0]), c(method.E))


@njit(cache=True)
def two_product(a, b):
    """a * b = hi + lo exactly (Dekker's product with Veltkamp splitting; no FMA needed)."""
    p = a * b
    c = 134217729.0 * a
    ah = c - (c - a)
    al = a - ah
    c = 134217729.0 * b
    bh = c - (c - b)
    bl = b - bh
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


@njit(cache=True)
def two_sum(a, b):
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


@njit(cache=True)
def _dd_add(x, c, j, inc_hi, inc_lo):
    """x[j] - c[j] (a double-double: c holds minus the low part) += inc_hi + inc_lo."""
    s, e = two_sum(x[j], inc_hi)
    lo = (e + inc_lo) - c[j]
    hi = s + lo
    c[j] = -(lo - (hi - s))
    x[j] = hi


@njit(cache=True)
def _energy(potential, params, q, p, minv):
    ke = 0.0
    for i in range(p.shape[0]):
        ke += 0.5 * p[i] * p[i] * minv[i]
    return ke + potential(q, params)


@njit(cache=True)
def integrate_separable(force, potential, params, q, p, cq, cp, minv, h, nsteps, sample_every,
                        t0, tau, tau_lo, W, W_lo, C2, C2_lo, X0, X0_lo, E, max_iter, plateau, tol,
                        out_t, out_q, out_p, out_e, counters, gamma):
    """Integrate ``nsteps`` steps in place.

    q, p, cq, cp : the state as double-double numbers q - cq, p - cp (cq, cp hold minus the low
    parts, as a Kahan compensation does); updated in place, left at the last completed step on
    failure.  gamma (s, m): the momentum coefficients of the previous step, or all
    zero to start from f(q0).  counters: [steps done, iterations, stage evaluations, status,
    last increment].  Samples at steps 0, sample_every, 2 sample_every, ... go to out_*.
    The method's arrays come from :func:`coefficients`.

    Products of two constants (h * h, h * tau_i) are rounded the same way on every step: left
    as plain products they perturb the method itself by one ulp and the energy drifts linearly
    (measured: 3e-14 over 1000 Jupiter years of the outer solar system).  They are therefore
    carried as exact (hi, lo) pairs, like the coefficients.

    Round-off is kept unbiased and small, so that the energy error is a random walk (Brouwer's
    law) rather than a drift:

    * the state is a double-double number (q - cq, p - cp); the increments h v + h^2 xg / m and
      h gamma_1 are formed without rounding (two_product, two_sum) and added exactly, and the
      low parts enter the velocities and the stage positions;
    * once the iteration has converged, one more evaluation projects the stage forces with a
      compensated dot product (Dot2, with the remainders W_lo) rounded once.  Its rounding is
      what the step keeps; a plain sum followed by ``+ sum(W_lo F)`` loses the remainder
      (a sub-ulp correction added to an already rounded value) and leaves W's fixed rounding as
      a bias.  Likewise h^2 xg is formed as h (h xg), never with the rounded constant h * h.

    Measured (max relative energy error, median over 7 starts perturbed by 1e-13): outer solar
    system over 1e6 days with HBVM(7, 6), dt = 250: 6.2e-15 before these changes, 2.7e-15
    after (IAS15: 3.1e-15); Kepler e = 0.6, 1e6 steps of HBVM(6, 3): 1.6e-14 .. 2.8e-14 before,
    8e-15 .. 1.3e-14 after, with no sign of drift.  The cost is one force evaluation a step.
    """
    n, s = W.shape[1], W.shape[0]
    m = q.shape[0]
    Q = np.empty((n, m))
    F = np.empty((n, m))
    g = np.empty((s, m))
    a = np.empty((s, m))
    dq = np.empty(m)
    dq_lo = np.empty(m)
    t, ct = t0, 0.0
    h2, h2_lo = two_product(h, h)
    ht = np.empty(n)
    ht_lo = np.empty(n)
    for i in range(n):
        ht[i], lo = two_product(h, tau[i])
        ht_lo[i] = lo + h * tau_lo[i]
    isample = 0
    if sample_every > 0:
        out_t[0] = t
        out_q[0] = q
        out_p[0] = p
        out_e[0] = _energy(potential, params, q, p, minv)
        isample = 1
    started = False
    for i in range(s):
        for j in range(m):
            if gamma[i, j] != 0.0:
                started = True
    if not started:
        for i in range(n):
            Q[i] = q
        force(Q, params, F)
        counters[2] += n
        gamma[0] = F[0]
    for step in range(nsteps):
        # initial guess: the previous polynomial extrapolated over the new step
        for i in range(s):
            for j in range(m):
                acc = 0.0
                for l in range(s):
                    acc += E[i, l] * gamma[l, j]
                g[i, j] = acc
        prev = np.inf
        first = np.inf
        bad = 0
        converged = False
        polish = False
        it = 0
        delta = 0.0
        while polish or it < max_iter:
            it += 1
            for i in range(s):
                for j in range(m):
                    a[i, j] = g[i, j] * minv[j]
            for i in range(n):
                for j in range(m):
                    acc = 0.0
                    acc_lo = 0.0
                    for l in range(s):
                        acc += C2[i, l] * a[l, j]
                        acc_lo += C2_lo[i, l] * a[l, j]
                    vj = p[j] * minv[j]
                    Q[i, j] = q[j] + ht[i] * vj + ((ht_lo[i] * vj - cq[j]) - ht[i] * cp[j] * minv[j]
                                                   + h2 * (acc + acc_lo) + h2_lo * acc)
            force(Q, params, F)
            counters[2] += n
            # round-off scale of W @ F: the size of the terms (see solvers.StopRule.run)
            fmax = 0.0
            for i in range(n):
                for j in range(m):
                    if abs(F[i, j]) > fmax:
                        fmax = abs(F[i, j])
            if polish:
                # one compensated projection at the converged stages: the rounding of this
                # last evaluation is what the step keeps, so it is done as if in twice the
                # working precision (Dot2) and rounded once: no fixed coefficient rounding
                # survives as a bias, and the error is about half that of a plain sum
                for i in range(s):
                    for j in range(m):
                        acc = 0.0
                        acc_lo = 0.0
                        for l in range(n):
                            ph, pl = two_product(W[i, l], F[l, j])
                            acc, e = two_sum(acc, ph)
                            acc_lo += (e + pl) + W_lo[i, l] * F[l, j]
                        g[i, j] = acc + acc_lo
                converged = True
                break
            delta = 0.0
            scale = 0.0
            for i in range(s):
                for j in range(m):
                    acc = 0.0
                    acc_lo = 0.0
                    for l in range(n):
                        acc += W[i, l] * F[l, j]
                        acc_lo += W_lo[i, l] * F[l, j]
                    v = acc + acc_lo
                    d = abs(v - g[i, j])
                    if d > delta or d != d:
                        delta = d
                    if abs(v) > scale:
                        scale = abs(v)
                    g[i, j] = v
            if not np.isfinite(delta):
                counters[3] = NOT_FINITE
                counters[4] = delta
                return
            if delta <= 2.0 * EPS * scale or delta <= tol * scale:
                polish = True
                continue
            if delta >= prev:
                if delta <= plateau * max(scale, fmax) or delta <= DECREASE * first:
                    polish = True
                    continue
                bad += 1
                if bad >= 2:
                    break
            if it == 1:
                first = delta
            prev = delta
        counters[1] += it
        if not converged:
            counters[3] = DIVERGED
            counters[4] = delta
            return
        for j in range(m):
            xg = 0.0
            for l in range(s):
                xg += X0[l] * g[l, j] + X0_lo[l] * g[l, j]
            # error-free increments into the double-double state: q += h v + h (h xg) / m
            # with v = (p - cp) / m; p += h gamma_1 (h (h xg): see the docstring)
            v_hi, v_lo = two_product(p[j], minv[j])
            v_lo -= cp[j] * minv[j]
            a_hi, a_lo = two_product(h, v_hi)
            a_lo += h * v_lo
            b = h * (h * xg) * minv[j]
            i_hi, i_lo = two_sum(a_hi, b)
            dq[j] = i_hi
            dq_lo[j] = a_lo + i_lo
        for j in range(m):
            _dd_add(q, cq, j, dq[j], dq_lo[j])
        for j in range(m):
            d_hi, d_lo = two_product(h, g[0, j])
            _dd_add(p, cp, j, d_hi, d_lo)
        for i in range(s):
            for j in range(m):
                gamma[i, j] = g[i, j]
        yk = h - ct
        tn = t + yk
        ct = (tn - t) - yk
        t = tn
        counters[0] += 1
        if sample_every > 0 and (step + 1) % sample_every == 0:
            out_t[isample] = t
            out_q[isample] = q
            out_p[isample] = p
            out_e[isample] = _energy(potential, params, q, p, minv)
            isample += 1
    counters[3] = OK
