"""Benchmark (not a test): wall time per simulated picosecond against energy error, HBVMDynamics
against VelocityVerlet at several time steps, on two ASE scenes.

* **EMT copper**, the scene of ASE's molecular-dynamics tutorial: fcc copper, 3 x 3 x 3 cubic
  cells (108 atoms, periodic), ``ase.calculators.emt.EMT``, Maxwell-Boltzmann momenta at 300 K.
  A calculator that is not a polynomial: HBVM's energy error is the quadrature error of its
  line integral, and k (the quadrature nodes) is a cost to choose.  Every stage configuration
  is one calculator call (moving the atoms there), as for any ASE calculator.
* **Polynomial-pair crystal**: the soft-sphere crystal of ``bench_md.py`` (rattled simple-cubic
  argon, phi(r) = 0.1 eV (1 - r^2 / 4^2)^4 with its cutoff, periodic), 4096 atoms, compiled
  stage forces in one batched call.  With its cutoff H is not a polynomial: HBVMDynamics'
  default is k = s + 1, as for EMT.
* **Polynomial cluster**: the 38-atom all-pairs quartic droplet of the MD comparison
  (``default_cluster``, ``PolynomialPairPotential``, compiled stage forces in one batched call),
  300 K, where HBVM(2s, s) conserves H exactly.

Each run goes for the same simulated time (``--ps``), driven as a user drives it: ``dyn =
VelocityVerlet(atoms, dt)`` or ``HBVMDynamics(atoms, dt, s=s, k=k)``, then ``dyn.run(steps)``,
with one observer reading the total energy each step.  Timed: building the dynamics and the run.
Reported: wall seconds per simulated ps, force configurations a step (calculator calls plus
batched stage configurations), iterations a step (stage sweeps, the polish included) and the
largest |E(t) - E(0)| per atom over the run (eV).  "default" marks HBVMDynamics' defaults
(``HBVMDynamics(atoms, dt)``: s = 2, k chosen by the class).

The equal-error crossover: each method's work-precision curve (cost per ps against the error,
over its time steps) is interpolated linearly on log-log axes; VelocityVerlet's is continued
beyond its time steps by the power law fitted through them (error ~ dt^2).  HBVM(k, s) is
cheaper than Verlet for a target error e when its curve lies below Verlet's there; the
crossover is the largest e where some HBVM(k, s) curve crosses Verlet's from below, or, when
a curve is still below Verlet's at its largest measured error, the error Verlet reaches for
that row's cost (a lower bound, marked ">=").  Both in wall time and in force evaluations.  The
numba kernels are loaded before timing (a short run of each method).  Every configuration is
run ``--repeat`` times, in rounds (every row once a round), and the fastest kept.

    python benchmarks/bench_md_cost.py [--ps 0.2] [--repeat 1] [--quick] [--from-csv]
                                       [--label before]

Writes ``benchmarks/results/md_cost.md`` (the tables), ``docs/figures/md_cost.csv`` and the
figure ``docs/figures/md_cost.png``.  ``--label before`` (or ``after``) writes the run's tables
as that section of the results file and keeps the other section as it is (the figure and
the CSV are the run's).
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
from integrators.core import C_ITER                                       # noqa: E402
from systems import PolynomialPairPotential                               # noqa: E402

T_K = 300.0
EMT_CU = "EMT copper, 108 atoms (ASE's MD tutorial)"
CRYSTAL = "soft-sphere crystal, 4096 atoms (polynomial pair potential with cutoff)"
CLUSTER = "polynomial cluster, 38 atoms"


def copper():
    """ASE's MD tutorial scene: 108 Cu atoms (3 x 3 x 3 fcc cubic cells), EMT, 300 K."""
    atoms = FaceCenteredCubic(directions=[[1, 0, 0], [0, 1, 0], [0, 0, 1]], symbol="Cu",
                              size=(3, 3, 3), pbc=True)
    maxwell_boltzmann(atoms, T_K, seed=0)
    atoms.calc = EMT()
    return atoms


def crystal(side: int = 16):
    """The soft-sphere crystal of bench_md.py: side^3 argon atoms on a rattled simple-cubic
    lattice (a = 3.5 A), phi(r) = 0.1 eV (1 - r^2 / 4^2)^4 with its cutoff, 300 K."""
    from ase.build import bulk
    atoms = bulk("Ar", "sc", a=3.5) * (side, side, side)
    atoms.rattle(0.05, seed=2)
    maxwell_boltzmann(atoms, T_K, seed=0)
    atoms.calc = PolynomialPairPotential.soft_sphere(0.1, 4.0)
    return atoms


