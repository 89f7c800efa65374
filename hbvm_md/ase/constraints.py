"""ASE constraints as the HBVM step sees them: projections, terms of H, and the rest refused.

:func:`classify` sorts each of ``atoms.constraints`` into one kind:

``"linear"`` (:class:`~ase.constraints.FixAtoms`, ``FixCom``, ``FixSubsetCom``, ``FixedPlane``,
``FixedLine``, ``FixCartesian``)
    Linear constraints A q = A q0 on the positions.  The dynamics on the affine subspace is
    q' = M^-1 p, p' = P F(q) with the projector P = I - A^T (A M^-1 A^T)^-1 A M^-1 applied to the
    forces and, once, to the momenta (:class:`LinearProjector`).  The projected system is the
    linear image of an unconstrained Hamiltonian system in coordinates of the subspace (mass
    N^T M N, potential V(q0 + N z)), and a Runge-Kutta method commutes with linear changes of
    variables: every stage stays on the subspace (to round-off), HBVM's energy conservation and
    order are those of the reduced system, with nothing to iterate.  P is the M^-1-orthogonal
    projector: for FixCom it removes m_i / M times the total force from atom i (the centre of
    mass does not accelerate), for the constraints of single atoms the Euclidean one.
``"energy"`` (:class:`~ase.constraints.Hookean`, ``ExternalForce``)
    Forces that ASE adds with an energy (``adjust_forces`` and ``adjust_potential_energy``):
    terms of H (:class:`EnergyTerms`), evaluated at every stage and part of the conserved total
    (``atoms.get_potential_energy()`` includes them, as for ASE's own integrators).
``"holonomic"`` (``FixBondLength(s)``, ``FixLinearTriatomic``)
    Nonlinear constraints of the positions, which need Lagrange multipliers inside the step:
    they run in the constrained step of :mod:`hbvm_md.ase.holonomic`, which takes them out of
    the list before this module sees it; here (:func:`refuse`) one left in is refused, naming
    the class as the user wrote it.
``"unsupported"``
    Anything else: refused naming the class (a silent drop would run a different system).
"""
from __future__ import annotations

import numpy as np
from ase.constraints import (ExternalForce, FixAtoms, FixBondLengths, FixCartesian, FixCom,
                             FixedLine, FixedPlane, FixLinearTriatomic, FixSubsetCom, Hookean)
from ase.geometry import find_mic

LINEAR, ENERGY, HOLONOMIC, UNSUPPORTED = "linear", "energy", "holonomic", "unsupported"


class UnsupportedConstraintError(NotImplementedError, ValueError):
    """A constraint HBVMDynamics does not run.  A NotImplementedError, as ASE's own dynamics
    raise for a constraint they cannot honour (``FixSymmetry`` in MD: ASE's ``test_fail_md``),
    and a ValueError (bad input), as this package raised before."""

#: the kind of each class the step knows (exact classes: a subclass may change what it does)
KINDS = {FixAtoms: LINEAR, FixCom: LINEAR, FixSubsetCom: LINEAR, FixedPlane: LINEAR,
         FixedLine: LINEAR, FixCartesian: LINEAR, Hookean: ENERGY, ExternalForce: ENERGY,
         FixBondLengths: HOLONOMIC, FixLinearTriatomic: HOLONOMIC}

SUPPORTED = ("FixAtoms, FixCom, FixSubsetCom, FixedPlane, FixedLine, FixCartesian (by "
             "projection), Hookean, ExternalForce (as terms of the energy), and "
             "FixBondLength(s) and FixLinearTriatomic with FixAtoms or FixCom (rigid bonds "
             "in the constrained step)")


def classify(constraint) -> str:
    """The kind of one ASE constraint: "linear", "energy", "holonomic" or "unsupported"."""
    return KINDS.get(type(constraint), UNSUPPORTED)


def sort_constraints(constraints) -> dict:
    """{kind: [constraints of that kind, in the order given]} for every kind."""
    out = {LINEAR: [], ENERGY: [], HOLONOMIC: [], UNSUPPORTED: []}
    for c in constraints:
        out[classify(c)].append(c)
    return out


