"""A calculator's own energy discontinuities, told apart from the integrator's error.

HBVM's step is a line integral: the kinetic energy it adds is its quadrature of the forces'
work along the step's path, so for a calculator whose energy is smooth and whose forces are
its gradient the energy change of a step is the quadrature's error (round-off once k is large
enough), and it falls like h^(2s+1) as the step shrinks.  A calculator whose energy jumps
(EMT at its neighbour list's cutoff, 5.8768 A for copper: 1.6e-5 eV for a Cu2 pair) changes the
energy by the jump however small the step: no integrator can conserve an energy that is not a
function of a continuous path.  This module holds the two tests the ASE host and the audit
(:mod:`hbvm_md.reports.audit`) share:

- :func:`change_persists`: the energy change of an interval, taken in 1, 2 and 4 steps, does
  not fall as the steps shrink (a jump) or does (the integrator's error);
- :func:`locate_jumps`: along a step's path, the pair distances that crossed the calculator's
  cutoff (when it has one) and the energy's jump there, bracketed to a few 1e-9 of the step;
  otherwise the jump is found by bisection of the step in time.

Both evaluate the calculator on a copy of the atoms and put its cached results back.  The path
between the step's ends is the cubic Hermite interpolant of the positions and velocities: for a
jump the path does not matter (the residual below is path-independent for a gradient field), and
it places the crossing within O(h^4) of the true path's.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from ase import units

from .atoms_system import calculator_cache


class CalculatorDiscontinuityWarning(RuntimeWarning):
    """The calculator's energy jumped within a step (a cutoff, a neighbour-list change): the
    step's energy change did not shrink with the step, so it is the calculator's, not the
    integrator's.  The step was accepted on the true path; the energy is not conserved across
    the jump because it is not a continuous function of the positions there."""


#: 3-point Gauss-Legendre on [0, 1]: the work of the forces on a piece of the path (exact for
#: polynomials of degree 5; the pieces used are far below a step once bracketed)
_GAUSS_X = 0.5 + 0.5 * np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)])
_GAUSS_W = np.array([5.0, 8.0, 5.0]) / 18.0
#: a crossing is bracketed to this fraction of the step before the jump is read
BRACKET = 1e-9
#: an energy residual on a bracket below this many units of round-off of the energies is noise
NOISE_ULPS = 1024


@dataclass(frozen=True)
class Jump:
    """One discontinuity of the calculator's energy met by a run.

    Attributes
    ----------
    t : float
        Time of the crossing, fs.
    atoms : tuple of int
        The pair whose distance crossed the cutoff (or, without a known cutoff, the pair
        whose distance changed most at the jump among the nearest).
    distance : float
        Their distance at the jump, A.
    energy : float
        The calculator's energy after minus before the jump, eV (the total energy changes by
        the same amount: the forces do no work across it).
    cutoff : float or None
        The calculator's cutoff the distance crossed, A; None when it has none we know of.
    step : int
        Index of the step (from 0) within the run that found it.
    """

    t: float
    atoms: tuple
    distance: float
    energy: float
    cutoff: float | None = None
    step: int = 0

    def describe(self) -> str:
        where = (f"atoms {self.atoms[0]} and {self.atoms[1]} crossed the calculator's cutoff "
                 f"{self.cutoff:.6g} A" if self.cutoff is not None else
                 f"atoms {self.atoms[0]} and {self.atoms[1]} at {self.distance:.6g} A")
        return f"t={self.t:.6g} fs: {where}, the energy stepped by {self.energy:+.3e} eV"


def calculator_cutoff(calc) -> float | None:
    """The distance beyond which the calculator sees no pair, A, when it declares one: EMT's
    neighbour-list cutoff ``rc_list`` (its energy jumps there), LennardJones' ``rc`` (its energy
    is shifted to 0 there, its forces jump unless ``smooth=True``), or a ``cutoff`` attribute
    that is a number.  None otherwise (the jump is then found by bisection in time)."""
    for get in (lambda c: c.rc_list, lambda c: c.parameters["rc"], lambda c: c.cutoff):
        try:
            rc = get(calc)
        except (AttributeError, KeyError, TypeError):
            continue
        if isinstance(rc, (int, float, np.number)) and not isinstance(rc, bool) and np.isfinite(rc) and rc > 0:
            return float(rc)
    return None


class PathProbe:
    """The calculator along one step's path, on a copy of the atoms.

    The path is the cubic Hermite interpolant tau in [0, 1] -> q(tau) of the step's ends
    (positions q0, q1 (N, 3), velocities v0, v1 in A per ASE time unit, step h in ASE time).
    ``residual(a, b)`` = V(q(b)) - V(q(a)) + int_a^b F(q(tau)) . q'(tau) dtau: zero for a
    smooth calculator whose forces are its energy's gradient (on any path), the jump when the
    piece crosses one, the non-conservative work otherwise.  Use as a context manager: the
    calculator's cached results are put back on exit.
    """

    def __init__(self, atoms, q0, v0, q1, v1, h: float):
        self.calc = atoms.calc
        self.work = atoms.copy()
        self.work.set_constraint()          # the calculator's own energy and forces
        self.work.calc = self.calc
        self.q0, self.q1 = np.asarray(q0, float), np.asarray(q1, float)
        self.d0, self.d1 = h * np.asarray(v0, float), h * np.asarray(v1, float)
        self.calls = 0

    def __enter__(self):
        self._saved = calculator_cache(self.calc)
        return self

    def __exit__(self, *exc):
        if self._saved is not None:
            self.calc.atoms, self.calc.results = self._saved
        return False

    def positions(self, tau: float) -> np.ndarray:
        t2, t3 = tau * tau, tau * tau * tau
        return ((2 * t3 - 3 * t2 + 1) * self.q0 + (t3 - 2 * t2 + tau) * self.d0
                + (-2 * t3 + 3 * t2) * self.q1 + (t3 - t2) * self.d1)

    def velocity(self, tau: float) -> np.ndarray:
        """dq/dtau."""
        t2 = tau * tau
        return ((6 * t2 - 6 * tau) * (self.q0 - self.q1) + (3 * t2 - 4 * tau + 1) * self.d0
                + (3 * t2 - 2 * tau) * self.d1)

    def _at(self, tau: float):
        self.work.set_positions(self.positions(tau), apply_constraint=False)
        self.calls += 1
        return self.work

    def energy(self, tau: float) -> float:
        return float(self._at(tau).get_potential_energy())

    def work_done(self, a: float, b: float) -> float:
        """int_a^b F . q' dtau, 3-point Gauss."""
        w = 0.0
        for x, wt in zip(a + (b - a) * _GAUSS_X, _GAUSS_W):
            F = self._at(x).get_forces()
            w += wt * float(np.sum(F * self.velocity(x)))
        return (b - a) * w

    def residual(self, a: float, b: float) -> float:
        return self.energy(b) - self.energy(a) + self.work_done(a, b)

    def noise(self, *taus) -> float:
        """Round-off of an energy difference at these points (NOISE_ULPS units)."""
        scale = max([1.0] + [abs(self.energy(x)) for x in taus])
        return NOISE_ULPS * np.finfo(float).eps * scale


