"""The user's handle: :class:`HBVMIntegrator` selects HBVM on a simulation with checked
settings, and reads its state back (it holds none itself)."""
from __future__ import annotations

import math

import numpy as np

from hbvm_md.rebound import layout as L
from hbvm_md.rebound.memory import doubles
from hbvm_md.rebound.checks import (_real, _step_size, check_particles, check_simulation,
                                    shortest_period)
from hbvm_md.rebound.composed import KEPLER_FEW_STEPS  # noqa: F401  (its home is composed)
from hbvm_md.rebound.host import NAME, _rebound, _slots, method_of, record_of_state, register
from integrators import EQUIP, HBVM
from integrators.equip import DEFAULT_EPSILON as EQUIP_DEFAULT_EPSILON, DEFAULT_S as EQUIP_DEFAULT_S
from integrators.core import N_COUNTERS
from integrators.engine import DEFAULT_EPSILON, Counted, check_adaptive, energy_check
from integrators.kchoice import adaptive_k, choose_k, period_steps
from systems.nbody import NBody


#: a scene with at most this many test particles is probed for k whole (:func:`probe_scene`)
PROBE_WHOLE = 64
#: test particles kept from each ranking of :func:`probe_scene` (its probe has at most
#: 2 PROBE_RANKED of them)
PROBE_RANKED = 16


def _closest_ahead(x, v, xs, vs, mu):
    """(r_a^3 / mu, r^3 / mu), each (n,), for test particles at x, v (n, 3) about one source
    at xs, vs (3,) of G m = mu (the squared two-body periods over 4 pi^2): r the distance now,
    r_a the closest distance their two-body motion about it still has ahead, the osculating
    pericentre h^2 / (mu (1 + e)) when the relative orbit is bound or approaching, else r (an
    unbound orbit moving away has its pericentre behind it).  mu < 0 (a negative mass, which
    repels): r^3 / |mu| for both."""
    r = x - xs
    w = v - vs
    r2 = np.einsum("ij,ij->i", r, r)
    rn = np.sqrt(r2)
    if mu < 0.0:
        # a source of negative mass repels: its time scale is that of |mu|, and no closer
        # approach than now is taken from a two-body motion that turns away from it
        return r2 * rn / -mu, r2 * rn / -mu
    c = np.cross(r, w)
    h2 = np.einsum("ij,ij->i", c, c)
    energy = 0.5 * np.einsum("ij,ij->i", w, w) - mu / rn
    e = np.sqrt(np.maximum(0.0, 1.0 + 2.0 * energy * h2 / (mu * mu)))
    ahead = (energy < 0.0) | (np.einsum("ij,ij->i", r, w) < 0.0)
    ra = np.where(ahead, np.minimum(h2 / (mu * (1.0 + e)), rn), rn)
    return ra * ra * ra / mu, r2 * rn / mu


