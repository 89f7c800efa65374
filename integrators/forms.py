"""The two forms of the HBVM nonlinear system that the engine iterates on.

Both have s unknown blocks, whatever k is (BIT, Remark in Sec. 5): each iteration evaluates the
vector field at all k stages in one batched call and projects with P_s^T Omega.

* :class:`FullForm`: any Hamiltonian system; unknowns gamma (s, 2m) (eqs. (expan), (orth)),
  stages Y = e (x) y0 + h I_s gamma, gamma <- P_s^T Omega f(Y), y1 = y0 + h gamma_1.
* :class:`SeparableForm`: H = p^T M^{-1} p / 2 + V(q).  Because P_s^T Omega I_s = X_s when the
  quadrature is exact to degree 2s - 1 (proof of Theorem 1), the position coefficients are
  gamma_q = M^{-1} (e_1 p0 + h X_s gamma_p): only the momentum blocks gamma_p (s, m) are
  unknown, the stage positions are Q = q0 + h tau v0 + h^2 (I_s X_s) M^{-1} gamma_p, and
  q1 = q0 + h v0 + h^2 M^{-1} (X_s gamma_p)_1, p1 = p0 + h gamma_p1.
"""
from __future__ import annotations

import numpy as np

from .fast import two_product


def _fd_jacobian(fun, x: np.ndarray, rel: float = 2.0 ** -26) -> np.ndarray:
    """Central-difference Jacobian of a batched function (one call on a stack of 2d points)."""
    d = x.size
    e = rel * np.maximum(1.0, np.abs(x))
    stack = np.concatenate([x + np.diag(e), x - np.diag(e)])
    vals = fun(stack)
    return ((vals[:d] - vals[d:]) / (2 * e[:, None])).T


def vector_field(system, Y: np.ndarray) -> np.ndarray:
    """f(Y) = J grad H(Y) for a stack of states, from the system's batched ``gradient``."""
    g = np.asarray(system.gradient(Y), dtype=float)
    d = system.dim
    return np.concatenate([g[..., d:], -g[..., :d]], axis=-1)


class FullForm:
    name = "full"

    def __init__(self, method, system):
        self.m, self.sys = method, system
        self.dim = 2 * system.dim
        self.f = lambda Y: vector_field(system, Y)

    def start(self, y0: np.ndarray) -> np.ndarray:
        g = np.zeros((self.m.s, self.dim))
        g[0] = self.f(y0[None, :])[0]
        return g

    def phi(self, y0: np.ndarray, h: float):
        m = self.m

        def phi(gamma):
            Y = y0 + h * (m.I @ gamma + m.I_lo @ gamma)
            F = self.f(Y)
            # the round-off of W @ F is relative to the terms F, not to their (possibly much
            # smaller) combination: the stopping rule reads this as its round-off scale
            phi.magnitude = float(np.max(np.abs(F)))
            return m.W @ F + m.W_lo @ F
        phi.magnitude = 0.0
        return phi

    def linear_part(self, y0: np.ndarray, h: float):
        """(L, power) for the simplified Newton matrix I - h X_s (x) J0, J0 = J hess H(y0)."""
        d = self.sys.dim
        if hasattr(self.sys, "hessian"):
            Hs = np.asarray(self.sys.hessian(y0), dtype=float)
            J0 = np.concatenate([Hs[d:], -Hs[:d]])
        else:
            J0 = _fd_jacobian(self.f, y0)
        return J0, 1

    def increment(self, y0: np.ndarray, gamma: np.ndarray, h: float) -> np.ndarray:
        return h * gamma[0]

    def stage_count(self) -> int:
        return self.m.n_stages


class SeparableForm:
    name = "separable"

    def __init__(self, method, system):
        self.m, self.sys = method, system
        self.d = system.dim
        self.minv = 1.0 / np.asarray(system.masses, dtype=float)
        if self.minv.shape != (self.d,):
            raise ValueError(f"`masses` of the system must have shape ({self.d},) "
                             f"(got {np.shape(system.masses)})")

    def start(self, y0: np.ndarray) -> np.ndarray:
        g = np.zeros((self.m.s, self.d))
        g[0] = self.sys.forces(y0[None, : self.d])[0]
        return g

    def phi(self, y0: np.ndarray, h: float):
        m, sys, minv = self.m, self.sys, self.minv
        q0, v0 = y0[: self.d], y0[self.d:] * minv
        base = q0 + (h * np.outer(m.tau, v0) + h * np.outer(m.tau_lo, v0))
        h2, h2_lo = two_product(h, h)   # exact: see integrators.fast.integrate_separable

        def phi(gp):
            a = gp * minv
            ca = m.C2 @ a
            Q = base + (h2 * (ca + m.C2_lo @ a) + h2_lo * ca)
            F = sys.forces(Q)
            phi.magnitude = float(np.max(np.abs(F)))   # round-off scale, see FullForm.phi
            return m.W @ F + m.W_lo @ F
        phi.magnitude = 0.0
        return phi

    def linear_part(self, y0: np.ndarray, h: float):
        """(dF/dq(q0) M^{-1}, 2): the Newton matrix I - h^2 X_s^2 (x) dF/dq M^{-1}."""
        d = self.d
        if hasattr(self.sys, "hessian"):
            K = -np.asarray(self.sys.hessian(y0), dtype=float)[:d, :d]
        else:
            K = _fd_jacobian(self.sys.forces, y0[:d])
        return K * self.minv[None, :], 2

    def increment(self, y0: np.ndarray, gamma: np.ndarray, h: float) -> np.ndarray:
        m, d = self.m, self.d
        xg = m.X[0] @ gamma + m.X_lo[0] @ gamma       # (X_s gamma_p)_1
        dq = h * (y0[d:] + h * xg) * self.minv
        return np.concatenate([dq, h * gamma[0]])

    def stage_count(self) -> int:
        return self.m.n_stages
