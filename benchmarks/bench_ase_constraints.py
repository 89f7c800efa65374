"""What ASE users attach (issue 35): the cost of the constraints' projection, and the force
calls per step before and after one transient failure.

* **Projection cost**: the same scene and step run with and without constraints, time per
  step as the ratio constrained / unconstrained (medians over ``--repeat`` alternated runs in
  one process), with the energy error and the constraint's drift of the constrained run.
  Scenes: a 147-atom quartic cluster (PolynomialPairPotential, the compiled forces_batch
  path) and a 43-atom EMT copper cluster (the stage-by-stage path of any calculator).
* **One nan force**: EMT copper (32 atoms, 5 fs), the calculator returns nan forces once; the
  calculator calls per step (median) before and after, and of the step that failed.

Run: ``python benchmarks/bench_ase_constraints.py`` (writes
``benchmarks/results/ase_constraints.md``).
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np
from ase import units
from ase.build import bulk
from ase.calculators.calculator import all_changes
from ase.calculators.emt import EMT
from ase.cluster.cubic import FaceCenteredCubic
from ase.constraints import FixCom, FixedPlane, Hookean

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from hbvm_md import HBVMDynamics  # noqa: E402
from hbvm_md.reports.md_comparison import default_cluster, maxwell_boltzmann  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results" / "ase_constraints.md"


def quartic():
    atoms, _ = default_cluster(147)
    maxwell_boltzmann(atoms, 300.0, 0)
    return atoms, 10 * units.fs


def emt_copper():
    atoms = FaceCenteredCubic("Cu", [(1, 0, 0), (1, 1, 0), (1, 1, 1)], [3, 3, 3],
                              latticeconstant=3.61)
    maxwell_boltzmann(atoms, 300.0, 0)
    atoms.calc = EMT()
    return atoms, 4 * units.fs


CONSTRAINTS = {
    "none": lambda a: [],
    "FixCom": lambda a: [FixCom()],
    "FixedPlane (half the atoms)": lambda a: [FixedPlane(range(0, len(a), 2), [0.0, 0.6, 0.8])],
    "Hookean (pair + tether)": lambda a: [Hookean(0, 1, k=1.0, rt=2.0),
                                          Hookean(2, a.positions[2] + [0.3, 0, 0], k=1.0, rt=0.0)],
}


def run(make, kind, steps):
    atoms, dt = make()
    calc = atoms.calc
    if make is quartic:
        atoms.calc = type(calc)(calc.coefficients)
    atoms.set_constraint(CONSTRAINTS[kind](atoms))
    x0, c0 = atoms.get_positions(), atoms.get_center_of_mass()
    t = time.perf_counter()
    dyn = HBVMDynamics(atoms, dt)
    E = []
    dyn.attach(lambda: E.append(atoms.get_potential_energy() + atoms.get_kinetic_energy()))
    dyn.run(steps)
    wall = time.perf_counter() - t
    x = atoms.get_positions()
    drift = {"none": float("nan"),
             "FixCom": float(np.max(np.abs(atoms.get_center_of_mass() - c0))),
             "FixedPlane (half the atoms)": float(np.max(np.abs((x - x0)[::2] @ [0.0, 0.6, 0.8]))),
             "Hookean (pair + tether)": float("nan")}[kind]
    return wall / steps, float(np.ptp(E) / len(atoms)), drift, dyn.stage_evaluations / steps


class _NaNOnce(EMT):
    def __init__(self, **kw):
        super().__init__(**kw)
        self.calls, self.fail_call = 0, None

    def calculate(self, atoms=None, properties=("energy",), system_changes=all_changes):
        self.calls += 1
        super().calculate(atoms, properties, system_changes)
        if self.calls == self.fail_call:
            self.results["forces"] = np.full_like(self.results["forces"], np.nan)


def transient(before=8, after=12):
    import warnings
    atoms = bulk("Cu", cubic=True) * (2, 2, 2)
    maxwell_boltzmann(atoms, 600.0, seed=3)
    calc = _NaNOnce()
    atoms.calc = calc
    dyn = HBVMDynamics(atoms, 5 * units.fs, s=2, k=3)
    calls = []
    dyn.attach(lambda: calls.append(calc.calls))
    dyn.run(before)
    calc.fail_call = calc.calls + 5
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dyn.run(after)
    d = np.diff(calls)
    return float(np.median(d[:before])), int(d[before]), float(np.median(d[before + 1:])), dyn


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--steps", type=int, default=25)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    lines = ["# What ASE users attach: the cost of constraints, one transient failure", "",
             f"`python benchmarks/bench_ase_constraints.py --repeat {args.repeat} --steps "
             f"{args.steps}`; a loaded 2-core machine: ratios of medians over {args.repeat} "
             f"alternated runs in one process, setup included.", "",
             "## Constraints: time per step against the same scene unconstrained", "",
             "| scene | constraint | time ratio | force evals / step | max dE (eV/atom) | "
             "constraint drift (A) |", "|---|---|---|---|---|---|"]
    for label, make, steps in (("quartic cluster, 147 atoms, 10 fs (compiled path)", quartic,
                                4 * args.steps),
                               ("EMT Cu cluster, 43 atoms, 4 fs (any calculator)", emt_copper,
                                args.steps)):
        times = {k: [] for k in CONSTRAINTS}
        info = {}
        for _ in range(args.repeat):
            for kind in CONSTRAINTS:
                per_step, dE, drift, evals = run(make, kind, steps)
                times[kind].append(per_step)
                info[kind] = (dE, drift, evals)
        base = np.median(times["none"])
        for kind in CONSTRAINTS:
            dE, drift, evals = info[kind]
            lines.append(f"| {label} | {kind} | {np.median(times[kind]) / base:.3f} | "
                         f"{evals:.1f} | {dE:.1e} | "
                         f"{'-' if np.isnan(drift) else f'{drift:.1e}'} |")
            print(lines[-1], flush=True)
    b, failed, a, dyn = transient()
    lines += ["", "## One nan force (EMT Cu, 32 atoms, 5 fs, solver='auto')", "",
              "| calls / step before | calls of the failed step | calls / step after | "
              "after / before | solver after | switches |", "|---|---|---|---|---|---|",
              f"| {b:.0f} | {failed} | {a:.0f} | {a / b:.2f} | {dyn.solver_in_use} | "
              f"{dyn.solver_switches} |", "",
              "Before issue 35 the run stayed with Newton after the failure (6N = 192 extra "
              "force calls a step from finite differences, silently)."]
    print("\n".join(lines[-6:]))
    if not args.no_write:
        RESULTS.write_text("\n".join(lines) + "\n")
        print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
