"""Energy conservation: exact for polynomial Hamiltonians (k >= nu s / 2), to round-off without
drift for Kepler, and first integrals of Gauss.

Energy behaviour is tested two ways (GeometricIntegrators.jl ``test_energy_behaviour``): the
maximum error is bounded, and a least-squares line through the error against time shows no drift.
"""
from __future__ import annotations

import numpy as np
import pytest

from integrators import HBVM, integrate
from systems import FPU, HenonHeiles, Kepler

STEPS = 10_000


def _signed_error(res) -> np.ndarray:
    return (res.energy - res.energy[0]) / abs(res.energy[0])


def _signed_drift(res) -> float:
    """Energy change over the whole run implied by the least-squares slope of the signed
    relative error against time."""
    t = res.t - res.t[0]
    return float(np.polyfit(t, _signed_error(res), 1)[0]) * t[-1]


def _drift_over_run(res) -> float:
    """|:func:`_signed_drift`|."""
    return abs(_signed_drift(res))


def _scatter(res) -> float:
    """Standard deviation of the signed relative energy error about its least-squares line: the
    round-off (and bounded oscillation) level against which a drift is judged."""
    t = res.t - res.t[0]
    err = _signed_error(res)
    return float(np.std(err - np.polyval(np.polyfit(t, err, 1), t)))


