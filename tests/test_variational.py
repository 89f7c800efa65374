"""The tangent map of the HBVM step (integrators.tangent, integrators.variational) and MEGNO."""
from __future__ import annotations

import numpy as np
import pytest

from integrators import HBVM, ConvergenceError, NonFiniteError, Stepper, integrate
from integrators.variational import Megno, VariationalStepper
from systems import HenonHeiles, Kepler, SeparableSystem
from systems.nbody import NBody, nbody_force_jvp, nbody_forces
from systems.solar import outer_solar_system


def step_differences(method, system, y0, h, eps, form="auto", solver="auto", scale=None):
    """The Jacobian of one step by fourth-order central differences, increment eps scale_j
    (default max(1, |y_j|); truncation C eps^4, rounding about 1e-16 |y1| / eps)."""
    d = y0.size
    J = np.empty((d, d))
    scale = np.maximum(1.0, np.abs(y0)) if scale is None else scale
    for j in range(d):
        e = np.zeros(d)
        e[j] = eps * scale[j]

        def f(c):
            return Stepper(method, system, y0 + c * e, form=form, solver=solver).step(h)
        J[:, j] = (-f(2) + 8 * f(1) - 8 * f(-1) + f(-2)) / (12 * e[j])
    return J


def tangent_of_step(method, system, y0, h, form="auto", solver="auto"):
    st = VariationalStepper(method, system, y0, form=form, solver=solver,
                            variational=np.eye(y0.size))
    st.step(h)
    return st.tangents.T


@pytest.mark.parametrize("form", ["separable", "full"])
@pytest.mark.parametrize("k,s", [(2, 2), (4, 2), (3, 3), (7, 3), (6, 6), (9, 6)])
def test_tangent_map_is_the_jacobian_of_the_step(k, s, form):
    """Kepler e = 0.6 from pericentre, h = 0.1.  The differences converge to the tangent map
    as their own truncation eps^4 says: 1.4e-9 at eps = 1e-3, 1.1e-11 at 3e-4 (ratio
    (10/3)^4 = 123, measured 123-129 for every method and both forms); a tangent map off by
    more than 1e-11 would break the ratio."""
    system = Kepler(0.6)
    y0, h, method = system.initial_state(), 0.1, HBVM(k, s)
    J = tangent_of_step(method, system, y0, h, form=form)
    err_coarse = np.abs(J - step_differences(method, system, y0, h, 1e-3, form)).max()
    err_fine = np.abs(J - step_differences(method, system, y0, h, 3e-4, form)).max()
    assert err_fine < 3e-11
    assert 80 < err_coarse / err_fine < 200


def test_newton_tangent_equals_fixed_point_tangent():
    """With solver='newton' the linear stage equations are solved with the step's Gauss
    matrices: the same tangent map to round-off."""
    system = Kepler(0.6)
    y0, method = system.initial_state(), HBVM(6, 3)
    J_fp = tangent_of_step(method, system, y0, 0.1, solver="fixed_point")
    J_nt = tangent_of_step(method, system, y0, 0.1, solver="newton")
    assert np.abs(J_fp - J_nt).max() < 1e-13 * np.abs(J_fp).max()


def test_python_path_gives_the_compiled_numbers():
    system = Kepler(0.3)
    y0, method = system.initial_state(), HBVM(4, 2)
    V0 = np.array([1e-3, 2e-3, -1e-3, 5e-4])
    a = integrate(method, system, y0, 0.05, 50, sample_every=10, variational=V0)
    b = integrate(method, system, y0, 0.05, 50, sample_every=10, variational=V0, fast=False)
    assert a.path == "compiled-separable" and b.path == "python-separable"
    assert np.array_equal(a.extra["variational"], b.extra["variational"])


def random_nbody(n_active=None, seed=3):
    rng = np.random.default_rng(seed)
    masses = np.array([1.0, 1e-3, 2e-3, 0.0, 5e-4, 0.0])
    x = rng.normal(size=(6, 3)) * 2.0
    return NBody(masses, G=1.3, n_active=n_active, positions=x, velocities=np.zeros((6, 3))), x


