"""A planetary system transformed by its Keplerian flows: HBVM composed with them (issue 48).

The construction of the flow-composed implicit Runge-Kutta methods of Antonana, Makazaga and
Murua (FCIRK, J. Sci. Comput. 2018, arXiv 1711.06050), with HBVM(k, s) in place of Gauss.

Coordinates (democratic heliocentric, canonical): Q_i = x_i - x_0 the heliocentric positions
of the N planets, P_i = m_i v_i their barycentric momenta (v_i barycentric velocities).  With
the barycentre's motion removed the Hamiltonian is exactly

    H = H_K + H_I,   H_K = sum_i |P_i|^2 / (2 m_i) - G m_0 m_i / |Q_i|,
                     H_I = -sum_{i<j} G m_i m_j / |Q_i - Q_j| + |sum_i P_i|^2 / (2 m_0),

(plus, with ``gr_c``, REBOUNDx's GR potential -sum_i 3 (G m_0)^2 m_i / (c^2 |Q_i|^2) in
H_I: :func:`_gr_potential`), the split of WHFast's democratic heliocentric coordinates (REBOUND's
``reb_integrator_whfast`` with ``coordinates = "democraticheliocentric"``, whose Kepler drift
uses mu = G m_0): H_K is N uncoupled Kepler problems with mu = G m_0, whose flow phi_t
(all planets at once, :mod:`integrators.kepler_flow`) is known to round-off.

The transformed system.  Write the state as x = phi_tau(X).  Then x solves x' = J grad H(x)
exactly when X solves X' = J grad_X K(X, tau), tau' = 1, with K(X, tau) = H_I(phi_tau(X))
(phi_tau is symplectic, so the transformed system is Hamiltonian with the time-dependent K;
grad_X K = Phi^T grad H_I(phi_tau(X)), Phi the flow's state transition matrix).  Time enters
as one more canonical pair (tau, p_tau) of the extended Hamiltonian

    H~(X, tau, P, p_tau) = K(X, tau) + p_tau,     tau' = 1,  p_tau' = -dK/dtau,

so every Runge-Kutta method integrates tau exactly and the force kernel reads each stage's
time from its row: the transformed system is an ordinary full-form system of the one step
(:mod:`integrators.loop`), not a second step.  dK/dtau = grad H_I(x) . J grad H_K(x).

A step [t_n, t_n + h] runs tau from -h/2 to h/2 (FCIRK: the flows centred on the step, so that
the composition of the two half flows and the symmetric HBVM step is symmetric); the state
entering it is X_n = phi_{h/2}(x_n) and the state leaving it x_{n+1} = phi_{h/2}(X_{n+1}).
Between two steps the two half flows are one flow: :func:`composed_recentre` maps
X <- phi_{tau + h/2}(X), tau <- -h/2 after each committed step (the hook ``_recentre`` of
:mod:`integrators.loop`), which changes the representation, not the physical state.

What it keeps.  HBVM keeps H~ (to round-off for k large enough: K is not a polynomial), and
the recentring keeps it too (K(phi_h(X), -h/2) = K(X, h/2)).  The physical energy is
H = H_K(X) + K(X, tau), so H - H~ = H_K(X) - p_tau, an invariant of the exact flow that the
method does not keep: the physical energy's error is that of H_K(X) - p_tau, O(eps h^(2s)) a
step with eps the size of H_I against H_K (measured in benchmarks/results/kepler_composed.md).
p_tau starts at H_K(x_0), so that H~ starts at H.

The state as the step sees it: Y = (Q_1 .. Q_N, c tau, P_1 .. P_N, p_tau / c), dim = 3N + 1,
c the clock's rate (:class:`FlowComposed`'s ``clock_rate``, a power of 2, default 1: it scales
the clock's rows exactly and moves only the iteration's stop rule),
``body_dim = 3`` (the step's own error estimate then judges each planet's block of Q and of P
by itself, and the clock alone: :func:`integrators.core.resolution_error`).
"""
from __future__ import annotations

import math

import numpy as np

from integrators.core import two_sum
from integrators.double_double import dd_add_d, dd_div, dd_mul_d
from integrators.jit import jit
from integrators.kepler_flow import (SAVED, kepler_flow, kepler_pullback, kepler_step,
                                     kepler_step_saved, kepler_step_stm, kepler_step_stm_x)
from integrators.kepler_flow_dd import kepler_refine_dd

from .base import HamiltonianSystem

#: the modules whose compiled functions the kernels call (integrators.specialise hashes them
#: into the generated step's name, so that a change there is compiled afresh)
KERNEL_DEPENDS = ("integrators.kepler_flow", "integrators.kepler_flow_dd",
                  "integrators.double_double")
# params: [N, G, m_0, m_1 .. m_N, c, n, i_1 .. i_n, c_light, J2, J4, R_eq, w_x, w_y, w_z, A,
# gamma]: the masses; c the clock's rate
# (FlowComposed's clock_rate, 1 by default); then the massive planets' indices (0-based among
# the planets; the test particles, m = 0, are the others), so that a scene of many test
# particles costs O(n N) pairs, not O(N^2); then the speed of light of the GR potential term
# (FlowComposed's gr_c; 0: no such term, and not one operation more); then the star's
# gravitational harmonics [J2, J4, R_eq, w_x, w_y, w_z] (FlowComposed's harmonics, w the unit
# spin axis; J2 = 0: no such term) and its central force [A, gamma] (FlowComposed's central;
# A = 0: none): _FORCE_TERMS entries, each term skipped, not computed as zero, when absent
_HEAD = 3
_FORCE_TERMS = 9


