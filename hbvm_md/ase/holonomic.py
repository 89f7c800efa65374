"""Rigid bonds of ASE (``FixBondLengths``, ``FixBondLength``, ``FixLinearTriatomic``) inside
the HBVM step.

Glue between :class:`hbvm_md.ase.HBVMDynamics` and the constrained step of
:mod:`integrators.holonomic`: it reads the bonds of the atoms' ``FixBondLengths`` constraints
(``FixBondLength(a, b)`` is one of them; ASE's rigid water ``TIP3P``/``TIP4P`` scenes use them on
the O-H, O-H and H-H pairs of each molecule), their minimum-image lattice offsets, the masses
(``FixAtoms`` atoms get an infinite mass: they never move), and calls the stage forces through
the same calculator adapter as the unconstrained step.  No numerics here.

Rigid linear molecules (``FixLinearTriatomic``: n--o--m, the central atom o at a fixed fraction
of the n-m axis, ASE's acetonitrile and CO2 scenes) are a linear change of coordinates away
from a rigid diatomic (:class:`LinearMolecules`): with Y the molecule's centre of mass and
r = q_n - q_m, every atom is q_i = Y + c_i r (sum m_i c_i = 0), the kinetic energy is
M |Y'|^2 / 2 + I |r'|^2 / 2 (I = sum m_i c_i^2), and the two pseudo-atoms
y_1,2 = Y +- (L / 2) r of mass M / 2 each, L = sqrt(4 I / M), have the same kinetic energy and
one bond |y_1 - y_2| = L d_nm.  The constrained step integrates the pseudo-atoms (forces
J^T F, J the linear map y -> q); a Runge-Kutta method commutes with linear changes of
variables, so what the step guarantees below holds for the molecule as it does for a bond.

What the step guarantees (see :mod:`integrators.holonomic`): the bond lengths at every step to
round-off, order 2s, and the energy of the constrained system conserved as HBVM(k, s) conserves
it without constraints (to the quadrature error of the potential's line integral).

``FixCom`` runs beside the bonds (the bond forces are internal: the centre-of-mass force is
removed from the calculator's alone); the other linear constraints and the energy terms are
refused with the reason (:func:`check_supported`).
"""
from __future__ import annotations

import warnings

import numpy as np
from ase import units
from ase.constraints import FixAtoms, FixBondLengths, FixCom, FixLinearTriatomic
from ase.geometry import find_mic

from integrators import NonFiniteError, StepError
from integrators.holonomic import CONSTRAINT_RTOL, BondConstraints, HolonomicHBVM

from .atoms_system import _AtomsSystem, calculator_cache
from .constraints import AtomsConstraints, UnsupportedConstraintError

#: why a constraint beside rigid bonds is refused (the others are "not a rigid bond")
REFUSED = {
    "FixedPlane": "the bonds' constraint forces would push its atoms off the plane; both kinds "
                  "of multiplier would have to be solved together, which the step does not do",
    "FixedLine": "the bonds' constraint forces would push its atoms off the line; both kinds of "
                 "multiplier would have to be solved together, which the step does not do",
    "FixCartesian": "the bonds' constraint forces would move its fixed coordinates; both kinds "
                    "of multiplier would have to be solved together, which the step does not do",
    "FixSubsetCom": "a bond across the subset's edge pulls on its centre of mass; both kinds of "
                    "multiplier would have to be solved together, which the step does not do",
    "Hookean": "the constrained step has no energy terms yet",
    "ExternalForce": "the constrained step has no energy terms yet",
}
HOLONOMIC_CLASSES = (FixBondLengths, FixLinearTriatomic)


class BondForcesAbsorbedWarning(RuntimeWarning):
    """HBVMDynamics' rigid-bond step integrates the forces' part across the bonds from now on:
    its iteration on the full forces failed (:mod:`integrators.holonomic`, "Forces along the
    bonds"); warned once per dynamics."""

#: a FixLinearTriatomic's central atom farther than this (relative to the n-m distance) off the
#: n-m axis at the start is refused: the three atoms are not in a line
LINEAR_RTOL = 1e-8


def bond_constraints(atoms) -> list:
    """The atoms' rigid-bond constraints (``FixBondLengths``, which ``FixBondLength`` builds,
    and ``FixLinearTriatomic``); [] if none."""
    return [c for c in atoms.constraints if isinstance(c, HOLONOMIC_CLASSES)]


def other_constraints(atoms) -> list:
    """The atoms' constraints but their rigid bonds (the linear ones and the energy terms of
    :mod:`hbvm_md.ase.constraints`)."""
    return [c for c in atoms.constraints if not isinstance(c, HOLONOMIC_CLASSES)]


