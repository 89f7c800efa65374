"""REBOUND's own forces at HBVM's stages: the right-hand side of a scene that the compiled
N-body kernel (:mod:`systems.nbody`) does not model.

Which scenes take this path
---------------------------
:func:`host_reasons` names what a scene has beyond plain Newtonian point masses: additional
forces (REBOUNDx's, named, or a user's function), ``softening > 0``, semi-active particles
(``testparticle_type = 1`` with particles past ``N_active``), ``gravity = 'none'`` or attached
ODEs (``sim._odes``).  Such a
scene is integrated on REBOUND's accelerations, as IAS15 does: every stage of the step writes
its positions, velocities and time into the particles and ``sim.t``, calls REBOUND's
``reb_simulation_update_acceleration`` (gravity in the scene's mode, softening, the additional
forces) and reads the accelerations back.  A plain Newtonian scene keeps the compiled kernel.

The form of the step
--------------------
The scene is the second-order system q'' = a(t, q, q') in the engine's *separable* form
(:mod:`integrators.loop`), as the compiled N-body kernel's is: the state is y = (q, v) with q
the positions and a clock tau = CLOCK t, v the velocities and the clock's rate CLOCK (the
step's weights M^{-1} are 1: the state holds velocities, the kernel returns accelerations).
The step solves for the s coefficients of the accelerations only (m unknowns a block, the
fixed point contracting like (h omega)^2), its stage positions Q = q0 + h c v0 + h^2 (I_s X_s)
gamma carry the stage times t0 + c_l h in the clock's coordinate, and the kernel writes them
into the particles and ``sim.t``.  A force that reads velocities (``sim.force_is_velocity_
dependent``: REBOUNDx ``gr``, ``gr_full``, tides, radiation drag, migration, a user's function
that sets it) is handed the stage velocities V = v0 + h I_s gamma too
(:func:`integrators.core.stage_velocities`, the step's variant with stage velocities): these
are the Runge-Kutta stages of HBVM(k, s) on y' = (v, a(t, q, v)), so the order 2s holds
(measured in the tests).  Without the flag the particles keep the step's initial velocities
during the stages, as IAS15 keeps them.

When the added forces derive from a potential U(q) (softening, REBOUNDx ``gr_potential``,
``gravitational_harmonics``, ``central_force``) the scene is Hamiltonian with

    H(q, v) = sum_i m_i |v_i|^2 / 2 + V(q) + U(q)

(the kinetic weights of the step: the gravitating masses per coordinate; V the (softened) pair
potential of the pairs REBOUND computes), and HBVM's line-integral argument conserves it; the
energy check guards this H (:func:`rebound_potential` gives V + U, U from REBOUNDx's own
exported potentials).  Velocities rather than momenta m v keep every coordinate of a kind at
one scale (a Mercury's momentum is 1e-7 of its velocity): the iteration's stop rule and the
step's error estimate take maxima over coordinates.  For any other added force there is no H
to keep: the energy check is off, and the adaptive step control (error estimate on the
accelerations, as IAS15's) and the iteration's convergence test carry the run.

The clock is scaled by CLOCK = 2^-200 (an exact scaling) so that it takes no part in the
step's convergence test; its force is 0, so it takes none in the error estimate either; the
glue resets it to ``sim.t`` before each step.

Attached ODEs
-------------
ODEs attached to the simulation (``sim.create_ode``: ``length``, ``y``, ``derivatives(ode, yDot,
y, t)``, ``needs_nbody``; REBOUNDx's spin ODE with its ``pre_timestep`` and ``post_timestep``)
are integrated with the bodies, at the step's stages.  The state is then
y = (x, 0 (nz), tau, v, sigma z (nz), CLOCK): each ODE's state z rides in the momenta, whose
stage values the step with stage velocities hands the kernel (p0 + h I_s gamma: the Runge-Kutta
stages of z' = f(t, x, v, z), so the order stays 2s), with a position-like partner that nothing
reads (set to 0 before each step by the glue, so that it never grows into the iteration's
scale).  At each stage the kernel writes the bodies and ``sim.t``, then each ODE's ``y`` <- the
stage's z and its ``post_timestep`` (REBOUNDx's spin ODE writes the spins into the particles'
"Omega", which its force reads), then calls REBOUND's accelerations, then each ODE's
``derivatives`` (``needs_nbody`` or not: the particles hold the stage either way), and returns
sigma z' as the ODE block's "acceleration".

sigma, one power of two per ODE (exact scalings), brings the ODE's largest component to the
bodies' largest velocity when the step is prepared (1 when either is 0; taken back from a kept or
saved state, :meth:`ReboundScene.adopt_sigma`): the iteration's stop rule, the step's error
estimate (body by body: the ODE's components in groups of three, as a body's coordinates) and the
controller (the largest weighted coefficients over the state) then compare the ODE with the
bodies as a body moving at its own rate.  An ODE has no energy in general: the energy check
(and the run's drift check, integrators.core.DRIFT_BOUND) guards the bodies' H, in which the
ODEs have no weight, and is off when an added force has no potential (:func:`hamiltonian`).  The glue (:mod:`hbvm_md.rebound.glue`) calls each
ODE's ``pre_timestep`` and rereads a changed ``y`` before a step, writes ``y`` (and calls
``post_timestep``) after it, or writes back the state from before a failed step, and hides the
ODEs from REBOUND's own stepping of them (``sim->N_odes`` = 0 between its steps).

The parameters (float64; every address and offset below 2^53 is exact in a double):
``[sim, update_acceleration, particles, N, stride, x, vx, ax, t, G_V, b^2, n_pot, velocities,
n_odes, the clock's column, the word of sim->N_odes, the N_odes the last step hid (0: none),
the offset of the derivatives field in reb_ode, then n_pot entries (function, arity, arg1,
arg2), then g (N), active (N), then n_odes entries of O_WIDTH]``: the
simulation's address, REBOUND's function, the particle array (the step checks that it has not
moved), REBOUND's offsets in doubles, the Newtonian G of V (0 for ``gravity = 'none'``), the
softening squared, REBOUNDx's potential functions with their arguments, whether the kernel is
handed stage velocities (1) or positions only (0), the gravitating masses (0: acts on nobody)
and whether each particle is active.  Addresses are run-time values handed in the parameters,
never compiled into the (disk-cached) code.
"""
from __future__ import annotations

