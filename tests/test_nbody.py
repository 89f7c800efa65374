"""N-body gravity (systems.nbody) and the planetary scenes (systems.solar)."""
import math

import numpy as np
import pytest

from integrators import HBVM, integrate
from systems import NBody, outer_solar_system, solar_system


def _random_nbody(rng, masses, **kw):
    nb = NBody(masses, **kw)
    return nb, rng.normal(size=(4, nb.dim)) * 3


def test_forces_are_minus_gradient_of_potential():
    rng = np.random.default_rng(1)
    nb, Q = _random_nbody(rng, [1.0, 1e-3, 2e-3, 5e-4], G=1.7)
    q = Q[0]
    e = 1e-6
    grad = np.array([(nb.potential(q + e * d) - nb.potential(q - e * d)) / (2 * e) for d in np.eye(nb.dim)])
    assert np.max(np.abs(nb.forces(q) + grad)) < 1e-8 * np.max(np.abs(grad))
    # pair forces cancel: total force zero
    assert np.max(np.abs(nb.forces(Q).reshape(4, -1, 3).sum(axis=1))) < 1e-15


def test_compiled_kernels_match_numpy():
    from numba import njit

    @njit
    def call(f, p, Q, par, out):
        f(Q, par, out)
        return p(Q[0], par)

    rng = np.random.default_rng(2)
    nb, Q = _random_nbody(rng, [1.0, 1e-3, 0.0, 5e-4, 2e-3], G=0.3, n_active=4)
    f, p, par = nb.separable_kernels()
    out = np.empty_like(Q)
    v = call(f, p, Q, par, out)
    assert np.max(np.abs(out - nb.forces(Q))) < 1e-14 * np.max(np.abs(out))
    assert v == pytest.approx(nb.potential(Q[0]), rel=1e-14)


def test_compiled_kernel_gives_each_row_the_numbers_it_gives_alone():
    """The kernel takes the rows (stages) four at a time, repeating the last row of a short
    group: every row of a stack must come out bit for bit as when evaluated alone."""
    from systems.nbody import nbody_forces
    rng = np.random.default_rng(11)
    for n in range(1, 12):
        N = int(rng.integers(2, 9))
        m = rng.uniform(1e-6, 1.0, N)
        m[-1] = 0.0                                     # a test particle too
        nb = NBody(m, G=1.7)
        params = nb.separable_kernels()[2]
        Q = rng.normal(size=(n, 3 * N))
        out = np.full_like(Q, np.nan)
        nbody_forces(Q, params, out)
        np.testing.assert_allclose(out, nb.forces(Q), rtol=1e-12, atol=0)     # numpy's
        for r in range(n):
            alone = np.full((1, 3 * N), np.nan)
            nbody_forces(Q[r:r + 1].copy(), params, alone)
            assert np.array_equal(out[r], alone[0]), (n, r)


def test_test_particles_feel_sources_and_exert_nothing():
    rng = np.random.default_rng(3)
    m = [1.0, 1e-3, 0.0, 2e-3]                          # particle 2 has zero mass; 3 is inactive
    nb = NBody(m, G=2.0, n_active=3)
    full = NBody([1.0, 1e-3], G=2.0)
    Q = rng.normal(size=nb.dim)
    F = nb.forces(Q).reshape(4, 3)
    assert np.array_equal(F[:2], full.forces(Q[:6]).reshape(2, 3))   # nothing acts on sources
    for t in (2, 3):   # a test particle's "force" is its acceleration from the sources
        d = Q.reshape(4, 3)[:2] - Q.reshape(4, 3)[t]
        acc = (2.0 * np.array([1.0, 1e-3])[:, None] * d / np.linalg.norm(d, axis=1)[:, None] ** 3).sum(0)
        assert np.allclose(F[t], acc, rtol=1e-13)
    assert list(nb.masses[6:]) == [1.0] * 6 and not nb.is_source[2] and not nb.is_source[3]


def _random_scene(rng, N):
    """Masses with sources, massless actives and massive inactive bodies (test particles too)
    in random order, and n_active."""
    m = rng.uniform(1e-6, 1.0, N) * (rng.random(N) < 0.5)
    return m, int(rng.integers(0, N + 1))


