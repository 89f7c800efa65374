"""REBOUND's clock under HBVM: both REBOUND steps (plain and kepler = 1) advance ``sim.t`` by a
compensated sum of their steps (hbvm_md.rebound.particles.step_end), kept in HBVM's saved state
(``t_comp``, ``t_written``), so that sim.t stays n dt to an ulp; a sim.t set by the user is taken
as it is; an archive saved before those fields existed loads and continues."""
import math
import struct
from fractions import Fraction

import numpy as np
import pytest
import rebound

from hbvm_md import HBVMIntegrator
from systems import outer_solar_system

DT = 100.1          # days: not a binary fraction, so that each plain t + dt rounds


def _sim(kind):
    sim = outer_solar_system().to_rebound()
    if kind == "kepler":
        HBVMIntegrator(sim, kepler=True, dt=DT)
    else:
        HBVMIntegrator(sim, s=6, k=8, dt=DT)
    return sim


def _xv(sim):
    xv = np.zeros(6 * sim.N)
    sim.serialize_particle_data(xyzvxvyvz=xv)
    return xv


def _near(t, exact: Fraction) -> bool:
    """t is the exact value rounded, to an ulp."""
    return abs(Fraction(t) - exact) <= Fraction(math.ulp(float(exact)))


@pytest.mark.parametrize("kind", ["plain", "kepler"])
def test_sim_t_after_many_fixed_steps_is_n_dt_to_an_ulp(kind):
    n = 4000
    sim = _sim(kind)
    sim.steps(n)
    naive = 0.0
    for _ in range(n):
        naive += DT
    exact = n * Fraction(DT)
    # (the plain sum is off by many ulps here: what the steps did before the compensation)
    assert not _near(naive, exact)
    assert _near(sim.t, exact), (sim.t, float(exact))
    assert sim.integrator.t_written == sim.t
    # a copy carries the compensation: both continue to the same sim.t and particles
    twin = sim.copy()
    for s in (sim, twin):
        s.steps(100)
    assert twin.t == sim.t and np.array_equal(_xv(twin), _xv(sim))
    assert _near(sim.t, (n + 100) * Fraction(DT))


@pytest.mark.parametrize("kind", ["plain", "kepler"])
def test_a_sim_t_set_by_the_user_is_taken_as_it_is(kind):
    sim = _sim(kind)
    sim.steps(300)
    assert sim.integrator.t_comp != 0.0        # (there is a compensation to forget)
    t0 = 12345.678
    sim.t = t0
    sim.steps(1)
    assert sim.t == t0 + DT and sim.integrator.t_comp == (sim.t - t0) - DT
    sim.steps(299)
    assert _near(sim.t, Fraction(t0) + 300 * Fraction(DT))


def _without_field(data: bytes, name: bytes) -> bytes:
    """REBOUND's binary file without the named field's record ([u64 length of the name with
    its NUL][u64 size of the data][name][data]): a file saved before the field existed."""
    i = data.find(name + b"\0")
    n, size = struct.unpack("<QQ", data[i - 16:i])
    assert i > 16 and n == len(name) + 1
    return data[:i - 16] + data[i + n + size:]


def test_an_archive_saved_before_the_clock_fields_loads_and_continues(tmp_path):
    sim = _sim("plain")
    sim.steps(300)
    path = tmp_path / "run.bin"
    sim.save_to_file(str(path), delete_file=True)
    data = path.read_bytes()
    for field in (b"integrator.hbvm.t_comp", b"integrator.hbvm.t_written"):
        data = _without_field(data, field)
    path.write_bytes(data)
    old = rebound.Simulation(str(path))
    assert old.integrator.t_comp == 0.0 and math.isnan(old.integrator.t_written)
    t_loaded = old.t
    assert t_loaded == sim.t
    sim.steps(100)
    old.steps(100)
    # the N-body kernel does not read t: the same particles; the old file's clock starts from
    # its sim.t, taken as exact
    assert np.array_equal(_xv(old), _xv(sim))
    assert _near(old.t, Fraction(t_loaded) + 100 * Fraction(DT))


@pytest.mark.parametrize("kind", ["plain", "kepler"])
def test_output_times_are_where_the_user_asked(kind):
    """integrate(t_i) with exact_finish_time at output times that the steps do not divide in
    binary (45 steps of 500/45 days an interval): sim.t is t_i exactly after each call, as with
    REBOUND's own integrators, and the bodies are there too.  Before, the plain t + dt of each
    step rounded at t ~ 1e4, exact_finish_time added a sliver step to reach t_i, and the bodies
    ran ahead of sim.t by the sum of the roundings (2.9e-10 AU over 1e5 days on the Sun and 8
    planets); a clock that only compensated ended at t_i - 1 ulp."""
    def run(dt, outputs):
        sim = outer_solar_system().to_rebound()
        if kind == "kepler":
            HBVMIntegrator(sim, kepler=True, dt=dt, s=6, k=8)
        else:
            HBVMIntegrator(sim, s=6, k=8, dt=dt)
        for t in outputs:
            sim.integrate(t, exact_finish_time=1)
            assert sim.t == t
        return sim

    outputs = 500.0 * np.arange(1, 201)          # (t up to 1e5 days: the sums round)
    odd = run(500.0 / 45, outputs)
    # the same motion at steps that sum exactly (500 / 32 = 15.625): the two runs agree to the
    # methods' difference at these steps, far below the clock's former 1e-9-day offset
    ref = run(500.0 / 64, outputs)
    x, xr = _xv(odd), _xv(ref)
    assert odd.steps_done <= 45 * len(outputs) + 2        # (no sliver at every output)
    assert np.max(np.abs(x - xr)) < 1e-12, np.max(np.abs(x - xr))
