"""The compiled core (integrators/csrc, integrators.ccore): built at install, the same numbers as
the numba step bit for bit, failures that change nothing, and a boundary that refuses a record
of the wrong shape by name."""
import os
from contextlib import contextmanager

import numpy as np
import pytest

from integrators import Stepper, integrate
from integrators import ccore
from integrators.errors import StepError
from integrators.records import Samples
from integrators.tableau import HBVM
from systems.base import SeparableSystem
from systems.nbody import NBody, nbody_forces
from systems.solar import outer_solar_system


@contextmanager
def numba_step():
    """Bindings made inside run on numba (ccore.available reads the environment)."""
    old = os.environ.get("HBVM_MD_CORE")
    os.environ["HBVM_MD_CORE"] = "numba"
    try:
        yield
    finally:
        if old is None:
            del os.environ["HBVM_MD_CORE"]
        else:
            os.environ["HBVM_MD_CORE"] = old


def both(fn):
    """fn() on the compiled core, then on the numba step."""
    a = fn()
    with numba_step():
        b = fn()
    return a, b


class Anharmonic(SeparableSystem):
    """A chain of quartic springs written in numpy (no compiled kernels): the Python path."""

    def __init__(self, n=4):
        self.dim = n
        self.masses = np.linspace(1.0, 2.0, n)

    def potential(self, q):
        d = np.diff(q, axis=-1)
        return np.sum(0.5 * d ** 2 + 0.25 * d ** 4, axis=-1) + 0.5 * np.sum(q ** 2, axis=-1)

    def forces(self, q):
        d = np.diff(q, axis=-1)
        t = d + d ** 3
        f = -q.copy()
        f[..., :-1] += t
        f[..., 1:] -= t
        return f


def test_the_core_is_built():
    # CI installs with a compiler: a missing core would silently fall back to numba
    assert ccore.STALE is None, ccore.STALE
    assert ccore._core is not None, "integrators._core was not built (setup.py)"
    assert ccore.lanes() in (2, 4, 8)


def test_the_engine_runs_n_body_scenes_on_the_core():
    st = Stepper(HBVM(9, 8), outer_solar_system(), outer_solar_system().initial_state())
    assert isinstance(st.binding.step_code, ccore.CoreStep)
    with numba_step():
        st = Stepper(HBVM(9, 8), outer_solar_system(), outer_solar_system().initial_state())
    assert not isinstance(st.binding.step_code, ccore.CoreStep)


@pytest.mark.parametrize("k,s,h,steps", [(9, 8, 500.0, 300), (6, 3, 100.0, 300),
                                         (4, 4, 50.0, 200), (3, 1, 20.0, 200),
                                         (9, 8, -500.0, 100)])
def test_fixed_steps_agree_with_numba_bit_for_bit(k, s, h, steps):
    system = outer_solar_system()
    y0 = system.initial_state()
    a, b = both(lambda: integrate(HBVM(k, s), system, y0, h, steps, sample_every=25))
    assert np.array_equal(a.y, b.y) and np.array_equal(a.t, b.t)
    assert np.array_equal(a.energy, b.energy)
    assert (a.nfev, a.iterations, a.steps) == (b.nfev, b.iterations, b.steps)
    assert a.error_estimate == b.error_estimate and a.error_estimate > 0   # (the run's estimate)


def test_adaptive_steps_agree_with_numba_bit_for_bit():
    # an eccentric pair and a light third body: the controller shrinks and grows the steps
    system = NBody([1.0, 1e-3, 1e-6], G=1.0)
    y0 = system.state(np.array([[0, 0, 0], [1, 0, 0], [0, 2.5, 0.1]], float),
                      np.array([[0, 0, 0], [0, 0.5, 0], [-0.6, 0, 0]], float))

    def run():
        return integrate(HBVM(7, 6), system, y0, 0.01, adaptive=True, t_end=30.0,
                         sample_every=5)
    a, b = both(run)
    assert a.steps == b.steps and a.steps > 40
    assert a.extra["h_max"] > 5 * a.extra["h_min"]          # (the steps did adapt)
    assert np.array_equal(a.y, b.y) and np.array_equal(a.t, b.t)


