"""The HBVM(k, s) method as data: nodes, weights, the Legendre matrices, the Butcher tableau.

References
----------
Brugnano, Iavernaro, Trigiante (BIT), "The lack of continuity and the role of infinite and
infinitesimal in numerical methods for ODEs: the case of symplecticity": eqs. (orto1), (IDPO),
(rk), (Xs)-(xij), Theorems 1 and 2.
"""
from __future__ import annotations

import math
import numbers
from functools import cached_property, lru_cache

import mpmath
import numpy as np

from . import quadrature as _q
from .quadrature import gauss_rule01

NODE_FAMILIES = ("gauss", "lobatto")


MAX_K = 128      # quadrature nodes at most (see HBVM.__init__)


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"`{name}` must be an integer >= {minimum} (got {name}={value!r}); "
                         f"pass a whole number such as {name}={minimum}")
    if value < minimum:
        raise ValueError(f"`{name}` must be >= {minimum} (got {name}={value})")
    return int(value)


def xi(j: int) -> float:
    """xi_j = 1 / (2 sqrt((2j+1)(2j-1))), eq. (xij)."""
    return 0.5 / math.sqrt((2 * j + 1) * (2 * j - 1))


def gauss_matrix(s: int) -> np.ndarray:
    """X_s of eq. (Xs): tridiagonal, 1/2 in the corner, -xi_j above and xi_j below the diagonal.

    Its eigenvalues are those of the s-stage Gauss-Legendre Butcher matrix (Lemma 1).
    """
    s = _check_int("s", s, 1)
    X = np.zeros((s, s))
    X[0, 0] = 0.5
    for j in range(1, s):
        X[j, j - 1] = xi(j)
        X[j - 1, j] = -xi(j)
    return X


@lru_cache(maxsize=None)
def _gauss_matrix_remainder(s: int) -> np.ndarray:
    """The rounding remainder of X_s (xi_j is irrational): X_s = gauss_matrix(s) + this
    (read-only, computed once per s: choosing k builds several methods of one s)."""
    R = np.zeros((s, s))
    with mpmath.workdps(_q._DPS):
        for j in range(1, s):
            x = 1 / (2 * mpmath.sqrt((2 * j + 1) * (2 * j - 1)))
            R[j, j - 1] = float(x - mpmath.mpf(xi(j)))
            R[j - 1, j] = -R[j, j - 1]
    R.flags.writeable = False
    return R


def gauss_spectrum(s: int) -> np.ndarray:
    """Eigenvalues of X_s (= those of the s-stage Gauss-Legendre method), sorted."""
    return _sort(np.linalg.eigvals(gauss_matrix(s)))


def _sort(z: np.ndarray) -> np.ndarray:
    z = np.asarray(z, dtype=complex)
    return z[np.lexsort((np.round(z.imag, 12), np.round(z.real, 12)))]


_CHECKED: set = set()      # (k, s, nodes) of the methods whose tableau passed HBVM._check


@lru_cache(maxsize=None)
def _mp_nodes(n: int, nodes: str):
    return _q.gauss_legendre(n) if nodes == "gauss" else _q.gauss_lobatto(n)


