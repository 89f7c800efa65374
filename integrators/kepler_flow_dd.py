"""The Keplerian flow in double-double: the recentring of the flow-composed methods (issue 48).

The flow-composed step (:mod:`systems.flow_composed`) keeps its state in double-double and
commits it exactly, but maps X <- phi_h(X) once a step between two steps.  A flow computed in
double rounds the state there once a step, and the physical energy's error then grows as
eps sqrt(steps) (Brouwer's law: 9e-15 after 1000 steps, 6e-14 after 2.5e5 on the outer solar
system, against IAS15's 2.7e-15).  This module refines the double flow of
:mod:`integrators.kepler_flow` to double-double, so that the recentred state is the exact flow
of the double-double state to about eps^2 (the stages keep the double flow: their rounding
only perturbs the small interaction forces, not the state).

How.  Kepler's equation in universal variables (the notation of :mod:`integrators.kepler_flow`)

    F(X) = r0 X + eta0 G2(X) + zeta0 G3(X) - dt = 0,     F'(X) = r(X)

is solved in double as before (:func:`integrators.kepler_flow.universal_anomaly`: every conic,
every eccentricity); then r0, eta0, beta, zeta0 are formed in double-double from the
double-double state, F is evaluated in double-double (:func:`stumpff_dd`), and Newton's steps
X <- X - F / r (one, almost always: the double root is within a few eps) make X a root to
about eps^2.  G1..G3 are carried over the last step by their Taylor series, and Gauss's

    x1 = x0 + (f - 1) x0 + g v0,      v1 = v0 + fdot x0 + (gdot - 1) v0

are formed in double-double.  Where they cancel (a pericentre passage, far along a
hyperbola: :func:`integrators.kepler_flow.new_state` takes the conic's frame there) they lose
the cancellation's factor of eps^2, which stays far below eps: no second formula is needed.
An elliptic flow longer than half a period is reduced by k periods as the double flow does,
with the period in double-double.
"""
from __future__ import annotations

import math
from fractions import Fraction

import numpy as np

from .double_double import (PI_HI, PI_LO, dd_add, dd_add_d, dd_div, dd_mul, dd_mul_d,
                            dd_sqrt)
from .jit import jit

EPS = 2.0 ** -52
NEWTON = 6                 # Newton steps at most (1 seen on every test orbit: the double root
                           # is within a few eps)
CLOSE = 4.0 * EPS          # |dX| / |X| below which Newton's step is the last (its own error,
                           # ~ dX^2 F'' / F', is then of the order of eps^2)
SERIES = 25                # the series of c2, c3 to 1 / 25!: (0.1)^11 / 25! < eps^2 / 100


def _inverse_factorials():
    hi = np.empty(SERIES + 1)
    lo = np.empty(SERIES + 1)
    for n in range(SERIES + 1):
        f = Fraction(1, math.factorial(n))
        hi[n] = float(f)
        lo[n] = float(f - Fraction(hi[n]))
    return hi, lo


_IF_HI, _IF_LO = _inverse_factorials()     # 1 / n! as double-doubles


