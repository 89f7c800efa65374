"""N-body gravity (systems.nbody) and the planetary scenes (systems.solar)."""
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


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="`masses` must be finite and >= 0"):
        NBody([1.0, -1.0])
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
