"""Total angular momentum of a set of point particles, vectorised over samples.

The one implementation behind :meth:`systems.NBody.angular_momentum` and the reports' reading of
ASE atoms (:mod:`hbvm_md.reports.md_comparison`, :mod:`hbvm_md.reports.workprecision`).  The
planar Kepler model has its own scalar ``q x p`` (:meth:`systems.Kepler.angular_momentum`).

For particles that interact through forces along the lines joining them (gravity, pair
potentials) and feel nothing from outside, L about any fixed point is a constant of the motion,
and so is L about the centre of mass (they differ by R x P, itself constant).  It is quadratic in
(q, p): symplectic Runge-Kutta methods (Gauss) and Stormer-Verlet keep it to round-off, HBVM(k,
s) with k > s does not (Brugnano, Iavernaro, Trigiante, "Energy- and quadratic
invariants-preserving integrators based upon Gauss collocation formulae").
"""
from __future__ import annotations

import numpy as np


def angular_momentum(positions, momenta, masses=None, about: str = "origin"):
    """L = sum_i (x_i - c) x p_i and its scale sum_i |x_i - c| |p_i|.

    Parameters
    ----------
    positions, momenta : array_like, shape (..., N, 3)
        Positions x_i and canonical momenta p_i = m_i v_i; any leading axes (samples) are kept.
    masses : array_like, shape (N,), optional
        Needed for ``about="com"`` only.
    about : {"origin", "com"}
        c = 0, or c = the centre of mass sum_i m_i x_i / sum_i m_i (per sample).  About the
        centre of mass, L does not depend on where the particles sit in the frame, and neither
        does its round-off.

    Returns
    -------
    L : ndarray, shape (..., 3)
    scale : ndarray, shape (...,)
        sum_i |x_i - c| |p_i|: the size of the individual terms, hence of L's round-off and of
        any error a method makes in it; the reports divide by it when |L| itself is tiny
        (:func:`hbvm_md.reports.invariants.relative_change`).
    """
    x = np.asarray(positions, dtype=float)
    p = np.asarray(momenta, dtype=float)
    if x.shape != p.shape or x.ndim < 2 or x.shape[-1] != 3:
        raise ValueError(f"`positions` and `momenta` must both have shape (..., N, 3) (got "
                         f"{x.shape} and {p.shape})")
    if about == "com":
        if masses is None:
            raise ValueError("`masses` (shape (N,)) is needed for about='com'")
        m = np.asarray(masses, dtype=float)
        if m.shape != x.shape[-2:-1] or not np.all(m > 0):
            raise ValueError(f"`masses` must be N = {x.shape[-2]} positive numbers (got shape {m.shape})")
        x = x - np.einsum("i,...ij->...j", m, x)[..., None, :] / m.sum()
    elif about != "origin":
        raise ValueError(f"`about` must be 'origin' or 'com' (got about={about!r})")
    L = np.cross(x, p).sum(axis=-2)
    scale = np.sum(np.linalg.norm(x, axis=-1) * np.linalg.norm(p, axis=-1), axis=-1)
    return L, scale
