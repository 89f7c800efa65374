"""EQUIP(k, s): the Gauss method perturbed, step by step, so that it conserves the energy too.

References
----------
L. Brugnano, F. Iavernaro, D. Trigiante, "Energy- and quadratic invariants-preserving
integrators based upon Gauss collocation formulae", SIAM J. Numer. Anal. 50 (2012) (preprint:
"On the existence of energy-preserving symplectic integrators based upon Gauss collocation
formulae").  L. Brugnano, G. Gurioli, F. Iavernaro, "Analysis of Energy and QUadratic Invariant
Preserving (EQUIP) methods", J. Comput. Appl. Math. 335 (2018).

The method, as derived and checked here
---------------------------------------
The s-stage Gauss method in the Legendre form is A = P_s X_s P_s^T Omega (P_s the orthonormal
shifted Legendre polynomials at the s Gauss points, Omega their weights, X_s the tridiagonal
matrix of :func:`integrators.tableau.gauss_matrix`).  With P_s^T Omega P_s = I,

    Omega A + A^T Omega - omega omega^T = Omega P_s (X + X^T - e_1 e_1^T) P_s^T Omega,

so a Runge-Kutta method A(alpha) = P_s X_s(alpha) P_s^T Omega, b = omega is symplectic for
every alpha as long as X_s(alpha) - e_1 e_1^T / 2 stays skew: X_s(alpha) = X_s + alpha S with S
skew.  Each step chooses alpha so that H(y1) = H(y0) (the energy condition); the method then
keeps every quadratic invariant (symplectic Runge-Kutta) and the energy, with order 2s.

Choices made here, and why (measured on Kepler, e = 0.6, h = 2 pi / 100):

* **S acts on the first Legendre pair**: S = xi_1 (e_2 e_1^T - e_1 e_2^T), i.e. xi_1 becomes
  (1 + alpha) xi_1.  Perturbing the last pair instead (xi_(s-1): a fixed alpha then keeps
  the order 2s - 2 that the 2012 paper states for its family), the energy is sensitive to
  alpha only at order h^(2s-3), and where the Gauss step's energy error is at round-off
  (near apocentre) alpha is undetermined: with s = 4 it wandered up to 1.4 and the energy
  error grew to 1.8e-12 over 1000 steps.  On the first pair dE/dalpha is of order h: alpha
  stays of order h^(2s-1) (2e-8 at pericentre, 1e-12 elsewhere, s = 4) and both invariants
  stay at round-off.  For s = 2 the two choices coincide.  A fixed alpha != 0 then has order 2
  (c = A 1 moves by alpha P_s S e_1); the alpha of the energy condition, O(h^(2s-1)), moves
  y1 by O(h^(2s+1)): the order stays 2s (tested).
* **k is the quadrature of the energy condition**: H(y1) - H(y0) is the line integral of
  grad H along the degree-s path sigma(c h) = y0 + h sum_j int_0^c P_j gamma_j (which ends at
  y1), taken by the k-point Gauss rule: the discrete line integral of HBVM(k, s).  A polynomial
  H of degree nu is then conserved exactly when k >= nu s / 2, as by HBVM(k, s); a smooth H
  to round-off once k is large enough for the step, as HBVM(k, s) does.  The residual is a sum
  of products of the coefficients with the projected gradients (no difference of two
  energies), so it is resolved far below eps |H|.  k = s is allowed (EQUIP(s, s) is Gauss's
  quadrature of the line integral, exact for quadratic H only: cubic or quartic H need k > s).
* **alpha by a secant iteration interleaved with the Gauss iteration**: gamma is iterated for
  the current alpha with the one stop rule and polished; the path's k points are then
  evaluated and alpha corrected (:func:`integrators.equip_core.update_alpha`: the slope from
  the last two residuals, else the last step's, else a probe), and gamma is iterated again
  from where it is; the step ends when the residual is at its round-off with a slope measured
  in the step, after one last correction of alpha for which gamma is iterated to convergence
  once more (without it the residual keeps one sign step after step and the energy drifts).
  Typically two or three path evaluations a step.

Why the energy condition can lose its small root, and what the step then does
-----------------------------------------------------------------------------
X_s(alpha) moves A by alpha P_s S P_s^T Omega and c = A 1 by alpha xi_1 P_1(c) (S e_1 =
xi_1 e_2).  In y1's B-series the weights of the two trees of order 3 change by b^T c^2:
+xi_1^2 (2 alpha + alpha^2) and b^T A c: -xi_1^2 (2 alpha + alpha^2), so y1(alpha) - y1(0) =
xi_1^2 h^3 (alpha + alpha^2 / 2) (f''(f, f) - 2 f'f'f) + O(h^4); with f = J grad H the
identities grad H^T f' v = -v^T H'' f and grad H^T f''(f, f) = -H'''(f, f, f) - 2 H''(f'f, f)
leave

    H(y1(alpha)) - H(y0) = g_0 - xi_1^2 h^3 H'''(y0)(f, f, f) (alpha + alpha^2 / 2) + O(h^4),

g_0 = O(h^(2s+1)) the Gauss step's own energy error.  The small root alpha ~ g_0 / (xi_1^2 h^3
H'''(f, f, f)) = O(h^(2s-2)) exists while H'''(f, f, f) stays away from zero: for a separable
H it is V'''(q)(v, v, v), the third derivative of the potential along the velocities, a sum
over all atoms of terms of both signs, which passes through zero along a trajectory where
g_0 need not.  There the small root moves out through large alpha, and E(alpha) may have no
root at all: for s = 2 alpha and -2 - alpha are the same method with its two stages swapped
(E is a function of (1 + alpha)^2, with an extremum at alpha = -1 that can stay on g_0's
side).  Measured on ASE's EMT copper nanoparticle (43 atoms, 5 fs, s = 2): at t = 205 fs the
slope dE/dalpha had changed sign since the last step (root -0.07 there, +0.031 here), and the
secant with the last step's slope left |alpha| <= 0.25 (the step failed before the root
search); at t = 985 fs the only roots are alpha = -0.48 and -1.52.  On 19 atoms (seed 2) at
t = 0, E(alpha) < 0 for every alpha: no EQUIP step of 5 fs exists there.

So :func:`integrators.equip_core.update_alpha` takes this step's own slope when the last
step's sends alpha out of range, and when the secant with its own slope does too, scans from
its last alpha (+-1/32, doubling, up to 1) and narrows the first bracket by regula falsi: the
root closest to where the secant stopped, never a point that is not a root.  A root with
|alpha| of order 1 is a symplectic step that keeps the energy and every quadratic invariant
but has order 2 (c moves by alpha xi_1 P_1): at t = 985 fs on the nanoparticle (alpha =
-0.48) the step moved the positions 3.7e-5 A from a converged reference, Gauss's step
4.1e-8 A.  No root within 1: the step fails with :class:`integrators.EnergyConditionError`
(a ConvergenceError naming EQUIP and the energy condition); a shorter step helps (the window
of states without a small root shrinks as h^2).  With s >= 3 a second skew direction (pairs
(0, 2) or (1, 2), whose first effect on H is of higher order and a different function of the
state) would keep a small root there; not done.

Cost a step: s forces an iteration (Gauss's) plus k at each residual, against k an iteration
for HBVM(k, s); the iterations after each change of alpha make it 2-9 times HBVM's time on
the scenes measured (``benchmarks/results/equip.md``; docs: "Choosing a method").
"""
from __future__ import annotations