import ctypes
import math

import numpy as np
from numba import carray, types
from numba.extending import intrinsic

from integrators.core import weighted_kinetic
from integrators.jit import jit
from integrators.pointers import float64_pointer
from hbvm_md.rebound.intrinsics import call_void

#: the clock's scale (tau = CLOCK t): a power of two, so tau and t convert exactly
CLOCK = 2.0 ** -200
CLOCK_INV = 2.0 ** 200
(P_SIM, P_UPDATE, P_PTR, P_N, P_STRIDE, P_IX, P_IVX, P_IAX, P_TWORD, P_G, P_SOFT2,
 P_NPOT, P_VEL, P_NODES, P_CLOCK, P_ODES_WORD, P_ODES_HELD, P_ODE_DERIV_AT) = range(18)
P_HEAD = 18
#: one attached ODE's entry in the parameters (after the active flags): the ``reb_ode``'s
#: address, its length, its ``derivatives``, ``pre_timestep`` and ``post_timestep`` functions
#: (0: none), its ``y`` and ``yDot`` arrays, its first column in the state's ODE block, and
#: sigma, the power of two by which the state holds it (module docstring, "Attached ODEs")
(O_ODE, O_LEN, O_DERIV, O_PRE, O_POST, O_Y, O_YDOT, O_COL, O_SIGMA) = range(9)
O_WIDTH = 9
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


