"""A user's system as the engine needs it: checked once, adapted where it is written the scipy way.

The engine calls ``energy`` and ``gradient`` on stacks of states (the k stages of a step, the
samples of a run).  A user who wrote them for one state, as for ``scipy.integrate.solve_ivp``,
would get wrong numbers silently (numpy broadcasts a stack through ``np.sum`` or ``y[:dim]``).
So, like scipy, which wraps the user's function once and checks its output on the first call,
:func:`adapt_system` looks at the system once, before the first step:

* ``dim`` may be left out: it is ``len(y0) // 2``;
* ``energy`` is called per state unless the system declares ``batched_energy = True`` or a
  stack of states gives the same values as single calls (then the stack route is used);
* ``gradient`` must be batched: on a stack of 3 distinct states (3 is never 2m, so a transposed
  result cannot pass) it must return shape (3, 2m), finite, row i equal to the gradient of state
  i alone; otherwise a ``ValueError`` names ``gradient`` and the shapes.

A system with ``stack_protocol = True`` (set by :class:`systems.base.HamiltonianSystem`, so all
of :mod:`systems`) declares all of this and passes through unchanged, unprobed, at no cost per
call.  (Whatever the class, the step compares each result of a model run as Python with the
shape it needs: :meth:`integrators.engine.Binding._python_kernels`.)
"""
from __future__ import annotations

import numpy as np

_PROBES = 3          # states in the probe stack: never equal to 2m, so a transpose shows
_AGREE = 1e-9        # relative agreement of a stacked and a single evaluation (round-off)


def adapt_system(system, y0):
    """The system the engine integrates: ``system`` itself when it follows the protocol of
    :mod:`systems.base`, else a thin wrapper that adds ``dim`` or evaluates ``energy`` per state.

    Parameters
    ----------
    system : object
        With ``energy(y)`` and ``gradient(y)``; ``dim`` optional.
    y0 : ndarray, shape (2m,)
        The initial state (float); the probes are small perturbations of it.

    Returns
    -------
    object
        ``system`` or a wrapper (every other attribute is the system's own).

    Raises
    ------
    TypeError
        ``energy`` or ``gradient`` missing.
    ValueError
        No ``dim`` and y0 of odd length; ``energy`` not a number per state; ``gradient`` that
        does not return one finite gradient per row of a stack.
    """
    if isinstance(system, _Adapted):
        return system
    _check_no_writes(system, np.asarray(y0, dtype=float))
    if getattr(system, "stack_protocol", False) is True:
        return system
    if not (callable(getattr(system, "energy", None)) and callable(getattr(system, "gradient", None))):
        raise TypeError(f"`system` must offer `energy(y)` and `gradient(y)` (and may give `dim`) "
                        f"(got {type(system).__name__}); see systems.base")
    y0 = np.asarray(y0, dtype=float)
    dim = getattr(system, "dim", None)
    if dim is None:
        if y0.ndim != 1 or y0.size % 2:
            raise ValueError(f"`y0` must hold (q, p) with as many momenta as positions, an even "
                             f"length, when the system has no `dim` (got shape {y0.shape}); give "
                             f"{type(system).__name__} a `dim` or pass y0 = concatenate([q, p])")
        dim = y0.size // 2
    if isinstance(dim, bool) or not isinstance(dim, (int, np.integer)) or dim < 1:
        # (before the probes: a system of no degree of freedom has no state to probe with)
        given = hasattr(system, "dim")
        raise ValueError(f"`dim` of {type(system).__name__} must be a positive integer, the "
                         f"number of degrees of freedom (got dim={dim!r}"
                         f"{'' if given else ', from y0 of shape ' + str(y0.shape)}); set it to "
                         "len(q), half the length of the state (q, p), and pass a y0 of that many "
                         "positions and momenta")
    if y0.shape != (2 * dim,):
        return system        # check_state names the shape mismatch
    Y = _probe_states(y0)
    batched = getattr(system, "batched_energy", None)
    if batched is None:
        batched = _energy_batches(system, Y)
    _check_gradient(system, Y)
    if batched and hasattr(system, "dim"):
        return system
    return _Adapted(system, int(dim), bool(batched))


#: modules whose systems are this project's own (tested not to write into their arguments;
#: the ASE adapter's calls are calculator calls, counted, and not made twice)
_OWN = ("systems.", "integrators.", "hbvm_md.")


