"""The tangent map of one HBVM(k, s) step: the Jacobian of the discrete step y1 = Phi_h(y0)
applied to tangent vectors, and the MEGNO accumulated from it.

Like :mod:`integrators.loop` this file is written once and bound to kernels by
:mod:`integrators.specialise`: its text is appended to the loop's, with a third kernel,
``_force_jvp(X, dX, params, out)``, writing for each row the derivative of the force kernel
along dX (separable form: dF/dq(Q_i) dQ_i; full form: Hess H(Y_i) dY_i).  Compiled kernels give
a compiled tangent map; anything else runs this same text as Python.

The linearised step.  The step's unknowns are the coefficients gamma (s, u) of the fixed point
gamma = W f(stages(y0, gamma)) (:mod:`integrators.core`); the stages are affine in (y0, gamma):

* separable: Q_i = q0 + h tau_i v0 + h^2 sum_l C2_il M^-1 gamma_l, and f = F(Q);
* full: Y_i = y0 + h sum_l I_il gamma_l, and f = J grad H(Y).

Differentiating the fixed point at the step's converged gamma, a tangent vector dy0 gives

    d gamma = W K (dX0 + (stages of d gamma)),   K_i = the force's Jacobian at stage i,

linear in d gamma and contracting exactly as the step's own iteration did (the same matrix
W K C2 h^2 is the Jacobian of the fixed-point map), and then the commit, itself linear:
dq1 = dq0 + h M^-1 dp0 + h^2 M^-1 (X_s d gamma)_1, dp1 = dp0 + h d gamma_1 (full form:
dy1 = dy0 + h d gamma_1).  So every piece of the step is reused as it is, fed with the tangent:
``core.stage_positions`` / ``full_stages`` with (dy0, 0) for (y0, cy0) give the stages of the
tangent, ``core.project`` the fixed-point update, ``core.newton_update`` the simplified Newton
update with the step's own Gauss matrices (when the step used Newton), and ``core.commit_separable`` / ``commit_full`` the commit.  The only new
operation is the force's derivative.  The result is the derivative of the map the step
computes (its fixed point solved exactly), to the iteration's round-off: what a central
difference of two steps converges to as the increment goes to zero.

The initial guess of each tangent's d gamma is the previous step's, extrapolated with the
step's own matrix E (as the step guesses gamma): a tangent vector changes by O(h) a step, so
the guess starts as close as the step's own.
"""
from typing import TYPE_CHECKING

import numpy as np

from integrators.core import (DIVERGED, EPS, NARROW, NOT_FINITE, OK, ROUNDOFF_ULPS,
                              STATE_ULPS, all_finite, carve, commit_full, commit_separable, copy1,
                              copy2, full_stages, full_stages_narrow, guess, guess_narrow, max_abs,
                              max_abs2, newton_update, project, project_narrow, stage_positions,
                              stage_positions_narrow, step_constants, symplectic, work_sizes)
from integrators.pointers import view, view1
from integrators.records import StepConstants

_force_jvp = None    # bound by integrators.specialise
_NEWTON = True       # as integrators.loop's (False in a step built without Newton: the
                     # generated module binds it once for both texts)
TANGENT_FAILED = 16  # run_variational's return for a step whose tangent map failed: + status
if TYPE_CHECKING:
    # run_variational calls the loop's advance and energy_parts: integrators.specialise appends
    # this text to the loop's, where they are the loop's bound to the same kernels (imported
    # here for readers and linters only: integrators.loop's own are not bound to any kernel)
    from integrators.loop import advance, energy_parts, tableau


def evaluate_jvp(full, X, dX, params, dF, dG):
    """dF <- the derivative of the right-hand side at the stages X along dX: dF/dq dX
    (separable) or J Hess H dX (full; dG is scratch)."""
    if full:
        _force_jvp(X, dX, params, dG)
        symplectic(dG, dF)
    else:
        _force_jvp(X, dX, params, dF)


