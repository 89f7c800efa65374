"""HBVMDynamics with rigid linear molecules (FixLinearTriatomic), FixCom beside rigid bonds,
and the constraint sets it must refuse or handle by name (issue 47, item 7)."""
import numpy as np
import pytest
from ase import Atoms, units
from ase.calculators.acn import ACN, m_me, r_cn, r_mec
from ase.calculators.emt import EMT
from ase.calculators.lj import LennardJones
from ase.calculators.tip3p import TIP3P
from ase.constraints import (FixAtoms, FixBondLengths, FixCom, FixedPlane, FixLinearTriatomic,
                             FixSymmetry)
from ase.data import s22

from hbvm_md.ase import HBVMDynamics


def acetonitrile_dimer() -> Atoms:
    """ASE's own test_rattle_linear scene: two rigid linear acetonitriles, ACN calculator."""
    dimer = Atoms("CCNCCN", [(-r_mec, 0, 0), (0, 0, 0), (r_cn, 0, 0), (r_mec, 3.7, 0),
                             (0, 3.7, 0), (-r_cn, 3.7, 0)])
    masses = dimer.get_masses()
    masses[::3] = m_me
    dimer.set_masses(masses)
    dimer.set_constraint(FixLinearTriatomic(triples=[(0, 1, 2), (3, 4, 5)]))
    dimer.calc = ACN()
    return dimer


def test_ase_rattle_linear_passes_with_hbvm_and_keeps_the_energy():
    """ASE's test_rattle_linear with HBVMDynamics in VelocityVerlet's place: the same
    assertions (distances to 1e-10, the potential energy's change -0.005 +- 0.001 eV), and
    the total energy to round-off (VelocityVerlet: 4e-7 eV)."""
    dimer = acetonitrile_dimer()
    d1, d2 = dimer[:3].get_all_distances(), dimer[3:].get_all_distances()
    e, E = dimer.get_potential_energy(), dimer.get_total_energy()
    HBVMDynamics(dimer, 2.0 * units.fs).run(100)
    assert np.all(abs(dimer[:3].get_all_distances() - d1) < 1e-10)
    assert np.all(abs(dimer[3:].get_all_distances() - d2) < 1e-10)
    assert abs(dimer.get_potential_energy() - e - -0.005) < 0.001
    assert abs(dimer.get_total_energy() - E) < 1e-12


def test_linear_molecule_across_a_periodic_boundary_stays_rigid():
    dimer = acetonitrile_dimer()
    dimer.set_cell([8.0, 8.0, 8.0])
    dimer.set_pbc(True)
    dimer.calc = ACN(rc=3.9)
    dimer.positions += [1.2, 1.0, 1.0]     # molecule 0 straddles the x = 0 face once wrapped
    dimer.wrap()
    rng = np.random.default_rng(3)
    dimer.set_momenta(rng.normal(size=(6, 3)) * 0.5)
    dyn = HBVMDynamics(dimer, 1.0 * units.fs)
    dyn.run(1)                                # the first step puts the momenta on the molecule
    d1 = dimer[:3].get_all_distances(mic=True)
    E = dimer.get_total_energy()
    dyn.run(30)
    assert np.max(abs(dimer[:3].get_all_distances(mic=True) - d1)) < 1e-12
    assert abs(dimer.get_total_energy() - E) < 1e-10


def water_dimer() -> Atoms:
    a = s22.create_s22_system("Water_dimer")
    a.constraints = FixBondLengths([(3 * i + j, 3 * i + (j + 1) % 3) for i in range(2) for j in range(3)])
    a.calc = TIP3P(rc=9.0)
    return a