@intrinsic
def call_void2(typingctx, fn, a, b):
    """``((void (*)(void*, void*)) fn)((void*) a, (void*) b)``: an ODE's ``pre_timestep`` or
    ``post_timestep`` (``ode``, ``y``)."""
    if not all(isinstance(x, types.Integer) for x in (fn, a, b)):
        return None

    def codegen(context, builder, signature, args):
        from llvmlite import ir
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i8p])
        builder.call(builder.inttoptr(args[0], fnty.as_pointer()),
                     [builder.inttoptr(args[1], i8p), builder.inttoptr(args[2], i8p)])
        return context.get_dummy_value()
    return types.none(fn, a, b), codegen


@intrinsic
def call_derivatives(typingctx, fn, ode, ydot, y, t):
    """``((void (*)(void*, double*, double*, double)) fn)(ode, yDot, y, t)``: an attached ODE's
    ``derivatives``."""
    if not (all(isinstance(x, types.Integer) for x in (fn, ode, ydot, y))
            and isinstance(t, types.Float)):
        return None

    def codegen(context, builder, signature, args):
        from llvmlite import ir
        i8p = ir.IntType(8).as_pointer()
        f64 = ir.DoubleType()
        fnty = ir.FunctionType(ir.VoidType(), [i8p, f64.as_pointer(), f64.as_pointer(), f64])
        builder.call(builder.inttoptr(args[0], fnty.as_pointer()),
                     [builder.inttoptr(args[1], i8p),
                      builder.inttoptr(args[2], f64.as_pointer()),
                      builder.inttoptr(args[3], f64.as_pointer()), args[4]])
        return context.get_dummy_value()
    return types.none(fn, ode, ydot, y, t), codegen


@jit
def odes_at(params):
    """Where the attached ODEs' entries start in the parameters (:data:`O_WIDTH` each)."""
    return P_HEAD + 4 * int(params[P_NPOT]) + 2 * int(params[P_N])


@jit
def odes_set(params, z, cz, low):
    """Each attached ODE's ``y`` <- its part of the state's ODE block z (sigma z: the ODE's
    columns from its O_COL; less cz when ``low``, the state's low parts), then its
    ``post_timestep`` when it has one (REBOUNDx's spin ODE writes the spins into the particles'
    "Omega", which its force reads)."""
    o0 = odes_at(params)
    for e in range(int(params[P_NODES])):
        at = o0 + O_WIDTH * e
        n, col, sig = int(params[at + O_LEN]), int(params[at + O_COL]), params[at + O_SIGMA]
        y = carray(float64_pointer(int(params[at + O_Y])), n)
        for i in range(n):
            zi = z[col + i] - cz[col + i] if low else z[col + i]
            y[i] = zi / sig             # (exact: sigma is a power of two)
        if params[at + O_POST] != 0.0:
            call_void2(int(params[at + O_POST]), int(params[at + O_ODE]), int(params[at + O_Y]))


@jit
def _write_positions(x, params, view, simd):
    """The particles' x and ``sim.t`` <- the stage x (>= m,) (positions, then the clock)."""
    N = int(params[P_N])
    ix = int(params[P_IX])
    for i in range(N):
        for c in range(3):
            view[i, ix + c] = x[3 * i + c]
    simd[int(params[P_TWORD])] = x[int(params[P_CLOCK])] * CLOCK_INV


