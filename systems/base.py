"""The Hamiltonian-system protocol that the integrators understand.

A system is any object with

``energy(y)``
    H(y) for y of shape (2m,) (a float).  Written for one state it is called once per state;
    when it also takes a stack (n, 2m) and returns shape (n,) (detected once, or declared with
    ``batched_energy = True``) the stack is passed in one call.
``gradient(y)``
    grad H(y), same shape as y; must accept a stack (n, 2m) of states and return one gradient
    per row, shape (n, 2m) (the k stages of a step are evaluated in one call).  Checked once on
    a stack of 3 states; a mistake is a ``ValueError`` naming ``gradient`` and the shapes.
    Whatever the class, a model run as Python code has every result of ``forces``,
    ``gradient``, ``potential`` and ``energy`` checked against the shape the step needs
    (:class:`integrators.engine.Binding`), also when it changes mid-run, and its first stack
    of several rows row by row (two extra calls, once; ``rows_independent = True`` declares
    that the rows are kept apart and skips them).

and optionally

``dim``
    Number of degrees of freedom m (a positive integer); states are y = (q, p) flat, shape
    (2m,).  Default ``len(y0) // 2``.
``body_dim``
    The coordinates of one body (3 for particles in space) when q is made of bodies, so that
    the step's own error estimate (:func:`integrators.core.resolution_error`) judges each body
    by its own motion (a fast pass of one light body is not hidden by the others); default:
    the whole state is one block.
``stack_protocol``
    True declares that ``dim`` is set and ``energy`` and ``gradient`` both take stacks: the
    system is then used as it is, without the one-time check of :mod:`integrators.protocol`
    (:class:`HamiltonianSystem` sets it).
``polynomial_degree``
    Degree of H as a polynomial in y (a non-negative integer), or None when H is not a
    polynomial.  Used to choose the smallest k that conserves H exactly.
``hessian(y)``
    The Hessian of H at one state y of shape (2m,): an array of shape (2m, 2m), rows and
    columns ordered like y = (q, p), entry (i, j) = d^2 H / dy_i dy_j.  Without it the Newton
    solver uses finite differences of ``gradient`` (2m extra gradient calls per Newton step).
``initial_state()``
    A default starting state.

Separable form, H = p^T M^{-1} p / 2 + V(q): ``masses`` (shape (m,), one per degree of
freedom, positive), ``potential(q)`` and ``forces(q)`` (= -grad V, accepting a stack (n, m)).  The
engine then iterates on the momentum coefficients only.

``forces_into(Q, out)``
    Optional, separable form: writes ``forces(Q)`` for a stack Q (n, m) into the C-contiguous
    float64 array ``out`` (n, m) and returns nothing; the Python path then skips copying the
    result (the ASE adapter provides it for calculators whose ``forces_batch`` takes ``out=``).
``separable_kernels()``
    Returns ``(force, potential, params)`` for the compiled step: ``force(Q, params, out)`` a
    numba ``njit`` function writing -grad V at each row of Q (n, m) into ``out`` (n, m);
    ``potential(q, params)`` one returning V(q) for q (m,); ``params`` a float64 array handed
    to both.  Define them at module level (importable by module and name): the step is then
    compiled with them called statically and cached on disk (:mod:`integrators.specialise`).
``full_kernels()``
    For a system that is not separable: ``(gradient, energy, params)``, ``gradient`` writing
    grad H at each row of a stack of states Y (n, 2m) into ``out`` and ``energy`` returning H(y);
    the engine then runs the compiled full form (see :class:`systems.poincare.PoincareKepler`).

For tangent vectors (``integrate(..., variational=V0)``, :mod:`integrators.variational`) the
engine needs the derivative of the force along a direction, one of (else a TypeError):

``separable_jvp()``
    Returns a numba ``njit`` kernel ``jvp(Q, dQ, params, out)`` writing (dF/dq)(Q_i) dQ_i for
    each row of Q, dQ (n, m) into ``out`` (n, m), F = -grad V, with the params of
    ``separable_kernels()`` (defined at module level, like them: the tangent map is then
    compiled with the step).  :class:`systems.Kepler` and :class:`systems.NBody` have one.
``full_jvp()``
    The same for the full form: ``jvp(Y, dY, params, out)`` writing Hess H(Y_i) dY_i, params
    of ``full_kernels()``.
``force_jvp(Q, dQ)`` / ``gradient_jvp(Y, dY)``
    Python versions returning the (n, m) / (n, 2m) array; or ``hessian(y)`` above, used row
    by row.

A system without kernels runs the same step as Python code calling ``forces`` / ``gradient``
and ``potential`` / ``energy`` (slower, the same numbers to round-off).

Writing your own is a small class; see :class:`HamiltonianSystem` and :class:`SeparableSystem`.
"""
from __future__ import annotations

import numpy as np


class HamiltonianSystem:
    """Base class: subclasses define ``dim``, ``energy`` and ``gradient`` (batched)."""

    dim: int
    polynomial_degree: int | None = None
    # energy and gradient take stacks: the engine uses the system unprobed (integrators.protocol)
    stack_protocol = True

    def energy(self, y: np.ndarray):  # pragma: no cover - abstract
        raise NotImplementedError

    def gradient(self, y: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def vector_field(self, y: np.ndarray) -> np.ndarray:
        """f(y) = J grad H(y) with J = [[0, I], [-I, 0]]: (dH/dp, -dH/dq); y may be a stack."""
        g = self.gradient(y)
        m = self.dim
        return np.concatenate([g[..., m:], -g[..., :m]], axis=-1)

    def split(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        y = np.asarray(y, dtype=float)
        return y[..., : self.dim], y[..., self.dim:]


class SeparableSystem(HamiltonianSystem):
    """H(q, p) = sum_i p_i^2 / (2 M_i) + V(q).  Subclasses define ``masses``, ``potential``,
    ``forces`` (= -grad V, batched over a leading axis)."""

    masses: np.ndarray

    def potential(self, q: np.ndarray):  # pragma: no cover - abstract
        raise NotImplementedError

    def forces(self, q: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def kinetic(self, p: np.ndarray):
        return 0.5 * np.sum(p * p / self.masses, axis=-1)

    def energy(self, y: np.ndarray):
        q, p = self.split(y)
        return self.kinetic(p) + self.potential(q)

    def gradient(self, y: np.ndarray) -> np.ndarray:
        q, p = self.split(y)
        return np.concatenate([-self.forces(q), p / self.masses], axis=-1)