@jit
def _header(params):
    """The kernels' params read once (layout above): (N, G, m_0, the planets' masses m_1 ..
    m_N, mu = G m_0, m = 3 N + 1 the coordinates of each half of the state)."""
    N = int(params[0])
    G = params[1]
    m0 = params[2]
    return N, G, m0, params[_HEAD:_HEAD + N], G * m0, 3 * N + 1


@jit
def _weight(mi):
    """The weight of a body's second half of the state, P = w V: its mass, 1 for a test
    particle (m = 0: its state is (Q, V), as :class:`systems.NBody`'s p = v)."""
    return mi if mi > 0.0 else 1.0


@jit
def _clock(params):
    """The clock's rate c (the state holds c tau and p_tau / c: :class:`FlowComposed`'s
    ``clock_rate``)."""
    return params[_HEAD + int(params[0])]


@jit
def _massive(params):
    """The massive planets' indices (as floats) from params (layout above)."""
    N = int(params[0])
    n = int(params[_HEAD + N + 1])
    return params[_HEAD + N + 2:_HEAD + N + 2 + n]


@jit
def _terms(params):
    """The force terms' block of params (layout above): [c_light, J2, J4, R_eq, w (3), A,
    gamma]."""
    N = int(params[0])
    k = _HEAD + N + 2 + int(params[_HEAD + N + 1])
    return params[k:k + _FORCE_TERMS]


@jit
def _harmonics(x, ms, mu, t, gx):
    """The star's zonal harmonics of REBOUNDx's ``gravitational_harmonics``
    (src/gravitational_harmonics.c) about the spin axis w (its ``Omega``, normalised as it
    does), a term of H_I: U = sum_i mu m_i [J2 R^2 P2(cos th) / r^3 + J4 R^4 P4(cos th) / r^5],
    r = |Q_i|, cos th = Q_i . w / r, t = [J2, J4, R_eq, w_x, w_y, w_z].  REBOUNDx applies the
    opposite force times m_i / m_0 to the star, so the pair's force is -grad of U(x_i - x_0) and
    U(Q_i) is exact in these coordinates.  Adds dU/dQ_i (per unit mass for a test particle,
    which REBOUNDx accelerates and whose mass weighs it out of U) to gx and returns U.  J4 = 0:
    no J4 term (REBOUNDx skips it, as it skips J2 = 0)."""
    j2, j4, R = t[0], t[1], t[2]
    wx, wy, wz = t[3], t[4], t[5]
    R2 = R * R
    u = 0.0
    for i in range(x.shape[0]):
        r2 = x[i, 0] * x[i, 0] + x[i, 1] * x[i, 1] + x[i, 2] * x[i, 2]
        r = np.sqrt(r2)
        w = x[i, 0] * wx + x[i, 1] * wy + x[i, 2] * wz
        c2 = (w / r) * (w / r)
        # the acceleration a = fq Q + fw w of REBOUNDx's j2_func / j4_func, written in the
        # frame of the scene (it rotates to the body's and back: the same vector)
        f1 = 1.5 * mu * j2 * R2 / (r2 * r2 * r)
        fq = f1 * (5.0 * c2 - 1.0)
        fw = -2.0 * f1 * w
        pot = mu * j2 * R2 / (r2 * r) * 0.5 * (3.0 * c2 - 1.0)
        if j4 != 0.0:
            f4 = 0.625 * mu * j4 * R2 * R2 / (r2 * r2 * r2 * r)
            f2 = 63.0 * c2 * c2 - 42.0 * c2 + 3.0
            fq += f4 * f2
            fw += f4 * (-28.0 * c2 + 12.0) * w
            pot += mu * j4 * R2 * R2 / (r2 * r2 * r) * 0.125 * (35.0 * c2 * c2 - 30.0 * c2 + 3.0)
        wi = 1.0
        if ms[i] > 0.0:
            wi = ms[i]
            u += ms[i] * pot
        gx[i, 0] -= wi * (fq * x[i, 0] + fw * wx)
        gx[i, 1] -= wi * (fq * x[i, 1] + fw * wy)
        gx[i, 2] -= wi * (fq * x[i, 2] + fw * wz)
    return u


