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
