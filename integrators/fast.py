"""Compiled fast path for separable Hamiltonians (numba, ``cache=True``).

The integration loop of :class:`integrators.forms.SeparableForm` with fixed-point iteration,
compiled.  The force and potential are numba ``cfunc`` kernels (signatures in
:mod:`systems.base`) passed as first-class function values: :func:`integrate_separable` is
typed by the kernels' signature, not their identity, so it is compiled once and cached on disk
for every system.

The step is built from small compiled pieces that take no function argument
(:func:`stage_positions`, :func:`project`, :func:`stop_action`, :func:`commit`), so that a
compiled caller with a kernel of its own can write the short iteration of :func:`solve_step`
again with a static call to that kernel: passing a kernel as a value would either cost about
5 us a call to unbox (a cfunc from Python) or, for a compiled kernel, embed its address and make
the caller uncachable (see ``hbvm_md.rebound_driver``).

Round-off is kept unbiased and small, so that the energy error is a random walk (Brouwer's law)
rather than a drift:

* products of two constants are never rounded once and reused: h * tau_i and h * h are carried as
  exact (hi, lo) pairs in the stage positions, and h^2 xg is formed as h (h xg).  Left as plain
  products they perturb the method itself by one ulp and the energy drifts linearly (measured:
  3e-14 over 1000 Jupiter years of the outer solar system);
* the state is a double-double number (q - cq, p - cp); the increments h v + h^2 xg / m and
  h gamma_1 are formed without rounding (two_product, two_sum) and added exactly, and the low
  parts enter the velocities and the stage positions;
* once the iteration has converged, one more evaluation projects the stage forces with a
  compensated dot product (Dot2, with the remainders W_lo) rounded once.  Its rounding is what
  the step keeps; a plain sum followed by ``+ sum(W_lo F)`` loses the remainder (a sub-ulp
  correction added to an already rounded value) and leaves W's fixed rounding as a bias.

Measured (max relative energy error, median over 7 starts perturbed by 1e-13): outer solar
system over 1e6 days with HBVM(7, 6), dt = 250: 6.2e-15 before the last two changes, 2.7e-15
after (IAS15: 3.1e-15); Kepler e = 0.6, 1e6 steps of HBVM(6, 3): 1.6e-14 .. 2.8e-14 before,
8e-15 .. 1.3e-14 after, with no sign of drift.  The cost is one force evaluation a step.
"""
from __future__ import annotations

import numpy as np
from numba import njit

EPS = np.finfo(float).eps
DECREASE = 2.0 ** -30   # same stopping rule as integrators.solvers.StopRule

# status codes of the compiled loop
OK, DIVERGED, NOT_FINITE = 0, 1, 2
# what the iteration does next (stop_action)
ITERATE, POLISH = 0, 1


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
    """a + b = s + e exactly (Knuth)."""
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
def all_zero(a):
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            if a[i, j] != 0.0:
                return False
    return True


@njit(cache=True)
def kinetic(p, minv):
    """p^T M^{-1} p / 2."""
    ke = 0.0
    for i in range(p.shape[0]):
        ke += 0.5 * p[i] * p[i] * minv[i]
    return ke


@njit(cache=True)
def step_constants(h, tau, tau_lo, ht, ht_lo):
    """h * tau_i as exact pairs (ht, ht_lo) and h * h as an exact pair, returned."""
    for i in range(tau.shape[0]):
        ht[i], lo = two_product(h, tau[i])
        ht_lo[i] = lo + h * tau_lo[i]
    return two_product(h, h)


@njit(cache=True)
def guess(E, gamma, g):
    """g = E gamma: the previous step's polynomial extrapolated over the new step."""
    s, m = g.shape
    for i in range(s):
        for j in range(m):
            acc = 0.0
            for l in range(s):
                acc += E[i, l] * gamma[l, j]
            g[i, j] = acc


@njit(cache=True)
def stage_positions(q, p, cq, cp, minv, g, C2, C2_lo, ht, ht_lo, h2, h2_lo, a, Q):
    """Q = q0 + h tau v0 + h^2 (I_s X_s) M^{-1} gamma_p (see forms.SeparableForm)."""
    s, m = g.shape
    n = Q.shape[0]
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


@njit(cache=True)
def project(W, W_lo, F, g):
    """g <- W F (plain sums); returns (max |increment|, max |g|, max |F|)."""
    s, m = g.shape
    n = F.shape[0]
    fmax = 0.0
    for i in range(n):
        for j in range(m):
            if abs(F[i, j]) > fmax:
                fmax = abs(F[i, j])
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
    return delta, scale, fmax


@njit(cache=True)
def project_compensated(W, W_lo, F, g):
    """g <- W F as if in twice the working precision (Dot2), rounded once."""
    s, m = g.shape
    n = F.shape[0]
    for i in range(s):
        for j in range(m):
            acc = 0.0
            acc_lo = 0.0
            for l in range(n):
                ph, pl = two_product(W[i, l], F[l, j])
                acc, e = two_sum(acc, ph)
                acc_lo += (e + pl) + W_lo[i, l] * F[l, j]
            g[i, j] = acc + acc_lo


