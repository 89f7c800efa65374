"""Negative masses with "hbvm" in IAS15's place: a negative mass is a source (REBOUND's and
IAS15's convention), so runs with one, a mass varied through zero by finite differences (as
REBOUND's own test_variational.py does) and a mass changed between runs are IAS15's, and the
energy check's reference follows a mass changed between runs."""
import ctypes

import numpy as np
import pytest
import rebound

import hbvm_md  # noqa: F401  (registers "hbvm")
from hbvm_md import HBVMIntegrator
from hbvm_md.rebound import layout as L
from hbvm_md.rebound.host import _prepared


def _xv(sim):
    a = np.zeros(6 * sim.N)
    sim.serialize_particle_data(xyzvxvyvz=a)
    return a


def _three(integrator, m1=-1e-3, m2=1e-3, test_particle=True, softening=0.0):
    """A star, a planet of mass m1 at a = 1 and one of m2 at a = 1.76 (elements about the
    star: REBOUND takes G (M + m)), and a test particle at a = 1.3; softening > 0: on
    REBOUND's own accelerations."""
    sim = rebound.Simulation()
    sim.softening = softening
    sim.add(m=1.0)
    sim.add(m=m1, a=1.0, e=0.1, f=0.3, inc=0.1)
    sim.add(m=m2, a=1.76, e=0.05, primary=sim.particles[0])
    if test_particle:
        sim.add(a=1.3, e=0.2, f=2.0, primary=sim.particles[0])
    sim.move_to_com()
    sim.integrator = integrator
    if integrator == "ias15":
        sim.integrator.epsilon = 0          # IAS15's fixed steps of 1e-3: far below 1e-12
        sim.dt = 1e-3
    return sim


@pytest.mark.parametrize("m1, m2, softening", [(-1e-3, 1e-3, 0.0), (-0.3, 0.0, 0.0),
                                               (-1e-5, 2e-5, 0.0), (-1e-3, 1e-3, 1e-3)])
def test_negative_masses_run_as_ias15_does(m1, m2, softening):
    """Before: refused ("negative masses ... use IAS15").  A planet of negative mass beside a
    positive one and a test particle (the followers in the field of a negative source), a
    star with a heavy negative companion, and a softened scene (REBOUND's own accelerations):
    IAS15's to 1e-10 over 3 orbits, adaptive and fixed steps (whose energy check sees a
    negative kinetic energy)."""
    ref = _three("ias15", m1, m2, softening=softening)
    ref.integrate(20.0)
    sim = _three("hbvm", m1, m2, softening=softening)
    sim.integrate(20.0)
    assert np.max(np.abs(_xv(sim) - _xv(ref))) < 1e-10
    fixed = _three("hbvm", m1, m2, softening=softening)
    HBVMIntegrator(fixed, s=6, k=8, dt=0.05, adaptive=False)
    fixed.integrate(20.0)
    assert np.max(np.abs(_xv(fixed) - _xv(ref))) < 1e-10


def _mass_run(m, vary=False, t=1.4):
    """REBOUND's test_variational.py scene with planet 1's mass m (and a variation of it)."""
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=m, a=2.0, e=0.02, inc=0.0132, Omega=0.33, omega=1.56, f=0.14)
    sim.add(primary=sim.particles[0], a=1.76, m=1e-3)
    sim.integrator = "hbvm"
    var = None
    if vary:
        var = sim.add_variation()
        var.vary(1, "m")
    sim.integrate(t)
    return sim, var


def test_a_mass_varied_through_zero_matches_central_differences():
    """Before: the finite-difference run at m - delta < 0 was refused.  d(planet)/dm at
    m = 1e-6 against central differences at delta = 1e-5 (the run at m = -9e-6: a negative
    source), as REBOUND's test_variational.py differences across m = 0."""
    m, delta = 1e-6, 1e-5
    sim, var = _mass_run(m, vary=True)
    plus, _ = _mass_run(m + delta)
    minus, _ = _mass_run(m - delta)
    fd = (np.array(_xv(plus)) - np.array(_xv(minus))) / (2 * delta)
    tangent = np.array([[p.x, p.y, p.z, p.vx, p.vy, p.vz] for p in var.particles]).ravel()
    assert np.max(np.abs(fd - tangent)) < 1e-9, np.max(np.abs(fd - tangent))     # (8e-12)