@pytest.mark.parametrize("n_active", [None, 3])
def test_nbody_jvp_is_the_derivative_of_the_force_kernel(n_active):
    """The tidal tensor against central differences of the force kernel (increment 1e-6:
    truncation ~1e-12 relative); test particles (zero mass, or beyond n_active) move nobody's
    force: their columns of dF/dq are zero outside their own rows."""
    system, x = random_nbody(n_active)
    params = system.separable_kernels()[2]
    q = x.reshape(1, -1)
    d = q.shape[1]
    jac, jvp = np.empty((d, d)), np.empty((d, d))
    out = np.empty((1, d))
    for j in range(d):
        e = np.zeros((1, d))
        e[0, j] = 1e-6
        fp, fm = np.empty((1, d)), np.empty((1, d))
        nbody_forces(q + e, params, fp)
        nbody_forces(q - e, params, fm)
        jac[:, j] = ((fp - fm) / 2e-6)[0]
        nbody_force_jvp(q, e / 1e-6, params, out)
        jvp[:, j] = out[0]
    assert np.abs(jvp - jac).max() < 1e-7 * np.abs(jac).max()
    tests = np.flatnonzero(~system.is_source)
    assert tests.size == (2 if n_active is None else 3)
    for t in tests:
        others = np.setdiff1d(np.arange(d), np.arange(3 * t, 3 * t + 3))
        assert np.all(jac[np.ix_(others, range(3 * t, 3 * t + 3))] == 0.0)


def test_nbody_tangent_map_is_the_jacobian_of_the_step():
    """Outer solar system, one 50-day step of HBVM(6, 3) (engine path with NBody's compiled
    jvp): fourth-order differences (increments eps AU in position, eps m_i 1e-2 AU/day in
    momentum) agree column by column, relative to the column's largest entry, to their own
    rounding, which grows as 1 / eps: measured 5.5e-13, 2.1e-12, 5.1e-12, 6.0e-11 at eps =
    1e-2, 3e-3, 1e-3, 1e-4 (their truncation is below that even at 1e-2)."""
    system = outer_solar_system()
    y0, method = system.initial_state(), HBVM(6, 3)
    scale = np.concatenate([np.ones(system.dim), 1e-2 * system.masses])
    J = tangent_of_step(method, system, y0, 50.0)
    errs = []
    for eps in (1e-2, 1e-4):
        Jd = step_differences(method, system, y0, 50.0, eps, scale=scale)
        errs.append(np.max(np.abs(J - Jd).max(axis=0) / np.abs(J).max(axis=0)))
    assert errs[0] < 2e-12
    assert 20 < errs[1] / errs[0] < 500


def test_kepler_tangent_grows_linearly():
    """A regular orbit's tangent grows linearly: Kepler e = 0.3, 100 steps a period, the
    tangent at whole periods lies on a line in n to 1e-6 of its size (the shear of the
    period's dependence on the energy)."""
    system = Kepler(0.3)
    y0 = system.initial_state()
    P = system.period
    res = integrate(HBVM(6, 3), system, y0, P / 100, 100 * 200, sample_every=100,
                    variational=np.array([1e-2, 0.0, 0.0, 0.0]))
    V = res.extra["variational"][:, 0]
    n = np.arange(V.shape[0])
    fit = np.polynomial.polynomial.polyfit(n, V, 1)
    resid = V - np.polynomial.polynomial.polyval(n, fit).T
    norms = np.linalg.norm(V, axis=1)
    assert norms[-1] > 50 * norms[0]
    assert np.abs(resid).max() < 1e-6 * norms[-1]


def two_planets(a2=2.0, m=1e-4):
    """Sun and two planets on circular, slightly inclined orbits, G = 1, a = 1 and a2."""
    x = np.zeros((3, 3))
    v = np.zeros((3, 3))
    x[1], v[1] = [1.0, 0, 0], [0, 1.0, 0]
    x[2], v[2] = [-a2, 0, 0.01], [0, -np.sqrt(1 / a2), 0]
    ms = np.array([1.0, m, m])
    x -= (ms[:, None] * x).sum(0) / ms.sum()
    v -= (ms[:, None] * v).sum(0) / ms.sum()
    return NBody(ms, positions=x, velocities=v)


def test_megno_tends_to_2_for_a_regular_two_planet_system():
    """Period ratio 2.83, masses 1e-4 (regular): <Y> after 500 inner orbits within 0.1 of 2
    (measured 1.937, approaching 2 as 2 - O(ln t / t)), rising; the finite-time Lyapunov
    indicator ln(|delta| / |delta_0|) / t about ln(t) / t."""
    system = two_planets()
    y0 = system.initial_state()
    V0 = np.random.default_rng(1).normal(size=y0.size)
    res = integrate(HBVM(6, 3), system, y0, 2 * np.pi / 50, 500 * 50, sample_every=50 * 50,
                    variational=V0)
    mg = res.extra["megno"]
    assert np.isnan(mg[0]) and np.all(np.diff(mg[2:]) > 0)
    assert abs(mg[-1] - 2.0) < 0.1
    assert 0 < res.extra["lyapunov"] < 2 * np.log(res.t[-1]) / res.t[-1]