def probe_scene(nb: NBody, y0: np.ndarray) -> tuple[NBody, np.ndarray, np.ndarray]:
    """The scene k is measured on (:func:`integrators.kchoice.choose_k`): ``nb`` itself when it
    has at most PROBE_WHOLE test particles, else its sources and the few test particles that
    decide k, so that the probe's cost does not grow with the number of test particles.

    Parameters
    ----------
    nb : systems.NBody
        The whole scene (sources and test particles, :mod:`systems.nbody`).
    y0 : ndarray (6N,)
        Its state (q, p).

    Returns
    -------
    probe : systems.NBody
        ``nb`` itself, or the scene of the kept particles (same G, masses and sources).
    y_probe : ndarray (6 N_p,)
        Their state, the entries of y0.
    kept : ndarray (N_p,) of int
        Their indices in ``nb``, increasing (so the sources come in the same order and their
        forces are the same numbers bit for bit).

    Notes
    -----
    choose_k measures the largest energy error of HBVM(k, s) over the test steps, and the
    energy is the sources' alone (test particles carry none, as in REBOUND).  The step solves
    the sources' stage equations as if alone and each test particle's after them with its own
    stop rule (:mod:`integrators.loop`, "Followers"), so the sources' trajectory, and the
    energy errors choose_k compares, are the same bit for bit whatever test particles the probe
    has, and every particle kept follows the same arithmetic as in the whole scene.  Test
    particles reach k in one way only: a trial run fails (``StepError``) on a particle the step
    does not resolve, and choose_k then keeps its reference k.  The sample keeps the particles
    likely to fail first:

    * the PROBE_RANKED test particles with the shortest two-body period about any source now,
      min_j r^3 / (G m_j): the fastest motion, where the fixed-point iteration contracts least
      (like (h / T)^2 for a time scale T); the whole scene's shortest period sets the number of
      test steps, taken by the caller on ``nb``;
    * the PROBE_RANKED with the shortest period at the closest distance their two-body motion
      about any source still has ahead (the osculating pericentre, :func:`_closest_ahead`): an
      eccentric orbit now at its apocentre, a particle falling towards a planet.

    When no trial step fails, the sample's k is the whole scene's exactly.  When one does, the
    sample gives the whole scene's k if it holds the particle that fails first, which the
    rankings make likely, not certain; the run then fails on that particle whatever k is, with
    the step's error (a fixed step that does not resolve a test particle is refused).  Measured
    (``python benchmarks/bench_testparticles.py --attach``, see ``benchmarks/results/
    testparticles_attach.md``): REBOUND's test-particle scene, n = 1e2 .. 1e4, 3 seeds x 9
    (s, dt), and ``tests/test_rebound_kprobe.py``'s scenes: the belt at a step of a third of
    its innermost periods and the particle falling onto the Jupiter need the closest approach
    ahead (without it the sample measured k = 8 and 7 for the whole scene's 14; the comet at
    apocentre is held by both rankings).  Before the followers (the sources and the
    particles in one iteration, whose stop rule took its maxima over all of them) the sample
    also kept the particles with the largest coordinates, momenta and forces, for the stop
    rule's scales; the followers took that dependence away, and them with it.
    """
    test = np.flatnonzero(~nb.is_source)
    if test.size <= PROBE_WHOLE:
        return nb, y0, np.arange(nb.N)
    src = np.flatnonzero(nb.is_source)
    N = nb.N
    x = y0[:nb.dim].reshape(N, 3)
    p = y0[nb.dim:].reshape(N, 3)
    v = p / nb.masses.reshape(N, 3)          # p = v for a test particle, m v for a source
    now = np.full(test.size, np.inf)
    ahead = np.full(test.size, np.inf)
    xt, vt = x[test], v[test]
    for j in src:                                  # O(N_s n) in memory O(n)
        a, b = _closest_ahead(xt, vt, x[j], v[j], nb.G * nb.body_masses[j])
        np.minimum(ahead, a, out=ahead)
        np.minimum(now, b, out=now)
    # the PROBE_RANKED smallest of each, deterministic (a partition: O(n), where a sort took
    # 0.5 ms at 1e4)
    keep = [test[np.argpartition(now, PROBE_RANKED)[:PROBE_RANKED]],
            test[np.argpartition(ahead, PROBE_RANKED)[:PROBE_RANKED]]]
    kept = np.union1d(src, np.concatenate(keep))
    probe = NBody(nb.body_masses[kept], G=nb.G, n_active=int(np.count_nonzero(kept < nb.n_active)),
                  positions=x[kept], velocities=v[kept])
    # the state's own entries (m (p / m) need not give p back)
    return probe, np.concatenate([x[kept].ravel(), p[kept].ravel()]), kept


