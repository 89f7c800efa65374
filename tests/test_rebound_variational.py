"""REBOUND's first-order variational particles and MEGNO with HBVM as the registered integrator:
the tangents are the derivative of the step taken, REBOUND's own MEGNO reads them as IAS15's."""
import numpy as np
import pytest
import rebound

import hbvm_md  # noqa: F401  (registers "hbvm")
from hbvm_md import HBVMIntegrator
from integrators import ConvergenceError, NonFiniteError

TWO_PI = 2 * np.pi


def _two_planets(integrator, a2=1.7, megno=True):
    """A star and two planets (1e-3 at a = 1, m2 at a2), e = 0.05: regular at a2 = 1.7 and 1.5,
    chaotic at a2 = 1.4 (MEGNO about 10 after 2000 inner orbits, IAS15 and HBVM alike)."""
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, e=0.05)
    sim.add(m=3e-4 if a2 > 1.6 else 1e-3, a=a2, e=0.05, f=2.0)
    sim.move_to_com()
    sim.integrator = integrator
    if integrator == "hbvm":
        sim.dt = 0.05
    if megno:
        sim.init_megno(seed=1)
    return sim


def _xv(particles):
    return np.array([[p.x, p.y, p.z, p.vx, p.vy, p.vz] for p in particles])


def test_one_step_tangent_equals_central_differences_of_two_steps():
    """A registered fixed step carries a variational particle set as central differences of
    two simulations stepped from x +- eps delta converge to (their own accuracy: eps^2
    truncation, round-off / eps)."""
    rng = np.random.default_rng(3)
    delta = rng.normal(size=(3, 6))
    delta /= np.linalg.norm(delta)

    def simulation(shift=0.0):
        sim = _two_planets("ias15", megno=False)
        for p, d in zip(sim.particles, delta):
            p.x, p.y, p.z = p.x + shift * d[0], p.y + shift * d[1], p.z + shift * d[2]
            p.vx, p.vy, p.vz = p.vx + shift * d[3], p.vy + shift * d[4], p.vz + shift * d[5]
        HBVMIntegrator(sim, s=6, k=8, dt=0.3, adaptive=False)
        return sim

    sim = simulation()
    var = sim.add_variation()
    for p, d in zip(var.particles, delta):
        p.x, p.y, p.z, p.vx, p.vy, p.vz = d
    sim.steps(1)
    tangent = _xv(var.particles)
    eps = 1e-5
    plus, minus = simulation(eps), simulation(-eps)
    plus.steps(1)
    minus.steps(1)
    fd = (_xv(plus.particles) - _xv(minus.particles)) / (2 * eps)
    assert sim.t == plus.t == 0.3
    err = np.max(np.abs(tangent - fd)) / np.max(np.abs(fd))
    assert err < 1e-8, err
    # and it is not the identity: the step moved the tangent by O(h)
    assert np.max(np.abs(tangent - delta)) > 1e-2


def test_megno_of_regular_orbits_tends_to_two_as_ias15s():
    """1e4 inner orbits of a regular two-planet system: sim.megno() near 2 and within 0.1 of
    IAS15's on the same start, REBOUND's Lyapunov estimate near zero."""
    out = {}
    for integrator in ("hbvm", "ias15"):
        sim = _two_planets(integrator)
        sim.integrate(1e4 * TWO_PI)
        out[integrator] = sim.megno(), sim.lyapunov(), _xv(sim.particles_var)
    (y_h, l_h, v_h), (y_i, l_i, v_i) = out["hbvm"], out["ias15"]
    assert abs(y_h - 2.0) < 0.01 and abs(y_h - y_i) < 0.01, (y_h, y_i)
    assert abs(l_h) < 1e-6
    # the variational particles themselves agree with IAS15's (both resolve the flow)
    assert np.max(np.abs(v_h - v_i)) / np.max(np.abs(v_i)) < 1e-6


