"""Rigid bonds of ASE (``FixBondLengths``, ``FixBondLength``) inside the HBVM step.

Glue between :class:`hbvm_md.ase.HBVMDynamics` and the constrained step of
:mod:`integrators.holonomic`: it reads the bonds of the atoms' ``FixBondLengths`` constraints
(``FixBondLength(a, b)`` is one of them; ASE's rigid water ``TIP3P``/``TIP4P`` scenes use them on
the O-H, O-H and H-H pairs of each molecule), their minimum-image lattice offsets, the masses
(``FixAtoms`` atoms get an infinite mass: they never move), and calls the stage forces through
the same calculator adapter as the unconstrained step.  No numerics here.

What the step guarantees (see :mod:`integrators.holonomic`): the bond lengths at every step to
round-off, order 2s, and the energy of the constrained system conserved as HBVM(k, s) conserves
it without constraints (to the quadrature error of the potential's line integral).
"""
from __future__ import annotations

import numpy as np
from ase.constraints import FixAtoms, FixBondLengths
from ase.geometry import find_mic

from integrators import NonFiniteError, StepError
from integrators.holonomic import CONSTRAINT_RTOL, BondConstraints, HolonomicHBVM

from .atoms_system import _AtomsSystem, calculator_cache
from .constraints import AtomsConstraints

#: ASE constraints built on rigid bonds that the constrained step does not take (yet)
REFUSED = {"FixLinearTriatomic": "its central atom is a linear (vector) constraint on the two "
                                 "outer atoms, which the bond-only step does not model"}


def bond_constraints(atoms) -> list:
    """The atoms' ``FixBondLengths`` constraints (``FixBondLength`` builds one); [] if none."""
    return [c for c in atoms.constraints if isinstance(c, FixBondLengths)]


def other_constraints(atoms) -> list:
    """The atoms' constraints but their rigid bonds (the linear ones and the energy terms of
    :mod:`hbvm_md.ase.constraints`)."""
    return [c for c in atoms.constraints if not isinstance(c, FixBondLengths)]


def fixed_indices(atoms) -> np.ndarray:
    """Sorted indices of the atoms a ``FixAtoms`` holds (they get an infinite mass here)."""
    fixed = set()
    for c in atoms.constraints:
        if isinstance(c, FixAtoms):
            fixed.update(int(i) for i in c.get_indices())
    return np.array(sorted(fixed), dtype=int)


def check_supported(atoms) -> None:
    """ValueError naming the class for a constraint the constrained step does not take."""
    for c in atoms.constraints:
        if not isinstance(c, (FixAtoms, FixBondLengths)):
            name = type(c).__name__
            why = REFUSED.get(name, "it is not a rigid bond")
            raise ValueError(f"HBVMDynamics with rigid bonds takes FixBondLengths / FixBondLength "
                             f"and FixAtoms only (got {name}: {why}); use VelocityVerlet for it")


def _bonds(atoms):
    """(pairs (P, 2), lengths (P,)) of every FixBondLengths; lengths initialised as ASE does
    (minimum-image distances at the current positions, stored on the constraint) when unset."""
    pairs, lengths = [], []
    for c in bond_constraints(atoms):
        if c.bondlengths is None:
            c.bondlengths = c.initialize_bond_lengths(atoms)
        pairs.append(np.asarray(c.pairs, dtype=np.int64).reshape(-1, 2))
        lengths.append(np.asarray(c.bondlengths, dtype=float).reshape(-1))
    return np.concatenate(pairs), np.concatenate(lengths)


def lattice_offsets(atoms, pairs: np.ndarray) -> np.ndarray:
    """o_a (P, 3): whole lattice vectors that make q_i - q_j + o_a the minimum-image bond
    vector at the current positions (zero without periodic boundaries).  Constant over a step:
    ASE's MD never wraps positions."""
    pos = atoms.get_positions()
    r = pos[pairs[:, 0]] - pos[pairs[:, 1]]
    if not atoms.pbc.any():
        return np.zeros_like(r)
    d, _ = find_mic(r, atoms.cell, atoms.pbc)
    n = np.rint(np.linalg.solve(atoms.cell.array.T, (d - r).T).T)     # integer cell shifts
    return n @ atoms.cell.array


