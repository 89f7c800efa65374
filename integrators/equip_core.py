"""The compiled pieces of an EQUIP(k, s) step that call no force kernel (numba).

:mod:`integrators.loop` calls them, inside its one step, when the method's packed arrays are
EQUIP's (``Cp.shape[0] > 4``, see :class:`integrators.equip.EQUIP`): the step iterates the
Gauss coefficients gamma exactly as for HBVM(s, s), and these pieces add what EQUIP adds:

* the perturbation of the stages by alpha (:func:`stage_correction`): the Butcher matrix is
  A(alpha) = P_s X_s(alpha) P_s^T Omega with X_s(alpha) = X_s + alpha S, S the skew matrix with
  -xi_1 at (0, 1) and xi_1 at (1, 0).  Full form: Y = y0 + h P_s X_s(alpha) gamma.  Separable
  form: Q = q0 + h (A 1) v0 + h^2 A^2 M^{-1} F, with A(alpha) 1 = c + alpha P_s S e_1 and
  A(alpha)^2 = P_s X_s(alpha)^2 P_s^T Omega (P_s^T Omega P_s = I for the s Gauss points), so
  Q gains h alpha (P_s S e_1) v0 + h^2 P_s (alpha (X S + S X) + alpha^2 S^2) M^{-1} gamma_p;
* the energy condition (:func:`energy_residual`): along the path
  sigma(c h) = y0 + h sum_j int_0^c P_j gamma_j (which ends at y1), H(y1) - H(y0) =
  h sum_j gamma_j^T int_0^1 P_j(c) grad H(sigma(c h)) dc, the integral taken by the k-point
  Gauss rule at the path's points (the "discrete line integral" of HBVM(k, s): exact for a
  polynomial H of degree nu when k >= nu s / 2).  The residual is a sum of products of the
  coefficients and the projected gradients, each of the size of the power flowing between
  kinetic and potential energy, never a difference of two energies: its rounding is a few
  ulps of h |v| |F|, not of |H|;
* the secant iteration on alpha (:func:`update_alpha`) and the correction of q1 by alpha
  (:func:`commit_correction`).

Separable form, the residual (divided by h): with v0 = M^{-1} p0, gamma_q = M^{-1}(p0 e_1 +
h X_s(alpha) gamma_p) and rho = P_k^T Omega_k F(sigma_q) the projected forces,
E = v0^T (gamma_0 - rho_0) + h/2 gamma_0^T M^{-1} gamma_0 - h sum_j (X_s(alpha) gamma)_j^T
M^{-1} rho_j (the kinetic part of the line integral is exact: P_k^T Omega_k I_k = X_s).
Full form: E = sum_j gamma_j^T rho_j with rho = P_k^T Omega_k grad H(sigma).

What a host provides for EQUIP (besides what :mod:`integrators.loop` asks of every caller):
the packed arrays of :attr:`integrators.equip.EQUIP.step_arrays` (``engine.method_arrays``
returns them), work buffers sized for ``EQUIP.work_rows`` stage rows, and ``eref`` of length
EREF_EQUIP, carried whole between steps (alpha and the slope ride in eref[1:3]; ``loop.attempt``
copies all of it into the trial and a host commits all of it back).

Measured and not adopted (outer solar system, HLW's, over 1e6 days, EQUIP(8, 6) adaptive at
epsilon 1e-3 of the earlier controller, where every step measures the slope: 110 force evaluations a step against
HBVM(8, 6)'s 56, energy 1.1e-14): forgetting alpha and the slope once alpha moves E by less
than 1/16 or 1/64 ulp of its terms (the next steps then take Gauss's residual, at round-off,
without a slope) cost 56-66 evaluations a step but drifted the energy to 2-4e-14, since
Gauss's residual there is a systematic 0.2-0.9 ulp that alpha's last correction removes at
every step; moving gamma to alpha's last correction along the secant through the last two
converged coefficients, instead of iterating it again, drifted it to 1.5e-12.  EQUIP's
defaults through REBOUND are s = 8 (at epsilon 1e-17 of issue 58's controller) instead (:data:`integrators.equip.DEFAULT_S`),
where Gauss's residual stays far below an ulp and alpha is seldom needed.

Every function here runs as plain Python under ``NUMBA_DISABLE_JIT=1``.
"""
from __future__ import annotations

import numpy as np

from .core import EPS, dd_add, work_sizes
from .jit import jit
from .pointers import view, view1

