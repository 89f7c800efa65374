"""PolynomialPairPotential: forces, stress, per-atom energies, batched path, modes, bad input."""
import numpy as np
import pytest
from ase import Atoms
from ase.build import bulk
from ase.calculators.fd import calculate_numerical_forces, calculate_numerical_stress

from systems import PolynomialPairPotential


def _cluster(n=13, seed=0):
    rng = np.random.default_rng(seed)
    return Atoms(f"Ar{n}", positions=rng.uniform(-4, 4, size=(n, 3)))


def _periodic(seed=1):
    atoms = bulk("Ar", "fcc", a=3.9, cubic=True) * (2, 2, 2)   # 32 atoms, box 7.8 A
    atoms.rattle(0.15, seed=seed)
    return atoms


def _all_setups():
    cl = _cluster()
    cl.calc = PolynomialPairPotential([0.3, -0.02, 1e-3, 2e-5])
    chain = Atoms("Ar6", positions=np.c_[np.arange(6) * 1.1, np.zeros(6), 0.1 * np.arange(6) ** 2])
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 5)]
    coefs = [[0.0, 0.5, 0.1], [0.0, 0.2, 0.0], [0.1, 0.3, 0.05], [0.0, 1.0, 0.0], [0.0, 0.1, 0.2],
             [0.0, 0.0, 0.01]]
    chain.calc = PolynomialPairPotential(coefs, pairs=pairs)
    per = _periodic()
    per.calc = PolynomialPairPotential.with_cutoff([0.05, -0.002], 5.0)
    return {"all_pairs": cl, "bonded": chain, "cutoff_periodic": per}


@pytest.mark.parametrize("name", ["all_pairs", "bonded", "cutoff_periodic"])
def test_forces_match_finite_differences_of_energy(name):
    atoms = _all_setups()[name]
    F = atoms.get_forces()
    Fnum = calculate_numerical_forces(atoms, eps=1e-5)
    assert np.max(np.abs(F)) > 1e-3
    np.testing.assert_allclose(F, Fnum, atol=1e-7 * max(1.0, np.max(np.abs(F))))


@pytest.mark.parametrize("name", ["bonded", "cutoff_periodic"])
def test_stress_matches_numerical_stress(name):
    atoms = _all_setups()[name]
    if name == "bonded":
        atoms.cell = [12.0, 11.0, 13.0]
    sigma = atoms.get_stress()
    num = calculate_numerical_stress(atoms, eps=1e-6)
    assert np.max(np.abs(sigma)) > 1e-6
    np.testing.assert_allclose(sigma, num, atol=1e-8 * max(1.0, np.max(np.abs(sigma))) + 1e-11)


def test_per_atom_energies_sum_to_energy_and_free_energy():
    for atoms in _all_setups().values():
        e = atoms.get_potential_energy()
        assert atoms.get_potential_energies().sum() == pytest.approx(e, rel=1e-13, abs=1e-14)
        assert atoms.get_potential_energy(force_consistent=True) == e


def test_dimer_energy_is_the_polynomial_in_r_squared():
    atoms = Atoms("Ar2", positions=[[0, 0, 0], [0.3, -0.4, 1.2]])   # r^2 = 1.69
    atoms.calc = PolynomialPairPotential([1.0, -2.0, 0.5])
    u = 1.69
    assert atoms.get_potential_energy() == pytest.approx(1.0 - 2.0 * u + 0.5 * u * u, rel=1e-14)


@pytest.mark.parametrize("name", ["all_pairs", "bonded", "cutoff_periodic"])
def test_batched_path_matches_one_configuration_path(name):
    atoms = _all_setups()[name]
    calc = atoms.calc
    rng = np.random.default_rng(3)
    Q = atoms.positions[None] + rng.normal(scale=0.05, size=(4, len(atoms), 3))
    Fb = calc.forces_batch(Q, atoms)
    for a in range(len(Q)):
        atoms.positions[:] = Q[a]
        np.testing.assert_allclose(Fb[a], atoms.get_forces(), rtol=1e-12, atol=1e-14)


def test_forces_batch_writes_into_out_and_refuses_a_wrong_one():
    atoms = _all_setups()["cutoff_periodic"]
    calc = atoms.calc
    Q = atoms.positions[None] + np.random.default_rng(4).normal(scale=0.05, size=(3, len(atoms), 3))
    out = np.full(Q.shape, np.nan)
    assert calc.forces_batch(Q, atoms, out=out) is out
    np.testing.assert_array_equal(out, calc.forces_batch(Q, atoms))
    for bad in (np.empty(Q.shape, dtype=np.float32), np.empty(Q.shape[:-1]),
                np.empty(Q.shape[::-1]).T):
        with pytest.raises(ValueError, match="`out` must be"):
            calc.forces_batch(Q, atoms, out=bad)
    with pytest.raises(ValueError, match="`out` must not share memory with `Q`"):
        calc.forces_batch(Q, atoms, out=Q)


