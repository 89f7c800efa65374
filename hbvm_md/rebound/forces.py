"""REBOUND's own forces at HBVM's stages: the right-hand side of a scene that the compiled
N-body kernel (:mod:`systems.nbody`) does not model.

Which scenes take this path
---------------------------
:func:`host_reasons` names what a scene has beyond plain Newtonian point masses: additional
forces (REBOUNDx's, named, or a user's function), ``softening > 0``, semi-active particles
(``testparticle_type = 1`` with particles past ``N_active``) or ``gravity = 'none'``.  Such a
scene is integrated on REBOUND's accelerations, as IAS15 does: every stage of the step writes
its positions, velocities and time into the particles and ``sim.t``, calls REBOUND's
``reb_simulation_update_acceleration`` (gravity in the scene's mode, softening, the additional
forces) and reads the accelerations back.  A plain Newtonian scene keeps the compiled kernel.

The form of the step
--------------------
A force that reads velocities (REBOUNDx ``gr``, ``gr_full``, tides, radiation drag, migration)
or the time needs the stage velocities and times, so the scene is an ODE y' = f(t, y) in the
engine's *full* form (:mod:`integrators.loop`): the kernel returns G with J G = f, and the
step applies J.  The state is y = (q, v): q the positions and a clock tau = CLOCK t, v the
velocities and the clock's partner pi (always 0).  The kernel's G = (-a, v, 0, CLOCK): dq/dt
= v, dv/dt = a, dtau/dt = CLOCK.  When the added forces derive from a potential U(q)
(softening, REBOUNDx ``gr_potential``, ``gravitational_harmonics``, ``central_force``) then
J G = B grad H with the constant skew-symmetric B = [[0, M^-1], [-M^-1, 0]] (M the masses of
the bodies that gravitate) and

    H(q, v) = sum_i m_i |v_i|^2 / 2 + V(q) + U(q) + CLOCK pi,

V the (softened) pair potential of the pairs REBOUND computes: a Poisson system with a constant
structure matrix, for which HBVM's line-integral argument (sum_j a_j^T B a_j = 0 for skew B)
conserves H as it does J grad H.  The energy check guards this H (:func:`rebound_energy`, U
from REBOUNDx's own exported potentials).  Velocities rather than momenta m v keep every
coordinate of a kind at one scale (a Mercury's momentum is 1e-7 of its velocity): the
iteration's stop rule and the step's error estimate take maxima over coordinates.  For any other added force there is no H to keep:
the energy check is off, and the adaptive step control (error estimate on the accelerations,
as IAS15's) and the iteration's convergence test carry the run.  HBVM(k, s) is a k-stage
Runge-Kutta method of order 2s on any ODE, so the order holds here too (measured in the
tests).

The clock is scaled by CLOCK = 2^-200 (an exact scaling) so that it takes no part in the
step's error estimate and convergence test; the glue resets it to ``sim.t`` before each step.

The parameters (float64; every address and offset below 2^53 is exact in a double):
``[sim, update_acceleration, particles, N, stride, x, vx, ax, t, G_V, b^2, n_pot, then n_pot
entries (function, arity, arg1, arg2), then w (N), 1/w (N), g (N), active (N)]`` (w = 1: the
state holds velocities): the
simulation's address, REBOUND's function, the particle array (the step checks that it has not
moved), REBOUND's offsets in doubles, the Newtonian G of V (0 for ``gravity = 'none'``), the
softening squared, REBOUNDx's potential functions with their arguments, the state's weights,
the gravitating masses (0: acts on nobody) and whether each particle is active.  Addresses are
run-time values handed in the parameters, never compiled into the (disk-cached) code.
"""
from __future__ import annotations

import ctypes
import math

import numpy as np
from numba import carray, types
from numba.extending import intrinsic

from integrators.jit import jit
from integrators.pointers import float64_pointer
from hbvm_md.rebound.cabi import call_void

#: the clock's scale (tau = CLOCK t): a power of two, so tau and t convert exactly
CLOCK = 2.0 ** -200
CLOCK_INV = 2.0 ** 200
(P_SIM, P_UPDATE, P_PTR, P_N, P_STRIDE, P_IX, P_IVX, P_IAX, P_TWORD, P_G, P_SOFT2,
 P_NPOT) = range(12)
P_HEAD = 12
#: REBOUNDx forces whose accelerations are -grad of a potential it exports: name ->
#: (C function, its arity: 1 takes the extras, 2 the extras and the force)
POTENTIALS = {"gr_potential": ("rebx_gr_potential_potential", 2),
              "gravitational_harmonics": ("rebx_gravitational_harmonics_potential", 1),
              "central_force": ("rebx_central_force_potential", 1)}


