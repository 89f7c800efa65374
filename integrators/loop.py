"""One HBVM(k, s) step, written once: :func:`advance` (and :func:`run`, many steps of it; and
:func:`attempt`, a step tried again smaller until the adaptive control accepts it).

Every path of the project runs this code: the compiled engine, the REBOUND and ASE adapters and
the Python path for user systems.  The force kernel is not an argument: the module globals
``_force(X, params, out)`` (-grad V(q) or grad H(y) for each row of X) and
``_potential(x, params)`` (V(q) or H(y)) are bound by :mod:`integrators.specialise`, compiled
into a module of their own for numba kernels, as Python for anything else.  :func:`advance`
returns a status code and changes y, cy, gamma and eref only when the step succeeded.

The implementer's contract (the arrays a caller provides and their shapes), the followers (test
particles solved after the sources, each with its own stop rule) and how EQUIP runs in this
step: the documentation's design page "One step, written once" (``docs/design/step.md``).
"""
import numpy as np

from integrators.core import (C_CHANGE, C_ITER, C_LAST, C_LASTIT, C_NEWTON, C_NFEV, C_STATUS,
                              C_STEPS, DIVERGED, EPS, FLOW_FRACTION, FOLLOWER_GROUP, ITERATE, NARROW, LIPSCHITZ_ULPS, NOT_FINITE, OK, POLISH,
                              TOO_SMALL, UNRESOLVED, next_step, select_extrapolation,
                              all_finite, all_zero, carve, energy_flow, fail, follower_size, lipschitz_probe, commit_full, commit_separable, copy1, copy2,
                              full_stages, full_stages_narrow,
                              guess, guess_narrow, max_abs, newton_update, project, project_compensated, project_narrow,
                              stage_positions, stage_positions_narrow, step_constants, stop_action, symplectic, tick,
                              weighted_kinetic, compact_slots, lipschitz_slots, project_each)
from integrators.core import step_error as error_estimate
from integrators import equip_core as eq
from integrators.pointers import view, view1

_force = None        # bound by integrators.specialise
_potential = None
_followers = None    # (the followers hooks: core.no_followers and core.no_field when none)
_field = None


def evaluate(full, X, params, F, G):
    """F <- the right-hand side at the stages X: forces (separable) or J grad H (full)."""
    if full:
        _force(X, params, G)
        symplectic(G, F)
    else:
        _force(X, params, F)


def energy_parts(full, y, kin_w, params):
    """(T, V) of the separable form (kinetic weights kin_w), or (H, 0) of the full form."""
    if full:
        return _potential(y, params), 0.0
    m = kin_w.shape[0]
    return weighted_kinetic(y[m:], kin_w), _potential(y[:m], params)


