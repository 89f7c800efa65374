"""Benchmark (not a test): HBVMDynamics against VelocityVerlet on a periodic soft-sphere fluid.

Cutoff polynomial potential phi(r) = eps (1 - r^2 / r_c^2)^4 (``PolynomialPairPotential.
soft_sphere``), 256 and 1000 atoms, same calculator, same seeded velocities.  Reports wall time
per step and per force evaluation of HBVM(k, s) for s = 1..4 (k chosen by HBVMDynamics) and of
VelocityVerlet, the batched compiled stage path against calling the calculator stage by stage,
and the energy error reached.  Writes the markdown table to benchmarks/results/md.md.

    python benchmarks/bench_md.py [--steps 300] [--sizes 256 1000]
"""
from __future__ import annotations

import argparse
import pathlib
import platform
import time

import numpy as np
from ase import units
from ase.build import bulk
from ase.md.verlet import VelocityVerlet

from hbvm_md import HBVMDynamics
from hbvm_md.md_comparison import maxwell_boltzmann
from systems import PolynomialPairPotential

EPS, RC, DT_FS, T_K = 0.1, 4.0, 5.0, 300.0


def fluid(n_atoms: int):
    if n_atoms == 256:
        atoms = bulk("Ar", "fcc", a=4.95, cubic=True) * (4, 4, 4)
    elif n_atoms == 1000:
        atoms = bulk("Ar", "sc", a=3.5) * (10, 10, 10)
    else:
        raise ValueError(f"sizes are 256 or 1000 (got {n_atoms})")
    atoms.rattle(0.05, seed=2)
    maxwell_boltzmann(atoms, T_K, seed=0)
    return atoms


class StageByStage(PolynomialPairPotential):
    """The same potential without ``forces_batch``: HBVMDynamics calls it stage by stage."""

    def __getattribute__(self, name):
        if name == "forces_batch":
            raise AttributeError(name)
        return super().__getattribute__(name)


def run(atoms, make_dyn, steps, calc):
    atoms = atoms.copy()
    atoms.calc = calc
    calls = [0]
    original = calc.calculate

    def counted(*a, **k):
        calls[0] += 1
        return original(*a, **k)
    calc.calculate = counted
    batch0 = getattr(calc, "batch_evaluations", 0)
    dyn = make_dyn(atoms)
    E = []
    dyn.attach(lambda: E.append(atoms.get_potential_energy() + atoms.get_kinetic_energy()))
    t0 = time.perf_counter()
    dyn.run(steps)
    wall = time.perf_counter() - t0
    del calc.calculate
    nfev = calls[0] + getattr(calc, "batch_evaluations", 0) - batch0
    E = np.array(E)
    return dict(wall_step_ms=1e3 * wall / steps, wall_fev_us=1e6 * wall / nfev, fev_step=nfev / steps,
                dE=float(np.max(np.abs(E - E[0])) / len(atoms)),
                rel=float(np.max(np.abs(E - E[0])) / abs(E[0])), label=getattr(dyn, "method", "VelocityVerlet"))


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 1000])
    args = ap.parse_args(argv)
    dt = DT_FS * units.fs
    rows = []
    for n in args.sizes:
        atoms = fluid(n)
        calc = PolynomialPairPotential.soft_sphere(EPS, RC)
        warm = atoms.copy()
        warm.calc = calc
        warm.get_forces()                                  # load the compiled kernels first
        calc.forces_batch(warm.positions[None], warm)
        runs = [("batched", run(atoms, lambda a: VelocityVerlet(a, dt), args.steps, calc))]
        for s in (1, 2, 3, 4):
            runs.append(("batched", run(atoms, lambda a, s=s: HBVMDynamics(a, dt, s=s), args.steps, calc)))
        runs.append(("stage by stage", run(atoms, lambda a: HBVMDynamics(a, dt, s=2), args.steps,
                                           StageByStage.with_cutoff([EPS], RC, smoothness=4))))
        vv = runs[0][1]
        for path, r in runs:
            rows.append((n, str(r["label"]), path if r["label"] != "VelocityVerlet" else "-",
                         r["wall_step_ms"], r["wall_step_ms"] / vv["wall_step_ms"], r["wall_fev_us"],
                         r["fev_step"], r["dE"], r["rel"]))
            print(rows[-1], flush=True)
    head = (f"Soft-sphere fluid phi(r) = {EPS} eV (1 - r^2/{RC}^2)^4 (cutoff {RC} A, periodic), "
            f"Ar masses, {T_K:g} K, dt = {DT_FS:g} fs, {args.steps} steps; "
            f"`python benchmarks/bench_md.py --steps {args.steps}` on {platform.processor() or platform.machine()}, "
            f"one run.\n\n")
    table = ["| atoms | method | stage forces | ms / step | x VelocityVerlet | us / force eval | "
             "force evals / step | max abs(E-E0)/N [eV] | max rel. energy error |",
             "|---|---|---|---|---|---|---|---|---|"]
    for n, m, path, ms, ratio, us, fev, de, rel in rows:
        table.append(f"| {n} | {m} | {path} | {ms:.2f} | {ratio:.1f} | {us:.1f} | {fev:.1f} | {de:.1e} | {rel:.1e} |")
    text = head + "\n".join(table) + "\n"
    out = pathlib.Path(__file__).parent / "results" / "md.md"
    out.parent.mkdir(exist_ok=True)
    out.write_text(text)
    print(text)
    return text


if __name__ == "__main__":
    main()
