"""The Keplerian flow: x'' = -mu x / |x|^3 over a time dt, every conic, to round-off (numba).

The building block of the flow-composed methods of issue 48 (Antonana, Makazaga and Murua,
J. Sci. Comput. 2018, arXiv 1711.06050): the uncoupled Keplerian motions of a planetary system
in heliocentric coordinates, applied to many bodies at once, and (for a Newton iteration or
the variational equations) the flow's Jacobian, the 6x6 state transition matrix.

Universal variables (Stiefel and Scheifele, *Linear and Regular Celestial Mechanics*, 1971;
Danby, *Fundamentals of Celestial Mechanics*, 2nd ed., Sec. 6.9).  With r0 = |x0|,
eta0 = x0 . v0, beta = 2 mu / r0 - |v0|^2 (= mu / a) and zeta0 = mu - beta r0, the universal
anomaly X solves Kepler's equation

    F(X) = r0 X + eta0 G2(X) + zeta0 G3(X) - dt = 0,        F'(X) = r(X) = r0 + eta0 G1 + zeta0 G2,

where G_n(X) = X^n c_n(beta X^2) and c_n are Stumpff's functions (c0 = cos sqrt z,
c1 = sin sqrt z / sqrt z, c2 = (1 - c0) / z, c3 = (1 - c1) / z; cosh and sinh for z < 0).
The new state is, with Gauss's f and g written without their leading terms
(f - 1 and g - dt are the small parts for a short dt, formed directly from G2 and G3):

    x = x0 + (f - 1) x0 + g v0,     f - 1 = -mu G2 / r0,        g = dt - mu G3,
    v = v0 + fdot x0 + (gdot - 1) v0,  fdot = -mu G1 / (r0 r),   gdot - 1 = -mu G2 / r.

How it keeps the error at round-off (anchor: WHFast's ``reb_whfast_kepler_solver`` in
REBOUND's ``src/integrator_whfast.c``, Rein and Tamayo, MNRAS 452, 376, 2015):

* Stumpff's series for |z| <= 0.1 (every term above eps/8 kept), brought to larger |z| by the
  quadruplication formulas c_n(4z) (no cancellation for z < 0; for z > 0 at most a factor 2,
  because an elliptic orbit's dt is first reduced modulo its period, so that z <= (2 pi)^2);
* dt - k P (P the period) formed with an exact product (:func:`integrators.core.two_product`):
  the state after dt is the state after dt - k P exactly, and the reduction rounds once;
* far along a hyperbola, F written with exp(+-sX) and coefficients zeta0 +- eta0 s, the small
  one from their product mu^2 + h^2 s^2 (on an orbit flown along an asymptote eta0 G2 and
  zeta0 G3 cancel by up to 3e3 otherwise);
* X from Laguerre's method (n = 5, Conway 1986: converges from any start on Kepler's
  equation), safeguarded by a bracket that every iterate narrows (r lies between the
  pericentre and the apocentre distances, and within vmax |dt| of r0) and bisection when a
  step leaves it; a step is the last when it is tiny or its own error estimate
  (4 ((F''/F')^2 + |F'''/F'|) |dX|^3) is below 1e-8 eps |X|, and the G_n are then carried to
  X + dX by their Taylor series (dG_n / dX = G_{n-1}) instead of one more series evaluation.

* where x0 + (f - 1) x0 + g v0 would cancel (a flow that ends deep inside r0 or far outside
  it, or far along an asymptote), the new state is built in the conic's own frame
  (:func:`conic_state`: the Laplace-Runge-Lenz direction and the eccentric or hyperbolic
  anomaly), which keeps the energy and angular momentum to round-off there.

Everything is compiled with :func:`integrators.jit.jit` and runs as plain Python under
``NUMBA_DISABLE_JIT=1``.  Measured errors: ``benchmarks/results/kepler_flow.md``.
"""
from __future__ import annotations

import math

import numpy as np

from .core import two_product
from .jit import jit

EPS = 2.0 ** -52
TWO_PI = 2.0 * math.pi
MAX_ITERATIONS = 60       # Laguerre steps plus bisections; 1.6 a planetary flow, at most 15 seen
CONVERGED = 1e-8          # |dX| / |X| below which the step's own correction is the last one
TAYLOR = 1e-10            # (dX / X)^2 max(1, |z|) below which the Taylor step is exact to eps
LAST = EPS * 1e-8         # a last Laguerre step's error estimate, over |X| (eps / 16 biased
                          # the energy: test_the_energy_walks_without_bias)
ARRIVAL = 8.0             # where f, g would cancel by this much, the state comes from the conic
WIDEN = 1e-6              # the bracket's radii are widened by this fraction (their rounding)
Z_SERIES = 4.0            # |z| beyond which the Stumpff functions come from sin, cos or exp
OK = -1                   # kepler_flow_into: no body failed

# 1 / n!, n = 0..19 (the series of c_n, n <= 5, to |z| <= 0.1)
_INV_FACTORIAL = np.array([1.0 / math.factorial(n) for n in range(20)])


@jit
def _stumpff_far(z):
    """c0..c3 for |z| > Z_SERIES from libm's functions of t = sqrt|z| (about one ulp each):
    on an ellipse c0 = 1 - 2 sin^2(t/2), c1 = sin t / t, c2 = 2 sin^2(t/2) / z (no
    cancellation near t = 2 pi, where 1 - cos t would lose every digit of c2),
    c3 = (t - sin t) / t^3; on a hyperbola with exp(t), whose quadruplications would lose
    about t ulps (73 ulps at z = -3000, measured)."""
    if z > 0.0:
        t = math.sqrt(z)
        sh = math.sin(0.5 * t)
        ch = math.cos(0.5 * t)
        s2 = 2.0 * sh * sh
        sn = 2.0 * sh * ch
        return 1.0 - s2, sn / t, s2 / z, (t - sn) / (z * t)
    t = math.sqrt(-z)
    ex = math.exp(0.5 * t)
    sh = 0.5 * (ex - 1.0 / ex)                  # sinh(t/2), t/2 > 1: no cancellation
    ch = 0.5 * (ex + 1.0 / ex)
    s2 = 2.0 * sh * sh                          # cosh t - 1
    sn = 2.0 * sh * ch                          # sinh t
    return 1.0 + s2, sn / t, -s2 / z, (sn - t) / (-z * t)


