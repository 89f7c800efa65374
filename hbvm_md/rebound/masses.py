"""Masses changed between two steps, taken in place: the REBOUND host's answer to a RESYNC
that a change of masses alone caused.

REBOUNDx's ``modify_mass`` (and any operator or callback that changes masses) changes a mass
after every step.  The compiled step then answers RESYNC (:mod:`hbvm_md.rebound.glue` reads
moved particles itself, but a mass is part of the model), and the host's ``prepare`` used to
build the model, the binding and the context block again at every step (measured on REBOUNDx's
ModifyMass notebook: about 0.4 ms a step, 34 times IAS15's time for the run).  With the same
particle array, N, G, N_active, settings and method, no variational particles and the same
bodies gravitating (no mass became zero or nonzero), nothing of that changes but numbers:
:func:`masses_only` writes the new masses where the step reads them and returns True, and the
step goes on.

What is updated: the masses in the kernel parameters (:func:`systems.nbody.nbody_set_masses`,
:func:`hbvm_md.rebound.forces.scene_set_masses`: each model owns its layout); on the separable
N-body form the weights 1/m and the kinetic weights of the sources (as
:class:`integrators.engine.Binding` computes them from ``NBody.masses``); the context's copy of
the particles; the state as the host's prepare takes a saved or copied run's (kept with its
compensations when it still holds the particles with the new weights, else read from them:
q = x, and p = v / (1/m) with the new masses, or the velocities on REBOUND's own
accelerations, the compensations zeroed, as the glue does for moved particles), so that a
restart continues bit for bit.  The reference energy starts afresh, as after any resync: the energy
check then compares each step with its own start, and the energy that the mass change moved
is not counted as the step's error.  The previous coefficients stay the next step's initial
guess (the fixed-point iteration converges from them to the same solution).
"""
from __future__ import annotations

import numpy as np

from hbvm_md.rebound import layout as L
from hbvm_md.rebound.memory import doubles, int64s
from hbvm_md.rebound.forces import masses_at, scene_set_masses
from integrators.jit import jit
from systems.nbody import nbody_set_masses

#: layout.py's digest (as cabi.LAYOUT_DIGEST): numba caches this module's compiled functions
#: with layout's slot numbers compiled in, keyed on this file alone, so a layout change must
#: change this file too (tests/test_rebound_host.py keeps it current); else a ``git pull`` of a
#: new layout over an old cache loads code that indexes the state with the old slots
LAYOUT_DIGEST = "e1008eefe6ce66b8"

_METHOD_SLOTS = ((L.SL_S, L.D_S), (L.SL_K, L.D_K), (L.SL_NODES, L.D_NODES),
                 (L.SL_METHOD, L.D_METHOD))


def same_model(ctx: np.ndarray, simi: np.ndarray) -> bool:
    """Does the simulation (simi: its first ctx[R_HEAD] words as int64) have the G, N_active
    and the settings HBVM checks that the context block (ctx: its int64 header) was built
    with?  The compiled step's RESYNC test of them (:func:`hbvm_md.rebound.glue.core_step`),
    for the host's Python side (here, and ``state.model_changed``)."""
    host = doubles(int(ctx[L.A_HOST]), L.N_HOST)
    return (simi.view(np.float64)[ctx[L.R_G]] == host[0]
            and float(simi[ctx[L.R_NACTIVE]]) == host[1]
            and np.array_equal(simi[ctx[L.C_WORDS:L.C_VALUES]],
                               ctx[L.C_VALUES:L.C_VALUES + L.N_CFG]))