from functools import cached_property

import numpy as np

from . import equip_core as _ec
from .tableau import HBVM, _check_int, _readonly, _sort, xi

#: EQUIP's adaptive defaults through REBOUND (``HBVMIntegrator(sim, method="equip")``): s = 8
#: keeps the Gauss step's own energy residual far below an ulp at the steps the control takes
#: on planetary orbits, so alpha is rarely needed and the step costs about HBVM(8, 6)'s force
#: evaluations at IAS15's energy and angular momentum (s = 6 has Gauss residuals of a
#: systematic 0.2-0.9 ulp that alpha must correct at every step: 110 evaluations a step;
#: ``benchmarks/bench_equip.py --rebound``).  epsilon (the bound on each step's estimated
#: local error, integrators.core.adapt_step) 1e-17, k = 9 from kchoice.adaptive_k: the outer
#: solar system (HLW) over 1e6 days in 2692 steps at 2.1e-15 in the energy (issue 58's
#: controller; the earlier one took 3367 steps at its epsilon 1e-4); 1e-16, 2336 steps, 3.6e-15
DEFAULT_S = 8
DEFAULT_EPSILON = 1e-17


class EQUIP:
    """EQUIP(k, s): the s-stage Gauss method made energy conserving by a symplectic
    perturbation tuned at each step (order 2s; the energy condition on a k-point quadrature).

    An immutable description of the method, with the interface of :class:`integrators.HBVM`
    (``integrate``, ``step``, ``order``, the tableau as data) so that the engine, the
    :class:`integrators.Stepper` and the hosts take either.

    Parameters
    ----------
    k : int
        Nodes of the Gauss quadrature of the energy condition (the discrete line integral),
        k >= s: a polynomial Hamiltonian of degree nu is conserved exactly when k >= nu s / 2.
    s : int
        Stages of the Gauss method, s >= 2 (s = 1, the midpoint rule, has no skew direction
        to perturb).  The order is 2s.

    Attributes
    ----------
    tau, omega : ndarray, shape (s,)
        The Gauss points and weights on [0, 1] (the stages).
    tau_path : ndarray, shape (k,)
        The k Gauss points of the energy condition's quadrature.
    P, I, W, X, C2 : ndarray
        Gauss's matrices (those of HBVM(s, s)): P_s (s, s), I_s = P_s X_s (s, s), W =
        P_s^T Omega (s, s), X_s (s, s), C2 = P_s X_s^2 (s, s).
    S : ndarray, shape (s, s)
        The skew direction of the perturbation: X_s(alpha) = X_s + alpha S.

    Examples
    --------
    >>> m = EQUIP(6, 2)
    >>> m.order, m.polynomial_degree_exact
    (4, 6)
    """

    def __init__(self, k: int, s: int):
        s = _check_int("s", s, 1)
        k = _check_int("k", k, 1)
        if s < 2:
            raise ValueError(f"`s` must be >= 2 for EQUIP (got s={s}): the midpoint rule (s = 1) "
                             f"has no skew perturbation; use HBVM(k, 1) for energy, or s=2")
        if k < s:
            raise ValueError(f"`k` must be >= `s` (got k={k}, s={s}); the energy condition needs "
                             f"at least the s-point rule, e.g. k={s}")
        gauss, path = HBVM(s, s), HBVM(k, s)      # HBVM validates k <= MAX_K with its message
        set_ = object.__setattr__
        set_(self, "k", k)
        set_(self, "s", s)
        set_(self, "_gauss", gauss)
        set_(self, "_path", path)
        S = np.zeros((s, s))
        S[1, 0], S[0, 1] = xi(1), -xi(1)
        set_(self, "S", _readonly(S))

    # -- data ---------------------------------------------------------------------------
    nodes = "gauss"

    @classmethod
    def for_polynomial_degree(cls, nu: int, s: int, nodes: str = "gauss") -> "EQUIP":
        """The smallest EQUIP(k, s) whose energy condition is exact for every polynomial
        Hamiltonian of degree nu: k >= nu s / 2, HBVM's rule (the same k-point line integral)."""
        if nodes != "gauss":
            raise ValueError(f"`nodes` must be 'gauss' for EQUIP (got nodes={nodes!r})")
        return cls(HBVM.for_polynomial_degree(nu, s).k, s)

    def __getattr__(self, name):
        # Gauss's arrays (the stages): tau, tau_lo, omega, P, I, I_lo, W, W_lo, X, X_lo, C2,
        # C2_lo, E
        if name in ("tau", "tau_lo", "omega", "P", "I", "I_lo", "W", "W_lo", "X", "X_lo",
                    "C2", "C2_lo", "E", "n_stages"):
            return getattr(self._gauss, name)
        if name in ("order", "quadrature_degree", "polynomial_degree_exact"):
            return getattr(self._path, name)
        raise AttributeError(name)

    @property
    def tau_path(self) -> np.ndarray:
        return self._path.tau

    def __setattr__(self, name, value):
        raise AttributeError(f"EQUIP is immutable; build a new one instead of setting {name!r}")

    def __repr__(self) -> str:
        return f"EQUIP({self.k}, {self.s})"

    def __eq__(self, other) -> bool:
        return isinstance(other, EQUIP) and (self.k, self.s) == (other.k, other.s)

    def __hash__(self) -> int:
        return hash(("EQUIP", self.k, self.s))

    def __reduce__(self):
        return (EQUIP, (self.k, self.s))

    # order (2s, Gauss's: alpha = O(h^(2s-1)) moves y1 by O(h^(2s+1))), quadrature_degree (the
    # energy condition's k-point rule, 2k - 1) and polynomial_degree_exact (nu s <= 2k: the
    # integrand sigma'^T grad H(sigma) along the degree-s path has degree nu s - 1) are those of
    # HBVM(k, s), whose rule the energy condition uses: read from it (see __getattr__)

    @property
    def work_rows(self) -> int:
        """Rows of stage work the engine sizes the step's buffer for (:mod:`.equip_core`'s
        views of the path and the root search's scratch fit in the space of k + 1 more stages)."""
        return self.s + self.k + 1

    def X_alpha(self, alpha: float = 0.0) -> np.ndarray:
        """X_s(alpha) = X_s + alpha S, shape (s, s)."""
        return self.X + float(alpha) * self.S

    def butcher_tableau(self, alpha: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A(alpha), b, c) with A(alpha) = P_s X_s(alpha) P_s^T Omega, b = omega, c = tau
        (the Gauss tableau at alpha = 0; A 1 = c + alpha P_s S e_1 otherwise)."""
        if alpha == 0.0:
            return self._gauss.butcher_tableau()
        return _readonly(self.P @ self.X_alpha(alpha) @ self.W), self.omega, self.tau

    def symplecticity_defect(self, alpha: float = 0.0) -> float:
        """max |b_i a_ij + b_j a_ji - b_i b_j| of A(alpha): zero (to rounding) for every alpha."""
        A, b, _ = self.butcher_tableau(alpha)
        M = b[:, None] * A + (b[:, None] * A).T - np.outer(b, b)
        return float(np.max(np.abs(M)))

    def essential_spectrum(self) -> np.ndarray:
        """The eigenvalues of A(0) (Gauss's), sorted."""
        return _sort(np.linalg.eigvals(self.butcher_tableau()[0]))

    def extrapolation_matrix(self, ratio: float = 1.0) -> np.ndarray:
        """Gauss's (the initial guess of gamma from the previous step's)."""
        return self._gauss.extrapolation_matrix(ratio)

    @cached_property
    def step_arrays(self) -> tuple:
        """(c1, c2): the arrays packed as :mod:`integrators.loop` takes them, Gauss's in the
        places where HBVM(s, s) has its own, EQUIP's in the planes of :mod:`.equip_core`
        (read-only, contiguous).  Cp is (N_CP, K, s) and Wp (4, s, K) with K = max(k, s):
        Gauss's planes are padded with zeros (the step reads their first s rows/columns)."""
        g, p, s, k = self._gauss, self._path, self.s, self.k
        K = max(k, s)
        S = self.S

        def pad(a, rows, cols):
            out = np.zeros((rows, cols))
            a = np.asarray(a, dtype=float)
            out[:a.shape[0], :a.shape[1]] = a
            return out

        cp = np.zeros((_ec.N_CP, K, s))
        for plane, a in ((0, g.C2), (1, g.C2_lo), (2, g.I), (3, g.I_lo),
                         (_ec.CP_PATH_C2, p.C2), (_ec.CP_PATH_C2_LO, p.C2_lo),
                         (_ec.CP_PATH_I, p.I), (_ec.CP_PATH_I_LO, p.I_lo),
                         (_ec.CP_PS, g.P @ S), (_ec.CP_B1, g.P @ (g.X @ S + S @ g.X)),
                         (_ec.CP_B2, g.P @ S @ S), (_ec.CP_PATH_S, p.I @ S), (_ec.CP_X, g.X),
                         (_ec.CP_X_LO, g.X_lo)):
            cp[plane] = pad(a, K, s)
        cp[_ec.CP_VEC, :k, 0] = p.tau
        cp[_ec.CP_VEC, :k, 1] = p.tau_lo
        wp = np.array([pad(g.W, s, K), pad(g.W_lo, s, K), pad(p.W, s, K), pad(p.W_lo, s, K)])
        ts = np.array([g.X[0], g.X_lo[0], S[0], g.P @ S[:, 0]])

        def ro(a):
            a = np.ascontiguousarray(a, dtype=float)
            a.flags.writeable = False
            return a
        return ((ro([g.tau, g.tau_lo]), ro(ts)), (ro(wp), ro(cp)))

    # -- stepping (delegated to the engine) ---------------------------------------------
    def step(self, system, y, h: float, solver: str = "auto"):
        """One step of size h from state y; returns y1.  See :class:`integrators.Stepper`."""
        from .engine import Stepper
        st = Stepper(self, system, y, solver=solver)
        st.step(h)
        return st.y.copy()

    def integrate(self, system, y0, h: float, steps: int | None = None, *args, **options):
        """Integrate ``steps`` steps of size h, or with ``adaptive=True`` up to ``t_end``: the
        module-level :func:`integrators.engine.integrate` with this method (the same
        arguments)."""
        from .engine import integrate
        return integrate(self, system, y0, h, steps, *args, **options)

