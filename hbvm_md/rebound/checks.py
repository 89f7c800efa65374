"""What HBVM in REBOUND refuses, with the reason and the fix, and the scene's time scale."""
from __future__ import annotations

import math
import numbers

import numpy as np

from systems.nbody import NBody, shortest_r3_over_m


def check_simulation(sim) -> None:
    """Raise ValueError if ``sim`` uses something HBVM cannot honour, with the reason and the
    fix.  Collisions are REBOUND's: it finds and resolves them after each step.

    Additional forces (REBOUNDx's or a user's), softening, semi-active particles
    (``testparticle_type = 1``), ``gravity = 'none'`` and attached ODEs (``sim.create_ode``,
    REBOUNDx's spins) are honoured: such a scene runs on REBOUND's own accelerations at the
    stages, the ODEs integrated with the bodies (:mod:`hbvm_md.rebound.forces`).  Negative
    masses are honoured too: a negative mass is a source of either kernel
    (:mod:`systems.nbody`), as in IAS15."""
    from hbvm_md.rebound.forces import NOT_OF_THE_STATE, host_reasons, random_forces
    problems = []
    host = host_reasons(sim)
    for j in range(int(sim.N_var_config) if sim.N_var > 0 else 0):
        vc = sim.var_config[j]
        if vc.order == 2 and not (vc.index_1st_order_a < vc.index
                                  and vc.index_1st_order_b < vc.index):
            problems.append("a second-order variation added before its first-order variations; "
                            "add the first-order ones first (sim.add_variation(order=2, "
                            "first_order=..., first_order_2=...) after them)")
            break
        if vc.testparticle >= sim.N:
            problems.append(f"a variation of particle {vc.testparticle} "
                            f"(add_variation(testparticle={vc.testparticle})) but the "
                            f"simulation has {sim.N} particles; add the variation after the "
                            "particle, with its index")
            break
        if host:
            problems.append(f"variational particles with {', '.join(host)} (HBVM's tangent map "
                            "differentiates its own N-body kernel, not REBOUND's forces); use "
                            "IAS15")
            break
    if sim.gravity not in ("basic", "compensated", "none"):
        problems.append(f"gravity={sim.gravity!r} (an approximate or integrator-specific "
                        "gravity; HBVM takes direct steps: use 'basic', 'compensated' or "
                        "'none')")
    if sim.boundary not in ("none", "open"):
        # ('open' only removes the particles that left the box, after a step: the next step
        # starts afresh from those that remain, as after any removal between runs)
        problems.append(f"boundary={sim.boundary!r} (REBOUND wraps particles across the box "
                        "between steps, which a high-order step's polynomial cannot follow; "
                        "set sim.boundary = 'none' or 'open')")
    for name in random_forces(sim):
        problems.append(
            f"REBOUNDx '{name}' ({NOT_OF_THE_STATE[name]}, so the stage equations of an "
            "implicit HBVM step have no solution: its iteration cannot converge, and adaptive "
            "steps shrink without end; IAS15 accepts its last iterate, WHFast takes one kick "
            "a step); use integrator 'ias15' or 'whfast'")
    if sim._N_odes > 0:
        from hbvm_md.rebound.forces import ode_owners, ode_signature
        owners = ode_owners(sim)
        for j, (_, n, _, deriv, *_) in enumerate(ode_signature(sim)):
            if not deriv:
                problems.append(f"{owners[j] or 'a user ODE'} (sim._odes[{j}], length {n}) has "
                                "no derivatives function; set ode.derivatives before integrating")
    if problems:
        raise ValueError("HBVM cannot honour this simulation: " + "; ".join(problems))


def _real(name: str, value) -> float:
    """``value`` as a float, or TypeError naming ``name`` (bools and strings are not numbers)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"`{name}` must be a real number (got {name}={value!r})")
    return float(value)


def _step_size(name: str, value) -> float:
    h = _real(name, value)
    if not (math.isfinite(h) and h != 0.0):
        raise ValueError(f"`{name}` must be a nonzero finite step size (got {name}={value!r}); "
                         "set it to the step you want, e.g. a fraction of the shortest period")
    return h


def check_particles(y: np.ndarray, model: NBody) -> None:
    """Raise ValueError when the state y = (q, p) of ``model`` is not finite, or when two
    particles of which one gravitates share a position (their force is infinite); the
    message names the particles by their index in ``sim.particles``."""
    if not np.all(np.isfinite(y)):
        raise ValueError("the simulation holds non-finite positions or velocities")
    x = np.asarray(y[: model.dim]).reshape(-1, 3)
    order = np.lexsort(x.T[::-1])
    xs = x[order]
    same = np.all(xs[1:] == xs[:-1], axis=1)        # sorted neighbours that coincide
    for i in np.flatnonzero(same):
        members = np.flatnonzero(np.all(x == xs[i], axis=1))
        if np.any(model.is_source[members]):
            raise ValueError(
                f"particles {', '.join(map(str, members))} are at the same position "
                f"{tuple(map(float, xs[i]))}: the force between them is infinite; remove one "
                "of them or move it")


def shortest_period(sim) -> float:
    """The shortest two-body orbital period 2 pi sqrt(r^3 / (G (|m_i| + |m_j|))) over pairs
    with a gravitating member, from the current positions (a crude time scale of the scene).
    ``sim``: a ``rebound.Simulation`` or the :class:`systems.NBody` read from one."""
    nb = sim if isinstance(sim, NBody) else NBody.from_rebound(sim)
    g = np.where(nb.is_source, nb.body_masses, 0.0)
    return 2 * math.pi * math.sqrt(shortest_r3_over_m(np.ascontiguousarray(nb.positions), g) / nb.G)