def run(full, y, cy, minv, kin_w, params, h, E, gamma, c1, c2, NV, NVinv, NM, max_iter, tol,
        etol, eref, counters, work, cwork, nsteps, sample_every, clock, out_t, out_y, out_e):
    """``nsteps`` steps of size h from the double-double state (y, cy), each committed in place
    when it succeeds; samples of (t, y, H) at steps 0, sample_every, 2 sample_every, ... (none
    when sample_every is 0).  Returns OK, or the status of the first failed step (also left in
    counters[C_STATUS]), with everything as after the last committed step.  The clock (t, its
    compensation) is read from and written back to ``clock``.

    With etol > 0 a converged step whose energy change exceeds etol (relative to |T| + |V|,
    or |H| for the full form) is refused as UNRESOLVED, its change in counters[C_CHANGE]
    (the check of a method exact for H: its energy error is round-off).  With etol < 0 such a
    step is refused only when its change also exceeds a fraction (1e-3 for s >= 3, 1.5e-2 for
    s = 2, 1 for s = 1) of the energy the step moved between the terms of H
    (:func:`integrators.core.energy_flow`):
    the check of a method not exact for H, whose own quadrature error stays far below that
    flow on any step that resolves its path (:data:`integrators.core.FLOW_FRACTION`).
    etol = 0: no check.  eref[0] carries the energy between steps (nan: not known yet).

    The step is written inside the loop, not called: a call with this many arrays costs about
    half a microsecond a step (measured on Kepler, where a step costs one)."""
    t, ct = clock[0], clock[1]
    tn, ts = c1
    Wp, Cp = c2
    tau, tau_lo, X0, X0_lo = tn[0], tn[1], ts[0], ts[1]
    W, W_lo, C2, C2_lo, I, I_lo = Wp[0], Wp[1], Cp[0], Cp[1], Cp[2], Cp[3]
    n = tau.shape[0]
    s, u = gamma.shape
    m = minv.shape[0]
    narrow = u < NARROW     # the sums entry by entry (see core.NARROW)
    ht, ht_lo, hist, dq, dq_lo, a, pg, g, X, F, G, Xp, Fp, yt, cyt, R, Rt, Z = carve(
        work, cwork, n, s, u, m, y.shape[0])
    # EQUIP (integrators.equip): Gauss's arrays in the places above, its own in more planes;
    # for HBVM the views are empty and every EQUIP branch below is skipped
    equip = Cp.shape[0] > 4
    K = Cp.shape[1] if equip else 0
    Xk, Fk, rho, htk, htk_lo, es = eq.carve(work, n, s, u, m, y.shape[0], K)
    if equip and eref.shape[0] < eq.EREF_EQUIP:
        raise ValueError("internal error: EQUIP carries alpha in eref[1:3]: eref too short")
    # Followers (module docstring): the sources' stage equations are solved as if alone, on
    # their own copies (the "block" the iteration below works on), then each follower's in
    # their field (follow); without followers the block is the whole system
    at = -1 if (full or equip or NM.shape[0] > 0) else _followers(params)
    yb, cyb, mb, gb, ab, Xb, Fb, Xpb, Fpb, pb = y, cy, minv, g, a, X, F, Xp, Fp, params
    fb = work[:0]
    fo = 0
    us = 0
    if at >= 0:
        us = int(params[at + 2])
        fb = np.empty(follower_size(n, s, us, int(params[at + 1]), int(params[at])))
        yb, cyb, mb = view1(fb, 0, 2 * us), view1(fb, 2 * us, 2 * us), view1(fb, 4 * us, us)
        gb, ab = view(fb, 5 * us, s, us), view(fb, 5 * us + s * us, s, us)
        fo = 5 * us + 2 * s * us
        Xb, Fb = view(fb, fo, n, us), view(fb, fo + n * us, n, us)
        Xpb, Fpb = view(fb, fo + 2 * n * us, n, us), view(fb, fo + 3 * n * us, n, us)
        fo += 4 * n * us
        pb = view1(params, at + 4 + us + int(params[at]), int(params[at + 3]))
        for c in range(us):
            mb[c] = minv[int(params[at + 4 + c])]
    narrowb = gb.shape[1] < NARROW
    isample = 0
    if sample_every > 0:
        out_t[0] = t
        copy1(out_y[0], y)
        e0, e1 = energy_parts(full, y, kin_w, params)
        out_e[0] = e0 + e1
        isample = 1
    for istep in range(nsteps):
        # a failed step leaves no trace in the counters of work (they count committed steps)
        work_iter, work_nfev, work_newton = counters[C_ITER], counters[C_NFEV], counters[C_NEWTON]
        h2, h2_lo = step_constants(h, tau, tau_lo, ht, ht_lo)
        if equip:
            eq.start(es, eref)
            step_constants(h, Cp[eq.CP_VEC, :, 0], Cp[eq.CP_VEC, :, 1], htk, htk_lo)
        energy_ok = not equip
        if all_zero(gamma):
            # no previous step: start from the right-hand side at y0, evaluated once
            u = g.shape[1]
            for j in range(u):
                X[0, j] = y[j]
            evaluate(full, X[:1], params, F[:1], G[:1])
            counters[C_NFEV] += 1
            for i in range(g.shape[0]):
                for j in range(u):
                    g[i, j] = F[0, j] if i == 0 else 0.0
        elif narrow:
            guess_narrow(E, gamma, g)
        else:
            guess(E, gamma, g)
        if at >= 0:          # the sources' block (their guess as computed for all: the same)
            for c in range(us):
                col = int(params[at + 4 + c])
                yb[c], yb[us + c] = y[col], y[m + col]
                cyb[c], cyb[us + c] = cy[col], cy[m + col]
                for i in range(s):
                    gb[i, c] = g[i, col]
        # the iteration: fixed point g <- P_s^T Omega f(stages(g)) (eq. (hbvm_sys)), or simplified
        # Newton when NM is not empty; the same stop rule either way (core.stop_action), then one
        # compensated evaluation (the polish) whose rounding is what the step keeps; only the polish
        # adds the low parts of the coefficients (C2_lo, I_lo, W_lo: below the rounding of the
        # iterations' own sums; leaving them out there costs nothing in accuracy, 4 % of a step
        # of the outer solar system in time, see core.project).  It is written
        # here, with the kernel called directly and the arrays passed one by one, because one more
        # call level or a tuple argument costs tens of nanoseconds an iteration (measured).
        n = Xb.shape[0]
        newton = NM.shape[0] > 0
        hist[0] = np.inf
        hist[1] = 0.0
        hist[2] = np.inf
        hist[3] = np.inf
        ymax = max_abs(yb)
        yscale = EPS * ymax
        lip = 0.0
        xmax = 0.0
        polish = False
        status = DIVERGED      # unless the loop ends otherwise: max_iter reached
        it = 0
        it0 = 0                # EQUIP: the iterations before the last change of alpha
        while polish or it - it0 < max_iter:
            it += 1
            if full:
                if narrowb:
                    full_stages_narrow(yb, cyb, gb, I, I_lo, h, Xb, polish)
                else:
                    full_stages(yb, cyb, gb, I, I_lo, h, Xb, R, polish)
                if equip:
                    eq.stage_correction(full, yb, mb, gb, ab, h, h2, es[0], Cp[eq.CP_PS],
                                        Cp[eq.CP_B1], Cp[eq.CP_B2], ts[eq.TS_PSE1], Xb)
                _force(Xb, pb, G)
                symplectic(G, Fb)
            else:
                if narrowb:
                    stage_positions_narrow(yb, cyb, mb, gb, C2, C2_lo, ht, ht_lo, h2, h2_lo, ab, Xb, polish)
                else:
                    stage_positions(yb, cyb, mb, gb, C2, C2_lo, ht, ht_lo, h2, h2_lo, ab, Xb, R, polish)
                if equip:
                    eq.stage_correction(full, yb, mb, gb, ab, h, h2, es[0], Cp[eq.CP_PS],
                                        Cp[eq.CP_B1], Cp[eq.CP_B2], ts[eq.TS_PSE1], Xb)
                _force(Xb, pb, Fb)
            counters[C_NFEV] += n
            if it <= 3:          # the force's Lipschitz constant, for the round-off floor
                if it > 1:
                    lip, xmax = lipschitz_probe(Xb, Fb, Xpb, Fpb, lip)
                else:
                    copy2(Xpb, Xb)
                    copy2(Fpb, Fb)
            if polish:
                if newton:      # a last Newton update from the compensated residual: a plain
                    # fixed-point polish would amplify the error by h L |X_s| (stiff problems)
                    project_compensated(W, W_lo, Fb, pg, R)
                    newton_update(gb, pg, NV, NVinv, NM, Rt, Z)
                else:
                    project_compensated(W, W_lo, Fb, gb, R)
                if energy_ok:
                    status = OK
                    break
                # EQUIP: gamma has converged for this alpha (and is polished: a residual
                # measured before the polish misses the coefficients' low parts, the same
                # every step, and the energy drifts: 1.8e-13 over 5000 steps of Kepler, s = 4);
                # the energy condition along the path through the k points of the line
                # integral's quadrature decides.  The path and its projection with the
                # coefficients' low parts, for the same reason
                if full:
                    if narrowb:
                        full_stages_narrow(yb, cyb, gb, Cp[eq.CP_PATH_I], Cp[eq.CP_PATH_I_LO], h, Xk, True)
                    else:
                        full_stages(yb, cyb, gb, Cp[eq.CP_PATH_I], Cp[eq.CP_PATH_I_LO], h, Xk, R, True)
                else:
                    if narrowb:
                        stage_positions_narrow(yb, cyb, mb, gb, Cp[eq.CP_PATH_C2], Cp[eq.CP_PATH_C2_LO],
                                               htk, htk_lo, h2, h2_lo, ab, Xk, True)
                    else:
                        stage_positions(yb, cyb, mb, gb, Cp[eq.CP_PATH_C2], Cp[eq.CP_PATH_C2_LO],
                                        htk, htk_lo, h2, h2_lo, ab, Xk, R, True)
                    eq.path_correction(gb, mb, h2, es[0], Cp[eq.CP_PATH_S], Xk)
                _force(Xk, pb, Fk)
                counters[C_NFEV] += K
                project_compensated(Wp[eq.WP_PATH], Wp[eq.WP_PATH_LO], Fk, rho, R)
                e_res, e_scale, e_weight = eq.energy_residual(full, yb, mb, kin_w, gb, rho, h, es[0],
                                                              Cp[eq.CP_X], Cp[eq.CP_X_LO],
                                                              ts[eq.TS_S0])
                answer = eq.update_alpha(es, e_res, e_scale,
                                         e_weight * LIPSCHITZ_ULPS * EPS * xmax * lip)
                if answer == eq.CONVERGED:      # polish once more (gamma as it is)
                    energy_ok = True
                elif answer == eq.UPDATED or answer == eq.REITERATE:
                    # iterate gamma again for the new alpha, with max_iter iterations again
                    # (REITERATE: alpha's last correction, no more measuring)
                    energy_ok = answer == eq.REITERATE
                    polish = False
                    it0 = it
                    hist[0] = np.inf
                    hist[1] = 0.0
                    hist[2] = np.inf
                    hist[3] = np.inf
                else:
                    status = eq.NO_ENERGY_ROOT      # no alpha near the last conserves H
                    break
                continue
            if newton:
                if narrowb:
                    project_narrow(W, Fb, pg)
                else:
                    project(W, Fb, pg, R)
                delta, scale = newton_update(gb, pg, NV, NVinv, NM, Rt, Z)
            else:
                if narrowb:
                    delta, scale = project_narrow(W, Fb, gb)
                else:
                    delta, scale = project(W, Fb, gb, R)
            counters[C_LAST] = delta
            hstate = abs(h) * delta / yscale if yscale > 0.0 else np.inf
            action = stop_action(delta, scale, Fb, LIPSCHITZ_ULPS * EPS * xmax * lip, hstate,
                                 abs(h) * scale, ymax, it, hist, tol)
            if action == POLISH:
                polish = True
            elif action != ITERATE:
                status = -action
                break
        if at >= 0 and status == OK:
            for c in range(us):
                col = int(params[at + 4 + c])
                for i in range(s):
                    g[i, col] = gb[i, c]
            status, itf, dlast = follow(y, cy, minv, g, Xb, params, at, h, ht, ht_lo, h2, h2_lo,
                                        C2, C2_lo, W, W_lo, max_iter, tol, R, fb, fo)
            if status != OK:
                counters[C_LAST] = dlast
            if itf > it:            # the counts are the longest block's (the step's depth)
                counters[C_NFEV] += n * (itf - it)
                it = itf
        counters[C_ITER] += it
        counters[C_LASTIT] = it
        if newton:
            counters[C_NEWTON] += 1
        if status != OK:
            return fail(counters, status, work_iter, work_nfev, work_newton)
        copy1(yt, y)
        copy1(cyt, cy)
        if full:
            commit_full(yt, cyt, h, g)
        else:
            commit_separable(yt, cyt, minv, h, g, X0, X0_lo, dq, dq_lo)
            if equip:
                eq.commit_correction(yt, cyt, minv, h, g, es[0], ts[eq.TS_S0])
        if not all_finite(yt):
            return fail(counters, NOT_FINITE, work_iter, work_nfev, work_newton)
        if etol != 0.0:
            if not np.isfinite(eref[0]):
                t0, v0 = energy_parts(full, y, kin_w, params)
                eref[0] = t0 + v0
            t1, v1 = energy_parts(full, yt, kin_w, params)
            scale = abs(t1) + abs(v1)
            change = abs(t1 + v1 - eref[0])
            if scale > 0.0:
                change = change / scale
            # etol < 0 (a method not exact for H): a change above |etol| is the method's own
            # quadrature error unless it exceeds FLOW_FRACTION of the energy the step moved
            # (core.energy_flow, at least the kinetic change |T1 - T0| in the separable form:
            # checked first, as it costs O(m) where the flow costs O(k s m)); the fraction
            # depends on s (core.FLOW_FRACTION: a lower order errs more at the same resolution)
            refuse = not change <= abs(etol)
            if refuse and etol < 0.0:
                moved = abs(t1 + v1 - eref[0]) / FLOW_FRACTION[min(s, 3) - 1]
                refuse = not ((not full and moved <= abs(t1 - weighted_kinetic(y[m:], kin_w)))
                              or moved <= energy_flow(full, y, kin_w, h, g, W, I, G))
            if refuse:
                counters[C_CHANGE] = change
                return fail(counters, UNRESOLVED, work_iter, work_nfev, work_newton)
            eref[0] = t1 + v1
        copy1(y, yt)
        copy1(cy, cyt)
        copy2(gamma, g)
        if equip:
            eq.finish(es, eref)
        counters[C_STEPS] += 1
        t, ct = tick(t, ct, h)
        clock[0] = t
        clock[1] = ct
        if sample_every > 0 and (istep + 1) % sample_every == 0:
            out_t[isample] = t
            copy1(out_y[isample], y)
            e0, e1 = energy_parts(full, y, kin_w, params)
            out_e[isample] = e0 + e1
            isample += 1
    counters[C_STATUS] = OK
    return OK


