"""The classic systems: published initial data, forces = -grad V, compiled kernels = numpy."""
from __future__ import annotations

import numpy as np
import pytest

from systems import FPU, HenonHeiles, Kepler, Morse, Pendulum

SYSTEMS = [Kepler(0.6), Kepler(0.9, mu=2.0), HenonHeiles(), FPU(3, 50.0), FPU(2, 7.0), Pendulum(), Morse(2.0, 1.5)]


def _ids(s):
    return type(s).__name__


def _sample_q(system, rng, n=5):
    q0 = system.initial_state()[: system.dim]
    return q0 + 0.1 * rng.normal(size=(n, system.dim))


@pytest.mark.parametrize("e", [0.0, 0.6, 0.9])
def test_kepler_initial_data(e):
    kep = Kepler(e)
    y0 = kep.initial_state()
    assert np.allclose(y0, [1 - e, 0, 0, np.sqrt((1 + e) / (1 - e))], rtol=0, atol=1e-15)
    assert kep.energy(y0) == pytest.approx(-0.5, abs=1e-15)
    assert kep.period == pytest.approx(2 * np.pi, rel=1e-15)
    assert kep.angular_momentum(y0) == pytest.approx(np.sqrt(1 - e * e), rel=1e-15)
    assert Kepler(e, mu=4.0).period == pytest.approx(np.pi, rel=1e-15)
    assert Kepler(e, mu=4.0).energy(Kepler(e, mu=4.0).initial_state()) == pytest.approx(-2.0, rel=1e-15)


@pytest.mark.parametrize("e, mu", [(0.0, 1.0), (0.6, 1.0), (0.95, 2.5)])
def test_kepler_exact_solution_is_the_flow(e, mu):
    """The reference of bench_kepler's solution error: the state returns to its start after
    its own period (that of the double-precision start, which is not exactly 2 pi), the flow
    composes, it conserves energy and angular momentum, and it agrees with a Gauss s = 8 run
    over one orbit (an independent check: the others hold for any map that is a flow of some
    conservative system); an unbound start is refused."""
    from integrators import HBVM, integrate
    L = np.longdouble
    kep = Kepler(e, mu)
    rot = np.array([[0.8, -0.6], [0.6, 0.8]])
    y0 = kep.initial_state()
    y0 = np.concatenate([rot @ y0[:2], rot @ y0[2:]])
    q, v = y0[:2].astype(L), y0[2:].astype(L)
    inv_a = 2 / np.sqrt(q @ q) - (v @ v) / L(mu)
    period = 8 * np.arctan(L(1)) / np.sqrt(L(mu) * inv_a ** 3)
    assert np.max(np.abs(kep.exact_solution(y0, period) - y0)) < 1e-16
    t1, t2 = L(0.37), L(5.1)
    mid = kep.exact_solution(y0, t1)
    assert mid.dtype == L
    assert np.max(np.abs(kep.exact_solution(mid, t2) - kep.exact_solution(y0, t1 + t2))) < 1e-16

    def energy(y):
        return (y[2:] @ y[2:]) / 2 - L(mu) / np.sqrt(y[:2] @ y[:2])

    y1 = kep.exact_solution(y0, t2)
    assert abs(energy(y1) - energy(y0.astype(L))) < 1e-17
    assert abs((y1[0] * y1[3] - y1[1] * y1[2]) - (q[0] * v[1] - q[1] * v[0])) < 1e-17
    n = 4000                     # enough steps for the pericentre of e = 0.95
    h = float(period) / n
    run = integrate(HBVM(8, 8), kep, y0, h, n, sample_every=n, fast=True)
    err = np.max(np.abs(run.y[-1] - kep.exact_solution(y0, L(n) * L(h))))
    assert err < 1e-12 * np.max(np.abs(y0)), err
    with pytest.raises(ValueError, match="bound orbit"):
        kep.exact_solution(np.array([1.0, 0.0, 0.0, 3.0 * np.sqrt(mu)]), 1.0)   # v > v_escape


def test_fpu_initial_data_in_rotated_variables():
    w = 50.0
    fpu = FPU(3, w)
    y0 = fpu.initial_state()
    q, p = y0[:6], y0[6:]
    x0 = (q[1::2] + q[0::2]) / np.sqrt(2)          # x_{i,0} = (q_{2i} + q_{2i-1}) / sqrt 2
    x1 = (q[1::2] - q[0::2]) / np.sqrt(2)
    y0r = (p[1::2] + p[0::2]) / np.sqrt(2)
    y1r = (p[1::2] - p[0::2]) / np.sqrt(2)
    assert np.allclose(x0, [1, 0, 0], atol=1e-15) and np.allclose(y0r, [1, 0, 0], atol=1e-15)
    assert np.allclose(x1, [1 / w, 0, 0], atol=1e-15) and np.allclose(y1r, [1, 0, 0], atol=1e-15)
    I = fpu.stiff_energies(y0)
    assert I[0] == pytest.approx(0.5 * (1 + w * w / w ** 2), rel=1e-14) and np.allclose(I[1:], 0)
    # H by the formula of HLW I.5.1, written out for m = 3 (q_0 = q_7 = 0)
    qq = np.concatenate([[0.0], q, [0.0]])
    H = 0.5 * p @ p + w ** 2 / 4 * sum((qq[2 * i] - qq[2 * i - 1]) ** 2 for i in (1, 2, 3)) \
        + sum((qq[2 * i + 1] - qq[2 * i]) ** 4 for i in (0, 1, 2, 3))
    assert fpu.energy(y0) == pytest.approx(H, rel=1e-14)