class HolonomicAtoms:
    """The constrained step of one :class:`HBVMDynamics` (built from the atoms, rebuilt by the
    dynamics when they change)."""

    def __init__(self, atoms, method, system, fixed: np.ndarray):
        check_supported(atoms)
        pairs, lengths = _bonds(atoms)
        n = len(atoms)
        masses = np.asarray(atoms.get_masses(), dtype=float).copy()
        masses[fixed] = np.inf
        self.system = system
        self.constraints = BondConstraints(pairs, lengths, n)
        self.stepper = HolonomicHBVM(method, self.constraints, masses, self._forces)
        self.key = (pairs.tobytes(), lengths.tobytes())

    def _forces(self, U: np.ndarray) -> np.ndarray:
        n = U.shape[0]
        return self.system.forces(U.reshape(n, -1)).reshape(U.shape)

    def start(self, atoms) -> None:
        """Put a start that breaks the bonds onto them (as ASE's RATTLE does in its first
        step) and remove the momenta along the bonds; the step's guess is dropped."""
        self.stepper.reset()
        q = atoms.get_positions()
        offsets = lattice_offsets(atoms, self.constraints.pairs)
        st = self.stepper
        moving = st._moving
        err = np.abs(self.constraints.length_errors(q, offsets[moving] if not moving.all() else offsets))
        if err.size and np.max(err / st.constraints.lengths) > CONSTRAINT_RTOL:
            q = st.project_positions(q, offsets[moving])
            atoms.set_positions(q, apply_constraint=False)
        p, _ = st.project_momenta_onto_bonds(q, atoms.get_momenta(), offsets[moving])
        atoms.set_momenta(p, apply_constraint=False)

    def step(self, atoms, dt: float, t: float):
        """(q1, p1) of one step from the atoms' state; raises a StepError, changing nothing."""
        q, p = atoms.get_positions(), atoms.get_momenta()
        offsets = lattice_offsets(atoms, self.constraints.pairs)
        return self.stepper.step(q, p, dt, offsets=offsets, t=t)


def holonomic_step(dyn):
    """One step of ``dyn`` (an HBVMDynamics whose atoms have FixBondLengths); returns the forces
    at the new positions.  A failed step leaves positions, momenta and the calculator's cached
    results as they were, then raises (h and t in fs)."""
    atoms = dyn.atoms
    fixed = fixed_indices(atoms)
    h = dyn._holonomic
    pairs, lengths = _bonds(atoms)
    q0, p0 = dyn._current_state()
    w = dyn._written
    fresh = (h is None or h.key != (pairs.tobytes(), lengths.tobytes()) or w is None
             or h.system.calc is not atoms.calc or h.system.n_atoms != len(atoms)
             or not (np.array_equal(w[0], q0) and np.array_equal(w[1], p0))
             or not np.array_equal(w[2], fixed))
    pos0, mom0 = atoms.get_positions(), atoms.get_momenta()
    calc = atoms.calc
    saved_calc = calculator_cache(calc)
    t = dyn.nsteps * dyn.dt
    if fresh:
        dyn._check_atoms(atoms)
        if h is not None:
            dyn._stage_total += h.system.stage_evaluations
        system = _AtomsSystem(atoms, AtomsConstraints(atoms, other_constraints(atoms)),
                              hasattr(calc, "forces_batch"))
        h = dyn._holonomic = HolonomicAtoms(atoms, dyn.method, system, fixed)
    evals = h.system.stage_evaluations
    try:
        if fresh:
            h.start(atoms)
        q1, p1 = h.step(atoms, dyn.dt, t)
        atoms.set_positions(q1, apply_constraint=False)
        atoms.set_momenta(p1, apply_constraint=False)
        forces = atoms.get_forces(md=True)
        if not np.all(np.isfinite(forces)):
            raise NonFiniteError(dyn.dt, 0, "fixed_point", t,
                                   hint="the forces at the new positions are not finite; "
                                        "try a smaller timestep")
    except BaseException as err:
        h.system.stage_evaluations = evals
        if fresh:
            h.stepper.reset()
        atoms.set_positions(pos0, apply_constraint=False)
        atoms.set_momenta(mom0, apply_constraint=False)
        if saved_calc is not None:
            calc.atoms, calc.results = saved_calc
        if isinstance(err, StepError):
            raise dyn._in_fs(err) from None
        raise
    dyn._written = (*dyn._current_state(), fixed)
    return forces