def test_python_kernels_agree_with_numba_bit_for_bit():
    system = Anharmonic()
    y0 = np.concatenate([np.array([0.3, -0.2, 0.5, 0.1]), np.array([0.0, 0.4, -0.1, 0.2])])
    a, b = both(lambda: integrate(HBVM(4, 2), system, y0, 0.05, 400, sample_every=40))
    st = Stepper(HBVM(4, 2), system, y0)
    assert isinstance(st.binding.step_code, ccore.PythonCoreStep)
    assert np.array_equal(a.y, b.y) and np.array_equal(a.energy, b.energy)
    assert a.nfev == b.nfev
    assert np.max(np.abs(a.energy / a.energy[0] - 1)) < 1e-13    # (k = 2s: exact for quartic H)


def test_a_failed_step_changes_nothing_and_names_the_same_error():
    # a close pair at a step far too long: the step's own error estimate refuses it
    system = NBody([1.0, 1e-3])
    y0 = system.state(np.array([[0, 0, 0], [1, 0, 0]], float),
                      np.array([[0, 0, 0], [0, 0.2, 0]], float))

    def fail():
        st = Stepper(HBVM(4, 2), system, y0)
        before = (st.y.copy(), st.t, st.counters.copy())
        with pytest.raises(StepError) as err:
            st.step(3.0)
        assert np.array_equal(st.y, before[0]) and st.t == before[1]
        assert np.array_equal(st.counters[:3], before[2][:3])
        return type(err.value), str(err.value)
    a, b = both(fail)
    assert a == b


def test_a_python_kernel_that_raises_leaves_the_state():
    class Broken(Anharmonic):
        calls = 0

        def forces(self, q):
            Broken.calls += 1
            if Broken.calls > 5:
                raise RuntimeError("the calculator failed")
            return super().forces(q)
    system = Broken()
    y0 = np.concatenate([np.full(4, 0.1), np.zeros(4)])
    st = Stepper(HBVM(4, 2), system, y0)
    y_before = st.y.copy()
    with pytest.raises(RuntimeError, match="the calculator failed"):
        for _ in range(10):
            st.step(0.05)
    assert st.nsteps < 10
    assert np.all(np.isfinite(st.y)) and st.y.shape == y_before.shape


def test_the_kernel_matches_numba_with_test_particles():
    rng = np.random.default_rng(3)
    system = NBody([1.0, 1e-3, 0.0, 2e-4, 0.0], n_active=5)
    _, _, params = system.separable_kernels()
    for n in (1, 3, 8, 9, 17):
        X = rng.normal(size=(n, 15))
        out_c, out_n = np.empty_like(X), np.empty_like(X)
        ccore._core.force(ccore._core.NBODY, X, params, out_c)
        nbody_forces(X, params, out_n)
        assert np.array_equal(out_c, out_n)


def test_the_boundary_refuses_a_record_of_the_wrong_shape():
    st = Stepper(HBVM(9, 8), outer_solar_system(), outer_solar_system().initial_state())
    b = st.binding
    state = st._state_record()
    bad = state._replace(gamma=np.zeros((3, 5)))
    args = (b.system_record, bad, 10.0, st._extrapolation(10.0, None), b.method_record,
            b.no_newton, st._options("fixed_point"), b.work_record(st.counters))
    with pytest.raises(ValueError, match="state.gamma"):
        b.step_code.run(*args, Samples(1, 0, np.zeros(0), np.zeros((0, 0)), np.zeros(0)))
    with pytest.raises(TypeError, match="state.y"):
        b.step_code.run(b.system_record, state._replace(y=state.y.astype(np.float32)),
                        *args[2:], Samples(1, 0, np.zeros(0), np.zeros((0, 0)), np.zeros(0)))