@jit
def rebound_accelerations(X, params, out):
    """out (n, m) <- REBOUND's accelerations at each stage row of X (module docstring): X
    (n, m) the positions and the clock, or (n, 2m) the positions and the clock, then the
    velocities and the clock's rate (a scene whose forces read velocities: the parameters'
    ``velocities`` flag, and the step's variant with stage velocities).  The clock's
    acceleration is 0.  Leaves the particles and ``sim.t`` at the last row (the glue restores
    them)."""
    N = int(params[P_N])
    m = out.shape[1]
    vel = params[P_VEL] != 0.0
    if vel and X.shape[1] != 2 * m:
        raise ValueError("internal error: a velocity-dependent REBOUND scene bound to a step "
                         "without stage velocities")
    sim, fn = int(params[P_SIM]), int(params[P_UPDATE])
    view = carray(float64_pointer(int(params[P_PTR])), (N, int(params[P_STRIDE])))
    simd = carray(float64_pointer(sim), int(params[P_TWORD]) + 1)
    iax, ivx = int(params[P_IAX]), int(params[P_IVX])
    for r in range(X.shape[0]):
        _write_positions(X[r], params, view, simd)
        if vel:
            for i in range(N):
                for c in range(3):
                    view[i, ivx + c] = X[r, m + 3 * i + c]
        nodes = int(params[P_NODES])
        if nodes > 0:           # the stage's ODE states, where the forces may read them
            odes_set(params, X[r, m + 3 * N:], X[r, m + 3 * N:], False)
        call_void(fn, sim)
        for i in range(N):
            for c in range(3):
                out[r, 3 * i + c] = view[i, iax + c]
        for j in range(3 * N, m):       # the clock's acceleration is 0
            out[r, j] = 0.0
        if nodes > 0:
            # each ODE's derivatives with the bodies, the time and every ODE at the stage;
            # yDot is filled with nan first, so that a Python derivatives function that raises
            # (ctypes prints it and returns) fails the step instead of leaving stale numbers
            t = simd[int(params[P_TWORD])]
            o0 = odes_at(params)
            for e in range(nodes):
                at = o0 + O_WIDTH * e
                n, col, sig = int(params[at + O_LEN]), int(params[at + O_COL]), params[at + O_SIGMA]
                yd = carray(float64_pointer(int(params[at + O_YDOT])), n)
                for i in range(n):
                    yd[i] = np.nan
                call_derivatives(int(params[at + O_DERIV]), int(params[at + O_ODE]),
                                 int(params[at + O_YDOT]), int(params[at + O_Y]), t)
                for i in range(n):
                    out[r, 3 * N + col + i] = yd[i] * sig


@jit
def rebound_potential(q, params):
    """V(q) + U(q) of the module docstring: the (softened) pair potential of the pairs REBOUND
    computes (an active particle with any gravitating one) and REBOUNDx's potentials,
    evaluated with the particles at the positions q (m,) (left there: the glue restores
    them).  Only meaningful (and only used by the energy check) for a scene whose added
    forces have one."""
    N = int(params[P_N])
    npot = int(params[P_NPOT])
    g0 = P_HEAD + 4 * npot
    a0 = g0 + N
    G, b2 = params[P_G], params[P_SOFT2]
    v = 0.0
    for i in range(N):
        gi = params[g0 + i]
        if gi == 0.0:
            continue
        for j in range(i + 1, N):
            gj = params[g0 + j]
            if gj == 0.0 or (params[a0 + i] == 0.0 and params[a0 + j] == 0.0):
                continue
            dx = q[3 * j] - q[3 * i]
            dy = q[3 * j + 1] - q[3 * i + 1]
            dz = q[3 * j + 2] - q[3 * i + 2]
            v -= gi * gj / np.sqrt(dx * dx + dy * dy + dz * dz + b2)
    u = 0.0
    if npot > 0:
        view = carray(float64_pointer(int(params[P_PTR])), (N, int(params[P_STRIDE])))
        simd = carray(float64_pointer(int(params[P_SIM])), int(params[P_TWORD]) + 1)
        _write_positions(q, params, view, simd)
        for e in range(npot):
            at = P_HEAD + 4 * e
            fn = int(params[at])
            if params[at + 1] == 1.0:
                u += call_double1(fn, int(params[at + 2]))
            else:
                u += call_double2(fn, int(params[at + 2]), int(params[at + 3]))
    return G * v + u


