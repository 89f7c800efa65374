"""Benchmark (not a test): HBVMDynamics against VelocityVerlet, 1e3 to 1e5 atoms, same calculator.

A periodic soft-sphere fluid phi(r) = eps (1 - r^2 / r_c^2)^4 (``PolynomialPairPotential.
soft_sphere``, cutoff mode), a rattled simple-cubic lattice of n^3 argon atoms, seeded
Maxwell-Boltzmann velocities.  Both integrators are driven the way a user drives them:
``atoms.calc = PolynomialPairPotential.soft_sphere(...)``, then ``dyn = VelocityVerlet(atoms, dt)``
or ``dyn = HBVMDynamics(atoms, dt, s=s)`` and ``dyn.run(steps)``, with one observer recording
the total energy each step.  They share the same calculator class with the same neighbour list:
VelocityVerlet calls it through ``atoms.get_forces()``; HBVMDynamics evaluates its stage
configurations through the calculator's ``forces_batch`` and the final positions of each step
through ``atoms.get_forces()``.

Timed: building the dynamics object and ``dyn.run(steps)`` (which includes ASE's first force
call and all neighbour-list builds), nothing else.  The numba kernels are loaded beforehand on a
small system (the one-off compilation is not timed).  Each run of a (size, method) is its own
process, so that the peak resident memory it reports is its own; the fastest of ``--repeat``
runs is reported (a shared machine slows single runs by 10-30 %), every row run once per round
and the rounds in turn, so that the machine's drift over minutes reaches every row alike (with
a row's runs back to back, three runs on one code gave a flatness of 1.44, 1.20 and 1.30).  ``force evals`` counts
configurations at which forces were computed (calculator calls plus batched stage
configurations), so HBVM's count includes every stage of every iteration.

    python benchmarks/bench_md.py [--steps 50] [--sizes 1000 10000 50000 100000] [--s 1 2 3 4]
                                  [--repeat 3]
"""
from __future__ import annotations

import argparse
import json
import pathlib
import resource
import subprocess
import sys
import time

import numpy as np
from ase import units
from ase.build import bulk
from ase.md.verlet import VelocityVerlet

from hbvm_md import HBVMDynamics
from hbvm_md.reports.machine import machine
from hbvm_md.reports.md_comparison import maxwell_boltzmann
from systems import PolynomialPairPotential

EPS, RC, DT_FS, T_K, LATTICE = 0.1, 4.0, 5.0, 300.0, 3.5


def fluid(n_atoms: int):
    """The rattled simple-cubic lattice with the cube number of atoms nearest to ``n_atoms``."""
    side = max(2, int(round(n_atoms ** (1.0 / 3.0))))
    atoms = bulk("Ar", "sc", a=LATTICE) * (side, side, side)
    atoms.rattle(0.05, seed=2)
    maxwell_boltzmann(atoms, T_K, seed=0)
    return atoms


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # KiB on Linux


def _make(method: str, atoms, dt):
    # k = s + 4, as the README's table was measured (HBVMDynamics' default for a calculator
    # that is not a polynomial, like this one with its cutoff, is now s + 1: bench_md_cost.py)
    return (VelocityVerlet(atoms, dt) if method == "VV"
            else HBVMDynamics(atoms, dt, s=int(method), k=int(method) + 4))


def _run_once(method: str, atoms, steps: int) -> dict:
    dt = DT_FS * units.fs
    atoms.calc = calc = PolynomialPairPotential.soft_sphere(EPS, RC)
    calls = [0]
    original = calc.calculate

    def counted(*a, **k):
        calls[0] += 1
        return original(*a, **k)
    calc.calculate = counted
    E = []
    t0 = time.perf_counter()
    dyn = _make(method, atoms, dt)
    dyn.attach(lambda: E.append(atoms.get_potential_energy() + atoms.get_kinetic_energy()))
    dyn.run(steps)
    wall = time.perf_counter() - t0
    E = np.array(E)
    return dict(label=str(getattr(dyn, "method", "VelocityVerlet")), wall=wall,
                nfev=calls[0] + getattr(calc, "batch_evaluations", 0),
                builds=getattr(calc, "neighbour_list_builds", -1),
                rel=float(np.max(np.abs(E - E[0])) / abs(E[0])))