def name(constraint) -> str:
    """The class as the user wrote it: ASE's ``FixBondLength(a, b)`` is a FixBondLengths of
    one pair."""
    if type(constraint) is FixBondLengths and len(np.atleast_2d(constraint.pairs)) == 1:
        return "FixBondLength"
    return type(constraint).__name__


def refuse(kinds: dict) -> None:
    """ValueError naming the first holonomic or unsupported constraint, if any."""
    for c in kinds[HOLONOMIC]:
        raise UnsupportedConstraintError(
            f"HBVMDynamics does not support the holonomic constraint {name(c)} yet (it keeps "
            f"distances, which needs Lagrange multipliers inside the step); supported: "
            f"{SUPPORTED}. Remove it, or use VelocityVerlet (RATTLE) for rigid molecules")
    for c in kinds[UNSUPPORTED]:
        raise UnsupportedConstraintError(f"HBVMDynamics does not support the constraint {name(c)}; supported: "
                         f"{SUPPORTED}. Remove it or use VelocityVerlet")


def _indices(c, n_atoms: int) -> np.ndarray:
    idx = np.arange(n_atoms)[c.index] if isinstance(c.index, slice) else np.asarray(c.index)
    idx = np.atleast_1d(idx).astype(int)
    if idx.size and (idx.min() < -n_atoms or idx.max() >= n_atoms):
        raise ValueError(f"constraint {name(c)} names atom {int(idx.max())} but the atoms have "
                         f"{n_atoms}; fix its indices")
    return idx % n_atoms if idx.size else idx


def signature(constraints) -> tuple:
    """What the step reads of each constraint, as plain values: a constraint changed in place
    (new indices, direction, spring) changes it, and the step is then rebuilt."""
    sig = []
    for c in constraints:
        parts = [type(c).__name__]
        for attr in ("index", "indices", "dir", "mask", "spring", "threshold", "origin", "plane",
                     "external_force", "_type", "pairs", "bondlengths"):
            v = getattr(c, attr, None)
            if v is None:
                continue
            if isinstance(v, slice):
                parts.append((attr, v.start, v.stop, v.step))
            else:
                a = np.asarray(v)
                parts.append((attr, a.dtype.str, a.shape, a.tobytes()))
        sig.append(tuple(parts))
    return tuple(sig)