# (system, nu, h): large steps at which fixed point still converges (h omega = 0.5 for FPU);
# the invariants hold at any step, so the step's own error check (which refuses steps of
# s = 1 that miss more than a thousandth of their motion) and the energy checks (Gauss's energy
# error is the comparison, and its drift passes 1e-3: integrators.core.DRIFT_BOUND) are off in
# these tests: NO_CHECK
NO_CHECK = dict(error_bound=None, energy_tol=None)
CASES = {"henon_heiles": (HenonHeiles(), 3, 0.5), "fpu": (FPU(3, 50.0), 4, 0.01)}


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("s", [1, 2, 3])
def test_polynomial_hamiltonian_conserved_exactly(name, s):
    system, nu, h = CASES[name]
    y0 = system.initial_state()
    exact = HBVM.for_polynomial_degree(nu, s)
    assert exact.k == max(s, -(-nu * s // 2))
    res = integrate(exact, system, y0, h, STEPS, sample_every=10, fast=True, **NO_CHECK)
    gauss = integrate(HBVM(s, s), system, y0, h, STEPS, sample_every=10, fast=True, **NO_CHECK)
    assert res.path == gauss.path == "compiled-separable" and res.steps == STEPS
    assert res.max_energy_error <= 1e-13, res.max_energy_error
    assert _drift_over_run(res) <= 1e-13
    assert gauss.max_energy_error >= 1e3 * res.max_energy_error, (gauss.max_energy_error, res.max_energy_error)
    # the numpy path takes the same steps (checked on the first 50)
    slow = integrate(exact, system, y0, h, 50, sample_every=10, fast=False, **NO_CHECK)
    assert np.max(np.abs(slow.y - res.y[:6])) <= 1e-12


# Known weakness: the full form (y' = J grad H, the form of REBOUND's own accelerations in
# hbvm_md.rebound) drifts linearly on a cubic H that its quadrature integrates exactly, the
# separable form does not; rate per step (median of 5 perturbed starts, 4000 steps, all of one
# sign), HBVM(12, 6) h = 0.5: 5.3e-18 (7.8e-18 before the stages kept I_lo gamma on average),
# h = 0.25: 1.3e-18; HBVM(5, 3) h = 0.5: 1.5e-18.  Located (exact arithmetic on each step): the
# iterations leave out the coefficients' low parts and the polish adds them (W_lo F: the same
# sign every step) after the stages were evaluated, so the stages lie off the final path by
# h I_s times that; the full form's stages depend on gamma at order h (the separable form's at
# h^2), hence a drift of order h^2 a step (4.7e-18 of the 7.8e-18).  Iterating the full form
# with the low parts and the compensated projection removes it (5.3e-19, the rest the stop
# rule's truncation, same sign) but made the step 27 % dearer (Kepler's Poincare transform,
# HBVM(6, 3)); tests/test_rebound_forces.py::test_full_form_h_does_not_drift_with_many_nodes
# is the same defect.
@pytest.mark.xfail(strict=True, reason="known weakness: the full form drifts linearly (order "
                   "h^2 a step) on a polynomial H it integrates exactly; see the comment above")
def test_full_form_conserves_a_polynomial_hamiltonian_without_drift():
    """Hénon-Heiles (degree 3) in the full form with HBVM(12, 6), exact for it (k >= 3 s / 2):
    no linear drift beyond the round-off scatter, as the separable form keeps
    (test_polynomial_hamiltonian_conserved_exactly).  Measured (4000 steps): drift 3e-14 over
    the run, scatter 6e-16."""
    hh = HenonHeiles()
    res = integrate(HBVM(12, 6), hh, hh.initial_state(), 0.5, 4000, sample_every=10,
                    form="full")
    assert res.path.endswith("full")
    assert _drift_over_run(res) <= 5 * _scatter(res) + 2e-15, (_drift_over_run(res),
                                                                _scatter(res))


def test_gauss_conserves_angular_momentum():
    """Gauss (k = s) conserves quadratic invariants: Kepler's angular momentum to round-off,
    while HBVM(k > s, s) (not symplectic) does not."""
    kep = Kepler(0.6)
    y0 = kep.initial_state()
    h = 2 * np.pi / 100
    for s in (1, 2, 3):
        gauss = integrate(HBVM(s, s), kep, y0, h, 10_000, sample_every=10, fast=True,
                          **NO_CHECK)
        L = kep.angular_momentum(gauss.y)
        assert np.max(np.abs(L - L[0])) / abs(L[0]) <= 1e-13, s
    hb = integrate(HBVM(4, 2), kep, y0, h, 10_000, sample_every=10, fast=True)
    L = kep.angular_momentum(hb.y)
    assert np.max(np.abs(L - L[0])) / abs(L[0]) > 1e-10


@pytest.mark.parametrize("k,s,bound", [(2, 2, 5e-6), (3, 3, 1e-8), (6, 3, 1e-13), (8, 4, 1e-13)])
def test_kepler_energy_bounded_without_drift(k, s, bound):
    """100 periods of Kepler e = 0.6 at h = 2 pi / 200: the error is bounded (per-method bound,
    measured Gauss errors 1.2e-6 (s = 2) and 2.2e-9 (s = 3)) and shows no linear drift."""
    kep = Kepler(0.6)
    res = integrate(HBVM(k, s), kep, kep.initial_state(), 2 * np.pi / 200, 20_000, sample_every=20)
    assert res.max_energy_error <= bound
    scatter = _scatter(res)
    # At round-off (k = 6, 8) the error is a random walk of a few ulps of H0 = -1/2: the line
    # fitted through it has a slope too, of either sign.  Measured over 1e-14 perturbations of
    # y0: |drift over the run| up to 5.8e-15 (HBVM(6, 3), (8, 4), (12, 4)).  A systematic bias of
    # 1e-18 a step, the size of the coefficient-rounding drift once found in the separable step,
    # would give 2e-14.
    assert _drift_over_run(res) <= 5 * scatter + 1e-14, (_drift_over_run(res), scatter)


@pytest.mark.slow
def test_kepler_million_steps_no_drift():
    """10^6 steps (5000 periods) of Kepler e = 0.6, HBVM(6, 3) at h = 2 pi / 200, compiled path,
    from 8 starts (y0 scaled by 1 + r 1e-14).

    At round-off the energy error of one run is a random walk, and the line fitted through one
    walk has a slope of either sign, often several times the scatter about it: one run cannot
    tell a drift from a walk.  A bias has the same sign from every start: the mean of the
    signed drifts over the run is held to three standard errors (plus 5e-15).  Measured: max
    relative energy error median 1.1e-14, drift 0.6e-15 +- 3.1e-15 (mean +- standard error, 16
    starts); an experimental stop rule that accepted the polish up to 1/16 ulp from the fixed
    point gave 5e-14 to 7e-14 from every start, which this rejects."""
    kep = Kepler(0.6)
    runs = [integrate(HBVM(6, 3), kep, kep.initial_state() * (1 + r * 1e-14), 2 * np.pi / 200,
                      1_000_000, sample_every=100, fast=True) for r in range(8)]
    for res in runs:
        assert res.path == "compiled-separable" and res.steps == 1_000_000
        assert res.y.shape == (10_001, 4)
        assert res.max_energy_error <= 5e-14
        assert _scatter(res) <= 2e-14
    drifts = [_signed_drift(res) for res in runs]
    mean, sem = np.mean(drifts), np.std(drifts, ddof=1) / np.sqrt(len(drifts))
    assert abs(mean) <= 3 * sem + 5e-15, drifts
    res = runs[0]
    # HBVM(6, 3) does not conserve angular momentum exactly, but its error stays bounded
    # (measured 8.1e-11, the same at the end of the run as after one period)
    L = np.abs(kep.angular_momentum(res.y) - kep.angular_momentum(res.y[0])) / abs(kep.angular_momentum(res.y[0]))
    assert np.max(L) <= 1e-9
    assert np.max(L[-200:]) <= 1.5 * np.max(L[:200]) + 1e-14


def test_drift_detector_can_fail():
    """The drift check is not vacuous: an energy error growing linearly is flagged."""
    kep = Kepler(0.6)
    res = integrate(HBVM(6, 3), kep, kep.initial_state(), 2 * np.pi / 200, 2_000, sample_every=20)
    res.energy = res.energy + 1e-12 * res.t        # a synthetic drift of 1e-12 per unit time
    assert _drift_over_run(res) > 5 * _scatter(res)