def masses_at(params) -> int:
    """Where the gravitating masses g start in a :class:`ReboundScene`'s parameters (for
    :func:`scene_set_masses`: computed here, in Python, so that a compiled caller cached by
    numba beside another file never holds an old layout; numba's cache of a function follows
    its own file only)."""
    return P_HEAD + 4 * int(params[P_NPOT])


@jit
def scene_set_masses(params, masses, g0):
    """A :class:`ReboundScene`'s parameters <- those of the same scene with the masses (N,),
    in place: the gravitating masses g, from g0 (:func:`masses_at`; the potential's; REBOUND
    reads its own masses for the accelerations; the kinetic weights are the step's, updated by
    the caller).  The caller keeps the gravitating bodies (no mass becomes 0 or nonzero)."""
    N = int(params[P_N])
    for i in range(N):
        if params[g0 + i] != 0.0:
            params[g0 + i] = masses[i]


# -- what a scene has, read from the simulation ---------------------------------------------------
def reboundx_forces(sim):
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
    return [name for name, _ in (reboundx_forces(sim) or []) if name in NOT_OF_THE_STATE]


def added_forces(sim) -> list[str]:
    """Names of the forces added to ``sim`` beyond its gravity: REBOUNDx's by name, else
    "a user's additional_forces function"; [] when there are none."""
    if not sim._additional_forces:
        return []
    rebx = reboundx_forces(sim)
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
    if sim._N_odes > 0:
        out.append("attached ODEs")
    return out


def ode_list(sim) -> list[int]:
    """The addresses of the ``reb_ode`` structs attached to ``sim`` (``sim._odes``)."""
    return [ctypes.cast(sim._odes[i], ctypes.c_void_p).value for i in range(int(sim._N_odes))]


def ode_signature(sim) -> tuple:
    """What the step's parameters hold of the attached ODEs (address, length, functions and
    arrays of each): a run whose ODEs differ from the prepared ones prepares the step again."""
    import rebound
    O = rebound.ode.ODE
    out = []
    for a in ode_list(sim):
        words = tuple(ctypes.c_void_p.from_address(a + getattr(O, f).offset).value or 0
                      for f in ("y", "_derivatives", "_pre_timestep", "_post_timestep", "_yDot"))
        out.append((a, ctypes.c_uint.from_address(a + O.length.offset).value) + words)
    return tuple(out)


def sync_odes_in(sim) -> None:
    """Each attached ODE's ``pre_timestep`` (REBOUNDx's spin ODE reads the spins from the
    particles' "Omega" into its ``y``: the state the step starts from), as REBOUND's BS
    integrator calls it before a step."""
    for a, n, y, deriv, pre, post, ydot in ode_signature(sim):
        if pre:
            ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p)(pre)(a, y)


def ode_entries(sim, vscale: float) -> tuple[list[float], int]:
    """(the parameters' ODE entries (:data:`O_WIDTH` each), the ODE block's width).  Each ODE
    is held in the state as sigma z, sigma the power of two nearest ``vscale`` / max |z| (1
    when either is 0): the module docstring, "Attached ODEs".  ``sim``'s ODEs are synced in
    first (:func:`sync_odes_in`)."""
    sync_odes_in(sim)
    out, col = [], 0
    for a, n, y, deriv, pre, post, ydot in ode_signature(sim):
        if not deriv:           # (checks.check_simulation names it first)
            raise ValueError(f"an ODE attached to the simulation (length {n}) has no "
                             "derivatives function; set ode.derivatives before integrating")
        if not y or not ydot:
            raise ValueError(f"an ODE attached to the simulation (length {n}) has no y array")
        z = np.ctypeslib.as_array((ctypes.c_double * n).from_address(y)) if n else np.zeros(0)
        if not np.all(np.isfinite(z)):
            raise ValueError(f"an ODE attached to the simulation (length {n}) holds non-finite "
                             f"values in ode.y: {z.tolist()}; set its initial state")
        zmax = float(np.max(np.abs(z))) if n else 0.0
        sigma = 1.0
        if zmax > 0.0 and vscale > 0.0:
            sigma = 2.0 ** round(math.log2(vscale / zmax))
            sigma = min(max(sigma, 2.0 ** -500), 2.0 ** 500)
        for v in (a, deriv, pre, post, y, ydot):
            if not 0 <= v < 2 ** 53:
                raise RuntimeError(f"an address (0x{int(v):x}) does not fit a double exactly")
        out += [float(a), float(n), float(deriv), float(pre), float(post), float(y), float(ydot),
                float(col), sigma]
        col += n
    return out, col


