"""Options of adaptive runs given to a fixed-step run (issue 37, item 6): each refused naming
the argument and the fix, where they used to be accepted and ignored."""
from __future__ import annotations

import numpy as np
import pytest

from integrators import HBVM, integrate
from systems import Kepler

KEP = Kepler(0.6)

# argument, value, what the fix must say
OPTIONS = [
    ("t_end", 3.0, r"give steps = round\(\(t_end - t0\) / h\), or adaptive=True"),
    ("sample_times", [0.5, 1.0], r"give sample_every .* or adaptive=True to land on each time"),
    ("epsilon", 1e-6, r"pass adaptive=True, or leave it out"),
    ("min_dt", 1e-3, r"pass adaptive=True, or leave it out"),
]


@pytest.mark.parametrize("name,value,fix", OPTIONS, ids=[o[0] for o in OPTIONS])
def test_an_adaptive_option_given_to_fixed_steps_is_refused(name, value, fix):
    with pytest.raises(ValueError, match=rf"`{name}` is an option of adaptive runs; a fixed-step "
                                         rf"run \(adaptive=False\) would ignore it \(got "
                                         rf"{name}=.*\): .*{fix}"):
        integrate(HBVM(4, 2), KEP, KEP.initial_state(), 0.05, 10, **{name: value})


def test_the_same_options_run_adaptive_steps():
    """The control: with adaptive=True the same arguments are taken (epsilon's default when
    left out is DEFAULT_EPSILON)."""
    from integrators.engine import DEFAULT_EPSILON
    y0 = KEP.initial_state()
    res = integrate(HBVM(8, 4), KEP, y0, 0.05, adaptive=True, t_end=3.0, sample_times=[1.0],
                    epsilon=1e-6, min_dt=1e-9)
    assert res.t[-1] == 3.0 and 1.0 in res.t
    a = integrate(HBVM(8, 4), KEP, y0, 0.05, adaptive=True, t_end=3.0)
    b = integrate(HBVM(8, 4), KEP, y0, 0.05, adaptive=True, t_end=3.0, epsilon=DEFAULT_EPSILON)
    assert np.array_equal(a.y, b.y) and a.extra["epsilon"] == DEFAULT_EPSILON