def masses_only(r: int, p: int) -> bool:
    """Take a change of masses only in place (module docstring): True when done, False
    (nothing changed) when the host must prepare the step afresh.  r: the simulation's
    address, p: HBVM's state's."""
    st = int64s(p, L.N_SLOTS)
    if not (st[L.SL_CTX] and st[L.SL_CORE]):
        return False
    ctx = int64s(int(st[L.SL_CTX]), L.N_HEADER)
    # (the composed step's state and parameters hold the masses: it is prepared afresh)
    if ctx[L.D_NV] != 0 or ctx[L.D_KEPLER] or any(st[a] != ctx[b] for a, b in _METHOD_SLOTS):
        return False
    # what the compiled step's RESYNC tests compare (glue.core_step, step_arrays)
    simi = int64s(r, int(ctx[L.R_HEAD]))
    N = int(ctx[L.D_N])
    if (simi[ctx[L.R_PARTICLES]] != ctx[L.D_PTR] or simi[ctx[L.R_N]] != N
            or not same_model(ctx, simi)):
        return False
    m = int(ctx[L.D_M])
    stride = int(ctx[L.R_STRIDE])
    done = update_masses(
        doubles(int(ctx[L.D_PTR]), N * stride).reshape(N, stride),
        doubles(int(ctx[L.A_WRITTEN]), 7 * N).reshape(N, 7),
        doubles(int(ctx[L.A_PARAMS]), int(ctx[L.D_P])),
        doubles(int(ctx[L.A_MINV]), m),
        doubles(int(ctx[L.A_KINW]), m), doubles(int(st[L.SL_Y]), 4 * m),
        doubles(p + 8 * L.SL_EREF, L.N_EREF), bool(ctx[L.D_HOST]),
        int(ctx[L.R_X]), int(ctx[L.R_VX]), int(ctx[L.R_M]),
        # (the layout of REBOUND's own accelerations' parameters read here, not compiled in)
        masses_at(doubles(int(ctx[L.A_PARAMS]), int(ctx[L.D_P]))) if ctx[L.D_HOST] else 0)
    if done:
        st[L.SL_RESYNCS] += 1
    return done


@jit
def update_masses(view, written, params, minv, kin_w, y, eref, host, ix, ivx, im, g0):
    """The step's arrays <- REBOUND's particles whose masses (and perhaps positions and
    velocities) changed since the last commit, in place (module docstring).

    view: (N, stride) REBOUND's particles (x, vx, m at columns ix, ivx, im); written (N, 7):
    the last commit's x, v, m; params: the kernel parameters; minv (u,), kin_w (m,): the
    step's weights; y (4m,): the state and its compensations; eref: the energy reference (and
    EQUIP's alpha and slope); host: the state is (q, clock, v, CLOCK) on REBOUND's own
    accelerations (weights 1, kinetic weights the gravitating masses), else (q, p) of the
    N-body kernel; g0: where the gravitating masses start in params on REBOUND's own
    accelerations (:func:`hbvm_md.rebound.forces.masses_at`).  Returns False, changing
    nothing, when no mass changed, a value is not finite, or a body's mass became or stopped
    being zero (the model's structure changes: the host prepares afresh).  A mass may change
    sign: a negative mass is a source (:mod:`systems.nbody`), its weights 1/m negative."""
    N = view.shape[0]
    changed = False
    for i in range(N):
        mi, wi = view[i, im], written[i, 6]
        if not np.isfinite(mi) or (mi != 0.0) != (wi != 0.0):
            return False
        changed = changed or mi != wi
        for c in range(3):
            if not (np.isfinite(view[i, ix + c]) and np.isfinite(view[i, ivx + c])):
                return False
    if not changed:
        return False
    mass = np.empty(N)
    for i in range(N):
        mass[i] = view[i, im]
    m = y.shape[0] // 4
    if host:
        scene_set_masses(params, mass, g0)
    else:
        nbody_set_masses(params, mass)
    # The state as the host's prepare takes a saved or copied run's (host._prepare), so that
    # a run restarted between a mass change and the next step continues as this one does, bit
    # for bit: kept with its compensations when it still holds the particles with the new
    # weights (q = x, p / m = v: sources at rest, test particles), else read afresh as moved
    # particles are (q = x, p = v / (1/m), the compensations zeroed).  (It used to take p =
    # m v and zero the compensations always: a restart differed by 1e-14.)
    keep = True
    for i in range(N):
        # a source's weights are 1/m (kin_w != 0 marks a source, of either sign: a test
        # particle's momentum is its velocity, weight 1, kinetic weight 0); on REBOUND's own
        # accelerations the state holds velocities and a source's kinetic weight is its mass
        source = kin_w[3 * i] != 0.0
        for c in range(3):
            j = 3 * i + c
            if host:
                if source:
                    kin_w[j] = mass[i]
            elif source:
                minv[j] = 1.0 / mass[i]
                kin_w[j] = minv[j]
            if y[j] != view[i, ix + c] or y[m + j] * minv[j] != view[i, ivx + c]:
                keep = False
    for i in range(N):
        for c in range(3):
            j = 3 * i + c
            if not keep:
                y[j] = view[i, ix + c]
                y[m + j] = view[i, ivx + c] / minv[j]
            written[i, c] = view[i, ix + c]
            written[i, 3 + c] = view[i, ivx + c]
        written[i, 6] = mass[i]
    if not keep:
        for j in range(2 * m, 4 * m):
            y[j] = 0.0                 # the compensations
    for j in range(eref.shape[0]):
        eref[j] = np.nan
    return True