@jit
def stumpff(z):
    """Stumpff's c0(z), c1(z), c2(z), c3(z) for any real z.

    For |z| <= Z_SERIES: the series (terms to (-z)^6 / (12 + n)!, below eps / 8 for |z| <= 0.1)
    at z / 4^k, |z / 4^k| <= 0.1, then k <= 3 quadruplications (the double-angle formulas of
    cos and sin: c3(4z) = (c2 + c0 c3) / 4, c2(4z) = c1^2 / 2, c1(4z) = c0 c1,
    c0(4z) = 1 - 4z c2(4z)); beyond, :func:`_stumpff_far`."""
    if abs(z) > Z_SERIES:
        return _stumpff_far(z)
    k = 0
    while abs(z) > 0.1:
        z *= 0.25
        k += 1
    f = _INV_FACTORIAL
    c3 = f[15]
    c2 = f[14]
    for j in range(13, 2, -2):
        c3 = f[j] - z * c3
        c2 = f[j - 1] - z * c2
    c1 = 1.0 - z * c3
    c0 = 1.0 - z * c2
    for _ in range(k):
        c3 = 0.25 * (c2 + c0 * c3)
        c2 = 0.5 * c1 * c1
        c1 = c0 * c1
        z *= 4.0
        c0 = 1.0 - z * c2
    return c0, c1, c2, c3


@jit
def stumpff5(z):
    """Stumpff's c0(z) .. c5(z) (the state transition matrix needs c4 and c5; beyond
    Z_SERIES c4 = (1/2 - c2) / z and c5 = (1/6 - c3) / z lose at most 2 bits there)."""
    if abs(z) > Z_SERIES:
        c0, c1, c2, c3 = _stumpff_far(z)
        return c0, c1, c2, c3, (0.5 - c2) / z, (1.0 / 6.0 - c3) / z
    k = 0
    while abs(z) > 0.1:
        z *= 0.25
        k += 1
    f = _INV_FACTORIAL
    c5 = f[17]
    c4 = f[16]
    for j in range(15, 4, -2):
        c5 = f[j] - z * c5
        c4 = f[j - 1] - z * c4
    c3 = f[3] - z * c5
    c2 = f[2] - z * c4
    c1 = 1.0 - z * c3
    c0 = 1.0 - z * c2
    for _ in range(k):
        c5 = 0.0625 * (c5 + c4 + c3 * c2)
        c4 = 0.125 * (1.0 + c1) * c3
        c3 = 0.25 * (c2 + c0 * c3)
        c2 = 0.5 * c1 * c1
        c1 = c0 * c1
        z *= 4.0
        c0 = 1.0 - z * c2
    return c0, c1, c2, c3, c4, c5


@jit
def kepler_scalars(x0, y0, z0, vx, vy, vz, mu):
    """r0, eta0 = x0 . v0, beta = 2 mu / r0 - v0^2, zeta0 = mu - beta r0, v0^2 and
    h^2 = |x0 x v0|^2 (from the cross product: r0^2 v0^2 - eta0^2 cancels on a nearly radial
    orbit)."""
    r0 = math.sqrt(x0 * x0 + y0 * y0 + z0 * z0)
    v2 = vx * vx + vy * vy + vz * vz
    eta0 = x0 * vx + y0 * vy + z0 * vz
    beta = 2.0 * mu / r0 - v2
    zeta0 = mu - beta * r0
    hx = y0 * vz - z0 * vy
    hy = z0 * vx - x0 * vz
    hz = x0 * vy - y0 * vx
    return r0, eta0, beta, zeta0, v2, hx * hx + hy * hy + hz * hz


@jit
def reduce_period(beta, mu, dt):
    """(dt - k P, k P): |dt - k P| <= P / 2 on an ellipse (beta > 0), k = 0 otherwise; the
    difference rounded once."""
    # |dt| > P / 2 = pi mu / beta^1.5, asked without a square root (most flows are short)
    if beta <= 0.0 or not dt * dt * (beta * beta * beta) > (math.pi * mu) ** 2:
        return dt, 0.0
    period = TWO_PI * mu / (beta * math.sqrt(beta))
    if not abs(dt) > 0.5 * period:
        return dt, 0.0
    k = math.floor(dt / period + 0.5)
    hi, lo = two_product(k, period)
    return (dt - hi) - lo, hi


@jit
def anomaly_bracket(r0, beta, v2, h2, mu, dt):
    """An interval that holds the root X of Kepler's equation: X = integral of dt / r, and r
    lies between the pericentre and apocentre distances q, Q and within vmax |dt| of r0 (the
    conic: e^2 = 1 - h^2 beta / mu^2, q = h^2 / (mu (1 + e)), vmax = mu (1 + e) / h, the speed
    at the pericentre); on an ellipse also |X| <= 2 pi / sqrt(beta) (one period, for dt
    reduced to half a period).  The radii are widened by WIDEN against their rounding."""
    e = math.sqrt(max(1.0 - h2 * beta / (mu * mu), 0.0))
    adt = abs(dt)
    q = h2 / (mu * (1.0 + e))
    rmin = q
    if h2 > 0.0:
        reach = r0 - mu * (1.0 + e) / math.sqrt(h2) * adt
        if reach > rmin:
            rmin = reach
    rmin *= 1.0 - WIDEN
    rmax = math.inf
    if q > 0.0:
        rmax = r0 + math.sqrt(v2 + 2.0 * mu * max(1.0 / q - 1.0 / r0, 0.0)) * adt
    if beta > 0.0:
        rmax = min(rmax, (1.0 + e) * mu / beta)
    rmax *= 1.0 + WIDEN
    xlo = adt / rmax
    xhi = adt / rmin if rmin > 0.0 else math.inf
    if beta > 0.0:
        xhi = min(xhi, TWO_PI / math.sqrt(beta) * (1.0 + WIDEN))
    if dt < 0.0:
        return -xhi, -xlo
    return xlo, xhi


