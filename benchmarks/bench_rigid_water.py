"""Rigid TIP3P water: HBVMDynamics (bonds inside the HBVM step) against VelocityVerlet (RATTLE
through ASE's FixBondLengths), in one process.

Scenes: 27 waters in ASE's TIP3P tutorial box (periodic, rc = 4.5 A: the cutoff's switching
function is C1, so it limits every method's energy error), and the same 27 waters as a free
cluster with rc beyond it (the cutoff never acts).  Each run: T fs of NVE from the same start,
the energy recorded at every step through an observer; the wall time is what the user pays
(the dynamics object built, the run, the observer).  VelocityVerlet is also run at smaller
steps; its cost at HBVM's energy error is read off its measured error ~ dt^2 (interpolated
between the measured steps where they bracket it, extrapolated from the smallest otherwise:
the table says which).

    PYTHONPATH=. python benchmarks/bench_rigid_water.py [--fs 10] [--vv-dts 1 0.25]

Writes benchmarks/results/rigid_water.md.  Timings were taken on a shared, loaded machine:
compare the ratios, not the absolute times.
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np
from ase import Atoms, units
from ase.calculators.tip3p import TIP3P, angleHOH, rOH
from ase.constraints import FixBondLengths
from ase.md.verlet import VelocityVerlet

from hbvm_md.ase import HBVMDynamics


def scene(periodic: bool, seed: int = 0) -> Atoms:
    x = np.deg2rad(angleHOH) / 2
    mol = Atoms("OH2", positions=[[0, 0, 0], [0, rOH * np.cos(x), rOH * np.sin(x)],
                                  [0, rOH * np.cos(x), -rOH * np.sin(x)]])
    a = (18.01528 / 6.022140857e23 / (0.9982 / 1e24)) ** (1 / 3)
    mol.set_cell((a, a, a))
    mol.center()
    atoms = mol.repeat((3, 3, 3))
    atoms.set_pbc(periodic)
    n = len(atoms) // 3
    atoms.constraints = FixBondLengths([(3 * i + j, 3 * i + (j + 1) % 3) for i in range(n) for j in range(3)])
    atoms.calc = TIP3P(rc=4.5 if periodic else 20.0)
    rng = np.random.default_rng(seed)
    atoms.rattle(0.05, rng=rng)
    p = rng.normal(size=(len(atoms), 3)) * np.sqrt(atoms.get_masses()[:, None] * units.kB * 300)
    atoms.set_momenta(p - p.mean(0))
    return atoms


def bond_error(atoms) -> float:
    c = atoms.constraints[0]
    return max(abs(atoms.get_distance(i, j, mic=True) - d) for (i, j), d in zip(c.pairs, c.bondlengths))


def run(cls, atoms, dt_fs: float, t_fs: float, **kw):
    e0 = atoms.get_total_energy()
    errs = []
    steps = int(round(t_fs / dt_fs))
    t0 = time.perf_counter()
    dyn = cls(atoms, dt_fs * units.fs, **kw)
    dyn.attach(lambda: errs.append(abs(atoms.get_total_energy() - e0)))
    dyn.run(steps)
    wall = time.perf_counter() - t0
    return max(errs) / len(atoms), bond_error(atoms), wall, steps


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--fs", type=float, default=10.0, help="simulated time per run (fs)")
    ap.add_argument("--vv-dts", type=float, nargs="+", default=[1.0, 0.25],
                    help="VelocityVerlet steps (fs); ASE's RATTLE costs seconds a step in a "
                         "periodic box (Python loops, find_mic per bond and iteration)")
    args = ap.parse_args()
    rows = []
    for periodic in (True, False):
        name = ("27 waters, periodic box, TIP3P(rc=4.5) (ASE tutorial)" if periodic
                else "27 waters, free cluster, TIP3P(rc=20) (no cutoff acts)")
        res = {}
        vv_labels = [f"VV {dt:g} fs" for dt in args.vv_dts]
        for label, cls, dt, kw in [("HBVM(3, 2)", HBVMDynamics, 1.0, dict(s=2)),
                                   ("HBVM(4, 3)", HBVMDynamics, 1.0, dict(s=3))] + [
                (lab, VelocityVerlet, dt, {}) for lab, dt in zip(vv_labels, args.vv_dts)]:
            e, b, wall, steps = run(cls, scene(periodic), dt, args.fs, **kw)
            res[label] = (e, b, wall, steps, dt)
            print(f"{name}: {label}: max|dE| {e:.2e} eV/atom, bonds {b:.1e} A, {wall:.2f} s", flush=True)
        vv = [res[k] for k in vv_labels]
        for label in ("HBVM(3, 2)", "HBVM(4, 3)"):
            e, b, wall, steps, _ = res[label]
            # VV's time at e: its error ~ dt^2, cost ~ 1/dt, from the nearest measured step
            errs = np.array([r[0] for r in vv])
            below = np.flatnonzero(errs <= e)
            ref = vv[below[0] - 1] if below.size and below[0] > 0 else vv[-1]
            dt_eq = ref[4] * np.sqrt(e / ref[0])
            how = "interpolated" if below.size and below[0] > 0 else "extrapolated"
            vv_wall = ref[2] * ref[4] / dt_eq
            rows.append((name, label, e, b, wall, vv[0][0], vv[0][0] / e,
                         dt_eq, vv_wall, how, vv_wall / wall))
        for label in vv_labels:
            e, b, wall, steps, dt = res[label]
            rows.append((name, label, e, b, wall, None, None, None, None, "", None))
    out = ["# Rigid TIP3P water: HBVMDynamics vs VelocityVerlet (RATTLE)", "",
           f"`PYTHONPATH=. python benchmarks/bench_rigid_water.py --fs {args.fs:g} --vv-dts {' '.join(f'{d:g}' for d in args.vv_dts)}`: {args.fs:g} fs "
           "of NVE from one start (300 K, rattled), energy at every step. Wall times in one "
           "process on a shared, loaded machine: read the ratios. 'VV at equal error' is "
           "VelocityVerlet's time to reach the HBVM run's energy error, from its measured "
           "error ~ dt^2 and cost ~ 1/dt (interpolated between measured steps or extrapolated "
           "from the smallest, as marked).", "",
           "| scene | run | max dE (eV/atom) | max bond error (A) | wall (s) | VV (largest dt) dE / this dE | "
           "VV dt at equal dE (fs) | VV wall at equal dE (s) | VV / HBVM time |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        name, label, e, b, wall, vv1, ratio, dt_eq, vv_wall, how, speed = r
        if ratio is None:
            out.append(f"| {name} | {label} | {e:.2e} | {b:.1e} | {wall:.2f} | | | | |")
        else:
            out.append(f"| {name} | {label} | {e:.2e} | {b:.1e} | {wall:.2f} | {ratio:.2e} | "
                       f"{dt_eq:.3g} | {vv_wall:.1f} ({how}) | {speed:.1f} |")
    path = os.path.join(os.path.dirname(__file__), "results", "rigid_water.md")
    with open(path, "w") as fh:
        fh.write("\n".join(out) + "\n")
    print("\n".join(out))


if __name__ == "__main__":
    main()
