"""A conservation audit of an ASE calculator, from HBVM's own line integral.

HBVM's step is a line integral: the kinetic energy a step adds is its quadrature of the work of
the calculator's forces along the step's path (exactly so in the separable form, T being
quadratic).  So the change of the total energy over a step is

    dH = (work of the forces) + (change of the calculator's energy)
       = jumps of the energy  +  non-conservative work  +  the quadrature's error and round-off,

and with k large enough the last term is round-off for a smooth calculator.  :func:`audit` runs
constant-energy HBVM on the atoms and separates the three:

- ``jumps``: a step whose energy change comes from a discontinuity of the calculator's energy
  (a cutoff, a neighbour list) is found where a pair crossed the calculator's cutoff, or, for a
  step whose change stands out, by bisection of the step in time
  (:func:`hbvm_md.ase.discontinuity.locate_jumps`); the jump is read on a bracket of 1e-9 of
  the step, where nothing else is left;
- ``nonconservative_work``: the rest of the energy change once the jumps are taken out
  (forces that are not the energy's gradient);
- ``integrator_error``: the part of that rest which is the quadrature's and round-off's,
  estimated by repeating a sample of steps with k + 4 nodes (the difference is the quadrature
  error of the run's k), plus the quadrature's error at the force's kink on the steps with a
  jump or a crossing of the cutoff (those steps done again in pieces that meet at the crossing:
  the difference is the run's step's error at the forces' kink) and the energies' round-off.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from ase import units

from hbvm_md.ase.atoms_system import calculator_cache
from hbvm_md.ase.discontinuity import calculator_cutoff, locate_jumps

#: nodes added to k for the repeated steps that measure the quadrature's share
K_EXTRA = 4
#: a step is looked at by bisection when its energy change exceeds this many times both its
#: neighbours' (and the round-off): a jump stands out of the smooth work around it
SPIKE = 8.0
#: at most this many such steps are bisected (the largest), each costs up to ~200 calculator
#: calls (a step with no jump stops once the residual is round-off)
MAX_BISECTED = 20
#: a step is split at a crossing no nearer its ends than this fraction of it
SPLIT_MARGIN = 1e-9
#: the audit's parts are separated when the integrator's share is below this fraction of them
MEANINGFUL = 1e-2
#: atoms whose largest displacement over the run is at most this (A) did not move: the audit
#: has then tested nothing (a structure at rest in its equilibrium)
STILL = 1e-8


@dataclass
class AuditReport:
    """What :func:`audit` found.  Energies in eV, times in fs.

    Attributes
    ----------
    jumps : list of hbvm_md.ase.discontinuity.Jump
        Each discontinuity of the calculator's energy met: ``t`` (fs), ``atoms`` (the pair),
        ``distance`` (A), ``energy`` (the step in eV), ``cutoff``, ``step``.
    nonconservative_work : float
        The work of the forces along the path (HBVM's quadrature) minus the calculator's
        energy change, the jumps taken out, eV.  Zero, up to
        ``integrator_error``, for forces that are the energy's gradient.
    integrator_error : float
        The quadrature's and round-off's share of the run's energy change, eV (an estimate:
        see the module's docstring).  The audit separates the other parts only when this is
        far below them (:attr:`meaningful`).
    kink_error : float
        The part of ``integrator_error`` measured on the steps across the calculator's cutoff
        (or a jump found by bisection): the quadrature's error where the forces jump (those
        steps done again in pieces that meet at the crossings tell it), eV.  Measured, not
        estimated: it falls like the step.
    uncertainty : float
        The estimated part of ``integrator_error`` (the quadrature's share elsewhere, the
        round-off, and how much the steps across the cutoff change when their pieces are
        halved): how far the split between jumps and non-conservative work can be off, eV.
    energy_change : float
        H at the end minus H at the start, eV (the sum of the jumps, the non-conservative work
        and the integrator's part).
    t, kinetic, potential : ndarray, shape (steps + 1,)
        Time (fs), kinetic and potential energy (eV) step by step.
    step_change, step_jump, step_nonconservative : ndarray, shape (steps,)
        Each step's energy change, its jumps, and its non-conservative work.
    method, timestep, steps, calculator, n_atoms, seconds, force_calls
        The run: HBVM(k, s), the step in fs, the number of steps, the calculator's class name,
        the atoms, the audit's wall time and its calculator calls (steps and checks).
    """

    jumps: list
    nonconservative_work: float
    integrator_error: float
    kink_error: float
    uncertainty: float
    energy_change: float
    t: np.ndarray
    kinetic: np.ndarray
    potential: np.ndarray
    step_change: np.ndarray
    step_jump: np.ndarray
    step_nonconservative: np.ndarray
    method: str
    timestep: float
    steps: int
    calculator: str
    n_atoms: int
    seconds: float = 0.0
    force_calls: int = 0
    notes: list = field(default_factory=list)
    displacement: float = float("nan")

    @property
    def moved(self) -> bool:
        """Did the atoms move during the run (largest displacement above :data:`STILL`)?  A
        structure at rest in equilibrium (no momenta and no force) stays where it is: its
        energy is trivially kept and nothing was audited."""
        return not self.displacement <= STILL

    @property
    def total(self) -> np.ndarray:
        return self.kinetic + self.potential

    @property
    def jump_energy(self) -> float:
        """Sum of the jumps, eV."""
        return float(sum(j.energy for j in self.jumps))

    @property
    def meaningful(self) -> bool:
        """Is the uncertain part of the integrator's share far (MEANINGFUL) below the
        calculator's parts?  A run with no jump and no non-conservative work above it is also
        meaningful: the calculator is then conservative to within ``uncertainty``."""
        parts = abs(self.nonconservative_work) + sum(abs(j.energy) for j in self.jumps)
        return self.uncertainty <= MEANINGFUL * parts or parts <= 2 * self.uncertainty

    def __str__(self) -> str:
        n = len(self.jumps)
        lines = [f"Conservation audit of {self.calculator} ({self.n_atoms} atoms): {self.method}, "
                 f"{self.steps} steps of {self.timestep:.6g} fs ({self.t[-1] - self.t[0]:.6g} fs)",
                 f"  energy change            {self.energy_change:+.3e} eV",
                 f"  jumps of the energy      {self.jump_energy:+.3e} eV in {n} jump{'s' * (n != 1)}"]
        for j in self.jumps[:10]:
            lines.append(f"    {j.describe()}")
        if n > 10:
            lines.append(f"    ... and {n - 10} more (report.jumps)")
        lines += [f"  non-conservative work    {self.nonconservative_work:+.3e} eV",
                  f"  integrator's share       {self.integrator_error:.1e} eV (a sum of "
                  f"magnitudes, |quadrature| + |kink| + |round-off|: a bound, not a signed "
                  f"part of the change)"]
        if self.kink_error:
            lines.append(f"    of which at the force's jump on the steps across the cutoff "
                         f"{self.kink_error:.1e} eV (measured; it falls with the step)")
        lines.append(f"    of which estimated (quadrature, round-off, pieces halved) "
                     f"{self.uncertainty:.1e} eV")
        parts = abs(self.nonconservative_work) + sum(abs(j.energy) for j in self.jumps)
        if not self.moved:
            lines.append(f"  The atoms did not move (largest displacement {self.displacement:.1e} "
                         "A over the run: no momenta and no force to start them): nothing was "
                         "audited. Start them moving: momenta in the structure, or "
                         "thermalize_momenta (hbvm-md audit --temperature K).")
        elif parts <= 2 * self.uncertainty:
            lines.append("  The calculator conserves its energy on this path: no jump and no "
                         "non-conservative work above the estimated part of the integrator's "
                         "share.")
        elif self.meaningful:
            lines.append("  The integrator's share is far below the calculator's own defects: "
                         "what is reported above is the calculator's.")
        else:
            lines.append("  The integrator's share is NOT far below the calculator's parts: the "
                         "split is uncertain; audit with a smaller timestep or a larger k.")
        lines += [f"  note: {x}" for x in self.notes]
        return "\n".join(lines)

    def plot(self, path=None, ax=None):
        """The energy's parts against time: the total energy change, the jumps and the
        non-conservative work accumulated, and the integrator's share (as a band).  Draws on
        ``ax`` (a matplotlib Axes) or a new figure, saved to ``path`` when given; returns the
        figure."""
        import matplotlib
        if ax is None and path is not None:
            matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt
        if ax is None:
            fig, ax = plt.subplots(figsize=(7, 4))
        else:
            fig = ax.figure
        t = self.t
        zero = np.zeros(1)
        ax.plot(t, self.total - self.total[0], label="total energy change", color="k")
        ax.plot(t, np.concatenate([zero, np.cumsum(self.step_jump)]), label="jumps", color="C3")
        ax.plot(t, np.concatenate([zero, np.cumsum(self.step_nonconservative)]),
                label="non-conservative work", color="C0")
        ax.axhspan(-self.integrator_error, self.integrator_error, color="C2", alpha=0.2,
                   label="integrator's share")
        ax.set_xlabel("t [fs]")
        ax.set_ylabel("energy [eV]")
        ax.set_title(f"{self.calculator}: {self.method}, {self.timestep:.6g} fs")
        ax.legend(loc="best", fontsize="small")
        if path is not None:
            fig.savefig(path, dpi=120, bbox_inches="tight")
        return fig


def _check(atoms, timestep, steps):
    if atoms.calc is None:
        raise ValueError("`atoms` has no calculator; set atoms.calc before the audit")
    if (isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1):
        raise ValueError(f"`steps` must be a positive integer (got steps={steps!r})")
    if (isinstance(timestep, bool) or not isinstance(timestep, (int, float, np.number))
            or not np.isfinite(timestep) or timestep <= 0):
        raise ValueError(f"`timestep` must be a positive number in ASE time units, e.g. "
                         f"1 * ase.units.fs (got timestep={timestep!r})")


def _copy(atoms, q, p):
    work = atoms.copy()
    work.calc = atoms.calc
    work.set_positions(q, apply_constraint=False)
    work.set_momenta(p, apply_constraint=False)
    return work


def _advance(work, h, options) -> None:
    from hbvm_md.ase import HBVMDynamics
    HBVMDynamics(work, h, energy_tol=None, **options).step()


def _energy(work) -> float:
    return work.get_potential_energy() + work.get_kinetic_energy()


def _change(atoms, q, p, steps, options) -> float:
    """H after minus H before the steps ``steps`` (sizes, ASE time) from (q, p), on a copy of
    the atoms with the same calculator."""
    work = _copy(atoms, q, p)
    e0 = _energy(work)
    for h in steps:
        _advance(work, h, options)
    return _energy(work) - e0


def _split_change(atoms, q, p, h, cuts, options, cutoff):
    """H after minus H before the step h from (q, p) done in pieces that end at the
    crossings ``cuts`` (sorted (tau, pair or None), tau the fraction of the step).  A piece
    ending at a pair's crossing of ``cutoff`` is sized (Newton on the pair's radial velocity,
    at most 5 corrections) so that the pair's distance at its end, on HBVM's own path, is the
    cutoff to 1e-13 of it: a piece that overshot by dd would keep an error of (the force's
    jump) x dd (Hermite's crossing alone left 1e-5 eV over 12 crossings of LJ13 at 2 fs).
    Returns the change and the pieces' sizes."""
    work = _copy(atoms, q, p)
    e0 = _energy(work)
    mic = bool(np.any(work.pbc))
    done = 0.0
    pieces = []
    for tau, pair in cuts:
        dt = (tau - done) * h
        start = work.get_positions(), work.get_momenta()
        for _ in range(6):
            _advance(work, dt, options)
            if pair is None or cutoff is None:
                break
            i, j = pair
            d = work.get_distance(i, j, mic=mic)
            unit = work.get_distance(i, j, mic=mic, vector=True) / d
            v = work.get_velocities()
            u = float(np.dot(v[j] - v[i], unit))
            if abs(d - cutoff) <= 1e-13 * cutoff or u == 0.0:
                break
            new = dt - (d - cutoff) / u
            if not 0.0 < new / h < 1.0 - done:
                break
            dt = new
            work.set_positions(start[0], apply_constraint=False)
            work.set_momenta(start[1], apply_constraint=False)
        done += dt / h
        pieces.append(dt)
    if done < 1.0:
        _advance(work, (1.0 - done) * h, options)
        pieces.append((1.0 - done) * h)
    return _energy(work) - e0, pieces


def audit(atoms, timestep: float, steps: int, *, s: int = 2, k: int | None = None, tol=None,
          sample: int = 8, **hbvm_options) -> AuditReport:
    """Audit the conservation of ``atoms.calc`` along a constant-energy HBVM run.

    Parameters
    ----------
    atoms : ase.Atoms
        With its calculator, constraints and momenta as the run should start; it is advanced
        by ``steps`` steps as :class:`hbvm_md.HBVMDynamics` would.
    timestep : float
        In ASE time units (``1 * ase.units.fs``).
    steps : int
    s, k, tol
        HBVM(k, s) and the iteration's tolerance.  Defaults: s = 2, k = s + 4 and the
        iteration to round-off (tol None), so that for a smooth calculator the quadrature's
        error is round-off and what remains is the calculator's.
    sample : int
        Steps repeated with k + 4 nodes to measure the quadrature's share (half the steps with
        the largest energy change, half spread over the run).
    **hbvm_options
        Passed to :class:`hbvm_md.HBVMDynamics` (``solver``, ``nodes``, ``method``, ``logfile``,
        ``trajectory``); ``energy_tol`` is the audit's (None: the run is not refused at a jump).

    Returns
    -------
    AuditReport
        ``print(report)`` for a summary, ``report.plot()`` for the parts against time.
    """
    _check(atoms, timestep, steps)
    if "energy_tol" in hbvm_options:
        raise TypeError("audit() runs without the step's energy check (energy_tol=None): the "
                        "jumps it looks for are what that check refuses; do not pass energy_tol")
    k = s + K_EXTRA if k is None else k
    options = dict(s=s, k=k, tol=tol, **hbvm_options)
    copy_options = {key: v for key, v in options.items() if key not in ("logfile", "trajectory",
                                                                          "loginterval")}
    calls = _CallCounter(atoms.calc)
    try:
        return _audit(atoms, float(timestep), steps, options, copy_options, k, sample, calls)
    finally:
        calls.finish()


def _audit(atoms, h, steps, options, copy_options, k, sample, calls) -> AuditReport:
    from hbvm_md.ase import HBVMDynamics
    calc = atoms.calc
    started = time.perf_counter()
    dyn = HBVMDynamics(atoms, h, energy_tol=None, **options)
    n = len(atoms)
    Q = np.empty((steps + 1, n, 3))
    P = np.empty((steps + 1, n, 3))
    T = np.empty(steps + 1)
    V = np.empty(steps + 1)

    def record(i):
        Q[i], P[i] = atoms.get_positions(), atoms.get_momenta()
        T[i], V[i] = atoms.get_kinetic_energy(), atoms.get_potential_energy()

    record(0)
    t0 = dyn._stepper.t if dyn._stepper is not None else 0.0
    for i in range(steps):
        dyn.run(1)
        record(i + 1)
    H = T + V
    dH = np.diff(H)
    scale = np.maximum(np.abs(T[:-1]) + np.abs(V[:-1]), np.abs(T[1:]) + np.abs(V[1:]))
    floor = 64 * np.finfo(float).eps * scale

    # -- the jumps: crossings of a declared cutoff, then steps that stand out ---------------
    saved = calculator_cache(calc)
    jumps_at = {}
    crossed = {}            # step -> the fractions of it where a pair crossed the cutoff
    cutoff = calculator_cutoff(calc)
    if cutoff is not None:
        for i in range(steps):
            seen = []
            found = locate_jumps(atoms, Q[i], P[i], Q[i + 1], P[i + 1], h, t0 + i * h, step=i,
                                 bisect=False, seen=seen)
            if found:
                jumps_at[i] = found
            if seen:
                crossed[i] = sorted(seen, key=lambda c: c[0])
    # a step whose change stands out of both its neighbours' (the quadrature's error and the
    # non-conservative work vary smoothly from step to step along a resolved path)
    size = np.abs(dH)
    around = np.maximum(np.concatenate([[0.0], size[:-1]]), np.concatenate([size[1:], [0.0]]))
    if steps == 1:
        around[:] = 0.0
    spikes = [int(i) for i in np.argsort(-size)
              if size[i] > SPIKE * around[i] and size[i] > floor[i] and i not in crossed]
    notes = []
    if len(spikes) > MAX_BISECTED:
        notes.append(f"{len(spikes)} steps stood out of the run's energy changes; the "
                     f"{MAX_BISECTED} largest were bisected for jumps")
    for i in spikes[:MAX_BISECTED]:
        found = locate_jumps(atoms, Q[i], P[i], Q[i + 1], P[i + 1], h, t0 + i * h, step=int(i),
                             bisect=True)
        found = [j for j in found if cutoff is None or j.cutoff is None]
        if found:
            jumps_at[int(i)] = found
    if saved is not None:
        calc.atoms, calc.results = saved
    jumps = [j for i in sorted(jumps_at) for j in jumps_at[i]]

    # a step across the cutoff (with a jump of the energy or only of the forces) or with a
    # jump found by bisection, done again in pieces that end and start where it crossed: each
    # piece has smooth forces, so their change less the jumps is the step's non-conservative
    # work; the run's own step differs from it by the quadrature's error at the force's kink
    step_jump = np.zeros(steps)
    step_nc = dH.copy()
    kink = 0.0
    for i, found in jumps_at.items():
        step_jump[i] = sum(j.energy for j in found)
        if i not in crossed:
            crossed[i] = sorted((((j.t * units.fs - (t0 + i * h)) / h, None) for j in found),
                                key=lambda c: c[0])
    saved = calculator_cache(calc)
    check = 0.0
    for i, taus in crossed.items():
        cuts = [c for c in taus if SPLIT_MARGIN < c[0] < 1 - SPLIT_MARGIN]
        if cuts:
            split, pieces = _split_change(atoms, Q[i], P[i], h, cuts, copy_options, cutoff)
            # the same pieces each in two halves: a crossing the path's interpolant missed
            # (a pair grazing the cutoff) leaves a kink inside a piece, whose error changes
            # with the piece.  (The halves end off the crossings by their own position error,
            # so this also counts the forces' jump times that offset: an upper bound.)
            finer = _change(atoms, Q[i], P[i], [x / 2 for x in pieces for _ in (0, 1)],
                            copy_options)
            check += abs(finer - split)
        else:
            split = step_jump[i]
        step_nc[i] = split - step_jump[i]
        kink += abs(dH[i] - split)
    if saved is not None:
        calc.atoms, calc.results = saved
    smooth = np.ones(steps, bool)
    smooth[list(crossed)] = False
    if crossed and not jumps_at:
        notes.append(f"pairs crossed the calculator's cutoff ({cutoff:.6g} A) on {len(crossed)} "
                     f"step{'s' * (len(crossed) != 1)} without a jump of its energy: where its "
                     f"forces jump instead (LennardJones without smooth=True), the quadrature's "
                     f"error across them is the 'force's jump' part of the integrator's share")

    # -- the integrator's share: a sample of steps again with k + K_EXTRA nodes -------------
    quadrature = 0.0
    candidates = np.flatnonzero(smooth)
    if candidates.size and sample > 0:
        largest = candidates[np.argsort(-np.abs(dH[candidates]))][: (sample + 1) // 2]
        spread = candidates[np.linspace(0, candidates.size - 1, sample // 2).astype(int)]
        picked = sorted(set(largest.tolist()) | set(spread.tolist()))
        high = dict(copy_options, k=k + K_EXTRA)
        saved = calculator_cache(calc)
        ratio = 0.0
        for i in picked:
            e = abs(dH[i] - _change(atoms, Q[i], P[i], (h,), high))
            ratio = max(ratio, min(1.0, e / max(abs(dH[i]), floor[i])))
        if saved is not None:
            calc.atoms, calc.results = saved
        quadrature = ratio * float(np.sum(np.abs(dH[candidates])))
    round_off = float(np.sqrt(steps) * np.max(floor)) if steps else 0.0
    integrator_error = quadrature + kink + round_off
    uncertainty = quadrature + round_off + check
    atoms.get_forces()      # the calculator's cache at the atoms, as after a normal run
    return AuditReport(
        jumps=jumps, nonconservative_work=float(np.sum(step_nc)),
        integrator_error=integrator_error, kink_error=kink, uncertainty=uncertainty,
        energy_change=float(H[-1] - H[0]),
        t=(t0 + h * np.arange(steps + 1)) / units.fs, kinetic=T, potential=V,
        step_change=dH, step_jump=step_jump, step_nonconservative=step_nc,
        method=repr(dyn.method), timestep=h / units.fs, steps=steps,
        calculator=type(calc).__name__, n_atoms=n, seconds=time.perf_counter() - started,
        force_calls=calls.count, notes=notes,
        displacement=float(np.max(np.linalg.norm(Q - Q[0], axis=-1), initial=0.0)))


class _CallCounter:
    """Counts the calculator's calculations during the audit (wraps ``calculate`` on the
    instance, removed by :meth:`finish`)."""

    def __init__(self, calc):
        self.calc, self.count = calc, 0
        self.wrapped = callable(getattr(calc, "calculate", None)) and "calculate" not in vars(calc)
        if self.wrapped:
            inner = calc.calculate

            def calculate(*args, **kwargs):
                self.count += 1
                return inner(*args, **kwargs)
            calc.calculate = calculate

    def finish(self) -> int:
        if self.wrapped:
            self.wrapped = False
            del self.calc.calculate
        return self.count