@jit
def asymptote_coefficients(beta, eta0, zeta0, h2, mu, sb):
    """On a hyperbola (beta < 0, sb = sqrt(-beta)): A = zeta0 + eta0 sb and B = zeta0 - eta0 sb
    (e exp(-+H0) times mu), the one that is a difference taken from A B = mu^2 + h^2 sb^2
    without cancellation (:func:`universal_anomaly`, :func:`conic_state`)."""
    if eta0 >= 0.0:
        ca = zeta0 + eta0 * sb
        return ca, (mu * mu - h2 * beta) / ca
    cb = zeta0 - eta0 * sb
    return (mu * mu - h2 * beta) / cb, cb


@jit
def universal_anomaly(r0, eta0, beta, zeta0, v2, h2, mu, dt):
    """Solve Kepler's equation in universal variables for X.

    ``dt`` is already reduced (:func:`reduce_period`).  Returns X, G1, G2, G3 (at X), r and the
    number of iterations (negative when the iteration did not converge)."""
    if dt == 0.0:
        return 0.0, 0.0, 0.0, 0.0, r0, 0
    adt = abs(dt)
    # far along a hyperbola (|beta X^2| > Z_SERIES) F is written with the exponentials,
    # eta0 s cosh(sX) + zeta0 sinh(sX) = (A exp(sX) - B exp(-sX)) / 2, s = sqrt(-beta),
    # A = zeta0 + eta0 s, B = zeta0 - eta0 s (e exp(-+H0) times mu): one of A, B is a
    # difference that vanishes on an orbit flown along an asymptote, and eta0 G2 + zeta0 G3
    # cancels by as much (3e3 measured).  A B = mu^2 + h^2 s^2 gives it without cancellation.
    sb = ca = cb = 0.0
    if beta < 0.0:
        sb = math.sqrt(-beta)
        ca, cb = asymptote_coefficients(beta, eta0, zeta0, h2, mu, sb)
    # start: the series of X(t) to dt^3 while it converges well (|v0 dt| <= r0 / 2, the
    # common case of a planetary step: there the analytic bracket is only computed if a step
    # ever leaves the one the iterates' signs of F make); else, on an ellipse, the mean
    # motion (Delta E = n dt); on a hyperbola, Delta H from e sinh(H0 + Delta H) ~ 2 n |dt|
    # (its growing exponential alone, Delta H = log(1 + 2 n |dt| / (e exp(+-H0))))
    r0i = 1.0 / r0
    u = dt * r0i
    X = u * (1.0 - 0.5 * u * r0i * (eta0 - u * (eta0 * eta0 * r0i - zeta0 * (1.0 / 3.0))))
    analytic = dt * dt * v2 > 0.25 * r0 * r0
    if analytic:
        xlo, xhi = anomaly_bracket(r0, beta, v2, h2, mu, dt)
        if beta > 0.0:
            X = beta * dt / mu
        elif beta < 0.0:
            w = (ca if dt > 0.0 else cb) / mu
            if w > 0.0:
                X = math.copysign(math.log1p(2.0 * sb * sb * sb / mu * adt / w), dt) / sb
    else:
        xlo, xhi = -math.inf, math.inf
    if not (xlo < X < xhi):
        X = 0.5 * (xlo + xhi) if math.isfinite(xhi - xlo) else (xlo if dt > 0.0 else xhi)
    step = math.inf
    was_far = False
    for it in range(1, MAX_ITERATIONS + 1):
        z = beta * X * X
        c0, c1, c2, c3 = stumpff(z)
        X2 = X * X
        G1 = X * c1
        G2 = X2 * c2
        G3 = X2 * X * c3
        if z < -Z_SERIES:
            ep = math.exp(sb * X)
            ha = 0.5 * ca * ep
            hb = 0.5 * cb / ep
            s2 = sb * sb
            F = r0 * X + ((ha - hb) - eta0 * sb - zeta0 * sb * X) / (s2 * sb) - dt
            Fp = r0 + ((ha + hb) - zeta0) / s2
            Fpp = (ha - hb) / sb
            Fppp = ha + hb
        else:
            F = r0 * X + eta0 * G2 + zeta0 * G3 - dt
            Fp = r0 + eta0 * G1 + zeta0 * G2
            Fpp = eta0 * c0 + zeta0 * G1
            Fppp = zeta0 * c0 - beta * eta0 * G1
        if F == 0.0:
            return X, G1, G2, G3, Fp, it
        if F > 0.0 or (not math.isfinite(F) and X > 0.0):
            xhi = X          # (cosh overflowed: far beyond the root of a hyperbola)
        else:
            xlo = X
        # Laguerre, n = 5 (F' = r > 0: the sign that avoids cancellation is +)
        dX = -5.0 * F / (Fp + math.sqrt(abs(16.0 * Fp * Fp - 20.0 * F * Fpp)))
        # the last step: a correction that is tiny, or whose own error is below round-off
        # (Laguerre's error after a step dX is about C dX^3, C of the order of
        # (F''/F')^2 + |F'''/F'| as for Halley's method; taken 4 times), while the Taylor
        # series below stays exact to its third order (dX^4 |z| / X^4 <= 1e-20)
        ax = abs(X)
        if abs(dX) <= CONVERGED * ax or (
                dX * dX * max(1.0, abs(z)) <= TAYLOR * ax * ax
                and 4.0 * (Fpp * Fpp + abs(Fppp) * Fp) * abs(dX) ** 3 <= LAST * ax * Fp * Fp):
            # carry G_n to X + dX by their Taylor series to dX^3 (dG_n/dX = G_{n-1},
            # dG0/dX = -beta G1) instead of one more series evaluation
            G0 = c0
            d2 = 0.5 * dX * dX
            d3 = d2 * dX / 3.0
            G1, G2, G3 = (G1 + G0 * dX - beta * (G1 * d2 + G0 * d3),
                          G2 + G1 * dX + G0 * d2 - beta * G1 * d3,
                          G3 + G2 * dX + G1 * d2 + G0 * d3)
            Fp = r0 + eta0 * G1 + zeta0 * G2
            return X + dX, G1, G2, G3, Fp, it
        Xn = X + dX
        # bisect when the step leaves the bracket, or when it does not at least halve the last
        # one from beyond the root (Laguerre's steps down a hyperbola's exponential are about
        # 1.1 / sqrt(-beta) each)
        far = F * dt > 0.0   # beyond the root, where a hyperbola's F grows exponentially
        if not (xlo < Xn < xhi) or (far and was_far and abs(dX) > 0.5 * step):
            if not analytic:
                lo, hi = anomaly_bracket(r0, beta, v2, h2, mu, dt)
                if max(xlo, lo) < min(xhi, hi):     # (else the signs of F know better)
                    xlo, xhi = max(xlo, lo), min(xhi, hi)
                analytic = True
            if math.isfinite(xhi - xlo):
                # the geometric mean when the bracket spans orders of magnitude (a hyperbola's
                # dt / q: the arithmetic mean would overflow cosh)
                Xn = 0.5 * (xlo + xhi)
                if xlo * xhi > 0.0 and xhi > 4.0 * xlo if xlo > 0.0 else xlo < 4.0 * xhi:
                    Xn = math.copysign(math.sqrt(xlo * xhi), xlo)
                if Xn == xlo or Xn == xhi:
                    # the bracket is two neighbouring doubles: X is a root to round-off
                    return X, G1, G2, G3, Fp, it
            elif not (xlo < Xn < xhi):
                return X, G1, G2, G3, Fp, -it
        step = abs(Xn - X)
        was_far = far
        X = Xn
    return X, G1, G2, G3, Fp, -MAX_ITERATIONS