@pytest.mark.parametrize("system", SYSTEMS, ids=_ids)
def test_forces_are_minus_gradient_of_potential(system):
    """Central differences of V (step 1e-6, error ~1e-10 relative) against forces(q)."""
    rng = np.random.default_rng(3)
    Q = _sample_q(system, rng)
    F = system.forces(Q)
    assert F.shape == Q.shape
    d = 1e-6
    for i in range(system.dim):
        e = np.zeros(system.dim)
        e[i] = d
        fd = -(system.potential(Q + e) - system.potential(Q - e)) / (2 * d)
        assert np.allclose(F[:, i], fd, rtol=1e-7, atol=1e-7 * max(1.0, np.max(np.abs(F)))), (type(system), i)
    # gradient (batched) = (-F, p / M)
    Y = np.concatenate([Q, rng.normal(size=Q.shape)], axis=1)
    G = system.gradient(Y)
    assert np.allclose(G[:, : system.dim], -F) and np.allclose(G[:, system.dim:], Y[:, system.dim:] / system.masses)
    assert np.allclose(system.energy(Y), [system.energy(y) for y in Y], rtol=1e-15)


@pytest.mark.parametrize("system", SYSTEMS, ids=_ids)
def test_compiled_kernels_equal_numpy(system):
    force, potential, params = system.separable_kernels()
    rng = np.random.default_rng(4)
    Q = np.ascontiguousarray(_sample_q(system, rng, 7))
    out = np.empty_like(Q)
    force(Q, np.ascontiguousarray(params, dtype=float), out)
    F = system.forces(Q)
    assert np.max(np.abs(out - F)) <= 1e-13 * max(1.0, np.max(np.abs(F)))
    for q in Q:
        V = potential(np.ascontiguousarray(q), np.ascontiguousarray(params, dtype=float))
        assert V == pytest.approx(float(system.potential(q)), rel=1e-14, abs=1e-14)


@pytest.mark.parametrize("system", [Kepler(0.6), HenonHeiles(), Pendulum()], ids=_ids)
def test_hessian_by_finite_differences(system):
    rng = np.random.default_rng(5)
    y = np.concatenate([_sample_q(system, rng, 1)[0], rng.normal(size=system.dim)])
    H = system.hessian(y)
    d = 1e-6
    fd = np.empty_like(H)
    for j in range(y.size):
        e = np.zeros(y.size)
        e[j] = d
        fd[:, j] = (system.gradient(y + e) - system.gradient(y - e)) / (2 * d)
    assert np.allclose(H, fd, rtol=1e-7, atol=1e-7)
    assert np.allclose(H, H.T)


def test_henon_heiles_defaults_and_degrees():
    hh = HenonHeiles()
    y0 = hh.initial_state()
    assert np.array_equal(y0, [0.18] * 4)
    x = y = 0.18
    assert hh.energy(y0) == pytest.approx(0.18 ** 2 + 0.5 * (x * x + y * y) + x * x * y - y ** 3 / 3, rel=1e-15)
    assert hh.energy(y0) < hh.escape_energy
    assert (hh.polynomial_degree, FPU().polynomial_degree, Kepler().polynomial_degree) == (3, 4, None)


@pytest.mark.parametrize("make,match", [
    (lambda: Kepler(1.0), r"`e` must satisfy 0 <= e < 1 \(got e=1\.0\)"),
    (lambda: Kepler(-0.1), r"`e` must satisfy 0 <= e < 1 \(got e=-0\.1\)"),
    (lambda: Kepler(float("nan")), r"`e` must satisfy 0 <= e < 1 \(got e=nan\)"),
    (lambda: Kepler(0.5, mu=0.0), r"`mu` must be a positive number \(got mu=0\.0\)"),
    (lambda: FPU(0), r"`m` must be an integer >= 1 \(got m=0\)"),
    (lambda: FPU(2.5), r"`m` must be an integer >= 1 \(got m=2\.5\)"),
    (lambda: FPU(True), r"`m` must be an integer >= 1 \(got m=True\)"),
    (lambda: FPU(3, omega=-1.0), r"`omega` must be a positive number \(got omega=-1\.0\)"),
    (lambda: HenonHeiles([0.1, 0.2]), r"`y0` must be 4 finite numbers \(q1, q2, p1, p2\)"),
    (lambda: HenonHeiles([0.1, 0.2, np.nan, 0.0]), r"`y0` must be 4 finite numbers"),
    (lambda: Pendulum(omega0=0.0), r"`omega0` must be a positive number \(got omega0=0\.0\)"),
    (lambda: Morse(D=-1.0), r"`D` must be a positive number \(got D=-1\.0\)"),
    (lambda: Morse(mass=0.0), r"`mass` must be a positive number \(got mass=0\.0\)"),
])
def test_system_validation(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize("system", [Kepler(0.6), HenonHeiles(), Pendulum()],
                         ids=lambda s: type(s).__name__)
def test_hessian_has_the_documented_shape_and_order(system):
    """systems.base: hessian(y) is (2m, 2m), ordered like y = (q, p): compare with central
    differences of the gradient."""
    y = np.asarray(system.initial_state(), dtype=float) + 0.01
    H = np.asarray(system.hessian(y))
    n = 2 * system.dim
    assert H.shape == (n, n)
    eps = 1e-6
    fd = np.array([(system.gradient(y + eps * e) - system.gradient(y - eps * e)) / (2 * eps)
                   for e in np.eye(n)]).T
    assert np.max(np.abs(H - fd)) <= 1e-6 * max(1.0, np.max(np.abs(H)))
