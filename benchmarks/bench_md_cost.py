"""Benchmark (not a test): wall time per simulated picosecond against energy error, HBVMDynamics
against VelocityVerlet at several time steps, on two ASE scenes.

* **EMT copper**, the scene of ASE's molecular-dynamics tutorial: fcc copper, 3 x 3 x 3 cubic
  cells (108 atoms, periodic), ``ase.calculators.emt.EMT``, Maxwell-Boltzmann momenta at 300 K.
  A calculator that is not a polynomial: HBVM's energy error is the quadrature error of its
  line integral, and k (the quadrature nodes) is a cost to choose.  Every stage configuration
  is one calculator call (moving the atoms there), as for any ASE calculator.
* **Polynomial cluster**: the 38-atom all-pairs quartic droplet of the MD comparison
  (``default_cluster``, ``PolynomialPairPotential``, compiled stage forces in one batched call),
  300 K, where HBVM(2s, s) conserves H exactly.

Each run goes for the same simulated time (``--ps``), driven as a user drives it: ``dyn =
VelocityVerlet(atoms, dt)`` or ``HBVMDynamics(atoms, dt, s=s, k=k)``, then ``dyn.run(steps)``,
with one observer reading the total energy each step.  Timed: building the dynamics and the run.
Reported: wall seconds per simulated ps, force configurations a step (calculator calls plus
batched stage configurations) and the largest |E(t) - E(0)| per atom over the run (eV).  The
numba kernels are loaded before timing (a short run of each method).  Every configuration is
run ``--repeat`` times, in rounds (every row once a round), and the fastest kept.

    python benchmarks/bench_md_cost.py [--ps 0.2] [--repeat 1] [--quick] [--from-csv]

Writes ``benchmarks/results/md_cost.md`` (the table), ``docs/figures/md_cost.csv`` and the
figure ``docs/figures/md_cost.png``.
"""
from __future__ import annotations

import argparse
import csv
import pathlib
import re
import sys
import time

import numpy as np
from ase import units
from ase.calculators.emt import EMT
from ase.lattice.cubic import FaceCenteredCubic
from ase.md.verlet import VelocityVerlet

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hbvm_md import HBVMDynamics                                          # noqa: E402
from hbvm_md.reports.machine import machine                               # noqa: E402
from hbvm_md.reports.md_comparison import default_cluster, maxwell_boltzmann  # noqa: E402

T_K = 300.0


def copper():
    """ASE's MD tutorial scene: 108 Cu atoms (3 x 3 x 3 fcc cubic cells), EMT, 300 K."""
    atoms = FaceCenteredCubic(directions=[[1, 0, 0], [0, 1, 0], [0, 0, 1]], symbol="Cu",
                              size=(3, 3, 3), pbc=True)
    maxwell_boltzmann(atoms, T_K, seed=0)
    atoms.calc = EMT()
    return atoms


def cluster():
    """The 38-atom quartic droplet (a polynomial H of degree 4), 300 K."""
    atoms, _ = default_cluster(38)
    maxwell_boltzmann(atoms, T_K, seed=0)
    return atoms


SCENES = {"EMT copper, 108 atoms (ASE's MD tutorial)": copper,
          "polynomial cluster, 38 atoms": cluster}

# (label, s, k or None for VelocityVerlet, time steps in fs)
GRID = {
    "EMT copper, 108 atoms (ASE's MD tutorial)": [
        ("VelocityVerlet", None, None, (0.25, 0.5, 1.0, 2.0, 5.0)),
        ("HBVM", 1, 2, (2.0, 5.0)),
        ("HBVM", 2, 2, (5.0, 10.0)), ("HBVM", 2, 3, (5.0, 10.0)), ("HBVM", 2, 4, (5.0, 10.0)),
        ("HBVM", 2, 6, (5.0,)),
        ("HBVM", 3, 4, (10.0, 20.0))],
    "polynomial cluster, 38 atoms": [
        ("VelocityVerlet", None, None, (1.0, 2.0, 5.0, 10.0)),
        ("HBVM", 1, 2, (5.0, 10.0)), ("HBVM", 2, 4, (5.0, 10.0, 20.0))],
}
QUICK = {
    "EMT copper, 108 atoms (ASE's MD tutorial)": [
        ("VelocityVerlet", None, None, (1.0, 5.0)), ("HBVM", 2, 3, (5.0,)),
        ("HBVM", 2, 6, (5.0,))],
    "polynomial cluster, 38 atoms": [
        ("VelocityVerlet", None, None, (5.0,)), ("HBVM", 2, 4, (10.0,))],
}


