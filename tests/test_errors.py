"""Bad input raises ValueError/TypeError naming the argument, the value and the fix; a step that
does not converge raises ConvergenceError.  Every message is pinned."""
from __future__ import annotations

import numpy as np
import pytest

from integrators import HBVM, ConvergenceError, Stepper, gauss_matrix, integrate
from systems import HamiltonianSystem, Kepler

KEP = Kepler(0.6)
Y0 = KEP.initial_state()


@pytest.mark.parametrize("k,s,match", [
    (2, 3, r"`k` must be >= `s` \(got k=2, s=3\).*e\.g\. k=3"),
    (1, 0, r"`s` must be >= 1 \(got s=0\)"),
    (0, 1, r"`k` must be >= 1 \(got k=0\)"),
    (2.5, 2, r"`k` must be an integer >= 1 \(got k=2\.5\); pass a whole number"),
    ("3", 2, r"`k` must be an integer >= 1 \(got k='3'\)"),
    (3, True, r"`s` must be an integer >= 1 \(got s=True\)"),
    (3, 2.0, r"`s` must be an integer >= 1 \(got s=2\.0\)"),
    (None, 1, r"`k` must be an integer >= 1 \(got k=None\)"),
])
def test_bad_k_s(k, s, match):
    with pytest.raises(ValueError, match=match):
        HBVM(k, s)


def test_numpy_integers_are_accepted():
    assert HBVM(np.int64(4), np.int32(2)) == HBVM(4, 2)


@pytest.mark.parametrize("nodes", ["radau", "Gauss", 3, None])
def test_unknown_nodes(nodes):
    with pytest.raises(ValueError, match=r"`nodes` must be one of \('gauss', 'lobatto'\) \(got nodes="):
        HBVM(3, 2, nodes)


@pytest.mark.parametrize("nu,s,match", [
    (0, 2, r"`nu` must be >= 1 \(got nu=0\)"),
    (2.5, 2, r"`nu` must be an integer >= 1 \(got nu=2\.5\)"),
    ("4", 2, r"`nu` must be an integer >= 1 \(got nu='4'\)"),
    (4, 0, r"`s` must be >= 1 \(got s=0\)"),
])
def test_for_polynomial_degree_bad(nu, s, match):
    with pytest.raises(ValueError, match=match):
        HBVM.for_polynomial_degree(nu, s)


def test_gauss_matrix_bad():
    with pytest.raises(ValueError, match=r"`s` must be >= 1 \(got s=0\)"):
        gauss_matrix(0)


@pytest.mark.parametrize("kwargs,match", [
    (dict(solver="euler"), r"`solver` must be one of \('auto', 'fixed_point', 'newton'\) \(got solver='euler'\)"),
    (dict(form="lagrangian"), r"`form` must be 'auto', 'full' or 'separable' \(got form='lagrangian'\)"),
    (dict(tol=0.0), r"`tol` must be None \(round-off\) or a number in \(0, 1\) \(got tol=0\.0\)"),
    (dict(tol=1.5), r"`tol` must be None .* \(got tol=1\.5\)"),
    (dict(tol="1e-10"), r"`tol` must be None .* \(got tol='1e-10'\)"),
    (dict(tol=float("nan")), r"`tol` must be None .* \(got tol=nan\)"),
    (dict(max_iter=0), r"`max_iter` must be a positive integer \(got max_iter=0\)"),
    (dict(max_iter=2.5), r"`max_iter` must be a positive integer \(got max_iter=2\.5\)"),
    (dict(max_iter=True), r"`max_iter` must be a positive integer \(got max_iter=True\)"),
    (dict(t0=float("inf")), r"`t0` must be a finite number \(got t0=inf\)"),
    (dict(t0="zero"), r"`t0` must be a finite number \(got t0='zero'\)"),
])
@pytest.mark.parametrize("fast", [None, False])
def test_bad_options_on_both_paths(kwargs, match, fast):
    with pytest.raises(ValueError, match=match):
        integrate(HBVM(4, 2), KEP, Y0, 0.1, 5, fast=fast, **kwargs)
    with pytest.raises(ValueError, match=match):
        Stepper(HBVM(4, 2), KEP, Y0, **kwargs)


