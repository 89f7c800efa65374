"""How every report measures the change of the angular momentum (one definition).

The figure in every table (``max_rel_angular_momentum_error``, "max rel. dL") is

    max over the output times t of |L(t) - L(0)| / D,   D = |L(0)|,

with |.| the Euclidean norm of the vector (the absolute value for the planar Kepler model).
When |L(0)| is tiny against the size of its terms, S = sum_i |x_i| |p_i| (a cluster set not
to rotate, L = 0 up to round-off; a cluster starting at rest), a relative change would divide
by round-off: then D is the largest S over the run and the figure says how far the method
moves L away from zero against the size of L's own terms (0 when nothing moved).  "Tiny" is
|L(0)| < :data:`TINY` S(0) (the largest S when S(0) = 0); the tables of this project never reach it (the outer solar system:
|L| = 0.92 S, Kepler e = 0.6: |L| = S, the seeded clusters: |L| is 0.2 S).

Which L each scene uses, the same for every method on it, comes from its model: Kepler's
q x p (:meth:`systems.Kepler.angular_momentum`); an N-body scene's sources about the origin
(:meth:`systems.NBody.angular_momentum`, ``sim.angular_momentum()`` of REBOUND for sources and
massless test particles); an ASE cluster's about its centre of mass
(:func:`systems.angular_momentum.angular_momentum`, see :func:`atoms_angular_momentum`).
"""
from __future__ import annotations

import numpy as np

#: |L(0)| below TINY times the size of its terms counts as zero (see the module docstring)
TINY = 1e-6


def change_series(L, scale) -> np.ndarray:
    """|L(t) - L(0)| / D at each sample, shape (n,); inf where L is not finite.

    Parameters
    ----------
    L : array_like, shape (n,) or (n, 3)
        The angular momentum at the output times, L[0] the start.
    scale : float or array_like, shape (n,)
        S, the size of L's terms (``angular_momentum_scale`` of the model): at the start, or at
        every sample (then a start at rest is measured against the largest S reached).
    """
    L = np.asarray(L, dtype=float)
    if L.ndim == 1:
        L = L[:, None]
    if L.ndim != 2 or len(L) < 1:
        raise ValueError(f"`L` must have shape (n,) or (n, 3) with n >= 1 (got {np.shape(L)})")
    D = denominator(L[0], scale)
    dL = np.linalg.norm(L - L[0], axis=1)
    if D == 0.0:                      # nothing moved: no change unless L itself is broken
        return np.where(np.isfinite(dL), dL, np.inf)
    with np.errstate(invalid="ignore", over="ignore"):
        d = dL / D
    return np.where(np.isfinite(d), d, np.inf)


def denominator(L0, scale) -> float:
    """D of the module docstring: |L(0)|, or the largest S of ``scale`` (a float or one per
    sample) when |L(0)| < TINY S(0); 0 when nothing moved."""
    n = float(np.linalg.norm(np.atleast_1d(np.asarray(L0, dtype=float))))
    S = np.atleast_1d(np.asarray(scale, dtype=float))
    if S.ndim != 1 or len(S) < 1 or not np.all(S >= 0):
        raise ValueError(f"`scale` must be a number >= 0 or one per sample (got {scale!r})")
    finite = S[np.isfinite(S)]
    largest = float(finite.max()) if len(finite) else 0.0
    # a start at rest has no S(0) to compare |L(0)| with: the largest S reached stands in
    if n > 0 and n >= TINY * (S[0] if S[0] > 0 else largest):
        return n
    return largest


def relative_change(L, scale) -> float:
    """max over the samples of :func:`change_series` (the tables' figure)."""
    return float(np.max(change_series(L, scale)))


def atoms_angular_momentum(positions, momenta, masses):
    """An ASE cluster's L about its centre of mass and its scale, for samples of positions and
    momenta of shape (n, N, 3) (``atoms.get_positions()``, ``atoms.get_momenta()``).

    About the centre of mass rather than ASE's ``atoms.get_angular_momentum()`` (about the
    origin): both are conserved by the exact flow of a free cluster, and they are equal when the
    total momentum is zero (``Stationary``, as the reports start), but the origin's value and
    its round-off grow with the distance of the cluster from the origin.

    Returns
    -------
    L : ndarray (n, 3)
    scale : ndarray (n,)
    """
    from systems.angular_momentum import angular_momentum
    return angular_momentum(positions, momenta, masses, about="com")