def test_megno_of_a_chaotic_configuration_grows():
    mean = []
    for integrator in ("hbvm", "ias15"):
        sim = _two_planets(integrator, a2=1.4)
        sim.integrate(1000 * TWO_PI)
        y1 = sim.megno()
        sim.integrate(2000 * TWO_PI)
        mean.append((y1, sim.megno(), sim.lyapunov()))
    (h1, h2, lh), (i1, i2, li) = mean
    assert h2 > 5.0 and h2 > 1.5 * h1, mean
    assert abs(h2 - i2) / i2 < 0.2 and abs(lh - li) / li < 0.2, mean


def test_failed_steps_leave_the_variational_particles_unchanged():
    # the step itself fails (one iteration allowed)
    sim = _two_planets("ias15")
    HBVMIntegrator(sim, s=6, k=8, dt=0.3, adaptive=False, max_iter=1)
    before, var_before = _xv(sim.particles), _xv(sim.particles_var)
    with pytest.raises(ConvergenceError):
        sim.integrate(1.0)
    assert sim.t == 0.0 and np.array_equal(_xv(sim.particles), before)
    assert np.array_equal(_xv(sim.particles_var), var_before)
    # the step converges, its tangent map does not (a non-finite tangent)
    sim = _two_planets("hbvm")
    sim.integrate(10.0)
    sim.particles_var[1].x = np.nan
    t, before, var_before = sim.t, _xv(sim.particles), _xv(sim.particles_var)
    megno = sim._megno_Ys, sim._megno_n
    with pytest.raises(NonFiniteError, match="tangent map"):
        sim.integrate(20.0)
    assert sim.t == t and np.array_equal(_xv(sim.particles), before)
    assert np.array_equal(_xv(sim.particles_var), var_before, equal_nan=True)
    assert (sim._megno_Ys, sim._megno_n) == megno


def test_save_and_load_continue_the_variational_run(tmp_path):
    """A run saved and loaded halfway continues as the run that stopped there without saving
    (the tangents' previous coefficients, an initial guess only, restart at zero: round-off
    apart)."""
    whole = _two_planets("hbvm")
    whole.integrate(100 * TWO_PI)
    whole.integrate(200 * TWO_PI)
    half = _two_planets("hbvm")
    half.integrate(100 * TWO_PI)
    path = tmp_path / "var.bin"
    half.save_to_file(str(path))
    loaded = rebound.Simulation(str(path))
    assert loaded.N_var == 3 and str(loaded.integrator) == "hbvm"
    loaded.integrate(200 * TWO_PI)
    assert loaded.t == whole.t
    v_w, v_l = _xv(whole.particles_var), _xv(loaded.particles_var)
    assert np.max(np.abs(v_l - v_w)) / np.max(np.abs(v_w)) < 1e-9
    assert abs(loaded.megno() - whole.megno()) < 1e-9


def test_variational_particles_with_equip_are_refused():
    sim = _two_planets("ias15")
    HBVMIntegrator(sim, s=6, k=8, dt=0.3, adaptive=False, method="equip")
    before = _xv(sim.particles_var)
    with pytest.raises(ValueError, match=r"3 variational particles with method='equip'.*use "
                                         r"method='hbvm'"):
        sim.integrate(1.0)
    assert sim.t == 0.0 and np.array_equal(_xv(sim.particles_var), before)


def test_a_users_edit_of_the_variational_particles_is_carried_on():
    """Tangents are linear: doubling the variational particles between two runs doubles them
    at the end (the edit is read, not overwritten by the step's own copy)."""
    out = []
    for scale in (1.0, 2.0):
        sim = _two_planets("hbvm", megno=False)
        var = sim.add_variation()
        var.particles[1].x, var.particles[2].vy = 1.0, 0.5
        sim.integrate(50.0)
        for p in sim.particles_var:
            p.x, p.y, p.z = scale * p.x, scale * p.y, scale * p.z
            p.vx, p.vy, p.vz = scale * p.vx, scale * p.vy, scale * p.vz
        sim.integrate(100.0)
        out.append(_xv(sim.particles_var))
    assert np.max(np.abs(out[1] - 2 * out[0])) / np.max(np.abs(out[1])) < 1e-12


