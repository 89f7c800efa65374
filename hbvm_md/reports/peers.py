"""The peers HBVM is measured against, run on the same systems in the same process.

* :func:`stormer_verlet`: the velocity-Verlet (leapfrog, Stormer-Verlet) scheme for separable
  systems, compiled when the system has ``separable_kernels`` (HLW Sec. I.3.1, eq. (3.4)).
* :func:`dop853`: scipy's explicit 8th-order Runge-Kutta (``solve_ivp(method="DOP853")``).
* :func:`rebound_kepler`: a Kepler orbit integrated by one of REBOUND's own integrators.
* :func:`from_integration`: an :class:`integrators.IntegrationResult` as a :class:`Run`.

Every peer returns a :class:`Run` so that reports treat all methods alike.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from integrators.jit import jit

from integrators.engine import check_state, check_step


@dataclass
class Run:
    """Samples and counters of one run of one method.

    Attributes
    ----------
    method : str
    t : ndarray (n,)
        Sample times.
    y : ndarray (n, 2m)
        States at the sample times.
    energy : ndarray (n,)
        H at the samples.
    steps, nfev : int
        Steps taken and force (or vector-field) evaluations.
    wall_time : float
        Seconds in the integration loop.
    finished : bool
        False when the method stopped early (diverged, failed to converge, left the
        tolerance); ``message`` says why.
    """

    method: str
    t: np.ndarray
    y: np.ndarray
    energy: np.ndarray
    steps: int
    nfev: int
    wall_time: float
    finished: bool = True
    message: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def energy_error(self) -> np.ndarray:
        """|H - H(y0)| / |H(y0)| at the samples (absolute when H(y0) = 0); inf where not finite."""
        e0 = self.energy[0]
        err = np.abs(self.energy - e0) / (abs(e0) if e0 != 0 else 1.0)
        return np.where(np.isfinite(err), err, np.inf)

    @property
    def max_energy_error(self) -> float:
        return float(np.max(self.energy_error)) if len(self.energy) else float("nan")


def sample_interval(steps: int, samples: int) -> int:
    """The largest divisor of ``steps`` not above steps // samples: sampling every that many
    steps keeps about ``samples`` samples and always ends on the final state."""
    target = max(1, int(steps) // max(int(samples), 1))
    for d in range(target, 0, -1):
        if steps % d == 0:
            return d
    return 1


def from_integration(method: str, res) -> Run:
    """Wrap an :class:`integrators.IntegrationResult`."""
    return Run(method, res.t, res.y, res.energy, res.steps, res.nfev, res.wall_time,
               extra={"iterations_per_step": res.iterations_per_step, "newton_steps": res.newton_steps,
                      "solver_switches": res.solver_switches, "path": res.path})


# -- Stormer-Verlet ------------------------------------------------------------------------
@jit
def _verlet_compiled(force, potential, params, q, p, minv, h, nsteps, sample_every,
                     out_q, out_p, out_e):
    m = q.shape[0]
    Q = np.empty((1, m))
    F = np.empty((1, m))
    for j in range(m):
        Q[0, j] = q[j]
    force(Q, params, F)
    out_q[0] = q
    out_p[0] = p
    ke = 0.0
    for j in range(m):
        ke += 0.5 * p[j] * p[j] * minv[j]
    out_e[0] = ke + potential(q, params)
    isample = 1
    for step in range(nsteps):
        for j in range(m):
            p[j] += 0.5 * h * F[0, j]
            q[j] += h * p[j] * minv[j]
            Q[0, j] = q[j]
        force(Q, params, F)
        for j in range(m):
            p[j] += 0.5 * h * F[0, j]
        if (step + 1) % sample_every == 0:
            out_q[isample] = q
            out_p[isample] = p
            ke = 0.0
            for j in range(m):
                ke += 0.5 * p[j] * p[j] * minv[j]
            out_e[isample] = ke + potential(q, params)
            isample += 1
        if not np.isfinite(ke):
            return step + 1
    return nsteps


def stormer_verlet(system, y0, h: float, steps: int, sample_every: int = 1,
                   name: str = "VelocityVerlet") -> Run:
    """Velocity Verlet (Stormer-Verlet, leapfrog kick-drift-kick) on a separable system.

    p_{1/2} = p0 + h/2 F(q0), q1 = q0 + h M^{-1} p_{1/2}, p1 = p_{1/2} + h/2 F(q1): one force
    evaluation a step, order 2, symplectic; on a linear oscillator of frequency omega it is
    stable only for h omega < 2 (HLW Sec. I.5).

    Parameters
    ----------
    system : SeparableSystem
        Needs ``masses``, ``forces``, ``potential``; compiled when it has ``separable_kernels``.
    y0 : array_like (2m,)
    h : float
    steps : int
    sample_every : int

    Returns
    -------
    Run
        ``finished`` is False when the energy stopped being finite (the run is cut there).
    """
    if not all(hasattr(system, a) for a in ("masses", "forces", "potential")):
        raise TypeError(f"`system` must be separable (masses, forces, potential) for Stormer-Verlet "
                        f"(got {type(system).__name__}); use dop853 for a general system")
    system, y0 = check_state(system, y0)
    h = check_step(h)
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise ValueError(f"`steps` must be an integer >= 0 (got steps={steps!r})")
    if isinstance(sample_every, bool) or not isinstance(sample_every, (int, np.integer)) or sample_every < 1:
        raise ValueError(f"`sample_every` must be an integer >= 1 (got sample_every={sample_every!r})")
    d = system.dim
    minv = 1.0 / np.asarray(system.masses, dtype=float)
    nsamp = steps // sample_every + 1
    q, p = y0[:d].copy(), y0[d:].copy()
    if hasattr(system, "separable_kernels"):
        force, potential, params = system.separable_kernels()
        out_q, out_p, out_e = np.full((nsamp, d), np.nan), np.full((nsamp, d), np.nan), np.full(nsamp, np.nan)
        # zero steps on copies: compiles (or loads from the disk cache) outside the timing
        _verlet_compiled(force, potential, np.ascontiguousarray(params, dtype=float), q.copy(), p.copy(),
                         minv, h, 0, 1, out_q[:1].copy(), out_p[:1].copy(), out_e[:1].copy())
        t0 = time.perf_counter()
        with np.errstate(all="ignore"):
            done = _verlet_compiled(force, potential, np.ascontiguousarray(params, dtype=float), q, p,
                                    minv, h, int(steps), int(sample_every), out_q, out_p, out_e)
        wall = time.perf_counter() - t0
        Y = np.concatenate([out_q, out_p], axis=1)
        E = out_e
    else:
        t0 = time.perf_counter()
        ys = [y0.copy()]
        done = 0
        with np.errstate(all="ignore"):
            F = system.forces(q)
            for i in range(steps):
                p += 0.5 * h * F
                q += h * p * minv
                F = system.forces(q)
                p += 0.5 * h * F
                done = i + 1
                if done % sample_every == 0:
                    ys.append(np.concatenate([q, p]))
                if not np.all(np.isfinite(p)):
                    break
        wall = time.perf_counter() - t0
        Y = np.full((nsamp, 2 * d), np.nan)
        Y[: len(ys)] = ys
        with np.errstate(all="ignore"):
            E = np.asarray(system.energy(Y), dtype=float)
    nkeep = done // sample_every + 1
    t = np.arange(nkeep) * sample_every * h
    finished = done == steps and bool(np.all(np.isfinite(E[:nkeep])))
    msg = "" if finished else f"unstable: energy not finite after {done} steps"
    return Run(name, t, Y[:nkeep], E[:nkeep], done, done + 1, wall, finished, msg)


# -- scipy DOP853 --------------------------------------------------------------------------
def dop853(system, y0, t_end: float, rtol: float, atol: float | None = None,
           samples: int = 200, name: str | None = None) -> Run:
    """scipy's DOP853 (``solve_ivp``) with tolerances rtol, atol (default atol = rtol * 1e-3).

    Parameters
    ----------
    system : HamiltonianSystem
    y0 : array_like (2m,)
    t_end : float
        Final time (> 0).
    rtol, atol : float
    samples : int
        Number of evenly spaced output times (dense output).

    Returns
    -------
    Run
        ``finished`` is False when solve_ivp reports failure.
    """
    from scipy.integrate import solve_ivp
    system, y0 = check_state(system, y0)
    if not (np.isfinite(t_end) and t_end > 0):
        raise ValueError(f"`t_end` must be a positive number (got t_end={t_end!r})")
    if not (np.isfinite(rtol) and 0 < rtol < 1):
        raise ValueError(f"`rtol` must be in (0, 1) (got rtol={rtol!r})")
    atol = rtol * 1e-3 if atol is None else atol
    d = system.dim

    def f(t, y):
        g = system.gradient(y)
        return np.concatenate([g[d:], -g[:d]])

    t_eval = np.linspace(0.0, t_end, samples + 1)
    t0 = time.perf_counter()
    sol = solve_ivp(f, (0.0, t_end), y0, method="DOP853", rtol=rtol, atol=atol, t_eval=t_eval)
    wall = time.perf_counter() - t0
    Y = sol.y.T
    E = np.asarray(system.energy(Y), dtype=float) if len(Y) else np.array([system.energy(y0)])
    steps = int(max(sol.nfev - 1, 0) // 12)  # DOP853 uses 12 evaluations per step
    return Run(name or f"DOP853(rtol={rtol:.0e})", sol.t, Y, E, steps, int(sol.nfev), wall,
               bool(sol.success), "" if sol.success else str(sol.message), extra={"rtol": rtol})


# -- REBOUND on Kepler ---------------------------------------------------------------------
def kepler_simulation(e: float, integrator: str, dt: float | None = None):
    """A REBOUND simulation of the Kepler orbit of :class:`systems.Kepler`: G = 1, a unit mass
    at the origin with a test particle on a = 1, eccentricity e, starting at pericentre.
    Heliocentric coordinates stay those of the reduced problem because the central mass does
    not move (the planet has m = 0)."""
    import rebound
    sim = rebound.Simulation()
    sim.G = 1.0
    sim.add(m=1.0)
    sim.add(m=0.0, a=1.0, e=float(e), f=0.0)
    sim.integrator = integrator
    if dt is not None:
        sim.dt = float(dt)
    return sim


def rebound_kepler(e: float, t_end: float, integrator: str = "ias15", dt: float | None = None,
                   samples: int = 200, epsilon: float | None = None) -> Run:
    """Kepler orbit with REBOUND's ``integrator`` to ``t_end``; states in the reduced (q, p).

    The energy is that of the reduced problem, |p|^2 / 2 - 1 / |q| (REBOUND's ``energy()`` leaves
    test particles out).
    """
    sim = kepler_simulation(e, integrator, dt)
    if epsilon is not None:
        sim.integrator.epsilon = float(epsilon)
    if integrator != "ias15":
        sim.exact_finish_time = 0
    t_eval = np.linspace(0.0, t_end, samples + 1)
    ys = []
    wall = 0.0
    steps0 = sim.steps_done
    for tt in t_eval:
        t0 = time.perf_counter()
        if tt > 0:
            sim.integrate(tt)
        wall += time.perf_counter() - t0
        pl = sim.particles[1]
        ys.append([pl.x, pl.y, pl.vx, pl.vy])
    Y = np.array(ys)
    E = 0.5 * (Y[:, 2] ** 2 + Y[:, 3] ** 2) - 1.0 / np.hypot(Y[:, 0], Y[:, 1])
    steps = int(sim.steps_done - steps0)
    label = integrator if dt is None else f"{integrator}(dt={dt:.3g})"
    return Run(label, np.array([sim.t if i == len(t_eval) - 1 else tt for i, tt in enumerate(t_eval)]),
               Y, E, steps, steps, wall)


# -- heyoka (Taylor method compiled by LLVM) on an N-body problem --------------------------
HEYOKA_MISSING = ("heyoka is not installed, so the heyoka peer is skipped; install it with "
                  "`pip install 'hbvm-md[bench]'` (or `pip install heyoka`)")


def import_heyoka():
    """The ``heyoka`` module, or ImportError with :data:`HEYOKA_MISSING` (an optional peer)."""
    try:
        import heyoka
    except ImportError as err:
        raise ImportError(HEYOKA_MISSING) from err
    return heyoka


class HeyokaNBody:
    """heyoka's adaptive Taylor integrator on a Newtonian N-body problem.

    ``heyoka.model.nbody`` with the scene's G and masses, ``heyoka.taylor_adaptive`` with
    tolerance ``tol`` (default: machine epsilon of ``fp_type``).  heyoka compiles the Taylor
    step for the system with LLVM when the integrator is built; that is a one-off per scene
    shape (number of bodies, masses, G, tolerance, precision), measured in :attr:`compile_time`
    and left out of :meth:`propagate`'s wall time, as numba's compile (or cache load) is left
    out of HBVM's.

    Parameters
    ----------
    masses : array_like (N,)
    G : float
    tol : float, optional
        heyoka's relative-absolute tolerance; None: ``np.finfo(fp_type).eps``.
    fp_type : type
        ``float`` or ``np.longdouble`` (80-bit extended on x86-64: a high-accuracy reference).
    compact_mode : bool
        heyoka's compact mode (compiles much faster; heyoka's default is False).

    Attributes
    ----------
    compile_time : float
        Seconds spent building (compiling) the integrator.
    order : int
        Order of the Taylor method heyoka chose for ``tol``.
    """

    def __init__(self, masses, G: float, tol: float | None = None, fp_type=float,
                 compact_mode: bool = False):
        hy = import_heyoka()
        masses = np.asarray(masses, dtype=float)
        if masses.ndim != 1 or len(masses) < 2 or not np.all(np.isfinite(masses)) or np.any(masses < 0):
            raise ValueError(f"`masses` must be N >= 2 finite non-negative numbers (got {masses!r})")
        if not (np.isfinite(G) and G > 0):
            raise ValueError(f"`G` must be a positive number (got G={G!r})")
        self.fp_type = np.dtype(fp_type).type
        if self.fp_type not in (np.float64, np.longdouble):
            raise ValueError(f"`fp_type` must be float or np.longdouble (got {fp_type!r})")
        self.tol = float(np.finfo(self.fp_type).eps) if tol is None else tol
        if not (0 < self.tol < 1):
            raise ValueError(f"`tol` must be in (0, 1) (got tol={tol!r})")
        self.N = len(masses)
        t0 = time.perf_counter()
        self._ta = hy.taylor_adaptive(hy.model.nbody(self.N, masses=[float(m) for m in masses], Gconst=float(G)),
                                      np.zeros(6 * self.N, dtype=self.fp_type), tol=self.fp_type(self.tol),
                                      fp_type=self.fp_type, compact_mode=bool(compact_mode))
        self.compile_time = time.perf_counter() - t0
        self.order = int(self._ta.order)

    def propagate(self, xv0, t_out) -> tuple[np.ndarray, float, int]:
        """Integrate from ``xv0`` at ``t_out[0]`` and return the states at every ``t_out``.

        Parameters
        ----------
        xv0 : array_like (N, 6) or (6N,)
            Positions and velocities, body after body (REBOUND's ``xyzvxvyvz`` layout).
        t_out : array_like (n,)
            Increasing output times (``propagate_grid``).

        Returns
        -------
        states : ndarray (n, N, 6) of ``fp_type``
        wall : float
            Seconds in ``propagate_grid`` (compile time excluded, see :attr:`compile_time`).
        steps : int
            Taylor steps taken.
        """
        xv0 = np.asarray(xv0, dtype=self.fp_type).reshape(-1)
        if xv0.shape != (6 * self.N,) or not np.all(np.isfinite(xv0)):
            raise ValueError(f"`xv0` must hold 6 N = {6 * self.N} finite numbers (got shape {np.shape(xv0)})")
        grid = np.asarray(t_out, dtype=self.fp_type)
        if grid.ndim != 1 or len(grid) < 1 or np.any(np.diff(grid) <= 0):
            raise ValueError("`t_out` must be a non-empty increasing sequence of times")
        ta = self._ta
        ta.time = grid[0]
        ta.state[:] = xv0
        t0 = time.perf_counter()
        outcome, _, _, steps, _, states = ta.propagate_grid(grid)
        wall = time.perf_counter() - t0
        if str(outcome) != "taylor_outcome.time_limit":
            raise RuntimeError(f"heyoka stopped early ({outcome}) at t = {float(ta.time):.6g}")
        return states.reshape(len(grid), self.N, 6), wall, int(steps)