# the planes of the packed arrays (see integrators.equip.EQUIP.step_arrays): Cp (planes, K, s),
# K = max(k, s); planes 0-3 are Gauss's (C2, C2_lo, I, I_lo: what HBVM(s, s) packs)
CP_PATH_C2, CP_PATH_C2_LO, CP_PATH_I, CP_PATH_I_LO = 4, 5, 6, 7     # HBVM(k, s)'s C2 and I
CP_PS, CP_B1, CP_B2, CP_PATH_S, CP_VEC, CP_X, CP_X_LO = 8, 9, 10, 11, 12, 13, 14
N_CP = 15
# CP_PS: P_s S; CP_B1: P_s (X_s S + S X_s); CP_B2: P_s S^2 (rows < s); CP_PATH_S: I_k S;
# CP_VEC: columns 0, 1 = the path's nodes tau_k and their rounding remainders (rows < k);
# CP_X, CP_X_LO: X_s and its rounding remainders (rows < s).  ts (4, s) = [X0, X0_lo (Gauss's), S's row 0, P_s S e_1]
TS_S0, TS_PSE1 = 2, 3
WP_PATH, WP_PATH_LO = 2, 3   # Wp (4, s, K): W, W_lo (Gauss), P_k^T Omega_k (the path's
                             # projection) and its rounding remainders
# the state carried between steps in eref (length EREF_EQUIP): [energy, alpha, dE/dalpha]
EREF_EQUIP = 3
# the per-step scratch es (ES entries): alpha, alpha and residual of the last measurement,
# the slope dE/dalpha, updates made, whether the slope was measured in this step; then the
# root search of the fallback (update_alpha): its mode (0: the secant; j + 1: scanning, the
# j-th offset being measured; -1, -2, -3: regula falsi (Illinois) in a bracket, nothing / A /
# B kept last), the centre of the scan, its first direction, and two points (alpha, E): the
# last of each side of the scan, then the bracket's ends A and B
ES = 13
ES_MODE, ES_CENTRE, ES_DIR, ES_A, ES_EA, ES_B, ES_EB = 6, 7, 8, 9, 10, 11, 12
ENERGY_ULPS = 16.0    # a residual that stops decreasing within this many ulps of its terms'
                      # size is round-off (two ulps: converged at once)
MAX_UPDATES = 12      # alpha updates a step at most (two or three are typical)
ALPHA_MAX = 0.25      # |alpha| beyond this: the step is far too long for the energy condition
FRESH_ULPS = 32.0     # the step past the root that measures this step's slope, in ulps of E
ALPHA_PROBE = 1e-6    # the first secant step when no slope is known (the first step)
SCAN_STEP = 1.0 / 32.0   # the fallback's first offset from the centre (doubled every two)
ALPHA_LIMIT = 1.0     # the fallback's largest offset: no root closer than this fails the step
FALLBACK_UPDATES = 36  # alpha updates the fallback may add to MAX_UPDATES
# update_alpha's answers
CONVERGED, UPDATED, FAILED, REITERATE = 0, 1, 2, 3
# the step's status when update_alpha fails (after core's OK .. TOO_SMALL, 0 .. 4; mapped to
# integrators.errors.EnergyConditionError by errors.step_error, the one table)
NO_ENERGY_ROOT = 5


@jit
def extra_work(s, u, K):
    """Float entries EQUIP's views take after :func:`core.carve`'s (see :func:`carve`)."""
    return 2 * K * u + s * u + 2 * K + ES


@jit
def carve(work, n, s, u, m, d, K):
    """EQUIP's work arrays, views of ``work`` after :func:`core.carve`'s: the path's points Xk
    and their forces (or gradients) Fk (K, u), the projected forces rho (s, u), the path's h tau_k as exact pairs htk, htk_lo (K) and the scratch es (ES).  K = 0
    (HBVM) gives empty views and reads nothing."""
    o = work_sizes(n, s, u, m, d)[0]
    if K > 0 and work.shape[0] < o + extra_work(s, u, K):
        raise ValueError("internal error: the step's work buffer is too short for EQUIP "
                         "(integrators.equip.EQUIP.work_rows)")
    Xk = view(work, o, K, u)
    Fk = view(work, o + K * u, K, u)
    o += 2 * K * u
    kk = s if K > 0 else 0
    rho = view(work, o, kk, u)
    o += kk * u
    htk = view1(work, o, K)
    htk_lo = view1(work, o + K, K)
    es = view1(work, o + 2 * K, ES if K > 0 else 0)
    return Xk, Fk, rho, htk, htk_lo, es