def _three_bodies(masses, start=None):
    sim = rebound.Simulation()
    sim.add(m=masses[0])
    sim.add(m=masses[1], a=1.0, e=0.1, inc=0.02, f=0.4)
    sim.add(primary=sim.particles[0], m=masses[2], a=1.76, f=2.0)
    for p, (x, v) in zip(sim.particles, start or ()):
        p.xyz, p.vxyz = x, v
    HBVMIntegrator(sim, s=6, k=8, dt=0.05, adaptive=False)
    return sim


@pytest.mark.parametrize("body, elements", [(0, False), (1, False), (2, False), (1, True)])
def test_a_varied_mass_is_the_central_difference_of_two_runs(body, elements):
    """A variational particle set that varies a mass (its particle's m, as ``var.vary(i, "m")``
    sets it; REBOUND's ``test_all_1st_order_full`` with "hbvm") is the derivative of the
    fixed-step map along that mass, as central differences of two runs with m_i +- eps converge
    to: the mass alone at a fixed Cartesian start (the star's moves every pull; a planet's, the
    others'), and with ``vary`` at fixed orbital elements (the velocities move too).  It used to
    be off by order one: the tangent map left the force's dependence on the masses out."""
    masses = np.array([1.0, 1e-3, 1e-3])
    start = None if elements else [(p.xyz, p.vxyz) for p in _three_bodies(masses).particles]
    sim = _three_bodies(masses, start)
    var = sim.add_variation()
    if elements:
        var.vary(body, "m")
    else:
        var.particles[body].m = 1.0
    sim.integrate(1.4)
    eps = 1e-6
    dm = eps * (np.arange(3) == body)
    plus, minus = _three_bodies(masses + dm, start), _three_bodies(masses - dm, start)
    plus.integrate(1.4)
    minus.integrate(1.4)
    fd = (_xv(plus.particles) - _xv(minus.particles)) / (2 * eps)
    tangent = _xv(var.particles)
    err = np.max(np.abs(tangent - fd)) / np.max(np.abs(fd))
    assert err < 1e-8, err                       # (measured 3e-11 to 1.4e-10)
    assert var.particles[body].m == 1.0          # (REBOUND's, carried through unchanged)


def test_a_variation_of_one_test_particle_is_the_central_difference_of_two_runs():
    """``sim.add_variation(testparticle=1)`` (REBOUND's variation of one particle: one
    variational particle, the others' variations zero) of a massless planet is the derivative
    of the fixed-step map along its start, as the whole system's variation is; a set of the
    whole system beside it is unchanged by it.  It used to be refused."""
    masses = np.array([1.0, 0.0, 1e-3])
    sim = _three_bodies(masses)
    start = [(p.xyz, p.vxyz) for p in sim.particles]
    one = sim.add_variation(testparticle=1)
    whole = sim.add_variation()
    one.particles[0].x = whole.particles[1].x = 1.0
    one.particles[0].vy = whole.particles[1].vy = 0.5
    sim.integrate(1.4)
    assert sim.N_var == 1 + 3
    eps = 1e-6
    runs = []
    for sign in (1, -1):
        moved = [(list(x), list(v)) for x, v in start]
        moved[1][0][0] += sign * eps
        moved[1][1][1] += sign * 0.5 * eps
        runs.append(_three_bodies(masses, moved))
        runs[-1].integrate(1.4)
    fd = (_xv(runs[0].particles) - _xv(runs[1].particles)) / (2 * eps)
    err = np.max(np.abs(_xv(one.particles)[0] - fd[1])) / np.max(np.abs(fd[1]))
    assert err < 1e-8, err                       # (measured 7e-11)
    assert np.array_equal(_xv(one.particles)[0], _xv(whole.particles)[1])
    assert not np.any(_xv(whole.particles)[[0, 2]])