def tangent_converged(delta, scale, dF, hstate, previous):
    """The stop rule of the linear iteration: 1 converged, 0 iterate, -NOT_FINITE.

    Converged when the increment is within two ulps of the coefficients d gamma, or has stopped
    decreasing (``previous``: the last increment) at its round-off level: ROUNDOFF_ULPS ulps
    of the larger of d gamma and the stage derivatives dF, or moving the new tangent by at
    most STATE_ULPS ulps of its largest component (``hstate``), the levels of the step's own
    rule (``core.stop_action``).  Unlike the step's rule a rise above round-off is no failure:
    the linear iteration's matrix is the step's (its spectral radius below one when the step
    converged), but not normal, and its increments can rise for an iteration before they fall
    (measured: the full form of Kepler, e = 0.6, h = 0.1, twice in eight iterations); a
    divergent one is stopped by the iteration cap."""
    if not np.isfinite(delta):
        return -NOT_FINITE
    if delta <= 2.0 * EPS * scale:
        return 1
    if delta >= previous and (delta <= ROUNDOFF_ULPS * EPS * max(scale, max_abs2(dF))
                              or hstate <= STATE_ULPS):
        return 1
    return 0


def tangent_sizes(n, s, u, m, d):
    """(float, complex) lengths of the tangent map's work buffers: the step's own
    (``core.work_sizes``, cut by ``core.carve``: its X holds the converged stages, Xp, F, G the
    tangent's stages and derivatives, g its d gamma, yt, cyt the new tangent), d zeros, and
    a second-order tangent's scratch: the stages of its two first-order tangents (2n, u) and
    its forcing (n, u)."""
    nf, nc = work_sizes(n, s, u, m, d)
    return nf + d + 3 * n * u, nc


def stages(full, narrow, y, cy, minv, g, tab, sc, a, X, R, exact):
    """X <- the stages of the coefficients g from the double-double state (y, cy): the stage
    positions (separable) or stage values (full), by the core's pieces as the step picks them
    (tab, sc: the method's arrays and the step's constants, :mod:`integrators.records`)."""
    if full:
        if narrow:
            full_stages_narrow(y, cy, g, tab.I, tab.I_lo, sc.h, X, exact)
        else:
            full_stages(y, cy, g, tab.I, tab.I_lo, sc.h, X, R, exact)
    elif narrow:
        stage_positions_narrow(y, cy, minv, g, tab.C2, tab.C2_lo, sc, a, X, exact)
    else:
        stage_positions(y, cy, minv, g, tab.C2, tab.C2_lo, sc, a, X, R, exact)


