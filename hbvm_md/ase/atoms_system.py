"""The atoms as a separable Hamiltonian system: the adapter the ASE host's steps advance.

H = p^T M^{-1} p / 2 + V(q) with q the flattened positions (3N,), p the flattened momenta and M
the masses repeated three times; the forces are the calculator's plus those of the constraints'
energy terms.  Both steps of :mod:`hbvm_md.ase` build it: the unconstrained one
(:class:`hbvm_md.ase.dynamics.HBVMDynamics`) and the one with rigid bonds
(:mod:`hbvm_md.ase.holonomic`); :func:`calculator_cache` is what either puts back after a
failed step.
"""
from __future__ import annotations

import inspect

import numpy as np

from systems.base import SeparableSystem

from .constraints import AtomsConstraints


def calculator_cache(calc):
    """(atoms, results) of an ASE calculator's cache, copied, to put back after a failed step
    (``calc.atoms, calc.results = saved``); None for a calculator without that cache."""
    if not (hasattr(calc, "results") and hasattr(calc, "atoms")):
        return None
    return (None if calc.atoms is None else calc.atoms.copy(),
            {key: (v.copy() if isinstance(v, np.ndarray) else v)
             for key, v in calc.results.items()})


class _AtomsSystem(SeparableSystem):
    """The atoms as a separable system (q, p flattened to (3N,)); the forces are the
    calculator's plus those of the constraints' energy terms, projected onto the linear
    constraints' subspace (:class:`hbvm_md.ase.constraints.AtomsConstraints`)."""

    polynomial_degree = None
    rows_independent = True     # forces keeps the stage rows apart: no probe (2 calculator calls)

    def __init__(self, atoms, constraints: AtomsConstraints, batched: bool):
        self.atoms = atoms
        self.calc = atoms.calc
        self.n_atoms = len(atoms)
        self.dim = 3 * self.n_atoms
        self.body_dim = 3       # an atom's coordinates (the step's error estimate, atom by atom)
        self.masses = np.repeat(np.asarray(atoms.get_masses(), dtype=float), 3)
        self.constraints = constraints
        self.batched = batched
        self.stage_evaluations = 0
        # (positions (N, 3), all finite, an atom) where the calculator returned a force that is
        # not finite (None: it has not); the host names the calculator in its NonFiniteError
        self.nonfinite_at = None
        # a polynomial calculator's degree: the engine's default energy check is then strict
        # (linear constraints keep H polynomial on their subspace; Hookean and ExternalForce
        # terms do not)
        self.polynomial_degree = (None if constraints.terms
                                  else getattr(self.calc, "polynomial_degree", None))
        # the engine writes the stage forces straight into its array when the calculator's
        # forces_batch takes out= (PolynomialPairPotential's does); the constraints then act
        # on that array in place
        try:
            takes_out = batched and "out" in inspect.signature(self.calc.forces_batch).parameters
        except (TypeError, ValueError):
            takes_out = False
        if takes_out:
            self.forces_into = self._forces_into

    def _forces_into(self, Q: np.ndarray, out: np.ndarray) -> None:
        """``out[...] = forces(Q)`` for stage rows Q (n, 3N), without the copy."""
        n = Q.shape[0]
        target = out.view()
        target.shape = (n, self.n_atoms, 3)    # raises rather than reshape into a copy
        X = Q.reshape(n, self.n_atoms, 3)
        self.calc.forces_batch(X, self.atoms, out=target)
        self.stage_evaluations += n
        self._note_nonfinite(X, target)
        if self.constraints.any:
            self.constraints.forces(X, target)

    def forces(self, Q: np.ndarray) -> np.ndarray:
        Q = np.asarray(Q, dtype=float)
        X = Q.reshape(Q.shape[:-1] + (self.n_atoms, 3))
        lead = X.shape[:-2]
        X = X.reshape((-1, self.n_atoms, 3))
        if self.batched:
            F = np.array(self._checked(self.calc.forces_batch(X, self.atoms), X.shape,
                                       "forces_batch"), dtype=float)
        else:
            # the real atoms object is moved to each stage (calculators may keep per-atoms
            # state); the step puts it back at the final positions afterwards
            F = np.empty_like(X)
            for a in range(X.shape[0]):
                self.atoms.set_positions(X[a], apply_constraint=False)
                F[a] = self._checked(self.calc.get_property("forces", self.atoms), X.shape[1:],
                                     "get_property('forces')")
        self.stage_evaluations += X.shape[0]
        self._note_nonfinite(X, F)
        if self.constraints.any:
            self.constraints.forces(X, F)
        return F.reshape(lead + (self.dim,))

    def _note_nonfinite(self, X: np.ndarray, F: np.ndarray) -> None:
        """Remember the first stage (n, N, 3) at finite positions whose calculator forces are
        not finite: the calculator's failure, not the step's (``nonfinite_at``)."""
        if np.isfinite(F).all():
            return
        bad = ~np.isfinite(F).reshape(F.shape[0], -1).all(axis=1)
        good = np.isfinite(X).reshape(X.shape[0], -1).all(axis=1)
        rows = np.flatnonzero(bad & good)
        if rows.size:
            atom = int(np.flatnonzero(~np.isfinite(F[rows[0]]).all(axis=-1))[0])
            self.nonfinite_at = (np.array(X[rows[0]]), atom)

    def _checked(self, F, shape: tuple, call: str) -> np.ndarray:
        """The calculator's forces, or a ValueError naming it and the shapes (numpy would say
        only that it cannot broadcast, or broadcast a wrong shape silently)."""
        F = np.asarray(F)
        if F.shape != shape:
            raise ValueError(f"the calculator {type(self.calc).__name__} returned forces of shape "
                             f"{F.shape} from {call} for {self.n_atoms} atoms (shape {shape} "
                             f"expected): one row of 3 components per atom of the Atoms it is "
                             f"given; check that it computes for these atoms (no extra ghost "
                             f"or dummy atom, no atom left out)")
        return F

    def potential(self, q: np.ndarray):
        q = np.asarray(q, dtype=float)
        terms = self.constraints.terms
        if q.ndim == 1:
            # one state (the step's energy check, at the new positions): on the atoms
            # themselves, so that the forces the step then asks there come from the cache (a
            # failed step puts the atoms and the calculator's results back, HBVMDynamics.step)
            X = q.reshape(self.n_atoms, 3)
            self.atoms.set_positions(X, apply_constraint=False)
            v = float(self.calc.get_property("energy", self.atoms))
            return v + float(terms.energy(X[None])[0]) if terms else v
        flat = q.reshape((-1, self.dim))
        work = self.atoms.copy()
        work.set_constraint()
        work.calc = self.calc
        out = np.empty(len(flat))
        saved = (self.calc.atoms, dict(self.calc.results)) if hasattr(self.calc, "results") else None
        for a, qa in enumerate(flat):
            work.set_positions(qa.reshape(self.n_atoms, 3), apply_constraint=False)
            out[a] = work.get_potential_energy()
        if saved is not None:
            self.calc.atoms, self.calc.results = saved
        if terms:
            out += terms.energy(flat.reshape(-1, self.n_atoms, 3))
        return out.reshape(q.shape[:-1]) if q.ndim > 1 else float(out[0])


class _AtomsSystemWithHessian(_AtomsSystem):
    """The atoms with a calculator that gives its exact Hessian (``calc.hessian(Q, atoms)``,
    e.g. :meth:`systems.PolynomialPairPotential.hessian`), used by the Newton solver."""

    def hessian(self, y: np.ndarray) -> np.ndarray:
        """Jacobian (2m, 2m) of ``gradient`` at one state: [[d^2V/dq^2, 0], [0, M^-1]], the
        rows of d^2V/dq^2 projected onto the linear constraints (d(P F)/dq = P dF/dq); the
        energy terms' second derivatives are left out (the simplified Newton iteration
        converges to the same step with an approximate matrix)."""
        y = np.asarray(y, dtype=float)
        m = self.dim
        H = np.zeros((2 * m, 2 * m))
        K = self.calc.hessian(y[:m].reshape(self.n_atoms, 3), self.atoms)
        proj = self.constraints.projector
        H[:m, :m] = K if proj is None else proj.matrix() @ K
        H[np.arange(m, 2 * m), np.arange(m, 2 * m)] = 1.0 / self.masses
        return H
