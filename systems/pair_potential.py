"""Polynomial pair potentials as an ASE calculator: phi(r) = sum_n c_n r^(2n).

A polynomial in r^2 is a polynomial in the Cartesian coordinates (r^2 = |x_j - x_i|^2), so
with all pairs or a fixed list of bonded pairs the Hamiltonian is a polynomial of degree
2 (len(c) - 1) and HBVM(k, s) with k >= nu s / 2 conserves it exactly (BIT, eq. (knu)).
Note that (r - r0)^2 is *not* a polynomial in r^2: springs here have zero rest length, or a
rest length encoded by a well such as c2 r^4 - c1 r^2.

The force kernel is compiled by numba and evaluates many configurations at once
(:meth:`PolynomialPairPotential.forces_batch`): the k stages of an HBVM step in one call.
:meth:`PolynomialPairPotential.hessian` gives the exact second derivatives (for Newton).

Neighbour list (cutoff mode): vesin (``vesin.NeighborList``, cell lists in C++, O(N)), used as
a Verlet list with a skin.  Measured on rattled simple-cubic argon, cutoff 5 A, one build:
1e3 / 1e4 / 5e4 / 1e5 atoms in 1.0 / 12 / 32 / 66 ms with vesin's half list, 1.6 / 24 / 72 /
147 ms with matscipy's ``neighbour_list`` (a full list, twice the pairs to filter), and 21 /
625 / 2100 / 4700 ms with ASE's ``neighbor_list`` (used before).  vesin was chosen because it is
the fastest of the three, returns each pair once (the half list this kernel wants), handles
cells smaller than twice the cutoff, unwrapped positions and partly periodic cells, and
depends on numpy only.  Its pair set matches ASE's except for pairs exactly at the list
cutoff (vesin includes r = r_c), which the kernels discard anyway (they require u < r_c^2).
"""
from __future__ import annotations

import numpy as np
import vesin
from ase.calculators.calculator import Calculator, PropertyNotImplementedError, all_changes, equal
from integrators.jit import jit


@jit
def _pair_forces(X, ii, jj, shift, ctype, C, rc2, F, ref):
    """F[a] = -grad E at each configuration X[a] (shapes (n, N, 3)); returns the largest
    |X[a, k] - ref[k]|^2 (the neighbour list's check, taken in the same pass over X), or 0 when
    ref is empty.

    E = sum_p G_t(u_p), u_p = |X_j - X_i + shift_p|^2, G_t(u) = sum_q C[t, q] u^q; pairs with
    u >= rc2 contribute nothing.  F_i = 2 G'(u) D, F_j = -2 G'(u) D with D = X_j - X_i + shift.

    The configuration index is innermost (positions copied to an atom-major scratch (N, n, 3)),
    so that the pair list is read once for all n configurations and the n positions of an atom
    share cache lines; each F[a] sums its pairs in list order, exactly as for n = 1.
    """
    deg = C.shape[1] - 1
    n, N = X.shape[0], X.shape[1]
    Xt = np.empty((N, n, 3))
    Ft = np.zeros((N, n, 3))
    worst = 0.0
    check = ref.shape[0] == N
    for k in range(N):          # atom-outer: Xt is written (and F below read) in order
        for a in range(n):
            for c in range(3):
                Xt[k, a, c] = X[a, k, c]
            if check:
                d2 = _displacement2(X, a, k, ref)
                if d2 > worst:
                    worst = d2
    for p in range(ii.shape[0]):
        i, j, t = ii[p], jj[p], ctype[p]
        s0, s1, s2 = shift[p, 0], shift[p, 1], shift[p, 2]
        for a in range(n):
            dx = Xt[j, a, 0] - Xt[i, a, 0] + s0
            dy = Xt[j, a, 1] - Xt[i, a, 1] + s1
            dz = Xt[j, a, 2] - Xt[i, a, 2] + s2
            u = dx * dx + dy * dy + dz * dz
            if u >= rc2:
                continue
            g = 0.0
            for q in range(deg, 0, -1):
                g = g * u + q * C[t, q]
            f = 2.0 * g
            Ft[i, a, 0] += f * dx
            Ft[i, a, 1] += f * dy
            Ft[i, a, 2] += f * dz
            Ft[j, a, 0] -= f * dx
            Ft[j, a, 1] -= f * dy
            Ft[j, a, 2] -= f * dz
    for k in range(N):
        for a in range(n):
            for c in range(3):
                F[a, k, c] = Ft[k, a, c]
    return worst


