"""Arguments that numpy or Python used to reject with a message that does not name them (issue
28): each now gets a ValueError/TypeError naming the argument, the value and what is accepted.
A new case is one line of ``CASES``."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from integrators import HBVM, Stepper, integrate
from systems import Kepler

KEP = Kepler(0.6)
Y0 = KEP.initial_state()
M = HBVM(6, 3)


def _run(**kw):
    return lambda: integrate(M, KEP, Y0, 0.1, 5, **kw)


def _adaptive(**kw):
    return lambda: integrate(M, KEP, Y0, 0.1, **{"adaptive": True, "t_end": 1.0, **kw})


def _dynamics(timestep):
    def make():
        from ase.build import bulk

        from hbvm_md import HBVMDynamics
        from systems import PolynomialPairPotential
        atoms = bulk("Ar", "fcc", a=5.2, cubic=True)
        atoms.calc = PolynomialPairPotential([0.0, -2e-3, 1e-4])
        HBVMDynamics(atoms, timestep=timestep)
    return make


ENERGY_TOL = r"`energy_tol` must be 'auto', a positive number or None \(got energy_tol="
TIMES = r"`sample_times` must (be a sequence of|hold finite) times between t0=0\.0 and t_end=1\.0"
CASES = [   # id, the call, exception, message
    ("energy_tol='a'", _run(energy_tol="a"), ValueError, ENERGY_TOL + r"'a'\)"),
    ("energy_tol=True", _run(energy_tol=True), ValueError, ENERGY_TOL + r"True\)"),
    ("energy_tol=0", _run(energy_tol=0), ValueError, ENERGY_TOL + r"0\)"),
    ("energy_tol=nan", _run(energy_tol=float("nan")), ValueError, ENERGY_TOL + r"nan\)"),
    ("energy_tol adaptive", _adaptive(energy_tol="1e-10"), ValueError, ENERGY_TOL + r"'1e-10'\)"),
    ("Stepper energy_tol", lambda: Stepper(M, KEP, Y0, energy_tol=[1e-10]), ValueError,
     ENERGY_TOL + r"\[1e-10\]\)"),
    ("timestep='1'", _dynamics("1"), ValueError,
     r"`timestep` must be a nonzero finite number \(got timestep='1'\)"),
    ("timestep=None", _dynamics(None), ValueError,
     r"`timestep` must be a nonzero finite number \(got timestep=None\)"),
    ("sample_times=1.0", _adaptive(sample_times=1.0), ValueError,
     TIMES + r" \(got sample_times=1\.0\); for one time write \[1\.0\]"),
    ("sample_times nan", _adaptive(sample_times=[0.5, float("nan")]), ValueError,
     TIMES + r" \(got sample_times\[1\]=nan\)"),
    ("sample_times after t_end", _adaptive(sample_times=[0.5, 2.0]), ValueError,
     TIMES + r" \(got sample_times\[1\]=2\.0\): a sample the run never reaches"),
    ("sample_times strings", _adaptive(sample_times=["0.5"]), ValueError,
     TIMES + r" \(got sample_times\[0\]='0\.5'\)"),
    ("t_end='x'", _adaptive(t_end="x"), ValueError,
     r"`t_end` must be a finite time other than t0 with adaptive=True \(got t_end='x'\)"),
    ("t_end=None", _adaptive(t_end=None), ValueError, r"`t_end` must be .* \(got t_end=None\)"),
    ("t_end=t0", _adaptive(t_end=0.0), ValueError, r"`t_end` must be .* \(got t_end=0\.0\)"),
    ("Stepper.run_adaptive t_end", lambda: Stepper(M, KEP, Y0).run_adaptive(0.1, "x", 1e-5, 0.0),
     ValueError, r"`t_end` must be a finite time other than t=0\.0 \(got t_end='x'\)"),
    ("h='0.1'", lambda: integrate(M, KEP, Y0, "0.1", 5), ValueError,
     r"`h` must be a nonzero finite number \(got h='0\.1'\)"),
    ("t0='1'", _run(t0="1"), ValueError, r"`t0` must be a finite number \(got t0='1'\)"),
    ("complex y0", lambda: integrate(M, KEP, Y0 + 1e-3j, 0.1, 5), ValueError,
     r"`y0` must be real \(got a complex array\)"),
    ("string y0", lambda: integrate(M, KEP, ["1", "0", "0", "1"], 0.1, 5), ValueError,
     r"`y0` must be an array of numbers"),
    ("the class Kepler", lambda: integrate(M, Kepler, Y0, 0.1, 5), TypeError,
     r"`system` must be a system instance, not the class Kepler: pass Kepler\(\.\.\.\)"),
    ("the class, adaptive", lambda: M.integrate(Kepler, Y0, 0.1, adaptive=True, t_end=1.0),
     TypeError, r"not the class Kepler"),
    ("the class, Stepper", lambda: Stepper(M, Kepler, Y0), TypeError, r"not the class Kepler"),
]


@pytest.mark.parametrize("call,exc,match", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_arguments_are_named_with_what_is_accepted(call, exc, match):
    with warnings.catch_warnings():
        warnings.simplefilter("error")         # not numpy's ComplexWarning instead
        with pytest.raises(exc, match=match):
            call()


def test_sample_times_within_the_run_are_still_taken():
    """The checks refuse only what the run can never honour: t0 and t_end themselves, numpy
    arrays and unsorted times are fine."""
    res = integrate(M, KEP, Y0, 0.1, adaptive=True, t_end=1.0,
                    sample_times=np.array([0.7, 0.0, 0.25, 1.0]), sample_every=10 ** 6)
    assert list(res.t) == [0.0, 0.25, 0.7, 1.0]
    back = integrate(M, KEP, Y0, 0.1, adaptive=True, t0=1.0, t_end=0.0, sample_times=[0.25, 0.5],
                     sample_every=10 ** 6)
    assert list(back.t) == [1.0, 0.5, 0.25, 0.0]        # (backwards, 0.5 was dropped silently)


def test_hbvm_integrate_takes_every_argument_of_integrate():
    """The method and the module-level function are one: every parameter of `integrate`, given
    by name to `HBVM.integrate`, gives the same run bit for bit (the README's adaptive call
    failed with "missing 1 required positional argument: 'steps'")."""
    import inspect

    from integrators.engine import integrate as engine_integrate
    params = inspect.signature(engine_integrate).parameters
    defaults = {n: p.default for n, p in params.items() if p.default is not inspect.Parameter.empty}
    assert {"steps", "t0", "solver", "sample_every", "fast", "tol", "max_iter", "form", "energy_tol",
            "adaptive", "t_end", "epsilon", "min_dt", "sample_times"} <= set(defaults)
    fixed = {**defaults, "steps": 20, "energy_tol": 1e-10, "sample_every": 5}
    adaptive = {**defaults, "steps": None, "adaptive": True, "t_end": 2.0, "sample_times": [1.0]}
    for kw in (fixed, adaptive):
        a = M.integrate(KEP, Y0, 0.1, **kw)
        b = engine_integrate(M, KEP, Y0, 0.1, **kw)
        assert np.array_equal(a.t, b.t) and np.array_equal(a.y, b.y) and a.steps == b.steps
    # positionally as far as the function takes positions (h and steps; the options after them
    # are keyword-only, issue 46), and the same refusal of a position past them
    a = M.integrate(KEP, Y0, 0.1, 20, sample_every=5)
    b = engine_integrate(M, KEP, Y0, 0.1, 20, sample_every=5)
    assert np.array_equal(a.y, b.y) and len(a.t) == 5
    for call in (lambda: M.integrate(KEP, Y0, 0.1, 20, 0.0), lambda: engine_integrate(M, KEP, Y0, 0.1, 20, 0.0)):
        with pytest.raises(TypeError, match="positional argument"):
            call()


# REBOUND host (issue 28, item 5): REBOUND's own NoParticles since issue 25's registered host.
def test_rebound_simulation_without_particles_is_refused_by_name():
    """IAS15 raises REBOUND's NoParticles; HBVMIntegrator gave AttributeError: '_cstep'."""
    rebound = pytest.importorskip("rebound")
    from hbvm_md import HBVMIntegrator
    sim = rebound.Simulation()
    with pytest.raises((ValueError, rebound.NoParticles), match="[Pp]articles"):
        HBVMIntegrator(sim, dt=0.1)
        sim.integrate(1.0)
