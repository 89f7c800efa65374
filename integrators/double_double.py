"""Double-double arithmetic: a number as an unevaluated sum hi + lo of two doubles,
|lo| <= ulp(hi) / 2, about 106 bits (Dekker 1971; Bailey's QD library; Hida, Li and Bailey,
"Library for double-double and quad-double arithmetic", 2007, whose "accurate" addition is used
here).

For the few places where one rounding of a double a step is the error that remains: the
compensated recentring of the flow-composed methods (:mod:`integrators.kepler_flow_dd`).
Scalars in and out (pairs), no arrays, so that numba keeps everything in registers.  Built on
:func:`integrators.core.two_sum` and :func:`integrators.core.two_product` (fused when compiled;
the same numbers as Python, ``NUMBA_DISABLE_JIT=1``).
"""
from __future__ import annotations

import math

from .core import two_product, two_sum
from .jit import jit

# pi as a double-double: pi - PI_HI rounded (the next 53 bits of pi)
PI_HI = math.pi
PI_LO = 1.2246467991473532e-16


@jit
def quick_two_sum(a, b):
    """a + b = s + e exactly, for |a| >= |b| (or a = 0)."""
    s = a + b
    return s, b - (s - a)


@jit
def dd_add(ah, al, bh, bl):
    """(ah + al) + (bh + bl), relative error about 2 eps^2 (the "accurate" sum: both parts
    added error-free, so that cancellation of the high parts keeps the low parts' digits)."""
    s, e = two_sum(ah, bh)
    t, f = two_sum(al, bl)
    e += t
    s, e = quick_two_sum(s, e)
    e += f
    return quick_two_sum(s, e)


@jit
def dd_add_d(ah, al, b):
    """(ah + al) + b for a double b."""
    s, e = two_sum(ah, b)
    e += al
    return quick_two_sum(s, e)


@jit
def dd_mul(ah, al, bh, bl):
    """(ah + al) (bh + bl), relative error about 4 eps^2."""
    p, e = two_product(ah, bh)
    e += ah * bl + al * bh
    return quick_two_sum(p, e)


@jit
def dd_mul_d(ah, al, b):
    """(ah + al) b for a double b."""
    p, e = two_product(ah, b)
    e += al * b
    return quick_two_sum(p, e)


@jit
def dd_div(ah, al, bh, bl):
    """(ah + al) / (bh + bl): the double quotient q1, then the remainder a - q1 b formed in
    double-double and divided once more (its error is eps^2 |q|)."""
    q1 = ah / bh
    ph, pl = dd_mul_d(bh, bl, q1)
    rh, rl = dd_add(ah, al, -ph, -pl)
    return quick_two_sum(q1, (rh + rl) / bh)


@jit
def dd_sqrt(ah, al):
    """sqrt(ah + al) for ah + al >= 0: one Newton step from the double root (the residual
    a - s^2 exact to eps^2 by :func:`two_product`)."""
    if not ah > 0.0:
        return 0.0, 0.0
    s = math.sqrt(ah)
    ph, pl = two_product(s, s)
    rh, rl = dd_add(ah, al, -ph, -pl)
    return quick_two_sum(s, (rh + rl) / (2.0 * s))