@jit
def _pair_properties(X, ii, jj, shift, ctype, C, rc2, F, e_atom, virial):
    """One configuration X (N, 3): forces F (N, 3), per-atom energies (N,) (half of each pair
    to each atom) and the virial sum_p 2 G'(u) D D^T (3, 3)."""
    deg = C.shape[1] - 1
    for k in range(X.shape[0]):
        e_atom[k] = 0.0
        for c in range(3):
            F[k, c] = 0.0
    for a in range(3):
        for b in range(3):
            virial[a, b] = 0.0
    d = np.empty(3)
    for p in range(ii.shape[0]):
        i, j, t = ii[p], jj[p], ctype[p]
        for c in range(3):
            d[c] = X[j, c] - X[i, c] + shift[p, c]
        u = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        if u >= rc2:
            continue
        e = 0.0
        g = 0.0
        for q in range(deg, 0, -1):
            e = e * u + C[t, q]
            g = g * u + q * C[t, q]
        e = e * u + C[t, 0]
        e_atom[i] += 0.5 * e
        e_atom[j] += 0.5 * e
        f = 2.0 * g
        for c in range(3):
            F[i, c] += f * d[c]
            F[j, c] -= f * d[c]
            for b in range(3):
                virial[c, b] += f * d[c] * d[b]


@jit
def _pair_hessian(X, ii, jj, shift, ctype, C, rc2, H):
    """H (3N, 3N) = d^2 E / dx dx at one configuration X (N, 3).

    Each pair adds B = 2 G'(u) I + 4 G''(u) D D^T to the (i, i) and (j, j) blocks and -B to the
    (i, j) and (j, i) blocks; an atom paired with its own image (i = j) adds nothing, as it
    should (its D does not depend on x_i).
    """
    deg = C.shape[1] - 1
    H[:, :] = 0.0
    d = np.empty(3)
    B = np.empty((3, 3))
    for p in range(ii.shape[0]):
        i, j, t = ii[p], jj[p], ctype[p]
        if i == j:
            continue
        for c in range(3):
            d[c] = X[j, c] - X[i, c] + shift[p, c]
        u = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        if u >= rc2:
            continue
        g1 = 0.0
        g2 = 0.0
        for q in range(deg, 0, -1):
            g1 = g1 * u + q * C[t, q]
        for q in range(deg, 1, -1):
            g2 = g2 * u + q * (q - 1) * C[t, q]
        for a in range(3):
            for b in range(3):
                B[a, b] = 4.0 * g2 * d[a] * d[b]
            B[a, a] += 2.0 * g1
        for a in range(3):
            for b in range(3):
                H[3 * i + a, 3 * i + b] += B[a, b]
                H[3 * j + a, 3 * j + b] += B[a, b]
                H[3 * i + a, 3 * j + b] -= B[a, b]
                H[3 * j + a, 3 * i + b] -= B[a, b]


@jit
def _displacement2(X, a, k, ref):
    """|X[a, k] - ref[k]|^2."""
    dx = X[a, k, 0] - ref[k, 0]
    dy = X[a, k, 1] - ref[k, 1]
    dz = X[a, k, 2] - ref[k, 2]
    return dx * dx + dy * dy + dz * dz


@jit
def _max_displacement2(X, ref):
    """max over configurations a and atoms i of |X[a, i] - ref[i]|^2 (X (n, N, 3), ref (N, 3))."""
    worst = 0.0
    for a in range(X.shape[0]):
        for i in range(X.shape[1]):
            r2 = _displacement2(X, a, i, ref)
            if r2 > worst:
                worst = r2
    return worst


_NO_REFERENCE = np.zeros((0, 3))    # _pair_forces without the neighbour-list check


def _check_coefficients(c, name: str) -> np.ndarray:
    try:
        arr = np.array(c, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be an array of numbers c_0, c_1, ... of "
                         f"phi(r) = sum_n c_n r^(2n) (got {c!r})") from None
    if arr.ndim == 0:
        arr = arr[None]
    if arr.size == 0 or arr.shape[-1] == 0:
        raise ValueError(f"`{name}` must hold at least one coefficient (got {c!r}); "
                         f"e.g. coefficients=[0.0, 1.0] for phi(r) = r^2")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"`{name}` must be finite (got {arr.tolist()}); remove nan or inf")
    return arr


