"""The REBOUND step as one compiled call: the C callback (no Python between steps) and the
Python callback run the same compiled step and must agree bit for bit, also when the user
changes the particles between runs and when a step fails."""
import ctypes

import numpy as np
import pytest
import rebound

from hbvm_md import HBVMIntegrator
from hbvm_md import rebound_step as glue
from integrators import ConvergenceError, StepSizeError
from systems import outer_solar_system


def _xv(sim):
    return np.array([[p.x, p.y, p.z, p.vx, p.vy, p.vz, p.m] for p in sim.particles])


def _pair(**kw):
    """Two identical driven simulations: the first runs natively, the second through the
    Python callback (a heartbeat that does nothing forces it)."""
    out = []
    for python in (False, True):
        sim = outer_solar_system().to_rebound()
        drv = HBVMIntegrator(sim, **kw)
        if python:
            sim.heartbeat = lambda simp: None
        out.append((sim, drv))
    return out


def _same(a, b):
    (sa, da), (sb, db) = a, b
    assert sa.t == sb.t and sa.dt == sb.dt and sa.dt_last_done == sb.dt_last_done
    assert sa.steps_done == sb.steps_done
    assert np.array_equal(_xv(sa), _xv(sb))
    assert (da.nsteps, da.rejected, da.niter, da.nfev, da.resyncs) == \
        (db.nsteps, db.rejected, db.niter, db.nfev, db.resyncs)


@pytest.mark.parametrize("kw", [{}, {"s": 6, "k": 8, "dt": 100.0}])
def test_native_and_python_callback_agree_bit_for_bit(kw):
    a, b = _pair(**kw)
    for t in np.linspace(0, 3e4, 31)[1:]:
        a[0].integrate(t)
        b[0].integrate(t)
    assert a[1].last_run_native and not b[1].last_run_native
    _same(a, b)
    a[0].steps(7)
    b[0].steps(7)
    _same(a, b)


def test_native_run_resyncs_after_the_user_changes_particles():
    a, b = _pair()
    for sim, _ in (a, b):
        sim.integrate(5000.0)
        sim.particles[3].vx *= 1.0 + 1e-9           # a kick
        sim.integrate(9000.0)
        sim.add(m=0.0, a=40.0, e=0.1, primary=sim.particles[0])   # a new test particle
        sim.integrate(14000.0)
        sim.remove(6)
        sim.steps(5)
    assert a[1].last_run_native
    assert a[1].resyncs == 4
    _same(a, b)


def test_native_or_python_is_decided_again_when_the_settings_change():
    """The native/Python choice is remembered between runs while nothing it depends on
    changed: a heartbeat or pre-timestep callback set (or removed) between runs, and the
    debugging switch, must be honoured by the very next run."""
    sim = outer_solar_system().to_rebound()
    drv = HBVMIntegrator(sim, s=6, k=8, dt=100.0)
    sim.integrate(1000.0)
    assert drv.last_run_native
    calls = []
    sim.heartbeat = lambda simp: calls.append(1)
    sim.integrate(2000.0)
    assert not drv.last_run_native and len(calls) >= 10
    sim.heartbeat = 0                    # REBOUND: a NULL function pointer
    n = len(calls)
    sim.integrate(3000.0)
    assert drv.last_run_native and len(calls) == n
    sim.pre_timestep_modifications = lambda simp: calls.append(2)
    sim.integrate(4000.0)
    assert not drv.last_run_native and calls.count(2) >= 10
    sim.pre_timestep_modifications = 0
    sim.integrate(5000.0)
    assert drv.last_run_native
    drv._allow_native = False
    sim.integrate(6000.0)
    assert not drv.last_run_native
    drv._allow_native = True
    sim.integrate(7000.0)
    assert drv.last_run_native


def test_native_failure_leaves_the_state_and_raises():
    a, b = _pair(s=6, k=8, dt=100.0)
    for sim, drv in (a, b):
        sim.integrate(300.0)
        before, t0 = _xv(sim), sim.t
        drv.max_iter = 1                             # cannot converge in one iteration
        with pytest.raises(ConvergenceError, match="did not converge"):
            sim.integrate(1000.0)
        assert sim.t == t0 and np.array_equal(_xv(sim), before)
        drv.max_iter = 60
        sim.integrate(1000.0)
    _same(a, b)


def test_native_adaptive_step_size_error():
    for sim, drv in _pair(epsilon=1e-15, min_dt=80.0):   # the first step (87 d) is refused
        t0 = sim.t
        before = _xv(sim)
        with pytest.raises(StepSizeError, match="min_dt"):
            sim.integrate(1e4)
        assert sim.t == t0 and np.array_equal(_xv(sim), before)


def test_stop_status_is_rebounds():
    """host_cstep stops REBOUND by writing the status that reb_simulation_stop writes."""
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.stop()
    assert sim._status == glue.REB_STATUS_USER


def test_native_integrate_call_restores_the_slots_and_takes_rebounds_arguments():
    """A native sim.integrate is one compiled call that sets REBOUND's post-timestep slot and
    ``extras`` to the C step, runs REBOUND's integrate and sets them back: after a run that
    ends normally, on REBOUND's own stop (Escape) and on a failed step alike, the slot holds
    the Python callback and ``extras`` is NULL again.  tmax and exact_finish_time are taken
    and refused as rebound.Simulation.integrate takes and refuses them."""
    sim = outer_solar_system().to_rebound()
    drv = HBVMIntegrator(sim, s=6, k=7, dt=100.0)
    cb = drv._cb_ptr

    def slots_are_pythons():
        return (drv._slots[0] == cb and drv._slots[-1] == 0 and not sim.extras
                and ctypes.cast(sim._post_timestep_modifications, ctypes.c_void_p).value == cb)

    sim.integrate(1000.0)
    assert drv.last_run_native and slots_are_pythons() and sim.t == 1000.0
    sim.exit_max_distance = 1.0
    with pytest.raises(rebound.Escape):
        sim.integrate(2000.0)
    assert drv.last_run_native and slots_are_pythons()
    sim.exit_max_distance = 0.0
    # an int, a numpy float and a float give the same run; a string is refused as REBOUND
    # refuses it (TypeError), and so is a float exact_finish_time, with nothing stepped
    ref = outer_solar_system().to_rebound()
    HBVMIntegrator(ref, s=6, k=7, dt=100.0)
    ref.integrate(1000.0)
    ref.integrate(sim.t)
    for tmax in (3000, np.float64(3500.0), 4000.25):
        sim.integrate(tmax)
        ref.integrate(float(tmax))
        assert sim.t == ref.t and np.array_equal(_xv(sim), _xv(ref))
    for tmax, eft in (("5000", 1), (5000.0, 1.5)):
        before = _xv(sim), sim.t
        for s in (sim, outer_solar_system().to_rebound()):      # REBOUND's own refuses too
            with pytest.raises(TypeError):
                s.integrate(tmax, exact_finish_time=eft)
        assert sim.t == before[1] and np.array_equal(_xv(sim), before[0])
        assert slots_are_pythons()
    # a failed step: the slots are set back as well
    drv.max_iter = 1
    with pytest.raises(ConvergenceError):
        sim.integrate(9000.0)
    assert drv.last_run_native and slots_are_pythons()
