"""HBVMDynamics with ASE's constraints (issue 35, items 2 and 7): linear constraints by
projection (FixAtoms, FixCom, FixSubsetCom, FixedPlane, FixedLine, FixCartesian), Hookean and
ExternalForce as terms of H, the rest refused by name.  Scenes in the spirit of ASE's own
constraint tests (ase/test/constraints), with HBVMDynamics where they use VelocityVerlet."""
import numpy as np
import pytest
from ase import Atom, Atoms, units
from ase.build import fcc100, fcc110
from ase.calculators.emt import EMT
from ase.calculators.lj import LennardJones
from ase.cluster.cubic import FaceCenteredCubic
from ase.constraints import (ExternalForce, FixAtoms, FixBondLength,
                             FixCartesian, FixCom, FixedLine, FixedMode, FixedPlane,
                             FixLinearTriatomic, FixSubsetCom, Hookean)
from ase.md.verlet import VelocityVerlet

from hbvm_md import HBVMDynamics
from hbvm_md.ase.constraints import LinearProjector, classify
from hbvm_md.reports.md_comparison import default_cluster, maxwell_boltzmann
from systems import PolynomialPairPotential


def _energies(dyn, atoms):
    E = []
    dyn.attach(lambda: E.append(atoms.get_potential_energy() + atoms.get_kinetic_energy()))
    return E


def _copper_cluster(T=300.0, seed=1):
    """19 atoms of ASE's FaceCenteredCubic copper (the MD tutorial's construction), EMT."""
    atoms = FaceCenteredCubic("Cu", [(1, 0, 0), (1, 1, 0), (1, 1, 1)], [2, 2, 2],
                              latticeconstant=3.61)
    maxwell_boltzmann(atoms, T, seed)
    atoms.calc = EMT()
    return atoms


# -- the projector by itself ------------------------------------------------------------------
def _random_atoms(n=7, seed=0):
    rng = np.random.default_rng(seed)
    atoms = Atoms(f"H{n}", positions=rng.normal(size=(n, 3)))
    atoms.set_masses(rng.uniform(1.0, 60.0, n))
    return atoms, rng


@pytest.mark.parametrize("constraints", [
    [FixCom()],
    [FixedPlane([0, 2], [0.2, 0.5, 1.0]), FixedLine([1], [1, -1, 0.3])],
    [FixCom(), FixedPlane([0, 1, 2], [0, 0, 1]), FixCartesian([3], [True, False, True])],
    [FixSubsetCom([1, 2, 4]), FixAtoms([0]), FixedLine([2], [0, 1, 0])],
    [FixCom(), FixedPlane(list(range(7)), [0, 0, 1])],       # the COM's z twice: redundant
])
def test_projector_is_the_mass_weighted_projection_onto_the_constraints(constraints):
    """P is idempotent, its image keeps every constraint (A M^-1 P F = 0: no constrained
    coordinate accelerates), and it is M^-1-self-adjoint (P^T M^-1 = M^-1 P), the property
    that makes the projected force the gradient of V restricted to the subspace."""
    atoms, rng = _random_atoms()
    m = atoms.get_masses()
    P = LinearProjector(constraints, m)
    Pm = P.matrix()
    Minv = np.diag(np.repeat(1.0 / m, 3))
    np.testing.assert_allclose(Pm @ Pm, Pm, atol=1e-13)
    np.testing.assert_allclose(Pm.T @ Minv, Minv @ Pm, atol=1e-13)
    F = rng.normal(size=(3, 7, 3))
    P.apply(F)
    a = F / m[None, :, None]                                   # accelerations
    for c in constraints:
        if isinstance(c, FixCom):
            idx = np.arange(7) if type(c) is FixCom else c.index
            np.testing.assert_allclose((m[idx, None] * a[:, idx]).sum(axis=1), 0.0, atol=1e-12)
        elif isinstance(c, FixedPlane):
            np.testing.assert_allclose(a[:, c.index] @ c.dir, 0.0, atol=1e-13)
        elif isinstance(c, FixedLine):
            along = (a[:, c.index] @ c.dir)[..., None] * c.dir
            np.testing.assert_allclose(a[:, c.index], along, atol=1e-13)
        elif isinstance(c, FixCartesian):
            assert np.all(a[:, c.index][..., c.mask] == 0.0)      # exactly: axis-aligned
        elif isinstance(c, FixAtoms):
            assert np.all(a[:, c.index] == 0.0)