def test_a_mass_that_changes_sign_between_runs_continues_as_ias15():
    """Before: a mass changed between runs to a negative value was refused at the next run.
    Now it is taken in place (the kernel's weights 1/m and its gravitating mass), as IAS15
    continues; the runs agree to 1e-10."""
    runs = []
    for integrator in ("ias15", "hbvm"):
        sim = _three(integrator, 1e-3, 1e-3)
        sim.integrate(5.0)
        sim.particles[2].m = -1e-3
        sim.integrate(10.0)
        runs.append(_xv(sim))
    assert np.max(np.abs(runs[0] - runs[1])) < 1e-10


def _energy_reference(sim) -> float:
    return float(_prepared(ctypes.addressof(sim))[1][L.SL_EREF])


def _symmetric(integrator):
    """A star at rest between two equal planets on mirrored orbits: the pulls on the star
    cancel exactly (x_2 = -x_1 in floating point), so its velocity stays exactly 0 and its
    momentum 0 whatever its mass; a variational set (so that a change of masses goes through
    the host's full preparation)."""
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, x=1.0, vy=1.0)
    sim.add(m=1e-3, x=-1.0, vy=-1.0)
    sim.integrator = integrator
    if integrator == "ias15":
        sim.integrator.epsilon = 0
        sim.dt = 1e-3
    else:
        HBVMIntegrator(sim, s=6, k=8, dt=0.05, adaptive=False)
    var = sim.add_variation()
    var.particles[1].x = 1.0
    return sim


def test_the_energy_reference_follows_a_mass_changed_between_runs():
    """The energy check's reference is the energy of the particles as the run starts, after a
    mass change between runs: no spurious refusal (a star kept at rest, whose state the host
    keeps across the change: before, UnresolvedStepError 'the step changed the energy by
    6.2e-2', the potential's jump read as the step's error) and no jump hidden (the energy after
    the run is the changed system's, and the check's reference tracks it); the same on a copy
    made before the change (a loaded or copied run keeps no record of its masses: refused as
    well before), and bit for bit the uninterrupted run's."""
    runs = []
    for integrator in ("ias15", "hbvm"):
        sim = _symmetric(integrator)
        sim.integrate(2.0)
        assert sim.particles[0].vx == sim.particles[0].vy == 0.0
        sim.particles[0].m = 1.1
        e_changed = sim.energy()
        sim.integrate(4.0)
        runs.append(_xv(sim))
        if integrator == "hbvm":
            assert abs(sim.energy() - e_changed) < 1e-13
            assert abs(_energy_reference(sim) - sim.energy()) < 1e-13
    assert np.max(np.abs(runs[0] - runs[1])) < 1e-10
    # the same change on a copy (no record of the masses its saved reference belongs to)
    sim = _symmetric("hbvm")
    sim.integrate(2.0)
    copy = sim.copy()
    copy.particles[0].m = 1.1
    copy.integrate(4.0)
    assert np.array_equal(_xv(copy), runs[1])
    # a change taken in place (no variational particles): the same
    sim = _three("hbvm", 1e-3, 1e-3, test_particle=False)
    HBVMIntegrator(sim, s=6, k=8, dt=0.05, adaptive=False)
    sim.integrate(2.0)
    sim.particles[1].m = -2e-3
    e_changed = sim.energy()
    sim.integrate(4.0)
    assert abs(sim.energy() - e_changed) < 1e-12
    assert abs(_energy_reference(sim) - sim.energy()) < 1e-13
