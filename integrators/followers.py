"""The followers' step: test particles solved after the sources, each with its own stop rule.

A separable system may split its unknowns into *sources* and *followers* (REBOUND's test
particles): :func:`integrators.loop.run` solves the sources' stage equations first, as if
alone, then calls :func:`follow` for the followers' in the sources' field at their stage
values (design page "One step, written once", "Followers").  Like the loop, this file is
compiled by :mod:`integrators.specialise` into the step module of a scene with followers, with
the system's hook ``_field(Xt, Xs, params, out)`` bound (the followers' right-hand side at
their stage values Xt from the sources' Xs); a scene without followers binds
:func:`integrators.absent.follow` instead and compiles none of this.
"""
import numpy as np

from integrators.core import (DIVERGED, EPS, FOLLOWER_GROUP, ITERATE, LIPSCHITZ_ULPS, NARROW, OK,
                              POLISH, compact_slots, copy2, lipschitz_slots, project_compensated,
                              project_each, stage_positions, stage_positions_narrow, stop_action)
from integrators.pointers import view, view1
from integrators.records import Block

_field = None        # bound by integrators.specialise (a system's followers field kernel)


def follower_stages(blk, g, tab, sc, Xs, ps, R, exact):
    """A group of followers' stage values blk.X from their state (blk.y, .cy, .minv) and
    coefficients g, then their right-hand side blk.F in the sources' field at their stage values
    Xs (``exact``: with the coefficients' low parts, for the polish, as in :func:`run`)."""
    if blk.X.shape[1] < NARROW:
        stage_positions_narrow(blk.y, blk.cy, blk.minv, g, tab.C2, tab.C2_lo, sc, blk.a, blk.X,
                               exact)
    else:
        stage_positions(blk.y, blk.cy, blk.minv, g, tab.C2, tab.C2_lo, sc, blk.a, blk.X, R,
                        exact)
    _field(blk.X, Xs, ps, blk.F)


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


def follow(y, cy, minv, g, Xs, params, at, sc, tab, opts, R, fb):
    """The followers' stage equations, after the sources': each follower (a slot of ``width``
    columns, a test particle's three) is iterated in the sources' field at their stage values
    Xs (n, us) with the fixed-point iteration and stop rule of :func:`run`, applied to it alone
    (its own increments, sizes, round-off floors and runaway test, :func:`core.stop_action`;
    opts: the step's :class:`integrators.records.Options`),
    and leaves the iteration when it has converged: one slow follower makes neither the
    sources nor the others iterate.  Then one compensated evaluation (the polish, as in
    :func:`run`).  The followers go through in groups of ``core.FOLLOWER_GROUP``, each
    iterated to the end before the next (their arrays stay in cache, and the time per
    follower does not depend on how many there are).  g (s, u): the step's coefficients, the
    followers' columns holding their initial guess, overwritten with the result; params[at:]:
    the followers block (``systems.nbody.followers_block``); fb: scratch
    (``core.follower_size`` past the sources' block); sc, tab: the step's constants and the
    method's arrays; R: the step's scratch of column sums.  Returns (status,
    iterations of the slowest follower, the polish included, and the last increment of the
    follower that failed (after max_iter iterations: the largest of those still iterating), 0
    when none did)."""
    h, W, W_lo = sc.h, tab.W, tab.W_lo
    max_iter, tol = opts.max_iter, opts.tol
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
    o_y, o_cy, o_m = 0, 2 * up, 4 * up
    o_g = 5 * up
    o_all = o_g + s * up
    o_a = o_g + 2 * s * up
    o_x = o_a + s * up
    o_f, o_xp, o_fp = o_x + n * up, o_x + 2 * n * up, o_x + 3 * n * up
    dcol = view1(fb, o_x + 4 * n * up, up)
    scol = view1(fb, o_x + 4 * n * up + up, up)
    o_h = o_x + 4 * n * up + 2 * up
    o_lip, o_xmax, o_ymax, o_who, o_keep = (o_h + 5 * nmax, o_h + 6 * nmax, o_h + 7 * nmax,
                                            o_h + 8 * nmax, o_h + 9 * nmax)
    if fb.shape[0] < o_keep + nmax:     # (the views below are not bounds-checked)
        raise ValueError("internal error: the followers' work buffer is shorter than its "
                         "layout here (core.follower_size)")
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
            follower_stages(Block(ya, cya, ma, aa, Xa, Fa), ga, tab, sc, Xs, ps, R, False)
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
        follower_stages(Block(ya, cya, ma, aa, Xa, Fa), gall, tab, sc, Xs, ps, R, True)
        project_compensated(W, W_lo, Fa, gall, R)
        for j in range(pc):
            c0 = int(params[fcol + j0 + j])
            for i in range(s):
                for c in range(w):
                    g[i, c0 + c] = gall[i, w * j + c]
    return OK, itmax, 0.0