def test_fixcom_beside_rigid_bonds_keeps_the_centre_of_mass_and_the_energy():
    atoms = water_dimer()
    atoms.set_constraint([atoms.constraints[0], FixCom()])
    rng = np.random.default_rng(1)
    atoms.set_momenta(rng.normal(size=(6, 3)) * 0.3 + 0.2)     # a drift FixCom removes
    dyn = HBVMDynamics(atoms, 1.0 * units.fs)
    dyn.run(1)
    com, E = atoms.get_center_of_mass(), atoms.get_total_energy()
    dyn.run(40)
    assert np.max(abs(atoms.get_center_of_mass() - com)) < 1e-12
    assert abs(atoms.get_momenta().sum(axis=0)).max() < 1e-12
    assert abs(atoms.get_total_energy() - E) < 1e-9


def test_fixsymmetry_raises_notimplementederror_as_ase_dynamics_do():
    atoms = Atoms("Cu2", positions=[[0, 0, 0], [2.5, 0, 0]])
    atoms.calc = LennardJones()
    # (built without its constructor: it needs spglib to refine the cell, and the refusal
    # looks at the class only)
    atoms.set_constraint(FixSymmetry.__new__(FixSymmetry))
    with pytest.raises(NotImplementedError, match="constraint FixSymmetry"):
        HBVMDynamics(atoms, 1 * units.fs).run(1)


def test_a_linear_constraint_beside_bonds_is_refused_with_the_reason():
    atoms = water_dimer()
    atoms.set_constraint([atoms.constraints[0], FixedPlane(0, [0, 0, 1])])
    with pytest.raises(ValueError, match=r"got FixedPlane: the bonds' constraint forces would "
                                         r"push its atoms off the plane.*remove it"):
        HBVMDynamics(atoms, 1 * units.fs)
    atoms.set_constraint(atoms.constraints[0])         # the way out: runs
    HBVMDynamics(atoms, 1 * units.fs).run(2)


def test_bonds_between_fixed_atoms_hold_by_themselves():
    atoms = Atoms("Cu5", positions=[[0, 0, 0], [2.5, 0, 0], [0, 2.5, 0], [2.6, 2.4, 0.1],
                                    [1.3, 1.2, 2.0]])
    atoms.calc = EMT()
    atoms.set_constraint([FixAtoms([0, 1, 2]), FixBondLengths([(0, 1), (1, 2), (0, 2)])])
    pos = atoms.get_positions()
    HBVMDynamics(atoms, 2 * units.fs).run(3)
    assert np.array_equal(atoms.positions[:3], pos[:3])
    assert not np.array_equal(atoms.positions[3:], pos[3:])


def test_dependent_bonds_are_named_and_removing_one_runs():
    atoms = Atoms("Cu4", positions=[[0, 0, 0], [2.5, 0, 0], [0, 2.5, 0], [2.5, 2.5, 0]])
    atoms.calc = EMT()
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    atoms.set_constraint(FixBondLengths(pairs))
    with pytest.raises(ValueError, match=r"rigid bonds \(0, 1\), .*\(2, 3\) are not independent "
                                         r"\(.*rank 5 < 6.*Remove redundant bonds"):
        HBVMDynamics(atoms, 2 * units.fs).run(1)
    atoms.set_constraint(FixBondLengths(pairs[:-1]))    # the way out: five bonds
    HBVMDynamics(atoms, 2 * units.fs).run(2)


def test_a_fixed_atom_inside_a_linear_molecule_is_refused():
    dimer = acetonitrile_dimer()
    dimer.set_constraint([dimer.constraints[0], FixAtoms([1])])
    with pytest.raises(ValueError, match=r"FixAtoms holds atom 1 of a FixLinearTriatomic.*"
                                         r"remove that atom from FixAtoms"):
        HBVMDynamics(dimer, 1 * units.fs).run(1)
    dimer.set_constraint([dimer.constraints[0], FixAtoms([])])     # the way out
    HBVMDynamics(dimer, 1 * units.fs).run(1)


