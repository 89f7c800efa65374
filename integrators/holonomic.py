"""HBVM(k, s) for Hamiltonian systems with holonomic bond constraints (rigid bonds).

The problem (masses m, positions q of shape (N, d), momenta p, potential V, forces F = -grad V)
is the constrained Hamiltonian system

    q' = M^-1 p,    p' = F(q) - G(q)^T lambda,    g(q) = 0,

with one constraint per bond a = (i, j, d_a),

    g_a(q) = (|r_a|^2 - d_a^2) / 2,    r_a = q_i - q_j + o_a,

(o_a a constant lattice offset for a bond across a periodic boundary) and G = dg/dq, whose row
a is r_a at atom i and -r_a at atom j.

The method (line-integral formulation of Brugnano, Gurioli, Iavernaro, Weinmueller, "Line
integral solution of Hamiltonian systems with holonomic constraints"; written here from the
line-integral argument below, see the notes).  On a step [0, h] the positions u and momenta v
are polynomials of degree s whose derivatives are expanded in the orthonormal shifted Legendre
basis P_1..P_s, as in HBVM(k, s) (Brugnano, Iavernaro, Trigiante, "The lack of continuity and
the role of infinite and infinitesimal in numerical methods for ODEs: the case of
symplecticity", eq. (expan)); the multiplier is a polynomial of degree s - 1,

    u'(ch) = sum_j P_j(c) gamma_j,   v'(ch) = sum_j P_j(c) delta_j,   lambda(ch) = sum_j P_j(c) rho_j,

    gamma_j = int_0^1 P_j M^-1 v,    delta_j = int_0^1 P_j [F(u) - G(u)^T lambda],          (1)

    int_0^1 P_j(c) G(u(ch)) u'(ch) dc = 0,    j = 1..s,                                     (2)

each integral by the k-point quadrature of HBVM(k, s).  Then, with exact integrals,

* constraints: the condition (2) for j = 1 (P_1 = 1) is (g(q1) - g(q0)) / h = 0, so g(q1) =
  g(q0) at every grid point.  g is quadratic, the integrand of degree 2s - 1, so any k >= s
  integrates it exactly.  This code imposes the j = 1 condition as g(q1) / h = 0 (the same
  equation when g(q0) = 0), so that round-off in g cannot accumulate from step to step;
* energy: along the polynomial path, H(y1) - H(y0) = h int (grad V(u)^T u' + v^T M^-1 v') and
  (1) turns the right side into -h int lambda^T G(u) u' = -h sum_j rho_j^T (2)_j = 0.  With
  the quadrature in place of the integrals this holds up to the quadrature error of the
  potential's line integral alone, exactly as for unconstrained HBVM(k, s): zero for a
  polynomial V of degree nu when nu s <= 2 k, O(h^(2k+1)) a step otherwise, so to round-off for
  k large enough on a smooth V (and limited by the smoothness of a cutoff);
* order 2s in q and p (measured: ``tests/test_holonomic.py``, slopes within 0.3 of 2s).

The hidden constraint G(q) M^-1 p = 0 (no velocity along a bond) is not part of (1)-(2): the
momenta v(h) of the polynomial carry a velocity along the bonds of O(h^(2s-2)) that builds up
from step to step (measured), while q and the tangential part of p have order 2s.  So after
each step (``project_momenta=True``, the default) the momenta are projected: first
M^-1-orthogonally onto G(q1) M^-1 p = 0 (HLW Sec. IV.4 and VII.1), which removes the kinetic
energy |G^T mu|^2_{M^-1} / 2 (``projection_energy``), then along their own direction relative
to the centre-of-mass velocity back to the kinetic energy they had, i.e. onto
{G M^-1 p = 0, H = H(q1, v(h))} within momentum space.  Both moves are of the size of the
violation, so the order stays 2s (measured for s = 1, 2, 3, q and p); the step then keeps

* g(q) = 0 and G(q) M^-1 p = 0 to round-off at every grid point,
* H exactly as the line integral gives it (above): round-off for polynomial V with nu s <= 2k,
  the quadrature error O(h^(2k+1)) a step otherwise,
* the total linear momentum (the bond forces are internal and the rescaling is about the
  centre of mass; with fixed atoms the momenta are scaled as a whole).

``project_momenta=False`` gives the bare method (1)-(2): energy and bonds as above, q of order
2s, p of order 2s - 2 along the bonds.

The nonlinear system is solved by a fixed-point iteration on the force part (one force call
at the k stages an iteration, as unconstrained HBVM) with, at each iteration, simplified
Newton sweeps on the multipliers: with G frozen at q0 the Jacobian of (2) in rho is
-h X_s (x) G M^-1 G^T (the Kronecker product of the HBVM matrix X_s and the sparse, per
molecule block matrix S = G M^-1 G^T), which is factorised once a step.

Forces along the bonds.  A calculator that pushes hard inside a rigid molecule (a pair
potential that does not exclude the molecule's own pairs: Lennard-Jones with sigma = 3 A on
bonds of 1.16 A gives 1e4-1e5 eV/A along them) is harmless to the constrained problem, whose
constraint forces absorb every force along the bonds, but not to the iteration: the stage
positions lie off the bond lengths by O(h^(s+1)), the stiff force there, K delta with h^2 K / m
in the thousands, is only partly absorbed by a multiplier of degree s - 1 when k > s, and the
fixed-point iteration runs away at its second iteration.  The step then (``normal_forces="auto"``,
the default: after the iteration on the full forces failed, and for every later step of the
stepper) integrates the forces' part across the bonds,

    F_t(u) = F(u) - G(u)^T S(u)^-1 G(u) M^-1 F(u),    S = G M^-1 G^T,

at each stage (the M^-1-orthogonal projection; the part removed is a constraint force).  On
g = 0 the two problems are the same (the multiplier takes up what F_t leaves out), so the
method keeps order 2s and the bonds at round-off; the energy argument above gains the term
-h sum_i w_i nu_i^T G(u_i) u'(c_i h) (nu the removed multiplier), which (2) does not cancel
when nu is not a polynomial of degree s - 1 in c: O(h^(2s+1)) a step instead of the line
integral's quadrature error (four rigid CO2 under Lennard-Jones, 100 steps of 2 fs: 4e-12 eV
against 1.2e-5 eV for VelocityVerlet; rigid water: 2e-9 eV in a potential energy of 2.5e5 eV).
The tangential part is known to the rounding of the full forces only (eps |F|), which is then
the iteration's round-off.  ``normal_forces="keep"`` never absorbs (the iteration fails
instead), ``"absorb"`` always does.

Notes
-----
The paper was not at hand when this was written: equations (1)-(2) are the line-integral
conditions as derived above, and the guarantees stated here are those derived and measured
here.  The layout: ``q``, ``p`` of shape (N, d), masses (N,), the force callable takes stage
positions (n, N, d) and returns forces (n, N, d).  A mass may be ``inf`` (a fixed atom: zero
inverse mass, it never moves); a bond between two fixed atoms is dropped.
"""
from __future__ import annotations