def _direct_forces(Q, nb):
    """dp/dt by a plain loop over every ordered pair (i, j), j ascending: the order the kernel
    promises, with each term in the kernel's form c (q_j - q_i), c = (w_i g_j) G / r^3."""
    G, N = nb.G, nb.N
    w = np.where(nb.is_source, nb.body_masses, 1.0)
    g = np.where(nb.is_source, nb.body_masses, 0.0)
    out = np.empty_like(Q)
    for r in range(Q.shape[0]):
        x = Q[r].reshape(N, 3)
        for i in range(N):
            acc = [0.0, 0.0, 0.0]
            for j in range(N):
                if j == i or g[j] == 0.0:
                    continue
                d = [float(x[j, c] - x[i, c]) for c in range(3)]
                s = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                c = (w[i] * g[j]) * (G / (s * math.sqrt(s)))
                acc = [acc[k] + c * d[k] for k in range(3)]
            out[r, 3 * i:3 * i + 3] = acc
    return out


def test_kernel_is_the_direct_pair_sum_bit_for_bit_on_random_scenes():
    """Sources act on every body, test particles (massless actives, inactive bodies) on none:
    the kernel's O(N_s N) walk gives the numbers of the direct O(N^2) loop over all pairs,
    bit for bit, whatever the order of sources and test particles; and the potential is the
    sum over pairs of sources, bit for bit."""
    from systems.nbody import nbody_forces, nbody_potential
    rng = np.random.default_rng(30)
    for trial in range(40):
        N = int(rng.integers(1, 12))
        m, n_active = _random_scene(rng, N)
        nb = NBody(m, G=1.3, n_active=n_active)
        params = nb.separable_kernels()[2]
        Q = rng.normal(size=(int(rng.integers(1, 10)), 3 * N))
        out = np.full_like(Q, np.nan)
        nbody_forces(Q, params, out)
        assert np.array_equal(out, _direct_forces(Q, nb)), (trial, m, n_active)
        g = np.where(nb.is_source, m, 0.0)
        v = 0.0
        x = Q[0].reshape(N, 3)
        for i in range(N):
            for j in range(i + 1, N):
                if g[i] > 0 and g[j] > 0:
                    d = x[j] - x[i]
                    v -= g[i] * g[j] / math.sqrt(float(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]))
        assert nbody_potential(Q[0], params) == 1.3 * v


def test_kernel_never_reads_a_pair_of_test_particles():
    """A test particle at the position of another (r = 0 between them) changes nothing: the
    pair is never formed (the old all-pairs loop skipped it too, but after forming it); and a
    test particle sitting on a source leaves the source's force finite and as without it."""
    from systems.nbody import nbody_forces
    rng = np.random.default_rng(31)
    m = np.array([1.0, 0.0, 2e-3, 0.0, 0.0])
    nb = NBody(m, G=1.0)
    Q = rng.normal(size=(5, 15))
    Q[:, 9:12] = Q[:, 12:15]                 # test particles 3 and 4 coincide
    Q[:, 3:6] = Q[:, 0:3]                    # test particle 1 sits on the star
    out = np.empty_like(Q)
    nbody_forces(Q, nb.separable_kernels()[2], out)
    alone = np.empty((5, 6))
    nbody_forces(np.ascontiguousarray(Q[:, [0, 1, 2, 6, 7, 8]]), NBody([1.0, 2e-3]).separable_kernels()[2], alone)
    assert np.array_equal(out[:, [0, 1, 2, 6, 7, 8]], alone)
    assert np.all(np.isfinite(out[:, 9:])) and np.array_equal(out[:, 9:12], out[:, 12:15])