@jit
def _central_force(x, ms, A, gamma, gx):
    """REBOUNDx's ``central_force`` from the star (src/central_force.c), a term of H_I: the
    acceleration A r^(gamma - 1) Q_i on each body, the opposite times m_i / m_0 on the star (so
    exact as U(Q_i) here, as :func:`_harmonics`), U = -sum_i m_i A r^(gamma + 1) / (gamma + 1)
    (-m_i A ln r when |gamma + 1| < DBL_EPSILON, as REBOUNDx's potential).  Adds dU/dQ_i (per
    unit mass for a test particle) to gx and returns U."""
    log = abs(gamma + 1.0) < 2.220446049250313e-16
    u = 0.0
    for i in range(x.shape[0]):
        r2 = x[i, 0] * x[i, 0] + x[i, 1] * x[i, 1] + x[i, 2] * x[i, 2]
        pre = A * r2 ** ((gamma - 1.0) / 2.0)
        wi = 1.0
        if ms[i] > 0.0:
            wi = ms[i]
            if log:
                u -= ms[i] * A * np.log(np.sqrt(r2))
            else:
                u -= ms[i] * A * r2 ** ((gamma + 1.0) / 2.0) / (gamma + 1.0)
        gx[i, 0] -= wi * pre * x[i, 0]
        gx[i, 1] -= wi * pre * x[i, 1]
        gx[i, 2] -= wi * pre * x[i, 2]
    return u


@jit
def _potential_terms(x, ms, mu, t, gx):
    """The potentials of params' force block t (:func:`_terms`) at heliocentric positions x:
    their gradients added to gx, their sum returned; an absent term costs one comparison."""
    u = 0.0
    if t[0] != 0.0:
        u += _gr_potential(x, ms, mu, t[0], gx)
    if t[1] != 0.0:
        u += _harmonics(x, ms, mu, t[1:7], gx)
    if t[7] != 0.0:
        u += _central_force(x, ms, t[7], t[8], gx)
    return u


@jit
def _gr_potential(x, ms, mu, light, gx):
    """The Nobili-Roxburgh potential of REBOUNDx's ``gr_potential`` (src/gr_potential.c), a
    term of H_I: U = -sum_i 3 mu^2 m_i / (c^2 |Q_i|^2), mu = G m_0, Q_i the heliocentric
    position (REBOUNDx's ``particles[i] - particles[0]``: always particle 0, no ``gr_source``).
    Adds dU/dQ_i = 6 mu^2 m_i Q_i / (c^2 |Q_i|^4) to gx (per unit mass for a test particle,
    whose rows are its own Hamiltonian's per unit mass: REBOUNDx accelerates it too) and returns
    U (a test particle is in no term of it, as in REBOUNDx's potential, which weighs by m_i).
    It depends on Q_i alone, so it leaves dH_I/dP (the star's momentum term) unchanged."""
    c2 = light * light
    pf = 6.0 * mu * mu / c2           # REBOUNDx's prefactors, as it writes them
    pu = 3.0 * mu * mu / c2
    u = 0.0
    for i in range(x.shape[0]):
        r2 = x[i, 0] * x[i, 0] + x[i, 1] * x[i, 1] + x[i, 2] * x[i, 2]
        c = pf / (r2 * r2)
        if ms[i] > 0.0:
            c *= ms[i]
            u -= pu * ms[i] / r2
        gx[i, 0] += c * x[i, 0]
        gx[i, 1] += c * x[i, 1]
        gx[i, 2] += c * x[i, 2]
    return u


@jit
def _interaction_gradient(x, v, ms, G, m0, gx, gp, massive):
    """grad H_I at heliocentric positions x (N, 3) and velocities v (N, 3): gx = dH_I/dQ (the
    planets' mutual attractions), gp = dH_I/dP (the same for every planet: sum P / m_0).
    Returns H_I.  A test particle (m = 0) is in no term of H_I; its rows are those of its own
    Hamiltonian per unit mass (the pull of the massive planets, indices ``massive``, and the same
    drift sum P / m_0), and nothing of it acts on the others."""
    N = x.shape[0]
    px = 0.0
    py = 0.0
    pz = 0.0
    for i in range(N):
        gx[i, 0] = 0.0
        gx[i, 1] = 0.0
        gx[i, 2] = 0.0
        px += ms[i] * v[i, 0]
        py += ms[i] * v[i, 1]
        pz += ms[i] * v[i, 2]
    hi = 0.5 * (px * px + py * py + pz * pz) / m0
    for i in range(N):
        # a massive planet meets every later body; a test particle only the later massive ones
        # (the massive pairs in the same order as without test particles: the same numbers)
        tp = not ms[i] > 0.0
        for jj in range(massive.shape[0] if tp else N - i - 1):
            j = int(massive[jj]) if tp else i + 1 + jj
            if j <= i:
                continue
            dx = x[i, 0] - x[j, 0]
            dy = x[i, 1] - x[j, 1]
            dz = x[i, 2] - x[j, 2]
            r2 = dx * dx + dy * dy + dz * dz
            if ms[i] > 0.0 and ms[j] > 0.0:
                r = np.sqrt(r2)
                gm = G * ms[i] * ms[j]
                hi -= gm / r
                c = gm / (r2 * r)
                gx[i, 0] += c * dx
                gx[i, 1] += c * dy
                gx[i, 2] += c * dz
                gx[j, 0] -= c * dx
                gx[j, 1] -= c * dy
                gx[j, 2] -= c * dz
            else:
                # a test particle and a planet: the pull per unit mass on the test particle
                r = np.sqrt(r2)
                if ms[i] > 0.0:
                    c = G * ms[i] / (r2 * r)
                    gx[j, 0] -= c * dx
                    gx[j, 1] -= c * dy
                    gx[j, 2] -= c * dz
                else:
                    c = G * ms[j] / (r2 * r)
                    gx[i, 0] += c * dx
                    gx[i, 1] += c * dy
                    gx[i, 2] += c * dz
    gp[0] = px / m0
    gp[1] = py / m0
    gp[2] = pz / m0
    return hi