class LinearProjector:
    """The projector P of the linear constraints (module docstring), applied to stage forces
    and momenta.

    Built in the mass-weighted coordinates x = M^(1/2) q, where P becomes the orthogonal
    projector Pi onto the intersection of the allowed subspaces: each constrained atom's own
    3 x 3 projector R_a (its forbidden directions: all three for FixAtoms, the normal for
    FixedPlane, the plane normal to the line for FixedLine, the masked axes for FixCartesian,
    whichever constraints name it), then the centre-of-mass rows G (three per FixCom or
    FixSubsetCom, projected by the R_a) removed as Pi f = R f - G^T (G G^T)^+ G R f.  Entries
    of R within a few ulps of 0 or 1 are snapped, so that axis-aligned constraints (FixAtoms,
    FixCartesian, planes and lines along an axis) keep their coordinates bit for bit.

    Parameters
    ----------
    constraints : list of ASE constraints of kind "linear"
    masses : ndarray (N,)
    """

    def __init__(self, constraints, masses: np.ndarray):
        n = masses.shape[0]
        forbidden: dict[int, list] = {}
        groups = []
        for c in constraints:
            if type(c) is FixCom:
                groups.append(np.arange(n))
                continue
            idx = _indices(c, n)
            if type(c) is FixSubsetCom:
                groups.append(np.unique(idx))
                continue
            if type(c) is FixAtoms:
                rows = np.eye(3)
            elif type(c) is FixedPlane:
                rows = np.asarray(c.dir, dtype=float)[None, :]
            elif type(c) is FixedLine:
                d = np.asarray(c.dir, dtype=float)
                rows = np.eye(3) - np.outer(d, d) / (d @ d)
            elif type(c) is FixCartesian:
                rows = np.eye(3)[np.asarray(c.mask, dtype=bool)]
            else:                                           # (classify keeps this out)
                raise TypeError(f"not a linear constraint: {name(c)}")
            for a in idx:
                forbidden.setdefault(int(a), []).append(rows)
        self.atoms = np.array(sorted(forbidden), dtype=int)
        self.R = np.empty((self.atoms.size, 3, 3))
        for j, a in enumerate(self.atoms):
            B = np.concatenate(forbidden[int(a)])
            _, sv, Vt = np.linalg.svd(B)
            r = int(np.sum(sv > 1e-12 * sv[0])) if sv.size and sv[0] > 0 else 0
            Ra = np.eye(3) - Vt[:r].T @ Vt[:r]
            Ra[np.abs(Ra) < 8 * np.finfo(float).eps] = 0.0
            Ra[np.abs(Ra - 1.0) < 8 * np.finfo(float).eps] = 1.0
            self.R[j] = Ra
        self.sqrt_m = np.sqrt(masses)
        self.G = None
        if groups:
            G = np.zeros((3 * len(groups), n, 3))
            for g, members in enumerate(groups):
                for d in range(3):
                    G[3 * g + d, members, d] = self.sqrt_m[members]
            G[:, self.atoms] = np.einsum("aij,raj->rai", self.R, G[:, self.atoms])
            K = np.einsum("rai,sai->rs", G, G)
            self.G = G
            self.Kinv = np.linalg.pinv(K, rcond=1e-12, hermitian=True)
        self.removed = int(sum(3 - round(np.trace(Ra)) for Ra in self.R))
        if self.G is not None:
            self.removed += int(np.linalg.matrix_rank(K, tol=1e-12 * max(1.0, np.max(np.abs(K)))))

    @property
    def empty(self) -> bool:
        return self.atoms.size == 0 and self.G is None

    def apply(self, F: np.ndarray) -> None:
        """F <- P F in place, for F of shape (n, N, 3) (stage forces, or momenta as (1, N, 3))."""
        if self.G is None:
            if self.atoms.size:
                F[:, self.atoms] = np.einsum("aij,naj->nai", self.R, F[:, self.atoms])
            return
        f = F / self.sqrt_m[None, :, None]
        if self.atoms.size:
            f[:, self.atoms] = np.einsum("aij,naj->nai", self.R, f[:, self.atoms])
        coef = np.einsum("rai,nai->nr", self.G, f) @ self.Kinv
        f -= np.einsum("nr,rai->nai", coef, self.G)
        np.multiply(f, self.sqrt_m[None, :, None], out=F)

    def matrix(self) -> np.ndarray:
        """P as a dense (3N, 3N) matrix (for Newton's Jacobian: d(P F)/dq = P dF/dq)."""
        n = self.sqrt_m.shape[0]
        E = np.eye(3 * n).reshape(3 * n, n, 3)
        self.apply(E)
        return E.reshape(3 * n, 3 * n).T