class HBVMIntegrator(Counted):
    """Select and configure HBVM(k, s) or EQUIP(k, s) on a ``rebound.Simulation``:
    ``sim.integrator = "hbvm"`` with these settings (checked), and k measured on the scene when
    not given.

    Parameters
    ----------
    sim : rebound.Simulation
        Plain Newtonian gravity runs on the compiled N-body kernel; additional forces
        (REBOUNDx's or a user's), softening, ``testparticle_type = 1`` and ``gravity =
        'none'`` run on REBOUND's own accelerations at the stages
        (:mod:`hbvm_md.rebound.forces`; k measured for a fixed step is measured on the plain
        N-body scene).  Test particles (``N_active``) and REBOUND's collision detection and
        resolve functions are honoured; what is refused: :mod:`hbvm_md.rebound`.
    s : int, optional
        Degree of the method (order 2s; EQUIP needs s >= 2).  None: 6 for HBVM, 8 for EQUIP
        (:data:`integrators.equip.DEFAULT_S`).
    k : int, optional
        Quadrature nodes (k >= s) of the line integral (EQUIP: of its energy condition, the
        same k-point discrete line integral, so the same k keeps the energy to round-off).
        None: measured on the scene at attach time for ``sim.dt``
        (:func:`integrators.kchoice.choose_k` over one shortest orbital period, on the sources
        and at most 32 of the test particles, those likely to decide k: :func:`probe_scene`) with a
        fixed step, :func:`integrators.kchoice.adaptive_k` (8 for the defaults) with adaptive
        steps.
    method : {"hbvm", "equip"}
        ``"hbvm"`` (default): HBVM(k, s), which conserves the energy; its angular momentum
        has an error of order h^2s (at round-off with s = 6 and planetary steps, visible at
        small s or long steps).  ``"equip"``: EQUIP(k, s) (:class:`integrators.EQUIP`), the
        Gauss method perturbed at each step so that it conserves the energy and stays
        symplectic: energy and angular momentum both at round-off, for 1.9-3.8 times HBVM's
        time a step where the steps resolve the orbits well and 6.7-7.5 times near the
        longest steps (2026-12-08: HBVM's plain step runs in C, EQUIP's still on numba; it
        was 1.2-1.3 and 2.5 when both ran on numba), where the Gauss step's own energy
        residual is a fraction of an ulp that alpha corrects at every step.  Its adaptive defaults are therefore its own, s = 8 at
        epsilon = 1e-17 (EQUIP(9, 8)): on the outer solar system over 1e5 and 1e6 days they
        keep both invariants at IAS15's level in less time than IAS15
        (``benchmarks/bench_equip.py --rebound``).  Saved as ``sim.integrator.method``; set
        that way (``sim.integrator = "hbvm"`` then ``sim.integrator.method = "equip"``), s
        and epsilon stay what they were (HBVM's defaults unless set).
    dt : float, optional
        Sets ``sim.dt`` (the nominal step; REBOUND may shrink the last one).
    max_iter : int
        Fixed-point iterations allowed per step.
    tol : float, optional
        Relative tolerance of the iteration; None iterates to round-off.
    nodes : {"gauss", "lobatto"}
        Quadrature of the line integral.
    adaptive : bool or None
        Step-size control (None, the default: adaptive unless ``dt`` is given, as with IAS15).
        Each step's own estimate of its local error relative to the motion over the step
        (:func:`integrators.core.resolution_error`, from its first omitted Legendre term: no
        extra force evaluation for k > s), is kept below ``epsilon``;
        a step whose estimate, iteration or energy check fails is retried smaller within the
        same REBOUND step, which then records the step taken (``sim.t``,
        ``sim.dt_last_done``); ``sim.dt`` shows the next step proposed.
    epsilon : float, optional
        Precision of the adaptive control: the bound on each step's estimated local error
        relative to the motion, the same accuracy at every s (:func:`integrators.core.
        adapt_step`; not IAS15's quantity).  None: 3e-15 for HBVM
        (``integrators.engine.DEFAULT_EPSILON``), 1e-17 for EQUIP
        (:data:`integrators.equip.DEFAULT_EPSILON`).
    min_dt : float
        Smallest step the adaptive control may take; below it a step that cannot be resolved
        raises :class:`integrators.StepSizeError`.
    max_dt : float
        Largest step the adaptive control may take (0, the default: no bound).  REBOUNDx
        operators are applied once per step, after it, so their splitting error grows with the
        step: a bound of about IAS15's step on the scene brings it to IAS15's
        (``sim.integrator.max_dt``, saved with the simulation).
    energy_tol : float, "auto" or None
        A step that changes the energy of the gravitating bodies by more than this, relative to
        |T| + |V|, is refused with :class:`integrators.UnresolvedStepError` (nothing committed).
        HBVM at round-off k changes it by about 1e-16 a step; a step that does not resolve the
        motion changes it visibly.  The check costs one potential evaluation a step.  "auto"
        (default): the engine's shared default, :func:`integrators.engine.energy_check`:
        ``DEFAULT_ENERGY_TOL`` (1e-10) when k is chosen here (for a round-off quadrature error)
        and ``tol`` is None, else its not-a-solution rule (a change above ``NOT_A_SOLUTION``
        that also exceeds 1e-3 of the energy the step moved between kinetic and potential
        energy: a step too large for the encounter it crosses; :attr:`energy_tol` then reads
        -NOT_A_SOLUTION).  While it is on, a fixed step also checks its test particles: one
        whose own error estimate (the weight of its last Legendre coefficient) exceeds
        max(1e-2, 10 x the gravitating bodies') is refused with UnresolvedStepError naming it.
        None disables both.

    kepler : bool
        True: HBVM(k, s) composed with the Keplerian flows about particle 0
        (:class:`systems.flow_composed.FlowComposed`, the engine's kernels bound with the same
        step; :mod:`hbvm_md.rebound.composed`): the step integrates the bodies' mutual pull
        only.  Fixed steps only (``dt``, or ``sim.dt``; ``adaptive=True`` is refused), k = s + 2
        unless given, HBVM only; test particles (mass 0) follow; forces beyond Newtonian
        gravity, variational particles, a particle 0 that does not dominate or a body not bound
        to it are refused by name (use kepler=False).  Not the default: it is not faster than
        plain HBVM today (``benchmarks/results/kepler_rebound.md``).  Saved as
        ``sim.integrator.kepler``.

    Attributes
    ----------
    method : integrators.HBVM or integrators.EQUIP
    nsteps, nfev, niter, rejected, resyncs : int
        Steps, force evaluations, fixed-point iterations, rejected adaptive trials and reads of
        the state afresh from the particles, as saved with the simulation.

    Notes
    -----
    This object holds no state: it is a view of ``sim.integrator`` (``HBVMIntegrator.of(sim)``
    makes one for any simulation whose integrator is HBVM, e.g. a copy or a loaded file).  A
    failed step raises ``ConvergenceError``, ``UnresolvedStepError``, ``StepSizeError``, ...
    from ``sim.integrate`` / ``sim.steps`` with the particles and ``sim.t`` as before it.  Its
    message names the closest encounter at the step's start and the ways out; its attribute
    ``encounter`` is that pair, dict(i, j, distance, speed, time) (j gravitates; None without
    one), and a test particle's refusal also has ``particle``, its index.
    """

    def __init__(self, sim, s: int | None = None, k: int | None = None,
                 dt: float | None = None, max_iter: int = 60, tol: float | None = None,
                 nodes: str = "gauss", energy_tol: float | str | None = "auto",
                 adaptive: bool | None = None, epsilon: float | None = None,
                 min_dt: float = 0.0, method: str = "hbvm", max_dt: float = 0.0,
                 kepler: bool = False):
        # Everything is checked before anything is changed: a failed attach leaves sim as it was.
        rebound = _rebound()
        if not isinstance(sim, rebound.Simulation):
            raise TypeError(f"`sim` must be a rebound.Simulation (got {type(sim).__name__})")
        L.check_version(rebound)
        register()
        if not isinstance(method, str) or method not in L.METHODS:
            raise ValueError(f"`method` must be one of {L.METHODS} (got method={method!r}): "
                             "'hbvm' conserves the energy, 'equip' the energy and every "
                             "quadratic invariant (angular momentum) too")
        if method == "equip" and nodes != "gauss":
            raise ValueError(f"`nodes` must be 'gauss' with method='equip' (got nodes={nodes!r}):"
                             " EQUIP perturbs the Gauss method")
        if isinstance(kepler, (bool, np.bool_)) or (isinstance(kepler, (int, np.integer))
                                                   and kepler in (0, 1)):
            kepler = bool(kepler)
        else:
            raise TypeError(f"`kepler` must be True or False (got kepler={kepler!r})")
        if kepler and method == "equip":
            raise ValueError("`kepler=True` composes HBVM with the Keplerian flows; "
                             "method='equip' is not composed: use method='hbvm' or kepler=False")
        if kepler and adaptive:
            raise ValueError("`kepler=True` takes fixed steps only (the composed step's clock "
                             "row hides the planets from the step-size controller's estimate): "
                             "pass dt=... (and adaptive=None or False), or kepler=False for "
                             "adaptive steps")
        if kepler:
            adaptive = False          # (fixed steps of dt, or of sim.dt)
        family = EQUIP if method == "equip" else HBVM
        # each method's own defaults (EQUIP's: integrators.equip.DEFAULT_S, DEFAULT_EPSILON)
        if s is None:
            s = EQUIP_DEFAULT_S if family is EQUIP else 6
        if epsilon is None:
            epsilon = EQUIP_DEFAULT_EPSILON if family is EQUIP else DEFAULT_EPSILON

        def build(k_):
            return EQUIP(k_, s) if family is EQUIP else HBVM(k_, s, nodes=nodes)
        method = build(s if k is None else k)     # checks s, k and nodes (EQUIP: s >= 2)
        if (isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer))
                or max_iter < 1):
            raise ValueError(f"`max_iter` must be a positive integer (got max_iter={max_iter!r})")
        if tol is not None and not 0 < _real("tol", tol) < 1:
            raise ValueError(f"`tol` must be None (round-off) or in (0, 1) (got tol={tol!r})")
        auto = isinstance(energy_tol, str) and energy_tol == "auto"
        if not auto and energy_tol is not None and not 0 < _real("energy_tol", energy_tol) < math.inf:
            raise ValueError(f"`energy_tol` must be a positive number or None, or 'auto' (got "
                             f"energy_tol={energy_tol!r}); None switches the energy check off")
        if epsilon == 0 and not isinstance(epsilon, bool) and adaptive is not True:
            # IAS15's idiom: epsilon = 0 takes fixed steps of sim.dt (here: of dt, or sim.dt)
            adaptive, epsilon = False, DEFAULT_EPSILON if family is HBVM else EQUIP_DEFAULT_EPSILON
        if adaptive is None:
            adaptive = dt is None      # like IAS15: no step to choose unless one is given
        if not isinstance(adaptive, (bool, np.bool_)):
            raise TypeError(f"`adaptive` must be True, False or None (got adaptive={adaptive!r})")
        if adaptive:
            epsilon, min_dt = check_adaptive(epsilon, min_dt, method.s)
        if not 0 <= _real("max_dt", max_dt) < math.inf:
            raise ValueError(f"`max_dt` must be a finite number >= 0 (got max_dt={max_dt!r}); "
                             "0 leaves the adaptive step unbounded")
        check_simulation(sim)
        if dt is not None:
            h = _step_size("dt", dt)
        elif adaptive:
            # the first step tried: the controller takes it from there
            period = shortest_period(sim) if sim.N > 1 else math.inf
            h = period / 50 if math.isfinite(period) else _step_size("sim.dt", sim.dt)
            h = math.copysign(h, sim.dt) if sim.dt != 0 else h
        else:
            h = _step_size("sim.dt", sim.dt)
        if kepler:
            from hbvm_md.rebound.composed import check_composed, warn_short_step
            check_composed(sim)
            if dt is None:
                warn_short_step(sim, h, "pass dt=...", stacklevel=3)
        if k is None and kepler:
            # benchmarks/results/kepler_composed.md: HBVM(s + 2, s) composed keeps the energy
            # at round-off on the outer solar system (H~ is not polynomial, but its
            # perturbation is small: two nodes beyond s suffice there)
            method = build(method.s + 2)
        elif k is None and adaptive:
            # the steps vary (pericentres, encounters): no single step to probe k on
            method = build(adaptive_k(method.s, epsilon))
        elif k is None and sim.N > 1:
            # HBVM's round-off k: EQUIP's energy condition is the same k-point line integral
            # along the same degree-s path, so its quadrature error is HBVM(k, s)'s
            nb = NBody.from_rebound(sim)
            y0 = nb.initial_state()
            check_particles(y0, nb)
            steps = period_steps(shortest_period(nb), h)     # the whole scene's fastest motion
            probe, yp, _ = probe_scene(nb, y0)     # its sources and test particles that decide k
            method = build(choose_k(probe, yp, method.s, h, steps, solver="fixed_point").k)
        # the engine's one default check; k chosen here is chosen for a round-off quadrature
        # error, so "auto" is its strict DEFAULT_ENERGY_TOL (gravity is not polynomial: a k the
        # user gives gets the not-a-solution rule)
        etol = energy_check(method, None, energy_tol, tol, round_off_k=k is None and not kepler)
        self._prev_integrator = str(sim.integrator)
        self.sim = sim
        sim.integrator = NAME
        sim.dt = h
        st, sd = self._slots()
        st[[L.SL_METHOD, L.SL_S, L.SL_K, L.SL_NODES, L.SL_MAX_ITER, L.SL_ADAPTIVE]] = (
            L.METHODS.index("equip" if family is EQUIP else "hbvm"), method.s, method.k,
            L.NODES.index(method.nodes), int(max_iter), int(adaptive))
        sd[[L.SL_EPSILON, L.SL_MIN_DT, L.SL_TOL, L.SL_ETOL, L.SL_MAX_DT]] = (
            float(epsilon), float(min_dt), float(tol or 0.0), etol, float(max_dt))
        st[L.SL_KEPLER] = int(kepler)
        if kepler:
            # a step given (dt=...) is chosen, a short sim.dt warned about above: the composed
            # step's preparation does not warn about it again (it warns for
            # sim.integrator.kepler = 1 with a short sim.dt)
            record_of_state(int(sim.integrator.state)).kepler_seen_dt = h

    @classmethod
    def of(cls, sim) -> "HBVMIntegrator | None":
        """A view of ``sim``'s HBVM integrator (a copy's, a loaded file's), or None when its
        integrator is not HBVM."""
        if str(sim.integrator) != NAME:
            return None
        self = cls.__new__(cls)
        self.sim, self._prev_integrator = sim, "ias15"
        return self

    def _slots(self) -> tuple[np.ndarray, np.ndarray]:
        name = str(self.sim.integrator)
        if name != NAME:
            raise ValueError(f"sim.integrator is '{name}', not HBVM (it was changed after "
                             "HBVMIntegrator(sim)); set sim.integrator = 'hbvm' or attach again")
        return _slots(self.sim.integrator.state)

    def _get(self, slot: int):
        st, sd = self._slots()
        return int(st[slot]) if slot in L.INT_SLOTS else float(sd[slot])

    @property
    def method(self) -> HBVM | EQUIP:
        return method_of(self._slots()[0])

    @property
    def counters(self) -> np.ndarray:
        """The core's counters (layout of :mod:`integrators.core`), as saved with the run."""
        st, _ = self._slots()
        n = int(st[L.SL_NCOUNTERS])
        return doubles(int(st[L.SL_COUNTERS]), n).copy() if n else np.zeros(N_COUNTERS)

    nsteps = property(lambda self: self._get(L.SL_NSTEPS), doc="Steps committed.")
    rejected = property(lambda self: self._get(L.SL_REJECTED),
                        doc="Adaptive trial steps rejected (and retried smaller).")
    resyncs = property(lambda self: self._get(L.SL_RESYNCS),
                       doc="How often the state was read afresh from the particles.")
    adaptive = property(lambda self: bool(self._get(L.SL_ADAPTIVE))
                        and self._get(L.SL_EPSILON) != 0.0,
                        doc="Adaptive steps (False: fixed steps of sim.dt, also with "
                            "``sim.integrator.epsilon = 0``, as with IAS15).")
    epsilon = property(lambda self: self._get(L.SL_EPSILON))
    min_dt = property(lambda self: self._get(L.SL_MIN_DT))

    @property
    def max_dt(self) -> float:
        """Largest adaptive step (0: no bound); settable between runs, also as
        ``sim.integrator.max_dt``."""
        return self._get(L.SL_MAX_DT)

    @max_dt.setter
    def max_dt(self, value: float) -> None:
        if not 0 <= _real("max_dt", value) < math.inf:
            raise ValueError(f"`max_dt` must be a finite number >= 0 (got max_dt={value!r}); "
                             "0 leaves the adaptive step unbounded")
        self._slots()[1][L.SL_MAX_DT] = float(value)

    @property
    def attached(self) -> bool:
        return str(self.sim.integrator) == NAME

    @property
    def max_iter(self) -> int:
        """Fixed-point iterations allowed per step (settable between runs)."""
        return self._get(L.SL_MAX_ITER)

    @max_iter.setter
    def max_iter(self, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"`max_iter` must be a positive integer (got max_iter={value!r})")
        self._slots()[0][L.SL_MAX_ITER] = int(value)

    @property
    def tol(self) -> float:
        """Relative tolerance of the iteration (0: round-off)."""
        return self._get(L.SL_TOL)

    @property
    def energy_tol(self) -> float | None:
        """The energy check's tolerance (None: off; negative: the not-a-solution rule with
        its absolute value, :func:`integrators.engine.energy_check`); settable between runs."""
        return self._get(L.SL_ETOL) or None

    @energy_tol.setter
    def energy_tol(self, value: float | None) -> None:
        if value is not None and not 0 < _real("energy_tol", value) < math.inf:
            raise ValueError(f"`energy_tol` must be a positive number or None (got "
                             f"energy_tol={value!r}); None switches the energy check off")
        self._slots()[1][L.SL_ETOL] = float(value or 0.0)

    @property
    def kepler(self) -> bool:
        """HBVM composed with the Keplerian flows about particle 0 (``sim.integrator.kepler``;
        :mod:`hbvm_md.rebound.composed`); settable between runs (True needs fixed steps)."""
        return bool(self._get(L.SL_KEPLER))

    @kepler.setter
    def kepler(self, value: bool) -> None:
        if not (isinstance(value, (bool, np.bool_)) or (isinstance(value, (int, np.integer))
                                                        and value in (0, 1))):
            raise TypeError(f"`kepler` must be True or False (got kepler={value!r})")
        self._slots()[0][L.SL_KEPLER] = int(value)

    def __repr__(self) -> str:
        kepler = ", kepler=True" if self.attached and self.kepler else ""
        return (f"HBVMIntegrator({self.method!r}{kepler}, attached={self.attached}, "
                f"nsteps={self.nsteps})")

    def integrate(self, tmax: float, exact_finish_time: int = 1) -> None:
        """``sim.integrate(tmax, exact_finish_time)``."""
        self.sim.integrate(tmax, exact_finish_time)

    def detach(self) -> None:
        """Give the simulation back its previous integrator."""
        if self.attached:
            self.sim.integrator = self._prev_integrator

    def save(self, path) -> None:
        """``sim.save_to_file(path, delete_file=True)``: REBOUND's binary holds HBVM's
        settings and state; ``rebound.Simulation(path)`` continues bit for bit."""
        self.sim.save_to_file(str(path), delete_file=True)

    @classmethod
    def load(cls, path) -> tuple:
        """``(sim, HBVMIntegrator.of(sim))`` for ``sim = rebound.Simulation(path)``."""
        sim = _rebound().Simulation(str(path))
        return sim, cls.of(sim)