@jit
def start(es, eref):
    """The step's scratch from the state carried between steps: alpha and the slope of the
    last committed step (its alpha is the first guess; nan: none yet, start from Gauss)."""
    a = eref[1]
    es[0] = a if np.isfinite(a) else 0.0
    es[1] = np.nan
    es[2] = np.nan
    es[3] = eref[2]
    es[4] = 0.0
    es[5] = 0.0
    es[ES_MODE] = 0.0


@jit
def finish(es, eref):
    """Carry alpha and the slope to the next step (after a committed step only)."""
    eref[1] = es[0]
    eref[2] = es[3]


@jit
def stage_correction(full, y, minv, g, a, sc, alpha, method, X):
    """Add what alpha changes to the Gauss stages X (s, u) built for alpha = 0 (the corrections
    are small: their own rounding is far below the stages'; ``a`` = M^{-1} gamma_p as the
    separable stage function left it; sc: the step's constants, method: EQUIP's packed arrays,
    :mod:`integrators.records`).  Full form: X += h alpha P_s S gamma.  Separable:
    X += h alpha (P_s S e_1) v0 (pse1) + h^2 (alpha B1 + alpha^2 B2) M^{-1} gamma_p."""
    if alpha == 0.0:
        return
    h, h2 = sc.h, sc.h2
    PS, B1, B2, pse1 = method.Cp[CP_PS], method.Cp[CP_B1], method.Cp[CP_B2], method.ts[TS_PSE1]
    s, u = g.shape
    if full:
        for i in range(s):
            for j in range(u):
                acc = 0.0
                for l in range(s):
                    acc += PS[i, l] * g[l, j]
                X[i, j] += h * alpha * acc
        return
    m = u
    for i in range(s):
        ci = h * alpha * pse1[i]
        for j in range(m):
            acc = 0.0
            for l in range(s):
                acc += (B1[i, l] + alpha * B2[i, l]) * a[l, j]
            X[i, j] += ci * (y[m + j] * minv[j]) + h2 * (alpha * acc)


@jit
def path_correction(g, minv, h2, alpha, IkS, Xk):
    """Separable form: the path's positions gain h^2 alpha (I_k S) M^{-1} gamma_p (gamma_q
    carries X_s(alpha))."""
    if alpha == 0.0:
        return
    K = Xk.shape[0]
    s, m = g.shape
    for i in range(K):
        for j in range(m):
            acc = 0.0
            for l in range(s):
                acc += IkS[i, l] * g[l, j]
            Xk[i, j] += h2 * alpha * acc * minv[j]


@jit
def energy_residual(full, y, minv, kin_w, g, rho, h, alpha, X, X_lo, S0):
    """(E, scale, weight): E = (H(y1) - H(y0)) / h by the discrete line integral (module
    docstring), scale the sum of the magnitudes of its terms (E's own rounding is a few ulps
    of it), weight the sum of the magnitudes of what multiplies the projected forces rho (the
    forces' rounding through the stage values, L eps |q|, enters E through it).  X, X_lo:
    X_s (s, s) and its rounding remainders (the path's positions carry X_s to twice the
    working precision; X_s rounded once here would bias E by an ulp of its terms step after
    step: measured, a drift of 1.8e-13 over 5000 steps of Kepler with s = 4); S0: S's row 0 (the rows of S below are its transpose's: S = xi_1 (e_2 e_1^T -
    e_1 e_2^T)).  kin_w: the kinetic weights (m,) of the separable form; a coordinate with
    kin_w = 0 (an N-body test particle) is outside H: neither T nor V depends on it, so it has
    no term (its force, from the sources, is no gradient of H; with its terms alpha conserved
    H plus the test particles' own, not conserved, energies: the sources' energy drifted to
    1.9e-11 over 1e5 days of the outer solar system with two test particles)."""
    s, u = g.shape
    E = 0.0
    scale = 0.0
    weight = 0.0
    if full:
        for i in range(s):
            for j in range(u):
                t = g[i, j] * rho[i, j]
                E += t
                scale += abs(t)
                weight += abs(g[i, j])
        return E, scale, weight
    m = u
    xi1 = -S0[1]
    for j in range(m):
        if kin_w[j] == 0.0:
            continue
        v = y[m + j] * minv[j]
        t = v * (g[0, j] - rho[0, j])
        E += t
        scale += abs(v) * (abs(g[0, j]) + abs(rho[0, j]))
        weight += abs(v)
        t = 0.5 * h * g[0, j] * g[0, j] * minv[j]
        E += t
        scale += abs(t)
        for i in range(s):
            xg = 0.0
            for l in range(s):
                xg += X[i, l] * g[l, j] + X_lo[i, l] * g[l, j]
            if i == 0:
                xg -= alpha * xi1 * g[1, j]
            elif i == 1:
                xg += alpha * xi1 * g[0, j]
            t = h * xg * minv[j] * rho[i, j]
            E -= t
            scale += abs(t)
            weight += abs(h * xg * minv[j])
    return E, scale, weight