@jit
def gauss_fg(mu, r0, r, dt, G1, G2, G3):
    """Gauss's f - 1, g, fdot and gdot - 1 (the small parts written from G2 and G3 directly,
    as WHFast does: no 1 is added and subtracted)."""
    mr0 = -mu / r0
    ri = 1.0 / r
    return mr0 * G2, dt - mu * G3, mr0 * G1 * ri, -mu * ri * G2


@jit
def conic_state(x0, y0, z0, vx, vy, vz, mu, r0, eta0, beta, zeta0, h2, X):
    """The state at universal anomaly X from the conic's own frame: for a flow that ends deep
    inside r0 (a pericentre passage), where x0 + (f - 1) x0 + g v0 would cancel to an absolute
    error of eps r0.  The pericentre direction P = A / |A| (A = v0 x L / mu - x0 / r0, the
    Laplace-Runge-Lenz vector), Q = L x P / h, and the eccentric (hyperbolic) anomaly
    E1 = E0 + sqrt(beta) X (H1 = H0 + sqrt(-beta) X):

        x1 = a (cos E1 - e) P + a sqrt(1 - e^2) sin E1 Q,
        v1 = sqrt(mu a) / r1 (-sin E1 P + sqrt(1 - e^2) cos E1 Q),   r1 = a (1 - e cos E1),

    with 1 - e = h^2 beta / (mu^2 (1 + e)), sqrt(1 - e^2) = h sqrt(beta) / mu and
    1 - cos E1 = 2 sin^2(E1 / 2): r1 and |v1| keep their relative accuracy, and the state lies
    on the conic of the rounded invariants (its energy is -mu / 2a to round-off).  On a
    hyperbola cosh and sinh, H0 = log(A / B) / 2 from A, B = zeta0 +- eta0 sqrt(-beta)."""
    lx = y0 * vz - z0 * vy
    ly = z0 * vx - x0 * vz
    lz = x0 * vy - y0 * vx
    h = math.sqrt(h2)
    ax = (vy * lz - vz * ly) / mu - x0 / r0
    ay = (vz * lx - vx * lz) / mu - y0 / r0
    az = (vx * ly - vy * lx) / mu - z0 / r0
    na = 1.0 / math.sqrt(ax * ax + ay * ay + az * az)
    px, py, pz = ax * na, ay * na, az * na
    qx, qy, qz = (ly * pz - lz * py) / h, (lz * px - lx * pz) / h, (lx * py - ly * px) / h
    e = math.sqrt(max(1.0 - h2 * beta / (mu * mu), 0.0))
    if beta > 0.0:
        sb = math.sqrt(beta)
        a = mu / beta
        E1 = math.atan2(eta0 * sb, zeta0) + sb * X
        sn = math.sin(E1)
        sh = math.sin(0.5 * E1)
        hs = 2.0 * sh * sh                          # 1 - cos E1
        ome = h2 * beta / (mu * mu) / (1.0 + e)     # 1 - e
        rt = h * sb / mu                            # sqrt(1 - e^2)
        r1 = a * (ome + e * hs)
        cp = a * (ome - hs)
        cq = a * rt * sn
        k = math.sqrt(mu * a) / r1
        wp = -k * sn
        wq = k * rt * (1.0 - hs)
    else:
        sb = math.sqrt(-beta)
        a = -mu / beta
        ca, cb = asymptote_coefficients(beta, eta0, zeta0, h2, mu, sb)
        H1 = 0.5 * math.log(ca / cb) + sb * X
        sn = math.sinh(H1)
        sh = math.sinh(0.5 * H1)
        hs = 2.0 * sh * sh                          # cosh H1 - 1
        em1 = -h2 * beta / (mu * mu) / (e + 1.0)    # e - 1
        rt = h * sb / mu                            # sqrt(e^2 - 1)
        r1 = a * (em1 + e * hs)
        cp = a * (em1 - hs)
        cq = a * rt * sn
        k = math.sqrt(mu * a) / r1
        wp = -k * sn
        wq = k * rt * (1.0 + hs)
    return (cp * px + cq * qx, cp * py + cq * qy, cp * pz + cq * qz,
            wp * px + wq * qx, wp * py + wq * qy, wp * pz + wq * qz)


