"""The angular-momentum diagnostic of the reports (hbvm_md.reports.invariants) and the one
function behind it (systems.angular_momentum)."""
import numpy as np
import pytest

from hbvm_md.reports.invariants import TINY, atoms_angular_momentum, change_series, relative_change
from systems.angular_momentum import angular_momentum


def _cluster(rng, n=7):
    m = rng.uniform(1, 40, n)
    x = rng.normal(size=(n, 3)) * 3
    p = rng.normal(size=(n, 3)) * m[:, None]
    return m, x, p


def test_about_the_centre_of_mass_does_not_depend_on_where_the_cluster_sits():
    rng = np.random.default_rng(0)
    m, x, p = _cluster(rng)
    p -= m[:, None] * p.sum(0) / m.sum()                       # zero total momentum
    L, S = atoms_angular_momentum(x[None], p[None], m)
    far, _ = atoms_angular_momentum((x + [1e3, -2e3, 5e2])[None], p[None], m)
    np.testing.assert_allclose(far, L, rtol=1e-9)
    # with P = 0 it is ASE's Atoms.get_angular_momentum() (about the origin)
    from ase import Atoms
    a = Atoms(f"Ar{len(m)}", positions=x, masses=m, momenta=p)
    np.testing.assert_allclose(L[0], a.get_angular_momentum(), rtol=1e-12)
    # with P != 0 they differ by R x P, and the origin's follows the frame
    q = p + m[:, None] * [0.3, 0.0, 0.0]
    Lo, So = angular_momentum((x + [0, 1e3, 0])[None], q[None])
    Lc, Sc = angular_momentum((x + [0, 1e3, 0])[None], q[None], m, about="com")
    R, P = (m[:, None] * (x + [0, 1e3, 0])).sum(0) / m.sum(), q.sum(0)
    np.testing.assert_allclose(Lo[0] - Lc[0], np.cross(R, P), rtol=1e-10, atol=1e-14 * So[0])
    assert So[0] > 100 * Sc[0]


def test_relative_change_divides_by_L0_and_by_the_scale_when_L0_is_tiny():
    L = np.array([[0.0, 0.0, 2.0], [0.0, 3e-12, 2.0], [1e-12, 0.0, 2.0 - 1e-12]])
    np.testing.assert_allclose(change_series(L, 5.0), [0.0, 1.5e-12, np.sqrt(2) * 0.5e-12], rtol=1e-3)
    assert relative_change(L, 5.0) == pytest.approx(1.5e-12, rel=1e-3)
    # planar (Kepler) L: shape (n,)
    assert relative_change(np.array([0.8, 0.8 + 8e-7]), 1.0) == pytest.approx(1e-6, rel=1e-9)
    # a cluster set not to rotate: L0 = 1e-17 of S, divide by S instead of by round-off
    Z = np.array([[0.0, 0.0, 1e-17], [0.0, 0.0, 2e-9]])
    assert TINY * 1.0 > 1e-17 and relative_change(Z, 1.0) == pytest.approx(2e-9, rel=1e-6)
    # a start at rest (S(0) = 0): against the largest S the run reached; nothing moved: 0
    assert relative_change(Z, np.array([0.0, 4.0])) == pytest.approx(5e-10, rel=1e-6)
    assert relative_change(np.zeros((3, 3)), np.zeros(3)) == 0.0
    # a run that blew up is inf, not nan (a table must not hide it)
    assert change_series(np.array([1.0, np.nan]), 1.0)[1] == np.inf


@pytest.mark.parametrize("call, match", [
    (lambda: angular_momentum(np.zeros((2, 3)), np.zeros((3, 3))), "must both have shape"),
    (lambda: angular_momentum(np.zeros((2, 3)), np.zeros((2, 3)), about="middle"), "`about` must be"),
    (lambda: angular_momentum(np.zeros((2, 3)), np.zeros((2, 3)), about="com"), "`masses`"),
    (lambda: change_series(np.ones(3), -1.0), "`scale` must be a number >= 0"),
])
def test_bad_input_is_named(call, match):
    with pytest.raises(ValueError, match=match):
        call()
