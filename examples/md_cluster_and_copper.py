"""Energy conservation of HBVM(k, s) against VelocityVerlet: a polynomial cluster and EMT copper.

1. A 38-atom droplet with the all-pairs quartic well phi(r) = eps ((r/sigma)^4 - 2 (r/sigma)^2):
   H is a polynomial of degree 4, so HBVM(2s, s) conserves it to round-off at any step size
   where the iteration converges, while VelocityVerlet's error grows like dt^2.
2. EMT copper, 32 atoms in a periodic box at 600 K: not a polynomial; HBVM's error is set by
   the quadrature and by EMT's smoothness at its cutoff, far below VelocityVerlet's.

    python examples/md_cluster_and_copper.py [--plot energy.png] [--quick]

``--quick`` runs a 13-atom cluster and a few steps (a smoke test, as in the test suite).
"""
from __future__ import annotations

import argparse

from ase.build import bulk
from ase.calculators.emt import EMT

from hbvm_md.reports.md_comparison import compare_md, default_cluster
from hbvm_md.reports.plots import energy_error_plot


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plot", help="save a plot of the relative energy error to this file")
    ap.add_argument("--quick", action="store_true", help="13 atoms and a few steps (smoke test)")
    args = ap.parse_args(argv)
    n_atoms, steps, cu_steps = (13, 20, 5) if args.quick else (38, 1000, 100)

    print(f"## Polynomial cluster ({n_atoms} atoms, all pairs, degree 4), 300 K, {steps} steps\n")
    atoms, calc = default_cluster(n_atoms)
    cluster = compare_md(atoms, calc, timesteps_fs=(5.0, 20.0),
                         methods=("VelocityVerlet", ("HBVM", 1), ("HBVM", 2)), steps=steps,
                         temperature_K=300.0, seed=0)

    print(f"\n## EMT copper (32 atoms, periodic), 600 K, {cu_steps} steps\n")
    cu = bulk("Cu", cubic=True) * (2, 2, 2)
    copper = compare_md(cu, EMT(), timesteps_fs=(5.0,),
                        methods=("VelocityVerlet", ("HBVM", 1, 2), ("HBVM", 2, 3)), steps=cu_steps,
                        temperature_K=600.0, seed=0)

    if args.plot:
        series = {f"{name}: {label}": ser for name, res in (("cluster", cluster), ("EMT Cu", copper))
                  for label, ser in res.series.items()}
        path = energy_error_plot(series, args.plot, "Quartic cluster and EMT copper", "t [ps]")
        print(f"\nplot written to {path}")
    return cluster, copper


if __name__ == "__main__":
    main()