@jit
def new_state(x0, y0, z0, vx, vy, vz, mu, r0, eta0, beta, zeta0, v2, h2, X, G1, G2, G3, r,
              dt):
    """x0 + (f - 1) x0 + g v0 and v0 + fdot x0 + (gdot - 1) v0, or :func:`conic_state` where
    that would lose digits, on an orbit that is not a parabola: a flow that ends deep inside r0
    (r < r0 / ARRIVAL: f = 1 + (f - 1) and g = dt - mu G3 are small differences there) or far
    outside it (r > ARRIVAL r0: v1 = fdot x0 + gdot v0 is then much slower than v0 and
    cancels), or one whose f x0 + g v0 cancels (|f| r0 + |g| |v0| > ARRIVAL r) or whose
    Wronskian f gdot - g fdot = 1 does (|f gdot| > ARRIVAL: the angular momentum x1 x v1 is
    (f gdot - g fdot) L0), far out along a hyperbola."""
    fm1, g, fd, gdm1 = gauss_fg(mu, r0, r, dt, G1, G2, G3)
    f = 1.0 + fm1
    if (r * ARRIVAL < r0 or r > ARRIVAL * r0
            or (f * f * r0 * r0 + g * g * v2) * 2.0 > (ARRIVAL * r) ** 2
            or abs(f * (1.0 + gdm1)) > ARRIVAL) and beta != 0.0 and h2 > 0.0:
        return conic_state(x0, y0, z0, vx, vy, vz, mu, r0, eta0, beta, zeta0, h2, X)
    return (x0 + (fm1 * x0 + g * vx), y0 + (fm1 * y0 + g * vy), z0 + (fm1 * z0 + g * vz),
            vx + (fd * x0 + gdm1 * vx), vy + (fd * y0 + gdm1 * vy), vz + (fd * z0 + gdm1 * vz))


@jit
def kepler_step(x0, y0, z0, vx, vy, vz, mu, dt):
    """The flow of one body over dt: (x, y, z, vx, vy, vz, iterations); iterations < 0 when the
    universal anomaly did not converge (the state returned is then NaN)."""
    r0, eta0, beta, zeta0, v2, h2 = kepler_scalars(x0, y0, z0, vx, vy, vz, mu)
    dtr, kp = reduce_period(beta, mu, dt)
    X, G1, G2, G3, r, it = universal_anomaly(r0, eta0, beta, zeta0, v2, h2, mu, dtr)
    if it < 0 or not r > 0.0:
        nan = math.nan
        return nan, nan, nan, nan, nan, nan, -abs(it) - 1
    a, b, c, d, e, f = new_state(x0, y0, z0, vx, vy, vz, mu, r0, eta0, beta, zeta0, v2, h2,
                                 X, G1, G2, G3, r, dtr)
    return a, b, c, d, e, f, it


@jit
def kepler_flow_into(x, v, mu, dt, x_out, v_out):
    """The Keplerian flows of N bodies over dt, into x_out, v_out (may be x, v: in place).

    Parameters
    ----------
    x, v : (N, 3) float64
        Positions and velocities relative to each body's centre.
    mu : (N,) float64
        G (M + m) of each body's two-body problem.
    dt : float
        The time of the flow (any sign).
    x_out, v_out : (N, 3) float64
        Written with the new state.

    Returns
    -------
    int
        :data:`OK` (-1), or the index of the first body whose universal anomaly did not
        converge (its outputs are NaN; the other bodies are flowed)."""
    bad = OK
    for i in range(x.shape[0]):
        a, b, c, d, e, f, it = kepler_step(x[i, 0], x[i, 1], x[i, 2], v[i, 0], v[i, 1], v[i, 2],
                                           mu[i], dt)
        x_out[i, 0] = a
        x_out[i, 1] = b
        x_out[i, 2] = c
        v_out[i, 0] = d
        v_out[i, 1] = e
        v_out[i, 2] = f
        if it < 0 and bad == OK:
            bad = i
    return bad



@jit
def beta_slopes(beta, X, G2, G3):
    """G_0 and dG_n/dbeta = (n G_{n+2} - X G_{n+1}) / 2, n = 1, 2, 3, at the universal anomaly
    X: the linearisation's terms that :func:`kepler_step_stm` and :func:`kepler_pullback`
    share (the one forward, the other in reverse mode)."""
    c0, c1, c2, c3, c4, c5 = stumpff5(beta * X * X)
    X2 = X * X
    G4 = X2 * X2 * c4
    G5 = X2 * X2 * X * c5
    return (c0, 0.5 * (G3 - X * G2), 0.5 * (2.0 * G4 - X * G3),
            0.5 * (3.0 * G5 - X * G4))


@jit
def kepler_step_stm(x0, v0, mu, dt, x1, v1, phi):
    """The flow of one body over dt and its Jacobian, the state transition matrix
    (:func:`kepler_step_stm_x`, its iterations only)."""
    it, X, kp = kepler_step_stm_x(x0, v0, mu, dt, x1, v1, phi)
    return it