def test_constraints_are_sorted_into_kinds():
    assert [classify(c) for c in (FixAtoms([0]), FixCom(), FixedPlane(0, [0, 0, 1]),
                                  FixedLine(0, [0, 0, 1]), FixCartesian([0]),
                                  FixSubsetCom([0, 1]))] == ["linear"] * 6
    assert classify(Hookean(0, 1, 1.0, 1.0)) == classify(ExternalForce(0, 1, 1.0)) == "energy"
    assert classify(FixBondLength(0, 1)) == classify(FixLinearTriatomic([(0, 1, 2)])) == "holonomic"
    assert classify(FixedMode(np.ones((2, 3)))) == "unsupported"


# (FixBondLength(s) and FixLinearTriatomic run in the constrained step: tests/test_ase_holonomic.py
# and tests/test_ase_rigid_molecules.py, where a linear constraint beside them is refused by name)
@pytest.mark.parametrize("constraint, named", [
    (FixedMode(np.ones((4, 3))), r"does not support the constraint FixedMode; supported: FixAtoms"),
])
def test_what_cannot_run_is_refused_by_its_own_name(constraint, named):
    atoms = Atoms("H4", positions=[[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1.5, 0]])
    atoms.calc = LennardJones()
    atoms.set_constraint(constraint)
    with pytest.raises(ValueError, match=named):
        HBVMDynamics(atoms, 1 * units.fs)
    atoms.set_constraint()
    dyn = HBVMDynamics(atoms, 1 * units.fs)
    atoms.set_constraint(constraint)                  # added later: refused at the next step
    with pytest.raises(ValueError, match=named):
        dyn.run(1)


# -- must show: EMT copper at 4 fs -------------------------------------------------------------
@pytest.mark.parametrize("kind", ["FixCom", "FixedPlane", "Hookean"])
def test_emt_copper_cluster_keeps_constraint_and_energy(kind):
    """Issue 35, must show: FixCom, FixedPlane and Hookean on an EMT copper cluster at 4 fs,
    the constraint kept to 1e-10 A and the energy to 1e-8 eV per atom.  FixCom: the cluster
    drifts at 1e-3 A/fs to begin with (the drift is projected out).  Hookean: a pair spring
    (stretched all along) and a tether to a point (r_t = 0): smooth terms of H."""
    atoms = _copper_cluster()
    n = len(atoms)
    x0 = atoms.get_positions()
    if kind == "FixCom":
        atoms.set_momenta(atoms.get_momenta() + atoms.get_masses()[:, None] * [0.01, 0, 0.005])
        cons = [FixCom()]
    elif kind == "FixedPlane":
        cons = [FixedPlane(range(0, n, 2), [0.0, 0.6, 0.8])]
    else:
        cons = [Hookean(0, 1, k=1.0, rt=2.0), Hookean(2, x0[2] + [0.3, 0.0, 0.0], k=1.0, rt=0.0)]
    atoms.set_constraint(cons)
    com0 = atoms.get_center_of_mass()
    dyn = HBVMDynamics(atoms, 4 * units.fs)
    E = _energies(dyn, atoms)
    dyn.run(25)
    x = atoms.get_positions()
    assert np.ptp(E) / n <= 1e-8
    assert np.max(np.abs(x - x0)) > 0.05                         # it moved
    if kind == "FixCom":
        assert np.max(np.abs(atoms.get_center_of_mass() - com0)) <= 1e-10
        assert np.max(np.abs(atoms.get_momenta().sum(axis=0))) <= 1e-12
    elif kind == "FixedPlane":
        assert np.max(np.abs((x - x0)[::2] @ [0.0, 0.6, 0.8])) <= 1e-10
    else:
        assert atoms.get_distance(0, 1) > 2.0                   # the spring stayed engaged
        hook = sum(c.adjust_potential_energy(atoms) for c in cons)
        assert hook > 1e-3                                       # part of the conserved total


