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
