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

from integrators.core import (C_CHANGE, C_ERR, C_ITER, C_LAST, C_LASTIT, C_NEWTON, C_NFEV,
                              C_RUN_ERR, C_STEPS, C_WORST, DRIFT_BOUND, DRIFT_PHASE, DRIFTED, EREF_RUN, EREF_TIME, EREF_TMAX, EREF_TMEAN, NOT_RESOLVED, endpoint_defect, omitted_coefficient,
                              resolution_error, run_error_share, DIVERGED, EPS, FLOW_FRACTION, ITERATE, NARROW, LIPSCHITZ_ULPS, NOT_FINITE, OK, POLISH,
                              TOO_SMALL, UNRESOLVED, adapt_step, select_extrapolation, test_particle_control,
                              all_finite, all_zero, carve, carve_velocities, energy_flow, fail, follower_size, lipschitz_probe, commit_full, commit_separable, copy1, copy2,
                              full_stages, full_stages_narrow,
                              guess, guess_narrow, max_abs, newton_update, project, project_compensated, project_narrow,
                              stage_positions, stage_positions_narrow, stage_velocities, step_constants,
                              stop_action, symplectic, tick, weighted_kinetic, work_sizes)
from integrators import equip_core as eq
from integrators.pointers import view, view1
from integrators.records import Options, Samples, State, StepConstants, Tableau
from integrators.followers import follow

_force = None        # bound by integrators.specialise
_potential = None
_followers = None    # (the followers hook: core.no_followers when none; their step is
                     # integrators.followers, bound with its own hook _field)
# What the step is built for, bound by integrators.specialise (module docstring there, "Compile
# time"): numba reads a module global as a constant and prunes the branches it decides before it
# types them, so the code of a form, a method or a feature a scene does not use is not compiled
_EQUIP = None        # the method: True EQUIP, False HBVM, None (a step for both): from its arrays
_FULL = None         # the form: True full, False separable, None (both): from system.full
_FOLLOWERS = True    # False: a system without followers (test particles)
_NEWTON = True       # False: a host that never hands the step Newton matrices (REBOUND: the
                     # fixed-point iteration only); the simplified-Newton branches are left out
_STAGE_VELOCITIES = False  # True: the separable step hands the kernel the stages (q, v), X of
                     # shape (n, 2m), instead of the positions (n, m) (core.stage_velocities),
                     # for a kernel that reads velocities
_RECENTRE = False    # True: the system's hook _recentre(y, cy, gamma, h, params) runs after each
_recentre = None     # committed step (bound by integrators.specialise)


def tableau(method):
    """The method's packed arrays (:class:`integrators.records.Method`) named at their shapes
    (:class:`integrators.records.Tableau`): tau, tau_lo (k,), X0, X0_lo (s,) (X_s's first row),
    W, W_lo (s, k), C2, C2_lo, I, I_lo (k, s) (for EQUIP, Gauss's: HBVM(s, s)'s)."""
    tn, ts, Wp, Cp = method
    return Tableau(tn[0], tn[1], ts[0], ts[1], Wp[0], Wp[1], Cp[0], Cp[1], Cp[2], Cp[3])


def evaluate(full, X, params, F, G):
    """F <- the right-hand side at the stages X: forces (separable) or J grad H (full)."""
    if _FULL is None:
        f = full
    else:
        f = _FULL                   # (as built: the other form's branch is not compiled)
    if f:
        _force(X, params, G)
        symplectic(G, F)
    else:
        _force(X, params, F)


def energy_parts(full, y, kin_w, params):
    """(T, V) of the separable form (kinetic weights kin_w), or (H, 0) of the full form."""
    if _FULL is None:
        f = full
    else:
        f = _FULL
    if f:
        return _potential(y, params), 0.0
    m = kin_w.shape[0]
    return weighted_kinetic(y[m:], kin_w), _potential(y[:m], params)


