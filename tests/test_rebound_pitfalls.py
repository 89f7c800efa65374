"""What a REBOUND user written for IAS15 does that HBVM must either honour or flag (issue 47):
IAS15's fixed-step idiom ``epsilon = 0``, a velocity-dependent Python force without
``force_is_velocity_dependent``, step-counted archives with adaptive steps, REBOUNDx operators
split at HBVM's long steps."""
import warnings

import numpy as np
import pytest
import rebound

import hbvm_md  # noqa: F401  (registers "hbvm")
from hbvm_md import HBVMIntegrator
from systems import outer_solar_system


def _xv(sim):
    return np.array([[p.x, p.y, p.z, p.vx, p.vy, p.vz] for p in sim.particles])


# -- epsilon = 0: fixed steps of sim.dt, as with IAS15 ---------------------------------------------
def test_epsilon_zero_takes_fixed_steps_of_sim_dt_as_ias15():
    sim = outer_solar_system().to_rebound()
    sim.integrator = "hbvm"
    sim.dt = 100.0
    sim.integrator.epsilon = 0           # IAS15's idiom (it used to fail at integrate)
    sim.integrate(1000.0)
    assert sim.t == 1000.0 and sim.dt == 100.0 and sim.steps_done == 10
    assert sim.dt_last_done == 100.0
    assert not HBVMIntegrator.of(sim).adaptive
    ref = outer_solar_system().to_rebound()
    HBVMIntegrator(ref, s=6, k=8, dt=100.0)
    ref.integrate(1000.0)
    assert np.array_equal(_xv(sim), _xv(ref))
    # and through the handle: epsilon=0 is a fixed step of sim.dt
    other = outer_solar_system().to_rebound()
    other.dt = 100.0
    assert not HBVMIntegrator(other, s=6, k=8, epsilon=0).adaptive
    other.integrate(1000.0)
    assert np.array_equal(_xv(other), _xv(ref))
    # a positive epsilon set afterwards makes the steps adaptive again
    sim.integrator.epsilon = 1e-3
    sim.integrate(5000.0)
    assert sim.dt != 100.0 and HBVMIntegrator.of(sim).adaptive


def test_negative_epsilon_is_refused_naming_zero_for_fixed_steps():
    sim = outer_solar_system().to_rebound()
    sim.integrator = "hbvm"
    sim.integrator.epsilon = -1.0
    with pytest.raises(ValueError, match=r"epsilon = 0 takes fixed steps of sim.dt"):
        sim.integrate(100.0)