def follower_stages(ya, cya, ma, g, C2, C2_lo, ht, ht_lo, h2, h2_lo, a, X, F, Xs, ps, R, exact):
    """A group of followers' stage values X from their state (ya, cya, ma) and coefficients g,
    then their right-hand side F in the sources' field at their stage values Xs (``exact``:
    with the coefficients' low parts, for the polish, as in :func:`run`)."""
    if X.shape[1] < NARROW:
        stage_positions_narrow(ya, cya, ma, g, C2, C2_lo, ht, ht_lo, h2, h2_lo, a, X, exact)
    else:
        stage_positions(ya, cya, ma, g, C2, C2_lo, ht, ht_lo, h2, h2_lo, a, X, R, exact)
    _field(X, Xs, ps, F)


def gather_followers(y, cy, minv, params, fcol, j0, pc, w, fb, o_y, o_cy, o_m):
    """Followers j0 .. j0 + pc (their first columns at params[fcol:]) gathered into fb: their
    state as (q, p) of 2 pc w entries at o_y, its compensation at o_cy, 1 / m at o_m."""
    m = minv.shape[0]
    uc = pc * w
    for j in range(pc):
        c0 = int(params[fcol + j0 + j])
        for c in range(w):
            fb[o_y + w * j + c], fb[o_y + uc + w * j + c] = y[c0 + c], y[m + c0 + c]
            fb[o_cy + w * j + c], fb[o_cy + uc + w * j + c] = cy[c0 + c], cy[m + c0 + c]
            fb[o_m + w * j + c] = minv[c0 + c]