@jit
def stumpff_dd(zh, zl):
    """Stumpff's c0 .. c3 at z = zh + zl in double-double: (c0h, c0l, c1h, c1l, c2h, c2l,
    c3h, c3l).  The series of c2, c3 at z / 4^k (|z / 4^k| <= 0.1), then k quadruplications
    (the formulas of :func:`integrators.kepler_flow.stumpff`) for every z: an elliptic z is at
    most about (2 pi)^2 after the period's reduction (4 quadruplications), and on a hyperbola
    each quadruplication loses at most sqrt|z| eps^2 relative (cosh's growth), far below eps
    wherever cosh does not overflow."""
    k = 0
    while abs(zh) > 0.1:
        zh *= 0.25
        zl *= 0.25
        k += 1
    fh = _IF_HI
    fl = _IF_LO
    c3h, c3l = fh[SERIES], fl[SERIES]
    c2h, c2l = fh[SERIES - 1], fl[SERIES - 1]
    for j in range(SERIES - 2, 2, -2):
        th, tl = dd_mul(zh, zl, c3h, c3l)
        c3h, c3l = dd_add(fh[j], fl[j], -th, -tl)
        th, tl = dd_mul(zh, zl, c2h, c2l)
        c2h, c2l = dd_add(fh[j - 1], fl[j - 1], -th, -tl)
    th, tl = dd_mul(zh, zl, c3h, c3l)
    c1h, c1l = dd_add_d(-th, -tl, 1.0)
    th, tl = dd_mul(zh, zl, c2h, c2l)
    c0h, c0l = dd_add_d(-th, -tl, 1.0)
    for _ in range(k):
        th, tl = dd_mul(c0h, c0l, c3h, c3l)
        th, tl = dd_add(c2h, c2l, th, tl)
        c3h, c3l = 0.25 * th, 0.25 * tl
        th, tl = dd_mul(c1h, c1l, c1h, c1l)
        c2h, c2l = 0.5 * th, 0.5 * tl
        c1h, c1l = dd_mul(c0h, c0l, c1h, c1l)
        zh *= 4.0
        zl *= 4.0
        th, tl = dd_mul(zh, zl, c2h, c2l)
        c0h, c0l = dd_add_d(-th, -tl, 1.0)
    return c0h, c0l, c1h, c1l, c2h, c2l, c3h, c3l


@jit
def _dot_dd(ah, al, bh, bl):
    """sum_a (ah[a] + al[a]) (bh[a] + bl[a]) over three components, in double-double."""
    sh, sl = dd_mul(ah[0], al[0], bh[0], bl[0])
    for a in range(1, 3):
        th, tl = dd_mul(ah[a], al[a], bh[a], bl[a])
        sh, sl = dd_add(sh, sl, th, tl)
    return sh, sl


