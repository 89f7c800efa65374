"""The tidal spin scene of REBOUNDx's ``tides_spin`` (issue 49) and its independent reference,
shared by ``tests/test_rebound_odes.py`` and ``benchmarks/bench_tides_spin.py``.

A Sun-like star and a hot Jupiter at 0.04 AU (e = 0.2, inc = 0.2), both spinning, with
quadrupole and constant-time-lag tides (AU, Msun, yr); the reference is scipy's DOP853 on
REBOUND's and REBOUNDx's own right-hand side (accelerations of
``reb_simulation_update_acceleration`` with the spins written into the particles' "Omega", the
spins' derivatives from the spin ODE's own ``derivatives``), so that it shares no code with
either integrator's stepping.
"""
from __future__ import annotations

import ctypes

import numpy as np
import rebound


def tidal_spin_scene(integrator: str, epsilon: float | None = None):
    """(sim, rebx): the scene with ``integrator`` set (and IAS15's ``epsilon`` when given), the
    spin ODE initialised."""
    import reboundx
    sim = rebound.Simulation()
    sim.units = ("AU", "Msun", "yr")
    sim.add(m=1.0, r=0.00465)
    sim.add(m=1e-3, r=0.000477, a=0.04, e=0.2, inc=0.2)
    sim.move_to_com()
    sim.integrator = integrator
    if epsilon is not None:
        sim.integrator.epsilon = epsilon
    rebx = reboundx.Extras(sim)
    tides = rebx.load_force("tides_spin")
    rebx.add_force(tides)
    for p, om, kk, tau in ((sim.particles[0], (0.0, 0.0, 230.0), 0.07, 1e-6),
                           (sim.particles[1], (30.0, 0.0, 2000.0), 0.25, 1e-4)):
        p.params["k2"] = 0.3
        p.params["tau"] = tau
        p.params["I"] = kk * p.m * p.r ** 2
        p.params["Omega"] = list(om)
    rebx.initialize_spin_ode(tides)
    return sim, rebx


def spins(sim) -> np.ndarray:
    """The spinning bodies' Omega, 3 each, flat."""
    return np.ravel([list(p.params["Omega"]) for p in sim.particles if "I" in p.params])


def state_with_spins(sim) -> np.ndarray:
    """(x, v (6N), spins (3 per spinning body)) of the simulation as it is."""
    xv = np.zeros(6 * sim.N)
    sim.serialize_particle_data(xyzvxvyvz=xv)
    return np.concatenate([xv, spins(sim)])


def dop853_reference(sim, T: float, rtol: float = 1e-13) -> np.ndarray:
    """:func:`state_with_spins` at time T from ``sim``'s state by DOP853 (module docstring);
    ``sim`` is used as the right-hand side's evaluator and left at the last evaluation."""
    from scipy.integrate import solve_ivp
    N = sim.N
    O = rebound.ode.ODE
    a = ctypes.cast(sim._odes[0], ctypes.c_void_p).value
    n = ctypes.c_uint.from_address(a + O.length.offset).value
    deriv = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.POINTER(ctypes.c_double),
                             ctypes.POINTER(ctypes.c_double), ctypes.c_double)(
        ctypes.c_void_p.from_address(a + O._derivatives.offset).value)
    spinning = [p for p in sim.particles if "I" in p.params]
    y0 = state_with_spins(sim)
    zd = (ctypes.c_double * n)()

    def f(t, Y):
        sim.set_serialized_particle_data(xyzvxvyvz=Y[:6 * N])
        for i, p in enumerate(spinning):
            p.params["Omega"] = list(Y[6 * N + 3 * i:6 * N + 3 * i + 3])
        sim.t = t
        rebound.clibrebound.reb_simulation_update_acceleration(ctypes.byref(sim))
        acc = np.array([[p.ax, p.ay, p.az] for p in sim.particles])
        deriv(a, zd, (ctypes.c_double * n)(*Y[6 * N:]), t)
        v = Y[:6 * N].reshape(N, 6)[:, 3:]
        return np.concatenate([np.concatenate([v, acc], axis=1).ravel(), zd[:]])
    sol = solve_ivp(f, (0.0, T), y0, method="DOP853", rtol=rtol, atol=rtol)
    return sol.y[:, -1]