def _with_test_particles(src, rng, ntp, rmin, rmax, massless_active=True):
    """src (an NBody of sources) with ntp test particles on circular orbits of radii in
    [rmin, rmax] about the origin, in random planes: a massless active one right after the
    first source (when asked), the rest inactive after the sources.  Returns the NBody and the
    indices of the sources in it."""
    r = rng.uniform(rmin, rmax, ntp)
    u = rng.normal(size=(ntp, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    t = np.cross(u, rng.normal(size=(ntp, 3)))
    t /= np.linalg.norm(t, axis=1)[:, None]
    x, v = u * r[:, None], t * np.sqrt(src.G * src.body_masses.sum() / r)[:, None]
    n = src.N
    order = ([0, n] + list(range(1, n)) + list(range(n + 1, n + ntp)) if massless_active
             else list(range(n + ntp)))
    nb = NBody(np.concatenate([src.body_masses, np.zeros(ntp)])[order], G=src.G,
               n_active=n + 1 if massless_active else n,
               positions=np.vstack([src.positions, x])[order],
               velocities=np.vstack([src.velocities, v])[order])
    return nb, np.array([order.index(i) for i in range(n)])


def _sources_drift(src, nb, idx, h, steps, method=HBVM(9, 6)):
    """Largest |difference| of the sources' (q, p) with and without the test particles after
    each quarter of ``steps`` fixed steps of the compiled loop, and both runs' iterations."""
    a = integrate(method, src, src.initial_state(), h, steps, sample_every=steps // 4)
    b = integrate(method, nb, nb.initial_state(), h, steps, sample_every=steps // 4)
    assert b.path == "compiled-separable"
    cols = (3 * idx[:, None] + np.arange(3)).ravel()
    d = max(np.max(np.abs(b.y[:, cols] - a.y[:, :src.dim])),
            np.max(np.abs(b.y[:, nb.dim + cols] - a.y[:, src.dim:])))
    return d, a.iterations, b.iterations


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_test_particles_never_act_on_the_sources_trajectory(seed):
    """REBOUND's test-particle scene (a star, a Jupiter at 5.2, asteroids at 2.1-3.3 and a
    massless active particle) and the outer solar system with particles among the planets:
    the sources' positions and momenta are those of the sources alone, bit for bit, after
    200 fixed steps, although the particles change the iterations a step (asteroids: 4.0 -> 6.0
    measured; among the planets 5.0 -> 5.0-5.4).  (The iterations of a step with test
    particles count its slowest block: the sources, or the slowest particle.)"""
    rng = np.random.default_rng(seed)
    star_jupiter = NBody([1.0, 1e-3], positions=[[-5.2e-3, 0, 0], [5.2 * (1 - 1e-3), 0, 0]],
                         velocities=[[0, -1e-3 * np.sqrt(1.001 / 5.2), 0],
                                     [0, (1 - 1e-3) * np.sqrt(1.001 / 5.2), 0]])
    for src, h, rmin, rmax in ((star_jupiter, 0.75, 2.1, 3.3), (outer_solar_system(), 100.0, 6.0, 25.0)):
        nb, idx = _with_test_particles(src, rng, 30, rmin, rmax)
        d, it_alone, it_with = _sources_drift(src, nb, idx, h, 200)
        assert it_with >= it_alone and d == 0.0, (src.N, it_alone, it_with, d)


def test_test_particles_far_outside_the_sources_leave_them_bit_for_bit():
    """Particles out to 60 au around the outer solar system (beyond Neptune): solved together
    with the sources, they lowered the stop rule's round-off floors (taken over all bodies)
    and the sources moved by 1.2e-15 in 200 steps; solved after the sources, with their own
    convergence test, they leave the sources bit for bit."""
    nb, idx = _with_test_particles(outer_solar_system(), np.random.default_rng(32), 20, 8.0, 60.0)
    d, it_alone, it_with = _sources_drift(outer_solar_system(), nb, idx, 100.0, 200, HBVM(8, 6))
    assert d == 0.0


@pytest.mark.parametrize("masses, n_active", [
    ([1.0, 1e-3, 3e-4], None),                      # sources only
    ([1.0, 0.0, 1e-3, 0.0, 2e-4], None),            # sources and test particles (followers)
    ([1.0, 1e-3, 5e-4, 1e-6], 2),                   # bodies past n_active
    ([0.0, 0.0], None),                             # test particles only
    ([1.0, -1e-3, 0.0, 2e-4], None)])               # a negative mass (a source)
def test_set_masses_gives_the_parameters_of_the_new_masses(masses, n_active):
    """nbody_set_masses (the REBOUND host's change of masses in place) writes exactly the
    kernel parameters an NBody of the new masses has, the followers block included."""
    from systems.nbody import nbody_set_masses
    m = np.array(masses)
    new = m * np.linspace(0.5, 0.9, m.size)               # the same bodies nonzero
    params = NBody(m, G=2.0, n_active=n_active)._params.copy()
    nbody_set_masses(params, new)
    assert np.array_equal(params, NBody(new, G=2.0, n_active=n_active)._params)
    nbody_set_masses(params, -new)                        # through zero: the same sources
    assert np.array_equal(params, NBody(-new, G=2.0, n_active=n_active)._params)


def test_a_negative_mass_is_a_source_and_zero_a_test_particle():
    """A negative mass gravitates (REBOUND's and IAS15's convention: a source of mass -|m|,
    momentum m v, kinetic energy m v^2 / 2 < 0), a zero mass stays a test particle; the time
    scale takes |m| (a pair of opposite masses has m_i + m_j = 0, and used to be skipped,
    with the sign of m, as no pair at all)."""
    from systems.nbody import shortest_r3_over_m
    nb = NBody([1.0, -1.0, 0.0], positions=[[0, 0, 0], [2, 0, 0], [0, 3, 0]],
               velocities=[[0, 0, 0], [0, 1, 0], [1, 0, 0]])
    assert nb.is_source.tolist() == [True, True, False]
    y = nb.initial_state()
    assert np.array_equal(y[9:], [0, 0, 0, 0, -1, 0, 1, 0, 0])            # p = m v, v
    assert nb.kinetic(y[9:]) == -0.5 and nb.potential(y[:9]) == 0.5      # -G m1 m2 / r
    f = nb.forces(y[:9]).reshape(3, 3)
    # the positive mass is pushed away from the negative one, which is pulled after it
    # (its acceleration f / m = -0.25 too: a chase)
    assert np.allclose(f[0], [-0.25, 0, 0]) and np.allclose(f[1], [0.25, 0, 0])
    # the test particle at (0, 3): the star's pull, and the negative mass's push from (2, 0)
    assert np.allclose(f[2], np.array([0, -3, 0]) / 27.0 - np.array([2, -3, 0]) / 13.0 ** 1.5)
    x = np.array(nb.positions)
    assert shortest_r3_over_m(x, np.array([1.0, -1.0, 0.0])) == 4.0      # 8 / (1 + 1)
    assert shortest_r3_over_m(x, np.array([1.0, 1.0, 0.0])) == 4.0


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="`masses` must be finite"):
        NBody([1.0, np.nan])
    with pytest.raises(ValueError, match="`n_active` must be an integer in"):
        NBody([1.0, 1.0], n_active=3)
    with pytest.raises(ValueError, match="`G` must be a positive number"):
        NBody([1.0], G=0.0)
    with pytest.raises(ValueError, match="`positions` must be a finite array of shape"):
        NBody([1.0, 1.0], positions=np.zeros((3, 3)))


def test_outer_solar_system_to_rebound_and_back():
    nb = outer_solar_system()
    assert nb.N == 6 and nb.G == 2.95912208286e-4 and nb.names[1] == "jupiter"
    sim = nb.to_rebound()
    y0 = nb.initial_state()
    assert sim.energy() == pytest.approx(nb.energy(y0), rel=1e-14)
    back = type(nb).from_rebound(sim)
    assert np.allclose(back.initial_state(), y0, rtol=1e-15, atol=0)


def test_engine_conserves_energy_on_outer_solar_system():
    nb = outer_solar_system()
    res = integrate(HBVM(8, 6), nb, nb.initial_state(), 100.0, 200, sample_every=10)
    assert res.path == "compiled-separable"
    assert res.max_energy_error < 2e-15


def test_solar_system_matches_astropy():
    from astropy import units as u
    from astropy.coordinates import get_body_barycentric_posvel, solar_system_ephemeris
    from astropy.time import Time
    epoch = Time("2010-06-01T00:00:00", scale="tdb")
    sc = solar_system(epoch, bodies=("sun", "jupiter", "saturn", "earth"))
    assert sc.names == ["sun", "jupiter", "saturn", "earth"]
    with solar_system_ephemeris.set("builtin"):
        for i, name in enumerate(sc.names):
            p, v = get_body_barycentric_posvel(name, epoch)
            assert np.allclose(sc.positions[i], p.xyz.to_value(u.au), rtol=0, atol=1e-14)
            assert np.allclose(sc.velocities[i], v.xyz.to_value(u.au / u.day), rtol=0, atol=1e-16)
    assert sc.body_masses[1] == pytest.approx(1 / 1047.348644)
    # the Sun absorbs the omitted inner planets; other units follow G
    inner = solar_system(epoch, bodies=("sun", "jupiter"), include_inner_in_sun=True)
    assert inner.body_masses[0] == pytest.approx(1 + 1 / 6023597.4 + 1 / 408523.719 + 1 / 328900.56 + 1 / 3098703.59, rel=1e-9)
    si = solar_system(epoch, bodies=("sun", "jupiter"), units=("m", "s", "kg"))
    assert si.G == pytest.approx(6.6743e-11, rel=1e-4)
    with pytest.raises(ValueError, match="`bodies` must be a non-empty sequence"):
        solar_system(epoch, bodies=("sun", "pluto"))


@pytest.mark.parametrize("kwargs, match", [
    ({"bodies": "jupiter"}, r"`bodies` must be a sequence of names, e\.g\. bodies=\('sun', 'jupiter'\) "
                            r"\(got the string 'jupiter'"),
    ({"bodies": ("jupiter", "saturn")}, r"`bodies` must include 'sun' \(got \['jupiter', 'saturn'\]\)"),
    ({"epoch": 2451545.0}, r"`epoch` must be an astropy Time or a date string .*got 2451545\.0\); "
                           r"for a Julian date pass Time\(2451545\.0, format='jd', scale='tdb'\)"),
    ({"epoch": None}, r"`epoch` must be an astropy Time or a date string .*\(got None\)"),
    ({"epoch": "yesterday-ish"}, r"`epoch` must be a date astropy reads.*got 'yesterday-ish'"),
    ({"ephemeris": "no/such/de440s.bsp"}, r"`ephemeris` must be 'builtin' or the path of a JPL "
                                          r"kernel file on disk \(got 'no/such/de440s\.bsp', no such file\)"),
    ({"ephemeris": "de440"}, r"`ephemeris` .*\(got 'de440', not a \.bsp file\).*never downloads"),
])
def test_solar_system_bad_input_is_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        solar_system(**kwargs)


def test_solar_system_refuses_a_time_array_and_sizes_its_masses():
    from astropy.time import Time
    epochs = Time(["2024-01-01", "2024-06-01"], scale="tdb")
    with pytest.raises(ValueError, match=r"`epoch` must be one time \(got a Time array of shape \(2,\)\)"):
        solar_system(epochs)
    sc = solar_system(epochs[0], bodies=["sun", "jupiter"])
    assert sc.body_masses.shape == (2,) and len(sc.masses) == 6
    assert np.all(sc.masses == np.repeat(sc.body_masses, 3))


def test_poincare_transformed_is_exported_and_built_for_kepler():
    from systems import Kepler, PoincareKepler, PoincareTransformed, distance_power
    pt = PoincareTransformed.for_kepler(Kepler(0.9), alpha=1.0)
    assert isinstance(pt, PoincareKepler) and pt.dim == 3 and callable(distance_power)
    assert float(pt.energy(pt.extend(Kepler(0.9).initial_state()))) == 0.0


def test_angular_momentum_is_reboundss_for_sources_and_leaves_test_particles_out():
    """NBody.angular_momentum is REBOUND's sim.angular_momentum() on a scene of sources (and
    massless test particles), vectorised over samples; a massive particle beyond N_active is
    left out (REBOUND counts it, but nothing conserves its share)."""
    nb = outer_solar_system()
    y = nb.initial_state()
    L = nb.angular_momentum(y)
    np.testing.assert_allclose(L, np.array(nb.to_rebound().angular_momentum()), rtol=1e-14)
    assert np.linalg.norm(L) <= nb.angular_momentum_scale(y) <= 1.2 * np.linalg.norm(L)
    Y = np.stack([y, 2 * y, y])
    assert nb.angular_momentum(Y).shape == (3, 3) and nb.angular_momentum_scale(Y).shape == (3,)
    np.testing.assert_allclose(nb.angular_momentum(Y)[1], 4 * L, rtol=1e-14)
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0]])
    v = np.array([[0.0, 0, 0], [0, 1, 0], [1, 0, 0]])
    sources = NBody([1.0, 1e-3, 0.0], positions=x, velocities=v)       # body 2: a test particle
    beyond = NBody([1.0, 1e-3, 5e-3], n_active=2, positions=x, velocities=v)
    for m in (sources, beyond):
        np.testing.assert_allclose(m.angular_momentum(m.initial_state()), [0, 0, 1e-3], rtol=1e-15)
    with pytest.raises(ValueError, match=r"`y` must have shape \(\.\.\., 18\)"):
        sources.angular_momentum(np.zeros(12))
