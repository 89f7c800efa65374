"""The Henon-Heiles system: a cubic (nu = 3) polynomial Hamiltonian."""
from __future__ import annotations

import numpy as np

from integrators.jit import jit

from .base import SeparableSystem


@jit
def _hh_force(Q, params, out):
    for i in range(Q.shape[0]):
        x, y = Q[i, 0], Q[i, 1]
        out[i, 0] = -x - 2.0 * x * y
        out[i, 1] = -y - x * x + y * y


@jit
def _hh_potential(q, params):
    x, y = q[0], q[1]
    return 0.5 * (x * x + y * y) + x * x * y - y * y * y / 3.0


class HenonHeiles(SeparableSystem):
    """H = (p1^2 + p2^2)/2 + (q1^2 + q2^2)/2 + q1^2 q2 - q2^3 / 3.

    Chaotic near the escape energy 1/6.  Degree 3: HBVM(k, s) conserves H exactly for
    k >= 3 s / 2.

    Parameters
    ----------
    y0 : array_like, shape (4,), optional
        Initial state; default q = p = (0.18, 0.18) (H about 0.0687).
    """

    dim = 2
    polynomial_degree = 3
    escape_energy = 1.0 / 6.0

    def __init__(self, y0=None):
        self.masses = np.ones(2)
        self._y0 = np.array([0.18, 0.18, 0.18, 0.18]) if y0 is None else np.asarray(y0, float).copy()
        if self._y0.shape != (4,) or not np.all(np.isfinite(self._y0)):
            raise ValueError(f"`y0` must be 4 finite numbers (q1, q2, p1, p2) (got {y0!r})")

    def initial_state(self) -> np.ndarray:
        return self._y0.copy()

    def potential(self, q):
        q = np.asarray(q, dtype=float)
        x, y = q[..., 0], q[..., 1]
        return 0.5 * (x * x + y * y) + x * x * y - y ** 3 / 3.0

    def forces(self, q):
        q = np.asarray(q, dtype=float)
        x, y = q[..., 0], q[..., 1]
        return np.stack([-x - 2 * x * y, -y - x * x + y * y], axis=-1)

    def hessian(self, y):
        x, yy = float(y[0]), float(y[1])
        H = np.eye(4)
        H[:2, :2] = [[1 + 2 * yy, 2 * x], [2 * x, 1 - 2 * yy]]
        return H

    def separable_kernels(self):
        return _hh_force, _hh_potential, np.zeros(1)
