"""Newtonian N-body gravity as a separable system, with a compiled (numba) force kernel.

Sources and test particles
--------------------------
Particle i is a *source* when it is active (i < ``n_active``) and has a nonzero mass; every other
particle is a *test particle*: it feels the sources and exerts nothing (REBOUND's
``testparticle_type = 0``).  A negative mass is a source like any other (REBOUND and IAS15 take
them; REBOUND's own ``test_variational.py`` differences runs across m = 0): its momentum m v
points against its velocity, its kinetic energy is negative, and it pulls with -|m|, so that
two bodies of opposite masses chase each other; nothing below assumes m > 0 (a time scale
takes |m|).  The unknowns are q (3N,) flat and

* p_i = m_i v_i for a source (the usual canonical momentum),
* p_i = v_i for a test particle (unit "mass" in M), so that a zero mass loses nothing.

The force kernel returns dp/dt: for a source the Newtonian force, for a test particle its
acceleration.  With sources only this is the separable Hamiltonian

    H(q, p) = sum_i |p_i|^2 / (2 m_i) - G sum_{i<j} m_i m_j / |q_i - q_j|.

With test particles the sources still form this closed Hamiltonian system (nothing acts back on
them) and each test particle follows the restricted problem in their field.  :meth:`energy`
reports the sources' H, which is what ``rebound.Simulation.energy()`` reports.

Kernel parameters: ``params = [G, N, w_0 .. w_{N-1}, g_0 .. g_{N-1}, f_0 .. f_N]`` (3N + 3,)
with w_i the mass in M (m_i for a source, 1 for a test particle), g_i the gravitating mass (m_i
for a source, 0 otherwise), and f_i the first source at or after i (N: none), so that the
sources are the linked list f_0, f_{f_0 + 1}, ... (:func:`source_links`).  The force on i from
j is G w_i g_j (q_j - q_i) / r^3; for two sources w_i g_j = w_j g_i = m_i m_j, so the pair
forces cancel exactly.  The kernels cost O(N_s N) for N_s sources whatever the order of the
particles: no pair of two test particles is visited.  With both sources and test particles the
parameters go on with :func:`followers_block`, which the force and potential kernels do not read:
the step uses it to solve the sources' stage equations first, as if alone, and each test
particle's after them in the sources' field (:func:`nbody_field`).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from integrators.jit import jit

from .base import SeparableSystem


@jit
def nbody_forces(Q, params, out):
    """dp/dt at each row of Q (n, 3N) into out (n, 3N); params as in the module docstring.

    O(n N_s N) for N_s sources: the sources' pairs, then each test particle against the sources
    (the linked list of sources in params), never a pair of two test particles.  Each body sums
    its terms in increasing index of its partner, as the pair loop over all i < j did before
    (with a pair of test particles skipped): the same numbers bit for bit, except that a source
    no longer adds the exact zeros G w_i g_j d / r^3 with g_j = 0 of its test particles (which
    could only flip the sign of an exactly zero force, or make it nan when a test particle sat
    on a source).  A term on i from a source k > i, + c (q_k - q_i), and one from a source k < i,
    - c (q_i - q_k), are the same number, so a test particle's sum runs over its sources in one
    loop, in registers.  (Measured and not taken: the test particles innermost, in runs between
    sources, is 20 % faster a particle but made the outer solar system's kernel 3-4 % slower.)

    The rows (the stages of a step) go four at a time through the pair loops: four independent
    square roots and divisions per pair keep the floating-point units busy where one row at a
    time waits on each (measured 19 % faster on the outer solar system, 7 % a step).  A group
    short of four repeats its last row and stores it once.  Each row receives the same
    operations in the same order as alone: the same numbers, bit for bit."""
    G = params[0]
    N = int(params[1])
    first = int(params[2 + 2 * N])
    n = Q.shape[0]
    for r in range(n):
        for a in range(3 * N):
            out[r, a] = 0.0
    for ra in range(0, n, 4):
        rb = min(ra + 1, n - 1)
        rc = min(ra + 2, n - 1)
        rd = min(ra + 3, n - 1)
        # the pairs of sources i < j: a range and a test per index costs O(N_s N) tests, and
        # the outer solar system's kernel ran 2-10 % slower with any other loop tried (bounds
        # from the sources' span, the linked list), measured
        for i in range(N):
            gi = params[2 + N + i]
            if gi == 0.0:
                continue
            wi = params[2 + i]
            for j in range(i + 1, N):
                gj = params[2 + N + j]
                if gj == 0.0:
                    continue
                xa = Q[ra, 3 * j] - Q[ra, 3 * i]
                ya = Q[ra, 3 * j + 1] - Q[ra, 3 * i + 1]
                za = Q[ra, 3 * j + 2] - Q[ra, 3 * i + 2]
                xb = Q[rb, 3 * j] - Q[rb, 3 * i]
                yb = Q[rb, 3 * j + 1] - Q[rb, 3 * i + 1]
                zb = Q[rb, 3 * j + 2] - Q[rb, 3 * i + 2]
                xc = Q[rc, 3 * j] - Q[rc, 3 * i]
                yc = Q[rc, 3 * j + 1] - Q[rc, 3 * i + 1]
                zc = Q[rc, 3 * j + 2] - Q[rc, 3 * i + 2]
                xd = Q[rd, 3 * j] - Q[rd, 3 * i]
                yd = Q[rd, 3 * j + 1] - Q[rd, 3 * i + 1]
                zd = Q[rd, 3 * j + 2] - Q[rd, 3 * i + 2]
                sa = xa * xa + ya * ya + za * za
                sb = xb * xb + yb * yb + zb * zb
                sc = xc * xc + yc * yc + zc * zc
                sd = xd * xd + yd * yd + zd * zd
                ia = G / (sa * np.sqrt(sa))
                ib = G / (sb * np.sqrt(sb))
                ic = G / (sc * np.sqrt(sc))
                id_ = G / (sd * np.sqrt(sd))
                wg = wi * gj                  # the force on i from j: G w_i g_j d / r^3
                gw = params[2 + j] * gi       # and on j from i
                _add_pair(out, ra, i, j, wg * ia, gw * ia, xa, ya, za)
                if rb > ra:
                    _add_pair(out, rb, i, j, wg * ib, gw * ib, xb, yb, zb)
                if rc > rb:
                    _add_pair(out, rc, i, j, wg * ic, gw * ic, xc, yc, zc)
                if rd > rc:
                    _add_pair(out, rd, i, j, wg * id_, gw * id_, xd, yd, zd)
        for t in range(N):                          # each test particle from every source
            if params[2 + N + t] != 0.0:
                continue
            wt = params[2 + t]
            xta, yta, zta = Q[ra, 3 * t], Q[ra, 3 * t + 1], Q[ra, 3 * t + 2]
            xtb, ytb, ztb = Q[rb, 3 * t], Q[rb, 3 * t + 1], Q[rb, 3 * t + 2]
            xtc, ytc, ztc = Q[rc, 3 * t], Q[rc, 3 * t + 1], Q[rc, 3 * t + 2]
            xtd, ytd, ztd = Q[rd, 3 * t], Q[rd, 3 * t + 1], Q[rd, 3 * t + 2]
            fxa = fya = fza = fxb = fyb = fzb = 0.0
            fxc = fyc = fzc = fxd = fyd = fzd = 0.0
            k = first
            while k < N:
                xa = Q[ra, 3 * k] - xta
                ya = Q[ra, 3 * k + 1] - yta
                za = Q[ra, 3 * k + 2] - zta
                xb = Q[rb, 3 * k] - xtb
                yb = Q[rb, 3 * k + 1] - ytb
                zb = Q[rb, 3 * k + 2] - ztb
                xc = Q[rc, 3 * k] - xtc
                yc = Q[rc, 3 * k + 1] - ytc
                zc = Q[rc, 3 * k + 2] - ztc
                xd = Q[rd, 3 * k] - xtd
                yd = Q[rd, 3 * k + 1] - ytd
                zd = Q[rd, 3 * k + 2] - ztd
                sa = xa * xa + ya * ya + za * za
                sb = xb * xb + yb * yb + zb * zb
                sc = xc * xc + yc * yc + zc * zc
                sd = xd * xd + yd * yd + zd * zd
                wg = wt * params[2 + N + k]
                ca = wg * (G / (sa * np.sqrt(sa)))
                cb = wg * (G / (sb * np.sqrt(sb)))
                cc = wg * (G / (sc * np.sqrt(sc)))
                cd = wg * (G / (sd * np.sqrt(sd)))
                fxa += ca * xa
                fya += ca * ya
                fza += ca * za
                fxb += cb * xb
                fyb += cb * yb
                fzb += cb * zb
                fxc += cc * xc
                fyc += cc * yc
                fzc += cc * zc
                fxd += cd * xd
                fyd += cd * yd
                fzd += cd * zd
                k = int(params[3 + 2 * N + k])
            out[ra, 3 * t] = fxa                    # (a repeated row stores the same numbers)
            out[ra, 3 * t + 1] = fya
            out[ra, 3 * t + 2] = fza
            out[rb, 3 * t] = fxb
            out[rb, 3 * t + 1] = fyb
            out[rb, 3 * t + 2] = fzb
            out[rc, 3 * t] = fxc
            out[rc, 3 * t + 1] = fyc
            out[rc, 3 * t + 2] = fzc
            out[rd, 3 * t] = fxd
            out[rd, 3 * t + 1] = fyd
            out[rd, 3 * t + 2] = fzd


@jit
def _add_pair(out, r, i, j, ci, cj, dx, dy, dz):
    """Row r of out: body i gets ci d, body j gets -cj d (d = x_j - x_i)."""
    out[r, 3 * i] += ci * dx
    out[r, 3 * i + 1] += ci * dy
    out[r, 3 * i + 2] += ci * dz
    out[r, 3 * j] -= cj * dx
    out[r, 3 * j + 1] -= cj * dy
    out[r, 3 * j + 2] -= cj * dz


@jit
def shortest_r3_over_m(x, g):
    """min of r^3 / (|g_i| + |g_j|) over the pairs of rows of x (N, 3) with a nonzero g among
    them (inf when there is none): the shortest two-body period is 2 pi sqrt(that / G).  The
    loop runs over the members with g != 0: O(N) for one star among test particles, no memory.
    |g| and not g: a negative mass (a source, :mod:`systems.nbody`) moves its partner as fast
    as a positive one of the same size, and a pair of opposite masses has g_i + g_j = 0 (and
    the same numbers as g_i + g_j when every mass is positive)."""
    N = x.shape[0]
    best = np.inf
    for i in range(N):
        if g[i] == 0.0:
            continue
        for j in range(N):
            if j == i or (g[j] != 0.0 and j < i):    # a pair of two sources once
                continue
            dx = x[j, 0] - x[i, 0]
            dy = x[j, 1] - x[i, 1]
            dz = x[j, 2] - x[i, 2]
            r2 = dx * dx + dy * dy + dz * dz
            t = r2 * np.sqrt(r2) / (abs(g[i]) + abs(g[j]))
            if t < best:
                best = t
    return best


@jit
def nbody_potential(q, params):
    """V(q) of the sources, q (3N,): O(N_s^2) over the sources' linked list (the pairs of
    sources in the order of the loop over all i < j they replace: the same number)."""
    G = params[0]
    N = int(params[1])
    v = 0.0
    i = int(params[2 + 2 * N])
    while i < N:
        gi = params[2 + N + i]
        j = int(params[3 + 2 * N + i])
        while j < N:
            gj = params[2 + N + j]
            dx = q[3 * j] - q[3 * i]
            dy = q[3 * j + 1] - q[3 * i + 1]
            dz = q[3 * j + 2] - q[3 * i + 2]
            v -= gi * gj / np.sqrt(dx * dx + dy * dy + dz * dz)
            j = int(params[3 + 2 * N + j])
        i = int(params[3 + 2 * N + i])
    return G * v


def source_links(is_source) -> np.ndarray:
    """[f_0 .. f_N] (N + 1,) floats, the sources as the kernels walk them (module docstring):
    f_i the first source at or after i (N for none), so f_0 is the first source and f_{i+1}
    the source after source i.  is_source: (N,) bool."""
    is_source = np.asarray(is_source, dtype=bool)
    N = is_source.size
    idx = np.where(is_source, np.arange(N), N).astype(float)
    return np.minimum.accumulate(np.append(idx, float(N))[::-1])[::-1].copy()


def kernel_params(G, masses, is_source) -> np.ndarray:
    """``[G, N, w, g, f]`` (3N + 3,), the kernels' parameters without the followers block
    (module docstring): w the mass in M (the mass for a source, 1 for a test particle), g the
    gravitating mass (0 for a test particle), f the sources' links (:func:`source_links`).
    masses, is_source: (N,)."""
    m = np.asarray(masses, dtype=float)
    return np.concatenate([[G, float(m.size)], np.where(is_source, m, 1.0),
                           np.where(is_source, m, 0.0), source_links(is_source)])


def followers_block(G, masses, is_source) -> np.ndarray:
    """The tail of the kernel parameters that lets the step solve the sources first and the test
    particles after them (:mod:`integrators.loop`, "Followers"): empty unless there are both
    sources and test particles, else ``[P, 3, 3 N_s, 3 N_s + 3, source columns (3 N_s),
    first column of each test particle (P), the sources' own kernel parameters (3 N_s + 3)]``,
    the last those of an :class:`NBody` of the sources alone (the same numbers its step
    computes with).  masses, is_source: (N,)."""
    src = np.flatnonzero(is_source)
    tp = np.flatnonzero(~np.asarray(is_source, dtype=bool))
    if src.size == 0 or tp.size == 0:
        return np.zeros(0)
    ns = src.size
    own = kernel_params(G, masses[src], np.ones(ns, dtype=bool))
    cols = (3 * src[:, None] + np.arange(3)).ravel()
    return np.concatenate([[float(tp.size), 3.0, 3.0 * ns, float(own.size)], cols, 3.0 * tp, own])


@jit
def nbody_set_masses(params, masses):
    """The kernel parameters of :meth:`NBody.separable_kernels` (``kernel_params`` then
    ``followers_block``) <- those of the same sources with the masses (N,), in place: each
    source's w and g, and its entries in the followers block's own parameters.  Every other
    entry depends on which bodies are sources, not on the masses' values: the caller keeps
    the sources (no source's mass becomes 0, no other body's nonzero, the same ``n_active``).
    The REBOUND host changes masses in place with it (a REBOUNDx operator changing a mass at
    every step)."""
    N = int(params[1])
    f = 3 * N + 3
    own = -1
    if params.shape[0] > f:                   # the followers block: its sources' own params
        own = f + 4 + int(params[f + 2]) + int(params[f])
    ns = int(params[own + 1]) if own >= 0 else 0
    k = 0
    for i in range(N):
        if params[2 + N + i] != 0.0:          # g: the gravitating mass (0: not a source)
            params[2 + i] = masses[i]
            params[2 + N + i] = masses[i]
            if own >= 0:
                params[own + 2 + k] = masses[i]
                params[own + 2 + ns + k] = masses[i]
            k += 1


@jit
def nbody_followers(params):
    """Where :func:`followers_block` starts in ``params``, or -1 when it is empty (a scene of
    sources only, or of test particles only): the step's hook (:mod:`integrators.loop`)."""
    N = int(params[1])
    at = 3 * N + 3
    return at if params.shape[0] > at else -1


@jit
def nbody_field(Xt, Xs, params, out):
    """The accelerations of test particles from the sources: row r of out (n, 3P) from the
    particles at row r of Xt (n, 3P) and the sources at row r of Xs (n, 3 N_s); params: the
    sources' own kernel parameters (the last part of :func:`followers_block`).

    Each particle sums over its sources in their order, as :func:`nbody_forces` sums a test
    particle's terms (a test particle's w is 1, so w g_k = g_k): given the same stage positions,
    the same numbers bit for bit.  The particles are the innermost loop (unsigned indices, no
    dependence between them): the compiler vectorises the square roots and divisions across
    particles, 12-15 ns a particle for 8 rows and 2 sources against 48-51 ns with the rows
    four at a time as in :func:`nbody_forces` (measured, 64 to 1000 particles)."""
    G = params[0]
    Ns = int(params[1])
    n = Xt.shape[0]
    P = np.uint64(Xt.shape[1] // 3)
    for r in range(n):
        for t in range(P):
            out[r, 3 * t] = 0.0
            out[r, 3 * t + 1] = 0.0
            out[r, 3 * t + 2] = 0.0
        for k in range(Ns):
            xs = Xs[r, 3 * k]
            ys = Xs[r, 3 * k + 1]
            zs = Xs[r, 3 * k + 2]
            gk = params[2 + Ns + k]
            for t in range(P):
                x = xs - Xt[r, 3 * t]
                y = ys - Xt[r, 3 * t + 1]
                z = zs - Xt[r, 3 * t + 2]
                d2 = x * x + y * y + z * z
                c = gk * (G / (d2 * np.sqrt(d2)))
                out[r, 3 * t] += c * x
                out[r, 3 * t + 1] += c * y
                out[r, 3 * t + 2] += c * z


class NBody(SeparableSystem):
    """N bodies under Newtonian gravity, H = sum |p_i|^2 / (2 m_i) - G sum_{i<j} m_i m_j / r_ij.

    Parameters
    ----------
    masses : array_like, shape (N,)
        Finite masses; zero-mass particles are test particles, a negative mass is a source
        (module docstring).
    G : float
        Gravitational constant (REBOUND's default is 1).
    n_active : int, optional
        Only the first ``n_active`` particles gravitate (REBOUND's ``N_active``, test particles
        of ``testparticle_type = 0``); default all.
    positions, velocities : array_like, shape (N, 3), optional
        Initial state for :meth:`initial_state` (default: not set).
    names : sequence of str, optional
        Labels of the bodies.

    Attributes
    ----------
    dim : int
        3N degrees of freedom; q = positions.ravel().
    masses : ndarray (3N,)
        The mass in M per degree of freedom: m_i for a source, 1 for a test particle (its
        momentum is its velocity), see the module docstring.
    body_masses : ndarray (N,)
    is_source : ndarray (N,) of bool

    Not a polynomial (``polynomial_degree`` is None).
    """

    polynomial_degree = None

    def __init__(self, masses, G: float = 1.0, n_active: int | None = None,
                 positions=None, velocities=None, names: Sequence[str] | None = None):
        m = np.array(masses, dtype=float).reshape(-1) if np.ndim(masses) <= 1 else None
        if m is None or m.size < 1:
            raise ValueError(f"`masses` must be a 1-d array of N >= 1 masses (got {masses!r})")
        if not np.all(np.isfinite(m)):
            raise ValueError(f"`masses` must be finite (got {m}); use 0 for test particles")
        if not (np.isfinite(G) and G > 0):
            raise ValueError(f"`G` must be a positive number (got G={G!r})")
        N = m.size
        if n_active is None:
            n_active = N
        if isinstance(n_active, bool) or not isinstance(n_active, (int, np.integer)) or not 0 <= n_active <= N:
            raise ValueError(f"`n_active` must be an integer in [0, N={N}] or None for all (got {n_active!r})")
        self.N, self.G, self.n_active = N, float(G), int(n_active)
        self.body_masses = m
        self.is_source = (np.arange(N) < self.n_active) & (m != 0)
        w = np.where(self.is_source, m, 1.0)
        self.masses = np.repeat(w, 3)
        self.dim = 3 * N
        self.body_dim = 3       # a body's coordinates (the step's error estimate, body by body)
        self._params = np.concatenate([kernel_params(self.G, m, self.is_source),
                                       followers_block(self.G, m, self.is_source)])
        self.names = list(names) if names is not None else [f"body{i}" for i in range(N)]
        if len(self.names) != N:
            raise ValueError(f"`names` must have N={N} entries (got {len(self.names)})")
        self.positions = self._check_xyz(positions, "positions")
        self.velocities = self._check_xyz(velocities, "velocities")

    def _check_xyz(self, a, name):
        if a is None:
            return None
        a = np.array(a, dtype=float)
        if a.shape != (self.N, 3) or not np.all(np.isfinite(a)):
            raise ValueError(f"`{name}` must be a finite array of shape ({self.N}, 3) (got shape {a.shape})")
        return a

    def __repr__(self) -> str:
        return f"NBody(N={self.N}, G={self.G!r}, n_active={self.n_active}, names={self.names})"

    # -- state conversions -------------------------------------------------------------
    def momenta_from_velocities(self, v) -> np.ndarray:
        """p (3N,) from velocities (N, 3) or (3N,): m v for sources, v for test particles."""
        return np.asarray(v, dtype=float).reshape(-1) * self.masses

    def velocities_from_momenta(self, p) -> np.ndarray:
        """Velocities (N, 3) from p (3N,)."""
        return (np.asarray(p, dtype=float).reshape(-1) / self.masses).reshape(self.N, 3)

    def state(self, positions, velocities) -> np.ndarray:
        """y = (q, p), shape (6N,), from positions and velocities of shape (N, 3)."""
        x = self._check_xyz(positions, "positions")
        v = self._check_xyz(velocities, "velocities")
        return np.concatenate([x.reshape(-1), self.momenta_from_velocities(v)])

    def initial_state(self) -> np.ndarray:
        if self.positions is None or self.velocities is None:
            raise ValueError("this NBody has no initial positions and velocities; pass them to "
                             "NBody(...) or use state(positions, velocities)")
        return self.state(self.positions, self.velocities)

    # -- the model ---------------------------------------------------------------------
    def potential(self, q):
        q = np.asarray(q, dtype=float)
        X = q.reshape(q.shape[:-1] + (self.N, 3))
        g = np.where(self.is_source, self.body_masses, 0.0)
        d = X[..., None, :, :] - X[..., :, None, :]
        r = np.sqrt(np.sum(d * d, axis=-1))
        iu = np.triu_indices(self.N, 1)
        gg = (g[:, None] * g[None, :])[iu]
        return -self.G * np.sum(gg / r[..., iu[0], iu[1]], axis=-1)

    def forces(self, q):
        q = np.asarray(q, dtype=float)
        Q = np.ascontiguousarray(q.reshape(-1, self.dim))
        out = np.empty_like(Q)
        self._force_numpy(Q, out)
        return out.reshape(q.shape)

    def _force_numpy(self, Q, out):
        X = Q.reshape(Q.shape[0], self.N, 3)
        w = self._params[2:2 + self.N]
        g = self._params[2 + self.N:2 + 2 * self.N]
        d = X[:, None, :, :] - X[:, :, None, :]          # d[i, j] = x_j - x_i
        r2 = np.sum(d * d, axis=-1)
        idx = np.arange(self.N)
        r2[:, idx, idx] = 1.0
        inv3 = self.G / (r2 * np.sqrt(r2))
        inv3[:, idx, idx] = 0.0
        acc = np.sum((g[None, None, :] * inv3)[..., None] * d, axis=2)
        out[:] = (w[None, :, None] * acc).reshape(Q.shape)

    def kinetic(self, p):
        """Kinetic energy of the sources (test particles carry no energy, as in REBOUND)."""
        p = np.asarray(p, dtype=float)
        src = np.repeat(self.is_source, 3)
        return 0.5 * np.sum(np.where(src, p * p / self.masses, 0.0), axis=-1)

    def angular_momentum(self, y) -> np.ndarray:
        """Total angular momentum of the sources about the origin, shape (..., 3).

        L = sum over sources of q_i x p_i (p_i = m_i v_i), the constant of motion of the closed
        system the sources form.  Test particles are left out, as :meth:`energy` leaves them
        out: their L is not conserved (the sources pull on them and feel nothing back).  On a
        scene of sources and massless test particles this is ``rebound.Simulation.
        angular_momentum()``, which also counts massive particles beyond ``N_active``.

        Parameters
        ----------
        y : array_like, shape (..., 6N)
            States (q, p); leading axes (samples) are kept.
        """
        return self._angular_momentum(y)[0]

    def angular_momentum_scale(self, y) -> np.ndarray:
        """sum over sources of |q_i| |p_i|, shape (...,): the size of the terms of
        :meth:`angular_momentum`, hence of its round-off."""
        return self._angular_momentum(y)[1]

    def _angular_momentum(self, y):
        from .angular_momentum import angular_momentum
        y = np.asarray(y, dtype=float)
        if y.shape[-1:] != (2 * self.dim,):
            raise ValueError(f"`y` must have shape (..., {2 * self.dim}) (got {y.shape})")
        x = y[..., : self.dim].reshape(y.shape[:-1] + (self.N, 3))[..., self.is_source, :]
        p = y[..., self.dim:].reshape(y.shape[:-1] + (self.N, 3))[..., self.is_source, :]
        return angular_momentum(x, p)

    @property
    def kinetic_weights(self) -> np.ndarray:
        """1 / m per degree of freedom for the sources, 0 for test particles (the kinetic
        energy :meth:`kinetic` counts)."""
        return np.where(np.repeat(self.is_source, 3), 1.0 / self.masses, 0.0)

    def separable_kernels(self):
        return nbody_forces, nbody_potential, self._params.copy()

    def separable_followers(self):
        """The step's hooks for solving the sources first and each test particle after them
        (:mod:`integrators.loop`, "Followers"): :func:`nbody_followers` and
        :func:`nbody_field`, params as :meth:`separable_kernels`; None without both sources
        and test particles (:func:`followers_block` is then empty: the step compiles no
        followers)."""
        if self.is_source.all() or not self.is_source.any():
            return None
        return nbody_followers, nbody_field

    def separable_jvp(self):
        """The force's derivative along a direction, for the tangent map
        (:mod:`integrators.variational`): :func:`nbody_force_jvp`, params as
        :meth:`separable_kernels`."""
        return nbody_force_jvp

    # -- hosts -------------------------------------------------------------------------
    def to_rebound(self, y=None):
        """A fresh ``rebound.Simulation`` with G, the masses, ``N_active`` and the state y
        (default :meth:`initial_state`)."""
        import rebound
        y = self.initial_state() if y is None else np.asarray(y, dtype=float)
        x = y[: self.dim].reshape(self.N, 3)
        v = self.velocities_from_momenta(y[self.dim:])
        sim = rebound.Simulation()
        sim.G = self.G
        for i in range(self.N):
            sim.add(m=float(self.body_masses[i]), x=x[i, 0], y=x[i, 1], z=x[i, 2],
                    vx=v[i, 0], vy=v[i, 1], vz=v[i, 2])
        if self.n_active < self.N:
            sim.N_active = self.n_active
        return sim

    @classmethod
    def from_rebound(cls, sim, names: Sequence[str] | None = None) -> "NBody":
        """The NBody model of a ``rebound.Simulation`` (G, masses, N_active, current state as
        the initial state).  Only plain Newtonian gravity is modelled: see
        :class:`hbvm_md.HBVMIntegrator` for what is refused."""
        N = sim.N
        xv = np.zeros(6 * N)
        m = np.zeros(N)
        sim.serialize_particle_data(xyzvxvyvz=xv, m=m)
        xv = xv.reshape(N, 6)
        n_active = None if sim.N_active < 0 or sim.N_active >= N else int(sim.N_active)
        return cls(m, G=sim.G, n_active=n_active, positions=xv[:, :3], velocities=xv[:, 3:],
                   names=names)


@jit
def nbody_force_jvp(Q, dQ, params, out):
    """The derivative of :func:`nbody_forces` along dQ, row by row: out[r] = (dF/dq)(Q[r]) dQ[r]
    (n, 3N), with the kernel's params (module docstring; only G, N, w and g are read).

    params whose N is given as -N (params[1]) hold a variation dg (N,) of the gravitating
    masses at 3N + 3 (after the kernel's own 3N + 3 entries; REBOUND's variational particles
    carry one in their m): the derivative along it is added, dF_i = G w_i sum_j dg_j (q_j -
    q_i) / r^3 (the force is linear in g; w, the masses of the momenta, stays: a tangent's
    momenta are w dv, so this is w times the acceleration's derivative, as REBOUND's
    variational equations take it).  (A sign, not a length: the followers' block may follow the
    kernel's entries.)

    The force on i from j, G w_i g_j d / r^3 with d = q_j - q_i, moves along dd = dq_j - dq_i by
    the tidal tensor G w_i g_j [dd / r^3 - 3 d (d . dd) / r^5]; j feels the opposite with w_j
    g_i.  As in the force kernel a test particle (g = 0) acts on nobody: a pair is visited only
    when a source is in it (a source's row and test particles' rows against the sources), so
    the cost is O(n N_s N) for N_s sources."""
    if dQ.shape[0] == 2 * Q.shape[0]:
        _second_jvp(Q, dQ, params, out)
        return
    G = params[0]
    N = abs(int(params[1]))
    for r in range(Q.shape[0]):
        for a in range(3 * N):
            out[r, a] = 0.0
        for i in range(N):
            gi = params[2 + N + i]
            if gi == 0.0:
                continue
            wi = params[2 + i]
            for j in range(N):
                gj = params[2 + N + j]
                # each pair once, from its source (from the smaller index when both are)
                if j == i or (gj != 0.0 and j < i):
                    continue
                dx = Q[r, 3 * j] - Q[r, 3 * i]
                dy = Q[r, 3 * j + 1] - Q[r, 3 * i + 1]
                dz = Q[r, 3 * j + 2] - Q[r, 3 * i + 2]
                ex = dQ[r, 3 * j] - dQ[r, 3 * i]
                ey = dQ[r, 3 * j + 1] - dQ[r, 3 * i + 1]
                ez = dQ[r, 3 * j + 2] - dQ[r, 3 * i + 2]
                r2 = dx * dx + dy * dy + dz * dz
                inv3 = G / (r2 * np.sqrt(r2))
                k = 3.0 * (dx * ex + dy * ey + dz * ez) / r2
                tx = inv3 * (ex - k * dx)
                ty = inv3 * (ey - k * dy)
                tz = inv3 * (ez - k * dz)
                ci = wi * gj                  # on i from j
                cj = params[2 + j] * gi       # on j from i
                out[r, 3 * i] += ci * tx
                out[r, 3 * i + 1] += ci * ty
                out[r, 3 * i + 2] += ci * tz
                out[r, 3 * j] -= cj * tx
                out[r, 3 * j + 1] -= cj * ty
                out[r, 3 * j + 2] -= cj * tz
    if params[1] < 0.0:
        _mass_jvp(Q, params, out)


@jit
def _second_jvp(Q, dQ, params, out):
    """The second derivative of :func:`nbody_forces` along a pair of directions, row by row:
    out[r] = F''(Q[r])[dQ[r], dQ[n + r]] (dQ: (2n, 3N), the two directions stacked; n rows
    of Q), with the derivatives along the pair's variations of the gravitating masses, dg_a
    and dg_b at 4N + 3 and 5N + 3 of params (zeros, or absent: none): the forcing of a
    second-order tangent (:func:`integrators.tangent.tangent_map`; REBOUND's second-order
    variational equations).

    With d = q_j - q_i and e = dq_j - dq_i, the pull on i from j is G w_i g_j f(d), f(d) =
    d / r^3, f'(d)[e] = e / r^3 - 3 d (d.e) / r^5 and f''(d)[ea, eb] = -3 (ea (d.eb) + eb (d.ea)
    + d (ea.eb)) / r^5 + 15 d (d.ea)(d.eb) / r^7; the masses' terms are dg_a f'(d)[eb] +
    dg_b f'(d)[ea]; j feels the opposite with w_j and i's masses."""
    G = params[0]
    N = abs(int(params[1]))
    n = Q.shape[0]
    masses = params.shape[0] >= 6 * N + 3
    A = 4 * N + 3
    B = 5 * N + 3
    for r in range(n):
        for a in range(3 * N):
            out[r, a] = 0.0
        for i in range(N):
            for j in range(i + 1, N):
                gi, gj = params[2 + N + i], params[2 + N + j]
                dai = dbi = daj = dbj = 0.0
                if masses:
                    dai, dbi, daj, dbj = params[A + i], params[B + i], params[A + j], params[B + j]
                if gi == 0.0 and gj == 0.0 and dai == 0.0 and dbi == 0.0 and daj == 0.0 \
                        and dbj == 0.0:
                    continue
                d0 = Q[r, 3 * j] - Q[r, 3 * i]
                d1 = Q[r, 3 * j + 1] - Q[r, 3 * i + 1]
                d2 = Q[r, 3 * j + 2] - Q[r, 3 * i + 2]
                a0 = dQ[r, 3 * j] - dQ[r, 3 * i]
                a1 = dQ[r, 3 * j + 1] - dQ[r, 3 * i + 1]
                a2 = dQ[r, 3 * j + 2] - dQ[r, 3 * i + 2]
                b0 = dQ[n + r, 3 * j] - dQ[n + r, 3 * i]
                b1 = dQ[n + r, 3 * j + 1] - dQ[n + r, 3 * i + 1]
                b2 = dQ[n + r, 3 * j + 2] - dQ[n + r, 3 * i + 2]
                r2 = d0 * d0 + d1 * d1 + d2 * d2
                inv3 = 1.0 / (r2 * np.sqrt(r2))
                inv5 = inv3 / r2
                inv7 = inv5 / r2
                da = d0 * a0 + d1 * a1 + d2 * a2
                db = d0 * b0 + d1 * b1 + d2 * b2
                ab = a0 * b0 + a1 * b1 + a2 * b2
                k2 = 15.0 * inv7 * da * db - 3.0 * inv5 * ab
                for c in range(3):
                    dc = d0 if c == 0 else (d1 if c == 1 else d2)
                    ac = a0 if c == 0 else (a1 if c == 1 else a2)
                    bc = b0 if c == 0 else (b1 if c == 1 else b2)
                    f2 = k2 * dc - 3.0 * inv5 * (ac * db + bc * da)
                    f1a = ac * inv3 - 3.0 * inv5 * dc * da
                    f1b = bc * inv3 - 3.0 * inv5 * dc * db
                    out[r, 3 * i + c] += G * params[2 + i] * (gj * f2 + daj * f1b + dbj * f1a)
                    out[r, 3 * j + c] -= G * params[2 + j] * (gi * f2 + dai * f1b + dbi * f1a)


@jit
def _mass_jvp(Q, params, out):
    """out[r] += G w_i sum_j dg_j (q_j - q_i) / r^3 at each row of Q: the force's derivative
    along the variation dg of the gravitating masses that follows the kernel's params
    (:func:`nbody_force_jvp`); nothing when dg is zero."""
    G = params[0]
    N = -int(params[1])
    base = 3 * N + 3
    varied = False
    for j in range(N):
        varied = varied or params[base + j] != 0.0
    if not varied:
        return
    for r in range(Q.shape[0]):
        for i in range(N):
            wi = params[2 + i]
            for j in range(N):
                dgj = params[base + j]
                if dgj == 0.0 or j == i:
                    continue
                dx = Q[r, 3 * j] - Q[r, 3 * i]
                dy = Q[r, 3 * j + 1] - Q[r, 3 * i + 1]
                dz = Q[r, 3 * j + 2] - Q[r, 3 * i + 2]
                r2 = dx * dx + dy * dy + dz * dz
                c = G * wi * dgj / (r2 * np.sqrt(r2))
                out[r, 3 * i] += c * dx
                out[r, 3 * i + 1] += c * dy
                out[r, 3 * i + 2] += c * dz