def first_guess(full, vel, y, minv, params, gamma, E, narrow, g, X, F, G, XV):
    """g <- the initial guess of the step's coefficients: extrapolated from the previous step's
    gamma (E, :func:`integrators.core.guess`), or, with no previous step (gamma all zero), the
    right-hand side at y0, evaluated once into g's first row.  Returns the evaluations made."""
    if all_zero(gamma):
        u = g.shape[1]
        if vel:
            for j in range(u):
                XV[0, j] = y[j]
                XV[0, u + j] = y[u + j] * minv[j]
            _force(XV[:1], params, F[:1])
        else:
            for j in range(u):
                X[0, j] = y[j]
            evaluate(full, X[:1], params, F[:1], G[:1])
        for i in range(g.shape[0]):
            for j in range(u):
                g[i, j] = F[0, j] if i == 0 else 0.0
        return 1
    if narrow:
        guess_narrow(E, gamma, g)
    else:
        guess(E, gamma, g)
    return 0


def stage_field(full, equip, vel, narrowb, polish, yb, cyb, mb, gb, ab, sc, es, method, tab, h,
                Xb, Fb, G, R, pb):
    """The stages of the coefficients gb and the right-hand side at them, Fb: the full form's
    Y = y0 + h I gamma and J grad H, or the separable form's positions (the double integral C2)
    and forces; with stage velocities (``_STAGE_VELOCITIES``) the separable stages carry
    (q, v), X of shape (n, 2m); EQUIP moves the stages by its correction before the kernel.
    ``polish``: with the coefficients' low parts (the compensated evaluation)."""
    if full:
        if narrowb:
            full_stages_narrow(yb, cyb, gb, tab.I, tab.I_lo, h, Xb, polish)
        else:
            full_stages(yb, cyb, gb, tab.I, tab.I_lo, h, Xb, R, polish)
        if equip:
            eq.stage_correction(full, yb, mb, gb, ab, sc, es[0], method, Xb)
        _force(Xb, pb, G)
        symplectic(G, Fb)
    else:
        if narrowb:
            stage_positions_narrow(yb, cyb, mb, gb, tab.C2, tab.C2_lo, sc, ab, Xb, polish)
        else:
            stage_positions(yb, cyb, mb, gb, tab.C2, tab.C2_lo, sc, ab, Xb, R, polish)
        if vel:
            stage_velocities(yb, cyb, mb, gb, tab.I, tab.I_lo, h, Xb, polish)
        if equip:
            eq.stage_correction(full, yb, mb, gb, ab, sc, es[0], method, Xb)
        _force(Xb, pb, Fb)


def coefficient_update(newton, narrowb, W, Fb, gb, pg, NV, NVinv, NM, R, Rt, Z):
    """One iteration's new coefficients from the right-hand side at the stages: the fixed point
    gb <- P_s^T Omega Fb (eq. (hbvm_sys)), or a simplified Newton update from the residual
    when the host handed Newton matrices (NM not empty).  Returns (increment, size) for the
    stop rule (:func:`integrators.core.stop_action`)."""
    if _NEWTON and newton:
        if narrowb:
            project_narrow(W, Fb, pg)
        else:
            project(W, Fb, pg, R)
        return newton_update(gb, pg, NV, NVinv, NM, Rt, Z)
    if narrowb:
        return project_narrow(W, Fb, gb)
    return project(W, Fb, gb, R)


def polish_coefficients(newton, W, W_lo, Fb, gb, pg, NV, NVinv, NM, R, Rt, Z):
    """The polish: the coefficients from one compensated projection of the right-hand side
    (the rounding the step keeps); with Newton matrices, a last Newton update from that
    compensated residual, since a plain fixed-point polish would amplify the error by
    h L |X_s| on a stiff problem."""
    if _NEWTON and newton:
        project_compensated(W, W_lo, Fb, pg, R)
        newton_update(gb, pg, NV, NVinv, NM, Rt, Z)
    else:
        project_compensated(W, W_lo, Fb, gb, R)