@pytest.mark.parametrize("name", ["kepler", "henon_heiles", "fpu", "pendulum", "morse"])
def test_the_small_systems_run_on_the_core_bit_for_bit(name):
    from systems import FPU, HenonHeiles, Kepler, Morse, Pendulum
    system, method, h, n = {"kepler": (Kepler(0.6), HBVM(6, 3), 0.05, 400),
                            "henon_heiles": (HenonHeiles(), HBVM(4, 2), 0.1, 400),
                            "fpu": (FPU(3, 50.0), HBVM(4, 2), 0.002, 400),
                            "pendulum": (Pendulum(), HBVM(6, 3), 0.1, 300),
                            "morse": (Morse(), HBVM(3, 3), 0.05, 300)}[name]
    st = Stepper(method, system, system.initial_state())
    assert isinstance(st.binding.step_code, ccore.CoreStep)
    a, b = both(lambda: integrate(method, system, system.initial_state(), h, n,
                                  sample_every=20))
    assert np.array_equal(a.y, b.y) and np.array_equal(a.energy, b.energy)
    assert (a.nfev, a.iterations) == (b.nfev, b.iterations)
    assert a.error_estimate == b.error_estimate


def test_the_extrapolation_matrix_is_numba_s_bit_for_bit():
    from integrators.core import select_extrapolation
    from integrators.engine import Extrapolation
    for s in (1, 3, 8):
        ex = Extrapolation(HBVM(s + 1, s))
        for h, hp in [(1.0, np.nan), (1.0, 1.0), (0.7, 1.0), (-2.5, 1.0), (5.0, 1.0),
                      (1e-5, 1.0), (1.0, 3.0), (3.999, 1.0)]:
            got = ccore._core.select_extrapolation(h, hp, ex.E1, ex.t, ex.w, ex.buf, ex.zero)
            got = got.copy()
            want = select_extrapolation(h, hp, ex.E1, ex.t, ex.w, np.empty_like(ex.buf),
                                        ex.zero)
            assert np.array_equal(got, want), (s, h, hp)


def test_the_run_s_drift_check_refuses_as_numba_s_does():
    # Kepler e = 0.9, the midpoint rule at P/3000 over a period from pericentre: the run's drift
    # check refuses it (the case), on the core as on numba, and with V + C (a Python
    # kernel: the core's callback path) as without
    from systems import Kepler
    from integrators.errors import EnergyDriftError
    kepler = Kepler(0.9)

    class Shifted(SeparableSystem):
        dim = 2
        masses = np.ones(2)

        def potential(self, q):
            return kepler.potential(q) + 1e3

        def forces(self, q):
            return kepler.forces(q)

    def run(system):
        with pytest.raises(EnergyDriftError) as err:
            integrate(HBVM(1, 1), system, kepler.initial_state(), 2 * np.pi / 3000, 3000)
        return err.value.result.steps
    for system in (kepler, Shifted()):
        a, b = both(lambda: run(system))
        assert a == b and 0 < a < 3000


# ---- test particles (followers): the sources' stage equations first, as if alone, then each
# particle's in their field with its own stop rule (integrators.followers), on the core