@jit
def composed_gradient(Y, params, out):
    """grad H~ at each row of Y (n, 2m), m = 3N + 1 (module docstring): the Keplerian flows
    over each row's own tau, grad H_I there, pulled back by Phi^T without forming Phi
    (:func:`integrators.kepler_flow.kepler_pullback`, from the scalars each flow kept);
    dH~/dtau = dK/dtau, dH~/dp_tau = 1.  A flow that fails (a collision orbit) gives NaN,
    which the step refuses."""
    N, G, m0, ms, mu, m = _header(params)
    massive = _massive(params)
    rate = _clock(params)
    terms = _terms(params)
    x = np.empty((N, 3))
    v = np.empty((N, 3))
    sv = np.empty((N, SAVED))
    gx = np.empty((N, 3))
    gp = np.empty(3)
    for r in range(Y.shape[0]):
        tau = Y[r, m - 1] / rate
        for i in range(N):
            mi = _weight(ms[i])
            (x[i, 0], x[i, 1], x[i, 2], v[i, 0], v[i, 1], v[i, 2], it) = kepler_step_saved(
                Y[r, 3 * i], Y[r, 3 * i + 1], Y[r, 3 * i + 2], Y[r, m + 3 * i] / mi,
                Y[r, m + 3 * i + 1] / mi, Y[r, m + 3 * i + 2] / mi, mu, tau, sv, i)
        _interaction_gradient(x, v, ms, G, m0, gx, gp, massive)
        _potential_terms(x, ms, mu, terms, gx)
        dkdt = 0.0
        for i in range(N):
            mi = _weight(ms[i])
            ri2 = x[i, 0] * x[i, 0] + x[i, 1] * x[i, 1] + x[i, 2] * x[i, 2]
            k = -mu / (ri2 * np.sqrt(ri2))
            # grad H_I . J grad H_K: H_I's change along the Keplerian motion (x' = v,
            # v' = -mu x / r^3, P' = m v'); a test particle is in no term of H_I
            if ms[i] > 0.0:
                for a in range(3):
                    dkdt += gx[i, a] * v[i, a] + gp[a] * mi * k * x[i, a]
            # (Q, V = P / m): K's gradient in (Q, V) is Phi^T (gx, m gp); dK/dP = dK/dV / m
            wx, wy, wz, wu, wv, ww = kepler_pullback(
                Y[r, 3 * i], Y[r, 3 * i + 1], Y[r, 3 * i + 2], Y[r, m + 3 * i] / mi,
                Y[r, m + 3 * i + 1] / mi, Y[r, m + 3 * i + 2] / mi, sv, i,
                gx[i, 0], gx[i, 1], gx[i, 2], mi * gp[0], mi * gp[1], mi * gp[2])
            out[r, 3 * i] = wx
            out[r, 3 * i + 1] = wy
            out[r, 3 * i + 2] = wz
            out[r, m + 3 * i] = wu / mi
            out[r, m + 3 * i + 1] = wv / mi
            out[r, m + 3 * i + 2] = ww / mi
        out[r, m - 1] = dkdt / rate
        out[r, 2 * m - 1] = rate


@jit
def composed_energy(y, params):
    """H~(y) = H_I(phi_tau(X)) + p_tau for one state y (2m,) (H_I with the GR potential term
    when params carry one)."""
    N, G, m0, ms, mu, m = _header(params)
    rate = _clock(params)
    tau = y[m - 1] / rate
    x = np.empty((N, 3))
    v = np.empty((N, 3))
    gx = np.empty((N, 3))
    gp = np.empty(3)
    for i in range(N):
        mi = _weight(ms[i])
        a, b, c, d, e, f, it = kepler_step(y[3 * i], y[3 * i + 1], y[3 * i + 2],
                                           y[m + 3 * i] / mi, y[m + 3 * i + 1] / mi,
                                           y[m + 3 * i + 2] / mi, mu, tau)
        x[i, 0], x[i, 1], x[i, 2] = a, b, c
        v[i, 0], v[i, 1], v[i, 2] = d, e, f
    hi = _interaction_gradient(x, v, ms, G, m0, gx, gp, _massive(params))
    hi += _potential_terms(x, ms, mu, _terms(params), gx)
    return hi + rate * y[2 * m - 1]


@jit
def _carry(vec, phi, i, m, mi, w):
    """Body i's block of a derivative-like vector (the coefficients gamma, or cy) carried through
    the flow: (dQ, dP) -> Phi_c (dQ, dP), Phi_c = diag(1, m) Phi diag(1, 1/m) the canonical state
    transition matrix of Phi = phi (6, 6); w (6,) scratch."""
    for a in range(3):
        w[a] = vec[3 * i + a]
        w[3 + a] = vec[m + 3 * i + a] / mi
    for a in range(3):
        sq = 0.0
        sv = 0.0
        for b in range(6):
            sq += phi[a, b] * w[b]
            sv += phi[3 + a, b] * w[b]
        vec[3 * i + a] = sq
        vec[m + 3 * i + a] = mi * sv