import numbers

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components

from .core import ROUNDOFF_ULPS, STATE_ULPS
from .errors import ConstraintError, ConvergenceError, NonFiniteError
from .tableau import HBVM

EPS = np.finfo(float).eps
RUNAWAY = 1e6               # an increment this many times the first one: diverged
MAX_ITERATIONS = 100        # fixed-point iterations of one step at most
NEWTON_SWEEPS = 4           # multiplier sweeps per force evaluation at most
#: the bond lengths after a step must hold to this, relative to the bond length (a step that
#: converged meets it with room: 1e-15 measured); otherwise ConstraintError
CONSTRAINT_RTOL = 1e-11


class BondConstraints:
    """Rigid bonds |q_i - q_j + o| = d as data: pairs (P, 2), lengths (P,), checked when built.

    Parameters
    ----------
    pairs : array_like of int, shape (P, 2)
        Atom indices (i, j), i != j, each pair at most once.
    lengths : array_like of float, shape (P,)
        Bond lengths d > 0 (in the positions' unit).
    n_atoms : int
        Number of atoms N (indices must be < N).
    """

    def __init__(self, pairs, lengths, n_atoms: int):
        if isinstance(n_atoms, bool) or not isinstance(n_atoms, numbers.Integral) or n_atoms < 2:
            raise ValueError(f"`n_atoms` must be an integer >= 2 (got n_atoms={n_atoms!r}); a bond "
                             f"joins two atoms")
        a = np.asarray(pairs)
        if a.dtype.kind not in "iu" or a.ndim != 2 or a.shape[1] != 2:
            raise ValueError(f"`pairs` must be integer atom indices of shape (P, 2) (got dtype "
                             f"{a.dtype}, shape {a.shape}); e.g. [(0, 1), (0, 2), (1, 2)]")
        d = np.asarray(lengths, dtype=float)
        if d.shape != (a.shape[0],):
            raise ValueError(f"`lengths` must have shape ({a.shape[0]},), one per pair (got shape "
                             f"{d.shape})")
        if a.size and (a.min() < 0 or a.max() >= n_atoms):
            bad = a[(a < 0) | (a >= n_atoms)][0]
            raise ValueError(f"`pairs` index {bad} is out of range for {n_atoms} atoms")
        if np.any(a[:, 0] == a[:, 1]):
            i = int(np.flatnonzero(a[:, 0] == a[:, 1])[0])
            raise ValueError(f"`pairs` joins atom {a[i, 0]} to itself (pair {i}); a bond needs two atoms")
        key = np.sort(a, axis=1)
        if len(np.unique(key, axis=0)) != len(key):
            raise ValueError("`pairs` lists a bond twice; each pair of atoms at most once (a "
                             "repeated constraint makes the multipliers singular)")
        if not np.all(np.isfinite(d) & (d > 0)):
            i = int(np.flatnonzero(~(np.isfinite(d) & (d > 0)))[0])
            raise ValueError(f"`lengths` must be positive and finite (got {d[i]} for pair {i}: "
                             f"{tuple(int(x) for x in a[i])})")
        self.pairs = np.array(a, dtype=np.int64)
        self.lengths = d.copy()
        self.n_atoms = int(n_atoms)
        self.pairs.flags.writeable = False
        self.lengths.flags.writeable = False
        # incidence B (N, P): +1 at i, -1 at j, so that G^T lambda = B (lambda r)
        P = len(a)
        self.incidence = sp.csr_matrix(
            (np.r_[np.ones(P), -np.ones(P)], (np.r_[a[:, 0], a[:, 1]], np.r_[np.arange(P), np.arange(P)])),
            shape=(n_atoms, P))

    def __len__(self) -> int:
        return len(self.lengths)

    def vectors(self, q: np.ndarray, offsets: np.ndarray | None = None) -> np.ndarray:
        """r_a = q_i - q_j + o_a for positions q (..., N, d); shape (..., P, d)."""
        r = q[..., self.pairs[:, 0], :] - q[..., self.pairs[:, 1], :]
        return r if offsets is None else r + offsets

    def residual(self, q: np.ndarray, offsets: np.ndarray | None = None) -> np.ndarray:
        """g(q) = (|r|^2 - d^2) / 2, shape (..., P)."""
        r = self.vectors(q, offsets)
        return 0.5 * (np.einsum("...k,...k->...", r, r) - self.lengths ** 2)

    def length_errors(self, q: np.ndarray, offsets: np.ndarray | None = None) -> np.ndarray:
        """|r_a| - d_a (in the positions' unit), shape (..., P)."""
        return np.linalg.norm(self.vectors(q, offsets), axis=-1) - self.lengths

    def transpose_apply(self, lam: np.ndarray, r: np.ndarray) -> np.ndarray:
        """G(q)^T lambda: lam (n, P) at vectors r (n, P, d) -> (n, N, d)."""
        n, P, d = r.shape
        f = (lam[..., None] * r).transpose(1, 0, 2).reshape(P, n * d)
        return np.asarray(self.incidence @ f).reshape(self.n_atoms, n, d).transpose(1, 0, 2)

    def apply(self, r: np.ndarray, x: np.ndarray) -> np.ndarray:
        """G(q) x: vectors r (n, P, d), x (n, N, d) -> (n, P)."""
        dx = x[:, self.pairs[:, 0], :] - x[:, self.pairs[:, 1], :]
        return np.einsum("npk,npk->np", r, dx)

    def gram(self, r: np.ndarray, minv: np.ndarray):
        """S = G M^-1 G^T at vectors r (P, d), factorised (scipy ``splu``); one block per
        molecule (bonds sharing no atom do not couple)."""
        key = minv.tobytes()
        if getattr(self, "_pattern", (None,))[0] != key:
            # B^T M^-1 B in CSC order: S has its pattern and values times r_a . r_b
            C = (self.incidence.T @ sp.diags(minv) @ self.incidence).tocsc()
            C.sort_indices()
            col = np.repeat(np.arange(C.shape[1]), np.diff(C.indptr))
            self._pattern = (key, C, C.indices.copy(), col)
        _, C, row, col = self._pattern
        S = sp.csc_matrix((C.data * np.einsum("ak,ak->a", r[row], r[col]), C.indices, C.indptr),
                          shape=C.shape)
        return spla.splu(S)