def equip_energy_condition(full, narrowb, yb, cyb, mb, kin_w, gb, ab, h, h2, sck, es, method,
                           Xk, Fk, rho, R, pb, lip, xmax):
    """EQUIP's energy condition, once gamma has converged (and is polished) for the current
    alpha: the path through the k points of the line integral's quadrature, projected with the
    coefficients' low parts (a residual measured before the polish misses them, the same every
    step, and the energy drifts: 1.8e-13 over 5000 steps of Kepler, s = 4), decides whether
    alpha conserves H (:func:`integrators.equip_core.update_alpha`'s answer: CONVERGED,
    UPDATED, REITERATE or no root)."""
    tn, ts, Wp, Cp = method
    if full:
        if narrowb:
            full_stages_narrow(yb, cyb, gb, Cp[eq.CP_PATH_I], Cp[eq.CP_PATH_I_LO], h, Xk, True)
        else:
            full_stages(yb, cyb, gb, Cp[eq.CP_PATH_I], Cp[eq.CP_PATH_I_LO], h, Xk, R, True)
    else:
        if narrowb:
            stage_positions_narrow(yb, cyb, mb, gb, Cp[eq.CP_PATH_C2], Cp[eq.CP_PATH_C2_LO],
                                   sck, ab, Xk, True)
        else:
            stage_positions(yb, cyb, mb, gb, Cp[eq.CP_PATH_C2], Cp[eq.CP_PATH_C2_LO],
                            sck, ab, Xk, R, True)
        eq.path_correction(gb, mb, h2, es[0], Cp[eq.CP_PATH_S], Xk)
    _force(Xk, pb, Fk)
    project_compensated(Wp[eq.WP_PATH], Wp[eq.WP_PATH_LO], Fk, rho, R)
    e_res, e_scale, e_weight = eq.energy_residual(full, yb, mb, kin_w, gb, rho, h, es[0],
                                                  Cp[eq.CP_X], Cp[eq.CP_X_LO], ts[eq.TS_S0])
    return eq.update_alpha(es, e_res, e_scale, e_weight * LIPSCHITZ_ULPS * EPS * xmax * lip)


def sources_block(params, at, n, s, minv):
    """The followers' side of the step (module docstring): the sources' own block, in a buffer
    of its own (``core.follower_size``; the followers' scratch past its offset fo): their state
    yb, cyb, 1 / m, coefficients gb and scratch ab, stages Xb, Fb and the Lipschitz probe's
    Xpb, Fpb, and their params pb.  Returns (fb, fo, us, yb, cyb, mb, gb, ab, Xb, Fb, Xpb, Fpb,
    pb), us the sources' columns."""
    us = int(params[at + 2])
    fb = np.empty(follower_size(n, s, us, int(params[at + 1]), int(params[at])))
    yb, cyb, mb = view1(fb, 0, 2 * us), view1(fb, 2 * us, 2 * us), view1(fb, 4 * us, us)
    gb, ab = view(fb, 5 * us, s, us), view(fb, 5 * us + s * us, s, us)
    fo = 5 * us + 2 * s * us
    Xb, Fb = view(fb, fo, n, us), view(fb, fo + n * us, n, us)
    Xpb, Fpb = view(fb, fo + 2 * n * us, n, us), view(fb, fo + 3 * n * us, n, us)
    fo += 4 * n * us
    if fb.shape[0] < fo:            # (views are not bounds-checked)
        raise ValueError("internal error: the sources' block is longer than "
                         "core.follower_size says")
    pb = view1(params, at + 4 + us + int(params[at]), int(params[at + 3]))
    for c in range(us):
        mb[c] = minv[int(params[at + 4 + c])]
    return fb, fo, us, yb, cyb, mb, gb, ab, Xb, Fb, Xpb, Fpb, pb


def gather_sources(y, cy, g, m, params, at, us, yb, cyb, gb):
    """The sources' state and initial guess (as computed for all: the same) into their block."""
    for c in range(us):
        col = int(params[at + 4 + c])
        yb[c], yb[us + c] = y[col], y[m + col]
        cyb[c], cyb[us + c] = cy[col], cy[m + col]
        for i in range(g.shape[0]):
            gb[i, c] = g[i, col]


