"""User systems written the scipy way (issue: energy for one state, no dim, a gradient that ignores
or transposes the batch): adapted or refused by name, never integrated into wrong numbers."""
from __future__ import annotations

import numpy as np
import pytest

from integrators import HBVM, Stepper, integrate
from integrators.protocol import adapt_system
from systems import FPU, HenonHeiles, Kepler, NBody

Y0 = np.array([1.0, 0.0, 0.0, 1.0])       # circular Kepler orbit, H = -0.5


def _kepler_gradient(y):
    y = np.asarray(y, dtype=float)
    q, p = y[..., :2], y[..., 2:]
    r = np.linalg.norm(q, axis=-1, keepdims=True)
    return np.concatenate([q / r ** 3, p], axis=-1)


class OneStateEnergy:
    """The issue's reproduction: energy written for one state, no dim."""

    def energy(self, y):
        q, p = y[:2], y[2:]
        return 0.5 * np.sum(p ** 2) - 1 / np.linalg.norm(q, axis=-1)

    def gradient(self, y):
        return _kepler_gradient(y)


class IgnoresBatch(OneStateEnergy):
    dim = 2

    def gradient(self, y):
        y = np.asarray(y, dtype=float)
        q, p = y[..., :2], y[..., 2:]
        r = np.linalg.norm(q)                 # no axis: the norm of the whole stack
        return np.concatenate([q / r ** 3, p], axis=-1)


class Transposed(OneStateEnergy):
    dim = 2

    def gradient(self, y):
        y = np.asarray(y, dtype=float).T      # written for states as columns
        q, p = y[:2], y[2:]
        r = np.linalg.norm(q, axis=0)
        return np.concatenate([q / r ** 3, p])


class Batched:
    dim = 2

    def energy(self, y):
        y = np.asarray(y)
        return 0.5 * np.sum(y[..., 2:] ** 2, axis=-1) - 1 / np.linalg.norm(y[..., :2], axis=-1)

    def gradient(self, y):
        return _kepler_gradient(y)


@pytest.mark.parametrize("fast", [None, False])
def test_energy_for_one_state_and_no_dim_integrate_correctly(fast):
    sys_ = OneStateEnergy()
    assert sys_.energy(np.array([Y0, Y0]))[0] != -0.5     # the garbage a stack gets
    res = integrate(HBVM(6, 3), sys_, Y0, 2 * np.pi / 100, 200, fast=fast)
    assert res.energy.shape == (201,) and res.energy[0] == -0.5
    assert res.max_energy_error <= 1e-13                   # was 3.8e-3 with stacked calls
    ref = integrate(HBVM(6, 3), Kepler(0.0), Kepler(0.0).initial_state(), 2 * np.pi / 100, 200,
                    fast=False)
    assert np.max(np.abs(res.y - ref.y)) <= 1e-12


def test_adapted_energy_keeps_the_stack_shape_and_dim_is_inferred():
    ad = adapt_system(OneStateEnergy(), Y0)
    assert ad.dim == 2
    assert ad.energy(Y0) == -0.5 and ad.energy(np.tile(Y0, (2, 3, 1))).shape == (2, 3)


@pytest.mark.parametrize("cls, k", [(IgnoresBatch, 4), (Transposed, 4), (IgnoresBatch, 3)])
def test_wrong_gradients_are_refused_by_name_even_when_k_is_2_dim(cls, k):
    match = {IgnoresBatch: r"`gradient` of IgnoresBatch on a stack of shape \(3, 4\) returned row 0 "
                           r"!= gradient\(state 0\) .*index the last axis",
             Transposed: r"`gradient` of Transposed must return shape \(3, 4\) for a stack of "
                         r"states of shape \(3, 4\), one gradient per row \(got shape \(4, 3\)\)"}[cls]
    with pytest.raises(ValueError, match=match):
        integrate(HBVM(k, 2), cls(), Y0, 0.05, 20)
    with pytest.raises(ValueError, match=match):
        Stepper(HBVM(k, 2), cls(), Y0)


def test_gradient_that_breaks_on_a_stack_is_named():
    class Breaks(OneStateEnergy):
        def gradient(self, y):
            q, p = y[:2], y[2:]
            return np.concatenate([q / np.linalg.norm(q) ** 3, p])
    with pytest.raises(ValueError, match=r"`gradient` of Breaks on a stack of shape \(3, 4\) "
                                         r"returned row 0 != gradient\(state 0\)"):
        integrate(HBVM(2, 2), Breaks(), Y0, 0.05, 5)


def test_odd_state_without_dim_is_refused():
    with pytest.raises(ValueError, match=r"`y0` must hold \(q, p\) .*even length, when the system "
                                         r"has no `dim` \(got shape \(3,\)\); give OneStateEnergy a `dim`"):
        integrate(HBVM(2, 2), OneStateEnergy(), [1.0, 0.0, 1.0], 0.1, 5)


def test_protocol_systems_pass_through_unchanged():
    for s in (Kepler(0.6), HenonHeiles(), FPU(3, 50.0), NBody([1.0, 1e-3])):
        y0 = s.initial_state() if hasattr(s, "initial_state") and s.dim != 6 else np.r_[0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 1, 0.0]
        assert adapt_system(s, y0) is s
        assert Stepper(HBVM(2, 2), s, y0).system is s
    b = Batched()
    assert adapt_system(b, Y0) is b                     # follows the protocol: no wrapper


def test_declared_batched_energy_gives_the_energies():
    """The step samples H one state at a time (through its kernel binding), which is right for
    a batched energy too."""
    calls = []

    class Declared(Batched):
        batched_energy = True

        def energy(self, y):
            calls.append(np.shape(y))
            return super().energy(y)
    res = integrate(HBVM(4, 2), Declared(), Y0, 0.05, 10, fast=False)
    assert calls and all(c == (4,) for c in calls) and res.max_energy_error <= 1e-13
    assert np.allclose(res.energy, [Declared().energy(y) for y in res.y], rtol=0, atol=0)