@jit
def kepler_step_stm_x(x0, v0, mu, dt, x1, v1, phi):
    """The flow of one body over dt and its Jacobian, the state transition matrix.

    ``x0``, ``v0``, ``x1``, ``v1``: (3,) arrays; ``phi``: (6, 6), written with
    d(x1, v1) / d(x0, v0).  Returns the iterations (< 0: no convergence; outputs NaN), the
    universal anomaly X and the period reduction k P (0: none) of the flow (the start of its
    double-double refinement, :func:`integrators.kepler_flow_dd.kepler_refine_dd`).

    The derivative of x1 = f x0 + g v0, v1 = fdot x0 + gdot v0 through the scalars r0, eta0,
    beta, zeta0 and X (Kepler's equation differentiated implicitly:
    r dX = -(X dr0 + G2 deta0 + G3 dzeta0 + (eta0 dG2/dbeta + zeta0 dG3/dbeta) dbeta),
    dG_n = G_{n-1} dX + dG_n/dbeta dbeta, dG_n/dbeta = (n G_{n+2} - X G_{n+1}) / 2); the same
    linearisation as WHFast's variational particles (Rein and Tamayo 2016), as a matrix."""
    r0, eta0, beta, zeta0, v2, h2 = kepler_scalars(x0[0], x0[1], x0[2], v0[0], v0[1], v0[2], mu)
    dtr, kp = reduce_period(beta, mu, dt)
    X, G1, G2, G3, r, it = universal_anomaly(r0, eta0, beta, zeta0, v2, h2, mu, dtr)
    if it < 0 or not r > 0.0:
        for i in range(3):
            x1[i] = math.nan
            v1[i] = math.nan
        phi[:, :] = math.nan
        return -abs(it) - 1, X, kp
    G0, G1b, G2b, G3b = beta_slopes(beta, X, G2, G3)
    fm1, g, fd, gdm1 = gauss_fg(mu, r0, r, dtr, G1, G2, G3)
    (x1[0], x1[1], x1[2], v1[0], v1[1], v1[2]) = new_state(
        x0[0], x0[1], x0[2], v0[0], v0[1], v0[2], mu, r0, eta0, beta, zeta0, v2, h2, X, G1, G2,
        G3, r, dtr)
    ri = 1.0 / r
    r0i = 1.0 / r0
    # gradients (6,) with respect to (x0, v0), one component j at a time
    for j in range(6):
        if j < 3:
            dr0 = x0[j] * r0i
            deta0 = v0[j]
            dbeta = -2.0 * mu * dr0 * r0i * r0i
        else:
            dr0 = 0.0
            deta0 = x0[j - 3]
            dbeta = -2.0 * v0[j - 3]
        dzeta0 = -beta * dr0 - r0 * dbeta
        # (the reduced time dt - k P moves with the period: d(k P) = -1.5 k P dbeta / beta)
        dX = -ri * (X * dr0 + G2 * deta0 + G3 * dzeta0 + (eta0 * G2b + zeta0 * G3b) * dbeta
                    - 1.5 * kp * dbeta / beta)
        dG1 = G0 * dX + G1b * dbeta
        dG2 = G1 * dX + G2b * dbeta
        dG3 = G2 * dX + G3b * dbeta
        dr = dr0 + G1 * deta0 + G2 * dzeta0 + eta0 * dG1 + zeta0 * dG2
        df = mu * (G2 * dr0 * r0i - dG2) * r0i
        dg = 1.5 * kp * dbeta / beta - mu * dG3
        dfd = mu * (G1 * (dr0 * r0i + dr * ri) - dG1) * r0i * ri
        dgd = mu * (G2 * dr * ri - dG2) * ri
        for i in range(3):
            phi[i, j] = df * x0[i] + dg * v0[i]
            phi[3 + i, j] = dfd * x0[i] + dgd * v0[i]
        if j < 3:
            phi[j, j] += 1.0 + fm1
            phi[3 + j, j] += fd
        else:
            phi[j - 3, j] += g
            phi[j, j] += 1.0 + gdm1
    return it, X, kp


SAVED = 12                # the scalars kepler_step_saved keeps for kepler_pullback


@jit
def kepler_step_saved(x0, y0, z0, vx, vy, vz, mu, dt, sv, row):
    """The flow of one body over dt, (x, y, z, vx, vy, vz, iterations) as :func:`kepler_step`,
    keeping in ``sv[row]`` (SAVED numbers) the scalars :func:`kepler_pullback` needs for
    Phi^T g later: a function of all the flowed states (the planets' interactions) is known
    only after every body has been flowed.  (Scalars in and out, no array views: a view a
    call cost 60 of 150 ns, measured.)"""
    r0, eta0, beta, zeta0, v2, h2 = kepler_scalars(x0, y0, z0, vx, vy, vz, mu)
    dtr, kp = reduce_period(beta, mu, dt)
    X, G1, G2, G3, r, it = universal_anomaly(r0, eta0, beta, zeta0, v2, h2, mu, dtr)
    if it < 0 or not r > 0.0:
        nan = math.nan
        for j in range(SAVED):
            sv[row, j] = nan
        return nan, nan, nan, nan, nan, nan, -abs(it) - 1
    a, b, c, d, e, f = new_state(x0, y0, z0, vx, vy, vz, mu, r0, eta0, beta, zeta0, v2, h2,
                                 X, G1, G2, G3, r, dtr)
    sv[row, 0] = r0
    sv[row, 1] = eta0
    sv[row, 2] = beta
    sv[row, 3] = zeta0
    sv[row, 4] = X
    sv[row, 5] = r
    sv[row, 6] = G1
    sv[row, 7] = G2
    sv[row, 8] = G3
    sv[row, 9] = dtr
    sv[row, 10] = kp
    sv[row, 11] = mu
    return a, b, c, d, e, f, it