def cluster():
    """The 38-atom quartic droplet (a polynomial H of degree 4), 300 K."""
    atoms, _ = default_cluster(38)
    maxwell_boltzmann(atoms, T_K, seed=0)
    return atoms


SCENES = {EMT_CU: copper, CRYSTAL: crystal, CLUSTER: cluster}

# (s, k: None for HBVMDynamics' default, 0 for VelocityVerlet; time steps in fs)
GRID = {
    EMT_CU: [(0, 0, (0.25, 0.5, 1.0, 2.0, 5.0)),
             (2, None, (5.0, 10.0, 15.0)),
             (2, 2, (5.0, 10.0, 15.0, 20.0, 25.0)),
             (3, 3, (10.0, 20.0, 30.0)),
             (3, 4, (20.0,))],
    CRYSTAL: [(0, 0, (1.0, 2.0, 5.0)),
              (2, None, (5.0, 10.0)),
              (2, 2, (5.0, 10.0))],
    CLUSTER: [(0, 0, (1.0, 2.0, 5.0, 10.0)),
              (1, 2, (5.0, 10.0)), (2, None, (5.0, 10.0, 20.0))],
}
QUICK = {
    EMT_CU: [(0, 0, (1.0, 5.0)), (2, None, (5.0,)), (2, 2, (10.0,))],
    CRYSTAL: [(0, 0, (5.0,)), (2, None, (5.0,))],
    CLUSTER: [(0, 0, (5.0,)), (2, None, (10.0,))],
}