@lru_cache(maxsize=256)
def _build(k: int, s: int, nodes: str) -> dict:
    """All coefficient matrices of HBVM(k, s), computed in mpmath and rounded once."""
    n = k if nodes == "gauss" else k + 1
    tau, omega = _mp_nodes(n, nodes)
    with mpmath.workdps(_q._DPS):
        P = [_q.shifted_legendre_values(t, s + 1) for t in tau]          # n x (s+1)
        I = [_q.shifted_legendre_integrals(t, s) for t in tau]           # n x s
        W = [[omega[i] * P[i][j] for i in range(n)] for j in range(s)]   # P_s^T Omega, s x n
        # X_s = P_s^T Omega I_s holds exactly when the rule is exact to degree 2s - 1;
        # C2 = I_s X_s gives the positions of the separable form (see separable.py)
        Xs = mpmath.matrix(s, s)
        Xs[0, 0] = mpmath.mpf(1) / 2
        for j in range(1, s):
            x = 1 / (2 * mpmath.sqrt((2 * j + 1) * (2 * j - 1)))
            Xs[j, j - 1], Xs[j - 1, j] = x, -x
        C2 = [[sum(I[i][l] * Xs[l, j] for l in range(s)) for j in range(s)] for i in range(n)]
        # extrapolation of the previous step's sigma' over the next step (h unchanged):
        # E_ij = int_0^1 P_i(x) P_j(1 + x) dx, exact with an s-point Gauss rule (degree 2s - 2)
        gt, gw = _q.gauss_legendre(s)
        Pg = [_q.shifted_legendre_values(t, s) for t in gt]
        Pg1 = [_q.shifted_legendre_values(1 + t, s) for t in gt]
        E = [[sum(gw[l] * Pg[l][i] * Pg1[l][j] for l in range(s)) for j in range(s)] for i in range(s)]
    tau_hi, tau_lo = _q.split(list(tau))
    om_hi, om_lo = _q.split(list(omega))
    P_hi, _ = _q.split([row[:s] for row in P])
    Pnext_hi, _ = _q.split([row[s] for row in P])
    I_hi, I_lo = _q.split(I)
    W_hi, W_lo = _q.split(W)
    C2_hi, C2_lo = _q.split(C2)
    E_hi, _ = _q.split(E)
    return dict(tau=tau_hi, tau_lo=tau_lo, omega=om_hi, omega_lo=om_lo, P=P_hi, P_next=Pnext_hi,
                I=I_hi, I_lo=I_lo, W=W_hi, W_lo=W_lo, C2=C2_hi, C2_lo=C2_lo, E=E_hi,
                mp=dict(tau=tau, omega=omega, P=P, I=I))


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float, copy=True)
    a.flags.writeable = False
    return a


@lru_cache(maxsize=256)
def _method_arrays(k: int, s: int, nodes: str) -> dict:
    """The attributes of HBVM(k, s, nodes) (read-only arrays, shared by every instance: the
    method is immutable).  Built once per process: the REBOUND driver builds three methods at
    each attach with the k probe, and copying the arrays each time cost 53-89 us for the three
    (9-15 us shared)."""
    d = _build(k, s, nodes)
    out = {name: _readonly(d[name]) for name in ("tau", "tau_lo", "omega", "P", "I", "W", "W_lo",
                                                 "I_lo", "C2", "C2_lo", "E", "P_next")}
    out["X"] = _readonly(gauss_matrix(s))
    out["X_lo"] = _readonly(_gauss_matrix_remainder(s))
    out["_mp"] = d["mp"]
    return out