def fixed_indices(atoms) -> np.ndarray:
    """Sorted indices of the atoms a ``FixAtoms`` holds (they get an infinite mass here)."""
    fixed = set()
    for c in atoms.constraints:
        if isinstance(c, FixAtoms):
            fixed.update(int(i) for i in c.get_indices())
    return np.array(sorted(fixed), dtype=int)


def check_supported(atoms) -> None:
    """Refuse (:class:`UnsupportedConstraintError`, a NotImplementedError and a ValueError)
    a constraint the constrained step does not take, naming the class and the reason."""
    for c in atoms.constraints:
        if type(c) in (FixAtoms, FixBondLengths, FixLinearTriatomic, FixCom):
            continue
        name = type(c).__name__
        why = REFUSED.get(name, "it is not a rigid bond")
        raise UnsupportedConstraintError(
            f"HBVMDynamics with rigid bonds takes FixBondLengths / FixBondLength, "
            f"FixLinearTriatomic, FixAtoms and FixCom (got {name}: {why}); remove it, or use "
            f"VelocityVerlet (RATTLE) for this scene")
    if any(type(c) is FixCom for c in atoms.constraints) and fixed_indices(atoms).size:
        raise UnsupportedConstraintError(
            "HBVMDynamics with rigid bonds takes FixCom or FixAtoms, not both (a bond to a "
            "fixed atom pushes on the centre of mass); remove one of them")
    triples = _triples(atoms)[0]
    if triples.size:
        inside = set(triples.ravel().tolist())
        if len(inside) != triples.size:
            raise ValueError("`FixLinearTriatomic` lists an atom in two triples (or twice in "
                             "one); each atom belongs to one linear molecule")
        for c in atoms.constraints:
            if isinstance(c, FixBondLengths):
                touch = [tuple(int(x) for x in pr) for pr in np.asarray(c.pairs).reshape(-1, 2)
                         if inside & set(int(x) for x in pr)]
                if touch:
                    raise UnsupportedConstraintError(
                        f"a FixBondLengths bond {touch[0]} joins an atom of a FixLinearTriatomic "
                        "molecule: the molecule is rigid already and the step does not couple "
                        "it to other bonds; remove that bond")
        held = inside & set(fixed_indices(atoms).tolist())
        if held:
            raise UnsupportedConstraintError(
                f"FixAtoms holds atom {min(held)} of a FixLinearTriatomic molecule, which the "
                "step moves as a whole (as two pseudo-atoms) and cannot pin by one atom; "
                "remove that atom from FixAtoms, or use VelocityVerlet for this scene")


def _triples(atoms):
    """(triples (T, 3) as (n, o, m), bond lengths (T, 2): n-o and o-m) of every
    FixLinearTriatomic, initialised as ASE does when unset."""
    trip, lengths = [], []
    for c in atoms.constraints:
        if isinstance(c, FixLinearTriatomic):
            if c.bondlengths is None:
                c.initialize(atoms)
            trip.append(np.asarray(c.triples, dtype=np.int64).reshape(-1, 3))
            lengths.append(np.asarray(c.bondlengths, dtype=float).reshape(-1, 2))
    if not trip:
        return np.zeros((0, 3), np.int64), np.zeros((0, 2))
    return np.concatenate(trip), np.concatenate(lengths)