@intrinsic
def call_double1(typingctx, fn, a):
    """``((double (*)(void*)) fn)((void*) a)``."""
    if not (isinstance(fn, types.Integer) and isinstance(a, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        from llvmlite import ir
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.DoubleType(), [i8p])
        return builder.call(builder.inttoptr(args[0], fnty.as_pointer()),
                            [builder.inttoptr(args[1], i8p)])
    return types.float64(fn, a), codegen


@intrinsic
def call_double2(typingctx, fn, a, b):
    """``((double (*)(void*, void*)) fn)((void*) a, (void*) b)``."""
    if not all(isinstance(x, types.Integer) for x in (fn, a, b)):
        return None

    def codegen(context, builder, signature, args):
        from llvmlite import ir
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.DoubleType(), [i8p, i8p])
        return builder.call(builder.inttoptr(args[0], fnty.as_pointer()),
                            [builder.inttoptr(args[1], i8p), builder.inttoptr(args[2], i8p)])
    return types.float64(fn, a, b), codegen


@jit
def _write_state(y, params, view, simd):
    """The particles' x and v and ``sim.t`` <- the state y (2m,) (module docstring's layout)."""
    N = int(params[P_N])
    m = y.shape[0] // 2
    ix, ivx = int(params[P_IX]), int(params[P_IVX])
    winv = P_HEAD + 4 * int(params[P_NPOT]) + N
    for i in range(N):
        for c in range(3):
            view[i, ix + c] = y[3 * i + c]
            view[i, ivx + c] = y[m + 3 * i + c] * params[winv + i]
    simd[int(params[P_TWORD])] = y[3 * N] * CLOCK_INV


@jit
def rebound_gradient(Y, params, out):
    """G (n, 2m) with J G = f(Y[r]) at each state row of Y (n, 2m): REBOUND's accelerations at
    the row's positions, velocities and time (module docstring).  Leaves the particles and
    ``sim.t`` at the last row (the glue restores them)."""
    N = int(params[P_N])
    m = Y.shape[1] // 2
    sim, fn = int(params[P_SIM]), int(params[P_UPDATE])
    view = carray(float64_pointer(int(params[P_PTR])), (N, int(params[P_STRIDE])))
    simd = carray(float64_pointer(sim), int(params[P_TWORD]) + 1)
    iax, ivx = int(params[P_IAX]), int(params[P_IVX])
    w0 = P_HEAD + 4 * int(params[P_NPOT])
    for r in range(Y.shape[0]):
        _write_state(Y[r], params, view, simd)
        call_void(fn, sim)
        for i in range(N):
            w = params[w0 + i]
            for c in range(3):
                out[r, 3 * i + c] = -w * view[i, iax + c]
                out[r, m + 3 * i + c] = view[i, ivx + c]
        out[r, 3 * N] = 0.0
        out[r, m + 3 * N] = CLOCK


@jit
def rebound_energy(y, params):
    """H(y) of the module docstring: the kinetic energy of the gravitating particles, the
    (softened) pair potential of the pairs REBOUND computes (an active particle with any
    gravitating one) and REBOUNDx's potentials, evaluated with the particles at y.  Only
    meaningful (and only used by the energy check) for a scene whose added forces have one."""
    N = int(params[P_N])
    m = y.shape[0] // 2
    npot = int(params[P_NPOT])
    w0 = P_HEAD + 4 * npot
    winv, g0, a0 = w0 + N, w0 + 2 * N, w0 + 3 * N
    G, b2 = params[P_G], params[P_SOFT2]
    kin = 0.0
    for i in range(N):
        gi = params[g0 + i]
        if gi > 0.0:
            for c in range(3):
                kin += gi * (y[m + 3 * i + c] * params[winv + i]) ** 2
    v = 0.0
    for i in range(N):
        gi = params[g0 + i]
        if gi == 0.0:
            continue
        for j in range(i + 1, N):
            gj = params[g0 + j]
            if gj == 0.0 or (params[a0 + i] == 0.0 and params[a0 + j] == 0.0):
                continue
            dx = y[3 * j] - y[3 * i]
            dy = y[3 * j + 1] - y[3 * i + 1]
            dz = y[3 * j + 2] - y[3 * i + 2]
            v -= gi * gj / np.sqrt(dx * dx + dy * dy + dz * dz + b2)
    u = 0.0
    if npot > 0:
        view = carray(float64_pointer(int(params[P_PTR])), (N, int(params[P_STRIDE])))
        simd = carray(float64_pointer(int(params[P_SIM])), int(params[P_TWORD]) + 1)
        _write_state(y, params, view, simd)
        for e in range(npot):
            at = P_HEAD + 4 * e
            fn = int(params[at])
            if params[at + 1] == 1.0:
                u += call_double1(fn, int(params[at + 2]))
            else:
                u += call_double2(fn, int(params[at + 2]), int(params[at + 3]))
    return 0.5 * kin + G * v + u


