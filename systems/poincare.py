"""Poincare time transformation: variable physical steps from a fixed fictitious step.

Given a Hamiltonian H(q, p) with m degrees of freedom, a positive step-size function g(q) and
the energy level H0 = H(y0), the extended Hamiltonian (HLW Sec. VIII.2, eq. (2.6))

    K(q, t, p, e) = g(q) (H(q, p) + e),        e = -H0 conjugate to the time t,

in the extended phase space (q, t; p, e) of dimension 2 (m + 1) is again Hamiltonian.  Its
flow in the fictitious time tau is

    dq/dtau = g dH/dp,   dp/dtau = -g dH/dq - (H + e) grad g,   dt/dtau = dK/de = g(q),
    de/dtau = -dK/dt = 0,

so on the level K = 0 (which holds at tau = 0) it is the flow of H with the clock slowed down by
g: a fixed step in tau is a physical step of about g(q) times it.  With g = |q|^alpha on the
Kepler problem the physical step shrinks at pericentre.  HBVM(k, s) conserves K (for
non-polynomial K: to round-off with k large enough); because e never changes, H = H0 - K / g
stays on H0 to the same accuracy.  Physical time is the coordinate t of the extended state.

The transformed system is not separable: use it through the full form of the engine (it offers
no ``masses``/``forces``), with the gradient batched over a leading axis, and
``polynomial_degree`` None.
"""
from __future__ import annotations

from typing import Callable

import numpy as np


from integrators.jit import jit

from .base import HamiltonianSystem


def distance_power(alpha: float, indices=None) -> tuple[Callable, Callable]:
    """g(q) = |q_I|^alpha and its gradient, batched over a leading axis.

    Parameters
    ----------
    alpha : float
        Exponent; alpha = 1 is Sundman's transformation (for Kepler the fictitious time is then
        the eccentric anomaly), alpha = 3/2 equalises the mean anomaly.
    indices : sequence of int, optional
        The coordinates that form the distance (default: all of q).

    Returns
    -------
    g : callable, q (..., m) -> (...)
    grad_g : callable, q (..., m) -> (..., m)
    """
    if not np.isfinite(alpha):
        raise ValueError(f"`alpha` must be a finite number (got alpha={alpha!r})")
    alpha = float(alpha)
    idx = None if indices is None else np.asarray(indices, dtype=int)

    def g(q):
        q = np.asarray(q, dtype=float)
        qi = q if idx is None else q[..., idx]
        return np.sum(qi * qi, axis=-1) ** (0.5 * alpha)

    def grad_g(q):
        q = np.asarray(q, dtype=float)
        qi = q if idx is None else q[..., idx]
        r2 = np.sum(qi * qi, axis=-1, keepdims=True)
        out = np.zeros_like(q)
        # d/dq |q|^alpha = alpha |q|^(alpha - 2) q
        gi = alpha * r2 ** (0.5 * alpha - 1.0) * qi
        if idx is None:
            out[...] = gi
        else:
            out[..., idx] = gi
        return out

    return g, grad_g


