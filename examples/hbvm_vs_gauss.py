"""HBVM(k, s) against Gauss-Legendre (= HBVM(s, s)) on polynomial Hamiltonians.

Henon-Heiles (degree 3) and the stiff FPU chain (degree 4): with k >= nu s / 2 the energy is
conserved to round-off; Gauss, symplectic but not energy-preserving, shows a bounded error.

For each order s the two methods run at one step size, with the default checks: a step at
which both resolve their motion (every step's own error check and the run's drift check pass,
and the run's accumulated error estimate stays below 1e-2, so no AccumulatedErrorWarning) and
Gauss's energy error still stands well above round-off.  The lower the order, the smaller that
step: on the stiff springs (omega = 50) Gauss(3) resolves h omega = 1, Gauss(2) h omega = 1/4
and the midpoint rule (s = 1) h omega = 1/100.  The runs are as long as a double-precision path
can be followed: this Henon-Heiles orbit is chaotic (two fine reference runs part between
t = 1000 and 1500), and so is the FPU chain's slow exchange (they differ by 2 % of its soft
motion at t = 400).  ``python benchmarks/bench_energy_check.py --scenes`` measures the ends of
the Gauss(2) and Gauss(3) runs against such a reference: within 0.6 % of their motion's scale
(for FPU, of the stiff springs' amplitude).

Run:  python examples/hbvm_vs_gauss.py
"""

from integrators import HBVM
from systems import FPU, HenonHeiles

# title, system, t_end, {s: h}
SCENES = [
    ("Henon-Heiles", HenonHeiles(y0=[0.0, 0.1, 0.5, 0.1]), 200.0, {1: 0.01, 2: 0.2, 3: 0.5}),
    ("FPU m=3, omega=50", FPU(m=3, omega=50.0), 20.0, {1: 0.01 / 50, 2: 0.25 / 50, 3: 1 / 50}),
]


def steps(t_end: float, h: float) -> int:
    """The number of steps of h to t_end."""
    return int(round(t_end / h))


def main() -> None:
    print(f"{'scene':18s} {'method':16s} {'h':>7s} {'steps':>7s} {'max |H-H0|/|H0|':>17s} "
          f"{'run estimate':>12s} {'iter/step':>9s} {'time s':>7s}")
    for title, system, t_end, hs in SCENES:
        nu = system.polynomial_degree
        for s, h in hs.items():
            n = steps(t_end, h)
            for method in (HBVM(s, s), HBVM.for_polynomial_degree(nu, s)):
                # the default checks: each run is a resolved one (the run estimate, its
                # accumulated error relative to the motion's scale, below 1e-2)
                r = method.integrate(system, system.initial_state(), h, n, sample_every=10)
                label = f"{method!r}" + (" Gauss" if method.k == s else "")
                print(f"{title:18s} {label:16s} {h:7.4g} {n:7d} {r.max_energy_error:17.2e} "
                      f"{r.error_estimate:12.1e} {r.iterations_per_step:9.2f} {r.wall_time:7.3f}")


if __name__ == "__main__":
    main()