def run_one(make, s, k, dt_fs: float, ps: float) -> dict:
    """One run of ``ps`` picoseconds; returns its row (k = 0: VelocityVerlet, k None:
    HBVMDynamics' default k)."""
    atoms = make()
    n = len(atoms)
    steps = max(1, int(round(ps * 1000.0 / dt_fs)))
    energies = []
    t0 = time.perf_counter()
    if k == 0:
        dyn = VelocityVerlet(atoms, dt_fs * units.fs)
    elif k is None and s == 2:
        dyn = HBVMDynamics(atoms, dt_fs * units.fs)            # the defaults, as a user writes it
    else:
        dyn = HBVMDynamics(atoms, dt_fs * units.fs, s=s, k=k)
    dyn.attach(lambda: energies.append(atoms.get_potential_energy() + atoms.get_kinetic_energy()))
    dyn.run(steps)
    wall = time.perf_counter() - t0
    E = np.asarray(energies)
    vv = k == 0
    evals = (steps + 1) if vv else (dyn.stage_evaluations + steps + 1)
    iters = 1.0 if vv else float(dyn._stepper.counters[C_ITER]) / steps
    return {"method": "VelocityVerlet" if vv else f"HBVM({dyn.k}, {dyn.s})",
            "default": int(k is None), "s": 0 if vv else dyn.s, "k": 0 if vv else dyn.k,
            "dt_fs": dt_fs, "steps": steps, "wall_s": wall,
            "s_per_ps": wall / (steps * dt_fs / 1000.0), "evals_per_step": evals / steps,
            "iters_per_step": iters, "evals_per_ps": evals / (steps * dt_fs / 1000.0),
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


def _verlet_cost(rows, cost: str):
    """log(cost) of VelocityVerlet as a function of log(error): its curve interpolated
    linearly on log-log axes between its time steps, continued by the power law fitted through
    them beyond (None with fewer than two Verlet rows)."""
    vv = sorted((r for r in rows if r["k"] == 0), key=lambda r: r["max_dE_per_atom"])
    if len(vv) < 2:
        return None
    x = np.log([r["max_dE_per_atom"] for r in vv])
    y = np.log([r[cost] for r in vv])
    a, b = np.polyfit(x, y, 1)

    def f(le):
        if x[0] <= le <= x[-1]:
            return float(np.interp(le, x, y))
        return float(a * le + b) + (y[0] - (a * x[0] + b) if le < x[0] else y[-1] - (a * x[-1] + b))

    def inverse(lc):          # the log error Verlet reaches for log cost lc (f decreasing)
        lo, hi = x[0] - 40.0, x[-1] + 40.0
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if f(mid) > lc else (lo, mid)
        return 0.5 * (lo + hi)
    return f, inverse


def crossover(rows, cost: str = "s_per_ps"):
    """(error, setting, bound) of the equal-error crossover against VelocityVerlet (see the
    module docstring): the largest error at which an HBVM(k, s) curve, interpolated on log-log
    axes through its time steps, is as cheap as Verlet's; ``bound`` True when that curve is
    still cheaper at its largest measured error (the error Verlet reaches for that row's cost,
    a lower bound).  None when no HBVM row is cheaper than Verlet at its own error."""
    vc = _verlet_cost(rows, cost)
    if vc is None:
        return None
    f, inverse = vc
    best = None
    curves = {}
    for r in rows:
        if r["k"] > 0 and r["max_dE_per_atom"] > 0:
            curves.setdefault((r["k"], r["s"]), []).append(r)
    for (k, s), pts in curves.items():
        pts.sort(key=lambda r: r["max_dE_per_atom"])
        le = [np.log(r["max_dE_per_atom"]) for r in pts]
        d = [np.log(r[cost]) - f(x) for r, x in zip(pts, le)]     # < 0: HBVM cheaper
        found = None
        if d[-1] < 0:
            found = (float(np.exp(inverse(np.log(pts[-1][cost])))), True)
        else:
            for i in range(len(pts) - 1, 0, -1):
                if d[i - 1] < 0 <= d[i]:          # crosses between rows i - 1 and i
                    x = le[i - 1] + (le[i] - le[i - 1]) * d[i - 1] / (d[i - 1] - d[i])
                    found = (float(np.exp(x)), False)
                    break
        if found and (best is None or found[0] > best[0]):
            best = (found[0], f"HBVM({k}, {s})", found[1])
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
        vc = _verlet_cost(rows, "s_per_ps")
        if vc is not None:      # Verlet's curve continued by its power law (error ~ dt^2)
            lo = min(max(r["max_dE_per_atom"], 1e-17) for r in rows)
            x = np.geomspace(lo, vv[-1]["max_dE_per_atom"], 50)
            ax.loglog(x, [np.exp(vc[0](np.log(v))) for v in x], color="k", linestyle="--",
                      linewidth=0.8, label="VelocityVerlet, continued (error ~ dt^2)")
        for r in vv:
            ax.annotate(f"{r['dt_fs']:g} fs", (r["max_dE_per_atom"], r["s_per_ps"]),
                        textcoords="offset points", xytext=(4, 4), fontsize=7)
        for (k, s) in sorted({(r["k"], r["s"]) for r in rows if r["k"] > 0}):
            hb = sorted((r for r in rows if (r["k"], r["s"]) == (k, s)), key=lambda r: r["dt_fs"])
            ax.loglog([max(r["max_dE_per_atom"], 1e-17) for r in hb], [r["s_per_ps"] for r in hb],
                      "-^", label=f"HBVM({k}, {s})")
            for r in hb:
                ax.annotate(f"{r['dt_fs']:g} fs", (max(r["max_dE_per_atom"], 1e-17), r["s_per_ps"]),
                            textcoords="offset points", xytext=(4, -9), fontsize=7)
        x = crossover(rows)
        if x is not None:
            ax.axvline(x[0], color="grey", linestyle=":", linewidth=1)
        ax.set_xlabel("max |E(t) - E(0)| per atom [eV]")
        ax.set_ylabel("wall time per simulated ps [s]")
        ax.set_title(scene, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ps", type=float, default=0.2, help="simulated picoseconds a run")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each row; the fastest is kept")
    ap.add_argument("--quick", action="store_true", help="a few rows, 0.1 ps, one run")
    ap.add_argument("--label", choices=("before", "after"), default="after",
                    help="the section of benchmarks/results/md_cost.md this run writes")
    ap.add_argument("--from-csv", action="store_true",
                    help="re-render the tables and figure from docs/figures/md_cost.csv")
    args = ap.parse_args(argv)
    if args.from_csv:
        return from_csv(args.label)
    grid, ps, repeat = (QUICK, 0.1, 1) if args.quick else (GRID, args.ps, args.repeat)
    # load the numba kernels and the step's compiled code (not timed)
    for make in SCENES.values():
        for s, k in ((2, None), (2, 2)):
            run_one(make if make is not crystal else (lambda: crystal(4)), s, k, 5.0, 0.01)
    results = {}
    for scene, specs in grid.items():
        configs = [(s, k, dt) for s, k, dts in specs for dt in dts]
        best = {}
        for _ in range(repeat):
            for s, k, dt in configs:
                row = run_one(SCENES[scene], s, k, dt, ps)
                key = (s, k, dt)
                if key not in best or row["wall_s"] < best[key]["wall_s"]:
                    best[key] = row
                print(f"{scene[:12]:12s} {row['method']:15s} {dt:5.1f} fs  {row['s_per_ps']:8.3f} s/ps  "
                      f"{row['evals_per_step']:5.1f} evals/step {row['iters_per_step']:5.2f} it/step  "
                      f"dE/atom {row['max_dE_per_atom']:.2e}", flush=True)
        results[scene] = [best[c] for c in configs]
    cmd = "python benchmarks/bench_md_cost.py" + (" --quick" if args.quick else
                                                  f" --ps {ps:g} --repeat {repeat} --label {args.label}")
    if not args.quick:
        with open(ROOT / "docs" / "figures" / "md_cost.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=["scene", "command", *results[next(iter(results))][0].keys()])
            w.writeheader()
            for scene, rows in results.items():
                for r in rows:
                    w.writerow({"scene": scene, "command": cmd, **r})
    report(results, cmd, ps, repeat, args.label, write=not args.quick)
    return 0


SECTIONS = {"before": "### Before: each step iterated to round-off",
            "after": '### After: the iteration stopped by its estimated error (tol="auto")'}


def report(results: dict, cmd: str, ps: float, repeat: int, label: str = "after",
           write: bool = True) -> None:
    """The tables (section ``label`` of benchmarks/results/md_cost.md) and the figure."""
    lines = [SECTIONS[label], "",
             f"Wall time per simulated picosecond against the largest energy error per atom over "
             f"{ps:g} ps, from Maxwell-Boltzmann momenta at {T_K:g} K; `{cmd}` on {machine()} "
             f"(loaded: times are ratios within the run), the fastest of {repeat} run(s) per "
             f"row.  Force evaluations count every configuration at which forces were computed "
             f"(HBVM: every stage of every iteration, plus the final positions of each step); "
             f"iterations count the stage sweeps of a step, the polish included.", ""]
    for scene, rows in results.items():
        front = pareto(rows)
        verdict = []
        for cost, what in (("s_per_ps", "wall time"), ("evals_per_ps", "force evaluations")):
            x = crossover(rows, cost)
            verdict.append(f"in {what}: none" if x is None else
                           f"in {what}: {'>= ' if x[2] else ''}{x[0]:.1e} eV/atom ({x[1]})")
        lines += [f"**{scene}**", "", "| method | default | dt [fs] | s / ps | x VV at 5 fs | "
                  "force evals / step | iterations / step | force evals / ps | "
                  "max dE / atom [eV] | front |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        ref = next((r for r in rows if r["k"] == 0 and r["dt_fs"] == 5.0), None)
        for r in rows:
            ratio = f"{r['s_per_ps'] / ref['s_per_ps']:.2f}" if ref else ""
            lines.append(f"| {r['method']} | {'yes' if r.get('default') else ''} | {r['dt_fs']:g} | "
                         f"{r['s_per_ps']:.3f} | {ratio} | {r['evals_per_step']:.1f} | "
                         f"{r['iters_per_step']:.2f} | {r['evals_per_ps']:.0f} | "
                         f"{r['max_dE_per_atom']:.1e} | {'*' if r in front else ''} |")
        lines += ["", "front: no other row is both faster and more accurate.  Equal-error "
                  "crossover (HBVM cheaper than VelocityVerlet below): " + "; ".join(verdict)
                  + ".", ""]
    text = "\n".join(lines)
    if write:
        path = ROOT / "benchmarks" / "results" / "md_cost.md"
        old = path.read_text() if path.exists() else ""
        sections = {key: "" for key in SECTIONS}
        for key, title in SECTIONS.items():
            if title in old:
                rest = old.split(title, 1)[1]
                other = [t for t in SECTIONS.values() if t != title and t in rest]
                sections[key] = title + (rest.split(other[0], 1)[0] if other else rest)
        sections[label] = text + "\n"
        header = ("Force evaluations per HBVM step and the equal-error crossover against "
                  "VelocityVerlet, written by `benchmarks/bench_md_cost.py`: the code before and "
                  "after HBVMDynamics' stop rule for a calculator that is not a polynomial "
                  "(tol=\"auto\"), each with the command that printed it.\n")
        path.write_text(header + "\n" + "\n".join(sections[k].rstrip() + "\n" for k in SECTIONS
                                                  if sections[k]))
        plot(results, ROOT / "docs" / "figures" / "md_cost.png")
    print(text)


def from_csv(label: str) -> int:
    """Re-render the tables and the figure from docs/figures/md_cost.csv (no runs)."""
    results, cmd = {}, ""
    with open(ROOT / "docs" / "figures" / "md_cost.csv") as fh:
        for row in csv.DictReader(fh):
            scene, cmd = row.pop("scene"), row.pop("command")
            r = {k: (v if k == "method" else float(v)) for k, v in row.items()}
            for key in ("s", "k", "steps", "default"):
                r[key] = int(r[key])
            results.setdefault(scene, []).append(r)
    ps = float(re.search(r"--ps (\S+)", cmd).group(1))
    repeat = int(re.search(r"--repeat (\S+)", cmd).group(1))
    found = re.search(r"--label (\S+)", cmd)
    report(results, cmd, ps, repeat, found.group(1) if found else label)
    return 0


if __name__ == "__main__":
    sys.exit(main())
