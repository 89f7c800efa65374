"""
A MEGNO map
===========

Chaos indicators come from variational equations: REBOUND's ``sim.init_megno()`` adds
variational particles, and with ``sim.integrator = "hbvm"`` HBVM carries them by the derivative
of its own step and hands REBOUND the MEGNO increments, so ``sim.megno()`` is REBOUND's own
bookkeeping. MEGNO <Y> (Cincotta and Simo) tends to 2 on a regular orbit and grows on a chaotic
one.

Here a Saturn-mass planet is placed beyond Jupiter on a small grid of semi-major axes and
eccentricities, each point run for 300 Jupiter periods. The grid is small so that the page
builds in seconds; ``hbvm-md ensemble stability-map`` (:doc:`../guide/ensembles`) spreads larger
maps over many cores.
"""
import matplotlib.pyplot as plt
import numpy as np
import rebound

import hbvm_md  # noqa: F401  (registers "hbvm" with REBOUND)
from integrators import StepError

P_JUPITER = 2 * np.pi * 5.204 ** 1.5             # G = 1, Sun mass 1, a in AU
A_VALUES = np.linspace(7.0, 10.0, 10)
E_VALUES = np.linspace(0.0, 0.3, 4)


def megno(a: float, e: float, orbits: float = 300) -> float:
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=9.54e-4, a=5.204, e=0.048, M=0.600, omega=0.257)    # Jupiter
    sim.add(m=2.85e-4, a=a, e=e, M=0.871, omega=1.616)            # a Saturn
    sim.move_to_com()
    sim.integrator = "hbvm"
    sim.dt = P_JUPITER / 50                       # the first trial step (adaptive after it)
    sim.init_megno(seed=0)
    try:
        sim.integrate(orbits * P_JUPITER)
    except StepError:                             # a close encounter: the planets collide
        return np.nan                             # (drawn grey)
    return sim.megno()


Y = np.array([[megno(a, e) for a in A_VALUES] for e in E_VALUES])
print("MEGNO <Y>, rows e =", E_VALUES, ":")
print(np.array2string(Y, precision=2, max_line_width=120))

# %%
# Regular orbits sit at <Y> = 2; the higher values mark chaos, strongest where the planets'
# orbits approach each other (small a, large e) and near mean-motion resonances with Jupiter;
# grey points stopped at a close encounter that no step could resolve (the planets collide), a
# clear error rather than a silently wrong orbit.

fig, ax = plt.subplots(figsize=(8, 3.8))
cmap = plt.get_cmap("viridis").with_extremes(bad="lightgrey")
mesh = ax.pcolormesh(A_VALUES, E_VALUES, np.ma.masked_invalid(np.clip(Y, 0, 8)), cmap=cmap,
                     vmin=1.5, vmax=8, shading="nearest")
fig.colorbar(mesh, ax=ax, label="MEGNO <Y> (clipped at 8)")
ax.set(xlabel="semi-major axis a [AU]", ylabel="eccentricity e",
       title="a Saturn beyond Jupiter, 300 Jupiter periods")
fig.tight_layout()
plt.show()
