"""User models and stopped runs (issue 28): every model passes one shape check whatever its
class, and whatever stops a run the caller gets the committed steps.

Both sweeps are built from a table: a new case is one line of ``SHAPES`` or ``STOPS``.
"""
from __future__ import annotations

import re

import numpy as np
import pytest

from integrators import (HBVM, ConvergenceError, NonFiniteError, StepError, Stepper,
                         StepSizeError, UnresolvedStepError, integrate)
from systems import Kepler, NBody
from systems.base import HamiltonianSystem, SeparableSystem

KEP = Kepler(0.6)
Y0 = KEP.initial_state()
METHOD = HBVM(4, 2)
H = 0.05
STEPS = 30
T_END = 1.5


# -- models as users write them (numpy methods, no compiled kernels: the Python path) -----------
class _Faults:
    """What goes wrong, and when: ``faults[name] = (at, action)`` applies ``action`` to the result
    of the method ``name`` from its call number ``at`` on, or with ``at = "stack"`` from its
    first call on a stack of several rows (``action``: a function of the correct result that
    returns a wrong one, or raises)."""

    def _apply(self, name, x, value):
        self.calls[name] = self.calls.get(name, 0) + 1
        at, action = self.faults.get(name, (None, None))
        if at == "stack" and np.ndim(x) == 2 and len(x) > 1:
            self.faults[name] = at, action = self.calls[name], action
        if at is None or at == "stack" or self.calls[name] < at:
            return value
        return action(value)

    def _setup(self, faults):
        self.faults, self.calls = dict(faults or {}), {}


class SepModel(SeparableSystem, _Faults):
    """Kepler's problem as a SeparableSystem subclass (``forces``, ``potential``)."""
    dim = 2

    def __init__(self, faults=None):
        self.masses = np.ones(2)
        self._setup(faults)

    def potential(self, q):
        return self._apply("potential", q, KEP.potential(q))

    def forces(self, q):
        return self._apply("forces", q, KEP.forces(q))


class HamModel(HamiltonianSystem, _Faults):
    """Kepler's problem as a HamiltonianSystem subclass (``gradient``, ``energy``: full form)."""
    dim = 2

    def __init__(self, faults=None):
        self._setup(faults)

    def energy(self, y):
        return self._apply("energy", y, KEP.energy(y))

    def gradient(self, y):
        return self._apply("gradient", y, KEP.gradient(y))


class ScipyModel(_Faults):
    """Written the scipy way, no base class and no ``dim``: probed once by integrators.protocol
    (a fault from call 10 on passes the probe and appears mid-run)."""

    def __init__(self, faults=None):
        self._setup(faults)

    def energy(self, y):
        return self._apply("energy", y, float(KEP.energy(np.asarray(y))))

    def gradient(self, y):
        return self._apply("gradient", y, KEP.gradient(y))


class DuckModel(_Faults):
    """No base class, the separable members and ``stack_protocol = True`` (not probed)."""
    dim = 2
    stack_protocol = True

    def __init__(self, faults=None):
        self.masses = np.ones(2)
        self._setup(faults)

    def energy(self, y):
        return KEP.energy(y)

    def gradient(self, y):
        return KEP.gradient(y)

    def potential(self, q):
        return self._apply("potential", q, KEP.potential(q))

    def forces(self, q):
        return self._apply("forces", q, KEP.forces(q))


MODELS = {"SeparableSystem": SepModel, "HamiltonianSystem": HamModel, "scipy-style": ScipyModel,
          "duck-typed": DuckModel}

RUNS = {                           # how a run is made (each calls the model differently)
    "fixed": (HBVM(4, 2), dict(h=H, steps=STEPS)),                      # the step loop, one call
    "newton": (HBVM(4, 2), dict(h=H, steps=STEPS, solver="newton")),    # step by step, rhs probes
    "adaptive": (HBVM(8, 4), dict(h=H, t_end=T_END, adaptive=True)),    # step_adaptive (s = 2
}                                                                       # takes 1.5e5 steps here)


def _column(f):
    return f[..., :1]


def _summed(f):
    return np.sum(f, axis=0)


def _transposed(f):
    return np.asarray(f).T


def _flat(f):
    return np.ravel(f)


def _vector(v):
    return np.array([v, v])


def _complex(f):
    return f + 0j


def _first_row(f):
    return np.broadcast_to(np.asarray(f)[:1], np.shape(f))