@jit
def composed_recentre(y, cy, gamma, h, params):
    """After a committed step of size h: X <- phi_{tau + h/2}(X), tau <- -h/2 (the next step's
    start, centred as in the module docstring; the same physical state).

    The flow is taken in double-double from the double-double state y - cy
    (:func:`integrators.kepler_flow_dd.kepler_refine_dd`) and written back as y - cy exactly:
    the state is then rounded nowhere between two steps (the double flow,
    :func:`composed_recentre_double`, rounded it here once a step, and the physical energy's
    error grew as eps sqrt(steps)).  The coefficients gamma (the next step's initial guess
    extrapolates them) are carried by the flow's state transition matrix, as derivatives are:
    the guess then describes the right-hand side in the new variables.  Returns 0, or 1 + the
    index of a planet whose flow did not converge (nothing changed then)."""
    N, G, m0, ms, mu, m = _header(params)
    rate = _clock(params)
    # dt = tau + h/2 in double-double (rate a power of 2: its products and quotients exact)
    th, tl = two_sum(y[m - 1], -cy[m - 1])
    th, tl = dd_add_d(th, tl, 0.5 * h * rate)
    dth, dtl = th / rate, tl / rate
    xh = np.empty(3)
    xl = np.empty(3)
    vh = np.empty(3)
    vl = np.empty(3)
    xs = np.empty(3)
    vs = np.empty(3)
    out = np.empty((N, 4, 3))           # x1 high, x1 low, v1 high, v1 low
    phi = np.empty((N, 6, 6))
    for i in range(N):
        mi = _weight(ms[i])
        for a in range(3):
            xh[a] = y[3 * i + a]
            xl[a] = -cy[3 * i + a]
            vh[a], vl[a] = dd_div(y[m + 3 * i + a], -cy[m + 3 * i + a], mi, 0.0)
        it, X, kp = kepler_step_stm_x(xh, vh, mu, dth, xs, vs, phi[i])
        if it < 0 or kepler_refine_dd(xh, xl, vh, vl, mu, dth, dtl, X, kp, out[i, 0],
                                      out[i, 1], out[i, 2], out[i, 3]) < 0:
            return 1 + i
    w = np.empty(6)
    for i in range(N):
        mi = _weight(ms[i])
        for a in range(3):
            y[3 * i + a] = out[i, 0, a]
            cy[3 * i + a] = -out[i, 1, a]
            ph, pl = dd_mul_d(out[i, 2, a], out[i, 3, a], mi)
            y[m + 3 * i + a] = ph
            cy[m + 3 * i + a] = -pl
        for row in range(gamma.shape[0]):
            _carry(gamma[row], phi[i], i, m, mi, w)
    y[m - 1] = -0.5 * h * rate
    cy[m - 1] = 0.0
    return 0


@jit
def composed_recentre_double(y, cy, gamma, h, params):
    """:func:`composed_recentre` with the flow in double (the recentring before issue 48's
    compensated one), the baseline of ``benchmarks/bench_kepler_composed.py`` and of the tests:
    the low parts cy are carried by the state transition matrix, and the state is rounded
    once a step.  Returns 0, or 1 + the index of a planet whose flow did not converge."""
    N, G, m0, ms, mu, m = _header(params)
    rate = _clock(params)
    dt = ((y[m - 1] - cy[m - 1]) + 0.5 * h * rate) / rate
    x0 = np.empty(3)
    v0 = np.empty(3)
    x = np.empty((N, 3))
    v = np.empty((N, 3))
    phi = np.empty((N, 6, 6))
    for i in range(N):
        for a in range(3):
            x0[a] = y[3 * i + a]
            v0[a] = y[m + 3 * i + a] / _weight(ms[i])
        if kepler_step_stm(x0, v0, mu, dt, x[i], v[i], phi[i]) < 0:
            return 1 + i
    w = np.empty(6)
    for i in range(N):
        mi = _weight(ms[i])
        for a in range(3):
            y[3 * i + a] = x[i, a]
            y[m + 3 * i + a] = mi * v[i, a]
        for row in range(-1, gamma.shape[0]):
            _carry(cy if row < 0 else gamma[row], phi[i], i, m, mi, w)
    y[m - 1] = -0.5 * h * rate
    cy[m - 1] = 0.0
    return 0