def outer_with_particles(n, seed=1, rmin=36.0, rmax=50.0, comet=False):
    """The outer solar system and n massless particles on near-circular orbits between rmin
    and rmax AU (more than FOLLOWER_GROUP: several groups), and a comet from 30 AU to a
    perihelion at 1.5 AU (a particle the adaptive control has to follow)."""
    base = outer_solar_system()
    rng = np.random.default_rng(seed)
    r = rng.uniform(rmin, rmax, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    x = np.stack([r * np.cos(phi), r * np.sin(phi), rng.normal(0, 0.02, n) * r], axis=1)
    v = (np.stack([-np.sin(phi), np.cos(phi), np.zeros(n)], axis=1)
         * (np.sqrt(base.G / r) * rng.uniform(0.9, 1.1, n))[:, None])
    m = np.concatenate([base.body_masses, np.zeros(n)])
    pos, vel = np.concatenate([base.positions, x]), np.concatenate([base.velocities, v])
    if comet:
        va = np.sqrt(base.G * (2 / 30.0 - 2 / 31.5))
        m = np.append(m, 0.0)
        pos, vel = np.vstack([pos, [-30.0, 0.0, 0.5]]), np.vstack([vel, [0.0, -va, 0.0]])
    return NBody(m, G=base.G, positions=pos, velocities=vel)


def stepped(system, method, h, steps, **kw):
    """Everything a Stepper's steps change (state, compensation, coefficients, energies,
    clock, counters) after ``steps`` steps of h; asserts the binding is the core's unless
    numba is asked for."""
    st = Stepper(method, system, system.initial_state(), **kw)
    assert (isinstance(st.binding.step_code, ccore.CoreStep)
            == (os.environ.get("HBVM_MD_CORE") != "numba"))
    st.run(h, steps, sample_every=steps)
    return st.save_state()[:6]


def same(a, b):
    return len(a) == len(b) and all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b))


def test_the_engine_runs_test_particle_scenes_on_the_core():
    system = outer_with_particles(20)
    st = Stepper(HBVM(9, 8), system, system.initial_state())
    assert isinstance(st.binding.step_code, ccore.CoreStep) and st.binding.step_code.follow
    assert st.binding.follow is not None
    with numba_step():
        st = Stepper(HBVM(9, 8), system, system.initial_state())
    assert not isinstance(st.binding.step_code, ccore.CoreStep)


@pytest.mark.parametrize("k,s,h,steps", [(9, 8, 500.0, 60), (7, 6, 250.0, 60), (6, 3, 100.0, 60),
                                         (4, 4, 50.0, 40), (3, 1, 20.0, 30), (11, 6, 300.0, 30),
                                         (16, 8, 500.0, 20), (9, 8, -500.0, 40)])
def test_test_particles_agree_with_numba_bit_for_bit(k, s, h, steps):
    # 300 particles: three groups of core.FOLLOWER_GROUP; k = 9, 11, 16: a last vector of one,
    # three and all stages (the field's scalar, half and whole lanes); k = s: the endpoint defect
    system = outer_with_particles(300)
    a, b = both(lambda: stepped(system, HBVM(k, s), h, steps))
    assert same(a, b)
    counters = a[5]
    assert counters[0] == steps and counters[9] > 0          # (steps, the run's estimate)
    y0 = system.initial_state()
    a, b = both(lambda: integrate(HBVM(k, s), system, y0, h, steps, sample_every=10))
    assert np.array_equal(a.y, b.y) and np.array_equal(a.energy, b.energy)
    assert (a.nfev, a.iterations, a.error_estimate) == (b.nfev, b.iterations, b.error_estimate)


def test_a_slow_test_particle_sets_the_step_s_depth_bit_for_bit():
    # the belt of tests/test_followers.py and a particle on a tight orbit about the star: its
    # iterations are the step's (the counts are the longest block's), on the core as on numba
    from test_followers import SLOW, _belt
    pos, vel, m = _belt(40, extra=[SLOW])
    slow = NBody(m, G=1.0, n_active=2, positions=pos, velocities=vel)
    pos, vel, m = _belt(40)
    belt = NBody(m, G=1.0, n_active=2, positions=pos, velocities=vel)
    a, b = both(lambda: stepped(slow, HBVM(8, 6), 0.25, 100))
    assert same(a, b)
    c, d = both(lambda: stepped(belt, HBVM(8, 6), 0.25, 100))
    assert same(c, d)
    assert a[5][1] > c[5][1]          # (more iterations with the slow particle)
    # ... and with a tolerance (the stop rule's contraction estimate)
    a, b = both(lambda: stepped(slow, HBVM(8, 6), 0.25, 50, tol=1e-12))
    assert same(a, b)