def solve_followers(y, cy, minv, g, gb, Xb, params, at, us, sc, tab, opts, R, fb, fo):
    """After the sources have converged: their coefficients back into g, then the followers'
    stage equations in their field (:func:`integrators.followers.follow`).  Returns follow's
    (status, iterations, last increment)."""
    for c in range(us):
        col = int(params[at + 4 + c])
        for i in range(g.shape[0]):
            g[i, col] = gb[i, c]
    return follow(y, cy, minv, g, Xb, params, at, sc, tab, opts, R,
                  view1(fb, fo, fb.shape[0] - fo))


def resolution_check(full, vel, yt, cyt, m, minv, gb, yb, mb, Xb, Fb, Xpb, Fpb, W, tau, h,
                     params, at, pb, group):
    """The step judged by its own error (:func:`integrators.core.resolution_error`), before the
    energy check, which cannot see a step that keeps H but leaves the solution.  The first
    omitted Legendre coefficient goes into Fpb[0] (the Lipschitz probe's scratch, free by now):
    from the stage values when k > s, else from one evaluation at y1 (the full form's grad H
    into Fpb[0], J grad H back over the stage in Xpb[0]).  Returns (estimate, the worst body
    as the whole state numbers it, evaluations made, the share of its motion the worst body
    turned: :func:`integrators.core.run_error_share`, for the run's accumulated estimate)."""
    om = Fpb[0]
    s = gb.shape[0]
    nfev = 0
    if Xb.shape[0] > s:
        omitted_coefficient(W, tau, Fb, om)
    else:
        ub = gb.shape[1]
        for c in range(ub):
            col = c
            if _FOLLOWERS and at >= 0:
                col = int(params[at + 4 + c])
            Xpb[0, c] = yt[col] - cyt[col]
            if vel:
                Xpb[0, ub + c] = (yt[m + col] - cyt[m + col]) * minv[col]
        f1 = Xpb[:1] if full else Fpb[:1]
        evaluate(full, Xpb[:1], pb, f1, Fpb[:1])
        endpoint_defect(gb, f1[0], om)
        nfev = 1
    err, worst = resolution_error(full, yb, mb, gb, om, h, group)
    share = run_error_share(full, yb, mb, gb, h, err, worst, group, s)
    if _FOLLOWERS and at >= 0 and worst >= 0 and group > 0:
        worst = int(params[at + 4 + worst * group]) // group
    return err, worst, nfev, share


def energy_check(full, y, yt, m, kin_w, params, etol, eref, h, g, W, I, G):
    """The energy check, a second guard independent of the step's own estimate (etol: see
    :func:`run`).  Returns (status: OK, UNRESOLVED or DRIFTED; the relative change of H, or the
    run's relative drift when DRIFTED); eref[0] holds the new energy when the step passes, and
    eref[EREF_RUN] the energy at the run's start (the energy before this step when not known:
    a host that starts a run afresh sets it to nan, one that only recomputes the energy of a
    loaded state, eref[0], keeps the run's start)."""
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
        moved = abs(t1 + v1 - eref[0]) / FLOW_FRACTION[min(g.shape[0], 3) - 1]
        refuse = not ((not full and moved <= abs(t1 - weighted_kinetic(y[m:], kin_w)))
                      or moved <= energy_flow(full, y, kin_w, h, g, W, I, G))
    if refuse:
        return UNRESOLVED, change
    if etol < 0.0 and not full:
        # ... and the run's energy against its start: each step of a symmetric method may pass
        # while the run keeps an offset that puts its orbit off (core.DRIFT_BOUND).  Only in
        # the separable form, whose kinetic energy is the size of the motion: a full-form H
        # has no such scale (a Poincare-transformed H is zero on the solution).  The scale is
        # the run's kinetic one, max(T1, <T> sqrt(<T> / Tmax)) with <T> T's time mean and Tmax
        # its largest over the run including this step (core.DRIFT_BOUND: none moves with the
        # potential's zero)
        if not (np.isfinite(eref[EREF_RUN]) and np.isfinite(eref[EREF_TMEAN])
                and np.isfinite(eref[EREF_TIME]) and np.isfinite(eref[EREF_TMAX])):
            # (not known, or a state saved before the scale's terms joined eref: a new run)
            eref[EREF_RUN] = eref[0]
            eref[EREF_TMEAN] = 0.0
            eref[EREF_TIME] = 0.0
            eref[EREF_TMAX] = 0.0
        run_time = eref[EREF_TIME] + abs(h)
        tmean = eref[EREF_TMEAN] + (abs(t1) - eref[EREF_TMEAN]) * (abs(h) / run_time)
        tmax = max(eref[EREF_TMAX], abs(t1))
        drift = abs(t1 + v1 - eref[EREF_RUN])
        kscale = abs(t1)
        if tmax > 0.0:
            kscale = max(kscale, tmean * np.sqrt(tmean / tmax))
        if kscale > 0.0:
            drift = drift / kscale
        if not drift <= DRIFT_BOUND:
            return DRIFTED, drift
        eref[EREF_TMEAN] = tmean
        eref[EREF_TIME] = run_time
        eref[EREF_TMAX] = tmax
        eref[0] = t1 + v1
        return OK, drift
    eref[0] = t1 + v1
    return OK, 0.0