def run_one(make, s, k, dt_fs: float, ps: float) -> dict:
    """One run of ``ps`` picoseconds; returns its row."""
    atoms = make()
    n = len(atoms)
    steps = max(1, int(round(ps * 1000.0 / dt_fs)))
    energies = []
    t0 = time.perf_counter()
    if k is None:
        dyn = VelocityVerlet(atoms, dt_fs * units.fs)
    else:
        dyn = HBVMDynamics(atoms, dt_fs * units.fs, s=s, k=k)
    dyn.attach(lambda: energies.append(atoms.get_potential_energy() + atoms.get_kinetic_energy()))
    dyn.run(steps)
    wall = time.perf_counter() - t0
    E = np.asarray(energies)
    evals = (steps + 1) if k is None else (dyn.stage_evaluations + steps + 1)
    return {"method": "VelocityVerlet" if k is None else f"HBVM({k}, {s})", "s": s or 0,
            "k": k or 0, "dt_fs": dt_fs, "steps": steps, "wall_s": wall,
            "s_per_ps": wall / (steps * dt_fs / 1000.0), "evals_per_step": evals / steps,
            "evals_per_ps": evals / (steps * dt_fs / 1000.0),
            "max_dE_per_atom": float(np.max(np.abs(E - E[0])) / n),
            "T_mean_K": float(atoms.get_temperature())}


def pareto(rows):
    """The rows no other row beats in both time and error (the work-precision front)."""
    front = []
    for r in rows:
        if not any(o is not r and o["s_per_ps"] <= r["s_per_ps"]
                   and o["max_dE_per_atom"] <= r["max_dE_per_atom"]
                   and (o["s_per_ps"], o["max_dE_per_atom"]) != (r["s_per_ps"], r["max_dE_per_atom"])
                   for o in rows):
            front.append(r)
    return front


def crossover(rows, cost: str = "s_per_ps") -> float | None:
    """The energy error below which HBVM is cheaper than VelocityVerlet.

    Verlet's cost per ps (``cost``: wall time or force evaluations) is fitted as a power law of
    its error through its time steps (cost ~ error^(-1/2): its error grows like dt^2).  An HBVM
    row with error e and cost c beats Verlet for every target error between e and e_v(c), the
    error Verlet reaches for the same cost; returns the largest such e_v(c) (None: no HBVM row
    is more accurate than Verlet at its cost)."""
    vv = [r for r in rows if r["k"] == 0]
    hb = [r for r in rows if r["k"] > 0]
    if len(vv) < 2 or not hb:
        return None
    a, b = np.polyfit(np.log([r["max_dE_per_atom"] for r in vv]), np.log([r[cost] for r in vv]), 1)
    best = None
    for r in hb:
        e_v = float(np.exp((np.log(r[cost]) - b) / a))
        if r["max_dE_per_atom"] < e_v:
            best = max(best or 0.0, e_v)
    return best


