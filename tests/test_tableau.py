"""Tableau algebra of HBVM(k, s), tested by itself (no time stepping).

References: Brugnano, Iavernaro, Trigiante, "The lack of continuity and the role of infinite and
infinitesimal in numerical methods for ODEs: the case of symplecticity": eqs. (Xs), (IDPO), (rk),
Lemma 2, Theorems 1 and 2; HLW Sec. IV.3 (stability function), IV.5 (Pade approximants).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from integrators import HBVM, gauss_collocation_tableau, gauss_matrix, gauss_spectrum
from integrators.tableau import xi

EPS = np.finfo(float).eps
S_RANGE = range(1, 11)
K_MAX = 40


def _sorted(z):
    z = np.asarray(z, dtype=complex)
    return z[np.lexsort((np.round(z.imag, 10), np.round(z.real, 10)))]


def _match(a, b) -> float:
    """Largest distance between two spectra paired by sorting (sizes must agree)."""
    a, b = _sorted(a), _sorted(b)
    assert a.shape == b.shape
    return float(np.max(np.abs(a - b)))


@pytest.mark.slow
@pytest.mark.parametrize("nodes", ["gauss", "lobatto"])
def test_theorems_1_and_2_and_simplifying_assumptions(nodes):
    """For s = 1..10 and every k = s..40 (710 tableaux in all, built in 40-digit arithmetic):

    * Theorem 1: the s nonzero eigenvalues of A equal eig(X_s) and those of the independently
      built s-stage Gauss collocation tableau (Lagrange polynomials), to 1e-12;
    * Theorem 2: A = calA P_s P_s^T Omega with calA the k-point collocation matrix on the nodes;
    * row sums of A equal c, sum b = 1, B(2s), C(s), symmetry a_ij + a_{n+1-i,n+1-j} = b_j,
      and for Lobatto the first row of A is zero (the first stage is y0).
    """
    worst = dict(thm1_X=0.0, thm1_gauss=0.0, thm2=0.0, rows=0.0, B=0.0, C=0.0, sym=0.0, lob=0.0)
    for s in S_RANGE:
        ev_X = gauss_spectrum(s)
        A_gauss, _, _ = gauss_collocation_tableau(s)
        ev_gauss = np.linalg.eigvals(A_gauss)
        assert _match(ev_X, ev_gauss) <= 1e-12, s   # Lemma 1: X_s carries the Gauss spectrum
        for k in range(s, K_MAX + 1):
            m = HBVM(k, s, nodes)
            A, b, c = m.butcher_tableau()
            n = m.n_stages
            ess = m.essential_spectrum()
            worst["thm1_X"] = max(worst["thm1_X"], _match(ess, ev_X))
            worst["thm1_gauss"] = max(worst["thm1_gauss"], _match(ess, ev_gauss))
            calA = m.collocation_matrix()
            worst["thm2"] = max(worst["thm2"], float(np.max(np.abs(A - calA @ m.P @ m.W))))
            worst["rows"] = max(worst["rows"], float(np.max(np.abs(A.sum(axis=1) - c))))
            worst["B"] = max(worst["B"], max(abs(b @ c ** (q - 1) - 1 / q) for q in range(1, 2 * s + 1)))
            worst["C"] = max(worst["C"], max(float(np.max(np.abs(A @ c ** (q - 1) - c ** q / q)))
                                             for q in range(1, s + 1)))
            worst["sym"] = max(worst["sym"], float(np.max(np.abs(A + A[::-1, ::-1] - b[None, :]))))
            assert abs(b.sum() - 1) <= 8 * EPS
            assert A.shape == (n, n) and n == (k if nodes == "gauss" else k + 1)
            if nodes == "lobatto":
                worst["lob"] = max(worst["lob"], float(np.max(np.abs(A[0]))))
    assert worst["thm1_X"] <= 1e-12, worst
    assert worst["thm1_gauss"] <= 1e-12, worst
    assert worst["thm2"] <= 1e-12, worst
    assert worst["rows"] <= 64 * EPS, worst
    assert worst["B"] <= 1e-13, worst
    assert worst["C"] <= 1e-13, worst
    assert worst["sym"] <= 1e-13, worst
    assert worst["lob"] <= 1e-15, worst


def test_essential_spectrum_is_not_trivially_x_s():
    """The check above can fail: a perturbed tableau (HBVM(k, s+1)) has a different spectrum."""
    assert _match(HBVM(6, 3).essential_spectrum(), gauss_spectrum(3)) <= 1e-12
    assert _match(HBVM(6, 4).essential_spectrum()[:3], gauss_spectrum(3)) > 1e-2


@pytest.mark.parametrize("s", S_RANGE)
def test_hbvm_s_s_is_the_gauss_method(s):
    A, b, c = HBVM(s, s).butcher_tableau()
    Ag, bg, cg = gauss_collocation_tableau(s)
    assert np.max(np.abs(A - Ag)) <= 1e-13
    assert np.max(np.abs(b - bg)) <= 4 * EPS
    assert np.max(np.abs(c - cg)) <= 4 * EPS


@pytest.mark.parametrize("s", range(1, 7))
def test_symplecticity(s):
    """Gauss = HBVM(s, s) is symplectic; HBVM(k > s, s) is not (BIT Sec. 5), with either nodes."""
    assert HBVM(s, s).symplecticity_defect() <= 16 * EPS
    for k in (s + 1, 2 * s, 3 * s + 2):
        if k == s:
            continue
        assert HBVM(k, s).symplecticity_defect() > 1e-4, (k, s)
        assert HBVM(k, s, "lobatto").symplecticity_defect() > 1e-4, (k, s)
    # Lobatto HBVM(s, s) is the Lobatto IIIA-type method, not symplectic either (s >= 1)
    assert HBVM(s, s, "lobatto").symplecticity_defect() > 1e-4


@pytest.mark.parametrize("nodes", ["gauss", "lobatto"])
def test_quadrature_degree_and_polynomial_degree_exact(nodes):
    """sum_i omega_i tau_i^d = 1/(d + 1) exactly for d <= 2k - 1 and not for d = 2k; the
    conserved polynomial degree nu is the largest with nu s <= 2k (eq. (knu))."""
    for k in range(1, 9):
        m = HBVM(k, 1, nodes)
        for d in range(0, 2 * k):
            assert abs(m.omega @ m.tau ** d - 1 / (d + 1)) <= 1e-14, (k, d)
        assert abs(m.omega @ m.tau ** (2 * k) - 1 / (2 * k + 1)) > 1e-11
        assert m.quadrature_degree == 2 * k - 1
    for s in range(1, 6):
        for k in range(s, 4 * s + 1):
            m = HBVM(k, s, nodes)
            nu = m.polynomial_degree_exact
            assert nu * s - 1 <= m.quadrature_degree < (nu + 1) * s - 1, (k, s)
            assert m.order == 2 * s


@pytest.mark.parametrize("nodes", ["gauss", "lobatto"])
@pytest.mark.parametrize("nu", [1, 2, 3, 4, 5, 6])
@pytest.mark.parametrize("s", [1, 2, 3, 4, 5])
def test_for_polynomial_degree_is_smallest(nodes, nu, s):
    m = HBVM.for_polynomial_degree(nu, s, nodes)
    assert (m.s, m.nodes) == (s, nodes)
    assert m.polynomial_degree_exact >= nu
    if m.k > s:
        assert HBVM(m.k - 1, s, nodes).polynomial_degree_exact < nu
    expected = {(4, 2): 4, (3, 3): 5, (4, 3): 6, (3, 2): 3}
    if (nu, s) in expected:
        assert m.k == expected[(nu, s)]


@pytest.mark.parametrize("nodes", ["gauss", "lobatto"])
@pytest.mark.parametrize("k,s", [(1, 1), (3, 1), (2, 2), (5, 2), (4, 4), (9, 4), (8, 8), (20, 8)])
def test_lemma_2_integrals_of_legendre_polynomials(nodes, k, s):
    """Lemma 2: I_s = P_{s+1} Xhat_s with Xhat_s = [X_s; xi_s e_s^T]."""
    m = HBVM(k, s, nodes)
    Pn = np.column_stack([m.P, m.P_next])
    Xhat = np.vstack([m.X, xi(s) * np.eye(s)[-1]])
    assert np.max(np.abs(m.I - Pn @ Xhat)) <= 1e-14
    # and P_s^T Omega I_s = X_s (the step in the proof of Theorem 1)
    assert np.max(np.abs(m.W @ m.I - m.X)) <= 1e-14


def test_gauss_matrix_structure():
    X = gauss_matrix(4)
    assert X[0, 0] == 0.5 and np.all(np.diag(X)[1:] == 0)
    for j in range(1, 4):
        assert X[j, j - 1] == -X[j - 1, j] == pytest.approx(1 / (2 * math.sqrt(4 * j * j - 1)), rel=1e-15)


def _pade_ss(s, z):
    """The (s, s) Pade approximant of exp(z): P(z)/P(-z), P(z) = sum_j (2s-j)! s! / ((2s)! j! (s-j)!) z^j."""
    coef = [math.factorial(2 * s - j) * math.factorial(s) /
            (math.factorial(2 * s) * math.factorial(j) * math.factorial(s - j)) for j in range(s + 1)]
    num = sum(c * z ** j for j, c in enumerate(coef))
    den = sum(c * (-z) ** j for j, c in enumerate(coef))
    return num / den


@pytest.mark.parametrize("nodes", ["gauss", "lobatto"])
@pytest.mark.parametrize("k,s", [(1, 1), (4, 1), (2, 2), (5, 2), (3, 3), (8, 3), (4, 4), (10, 4), (6, 6)])
def test_stability_function_is_gauss_pade_and_a_stable(nodes, k, s):
    """R(z) of HBVM(k, s) equals the Gauss (s, s) Pade approximant and
    1 + z e1^T (I - z X_s)^{-1} e1; |R(iy)| = 1 and |R(z)| < 1 for Re z < 0 (A-stable)."""
    m = HBVM(k, s, nodes)
    rng = np.random.default_rng(1)
    y = np.concatenate([np.linspace(-30, 30, 61), [1e-3, -1e-3, 100.0]])
    left = -rng.uniform(1e-3, 30, 60) + 1j * rng.uniform(-30, 30, 60)
    z = np.concatenate([1j * y, left, [-0.5 + 0j, -1e-6 + 0j]])
    R = m.stability_function(z)
    pade = _pade_ss(s, z)
    X = gauss_matrix(s)
    e1 = np.eye(s)[0]
    RX = np.array([1 + zi * (e1 @ np.linalg.solve(np.eye(s) - zi * X, e1)) for zi in z])
    scale = np.maximum(1.0, np.abs(pade))
    assert np.max(np.abs(R - pade) / scale) <= 1e-11
    assert np.max(np.abs(RX - pade) / scale) <= 1e-11
    on_axis = np.abs(R[: y.size])
    assert np.max(np.abs(on_axis - 1)) <= 1e-12
    assert np.all(np.abs(R[y.size:]) < 1)
    # exp(z) itself is reproduced to order 2s near 0
    zz = 1e-2
    assert abs(m.stability_function(zz) - np.exp(zz)) <= 10 * zz ** (2 * s + 1) + 1e-15


def test_tableau_is_immutable_and_hashable():
    m = HBVM(4, 2)
    with pytest.raises(AttributeError, match="HBVM is immutable"):
        m.k = 5
    with pytest.raises(ValueError, match="read-only"):
        m.tau[0] = 0.0
    assert m == HBVM(4, 2) and hash(m) == hash(HBVM(4, 2)) and m != HBVM(4, 2, "lobatto")
    assert repr(HBVM(4, 2, "lobatto")) == "HBVM(4, 2, nodes='lobatto')"
    # the arrays are built once per (k, s, nodes) and shared, which only read-only arrays allow
    other = HBVM(4, 2)
    for name in ("tau", "tau_lo", "omega", "P", "I", "W", "W_lo", "I_lo", "C2", "C2_lo", "E",
                 "P_next", "X", "X_lo"):
        a = getattr(m, name)
        assert a is getattr(other, name) and not a.flags.writeable, name
        with pytest.raises(ValueError, match="read-only"):
            a.flat[0] = 0.0