@pytest.mark.parametrize("h", [0, 0.0, float("nan"), float("inf"), "big", None])
def test_bad_step_size(h):
    with pytest.raises(ValueError, match=r"`h` must be a nonzero finite number \(got h="):
        integrate(HBVM(4, 2), KEP, Y0, h, 5)
    st = Stepper(HBVM(4, 2), KEP, Y0)
    with pytest.raises(ValueError, match=r"`h` must be a nonzero finite number"):
        st.step(h)
    assert st.nsteps == 0 and np.array_equal(st.y, Y0)


@pytest.mark.parametrize("steps", [-1, 2.0, True, "10"])
def test_bad_steps(steps):
    with pytest.raises(ValueError, match=r"`steps` must be an integer >= 0 \(got steps="):
        integrate(HBVM(4, 2), KEP, Y0, 0.1, steps)


@pytest.mark.parametrize("every", [0, -3, 1.5, False])
def test_bad_sample_every(every):
    with pytest.raises(ValueError, match=r"`sample_every` must be an integer >= 1 \(got sample_every="):
        integrate(HBVM(4, 2), KEP, Y0, 0.1, 10, sample_every=every)
    # the adaptive path and the Stepper's own methods say the same (they raised
    # ZeroDivisionError or numpy's negative-dimension error before), and take no step
    with pytest.raises(ValueError, match=r"`sample_every` must be an integer >= 1 \(got sample_every="):
        integrate(HBVM(4, 2), KEP, Y0, 0.1, t_end=1.0, adaptive=True, sample_every=every)
    for fast in (True, False):
        st = Stepper(HBVM(4, 2), KEP, Y0, fast=fast)
        with pytest.raises(ValueError, match=r"`sample_every` must be an integer >= 1 \(got "):
            st.run(0.1, 10, sample_every=every)
        with pytest.raises(ValueError, match=r"`sample_every` must be an integer >= 1 \(got "):
            st.run_adaptive(0.1, 1.0, 1e-6, 1e-12, sample_every=every)
        assert st.nsteps == 0 and np.array_equal(st.y, Y0)


@pytest.mark.parametrize("steps", [-1, 2.0, True, "10"])
def test_bad_steps_on_the_stepper(steps):
    for fast in (True, False):
        st = Stepper(HBVM(4, 2), KEP, Y0, fast=fast)
        with pytest.raises(ValueError, match=r"`steps` must be an integer >= 0 \(got steps="):
            st.run(0.1, steps)
        assert st.nsteps == 0 and np.array_equal(st.y, Y0)


def test_zero_steps_is_the_initial_state():
    r = integrate(HBVM(4, 2), KEP, Y0, 0.1, 0)
    assert r.steps == 0 and r.y.shape == (1, 4) and np.array_equal(r.y[0], Y0)


class Oscillator(HamiltonianSystem):
    """A user-defined system with only dim, energy and gradient (the minimal protocol):
    H = (p^2 + q^2) / 2 in one degree of freedom."""

    dim = 1

    def energy(self, y):
        y = np.asarray(y, float)
        return 0.5 * (y[..., 0] ** 2 + y[..., 1] ** 2)

    def gradient(self, y):
        return np.asarray(y, float).copy()


def test_fast_needs_kernels_and_compatible_options():
    with pytest.raises(ValueError, match=r"`fast=True` needs a system with `(separable|full)_kernels\(\)`.*fast=False"):
        integrate(HBVM(2, 2), Oscillator(), [1.0, 0.0], 0.1, 5, fast=True)
    # Newton runs on the compiled step too, and matches the Python step exactly
    fast = integrate(HBVM(2, 2), KEP, Y0, 0.1, 5, fast=True, solver="newton")
    slow = integrate(HBVM(2, 2), KEP, Y0, 0.1, 5, fast=False, solver="newton")
    assert fast.path == "compiled-separable" and slow.path == "python-separable"
    assert np.array_equal(fast.y, slow.y) and (fast.iterations, fast.nfev) == (slow.iterations, slow.nfev)
    with pytest.raises(ValueError, match=r"`fast=True` needs a system with `full_kernels\(\)` \(compiled kernels for the full form\); Kepler has none"):
        integrate(HBVM(2, 2), KEP, Y0, 0.1, 5, fast=True, form="full")
    with pytest.raises(ValueError, match=r"`form='separable'` needs a system with `masses`, `forces` and `potential`; use form='full'"):
        Stepper(HBVM(2, 2), Oscillator(), [1.0, 0.0], form="separable")