def tangent_map(system, y0, cy0, gamma, h, E, method, newton, max_iter, tan):
    """V (nv, d) <- dPhi_h/dy0 V: the tangent vectors carried through the step of size h from
    the double-double state (y0, cy0) whose converged coefficients are gamma (s, u).  The
    records (:mod:`integrators.records`): ``tan`` holds V, DG, Vt, DGt, tw, tcw, tcount and P
    (nv, p): each tangent's params for the jvp kernel, or p = 0 for the system's (a parameter
    varied along the tangent, as a mass of REBOUND's variational particles: the kernel's
    derivative along it is part of the linearised stage equations), and O (nv, 3): each
    tangent's order, and a second-order one's two first-order tangents (earlier rows of V),
    whose forcing the kernel computes when handed 2n rows of directions (separable form only:
    :func:`systems.nbody.nbody_force_jvp`).

    DG (nv, s, u): each tangent's coefficients d gamma of the previous step (zero: none), the
    initial guess extrapolated with E, and replaced by this step's.  (NV, NVinv, NM): the
    step's simplified-Newton matrices, NM of shape (0, u, u) for the fixed-point iteration.
    Vt, DGt: trial arrays shaped as V, DG; tw, tcw: work buffers (:func:`tangent_sizes`).
    tcount[0] += iterations, tcount[1] += stage evaluations of the jvp; tcount[2] = the last
    tangent's iterations.  Returns OK, or DIVERGED / NOT_FINITE with V and DG unchanged."""
    full, minv, _, params = system
    NV, NVinv, NM = newton
    V, DG, Vt, DGt, tw, tcw, tcount, P, O = tan
    tab = tableau(method)
    tau, tau_lo, X0, X0_lo, W = tab.tau, tab.tau_lo, tab.X0, tab.X0_lo, tab.W
    n = tau.shape[0]
    s, u = gamma.shape
    m = minv.shape[0]
    d = y0.shape[0]
    narrow = u < NARROW
    newton = NM.shape[0] > 0
    ht, ht_lo, _, dq, dq_lo, a, pg, dg, X, dF, dG, dX, _, vt, cvt, R, Rt, Z = carve(
        tw, tcw, n, s, u, m, d)
    if tw.shape[0] < tangent_sizes(n, s, u, m, d)[0]:    # (views are not bounds-checked)
        raise ValueError("internal error: the tangent map's work buffer is shorter than "
                         "tangent_sizes says")
    off = work_sizes(n, s, u, m, d)[0]
    zero = view1(tw, off, d)
    for j in range(d):
        zero[j] = 0.0
    # a second-order tangent's scratch: its first-order tangents' stages, stacked, and forcing
    pair = view(tw, off + d, 2 * n, u)
    dXa = view(tw, off + d, n, u)
    dXb = view(tw, off + d + n * u, n, u)
    S = view(tw, off + d + 2 * n * u, n, u)
    h2, h2_lo = step_constants(h, tau, tau_lo, ht, ht_lo)
    sc = StepConstants(h, ht, ht_lo, h2, h2_lo)
    # the stages at the converged coefficients (as the step's last, compensated evaluation)
    stages(full, narrow, y0, cy0, minv, gamma, tab, sc, a, X, R, True)
    for v in range(V.shape[0]):
        dy = V[v]
        # a tangent's own params (a variation of a parameter the force depends on, e.g. a mass:
        # the jvp then adds the force's derivative along it, the same at every iteration)
        pv = params if P.shape[1] == 0 else P[v]
        # A second-order tangent (the second derivative of the step along two first-order
        # tangents a, b, as REBOUND's second-order variational particles): differentiating the
        # fixed point twice gives the first-order equation for its d gamma plus a constant
        # forcing, the force's second derivative along the stages of a and b (the stage map and
        # the commit are affine, so nothing else): those stages come from a's and b's tangents
        # before the step and their coefficients of this step (DGt, mapped above).
        second = O[v, 0] == 2
        if second:
            ia, ib = int(O[v, 1]), int(O[v, 2])
            if full or not (0 <= ia < v and 0 <= ib < v):
                raise ValueError("internal error: a second-order tangent needs the separable "
                                 "form and its first-order tangents before it")
            stages(full, narrow, V[ia], zero, minv, DGt[ia], tab, sc, a, dXa, R, False)
            stages(full, narrow, V[ib], zero, minv, DGt[ib], tab, sc, a, dXb, R, False)
            _force_jvp(X, pair, pv, S)
            tcount[1] += n
        if narrow:
            guess_narrow(E, DG[v], dg)
        else:
            guess(E, DG[v], dg)
        previous = np.inf
        yscale = EPS * max_abs(dy)
        status = DIVERGED
        it = 0
        while it < max_iter:
            it += 1
            # the tangent's stages: the step's affine stage map with (dy0, 0) for (y0, cy0)
            stages(full, narrow, dy, zero, minv, dg, tab, sc, a, dX, R, False)
            evaluate_jvp(full, X, dX, pv, dF, dG)
            tcount[1] += n
            if second:
                for i in range(n):
                    for j in range(u):
                        dF[i, j] += S[i, j]
            if _NEWTON and newton:
                if narrow:
                    project_narrow(W, dF, pg)
                else:
                    project(W, dF, pg, R)
                delta, scale = newton_update(dg, pg, NV, NVinv, NM, Rt, Z)
            else:
                if narrow:
                    delta, scale = project_narrow(W, dF, dg)
                else:
                    delta, scale = project(W, dF, dg, R)
            hstate = abs(h) * delta / yscale if yscale > 0.0 else np.inf
            action = tangent_converged(delta, scale, dF, hstate, previous)
            previous = delta
            if action == 1:
                status = OK
                break
            if action < 0:
                status = -action
                break
        tcount[0] += it
        tcount[2] = it
        if status != OK:
            return status
        copy1(vt, dy)
        copy1(cvt, zero)
        if full:
            commit_full(vt, cvt, h, dg)
        else:
            commit_separable(vt, cvt, minv, h, dg, X0, X0_lo, dq, dq_lo)
        for j in range(d):
            Vt[v, j] = vt[j] - cvt[j]
        if not all_finite(Vt[v]):
            return NOT_FINITE
        copy2(DGt[v], dg)
    for v in range(V.shape[0]):
        copy1(V[v], Vt[v])
        copy2(DG[v], DGt[v])
    return OK


