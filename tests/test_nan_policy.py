"""A force that is not finite once has one policy from the first step on (issue 47, item 7):
the step reports it (solver="auto" switches to Newton for the step), in the first step as in
a later one; the first stack's row check used to take the nan for rows mixed up (ValueError)."""
import numpy as np
import pytest

from integrators import HBVM, Stepper
from systems.base import SeparableSystem


class _OnceNan(SeparableSystem):
    dim = 1
    polynomial_degree = None

    def __init__(self, bad_call):
        self.masses = np.ones(1)
        self.calls = 0
        self.bad_call = bad_call

    def potential(self, q):
        q = np.asarray(q, dtype=float)
        return 0.5 * np.sum(q * q, axis=-1)

    def forces(self, q):
        self.calls += 1
        out = -np.asarray(q, dtype=float)
        if self.calls == self.bad_call:
            out = out * np.nan
        return out


@pytest.mark.parametrize("bad_call", [1, 2, 12])   # (the stack, its first row alone, later)
def test_a_nan_force_switches_to_newton_in_the_first_step_as_later(bad_call):
    sys_ = _OnceNan(bad_call)
    st = Stepper(HBVM(3, 2), sys_, [1.0, 0.0], solver="auto", fast=False)
    for _ in range(5):
        st.step(0.1)
    assert st.solver_switches == 1 and np.all(np.isfinite(st.y))
