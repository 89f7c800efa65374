"""Benchmark (not a test): CPU time a step of the step loop itself, for A/B checks of a change
to the engine against another source tree of hbvm-md, run alternately.

Scenes (microseconds of process CPU a step, median of 3 runs in one process, after a warm-up):
HLW's outer solar system through REBOUND with HBVM(9, 8) at 500 days ("fixed") and at the
adaptive defaults ("adaptive"); the same with 200 test particles at 100 days ("followers"); a
125-atom soft-sphere crystal under HBVMDynamics (s = 2, 2 fs; "md": the engine's per-step
Python path).  Per ``sim.integrate`` call rather than per step: "call", a call that takes one
step of "fixed" (an output every step, as bench_rebound's 1e5-day scene), "empty", a call that
takes none (the host's per-call cost alone), and "empty-whfast", the same call with WHFast
(REBOUND's own per-call cost, for scale; the table's last row is the ratio of the two, taken
in each process, which the machine's drifting speed leaves alone).  Each tree runs in its own
process with its own compile cache, warmed by a first round that is not reported; the rounds
alternate the trees and the table gives each tree's fastest round (a shared machine slows
single runs).

    python benchmarks/bench_step_cost.py [--compare DIR] [--rounds 3]

Last run (2026-11-28, this tree against 65de54b, the commit before the per-call cuts and the
compensated clock; two runs of 3 rounds each, load average 0.9-1.1 on 2 cores, fastest round):
empty 3.1 us against 5.9 (0.53x; against WHFast's empty call 1.06x, was 2.04x), call 24.2-24.3
against 27.0-27.1 (0.90x), fixed 20.3-20.7 against 20.4-20.5, adaptive 15.0 against 14.8-14.9,
followers 181-189 against 182-184, md 495-502 against 499 (the same within the machine's noise).
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = ("fixed", "adaptive", "followers", "md", "call", "empty", "empty-whfast")

CHILD = r"""
import resource, statistics, sys
import numpy as np
import rebound
import hbvm_md
from hbvm_md import HBVMIntegrator
from systems import outer_solar_system

def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF); return r.ru_utime + r.ru_stime

out = []
for mode in ("fixed", "adaptive", "followers"):
    ts = []
    for rep in range(3):
        sim = outer_solar_system().to_rebound()
        if mode == "followers":
            rng = np.random.default_rng(rep)
            for i in range(200):
                sim.add(a=rng.uniform(20, 40), e=0.05 * rng.random(), inc=0.02 * rng.random(), l=6.28 * rng.random())
            sim.N_active = 6
        if mode == "fixed":
            HBVMIntegrator(sim, s=8, k=9, dt=500.0)
        elif mode == "followers":
            HBVMIntegrator(sim, s=8, k=9, dt=100.0)
        else:
            sim.integrator = "hbvm"
        sim.integrate(1000.0)
        n0 = sim.steps_done; c0 = cpu()
        sim.integrate(2e6 if mode != "followers" else 5e4)
        ts.append((cpu() - c0) / (sim.steps_done - n0) * 1e6)
    out.append(f"{mode} {statistics.median(ts):.3f}")
for mode in ("call", "empty", "empty-whfast"):
    ts = []
    for rep in range(3):
        sim = outer_solar_system().to_rebound()
        if mode == "empty-whfast":
            sim.integrator = "whfast"
            sim.dt = 500.0
        else:
            HBVMIntegrator(sim, s=8, k=9, dt=500.0)
        sim.integrate(1000.0)
        t = sim.t
        c0 = cpu()
        for i in range(5000):
            if mode == "call":
                t += 500.0
            sim.integrate(t)
        ts.append((cpu() - c0) / 5000 * 1e6)
    out.append(f"{mode} {statistics.median(ts):.3f}")
from ase.build import bulk
from ase import units
from hbvm_md import HBVMDynamics
from systems.pair_potential import PolynomialPairPotential
from ase.md.velocitydistribution import MaxwellBoltzmannDistribution
ts = []
for rep in range(3):
    atoms = bulk("Ar", "sc", a=3.4, cubic=True).repeat((5, 5, 5))
    atoms.rattle(0.05, seed=rep)
    MaxwellBoltzmannDistribution(atoms, temperature_K=50, rng=np.random.default_rng(rep))
    atoms.calc = PolynomialPairPotential.soft_sphere(0.01, 5.0)
    dyn = HBVMDynamics(atoms, 2 * units.fs, s=2)
    dyn.run(5)
    c0 = cpu(); dyn.run(200)
    ts.append((cpu() - c0) / 200 * 1e6)
out.append(f"md {statistics.median(ts):.1f}")
print(" ".join(out))
"""


def run(tree: str, cache: str) -> dict:
    env = dict(os.environ, PYTHONPATH=tree, HBVM_MD_CACHE_DIR=cache,
               NUMBA_CACHE_DIR=os.path.join(cache, "numba"))
    r = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, env=env,
                       cwd=tempfile.gettempdir())
    if r.returncode != 0:
        raise RuntimeError(f"the scenes failed in {tree}:\n{r.stderr[-2000:]}")
    words = r.stdout.strip().splitlines()[-1].split()
    return {k: float(v) for k, v in zip(words[::2], words[1::2])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--compare", default=None, help="another hbvm-md source tree")
    ap.add_argument("--label", default="compared", help="its name in the table")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    trees = [("this tree", ROOT)] + ([(args.label, os.path.abspath(args.compare))]
                                     if args.compare else [])
    caches = {label: tempfile.mkdtemp(prefix="hbvm-md-ab-") for label, _ in trees}
    best: dict = {}
    ratios: dict = {}
    for r in range(args.rounds + 1):
        for label, tree in trees:
            res = run(tree, caches[label])
            if r == 0:
                continue                      # the warm-up round compiles
            print(f"round {r} {label}: " + " ".join(f"{k} {v:.3f}" for k, v in res.items()),
                  flush=True)
            for k, v in res.items():
                best[(label, k)] = min(best.get((label, k), v), v)
            # the host's per-call cost against REBOUND's own in the same process (the machine's
            # speed drifts between processes by up to 2x: the ratio does not)
            ratios.setdefault(label, []).append(res["empty"] / res["empty-whfast"])
    print(f"\nload average {os.getloadavg()[0]:.1f}; us of CPU a step (call, empty, "
          "empty-whfast: a sim.integrate call), fastest round")
    print("| scene | " + " | ".join(label for label, _ in trees) + " |")
    print("|---|" + "---:|" * len(trees))
    for k in SCENES:
        print(f"| {k} | " + " | ".join(f"{best.get((label, k), float('nan')):.1f}"
                                       for label, _ in trees) + " |")
    print("| empty / empty-whfast (median of the rounds' ratios) | "
          + " | ".join(f"{statistics.median(ratios[label]):.2f}" for label, _ in trees) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