def test_megno_grows_linearly_for_a_chaotic_orbit():
    """Henon-Heiles just below the escape energy, q = (0, 0), p2 = 0.1 (chaotic; Python path,
    its hessian): <Y> passes 20 by t = 400 and keeps growing (measured 6.3, 16.4, 27.4 at
    t = 100, 200, 300)."""
    E = 1 / 6 - 1e-3
    y0 = np.array([0.0, 0.0, np.sqrt(2 * E - 0.01), 0.1])
    res = integrate(HBVM(3, 2), HenonHeiles(y0), y0, 0.1, 4000, sample_every=1000,
                    variational=np.array([1.0, 0, 0, 0]))
    mg = res.extra["megno"]
    assert res.path == "python-separable"
    assert mg[-1] > 20 and np.all(np.diff(mg[1:]) > 3)
    assert res.extra["lyapunov"] > 0.05


def test_megno_accumulator_on_known_growth():
    """|delta| = 1 + t (regular): Y = 2 - 2 ln(1 + t) / t and <Y>(T) = 2 + 2 Li2(-T) / T
    (1.9695 at T = 2000, tending to 2); |delta| = exp(lambda t): <Y> = lambda T / 2."""
    import mpmath
    T = 2000.0
    t = np.linspace(0, T, 20001)
    regular = 2 + 2 * float(mpmath.polylog(2, -T)) / T
    for growth, check in [(lambda t: 1 + t, lambda mg: abs(mg.mean - regular) < 1e-5),
                          (lambda t: np.exp(0.01 * t), lambda mg: abs(mg.mean - 0.01 * T / 2) < 1e-9)]:
        mg = Megno(0.0, np.array([1.0, 0.0]), np.ones(2))
        for ti in t[1:]:
            mg.update(ti, np.array([growth(ti), 0.0]))
        assert check(mg), mg.mean
    assert abs(mg.lyapunov - 0.01) < 1e-12


def exact_jacobian(system, y0, t):
    """The Kepler flow's Jacobian at time t: central differences of Kepler.exact_solution in
    long double, increment 1e-10 (accurate to about 1e-11 relative; at 1e-6 their own
    truncation is 0.08 after a period of e = 0.9)."""
    J = np.empty((4, 4))
    for j in range(4):
        e = np.zeros(4, dtype=np.longdouble)
        e[j] = 1e-10
        J[:, j] = (system.exact_solution(y0 + e, t) - system.exact_solution(y0 - e, t)) / 2e-10
    return J


def test_adaptive_tangent_approximates_the_flow_and_ignores_rejected_attempts():
    """Adaptive steps map the tangents once per accepted step: over one period of Kepler
    e = 0.9 (attempts rejected on the way) the tangents at the samples (every 50th step, the
    sample times 1.0 and 2.5, the end) agree with the exact flow's Jacobian there: to 1.4e-11
    relative at the end (epsilon = 1e-12, 1e-14 and 1e-15 alike), to 2e-10 at the first sample
    (t = 0.0026, |J| = 5: the steps' own error).  A rejected attempt mapped too would be off by
    O(1), a sample paired with its neighbouring step by about 1e-2 (J moves by O(1) per unit
    time near pericentre, the steps there are 1e-4 long)."""
    system = Kepler(0.9)
    y0 = system.initial_state()
    P = system.period
    res = integrate(HBVM(6, 3), system, y0, 0.05, adaptive=True, t_end=P, epsilon=1e-12,
                    variational=np.eye(4), sample_every=50, sample_times=[1.0, 2.5])
    V = res.extra["variational"]
    assert res.extra["rejected"] > 0
    assert V.shape == (len(res.t), 4, 4) and np.array_equal(V[0], np.eye(4))
    marks = [int(np.flatnonzero(res.t == t)[0]) for t in (1.0, 2.5, P)]
    for i in (1, 2, *marks):
        J = exact_jacobian(system, y0, res.t[i])
        assert np.abs(V[i].T - J).max() < (1e-9 if i == marks[-1] else 1e-7) * np.abs(J).max()


def test_failed_step_leaves_state_and_tangents():
    system = Kepler(0.6)
    st = VariationalStepper(HBVM(4, 2), system, system.initial_state(), solver="fixed_point",
                            max_iter=5, variational=np.ones(4))
    st.step(0.01)
    before = (st.y, st.tangents, st.t, st.megno.state.copy(), st.nsteps)
    with pytest.raises(ConvergenceError, match="h=3 at t=0.01"):
        st.step(3.0)
    after = (st.y, st.tangents, st.t, st.megno.state, st.nsteps)
    for a, b in zip(before, after):
        assert np.array_equal(a, b)