def test_a_bond_into_a_linear_molecule_and_fixcom_with_fixatoms_are_refused():
    dimer = acetonitrile_dimer()
    linear = dimer.constraints[0]
    dimer.set_constraint([linear, FixBondLengths([(2, 3)])])
    with pytest.raises(ValueError, match=r"bond \(2, 3\) joins an atom of a FixLinearTriatomic "
                                         r"molecule.*remove that bond"):
        HBVMDynamics(dimer, 1 * units.fs)
    water = water_dimer()
    bonds = water.constraints[0]
    water.set_constraint([bonds, FixCom(), FixAtoms([0])])
    with pytest.raises(ValueError, match=r"FixCom or FixAtoms, not both.*remove one of them"):
        HBVMDynamics(water, 1 * units.fs)
    water.set_constraint([bonds, FixAtoms([0])])                 # the way out
    HBVMDynamics(water, 1 * units.fs).run(1)


def lj_molecules(name: str) -> Atoms:
    """Four rigid molecules under ASE's LennardJones, which does not exclude a molecule's own
    pairs (sigma 3 A against bonds of 1 A: 1e4-1e5 eV/A along the bonds): CO2 as
    FixLinearTriatomic, water as FixBondLengths on its three pairs (issue 58, item 5)."""
    from ase.build import molecule
    atoms = Atoms()
    for off in [(0, 0, 0), (4.5, 0, 0), (0, 4.5, 0), (4.5, 4.5, 0.5)]:
        m = molecule(name)
        m.translate(off)
        atoms += m
    if name == "CO2":       # ASE's CO2: C, O, O
        atoms.set_constraint(FixLinearTriatomic(triples=[(3 * i + 1, 3 * i, 3 * i + 2)
                                                         for i in range(4)]))
    else:
        atoms.set_constraint(FixBondLengths([(3 * i + a, 3 * i + b) for i in range(4)
                                             for a, b in ((0, 1), (0, 2), (1, 2))]))
    atoms.calc = LennardJones(sigma=3.0, epsilon=0.01, rc=10.0)
    rng = np.random.default_rng(1)
    atoms.set_momenta(rng.normal(size=(12, 3)) * np.sqrt(atoms.get_masses())[:, None] * 0.01)
    return atoms


@pytest.mark.parametrize("name", ["CO2", "H2O"])
def test_rigid_molecules_under_a_pair_potential_that_pushes_along_their_bonds(name):
    """The full forces make the iteration run away at its second iteration; the step then
    integrates their part across the bonds (the constraint forces absorb the rest), keeps the
    bonds and the energy, and says so in todict()."""
    from ase.md.verlet import VelocityVerlet
    atoms = lj_molecules(name)
    d0 = atoms.get_all_distances()
    from hbvm_md.ase.holonomic import BondForcesAbsorbedWarning
    dyn = HBVMDynamics(atoms, timestep=2 * units.fs, s=2, k=3)
    E0 = atoms.get_total_energy()
    with pytest.warns(BondForcesAbsorbedWarning, match=r"the rigid-bond step's iteration on the "
                      r"full forces failed at t=0 fs, so from this step on it integrates the "
                      r"forces' part across the bonds .* otherwise the timestep is too large") as w:
        dyn.run(20)
    assert len(w) == 1                          # once, not at every step
    assert dyn.todict()["bond_forces_absorbed"] is True
    assert abs(atoms.get_total_energy() - E0) < 1e-8 * abs(E0)
    bonded = [(3 * i + a, 3 * i + b) for i in range(4) for a, b in ((0, 1), (0, 2), (1, 2))]
    d1 = atoms.get_all_distances()
    assert max(abs(d1[a, b] - d0[a, b]) for a, b in bonded) < 1e-10
    assert np.max(np.abs(d1 - d0)) > 1e-3           # the molecules moved
    if name == "CO2":           # RATTLE runs this scene too; HBVM keeps its energy far better
        vv = lj_molecules(name)
        E0v = vv.get_total_energy()
        VelocityVerlet(vv, 2 * units.fs).run(20)
        assert abs(atoms.get_total_energy() - E0) < 1e-3 * abs(vv.get_total_energy() - E0v)
