"""The hard-case suite at quick size: each case asserts its numbers."""
import numpy as np
import pytest

from hbvm_md.reports import hard_cases as hc
from integrators import HBVM, ConvergenceError, Stepper
from systems import HenonHeiles


def test_stiff_fpu_newton_takes_over_and_energy_stays_exact():
    rep = hc.stiff_fpu(quick=True)
    f = rep.facts
    for omega in (50.0, 1000.0):
        assert f["newton_took_over"][(omega, 0.5)] is False        # fixed point suffices
        assert f["newton_took_over"][(omega, 2.0)] is True          # it stops converging
        assert f["newton_took_over"][(omega, 10.0)] is True
        for hw in (0.5, 2.0, 10.0):
            assert f["hbvm_finished"][(omega, hw)]
            assert f["hbvm_energy"][(omega, hw)] < 1e-11
        assert f["verlet_finished"][(omega, 0.5)] and f["verlet_energy"][(omega, 0.5)] < 0.05
        assert not f["verlet_finished"][(omega, 2.0)]               # unstable beyond h omega = 2
        assert not f["verlet_finished"][(omega, 10.0)]
    assert "Newton took over" in rep.table()


def test_eccentric_kepler_poincare_against_fixed_and_ias15():
    rep = hc.eccentric_kepler(quick=True)
    for e in (0.9, 0.99):
        fx, pc, ias = rep.facts[e]["fixed"], rep.facts[e]["poincare"], rep.facts[e]["ias15"]
        assert pc["energy_error"] < 1e-12
        assert pc["steps"] * 10 <= fx["steps"]
        assert pc["solution_error"] < 2 * fx["solution_error"]
        assert ias["energy_error"] < 1e-12
    # at e = 0.99 fixed stepping with 100x more steps is still far less accurate
    assert rep.facts[0.99]["poincare"]["solution_error"] < 1e-3 * rep.facts[0.99]["fixed"]["solution_error"]


def test_close_encounter_fixed_step_peers_lose_the_energy_hbvm_does_not_silently():
    rep = hc.close_encounter(quick=True)
    f = rep.facts
    assert f["min_distance"] < f["hill_radius"]
    assert f["ias15"] < 1e-12
    for spo in (200, 2000):
        assert f[f"whfast {spo}"] > 1e-3 and f[f"leapfrog {spo}"] > 1e-3
    # HBVM at a fixed step never returns a silently wrong energy: it keeps H (each step within
    # the driver's energy_tol = 1e-10) or stops with ConvergenceError / UnresolvedStepError (inf).
    # Here the planets pass 4e-4 apart at relative speed 3, within half a step of P/20000, so
    # every step size tried stops cleanly (P/200000 resolves it: test_rebound_driver).
    for spo in (200, 2000, 20000):
        assert f[f"hbvm {spo}"] == np.inf or f[f"hbvm {spo}"] < 1e-8
    assert f["hbvm 20000"] == np.inf
    notes = {o.setting: o.note for o in rep.outcomes if o.method.startswith("HBVM")}
    assert "UnresolvedStepError" in notes["dt=P/20000"], notes


def test_chaotic_henon_heiles_energy_exact():
    rep = hc.chaotic_henon_heiles(quick=True)
    f = rep.facts
    assert not f["escaped"]
    assert f["hbvm_energy"] < 1e-14
    assert f["gauss_energy"] > 1e-10          # Gauss (k = s) does not conserve the cubic H
    assert f["verlet_energy"] > 1e-4
    assert f["dop853_energy"] > 1e-12


def test_steps_too_large_raise_cleanly_never_silently_wrong():
    rep = hc.step_too_large(quick=True)
    f = rep.facts
    # (h = 1 misses more than a thousandth of its motion a step: refused by the step's own
    # error check since issue 46, where it used to conserve H and pass)
    assert f["raised"] == {0.5: False, 1.0: True, 2.0: True, 3.0: True, 5.0: True}
    assert all(err < 1e-14 for err in f["energy"].values())
    assert f["state_untouched"]


def test_convergence_error_message_and_state():
    y0 = hc.henon_heiles_start()
    st = Stepper(HBVM(3, 2), HenonHeiles(y0), y0)
    with pytest.raises(ConvergenceError, match=r"h=3 at t=0 did not converge: fixed_point iteration"):
        st.step(3.0)
    assert np.array_equal(st.y, y0) and st.t == 0.0 and st.nsteps == 0


def test_kepler_exact_returns_to_start_and_conserves_energy():
    for e in (0.6, 0.99):
        y = hc.kepler_exact(e, np.array([0.0, 1.0, 2 * np.pi * 3]))
        assert np.allclose(y[0], y[2], atol=1e-12)
        H = 0.5 * np.sum(y[:, 2:] ** 2, axis=1) - 1 / np.hypot(y[:, 0], y[:, 1])
        assert np.allclose(H, -0.5, atol=1e-12)


def test_unknown_case_is_named():
    with pytest.raises(ValueError, match="unknown hard case"):
        hc.run_all(quick=True, names=["nope"])
