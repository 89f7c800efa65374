"""HBVM(k, s) as an ASE molecular-dynamics class (NVE), a drop-in for ``VelocityVerlet``.

The atoms become a separable Hamiltonian system H = p^T M^{-1} p / 2 + V(q) with q the
flattened positions (3N,), p the flattened momenta and M the masses repeated three times; the
engine (:class:`integrators.Stepper`, separable form) advances it.  Units are ASE's: time in ASE
units, p in amu A / time unit, F in eV / A, so dq/dt = p / m and dp/dt = F.
"""
from __future__ import annotations

import copy
import inspect
import logging
import re

import numpy as np
from ase import units
from ase.constraints import FixAtoms
from ase.md.md import MolecularDynamics

from integrators import EQUIP, HBVM, ConvergenceError, Stepper
from integrators.engine import check_step
from systems.base import SeparableSystem

_log = logging.getLogger(__name__)

# keyword arguments of ASE's thermostats and barostats: HBVMDynamics conserves energy (NVE)
METHODS = ("hbvm", "equip")      # the integrators' family: integrators.HBVM, integrators.EQUIP
_ENSEMBLE_KWARGS = ("temperature_K", "temperature", "friction", "taut", "ttime", "pressure_au",
                    "pressure", "taup", "externalstress")

def default_k(s: int, polynomial_degree: int | None) -> int:
    """The k that ``HBVMDynamics(k=None)`` uses.

    Polynomial H of degree nu: the smallest k with nu s <= 2 k, which conserves H exactly
    (BIT, eq. (knu)).  Otherwise k = s + 1, chosen by cost: the energy error of HBVM(k, s) on
    a non-polynomial H is the quadrature error of the line integral, O(h^(2k+1)) a step, so
    k = s + 1 already puts it two orders of h below the trajectory's own error, and each
    further node costs one more force evaluation a stage sweep.  Measured on ASE's MD tutorial
    (EMT copper, 108 atoms, 300 K, 5 fs; ``benchmarks/bench_md_cost.py``): HBVM(3, 2) and
    HBVM(6, 2) reach the same energy error, 2.8e-10 eV per atom (a floor set by EMT's cutoff,
    which no k removes), with 30 and 62 force evaluations a step.  On smooth potentials at
    large steps (Morse, the pendulum) a larger k (s + 4) brings the energy error down to
    round-off: pass ``k`` for that.
    """
    if polynomial_degree is not None:
        return HBVM.for_polynomial_degree(max(int(polynomial_degree), 2), s).k
    return s + 1