# -- 1. wrong shapes -----------------------------------------------------------------------------
# model class, method, from call, wrong result, what the message must say it got
SHAPES = [
    ("SeparableSystem", "forces", 1, _column, r"got shape \(\d+, 1\)"),
    ("SeparableSystem", "forces", 1, _summed, r"got shape \(2,\)"),
    ("SeparableSystem", "forces", 1, _transposed, r"got shape \(2, \d+\)"),
    ("SeparableSystem", "forces", 1, _flat, r"got shape \(\d+,\)"),
    ("SeparableSystem", "forces", 12, _column, r"got shape \(\d+, 1\)"),       # mid-run
    ("SeparableSystem", "forces", 1, _complex, r"real numbers \(got dtype complex128\)"),
    ("SeparableSystem", "potential", 1, _vector, r"one real number .* \(got shape \(2,\)\)"),
    ("SeparableSystem", "potential", 5, _vector, r"one real number .* \(got shape \(2,\)\)"),
    ("HamiltonianSystem", "gradient", 1, _column, r"got shape \(\d+, 1\)"),
    ("HamiltonianSystem", "gradient", 1, _summed, r"got shape \(4,\)"),
    ("HamiltonianSystem", "gradient", 1, _transposed, r"got shape \(4, \d+\)"),
    # right shapes, mixed rows: caught on the first stack of several rows (square for HBVM(4, 2))
    ("HamiltonianSystem", "gradient", "stack", _transposed, r"mixes the rows|got shape \(4, 8\)"),
    ("SeparableSystem", "forces", "stack", _first_row, r"mixes the rows"),
    ("HamiltonianSystem", "energy", 1, _vector, r"one real number .* \(got shape \(2,\)\)"),
    ("scipy-style", "gradient", 10, _column, r"got shape \(\d+, 1\)"),
    ("scipy-style", "gradient", 10, _summed, r"got shape \(4,\)"),
    ("duck-typed", "forces", 1, _summed, r"got shape \(2,\)"),
    ("duck-typed", "forces", 12, _flat, r"got shape \(\d+,\)"),
]


@pytest.mark.parametrize("run", list(RUNS))
@pytest.mark.parametrize("cls,method,at,wrong,got", SHAPES,
                         ids=[f"{c}-{m}-{w.__name__[1:]}-from-{a}" for c, m, a, w, _ in SHAPES])
def test_wrong_shapes_are_refused_by_name_whatever_the_class(cls, method, at, wrong, got, run):
    model = MODELS[cls]({method: (at, wrong)})
    method_, kw = RUNS[run]
    with pytest.raises(ValueError, match=rf"`{method}` of {type(model).__name__} .*({got})") as err:
        integrate(method_, model, Y0, **kw)
    if method in ("forces", "gradient"):   # the shapes expected and given
        assert re.search(r"(must return shape \((\d+), (\d)\) for|on) a stack of shape "
                         r"\((\d+), (\d)\)", str(err.value)), err.value
    # raised mid-run, it stops the run like any exception from the model: the steps are kept
    res = err.value.result
    assert res.status == "failed" and res.message.startswith("ValueError: `")
    # nothing of the wrong results was committed: the samples are the right model's
    ref = integrate(method_, MODELS[cls](), Y0, **kw)
    n = len(res.t)        # (n = steps: the energy of the last committed step was refused)
    assert res.steps in (n - 1, n) and np.array_equal(res.y, ref.y[:n])


@pytest.mark.parametrize("run", list(RUNS))
@pytest.mark.parametrize("cls", list(MODELS))
def test_right_models_of_every_class_run_as_the_compiled_kepler(cls, run):
    """The control of the sweep above: the same classes, without a fault, finish with the
    compiled Kepler's numbers (to round-off: the Python and compiled kernels round apart)."""
    method, kw = RUNS[run]
    res = integrate(method, MODELS[cls](), Y0, **kw)
    ref = integrate(method, KEP, Y0, **kw)
    assert res.status == "finished" and res.path.startswith("python")
    if run == "adaptive":       # (round-off differences choose other steps: the same end)
        assert res.t[-1] == ref.t[-1] == T_END and np.max(np.abs(res.y[-1] - ref.y[-1])) < 1e-9
    else:
        assert res.t.shape == ref.t.shape and np.max(np.abs(res.y - ref.y)) < 1e-12


# -- 2. stopped runs ----------------------------------------------------------------------------
def _raises(exc_type, *args):
    def action(value):
        raise exc_type(*args)
    action.__name__ = exc_type.__name__
    return action


def _divide_by_zero(value):
    with np.errstate(divide="raise"):
        return value / np.zeros_like(value)


def _nan(value):
    return value * np.nan


def _singular(value):
    return np.linalg.solve(np.zeros((2, 2)), np.ones(2)) * value


def _head_on():
    """Two equal masses at rest: they fall onto each other at t = pi / 2 (for r0 = 2, G m = 1)."""
    nb = NBody([1.0, 1.0], positions=[[-1.0, 0, 0], [1.0, 0, 0]], velocities=np.zeros((2, 3)))
    return nb, nb.initial_state()