class PoincareTransformed(HamiltonianSystem):
    """K(q, t, p, e) = g(q) (H(q, p) + e) in the extended phase space (q, t; p, e).

    Build it with :meth:`for_kepler` for a Kepler problem (g = |q|^alpha, compiled kernels), or
    from any system with your own g and its gradient (e.g. :func:`distance_power`).

    Parameters
    ----------
    system : HamiltonianSystem
        The original system H (batched ``energy`` and ``gradient``), m = ``system.dim``.
    g, grad_g : callable
        The step-size function g(q) > 0 and its gradient, batched: q (..., m) -> (...) and
        (..., m).  See :func:`distance_power`.
    H0 : float
        The energy level of the orbit, H(y0); the extended state starts with e = -H0.

    Attributes
    ----------
    dim : int
        m + 1.  Extended states are Y = (q (m), t, p (m), e), shape (2 m + 2,).
    polynomial_degree : None

    Examples
    --------
    >>> from systems import Kepler
    >>> kep = Kepler(0.9)
    >>> pt = PoincareTransformed.for_kepler(kep, alpha=1.0)
    >>> Y0 = pt.extend(kep.initial_state())
    >>> float(pt.energy(Y0))
    0.0
    """

    polynomial_degree = None

    def __init__(self, system, g: Callable, grad_g: Callable, H0: float):
        if not hasattr(system, "dim") or not hasattr(system, "gradient") or not hasattr(system, "energy"):
            raise TypeError(f"`system` must offer `dim`, `energy(y)` and `gradient(y)` "
                            f"(got {type(system).__name__}); see systems.base")
        if not callable(g) or not callable(grad_g):
            raise TypeError("`g` and `grad_g` must be callables q (..., m) -> (...) and (..., m); "
                            "see systems.poincare.distance_power")
        if not np.isfinite(H0):
            raise ValueError(f"`H0` must be a finite number, the energy of the orbit (got H0={H0!r})")
        self.base, self.g, self.grad_g = system, g, grad_g
        self.m = int(system.dim)
        self.dim = self.m + 1
        self.H0 = float(H0)

    @classmethod
    def for_kepler(cls, kepler, alpha: float = 1.0, y0=None) -> "PoincareTransformed":
        """g = |q|^alpha on a Kepler problem, at the energy of y0 (default its initial state).

        Returns a :class:`PoincareKepler`, which also offers compiled kernels
        (``full_kernels``), so that ``integrate`` runs it on the compiled full-form path."""
        y0 = kepler.initial_state() if y0 is None else np.asarray(y0, dtype=float)
        g, grad_g = distance_power(alpha)
        return PoincareKepler(kepler, g, grad_g, float(kepler.energy(y0)), float(alpha))

    # -- the extended state ------------------------------------------------------------
    def extend(self, y, t: float = 0.0) -> np.ndarray:
        """Y = (q, t, p, -H0) from an original state y = (q, p), shape (2m,) -> (2m + 2,)."""
        y = np.asarray(y, dtype=float)
        if y.shape != (2 * self.m,):
            raise ValueError(f"`y` must have shape ({2 * self.m},) (got shape {y.shape})")
        q, p = y[: self.m], y[self.m:]
        return np.concatenate([q, [float(t)], p, [-self.H0]])

    def physical(self, Y) -> tuple[np.ndarray, np.ndarray]:
        """(t, y) from extended states Y (..., 2m + 2): physical time (...) and y (..., 2m)."""
        Y = np.asarray(Y, dtype=float)
        m = self.m
        q, t, p = Y[..., :m], Y[..., m], Y[..., m + 1: 2 * m + 1]
        return t, np.concatenate([q, p], axis=-1)

    def original_energy(self, Y):
        """H(q, p) of extended states Y (..., 2m + 2)."""
        return self.base.energy(self.physical(Y)[1])

    def step_factor(self, Y):
        """g(q) = dt/dtau at extended states Y (..., 2m + 2)."""
        return self.g(np.asarray(Y, dtype=float)[..., : self.m])

    # -- the protocol ------------------------------------------------------------------
    def energy(self, Y):
        """K(Y) = g(q) (H(q, p) + e), for Y (2m + 2,) or a stack (n, 2m + 2)."""
        Y = np.asarray(Y, dtype=float)
        t, y = self.physical(Y)
        e = Y[..., -1]
        return self.g(Y[..., : self.m]) * (self.base.energy(y) + e)

    def gradient(self, Y):
        """grad K = (g H_q + (H + e) grad g, 0, g H_p, g), batched over a leading axis."""
        Y = np.asarray(Y, dtype=float)
        m = self.m
        _, y = self.physical(Y)
        q, e = Y[..., :m], Y[..., -1]
        gq = self.g(q)[..., None]
        gradH = np.asarray(self.base.gradient(y), dtype=float)
        shift = (np.asarray(self.base.energy(y), dtype=float) + e)[..., None]
        dq = gq * gradH[..., :m] + shift * self.grad_g(q)
        dp = gq * gradH[..., m:]
        zero = np.zeros(Y.shape[:-1] + (1,))
        return np.concatenate([dq, zero, dp, gq], axis=-1)


@jit
def _kepler_poincare_gradient(Y, params, out):
    # Y = (q1, q2, t, p1, p2, e); K = g (H + e), g = |q|^alpha, H = |p|^2 / 2 - mu / |q|
    mu, alpha = params[0], params[1]
    for i in range(Y.shape[0]):
        x, y, p1, p2, e = Y[i, 0], Y[i, 1], Y[i, 3], Y[i, 4], Y[i, 5]
        r2 = x * x + y * y
        r = np.sqrt(r2)
        H = 0.5 * (p1 * p1 + p2 * p2) - mu / r
        g = r ** alpha
        c = alpha * r ** (alpha - 2.0) * (H + e) + g * mu / (r2 * r)
        out[i, 0] = c * x
        out[i, 1] = c * y
        out[i, 2] = 0.0
        out[i, 3] = g * p1
        out[i, 4] = g * p2
        out[i, 5] = g


@jit
def _kepler_poincare_energy(Y, params):
    mu, alpha = params[0], params[1]
    r = np.sqrt(Y[0] * Y[0] + Y[1] * Y[1])
    return r ** alpha * (0.5 * (Y[3] * Y[3] + Y[4] * Y[4]) - mu / r + Y[5])


class PoincareKepler(PoincareTransformed):
    """:class:`PoincareTransformed` of a :class:`systems.Kepler` problem with g = |q|^alpha,
    with compiled kernels of grad K and K (``full_kernels``) for the compiled full-form path."""

    def __init__(self, kepler, g, grad_g, H0: float, alpha: float):
        super().__init__(kepler, g, grad_g, H0)
        if self.m != 2 or not hasattr(kepler, "mu"):
            raise TypeError("PoincareKepler needs a systems.Kepler problem (2 degrees of freedom)")
        self.alpha = float(alpha)
        self._params = np.array([float(kepler.mu), self.alpha])

    def full_kernels(self):
        """(gradient, energy, params): cfuncs of grad K at a stack of extended states and of K."""
        return _kepler_poincare_gradient, _kepler_poincare_energy, self._params.copy()