def test_forces_batch_checks_its_list_in_the_kernel_pass():
    """forces_batch checks in the kernel's own pass that every atom of every configuration
    stayed within skin / 2 of the list's reference: a batch that moved further is computed
    again with a new list, and configurations far apart from each other one list each."""
    atoms = _periodic()
    calc = PolynomialPairPotential.soft_sphere(0.1, 4.5, skin=0.2)
    atoms.calc = calc

    def fresh(Q):
        other = PolynomialPairPotential.soft_sphere(0.1, 4.5, skin=0.2)
        return np.stack([other.forces_batch(Q[a:a + 1], atoms)[0] for a in range(len(Q))])

    x = atoms.positions
    Q = x[None] + np.random.default_rng(5).normal(scale=0.01, size=(3, len(atoms), 3))
    np.testing.assert_allclose(calc.forces_batch(Q, atoms), fresh(Q), rtol=1e-13, atol=1e-15)
    assert calc.neighbour_list_builds == 1
    Q[:, 0] += [0.7, -0.4, 0.5]              # one atom beyond the skin in every stage
    np.testing.assert_allclose(calc.forces_batch(Q, atoms), fresh(Q), rtol=1e-13, atol=1e-15)
    assert calc.neighbour_list_builds == 2     # one new list, at Q[0], serves them all
    Q[2, 5] -= [0.4, 0.4, 0.0]                 # stages far apart: a list for the far one
    np.testing.assert_allclose(calc.forces_batch(Q, atoms), fresh(Q), rtol=1e-13, atol=1e-15)
    assert calc.neighbour_list_builds == 4


def test_neighbour_list_is_rebuilt_when_atoms_move_beyond_the_skin():
    atoms = _periodic()
    atoms.calc = PolynomialPairPotential.soft_sphere(0.1, 4.5, skin=0.2)
    atoms.get_forces()
    atoms.positions[0] += [0.7, -0.4, 0.5]
    moved = atoms.get_forces()
    fresh = atoms.copy()
    fresh.calc = PolynomialPairPotential.soft_sphere(0.1, 4.5, skin=0.2)
    np.testing.assert_allclose(moved, fresh.get_forces(), rtol=1e-13, atol=1e-15)


def test_cutoff_potential_vanishes_smoothly_at_rc():
    calc = PolynomialPairPotential.soft_sphere(0.2, 3.0)
    for r, bound in ((3.0 - 1e-3, 1e-11), (3.0, 0.0), (3.5, 0.0)):
        atoms = Atoms("Ar2", positions=[[0, 0, 0], [r, 0, 0]])
        atoms.calc = calc
        assert abs(atoms.get_potential_energy()) <= bound
        assert np.max(np.abs(atoms.get_forces())) <= bound * 1e3


def test_polynomial_degree_per_mode():
    assert PolynomialPairPotential([0.0, -1.0, 0.5]).polynomial_degree == 4
    assert PolynomialPairPotential([0.0, 1.0]).polynomial_degree == 2
    assert PolynomialPairPotential([0.0, -1.0, 0.5, 0.0]).polynomial_degree == 4   # trailing zero
    assert PolynomialPairPotential([[0, 1, 0, 0, 1]], pairs=[(0, 1)]).polynomial_degree == 8
    assert PolynomialPairPotential.soft_sphere(1.0, 2.0).polynomial_degree is None


