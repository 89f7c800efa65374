"""The Fermi-Pasta-Ulam stiff chain, HLW Sec. I.5.1 and XIII.2 (degree nu = 4)."""
from __future__ import annotations

import numpy as np

from integrators.jit import jit

from .base import SeparableSystem


@jit
def _fpu_force(Q, params, out):
    w2 = params[0] * params[0]
    n = Q.shape[1]
    for r in range(Q.shape[0]):
        for i in range(n):
            out[r, i] = 0.0
        # soft cubic-force springs between q_{2i} and q_{2i+1}, walls q_0 = q_{2m+1} = 0
        for i in range(n // 2 + 1):
            left = Q[r, 2 * i - 1] if i > 0 else 0.0
            right = Q[r, 2 * i] if 2 * i < n else 0.0
            d = right - left
            f = 4.0 * d * d * d
            if i > 0:
                out[r, 2 * i - 1] += f
            if 2 * i < n:
                out[r, 2 * i] -= f
        # stiff linear springs between q_{2i-1} and q_{2i} (1-based)
        for i in range(n // 2):
            d = Q[r, 2 * i + 1] - Q[r, 2 * i]
            f = 0.5 * w2 * d
            out[r, 2 * i] += f
            out[r, 2 * i + 1] -= f


@jit
def _fpu_potential(q, params):
    w2 = params[0] * params[0]
    n = q.shape[0]
    v = 0.0
    for i in range(n // 2):
        d = q[2 * i + 1] - q[2 * i]
        v += 0.25 * w2 * d * d
    for i in range(n // 2 + 1):
        left = q[2 * i - 1] if i > 0 else 0.0
        right = q[2 * i] if 2 * i < n else 0.0
        d = right - left
        v += d * d * d * d
    return v


class FPU(SeparableSystem):
    """H = 1/2 sum p_i^2 + omega^2/4 sum_{i=1}^m (q_{2i} - q_{2i-1})^2
    + sum_{i=0}^m (q_{2i+1} - q_{2i})^4, with q_0 = q_{2m+1} = 0 (2m unit masses).

    Alternating stiff linear springs (frequency omega) and soft cubic-force springs; a
    polynomial of degree 4, so HBVM(k, s) is exact for k >= 2s.  Default initial data of HLW
    (x_{1,0} = 1, y_{1,0} = 1, x_{1,1} = 1/omega, y_{1,1} = 1 in the rotated variables).

    Coordinates are stored 0-based: q[0] = q_1, ..., q[2m-1] = q_{2m}.
    """

    polynomial_degree = 4

    def __init__(self, m: int = 3, omega: float = 50.0):
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 1:
            raise ValueError(f"`m` must be an integer >= 1 (got m={m!r})")
        if not (np.isfinite(omega) and omega > 0):
            raise ValueError(f"`omega` must be a positive number (got omega={omega!r})")
        self.m, self.omega = int(m), float(omega)
        self.dim = 2 * self.m
        self.masses = np.ones(self.dim)

    def initial_state(self) -> np.ndarray:
        x = np.zeros((self.m, 2))   # x_{i,0}, x_{i,1}
        yv = np.zeros((self.m, 2))
        x[0, 0], yv[0, 0], x[0, 1], yv[0, 1] = 1.0, 1.0, 1.0 / self.omega, 1.0
        s2 = np.sqrt(2.0)
        q = np.empty(self.dim)
        p = np.empty(self.dim)
        q[1::2], q[0::2] = (x[:, 0] + x[:, 1]) / s2, (x[:, 0] - x[:, 1]) / s2   # q_{2i}, q_{2i-1}
        p[1::2], p[0::2] = (yv[:, 0] + yv[:, 1]) / s2, (yv[:, 0] - yv[:, 1]) / s2
        return np.concatenate([q, p])

    def _padded(self, q):
        q = np.asarray(q, dtype=float)
        z = np.zeros(q.shape[:-1] + (1,))
        return np.concatenate([z, q, z], axis=-1)   # q_0 .. q_{2m+1}

    def potential(self, q):
        qq = self._padded(q)
        stiff = qq[..., 2:-1:2] - qq[..., 1:-1:2]   # q_{2i} - q_{2i-1}
        soft = qq[..., 1::2] - qq[..., 0::2]        # q_{2i+1} - q_{2i}, i = 0..m
        return 0.25 * self.omega ** 2 * np.sum(stiff ** 2, axis=-1) + np.sum(soft ** 4, axis=-1)

    def forces(self, q):
        qq = self._padded(q)
        stiff = qq[..., 2:-1:2] - qq[..., 1:-1:2]
        soft = qq[..., 1::2] - qq[..., 0::2]
        fs = 4 * soft ** 3                          # dV/d(difference)
        F = np.zeros(qq.shape)
        F[..., 1::2] -= fs                          # q_{2i+1} term
        F[..., 0::2] += fs                          # q_{2i} term
        g = 0.5 * self.omega ** 2 * stiff
        F[..., 2:-1:2] -= g
        F[..., 1:-1:2] += g
        return F[..., 1:-1]

    def stiff_energies(self, y):
        """Energies I_j = (y_{j,1}^2 + omega^2 x_{j,1}^2) / 2 of the stiff springs (HLW XIII.2)."""
        q, p = self.split(y)
        x1 = (q[..., 1::2] - q[..., 0::2]) / np.sqrt(2)
        y1 = (p[..., 1::2] - p[..., 0::2]) / np.sqrt(2)
        return 0.5 * (y1 ** 2 + self.omega ** 2 * x1 ** 2)

    def separable_kernels(self):
        return _fpu_force, _fpu_potential, np.array([self.omega])
