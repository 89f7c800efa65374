"""integrators.kchoice: the one rule that chooses k (REBOUND driver, reports, benchmarks)."""
import logging
import math

import numpy as np
import pytest

from integrators import HBVM, integrate
from integrators.core import monomial_weight
from integrators.kchoice import EARLY_ULPS, adaptive_k, choose_k, energy_rounding
from systems import FPU, HenonHeiles, Kepler


def _rotated(y, angle):
    c, s = math.cos(angle), math.sin(angle)
    R = np.array([[c, -s], [s, c]])
    return np.concatenate([R @ y[:2], R @ y[2:]])


@pytest.mark.parametrize("system, s", [(HenonHeiles(), 2), (FPU(), 3)])
def test_a_polynomial_hamiltonian_gets_the_exact_k_without_a_run(runs, system, s):
    c = choose_k(system, system.initial_state(), s, 0.05, 20)
    assert c.k == HBVM.for_polynomial_degree(system.polynomial_degree, s).k
    assert c.k == max(s, math.ceil(system.polynomial_degree * s / 2))
    assert c.reason.startswith("exact for polynomial degree") and runs == [] and c.trial_errors == {}


@pytest.mark.parametrize("s, n", [(2, 100), (3, 100), (4, 200)])
def test_the_chosen_k_conserves_kepler_energy_as_well_as_the_reference(s, n):
    """Kepler e = 0.6, one period of test steps: the k chosen is well below the reference k
    (the rule is not 'always the largest'), above s (HBVM(s, s)'s quadrature error shows at
    these steps), and over five periods from 5 rotated starts its energy error is at the
    reference's round-off (medians: one run at round-off is a random draw)."""
    kep = Kepler(0.6)
    h = 2 * math.pi / n
    k_ref = max(2 * s, s + 8)
    picked, e_k, e_ref = [], [], []
    for rep in range(5):
        y0 = _rotated(kep.initial_state(), 0.7 * rep)
        c = choose_k(kep, y0, s, h, n)
        assert c.reason == "round-off quadrature error" and c.steps == n
        assert c.trial_errors[s] > 100 * np.finfo(float).eps      # visible at k = s
        picked.append(c.k)
        e_k.append(integrate(HBVM(c.k, s), kep, y0, h, 5 * n).max_energy_error)
        e_ref.append(integrate(HBVM(k_ref, s), kep, y0, h, 5 * n).max_energy_error)
    assert all(s < k < k_ref for k in picked)
    assert np.median(e_k) <= 1.5 * np.median(e_ref) + 2 * np.finfo(float).eps


def test_the_margin_is_one_above_the_first_k_at_round_off():
    """The documented contract: the k returned is one above the first k whose test-step error
    is at most max(2 eps, 1.5 x the reference's, EARLY_ULPS ulps of the energy's rounding), and
    every k below that one is above it."""
    kep = Kepler(0.6)
    y0 = kep.initial_state()
    c = choose_k(kep, y0, 2, 2 * math.pi / 100, 100)
    e = c.trial_errors
    bound = max(2 * np.finfo(float).eps, 1.5 * e[max(4, 10)], EARLY_ULPS * energy_rounding(kep, y0))
    first = c.k - 1
    assert e[first] <= bound and all(e[k] > bound for k in range(2, first))


def test_a_step_that_no_k_takes_returns_the_reference_k_and_says_so(caplog):
    kep = Kepler(0.6)
    with caplog.at_level(logging.WARNING, logger="integrators.kchoice"):
        c = choose_k(kep, kep.initial_state(), 2, 2 * math.pi / 8, 20, solver="fixed_point")
    assert c.k == 10 and c.reason == "reference k (test steps failed)"
    assert c.trial_errors[10] == math.inf
    assert "HBVM(10, 2) failed" in caplog.text


@pytest.mark.parametrize("kwargs, name", [(dict(s=0), "`s`"), (dict(steps=0), "`steps`"),
                                          (dict(steps=2.5), "`steps`"), (dict(k_max=1), "`k_max`")])
def test_bad_arguments_are_named(kwargs, name):
    kep = Kepler(0.6)
    args = dict(s=2, h=0.05, steps=20) | kwargs
    with pytest.raises(ValueError, match=name):
        choose_k(kep, kep.initial_state(), **args)


def test_adaptive_k_keeps_the_quadrature_below_round_off_at_the_controls_precision():
    from integrators.engine import DEFAULT_EPSILON
    from integrators.equip import DEFAULT_EPSILON as EQUIP_EPSILON
    assert adaptive_k(6, DEFAULT_EPSILON) == 8           # the REBOUND driver's default
    assert adaptive_k(8, EQUIP_EPSILON) == 9              # ... and EQUIP's
    ks = [adaptive_k(6, eps) for eps in (1e-3, 1e-6, 1e-9, 1e-12)]
    assert ks == sorted(ks, reverse=True) and all(k > 6 for k in ks)
    for s, eps in [(1, 1e-9), (4, 1e-10), (6, 1e-14), (8, 1e-12)]:
        k = adaptive_k(s, eps)
        wh = eps ** (1.0 / (2 * s + 1))     # omega h of a step whose local error is epsilon
        assert wh ** (2 * k) <= 1e-16 < wh ** (2 * (k - 1)) or k == s + 1


@pytest.mark.parametrize("y0, match", [(np.full(4, np.nan), "non-finite"), (np.zeros((2, 4)), "shape"),
                                       (np.zeros(3), "shape")])
def test_a_state_that_cannot_be_measured_from_is_refused(y0, match):
    """Not a warning and the largest k: a clear error naming y0."""
    with pytest.raises(ValueError, match=f"`y0`.*{match}"):
        choose_k(Kepler(0.6), y0, 2, 0.05, 20)
