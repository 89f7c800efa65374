"""Test particles as followers (issue 30, item 2): the step solves the sources' stage equations
as if alone, then each test particle's in their field with its own stop rule
(:mod:`integrators.loop`, "Followers")."""
import numpy as np
import pytest

from integrators import HBVM, Stepper, integrate
from integrators.errors import StepError
from systems import NBody


class Coupled(NBody):
    """The same scene solved with every unknown together (no followers hooks)."""
    separable_followers = None


def _belt(n, seed=3, extra=()):
    """A star, a Jupiter at 5.2 and n massless particles at 2.1-3.3 (REBOUND's test-particle
    scene, coplanar-ish), plus the particles ``extra`` ((position, velocity) pairs)."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(2.1, 3.3, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    x = np.stack([r * np.cos(phi), r * np.sin(phi), rng.normal(0, 0.05, n)], axis=1)
    v = np.stack([-np.sin(phi), np.cos(phi), np.zeros(n)], axis=1) / np.sqrt(r)[:, None]
    pos = [[-5.2e-3, 0, 0], [5.2 * (1 - 1e-3), 0, 0]] + list(x) + [p for p, _ in extra]
    vel = [[0, -1e-3 * np.sqrt(1.001 / 5.2), 0], [0, (1 - 1e-3) * np.sqrt(1.001 / 5.2), 0]] \
        + list(v) + [q for _, q in extra]
    m = np.zeros(len(pos))
    m[:2] = 1.0, 1e-3
    return np.array(pos, dtype=float), np.array(vel, dtype=float), m


def _run(cls, pos, vel, m, h, steps, **kw):
    nb = cls(m, G=1.0, n_active=2, positions=pos, velocities=vel)
    return integrate(HBVM(8, 6), nb, nb.initial_state(), h, steps, sample_every=steps, **kw), nb


# a particle on a tight orbit about the star (r = 0.3, period 1.03): it needs more iterations a
# step than the belt at h = 0.25
SLOW = ([0.3, 0.0, 0.0], [0.0, 1.0 / np.sqrt(0.3), 0.0])


def test_each_particle_is_the_same_whichever_others_are_there():
    """A particle's trajectory is bit for bit the same with 40 others, with 5, and with a slow
    one among them, although the slow one makes the step's deepest iteration longer: one
    slow particle makes neither the sources nor the others iterate."""
    pos, vel, m = _belt(40, extra=[SLOW])
    full, _ = _run(NBody, pos, vel, m, 0.25, 120)
    keep = [0, 1, 2, 3, 4, 5, 6]                       # the sources and five particles
    few, _ = _run(NBody, pos[keep], vel[keep], m[keep], 0.25, 120)
    cols = lambda idx: (3 * np.asarray(idx)[:, None] + np.arange(3)).ravel()
    n_all, n_few = len(m), len(keep)
    assert np.array_equal(full.y[:, cols(keep)], few.y[:, cols(range(n_few))])
    assert np.array_equal(full.y[:, 3 * n_all + cols(keep)], few.y[:, 3 * n_few + cols(range(n_few))])
    assert full.iterations > few.iterations            # the slow particle's own iterations


def test_followers_agree_with_the_coupled_solution_to_round_off():
    """Solved after the sources or together with them, the step is the same to round-off: the
    particles' positions after 400 steps (100 particles, 2.4 orbits of the inner belt) agree
    to 1e-12 of their size, the sources to the same."""
    pos, vel, m = _belt(100, seed=7)
    a, nb = _run(NBody, pos, vel, m, 0.75, 400)
    b, _ = _run(Coupled, pos, vel, m, 0.75, 400)
    assert a.path == b.path == "compiled-separable"
    d = np.abs(a.y[-1] - b.y[-1])
    assert d[: nb.dim].max() < 1e-12 * 3.3 and 0.0 < d.max()
    assert d[nb.dim:].max() < 1e-12


def test_followers_in_python_equal_the_compiled_step_bit_for_bit():
    pos, vel, m = _belt(12, seed=9, extra=[SLOW])
    a, _ = _run(NBody, pos, vel, m, 0.25, 6)
    b, _ = _run(NBody, pos, vel, m, 0.25, 6, fast=False)
    assert b.path.startswith("python")
    assert np.array_equal(a.y, b.y) and a.iterations == b.iterations


@pytest.mark.parametrize("where", ["on the star", "grazing the star"])
def test_a_failing_particle_fails_the_step_and_changes_nothing(where):
    """A particle whose stage equations have no solution the iteration reaches (sitting on the
    star: non-finite forces; passing 1e-6 from it within the step: no convergence) fails the
    whole step, with the state as before it."""
    p = [-5.2e-3, 0.0, 0.0] if where == "on the star" else [-5.2e-3 + 1e-4, 1e-6, 0.0]
    q = [0.0, 0.0, 0.0] if where == "on the star" else [-1.0, 0.0, 0.0]
    pos, vel, m = _belt(10, extra=[(p, q)])
    nb = NBody(m, G=1.0, n_active=2, positions=pos, velocities=vel)
    st = Stepper(HBVM(8, 6), nb, nb.initial_state())
    y0 = st.y.copy()
    with pytest.raises(StepError):
        st.step(0.5)
    assert np.array_equal(st.y, y0) and st.t == 0.0


@pytest.mark.parametrize("seed", range(4))
def test_field_kernel_equals_the_n_body_kernel_on_test_particles(seed):
    """nbody_field, given the sources' rows, gives the test particles' columns of nbody_forces
    bit for bit (random scenes: 1-4 sources among 1-40 test particles in any order, 1-9 rows),
    and both agree with a direct sum over the sources to round-off."""
    from systems.nbody import nbody_field, nbody_forces, nbody_followers
    rng = np.random.default_rng(seed)
    for _ in range(10):
        ns, nt, n = rng.integers(1, 5), rng.integers(1, 41), rng.integers(1, 10)
        m = np.concatenate([rng.uniform(0.1, 2.0, ns), np.zeros(nt)])
        order = rng.permutation(ns + nt)
        m = m[order]
        nb = NBody(m, G=rng.uniform(0.5, 2.0))
        params = nb.separable_kernels()[2]
        at = nbody_followers(params)
        P, us = int(params[at]), int(params[at + 2])
        src_cols = params[at + 4:at + 4 + us].astype(int)
        tp_first = params[at + 4 + us:at + 4 + us + P].astype(int)
        own = params[at + 4 + us + P:]
        assert np.array_equal(own, NBody(m[m > 0], G=nb.G).separable_kernels()[2])
        Q = rng.normal(size=(n, 3 * nb.N)) * 3
        full = np.empty_like(Q)
        nbody_forces(Q, params, full)
        tcols = (tp_first[:, None] + np.arange(3)).ravel()
        out = np.empty((n, 3 * P))
        nbody_field(np.ascontiguousarray(Q[:, tcols]), np.ascontiguousarray(Q[:, src_cols]), own, out)
        assert np.array_equal(out, full[:, tcols])
        x = Q.reshape(n, nb.N, 3)
        direct = np.zeros((n, P, 3))
        for j, t in enumerate(tp_first // 3):
            for k in np.flatnonzero(m > 0):
                d = x[:, k] - x[:, t]
                direct[:, j] += nb.G * m[k] * d / np.linalg.norm(d, axis=1)[:, None] ** 3
        assert np.allclose(out, direct.reshape(n, -1), rtol=1e-12, atol=1e-15 * np.abs(direct).max())


def test_no_followers_block_without_both_kinds():
    """Sources only, or test particles only: no block, and the step solves all unknowns
    together (the hook says -1)."""
    from systems.nbody import nbody_followers
    for m in ([1.0, 1e-3], [0.0, 0.0, 0.0]):
        params = NBody(m).separable_kernels()[2]
        assert params.size == 3 * len(m) + 3 and nbody_followers(params) == -1


def test_adaptive_steps_are_the_sources_own_when_no_particle_needs_smaller():
    """Adaptive steps (the defaults' control): Kuiper-belt particles (35-50 au) around the outer
    solar system leave the steps and the planets' trajectory those of the planets alone, bit for
    bit (no particle is close to anything); asteroids at 2-3 au, whose orbits are the fastest
    motion of the scene, make the steps smaller (their encounters and orbits resolved)."""
    from systems import outer_solar_system
    from tests.test_nbody import _with_test_particles
    src = outer_solar_system()
    alone = integrate(HBVM(8, 6), src, src.initial_state(), 100.0, adaptive=True, t_end=2e4)
    far, idx = _with_test_particles(src, np.random.default_rng(11), 40, 35.0, 50.0)
    with_far = integrate(HBVM(8, 6), far, far.initial_state(), 100.0, adaptive=True, t_end=2e4)
    cols = (3 * idx[:, None] + np.arange(3)).ravel()
    assert np.array_equal(with_far.t, alone.t)
    assert np.array_equal(with_far.y[:, cols], alone.y[:, :src.dim])
    assert np.array_equal(with_far.y[:, far.dim + cols], alone.y[:, src.dim:])
    near, _ = _with_test_particles(src, np.random.default_rng(11), 40, 2.0, 3.0)
    with_near = integrate(HBVM(8, 6), near, near.initial_state(), 100.0, adaptive=True, t_end=2e4)
    assert len(with_near.t) > 2 * len(alone.t)


def test_through_rebound_the_planets_are_the_same_with_and_without_test_particles():
    """The registered integrator, fixed steps: the outer solar system with 20 test particles
    out to 60 au ends bit for bit where it ends without them (solved together with them, it
    did not: 1.2e-15 apart after 200 steps, the particles' round-off floors), and the particles
    end where the engine's step puts them."""
    import hbvm_md  # noqa: F401  (registers "hbvm")
    from hbvm_md import HBVMIntegrator
    from systems import outer_solar_system
    from tests.test_nbody import _with_test_particles
    src = outer_solar_system()
    nb, idx = _with_test_particles(src, np.random.default_rng(32), 20, 8.0, 60.0)
    out = []
    for system in (src, nb):
        sim = system.to_rebound()
        HBVMIntegrator(sim, dt=100.0, k=8, s=6, energy_tol=None)   # (a close passage)
        sim.integrate(2e4)
        xv = np.zeros((sim.N, 6))
        sim.serialize_particle_data(xyzvxvyvz=xv)
        out.append(xv)
    assert np.array_equal(out[0], out[1][idx])
    ref = integrate(HBVM(8, 6), nb, nb.initial_state(), 100.0, 200, sample_every=200)
    assert np.array_equal(out[1][:, :3].ravel(), ref.y[-1, :nb.dim])
