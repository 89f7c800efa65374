"""Benchmark (not a test): the conservation audit (``hbvm_md.audit``, issue 50) against the
drift a VelocityVerlet run of the same length reports, and a Cu2 collision through EMT's
cutoff (issue 46, item 4).

* **Cu2 through EMT's cutoff**: a head-on Cu2 pair (6 A apart, 0.03 A/fs each) collides and
  separates, crossing EMT's neighbour-list cutoff (5.8768 A, where the energy steps by
  1.6e-5 eV) twice.  ``HBVMDynamics`` at 1 and 0.5 fs (defaults) against VelocityVerlet at
  0.01 fs over 200 fs: the warnings (one a crossing), the largest position difference, and the
  run's time.  Before issue 46 item 4 the run stopped at the first crossing.
* **Audits**: per scene, ``hbvm_md.audit(atoms, dt, steps)`` (HBVM(6, 2), iteration to
  round-off, 8 steps repeated with k = 10) and ``VelocityVerlet(atoms, dt).run(steps)`` from
  the same start, each timed in the same process (rounds interleaved, fastest kept).
  Reported: the time ratio and the calculator calls ratio (audit against Verlet), what the audit
  found (jumps, non-conservative work, the integrator's share) and what Verlet reports: the
  drift (slope of a linear fit of E(t), eV/ps) and the largest |E(t) - E(0)| (eV), where the
  integrator's error and the calculator's defects are one number.

  Scenes: EMT copper (fcc, 2 x 2 x 2 cubic cells, periodic, 600 K: its fifth neighbours at
  5.71 A cross the cutoff at 5.8768 A as they vibrate); ASE's
  LennardJones on a 13-atom argon-like cluster (sigma 1 A, epsilon 1 eV) with its plain cutoff
  (rc = 1.9 A: forces jump there, the energy does not), with ``smooth=True`` (ro = 1.45,
  rc = 2.8 A) and the same with forces scaled by 1.03 (not the energy's gradient).

    python benchmarks/bench_audit.py [--steps 200] [--repeat 2] [--quick]

Writes ``benchmarks/results/audit.md``.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time
import warnings

import numpy as np
from ase import units
from ase.calculators.emt import EMT
from ase.calculators.lj import LennardJones
from ase.build import bulk
from ase.md.verlet import VelocityVerlet
from ase.md.velocitydistribution import thermalize_momenta

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hbvm_md import HBVMDynamics, audit                                       # noqa: E402
from hbvm_md.ase.discontinuity import CalculatorDiscontinuityWarning          # noqa: E402
from hbvm_md.reports.machine import machine                                   # noqa: E402
from hbvm_md.reports.audit_scenes import ScaledForcesLJ, cu2_pair, lj_cluster  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "audit.md"


def cu2(distance=6.0, speed=0.03):
    return cu2_pair(distance, speed)


def cu_crystal():
    atoms = bulk("Cu", cubic=True) * (2, 2, 2)
    thermalize_momenta(atoms, temperature_K=600, rng=np.random.default_rng(3))
    atoms.calc = EMT()
    return atoms


SCENES = {
    "EMT Cu fcc 32 atoms (periodic), 600 K, 2 fs": (cu_crystal, 2.0),
    "LJ13, plain cutoff rc = 1.9 A, 2 fs": (lambda: lj_cluster(LennardJones(rc=1.9)), 2.0),
    "LJ13, smooth=True (ro 1.45, rc 2.8 A), 2 fs":
        (lambda: lj_cluster(LennardJones(smooth=True, rc=2.8, ro=1.45)), 2.0),
    "LJ13 smooth, forces x 1.03, 2 fs":
        (lambda: lj_cluster(ScaledForcesLJ(smooth=True, rc=2.8, ro=1.45)), 2.0),
}


class Counting:
    """Counts a calculator's calculations."""

    def __init__(self, calc):
        self.n = 0
        inner = calc.calculate

        def calculate(*a, **k):
            self.n += 1
            return inner(*a, **k)
        calc.calculate = calculate


def collision(dt_fs: float, t_fs: float = 200.0):
    atoms = cu2()
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        HBVMDynamics(atoms, dt_fs * units.fs).run(int(round(t_fs / dt_fs)))
    took = time.perf_counter() - t0
    n = sum(issubclass(w.category, CalculatorDiscontinuityWarning) for w in seen)
    return atoms, took, n, [str(w.message) for w in seen]