def test_fixcom_on_a_drifting_cluster_follows_the_unconstrained_run_minus_the_drift():
    """FixCom on a drifting cluster (a polynomial pair potential, the compiled path): the run
    is the free run seen from the centre of mass, to 1e-10 A (Galilean invariance), with the
    energy exact to round-off."""
    dt, steps = 10 * units.fs, 40
    atoms, calc = default_cluster(13)
    maxwell_boltzmann(atoms, 300.0, 0)
    atoms.set_momenta(atoms.get_momenta() - atoms.get_momenta().sum(axis=0) / len(atoms))
    free = atoms.copy()
    free.calc = PolynomialPairPotential(calc.coefficients)
    v = np.array([0.02, -0.01, 0.03])
    free.set_momenta(free.get_momenta() + free.get_masses()[:, None] * v)
    held = atoms.copy()
    held.calc = PolynomialPairPotential(calc.coefficients)
    held.set_momenta(free.get_momenta())
    held.set_constraint(FixCom())
    c0 = held.get_center_of_mass()
    HBVMDynamics(free, dt).run(steps)
    dyn = HBVMDynamics(held, dt)
    E = _energies(dyn, held)
    dyn.run(steps)
    np.testing.assert_allclose(held.get_center_of_mass(), c0, rtol=0, atol=1e-12)
    moved = free.get_positions() - free.get_center_of_mass() + c0
    np.testing.assert_allclose(held.get_positions(), moved, rtol=0, atol=1e-10)
    assert np.ptp(E) / abs(E[0]) <= 1e-13


def test_mixed_linear_constraints_on_the_compiled_and_the_generic_path():
    """A quartic cluster with FixCom, FixedPlane, FixedLine, FixCartesian and FixAtoms: the
    compiled path (forces_batch writing into the step's array, projected there) and the
    stage-by-stage path of any calculator give the same run; every constraint holds to
    round-off and H, a polynomial on the subspace, is exact."""
    dt, steps = 10 * units.fs, 30
    atoms, calc = default_cluster(20)
    maxwell_boltzmann(atoms, 600.0, 2)
    cons = [FixCom(), FixedPlane([1, 2], [0.3, 0.4, 0.5]), FixedLine([3], [1, 1, 1]),
            FixCartesian([4, 5], [False, True, False]), FixAtoms([6])]
    runs = []
    for batched in (True, False):
        a = atoms.copy()
        a.calc = (PolynomialPairPotential if batched else _Plain)(calc.coefficients)
        a.set_constraint([c.copy() for c in cons])
        x0 = a.get_positions()
        com0 = a.get_center_of_mass()
        dyn = HBVMDynamics(a, dt)
        E = _energies(dyn, a)
        dyn.run(steps)
        x = a.get_positions()
        d = x - x0
        assert np.max(np.abs(a.get_center_of_mass() - com0)) <= 1e-12
        assert np.max(np.abs(d[[1, 2]] @ [0.3, 0.4, 0.5])) <= 1e-12
        assert np.max(np.abs(np.cross(d[3], [1, 1, 1]))) <= 1e-12
        assert np.all(d[[4, 5], 1] == 0.0) and np.all(d[6] == 0.0)
        assert np.ptp(E) / abs(E[0]) <= 1e-12
        runs.append(x)
    np.testing.assert_allclose(runs[0], runs[1], rtol=0, atol=1e-10)


class _Plain(PolynomialPairPotential):
    """The same potential without forces_batch: the stage-by-stage path of any calculator."""
    forces_batch = property(lambda self: (_ for _ in ()).throw(AttributeError("forces_batch")))