class LinearMolecules:
    """Rigid linear triatomics as pseudo-diatomics: the linear map J from the reduced
    coordinates y (every atom but the central ones; atom n's slot holds pseudo-atom 1, atom
    m's pseudo-atom 2) to the positions q, and its transpose for forces and momenta (see the
    module docstring).  Without triples, J is the identity.

    Parameters
    ----------
    triples : (T, 3) int, (n, o, m)
    lengths : (T, 2) float, the n-o and o-m distances
    masses : (N,) float
    """

    def __init__(self, triples: np.ndarray, lengths: np.ndarray, masses: np.ndarray):
        n_atoms = masses.shape[0]
        self.triples = triples
        self.n_atoms = n_atoms
        keep = np.setdiff1d(np.arange(n_atoms), triples[:, 1])
        self.keep = keep
        self.slot = np.full(n_atoms, -1, dtype=np.int64)
        self.slot[keep] = np.arange(keep.size)
        self.n_reduced = keep.size
        m = masses[triples]                                     # (T, 3)
        d_nm = lengths.sum(axis=1)
        a_n, a_m = lengths[:, 1] / d_nm, lengths[:, 0] / d_nm   # q_o = a_n q_n + a_m q_m
        self.a = np.stack([a_n, a_m], axis=1)
        total = m.sum(axis=1)
        c_n = (m[:, 1] * a_m + m[:, 2]) / total                 # sum m_i c_i = 0, c_n - c_m = 1
        c = np.stack([c_n, a_n * c_n + a_m * (c_n - 1.0), c_n - 1.0], axis=1)
        inertia = np.sum(m * c * c, axis=1)
        self.L = np.sqrt(4.0 * inertia / total)
        self.w1 = 0.5 + c / self.L[:, None]                     # q_i = w1_i y1 + w2_i y2
        self.w2 = 0.5 - c / self.L[:, None]
        self.m = m
        self.total = total
        self.masses = masses[keep].copy()
        if triples.size:
            self.masses[self.slot[triples[:, 0]]] = 0.5 * total
            self.masses[self.slot[triples[:, 2]]] = 0.5 * total
        self.pairs = np.stack([self.slot[triples[:, 0]], self.slot[triples[:, 2]]], axis=1)
        self.lengths = self.L * d_nm                            # |y1 - y2|

    def to_atoms(self, y: np.ndarray) -> np.ndarray:
        """q (..., N, 3) = J y for y (..., N_reduced, 3)."""
        q = np.empty(y.shape[:-2] + (self.n_atoms, 3))
        q[..., self.keep, :] = y
        if self.triples.size:
            y1 = y[..., self.pairs[:, 0], :]
            y2 = y[..., self.pairs[:, 1], :]
            for k in range(3):
                q[..., self.triples[:, k], :] = (self.w1[:, k, None] * y1
                                                 + self.w2[:, k, None] * y2)
        return q

    def transpose(self, f: np.ndarray) -> np.ndarray:
        """J^T f (..., N_reduced, 3) for forces or momenta f (..., N, 3)."""
        out = np.array(f[..., self.keep, :])
        if self.triples.size:
            parts = [f[..., self.triples[:, k], :] for k in range(3)]
            out[..., self.pairs[:, 0], :] = sum(self.w1[:, k, None] * parts[k] for k in range(3))
            out[..., self.pairs[:, 1], :] = sum(self.w2[:, k, None] * parts[k] for k in range(3))
        return out

    def reduce_positions(self, q: np.ndarray) -> np.ndarray:
        """y with J y = q when q is a linear molecule (q unwrapped; the central atom's part
        off the axis, if any, is dropped: J y puts it back on the axis)."""
        y = np.array(q[self.keep])
        if self.triples.size:
            qs = q[self.triples]                                  # (T, 3, 3)
            Y = np.einsum("tk,tkd->td", self.m, qs) / self.total[:, None]
            r = qs[:, 0] - qs[:, 2]
            y[self.pairs[:, 0]] = Y + 0.5 * self.L[:, None] * r
            y[self.pairs[:, 1]] = Y - 0.5 * self.L[:, None] * r
        return y

    def momenta_to_atoms(self, py: np.ndarray, masses: np.ndarray) -> np.ndarray:
        """p = M J M_y^-1 p_y: the atoms' momenta of the reduced momenta (the atoms outside
        the molecules keep theirs as they are: a fixed atom's mass is infinite)."""
        p = np.empty((self.n_atoms, 3))
        p[self.keep] = py
        if self.triples.size:
            v1 = py[self.pairs[:, 0]] / self.masses[self.pairs[:, 0], None]
            v2 = py[self.pairs[:, 1]] / self.masses[self.pairs[:, 1], None]
            for k in range(3):
                i = self.triples[:, k]
                p[i] = masses[i, None] * (self.w1[:, k, None] * v1 + self.w2[:, k, None] * v2)
        return p


