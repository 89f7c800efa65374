"""The Kepler problem (reduced two-body), HLW Sec. I.2.3."""
from __future__ import annotations

import numpy as np

from integrators.jit import jit

from .base import SeparableSystem


@jit
def _kepler_force(Q, params, out):
    mu = params[0]
    for i in range(Q.shape[0]):
        x, y = Q[i, 0], Q[i, 1]
        r2 = x * x + y * y
        f = -mu / (r2 * np.sqrt(r2))
        out[i, 0] = f * x
        out[i, 1] = f * y


@jit
def _kepler_force_jvp(Q, dQ, params, out):
    """(dF/dq)(Q_i) dQ_i for each row: mu (3 q (q . dq) / r^5 - dq / r^3)."""
    mu = params[0]
    for i in range(Q.shape[0]):
        x, y = Q[i, 0], Q[i, 1]
        dx, dy = dQ[i, 0], dQ[i, 1]
        r2 = x * x + y * y
        f = mu / (r2 * np.sqrt(r2))
        k = 3.0 * (x * dx + y * dy) / r2
        out[i, 0] = f * (k * x - dx)
        out[i, 1] = f * (k * y - dy)


@jit
def _kepler_potential(q, params):
    return -params[0] / np.sqrt(q[0] * q[0] + q[1] * q[1])


class Kepler(SeparableSystem):
    """H(q, p) = |p|^2 / 2 - mu / |q| in the plane.

    Parameters
    ----------
    e : float
        Eccentricity of the default orbit, 0 <= e < 1: q0 = (1 - e, 0),
        p0 = (0, sqrt((1 + e) / (1 - e))), energy -1/2 and period 2 pi for mu = 1.
    mu : float
        Gravitational parameter.

    Not a polynomial (``polynomial_degree`` is None): HBVM conserves H to round-off once k is
    large enough for the step size.
    """

    dim = 2
    polynomial_degree = None

    def __init__(self, e: float = 0.6, mu: float = 1.0):
        if not (np.isfinite(e) and 0.0 <= e < 1.0):
            raise ValueError(f"`e` must satisfy 0 <= e < 1 (got e={e!r})")
        if not (np.isfinite(mu) and mu > 0):
            raise ValueError(f"`mu` must be a positive number (got mu={mu!r})")
        self.e, self.mu = float(e), float(mu)
        self.masses = np.ones(2)

    def initial_state(self) -> np.ndarray:
        e = self.e
        return np.array([1 - e, 0.0, 0.0, np.sqrt(self.mu * (1 + e) / (1 - e))])

    @property
    def period(self) -> float:
        a = 1.0  # semi-major axis of the default orbit
        return 2 * np.pi * np.sqrt(a ** 3 / self.mu)

    def potential(self, q):
        q = np.asarray(q, dtype=float)
        return -self.mu / np.sqrt(np.sum(q * q, axis=-1))

    def forces(self, q):
        q = np.asarray(q, dtype=float)
        r = np.sqrt(np.sum(q * q, axis=-1, keepdims=True))
        return -self.mu * q / r ** 3

    def hessian(self, y):
        q = np.asarray(y, dtype=float)[:2]
        r = np.sqrt(q @ q)
        Hqq = self.mu * (np.eye(2) / r ** 3 - 3 * np.outer(q, q) / r ** 5)
        H = np.zeros((4, 4))
        H[:2, :2] = Hqq
        H[2:, 2:] = np.eye(2)
        return H

    def angular_momentum(self, y):
        """L = q x p = q_1 p_2 - q_2 p_1 for states y of shape (..., 4): shape (...,)."""
        y = np.asarray(y, dtype=float)
        return y[..., 0] * y[..., 3] - y[..., 1] * y[..., 2]

    def angular_momentum_scale(self, y):
        """|q| |p| for states y of shape (..., 4): the size of L's terms, shape (...,)."""
        y = np.asarray(y, dtype=float)
        return np.hypot(y[..., 0], y[..., 1]) * np.hypot(y[..., 2], y[..., 3])

    def separable_kernels(self):
        return _kepler_force, _kepler_potential, np.array([self.mu])

    def separable_jvp(self):
        """The force's derivative along a direction (the tangent map, see
        :mod:`integrators.variational`); params as :meth:`separable_kernels`."""
        return _kepler_force_jvp

    def exact_solution(self, y0, t) -> np.ndarray:
        """The exact flow: the state at time t from the state y0 at time 0 (any bound orbit,
        not only the default one), in extended precision (``np.longdouble``; y0 and t are
        taken as exact, so pass t as ``np.longdouble(n) * h`` for n steps of size h).

        Lagrange's f and g with the change of eccentric anomaly dE solved by Newton's method
        from n t = dE + sigma0 / sqrt(mu a) (1 - cos dE) - (1 - r0 / a) sin dE (sigma0 = q0 . p0),
        whose derivative r / a is positive: the iteration converges from dE = n t for every
        e < 1.  Raises ValueError for an unbound state (energy >= 0)."""
        L = np.longdouble
        y0 = np.asarray(y0)
        if y0.shape != (4,):
            raise ValueError(f"`y0` must be a state (q, p) of shape (4,) (got shape {y0.shape})")
        q, v = y0[:2].astype(L), y0[2:].astype(L)
        t, mu = L(t), L(self.mu)
        r0 = np.sqrt(q @ q)
        inv_a = 2 / r0 - (v @ v) / mu
        if not inv_a > 0:
            raise ValueError("exact_solution needs a bound orbit (energy < 0); this state escapes")
        a = 1 / inv_a
        n = np.sqrt(mu * inv_a ** 3)
        c1 = (q @ v) / np.sqrt(mu * a)
        c2 = 1 - r0 / a
        M = n * t
        dE = M
        for _ in range(100):
            step = (dE + c1 * (1 - np.cos(dE)) - c2 * np.sin(dE) - M) / (
                1 + c1 * np.sin(dE) - c2 * np.cos(dE))
            dE -= step
            if abs(step) <= 4 * np.finfo(L).eps * max(1, abs(dE)):
                break
        cos_d, sin_d = np.cos(dE), np.sin(dE)
        r = a * (1 + c1 * sin_d - c2 * cos_d)
        f = 1 - a / r0 * (1 - cos_d)
        g = t - (dE - sin_d) / n
        fd = -np.sqrt(mu * a) / (r * r0) * sin_d
        gd = 1 - a / r * (1 - cos_d)
        return np.concatenate([f * q + g * v, fd * q + gd * v])