def test_the_worst_body_is_named_in_the_whole_state():
    # test particles before and among the sources: the sources' block numbers its bodies
    # otherwise; the step's worst body (counters[C_WORST]) is the whole state's, as on numba
    rng = np.random.default_rng(5)
    m = np.array([0.0, 1.0, 0.0, 0.0, 1e-3, 0.0, 3e-4])
    r = np.array([2.0, 0.0, 3.1, 4.2, 5.2, 7.0, 9.5])
    phi = rng.uniform(0, 2 * np.pi, r.size)
    pos = np.stack([r * np.cos(phi), r * np.sin(phi), np.zeros(r.size)], axis=1)
    v = np.where(r > 0, 1.0 / np.sqrt(np.where(r > 0, r, 1.0)), 0.0)
    vel = np.stack([-np.sin(phi) * v, np.cos(phi) * v, np.zeros(r.size)], axis=1)
    system = NBody(m, G=1.0, positions=pos, velocities=vel)
    for k, s in ((8, 6), (4, 4)):
        a, b = both(lambda: stepped(system, HBVM(k, s), 0.2, 30))
        assert same(a, b)
        assert a[5][8] in (1, 4, 6)          # C_WORST: a source, numbered in the whole state


def test_adaptive_steps_with_test_particles_agree_with_numba_bit_for_bit():
    # the comet's perihelion: the test particles' term of the adaptive control
    # (core.test_particle_control) shrinks the steps, on the core (its C copy) as on numba
    system = outer_with_particles(20, rmin=6.0, rmax=40.0, comet=True)
    y0 = system.initial_state()

    def run():
        return integrate(HBVM(7, 6), system, y0, 300.0, adaptive=True, epsilon=1e-10,
                         t_end=3e4, sample_every=5)
    a, b = both(run)
    assert a.steps == b.steps and np.array_equal(a.y, b.y) and np.array_equal(a.t, b.t)
    assert a.extra["h_max"] > 5 * a.extra["h_min"]
    plain = outer_with_particles(20, rmin=6.0, rmax=40.0)
    without = integrate(HBVM(7, 6), plain, plain.initial_state(), 300.0, adaptive=True,
                        epsilon=1e-10, t_end=3e4)
    assert a.steps > without.steps          # (the comet's own steps)


def test_the_core_s_attempt_agrees_with_numba_s_bit_for_bit():
    # integrators.loop.attempt's contract in C (hbvm_attempt, the one retry loop of the hosts),
    # with the test particles' term of the adaptive control: fixed and adaptive steps, the
    # rejected attempts, the proposed steps, the counters, the trial state
    from integrators.core import C_ERR, test_particle_control
    from integrators.engine import Extrapolation as Ext
    from integrators.records import Adaptive, Extrapolation, State
    system = outer_with_particles(20, rmin=6.0, rmax=40.0, comet=True)

    def attempts(eps, n=120):
        st = Stepper(HBVM(7, 6), system, system.initial_state())
        b = st.binding
        e = Ext(HBVM(7, 6))
        ext = Extrapolation(e.E1, e.t, e.w, e.buf, e.zero)
        state = st._state_record()
        trial = State(state.y.copy(), state.cy.copy(), state.gamma.copy(), state.eref.copy(),
                      state.clock)
        res, out, h, h_prev = np.zeros(5), [], 300.0, np.nan
        for _ in range(n):
            status = b.step_code.attempt(b.system_record, state, trial, h, h_prev,
                                         state.clock[0], ext, b.method_record, b.no_newton,
                                         st._options("fixed_point"), b.work_record(st.counters),
                                         Adaptive(eps, 1e-8, res))
            out.append((status, res.copy(), st.counters.copy(), trial.y.copy(),
                        trial.gamma.copy(), trial.eref.copy(), state.clock.copy()))
            if status != 0:
                break
            for mine, new in zip(state[:4], trial[:4]):
                mine[...] = new
            h_prev, h = res[0], res[1]
        return out, b
    for eps in (0.0, 1e-10):
        (a, ba), (b, _) = both(lambda: attempts(eps))
        assert len(a) == len(b) and all(same(p, q) for p, q in zip(a, b))
        if eps > 0:
            assert a[-1][1][2] > 0               # (rejections)
            raised = [test_particle_control(r[4], ba.minv, ba.kin_w, r[2][C_ERR]) > r[2][C_ERR]
                      for r in a]
            assert any(raised)                   # (the particles' term decided steps)


