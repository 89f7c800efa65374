"""Quadrature rules and the orthonormal shifted Legendre basis, in extended precision.

Everything here is computed with mpmath at ``_DPS`` decimal digits and rounded once to
double at the end; :func:`split` keeps the rounding remainder (``lo``) of each coefficient so
that the stepping engine can apply a coefficient matrix as ``hi @ x + lo @ x``.

References
----------
Brugnano, Iavernaro, Trigiante, "The lack of continuity and the role of infinite and
infinitesimal in numerical methods for ODEs: the case of symplecticity", eqs. (orto1), (IDPO).
"""
from __future__ import annotations

from functools import lru_cache

import mpmath
import numpy as np

_DPS = 40  # about 2.5 times double precision: the remainders are exact to double


def _legendre_pair(n: int, x: mpmath.mpf) -> tuple[mpmath.mpf, mpmath.mpf]:
    """(L_{n-1}(x), L_n(x)) by the three-term recurrence (n >= 1)."""
    p0, p1 = mpmath.mpf(1), x
    for j in range(2, n + 1):
        p0, p1 = p1, ((2 * j - 1) * x * p1 - (j - 1) * p0) / j
    return p0, p1


def _legendre_value(n: int, x: mpmath.mpf) -> mpmath.mpf:
    """L_n(x), valid on the whole of [-1, 1] including the end points."""
    return mpmath.mpf(1) if n == 0 else _legendre_pair(n, x)[1]


def _legendre(n: int, x: mpmath.mpf) -> tuple[mpmath.mpf, mpmath.mpf]:
    """L_n(x) and L'_n(x) for n >= 1 and |x| < 1."""
    p0, p1 = _legendre_pair(n, x)
    return p1, n * (x * p1 - p0) / (x * x - 1)


@lru_cache(maxsize=None)
def gauss_legendre(n: int) -> tuple[tuple, tuple]:
    """Nodes and weights of the n-point Gauss-Legendre rule on [0, 1], as mpmath numbers.

    Exact for polynomials of degree 2n - 1.  Newton's method in extended precision, started
    from numpy's double-precision nodes.
    """
    with mpmath.workdps(_DPS):
        x0, _ = np.polynomial.legendre.leggauss(n)
        nodes, weights = [], []
        for xi in x0:
            x = mpmath.mpf(float(xi))
            for _ in range(100):
                p, dp = _legendre(n, x)
                dx = p / dp
                x -= dx
                if abs(dx) < mpmath.mpf(10) ** (-_DPS + 3):
                    break
            _, dp = _legendre(n, x)
            w = 2 / ((1 - x * x) * dp * dp)
            nodes.append((x + 1) / 2)
            weights.append(w / 2)
        return tuple(nodes), tuple(weights)


@lru_cache(maxsize=None)
def gauss_lobatto(n: int) -> tuple[tuple, tuple]:
    """Nodes and weights of the n-point Lobatto rule on [0, 1] (n >= 2, including 0 and 1).

    Exact for polynomials of degree 2n - 3.  Interior nodes are the roots of L'_{n-1}.
    """
    if n < 2:
        raise ValueError(f"a Lobatto rule needs at least 2 points (got n={n})")
    with mpmath.workdps(_DPS):
        m = n - 1
        # interior nodes: roots of L'_m, i.e. the Gauss-Jacobi(1,1) nodes; double-precision start
        start = np.sort(np.polynomial.legendre.Legendre.basis(m).deriv().roots().real)
        xs = [mpmath.mpf(-1)]
        for xi in start:
            x = mpmath.mpf(float(xi))
            for _ in range(100):
                p, dp = _legendre(m, x)
                # L'_m and L''_m: (1 - x^2) L''_m = 2 x L'_m - m (m + 1) L_m
                d2p = (2 * x * dp - m * (m + 1) * p) / (1 - x * x)
                dx = dp / d2p
                x -= dx
                if abs(dx) < mpmath.mpf(10) ** (-_DPS + 3):
                    break
            xs.append(x)
        xs.append(mpmath.mpf(1))
        nodes, weights = [], []
        for x in xs:
            p = _legendre_value(m, x)
            w = mpmath.mpf(2) / (m * (m + 1) * p * p)
            nodes.append((x + 1) / 2)
            weights.append(w / 2)
        return tuple(nodes), tuple(weights)


def shifted_legendre_values(t: mpmath.mpf, s: int) -> list:
    """P_1(t), ..., P_s(t): the orthonormal shifted Legendre basis on [0, 1], eq. (orto1).

    P_j(t) = sqrt(2j - 1) L_{j-1}(2t - 1) has degree j - 1 and int_0^1 P_i P_j = delta_ij.
    """
    x = 2 * t - 1
    vals, p0, p1 = [], mpmath.mpf(1), x
    for j in range(1, s + 1):
        n = j - 1
        if n == 0:
            ln = p0
        elif n == 1:
            ln = p1
        else:
            p0, p1 = p1, ((2 * n - 1) * x * p1 - (n - 1) * p0) / n
            ln = p1
        vals.append(mpmath.sqrt(2 * j - 1) * ln)
    return vals


def shifted_legendre_integrals(t: mpmath.mpf, s: int) -> list:
    """int_0^t P_j(x) dx for j = 1..s, eq. (IDPO).

    Uses the Legendre identity int_{-1}^{x} L_n = (L_{n+1}(x) - L_{n-1}(x)) / (2n + 1), n >= 1,
    which is independent of Lemma 2 of the paper (so that tests of the lemma are not circular).
    """
    x = 2 * t - 1
    L = [mpmath.mpf(1), x]
    for n in range(1, s + 1):
        L.append(((2 * n + 1) * x * L[n] - n * L[n - 1]) / (n + 1))
    out = []
    for j in range(1, s + 1):
        n = j - 1
        integral = t if n == 0 else (L[n + 1] - L[n - 1]) / (2 * (2 * n + 1))
        out.append(mpmath.sqrt(2 * j - 1) * integral)
    return out


def split(values) -> tuple[np.ndarray, np.ndarray]:
    """Round an (nested) sequence of mpmath numbers to double: (hi, lo) with hi + lo ~ value.

    ``lo`` is the rounding remainder, itself rounded: the pair carries about 32 digits.
    """
    arr = np.array(values, dtype=object)
    hi = np.vectorize(lambda v: float(v), otypes=[float])(arr) if arr.size else arr.astype(float)
    with mpmath.workdps(_DPS):
        lo = np.vectorize(lambda v, h: float(v - mpmath.mpf(h)), otypes=[float])(arr, hi) if arr.size else hi * 0
    return hi, lo


@lru_cache(maxsize=None)
def gauss_rule01(s: int) -> tuple[np.ndarray, np.ndarray]:
    """The s-point Gauss-Legendre rule on [0, 1] (nodes, weights; read-only, once per s), which
    integrates the extrapolation matrices' products of degree 2s - 2 exactly."""
    t, w = np.polynomial.legendre.leggauss(s)
    t, w = (t + 1) / 2, w / 2
    t.flags.writeable = False
    w.flags.writeable = False
    return t, w