def test_fixedplane_slab():
    """A copper (100) slab with its bottom layer fixed and its top layer held in its plane by
    FixedPlane (ASE's fixed-plane scene, with dynamics): the plane and the fixed atoms hold,
    the energy is conserved far below VelocityVerlet's at the same step."""
    slab = fcc100("Cu", (2, 2, 3), vacuum=5.0)
    maxwell_boltzmann(slab, 500.0, 4)
    z = slab.positions[:, 2]
    bottom, top = np.flatnonzero(z < z.min() + 0.1), np.flatnonzero(z > z.max() - 0.1)
    errors = {}
    for cls in (HBVMDynamics, VelocityVerlet):
        a = slab.copy()
        a.calc = EMT()
        a.set_constraint([FixAtoms(bottom), FixedPlane(top, [0, 0, 1])])
        if cls is HBVMDynamics:
            x0 = a.get_positions()
        dyn = cls(a, 4 * units.fs)
        E = _energies(dyn, a)
        dyn.run(20)
        errors[cls] = np.ptp(E) / len(a)
        if cls is HBVMDynamics:
            x = a.get_positions()
            assert np.all(x[bottom] == x0[bottom])
            assert np.max(np.abs(x[top, 2] - x0[top, 2])) <= 1e-10
            assert np.max(np.abs(x[top, :2] - x0[top, :2])) > 1e-3
    assert errors[HBVMDynamics] <= 1e-8 and errors[HBVMDynamics] < 1e-3 * errors[VelocityVerlet]


def test_ases_hookean_scene_with_hbvm():
    """ASE's Hookean test (ase/test/constraints/test_hookean.py) with HBVMDynamics where it
    runs VelocityVerlet: a Pt(110) slab, fixed, with a Cu2 adsorbate held by a pair spring and
    a plane; the bond and the height stay bounded, and the energy, Hookean terms included,
    changes far less than VelocityVerlet's (the springs engage and release: H is only C^1
    there, which bounds any method's accuracy)."""
    atoms = fcc110("Pt", (2, 2, 2), vacuum=7.0)
    atoms.extend(Atoms([Atom("Cu", atoms[7].position + (0.0, 0.0, 2.5)),
                        Atom("Cu", atoms[7].position + (0.0, 0.0, 5.0))]))
    p = atoms.get_momenta()
    p[9, 2] += 20.0
    p[9, 1] += 2.0
    atoms.set_momenta(p)
    spread = {}
    for cls in (HBVMDynamics, VelocityVerlet):
        a = atoms.copy()
        a.calc = EMT()
        a.set_constraint([FixAtoms([i for i in range(len(a)) if a[i].symbol == "Pt"]),
                          Hookean(a1=8, a2=9, rt=2.6, k=15.0),
                          Hookean(a1=8, a2=(0.0, 0.0, 1.0, -15.0), k=15.0)])
        dyn = cls(a, 2.0 * units.fs)
        E = _energies(dyn, a)
        dyn.run(25)
        spread[cls] = np.ptp(E)
        assert a.get_distance(8, 9) < 3.0 and a[9].z < 15.0
    assert spread[HBVMDynamics] < 0.05 * spread[VelocityVerlet]


def test_external_force_is_a_term_of_the_energy():
    """ExternalForce pulling two atoms of a Lennard-Jones dimer apart: the energy with its
    term -f |r| (ASE's adjust_potential_energy) is conserved to round-off's neighbourhood."""
    atoms = Atoms("Ar2", positions=[[0, 0, 0], [0, 0, 3.8]])
    atoms.calc = LennardJones(epsilon=0.0104, sigma=3.4, rc=12.0)
    atoms.set_constraint(ExternalForce(0, 1, 0.005))
    dyn = HBVMDynamics(atoms, 5 * units.fs)
    E = _energies(dyn, atoms)
    dyn.run(60)
    assert abs(atoms.get_distance(0, 1) - 3.8) > 0.01
    assert np.ptp(E) <= 1e-10


def test_a_constraint_changed_in_place_rebuilds_the_step():
    """FixedPlane's direction changed between two runs: the new plane holds (the step does
    not keep the old projector)."""
    atoms, calc = default_cluster(13)
    maxwell_boltzmann(atoms, 300.0, 1)
    c = FixedPlane([0, 1], [0, 0, 1])
    atoms.set_constraint(c)
    dyn = HBVMDynamics(atoms, 10 * units.fs)
    dyn.run(5)
    c.dir = np.array([1.0, 0.0, 0.0])
    x1 = atoms.get_positions()
    dyn.run(5)
    d = atoms.get_positions() - x1
    assert np.max(np.abs(d[[0, 1], 0])) <= 1e-13 and np.max(np.abs(d[[0, 1], 2])) > 1e-4