class _AtomsSystem(SeparableSystem):
    """The atoms as a separable system (q, p flattened to (3N,)); fixed atoms feel no force."""

    polynomial_degree = None
    rows_independent = True     # forces keeps the stage rows apart: no probe (2 calculator calls)

    def __init__(self, atoms, fixed: np.ndarray, batched: bool):
        self.atoms = atoms
        self.calc = atoms.calc
        self.n_atoms = len(atoms)
        self.dim = 3 * self.n_atoms
        self.masses = np.repeat(np.asarray(atoms.get_masses(), dtype=float), 3)
        self.free = np.ones((self.n_atoms, 1))
        self.free[fixed] = 0.0
        self.fixed = np.asarray(fixed, dtype=int)
        self.batched = batched
        self.stage_evaluations = 0
        # a polynomial calculator's degree: the engine's default energy check is then strict
        self.polynomial_degree = getattr(self.calc, "polynomial_degree", None)
        # the engine writes the stage forces straight into its array when the calculator's
        # forces_batch takes out= (PolynomialPairPotential's does) and no atom is fixed
        try:
            takes_out = batched and "out" in inspect.signature(self.calc.forces_batch).parameters
        except (TypeError, ValueError):
            takes_out = False
        if takes_out and not self.fixed.size:
            self.forces_into = self._forces_into

    def _forces_into(self, Q: np.ndarray, out: np.ndarray) -> None:
        """``out[...] = forces(Q)`` for stage rows Q (n, 3N), without the copy."""
        n = Q.shape[0]
        target = out.view()
        target.shape = (n, self.n_atoms, 3)    # raises rather than reshape into a copy
        self.calc.forces_batch(Q.reshape(n, self.n_atoms, 3), self.atoms, out=target)
        self.stage_evaluations += n

    def forces(self, Q: np.ndarray) -> np.ndarray:
        Q = np.asarray(Q, dtype=float)
        X = Q.reshape(Q.shape[:-1] + (self.n_atoms, 3))
        lead = X.shape[:-2]
        X = X.reshape((-1, self.n_atoms, 3))
        if self.batched:
            F = self._checked(self.calc.forces_batch(X, self.atoms), X.shape, "forces_batch")
        else:
            # the real atoms object is moved to each stage (calculators may keep per-atoms
            # state); the step puts it back at the final positions afterwards
            F = np.empty_like(X)
            for a in range(X.shape[0]):
                self.atoms.set_positions(X[a], apply_constraint=False)
                F[a] = self._checked(self.calc.get_property("forces", self.atoms), X.shape[1:],
                                     "get_property('forces')")
        self.stage_evaluations += X.shape[0]
        if self.fixed.size:
            F = F * self.free
        return F.reshape(lead + (self.dim,))

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
        if q.ndim == 1:
            # one state (the step's energy check, at the new positions): on the atoms
            # themselves, so that the forces the step then asks there come from the cache (a
            # failed step puts the atoms and the calculator's results back, HBVMDynamics.step)
            self.atoms.set_positions(q.reshape(self.n_atoms, 3), apply_constraint=False)
            return float(self.calc.get_property("energy", self.atoms))
        flat = q.reshape((-1, self.dim))
        work = self.atoms.copy()
        work.calc = self.calc
        out = np.empty(len(flat))
        saved = (self.calc.atoms, dict(self.calc.results)) if hasattr(self.calc, "results") else None
        for a, qa in enumerate(flat):
            work.set_positions(qa.reshape(self.n_atoms, 3), apply_constraint=False)
            out[a] = work.get_potential_energy()
        if saved is not None:
            self.calc.atoms, self.calc.results = saved
        return out.reshape(q.shape[:-1]) if q.ndim > 1 else float(out[0])


class _AtomsSystemWithHessian(_AtomsSystem):
    """The atoms with a calculator that gives its exact Hessian (``calc.hessian(Q, atoms)``,
    e.g. :meth:`systems.PolynomialPairPotential.hessian`), used by the Newton solver."""

    def hessian(self, y: np.ndarray) -> np.ndarray:
        """Jacobian (2m, 2m) of ``gradient`` at one state: [[d^2V/dq^2, 0], [0, M^-1]], with
        the rows of fixed atoms zero (they feel no force)."""
        y = np.asarray(y, dtype=float)
        m = self.dim
        H = np.zeros((2 * m, 2 * m))
        K = self.calc.hessian(y[:m].reshape(self.n_atoms, 3), self.atoms)
        H[:m, :m] = K * np.repeat(self.free[:, 0], 3)[:, None]
        H[np.arange(m, 2 * m), np.arange(m, 2 * m)] = 1.0 / self.masses
        return H


