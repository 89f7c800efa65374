"""
A work-precision diagram
========================

How much work buys how much accuracy, on the Kepler problem at e = 0.6 over 20 periods: for
each method the step is swept from 25 to 400 steps a period, and each run gives a point (force
evaluations, error). Two errors: the largest relative energy error over the run, and the
distance of the final state from the exact solution. Gauss, HBVM(s, s), and HBVM(8, s) share
the order 2s; HBVM(8, s) computes the line integral of the energy with 8 quadrature nodes, so
its energy error sits at round-off.

Force evaluations are counted, not timed: the count is the same on every machine (the
benchmarks time the same runs, :doc:`../results/engine`).

At 25 steps a period an order-4 step misses more than a thousandth of the motion through
pericentre: by default such a run is refused by the step's own error check
(``UnresolvedStepError``), and a Gauss run whose energy ends up more than 1e-3 of ``|T| + |V|``
away from its start by the run's drift check (``EnergyDriftError``). A diagram measures each
point's error against the exact solution, so these runs pass ``error_bound=None`` and
``energy_tol=None`` to keep the coarse points.
"""
import matplotlib.pyplot as plt
import numpy as np

from integrators import HBVM
from systems import Kepler

kepler = Kepler(0.6)
y0 = kepler.initial_state()
PERIODS = 20
T = PERIODS * kepler.period
exact = kepler.exact_solution(y0, T)

methods = [HBVM(2, 2), HBVM(8, 2), HBVM(4, 4), HBVM(8, 4)]
per_period = [25, 50, 100, 200, 400]
points = {}
for method in methods:
    rows = []
    for n in per_period:
        res = method.integrate(kepler, y0, h=kepler.period / n, steps=n * PERIODS,
                               error_bound=None, energy_tol=None)
        rows.append((res.nfev, res.max_energy_error, np.linalg.norm(res.y[-1] - exact)))
    points[str(method)] = np.array(rows)
    print(method, "energy errors:", " ".join(f"{r[1]:.1e}" for r in rows))

# %%
# On the right, both methods of a given s converge at the same order 2s; HBVM(8, s) pays for
# its 8 stages with more force evaluations for the same solution error. On the left is what it
# buys: the Gauss methods' energy error falls with the step at order 2s, while HBVM(8, s) has
# the energy at round-off from about 50 steps a period on (at the largest step its iteration
# still converges, but the 8-node quadrature is not yet exact to round-off).

fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), sharex=True)
for name, rows in points.items():
    style = "--o" if name.startswith("HBVM(2, 2)") or name.startswith("HBVM(4, 4)") else "-s"
    axes[0].loglog(rows[:, 0], np.maximum(rows[:, 1], 1e-17), style, label=name)
    axes[1].loglog(rows[:, 0], rows[:, 2], style, label=name)
axes[0].set(xlabel="force evaluations", ylabel="max |H - H0| / |H0|", title="energy error")
axes[1].set(xlabel="force evaluations", ylabel="|y(T) - y_exact(T)|", title="solution error")
axes[0].legend()
fig.tight_layout()
plt.show()