def worker(method: str, n_atoms: int, steps: int) -> dict:
    """One measurement in this process: warm the kernels on 64 atoms, then time the real run."""
    _run_once(method, fluid(64), 2)
    idle = _peak_rss_mb()
    atoms = fluid(n_atoms)
    r = _run_once(method, atoms, steps)
    r.update(n=len(atoms), steps=steps, peak_mb=_peak_rss_mb(), idle_mb=idle)
    return r


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 50000, 100000])
    ap.add_argument("--s", type=int, nargs="+", default=[1, 2, 3, 4],
                    help="HBVM degrees run at the smallest size; larger sizes run s = 2 (the default)")
    ap.add_argument("--repeat", type=int, default=3,
                    help="runs per row, each in a fresh process; the fastest is reported (a shared "
                         "machine slows single runs by 10-30 %%)")
    ap.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results" / "md.md"))
    ap.add_argument("--worker", nargs=3, metavar=("METHOD", "N", "STEPS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        method, n, steps = args.worker
        print(json.dumps(worker(method, int(n), int(steps))))
        return ""
    # every row once per round, the rounds in turn (interleaved), then the fastest of each row:
    # the machine's speed drifts over minutes, and with a row's runs back to back the flatness
    # (a ratio across rows) measured that drift as much as the code
    cells = [(n, m) for idx, n in enumerate(args.sizes)
             for m in ["VV"] + [str(s) for s in (args.s if idx == 0 else [2])]]
    runs = {cell: [] for cell in cells}
    for _ in range(max(1, args.repeat)):
        for n, m in cells:
            out = subprocess.run([sys.executable, __file__, "--worker", m, str(n), str(args.steps)],
                                 check=True, capture_output=True, text=True).stdout
            runs[n, m].append(json.loads(out.strip().splitlines()[-1]))
    rows = []
    for n, m in cells:
        r = min(runs[n, m], key=lambda x: x["wall"])
        r["method"] = m
        rows.append(r)
        print({k: r[k] for k in ("n", "label", "wall", "nfev", "builds", "peak_mb", "rel")}, flush=True)
    vv = {r["n"]: r for r in rows if r["method"] == "VV"}
    head = (f"Soft-sphere fluid phi(r) = {EPS} eV (1 - r^2/{RC}^2)^4 (cutoff {RC} A, periodic), "
            f"rattled simple-cubic argon (a = {LATTICE} A), {T_K:g} K, dt = {DT_FS:g} fs, "
            f"{args.steps} steps; both integrators driven through `atoms.calc = "
            f"PolynomialPairPotential.soft_sphere(...)` and `dyn.run({args.steps})` (timed: building "
            f"the dynamics and the run); `python benchmarks/bench_md.py --steps {args.steps} --sizes "
            f"{' '.join(map(str, args.sizes))} --repeat {args.repeat}` on {machine()}, "
            f"each run in its own process, the fastest of {args.repeat} runs per row (every row "
            f"once per round, the rounds in turn).\n\n")
    table = ["| atoms | method | ms / step | us / (step atom) | x VelocityVerlet | force evals / step | "
             "neighbour-list builds | peak memory [MB] (idle) | max rel. energy error |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ms = 1e3 * r["wall"] / r["steps"]
        ratio = r["wall"] / vv[r["n"]]["wall"]
        table.append(f"| {r['n']} | {r['label']} | {ms:.2f} | {1e3 * ms / r['n']:.3f} | {ratio:.2f} | "
                     f"{r['nfev'] / r['steps']:.1f} | {r['builds']} | {r['peak_mb']:.0f} ({r['idle_mb']:.0f}) | "
                     f"{r['rel']:.1e} |")
    flat = []
    for m in sorted({r["method"] for r in rows}):
        per = [1e6 * r["wall"] / r["steps"] / r["n"] for r in rows if r["method"] == m]
        if len(per) > 1:
            label = next(r["label"] for r in rows if r["method"] == m)
            flat.append(f"{label}: largest / smallest time per step per atom over the sizes = "
                        f"{max(per) / min(per):.2f}")
    text = head + "\n".join(table) + "\n\n" + "\n".join(flat) + "\n"
    out = pathlib.Path(args.out)
    out.parent.mkdir(exist_ok=True)
    out.write_text(text)
    print(text)
    return text


if __name__ == "__main__":
    main()