class BrokenJvp(Kepler):
    """Kepler whose force derivative (Python) turns nan on its 40th call."""
    separable_jvp = None

    def __init__(self):
        super().__init__(0.6)
        self.calls = 0

    def force_jvp(self, Q, dQ):
        self.calls += 1
        K = np.array([_kepler_jacobian(q) for q in Q])
        out = np.einsum("nij,nj->ni", K, dQ)
        return out * np.nan if self.calls >= 40 else out


def _kepler_jacobian(q):
    r = np.sqrt(q @ q)
    return 3 * np.outer(q, q) / r ** 5 - np.eye(2) / r ** 3


def test_failed_tangent_map_takes_the_step_back():
    """A step that converged but whose tangent map did not is taken back, tangents and all,
    and raises naming the tangent map."""
    system = BrokenJvp()
    st = VariationalStepper(HBVM(4, 2), system, system.initial_state(), variational=np.eye(4))
    assert st.binding.name == "python-separable"
    with pytest.raises(NonFiniteError, match="tangent vectors") as info:
        for _ in range(20):
            before = (st.y, st.tangents, st.t, st.megno.state.copy(), st.nsteps, st.niter)
            st.step(0.01)
    assert 0 < before[4] < 20
    after = (st.y, st.tangents, st.t, st.megno.state, st.nsteps, st.niter)
    for a, b in zip(before, after):
        assert np.array_equal(a, b)
    assert info.value.h == 0.01
    # the same inside a run's loop (run_variational): the error names the tangent map and
    # carries the samples up to the last step whose tangents were mapped
    with pytest.raises(NonFiniteError, match="tangent vectors") as info:
        integrate(HBVM(4, 2), BrokenJvp(), system.initial_state(), 0.01, 20,
                  variational=np.eye(4))
    res = info.value.result
    assert res.status == "failed" and 0 < res.steps < 20 and res.solver_switches == 0
    assert len(res.t) == res.steps + 1 and res.extra["variational"].shape == (res.steps + 1, 4, 4)


class NoDerivative(SeparableSystem):
    dim = 1
    masses = np.ones(1)

    def potential(self, q):
        return 0.5 * np.sum(np.asarray(q) ** 2, axis=-1)

    def forces(self, q):
        return -np.asarray(q, dtype=float)


def test_refusals():
    with pytest.raises(TypeError, match="derivative of the force of NoDerivative.*hessian"):
        integrate(HBVM(2, 2), NoDerivative(), np.array([1.0, 0.0]), 0.1, 3,
                  variational=np.array([1.0, 0.0]))
    system = Kepler(0.5)
    y0 = system.initial_state()
    with pytest.raises(ValueError, match=r"`variational` must have shape \(4,\) or \(nv, 4\)"):
        integrate(HBVM(2, 2), system, y0, 0.1, 3, variational=np.ones(3))
    with pytest.raises(ValueError, match="first tangent vector is zero"):
        integrate(HBVM(2, 2), system, y0, 0.1, 3, variational=np.zeros((2, 4)))
    with pytest.raises(ValueError, match="must be finite"):
        integrate(HBVM(2, 2), system, y0, 0.1, 3, variational=[1.0, np.nan, 0, 0])
    from integrators.equip import EQUIP
    with pytest.raises(TypeError, match=r"need an HBVM\(k, s\) method .*EQUIP"):
        integrate(EQUIP(4, 2), system, y0, 0.1, 3, variational=np.ones(4))


def test_full_form_of_nbody_gives_the_separable_tangents():
    """NBody run in the full form (Python path: the separable jvp composed into Hess H dY)
    carries three tangents as the separable form does, to round-off of the iterations
    (measured 6.5e-12 relative to the largest entry after two 50-day steps)."""
    system = outer_solar_system()
    y0 = system.initial_state()
    V0 = np.random.default_rng(2).normal(size=(3, y0.size))
    a = VariationalStepper(HBVM(6, 3), system, y0, variational=V0)
    b = VariationalStepper(HBVM(6, 3), system, y0, variational=V0, form="full")
    for st in (a, b):
        st.step(50.0)
        st.step(50.0)
    assert b.binding.name == "python-full"
    assert np.abs(a.tangents - b.tangents).max() < 1e-10 * np.abs(a.tangents).max()