def test_the_test_particle_control_is_numba_s_bit_for_bit():
    from integrators.core import test_particle_control
    rng = np.random.default_rng(11)
    system = outer_with_particles(7)
    st = Stepper(HBVM(7, 6), system, system.initial_state())
    w, kw = st.binding.minv, st.binding.kin_w
    for s in (1, 2, 3, 6, 8):
        for _ in range(20):
            g = rng.normal(size=(s, w.size)) * 10.0 ** rng.uniform(-8, 2, size=(1, w.size))
            if rng.uniform() < 0.2:
                g[:, rng.integers(w.size)] = 0.0
            for err in (0.0, 1e-9, 3.5e-3):
                assert (ccore._core.test_particle_control(g, w, kw, err)
                        == test_particle_control(g, w, kw, err))


@pytest.mark.parametrize("where", ["on the star", "grazing the star", "slow"])
def test_a_failing_test_particle_changes_nothing_and_fails_as_on_numba(where):
    # a particle on the star (non-finite forces), one passing 1e-6 from it (its iteration runs
    # away), and the slow one at too few iterations (max_iter: the largest increment of those
    # still iterating): the step fails with the same error and counters, and changes nothing
    from test_followers import SLOW, _belt
    p = {"on the star": ([-5.2e-3, 0.0, 0.0], [0.0, 0.0, 0.0]),
         "grazing the star": ([-5.2e-3 + 1e-4, 1e-6, 0.0], [-1.0, 0.0, 0.0]), "slow": SLOW}[where]
    pos, vel, m = _belt(200, extra=[p])
    system = NBody(m, G=1.0, n_active=2, positions=pos, velocities=vel)
    h, max_iter = (0.25, 7) if where == "slow" else (0.5, None)
    for solver in ("fixed_point", "auto"):
        def fail():
            st = Stepper(HBVM(8, 6), system, system.initial_state(), solver=solver,
                         max_iter=max_iter)
            before = st.save_state()
            with pytest.raises(StepError) as err:
                st.step(h)
            after = st.save_state()
            assert same(before[:5], after[:5])                  # nothing changed ...
            assert np.array_equal(before[5][:3], after[5][:3])  # ... nor counted
            return type(err.value), str(err.value), after[5]
        a, b = both(fail)
        assert a[:2] == b[:2] and np.array_equal(a[2], b[2], equal_nan=True), (a, b)


def test_a_new_user_s_first_test_particle_run_compiles_nothing(tmp_path):
    # the outer solar system and 200 test particles in a fresh process with empty caches: no
    # numba compilation (the caches stay empty), the same numbers as in this process
    import subprocess
    import sys
    import textwrap
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    code = textwrap.dedent("""
        import sys
        sys.path.insert(0, %r)
        from test_core import outer_with_particles
        from integrators import HBVM, integrate
        system = outer_with_particles(200)
        r = integrate(HBVM(9, 8), system, system.initial_state(), 500.0, 100)
        print(repr(float(r.y[-1, -1])), r.iterations)
    """ % os.path.join(root, "tests"))
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"),
               HBVM_MD_CACHE_DIR=str(tmp_path / "hbvm"), PYTHONPATH=root)
    env.pop("HBVM_MD_CORE", None)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert "compiling" not in out.stderr
    assert [p for p in tmp_path.rglob("*") if p.is_file()] == []
    system = outer_with_particles(200)
    r = integrate(HBVM(9, 8), system, system.initial_state(), 500.0, 100)
    assert out.stdout.split() == [repr(float(r.y[-1, -1])), str(r.iterations)]
