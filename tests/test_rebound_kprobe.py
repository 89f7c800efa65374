"""HBVMIntegrator(sim, dt=...) measures k on the sources and the few test particles that decide
it (:func:`hbvm_md.rebound.integrator.probe_scene`): the whole scene's k, for a probe whose size
does not grow with the number of test particles."""
import importlib.util
import math
import pathlib

import numpy as np
import pytest
import rebound

import hbvm_md.rebound.integrator as hi
from hbvm_md import HBVMIntegrator
from hbvm_md.rebound import shortest_period
from integrators.kchoice import choose_k, period_steps
from systems import NBody, outer_solar_system

#: the most particles probe_scene keeps besides the sources: two rankings
MOST_KEPT = 2 * hi.PROBE_RANKED


def _load_bench():
    """benchmarks/bench_testparticles.py as a module (benchmarks is not a package)."""
    path = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "bench_testparticles.py"
    spec = importlib.util.spec_from_file_location("bench_testparticles", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


#: REBOUND's test-particle scene of the issue (a star, a Jupiter at a = 5.2, n test particles
#: at a = 2.1-3.3, N_active = 2), the benchmark's own
_belt = _load_bench().scene


def _comet(sim):
    """A test particle near its apocentre (e = 0.97) added last: the fastest motion ahead."""
    sim.add(a=3.0, e=0.97, f=0.9 * math.pi)
    return sim


def _falling_onto_jupiter(sim):
    """A test particle 0.3 from the Jupiter, falling towards it, added last."""
    jup = sim.particles[1]
    sim.add(x=jup.x + 0.3, y=jup.y, z=jup.z, vx=jup.vx - 0.05, vy=jup.vy + 0.01, vz=jup.vz)
    return sim


def _kuiper(n: int):
    """The outer solar system (Pluto a source) and n test particles at a = 35-50 AU."""
    rng = np.random.default_rng(7)
    sim = outer_solar_system().to_rebound()
    sim.N_active = sim.N
    for _ in range(n):
        sim.add(primary=sim.particles[0], a=rng.uniform(35, 50), e=rng.uniform(0, 0.3),
                inc=rng.uniform(0, 0.3), f=rng.uniform(0, 2 * math.pi))
    sim.testparticle_type = 0
    return sim


def _whole_k(sim, s: int, dt: float) -> int:
    """k measured as before the sample: choose_k on the whole scene."""
    nb = NBody.from_rebound(sim)
    y0 = nb.initial_state()
    return choose_k(nb, y0, s, dt, period_steps(shortest_period(nb), dt), solver="fixed_point").k


@pytest.fixture
def probed(monkeypatch):
    """The number of particles of each system the attach hands to choose_k."""
    sizes = []
    real = hi.choose_k

    def spy(system, *args, **kw):
        sizes.append(system.N)
        return real(system, *args, **kw)
    monkeypatch.setattr(hi, "choose_k", spy)
    return sizes


@pytest.mark.parametrize("make, s, dt, k", [
    # k from the full measurement (HBVM(3, 3) is not at round-off)
    (lambda: _belt(300), 3, 0.5, 5),
    # steps of a third of the innermost periods: the trial steps fail on the inner belt and
    # k_ref is kept (without the closest approach ahead the sample measured k = 8)
    (lambda: _belt(300), 6, 6.0, 14),
    # the comet's pericentre is ahead: its steps fail, k_ref is kept (both rankings hold it;
    # before the followers, without the closest approach ahead the sample measured k = 9)
    (lambda: _comet(_belt(300, seed=4)), 6, 8.0, 14),
    # the encounter with the Jupiter is ahead (without that ranking: k = 7)
    (lambda: _falling_onto_jupiter(_belt(300, seed=5)), 6, 1.0, 14),
    # the outer solar system: HBVM(6, 6)'s quadrature error shows at 300 days
    (lambda: _kuiper(200), 6, 300.0, 8),
])
def test_sampled_probe_picks_the_whole_scenes_k(probed, make, s, dt, k):
    sim = make()
    sim.move_to_com()
    whole = _whole_k(sim, s, dt)
    drv = HBVMIntegrator(sim, s=s, dt=dt)
    assert (drv.method.k, whole) == (k, k)
    assert probed[0] <= sim.N_active + MOST_KEPT < sim.N     # a sample, not the whole scene


def test_probe_size_does_not_grow_with_the_test_particles(probed):
    """The same scene with 4x and 16x the test particles: the probe keeps the sources and at
    most MOST_KEPT test particles, and picks the same k."""
    ks = [HBVMIntegrator(_belt(n), dt=0.5).method.k for n in (100, 400, 1600)]
    assert ks == [7, 7, 7]
    assert all(2 + hi.PROBE_RANKED <= n <= 2 + MOST_KEPT for n in probed), probed


def test_probe_keeps_the_fastest_particles_and_their_arithmetic():
    """The kept particles: every source, the test particle with the shortest period now, the
    one with the closest approach ahead (the comet); the probe's state is y0's own entries and
    each kept particle's force is the whole scene's, bit for bit."""
    sim = _comet(_belt(200))
    sim.add(m=1e-4, a=1.0)     # beyond N_active: a test particle (with a mass), the fastest
    nb = NBody.from_rebound(sim)
    y0 = nb.initial_state()
    probe, yp, kept = hi.probe_scene(nb, y0)
    assert np.all(np.diff(kept) > 0) and probe.N == kept.size <= 2 + MOST_KEPT
    assert kept[:2].tolist() == [0, 1] and probe.n_active == 2
    assert np.array_equal(probe.is_source, nb.is_source[kept])
    x = nb.positions
    r3 = np.linalg.norm(x[2:-1] - x[0], axis=1) ** 3      # the star dominates every period here
    assert 2 + int(np.argmin(r3)) in kept                  # the shortest period now of the belt
    assert {sim.N - 2, sim.N - 1} <= set(kept.tolist())    # the comet, the one at a = 1
    q, p = y0[:nb.dim].reshape(-1, 3), y0[nb.dim:].reshape(-1, 3)
    assert np.array_equal(yp, np.concatenate([q[kept].ravel(), p[kept].ravel()]))
    f_whole = nb.forces(y0[:nb.dim]).reshape(-1, 3)
    f_probe = probe.forces(yp[:probe.dim]).reshape(-1, 3)
    np.testing.assert_array_equal(f_probe, f_whole[kept])


@pytest.mark.parametrize("make, n_test", [
    (lambda: outer_solar_system().to_rebound(), 0),
    (lambda: _belt(hi.PROBE_WHOLE), hi.PROBE_WHOLE),
])
def test_few_test_particles_are_probed_whole(probed, make, n_test):
    """Without test particles, or with at most PROBE_WHOLE, the scene is probed as before: the
    NBody itself goes to choose_k."""
    assert MOST_KEPT < hi.PROBE_WHOLE <= 100       # a sample only where it keeps fewer particles
    sim = make()
    nb = NBody.from_rebound(sim)
    y0 = nb.initial_state()
    probe, yp, kept = hi.probe_scene(nb, y0)
    assert probe is nb and yp is y0 and kept.tolist() == list(range(nb.N))
    HBVMIntegrator(sim, dt=100.0 if n_test == 0 else 0.5)
    assert probed == [sim.N]
    sim = _belt(hi.PROBE_WHOLE + 1)
    HBVMIntegrator(sim, dt=0.5)
    assert probed[-1] < sim.N