def _poly_u_derivatives(c: np.ndarray, u: float, order: int) -> list[float]:
    """G(u), G'(u), ..., G^(order)(u) for G(u) = sum c_n u^n."""
    poly = np.polynomial.Polynomial(c)
    return [float(poly.deriv(m)(u)) if m else float(poly(u)) for m in range(order + 1)]


class PolynomialPairPotential(Calculator):
    """Pair potential phi(r) = sum_n c_n r^(2n), an ASE calculator.

    Parameters
    ----------
    coefficients : array_like, shape (n_c,) or (n_pairs, n_c)
        c_0 .. c_{n_c - 1} of phi as a polynomial in r^2 (units eV / A^(2n)).  With ``pairs``
        a 2-D array gives every pair its own polynomial.
    pairs : array_like of int, shape (n_pairs, 2), optional
        Bonded mode: only these pairs interact (spring networks, FPU-like chains, elastic
        networks).  The separation is the plain difference x_j - x_i of the (unwrapped)
        positions, also with periodic cells, so H stays a polynomial.
    cutoff : float, optional
        Cutoff mode: all pairs closer than ``cutoff`` (minimum image and periodic images, also
        in cells smaller than 2 ``cutoff``, through a vesin neighbour list with a skin).  phi must vanish at r_c with its first two
        derivatives (C^2); build such a phi with :meth:`soft_sphere` or :meth:`with_cutoff`.
        H is then only *piecewise* polynomial: HBVM conserves it to the accuracy of its
        quadrature across pairs that enter or leave the cutoff, not exactly.
    skin : float, optional
        Verlet skin of the neighbour list in the cutoff mode (default 0.25 * cutoff): the list
        of pairs within cutoff + skin is reused until an atom moves more than skin / 2.

    With neither ``pairs`` nor ``cutoff`` (all-pairs mode, clusters and droplets) every pair
    interacts, no periodic boundaries are allowed, and phi must be bounded below: the leading
    coefficient must be positive.

    Attributes
    ----------
    polynomial_degree : int or None
        Degree of H as a polynomial in (q, p): max(2, 2 (n_c - 1)) in the all-pairs and
        bonded modes (trailing zero coefficients ignored), None in the cutoff mode.
    batch_evaluations : int
        Number of configurations evaluated by :meth:`forces_batch` so far.
    neighbour_list_builds : int
        Number of times the cutoff mode's neighbour list was built so far.

    Examples
    --------
    >>> from ase import Atoms
    >>> atoms = Atoms("Ar2", positions=[[0, 0, 0], [0, 0, 1.5]])
    >>> atoms.calc = PolynomialPairPotential([0.0, -1.0, 0.5])   # r^4 / 2 - r^2
    >>> round(atoms.get_potential_energy(), 6)
    0.28125
    """

    implemented_properties = ["energy", "free_energy", "forces", "stress", "energies"]
    nolabel = True

    def __init__(self, coefficients, pairs=None, cutoff: float | None = None,
                 skin: float | None = None, **kwargs):
        super().__init__(**kwargs)
        C = _check_coefficients(coefficients, "coefficients")
        if C.ndim > 2:
            raise ValueError(f"`coefficients` must have shape (n_c,) or (n_pairs, n_c) "
                             f"(got shape {C.shape})")
        if pairs is not None and cutoff is not None:
            raise ValueError("give either `pairs` (bonded mode) or `cutoff` (cutoff mode), not "
                             f"both (got pairs with {len(pairs)} entries and cutoff={cutoff!r})")
        self.pairs = None
        if pairs is not None:
            try:
                P = np.array(pairs)
            except (TypeError, ValueError):
                raise ValueError(f"`pairs` must be an integer array of shape (n_pairs, 2) "
                                 f"(got {pairs!r})") from None
            if P.size == 0:
                P = P.reshape(0, 2)
            if P.ndim != 2 or P.shape[1] != 2 or (P.size and not np.issubdtype(P.dtype, np.integer)):
                raise ValueError(f"`pairs` must be an integer array of shape (n_pairs, 2) "
                                 f"(got shape {P.shape}, dtype {P.dtype})")
            if P.size and P.min() < 0:
                raise ValueError(f"`pairs` holds a negative atom index ({int(P.min())}); use "
                                 f"indices 0 .. len(atoms) - 1")
            same = np.nonzero(P[:, 0] == P[:, 1])[0]
            if same.size:
                raise ValueError(f"`pairs` row {int(same[0])} joins atom {int(P[same[0], 0])} to "
                                 f"itself; remove it")
            self.pairs = P.astype(np.int64)
        if C.ndim == 2:
            if self.pairs is None:
                raise ValueError("a 2-D `coefficients` (one polynomial per pair) needs `pairs`; "
                                 "give a 1-D array c_0, c_1, ... for the all-pairs and cutoff modes")
            if C.shape[0] != len(self.pairs):
                raise ValueError(f"`coefficients` has {C.shape[0]} rows but `pairs` has "
                                 f"{len(self.pairs)}; give one row per pair or a single 1-D row")
        # trailing zero columns change nothing but the degree
        while C.shape[-1] > 1 and np.all(C[..., -1] == 0):
            C = C[..., :-1]
        self.coefficients = C
        self._table = np.ascontiguousarray(C if C.ndim == 2 else C[None, :])
        self.cutoff = None
        if cutoff is not None:
            try:
                rc = float(cutoff)
            except (TypeError, ValueError):
                raise ValueError(f"`cutoff` must be a positive number (got cutoff={cutoff!r})") from None
            if not (np.isfinite(rc) and rc > 0):
                raise ValueError(f"`cutoff` must be a positive number (got cutoff={cutoff!r}); "
                                 f"use cutoff=None for all pairs")
            self.cutoff = rc
            self._check_vanishing(C, rc)
        if skin is not None and not (np.isfinite(skin) and skin >= 0):
            raise ValueError(f"`skin` must be a number >= 0 (got skin={skin!r})")
        self.skin = (0.25 * self.cutoff if self.cutoff else 0.0) if skin is None else float(skin)
        if self.pairs is None and self.cutoff is None and C.shape[-1] > 1 and not C[-1] > 0:
            raise ValueError(
                f"all-pairs potential phi(r) = sum c_n r^(2n) with leading coefficient "
                f"c_{C.shape[-1] - 1} = {C[-1]!r} is not bounded below; make the highest "
                f"coefficient positive (e.g. add a repulsive c r^{2 * C.shape[-1]} term), or "
                f"give `pairs` or `cutoff`")
        self.batch_evaluations = 0
        self.neighbour_list_builds = 0
        self._nl = None    # (ii, jj, shift, ctype, reference positions, cell, pbc, n_atoms)

    # -- constructors ----------------------------------------------------------------------
    @classmethod
    def soft_sphere(cls, epsilon: float, cutoff: float, **kwargs) -> "PolynomialPairPotential":
        """Repulsive soft spheres phi(r) = epsilon (1 - r^2 / r_c^2)^4 for r < r_c (C^3 at r_c)."""
        if not (np.isfinite(epsilon) and epsilon > 0):
            raise ValueError(f"`epsilon` must be a positive number (got epsilon={epsilon!r})")
        return cls.with_cutoff([float(epsilon)], cutoff, smoothness=4, **kwargs)

    @classmethod
    def with_cutoff(cls, coefficients, cutoff: float, smoothness: int = 3,
                    **kwargs) -> "PolynomialPairPotential":
        """phi(r) = g(r^2) (1 - r^2 / r_c^2)^smoothness, g(u) = sum_n c_n u^n, for r < r_c.

        The factor makes phi vanish at r_c with its first ``smoothness - 1`` derivatives
        (smoothness >= 3 gives the C^2 the cutoff mode requires).
        """
        if isinstance(smoothness, bool) or not isinstance(smoothness, (int, np.integer)) or smoothness < 3:
            raise ValueError(f"`smoothness` must be an integer >= 3 (got smoothness={smoothness!r}) "
                             f"so that phi is C^2 at the cutoff")
        g = _check_coefficients(coefficients, "coefficients")
        if g.ndim != 1:
            raise ValueError(f"`coefficients` must be 1-D here (got shape {g.shape})")
        try:
            rc = float(cutoff)
        except (TypeError, ValueError):
            raise ValueError(f"`cutoff` must be a positive number (got cutoff={cutoff!r})") from None
        if not (np.isfinite(rc) and rc > 0):
            raise ValueError(f"`cutoff` must be a positive number (got cutoff={cutoff!r})")
        factor = np.polynomial.Polynomial([1.0, -1.0 / rc ** 2]) ** int(smoothness)
        c = (np.polynomial.Polynomial(g) * factor).coef
        return cls(c, cutoff=rc, **kwargs)

    @staticmethod
    def _check_vanishing(C: np.ndarray, rc: float) -> None:
        uc = rc * rc
        scale = float(np.sum(np.abs(C) * uc ** np.arange(C.shape[-1])))
        vals = _poly_u_derivatives(C, uc, 2)
        bad = [m for m, v in enumerate(vals) if abs(v) * uc ** m > 1e-10 * max(scale, 1e-300)]
        if bad:
            raise ValueError(
                f"with cutoff={rc!r} phi must vanish at r_c together with its first two "
                f"derivatives (got d^m phi/d(r^2)^m at r_c = {[vals[m] for m in bad]} for m = {bad}); "
                f"build it with PolynomialPairPotential.with_cutoff(coefficients, cutoff) or "
                f"PolynomialPairPotential.soft_sphere(epsilon, cutoff)")

    # -- metadata --------------------------------------------------------------------------
    @property
    def polynomial_degree(self) -> int | None:
        if self.cutoff is not None:
            return None
        return max(2, 2 * (self.coefficients.shape[-1] - 1))

    def todict(self) -> dict:
        d = {"coefficients": self.coefficients.tolist()}
        if self.pairs is not None:
            d["pairs"] = self.pairs.tolist()
        if self.cutoff is not None:
            d["cutoff"] = self.cutoff
            d["skin"] = self.skin
        return d

    # -- pairs -------------------------------------------------------------------------------
    def _pair_list(self, atoms, X: np.ndarray):
        """(ii, jj, shift, ctype, rc2) valid for configurations X (n, N, 3) of ``atoms``."""
        n_atoms = len(atoms)
        if self.pairs is not None:
            if len(self.pairs) and self.pairs.max() >= n_atoms:
                raise ValueError(f"`pairs` refers to atom {int(self.pairs.max())} but the atoms "
                                 f"have {n_atoms}; use indices 0 .. {n_atoms - 1}")
            ctype = (np.arange(len(self.pairs)) if self.coefficients.ndim == 2
                     else np.zeros(len(self.pairs), dtype=np.int64))
            return (self.pairs[:, 0].copy(), self.pairs[:, 1].copy(),
                    np.zeros((len(self.pairs), 3)), ctype.astype(np.int64), np.inf)
        if self.cutoff is None:
            if np.any(atoms.pbc):
                raise ValueError("the all-pairs mode has no cutoff and cannot sum over periodic "
                                 f"images (got pbc={atoms.pbc.tolist()}); give `cutoff` or set "
                                 "atoms.pbc = False")
            ii, jj = np.triu_indices(n_atoms, 1)
            return (ii.astype(np.int64), jj.astype(np.int64), np.zeros((len(ii), 3)),
                    np.zeros(len(ii), dtype=np.int64), np.inf)
        return self._neighbours(atoms, X)

    def _neighbours(self, atoms, X):
        """The Verlet list (pairs within cutoff + skin of reference positions), rebuilt when an
        atom of any configuration in X (n, N, 3) has moved skin / 2 or more from them.

        While every atom stays within skin / 2 of the reference, a pair closer than the cutoff
        in any configuration was closer than cutoff + skin at the reference, so one list serves
        all the stage configurations of an HBVM step and the steps that follow.
        """
        nl = self._verlet_list(atoms, X[0], lambda nl: _max_displacement2(X, nl[4]))
        if nl is None:
            return None    # configurations too far apart for one list
        return nl[0], nl[1], nl[2], nl[3], self.cutoff ** 2

    def _verlet_list(self, atoms, x0, worst):
        """The list for configurations whose largest squared displacement from a list's
        reference is ``worst(list)``: the kept list while that stays below (skin / 2)^2, else
        a new one built at x0; None when even the new one does not serve them all."""
        bound = (0.5 * self.skin) ** 2
        nl = self._current_list(atoms)
        if nl is not None and worst(nl) < bound:
            return nl
        nl = self._build_list(atoms, x0)
        return nl if worst(nl) < bound else None

    def _current_list(self, atoms):
        """The kept list when it was built for these atoms' number, cell and pbc, else None
        (whether the atoms stayed within skin / 2 of its reference is checked by the caller)."""
        nl = self._nl
        if (nl is not None and nl[7] == len(atoms) and np.array_equal(nl[5], atoms.cell.array)
                and np.array_equal(nl[6], atoms.pbc)):
            return nl
        return None

    def _build_list(self, atoms, x0):
        """Build, keep and return the Verlet list at positions x0 (N, 3)."""
        cell = np.array(atoms.cell)
        pbc = np.array(atoms.pbc)
        # vesin accepts unwrapped positions: the shifts S it returns make
        # X_j - X_i + S @ cell the separation of the positions given
        search = vesin.NeighborList(cutoff=self.cutoff + self.skin, full_list=False,
                                    sorted=True)   # by i: better cache use in the kernels
        i, j, S = search.compute(x0, cell, pbc, "ijS")
        shift = np.ascontiguousarray(np.asarray(S, dtype=float) @ cell)
        nl = (np.ascontiguousarray(i, dtype=np.int64), np.ascontiguousarray(j, dtype=np.int64),
              shift, np.zeros(len(i), dtype=np.int64), np.array(x0, dtype=float), cell, pbc,
              len(atoms))
        self._nl = nl
        self.neighbour_list_builds += 1
        return nl

    # -- evaluation --------------------------------------------------------------------------
    def forces_batch(self, Q, atoms=None, out=None) -> np.ndarray:
        """Forces at many configurations at once (compiled), e.g. the k stages of a step.

        Parameters
        ----------
        Q : array_like, shape (n, N, 3)
            Positions of the N atoms in n configurations (A).
        atoms : ase.Atoms, optional
            Supplies cell, pbc and the number of atoms; default the atoms of the last
            calculation.
        out : ndarray of float64, shape (n, N, 3), C-contiguous, optional
            Written with the forces and returned (no new array: at 1e5 atoms a copy of the
            result costs about 4 % of an HBVM step).

        Returns
        -------
        ndarray, shape (n, N, 3)
            -grad E at each configuration (eV / A).  Evaluates no energy and changes no cached
            result.
        """
        if atoms is None:
            atoms = self.atoms
            if atoms is None:
                raise ValueError("`forces_batch` needs `atoms` (cell, pbc) before any "
                                 "calculation; pass atoms=...")
        X = np.ascontiguousarray(Q, dtype=float)
        if X.ndim != 3 or X.shape[1:] != (len(atoms), 3):
            raise ValueError(f"`Q` must have shape (n, {len(atoms)}, 3) (got shape {X.shape})")
        if out is None:
            F = np.empty_like(X)
        else:
            F = out
            if not (isinstance(F, np.ndarray) and F.dtype == np.float64 and F.shape == X.shape
                    and F.flags.c_contiguous and F.flags.writeable):
                raise ValueError(f"`out` must be a writable C-contiguous float64 array of shape "
                                 f"{X.shape} (got {type(F).__name__} "
                                 f"{getattr(F, 'shape', None)}, {getattr(F, 'dtype', None)})")
            if np.may_share_memory(F, X):      # the forces would overwrite the positions
                raise ValueError("`out` must not share memory with `Q`; pass a separate array")
        if self.pairs is None and self.cutoff is not None:
            # cutoff mode: the kernel checks, in its pass over X, that every atom stayed within
            # skin / 2 of the list's reference; when one did not, the forces are computed again
            # with a list built at X[0] (a few steps in a hundred)
            rc2 = self.cutoff ** 2
            nl = self._verlet_list(atoms, X[0], lambda nl: _pair_forces(
                X, nl[0], nl[1], nl[2], nl[3], self._table, rc2, F, nl[4]))
            if nl is None:
                self._one_list_each(X, atoms, F)       # configurations far apart
        else:
            ii, jj, shift, ctype, rc2 = self._pair_list(atoms, X)
            _pair_forces(X, ii, jj, shift, ctype, self._table, rc2, F, _NO_REFERENCE)
        self.batch_evaluations += X.shape[0]
        return F

    def _one_list_each(self, X, atoms, F):
        for a in range(X.shape[0]):
            F[a] = self.forces_batch(X[a:a + 1], atoms)[0]
            self.batch_evaluations -= 1

    def hessian(self, Q=None, atoms=None) -> np.ndarray:
        """The exact Hessian d^2 E / dx dx of the potential energy (compiled, dense).

        Parameters
        ----------
        Q : array_like, shape (N, 3), optional
            Positions (A); default the positions of ``atoms``.
        atoms : ase.Atoms, optional
            Supplies cell, pbc and the number of atoms; default the atoms of the last
            calculation.

        Returns
        -------
        ndarray, shape (3N, 3N)
            Rows and columns ordered x_0, y_0, z_0, x_1, ... (eV / A^2); symmetric.  Dense:
            72 N^2 bytes (0.7 MB at 100 atoms, 72 MB at 1000), meant for the simplified Newton
            solver of :class:`hbvm_md.HBVMDynamics` on small and medium systems.
        """
        if atoms is None:
            atoms = self.atoms
            if atoms is None:
                raise ValueError("`hessian` needs `atoms` (cell, pbc) before any calculation; "
                                 "pass atoms=...")
        X = np.ascontiguousarray(atoms.positions if Q is None else Q, dtype=float)
        if X.shape != (len(atoms), 3):
            raise ValueError(f"`Q` must have shape ({len(atoms)}, 3) (got shape {X.shape})")
        lst = self._pair_list(atoms, X[None])
        ii, jj, shift, ctype, rc2 = lst
        H = np.empty((3 * len(atoms), 3 * len(atoms)))
        _pair_hessian(X, ii, jj, shift, ctype, self._table, rc2, H)
        return H

    def check_state(self, atoms, tol=1e-15):
        """ASE's check for changes since the last calculation, answered at once in the two
        cases a dynamics run produces: nothing ASE checks changed bit for bit (the answer is
        then []), or only the positions did (then ASE's own tolerance test of the positions
        alone decides between [] and ["positions"]).  Anything else is left to ASE's whole
        test, which costs about 170-215 us a call at 1e3 atoms whatever the call (four numpy
        allclose): after every MD step (``atoms.get_forces()``) and at every property read of
        an observer."""
        old = self.atoms
        if old is not None and len(old) == len(atoms) and self._unchanged(old, atoms):
            if "positions" in self.ignored_changes or np.array_equal(old.positions,
                                                                     atoms.positions):
                return []
            return [] if equal(old.positions, atoms.positions, atol=tol) else ["positions"]
        return super().check_state(atoms, tol)

    def _unchanged(self, old, atoms) -> bool:
        """Is every property ASE checks, the positions aside, the same bit for bit?"""
        ignored = set(self.ignored_changes)
        if "cell" not in ignored and not np.array_equal(old.cell.array, atoms.cell.array):
            return False
        if "pbc" not in ignored and not np.array_equal(old.pbc, atoms.pbc):
            return False
        for name in all_changes:
            if name in ("cell", "pbc", "positions") or name in ignored:
                continue
            a, b = old.arrays.get(name), atoms.arrays.get(name)
            if (a is None) != (b is None) or (a is not None and not np.array_equal(a, b)):
                return False
        return True

    def calculate(self, atoms=None, properties=("energy",), system_changes=all_changes):
        super().calculate(atoms, properties, system_changes)
        atoms = self.atoms
        X = np.ascontiguousarray(atoms.positions, dtype=float)
        lst = self._pair_list(atoms, X[None])
        ii, jj, shift, ctype, rc2 = lst
        F = np.empty_like(X)
        e_atom = np.empty(len(atoms))
        virial = np.empty((3, 3))
        _pair_properties(X, ii, jj, shift, ctype, self._table, rc2, F, e_atom, virial)
        energy = float(np.sum(e_atom))
        self.results = {"energy": energy, "free_energy": energy, "forces": F, "energies": e_atom}
        if atoms.cell.rank == 3:
            sigma = virial / atoms.get_volume()
            self.results["stress"] = sigma.flat[[0, 4, 8, 5, 2, 1]].copy()
        elif "stress" in properties:
            raise PropertyNotImplementedError(
                "stress needs a cell of nonzero volume (got cell rank "
                f"{atoms.cell.rank}); set atoms.cell")