def hamiltonian(sim) -> bool:
    """Does the scene conserve the H of the module docstring: no added force, or only REBOUNDx
    forces whose potential REBOUNDx exports (:data:`POTENTIALS`)?"""
    # (attached ODEs ride in the momenta with no kinetic weight and no potential: the H guarded
    # is the bodies', which an ODE changes only through an added force, judged below)
    if not sim._additional_forces:
        return True
    rebx = reboundx_forces(sim)
    return rebx is not None and all(name in POTENTIALS for name, _ in rebx)


def _potential_entries(sim) -> list[tuple[float, float, float, float]]:
    """(function, arity, arg1, arg2) of REBOUNDx's potentials of the scene's forces (a
    one-argument potential sums over every force of its kind: listed once)."""
    rebx = reboundx_forces(sim) or []
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


def velocity_dependent(sim) -> bool:
    """Does a force of ``sim`` read velocities (REBOUND's ``force_is_velocity_dependent``, which
    REBOUNDx sets for the forces that do and a user sets for a Python one)?"""
    return bool(sim.force_is_velocity_dependent)


class ReboundScene:
    """A REBOUND simulation's particles as a separable system on REBOUND's accelerations
    (module docstring): ``dim`` = 3N + 1 (the positions and the clock), ``masses`` (ones: the
    state holds velocities), ``kinetic_weights`` (the gravitating masses per coordinate),
    :meth:`separable_kernels`, and ``velocities`` (the kernel reads the stage velocities).

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
        v = np.zeros(3 * N)
        sim.serialize_particle_data(vxvyvz=v)
        vmax = float(np.max(np.abs(v))) if np.all(np.isfinite(v)) else 0.0
        odes, nz = ode_entries(sim, vmax)
        self.N, self.nz, self.dim = N, nz, 3 * N + nz + 1
        self.gravitating = (m != 0) & (act | semi)       # (a negative mass gravitates too)
        self.masses = np.ones(self.dim)
        self.kinetic_weights = np.concatenate(
            [np.repeat(np.where(self.gravitating, m, 0.0), 3), np.zeros(nz + 1)])
        self.hamiltonian = hamiltonian(sim)
        # (an ODE's stages are the momenta's: the step with stage velocities hands them over)
        self.velocities = velocity_dependent(sim) or len(odes) > 0
        self.sigma = np.repeat(odes[O_SIGMA::O_WIDTH], odes[O_LEN::O_WIDTH]).astype(float)
        pots = _potential_entries(sim) if self.hamiltonian else []
        fn = ctypes.cast(rebound.clibrebound.reb_simulation_update_acceleration,
                         ctypes.c_void_p).value
        addr = ctypes.addressof(sim)
        head = [addr, fn, ptr, N, stride, ix, ivx, iax, tword,
                0.0 if sim.gravity == "none" else sim.G, sim.softening ** 2, len(pots),
                float(self.velocities), len(odes) // O_WIDTH, self.dim - 1,
                type(sim)._N_odes.offset // 8, 0.0, rebound.ode.ODE._derivatives.offset]
        for a in (addr, fn, ptr) + tuple(x for e in pots for x in (e[0], e[2], e[3])):
            if not 0 <= a < 2 ** 53:
                raise RuntimeError(f"an address (0x{int(a):x}) does not fit a double exactly")
        self.params = np.concatenate([np.array(head, dtype=float),
                                      np.array(pots, dtype=float).reshape(-1),
                                      np.where(self.gravitating, m, 0.0), act.astype(float),
                                      np.array(odes, dtype=float)])

    def separable_kernels(self):
        return rebound_accelerations, rebound_potential, self.params

    def forces(self, q: np.ndarray) -> np.ndarray:
        """The accelerations (m,) at the positions and clock q (m,) (the step calls the
        compiled kernel; this is for a reader)."""
        out = np.empty((1, self.dim))
        X = np.asarray(q, float).reshape(1, -1)
        if self.velocities:
            raise ValueError("this scene's forces read velocities: call the kernel with "
                             "stage rows (q, v)")
        rebound_accelerations(X, self.params, out)
        return out[0]

    def potential(self, q: np.ndarray) -> float:
        """V(q) + U(q) (module docstring)."""
        return float(rebound_potential(np.asarray(q, float), self.params))

    def ode_state(self) -> np.ndarray:
        """The attached ODEs' state as the step holds it, sigma z (nz,), read from their ``y``
        (synced in when the scene was built)."""
        z = np.zeros(self.nz)
        o0 = int(odes_at(self.params))
        for e in range(int(self.params[P_NODES])):
            at = o0 + O_WIDTH * e
            n, col = int(self.params[at + O_LEN]), int(self.params[at + O_COL])
            if n:
                z[col:col + n] = np.ctypeslib.as_array(
                    (ctypes.c_double * n).from_address(int(self.params[at + O_Y])))
        return z * self.sigma

    def adopt_sigma(self, held: np.ndarray) -> bool:
        """Take each ODE's sigma from ``held``, the ODE block of a state of this scene saved or
        kept from an earlier preparation (sigma z, as :meth:`ode_state`), when its y gives one
        power of two held / z for every nonzero component: a loaded, copied or resynced run
        then goes on as the uninterrupted one, bit for bit (sigma sets the scales of the
        iteration's stop rule and of the step control).  Returns whether every ODE's sigma
        was taken so (an ODE whose y is all zeros keeps its own)."""
        z = self.ode_state() / self.sigma
        o0 = int(odes_at(self.params))
        every = True
        for e in range(int(self.params[P_NODES])):
            at = o0 + O_WIDTH * e
            n, col = int(self.params[at + O_LEN]), int(self.params[at + O_COL])
            zz, hh = z[col:col + n], held[col:col + n]
            nz = zz != 0.0
            if not np.any(nz):
                continue
            with np.errstate(all="ignore"):
                r = hh[nz] / zz[nz]
            mant, _ = np.frexp(r)
            if np.all(r == r[0]) and r[0] > 0 and mant[0] == 0.5 and np.all(hh[~nz] == 0.0):
                self.params[at + O_SIGMA] = r[0]
                self.sigma[col:col + n] = r[0]
            else:
                every = False
        return every

    def state(self, x: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        """y = (x, 0, CLOCK t, v, sigma z, CLOCK) (2 dim,) from positions and velocities (N, 3)
        and the attached ODEs' y (:meth:`ode_state`; 0: their positions, which nothing reads)."""
        q = np.concatenate([np.asarray(x, float).reshape(-1), np.zeros(self.nz), [t * CLOCK]])
        p = np.concatenate([np.asarray(v, float).reshape(-1), self.ode_state(), [CLOCK]])
        return np.concatenate([q, p])


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
        # (the kinetic energy as the step's energy check takes it: loop.energy_parts)
        e = (weighted_kinetic(y[sc.dim:], sc.kinetic_weights)
             + float(rebound_potential(y[:sc.dim], sc.params)))
    finally:        # (REBOUNDx's potentials read the particles: the positions went through q)
        sim.set_serialized_particle_data(xyzvxvyvz=xv.reshape(-1))
        sim.t = t
    return e if math.isfinite(e) else math.nan