class HolonomicHBVM:
    """One-step map of HBVM(k, s) with rigid bonds (equations (1)-(2) of the module docstring).

    Parameters
    ----------
    method : HBVM
        HBVM(k, s) (Gauss or Lobatto nodes): order 2s; the quadrature of k nodes integrates the
        potential's line integral (energy exact for polynomial V of degree nu when nu s <= 2k).
    constraints : BondConstraints
    masses : array_like, shape (N,)
        Positive; ``inf`` for an atom that must not move.
    force : callable
        ``force(Q)`` with Q of shape (n, N, d), the stage positions, returns the forces
        -grad V of shape (n, N, d).  Called with n = the number of stages, once an iteration.
    project_momenta : bool
        Project p1 onto G(q1) M^-1 p = 0 after each step keeping its kinetic energy (default;
        see the module docstring).
    max_iterations : int
    normal_forces : {"auto", "keep", "absorb"}
        The forces' part along the bonds (module docstring, "Forces along the bonds"):
        "auto" integrates the full forces, and their part across the bonds once an iteration
        on the full forces failed (then for every later step: ``absorbing``); "keep" the full
        forces always; "absorb" the part across the bonds always.

    Attributes
    ----------
    force_evaluations : int
        Stage configurations evaluated so far.
    iterations : int
        Fixed-point iterations of the last step.
    projection_energy : float
        Kinetic energy the last orthogonal projection took (>= 0), before it was given back.
    absorbing : bool
        The steps integrate the forces' part across the bonds (``normal_forces="auto"`` after
        an iteration on the full forces failed).

    Notes
    -----
    :meth:`step` returns new arrays and changes neither its inputs nor, on failure, anything
    else (the initial guess kept for the next step is replaced only on success).
    """

    def __init__(self, method: HBVM, constraints: BondConstraints, masses, force, *,
                 project_momenta: bool = True, max_iterations: int = MAX_ITERATIONS,
                 normal_forces: str = "auto"):
        if not isinstance(method, HBVM):
            raise TypeError(f"`method` must be an integrators.HBVM (got {type(method).__name__}); "
                            f"e.g. HBVM(3, 2)")
        if not isinstance(constraints, BondConstraints):
            raise TypeError(f"`constraints` must be a BondConstraints (got {type(constraints).__name__})")
        if not callable(force):
            raise TypeError(f"`force` must be callable, force(Q) -> F with Q, F of shape (n, N, d) "
                            f"(got {type(force).__name__})")
        m = np.asarray(masses, dtype=float)
        if m.shape != (constraints.n_atoms,):
            raise ValueError(f"`masses` must have shape ({constraints.n_atoms},), one per atom (got "
                             f"shape {m.shape})")
        if not np.all(m > 0) or np.any(np.isnan(m)):
            i = int(np.flatnonzero(~(m > 0))[0])
            raise ValueError(f"`masses` must be positive (inf for a fixed atom; got {m[i]} for atom {i})")
        self.method = method
        self.masses = m
        self.minv = np.where(np.isinf(m), 0.0, 1.0 / m)
        # a bond between two atoms that never move holds by itself and would make S singular
        moving = (self.minv[constraints.pairs[:, 0]] > 0) | (self.minv[constraints.pairs[:, 1]] > 0)
        if not moving.all():
            constraints = BondConstraints(constraints.pairs[moving], constraints.lengths[moving],
                                          constraints.n_atoms)
        self._moving = moving
        self.constraints = constraints
        self.force = force
        self.project_momenta = bool(project_momenta)
        if normal_forces not in ("auto", "keep", "absorb"):
            raise ValueError(f"`normal_forces` must be 'auto', 'keep' or 'absorb' (got "
                             f"normal_forces={normal_forces!r})")
        self.normal_forces = normal_forces
        self.absorbing = False
        self.max_iterations = int(max_iterations)
        self.force_evaluations = 0
        self.iterations = 0
        self.projection_energy = 0.0
        # the tableau in the shapes used here
        self._c = np.asarray(method.tau)                     # (n,)
        self._P = np.asarray(method.P)                       # (n, s)
        self._W = np.asarray(method.W)                       # (s, n) = P_s^T Omega
        self._X = np.asarray(method.X)                       # (s, s)
        self._C2 = np.asarray(method.C2)                     # (n, s) = I_s X_s
        self._PX = self._P @ self._X                         # (n, s): u' at the stages
        self._Xinv = np.linalg.inv(self._X)
        self._guess = None                                   # (h, delta, rho) of the last step

    def reset(self) -> None:
        """Forget the previous step (its coefficients are the next step's initial guess); call
        when the state was changed from outside."""
        self._guess = None

    # -- the pieces ----------------------------------------------------------------------------
    def _check(self, q, p, offsets):
        N = self.constraints.n_atoms
        q = np.asarray(q, dtype=float)
        p = np.asarray(p, dtype=float)
        if q.ndim != 2 or q.shape[0] != N or p.shape != q.shape:
            raise ValueError(f"`q` and `p` must have shape ({N}, d) (got {q.shape} and {p.shape})")
        for name, a in (("q", q), ("p", p)):
            if not np.all(np.isfinite(a)):
                i = int(np.flatnonzero(~np.all(np.isfinite(a), axis=1))[0])
                raise ValueError(f"`{name}` must be finite (nan or inf at atom {i})")
        if offsets is not None:
            offsets = np.asarray(offsets, dtype=float)
            full = (len(self._moving), q.shape[1])
            if offsets.shape != full:
                raise ValueError(f"`offsets` must have shape {full}, one per pair (got {offsets.shape})")
            offsets = offsets[self._moving]
        return q, p, offsets

    def project_momenta_onto_bonds(self, q, p, offsets=None):
        """(p - G^T mu, removed kinetic energy): the M^-1-orthogonal projection of p (N, d)
        onto G(q) M^-1 p = 0 (no relative velocity along any bond)."""
        con = self.constraints
        r = con.vectors(q, offsets)
        lu = con.gram(r, self.minv)
        mu = lu.solve(con.apply(r[None], (self.minv[:, None] * p)[None])[0])
        dp = con.transpose_apply(mu[None], r[None])[0]
        return p - dp, 0.5 * float(np.sum(self.minv[:, None] * dp * dp))

    def _project_keeping_energy(self, q, p, offsets):
        """(p1, removed): p projected onto G(q) M^-1 p = 0, then scaled about the centre-of-mass
        velocity back to its kinetic energy (the projection onto that energy level within the
        tangent space, along the momenta); ``removed`` is the kinetic energy the first
        projection took.  Keeps g, G M^-1 p = 0, H as the step left it, and the total momentum."""
        pt, removed = self.project_momenta_onto_bonds(q, p, offsets)
        if removed == 0.0:
            return pt, removed
        minv = self.minv[:, None]
        moving = self.minv > 0
        # the centre-of-mass velocity (zero with fixed atoms: a uniform velocity would then
        # stretch a bond to a fixed atom, and the momentum is not conserved anyway)
        if moving.all():
            V = pt.sum(axis=0) / self.masses.sum()
        else:
            V = np.zeros(q.shape[1])
        w = np.where(moving[:, None], pt - np.where(moving, self.masses, 0.0)[:, None] * V, 0.0)
        t_rel = 0.5 * float(np.sum(minv * w * w))
        if t_rel <= 0.0:
            return pt, removed
        # T(pt + e w) = T(pt) + e (w . M^-1 pt) + e^2 t_rel = T(pt) + removed;
        # w . M^-1 pt = 2 t_rel (w is pt less its centre-of-mass part, M^-1-orthogonal to w)
        b = float(np.sum(minv * w * pt)) / t_rel
        e = removed / t_rel / (0.5 * b + np.sqrt(0.25 * b * b + removed / t_rel))
        return pt + e * w, removed

    def _tangential(self, F, R):
        """The stage forces F (n, N, d) less their part along the constraint normals at each
        stage, G_i^T S_i^-1 G_i M^-1 F_i (S_i = G_i M^-1 G_i^T at the stage's bond vectors R_i):
        the part the constraint forces absorb (module docstring, "Forces along the bonds")."""
        con = self.constraints
        out = np.empty_like(F)
        for i in range(F.shape[0]):
            lu = con.gram(R[i], self.minv)
            mu = lu.solve(con.apply(R[i:i + 1], (self.minv[:, None] * F[i])[None])[0])
            out[i] = F[i] - con.transpose_apply(mu[None], R[i:i + 1])[0]
        return out

    def dependent_bonds(self, q, offsets=None, rtol: float = 1e-8):
        """(bond indices, rank) of the first molecule whose bonds are not independent at q
        (the rows of G M^-1/2 on its atoms have rank below their number: the multipliers are
        then undetermined and S = G M^-1 G^T singular), or None.  Bonds that share no atom do
        not couple, so each molecule (connected set of bonds) is checked by itself."""
        con = self.constraints
        P = len(con)
        if P < 2:
            return None
        r = con.vectors(np.asarray(q, dtype=float), offsets)
        B = abs(con.incidence)
        n, label = connected_components(B.T @ B, directed=False)
        w = np.sqrt(self.minv)
        for comp in range(n):
            bonds = np.flatnonzero(label == comp)
            if bonds.size < 2:
                continue
            atoms = np.unique(con.pairs[bonds])
            col = {int(a): k for k, a in enumerate(atoms)}
            G = np.zeros((bonds.size, atoms.size, r.shape[1]))
            for row, b in enumerate(bonds):
                i, j = con.pairs[b]
                G[row, col[int(i)]] += w[i] * r[b]
                G[row, col[int(j)]] -= w[j] * r[b]
            sv = np.linalg.svd(G.reshape(bonds.size, -1), compute_uv=False)
            rank = int(np.sum(sv > rtol * sv[0])) if sv[0] > 0 else 0
            if rank < bonds.size:
                return bonds, rank
        return None

    def project_positions(self, q, offsets=None, max_iterations: int = 50):
        """q moved onto g(q) = 0 along M^-1 G(q)^T (the direction of the constraint forces;
        simplified Newton with G frozen at q), for a start that breaks the bond lengths."""
        con = self.constraints
        q = np.array(q, dtype=float)
        r0 = con.vectors(q, offsets)
        lu = con.gram(r0, self.minv)
        tol = CONSTRAINT_RTOL * 0.1 * con.lengths
        for _ in range(max_iterations):
            g = con.residual(q, offsets)
            if np.all(np.abs(g) <= tol * con.lengths):
                return q
            mu = lu.solve(g)
            q -= self.minv[:, None] * con.transpose_apply(mu[None], r0[None])[0]
        raise ConstraintError(0.0, None, float(np.max(np.abs(con.length_errors(q, offsets)))),
                              "the positions could not be moved onto the bond lengths; check that "
                              "the lengths can be met together")

    # -- the step ------------------------------------------------------------------------------
    def step(self, q, p, h: float, offsets=None, t: float | None = None):
        """One step of size h from (q, p), both (N, d); returns (q1, p1).

        ``offsets`` (P, d): the lattice offsets o_a of the bonds (constant over the step).
        Raises :class:`integrators.ConvergenceError` (the iteration did not converge),
        :class:`integrators.NonFiniteError` (a force or the new state is not finite) or
        :class:`integrators.ConstraintError` (the bonds are not kept); nothing is changed then.
        """
        q0, p0, offsets = self._check(q, p, offsets)
        h = float(h)
        if not (np.isfinite(h) and h != 0.0):
            raise ValueError(f"`h` must be a nonzero finite number (got h={h!r})")
        if self.normal_forces == "absorb" or self.absorbing or not len(self.constraints):
            return self._step(q0, p0, h, offsets, t, absorb=self.normal_forces == "absorb"
                              or self.absorbing)
        try:
            return self._step(q0, p0, h, offsets, t, absorb=False)
        except ConvergenceError as first:
            if self.normal_forces == "keep":
                raise
            try:
                out = self._step(q0, p0, h, offsets, t, absorb=True)
            except ConvergenceError as err:
                if type(err) is not ConvergenceError:
                    raise
                raise ConvergenceError(
                    h, err.residual, err.iterations, err.solver, t,
                    f"{err.hint} (this with the forces along the rigid bonds absorbed by the "
                    f"constraint forces; with the full forces the iteration stopped after "
                    f"{first.iterations} iterations with increment {first.residual:.3e})") from None
            self.absorbing = True
            return out

    def _step(self, q0, p0, h, offsets, t, absorb: bool):
        """The step of :meth:`step` on checked input; ``absorb``: integrate the stage forces'
        tangential part (:meth:`_tangential`)."""
        con = self.constraints
        minv = self.minv[:, None]
        c, Pm, W, X, C2, PX, Xinv = self._c, self._P, self._W, self._X, self._C2, self._PX, self._Xinv
        s = X.shape[0]
        v0 = minv * p0
        r0 = con.vectors(q0, offsets)
        lu = con.gram(r0, self.minv)
        # initial guess: the previous step's polynomials extrapolated (h unchanged), else zero
        if self._guess is not None and self._guess[0] == h and self._guess[1].shape[1:] == q0.shape:
            E = self.method.E
            delta = np.tensordot(E, self._guess[1], axes=1)
            rho = E @ self._guess[2]
        else:
            delta = np.zeros((s,) + q0.shape)
            rho = np.zeros((s, len(con)))
        base = q0[None] + h * c[:, None, None] * v0[None]
        prev, stalls, nfev = np.inf, 0, 0
        for it in range(1, self.max_iterations + 1):
            U = base + h * h * minv[None] * np.tensordot(C2, delta, axes=1)
            with np.errstate(all="ignore"):       # a runaway is caught below, by name
                F = np.asarray(self.force(U), dtype=float)
            nfev += U.shape[0]
            if F.shape != U.shape:
                raise ValueError(f"`force` returned shape {F.shape} for stage positions of shape "
                                 f"{U.shape}; it must return one force per atom and stage")
            R = con.vectors(U, offsets)
            floor = 0.0
            if absorb and np.all(np.isfinite(F)):
                # the tangential part is known to the rounding of the full forces only
                floor = 4 * EPS * float(np.max(np.abs(F), initial=0.0))
                F = self._tangential(F, R)
            WF = np.tensordot(W, F, axes=1)
            dprev = np.inf
            for _ in range(NEWTON_SWEEPS):
                new = WF - np.tensordot(W, con.transpose_apply(Pm @ rho, R), axes=1)
                # (2) for j >= 2 by quadrature, for j = 1 as g(q1) / h
                dU = v0[None] + h * minv[None] * np.tensordot(PX, new, axes=1)
                phi = W @ con.apply(R, dU)
                q1 = q0 + h * v0 + h * h * minv * np.tensordot(X[0], new, axes=1)
                phi[0] = con.residual(q1, offsets) / h
                dz = lu.solve(np.ascontiguousarray(phi.T)).T       # (s, P): S^-1 phi_j
                drho = (Xinv @ dz) / h
                rho = rho + drho
                # done when at round-off, or no longer contracting (the rounding of g(q1) / h^2)
                dmax = float(np.max(np.abs(drho), initial=0.0))
                if dmax <= 4 * EPS * float(np.max(np.abs(rho), initial=0.0)) or dmax >= 0.5 * dprev:
                    break
                dprev = dmax
            new = WF - np.tensordot(W, con.transpose_apply(Pm @ rho, R), axes=1)
            inc = float(np.max(np.abs(new - delta)))
            scale = float(np.max(np.abs(new)))
            # how far this increment moves the stage positions (where the forces are taken)
            move = float(np.max(np.abs(h * h * minv[None] * np.tensordot(C2, new - delta, axes=1))))
            umax = float(np.max(np.abs(U)))
            delta = new
            if not (np.isfinite(inc) and np.all(np.isfinite(F))):
                self.force_evaluations += nfev
                raise NonFiniteError(h, it, "fixed_point", t, "a force or the stage state is not "
                                     "finite; try a smaller timestep")
            # converged (HLW Sec. VIII.6: iterate until the increment vanishes or stops
            # decreasing at round-off): the coefficients are at their own round-off, or the
            # stage positions, hence the forces, no longer move beyond STATE_ULPS ulps.  The
            # momenta keep the rounding of the multipliers, eps |q| / h^2 (g(q1) / h is the
            # condition), which lies along the bonds and is removed by the projection.
            if (inc <= 2 * EPS * scale or inc <= floor
                    or (it > 1 and move <= STATE_ULPS * EPS * umax)):
                break
            if it == 1:
                first = inc
            elif inc > RUNAWAY * first:
                self.force_evaluations += nfev
                raise ConvergenceError(h, inc, it, "fixed_point", t, "the iteration runs away; "
                                       "try a smaller timestep")
            if inc >= prev:
                if move <= ROUNDOFF_ULPS * EPS * umax:
                    break
                stalls += 1
                if stalls >= 2:
                    self.force_evaluations += nfev
                    raise ConvergenceError(h, inc, it, "fixed_point", t, "try a smaller timestep")
            prev = inc
        else:
            self.force_evaluations += nfev
            raise ConvergenceError(h, inc, self.max_iterations, "fixed_point", t, "try a smaller timestep")
        self.force_evaluations += nfev
        q1 = q0 + h * v0 + h * h * minv * np.tensordot(X[0], delta, axes=1)
        # an atom of infinite mass keeps its momentum (the bond forces on it move nothing)
        p1 = np.where(minv > 0, p0 + h * delta[0], p0)
        if not (np.all(np.isfinite(q1)) and np.all(np.isfinite(p1))):
            raise NonFiniteError(h, it, "fixed_point", t)
        err = np.abs(con.length_errors(q1, offsets))
        if err.size and np.max(err / con.lengths) > CONSTRAINT_RTOL:
            a = int(np.argmax(err / con.lengths))
            raise ConstraintError(h, t, float(err[a]),
                                  f"bond {tuple(int(x) for x in con.pairs[a])} is off its length "
                                  f"{con.lengths[a]:.6g} by {err[a]:.3e} after the step; try a "
                                  f"smaller timestep")
        projected = 0.0
        if self.project_momenta and len(con):
            p1, projected = self._project_keeping_energy(q1, p1, offsets)
        self.iterations = it
        self.projection_energy = projected
        self._guess = (h, delta, rho)
        return q1, p1
