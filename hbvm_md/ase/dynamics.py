"""HBVM(k, s) as an ASE molecular-dynamics class (NVE), a drop-in for ``VelocityVerlet``.

The atoms become a separable Hamiltonian system H = p^T M^{-1} p / 2 + V(q) with q the
flattened positions (3N,), p the flattened momenta and M the masses repeated three times
(:mod:`hbvm_md.ase.atoms_system`); the engine (:class:`integrators.Stepper`, separable form)
advances it.  Units are ASE's: time in ASE units, p in amu A / time unit, F in eV / A, so
dq/dt = p / m and dp/dt = F.
"""
from __future__ import annotations

import copy
import logging
import re
import warnings

import numpy as np
from ase import units
from ase.md.md import MolecularDynamics

from integrators import (EQUIP, HBVM, ConvergenceError, NonFiniteError, Stepper, StepError,
                         UnresolvedStepError)
from integrators.errors import EnergyDriftError
from integrators.engine import (check_adaptive, check_step, energy_check,
                                error_check)

from .atoms_system import _AtomsSystem, _AtomsSystemWithHessian, calculator_cache
from .constraints import AtomsConstraints, signature
from .discontinuity import change_persists, locate_jumps, warn_jumps
from .holonomic import bond_constraints, check_supported, holonomic_step, other_constraints

_log = logging.getLogger(__name__)

# keyword arguments of ASE's thermostats and barostats: HBVMDynamics conserves energy (NVE)
METHODS = ("hbvm", "equip")      # the integrators' family: integrators.HBVM, integrators.EQUIP
#: H at a step's start and the reference the last step ended with differ by more than this
#: (relative to |T| + |V|; both are computed by the same code and agree bit for bit when
#: nothing changed): the calculator was changed in place
CHANGED_H = 64 * np.finfo(float).eps


class SolverSwitchWarning(RuntimeWarning):
    """HBVMDynamics(solver="auto") did a step with Newton's method after the fixed-point
    iteration failed; the message says why and what Newton costs with this calculator."""


#: tol="auto" for a calculator that is not a polynomial: the iteration stops once its error,
#: estimated from the contraction (core.stop_action), is below this fraction of the
#: coefficients, then polishes (see HBVMDynamics.iteration_tol)
MD_TOL = 1e-12

#: ``HBVMDynamics(adaptive=True)``'s defaults: s = 4 (HBVM(5, 4) with a calculator that is
#: not a polynomial) at epsilon = 1e-6, the bound on each inner step's estimated local error
#: relative to the atom's motion over it (:func:`integrators.core.adapt_step`).  Measured
#: (``benchmarks/bench_adaptive_steps.py``, EMT copper, 8 fs timestep, 200 fs): the hot Cu55
#: icosahedron (2400 K) takes one inner step a timestep, 811 calculator calls against 810 for
#: the fixed steps that reach its energy error (4.0e-10 eV per atom); s = 2 at 1e-6 took 117
#: inner steps and 1.35x the calls of its fixed steps, s = 3 48 steps and 1.03x, s = 4 at 1e-8
#: 47 steps and 1.58x at the same energy error (EMT's floor: smaller steps do not lower it).
#: Fixed steps keep s = 2.
MD_ADAPTIVE_S = 4
MD_ADAPTIVE_EPSILON = 1e-6

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