@jit
def scene_set_masses(params, masses):
    """A :class:`ReboundScene`'s parameters <- those of the same scene with the masses (N,),
    in place: the gravitating masses g (the energy's; REBOUND reads its own masses for the
    accelerations).  The caller keeps the gravitating bodies (no mass becomes 0 or nonzero)."""
    N = int(params[P_N])
    g0 = P_HEAD + 4 * int(params[P_NPOT]) + 2 * N
    for i in range(N):
        if params[g0 + i] > 0.0:
            params[g0 + i] = masses[i]


# -- what a scene has, read from the simulation ---------------------------------------------------
def _reboundx_forces(sim):
    """[(name, address of the rebx_force)] of the REBOUNDx forces attached to ``sim`` when its
    ``additional_forces`` is REBOUNDx's, else None (a user's function, or none)."""
    if not sim._additional_forces or not sim.extras:
        return None
    try:
        import reboundx
    except ImportError:
        return None
    lib = reboundx.clibreboundx
    fp = ctypes.cast(sim._additional_forces, ctypes.c_void_p).value
    if fp != ctypes.cast(lib.rebx_additional_forces, ctypes.c_void_p).value:
        return None
    extras = reboundx.extras.Extras.from_address(sim.extras)
    out, node = [], extras._additional_forces
    while node:
        f = reboundx.extras.Force.from_address(node.contents.object)
        out.append((f.name.decode() if f.name else "?", node.contents.object))
        node = node.contents.next
    return out


#: REBOUNDx forces that are not functions of the state (name -> why): an implicit step has no
#: stage equations to solve with them
NOT_OF_THE_STATE = {"stochastic_forces": "draws new random kicks at every call"}


def random_forces(sim) -> list[str]:
    """Names of the REBOUNDx forces attached to ``sim`` that are not functions of the state
    (:data:`NOT_OF_THE_STATE`)."""
    return [name for name, _ in (_reboundx_forces(sim) or []) if name in NOT_OF_THE_STATE]


def added_forces(sim) -> list[str]:
    """Names of the forces added to ``sim`` beyond its gravity: REBOUNDx's by name, else
    "a user's additional_forces function"; [] when there are none."""
    if not sim._additional_forces:
        return []
    rebx = _reboundx_forces(sim)
    if rebx is None:
        return ["a user's additional_forces function"]
    return [f"REBOUNDx '{name}'" for name, _ in rebx]


def ode_owners(sim) -> list[str | None]:
    """What each ODE attached to ``sim`` (``sim._odes``) is: "REBOUNDx 'NAME''s ODE (...)" for the
    one a REBOUNDx force carries (``Extras.initialize_spin_ode``: the spins that ``tides_spin``
    evolves, found as the force's ``ode`` parameter; ``spin_ode`` in older REBOUNDx), else "a user's ODE"."""
    n = int(sim._N_odes)
    odes = [ctypes.cast(sim._odes[i], ctypes.c_void_p).value for i in range(n)]
    owner = {}
    if n and sim.extras:
        try:
            import reboundx
        except ImportError:
            reboundx = None
        if reboundx is not None:
            E = reboundx.extras
            node = E.Extras.from_address(sim.extras)._allocated_forces
            while node:
                force = E.Force.from_address(node.contents.object)
                ap = force.ap
                while ap:
                    par = E.Param.from_address(ap.contents.object)
                    if par.name in (b"ode", b"spin_ode") and par.value in odes:
                        owner[par.value] = force.name.decode() if force.name else "?"
                    ap = ap.contents.next
                node = node.contents.next
    return [f"REBOUNDx '{owner[o]}''s ODE (its bodies' spins)" if o in owner else None
            for o in odes]


def semi_active(sim) -> bool:
    """Does ``sim`` have semi-active particles (``testparticle_type = 1`` with particles past
    ``N_active``)?"""
    na = sim.N_active
    return sim.testparticle_type == 1 and 0 <= na < sim.N


def host_reasons(sim) -> list[str]:
    """Why ``sim`` needs REBOUND's own accelerations (empty: the compiled N-body kernel models
    it): additional forces (named), softening, semi-active particles, no gravity."""
    out = list(added_forces(sim))
    if sim.softening != 0.0:
        out.append(f"softening={sim.softening!r}")
    if semi_active(sim):
        out.append("testparticle_type=1")
    if sim.gravity == "none":
        out.append("gravity='none'")
    return out


def hamiltonian(sim) -> bool:
    """Does the scene conserve :func:`rebound_energy`'s H: no added force, or only REBOUNDx
    forces whose potential REBOUNDx exports (:data:`POTENTIALS`)?"""
    if not sim._additional_forces:
        return True
    rebx = _reboundx_forces(sim)
    return rebx is not None and all(name in POTENTIALS for name, _ in rebx)