def megno_step(mg, t, dy, wv):
    """Advance the MEGNO accumulator ``mg`` to time t with the tangent dy (d,), its norm
    |dy|_w = sqrt(sum (wv_j dy_j)^2) (wv: 1 for positions, 1/m for momenta: the (dx, dv) norm
    REBOUND's variational particles use).

    Cincotta and Simo (2000): Y(t) = (2 / t) int_0^t (delta' . delta / delta . delta) t' dt'
    and <Y>(t) = (1 / t) int_0^t Y dt', t measured from the start.  The integrand is
    d ln|delta| / dt' times t', and the discrete tangent gives ln|delta| exactly at the step
    ends, so over a step the integral is taken as (t_n + t_(n+1)) / 2 (ln|delta_(n+1)| -
    ln|delta_n|) (exact when ln|delta| is linear over the step, second order otherwise), and
    <Y> by the trapezoidal rule on Y.  Regular orbits: |delta| ~ t, Y -> 2; chaotic:
    |delta| ~ exp(lambda t), <Y> ~ lambda t / 2.

    mg = [t0, ln|delta_0|, t_prev, ln|delta_prev|, int (t' d ln|delta|), int Y dt', Y_prev]
    (:class:`integrators.variational.Megno`)."""
    acc = 0.0
    for j in range(dy.shape[0]):
        x = wv[j] * dy[j]
        acc += x * x
    lnd = 0.5 * np.log(acc)
    tau_prev = mg[2] - mg[0]
    tau = t - mg[0]
    mg[4] += 0.5 * (tau_prev + tau) * (lnd - mg[3])
    y = 2.0 * mg[4] / tau if tau != 0.0 else 0.0
    mg[5] += 0.5 * (mg[6] + y) * (tau - tau_prev)
    mg[2] = t
    mg[3] = lnd
    mg[6] = y


def run_variational(system, state, h, E, method, newton, opts, wk, tan, var, samples):
    """``samples.nsteps`` steps of :func:`advance` (arguments as for :func:`run`), each followed
    by the tangent map (:func:`tangent_map`, at most var.max_iter iterations) of the tangent
    vectors tan.V (nv, d) and, when var.mg has entries, the MEGNO of V[0] (:func:`megno_step`,
    weights var.wv).  var.y0, var.cy0 (d), var.gsave (s, u), var.snap (>= len(counters)):
    scratch for the state before a step.  A step whose tangent map fails is taken back: state,
    clock, coefficients, counters and tangents as before it, and status + TANGENT_FAILED
    returned (a failed step: its status).  Samples (none when
    samples.every is 0) at steps every, 2 every, ... (the caller records step 0): t, y, H into
    samples.t, .y, .e, and V and the MEGNO <Y> into var.out_v (n, nv, d) and var.out_m.
    (:class:`integrators.records.Variational`)."""
    full, _, kin_w, params = system
    y, cy, gamma, eref, clock = state
    counters = wk.counters
    V = tan.V
    tmax_iter, y0, cy0, gsave, snap, mg, wv, out_v, out_m = var
    nsteps, sample_every, out_t, out_y, out_e = samples
    isample = 0
    for istep in range(nsteps):
        copy1(y0, y)
        copy1(cy0, cy)
        copy2(gsave, gamma)
        e0 = eref[0]
        t0, ct0 = clock[0], clock[1]
        for i in range(counters.shape[0]):
            snap[i] = counters[i]
        status = advance(system, state, h, E, method, newton, opts, wk)
        if status != OK:
            return status
        status = tangent_map(system, y0, cy0, gamma, h, E, method, newton, tmax_iter, tan)
        if status != OK:
            copy1(y, y0)
            copy1(cy, cy0)
            copy2(gamma, gsave)
            eref[0] = e0
            clock[0] = t0
            clock[1] = ct0
            for i in range(counters.shape[0]):
                counters[i] = snap[i]
            return status + TANGENT_FAILED
        if mg.shape[0] > 0:
            megno_step(mg, clock[0], V[0], wv)
        if sample_every > 0 and (istep + 1) % sample_every == 0:
            out_t[isample] = clock[0]
            copy1(out_y[isample], y)
            p0, p1 = energy_parts(full, y, kin_w, params)
            out_e[isample] = p0 + p1
            copy2(out_v[isample], V)
            out_m[isample] = mg[5] / (mg[2] - mg[0]) if mg.shape[0] > 0 else np.nan
            isample += 1
    return OK
