"""Nonlinear solvers for the HBVM system in the coefficients gamma (s blocks, whatever k is).

Both solvers iterate on a map ``phi`` (gamma -> P_s^T Omega f(stages(gamma)), eq. (hbvm_sys))
and stop by the same round-off-aware rule (:class:`StopRule`).
"""
from __future__ import annotations

import numpy as np
import scipy.linalg

from .errors import ConvergenceError

EPS = np.finfo(float).eps
DECREASE = 2.0 ** -30   # increments fell this much before stalling: round-off, see StopRule.run


class StopRule:
    """When to stop an iteration whose increments are delta_0, delta_1, ... (max norms).

    Converged when the increment vanishes, is below ``tol * scale`` (if a tolerance is given),
    or stops decreasing once it is at round-off level (below ``plateau * scale``), as in HLW
    Sec. VIII.6 ("iterate until delta = 0 or delta_k >= delta_{k-1}").  Diverged when it stops
    decreasing above that level ``patience`` times, or exceeds ``max_iter``.
    """

    def __init__(self, max_iter: int, tol: float | None = None, plateau: float = 2.0 ** -40,
                 patience: int = 2):
        self.max_iter, self.tol, self.plateau, self.patience = max_iter, tol, plateau, patience

    def run(self, update, gamma: np.ndarray, h: float, solver: str, t: float | None,
            magnitude=None):
        """Iterate ``gamma <- update(gamma)`` until converged; returns (gamma, iterations).

        ``magnitude``, optional, returns the size of the terms combined by the last update
        (max |f| at the stages).  The round-off plateau is measured against the larger of it and
        max |gamma|: when the stage forces nearly cancel (a stiff spring averaged over a step
        of several periods), max |gamma| alone understates the round-off of the update and a
        converged iteration would be reported as diverged.  Likewise an iteration whose
        increments fell below ``2**-30`` times the first one before they stopped falling has
        reached the round-off of the stage values (with a stiff force it is about
        eps |q| omega^2, which no scale of gamma shows) and is converged.
        """
        prev = np.inf
        first = None
        bad = 0
        for it in range(1, self.max_iter + 1):
            new = update(gamma)
            delta = float(np.max(np.abs(new - gamma)))
            if first is None:
                first = delta
            scale = float(np.max(np.abs(new)))
            gamma = new
            if not np.isfinite(delta):
                raise ConvergenceError(h, delta, it, solver, t,
                                       hint="the stage values are not finite; try a smaller step size h")
            if delta <= 2 * EPS * scale or (self.tol is not None and delta <= self.tol * scale):
                return gamma, it
            if delta >= prev:
                ref = scale if magnitude is None else max(scale, magnitude())
                if delta <= self.plateau * ref or delta <= DECREASE * first:
                    return gamma, it
                bad += 1
                if bad >= self.patience:
                    raise ConvergenceError(h, delta, it, solver, t)
            prev = delta
        raise ConvergenceError(h, delta, self.max_iter, solver, t)


def fixed_point(phi, gamma0, rule: StopRule, h: float, t=None):
    """gamma <- phi(gamma).  Converges when h L ||X_s|| < 1 (non-stiff problems)."""
    return rule.run(phi, gamma0, h, "fixed_point", t, _magnitude(phi))


class SimplifiedNewton:
    """(I - X_s^p (x) L) delta = -(gamma - phi(gamma)), with the Gauss matrix X_s.

    By the isospectral property the matrix of HBVM(k, s)'s simplified Newton iteration is the
    Gauss one, I - h X_s (x) J0, whatever k is.  With X_s = V Lambda V^{-1} it splits into s
    complex systems (I - mu_i L) of the size of one state block, each factorised once per step
    (conjugate eigenvalues share a factorisation).

    Parameters
    ----------
    X : ndarray (s, s)
        X_s.
    L : ndarray (d, d)
        The linear part: J0 = J grad^2 H(y0) for the full form (power 1, mu = h lambda), or
        dF/dq M^{-1} for the separable form (power 2, mu = h^2 lambda^2).
    """

    def __init__(self, X: np.ndarray, L: np.ndarray, h: float, power: int = 1):
        lam, V = np.linalg.eig(X)
        self.V, self.Vinv = V, np.linalg.inv(V)
        mu = (h * lam) ** power
        d = L.shape[0]
        self._lu = []
        self._conj = []
        for i, m in enumerate(mu):
            j = next((j for j in range(i) if abs(mu[j] - np.conj(m)) <= 1e-14 * (1 + abs(m))
                      and self._conj[j] is None), None)
            if j is not None:
                self._lu.append(None)
                self._conj.append(j)
                continue
            self._lu.append(scipy.linalg.lu_factor(np.eye(d) - m * L, check_finite=False))
            self._conj.append(None)

    def solve(self, R: np.ndarray) -> np.ndarray:
        Rt = self.Vinv @ R
        out = np.empty_like(Rt)
        for i, lu in enumerate(self._lu):
            if lu is None:
                out[i] = np.conj(out[self._conj[i]])
            else:
                out[i] = scipy.linalg.lu_solve(lu, Rt[i], check_finite=False)
        return np.real(self.V @ out)


def newton(phi, gamma0, rule: StopRule, h: float, lin: SimplifiedNewton, t=None):
    """Simplified Newton on gamma - phi(gamma) = 0 with the factorised Gauss matrix."""
    def update(g):
        return g - lin.solve(g - phi(g))
    return rule.run(update, gamma0, h, "newton", t, _magnitude(phi))


def _magnitude(phi):
    """A callable returning ``phi.magnitude`` (see :meth:`StopRule.run`), or None."""
    return (lambda: phi.magnitude) if hasattr(phi, "magnitude") else None