@njit(cache=True)
def stop_action(delta, scale, fmax, it, hist, tol, plateau):
    """The stopping rule of :class:`integrators.solvers.StopRule`, one increment at a time.

    hist = [previous increment, first increment, stalls above round-off], updated.  Returns
    ITERATE, POLISH (converged: one compensated evaluation to go), DIVERGED or NOT_FINITE (as
    negative codes -DIVERGED, -NOT_FINITE)."""
    if not np.isfinite(delta):
        return -NOT_FINITE
    if delta <= 2.0 * EPS * scale or delta <= tol * scale:
        return POLISH
    if delta >= hist[0]:
        if delta <= plateau * max(scale, fmax) or delta <= DECREASE * hist[1]:
            return POLISH
        hist[2] += 1.0
        if hist[2] >= 2.0:
            return -DIVERGED
    if it == 1:
        hist[1] = delta
    hist[0] = delta
    return ITERATE


@njit(cache=True)
def commit(q, p, cq, cp, minv, h, g, X0, X0_lo, gamma, dq, dq_lo):
    """y1 from the converged coefficients, added exactly to the double-double state:
    q += h v + h (h xg) / m with v = (p - cp) / m and xg = (X_s gamma_p)_1; p += h gamma_1."""
    s, m = g.shape
    for j in range(m):
        xg = 0.0
        for l in range(s):
            xg += X0[l] * g[l, j] + X0_lo[l] * g[l, j]
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
    add_h_gamma1(p, cp, h, g, gamma)


@njit(cache=True)
def add_h_gamma1(x, c, h, g, gamma):
    """x - c (double-double) += h gamma_1 exactly; keep g as the step's coefficients gamma."""
    s, d = g.shape
    for j in range(d):
        d_hi, d_lo = two_product(h, g[0, j])
        _dd_add(x, c, j, d_hi, d_lo)
    for i in range(s):
        for j in range(d):
            gamma[i, j] = g[i, j]


@njit(cache=True)
def tick(t, ct, h):
    """Compensated t += h; returns (t, ct)."""
    yk = h - ct
    tn = t + yk
    return tn, (tn - t) - yk


@njit(cache=True)
def solve_step(force, params, q, p, cq, cp, minv, W, W_lo, C2, C2_lo, E, ht, ht_lo, h2, h2_lo,
               gamma, g, a, Q, F, hist, max_iter, plateau, tol, counters):
    """Solve one step's nonlinear system for g (from the guess E gamma); returns a status.

    counters[1] += iterations, counters[2] += stage evaluations, counters[4] = last increment.
    ``hbvm_md.rebound_driver._solve_nbody`` is this function with a static kernel call: keep
    the two alike."""
    n = Q.shape[0]
    guess(E, gamma, g)
    hist[0], hist[1], hist[2] = np.inf, np.inf, 0.0
    polish = False
    it = 0
    while polish or it < max_iter:
        it += 1
        stage_positions(q, p, cq, cp, minv, g, C2, C2_lo, ht, ht_lo, h2, h2_lo, a, Q)
        force(Q, params, F)
        counters[2] += n
        if polish:
            project_compensated(W, W_lo, F, g)
            counters[1] += it
            return OK
        delta, scale, fmax = project(W, W_lo, F, g)
        counters[4] = delta
        action = stop_action(delta, scale, fmax, it, hist, tol, plateau)
        if action == POLISH:
            polish = True
        elif action < 0:
            counters[1] += it
            return -action
    counters[1] += it
    return DIVERGED