def verlet(make, dt_fs, steps):
    atoms = make()
    count = Counting(atoms.calc)
    energies = [atoms.get_total_energy()]
    dyn = VelocityVerlet(atoms, dt_fs * units.fs)
    dyn.attach(lambda: energies.append(atoms.get_total_energy()))
    t0 = time.perf_counter()
    dyn.run(steps)
    took = time.perf_counter() - t0
    e = np.array(energies[1:])
    t = dt_fs * np.arange(len(e)) / 1000.0           # ps
    slope = np.polyfit(t, e - e[0], 1)[0]
    return took, count.n, slope, float(np.max(np.abs(e - e[0])))


def run_audit(make, dt_fs, steps):
    atoms = make()
    t0 = time.perf_counter()
    report = audit(atoms, dt_fs * units.fs, steps)
    return time.perf_counter() - t0, report


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="20 steps, one round, no collision "
                    "against Verlet at 0.01 fs")
    args = ap.parse_args(argv)
    steps = 20 if args.quick else args.steps
    repeat = 1 if args.quick else args.repeat
    lines = ["# The conservation audit against VelocityVerlet's drift", "",
             "Conservation audit against VelocityVerlet's drift (issue 50) and a Cu2 collision "
             "through EMT's cutoff (issue 46, item 4), written by `benchmarks/bench_audit.py`.",
             "", f"`python benchmarks/bench_audit.py --steps {steps} --repeat {repeat}"
             f"{' --quick' if args.quick else ''}` on {machine()} (loaded: times are ratios "
             f"within the run).", ""]

    # -- the collision ----------------------------------------------------------------------
    if not args.quick:
        ref = cu2()
        t0 = time.perf_counter()
        VelocityVerlet(ref, 0.01 * units.fs).run(20000)
        t_ref = time.perf_counter() - t0
        lines += ["## Cu2 through EMT's cutoff, 200 fs", "",
                  "| method | dt [fs] | finished | warnings | max position diff to VV 0.01 fs [A] "
                  "| final distance [A] | s |", "|---|---|---|---|---|---|---|",
                  f"| VelocityVerlet | 0.01 | yes | 0 | 0 | {ref.get_distance(0, 1):.6f} | "
                  f"{t_ref:.2f} |"]
        for dt in (1.0, 0.5):
            atoms, took, n, messages = collision(dt)
            diff = float(np.max(np.abs(atoms.positions - ref.positions)))
            lines.append(f"| HBVMDynamics (defaults) | {dt:g} | yes | {n} | {diff:.1e} | "
                         f"{atoms.get_distance(0, 1):.6f} | {took:.2f} |")
        lines += ["", f"The first warning at 1 fs: \"{messages[0] if messages else ''}\"", ""]

    # -- the audits -------------------------------------------------------------------------
    lines += [f"## Audits of {steps} steps against VelocityVerlet of the same length", "",
              "| scene | audit / VV time | audit / VV calculator calls | jumps | jump sum [eV] "
              "| non-conservative work [eV] | integrator's share [eV] | VV drift [eV/ps] "
              "| VV max abs dE [eV] |", "|---|---|---|---|---|---|---|---|---|"]
    summaries = []
    for name, (make, dt) in SCENES.items():
        best_a = best_v = np.inf
        for _ in range(repeat):
            ta, report = run_audit(make, dt, steps)
            tv, calls_v, slope, dmax = verlet(make, dt, steps)
            best_a, best_v = min(best_a, ta), min(best_v, tv)
        lines.append(f"| {name} | {best_a / best_v:.0f} | {report.force_calls / calls_v:.0f} | "
                     f"{len(report.jumps)} | {report.jump_energy:+.2e} | "
                     f"{report.nonconservative_work:+.2e} | {report.integrator_error:.1e} | "
                     f"{slope:+.2e} | {dmax:.1e} |")
        summaries.append((name, str(report)))
        print(lines[-1], flush=True)
    lines += ["", "Each audit's own summary (`print(report)`):", ""]
    for name, text in summaries:
        lines += [f"**{name}**", "", "```", text, "```", ""]
    OUT.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
