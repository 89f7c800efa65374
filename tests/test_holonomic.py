"""HBVM(k, s) with rigid bonds (integrators.holonomic): order, constraints, energy, failures."""
import numpy as np
import pytest

from integrators import HBVM, ConstraintError, ConvergenceError
from integrators.holonomic import BondConstraints, HolonomicHBVM

# a rigid water-like triangle (O, H, H) in a smooth, non-polynomial external field
MASSES = np.array([16.0, 1.0, 1.0])
CHARGE = np.array([-0.8, 0.4, 0.4])
D_OH, ANGLE = 0.9572, np.deg2rad(104.52)
Q0 = np.array([[0, 0, 0], [D_OH, 0, 0], [D_OH * np.cos(ANGLE), D_OH * np.sin(ANGLE), 0]])
BONDS = BondConstraints([(0, 1), (0, 2), (1, 2)],
                        [D_OH, D_OH, np.linalg.norm(Q0[1] - Q0[2])], 3)


def field_force(Q):
    F = -MASSES[:, None] * Q
    c = np.cos(Q[..., 0] + 0.5 * Q[..., 1]) * CHARGE
    F[..., 0] -= c
    F[..., 1] -= 0.5 * c
    F[..., 2] += 0.6 * CHARGE * np.sin(2 * Q[..., 2])
    return F


def field_energy(q, p):
    V = np.sum(0.5 * MASSES * np.sum(q ** 2, -1) + CHARGE * np.sin(q[:, 0] + 0.5 * q[:, 1])
               + 0.3 * CHARGE * np.cos(2 * q[:, 2]))
    return V + 0.5 * np.sum(p ** 2 / MASSES[:, None])


def quartic_force(Q):
    """V = sum_i m_i |q_i|^4 / 4 + c_i q_ix q_iy: a polynomial of degree 4."""
    r2 = np.sum(Q ** 2, -1, keepdims=True)
    F = -MASSES[:, None] * r2 * Q
    F[..., 0] -= CHARGE * Q[..., 1]
    F[..., 1] -= CHARGE * Q[..., 0]
    return F


def quartic_energy(q, p):
    return (np.sum(0.25 * MASSES * np.sum(q ** 2, -1) ** 2 + CHARGE * q[:, 0] * q[:, 1])
            + 0.5 * np.sum(p ** 2 / MASSES[:, None]))


def start(seed):
    rng = np.random.default_rng(seed)
    q = Q0 + np.array([0.3, -0.2, 0.1]) + 0.0 * rng.normal()
    # rotate the molecule at random (bonds unchanged), random momenta made tangent
    A, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q = (q - q[0]) @ A.T + q[0]
    p = rng.normal(size=(3, 3)) * np.sqrt(MASSES)[:, None]
    p, _ = HolonomicHBVM(HBVM(1, 1), BONDS, MASSES, field_force).project_momenta_onto_bonds(q, p)
    return q, p


def run(method, force, q, p, h, n, **kw):
    st = HolonomicHBVM(method, BONDS, MASSES, force, **kw)
    out = [(q, p)]
    for _ in range(n):
        q, p = st.step(q, p, h)
        out.append((q, p))
    return out


def hidden(q, p):
    r = BONDS.vectors(q)
    return BONDS.apply(r[None], (p / MASSES[:, None])[None])[0]


@pytest.fixture(scope="module")
def reference():
    q0, p0 = start(1)
    return q0, p0, run(HBVM(7, 5), field_force, q0, p0, 2.0 / 160, 160)[-1]


@pytest.mark.parametrize("k, s", [(2, 1), (3, 2), (4, 3)])
def test_order_2s_in_q_and_p(k, s, reference):
    q0, p0, (qr, pr) = reference
    T = 2.0
    steps = [10, 20, 40, 80]
    err = []
    for n in steps:
        q, p = run(HBVM(k, s), field_force, q0, p0, T / n, n)[-1]
        err.append(max(np.max(np.abs(q - qr)), np.max(np.abs(p - pr))))
    err = np.array(err)
    keep = err > 1e-12               # points on the round-off plateau are dropped
    assert keep.sum() >= 3
    slope = -np.polyfit(np.log(np.array(steps)[keep]), np.log(err[keep]), 1)[0]
    assert abs(slope - 2 * s) < 0.3, (slope, err)