class HBVMDynamics(MolecularDynamics):
    """NVE molecular dynamics with the energy-conserving HBVM(k, s) of order 2s.

    Parameters
    ----------
    atoms : ase.Atoms
        With a calculator.  Constraints: only :class:`ase.constraints.FixAtoms` (fixed atoms
        keep zero displacement and zero momentum; their momenta are set to zero here); others
        raise ``ValueError``.
    timestep : float
        In ASE time units (e.g. ``2 * ase.units.fs``).
    s : int
        Degree of the method (order 2s); s = 1 with k = 1 is the implicit midpoint rule.
    k : int, optional
        Number of quadrature nodes (k >= s).  None: the smallest k that conserves H exactly
        when the calculator has a ``polynomial_degree`` (e.g. :class:`systems.PolynomialPairPotential`
        without cutoff), otherwise :func:`default_k` = s + 1, the cheapest k whose quadrature
        error is below the trajectory's own error (measured on EMT copper).
    solver : {"auto", "fixed_point", "newton"}
        Nonlinear solver of the engine (see :class:`integrators.Stepper`).  "newton" (and
        "auto" once fixed point has failed) needs d^2V/dq^2 at the start of each step: a
        calculator with a ``hessian(Q, atoms)`` method returning the (3N, 3N) Hessian
        (:class:`systems.PolynomialPairPotential` has an exact, compiled one) gives it in one
        call; for any other calculator it is taken by central finite differences of the
        forces, 6N extra force evaluations a step (2 per coordinate), which dominates the
        cost beyond a few atoms.
    nodes : {"gauss", "lobatto"}
    method : {"hbvm", "equip"}
        ``"hbvm"`` (default): HBVM(k, s), energy conserving.  ``"equip"``: EQUIP(k, s)
        (:class:`integrators.EQUIP`), the Gauss method perturbed at each step so that it
        conserves the energy and stays symplectic, so the total angular momentum of a free
        cluster is kept to round-off as well; k is then the quadrature of its energy
        condition (the same default), s >= 2, Gauss nodes.
    trajectory, logfile, loginterval, **kwargs
        As for :class:`ase.md.md.MolecularDynamics`.

    Attributes
    ----------
    method : integrators.HBVM or integrators.EQUIP
    k, s : int
    stage_evaluations : int
        Force evaluations at stage configurations so far (plus one per step at the final
        positions, made through ``atoms.get_forces``).

    Notes
    -----
    A :class:`systems.PolynomialPairPotential` calculator is evaluated at all stages in one
    compiled call (``forces_batch``); any other calculator is called once per stage with the
    atoms moved to the stage positions.  Each step ends with the atoms at the new positions and
    momenta and ``atoms.get_forces(md=True)`` computed there, so loggers and observers read
    cached values.  A failed step (:class:`integrators.ConvergenceError`, non-finite forces)
    leaves positions, momenta and the calculator's cached results as they were, then raises.
    The engine (with its extrapolated initial guess and compensated summation) is kept between
    steps and rebuilt when the atoms were changed from outside.  The message of a
    ``ConvergenceError`` gives h and t in fs (its attributes ``h`` and ``t`` stay in ASE units).
    Masses must be positive and positions and momenta finite (``ValueError`` naming the atoms);
    with no atoms a step does nothing.  The ensemble is NVE: thermostat arguments such as
    ``temperature_K`` raise ``TypeError`` pointing to ASE's Langevin, Bussi and
    NoseHooverChainNVT.
    """

    def __init__(self, atoms, timestep: float, s: int = 2, k: int | None = None,
                 solver: str = "auto", nodes: str = "gauss", trajectory=None, logfile=None,
                 loginterval: int = 1, method: str = "hbvm", **kwargs):
        thermo = [key for key in _ENSEMBLE_KWARGS if key in kwargs]
        if thermo:
            raise TypeError(f"HBVMDynamics is NVE (it conserves the energy) and takes no "
                            f"{', '.join(f'`{key}`' for key in thermo)}; for constant temperature use "
                            f"ASE's ase.md.langevin.Langevin, ase.md.bussi.Bussi or "
                            f"ase.md.nose_hoover_chain.NoseHooverChainNVT, and to start at a "
                            f"temperature set momenta with ase.md.velocitydistribution."
                            f"MaxwellBoltzmannDistribution(atoms, temperature_K=...)")
        if atoms.calc is None:
            raise ValueError("`atoms` has no calculator; set atoms.calc before creating "
                             "HBVMDynamics")
        self._check_atoms(atoms)
        timestep = check_step(timestep, "timestep")
        if solver not in ("auto", "fixed_point", "newton"):
            raise ValueError(f"`solver` must be 'auto', 'fixed_point' or 'newton' (got solver={solver!r})")
        if not isinstance(method, str) or method not in METHODS:
            raise ValueError(f"`method` must be one of {METHODS} (got method={method!r}): "
                             f"'hbvm' conserves the energy, 'equip' the energy and every "
                             f"quadratic invariant (angular momentum) too")
        if method == "equip" and nodes != "gauss":
            raise ValueError(f"`nodes` must be 'gauss' with method='equip' (got nodes={nodes!r}): "
                             f"EQUIP perturbs the Gauss method")
        if k is None:
            HBVM(s, s, nodes)   # validates s and nodes with their own messages
            nu = getattr(atoms.calc, "polynomial_degree", None)
            k = default_k(s, nu)
            why = (f"chosen: exact for the calculator's polynomial degree {nu}" if nu is not None
                   else "chosen: s + 1, the cheapest k for a non-polynomial calculator")
        else:
            why = "given"
        self.method = EQUIP(k, s) if method == "equip" else HBVM(k, s, nodes)
        _log.info("HBVMDynamics: %r, k=%d (%s), s=%d (order %d), solver=%s",
                  self.method, k, why, s, self.method.order, solver)
        self.solver = solver
        fixed = self._fixed_indices(atoms)
        self._stepper = None
        self._system = None
        self._written = None
        self._stage_total = 0
        super().__init__(atoms, timestep, trajectory=trajectory, logfile=logfile,
                         loginterval=loginterval, **kwargs)
        if fixed.size:
            # fixed atoms carry no momentum, so that the first logged energy is the conserved one
            p = atoms.get_momenta()
            p[fixed] = 0.0
            atoms.set_momenta(p, apply_constraint=False)

    @property
    def k(self) -> int:
        return self.method.k

    @property
    def s(self) -> int:
        return self.method.s

    @property
    def stage_evaluations(self) -> int:
        return self._stage_total + (self._system.stage_evaluations if self._system else 0)

    def todict(self) -> dict:
        d = super().todict()
        d.update({"method": repr(self.method), "k": self.k, "s": self.s,
                  "nodes": self.method.nodes, "solver": self.solver})
        return d

    # -- state ---------------------------------------------------------------------------------
    @staticmethod
    def _fixed_indices(atoms) -> np.ndarray:
        fixed = []
        for c in atoms.constraints:
            if isinstance(c, FixAtoms):
                fixed.extend(int(i) for i in c.get_indices())
            else:
                raise ValueError(f"HBVMDynamics supports only FixAtoms constraints (got "
                                 f"{type(c).__name__}); remove it or use VelocityVerlet")
        return np.array(sorted(set(fixed)), dtype=int)

    @staticmethod
    def _check_atoms(atoms) -> None:
        """Masses positive and finite, positions and momenta finite; the message names the
        atoms (at most 10 indices), never the whole state."""
        def first(bad) -> str:
            idx = np.flatnonzero(bad)
            more = f" and {idx.size - 10} more" if idx.size > 10 else ""
            return f"{idx[:10].tolist()}{more} (of {len(atoms)})"

        m = np.asarray(atoms.get_masses(), dtype=float)
        bad = ~(np.isfinite(m) & (m > 0))
        if bad.any():
            raise ValueError(f"`atoms` masses must be positive and finite (got {m[bad][:10].tolist()} "
                             f"for atoms {first(bad)}); HBVMDynamics divides by the masses: set "
                             f"them with atoms.set_masses(...), or keep an atom in place with "
                             f"FixAtoms and a nonzero mass")
        for what, v in (("positions", atoms.get_positions()), ("momenta", atoms.get_momenta())):
            bad = ~np.all(np.isfinite(v), axis=1)
            if bad.any():
                raise ValueError(f"`atoms` {what} are not finite (nan or inf) for atoms {first(bad)}; "
                                 f"check how the structure or the velocities were built")

    def _in_fs(self, err: ConvergenceError) -> ConvergenceError:
        """The same error (same type and attributes, h and t in ASE units) with h and t shown
        in fs in the message, and a hint in the words of this class."""
        if type(err) is ConvergenceError:
            # "auto" has tried Newton after fixed point: suggest a smaller timestep only
            hint = ("try a smaller timestep, or solver='newton' for a stiff problem"
                    if self.solver == "fixed_point" else "try a smaller timestep")
            if "not finite" in str(err):
                hint = "the forces or the new state are not finite; " + hint
            new = ConvergenceError(err.h, err.residual, err.iterations,
                                   "auto" if self.solver == "auto" else err.solver, err.t, hint)
        else:
            new = copy.copy(err)
        where = f"h={err.h / units.fs:.6g} fs" + ("" if err.t is None else f" at t={err.t / units.fs:.6g} fs")
        new.args = (re.sub(r"h=\S+( at t=\S+)?", lambda _: where, str(new), count=1),)
        return new

    def _current_state(self):
        atoms = self.atoms
        return (np.asarray(atoms.get_positions(), dtype=float).ravel(),
                np.asarray(atoms.get_momenta(), dtype=float).ravel())

    def _ensure_stepper(self, fixed: np.ndarray) -> Stepper:
        atoms = self.atoms
        q, p = self._current_state()
        w = self._written
        sys_ = self._system
        fresh = (self._stepper is None or sys_ is None or sys_.calc is not atoms.calc
                 or sys_.n_atoms != len(atoms) or w is None
                 or not (np.array_equal(w[0], q) and np.array_equal(w[1], p))
                 or not np.array_equal(w[2], fixed)
                 or not np.array_equal(sys_.masses, np.repeat(atoms.get_masses(), 3)))
        if fresh:
            self._check_atoms(atoms)
            if sys_ is not None:
                self._stage_total += sys_.stage_evaluations
            batched = hasattr(atoms.calc, "forces_batch")
            kind = _AtomsSystemWithHessian if callable(getattr(atoms.calc, "hessian", None)) else _AtomsSystem
            sys_ = kind(atoms, fixed, batched)
            p = p.reshape(-1, 3) * sys_.free
            self._system = sys_
            self._stepper = Stepper(self.method, sys_, np.concatenate([q, p.ravel()]),
                                    solver=self.solver, form="separable")
        return self._stepper

    def step(self, forces=None):
        """Advance one step; returns the forces (N, 3) at the new positions.

        ``forces`` is accepted for compatibility with ``VelocityVerlet.step`` and not used:
        HBVM evaluates its own stage forces.
        """
        atoms = self.atoms
        if len(atoms) == 0:
            return np.zeros((0, 3))      # nothing moves, as with VelocityVerlet
        fixed = self._fixed_indices(atoms)
        st = self._ensure_stepper(fixed)
        pos0 = atoms.get_positions()
        mom0 = atoms.get_momenta()
        calc = atoms.calc
        saved_calc = None
        if hasattr(calc, "results") and hasattr(calc, "atoms"):
            saved_calc = (None if calc.atoms is None else calc.atoms.copy(),
                          {key: (v.copy() if isinstance(v, np.ndarray) else v)
                           for key, v in calc.results.items()})
        saved_stepper = st.save_state()
        saved_count = self._system.stage_evaluations
        try:
            y = st.step(self.dt)
            n = len(atoms)
            atoms.set_positions(y[: 3 * n].reshape(n, 3), apply_constraint=False)
            atoms.set_momenta(y[3 * n:].reshape(n, 3), apply_constraint=False)
            forces = atoms.get_forces(md=True)
            if not np.all(np.isfinite(forces)):
                raise ConvergenceError(self.dt, float("nan"), 0, st.solver, st.t - self.dt,
                                       hint="the forces at the new positions are not finite; "
                                            "try a smaller timestep")
        except BaseException as err:
            # the engine as before the step (its arrays are changed in place by a step that
            # succeeded before the forces at the new positions failed), then the atoms
            st.restore_state(saved_stepper)
            self._system.stage_evaluations = saved_count
            atoms.set_positions(pos0, apply_constraint=False)
            atoms.set_momenta(mom0, apply_constraint=False)
            if saved_calc is not None:
                calc.atoms, calc.results = saved_calc
            else:
                atoms.get_forces(md=True)
            if isinstance(err, ConvergenceError):
                raise self._in_fs(err) from None
            raise
        self._written = (*self._current_state(), fixed)
        return forces