def follow(y, cy, minv, g, Xs, params, at, h, ht, ht_lo, h2, h2_lo, C2, C2_lo, W, W_lo,
           max_iter, tol, R, fb, fo):
    """The followers' stage equations, after the sources': each follower (a slot of ``width``
    columns, a test particle's three) is iterated in the sources' field at their stage values
    Xs (n, us) with the fixed-point iteration and stop rule of :func:`run`, applied to it alone
    (its own increments, sizes, round-off floors and runaway test, :func:`core.stop_action`),
    and leaves the iteration when it has converged: one slow follower makes neither the
    sources nor the others iterate.  Then one compensated evaluation (the polish, as in
    :func:`run`).  The followers go through in groups of ``core.FOLLOWER_GROUP``, each
    iterated to the end before the next (their arrays stay in cache, and the time per
    follower does not depend on how many there are).  g (s, u): the step's coefficients, the
    followers' columns holding their initial guess, overwritten with the result; params[at:]:
    the followers block (``systems.nbody.followers_block``); fb[fo:]: scratch
    (``core.follower_size``); R: the step's scratch of column sums.  Returns (status,
    iterations of the slowest follower, the polish included, and the last increment of the
    follower that failed (after max_iter iterations: the largest of those still iterating), 0
    when none did)."""
    P = int(params[at])
    w = int(params[at + 1])
    us = int(params[at + 2])
    fcol = at + 4 + us
    ps = view1(params, fcol + P, int(params[at + 3]))
    s = g.shape[0]
    n = Xs.shape[0]
    m = minv.shape[0]
    nmax = min(P, FOLLOWER_GROUP)
    up = nmax * w
    o_y, o_cy, o_m = fo, fo + 2 * up, fo + 4 * up
    o_g = fo + 5 * up
    o_all = o_g + s * up
    o_a = o_g + 2 * s * up
    o_x = o_a + s * up
    o_f, o_xp, o_fp = o_x + n * up, o_x + 2 * n * up, o_x + 3 * n * up
    dcol = view1(fb, o_x + 4 * n * up, up)
    scol = view1(fb, o_x + 4 * n * up + up, up)
    o_h = o_x + 4 * n * up + 2 * up
    o_lip, o_xmax, o_ymax, o_who, o_keep = (o_h + 5 * nmax, o_h + 6 * nmax, o_h + 7 * nmax,
                                            o_h + 8 * nmax, o_h + 9 * nmax)
    itmax = 0
    for j0 in range(0, P, nmax):
        pc = min(nmax, P - j0)
        uc = pc * w
        gall = view(fb, o_all, s, uc)
        gather_followers(y, cy, minv, params, fcol, j0, pc, w, fb, o_y, o_cy, o_m)
        for j in range(pc):             # their coefficients and stop rules, in their order
            c0 = int(params[fcol + j0 + j])
            ym = 0.0
            for c in range(w):
                ym = max(ym, abs(y[c0 + c]), abs(y[m + c0 + c]))
                for i in range(s):
                    fb[o_g + i * uc + w * j + c] = g[i, c0 + c]
            fb[o_h + 5 * j] = np.inf            # core.stop_action's history, as run starts it
            fb[o_h + 5 * j + 1] = 0.0
            fb[o_h + 5 * j + 2] = np.inf
            fb[o_h + 5 * j + 3] = np.inf
            fb[o_h + 5 * j + 4] = 0.0
            fb[o_lip + j] = 0.0
            fb[o_xmax + j] = 0.0
            fb[o_ymax + j] = ym
            fb[o_who + j] = j
        na = pc
        it = 0
        worst = 0.0                     # the largest increment of those still iterating
        while na > 0:
            if it >= max_iter:
                return DIVERGED, it, worst
            it += 1
            worst = 0.0
            ua = na * w
            ya, cya, ma = view1(fb, o_y, 2 * ua), view1(fb, o_cy, 2 * ua), view1(fb, o_m, ua)
            ga, aa = view(fb, o_g, s, ua), view(fb, o_a, s, ua)
            Xa, Fa = view(fb, o_x, n, ua), view(fb, o_f, n, ua)
            Xpa, Fpa = view(fb, o_xp, n, ua), view(fb, o_fp, n, ua)
            follower_stages(ya, cya, ma, ga, C2, C2_lo, ht, ht_lo, h2, h2_lo, aa, Xa, Fa, Xs, ps,
                            R, False)
            if it <= 3:          # each follower's Lipschitz constant, for its round-off floor
                if it > 1:
                    lipschitz_slots(Xa, Fa, Xpa, Fpa, w, view1(fb, o_lip, na),
                                    view1(fb, o_xmax, na))
                else:
                    copy2(Xpa, Xa)
                    copy2(Fpa, Fa)
            project_each(W, Fa, ga, R, dcol, scol)
            nk = 0
            for j in range(na):
                delta = 0.0
                scale = 0.0
                for c in range(w * j, w * j + w):
                    if dcol[c] > delta or dcol[c] != dcol[c]:
                        delta = dcol[c]
                    if scol[c] > scale:
                        scale = scol[c]
                ym = fb[o_ymax + j]
                hstate = abs(h) * delta / (EPS * ym) if ym > 0.0 else np.inf
                action = stop_action(delta, scale, Fa[:, w * j:w * j + w],
                                     LIPSCHITZ_ULPS * EPS * fb[o_xmax + j] * fb[o_lip + j],
                                     hstate, abs(h) * scale, ym, it, view1(fb, o_h + 5 * j, 5),
                                     tol)
                if action == POLISH:
                    k = int(fb[o_who + j])
                    for i in range(s):
                        for c in range(w):
                            gall[i, w * k + c] = ga[i, w * j + c]
                elif action == ITERATE:
                    fb[o_keep + nk] = j
                    nk += 1
                    worst = max(worst, delta)
                else:
                    return -action, it, delta
            if nk < na:                     # the converged leave: the others move up
                keep = view1(fb, o_keep, nk)
                compact_slots(fb, o_y, 2, w, na, keep, nk)
                compact_slots(fb, o_cy, 2, w, na, keep, nk)
                compact_slots(fb, o_m, 1, w, na, keep, nk)
                compact_slots(fb, o_g, s, w, na, keep, nk)
                if it < 3:
                    compact_slots(fb, o_xp, n, w, na, keep, nk)
                    compact_slots(fb, o_fp, n, w, na, keep, nk)
                compact_slots(fb, o_h, 1, 5, na, keep, nk)
                for o in (o_lip, o_xmax, o_ymax, o_who):
                    compact_slots(fb, o, 1, 1, na, keep, nk)
                na = nk
        itmax = max(itmax, it + 1)
        # the polish, the group at once from its state gathered again in its order
        gather_followers(y, cy, minv, params, fcol, j0, pc, w, fb, o_y, o_cy, o_m)
        ya, cya, ma = view1(fb, o_y, 2 * uc), view1(fb, o_cy, 2 * uc), view1(fb, o_m, uc)
        aa, Xa, Fa = view(fb, o_a, s, uc), view(fb, o_x, n, uc), view(fb, o_f, n, uc)
        follower_stages(ya, cya, ma, gall, C2, C2_lo, ht, ht_lo, h2, h2_lo, aa, Xa, Fa, Xs, ps, R,
                        True)
        project_compensated(W, W_lo, Fa, gall, R)
        for j in range(pc):
            c0 = int(params[fcol + j0 + j])
            for i in range(s):
                for c in range(w):
                    g[i, c0 + c] = gall[i, w * j + c]
    return OK, itmax, 0.0