def test_a_variation_of_one_massive_particle_is_ias15s():
    """Of a massive planet, REBOUND's variation of one particle moves it in the field of the
    others with its own pull on them left out (not the system's derivative): HBVM's agrees
    with IAS15's, varied in an orbital element, beside a whole-system set after it."""
    out = []
    for integrator in ("ias15", "hbvm"):
        sim = _three_bodies(np.array([1.0, 1e-3, 1e-3]))
        sim.integrator = integrator
        one = sim.add_variation(testparticle=1)
        one.vary(1, "e")
        whole = sim.add_variation()
        whole.vary(1, "e")
        sim.integrate(1.4)
        out.append((_xv(one.particles)[0], _xv(whole.particles)[1]))
    (ias_one, ias_whole), (hb_one, hb_whole) = out
    # (measured 2.6e-15 and 2.5e-15)
    assert np.max(np.abs(hb_one - ias_one)) / np.max(np.abs(ias_one)) < 1e-11
    assert np.max(np.abs(hb_whole - ias_whole)) / np.max(np.abs(ias_whole)) < 1e-11
    # (REBOUND's definition differs from the whole system's derivative by the planet's pull:
    # 1.4e-3 here, so the comparison above tells the two apart)
    assert np.max(np.abs(ias_one - ias_whole)) > 1e-4 * np.max(np.abs(ias_whole))



def _planets(integrator="hbvm", **change):
    """A star, a planet (or a massless particle) with the elements ``change`` moves, and a second
    planet: the scene of REBOUND's test_variational.py, at fixed steps for HBVM."""
    elements = dict(m=1e-3, a=1.0, e=0.1, inc=0.02, omega=0.56, f=0.4)
    for k, dv in change.items():
        elements[k] += dv
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(**elements)
    sim.add(primary=sim.particles[0], m=1e-3, a=1.76, f=2.0)
    if integrator == "hbvm":
        HBVMIntegrator(sim, s=6, k=8, dt=0.05, adaptive=False)
    else:
        sim.integrator = integrator
    return sim


@pytest.mark.parametrize("v1, v2, tp", [("e", "m", False), ("a", "omega", False),
                                        ("e", "f", True)])
def test_a_second_order_variation_is_the_central_difference_of_first_order_ones(v1, v2, tp):
    """REBOUND's second-order variational particles (``add_variation(order=2, first_order=a,
    first_order_2=b)``, and of one particle) are the second derivative of the fixed-step map: the
    central difference, along the second parameter, of the first-order variation along the
    first (a mass among them: its cross terms); and they agree with IAS15's.  They used to be
    refused."""
    kw = {"testparticle": 1} if tp else {}
    massless = {"m": -1e-3} if tp else {}
    out = {}
    for integrator in ("hbvm", "ias15"):
        sim = _planets(integrator, **massless)
        a, b = sim.add_variation(**kw), sim.add_variation(**kw)
        ab = sim.add_variation(order=2, first_order=a, first_order_2=b, **kw)
        a.vary(1, v1)
        b.vary(1, v2)
        ab.vary(1, v1, v2)
        sim.integrate(1.4)
        out[integrator] = _xv(ab.particles)
    eps = 1e-6
    first = []
    for sign in (1, -1):
        sim = _planets(**{**massless, v2: massless.get(v2, 0.0) + sign * eps})
        a = sim.add_variation(**kw)
        a.vary(1, v1)
        sim.integrate(1.4)
        first.append(_xv(a.particles))
    fd = (first[0] - first[1]) / (2 * eps)
    hb, ias = out["hbvm"], out["ias15"]
    assert hb.shape == fd.shape
    scale = np.max(np.abs(fd))
    # (measured 2.6e-10 to 1.6e-9: the difference's own error; IAS15 7e-16 to 1.2e-15)
    assert np.max(np.abs(hb - fd)) / scale < 1e-8, np.max(np.abs(hb - fd)) / scale
    assert np.max(np.abs(hb - ias)) / scale < 1e-12, np.max(np.abs(hb - ias)) / scale