def _pairs(atoms, positions, cutoff):
    """Pairs i < j within ``cutoff`` at these positions: {(i, j, cell shift): shift @ cell}."""
    from ase.neighborlist import neighbor_list
    a = atoms.copy()
    a.set_constraint()
    a.set_positions(positions, apply_constraint=False)
    if len(a) < 2:
        return {}
    i, j, S = neighbor_list("ijS", a, cutoff)
    keep = i < j
    cell = np.asarray(a.cell[:])
    return {(int(ii), int(jj), tuple(int(x) for x in s)): s @ cell
            for ii, jj, s in zip(i[keep], j[keep], S[keep])}


def crossings(atoms, probe: PathProbe, cutoff: float):
    """The pairs whose distance crosses ``cutoff`` on the probe's path: a list of (tau,
    (i, j), cutoff, lo, hi), the crossing bracketed by bisection to [lo, hi] (BRACKET of the
    step).  The pairs looked at are those within ``cutoff`` plus twice the largest
    displacement of the step at either end; a pair's distance is sampled at 9 points of the
    path, so that a pair that crosses and crosses back within a step is found too."""
    disp = float(np.max(np.linalg.norm(probe.q1 - probe.q0, axis=1), initial=0.0))
    reach = cutoff + 2 * disp + 1e-6
    pairs = _pairs(atoms, probe.q0, reach)
    pairs.update(_pairs(atoms, probe.q1, reach))
    if not pairs:
        return []
    keys = list(pairs)
    I = np.array([k[0] for k in keys])
    J = np.array([k[1] for k in keys])
    shift = np.array([pairs[k] for k in keys])

    def dist(taus, rows=slice(None)):
        X = np.array([probe.positions(x) for x in np.atleast_1d(taus)])      # (n, N, 3)
        return np.linalg.norm(X[:, J[rows]] - X[:, I[rows]] + shift[rows], axis=-1) - cutoff

    grid = np.linspace(0.0, 1.0, 9)
    D = dist(grid)                                        # (9, pairs)
    found = []
    for g, p in zip(*np.nonzero(np.sign(D[:-1]) * np.sign(D[1:]) < 0)):
        lo, hi, f_lo = grid[g], grid[g + 1], D[g, p]
        while hi - lo > BRACKET:
            mid = 0.5 * (lo + hi)
            f = dist(mid, [p])[0, 0]
            if np.sign(f) == np.sign(f_lo):
                lo, f_lo = mid, f
            else:
                hi = mid
        found.append((0.5 * (lo + hi), (int(I[p]), int(J[p])), cutoff, lo, hi))
    return sorted(found)