@njit(cache=True)
def integrate_separable(force, potential, params, q, p, cq, cp, minv, h, nsteps, sample_every,
                        t0, tau, tau_lo, W, W_lo, C2, C2_lo, X0, X0_lo, E, max_iter, plateau, tol,
                        out_t, out_q, out_p, out_e, counters, gamma):
    """Integrate ``nsteps`` steps in place.

    q, p, cq, cp : the state as double-double numbers q - cq, p - cp (cq, cp hold minus the low
    parts, as a Kahan compensation does); updated in place, left at the last completed step on
    failure.  gamma (s, m): the momentum coefficients of the previous step, or all zero to start
    from f(q0).  counters: [steps done, iterations, stage evaluations, status, last increment].
    Samples at steps 0, sample_every, 2 sample_every, ... go to out_* (none if sample_every is
    0).  The method's arrays come from :func:`coefficients`.
    """
    n, s = W.shape[1], W.shape[0]
    m = q.shape[0]
    Q = np.empty((n, m))
    F = np.empty((n, m))
    g = np.empty((s, m))
    a = np.empty((s, m))
    dq = np.empty(m)
    dq_lo = np.empty(m)
    hist = np.empty(3)
    ht = np.empty(n)
    ht_lo = np.empty(n)
    h2, h2_lo = step_constants(h, tau, tau_lo, ht, ht_lo)
    t, ct = t0, 0.0
    isample = 0
    if sample_every > 0:
        out_t[0] = t
        out_q[0] = q
        out_p[0] = p
        out_e[0] = kinetic(p, minv) + potential(q, params)
        isample = 1
    if all_zero(gamma):        # no previous step: start from the forces at q0
        for i in range(n):
            Q[i] = q
        force(Q, params, F)
        counters[2] += n
        gamma[0] = F[0]
    for step in range(nsteps):
        status = solve_step(force, params, q, p, cq, cp, minv, W, W_lo, C2, C2_lo, E, ht, ht_lo,
                            h2, h2_lo, gamma, g, a, Q, F, hist, max_iter, plateau, tol, counters)
        if status != OK:
            counters[3] = status
            return
        commit(q, p, cq, cp, minv, h, g, X0, X0_lo, gamma, dq, dq_lo)
        t, ct = tick(t, ct, h)
        counters[0] += 1
        if sample_every > 0 and (step + 1) % sample_every == 0:
            out_t[isample] = t
            out_q[isample] = q
            out_p[isample] = p
            out_e[isample] = kinetic(p, minv) + potential(q, params)
            isample += 1
    counters[3] = OK


# -- the full form (any Hamiltonian with compiled kernels) -----------------------------------
@njit(cache=True)
def full_stages(y, cy, g, I, I_lo, h, Y):
    """Y = y0 + h I_s gamma at the stages, with y0 the double-double y - cy (forms.FullForm)."""
    n = Y.shape[0]
    s, d = g.shape
    for i in range(n):
        for j in range(d):
            acc = 0.0
            acc_lo = 0.0
            for l in range(s):
                acc += I[i, l] * g[l, j]
                acc_lo += I_lo[i, l] * g[l, j]
            Y[i, j] = y[j] + (h * (acc + acc_lo) - cy[j])


@njit(cache=True)
def _symplectic(G, F):
    """F = J G with J = [[0, I], [-I, 0]]: (dH/dp, -dH/dq) from G = grad H, row by row."""
    m = G.shape[1] // 2
    for i in range(G.shape[0]):
        for j in range(m):
            F[i, j] = G[i, m + j]
            F[i, m + j] = -G[i, j]


@njit(cache=True)
def integrate_full(gradient, energy, params, y, cy, h, nsteps, sample_every, t0, W, W_lo, I, I_lo,
                   E, max_iter, plateau, tol, out_t, out_y, out_e, counters, gamma):
    """The full form compiled: ``gradient`` writes grad H at each row of Y (n, d) (signature of
    ``systems.base.FORCE_SIGNATURE``), ``energy`` returns H(y) (``POTENTIAL_SIGNATURE``).

    Same conventions as :func:`integrate_separable` (double-double state y - cy, counters,
    samples, gamma (s, d)), with the same unbiased round-off: y1 = y0 + h gamma_1 added
    exactly, the last projection compensated.
    """
    n, s = W.shape[1], W.shape[0]
    d = y.shape[0]
    Y = np.empty((n, d))
    G = np.empty((n, d))
    F = np.empty((n, d))
    g = np.empty((s, d))
    hist = np.empty(3)
    t, ct = t0, 0.0
    isample = 0
    if sample_every > 0:
        out_t[0] = t
        out_y[0] = y
        out_e[0] = energy(y, params)
        isample = 1
    if all_zero(gamma):        # no previous step: start from f(y0)
        for i in range(n):
            Y[i] = y
        gradient(Y, params, G)
        _symplectic(G, F)
        counters[2] += n
        gamma[0] = F[0]
    for step in range(nsteps):
        guess(E, gamma, g)
        hist[0], hist[1], hist[2] = np.inf, np.inf, 0.0
        polish = False
        status = DIVERGED
        it = 0
        while polish or it < max_iter:
            it += 1
            full_stages(y, cy, g, I, I_lo, h, Y)
            gradient(Y, params, G)
            _symplectic(G, F)
            counters[2] += n
            if polish:
                project_compensated(W, W_lo, F, g)
                status = OK
                break
            delta, scale, fmax = project(W, W_lo, F, g)
            counters[4] = delta
            action = stop_action(delta, scale, fmax, it, hist, tol, plateau)
            if action == POLISH:
                polish = True
            elif action < 0:
                status = -action
                break
        counters[1] += it
        if status != OK:
            counters[3] = status
            return
        add_h_gamma1(y, cy, h, g, gamma)
        t, ct = tick(t, ct, h)
        counters[0] += 1
        if sample_every > 0 and (step + 1) % sample_every == 0:
            out_t[isample] = t
            out_y[isample] = y
            out_e[isample] = energy(y, params)
            isample += 1
    counters[3] = OK
