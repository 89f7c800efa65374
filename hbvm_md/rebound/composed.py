"""``sim.integrator.kepler = 1``: the host's preparation of HBVM composed with the Keplerian
flows (issue 48).  The model, its variables and its step are the engine's
(:class:`systems.flow_composed.FlowComposed`, bound with the one step by
:class:`integrators.engine.Binding`); the step REBOUND calls is
:mod:`hbvm_md.rebound.kepler_glue`.  Here: what the composed step cannot take (refused by
name, with the way out; REBOUNDx's ``gr_potential`` is modelled, as a term of the perturbation),
the state from the particles (or the saved one, when it is theirs: a copy or a loaded file
continues bit for bit) and the context block."""
from __future__ import annotations

import ctypes
import math

import numpy as np

from hbvm_md.rebound import layout as L
from hbvm_md.rebound.checks import check_particles
from hbvm_md.rebound.forces import host_reasons, ode_signature, reboundx_forces
from hbvm_md.rebound.kepler_glue import N_COM
from hbvm_md.rebound.memory import doubles
from integrators.core import N_COUNTERS
from integrators.engine import Binding
from systems.flow_composed import FlowComposed, composed_bodies
from systems.nbody import NBody

#: the way out named by every refusal
WAY_OUT = "use sim.integrator.kepler = 0 (HBVMIntegrator(sim, kepler=False)), plain HBVM"


#: the REBOUNDx force the composed step models, as a term of its perturbation
GR_POTENTIAL = "gr_potential"


def gr_potential_c(sim) -> float | None:
    """The speed of light ``c`` of the REBOUNDx ``gr_potential`` force attached to ``sim`` (the
    term :class:`FlowComposed` takes as ``gr_c``), None when none is attached; a ValueError when
    its ``c`` is not set or not a positive number, or when more than one is attached."""
    forces = [a for name, a in (reboundx_forces(sim) or []) if name == GR_POTENTIAL]
    if not forces:
        return None
    if len(forces) > 1:
        raise ValueError(f"sim.integrator.kepler = 1 models one REBOUNDx 'gr_potential' force "
                         f"(got {len(forces)}); attach one, or {WAY_OUT}")
    import reboundx
    try:
        c = reboundx.extras.Force.from_address(forces[0]).params["c"]
    except AttributeError:
        c = None
    if c is None or not (math.isfinite(c) and c > 0):
        raise ValueError(f"REBOUNDx 'gr_potential' needs its speed of light in the simulation's "
                         f"units: set force.params['c'] (got c={c!r}; 63241.077 in AU/yr)")
    return float(c)


def check_composed(sim) -> None:
    """Refuse, naming the reason and the way out, a simulation the composed step does not
    model: anything beyond Newtonian gravity and one REBOUNDx ``gr_potential`` (the rest would
    be left out of the perturbation), variational particles, massive bodies past N_active,
    fewer than two bodies, a particle 0 that is not the dominant mass, or a body not bound to
    it."""
    reasons = host_reasons(sim)
    # REBOUNDx's gr_potential is a potential of the heliocentric positions about particle 0,
    # the composed step's central body: a term of H_I (systems.flow_composed._gr_potential)
    if gr_potential_c(sim) is not None:
        reasons.remove(f"REBOUNDx '{GR_POTENTIAL}'")
    if reasons:
        raise ValueError(
            f"sim.integrator.kepler = 1 composes HBVM with the Keplerian flows of Newtonian "
            f"gravity about particle 0, and its perturbation holds the planets' mutual gravity "
            f"and REBOUNDx's 'gr_potential' only; this simulation has {', '.join(reasons)}, "
            f"which it would leave out: {WAY_OUT}, which runs them on REBOUND's own "
            f"accelerations")
    if sim.N_var > 0:
        raise ValueError(f"sim.integrator.kepler = 1 with {sim.N_var} variational particles: "
                         f"the tangent map is plain HBVM's; {WAY_OUT}")
    N = sim.N
    if N < 2:
        raise ValueError(f"sim.integrator.kepler = 1 needs a central body (particle 0) and at "
                         f"least one more (got {N} particles); {WAY_OUT}")
    xv, m = np.zeros(6 * N), np.zeros(N)
    sim.serialize_particle_data(xyzvxvyvz=xv, m=m)
    xv = xv.reshape(N, 6)
    if not np.all(np.isfinite(xv)) or not np.all(np.isfinite(m)):
        raise ValueError("the simulation holds non-finite positions, velocities or masses")
    # test particles are bodies of mass 0 (systems.flow_composed); a massive body past
    # N_active would be a body that pulls nothing yet has a mass, which it does not model
    passive = np.flatnonzero(m[sim.N_active:] != 0.0) if 0 <= sim.N_active < N else []
    if len(passive):
        i = int(passive[0]) + sim.N_active
        raise ValueError(f"sim.integrator.kepler = 1 takes test particles of mass 0 only; "
                         f"particle {i} is past N_active={sim.N_active} with m={m[i]!r}; set "
                         f"its mass to 0, or {WAY_OUT}")
    bad = np.flatnonzero(m[1:] < 0.0)
    if bad.size:
        i = int(bad[0]) + 1
        raise ValueError(f"sim.integrator.kepler = 1 needs masses >= 0 (0: a test particle; "
                         f"got m[{i}]={m[i]!r}); {WAY_OUT}")
    big = np.flatnonzero(m[1:] >= m[0])
    if not m[0] > 0.0 or big.size:
        i = int(big[0]) + 1 if big.size else 0
        raise ValueError(f"sim.integrator.kepler = 1 needs particle 0 to be the dominant mass, "
                         f"about which the others move on Keplerian orbits (m[0]={m[0]!r}, "
                         f"m[{i}]={m[i]!r}); put the central body first, or {WAY_OUT}")
    # the composed variables' Keplerian part: heliocentric positions, barycentric velocities,
    # mu = G m_0 (systems.flow_composed)
    vcm = (m[:, None] * xv[:, 3:]).sum(axis=0) / m.sum()
    Q = xv[1:, :3] - xv[0, :3]
    V = xv[1:, 3:] - vcm
    r = np.linalg.norm(Q, axis=1)
    energy = 0.5 * np.einsum("ij,ij->i", V, V) - sim.G * m[0] / r
    unbound = np.flatnonzero(~(energy < 0.0))
    if unbound.size:
        i = int(unbound[0]) + 1
        raise ValueError(f"sim.integrator.kepler = 1 needs every body bound to particle 0; "
                         f"particle {i} is not (its Keplerian energy about particle 0 is "
                         f"{energy[i - 1]:.3g} >= 0, at distance {r[i - 1]:.3g}): its "
                         f"perturbation would not stay small; {WAY_OUT}")