def test_bonds_and_hidden_constraint_at_round_off():
    q, p = start(2)
    traj = run(HBVM(3, 2), field_force, q, p, 0.05, 200)
    bond = max(np.max(np.abs(BONDS.length_errors(q))) for q, _ in traj)
    vel = max(np.max(np.abs(hidden(q, p))) for q, p in traj)
    assert bond < 1e-14
    assert vel < 1e-13


def test_bare_method_drifts_along_the_bonds_and_projection_removes_it():
    """Without the projection the momenta gain a velocity along the bonds (O(h^(2s-2))); the
    energy and the bond lengths hold either way."""
    q, p = start(2)
    bare = run(HBVM(3, 2), field_force, q, p, 0.05, 100, project_momenta=False)
    assert np.max(np.abs(hidden(*bare[-1]))) > 1e-6
    assert np.max(np.abs(BONDS.length_errors(bare[-1][0]))) < 1e-14


@pytest.mark.parametrize("k, s", [(4, 2), (6, 3)])
def test_energy_exact_for_polynomial_potential(k, s):
    """nu = 4: HBVM(k, s) with 4 s <= 2k conserves H to round-off, constraints and all (medians
    over perturbed starts); HBVM(s, s) (Gauss) does not."""
    errs, gauss = [], []
    for seed in range(3):
        q, p = start(10 + seed)
        H0 = quartic_energy(q, p)
        for meth, out in ((HBVM(k, s), errs), (HBVM(s, s), gauss)):
            traj = run(meth, quartic_force, q, p, 0.1, 50)
            out.append(max(abs(quartic_energy(*y) - H0) for y in traj) / abs(H0))
    assert np.median(errs) < 1e-14, errs
    assert np.median(gauss) > 1e3 * np.median(errs), gauss


def test_energy_of_smooth_potential_falls_with_k():
    """Non-polynomial V: the energy error is the quadrature error of the line integral,
    O(h^(2k+1)) a step: HBVM(6, 2) conserves it to round-off where HBVM(2, 2) does not."""
    res = {}
    for k in (2, 6):
        errs = []
        for seed in range(3):
            q, p = start(20 + seed)
            H0 = field_energy(q, p)
            traj = run(HBVM(k, 2), field_force, q, p, 0.1, 50)
            errs.append(max(abs(field_energy(*y) - H0) for y in traj) / abs(H0))
        res[k] = np.median(errs)
    assert res[6] < 1e-14
    assert res[2] > 1e3 * res[6]


def test_total_momentum_kept():
    q, p = start(3)
    def free(Q):              # internal pair forces only: the total momentum is conserved
        r = Q[:, 0] - Q[:, 1]
        f = -np.sin(np.sum(r * r, -1))[:, None] * r
        F = np.zeros_like(Q)
        F[:, 0], F[:, 1] = f, -f
        return F
    traj = run(HBVM(3, 2), free, q, p, 0.1, 100)
    assert np.max(np.abs(traj[-1][1].sum(0) - p.sum(0))) < 1e-13


def test_failure_changes_nothing():
    q, p = start(4)
    st = HolonomicHBVM(HBVM(3, 2), BONDS, MASSES, field_force)
    q1, p1 = st.step(q, p, 0.05)
    q_, p_ = q1.copy(), p1.copy()
    with pytest.raises(ConvergenceError, match="did not converge.*runs away"):
        st.step(q1, p1 * 1e3, 5.0)
    assert np.array_equal(q1, q_) and np.array_equal(p1, p_)
    # the next step is bit for bit the one without the failed attempt
    ref = HolonomicHBVM(HBVM(3, 2), BONDS, MASSES, field_force)
    ref.step(q, p, 0.05)
    a, b = st.step(q1, p1, 0.05), ref.step(q1, p1, 0.05)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_unreachable_bond_lengths_raise_constraint_error():
    con = BondConstraints([(0, 1), (1, 2), (0, 2)], [1.0, 1.0, 3.0], 3)   # triangle inequality
    st = HolonomicHBVM(HBVM(2, 1), con, MASSES, field_force)
    with pytest.raises(ConstraintError, match="bond-length error"):
        st.project_positions(Q0)