def _bonds(atoms):
    """(pairs (P, 2), lengths (P,)) of every FixBondLengths; lengths initialised as ASE does
    (minimum-image distances at the current positions, stored on the constraint) when unset."""
    pairs, lengths = [np.zeros((0, 2), np.int64)], [np.zeros(0)]
    for c in atoms.constraints:
        if not isinstance(c, FixBondLengths):
            continue
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
    dynamics when they change), in the reduced coordinates of :class:`LinearMolecules`."""

    def __init__(self, atoms, method, system, fixed: np.ndarray):
        check_supported(atoms)
        pairs, lengths = _bonds(atoms)
        triples, tlengths = _triples(atoms)
        self.atom_masses = np.asarray(atoms.get_masses(), dtype=float).copy()
        self.lin = LinearMolecules(triples, tlengths, self.atom_masses)
        self.atom_pairs = pairs
        masses = self.lin.masses.copy()
        masses[self.lin.slot[fixed]] = np.inf
        self.system = system
        self.constraints = BondConstraints(
            np.concatenate([self.lin.slot[pairs], self.lin.pairs]).astype(np.int64),
            np.concatenate([lengths, self.lin.lengths]), self.lin.n_reduced)
        self.stepper = HolonomicHBVM(method, self.constraints, masses, self._forces)
        self.key = _key(atoms)
        self._shift = np.zeros((len(atoms), 3))
        self._last = None           # (q, p written, y, p_y): the reduced state of the last step

    def _forces(self, U: np.ndarray) -> np.ndarray:
        n = U.shape[0]
        X = self.lin.to_atoms(U) + self._shift
        F = self.system.forces(X.reshape(n, -1)).reshape(X.shape)
        return self.lin.transpose(F)

    def _offsets(self, atoms) -> np.ndarray:
        """The lattice offsets of the bonds (the molecules' pseudo-bonds: none, they are
        unwrapped in the reduced coordinates)."""
        return np.concatenate([lattice_offsets(atoms, self.atom_pairs),
                               np.zeros((len(self.lin.pairs), 3))])

    def _reduced(self, atoms):
        """(y, p_y) of the atoms' state; ``_shift`` the lattice vectors that put each
        molecule's atoms back where the atoms have them."""
        q, p = atoms.get_positions(), atoms.get_momenta()
        if (self._last is not None and np.array_equal(self._last[0], q)
                and np.array_equal(self._last[1], p)):
            return self._last[2], self._last[3]      # no round trip through J between steps
        unwrapped = q.copy()
        t = self.lin.triples
        if t.size and atoms.pbc.any():
            for k in (1, 2):
                d, _ = find_mic(q[t[:, k]] - q[t[:, 0]], atoms.cell, atoms.pbc)
                unwrapped[t[:, k]] = q[t[:, 0]] + d
        self._shift = q - unwrapped
        return self.lin.reduce_positions(unwrapped), self.lin.transpose(p)

    def _write(self, atoms, y, py):
        q = self.lin.to_atoms(y) + self._shift
        p = self.lin.momenta_to_atoms(py, self.atom_masses)
        return q, p

    def start(self, atoms) -> None:
        """Put a start that breaks the bonds onto them (as ASE's RATTLE does in its first
        step) and remove the momenta along the bonds; the step's guess is dropped.  Raises
        ValueError naming a set of bonds whose lengths are not independent."""
        self.stepper.reset()
        self._last = None
        self._check_linear(atoms)
        y, py = self._reduced(atoms)
        st = self.stepper
        moving = st._moving
        offsets = self._offsets(atoms)[moving]
        dependent = st.dependent_bonds(y, offsets)
        if dependent is not None:
            bonds, rank = dependent
            names = [self._name(b) for b in bonds]
            raise ValueError(
                f"the rigid bonds {', '.join(names)} are not independent (their constraint "
                f"Jacobian has rank {rank} < {len(bonds)} at the start: e.g. four "
                "atoms in a plane with all six pairs held, or a bond implied by the others); "
                "the multipliers are then undetermined. Remove redundant bonds (keep a set "
                "whose lengths fix the shape once each)")
        err = np.abs(st.constraints.length_errors(y, offsets))
        if err.size and np.max(err / st.constraints.lengths) > CONSTRAINT_RTOL:
            y = st.project_positions(y, offsets)
        py, _ = st.project_momenta_onto_bonds(y, py, offsets)
        q, p = self._write(atoms, y, py)
        atoms.set_positions(q, apply_constraint=False)
        atoms.set_momenta(p, apply_constraint=False)
        self._last = (atoms.get_positions(), atoms.get_momenta(), y, py)

    def _check_linear(self, atoms) -> None:
        """Refuse (ValueError) a FixLinearTriatomic whose three atoms are not in a line at the
        start: the reduced coordinates would drop the central atom's part off the axis, i.e.
        straighten the molecule without a word."""
        t = self.lin.triples
        if not t.size:
            return
        q = atoms.get_positions()
        r_no, r_nm = q[t[:, 1]] - q[t[:, 0]], q[t[:, 2]] - q[t[:, 0]]
        if atoms.pbc.any():
            r_no, _ = find_mic(r_no, atoms.cell, atoms.pbc)
            r_nm, _ = find_mic(r_nm, atoms.cell, atoms.pbc)
        d_nm = np.linalg.norm(r_nm, axis=1)
        off = np.linalg.norm(np.cross(r_no, r_nm), axis=1) / np.maximum(d_nm, 1e-300)
        bad = np.flatnonzero(off > LINEAR_RTOL * d_nm)
        if bad.size:
            n, o, m = (int(x) for x in t[bad[0]])
            a, b = r_no[bad[0]], r_nm[bad[0]] - r_no[bad[0]]
            angle = np.degrees(np.arccos(np.clip(np.dot(-a, b) / (np.linalg.norm(a)
                                                               * np.linalg.norm(b)), -1, 1)))
            raise ValueError(
                f"FixLinearTriatomic({n}, {o}, {m}): the three atoms are not in a line (atom {o} "
                f"is {off[bad[0]]:.3g} A off the axis through atoms {n} and {m}; the angle "
                f"{n}-{o}-{m} is {angle:.6g} degrees, not 180); the constraint holds a "
                f"linear molecule: put atom {o} on that axis, or hold a bent molecule with "
                f"FixBondLengths on its three pairs")

    def _name(self, b: int) -> str:
        """A bond of the reduced step as the user wrote it."""
        P = len(self.atom_pairs)
        moving = np.flatnonzero(self.stepper._moving)
        b = int(moving[b])
        if b < P:
            return str(tuple(int(x) for x in self.atom_pairs[b]))
        return f"FixLinearTriatomic{tuple(int(x) for x in self.lin.triples[b - P])}"

    def step(self, atoms, dt: float, t: float):
        """(q1, p1) of one step from the atoms' state; raises a StepError, changing nothing."""
        y, py = self._reduced(atoms)
        y1, py1 = self.stepper.step(y, py, dt, offsets=self._offsets(atoms), t=t)
        q1, p1 = self._write(atoms, y1, py1)
        self._pending = (y1, py1)
        return q1, p1

    def written(self, atoms) -> None:
        """The step's state was written to the atoms: remember its reduced form."""
        self._last = (atoms.get_positions(), atoms.get_momenta(), *self._pending)


