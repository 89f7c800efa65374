"""``sim.integrator.kepler = 1``: the host's preparation of HBVM composed with the Keplerian
flows (issue 48).  The model, its variables and its step are the engine's
(:class:`systems.flow_composed.FlowComposed`, bound with the one step by
:class:`integrators.engine.Binding`); the step REBOUND calls is
:mod:`hbvm_md.rebound.kepler_glue`.  Here: what the composed step cannot take (refused by
name, with the way out; REBOUNDx's ``gr_potential``, and ``gravitational_harmonics`` and
``central_force`` from particle 0, are modelled, as terms of the perturbation),
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
#: steps shorter than the shortest orbital period over this are warned about (REBOUND's default
#: sim.dt is 0.001: a user who forgot to set a step would wait hours, and the flows' round-off
#: grows with the number of steps)
KEPLER_FEW_STEPS = 1000
def warn_short_step(sim, h: float, fix: str, stacklevel: int | None = None,
                    state: int | None = None) -> None:
    """The composed method's warning for a step far shorter than it is for (1/25 to 1/50 of
    the shortest orbital period), naming ``fix`` ("pass dt=", "set sim.dt"); not for the step
    HBVMIntegrator attached HBVM's ``state`` with (its record's kepler_seen_dt)."""
    import warnings
    from hbvm_md.rebound.checks import shortest_period
    from hbvm_md.rebound.state import record_of_state
    if state is not None and record_of_state(state).kepler_seen_dt == h:
        return
    period = shortest_period(sim)
    if not (math.isfinite(period) and abs(h) < period / KEPLER_FEW_STEPS):
        return
    if stacklevel is None:
        from hbvm_md.rebound.state import user_stacklevel as _user_stacklevel
        stacklevel = _user_stacklevel()
    warnings.warn(
        f"{'kepler=True' if fix.startswith('pass') else 'sim.integrator.kepler = 1'} steps "
        f"sim.dt={h!r}, 1/{period / abs(h):.3g} of the shortest orbital period "
        f"({period:.3g}): the composed method is for long steps (1/25 to 1/50 of it); {fix}, "
        f"e.g. {'dt' if fix.startswith('pass') else 'sim.dt'}={period / 50:.3g}", RuntimeWarning,
        stacklevel=stacklevel)


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


#: REBOUNDx's forces from particle 0 that are potentials of the heliocentric positions, with
#: the reaction on it, and the particle parameters that set them: terms of H_I
HARMONICS, CENTRAL = "gravitational_harmonics", "central_force"
MODELLED = (GR_POTENTIAL, HARMONICS, CENTRAL)


def _one(sim, name):
    """True when exactly one REBOUNDx force ``name`` is attached (False: none); a ValueError
    when several are (REBOUNDx would apply each)."""
    n = sum(1 for f, _ in (reboundx_forces(sim) or []) if f == name)
    if n > 1:
        raise ValueError(f"sim.integrator.kepler = 1 models one REBOUNDx '{name}' force "
                         f"(got {n}); attach one, or {WAY_OUT}")
    return n == 1


def _param(p, name):
    try:
        return p.params[name]
    except AttributeError:          # (REBOUNDx's "Parameter not found on object")
        return None


def _number(i, name, v, fix):
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"REBOUNDx parameter {name} of particle {i} must be a finite number "
                         f"(got {name}={v!r}); {fix}")
    return float(v)


def force_terms(sim) -> tuple:
    """The REBOUNDx forces the composed step models as terms of H_I, as
    :class:`FlowComposed` takes them: (gr_c, harmonics, central), each None when absent
    (``gr_potential``'s c; ``gravitational_harmonics`` with particle 0's J2, J4, R_eq, Omega;
    ``central_force`` with its Acentral, gammacentral).  A ValueError names what it cannot
    take: a harmonic or a central force from another particle (its reaction moves that
    particle, not the star of the Keplerian flows), a parameter that is not a finite number."""
    gr_c = gr_potential_c(sim)
    harm = _one(sim, HARMONICS)
    cent = _one(sim, CENTRAL)
    harmonics = central = None
    if not (harm or cent):
        return gr_c, None, None
    ps = sim.particles
    for i in range(sim.N):
        p = ps[i]
        if not p.ap:
            continue                # (no REBOUNDx parameter on it)
        if harm:
            # REBOUNDx applies the harmonics of a particle with J2 != 0 and R_eq set
            j2 = _number(i, "J2", _param(p, "J2"), f"set it, or {WAY_OUT}")
            R = _number(i, "R_eq", _param(p, "R_eq"), f"set it, or {WAY_OUT}")
            if j2 not in (None, 0.0) and R is not None:
                if i != 0:
                    raise ValueError(
                        f"sim.integrator.kepler = 1 models REBOUNDx's '{HARMONICS}' of "
                        f"particle 0 only; particle {i} has J2={j2!r}: its harmonics pull the "
                        f"star off the Keplerian flows' centre; set its J2 to 0, or {WAY_OUT}")
                j4 = _number(i, "J4", _param(p, "J4"), f"set it, or {WAY_OUT}") or 0.0
                omega = _param(p, "Omega")
                if not R > 0:
                    raise ValueError(f"REBOUNDx parameter R_eq of particle 0 must be > 0 (got "
                                     f"R_eq={R!r}); set it, or {WAY_OUT}")
                if omega is not None and not (
                        len(omega) == 3 and all(math.isfinite(o) for o in omega) and any(omega)):
                    raise ValueError(f"REBOUNDx parameter Omega of particle 0 (the spin axis of "
                                     f"its harmonics) must be 3 finite numbers, not all 0 (got "
                                     f"Omega={omega!r}); {WAY_OUT}")
                harmonics = (j2, j4, R) + (() if omega is None else (tuple(omega),))
        if cent:
            A = _number(i, "Acentral", _param(p, "Acentral"), f"set it, or {WAY_OUT}")
            gamma = _number(i, "gammacentral", _param(p, "gammacentral"),
                            f"set it, or {WAY_OUT}")
            # REBOUNDx applies the force of a particle with both set (A = 0: no force)
            if A not in (None, 0.0) and gamma is not None:
                if i != 0:
                    raise ValueError(
                        f"sim.integrator.kepler = 1 models REBOUNDx's '{CENTRAL}' from "
                        f"particle 0 only; particle {i} has Acentral={A!r}: its reaction moves "
                        f"that particle, not the Keplerian flows' centre; {WAY_OUT}")
                central = (A, gamma)
    return gr_c, harmonics, central


def terms_record(fc) -> np.ndarray:
    """The force terms' block of FlowComposed's params (its layout: c_light, J2, J4, R_eq, the
    unit spin axis, A, gamma): what the saved state records it was integrated with."""
    from systems.flow_composed import _terms
    return np.array(_terms(fc._params))


def check_composed(sim) -> None:
    """Refuse, naming the reason and the way out, a simulation the composed step does not
    model: anything beyond Newtonian gravity and one REBOUNDx ``gr_potential`` (the rest would
    be left out of the perturbation), variational particles, massive bodies past N_active,
    fewer than two bodies, a particle 0 that is not the dominant mass, or a body not bound to
    it."""
    reasons = host_reasons(sim)
    # REBOUNDx's gr_potential, gravitational_harmonics and central_force from particle 0 are
    # potentials of the heliocentric positions about it, the composed step's central body:
    # terms of H_I (systems.flow_composed._potential_terms); force_terms refuses the rest
    force_terms(sim)
    for name in MODELLED:
        if f"REBOUNDx '{name}'" in reasons:
            reasons.remove(f"REBOUNDx '{name}'")
    if reasons:
        raise ValueError(
            f"sim.integrator.kepler = 1 composes HBVM with the Keplerian flows of Newtonian "
            f"gravity about particle 0, and its perturbation holds the planets' mutual gravity "
            f"and REBOUNDx's {', '.join(repr(n) for n in MODELLED)} from particle 0 only; this "
            f"simulation has {', '.join(reasons)}, "
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
    from hbvm_md.rebound import state as H
    from hbvm_md.rebound.checks import _step_size
    st, sd = H.slots(p)
    check_composed(sim)
    import numba
    if numba.config.DISABLE_JIT:
        raise ValueError(f"sim.integrator.kepler = 1 runs compiled only; unset "
                         f"NUMBA_DISABLE_JIT, or {WAY_OUT}")
    h = sim.dt
    if not (math.isfinite(h) and h != 0.0):
        _step_size("sim.dt", h)
    N = sim.N
    offsets = H.REG["offsets"]
    stride = offsets[L.R_STRIDE - L.R_T]
    ix, ivx, im = (offsets[i - L.R_T] for i in (L.R_X, L.R_VX, L.R_M))
    ptr = ctypes.cast(sim._particles, ctypes.c_void_p).value
    view = doubles(ptr, N * stride).reshape(N, stride)
    nb = NBody.from_rebound(sim)
    terms = force_terms(sim)
    fc = FlowComposed.from_nbody(nb, h, gr_c=terms[0], harmonics=terms[1], central=terms[2])
    record = terms_record(fc)
    binding = Binding(method, fc, form="full", fast=None, glue="hbvm_md.rebound.kepler_glue")
    m, s = fc.dim, method.s
    size = 4 * m + N_COM
    y, g, c = (doubles(int(st[a]), int(st[n])) for a, n in
               ((L.SL_Y, L.SL_NY), (L.SL_GAMMA, L.SL_NGAMMA), (L.SL_COUNTERS, L.SL_NCOUNTERS)))
    keep = False
    if (not H.model_changed(st, sim, False) and y.size == size and g.size == s * 2 * m
            and np.isfinite(sd[L.SL_H_PREV])):
        # a copied or loaded run, or one resynced: its state is the particles' when the bodies
        # it gives are the particles bit for bit (the last step wrote them from it)
        out = np.empty((N, 6))
        bad = composed_bodies(y[:2 * m], fc._params, y[4 * m:], sim.t, out)
        # ... and it was integrated with this model's force terms (com[8:]: a copy loses
        # REBOUNDx's forces, a user may change c, J2, Acentral between runs): else its reference energy and
        # coefficients belong to another H, and it starts afresh, as after a mass change
        keep = (bad == 0 and np.array_equal(out[:, :3], view[:, ix:ix + 3])
                and np.array_equal(out[:, 3:], view[:, ivx:ivx + 3])
                and np.array_equal(y[4 * m + 8:], record))
        if keep:
            y[4 * m + 7] = sim.t          # (the bodies are those of this time)
    if not keep:
        warn_short_step(sim, h, "set sim.dt", state=p)
        y0 = nb.initial_state()
        check_particles(y0, nb)
        y = H.array(st, L.SL_Y, L.SL_NY, size)
        y[:] = 0.0
        y[:2 * m] = fc.extend(y0)
        xcm, vcm = fc._com
        y[4 * m:4 * m + 3], y[4 * m + 3:4 * m + 6] = xcm, vcm
        y[4 * m + 6] = y[4 * m + 7] = sim.t
        y[4 * m + 8:] = record
        H.array(st, L.SL_GAMMA, L.SL_NGAMMA, s * 2 * m)[:] = 0.0
        sd[L.SL_H_PREV] = np.nan
        sd[L.SL_EREF:L.SL_EREF + L.N_EREF] = np.nan
        st[L.SL_RESYNCS] += 1
    if c.size != N_COUNTERS:
        H.array(st, L.SL_COUNTERS, L.SL_NCOUNTERS, N_COUNTERS)[:] = 0.0
    st[L.SL_ECHECK] = 1
    H.context(st, binding, method, None, view, ptr, sim, ix, ivx, im, kepler=True)
    st[L.SL_CORE] = binding.step_code.core_step.address
    rec = H.record_of_state(p)
    rec.forces = tuple(reboundx_forces(sim) or ())
    # (their parameters are read into the model: a change between runs prepares the step again,
    # host._recheck_forces)
    rec.kepler_terms = terms
    rec.odes = ode_signature(sim)
    rec.host_path = False