@jit
def update_alpha(es, E, scale, floor):
    """One step of the secant iteration on alpha for E(alpha) = 0 (es: the step's scratch).

    Returns CONVERGED, REITERATE (converged, with alpha's last correction in es[0]: gamma is
    iterated to convergence for it, without measuring again), UPDATED (a new alpha in es[0])
    or FAILED (E not finite, or no root found by the fallback, :func:`start_root_search`:
    no sign change of E within ALPHA_LIMIT of where the secant stopped; the loop's status
    NO_ENERGY_ROOT).  A secant step beyond ALPHA_MAX with the last step's slope is replaced by
    a probe that measures this step's slope (dE/dalpha may have changed sign since: its
    leading term is -xi_1^2 h^3 H'''(f, f, f), :mod:`integrators.equip`); one beyond ALPHA_MAX
    with this step's own slope, or MAX_UPDATES updates, starts the fallback.  Where the
    secant converges the answers are those of the secant alone, bit for bit.

    The slope is the secant of the last two measurements when their residuals differ by more
    than their rounding (four ulps of the terms' size), else the last step's (E(alpha) is
    smooth in time; divided by 8 after an update that moved E by its rounding only), else
    (the first step) a probe.  Converged: |E| at its round-off (two ulps of the terms' size,
    or within ENERGY_ULPS ulps (or ``floor``) and no longer halved by the last update,
    the stop rule of the gamma iteration applied to alpha) with a slope measured in this step;
    then one last correction alpha -= E / slope, for which gamma is iterated again to
    convergence (one polish only left gamma partly at the previous alpha, which can be a probe
    far from the root: the outer solar system drifted to 1.5e-12 over 1e6 days), without
    measuring again: the secant approaches the root from one side, and a residual left with
    the same sign step after step makes the energy drift (measured: 2.4e-13 over 1e4 steps of
    Kepler with EQUIP(12, 4) without it, and 2.5e-14 over 5000 steps with the last step's
    slope, which changes sign near apocentre).  A residual at round-off that no change of
    alpha moves (a quadratic H, which every alpha conserves) is converged as it is.
    ``floor``: E's rounding through the forces (the stop rule's floor,
    :func:`integrators.core.stop_action`, times the residual's weight of the forces): a
    residual that stops decreasing below it is converged (two bodies far from the origin, FPU's
    stiff springs: residuals of 100 ulps of the terms, which no alpha reduces, failed the
    step without it)."""
    tol = ENERGY_ULPS * EPS * scale
    if not np.isfinite(E):
        return FAILED
    E_prev = es[2]
    measured = np.isfinite(E_prev) and es[0] != es[1]
    if measured and abs(E - E_prev) > 4.0 * EPS * scale:
        es[3] = (E - E_prev) / (es[0] - es[1])
        es[5] = 1.0
    elif measured and abs(E) > 0.5 * abs(E_prev):
        # the last step moved E by its rounding only: the slope was far too steep (the last
        # step's, 100 times the present one near apocentre, measured): longer steps
        es[3] *= 0.125
    D = es[3]
    slope = np.isfinite(D) and D != 0.0
    at_round_off = abs(E) <= 2.0 * EPS * scale or (
        abs(E) <= max(tol, floor) and np.isfinite(E_prev) and abs(E) >= 0.5 * abs(E_prev))
    if at_round_off and (es[5] > 0.0 or not slope or (measured and abs(E - E_prev) <= max(4.0 * EPS * scale, floor))):
        if es[5] > 0.0 and abs(E / D) <= ALPHA_MAX and E != 0.0:
            es[0] -= E / D
            return REITERATE
        return CONVERGED
    if es[ES_MODE] != 0.0:
        return root_search(es, E)
    if es[4] >= MAX_UPDATES:
        return start_root_search(es, E, D)
    es[1] = es[0]
    es[2] = E
    if slope:
        a = es[0] - E / D
        if es[5] == 0.0 and abs(E) <= tol:
            # small already with the last step's slope: step past the root by a resolvable
            # amount, so that the next residual gives this step's slope
            a += FRESH_ULPS * EPS * scale / abs(D)
    else:
        a = es[0] + ALPHA_PROBE
    if not (abs(a) <= ALPHA_MAX):
        if es[5] == 0.0 and slope:
            # the last step's slope sends alpha out of range: dE/dalpha changes along the
            # trajectory and may have changed sign since (its leading term is a third
            # derivative of H, module docstring of integrators.equip): measure this step's
            a = es[0] + ALPHA_PROBE
        else:
            return start_root_search(es, E, D)
    es[0] = a
    es[4] += 1.0
    return UPDATED