def prepare_composed(sim, p: int, method) -> None:
    """Build (again) the composed step for ``sim`` (HBVM's state at ``p``): the checks, the
    engine's :class:`FlowComposed` bound with the step and the kepler glue, the state (the
    saved one when its bodies are the particles bit for bit, else afresh from the particles:
    ``FlowComposed.extend``, the barycentre kept in ``com``) and the context block."""
    from hbvm_md.rebound import host as H
    st, sd = H._slots(p)
    check_composed(sim)
    import numba
    if numba.config.DISABLE_JIT:
        raise ValueError(f"sim.integrator.kepler = 1 runs compiled only; unset "
                         f"NUMBA_DISABLE_JIT, or {WAY_OUT}")
    h = sim.dt
    if not (math.isfinite(h) and h != 0.0):
        H._step_size("sim.dt", h)
    N = sim.N
    offsets = H._REG["offsets"]
    stride = offsets[L.R_STRIDE - L.R_T]
    ix, ivx, im = (offsets[i - L.R_T] for i in (L.R_X, L.R_VX, L.R_M))
    ptr = ctypes.cast(sim._particles, ctypes.c_void_p).value
    view = doubles(ptr, N * stride).reshape(N, stride)
    nb = NBody.from_rebound(sim)
    gr_c = gr_potential_c(sim)
    fc = FlowComposed.from_nbody(nb, h, gr_c=gr_c)
    binding = Binding(method, fc, form="full", fast=None, glue="hbvm_md.rebound.kepler_glue")
    m, s = fc.dim, method.s
    size = 4 * m + N_COM
    y, g, c = (doubles(int(st[a]), int(st[n])) for a, n in
               ((L.SL_Y, L.SL_NY), (L.SL_GAMMA, L.SL_NGAMMA), (L.SL_COUNTERS, L.SL_NCOUNTERS)))
    keep = False
    if (not H._model_changed(st, sim, False) and y.size == size and g.size == s * 2 * m
            and np.isfinite(sd[L.SL_H_PREV])):
        # a copied or loaded run, or one resynced: its state is the particles' when the bodies
        # it gives are the particles bit for bit (the last step wrote them from it)
        out = np.empty((N, 6))
        bad = composed_bodies(y[:2 * m], fc._params, y[4 * m:], sim.t, out)
        # ... and it was integrated with this model's GR term (com[8]: a copy loses REBOUNDx's
        # forces, a user may change c between runs): else its reference energy and
        # coefficients belong to another H, and it starts afresh, as after a mass change
        keep = (bad == 0 and np.array_equal(out[:, :3], view[:, ix:ix + 3])
                and np.array_equal(out[:, 3:], view[:, ivx:ivx + 3])
                and y[4 * m + 8] == (gr_c or 0.0))
        if keep:
            y[4 * m + 7] = sim.t          # (the bodies are those of this time)
    if not keep:
        y0 = nb.initial_state()
        check_particles(y0, nb)
        y = H._array(st, L.SL_Y, L.SL_NY, size)
        y[:] = 0.0
        y[:2 * m] = fc.extend(y0)
        xcm, vcm = fc._com
        y[4 * m:4 * m + 3], y[4 * m + 3:4 * m + 6] = xcm, vcm
        y[4 * m + 6] = y[4 * m + 7] = sim.t
        y[4 * m + 8] = gr_c or 0.0
        H._array(st, L.SL_GAMMA, L.SL_NGAMMA, s * 2 * m)[:] = 0.0
        sd[L.SL_H_PREV] = np.nan
        sd[L.SL_EREF:L.SL_EREF + L.N_EREF] = np.nan
        st[L.SL_RESYNCS] += 1
    if c.size != N_COUNTERS:
        H._array(st, L.SL_COUNTERS, L.SL_NCOUNTERS, N_COUNTERS)[:] = 0.0
    st[L.SL_ECHECK] = 1
    H._context(st, binding, method, None, view, ptr, sim, ix, ivx, im, kepler=True)
    st[L.SL_CORE] = binding.step_code.core_step.address
    addr = ctypes.addressof(sim)
    H._FORCES[addr] = tuple(reboundx_forces(sim) or ())
    # (its c is read into the model: a change between runs prepares the step again,
    # host._recheck_forces)
    H._KEPLER_GR[addr] = gr_c
    H._ODES[addr] = ode_signature(sim)
    H._HOST_PATH.discard(addr)
