"""Energy conservation of HBVM(k, s) against VelocityVerlet: a polynomial cluster and EMT copper.

1. A 38-atom droplet with the all-pairs quartic well phi(r) = eps ((r/sigma)^4 - 2 (r/sigma)^2):
   H is a polynomial of degree 4, so HBVM(2s, s) conserves it to round-off at any step size
   where the iteration converges, while VelocityVerlet's error grows like dt^2.
2. EMT copper, 32 atoms in a periodic box at 600 K: not a polynomial; HBVM's error is set by
   the quadrature and by EMT's smoothness at its cutoff, far below VelocityVerlet's.

    /tmp/venv/bin/python examples/md_cluster_and_copper.py [--plot energy.png]
"""
from __future__ import annotations

import argparse

from ase.build import bulk
from ase.calculators.emt import EMT

from hbvm_md.md_comparison import compare_md, default_cluster


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plot", help="save a plot of the relative energy error to this file")
    args = ap.parse_args(argv)

    print("## Polynomial cluster (38 atoms, all pairs, degree 4), 300 K, 1000 steps\n")
    atoms, calc = default_cluster(38)
    cluster = compare_md(atoms, calc, timesteps_fs=(5.0, 20.0),
                         methods=("VelocityVerlet", ("HBVM", 1), ("HBVM", 2)), steps=1000,
                         temperature_K=300.0, seed=0)

    print("\n## EMT copper (32 atoms, periodic), 600 K, 100 steps\n")
    cu = bulk("Cu", cubic=True) * (2, 2, 2)
    copper = compare_md(cu, EMT(), timesteps_fs=(5.0,),
                        methods=("VelocityVerlet", ("HBVM", 1, 2), ("HBVM", 2, 3)), steps=100,
                        temperature_K=600.0, seed=0)

    if args.plot:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for ax, res, title in ((axes[0], cluster, "quartic cluster"), (axes[1], copper, "EMT Cu")):
            for label, (t, err) in res.series.items():
                ax.semilogy(t, abs(err) + 1e-17, label=label)
            ax.set_xlabel("t [ps]")
            ax.set_ylabel("|E - E0| / |E0|")
            ax.set_title(title)
            ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(args.plot, dpi=120)
        print(f"\nplot written to {args.plot}")
    return cluster, copper


if __name__ == "__main__":
    main()
