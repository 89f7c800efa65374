"""Non-polynomial test systems: the mathematical pendulum and a Morse oscillator."""
from __future__ import annotations

import numpy as np

from integrators.jit import jit

from .base import SeparableSystem


@jit
def _pendulum_force(Q, params, out):
    for i in range(Q.shape[0]):
        out[i, 0] = -params[0] * np.sin(Q[i, 0])


@jit
def _pendulum_potential(q, params):
    return -params[0] * np.cos(q[0])


class Pendulum(SeparableSystem):
    """H = p^2 / 2 - omega0^2 cos q (not a polynomial).  Default start q = 2, p = 0 (libration)."""

    dim = 1
    polynomial_degree = None

    def __init__(self, omega0: float = 1.0, q0: float = 2.0, p0: float = 0.0):
        if not (np.isfinite(omega0) and omega0 > 0):
            raise ValueError(f"`omega0` must be a positive number (got omega0={omega0!r})")
        self.w2 = float(omega0) ** 2
        self.masses = np.ones(1)
        self._y0 = np.array([q0, p0], dtype=float)

    def initial_state(self):
        return self._y0.copy()

    def potential(self, q):
        return -self.w2 * np.cos(np.asarray(q, float)[..., 0])

    def forces(self, q):
        return -self.w2 * np.sin(np.asarray(q, float))

    def hessian(self, y):
        return np.diag([self.w2 * np.cos(y[0]), 1.0])

    def separable_kernels(self):
        return _pendulum_force, _pendulum_potential, np.array([self.w2])


@jit
def _morse_force(Q, params, out):
    D, a = params[0], params[1]
    for i in range(Q.shape[0]):
        e = np.exp(-a * Q[i, 0])
        out[i, 0] = -2.0 * D * a * (e - e * e)


@jit
def _morse_potential(q, params):
    e = 1.0 - np.exp(-params[1] * q[0])
    return params[0] * e * e


class Morse(SeparableSystem):
    """H = p^2 / (2 mass) + D (1 - exp(-a q))^2, a Morse oscillator (not a polynomial)."""

    dim = 1
    polynomial_degree = None

    def __init__(self, D: float = 1.0, a: float = 1.0, mass: float = 1.0, q0: float = 0.0, p0: float = 1.0):
        for name, v in (("D", D), ("a", a), ("mass", mass)):
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"`{name}` must be a positive number (got {name}={v!r})")
        self.D, self.a = float(D), float(a)
        self.masses = np.array([float(mass)])
        self._y0 = np.array([q0, p0], dtype=float)

    def initial_state(self):
        return self._y0.copy()

    def potential(self, q):
        return self.D * (1 - np.exp(-self.a * np.asarray(q, float)[..., 0])) ** 2

    def forces(self, q):
        e = np.exp(-self.a * np.asarray(q, float))
        return -2 * self.D * self.a * (e - e * e)

    def separable_kernels(self):
        return _morse_force, _morse_potential, np.array([self.D, self.a])