def _check_no_writes(system, y0: np.ndarray) -> None:
    """ValueError when the energy of a user's system writes into the array it is given.

    The engine hands ``energy`` and ``potential`` its own state (no copy a call), so a
    function that works in place (``q *= s``, ``y[0] = ...``) moves the run itself, silently.
    One of them is called once here on a copy of y0 and the copy compared bit for bit
    afterwards (one call more of the user's function a run).""" 
    if type(system).__module__.startswith(_OWN) or y0.ndim != 1 or y0.size == 0:
        return
    dim = getattr(system, "dim", None)
    if not (isinstance(dim, (int, np.integer)) and not isinstance(dim, bool)
            and 0 < dim and 2 * dim == y0.size):
        dim = y0.size // 2 if y0.size % 2 == 0 else None
    # one call: a separable system's potential (its energy calls it), else its energy
    if dim and callable(getattr(system, "forces", None)) and hasattr(system, "masses"):
        calls = [("potential", y0[:dim])]
    else:
        calls = [("energy", y0)]
    for method, arg in calls:
        fn = getattr(system, method, None)
        if not callable(fn):
            continue
        given = np.array(arg)
        try:
            fn(given)
        except Exception:  # noqa: BLE001 - its own errors are named by the checks that follow
            continue
        if not np.array_equal(given, arg, equal_nan=True):
            raise ValueError(
                f"`{method}` of {type(system).__name__} writes into the array it is given (the "
                f"{'state' if method in ('energy', 'gradient') else 'positions'} changed during "
                "the call): the engine passes its own state and stages, so the run would move "
                "with it. Compute on a copy (`q = np.array(q)`) or without in-place operations "
                "(`q = q * s`, not `q *= s`)")


def _probe_states(y0: np.ndarray) -> np.ndarray:
    """y0 and two perturbations of it with unequal, non-symmetric offsets (fixed seed)."""
    rng = np.random.default_rng(20240521)
    scale = 1e-3 * (1.0 + np.abs(y0))
    offsets = rng.uniform(0.5, 1.0, size=(_PROBES, y0.size)) * rng.choice([-1, 1], (_PROBES, y0.size))
    offsets[0] = 0.0
    return y0 + scale * offsets


def _close(a, b) -> bool:
    return bool(np.all(np.abs(a - b) <= _AGREE * (np.max(np.abs(b)) + 1e-300)))


def _energy_batches(system, Y: np.ndarray) -> bool:
    """True when ``energy`` on the stack Y equals single calls row by row."""
    name = type(system).__name__
    try:
        single = np.array([float(np.asarray(system.energy(y)).reshape(())) for y in Y])
    except (TypeError, ValueError) as err:
        raise ValueError(f"`energy` of {name} must return one number for a state of shape "
                         f"{Y[0].shape} ({err})") from None
    if not np.all(np.isfinite(single)):
        raise ValueError(f"`energy` of {name} is not finite near y0 (got {single[0]!r} at y0)")
    try:
        stacked = np.asarray(system.energy(Y), dtype=float)
    except Exception:      # noqa: BLE001 - a function written for one state may fail on a stack
        return False
    return stacked.shape == (len(Y),) and _close(stacked, single)


def _check_gradient(system, Y: np.ndarray) -> None:
    name = type(system).__name__
    n, d2 = Y.shape
    single = [np.asarray(system.gradient(y), dtype=float) for y in Y]
    if single[0].shape != (d2,):
        raise ValueError(f"`gradient` of {name} must return shape ({d2},) for one state of shape "
                         f"({d2},) (got shape {single[0].shape})")
    try:
        G = np.asarray(system.gradient(Y), dtype=float)
    except Exception as err:   # noqa: BLE001 - numpy's broadcast errors do not name gradient
        raise ValueError(f"`gradient` of {name} must accept a stack of states of shape ({n}, {d2}) "
                         f"(the k stages of a step) and return shape ({n}, {d2}); it raised "
                         f"{type(err).__name__}: {err}") from None
    if G.shape != (n, d2):
        raise ValueError(f"`gradient` of {name} must return shape ({n}, {d2}) for a stack of states "
                         f"of shape ({n}, {d2}), one gradient per row (got shape {G.shape})")
    if not np.all(np.isfinite(G)):
        raise ValueError(f"`gradient` of {name} is not finite near y0")
    for i in range(n):
        if not _close(G[i], single[i]):
            raise ValueError(f"`gradient` of {name} on a stack of shape ({n}, {d2}) returned row "
                             f"{i} != gradient(state {i}) (max difference "
                             f"{np.max(np.abs(G[i] - single[i])):.3g}): it mixes the states of a "
                             f"stack; index the last axis (y[..., :dim], not y[:dim]) and return "
                             f"one gradient per row, shape (n, {d2})")


class _Adapted:
    """The user's system with ``dim`` added and ``energy`` evaluated per state when needed."""

    def __init__(self, system, dim: int, batched_energy: bool):
        self._system, self.dim, self._batched = system, dim, batched_energy

    def __getattr__(self, name):
        return getattr(self._system, name)

    def energy(self, y):
        if self._batched:
            return self._system.energy(y)
        y = np.asarray(y, dtype=float)
        if y.ndim == 1:
            return float(np.asarray(self._system.energy(y)).reshape(()))
        flat = y.reshape(-1, y.shape[-1])
        return np.array([float(np.asarray(self._system.energy(r)).reshape(())) for r in flat]
                        ).reshape(y.shape[:-1])

    def __repr__(self) -> str:
        return f"adapted({self._system!r})"