def advance(full, y, cy, minv, kin_w, params, h, E, gamma, c1, c2, NV, NVinv, NM, max_iter, tol,
            etol, eref, counters, work, cwork, clock):
    """One step of :func:`run` (no samples); returns its status."""
    no_samples = view1(work, 0, 0)          # (no allocation: see integrators.pointers)
    return run(full, y, cy, minv, kin_w, params, h, E, gamma, c1, c2, NV, NVinv, NM, max_iter,
               tol, etol, eref, counters, work, cwork, 1, 0, clock, no_samples,
               view(work, 0, 0, 0), no_samples)


def attempt(full, y, cy, gamma, eref, yt, cyt, gammat, ereft, minv, kin_w, params, h, h_prev,
            E1, Et, Ew, Ebuf, Ezero, c1, c2, NV, NVinv, NM, max_iter, tol, etol, counters, work,
            cwork, clock, epsilon, min_dt, t_start, res):
    """One step from the state (y, cy, gamma, eref) into the trial arrays (yt, cyt, gammat,
    ereft); nothing of the state is changed.  h_prev: the previous step (nan: none), for the
    initial guess's extrapolation E (``core.select_extrapolation`` with E1, the Gauss rule
    (Et, Ew), the buffers Ebuf and Ezero).

    epsilon = 0: a fixed step; returns its status.  epsilon > 0: adaptive; a step whose error
    estimate (``core.step_error`` with weights minv) exceeds epsilon, or whose iteration or
    energy check fails, is tried again smaller (the controller ``core.next_step``, a quarter
    after a failure), leaving no trace in the counters; TOO_SMALL when the step would fall
    below min_dt (or vanish at t_start).  res: [h taken (or last tried), next h proposed,
    rejections (added), last rejection's error estimate (nan after a failed iteration), last
    failure's status]."""
    s = gamma.shape[0]
    snap = np.empty(counters.shape[0])
    clock0, clock1 = clock[0], clock[1]
    while True:
        copy1(yt, y)
        copy1(cyt, cy)
        copy2(gammat, gamma)
        copy1(ereft, eref)          # (the energy; EQUIP's alpha and slope)
        clock[0] = clock0
        clock[1] = clock1
        for i in range(counters.shape[0]):
            snap[i] = counters[i]
        E = select_extrapolation(h, h_prev, E1, Et, Ew, Ebuf, Ezero)
        status = advance(full, yt, cyt, minv, kin_w, params, h, E, gammat, c1, c2, NV, NVinv, NM,
                         max_iter, tol, etol, ereft, counters, work, cwork, clock)
        res[0] = h
        res[1] = h
        if epsilon <= 0.0:
            return status
        if status == OK:
            err = error_estimate(gammat, minv)
            if err <= epsilon:
                res[1] = next_step(h, err, epsilon, s)
                return OK
            for i in range(counters.shape[0]):      # a rejected step leaves no trace
                counters[i] = snap[i]
            res[3] = err
            h_new = next_step(h, err, epsilon, s)
        else:
            res[3] = np.nan
            h_new = 0.25 * h
        res[4] = status
        res[2] += 1.0
        if abs(h_new) < min_dt or h_new == 0.0 or t_start + h_new == t_start:
            return TOO_SMALL
        h = h_new