def test_bad_input_named():
    with pytest.raises(ValueError, match="`pairs` must be integer"):
        BondConstraints([(0.0, 1.0)], [1.0], 3)
    with pytest.raises(ValueError, match="out of range"):
        BondConstraints([(0, 3)], [1.0], 3)
    with pytest.raises(ValueError, match="to itself"):
        BondConstraints([(1, 1)], [1.0], 3)
    with pytest.raises(ValueError, match="twice"):
        BondConstraints([(0, 1), (1, 0)], [1.0, 1.0], 3)
    with pytest.raises(ValueError, match="positive and finite"):
        BondConstraints([(0, 1)], [np.nan], 3)
    st = HolonomicHBVM(HBVM(2, 1), BONDS, MASSES, field_force)
    with pytest.raises(ValueError, match=r"`q` and `p` must have shape \(3, d\)"):
        st.step(Q0[:2], Q0[:2], 0.1)
    bad = Q0.copy()
    bad[1, 0] = np.nan
    with pytest.raises(ValueError, match="`q` must be finite.*atom 1"):
        st.step(bad, np.zeros((3, 3)), 0.1)
    with pytest.raises(ValueError, match="`masses` must have shape"):
        HolonomicHBVM(HBVM(2, 1), BONDS, MASSES[:2], field_force)
    with pytest.raises(ValueError, match="`force` returned shape"):
        HolonomicHBVM(HBVM(2, 1), BONDS, MASSES, lambda Q: Q[:, :2]).step(Q0, np.zeros((3, 3)), 0.1)


def stiff_bonds_force(Q):
    """The field force plus stiff springs along the three bonds of the rigid molecule (as a
    pair potential that does not exclude a molecule's own pairs): K = 1e6, rest length 0.9."""
    F = field_force(Q)
    r = BONDS.vectors(Q)
    d = np.linalg.norm(r, axis=-1)
    lam = -1e6 * (d - 0.9) / d
    return F + BONDS.transpose_apply(lam, r)


def test_forces_along_the_bonds_are_absorbed_when_they_make_the_iteration_diverge():
    """The spring forces are constraint forces on g = 0: "keep" runs away, "auto" absorbs them
    after that failure (the same trajectory as without the springs, to the method's error), and
    an ordinary force keeps the full forces (energy to round-off for a polynomial V stays)."""
    q, p = start(3)
    with pytest.raises(ConvergenceError, match=r"fixed_point iteration stopped after \d+ "
                                               r"iterations .*try a smaller timestep"):
        run(HBVM(3, 2), stiff_bonds_force, q, p, 0.05, 1, normal_forces="keep")
    st = HolonomicHBVM(HBVM(3, 2), BONDS, MASSES, stiff_bonds_force)
    plain = HolonomicHBVM(HBVM(3, 2), BONDS, MASSES, field_force)
    y, z = (q, p), (q, p)
    for _ in range(40):
        y = st.step(*y, 0.05)
        z = plain.step(*z, 0.05)
    assert st.absorbing and not plain.absorbing
    assert np.max(np.abs(BONDS.length_errors(y[0]))) < 1e-14
    assert np.max(np.abs(y[0] - z[0])) < 1e-6
    assert abs(field_energy(*y) - field_energy(q, p)) < 1e-7 * abs(field_energy(q, p))
    with pytest.raises(ValueError, match=r"`normal_forces` must be 'auto', 'keep' or 'absorb' "
                                         r"\(got normal_forces='yes'\)"):
        HolonomicHBVM(HBVM(3, 2), BONDS, MASSES, field_force, normal_forces="yes")