def _key(atoms) -> tuple:
    """What the constrained step is built from: its bonds and molecules."""
    pairs, lengths = _bonds(atoms)
    triples, tl = _triples(atoms)
    return (pairs.tobytes(), lengths.tobytes(), triples.tobytes(), tl.tobytes())


def holonomic_step(dyn):
    """One step of ``dyn`` (an HBVMDynamics whose atoms have rigid bonds); returns the forces
    at the new positions.  A failed step leaves positions, momenta and the calculator's cached
    results as they were, then raises (h and t in fs)."""
    atoms = dyn.atoms
    check_supported(atoms)
    fixed = fixed_indices(atoms)
    h = dyn._holonomic
    q0, p0 = dyn._current_state()
    w = dyn._written
    fresh = (h is None or h.key != _key(atoms) or w is None
             or h.system.calc is not atoms.calc or h.system.n_atoms != len(atoms)
             or not (np.array_equal(w[0], q0) and np.array_equal(w[1], p0))
             or not np.array_equal(w[2], fixed)
             or not np.array_equal(h.atom_masses, atoms.get_masses()))
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
        absorbing = h is not None and h.stepper.absorbing
        h = dyn._holonomic = HolonomicAtoms(atoms, dyn.method, system, fixed)
        h.stepper.absorbing = absorbing     # the forces' part along the bonds stays absorbed
    evals = h.system.stage_evaluations
    h.system.nonfinite_at = None
    absorbing = h.stepper.absorbing
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
        h.stepper.absorbing = absorbing
        if fresh:
            h.stepper.reset()
            h._last = None
        atoms.set_positions(pos0, apply_constraint=False)
        atoms.set_momenta(mom0, apply_constraint=False)
        if saved_calc is not None:
            calc.atoms, calc.results = saved_calc
        if isinstance(err, StepError):
            err = dyn._calculator_nonfinite(err, h.system, pos0)
            raise dyn._in_fs(err, own_hint=True) from None
        raise
    h.written(atoms)
    dyn._written = (*dyn._current_state(), fixed)
    if h.stepper.absorbing and not absorbing:
        warnings.warn(
            f"HBVMDynamics: the rigid-bond step's iteration on the full forces failed at "
            f"t={t / units.fs:.6g} fs, so from this step on it integrates the forces' part across "
            "the bonds (the constraint forces absorb the rest; dyn.todict()['bond_forces_"
            "absorbed']): the bonds and order 2s as before, the energy to O(h^(2s+1)) a step "
            "instead of the quadrature's error. Expected when the calculator pushes hard along "
            "the bonds (a pair potential that does not exclude a molecule's own pairs); "
            "otherwise the timestep is too large: try a smaller one",
            BondForcesAbsorbedWarning, stacklevel=3)
    return forces

