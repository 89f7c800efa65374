"""Benchmark (not a test): EQUIP on ASE's tutorial copper nanoparticle (issue 35, item 5).

The scene as ASE's MD tutorial builds it: ``ase.cluster.cubic.FaceCenteredCubic("Cu",
[(1, 0, 0), (1, 1, 0), (1, 1, 1)], [3, 3, 3], latticeconstant=3.61)`` (43 atoms), EMT,
Maxwell-Boltzmann momenta at 300 K (seeded, zero total momentum), 5 fs, 200 steps (1 ps).
For each seed the methods run in turn in one process: ASE's VelocityVerlet, HBVM(k, s) and
EQUIP(k, s) (``HBVMDynamics(..., s=s)``, method "hbvm" and "equip", k the default s + 1).

Columns: the largest |E - E0| over the run per atom (eV/atom, E read every step), the largest
change of the total angular momentum |L - L0| / |L0|, the wall time of ``dyn.run`` (the
engine's compile done before, on a two-step run) as a ratio to VelocityVerlet's and EQUIP's
to HBVM's (medians over the seeds; a loaded machine: ratios, not seconds), the force
evaluations a step (``stage_evaluations``), and for EQUIP the largest |alpha| and the steps
whose alpha exceeds 0.25 (the secant's range; the root search of
:func:`integrators.equip_core.update_alpha` found them: order 2 at that step, see
:mod:`integrators.equip`).  A run that fails says so in its row.

Run:  python benchmarks/bench_equip_nanoparticle.py [--seeds 3] [--s 2 3] [--steps 200]
(writes benchmarks/results/equip_nanoparticle.md)
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np
from ase import units
from ase.calculators.emt import EMT
from ase.cluster.cubic import FaceCenteredCubic
from ase.md.verlet import VelocityVerlet

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from hbvm_md import HBVMDynamics  # noqa: E402
from hbvm_md.reports.md_comparison import maxwell_boltzmann  # noqa: E402
from integrators.equip_core import ALPHA_MAX  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results" / "equip_nanoparticle.md"
DT_FS = 5.0


def nanoparticle(seed: int):
    atoms = FaceCenteredCubic("Cu", [(1, 0, 0), (1, 1, 0), (1, 1, 1)], [3, 3, 3],
                              latticeconstant=3.61)
    maxwell_boltzmann(atoms, 300.0, seed)
    atoms.calc = EMT()
    return atoms


def make(name: str, atoms, s: int):
    if name == "VelocityVerlet":
        return VelocityVerlet(atoms, DT_FS * units.fs)
    return HBVMDynamics(atoms, DT_FS * units.fs, s=s, method=name.lower())


def run(name: str, s: int, seed: int, steps: int) -> dict:
    make(name, nanoparticle(seed), s).run(2)             # compile outside the timing
    atoms = nanoparticle(seed)
    dyn = make(name, atoms, s)
    E, L, alpha = [], [], []

    def observe():
        E.append(atoms.get_potential_energy() + atoms.get_kinetic_energy())
        L.append(np.cross(atoms.get_positions(), atoms.get_momenta()).sum(axis=0))
        st = getattr(dyn, "_stepper", None)
        if name == "EQUIP" and st is not None:
            alpha.append(abs(float(st._eref[1])))
    dyn.attach(observe)
    failure = ""
    t = time.perf_counter()
    try:
        dyn.run(steps)
    except Exception as err:                               # reported in the row
        failure = f"{type(err).__name__}: {err}"
    wall = time.perf_counter() - t
    E, L = np.array(E), np.array(L)
    n = len(E) - 1
    return {"method": name if name == "VelocityVerlet" else repr(dyn.method), "seed": seed,
            "steps": n, "dE": float(np.max(np.abs(E - E[0]))) / len(atoms),
            "dL": float(np.max(np.linalg.norm(L - L[0], axis=1)) / np.linalg.norm(L[0])),
            "wall": wall / max(n, 1),
            "nfev": (dyn.stage_evaluations / max(n, 1)) if hasattr(dyn, "stage_evaluations")
            else 1.0,
            "alpha": max(alpha) if alpha else float("nan"),
            "big": int(np.sum(np.array(alpha) > ALPHA_MAX)) if alpha else 0,
            "failure": failure}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--s", type=int, nargs="+", default=[2, 3])
    ap.add_argument("--steps", type=int, default=200)
    args = ap.parse_args(argv)
    rows = []
    for s in args.s:
        for seed in range(args.seeds):
            for name in ("VelocityVerlet", "HBVM", "EQUIP"):
                if name == "VelocityVerlet" and s != args.s[0]:
                    continue
                r = run(name, s, seed, args.steps)
                r["s"] = s
                rows.append(r)
                print(r, flush=True)
    vv = np.median([r["wall"] for r in rows if r["method"] == "VelocityVerlet"])
    lines = [
        "# EQUIP on ASE's tutorial copper nanoparticle",
        "",
        f"`python benchmarks/bench_equip_nanoparticle.py --seeds {args.seeds} --s "
        f"{' '.join(map(str, args.s))} --steps {args.steps}`: 43 EMT copper atoms "
        f"(`ase.cluster.cubic.FaceCenteredCubic`, layers [3, 3, 3], a = 3.61 A), 300 K "
        f"(seeded Maxwell-Boltzmann, zero total momentum), {DT_FS:g} fs, {args.steps} steps "
        f"({args.steps * DT_FS / 1000:g} ps).  dE: max |E - E0| per atom; dL: max |L - L0| / "
        f"|L0| (total angular momentum); time: dyn.run's wall time a step over VelocityVerlet's "
        f"(same process, loaded machine); evaluations: force evaluations a step; |alpha|: "
        f"EQUIP's largest, and its steps beyond {ALPHA_MAX:g} (found by the root search, "
        f"order 2 at that step).",
        "",
        "| method | seed | steps | dE (eV/atom) | dL | time / VV | evaluations a step "
        "| max abs(alpha) | steps with abs(alpha) > 0.25 | failure |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        a = "" if np.isnan(r["alpha"]) else f"{r['alpha']:.2g}"
        big = str(r["big"]) if r["method"].startswith("EQUIP") else ""
        lines.append(f"| {r['method']} | {r['seed']} | {r['steps']} | {r['dE']:.2e} | "
                     f"{r['dL']:.1e} | {r['wall'] / vv:.1f} | {r['nfev']:.1f} | {a} | {big} | "
                     f"{r['failure'][:160]} |")
    lines.append("")
    for s in args.s:
        eq = [r["wall"] for r in rows if r["s"] == s and r["method"].startswith("EQUIP")]
        hb = [r["wall"] for r in rows if r["s"] == s and r["method"].startswith("HBVM")]
        lines.append(f"s = {s}: EQUIP's time a step over HBVM's (medians over the seeds): "
                     f"{np.median(eq) / np.median(hb):.2f}; over VelocityVerlet's: "
                     f"{np.median(eq) / vv:.1f}.")
    lines.append("")
    RESULTS.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