ALL = tuple(RUNS)
# id, model and y0, run options, exception, status, runs it applies to, samples lost (the last
# committed step's own sample when its energy raised)
STOPS = [
    ("user error in forces", lambda: SepModel({"forces": (40, _raises(RuntimeError, "model broke"))}),
     {}, RuntimeError, "failed", ALL, 0),
    ("numpy error in forces", lambda: SepModel({"forces": (40, _divide_by_zero)}),
     {}, FloatingPointError, "failed", ALL, 0),
    ("LinAlgError in gradient", lambda: HamModel({"gradient": (40, _singular)}),
     {}, np.linalg.LinAlgError, "failed", ALL, 0),
    ("Ctrl-C in forces", lambda: SepModel({"forces": (40, _raises(KeyboardInterrupt))}),
     {}, KeyboardInterrupt, "interrupted", ALL, 0),
    ("Ctrl-C in gradient", lambda: ScipyModel({"gradient": (40, _raises(KeyboardInterrupt))}),
     {}, KeyboardInterrupt, "interrupted", ALL, 0),
    # with the energy check off, the engine's 9th potential/energy call is a sample's: the
    # last committed step keeps no sample (the 10th call counted here: the first is
    # integrators.protocol's check that the function does not write into its argument)
    ("SystemExit in potential", lambda: SepModel({"potential": (10, _raises(SystemExit, 3))}),
     dict(energy_tol=None), SystemExit, "interrupted", ALL, 1),
    ("user error in energy", lambda: HamModel({"energy": (10, _raises(ArithmeticError, "no"))}),
     dict(energy_tol=None), ArithmeticError, "failed", ALL, 1),
    # with the default energy check, it is the check's inside a step: that step is not committed
    ("SystemExit in checked potential", lambda: SepModel({"potential": (10, _raises(SystemExit, 3))}),
     {}, SystemExit, "interrupted", ALL, 0),
    ("user error in checked energy", lambda: HamModel({"energy": (10, _raises(ArithmeticError, "no"))}),
     {}, ArithmeticError, "failed", ALL, 0),
    ("nan in forces", lambda: SepModel({"forces": (40, _nan)}), {}, NonFiniteError, "failed",
     ("fixed", "newton"), 0),
    ("nan in forces", lambda: SepModel({"forces": (40, _nan)}), {}, NonFiniteError, "failed",
     ("adaptive",), 0),          # (at once: the forces at the step's start are nan too)
    ("no convergence", SepModel, dict(max_iter=2, solver="fixed_point"), ConvergenceError,
     "failed", ("fixed",), 0),
    ("energy check", SepModel, dict(energy_tol=1e-300), UnresolvedStepError, "failed",
     ("fixed", "newton"), 0),
    ("head-on collision", _head_on, dict(t_end=5.0), StepSizeError, "failed", ("adaptive",), 0),
]
STOP_CASES = [pytest.param(row, run, id=f"{row[0]}-{run}") for row in STOPS for run in row[5]]


def _build(make):
    made = make()
    return made if isinstance(made, tuple) else (made, Y0)


@pytest.mark.parametrize("row,run", STOP_CASES)
def test_stopped_runs_reach_the_caller_with_their_committed_steps(row, run):
    name, make, options, exc, status, _, lost = row
    model, y0 = _build(make)
    method, kw = RUNS[run]
    kw = {**kw, **options}
    with pytest.raises(exc) as err:
        integrate(method, model, y0, **kw)
    res = err.value.result
    assert res is not None and res.status == status
    assert res.message.startswith(f"{exc.__name__}: " if not issubclass(exc, StepError) else "HBVM step")
    # one sample a committed step (sample_every=1), the start included, but a last step whose
    # energy could not be evaluated
    assert len(res.t) == len(res.y) == len(res.energy) == res.steps + 1 - lost
    assert res.y.shape[1:] == y0.shape and np.all(np.isfinite(res.energy))
    # the same numbers as a run that was not stopped, counters included (the stopped step's
    # evaluations are not counted: they belong to no committed step)
    ref_model, _ = _build(make)
    ref_model.faults = {}
    if run == "adaptive":
        try:
            ref = integrate(method, ref_model, y0, **kw)
        except StepError as e:
            ref = e.result
        n = len(res.t)
        assert np.array_equal(res.t, ref.t[:n]) and np.array_equal(res.y, ref.y[:n])
        assert np.array_equal(res.energy, ref.energy[:n])
    elif res.steps > 0:
        ref = integrate(method, ref_model, y0, **{**kw, "steps": res.steps, "energy_tol": None})
        n = len(res.t)
        assert np.array_equal(res.t, ref.t[:n]) and np.array_equal(res.y, ref.y[:n])
        assert np.array_equal(res.energy, ref.energy[:n])
        assert (res.nfev, res.iterations, res.newton_steps) == (ref.nfev, ref.iterations,
                                                                ref.newton_steps)
    if not issubclass(exc, StepError) and hasattr(err.value, "__notes__"):
        assert any(".result" in n for n in err.value.__notes__)