def run(system, state, h, E, method, newton, opts, wk, samples):
    """``samples.nsteps`` steps of size h from the double-double state (state.y, state.cy), each
    committed in place when it succeeds; samples of (t, y, H) at steps 0, every, 2 every, ...
    into samples.t, .y, .e (none when samples.every is 0).  Returns OK, or the status of the
    first failed step, with everything as after the last
    committed step.  The clock (t, its compensation) is read from and written back to
    ``state.clock``.  The records: :mod:`integrators.records` (E: the initial guess's
    extrapolation matrix (s, s)); opts.etol is the energy check's tolerance:

    With etol > 0 a converged step whose energy change exceeds etol (relative to |T| + |V|,
    or |H| for the full form) is refused as UNRESOLVED, its change in counters[C_CHANGE]
    (the check of a method exact for H: its energy error is round-off).  With etol < 0 such a
    step is refused only when its change also exceeds a fraction (1e-3 for s >= 3, 1.5e-2 for
    s = 2, 1 for s = 1) of the energy the step moved between the terms of H
    (:func:`integrators.core.energy_flow`):
    the check of a method not exact for H, whose own quadrature error stays far below that
    flow on any step that resolves its path (:data:`integrators.core.FLOW_FRACTION`).
    etol = 0: no check.  eref[0] carries the energy between steps (nan: not known yet).
    opts.ebound > 0: a step whose own error estimate exceeds it is refused as NOT_RESOLVED
    (:func:`resolution_check`).

    How to read it: the step is the loop over ``istep``; each feature is a function of its
    own, called where it acts: :func:`first_guess`, the iteration (:func:`stage_field`, the
    stage velocities among them; :func:`coefficient_update`, Newton or the fixed point;
    :func:`polish_coefficients`), EQUIP's :func:`equip_energy_condition`, the followers'
    :func:`sources_block`, :func:`gather_sources` and :func:`solve_followers`, then the
    commit and the two guards, :func:`resolution_check` and :func:`energy_check`.  These are
    inlined into this function when compiled (``integrators.specialise.INLINED``): one call
    level with this many arrays costs tens of nanoseconds an iteration (measured on Kepler,
    where a step costs one microsecond), inlined it costs nothing, and the floating-point
    operations are the same, in the same order."""
    _, minv, kin_w, params = system
    if _FULL is None:
        full = system.full
    else:
        full = _FULL
        if system.full != _FULL:
            raise RuntimeError("hbvm-md: internal error: the step was compiled for the other "
                               "form (integrators.specialise); its binding does not match the "
                               "system")
    y, cy, gamma, eref, clock = state
    NV, NVinv, NM = newton
    if _NEWTON:          # (the constant first: numba prunes the branch it decides)
        pass
    elif NM.shape[0] > 0:
        raise RuntimeError("hbvm-md: internal error: the step was compiled without the "
                           "simplified Newton iteration (integrators.specialise); its binding "
                           "hands it Newton matrices")
    max_iter, tol, etol, ebound, group = opts
    work, cwork, counters = wk
    nsteps, sample_every, out_t, out_y, out_e = samples
    t, ct = clock[0], clock[1]
    ts, Cp = method.ts, method.Cp       # (EQUIP's arrays; the rest is named by tableau)
    tab = tableau(method)
    tau, tau_lo, X0, X0_lo = tab.tau, tab.tau_lo, tab.X0, tab.X0_lo
    W, W_lo, I = tab.W, tab.W_lo, tab.I
    n = tau.shape[0]
    s, u = gamma.shape
    m = minv.shape[0]
    narrow = u < NARROW     # the sums entry by entry (see core.NARROW)
    ht, ht_lo, hist, dq, dq_lo, a, pg, g, X, F, G, Xp, Fp, yt, cyt, R, Rt, Z = carve(
        work, cwork, n, s, u, m, y.shape[0])
    # EQUIP (integrators.equip): Gauss's arrays in the places above, its own in more planes;
    # for HBVM the views are empty and every EQUIP branch below is skipped
    if _EQUIP is None:
        equip = Cp.shape[0] > 4
    else:
        equip = _EQUIP
    if equip:
        Xk, Fk, rho, htk, htk_lo, es = eq.carve(work, n, s, u, m, y.shape[0], Cp.shape[1])
        if eref.shape[0] < eq.EREF_EQUIP:
            raise ValueError("internal error: EQUIP carries alpha in eref[1:3]: eref too short")
    else:
        Xk, Fk, rho = view(work, 0, 0, u), view(work, 0, 0, u), view(work, 0, 0, u)
        htk, htk_lo, es = view1(work, 0, 0), view1(work, 0, 0), view1(work, 0, 0)
    K = Xk.shape[0]
    vel = _STAGE_VELOCITIES
    if vel and (full or equip):
        raise ValueError("internal error: stage velocities are the separable HBVM step's")
    XV, XVp = carve_velocities(work, work_sizes(n, s, u, m, y.shape[0])[0], n, m, vel)
    # Followers (module docstring): the sources' stage equations are solved as if alone, on
    # their own copies (the "block" the iteration below works on), then each follower's in
    # their field (solve_followers); without followers the block is the whole system
    at = -1
    if _FOLLOWERS and not (full or equip or vel or NM.shape[0] > 0):
        at = _followers(params)
    yb, cyb, mb, gb, ab, Xb, Fb, Xpb, Fpb, pb = y, cy, minv, g, a, X, F, Xp, Fp, params
    fb = work[:0]
    fo = 0
    us = 0
    if _FOLLOWERS and at >= 0:
        fb, fo, us, yb, cyb, mb, gb, ab, Xb, Fb, Xpb, Fpb, pb = sources_block(params, at, n, s,
                                                                              minv)
    if vel:              # the kernel reads (q, v) at the stages; the probe compares them too
        Xb, Xpb = XV, XVp
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
        sc = StepConstants(h, ht, ht_lo, h2, h2_lo)
        sck = StepConstants(h, htk, htk_lo, h2, h2_lo)     # (EQUIP's path)
        if equip:
            eq.start(es, eref)
            step_constants(h, Cp[eq.CP_VEC, :, 0], Cp[eq.CP_VEC, :, 1], htk, htk_lo)
        energy_ok = not equip
        counters[C_NFEV] += first_guess(full, vel, y, minv, params, gamma, E, narrow, g, X, F, G,
                                        XV)
        if _FOLLOWERS and at >= 0:
            gather_sources(y, cy, g, m, params, at, us, yb, cyb, gb)
        # the iteration: fixed point g <- P_s^T Omega f(stages(g)) (eq. (hbvm_sys)), or simplified
        # Newton when NM is not empty; the same stop rule either way (core.stop_action), then one
        # compensated evaluation (the polish) whose rounding is what the step keeps; only the polish
        # adds the low parts of the coefficients (C2_lo, I_lo, W_lo: below the rounding of the
        # iterations' own sums; leaving them out there costs nothing in accuracy, 4 % of a step
        # of the outer solar system in time, see core.project).  Not so in the full form, whose
        # stages depend on gamma at order h (the separable form's at order h^2): there the
        # polish moves gamma by what the low parts add (W_lo F, the same sign every step), the
        # stages it was evaluated at are off the final path by h I_s times that, and the energy
        # of a polynomial H drifts as h^2 (4.7e-18 a step of the 7.8e-18 of Henon-Heiles,
        # HBVM(12, 6), h = 0.5).  Iterating the full form with the low parts and the compensated
        # projection removes it (the rest, 0.5e-18, is the stop rule's truncation) but made its
        # step 27 % dearer (Kepler's Poincare transform, HBVM(6, 3)): left as a known weakness
        # (tests/test_conservation.py).
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
            stage_field(full, equip, vel, narrowb, polish, yb, cyb, mb, gb, ab, sc, es, method,
                        tab, h, Xb, Fb, G, R, pb)
            counters[C_NFEV] += n
            if it <= 3:          # the force's Lipschitz constant, for the round-off floor
                if it > 1:
                    lip, xmax = lipschitz_probe(Xb, Fb, Xpb, Fpb, lip)
                else:
                    copy2(Xpb, Xb)
                    copy2(Fpb, Fb)
            if polish:
                polish_coefficients(newton, W, W_lo, Fb, gb, pg, NV, NVinv, NM, R, Rt, Z)
                if energy_ok:
                    status = OK
                    break
                if not equip:      # (never reached: HBVM's energy_ok is True; this test lets
                    break          # numba leave EQUIP's energy condition out of HBVM's step)
                answer = equip_energy_condition(full, narrowb, yb, cyb, mb, kin_w, gb, ab, h, h2,
                                                sck, es, method, Xk, Fk, rho, R, pb, lip, xmax)
                counters[C_NFEV] += K
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
            delta, scale = coefficient_update(newton, narrowb, W, Fb, gb, pg, NV, NVinv, NM, R,
                                              Rt, Z)
            counters[C_LAST] = delta
            hstate = abs(h) * delta / yscale if yscale > 0.0 else np.inf
            action = stop_action(delta, scale, Fb, LIPSCHITZ_ULPS * EPS * xmax * lip, hstate,
                                 abs(h) * scale, ymax, it, hist, tol)
            if action == POLISH:
                polish = True
            elif action != ITERATE:
                status = -action
                break
        if _FOLLOWERS and at >= 0 and status == OK:
            status, itf, dlast = solve_followers(y, cy, minv, g, gb, Xb, params, at, us, sc, tab,
                                                 opts, R, fb, fo)
            if status != OK:
                counters[C_LAST] = dlast
            if itf > it:            # the counts are the longest block's (the step's depth)
                counters[C_NFEV] += n * (itf - it)
                it = itf
        counters[C_ITER] += it
        counters[C_LASTIT] = it
        if _NEWTON and newton:
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
        err = 0.0
        share = 0.0
        drift = 0.0
        if ebound > 0.0:
            err, worst, nfev, share = resolution_check(full, vel, yt, cyt, m, minv, gb, yb, mb,
                                                       Xb, Fb, Xpb, Fpb, W, tau, h, params, at,
                                                       pb, group)
            counters[C_NFEV] += nfev
            counters[C_ERR] = err
            counters[C_WORST] = worst
            if not err <= ebound:
                return fail(counters, NOT_RESOLVED, work_iter, work_nfev, work_newton)
        if etol != 0.0:
            checked, change = energy_check(full, y, yt, m, kin_w, params, etol, eref, h, g, W,
                                           I, G)
            if checked != OK:
                counters[C_CHANGE] = change
                return fail(counters, checked, work_iter, work_nfev, work_newton)
            drift = change
        if ebound > 0.0:     # (committed: the run's accumulated estimate, core.C_RUN_ERR)
            counters[C_RUN_ERR] += (err + DRIFT_PHASE * drift) * share
        copy1(y, yt)
        copy1(cy, cyt)
        copy2(gamma, g)
        if _RECENTRE:        # a system re-expressed between steps (systems.flow_composed)
            _recentre(y, cy, gamma, h, params)
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
    return OK