def plot(results: dict, path: pathlib.Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(6.2 * len(results), 4.6))
    for ax, (scene, rows) in zip(np.atleast_1d(axes), results.items()):
        vv = sorted((r for r in rows if r["k"] == 0), key=lambda r: r["dt_fs"])
        ax.loglog([r["max_dE_per_atom"] for r in vv], [r["s_per_ps"] for r in vv], "k-o",
                  label="VelocityVerlet")
        if len(vv) >= 2:      # Verlet's power law (error ~ dt^2) carried to HBVM's errors
            a, b = np.polyfit(np.log([r["max_dE_per_atom"] for r in vv]),
                              np.log([r["s_per_ps"] for r in vv]), 1)
            lo = min(max(r["max_dE_per_atom"], 1e-17) for r in rows)
            x = np.geomspace(lo, vv[-1]["max_dE_per_atom"], 50)
            ax.loglog(x, np.exp(a * np.log(x) + b), color="k", linestyle="--", linewidth=0.8,
                      label="VelocityVerlet, extrapolated (error ~ dt^2)")
        for r in vv:
            ax.annotate(f"{r['dt_fs']:g} fs", (r["max_dE_per_atom"], r["s_per_ps"]),
                        textcoords="offset points", xytext=(4, 4), fontsize=7)
        for s, marker in ((1, "s"), (2, "^"), (3, "D")):
            hb = [r for r in rows if r["s"] == s and r["k"] > 0]
            if not hb:
                continue
            ax.loglog([max(r["max_dE_per_atom"], 1e-17) for r in hb], [r["s_per_ps"] for r in hb],
                      marker, linestyle="none", label=f"HBVM(k, {s})")
            for r in hb:
                ax.annotate(f"k={r['k']}, {r['dt_fs']:g} fs",
                            (max(r["max_dE_per_atom"], 1e-17), r["s_per_ps"]),
                            textcoords="offset points", xytext=(4, -9), fontsize=7)
        x = crossover(rows)
        if x is not None:
            ax.axvline(x, color="grey", linestyle=":", linewidth=1)
        ax.set_xlabel("max |E(t) - E(0)| per atom [eV]")
        ax.set_ylabel("wall time per simulated ps [s]")
        ax.set_title(scene, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ps", type=float, default=0.2, help="simulated picoseconds a run")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each row; the fastest is kept")
    ap.add_argument("--quick", action="store_true", help="a few rows, 0.1 ps, one run")
    ap.add_argument("--from-csv", action="store_true",
                    help="re-render the table and figure from docs/figures/md_cost.csv")
    args = ap.parse_args(argv)
    if args.from_csv:
        return from_csv()
    grid, ps, repeat = (QUICK, 0.1, 1) if args.quick else (GRID, args.ps, args.repeat)
    # load the numba kernels and the step's compiled code (not timed)
    for make in SCENES.values():
        for s, k in ((1, 2), (2, 3), (2, 4)):
            run_one(make, s, k, 5.0, 0.01)
    results = {}
    for scene, specs in grid.items():
        configs = [(s, k, dt) for _, s, k, dts in specs for dt in dts]
        best = {}
        for _ in range(repeat):
            for s, k, dt in configs:
                row = run_one(SCENES[scene], s, k, dt, ps)
                key = (s, k, dt)
                if key not in best or row["wall_s"] < best[key]["wall_s"]:
                    best[key] = row
                print(f"{scene[:12]:12s} {row['method']:15s} {dt:5.1f} fs  {row['s_per_ps']:8.3f} s/ps  "
                      f"{row['evals_per_step']:5.1f} evals/step  dE/atom {row['max_dE_per_atom']:.2e}",
                      flush=True)
        results[scene] = [best[c] for c in configs]
    cmd = "python benchmarks/bench_md_cost.py" + (" --quick" if args.quick else
                                                  f" --ps {ps:g} --repeat {repeat}")
    if not args.quick:
        with open(ROOT / "docs" / "figures" / "md_cost.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=["scene", "command", *results[next(iter(results))][0].keys()])
            w.writeheader()
            for scene, rows in results.items():
                for r in rows:
                    w.writerow({"scene": scene, "command": cmd, **r})
    report(results, cmd, ps, repeat, write=not args.quick)
    return 0


def report(results: dict, cmd: str, ps: float, repeat: int, write: bool = True) -> None:
    """The table (benchmarks/results/md_cost.md) and the figure from the rows."""
    lines = [f"Wall time per simulated picosecond against the largest energy error per atom over "
             f"{ps:g} ps, from Maxwell-Boltzmann momenta at {T_K:g} K; `{cmd}` on {machine()}, "
             f"the fastest of {repeat} run(s) per row.  Force evaluations count every "
             f"configuration at which forces were computed (HBVM: every stage of every "
             f"iteration, plus the final positions of each step).", ""]
    for scene, rows in results.items():
        front = pareto(rows)
        x, xe = crossover(rows), crossover(rows, "evals_per_ps")
        verdict = ("" if x is None and xe is None else
                   f" HBVM is cheaper than VelocityVerlet for energy errors below {x or 0:.1e} "
                   f"eV/atom in wall time, {xe or 0:.1e} eV/atom in force evaluations (the error "
                   f"Verlet reaches for the cost of HBVM's cheapest row, Verlet's cost fitted as "
                   f"a power law of its error through its time steps).")
        lines += [f"**{scene}**", "", "| method | dt [fs] | s / ps | x VV at 5 fs | "
                  "force evals / step | force evals / ps | max dE / atom [eV] | front |",
                  "|---|---|---|---|---|---|---|---|"]
        ref = next((r for r in rows if r["k"] == 0 and r["dt_fs"] == 5.0), None)
        for r in rows:
            ratio = f"{r['s_per_ps'] / ref['s_per_ps']:.2f}" if ref else ""
            lines.append(f"| {r['method']} | {r['dt_fs']:g} | {r['s_per_ps']:.3f} | {ratio} | "
                         f"{r['evals_per_step']:.1f} | {r['evals_per_ps']:.0f} | "
                         f"{r['max_dE_per_atom']:.1e} | {'*' if r in front else ''} |")
        lines += ["", f"front: no other row is both faster and more accurate.{verdict}", ""]
    if write:
        (ROOT / "benchmarks" / "results" / "md_cost.md").write_text("\n".join(lines))
        plot(results, ROOT / "docs" / "figures" / "md_cost.png")
    print("\n".join(lines))


def from_csv() -> int:
    """Re-render the table and the figure from docs/figures/md_cost.csv (no runs)."""
    results, cmd = {}, ""
    with open(ROOT / "docs" / "figures" / "md_cost.csv") as fh:
        for row in csv.DictReader(fh):
            scene, cmd = row.pop("scene"), row.pop("command")
            r = {k: (v if k == "method" else float(v)) for k, v in row.items()}
            for key in ("s", "k", "steps"):
                r[key] = int(r[key])
            results.setdefault(scene, []).append(r)
    ps = float(re.search(r"--ps (\S+)", cmd).group(1))
    repeat = int(re.search(r"--repeat (\S+)", cmd).group(1))
    report(results, cmd, ps, repeat)
    return 0


if __name__ == "__main__":
    sys.exit(main())