@jit
def composed_bodies(y, params, com, t, out):
    """The barycentric positions and velocities of the star and the N planets, out (N + 1, 6),
    of one state y (2m,) at its own tau (x = phi_tau(X)), the barycentre at com[0:3] +
    com[3:6] (t - com[6]) moving with velocity com[3:6] (:meth:`FlowComposed.physical`, for a
    host that writes bodies at every step).  Returns 0, or 1 + the index of a planet whose flow
    did not converge (out is then partly NaN)."""
    N, G, m0, ms, mu, m = _header(params)
    tau = y[m - 1]
    bad = 0
    M = m0
    for i in range(N):
        M += ms[i]
    sx = np.zeros(3)
    sv = np.zeros(3)
    for i in range(N):
        mi = ms[i]
        wi = _weight(mi)
        a, b, c, d, e, f, it = kepler_step(y[3 * i], y[3 * i + 1], y[3 * i + 2],
                                           y[m + 3 * i] / wi, y[m + 3 * i + 1] / wi,
                                           y[m + 3 * i + 2] / wi, mu, tau)
        if it < 0 and bad == 0:
            bad = 1 + i
        out[i + 1, 0], out[i + 1, 1], out[i + 1, 2] = a, b, c
        out[i + 1, 3], out[i + 1, 4], out[i + 1, 5] = d, e, f
        sx[0] += mi * a
        sx[1] += mi * b
        sx[2] += mi * c
        sv[0] += mi * d
        sv[1] += mi * e
        sv[2] += mi * f
    dt = t - com[6]
    for a in range(3):
        # the star: the barycentre less the planets' moments (heliocentric Q, barycentric V)
        x0 = com[a] + com[3 + a] * dt - sx[a] / M
        out[0, a] = x0
        out[0, 3 + a] = com[3 + a] - sv[a] / m0
        for i in range(N):
            out[i + 1, a] += x0
            out[i + 1, 3 + a] += com[3 + a]
    return bad


def _real(v) -> bool:
    """A finite real number (not a bool): the arguments' common test."""
    return (not isinstance(v, bool) and isinstance(v, (int, float, np.number))
            and bool(np.isfinite(v)))


def _check_harmonics(harmonics) -> tuple:
    """FlowComposed's ``harmonics`` as the params' six numbers (J2, J4, R_eq, w), w the unit
    spin axis computed as REBOUNDx's uvw() does; a ValueError naming what is wrong."""
    hint = ("`harmonics` must be (J2, J4, R_eq) or (J2, J4, R_eq, Omega): J2 != 0, J4 and "
            "R_eq > 0 finite numbers, Omega the star's spin axis, 3 finite numbers not all 0")
    if not isinstance(harmonics, (tuple, list)) or len(harmonics) not in (3, 4):
        raise ValueError(f"{hint} (got harmonics={harmonics!r})")
    j2, j4, R = harmonics[:3]
    omega = harmonics[3] if len(harmonics) == 4 else (0.0, 0.0, 1.0)
    try:
        om = [float(o) for o in omega]
    except (TypeError, ValueError):
        om = []
    if (not (_real(j2) and _real(j4) and _real(R)) or j2 == 0 or not R > 0 or len(om) != 3
            or not all(math.isfinite(o) for o in om) or not any(om)):
        raise ValueError(f"{hint} (got harmonics={harmonics!r})")
    w = math.sqrt(om[0] * om[0] + om[1] * om[1] + om[2] * om[2])
    return (float(j2), float(j4), float(R), om[0] / w, om[1] / w, om[2] / w)


def _check_central(central) -> tuple:
    """FlowComposed's ``central`` as the params' two numbers (A, gamma)."""
    if (not isinstance(central, (tuple, list)) or len(central) != 2
            or not all(_real(v) for v in central) or central[0] == 0):
        raise ValueError(f"`central` must be (A, gamma), REBOUNDx's Acentral (finite, != 0) and "
                         f"gammacentral (finite) of the star (got central={central!r})")
    return (float(central[0]), float(central[1]))


def _no_recentre(y, cy, gamma, h, params):      # pragma: no cover - the stand-in's shape
    return 0