def advance(system, state, h, E, method, newton, opts, wk):
    """One step of :func:`run` (no samples); returns its status."""
    no_samples = view1(wk.work, 0, 0)          # (no allocation: see integrators.pointers)
    return run(system, state, h, E, method, newton, opts, wk,
               Samples(np.int64(1), np.int64(0), no_samples, view(wk.work, 0, 0, 0), no_samples))


def attempt(system, state, trial, h, h_prev, t_start, ext, method, newton, opts, wk, adaptive):
    """One step from ``state`` into ``trial`` (:class:`integrators.records.State`s sharing one
    clock); nothing of the state is changed.  h_prev: the previous step (nan: none), for the
    initial guess's extrapolation (``core.select_extrapolation`` with the arrays of ``ext``,
    :class:`integrators.records.Extrapolation`).

    adaptive.epsilon = 0: a fixed step; returns its status.  epsilon > 0: adaptive; a step whose
    own estimate of its local error (``core.resolution_error``, computed by the step's
    resolution check, which adaptive steps always run: with opts.ebound 0 at an infinite bound)
    exceeds epsilon, or whose iteration, own error check or energy check fails, is tried again
    smaller (the one controller, ``core.adapt_step``), leaving no trace in the counters;
    TOO_SMALL when the step would fall
    below adaptive.min_dt (or vanish at t_start).  adaptive.res: [h taken (or last tried), next
    h proposed, rejections (added), last rejection's error estimate (nan after a failed
    iteration), last failure's status]."""
    y, cy, gamma, eref, clock = state
    yt, cyt, gammat, ereft, _ = trial
    epsilon, min_dt, res = adaptive
    counters = wk.counters
    s = gamma.shape[0]
    snap = np.empty(counters.shape[0])
    clock0, clock1 = clock[0], clock[1]
    if epsilon > 0.0 and not opts.ebound > 0.0:
        # (the controller reads the step's own error estimate: computed, never refused)
        opts = Options(opts.max_iter, opts.tol, opts.etol, np.inf, opts.group)
    while True:
        copy1(yt, y)
        copy1(cyt, cy)
        copy2(gammat, gamma)
        copy1(ereft, eref)          # (the energy; EQUIP's alpha and slope)
        clock[0] = clock0
        clock[1] = clock1
        for i in range(counters.shape[0]):
            snap[i] = counters[i]
        E = select_extrapolation(h, h_prev, ext.E1, ext.t, ext.w, ext.buf, ext.zero)
        status = advance(system, State(yt, cyt, gammat, ereft, clock), h, E, method, newton,
                         opts, wk)
        res[0] = h
        res[1] = h
        if epsilon <= 0.0 or status == DRIFTED:   # (the run's past: no shorter step undoes it)
            return status
        err = counters[C_ERR] if status == OK or status == NOT_RESOLVED else np.nan
        if _FOLLOWERS and status == OK:     # (the test particles, solved apart: core's docs)
            err = test_particle_control(gammat, system.minv, system.kin_w, err)
        accept, h_new, too_small = adapt_step(h, status, err, epsilon, s, t_start, min_dt)
        if accept:
            res[1] = h_new
            return OK
        if status == OK:
            for i in range(counters.shape[0]):      # a rejected step leaves no trace
                counters[i] = snap[i]
        res[3] = err
        res[4] = status
        res[2] += 1.0
        if too_small:
            return TOO_SMALL
        h = h_new