class HBVM:
    """HBVM(k, s): the k-stage Hamiltonian Boundary Value Method of degree s (order 2s).

    An immutable description of the method, built from its defining formulas and checked when
    built.  The solution on each step is a polynomial sigma of degree s whose derivative is
    expanded in the orthonormal shifted Legendre basis P_1..P_s (eq. (expan)); the line
    integral is discretised by a quadrature on the abscissae tau (eq. (discr_lin)).

    Parameters
    ----------
    k : int
        Number of steps of the method, k >= s.  With Gauss nodes the method has k stages.
    s : int
        Degree of the polynomial sigma, s >= 1.  The order is 2s.
    nodes : {"gauss", "lobatto"}
        Abscissae of the quadrature.  ``"gauss"``: the k Gauss-Legendre points on [0, 1]
        (exact to degree 2k - 1).  ``"lobatto"``: following BIT (2010), HBVM(k, s) on Lobatto
        abscissae uses the k + 1 Lobatto points including 0 and 1 (k steps between them), also
        exact to degree 2k - 1; the Runge-Kutta form then has k + 1 stages, the first of which
        is y0 itself.

    Attributes
    ----------
    tau, omega : ndarray, shape (n,)
        Abscissae and weights (n = k for Gauss, k + 1 for Lobatto), rounded once from 40 digits.
    P : ndarray, shape (n, s)
        (P_s)_ij = P_j(tau_i), eq. (IDPO).
    I : ndarray, shape (n, s)
        (I_s)_ij = int_0^tau_i P_j, eq. (IDPO).
    X : ndarray, shape (s, s)
        X_s of eq. (Xs).
    W : ndarray, shape (s, n)
        P_s^T Omega, the projection that maps stage values to the coefficients gamma_j
        (eq. (orth) discretised).  ``tau_lo``, ``W_lo``, ``I_lo``, ``C2_lo``, ``X_lo`` hold the
        rounding remainders.

    Examples
    --------
    >>> m = HBVM(6, 2)
    >>> m.order, m.polynomial_degree_exact
    (4, 6)
    """

    __slots__ = ("k", "s", "nodes", "n_stages", "tau", "tau_lo", "omega", "P", "I", "X", "X_lo", "W",
                 "W_lo", "I_lo", "C2", "C2_lo", "E", "P_next", "_mp", "__dict__")

    def __init__(self, k: int, s: int, nodes: str = "gauss"):
        s = _check_int("s", s, 1)
        k = _check_int("k", k, 1)
        if k < s:
            raise ValueError(f"`k` must be >= `s` (got k={k}, s={s}); HBVM(k, s) needs at least "
                             f"s quadrature steps, e.g. k={s}")
        if k > MAX_K:
            raise ValueError(f"`k` must be <= {MAX_K} (got k={k}, s={s}): {MAX_K} nodes integrate "
                             f"polynomials of degree {2 * MAX_K - 1} exactly, far beyond what double "
                             f"precision resolves, and building the quadrature costs O(k^3) in "
                             f"40-digit arithmetic (minutes for thousands of nodes); for a "
                             f"polynomial H of degree nu > {2 * MAX_K}/s, HBVM({MAX_K}, s) already "
                             f"conserves it to round-off")
        if not isinstance(nodes, str) or nodes not in NODE_FAMILIES:
            raise ValueError(f"`nodes` must be one of {NODE_FAMILIES} (got nodes={nodes!r})")
        set_ = object.__setattr__
        set_(self, "k", k)
        set_(self, "s", s)
        set_(self, "nodes", nodes)
        arrays = _method_arrays(k, s, nodes)
        set_(self, "n_stages", len(arrays["tau"]))
        for name, a in arrays.items():
            set_(self, name, a)
        if (k, s, nodes) not in _CHECKED:        # once per method and process
            self._check()
            _CHECKED.add((k, s, nodes))

    def __setattr__(self, name, value):
        raise AttributeError(f"HBVM is immutable; build a new one instead of setting {name!r}")

    def __repr__(self) -> str:
        extra = "" if self.nodes == "gauss" else f", nodes={self.nodes!r}"
        return f"HBVM({self.k}, {self.s}{extra})"

    def __eq__(self, other) -> bool:
        return isinstance(other, HBVM) and (self.k, self.s, self.nodes) == (other.k, other.s, other.nodes)

    def __hash__(self) -> int:
        return hash((self.k, self.s, self.nodes))

    def __reduce__(self):
        return (HBVM, (self.k, self.s, self.nodes))

    def _check(self) -> None:
        """Consistency checks done once at construction (cheap, in double precision)."""
        A, b, c = self.butcher_tableau()
        n = self.n_stages
        if A.shape != (n, n) or b.shape != (n,) or c.shape != (n,):
            raise RuntimeError(f"{self!r}: tableau shapes are wrong")
        if abs(b.sum() - 1.0) > 8 * np.finfo(float).eps:
            raise RuntimeError(f"{self!r}: weights do not sum to 1 ({b.sum()!r})")
        if np.max(np.abs(A.sum(axis=1) - c)) > 64 * np.finfo(float).eps:
            raise RuntimeError(f"{self!r}: row sums of A differ from c")
        if np.max(np.abs(self.W @ self.P - np.eye(self.s))) > 1e-13 * n:
            raise RuntimeError(f"{self!r}: the quadrature is not exact to degree 2s - 2")

    # -- the Runge-Kutta form -------------------------------------------------------------
    @property
    def order(self) -> int:
        """Order of accuracy, 2s, for every k >= s."""
        return 2 * self.s

    @property
    def quadrature_degree(self) -> int:
        """The largest degree the quadrature integrates exactly: 2k - 1 (Gauss and Lobatto)."""
        return 2 * self.k - 1

    @property
    def polynomial_degree_exact(self) -> int:
        """Largest degree nu of a polynomial Hamiltonian conserved exactly.

        The line-integral integrand sigma'(t)^T grad H(sigma(t)) has degree (s - 1) + (nu - 1) s
        = nu s - 1; the quadrature is exact to 2k - 1 for both node families (k Gauss points,
        or k + 1 Lobatto points), so the condition is nu s <= 2k, i.e. k >= nu s / 2 (eq. (knu)).
        """
        return (2 * self.k) // self.s

    @classmethod
    def for_polynomial_degree(cls, nu: int, s: int, nodes: str = "gauss") -> "HBVM":
        """The smallest HBVM(k, s) that conserves every polynomial Hamiltonian of degree nu."""
        nu = _check_int("nu", nu, 1)
        s = _check_int("s", s, 1)
        return cls(max(s, -(-nu * s // 2)), s, nodes)

    def butcher_tableau(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A, b, c) with A = I_s P_s^T Omega (eq. (rk)), b = omega, c = tau."""
        return self._A, self.omega, self.tau

    @cached_property
    def _A(self) -> np.ndarray:
        # I_s P_s^T Omega from the (hi, lo) pairs: the products of the remainders are below
        # double precision, the rest is a sum of s terms (a few ulps)
        A = self.I @ self.W + (self.I @ self.W_lo + self.I_lo @ self.W)
        return _readonly(A)

    def essential_spectrum(self) -> np.ndarray:
        """The s nonzero eigenvalues of A (computed from the full n x n matrix), sorted."""
        ev = np.linalg.eigvals(self._A)
        return _sort(ev[np.argsort(-np.abs(ev))[: self.s]])

    def collocation_matrix(self) -> np.ndarray:
        """calA of Section 5: alpha_ij = int_0^tau_i ell_j, the collocation method on the nodes.

        Built from Lagrange polynomials in extended precision, independently of P_s and I_s, so
        that Theorem 2 (A = calA P_s P_s^T Omega) can be checked.
        """
        return _collocation(self.k, self.nodes)

    def stability_function(self, z):
        """R(z) = 1 + z b^T (I - z A)^{-1} e, for scalar or array z."""
        z = np.asarray(z, dtype=complex)
        A, b, _ = self.butcher_tableau()
        n = self.n_stages
        flat = z.reshape(-1)
        out = np.empty_like(flat)
        e = np.ones(n)
        for i, zi in enumerate(flat):
            out[i] = 1 + zi * (b @ np.linalg.solve(np.eye(n) - zi * A, e))
        return out.reshape(z.shape) if z.ndim else out[0]

    def symplecticity_defect(self) -> float:
        """max |b_i a_ij + b_j a_ji - b_i b_j|: zero exactly for symplectic Runge-Kutta methods."""
        A, b, _ = self.butcher_tableau()
        M = b[:, None] * A + (b[:, None] * A).T - np.outer(b, b)
        return float(np.max(np.abs(M)))

    def extrapolation_matrix(self, ratio: float = 1.0) -> np.ndarray:
        """E(r)_ij = int_0^1 P_i(x) P_j(1 + r x) dx: initial gamma from the previous step's.

        sigma'_prev(t_n + x h_new) = sum_j gamma_j P_j(1 + r x) with r = h_new / h_old.
        """
        if ratio == 1.0:
            return self.E
        # compiled: an adaptive run needs it at every step (a new ratio each time)
        from .core import extrapolation_matrix
        t, w = gauss_rule01(self.s)
        E = np.empty((self.s, self.s))
        extrapolation_matrix(float(ratio), t.copy(), w.copy(), E)    # writable: one signature
        return E

    # -- stepping (delegated to the engine) ---------------------------------------------
    def step(self, system, y, h: float, solver: str = "auto"):
        """One step of size h from state y; returns y1.  See :class:`integrators.Stepper`."""
        from .engine import Stepper
        st = Stepper(self, system, y, solver=solver)
        st.step(h)
        return st.y.copy()

    def integrate(self, system, y0, h: float, steps: int | None = None, *args, **options):
        """Integrate ``steps`` steps of size h, or with ``adaptive=True`` up to ``t_end``: the
        module-level :func:`integrators.engine.integrate` with this method, which takes the
        same arguments (``t0``, ``solver``, ..., ``adaptive``, ``t_end``, ``epsilon``,
        ``min_dt``, ``sample_times``)."""
        from .engine import integrate
        return integrate(self, system, y0, h, steps, *args, **options)


def _legendre_basis(t: np.ndarray, s: int) -> np.ndarray:
    """P_1..P_s at points t (double precision), shape (len(t), s)."""
    t = np.asarray(t, dtype=float)
    x = 2 * t - 1
    L = np.empty((t.size, s))
    L[:, 0] = 1.0
    if s > 1:
        L[:, 1] = x
    for n in range(1, s - 1):
        L[:, n + 1] = ((2 * n + 1) * x * L[:, n] - n * L[:, n - 1]) / (n + 1)
    return L * np.sqrt(2 * np.arange(1, s + 1) - 1)


@lru_cache(maxsize=128)
def _collocation(k: int, nodes: str) -> np.ndarray:
    """alpha_ij = int_0^tau_i ell_j(x) dx with ell_j the Lagrange basis on the nodes.

    The Lagrange polynomials are evaluated by the (stable) barycentric formula at the points of
    numpy's n-point Gauss rule mapped onto [0, tau_i], which integrates degree n - 1 exactly.
    Nothing here uses the Legendre matrices P_s or I_s.
    """
    n = k if nodes == "gauss" else k + 1
    tau = np.array([float(t) for t in _mp_nodes(n, nodes)[0]])
    diff = tau[:, None] - tau[None, :]
    np.fill_diagonal(diff, 1.0)
    bw = 1.0 / np.prod(diff, axis=1)                      # barycentric weights
    x, w = np.polynomial.legendre.leggauss(n)
    x, w = (x + 1) / 2, w / 2
    pts = tau[:, None] * x[None, :]                       # (n, q): quadrature points on [0, tau_i]
    d = pts[..., None] - tau[None, None, :]               # (n, q, n)
    hit = d == 0                                          # a point on a node: ell_j = delta
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = bw / np.where(hit, 1.0, d)
        ell = terms / terms.sum(axis=-1, keepdims=True)  # ell_j(pts), (n, q, n)
    on_node = hit.any(axis=-1)
    ell[on_node] = hit[on_node]
    return _readonly(tau[:, None] * np.einsum("q,iqj->ij", w, ell))


def gauss_collocation_tableau(s: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The s-stage Gauss-Legendre collocation tableau (A, b, c), built from Lagrange polynomials."""
    s = _check_int("s", s, 1)
    tau, omega = _mp_nodes(s, "gauss")
    return _collocation(s, "gauss"), np.array([float(w) for w in omega]), np.array([float(t) for t in tau])
