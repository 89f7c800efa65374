"""Energy and angular-momentum conservation of HBVM(k, s) against ASE's VelocityVerlet on the
same atoms.

:func:`compare_md` runs every method at every time step from the same positions, the same
calculator and the same seeded Maxwell-Boltzmann velocities, records the total energy at full
precision and the positions and momenta after every step (through an observer; MDLogger prints
3-4 decimals) and returns an :class:`MDComparison` with a table and the error series.  The
angular momentum is the cluster's about its centre of mass
(:func:`hbvm_md.reports.invariants.atoms_angular_momentum`), its change measured as
:mod:`hbvm_md.reports.invariants` defines: a free cluster conserves it, so does VelocityVerlet
to round-off, and HBVM(k, s) with k > s, which is not symplectic, does not.  In a periodic cell
or with constraints L is no invariant (the cell's images and the fixed atoms exert torques): the
column is then nan, printed "-".
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from ase import Atoms, units

from integrators import HBVM

__all__ = ["compare_md", "MDComparison", "default_cluster", "maxwell_boltzmann"]

_COLUMNS = [("method", "method", "{}"), ("dt_fs", "dt [fs]", "{:g}"), ("steps", "steps", "{}"),
            ("max_abs_dE_per_atom_eV", "max abs(E-E0)/N [eV]", "{:.2e}"),
            ("max_rel_dE", "max abs(E-E0)/abs(E0)", "{:.2e}"),
            ("drift_slope", "drift [eV/atom/ps]", "{:.1e}"),
            ("max_rel_dL", "max abs(L-L0)/abs(L0)", "{:.2e}"),
            ("force_evals", "force evals", "{}"), ("wall_time_s", "wall [s]", "{:.3f}")]


@dataclass
class MDComparison:
    """Result of :func:`compare_md`.

    Attributes
    ----------
    rows : list of dict
        One per (method, time step): ``method``, ``dt_fs``, ``steps``, ``max_abs_dE_per_atom_eV``
        (max |E - E0| / N), ``max_rel_dE`` (max |E - E0| / |E0|), ``drift_slope`` (slope of a
        least-squares line through (E - E0) / N against time, eV per atom per ps),
        ``max_rel_dL`` (max |L - L0| / |L0| of the angular momentum about the centre of mass,
        :mod:`hbvm_md.reports.invariants`; nan when the atoms have a periodic direction or
        constraints, where L is not conserved), ``force_evals`` (configurations at which forces were
        computed, including the initial one), ``wall_time_s`` (the run without the observer
        that records the energy and the state: what the integration costs), ``E0_eV`` (initial
        total energy) and ``k``, ``s`` (None for VelocityVerlet).
    series : dict
        label -> (t_ps (steps + 1,), (E - E0) / |E0| (steps + 1,)), label "method dt=... fs".
    angular_momentum_series : dict
        label -> (t_ps (steps + 1,), |L - L0| / |L0| (steps + 1,)), the same labels.
    n_atoms : int
    """

    rows: list = field(default_factory=list)
    series: dict = field(default_factory=dict)
    n_atoms: int = 0
    angular_momentum_series: dict = field(default_factory=dict)

    def table(self) -> str:
        """The rows as a markdown table."""
        head = "| " + " | ".join(c[1] for c in _COLUMNS) + " |"
        rule = "|" + "|".join("---" for _ in _COLUMNS) + "|"
        lines = [head, rule]
        for r in self.rows:
            lines.append("| " + " | ".join("-" if isinstance(r[key], float) and np.isnan(r[key]) else fmt.format(r[key])
                                           for key, _, fmt in _COLUMNS) + " |")
        return "\n".join(lines)

    def row(self, method: str, dt_fs: float | None = None) -> dict:
        """The row of ``method`` (e.g. "VelocityVerlet", "HBVM(4, 2)") at ``dt_fs``."""
        for r in self.rows:
            if r["method"] == method and (dt_fs is None or r["dt_fs"] == dt_fs):
                return r
        raise KeyError(f"no row for method={method!r}, dt_fs={dt_fs!r}; have "
                       f"{[(r['method'], r['dt_fs']) for r in self.rows]}")


def _parse_method(spec):
    """("VelocityVerlet",) / "VelocityVerlet" / ("HBVM", s) / ("HBVM", s, k) / HBVM -> (kind, s, k)."""
    if isinstance(spec, HBVM):
        return "HBVM", spec.s, spec.k
    if isinstance(spec, str):
        spec = (spec,)
    if isinstance(spec, tuple) and spec and spec[0] in ("VelocityVerlet", "VV") and len(spec) == 1:
        return "VelocityVerlet", None, None
    if isinstance(spec, tuple) and spec and spec[0] == "HBVM" and len(spec) in (2, 3):
        s = spec[1]
        k = spec[2] if len(spec) == 3 else None
        HBVM(s if k is None else k, s)   # validates s and k with the tableau's messages
        return "HBVM", s, k
    raise ValueError(f"`methods` entries must be 'VelocityVerlet', ('HBVM', s), ('HBVM', s, k) or "
                     f"an integrators.HBVM (got {spec!r})")


class _CountingCalculator:
    """Counts calls of ``calculator.calculate`` while active (restored on exit)."""

    def __init__(self, calc):
        self.calc, self.count = calc, 0

    def __enter__(self):
        original = self.calc.calculate

        def counted(*args, **kwargs):
            self.count += 1
            return original(*args, **kwargs)
        self.calc.calculate = counted
        return self

    def __exit__(self, *exc):
        del self.calc.calculate
        return False


def maxwell_boltzmann(atoms: Atoms, temperature_K: float, seed: int = 0) -> None:
    """Seeded Maxwell-Boltzmann momenta (``rng=np.random.default_rng(seed)``), then zero total
    momentum (``Stationary``).  ASE >= 3.29 calls the sampler ``thermalize_momenta`` and
    deprecates ``MaxwellBoltzmannDistribution``; both draw the same numbers."""
    from ase.md import velocitydistribution as vd

    rng = np.random.default_rng(seed)
    if hasattr(vd, "thermalize_momenta"):
        vd.thermalize_momenta(atoms, temperature_K, rng=rng)
    else:  # pragma: no cover - ASE < 3.29
        vd.MaxwellBoltzmannDistribution(atoms, temperature_K=temperature_K, rng=rng)
    vd.Stationary(atoms)


def compare_md(atoms: Atoms, calculator=None, timesteps_fs=(1.0,),
               methods=("VelocityVerlet", ("HBVM", 2)), steps: int = 1000,
               temperature_K: float | None = 300.0, seed: int = 0,
               verbose: bool = True) -> MDComparison:
    """Run VelocityVerlet and HBVM(k, s) from the same state and compare energy conservation.

    Parameters
    ----------
    atoms : ase.Atoms
        Initial positions (not modified; every run uses a copy).
    calculator : ase Calculator, optional
        Default ``atoms.calc``.  The same object serves every run, one after the other.
    timesteps_fs : sequence of float
        Time steps in femtoseconds.
    methods : sequence
        Entries "VelocityVerlet", ("HBVM", s) (k chosen by :class:`HBVMDynamics`),
        ("HBVM", s, k) or an :class:`integrators.HBVM`.
    steps : int
        Steps per run.
    temperature_K : float or None
        Initial velocities from ``MaxwellBoltzmannDistribution`` with
        ``rng=np.random.default_rng(seed)`` followed by ``Stationary``; None keeps the momenta
        of ``atoms``.
    seed : int
    verbose : bool
        Print the markdown table.

    Returns
    -------
    MDComparison
    """
    from ase.md.verlet import VelocityVerlet

    from ..ase import HBVMDynamics
    from .invariants import atoms_angular_momentum, change_series

    calc = atoms.calc if calculator is None else calculator
    if calc is None:
        raise ValueError("no calculator: pass `calculator=` or set atoms.calc")
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ValueError(f"`steps` must be an integer >= 1 (got steps={steps!r})")
    dts = [float(dt) for dt in np.atleast_1d(timesteps_fs)]
    if not dts or not all(np.isfinite(dt) and dt > 0 for dt in dts):
        raise ValueError(f"`timesteps_fs` must be positive numbers (got {timesteps_fs!r})")
    specs = [_parse_method(m) for m in methods]
    if not specs:
        raise ValueError("`methods` is empty; give e.g. methods=('VelocityVerlet', ('HBVM', 2))")

    start = atoms.copy()
    start.calc = None
    if temperature_K is not None:
        if not (np.isfinite(temperature_K) and temperature_K >= 0):
            raise ValueError(f"`temperature_K` must be >= 0 or None (got {temperature_K!r})")
        maxwell_boltzmann(start, temperature_K, seed)

    # L is an invariant of a free cluster only: no periodic direction, no constraints
    free = not np.any(start.pbc) and not start.constraints
    result = MDComparison(n_atoms=len(start))
    for dt in dts:
        for kind, s, k in specs:
            a = start.copy()
            if hasattr(calc, "reset"):
                calc.reset()    # every run starts with an empty cache (fair force counts)
            a.calc = calc
            energies, states = [], []
            batch0 = getattr(calc, "batch_evaluations", 0)
            with _CountingCalculator(calc) as counter:
                if kind == "VelocityVerlet":
                    dyn = VelocityVerlet(a, timestep=dt * units.fs)
                    label = "VelocityVerlet"
                else:
                    # (a comparison at equal timesteps measures each method's own error: the
                    # step's own error check, which refuses s = 1 at 5 fs on hot copper, and the
                    # run's drift check are off)
                    dyn = HBVMDynamics(a, timestep=dt * units.fs, s=s, k=k, error_bound=None,
                                       energy_tol=None)
                    label = repr(dyn.method)
                observing = [0.0]

                def observe(a=a, observing=observing):
                    # the time spent recording is left out of the wall time: the diagnostics
                    # are not what a method costs (the same for every method)
                    t1 = time.perf_counter()
                    energies.append(a.get_potential_energy() + a.get_kinetic_energy())
                    states.append((a.get_positions(), a.get_momenta()))
                    observing[0] += time.perf_counter() - t1
                dyn.attach(observe)
                t0 = time.perf_counter()
                dyn.run(steps)
                wall = time.perf_counter() - t0 - observing[0]
            nfev = counter.count + getattr(calc, "batch_evaluations", 0) - batch0
            E = np.array(energies)
            t_ps = np.arange(len(E)) * dt / 1000.0
            dE = E - E[0]
            scale = abs(E[0]) if E[0] != 0 else 1.0
            if free:
                L, L_scale = atoms_angular_momentum(np.array([x for x, _ in states]),
                                                    np.array([p for _, p in states]), a.get_masses())
                dL = change_series(L, L_scale)
            else:
                dL = np.full(len(states), np.nan)
            row = {"method": label, "dt_fs": dt, "steps": steps, "E0_eV": float(E[0]),
                   "max_abs_dE_per_atom_eV": float(np.max(np.abs(dE)) / len(a)),
                   "max_rel_dE": float(np.max(np.abs(dE)) / scale),
                   "drift_slope": float(np.polyfit(t_ps, dE / len(a), 1)[0]),
                   "max_rel_dL": float(np.max(dL)),
                   "force_evals": int(nfev), "wall_time_s": wall,
                   "k": getattr(dyn, "k", None), "s": getattr(dyn, "s", None)}
            result.rows.append(row)
            result.series[f"{label} dt={dt:g} fs"] = (t_ps, dE / scale)
            result.angular_momentum_series[f"{label} dt={dt:g} fs"] = (t_ps, dL)
    if verbose:
        print(result.table())
    return result


def default_cluster(n_atoms: int = 38, epsilon: float = 0.01, spacing: float = 3.8,
                    symbol: str = "Ar"):
    """A droplet of ``n_atoms`` atoms with the all-pairs quartic well
    phi(r) = epsilon ((r / sigma)^4 - 2 (r / sigma)^2), and its calculator.

    sigma is chosen so that the nearest-neighbour distance of the starting structure is
    ``spacing`` (A); ``epsilon`` (eV) is the depth of the pair well.

    H is a polynomial of degree 4, so HBVM(2s, s) conserves it exactly.  The well keeps the
    droplet together (phi grows like r^4, bounded below) and its -r^2 part keeps it from
    collapsing.  The atoms start on the fcc sites nearest to the centre, scaled to the size
    that minimises the potential energy, with zero momenta.

    Returns
    -------
    (ase.Atoms, systems.PolynomialPairPotential)
    """
    from systems.pair_potential import PolynomialPairPotential

    if isinstance(n_atoms, bool) or not isinstance(n_atoms, (int, np.integer)) or n_atoms < 2:
        raise ValueError(f"`n_atoms` must be an integer >= 2 (got n_atoms={n_atoms!r})")
    if not (np.isfinite(epsilon) and epsilon > 0 and np.isfinite(spacing) and spacing > 0):
        raise ValueError(f"`epsilon` and `spacing` must be positive numbers (got epsilon={epsilon!r}, "
                         f"spacing={spacing!r})")
    m = int(np.ceil((n_atoms / 4) ** (1 / 3))) + 2
    g = np.arange(-m, m + 1)
    pts = np.array([(x, y, z) for x in g for y in g for z in g if (x + y + z) % 2 == 0], float)
    centre = np.array([0.25, 0.25, 0.25])   # off-lattice so that shells are not cut symmetrically
    order = np.lexsort((pts[:, 2], pts[:, 1], pts[:, 0], np.round(np.sum((pts - centre) ** 2, 1), 9)))
    X = pts[order[:n_atoms]]
    X -= X.mean(axis=0)
    # E(lambda) = eps (lambda^4 S4 / sigma^4 - 2 lambda^2 S2 / sigma^2) is least at
    # lambda^2 = sigma^2 S2 / S4; the fcc sites are sqrt(2) apart, so lambda = spacing / sqrt(2)
    d2 = np.sum((X[:, None] - X[None]) ** 2, axis=-1)[np.triu_indices(n_atoms, 1)]
    lam = spacing / np.sqrt(2.0)
    sigma = lam / np.sqrt(d2.sum() / (d2 ** 2).sum())
    atoms = Atoms(f"{symbol}{n_atoms}", positions=lam * X)
    calc = PolynomialPairPotential([0.0, -2.0 * epsilon / sigma ** 2, epsilon / sigma ** 4])
    atoms.calc = calc
    return atoms, calc
