"""Bad input of issue 47, item 8, refused by name: a system of no degree of freedom, a demo
shorter than a day, and a user function that writes into the state it is given."""
import numpy as np
import pytest

from hbvm_md.cli import main
from hbvm_md.reports.rebound_comparison import _slope
from integrators import HBVM, integrate
from systems.base import SeparableSystem


class Empty:
    dim = 0

    def energy(self, y):
        return 0.0

    def gradient(self, y):
        return np.zeros_like(y)


def test_a_system_of_no_degree_of_freedom_is_named_by_dim():
    with pytest.raises(ValueError, match=r"`dim` of Empty must be a positive integer.*got dim=0"):
        integrate(HBVM(3, 2), Empty(), np.zeros(0), 0.1, 5)


def test_demo_shorter_than_a_day_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["demo", "--t-end", "1e-300", "--quick"])
    assert exit_.value.code == 2
    assert "--t-end: expected a run of at least 1 day, got '1e-300'" in capsys.readouterr().err


def test_drift_slope_of_a_very_short_run_is_finite():
    # (the fit in unscaled time met numpy's LinAlgError at 1e-300 days)
    ts = np.linspace(5e-303, 1e-300, 200)
    err = 1e-16 * (ts - ts[0]) / (ts[-1] - ts[0])          # 1e-16 over the run
    assert _slope(ts, err) == pytest.approx(1e-16 / (ts[-1] - ts[0]), rel=1e-9)
    assert _slope(np.linspace(0.0, 10.0, 11), 2.0 * np.arange(11.0)) == pytest.approx(0.2 * 10)


class Spring(SeparableSystem):
    dim = 1
    masses = np.ones(1)

    def potential(self, q):
        return 0.5 * np.sum(q * q, axis=-1)

    def forces(self, q):
        return -np.array(q)


class InPlace(Spring):
    def potential(self, q):
        v = 0.5 * np.sum(q * q, axis=-1)
        q *= 1.0000001            # the mistake: the engine's own state moves with it
        return v


class Copied(Spring):
    def potential(self, q):
        q = np.array(q)           # the way out the message gives
        v = 0.5 * np.sum(q * q, axis=-1)
        q *= 1.0000001
        return v


def test_a_potential_that_writes_into_its_input_is_refused_and_a_copy_runs():
    y0 = np.array([1.0, 0.0])
    with pytest.raises(ValueError, match=r"`potential` of InPlace writes into the array it is "
                                         r"given.*Compute on a copy"):
        integrate(HBVM(3, 2), InPlace(), y0, 0.1, 20)
    clean = integrate(HBVM(3, 2), Spring(), y0, 0.1, 20)
    assert np.array_equal(integrate(HBVM(3, 2), Copied(), y0, 0.1, 20).y, clean.y)