def _potential_entries(sim) -> list[tuple[float, float, float, float]]:
    """(function, arity, arg1, arg2) of REBOUNDx's potentials of the scene's forces (a
    one-argument potential sums over every force of its kind: listed once)."""
    rebx = _reboundx_forces(sim) or []
    if not rebx:
        return []
    import reboundx
    lib = reboundx.clibreboundx
    out, seen = [], set()
    for name, addr in rebx:
        fname, arity = POTENTIALS[name]
        if arity == 1 and name in seen:
            continue
        seen.add(name)
        fn = ctypes.cast(getattr(lib, fname), ctypes.c_void_p).value
        out.append((float(fn), float(arity), float(sim.extras), float(addr)))
    return out


class ReboundScene:
    """A REBOUND simulation's particles as an ODE on REBOUND's accelerations, for the engine's
    full form (module docstring): ``dim`` = 3N + 1 (the positions and the clock),
    :meth:`full_kernels`, and the step's error weights.

    Parameters
    ----------
    sim : rebound.Simulation
    offsets : (stride, x, vx, ax, t) in doubles: the particle's size and fields, the
        simulation's ``t``
    ptr : int
        The particle array's address (the step checks it has not moved).
    """

    def __init__(self, sim, offsets, ptr: int):
        import rebound
        N = sim.N
        stride, ix, ivx, iax, tword = offsets
        m = np.zeros(N)
        sim.serialize_particle_data(m=m)
        na = sim.N_active
        act = np.arange(N) < (N if na < 0 or na >= N else na)
        semi = sim.testparticle_type == 1
        self.N, self.dim = N, 3 * N + 1
        self.gravitating = (m > 0) & (act | semi)
        self.w = np.ones(N)           # the state's second half: the velocities (docstring)
        self.hamiltonian = hamiltonian(sim)
        pots = _potential_entries(sim) if self.hamiltonian else []
        fn = ctypes.cast(rebound.clibrebound.reb_simulation_update_acceleration,
                         ctypes.c_void_p).value
        addr = ctypes.addressof(sim)
        head = [addr, fn, ptr, N, stride, ix, ivx, iax, tword,
                0.0 if sim.gravity == "none" else sim.G, sim.softening ** 2, len(pots)]
        for a in (addr, fn, ptr) + tuple(x for e in pots for x in (e[0], e[2], e[3])):
            if not 0 <= a < 2 ** 53:
                raise RuntimeError(f"an address (0x{int(a):x}) does not fit a double exactly")
        self.params = np.concatenate([np.array(head, dtype=float),
                                      np.array(pots, dtype=float).reshape(-1),
                                      self.w, 1.0 / self.w, np.where(self.gravitating, m, 0.0),
                                      act.astype(float)])

    def full_kernels(self):
        return rebound_gradient, rebound_energy, self.params

    def state(self, x: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        """y = (x, CLOCK t, w v, 0) (2 dim,) from positions and velocities (N, 3) (w = 1)."""
        q = np.append(np.asarray(x, float).reshape(-1), t * CLOCK)
        p = np.append((np.asarray(v, float) * self.w[:, None]).reshape(-1), 0.0)
        return np.concatenate([q, p])

    def error_weights(self) -> np.ndarray:
        """(2 dim,): 1/w on the velocities, 0 on the positions and the clock, so that the
        step's error estimate (``integrators.core.step_error``) is taken on the accelerations,
        as the separable step's and IAS15's are."""
        wts = np.zeros(2 * self.dim)
        wts[self.dim:self.dim + 3 * self.N] = np.repeat(1.0 / self.w, 3)
        return wts


def scene_energy(sim) -> float:
    """H of the module docstring for ``sim`` as it stands (REBOUND's energy with the
    softened pair potential of the pairs REBOUND computes and REBOUNDx's potentials; no
    ``energy_offset``): the quantity HBVM keeps on a Hamiltonian host-force scene."""
    import rebound
    lay = rebound.Particle
    stride = ctypes.sizeof(lay) // 8
    ptr = ctypes.cast(sim._particles, ctypes.c_void_p).value
    sc = ReboundScene(sim, (stride, lay.x.offset // 8, lay.vx.offset // 8, lay.ax.offset // 8,
                            rebound.Simulation.t.offset // 8), ptr)
    xv = np.zeros(6 * sim.N)
    sim.serialize_particle_data(xyzvxvyvz=xv)
    xv = xv.reshape(-1, 6)
    t = sim.t
    y = sc.state(xv[:, :3], xv[:, 3:], t)
    try:
        e = float(rebound_energy(y, sc.params))
    finally:        # (REBOUNDx's potentials read the particles: v went through w v / w)
        sim.set_serialized_particle_data(xyzvxvyvz=xv.reshape(-1))
        sim.t = t
    return e if math.isfinite(e) else math.nan