def bisect_jump(probe: PathProbe, levels: int = 32):
    """Bisection of the step in time for a jump: the half with the larger residual, ``levels``
    times, or until the residual is round-off (no jump).  Returns (lo, hi, residual on
    [lo, hi], the whole step's residual); a jump keeps its size while the bracket shrinks,
    non-conservative work and the quadrature's error shrink with it."""
    energy = {}

    def V(x):
        if x not in energy:
            energy[x] = probe.energy(x)
        return energy[x]

    def residual(a, b):
        return V(b) - V(a) + probe.work_done(a, b)

    lo, hi = 0.0, 1.0
    whole = r = residual(lo, hi)
    noise = probe.noise(0.0, 1.0)
    for _ in range(levels):
        if abs(r) <= noise:
            break
        mid = 0.5 * (lo + hi)
        r_left, r_right = residual(lo, mid), residual(mid, hi)
        if abs(r_left) >= abs(r_right):
            hi, r = mid, r_left
        else:
            lo, r = mid, r_right
    return lo, hi, r, whole


def _nearest_changed(atoms, probe: PathProbe, lo: float, hi: float):
    """Without a cutoff: among each atom's nearest neighbours, the pair whose distance changed
    most over the step; its distance at the jump."""
    X0, X1 = probe.positions(0.0), probe.positions(1.0)
    n = len(X0)
    if n < 2:
        return (0, 0), 0.0
    a = atoms.copy()
    a.set_constraint()
    best, pair = -1.0, (0, 1)
    a.set_positions(X0, apply_constraint=False)
    D0 = a.get_all_distances(mic=any(a.pbc))
    a.set_positions(X1, apply_constraint=False)
    D1 = a.get_all_distances(mic=any(a.pbc))
    np.fill_diagonal(D0, np.inf)
    for i in range(n):
        for j in np.argsort(D0[i])[: min(12, n - 1)]:
            change = abs(D1[i, j] - D0[i, j])
            if change > best:
                best, pair = change, (min(i, int(j)), max(i, int(j)))
    a.set_positions(probe.positions(0.5 * (lo + hi)), apply_constraint=False)
    return pair, float(a.get_distance(*pair, mic=any(a.pbc)))