@jit
def kepler_pullback(x0, y0, z0, vx, vy, vz, sv, row, gx, gy, gz, gu, gv, gw):
    """Phi^T (g_x, g_v) as six numbers (the x part, then the v part), Phi = d(x1, v1) /
    d(x0, v0) the state transition matrix of the flow :func:`kepler_step_saved` took from
    (x0, v0) (its scalars in ``sv[row]``), without forming Phi: the gradient of a function of
    the flowed state pulled back to the initial one (the flow-composed methods' right-hand
    side, :mod:`systems.flow_composed`).

    The same linearisation as :func:`kepler_step_stm`, whose every column is a combination of
    the gradients of the three scalars r0, eta0 and beta (zeta0, X, the G_n and r follow from
    them): Phi^T g is those three gradients weighted by three numbers, plus f, g, fdot and
    gdot times g (measured: the flow 90 ns, with the STM 196 ns)."""
    r0, eta0, beta, zeta0, X, r = sv[row, 0], sv[row, 1], sv[row, 2], sv[row, 3], sv[row, 4], sv[row, 5]
    G1, G2, G3, dtr, kp, mu = sv[row, 6], sv[row, 7], sv[row, 8], sv[row, 9], sv[row, 10], sv[row, 11]
    G0, G1b, G2b, G3b = beta_slopes(beta, X, G2, G3)
    fm1, g, fd, gdm1 = gauss_fg(mu, r0, r, dtr, G1, G2, G3)
    ri = 1.0 / r
    r0i = 1.0 / r0
    xg = x0 * gx + y0 * gy + z0 * gz
    vg = vx * gx + vy * gy + vz * gz
    xw = x0 * gu + y0 * gv + z0 * gw
    vw = vx * gu + vy * gv + vz * gw
    # the weights cr, ce, cb of the gradients of r0, eta0 and beta: the STM's column formulas
    # (kepler_step_stm: df, dg, dfd, dgd from dr0, deta0, dbeta through dzeta0, dX, dG_n and
    # dr) run backwards once (reverse mode), dotted with the vector
    K = 1.5 * kp / beta if kp != 0.0 else 0.0
    # c = xg df + vg dg + xw dfd + vw dgd
    w_dr = mu * ri * ri * (xw * r0i * G1 + vw * G2)
    w_G1 = -xw * mu * r0i * ri + eta0 * w_dr
    w_G2 = -xg * mu * r0i - vw * mu * ri + zeta0 * w_dr
    w_G3 = -vg * mu
    cr = mu * r0i * r0i * (xg * G2 + xw * ri * G1) + w_dr
    ce = G1 * w_dr
    w_z = G2 * w_dr
    cb = vg * K + G1b * w_G1 + G2b * w_G2 + G3b * w_G3
    w_X = G0 * w_G1 + G1 * w_G2 + G2 * w_G3
    cr -= ri * X * w_X
    ce -= ri * G2 * w_X
    w_z -= ri * G3 * w_X
    cb -= ri * (eta0 * G2b + zeta0 * G3b - K) * w_X
    cr -= beta * w_z
    cb -= r0 * w_z
    # grad r0 = (x0 / r0, 0), grad eta0 = (v0, x0), grad beta = (-2 mu x0 / r0^3, -2 v0)
    a = cr * r0i - 2.0 * mu * cb * r0i * r0i * r0i
    f1 = 1.0 + fm1
    gd1 = 1.0 + gdm1
    b = -2.0 * cb
    return (a * x0 + ce * vx + f1 * gx + fd * gu, a * y0 + ce * vy + f1 * gy + fd * gv,
            a * z0 + ce * vz + f1 * gz + fd * gw, ce * x0 + b * vx + g * gx + gd1 * gu,
            ce * y0 + b * vy + g * gy + gd1 * gv, ce * z0 + b * vz + g * gz + gd1 * gw)


@jit
def kepler_step_vjp(x0, v0, mu, dt, gx, gv, x1, v1, wx, wv):
    """The flow of one body over dt into x1, v1 and (wx, wv) = Phi^T (gx, gv)
    (:func:`kepler_pullback`); (3,) arrays.  Returns the iterations (< 0: no convergence;
    outputs NaN)."""
    sv = np.empty((1, SAVED))
    x1[0], x1[1], x1[2], v1[0], v1[1], v1[2], it = kepler_step_saved(
        x0[0], x0[1], x0[2], v0[0], v0[1], v0[2], mu, dt, sv, 0)
    wx[0], wx[1], wx[2], wv[0], wv[1], wv[2] = kepler_pullback(
        x0[0], x0[1], x0[2], v0[0], v0[1], v0[2], sv, 0, gx[0], gx[1], gx[2], gv[0], gv[1], gv[2])
    return it


@jit
def kepler_flow_stm_into(x, v, mu, dt, x_out, v_out, phi):
    """:func:`kepler_flow_into` with each body's 6x6 state transition matrix into ``phi``
    (N, 6, 6).  Returns :data:`OK` or the index of the first body that did not converge."""
    bad = OK
    for i in range(x.shape[0]):
        it = kepler_step_stm(x[i], v[i], mu[i], dt, x_out[i], v_out[i], phi[i])
        if it < 0 and bad == OK:
            bad = i
    return bad


def _check(x, v, mu, dt):
    x = np.asarray(x, dtype=float)
    v = np.asarray(v, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"`x` must have shape (N, 3) (got {x.shape}): one row per body")
    if v.shape != x.shape:
        raise ValueError(f"`v` must have the shape of `x`, {x.shape} (got {v.shape})")
    mu = np.broadcast_to(np.asarray(mu, dtype=float), (x.shape[0],))
    if not np.all(np.isfinite(mu) & (mu > 0)):
        raise ValueError(f"`mu` must be finite and > 0 for every body (got {mu[~(mu > 0)][:3]}"
                         " ...): mu = G (M + m)")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
        raise ValueError("`x` and `v` must be finite")
    r = np.sqrt(np.einsum("ij,ij->i", x, x))
    if np.any(r == 0.0):
        raise ValueError(f"`x` of body {int(np.argmin(r))} is at the centre (|x| = 0): the "
                         "Keplerian flow is singular there")
    if not math.isfinite(float(dt)):
        raise ValueError(f"`dt` must be finite (got {dt})")
    return (np.ascontiguousarray(x), np.ascontiguousarray(v), np.ascontiguousarray(mu),
            float(dt))


def kepler_flow_stm(x, v, mu, dt: float):
    """The Keplerian flows and their state transition matrices: ``(x_out, v_out, phi)``,
    ``phi`` (N, 6, 6) = d(x_out, v_out) / d(x, v) (checked wrapper of
    :func:`kepler_flow_stm_into`)."""
    x, v, mu, dt = _check(x, v, mu, dt)
    x_out, v_out = np.empty_like(x), np.empty_like(v)
    phi = np.empty((x.shape[0], 6, 6))
    _raise(kepler_flow_stm_into(x, v, mu, dt, x_out, v_out, phi), x, v, mu, dt)
    return x_out, v_out, phi


def _raise(bad, x, v, mu, dt):
    if bad != OK:
        raise RuntimeError(f"Kepler solver: the universal anomaly of body {bad} did not converge "
                           f"(dt={dt!r}, x={x[bad].tolist()}, v={v[bad].tolist()}, "
                           f"mu={mu[bad]!r}); a collision orbit (zero angular momentum)?")