@pytest.mark.parametrize("y0,match", [
    ([1.0, 0.0, 0.0], r"`y0` must have shape \(4,\) = \(q, p\) of a system with 2 degrees of freedom \(got shape \(3,\)\)"),
    (np.zeros((2, 2)), r"`y0` must have shape \(4,\).*\(got shape \(2, 2\)\)"),
    ([0.4, 0.0, np.nan, 2.0], r"`y0` must be finite .*check the initial state for nan or inf"),
    ([0.4, 0.0, np.inf, 2.0], r"`y0` must be finite"),
    (["a", "b", "c", "d"], r"`y0` must be an array of numbers"),
])
def test_bad_initial_state(y0, match):
    with pytest.raises(ValueError, match=match):
        integrate(HBVM(2, 2), KEP, y0, 0.1, 5)
    with pytest.raises(ValueError, match=match):
        Stepper(HBVM(2, 2), KEP, y0)


def test_not_a_system():
    with pytest.raises(TypeError, match=r"`system` must offer `energy\(y\)` and `gradient\(y\)` \(and may give `dim`\) \(got dict\)"):
        integrate(HBVM(2, 2), {}, Y0, 0.1, 5)


@pytest.mark.parametrize("fast", [True, False])
def test_forced_non_convergence(fast):
    """A huge step with fixed point and a small iteration cap: a named error with h, t, the
    solver and a hint; integrate(solver='fixed_point') does not fall back to Newton."""
    with pytest.raises(ConvergenceError, match=r"HBVM step of size h=5 at t=0 did not converge: fixed_point "
                                               r"iteration stopped after 3 iterations .*solver='newton'") as info:
        integrate(HBVM(4, 2), KEP, Y0, 5.0, 10, solver="fixed_point", max_iter=3, fast=fast)
    err = info.value
    assert err.h == 5.0 and err.solver == "fixed_point" and err.iterations == 3 and err.residual > 0
    assert isinstance(err, RuntimeError)


def test_newton_failure_message():
    with pytest.raises(ConvergenceError, match=r"newton iteration stopped after 2 iterations .*try a smaller step size h$"):
        Stepper(HBVM(4, 2), KEP, Y0, solver="newton", max_iter=2).step(5.0)


def test_user_defined_system_integrates_and_oscillator_is_exact():
    """The minimal protocol (dim, energy, gradient) is enough; for the harmonic oscillator the
    one-step map of HBVM(k, s) has the Gauss stability function, so after n steps the solution
    is R(ih)^n applied to q + i p, and the quadratic energy is conserved to round-off."""
    osc = Oscillator()
    m = HBVM(4, 2)
    h, n = 0.3, 100
    for solver in ("fixed_point", "newton"):
        res = integrate(m, osc, [1.0, 0.0], h, n, solver=solver)
        assert res.path == "python-full"
        assert res.max_energy_error <= 1e-13
        R = m.stability_function(-1j * h)      # q + i p rotates as exp(-i t)
        z = (1.0 + 0.0j) * R ** n
        assert abs(res.y[-1, 0] - z.real) <= 1e-12 and abs(res.y[-1, 1] - z.imag) <= 1e-12
        assert abs(res.y[-1, 0] - np.cos(h * n)) <= 1e-3    # and close to the exact rotation


def test_failed_auto_does_not_suggest_newton():
    """solver="auto" has tried Newton after fixed point: its hint is a smaller step only."""
    msg = str(ConvergenceError(5.0, 1e-3, 30, "auto", 0.0))
    assert msg.endswith("try a smaller step size h") and "newton" not in msg.split(";")[-1]
    assert "solver='newton'" in str(ConvergenceError(5.0, 1e-3, 60, "fixed_point", 0.0))


def test_hbvm_md_exports_both_step_errors():
    import hbvm_md
    from integrators import UnresolvedStepError
    assert hbvm_md.UnresolvedStepError is UnresolvedStepError and "UnresolvedStepError" in hbvm_md.__all__