class EnergyTerms:
    """Hookean and ExternalForce as terms of H, at many configurations at once.

    Their formulas are ASE's (``adjust_forces``, ``adjust_potential_energy``: Hookean is
    k (r - r_t) toward its partner, point or plane beyond the threshold, ExternalForce pulls
    two atoms apart with a constant force), evaluated at the rows X (n, N, 3) of a step's
    stages rather than at ``atoms.positions``; pair separations use the minimum image, as ASE
    does.

    Parameters
    ----------
    constraints : list of Hookean and ExternalForce
    atoms : ase.Atoms (cell and pbc)
    """

    def __init__(self, constraints, atoms):
        self.terms = list(constraints)
        self.cell = np.array(atoms.cell.array)
        self.pbc = np.array(atoms.pbc)
        self.periodic = bool(np.any(self.pbc))

    def __bool__(self) -> bool:
        return bool(self.terms)

    def _mic(self, D: np.ndarray) -> np.ndarray:
        return find_mic(D, self.cell, self.pbc)[0] if self.periodic else D

    def add_forces(self, X: np.ndarray, F: np.ndarray) -> None:
        """F += the terms' forces at X; X and F of shape (n, N, 3)."""
        for c in self.terms:
            if type(c) is ExternalForce:
                i, j = c.indices
                D = X[:, i] - X[:, j]
                f = c.external_force * D / np.linalg.norm(D, axis=1)[:, None]
                F[:, i] += f
                F[:, j] -= f
            elif c._type == "plane":
                n_, d_, r = self._plane(c, X)
                F[:, c.index] -= np.where(d_ >= 0, c.spring * d_, 0.0)[:, None] * n_[None, :]
            else:
                i, D = self._pair(c, X)
                r = np.linalg.norm(D, axis=1)
                mag = np.where(r > c.threshold, c.spring * (r - c.threshold), 0.0)
                f = D * (mag / np.where(r > 0, r, 1.0))[:, None]
                F[:, i] += f
                if c._type == "two atoms":
                    F[:, c.indices[1]] -= f

    def energy(self, X: np.ndarray) -> np.ndarray:
        """The terms' energy at each row of X (n, N, 3): shape (n,)."""
        E = np.zeros(X.shape[0])
        for c in self.terms:
            if type(c) is ExternalForce:
                i, j = c.indices
                E -= c.external_force * np.linalg.norm(X[:, i] - X[:, j], axis=1)
            elif c._type == "plane":
                _, d_, _ = self._plane(c, X)
                E += np.where(d_ > 0, 0.5 * c.spring * d_ ** 2, 0.0)
            else:
                _, D = self._pair(c, X)
                r = np.linalg.norm(D, axis=1)
                E += np.where(r > c.threshold, 0.5 * c.spring * (r - c.threshold) ** 2, 0.0)
        return E

    def _pair(self, c, X):
        """(the atom pulled, its separation to the partner or point, (n, 3))."""
        if c._type == "two atoms":
            i, j = c.indices
            return i, self._mic(X[:, j] - X[:, i])
        return c.index, self._mic(np.asarray(c.origin, dtype=float)[None, :] - X[:, c.index])

    @staticmethod
    def _plane(c, X):
        A = np.asarray(c.plane[:3], dtype=float)
        norm = np.linalg.norm(A)
        d = (X[:, c.index] @ A + c.plane[3]) / norm
        return A / norm, d, norm


class AtomsConstraints:
    """The constraints of one atoms object as the step applies them.

    ``constraints``: the ones to apply, ``atoms.constraints`` by default (the rigid bonds of
    :mod:`hbvm_md.ase.holonomic` are left out by its caller: they are the constrained step's).

    Attributes
    ----------
    kinds : dict
        :func:`sort_constraints` of those constraints.
    projector : LinearProjector or None
        None without linear constraints.
    terms : EnergyTerms
        Falsy without energy terms.
    key : tuple
        :func:`signature` of the constraints: the step compares it to see a change.
    """

    def __init__(self, atoms, constraints=None):
        self.kinds = sort_constraints(atoms.constraints if constraints is None else constraints)
        refuse(self.kinds)
        masses = np.asarray(atoms.get_masses(), dtype=float)
        lin = LinearProjector(self.kinds[LINEAR], masses) if self.kinds[LINEAR] else None
        self.projector = None if lin is None or lin.empty else lin
        self.terms = EnergyTerms(self.kinds[ENERGY], atoms)
        self.key = signature(atoms.constraints)

    @property
    def any(self) -> bool:
        return self.projector is not None or bool(self.terms)

    def forces(self, X: np.ndarray, F: np.ndarray) -> None:
        """F (n, N, 3), the calculator's forces at X (n, N, 3), in place to the forces the
        step integrates: plus the energy terms', then projected."""
        if self.terms:
            self.terms.add_forces(X, F)
        if self.projector is not None:
            self.projector.apply(F)

    def momenta(self, p: np.ndarray) -> np.ndarray:
        """The momenta (N, 3) projected onto the constraints' subspace (a copy)."""
        p = np.array(p, dtype=float)
        if self.projector is not None:
            self.projector.apply(p[None])
        return p