def test_the_collision_stops_where_the_steps_stop_resolving_the_time():
    """The issue's case: the steps into a head-on collision shrank to h = 0 and the run ended
    in `h must be a nonzero finite number (got h=0.0)`, with no result."""
    nb, y0 = _head_on()
    with pytest.raises(StepSizeError, match=r"fell below the smallest step that changes t .*"
                                             r"no longer changes t=2\.22144146907") as err:
        integrate(HBVM(8, 4), nb, y0, 0.1, adaptive=True, t_end=5.0)
    res = err.value.result
    t_fall = np.pi / 2 * np.sqrt(2.0)          # free fall from r0 = 2 with G (m1 + m2) = 2
    assert abs(res.t[-1] - t_fall) < 1e-13
    assert abs(err.value.h) <= 4 * np.finfo(float).eps * res.t[-1]


def test_stepper_status_follows_the_last_step():
    """`status` is "failed" after a failed step or an exception from the model, and "running"
    again after a later step succeeds; the failed attempts leave state and counters as before."""
    model = SepModel()
    st = Stepper(HBVM(4, 2), model, Y0, solver="fixed_point")
    st.step(H)
    y1, counters = st.y, st.counters.copy()
    model.faults = {"forces": (model.calls["forces"] + 2, _raises(RuntimeError, "once"))}
    with pytest.raises(RuntimeError, match="once"):
        st.step(H)                      # the 2nd forces call of the 2nd step
    assert st.status == "failed" and np.array_equal(st.y, y1)
    assert np.array_equal(st.counters, counters)
    model.faults = {}
    st.step(H)
    assert st.status == "running"
    with pytest.raises(ConvergenceError):
        st.step(2.0)
    assert st.status == "failed"
    st.step(H)
    assert st.status == "running" and st.nsteps == 3
    with pytest.raises(KeyboardInterrupt):
        model.faults = {"forces": (model.calls["forces"] + 1, _raises(KeyboardInterrupt))}
        st.step(H)
    assert st.status == "interrupted"



class _Alarm(KeyboardInterrupt):
    """Ctrl-C as a signal delivers it: between any two bytecodes of the Python step."""


@pytest.mark.parametrize("run", ["fixed", "adaptive"])
def test_a_signal_anywhere_in_a_python_run_keeps_the_committed_steps(run):
    """A KeyboardInterrupt raised by a signal handler lands wherever the Python step is (in the
    iteration, between the writes of a commit, in a sample): the result still holds whole
    committed steps, bit for bit those of an uninterrupted run."""
    signal = pytest.importorskip("signal")
    if not hasattr(signal, "setitimer"):
        pytest.skip("no interval timer on this platform")

    def alarm(signum, frame):
        raise _Alarm

    method, kw = RUNS[run]
    kw = {**kw, "steps": 20000} if run == "fixed" else {**kw, "t_end": 300.0}
    # numba compiles the pieces the Python step calls on their first call, and a signal that
    # lands in the compiler's callbacks is lost (numba's, not ours): compile them first
    integrate(method, SepModel(), Y0, **{**kw, "steps": 3} if run == "fixed" else {**kw, "t_end": 0.2})
    old = signal.signal(signal.SIGALRM, alarm)
    try:
        for delay in (0.0007, 0.0019, 0.0031, 0.0057, 0.0093, 0.0173):
            armed = []

            def arm(value):       # the timer starts with the run (not while the step is built)
                if not armed:
                    armed.append(signal.setitimer(signal.ITIMER_REAL, delay))
                return value
            try:
                # (a signal that lands inside numba's dispatch or boxing can come out of numba
                # as another exception, SystemError or KeyError: numba's; the run is stopped
                # and its steps kept all the same)
                with pytest.raises(BaseException) as err:
                    integrate(method, SepModel({"forces": (1, arm)}), Y0, **kw)
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            res = err.value.result
            interrupted = isinstance(err.value, _Alarm)
            assert res.status == ("interrupted" if interrupted else "failed")
            assert res.steps >= len(res.t) - 1 >= 0
            n = len(res.t)
            if run == "fixed":
                ref = integrate(method, SepModel(), Y0, **{**kw, "steps": n - 1})
            else:
                # (a run to a later time takes the same steps up to there: landing on res.t[-1]
                # exactly would take another last step)
                ref = integrate(method, SepModel(), Y0, **{**kw, "t_end": float(res.t[-1]) + 1.0})
            assert np.array_equal(res.t, ref.t[:n]) and np.array_equal(res.y, ref.y[:n])
            assert np.array_equal(res.energy, ref.energy[:n])
    finally:
        signal.signal(signal.SIGALRM, old)