def kepler_flow(x, v, mu, dt: float, x_out=None, v_out=None):
    """The Keplerian flows of N bodies over ``dt`` (checked wrapper of :func:`kepler_flow_into`).

    ``x``, ``v``: (N, 3); ``mu``: (N,) or a scalar.  Returns ``(x_out, v_out)`` (new arrays
    unless given; they may be ``x`` and ``v``).  Raises ``ValueError`` for bad input and
    ``RuntimeError`` naming the body whose universal anomaly did not converge."""
    x, v, mu, dt = _check(x, v, mu, dt)
    x_out = np.empty_like(x) if x_out is None else x_out
    v_out = np.empty_like(v) if v_out is None else v_out
    _raise(kepler_flow_into(x, v, mu, dt, x_out, v_out), x, v, mu, dt)
    return x_out, v_out


def reference_flow(x0, v0, mu, dt, dps: int = 40):
    """The two-body flow in extended precision (mpmath, ``dps`` digits), for tests: classical
    elements, not universal variables (an independent formulation).

    The double inputs are taken exactly; the eccentric (or hyperbolic) anomaly solves
    Kepler's equation E - e sin E = M (e sinh H - H = M) by Newton's method kept inside the
    bracket ``|E - M| <= e`` (``0 <= H / sign(M) <= asinh(|M| / (e - 1))``).  Returns (x, v), each a
    list of three ``mpmath.mpf``; not defined for an exactly parabolic state (1/a = 0)."""
    import mpmath as mp
    with mp.workdps(dps + 10):
        x0 = [mp.mpf(float(c)) for c in x0]
        v0 = [mp.mpf(float(c)) for c in v0]
        mu, dt = mp.mpf(float(mu)), mp.mpf(float(dt))
        r0 = mp.sqrt(sum(c * c for c in x0))
        eta0 = sum(a * b for a, b in zip(x0, v0))
        alpha = 2 / r0 - sum(c * c for c in v0) / mu          # 1 / a
        tol = mp.mpf(10) ** -(dps + 5)
        if alpha > 0:
            a = 1 / alpha
            n = mp.sqrt(mu * alpha ** 3)
            ec, es = 1 - r0 * alpha, eta0 / mp.sqrt(mu * a)    # e cos E0, e sin E0
            e, E0 = mp.sqrt(ec * ec + es * es), mp.atan2(es, ec)
            M = E0 - es + n * dt
            lo, hi, E = M - e, M + e, M
            for _ in range(400):
                k = E - e * mp.sin(E) - M
                lo, hi = (E, hi) if k < 0 else (lo, E)
                En = E - k / (1 - e * mp.cos(E))
                if not lo <= En <= hi:
                    En = (lo + hi) / 2
                if abs(En - E) <= tol * (1 + abs(E)):
                    E = En
                    break
                E = En
            else:
                raise RuntimeError("reference_flow: Kepler's equation did not converge")
            dE = E - E0
            f = 1 - a / r0 * (1 - mp.cos(dE))
            g = dt - (dE - mp.sin(dE)) / n
            r = a * (1 - e * mp.cos(E))
            fd = -mp.sqrt(mu * a) * mp.sin(dE) / (r * r0)
            gd = 1 - a / r * (1 - mp.cos(dE))
        elif alpha < 0:
            a = 1 / alpha
            n = mp.sqrt(mu * (-alpha) ** 3)
            ec, es = 1 - r0 * alpha, eta0 / mp.sqrt(-mu * a)   # e cosh H0, e sinh H0
            e, H0 = mp.sqrt(ec * ec - es * es), mp.atanh(es / ec)
            M = es - H0 + n * dt
            lo, hi = (mp.mpf(0), mp.asinh(M / (e - 1))) if M >= 0 else \
                (mp.asinh(M / (e - 1)), mp.mpf(0))
            H = (lo + hi) / 2
            for _ in range(400):
                k = e * mp.sinh(H) - H - M
                lo, hi = (H, hi) if k < 0 else (lo, H)
                Hn = H - k / (e * mp.cosh(H) - 1)
                if not lo <= Hn <= hi:
                    Hn = (lo + hi) / 2
                if abs(Hn - H) <= tol * (1 + abs(H)):
                    H = Hn
                    break
                H = Hn
            else:
                raise RuntimeError("reference_flow: Kepler's equation did not converge")
            dH = H - H0
            f = 1 - a / r0 * (1 - mp.cosh(dH))
            g = dt - (mp.sinh(dH) - dH) / n
            r = a * (1 - e * mp.cosh(H))
            fd = -mp.sqrt(-mu * a) * mp.sinh(dH) / (r * r0)
            gd = 1 - a / r * (1 - mp.cosh(dH))
        else:
            raise ValueError("reference_flow: the state is exactly parabolic (1/a = 0)")
        x = [f * p + g * q for p, q in zip(x0, v0)]
        v = [fd * p + gd * q for p, q in zip(x0, v0)]
    return x, v


def orbit_state(e, M, mu=1.0, inc=0.3, node=0.7, peri=1.1):
    """Position and velocity (3,), (3,) at mean anomaly M of the conic a = 1 (ellipse) or
    a = -1 (hyperbola) with eccentricity e about mu, tilted out of every coordinate plane: the
    test and benchmark states of the flow (plain Python, not compiled)."""
    if e < 1:
        E = M
        for _ in range(100):
            E -= (E - e * math.sin(E) - M) / (1 - e * math.cos(E))
        d = 1 - e * math.cos(E)
        p = (math.cos(E) - e, math.sqrt(1 - e * e) * math.sin(E))
        w = (-math.sin(E) / d, math.sqrt(1 - e * e) * math.cos(E) / d)
    else:
        H = math.asinh(M / e)
        for _ in range(200):
            H -= (e * math.sinh(H) - H - M) / (e * math.cosh(H) - 1)
        d = e * math.cosh(H) - 1
        p = (e - math.cosh(H), math.sqrt(e * e - 1) * math.sinh(H))
        w = (-math.sinh(H) / d, math.sqrt(e * e - 1) * math.cosh(H) / d)
    co, so, ci, si, cn, sn = (math.cos(peri), math.sin(peri), math.cos(inc), math.sin(inc),
                              math.cos(node), math.sin(node))

    def rot(a, b):
        a, b = co * a - so * b, so * a + co * b
        return np.array([cn * a - sn * ci * b, sn * a + cn * ci * b, si * b])
    return rot(*p), rot(*w) * math.sqrt(mu)