class FlowComposed(HamiltonianSystem):
    """A star and N planets in the variables transformed by their Keplerian flows.

    Parameters
    ----------
    masses : array_like (N + 1,)
        The star's mass first, then the planets' (all > 0).
    G : float
    h : float
        The step the integration will take: the first state is centred on the first step
        (tau = -h/2).  A step of another size afterwards stays exact (the flows are taken over
        each step's own tau), only not centred.
    clock_rate : float, optional
        c, a power of 2 (default 1): the state holds the clock as c tau and its momentum as
        p_tau / c (H~ = K(X, tau) + c (p_tau / c)), so that every operation of the step on those
        two rows is scaled exactly and only the iteration's stop rule sees c: it compares the
        increments with max |gamma| over the state, whose largest entry is the clock's rate.
        With c = 1 that scale is 1 in the scene's unit of time (4.5 sweeps a step on the outer
        solar system in days, 3.2 in seconds, the same results to round-off); a larger c stops
        the iteration earlier, as a longer unit of time does (measured:
        ``benchmarks/bench_kepler_composed.py``, "Where the time goes").  Opt-in until a stop
        rule that uses the iteration's measured contraction makes it unnecessary.
    gr_c : float, optional
        The speed of light, in the scene's units, of a general-relativistic potential term
        in H_I: REBOUNDx's ``gr_potential`` (Nobili and Roxburgh 1986; Tamayo et al. 2020),
        U = -sum_i 3 (G m_0)^2 m_i / (c^2 |Q_i|^2) about the star, which gets the pericentre
        precession right.  It is conservative and a function of the heliocentric positions
        only, so the composed method keeps H~ with it as without it, and the physical energy is
        REBOUND's ``sim.energy()`` plus REBOUNDx's ``gr_potential_potential``.  None (default):
        no such term, and the same numbers bit for bit as before it existed.
    harmonics : tuple, optional
        The star's zonal harmonics (J2, J4, R_eq) or (J2, J4, R_eq, Omega), Omega its spin
        axis (3,) (any length; default the z axis): REBOUNDx's ``gravitational_harmonics``
        with the star's ``J2``, ``J4``, ``R_eq`` and ``Omega``, U = sum_i G m_0 m_i [J2 R_eq^2
        P2(cos th) / r^3 + J4 R_eq^4 P4(cos th) / r^5] in H_I (:func:`_harmonics`), its energy
        REBOUNDx's ``gravitational_harmonics_potential``.  J4 = 0: J2 alone.  None (default):
        no such term.
    central : tuple, optional
        (A, gamma): REBOUNDx's ``central_force`` from the star (its ``Acentral`` and
        ``gammacentral``), the acceleration A r^(gamma - 1) Q_i on each body, a potential in
        H_I (:func:`_central_force`), its energy REBOUNDx's ``central_force_potential``.  None
        (default): no such term.  Each of the three terms is exact in these coordinates because
        REBOUNDx applies the reaction on the star (m_i / m_0 times the opposite force); they
        add up in H_I when several are given.

    Build it with :meth:`from_nbody`.  States: :meth:`extend` (from a barycentric
    :class:`systems.NBody` state) and :meth:`physical` (back, at the state's own tau).
    """

    polynomial_degree = None
    # the adaptive controller's estimate (integrators.core.step_error) takes the largest
    # coefficient over the whole state, which is the clock's rate 1 here: it would accept any
    # step the resolution check lets through, so adaptive steps are refused by name
    fixed_steps_only = ("its clock row (tau' = 1) hides the planets from the step-size "
                        "controller's estimate; use fixed steps (integrate(..., h, steps)), "
                        "whose own error check (error_bound) still refuses an unresolved step")

    def __init__(self, masses, G: float, h: float, clock_rate: float = 1.0,
                 gr_c: float | None = None, harmonics: tuple | None = None,
                 central: tuple | None = None):
        ms = np.asarray(masses, dtype=float).reshape(-1)
        if ms.size < 2 or not np.all(np.isfinite(ms) & (ms >= 0)) or not ms[0] > 0:
            raise ValueError(f"`masses` must be the star's mass (> 0) then each planet's (>= 0: "
                             f"0 for a test particle), all finite (got {ms!r})")
        if not (np.isfinite(G) and G > 0):
            raise ValueError(f"`G` must be a positive number (got G={G!r})")
        if not (np.isfinite(h) and h != 0):
            raise ValueError(f"`h` must be the (nonzero, finite) step the run will take (got h={h!r})")
        c = clock_rate
        if (not _real(c) or not c > 0 or math.frexp(float(c))[0] != 0.5
                or not 2.0 ** -64 <= c <= 2.0 ** 64):
            raise ValueError(f"`clock_rate` must be a power of 2 between 2**-64 and 2**64, so that "
                             f"the clock's rows scale exactly (got clock_rate={clock_rate!r}); "
                             f"1 is the default")
        self.clock_rate = float(c)
        if gr_c is not None and (not _real(gr_c) or not gr_c > 0):
            raise ValueError(f"`gr_c` must be the speed of light in the scene's units, a "
                             f"positive finite number (got gr_c={gr_c!r}); None for no GR "
                             f"potential term")
        self.gr_c = None if gr_c is None else float(gr_c)
        self.harmonics = None if harmonics is None else _check_harmonics(harmonics)
        self.central = None if central is None else _check_central(central)
        self.m0, self.planet_masses, self.G, self.h = float(ms[0]), ms[1:].copy(), float(G), float(h)
        self.N = ms.size - 1
        self.dim = 3 * self.N + 1
        self.body_dim = 3
        self.body_masses = ms.copy()
        # the weights of the second half of the state, P = w V (1 for a test particle, whose
        # state is (Q, V), as NBody's p = v; _weight), the star's first
        self.weights = np.where(ms > 0, ms, 1.0)
        massive = np.flatnonzero(self.planet_masses > 0)
        self._params = np.concatenate([[self.N, self.G, self.m0], self.planet_masses,
                                       [self.clock_rate, massive.size], massive,
                                       [0.0 if gr_c is None else self.gr_c],
                                       self.harmonics or np.zeros(6),
                                       self.central or np.zeros(2)])
        self._com = (np.zeros(3), np.zeros(3))

    @classmethod
    def from_nbody(cls, nbody, h: float, clock_rate: float = 1.0,
                   gr_c: float | None = None, harmonics: tuple | None = None,
                   central: tuple | None = None) -> "FlowComposed":
        """The system of an :class:`systems.NBody` whose first body is the star."""
        return cls(nbody.body_masses, nbody.G, h, clock_rate, gr_c, harmonics, central)

    def full_kernels(self):
        return composed_gradient, composed_energy, self._params

    def bodies_kernel(self):
        """The compiled map of a state to its bodies (:func:`composed_bodies`)."""
        return composed_bodies

    def recentre_kernel(self):
        """The hook run after each committed step (:func:`composed_recentre`)."""
        return composed_recentre

    # -- states ------------------------------------------------------------------------
    def extend(self, y) -> np.ndarray:
        """Y from a barycentric NBody state y = (positions (N+1)*3, momenta (N+1)*3): the
        heliocentric Q, barycentric P, flowed by phi_{h/2} (tau = -h/2), p_tau = H_K.  The
        barycentre's position and velocity are kept for :meth:`physical`."""
        y = np.asarray(y, dtype=float)
        n = self.N + 1
        if y.shape != (6 * n,):
            raise ValueError(f"`y` must be a state of {n} bodies, shape ({6 * n},) (got {y.shape})")
        x = y[:3 * n].reshape(n, 3)
        p = y[3 * n:].reshape(n, 3)
        M = self.body_masses.sum()
        # (a test particle's p is its velocity: no momentum)
        vcm = np.where(self.body_masses[:, None] > 0, p, 0.0).sum(axis=0) / M
        xcm = (self.body_masses[:, None] * x).sum(axis=0) / M
        self._com = (xcm, vcm)
        Q = x[1:] - x[0]
        V = p[1:] / self.weights[1:, None] - vcm               # barycentric velocities
        hk = float(np.sum(0.5 * self.planet_masses * np.sum(V * V, axis=1)
                          - self.G * self.m0 * self.planet_masses / np.linalg.norm(Q, axis=1)))
        tau0 = -0.5 * self.h
        X, W = kepler_flow(Q, V, self.G * self.m0, -tau0)
        c = self.clock_rate
        return np.concatenate([X.ravel(), [c * tau0], (W * self.weights[1:, None]).ravel(),
                               [hk / c]])

    def heliocentric(self, Y):
        """(Q, V), each (..., N, 3), of states Y (..., 2m) at their own time tau:
        x = phi_tau(X).  One compiled call when every state has the same tau (the samples of
        a run: the hook leaves tau at -h/2 after every step)."""
        Y = np.asarray(Y, dtype=float)
        lead = Y.shape[:-1]
        Y2 = Y.reshape(-1, Y.shape[-1])
        m = self.dim
        X = Y2[:, :m - 1].reshape(-1, 3)
        V = (Y2[:, m:2 * m - 1].reshape(-1, self.N, 3) / self.weights[1:, None]).reshape(-1, 3)
        mu = np.full(X.shape[0], self.G * self.m0)
        taus = Y2[:, m - 1] / self.clock_rate
        if np.all(taus == taus[0]):
            Q, W = kepler_flow(X, V, mu, float(taus[0]))
        else:
            Q, W = np.empty_like(X), np.empty_like(V)
            for r, tau in enumerate(taus):
                rows = slice(r * self.N, (r + 1) * self.N)
                Q[rows], W[rows] = kepler_flow(X[rows], V[rows], mu[rows], float(tau))
        return Q.reshape(lead + (self.N, 3)), W.reshape(lead + (self.N, 3))

    def physical(self, Y, t=0.0) -> np.ndarray:
        """The barycentric NBody states (positions, momenta), (..., 6 (N + 1)), of states Y
        (..., 2m) at times t since :meth:`extend` (the barycentre moves uniformly)."""
        Q, V = self.heliocentric(Y)
        ms = self.planet_masses[:, None]
        M = self.body_masses.sum()
        xcm, vcm = self._com
        t = np.asarray(t, dtype=float)[..., None, None]
        x0 = -(ms * Q).sum(axis=-2, keepdims=True) / M       # the star, barycentre at the origin
        v0 = -(ms * V).sum(axis=-2, keepdims=True) / self.m0
        x = np.concatenate([x0, Q + x0], axis=-2) + xcm + vcm * t
        v = np.concatenate([v0, V], axis=-2) + vcm
        lead = x.shape[:-2]
        return np.concatenate([x.reshape(lead + (-1,)),
                               (v * self.weights[:, None]).reshape(lead + (-1,))], axis=-1)

    def physical_energy(self, Y) -> float:
        """H = H_K + H_I at the physical state of Y (barycentric frame), H_I with the GR potential
        term when there is one (``gr_c``)."""
        Q, V = self.heliocentric(Y)
        ms = self.planet_masses
        hk = np.sum(0.5 * ms * np.sum(V * V, axis=1) - self.G * self.m0 * ms / np.linalg.norm(Q, axis=1))
        gx, gp = np.empty((self.N, 3)), np.empty(3)
        hi = _interaction_gradient(Q, V, ms, self.G, self.m0, gx, gp, _massive(self._params))
        hi += _potential_terms(np.ascontiguousarray(Q), ms, self.G * self.m0,
                               _terms(self._params), gx)
        return float(hk + hi)

    # -- the protocol (Python path) ----------------------------------------------------
    def energy(self, Y):
        Y = np.asarray(Y, dtype=float)
        if Y.ndim == 1:
            return composed_energy(np.ascontiguousarray(Y), self._params)
        return np.array([composed_energy(np.ascontiguousarray(r), self._params) for r in Y])

    def gradient(self, Y):
        Y = np.atleast_2d(np.asarray(Y, dtype=float))
        out = np.empty_like(Y)
        composed_gradient(np.ascontiguousarray(Y), self._params, out)
        return out