def locate_jumps(atoms, q0, p0, q1, p1, h: float, t0: float, step: int = 0,
                 bisect: bool = True, seen: list | None = None) -> list:
    """The calculator's energy jumps on the step from (q0, p0) at t0 to (q1, p1), h later.

    ``atoms`` gives the calculator, masses, cell and pbc (it is not moved); positions (N, 3)
    in A, momenta (N, 3) in ASE units, h and t0 in ASE time.  With a known cutoff
    (:func:`calculator_cutoff`) every pair that crossed it is looked at and the energy's jump
    read on a bracket of BRACKET of the step around the crossing; without one (or when no
    crossing jumps and ``bisect``), the step is bisected in time.  Returns a list of
    :class:`Jump` (empty when the energy has no jump on this step above round-off); every
    crossing of the cutoff, with a jump or not, is appended to ``seen`` as (tau, (i, j)), tau
    the fraction of the step."""
    m = np.asarray(atoms.get_masses(), float)[:, None]
    q0, q1 = np.asarray(q0, float).reshape(-1, 3), np.asarray(q1, float).reshape(-1, 3)
    v0, v1 = np.asarray(p0, float).reshape(-1, 3) / m, np.asarray(p1, float).reshape(-1, 3) / m
    jumps = []
    with PathProbe(atoms, q0, v0, q1, v1, h) as probe:
        cutoff = calculator_cutoff(atoms.calc)
        if cutoff is not None:
            for tau, pair, d, lo, hi in crossings(atoms, probe, cutoff):
                if seen is not None:
                    seen.append((tau, pair))
                a, b = max(0.0, lo - BRACKET), min(1.0, hi + BRACKET)
                r = probe.residual(a, b)
                if abs(r) > probe.noise(a, b):
                    jumps.append(Jump(float((t0 + tau * h) / units.fs), pair, d, float(r), cutoff, step))
        if not jumps and bisect:
            lo, hi, r, whole = bisect_jump(probe)
            # a jump keeps its size on the final bracket (2^-32 of the step); work spread over
            # the step would have shrunk by that factor
            if hi - lo < 1e-8 and abs(r) > probe.noise(lo, hi) and abs(r) > 1e-6 * abs(whole):
                pair, d = _nearest_changed(atoms, probe, lo, hi)
                jumps.append(Jump(float((t0 + 0.5 * (lo + hi) * h) / units.fs), pair, d, float(r),
                                  None, step))
    return jumps


def change_persists(changes) -> bool:
    """Is the energy change of one interval, taken in 1, 2 and 4 steps (``changes``, eV),
    the calculator's rather than the integrator's?  An integrator error of order 2s >= 2 over a
    fixed interval falls at least 4 times at each halving of the step (16 times over the two);
    a jump keeps its size (the quadrature's error at the force's kink that comes with it falls
    like the step).  The change in 4 steps still at least half of that in one is a jump."""
    d1, d2, d4 = (abs(float(c)) for c in changes)
    return d1 > 0 and d4 >= 0.5 * d1 and d2 >= 0.5 * d1


def warn_jumps(jumps, stacklevel: int = 3) -> None:
    """One :class:`CalculatorDiscontinuityWarning` naming the jumps of one step."""
    what = "; ".join(j.describe() for j in jumps)
    warnings.warn(f"HBVMDynamics: the calculator's energy is not continuous here ({what}): the "
                  f"step's energy change did not shrink with the step (tried at h/2 and h/4), "
                  f"so it is the calculator's jump, not the integrator's error; no integrator "
                  f"can conserve an energy that jumps. The step was accepted and the run goes on "
                  f"on the true path (an audit of the calculator: hbvm_md.audit)",
                  CalculatorDiscontinuityWarning, stacklevel=stacklevel)