@jit
def start_root_search(es, E, D):
    """The fallback of :func:`update_alpha` when the secant with this step's own slope leaves
    |alpha| <= ALPHA_MAX, or makes no progress in MAX_UPDATES updates: E(alpha) is smooth, but
    the secant's linear model does not hold so far out (E is nearly quadratic in alpha where
    dE/dalpha passes through zero).  The point just measured, (es[0], E), becomes the centre of
    a scan at offsets +-SCAN_STEP, +-2 SCAN_STEP, +-4 SCAN_STEP, ... (first towards the
    secant's side) up to ALPHA_LIMIT, and the first sign change of E on either side gives a
    bracket, narrowed by regula falsi (:func:`root_search`): the root closest to the centre,
    never a point that is not a root (the step then fails)."""
    c = es[0]
    es[1] = c
    es[2] = E
    direction = 1.0
    if np.isfinite(D) and D != 0.0 and E / D > 0.0:
        direction = -1.0
    es[ES_CENTRE] = c
    es[ES_DIR] = direction
    es[ES_A] = c
    es[ES_EA] = E
    es[ES_B] = c
    es[ES_EB] = E
    es[ES_MODE] = 1.0
    es[0] = c + direction * SCAN_STEP
    es[4] += 1.0
    return UPDATED


@jit
def root_search(es, E):
    """One step of the fallback's scan or regula falsi (:func:`start_root_search`) from the
    residual E measured at es[0]; UPDATED (the next alpha in es[0]) or FAILED (no sign change
    up to ALPHA_LIMIT from the centre, or a bracket narrowed to adjacent numbers without a
    residual at round-off: E is not continuous there)."""
    if es[4] >= MAX_UPDATES + FALLBACK_UPDATES:
        return FAILED
    mode = es[ES_MODE]
    a = es[0]
    es[1] = a
    es[2] = E
    if mode > 0.0:
        j = int(mode) - 1
        ia, ie = (ES_A, ES_EA) if j % 2 == 0 else (ES_B, ES_EB)
        Ep = es[ie]
        if (E > 0.0) != (Ep > 0.0):
            # a sign change between this side's last point and this one: the bracket
            es[ES_A] = es[ia]
            es[ES_EA] = Ep
            es[ES_B] = a
            es[ES_EB] = E
            mode = -1.0
        else:
            es[ia] = a
            es[ie] = E
            j += 1
            offset = SCAN_STEP * 2.0 ** (j // 2)
            if offset > ALPHA_LIMIT:
                return FAILED
            side = 1.0 if j % 2 == 0 else -1.0
            es[ES_MODE] = j + 1.0
            es[0] = es[ES_CENTRE] + side * es[ES_DIR] * offset
            es[4] += 1.0
            return UPDATED
    elif (E > 0.0) == (es[ES_EA] > 0.0):
        es[ES_A] = a
        es[ES_EA] = E
        if mode == -2.0:           # A kept twice: Illinois halves B's residual
            es[ES_EB] *= 0.5
        mode = -2.0
    else:
        es[ES_B] = a
        es[ES_EB] = E
        if mode == -3.0:
            es[ES_EA] *= 0.5
        mode = -3.0
    aA, eA, aB, eB = es[ES_A], es[ES_EA], es[ES_B], es[ES_EB]
    new = (aA * eB - aB * eA) / (eB - eA)
    if not (min(aA, aB) < new < max(aA, aB)):
        return FAILED
    es[ES_MODE] = mode
    es[0] = new
    es[4] += 1.0
    return UPDATED


@jit
def commit_correction(yt, cyt, minv, h, g, alpha, S0):
    """Separable form: q1 gains h^2 M^{-1} alpha (S gamma_p)_0 (X_s(alpha)'s first row),
    added to the double-double state (a small term: its rounding is below q1's)."""
    if alpha == 0.0:
        return
    s, m = g.shape
    for j in range(m):
        acc = 0.0
        for l in range(s):
            acc += S0[l] * g[l, j]
        dd_add(yt, cyt, j, h * (h * alpha * acc) * minv[j], 0.0)