@jit
def kepler_refine_dd(xh, xl, vh, vl, mu, dth, dtl, X, kp, x1h, x1l, v1h, v1l):
    """The flow of one body over dt = dth + dtl from the double-double state (xh + xl,
    vh + vl) ((3,) arrays each), into x1h + x1l, v1h + v1l, to about eps^2.

    ``X``: the universal anomaly of the double flow of (xh, vh) over dth
    (:func:`integrators.kepler_flow.kepler_step_stm_x`); ``kp``: its period reduction k P
    (0: none), whose k is taken again with the double-double period.  Returns the Newton steps
    taken, or -1 when they did not converge or a number overflowed (outputs then partly
    written: the caller flows into scratch arrays)."""
    # the scalars of the conic, as kepler_scalars, in double-double
    r2h, r2l = _dot_dd(xh, xl, xh, xl)
    r0h, r0l = dd_sqrt(r2h, r2l)
    v2h, v2l = _dot_dd(vh, vl, vh, vl)
    eh, el = _dot_dd(xh, xl, vh, vl)                   # eta0
    th, tl = dd_div(2.0 * mu, 0.0, r0h, r0l)
    bh, bl = dd_add(th, tl, -v2h, -v2l)               # beta = 2 mu / r0 - v0^2
    th, tl = dd_mul(bh, bl, r0h, r0l)
    zh, zl = dd_add_d(-th, -tl, mu)                   # zeta0 = mu - beta r0
    dh, dl = dth, dtl
    if kp != 0.0:
        # dt - k P with P = 2 pi mu / beta^1.5 in double-double (k: the double flow's)
        sh, sl = dd_sqrt(bh, bl)
        th, tl = dd_mul(bh, bl, sh, sl)
        ph, pl = dd_mul_d(PI_HI, PI_LO, 2.0 * mu)
        ph, pl = dd_div(ph, pl, th, tl)
        k = math.floor(kp / ph + 0.5)
        th, tl = dd_mul_d(ph, pl, k)
        dh, dl = dd_add(dh, dl, -th, -tl)
    Xh, Xl = X, 0.0
    c0h = G1h = G1l = G2h = G2l = G3h = G3l = dX = 0.0
    done = -1
    for it in range(1, NEWTON + 1):
        X2h, X2l = dd_mul(Xh, Xl, Xh, Xl)
        th, tl = dd_mul(bh, bl, X2h, X2l)
        c0h, c0l, c1h, c1l, c2h, c2l, c3h, c3l = stumpff_dd(th, tl)
        G1h, G1l = dd_mul(Xh, Xl, c1h, c1l)
        G2h, G2l = dd_mul(X2h, X2l, c2h, c2l)
        th, tl = dd_mul(X2h, X2l, Xh, Xl)
        G3h, G3l = dd_mul(th, tl, c3h, c3l)
        Fh, Fl = dd_mul(r0h, r0l, Xh, Xl)
        th, tl = dd_mul(eh, el, G2h, G2l)
        Fh, Fl = dd_add(Fh, Fl, th, tl)
        th, tl = dd_mul(zh, zl, G3h, G3l)
        Fh, Fl = dd_add(Fh, Fl, th, tl)
        Fh, Fl = dd_add(Fh, Fl, -dh, -dl)
        rr = r0h + eh * G1h + zh * G2h                # F' = r, in double: a Newton step's size
        dX = -Fh / rr
        if not (math.isfinite(dX) and rr > 0.0):
            return -1
        if abs(dX) <= CLOSE * abs(Xh):
            done = it
            break
        Xh, Xl = dd_add_d(Xh, Xl, dX)
    if done < 0:
        return -1
    # the last step: G_n carried to X + dX to dX^2 (dG_n/dX = G_{n-1}, dG0/dX = -beta G1)
    d2 = 0.5 * dX * dX
    i1 = c0h * dX - bh * G1h * d2
    i2 = G1h * dX + c0h * d2
    i3 = G2h * dX + G1h * d2
    G1h, G1l = dd_add_d(G1h, G1l, i1)
    G2h, G2l = dd_add_d(G2h, G2l, i2)
    G3h, G3l = dd_add_d(G3h, G3l, i3)
    # r = r0 + eta0 G1 + zeta0 G2
    th, tl = dd_mul(eh, el, G1h, G1l)
    rh, rl = dd_add(r0h, r0l, th, tl)
    th, tl = dd_mul(zh, zl, G2h, G2l)
    rh, rl = dd_add(rh, rl, th, tl)
    # Gauss's f - 1 = -mu G2 / r0, g = dt - mu G3, fdot = -mu G1 / (r0 r), gdot - 1 = -mu G2 / r
    th, tl = dd_mul_d(G2h, G2l, -mu)
    fh, fl = dd_div(th, tl, r0h, r0l)
    gdh, gdl = dd_div(th, tl, rh, rl)
    th, tl = dd_mul_d(G3h, G3l, -mu)
    gh, gl = dd_add(dh, dl, th, tl)
    th, tl = dd_mul_d(G1h, G1l, -mu)
    th, tl = dd_div(th, tl, r0h, r0l)
    fdh, fdl = dd_div(th, tl, rh, rl)
    for a in range(3):
        ph, pl = dd_mul(fh, fl, xh[a], xl[a])
        qh, ql = dd_mul(gh, gl, vh[a], vl[a])
        ph, pl = dd_add(ph, pl, qh, ql)
        sxh, sxl = dd_add(xh[a], xl[a], ph, pl)
        ph, pl = dd_mul(fdh, fdl, xh[a], xl[a])
        qh, ql = dd_mul(gdh, gdl, vh[a], vl[a])
        ph, pl = dd_add(ph, pl, qh, ql)
        svh, svl = dd_add(vh[a], vl[a], ph, pl)
        if not (math.isfinite(sxh) and math.isfinite(svh)):
            return -1
        x1h[a], x1l[a], v1h[a], v1l[a] = sxh, sxl, svh, svl
    return done
