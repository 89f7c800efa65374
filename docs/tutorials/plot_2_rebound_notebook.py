"""
A REBOUND notebook with "hbvm"
==============================

The pattern of REBOUND's own example notebooks, with one line changed: build a simulation,
``sim.integrator = "hbvm"``, integrate over a list of output times and read the particles.
Everything REBOUND offers around the step stays REBOUND's: units, orbital elements,
``sim.copy()``, ``save_to_file``, archives. HBVM's settings are fields of ``sim.integrator``.
"""
import matplotlib.pyplot as plt
import numpy as np
import rebound

import hbvm_md  # noqa: F401  (registers "hbvm" with REBOUND)
from hbvm_md import HBVMIntegrator

sim = rebound.Simulation()
sim.units = ("yr", "AU", "Msun")
sim.add(m=1.0)                                                      # the Sun
sim.add(m=9.55e-4, a=5.20, e=0.048, omega=0.257, M=0.600)           # Jupiter
sim.add(m=2.86e-4, a=9.58, e=0.056, omega=1.616, M=0.871, inc=0.04)  # Saturn
sim.move_to_com()

sim.integrator = "hbvm"            # was: "ias15"
print("s, k, epsilon:", sim.integrator.s, sim.integrator.k, sim.integrator.epsilon)

# %%
# Integrate over output times and record what a notebook plots: positions and orbital
# elements. Adaptive steps land exactly on each output time, as IAS15's do.

times = np.linspace(0.0, 600.0, 1201)             # years: about 50 Jupiter orbits
xy = np.empty((len(times), 3, 2))
ecc = np.empty((len(times), 2))
E0 = sim.energy()
for i, t in enumerate(times):
    sim.integrate(t)
    xy[i] = [(p.x, p.y) for p in sim.particles]
    ecc[i] = [o.e for o in sim.orbits()]
print(f"relative energy error after {sim.t:.0f} years: {abs(sim.energy() / E0 - 1):.1e}")

view = HBVMIntegrator.of(sim)                     # HBVM's counters, read from the simulation
print("steps:", view.nsteps, " force evaluations:", view.nfev, " rejected:", view.rejected)

# %%
# A copy continues bit for bit, and so does a file: HBVM's state is saved in REBOUND's own
# binary, with no file of ours beside it.

copy = sim.copy()
sim.integrate(700.0)
copy.integrate(700.0)
print("copy == original after 100 more years:",
      all(a.xyz == b.xyz for a, b in zip(sim.particles, copy.particles)))

fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
for j, name in enumerate(["Sun", "Jupiter", "Saturn"]):
    axes[0].plot(xy[:, j, 0], xy[:, j, 1], lw=0.6, label=name)
axes[0].set(xlabel="x [AU]", ylabel="y [AU]", title="orbits", aspect="equal")
axes[0].legend(loc="upper right")
axes[1].plot(times, ecc[:, 0], label="Jupiter")
axes[1].plot(times, ecc[:, 1], label="Saturn")
axes[1].set(xlabel="time [years]", ylabel="eccentricity", title="eccentricities")
axes[1].legend()
fig.tight_layout()
plt.show()