@pytest.mark.parametrize("kwargs, match", [
    (dict(coefficients=[0.0, 1.0], cutoff=-2.0), "`cutoff` must be a positive number"),
    (dict(coefficients=[0.0, np.nan]), "`coefficients` must be finite"),
    (dict(coefficients=[0.0, 1.0, -0.5]), "not bounded below; make the highest coefficient positive"),
    (dict(coefficients=[0.0, 1.0], cutoff=3.0), "must vanish at r_c .*with_cutoff"),
    (dict(coefficients=[0.0, 1.0], pairs=[(0, -1)]), "negative atom index"),
    (dict(coefficients=[0.0, 1.0], pairs=[(2, 2)]), "joins atom 2 to itself"),
    (dict(coefficients=[[0.0, 1.0]] * 3, pairs=[(0, 1)]), "has 3 rows but `pairs` has 1"),
    (dict(coefficients=[0.0, 1.0], pairs=[(0, 1)], cutoff=2.0), "either `pairs`"),
])
def test_bad_input_is_refused_with_the_fix(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PolynomialPairPotential(**kwargs)


def test_pairs_out_of_range_and_all_pairs_with_pbc_are_refused_at_evaluation():
    atoms = _cluster(4)
    atoms.calc = PolynomialPairPotential([0.0, 1.0], pairs=[(0, 1), (2, 7)])
    with pytest.raises(ValueError, match="refers to atom 7 but the atoms have 4"):
        atoms.get_forces()
    per = _periodic()
    per.calc = PolynomialPairPotential([0.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="all-pairs mode has no cutoff.*give `cutoff`"):
        per.get_potential_energy()


# -- the neighbour list (vesin) against a brute-force sum over periodic images ----------------
def _image_sum(atoms, calc):
    """Energy and forces by summing phi over all images within reach (numpy, independent of
    any neighbour list); positions wrapped into the cell first, which changes no separation."""
    X, cell, rc = atoms.get_positions(wrap=True), np.array(atoms.cell), calc.cutoff
    reach = [int(np.ceil(rc / (atoms.cell.volume / np.linalg.norm(np.cross(*np.delete(cell, d, 0)))))) + 1
             if atoms.pbc[d] else 0 for d in range(3)]
    grid = np.stack(np.meshgrid(*[np.arange(-m, m + 1) for m in reach], indexing="ij"), -1).reshape(-1, 3)
    D = X[None, :, None, :] - X[:, None, None, :] + (grid @ cell)[None, None]   # (i, j, image, 3)
    u = np.sum(D * D, axis=-1)
    u[np.arange(len(X)), np.arange(len(X)), np.all(grid == 0, axis=1).argmax()] = np.inf
    inside = u < rc * rc
    c = calc.coefficients
    G = np.where(inside, np.polynomial.polynomial.polyval(np.where(inside, u, 0), c), 0.0)
    dG = np.where(inside, np.polynomial.polynomial.polyval(np.where(inside, u, 0),
                                                           np.polynomial.polynomial.polyder(c)), 0.0)
    F = 2 * np.einsum("ijn,ijnc->ic", dG, D)   # F_i = sum_j 2 G'(u) D_ij
    return 0.5 * G.sum(), F


def _small_cells():
    one = bulk("Ar", "fcc", a=3.6)                     # one atom, cell far smaller than 2 r_c
    one.positions[0] += [0.3, -0.2, 0.1]
    two = bulk("Ar", "sc", a=3.0) * (2, 1, 1)
    two.rattle(0.2, seed=4)
    hcp = bulk("Cu", "hcp", a=2.5, c=4.0) * (2, 2, 1)   # skewed cell
    hcp.rattle(0.1, seed=5)
    slab = _periodic(seed=6)
    slab.pbc = [True, True, False]
    unwrapped = _periodic(seed=7)
    unwrapped.positions += np.random.default_rng(7).integers(-2, 3, (len(unwrapped), 3)) @ unwrapped.cell[:]
    return {"one_atom": one, "two_atoms": two, "skewed": hcp, "slab": slab, "unwrapped": unwrapped}


@pytest.mark.parametrize("name", ["one_atom", "two_atoms", "skewed", "slab", "unwrapped"])
def test_cutoff_mode_matches_a_brute_force_image_sum(name):
    atoms = _small_cells()[name]
    atoms.calc = PolynomialPairPotential.with_cutoff([0.05, -0.002], 5.0)
    E, F = _image_sum(atoms, atoms.calc)
    assert abs(E) > 1e-3
    assert atoms.get_potential_energy() == pytest.approx(E, rel=1e-13)
    np.testing.assert_allclose(atoms.get_forces(), F, rtol=0, atol=1e-13 * np.max(np.abs(F)) + 1e-15)


def test_batched_configurations_farther_apart_than_the_skin_get_their_own_lists():
    atoms = _periodic()
    calc = PolynomialPairPotential.soft_sphere(0.1, 4.5, skin=0.2)
    atoms.calc = calc
    Q = atoms.positions[None] + np.array([0.0, 0.3, 0.6])[:, None, None] * [1.0, 0.5, -0.2]
    Fb = calc.forces_batch(Q, atoms)
    assert calc.neighbour_list_builds >= 3      # one list cannot serve configurations 0.7 A apart
    for a in range(3):
        atoms.positions[:] = Q[a]
        np.testing.assert_allclose(Fb[a], _image_sum(atoms, calc)[1], rtol=0, atol=1e-13)


def test_md_run_rebuilds_the_list_when_atoms_pass_the_skin_and_stays_exact():
    from ase import units
    from hbvm_md import HBVMDynamics
    from hbvm_md.reports.md_comparison import maxwell_boltzmann
    atoms = _periodic()
    maxwell_boltzmann(atoms, 3000.0, seed=1)
    calc = PolynomialPairPotential.soft_sphere(0.1, 4.5, skin=0.05)
    atoms.calc = calc
    start = atoms.positions.copy()
    HBVMDynamics(atoms, 5 * units.fs, s=2).run(15)
    assert np.max(np.linalg.norm(atoms.positions - start, axis=1)) > 0.05   # beyond the skin
    assert calc.neighbour_list_builds >= 3
    np.testing.assert_allclose(atoms.get_forces(), _image_sum(atoms, calc)[1], rtol=0, atol=1e-13)


# -- the analytic Hessian ---------------------------------------------------------------------
@pytest.mark.parametrize("name", ["all_pairs", "bonded", "cutoff_periodic", "one_atom_cell"])
def test_hessian_matches_finite_differences_of_forces(name):
    if name == "one_atom_cell":
        atoms = _small_cells()["two_atoms"]
        atoms.calc = PolynomialPairPotential.with_cutoff([0.05, -0.002], 5.0)
    else:
        atoms = _all_setups()[name]
    calc = atoms.calc
    H = calc.hessian(atoms=atoms)
    x0 = atoms.positions.copy()
    eps = 1e-5
    num = np.empty_like(H)
    for k in range(3 * len(atoms)):
        Q = np.stack([x0, x0])
        Q[0].flat[k] += eps
        Q[1].flat[k] -= eps
        F = calc.forces_batch(Q, atoms)
        num[:, k] = -(F[0] - F[1]).ravel() / (2 * eps)
    scale = np.max(np.abs(H))
    assert scale > 1e-3
    np.testing.assert_allclose(H, H.T, rtol=0, atol=1e-14 * scale)
    np.testing.assert_allclose(H, num, rtol=0, atol=1e-7 * scale)


def test_hessian_rejects_wrong_shapes_and_missing_atoms():
    calc = PolynomialPairPotential([0.0, 1.0])
    with pytest.raises(ValueError, match="needs `atoms`"):
        calc.hessian(np.zeros((2, 3)))
    atoms = Atoms("Ar2", positions=[[0, 0, 0], [1, 0, 0]])
    with pytest.raises(ValueError, match=r"`Q` must have shape \(2, 3\)"):
        calc.hessian(np.zeros((3, 3)), atoms)


def test_check_state_answers_as_ase_does_and_skips_recomputing_unchanged_atoms():
    """The calculator's fast answers (nothing changed; only the positions changed) must be
    ASE's answer (compare_atoms) for every kind of change, a move within ASE's tolerance and
    two changes at once included, and a cached property read must not recompute."""
    from ase.calculators.calculator import compare_atoms
    atoms = bulk("Ar", "sc", a=3.5) * (3, 3, 3)
    atoms.rattle(0.05, seed=1)
    calc = PolynomialPairPotential.soft_sphere(0.1, 4.0)
    atoms.calc = calc
    atoms.get_forces()
    calls = []
    original = calc.calculate
    calc.calculate = lambda *a, **k: (calls.append(1), original(*a, **k))
    atoms.get_potential_energy()
    atoms.get_forces()
    assert calls == []

    def mutations():
        yield "nothing", lambda a: None
        yield "momenta only", lambda a: a.set_momenta(np.ones((len(a), 3)))
        yield "one-ulp move (within ASE's tolerance)", lambda a: a.positions.__setitem__(
            (0, 0), np.nextafter(a.positions[0, 0], np.inf))
        yield "move", lambda a: a.positions.__setitem__((1, 2), a.positions[1, 2] + 1e-3)
        yield "numbers", lambda a: a.numbers.__setitem__(0, 10)
        yield "cell", lambda a: a.set_cell(a.cell * 1.01)
        yield "pbc", lambda a: a.set_pbc([True, False, True])
        yield "charges", lambda a: a.set_initial_charges(np.full(len(a), 0.1))
        yield "magmoms", lambda a: a.set_initial_magnetic_moments(np.zeros(len(a)))
        yield "move and cell", lambda a: (a.positions.__setitem__((2, 0), 0.5), a.set_cell(a.cell * 2))

    for label, change in mutations():
        other = atoms.copy()
        change(other)
        assert sorted(calc.check_state(other)) == sorted(compare_atoms(calc.atoms, other)), label
    calc.ignored_changes = {"initial_charges"}
    other = atoms.copy()
    other.set_initial_charges(np.full(len(other), 0.1))
    assert calc.check_state(other) == []