class HBVMDynamics(MolecularDynamics):
    """NVE molecular dynamics with the energy-conserving HBVM(k, s) of order 2s.

    Parameters
    ----------
    atoms : ase.Atoms
        With a calculator.  Constraints (:mod:`hbvm_md.ase.constraints`): the linear ones
        (FixAtoms, FixCom, FixSubsetCom, FixedPlane, FixedLine, FixCartesian) by projection
        of the stage forces and the momenta, kept to round-off, the momenta projected onto
        them here (fixed atoms at rest, no centre-of-mass drift with FixCom); Hookean and
        ExternalForce as terms of the energy, which is conserved with them; rigid bonds
        (FixBondLength(s), FixLinearTriatomic, alone or with FixAtoms or FixCom) inside the
        step (:mod:`hbvm_md.ase.holonomic`), bonds and energy kept to round-off.  Any other
        class, or combination, raises :class:`hbvm_md.ase.constraints.UnsupportedConstraintError`
        (a ``NotImplementedError``, as ASE's dynamics raise for FixSymmetry, and a
        ``ValueError``) naming it and the reason.
    timestep : float
        In ASE time units (e.g. ``2 * ase.units.fs``).
    s : int, optional
        Degree of the method (order 2s); s = 1 with k = 1 is the implicit midpoint rule.
        None (default): 2 for fixed steps, :data:`MD_ADAPTIVE_S` (4) with ``adaptive=True``.
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
    tol : "auto", None or float
        Relative tolerance of the step's iteration (fixed point or Newton): it stops at the
        first increment, or the first error estimated from the iteration's contraction,
        below ``tol`` times the coefficients' size (``core.stop_action``), then polishes.
        None: to round-off (until the increments stop decreasing there).  "auto": None when
        HBVM(k, s) conserves H exactly (a polynomial calculator and k from its degree) and
        for EQUIP, otherwise 1e-12 (:meth:`iteration_tol`: the stage forces' own round-off;
        a third fewer force evaluations a step on EMT copper at 5 fs, the same energy error).
    energy_tol : "auto", float or None
        The step's energy check (:class:`integrators.Stepper`'s): a converged step whose
        energy change, relative to |T| + |V|, exceeds it is refused
        (:class:`integrators.UnresolvedStepError`, nothing committed).  "auto" (default):
        1e-10 when the method conserves the calculator's polynomial energy exactly; otherwise a
        change above 1e-6 that is also far above the method's own error against the energy the
        step moved between T and V (a step too large for what it crosses).  A number: that
        tolerance.  None: no check.  A refused step whose energy change does not shrink when
        the step is retried at h/2 and h/4 (on a copy of the atoms) is the calculator's own
        jump (EMT's cutoff, a neighbour list), not the step's error: it is accepted with one
        :class:`hbvm_md.ase.discontinuity.CalculatorDiscontinuityWarning` naming the time,
        the pair of atoms, the jump in eV, and the run goes on (``warnings.simplefilter(
        "error", CalculatorDiscontinuityWarning)`` makes it an error, the step not taken).
    error_bound : "auto", float or None
        Each step is judged by its own estimate of its local error, atom by atom (the first
        Legendre term it leaves out of the atom's velocity, :func:`integrators.core.
        resolution_error`), independent of the energy (which HBVM keeps whether or not the
        step followed the motion): a step above the bound is refused with
        :class:`integrators.UnresolvedStepError` naming the atom and a timestep that would
        pass, the atoms unchanged.  "auto": :data:`integrators.core.ERROR_BOUND` (1e-3 of the
        atom's motion over the step); None: no check.
    adaptive : bool
        False (default): every step is one HBVM step of ``timestep``.  True: every
        :meth:`step` still advances exactly ``timestep`` (observers, loggers and trajectories
        keep ASE's meaning), made of as many inner steps as the error needs, chosen by the
        engine's one controller (:func:`integrators.core.adapt_step`) and the last shortened
        to land on the timestep (as IAS15 with ``exact_finish_time``); a hot moment pays small
        inner steps and the rest of the run does not.  ``inner_steps`` and
        ``inner_rejections`` count them (also in :meth:`todict`).
    epsilon : float, optional
        The precision of adaptive inner steps, with the meaning of the engine's ``epsilon``
        (:func:`integrators.integrate`): the bound on each inner step's own estimate of its
        local error relative to the atom's motion over it, the same at every s (the estimate
        ``error_bound`` bounds for every step).  Default :data:`MD_ADAPTIVE_EPSILON` (1e-6).
    trajectory, logfile, loginterval, **kwargs
        As for :class:`ase.md.md.MolecularDynamics`.

    Attributes
    ----------
    method : integrators.HBVM or integrators.EQUIP
    k, s : int
    stage_evaluations : int
        Force evaluations at stage configurations so far (plus one per step at the final
        positions, made through ``atoms.get_forces``).
    error_estimate : float
        The run's accumulated error estimate (the engine's
        :attr:`integrators.Stepper.error_estimate`, summed over the engines this dynamics
        started: a new calculator, a changed Hamiltonian): each step's own error estimate
        times the share of its atom's motion the step turned, summed, the error of the
        atoms' paths relative to their motion's scale when the steps' errors add.  Molecular
        trajectories are chaotic, so it is a lower bound of the path's error, and MD asks for
        the energy and the statistics, not the path: reported (also in :meth:`todict`), never
        warned.  Steps of a holonomic run (``FixBondLengths``, ``FixLinearTriatomic``) and
        steps over a calculator's accepted jump carry no estimate and add nothing.
    jumps : list of hbvm_md.ase.discontinuity.Jump
        The calculator's energy jumps the run stepped through (each also warned once).

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

    def __init__(self, atoms, timestep: float, s: int | None = None, k: int | None = None,
                 solver: str = "auto", nodes: str = "gauss", trajectory=None, logfile=None,
                 loginterval: int = 1, method: str = "hbvm", tol="auto",
                 energy_tol="auto", error_bound="auto", adaptive: bool = False,
                 epsilon: float | None = None, **kwargs):
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
        if s is None:
            s = MD_ADAPTIVE_S if (isinstance(adaptive, (bool, np.bool_)) and adaptive) else 2
        if solver not in ("auto", "fixed_point", "newton"):
            raise ValueError(f"`solver` must be 'auto', 'fixed_point' or 'newton' (got solver={solver!r})")
        if not isinstance(method, str) or method not in METHODS:
            raise ValueError(f"`method` must be one of {METHODS} (got method={method!r}): "
                             f"'hbvm' conserves the energy, 'equip' the energy and every "
                             f"quadratic invariant (angular momentum) too")
        if not (tol is None or (isinstance(tol, str) and tol == "auto")
                or (isinstance(tol, (int, float, np.number)) and not isinstance(tol, bool)
                    and np.isfinite(tol) and 0 < tol < 1)):
            raise ValueError(f"`tol` must be 'auto', None (iterate to round-off) or a number in "
                             f"(0, 1) (got tol={tol!r})")
        if method == "equip" and nodes != "gauss":
            raise ValueError(f"`nodes` must be 'gauss' with method='equip' (got nodes={nodes!r}): "
                             f"EQUIP perturbs the Gauss method")
        if bond_constraints(atoms):     # rigid bonds: the constrained step of hbvm_md.ase.holonomic
            if method == "equip":
                raise ValueError("`method` must be 'hbvm' with rigid bonds (FixBondLengths): the "
                                 "constrained step is HBVM(k, s); EQUIP does not take constraints")
            check_supported(atoms)
        # refuses what the step cannot run (the rigid bonds are the constrained step's)
        constraints = AtomsConstraints(atoms, other_constraints(atoms))
        if k is None:
            HBVM(s, s, nodes)   # validates s and nodes with their own messages
            nu = None if constraints.terms else getattr(atoms.calc, "polynomial_degree", None)
            k = default_k(s, nu)
            why = (f"chosen: exact for the calculator's polynomial degree {nu}" if nu is not None
                   else "chosen: s + 1, the cheapest k for a non-polynomial calculator")
        else:
            why = "given"
        self.method = EQUIP(k, s) if method == "equip" else HBVM(k, s, nodes)
        _log.info("HBVMDynamics: %r, k=%d (%s), s=%d (order %d), solver=%s",
                  self.method, k, why, s, self.method.order, solver)
        energy_check(self.method, None, energy_tol)     # the argument's own message
        self.solver = solver
        self.tol = tol
        self.energy_tol = energy_tol
        self.jumps = []
        self._through_jump = False
        self.error_bound = error_bound
        error_check(error_bound)            # checks the argument (ValueError naming it)
        if not isinstance(adaptive, (bool, np.bool_)):
            raise ValueError(f"`adaptive` must be True or False (got adaptive={adaptive!r})")
        self.adaptive = bool(adaptive)
        if epsilon is not None and not self.adaptive:
            raise ValueError("`epsilon` is the precision of adaptive steps: pass adaptive=True "
                             f"with it (got epsilon={epsilon!r} with fixed steps)")
        self.epsilon, _ = (check_adaptive(MD_ADAPTIVE_EPSILON if epsilon is None else epsilon,
                                          None, s) if self.adaptive else (None, None))
        self.inner_steps = 0        # adaptive: the inner steps taken and rejected so far
        self.inner_rejections = 0
        self._h_inner = None        # adaptive: the inner step the controller proposes next
        self._energy_scale = np.nan  # |T| + |V| (eV) at a failed step's start, for its message
        self._clock0 = (0.0, 0.0)    # (the run's time, the engine's) at the step's start
        self._elapsed = 0.0          # the run's time: the steps taken, each of its own timestep
        self._stepper = None
        self._system = None
        self._holonomic = None      # the constrained step when the atoms have rigid bonds
        self._written = None
        self._stage_total = 0
        self._run_error_prior = 0.0     # (the estimate of the engines replaced: error_estimate)
        self.hamiltonian_changes = 0
        super().__init__(atoms, timestep, trajectory=trajectory, logfile=logfile,
                         loginterval=loginterval, **kwargs)
        # the momenta on the constraints' subspace (fixed atoms at rest, no centre-of-mass
        # drift with FixCom, ...), so that the first logged energy is the conserved one
        self._project_momenta(atoms, constraints)

    @property
    def k(self) -> int:
        return self.method.k

    @property
    def s(self) -> int:
        return self.method.s

    @property
    def error_estimate(self) -> float:
        # (documented in the class docstring's Attributes: a docstring here would describe it
        # twice on the API page); reported, never warned
        return self._run_error_prior + (self._stepper.error_estimate
                                        if self._stepper is not None else 0.0)

    @property
    def stage_evaluations(self) -> int:
        return (self._stage_total + (self._system.stage_evaluations if self._system else 0)
                + (self._holonomic.system.stage_evaluations if self._holonomic else 0))

    @property
    def solver_in_use(self) -> str:
        """The iteration the next step starts with: "fixed_point" or "newton" (with
        solver="auto", Newton after a fixed-point failure until fixed point converges again)."""
        return self._stepper.solver if self._stepper is not None else (
            "newton" if self.solver == "newton" else "fixed_point")

    @property
    def solver_switches(self) -> int:
        """Steps that solver="auto" did with Newton after the fixed-point iteration failed
        (each reported by a :class:`SolverSwitchWarning`), over this engine's life."""
        return self._stepper.solver_switches if self._stepper is not None else 0

    @property
    def last_switch(self) -> dict | None:
        """The last switch to Newton: ``t`` and ``h`` in fs, ``why`` in words; None before."""
        sw = self._stepper.last_switch if self._stepper is not None else None
        return None if sw is None else {"t": sw["t"] / units.fs, "h": sw["h"] / units.fs,
                                        "why": sw["why"]}

    def iteration_tol(self, system=None) -> float | None:
        """The stop of the step's iteration (the engine's ``tol``) for ``tol="auto"``: None
        (to round-off) when HBVM(k, s) conserves this calculator's H exactly (a polynomial of
        degree nu with k >= nu s / 2) and for EQUIP; otherwise MD_TOL, 1e-12.

        Why: with a calculator that is not a polynomial the energy error is the quadrature
        error of the line integral (2.8e-10 eV per atom for EMT copper at 5 fs), and the
        coefficients are only known to the stage forces' round-off: the floor of
        ``core.stop_action`` (the stage values' rounding through the force's Lipschitz
        constant) measured 0.8-1.7e-13 of max |gamma| on EMT copper, 108 atoms, 5-20 fs, the
        increments then wandering at 1-5e-14.  The round-off rule waits there until the
        increments stop decreasing: two to three sweeps of k force evaluations that change
        nothing (a quarter of the step at 5 fs).  With tol = 1e-12 the iteration stops once
        its error, estimated from the contraction theta (0.005 at 5 fs to 0.1 at 20 fs on EMT
        copper), is below 1e-12 (``core.stop_action``), and the polish takes it theta times
        closer: within 1e-13, at that floor.  Measured (``benchmarks/bench_md_cost.py``): the
        same energy errors to the digits shown, 30.7 -> 19.2 force evaluations a step for
        HBVM(3, 2) at 5 fs (9.9 -> 6 iterations)."""
        if not (isinstance(self.tol, str) and self.tol == "auto"):
            return self.tol
        if isinstance(self.method, EQUIP):
            return None
        sys_ = self._system if system is None else system
        if sys_ is not None:
            nu = sys_.polynomial_degree
        else:           # before the first step: as the system will be built
            nu = (None if AtomsConstraints(self.atoms).terms
                  else getattr(self.atoms.calc, "polynomial_degree", None))
        exact = nu is not None and self.method.k >= HBVM.for_polynomial_degree(
            max(int(nu), 1), self.s, self.method.nodes).k
        return None if exact else MD_TOL

    def todict(self) -> dict:
        d = super().todict()
        d.update({"method": repr(self.method), "k": self.k, "s": self.s,
                  "nodes": self.method.nodes, "solver": self.solver,
                  "tol": self.tol if isinstance(self.tol, str) else self.iteration_tol(),
                  "energy_tol": self.energy_tol, "adaptive": self.adaptive,
                  "error_estimate": self.error_estimate})
        if self._holonomic is not None:
            # the rigid-bond step integrates the forces' part across the bonds when the full
            # forces make its iteration diverge (integrators.holonomic, "forces along the bonds")
            d["bond_forces_absorbed"] = bool(self._holonomic.stepper.absorbing)
        if self.adaptive:
            d.update({"epsilon": self.epsilon, "inner_steps": self.inner_steps,
                      "inner_rejections": self.inner_rejections})
        return d

    # -- state ---------------------------------------------------------------------------------
    @staticmethod
    def _project_momenta(atoms, constraints: AtomsConstraints) -> None:
        """Write the momenta projected onto the linear constraints' subspace, when that
        changes them (set_momenta without ASE's own adjustments: FixCom's is ours, FixedPlane's
        has none)."""
        if constraints.projector is None:
            return
        p = atoms.get_momenta()
        q = constraints.momenta(p)
        if not np.array_equal(p, q):
            atoms.set_momenta(q, apply_constraint=False)

    def _constraints(self, atoms) -> AtomsConstraints:
        """The constraints as the step applies them, rebuilt only when they changed (a new
        list, or one changed in place: :func:`hbvm_md.ase.constraints.signature`)."""
        sys_ = self._system
        if (sys_ is not None and sys_.atoms is atoms and sys_.n_atoms == len(atoms)
                and sys_.constraints.key == signature(atoms.constraints)
                and np.array_equal(sys_.masses, np.repeat(atoms.get_masses(), 3))):
            return sys_.constraints
        return AtomsConstraints(atoms)

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

    def _in_fs(self, err: ConvergenceError, t_of=None, own_hint: bool = False) -> ConvergenceError:
        """The same error (same type and attributes, h and t in ASE units) with every h and t
        of the message in fs, and a hint in the words of this class (``own_hint``: the error's
        own, e.g. the rigid-bond step's, which has its own iteration and no Newton).  ``t_of``:
        the run's time of an engine time (:meth:`_run_time`), for the step's own time in the
        message (the engine's clock restarts at 0 with every fresh engine); None: the error's
        own t.  The energy check's relative change is given in eV too, against |T| + |V| at the
        step's start (``_energy_scale``)."""
        if t_of is None:
            t_of = lambda t: t          # noqa: E731
        if type(err) is ConvergenceError and not own_hint:
            # "auto" has tried Newton after fixed point: suggest a smaller timestep only
            hint = ("try a smaller timestep, or solver='newton' for a stiff problem"
                    if self.solver == "fixed_point" else "try a smaller timestep")
            if "not finite" in str(err):
                hint = "the forces or the new state are not finite; " + hint
            new = ConvergenceError(err.h, err.residual, err.iterations,
                                   "auto" if self.solver == "auto" else err.solver, err.t, hint)
        else:
            new = copy.copy(err)

        def where(match):       # every "h=... at t=..." (a cause quoted inside a message too)
            try:
                h = float(match.group(1))
                t = None if match.group(2) is None else float(match.group(2))
            except ValueError:
                return match.group(0)
            return (f"h={h / units.fs:.6g} fs"
                    + ("" if t is None else f" at t={t_of(t) / units.fs:.6g} fs"))
        text = str(new)
        if getattr(new, "suggested_h", None) is not None:     # the step that would pass, in fs
            text = text.replace(f"(h={new.suggested_h:.3g} or less",
                                f"(timestep={new.suggested_h / units.fs:.3g} fs or less")
        text = re.sub(r"\bh=([-+0-9.eE]+)(?: at t=([-+0-9.eE]+))?(?![-+0-9.eE]| fs)", where, text)
        # the method's own name (EQUIP's steps are not HBVM's), the timestep in ASE's words
        text = re.sub(r"^HBVM step", f"{type(self.method).__name__} step", text)
        text = text.replace("use a smaller step", "use a smaller timestep")
        if isinstance(new, UnresolvedStepError) and not getattr(new, "suggested_h", None) \
                and not isinstance(new, EnergyDriftError) and np.isfinite(self._energy_scale):
            # the energy check's relative change, in eV too
            text = re.sub(r"changed the energy by (\S+) \(relative\)",
                          lambda m: f"changed the energy by {m.group(1)} (relative, about "
                                    f"{float(m.group(1)) * self._energy_scale:.3g} eV)", text,
                          count=1)
        if self.adaptive:
            # a run with adaptive steps is not advised to take them; HBVMDynamics has no min_dt
            text = text.replace(", or adaptive steps (adaptive=True), which shrink through it", "")
            text = text.replace(", or adaptive steps)", ")").replace(", or adaptive steps;", ";")
            text = text.replace("lower min_dt, raise epsilon, or check the state (two bodies on "
                                "top of each other, a singular force)",
                                "raise epsilon or the timestep's resolution (a larger s), or "
                                "check the structure (two atoms on top of each other, a "
                                "calculator whose forces are not finite or whose energy jumps "
                                "where no cutoff is known)")
            text = text.replace("the smallest step that changes t", "the smallest inner step "
                                "that changes the time")
        new.args = (text,)
        return new

    def _calculator_nonfinite(self, err, system, pos0):
        """``err`` (a NonFiniteError) with a hint that names the calculator when it is the
        calculator that returned forces that are not finite at finite positions (the system
        noted them: :attr:`_AtomsSystem.nonfinite_at`); else ``err`` itself."""
        seen = getattr(system, "nonfinite_at", None)
        if type(err) is not NonFiniteError or seen is None:
            return err
        pos0 = np.asarray(pos0, dtype=float)
        if not np.array_equal(seen[0], pos0):
            # the forces at the start too (one calculator call; the atoms are back there)
            count = system.stage_evaluations
            try:
                system.forces(pos0.reshape(1, -1))
            except Exception:       # (the calculator's own failure: the stage's note stands)
                pass
            system.stage_evaluations = count
            if not np.array_equal(system.nonfinite_at[0], pos0):
                system.nonfinite_at = seen
        X, atom = system.nonfinite_at
        name = type(self.atoms.calc).__name__
        if np.array_equal(X, pos0):
            where = "at the positions the step starts from, so no smaller timestep helps"
        else:
            where = ("at a stage of the step (finite positions near the step's start); "
                     "a smaller timestep keeps the stages closer to it")
        return NonFiniteError(err.h, err.iterations, err.solver, err.t,
                              hint=f"the calculator {name} returned a force that is not finite "
                                   f"(nan or inf) on atom {atom} {where}; check the calculator "
                                   f"(its parameters and its input there)")

    def _current_state(self):
        atoms = self.atoms
        return (np.asarray(atoms.get_positions(), dtype=float).ravel(),
                np.asarray(atoms.get_momenta(), dtype=float).ravel())

    def _ensure_stepper(self, constraints: AtomsConstraints) -> Stepper:
        atoms = self.atoms
        q, p = self._current_state()
        w = self._written
        sys_ = self._system
        fresh = (self._stepper is None or sys_ is None or sys_.calc is not atoms.calc
                 or sys_.n_atoms != len(atoms) or w is None
                 or not (np.array_equal(w[0], q) and np.array_equal(w[1], p))
                 or sys_.constraints is not constraints
                 or not np.array_equal(sys_.masses, np.repeat(atoms.get_masses(), 3)))
        if fresh:
            self._check_atoms(atoms)
            if sys_ is not None:
                self._stage_total += sys_.stage_evaluations
            if self._stepper is not None:
                self._run_error_prior += self._stepper.error_estimate
            batched = hasattr(atoms.calc, "forces_batch")
            kind = _AtomsSystemWithHessian if callable(getattr(atoms.calc, "hessian", None)) else _AtomsSystem
            sys_ = kind(atoms, constraints, batched)
            self._project_momenta(atoms, constraints)
            q, p = self._current_state()
            self._system = sys_
            self._stepper = Stepper(self.method, sys_, np.concatenate([q, p.ravel()]),
                                    solver=self.solver, form="separable",
                                    tol=self.iteration_tol(sys_), energy_tol=self.energy_tol,
                                    error_bound=self.error_bound)
            self._stepper.hints = {"body": "atom {i}",
                                   "resolution": "or a larger s (a higher order resolves more "
                                                 "of the motion in one step)",
                                   "drifted": "give more quadrature nodes (k >= 2s: "
                                              "HBVMDynamics(..., k=2 * s) or more)"}
        return self._stepper

    def _advance(self, st: Stepper) -> np.ndarray:
        """The engine's state one ``timestep`` later: one fixed step, or (``adaptive``) as
        many inner steps as the error needs, the last one landing exactly on the timestep
        (:meth:`integrators.Stepper.step_toward`, the engine's one controller), as IAS15 with
        ``exact_finish_time``: observers, loggers and trajectories keep ASE's meaning.  The
        counters change only when the whole timestep succeeded (a failure restores the engine
        as before it)."""
        if not self.adaptive:
            return st.step(self.dt)
        mark = st.t + self.dt
        h = self._h_inner or self.dt
        steps, rejected = 0, st.rejected
        # an inner step the energy check refuses is tested for the calculator's jump before
        # the controller shrinks it (:meth:`_inner_jump`), as a fixed step is
        st.through_refusal = None if self._through_jump else self._inner_jump
        try:
            while st.t < mark:
                _, h = st.step_toward(mark, h, self.epsilon, 0.0)
                steps += 1
        finally:
            st.through_refusal = None
        self._h_inner = h
        self.inner_steps += steps
        self.inner_rejections += st.rejected - rejected
        _log.debug("HBVMDynamics: t=%.6g fs: %d inner steps (%d rejected), next inner step "
                   "%.3g fs", st.t / units.fs, steps, st.rejected - rejected, h / units.fs)
        return st.y

    def step(self, forces=None):
        """Advance one step; returns the forces (N, 3) at the new positions.

        ``forces`` is accepted for compatibility with ``VelocityVerlet.step`` and not used:
        HBVM evaluates its own stage forces.
        """
        atoms = self.atoms
        if len(atoms) == 0:
            return np.zeros((0, 3))      # nothing moves, as with VelocityVerlet
        if bond_constraints(atoms):
            forces = holonomic_step(self)   # rigid bonds: hbvm_md.ase.holonomic
            self._elapsed += self.dt
            return forces
        st = self._ensure_stepper(self._constraints(atoms))
        if self._hamiltonian_changed(st):
            st = self._new_hamiltonian("the energy at the step's start no longer matches the "
                                       "last step's")
        pos0 = atoms.get_positions()
        mom0 = atoms.get_momenta()
        calc = atoms.calc
        saved_calc = calculator_cache(calc)
        saved_stepper = st.save_state()
        saved_count = self._system.stage_evaluations
        self._system.nonfinite_at = None
        saved_jumps = len(self.jumps)
        switches = st.solver_switches
        per_step = self.stage_evaluations / max(self.nsteps, 1)
        self._clock0 = (self._elapsed, st.t)
        try:
            y = self._advance(st)
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
            del self.jumps[saved_jumps:]        # (an adaptive step's inner jumps: not taken)
            atoms.set_positions(pos0, apply_constraint=False)
            atoms.set_momenta(mom0, apply_constraint=False)
            if saved_calc is not None:
                calc.atoms, calc.results = saved_calc
            else:
                atoms.get_forces(md=True)
            if (isinstance(err, UnresolvedStepError) and saved_calc is not None
                    and self._changed_under_cache(st, saved_calc)):
                # calc.set(...) without calc.reset(): the cached results at the start were
                # the old parameters'; the step again, fresh, with the new ones
                self._new_hamiltonian("the calculator's results at the step's start, computed "
                                      "again, no longer match the last step's energy")
                return self.step()
            if isinstance(err, UnresolvedStepError) and not self._through_jump:
                jumps = self._calculator_jumps(pos0, mom0)
                if jumps:
                    return self._step_through(st, jumps)
            if isinstance(err, StepError):
                try:
                    self._energy_scale = float(atoms.get_kinetic_energy()
                                               + abs(atoms.get_potential_energy()))
                except Exception:
                    self._energy_scale = np.nan
                raise self._in_fs(self._calculator_nonfinite(err, self._system, pos0),
                                  self._run_time) from None
            raise
        if st.solver_switches > switches:
            self._warn_switch(st, per_step)
        self._written = self._current_state()
        self._elapsed = self._clock0[0] + self.dt
        return forces

    # -- a calculator's own discontinuity -----------------------------------------------------
    def _copy_run(self, pos0, mom0, h: float, n: int):
        """(energy change, positions, momenta) after n steps of size h from (pos0, mom0), on a
        copy of the atoms with the same calculator and no energy check."""
        work = self.atoms.copy()
        work.set_positions(pos0, apply_constraint=False)
        work.set_momenta(mom0, apply_constraint=False)
        work.calc = self.atoms.calc
        dyn = HBVMDynamics(work, h, s=self.s, k=self.k, solver=self.solver,
                           nodes=self.method.nodes, tol=self.tol, energy_tol=None,
                           error_bound=None,
                           method="equip" if isinstance(self.method, EQUIP) else "hbvm")
        e0 = work.get_potential_energy() + work.get_kinetic_energy()
        for _ in range(n):
            dyn.step()
        e1 = work.get_potential_energy() + work.get_kinetic_energy()
        return e1 - e0, work.get_positions(), work.get_momenta()

    def _run_time(self, t: float) -> float:
        """The run's time of the engine's time t within the current step: the steps taken
        before it, each of its own timestep (the engine's clock restarts at 0 with every fresh
        engine; ASE's :meth:`get_time`, nsteps times the current timestep, moves when the
        timestep is changed), plus the engine's time since the step's start."""
        return self._clock0[0] + (t - self._clock0[1])

    def _calculator_jumps(self, pos0, mom0, h: float | None = None,
                          t0: float | None = None) -> list:
        """After a step refused for its energy change: the step again at h, h/2 and h/4 on
        copies (:func:`hbvm_md.ase.discontinuity.change_persists`); when the change does not
        shrink, the calculator's jumps on the step (:func:`locate_jumps`), else [].  h: the
        step (default the timestep), t0 its start in the run's time (default the step's).  The
        calculator's cached results are put back."""
        h = self.dt if h is None else h
        t0 = self._clock0[0] if t0 is None else t0
        calc = self.atoms.calc
        saved = calculator_cache(calc)
        try:
            runs = [self._copy_run(pos0, mom0, h / n, n) for n in (1, 2, 4)]
            if not change_persists([r[0] for r in runs]):
                return []
            jumps = locate_jumps(self.atoms, pos0, mom0, runs[0][1], runs[0][2], h, t0,
                                 step=self.nsteps)
        except (ConvergenceError, UnresolvedStepError):
            return []
        finally:
            if saved is not None:
                calc.atoms, calc.results = saved
        if not jumps:
            _log.info("HBVMDynamics: a step's energy change did not shrink with the step but no "
                      "jump of the calculator's energy was found on it")
        return jumps

    def _inner_jump(self, err, h: float) -> bool:
        """An adaptive inner step of size h refused by the energy check (``err``): when its
        energy change does not shrink with the step (:meth:`_calculator_jumps` from the
        engine's state), the calculator's jump is warned (one
        :class:`~hbvm_md.ase.discontinuity.CalculatorDiscontinuityWarning`, as for a fixed
        step) and the inner step taken through it without the energy check and the step's
        own error check (a jump in the force makes its omitted term large at any step); True
        then, False (the controller shrinks the step) otherwise."""
        st = self._stepper
        n = len(self.atoms)
        y = st.y
        jumps = self._calculator_jumps(y[:3 * n].reshape(n, 3), y[3 * n:].reshape(n, 3), h,
                                       self._run_time(st.t))
        if not jumps:
            return False
        warn_jumps(jumps, stacklevel=7)
        etol, ebound = st.energy_tol, st.error_bound
        st.energy_tol = float(np.finfo(float).max)      # (as _step_through: see there)
        st.error_bound = None
        before = st.energy_reference
        try:
            st.step(h)
            st.accept_energy_jump(st.energy_reference - before)
        except StepError:
            return False
        finally:
            st.energy_tol, st.error_bound = etol, ebound
        self.jumps.extend(jumps)
        return True

    def _step_through(self, st: Stepper, jumps: list):
        """The step through the calculator's jumps: warned first (so that a warning made an
        error leaves the step untaken), then taken without the energy check."""
        warn_jumps(jumps, stacklevel=4)
        etol = st.energy_tol
        # a check that passes every change rather than none (None): the engine then still
        # takes the step's end as the next step's energy reference, which None would leave at
        # the start (the next step would see a changed Hamiltonian)
        st.energy_tol = float(np.finfo(float).max)
        # (the force jumps with the energy: the step's own error estimate, whose omitted
        # Legendre term a jump in the force makes large at any step, stands aside too)
        ebound = st.error_bound
        st.error_bound = None
        self._through_jump = True
        before = st.energy_reference
        try:
            forces = self.step()
            # the jump is the calculator's: the run's drift (core.DRIFT_BOUND) is not charged
            st.accept_energy_jump(st.energy_reference - before)
        finally:
            st.energy_tol = etol
            st.error_bound = ebound
            self._through_jump = False
        self.jumps.extend(jumps)
        return forces

    # -- a Hamiltonian changed between steps, the solver policy --------------------------------
    def _hamiltonian_changed(self, st: Stepper) -> bool:
        """Does H at the engine's state (the calculator's energy now, plus the kinetic energy
        and the constraints' terms) differ from the energy the last step ended with?  Both are
        computed by the same code: bit for bit equal unless H changed (a calculator whose
        parameters were set and reset, or replaced by one with other results)."""
        ref = st.energy_reference
        if not np.isfinite(ref):
            return False
        b = st.binding
        T, V = b.step_code.energy_parts(b.full, st.y, b.kin_w, b.params)
        return not abs(T + V - ref) <= CHANGED_H * (abs(T) + abs(V))

    def _changed_under_cache(self, st: Stepper, saved_calc) -> bool:
        """After a step refused for its energy change: is the calculator's energy at the
        step's start, computed again (``calc.reset()``), other than the reference?  Then its
        cached results were stale (``calc.set(...)`` alone keeps them).  If not, the cache is
        put back as it was."""
        calc = self.atoms.calc
        if not callable(getattr(calc, "reset", None)):
            return False
        calc.reset()
        try:
            changed = self._hamiltonian_changed(st)
        except Exception:
            changed = False
        if not changed:
            calc.atoms, calc.results = saved_calc
        return changed

    def _new_hamiltonian(self, why: str) -> Stepper:
        """A fresh engine at the current state for the new H (as a new HBVMDynamics would
        start: the run goes on exactly as a fresh run on the new parameters)."""
        self.hamiltonian_changes += 1
        _log.info("HBVMDynamics: the Hamiltonian changed at t=%.6g fs (%s): the run goes on "
                  "with the new one", self._stepper.t / units.fs, why)
        self._run_error_prior += self._stepper.error_estimate
        self._stepper = None
        return self._ensure_stepper(self._constraints(self.atoms))

    def _warn_switch(self, st: Stepper, per_step: float) -> None:
        sw = st.last_switch
        n3 = 3 * len(self.atoms)
        if isinstance(self._system, _AtomsSystemWithHessian):
            cost = "its matrix comes from the calculator's exact Hessian, one call a step"
        else:
            cost = (f"its matrix comes from finite differences of the forces, {2 * n3} extra "
                    f"force evaluations a step ({len(self.atoms)} atoms), against "
                    f"{per_step:.0f} a step before")
        warnings.warn(f"HBVMDynamics(solver='auto'): the step at t={sw['t'] / units.fs:.6g} fs "
                      f"(h={sw['h'] / units.fs:.6g} fs) was done with Newton's method because "
                      f"{sw['why']}; {cost}. Fixed point is tried again at the next step and "
                      f"kept once it converges (switches so far: {st.solver_switches}; see "
                      f"dyn.solver_in_use, dyn.solver_switches)", SolverSwitchWarning,
                      stacklevel=3)
