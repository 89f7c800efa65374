"""The hard-case suite: where numerical integrators break, and what HBVM and its peers do there.

Each case is a function returning a :class:`CaseReport` (one :class:`Outcome` per method and
setting, plus the facts a test asserts).  ``quick=True`` shrinks every run for tests and CI;
``hbvm-md hard-cases`` runs them at full size.

* :func:`stiff_fpu` - the stiff Fermi-Pasta-Ulam chain, h omega from 0.1 to 10 (HLW XIII.2).
* :func:`eccentric_kepler` - Kepler with e = 0.9, 0.99: fixed steps, the Poincare time
  transformation (:mod:`systems.poincare`), and REBOUND's IAS15.
* :func:`close_encounter` - two planets in a Hill-unstable pair (REBOUND scene).
* :func:`chaotic_henon_heiles` - Henon-Heiles just below the escape energy 1/6.
* :func:`step_too_large` - step sizes where the nonlinear iteration fails: a ConvergenceError,
  never a silent wrong answer.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from integrators import HBVM, StepError, Stepper, integrate
from systems import FPU, HenonHeiles, Kepler
from systems.poincare import PoincareTransformed

from .peers import Run, dop853, from_integration, rebound_kepler, sample_interval, stormer_verlet


@dataclass
class Outcome:
    """What one method did on one setting of a case.

    Attributes
    ----------
    method, setting : str
    finished : bool
    steps : int
    energy_error : float
        Largest relative energy error over the run (inf if the run blew up, nan if none ran).
    solution_error : float
        Max-norm error of the final state against the case's reference (nan if not measured).
    wall_time : float
        Seconds.
    note : str
    """

    method: str
    setting: str
    finished: bool
    steps: int
    energy_error: float
    solution_error: float
    wall_time: float
    note: str = ""


@dataclass
class CaseReport:
    """The outcomes of one hard case and the facts its test asserts."""

    name: str
    description: str
    outcomes: list = field(default_factory=list)
    facts: dict = field(default_factory=dict)

    def table(self) -> str:
        """A fixed-width text table of the outcomes."""
        head = f"{'method':<26} {'setting':<24} {'done':<5} {'steps':>9} {'max rel dE':>10} " \
               f"{'sol. error':>10} {'wall s':>8}  note"
        lines = [f"== {self.name}: {self.description}", head, "-" * len(head)]
        for o in self.outcomes:
            lines.append(f"{o.method:<26} {o.setting:<24} {'yes' if o.finished else 'NO':<5} {o.steps:>9d} "
                         f"{_fmt(o.energy_error):>10} {_fmt(o.solution_error):>10} {o.wall_time:>8.3f}  {o.note}")
        return "\n".join(lines)


def _fmt(x: float) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return "inf" if math.isinf(x) else f"{x:.2e}"


def _outcome(run: Run, setting: str, ref=None, note: str = "") -> Outcome:
    sol = float("nan")
    if ref is not None and run.finished:
        sol = float(np.max(np.abs(run.y[-1] - ref)))
    return Outcome(run.method, setting, run.finished, run.steps, run.max_energy_error if run.finished else float("inf"),
                   sol, run.wall_time, note or run.message)


# -- Kepler's exact solution ---------------------------------------------------------------
def kepler_exact(e: float, t) -> np.ndarray:
    """The exact state of :class:`systems.Kepler` (mu = 1, a = 1, from pericentre) at times t.

    Solves Kepler's equation E - e sin E = t (mean anomaly) by Newton's method from E = pi,
    which converges for every e < 1.

    Returns
    -------
    ndarray, shape t.shape + (4,)
        (q1, q2, p1, p2).
    """
    t = np.asarray(t, dtype=float)
    M = np.mod(t, 2 * np.pi)
    E = np.full_like(M, np.pi)
    for _ in range(100):
        dE = (E - e * np.sin(E) - M) / (1 - e * np.cos(E))
        E = E - dE
        if np.all(np.abs(dE) < 1e-16):
            break
    den = 1 - e * np.cos(E)
    b = math.sqrt(1 - e * e)
    return np.stack([np.cos(E) - e, b * np.sin(E), -np.sin(E) / den, b * np.cos(E) / den], axis=-1)


# -- stiff FPU -----------------------------------------------------------------------------
def stiff_fpu(quick: bool = False, omegas=None, h_omegas=None, t_end: float | None = None,
              s: int = 2) -> CaseReport:
    """Stiff FPU chain (m = 3) with HBVM(2s, s) (exact for the quartic H) and Velocity Verlet.

    The fixed-point iteration contracts only for h omega below about 2 / rho(X_s); beyond, the
    engine's "auto" solver switches to simplified Newton (whose matrix I - h X_s (x) J0 carries
    the stiff linear part) and the energy stays exact.  Verlet is unstable for h omega > 2.
    The reference is HBVM(8, 4) at h omega = 0.02.

    Facts: ``newton_took_over`` (omega, h omega) -> bool, ``hbvm_energy`` -> max rel error,
    ``verlet_finished`` and ``verlet_energy`` -> per setting.
    """
    omegas = ((50.0, 1000.0) if omegas is None else tuple(omegas))
    h_omegas = ((0.5, 2.0, 10.0) if quick else (0.1, 0.5, 1.0, 2.0, 5.0, 10.0)) if h_omegas is None else tuple(h_omegas)
    t_end = (1.0 if quick else 10.0) if t_end is None else float(t_end)
    rep = CaseReport("stiff-fpu", f"FPU chain m=3, T={t_end:g}, HBVM({2 * s},{s}) vs Velocity Verlet")
    rep.facts.update(newton_took_over={}, hbvm_energy={}, hbvm_finished={}, verlet_finished={}, verlet_energy={})
    method = HBVM.for_polynomial_degree(4, s)
    for omega in omegas:
        fpu = FPU(3, omega)
        y0 = fpu.initial_state()
        href = 0.02 / omega
        nref = int(round(t_end / href))
        ref = integrate(HBVM(8, 4), fpu, y0, t_end / nref, nref, sample_every=nref).y[-1]
        for hw in h_omegas:
            n = max(1, int(round(t_end * omega / hw)))
            h = t_end / n
            key = (omega, hw)
            setting = f"omega={omega:g} h*omega={hw:g}"
            try:
                # (steps that do not resolve the stiff springs, on purpose: A-stability and the
                # energy at any step, so the step's own error check is off)
                r = integrate(method, fpu, y0, h, n, sample_every=sample_interval(n, 200),
                              error_bound=None)
                run = from_integration(f"HBVM{(method.k, method.s)}", r)
                took = r.newton_steps > 0
                note = (f"Newton took over ({r.newton_steps} Newton steps)" if took else
                        f"fixed point, {r.iterations_per_step:.1f} it/step")
                rep.outcomes.append(_outcome(run, setting, ref, note))
                rep.facts["newton_took_over"][key] = took
                rep.facts["hbvm_energy"][key] = run.max_energy_error
                rep.facts["hbvm_finished"][key] = True
            except StepError as err:
                rep.outcomes.append(Outcome(f"HBVM{(method.k, method.s)}", setting, False, 0, float("nan"),
                                            float("nan"), 0.0, f"ConvergenceError: {err}"[:80]))
                rep.facts["hbvm_finished"][key] = False
            vv = stormer_verlet(fpu, y0, h, n, sample_every=sample_interval(n, 200))
            unstable = (not vv.finished) or vv.max_energy_error > 1.0
            rep.outcomes.append(_outcome(vv, setting, ref, "unstable" if unstable else ""))
            rep.facts["verlet_finished"][key] = vv.finished and not unstable
            rep.facts["verlet_energy"][key] = vv.max_energy_error if vv.finished else float("inf")
    return rep


# -- eccentric Kepler ----------------------------------------------------------------------
def eccentric_kepler(quick: bool = False, eccentricities=(0.9, 0.99), periods: int | None = None,
                     s: int = 3, k: int = 10, fixed_steps: dict | None = None,
                     poincare_steps: dict | None = None) -> CaseReport:
    """Kepler with high eccentricity: fixed steps, Poincare-transformed steps, IAS15.

    HBVM(k, s) with a fixed step resolves the pericentre passage only with many steps per
    period.  The Poincare transformation with g = |q| (Sundman) integrates K = g (H - H0) with a
    fixed step in the fictitious time (for a = 1 its period is 2 pi, the eccentric anomaly), so
    the physical step is proportional to r.  Solution errors are against Kepler's exact
    solution at the final physical time.

    Facts: per e, ``fixed``, ``poincare`` and ``ias15`` -> dict(steps, energy_error,
    solution_error).
    """
    periods = (10 if quick else 1000) if periods is None else int(periods)
    fixed_steps = fixed_steps or {0.9: 2000, 0.99: 20000}
    poincare_steps = poincare_steps or {0.9: 100, 0.99: 200}
    rep = CaseReport("eccentric-kepler", f"Kepler, {periods} periods, HBVM({k},{s}) fixed and "
                     f"Poincare-transformed (g=|q|) vs IAS15")
    method = HBVM(k, s)
    for e in eccentricities:
        kep = Kepler(e)
        y0 = kep.initial_state()
        T = 2 * np.pi * periods
        facts = {}
        n = fixed_steps.get(e, 20000)
        r = integrate(method, kep, y0, T / (n * periods), n * periods, sample_every=n)
        err = float(np.max(np.abs(r.y[-1] - kepler_exact(e, r.t[-1]))))
        rep.outcomes.append(Outcome(f"HBVM{(k, s)} fixed", f"e={e} {n}/period", True, r.steps,
                                    r.max_energy_error, err, r.wall_time, r.path))
        facts["fixed"] = dict(steps=r.steps, energy_error=r.max_energy_error, solution_error=err)
        npt = poincare_steps.get(e, 200)
        pt = PoincareTransformed.for_kepler(kep, alpha=1.0, y0=y0)
        Y0 = pt.extend(y0)
        try:
            rp = integrate(method, pt, Y0, 2 * np.pi / npt, npt * periods, sample_every=npt)
            tph, yph = pt.physical(rp.y)
            H = kep.energy(yph)
            dH = float(np.max(np.abs(H - H[0])) / abs(H[0]))
            errp = float(np.max(np.abs(yph[-1] - kepler_exact(e, tph[-1]))))
            rep.outcomes.append(Outcome(f"HBVM{(k, s)} Poincare", f"e={e} {npt}/period", True, rp.steps,
                                        dH, errp, rp.wall_time, f"t_end={tph[-1]:.6g}"))
            facts["poincare"] = dict(steps=rp.steps, energy_error=dH, solution_error=errp)
        except StepError as err_:
            rep.outcomes.append(Outcome(f"HBVM{(k, s)} Poincare", f"e={e} {npt}/period", False, 0,
                                        float("nan"), float("nan"), 0.0, str(err_)[:80]))
            facts["poincare"] = None
        ias = rebound_kepler(e, T, "ias15", samples=periods)
        erri = float(np.max(np.abs(ias.y[-1] - kepler_exact(e, ias.t[-1]))))
        rep.outcomes.append(Outcome("IAS15 (REBOUND)", f"e={e} adaptive", True, ias.steps,
                                    ias.max_energy_error, erri, ias.wall_time))
        facts["ias15"] = dict(steps=ias.steps, energy_error=ias.max_energy_error, solution_error=erri)
        rep.facts[e] = facts
    return rep


# -- close encounter -----------------------------------------------------------------------
def encounter_scene():
    """Star (m = 1) and two Jupiter-mass planets (1e-3) on circular orbits at a = 1 and 1.15,
    G = 1: closer than 2 sqrt(3) mutual Hill radii, so they meet within a few orbits."""
    from systems import NBody
    import rebound
    sim = rebound.Simulation()
    sim.G = 1.0
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, e=0.0, f=0.0)
    sim.add(m=1e-3, a=1.15, e=0.0, f=0.5)
    sim.move_to_com()
    return NBody.from_rebound(sim, names=["star", "planet b", "planet c"])


def _nbody_min_distance(nb, Y):
    X = Y[:, : nb.dim].reshape(len(Y), nb.N, 3)
    return float(np.min(np.linalg.norm(X[:, 1] - X[:, 2], axis=-1)))


def close_encounter(quick: bool = False, t_end: float | None = None, s: int = 6,
                    steps_per_orbit=(200, 2000, 20000)) -> CaseReport:
    """A close encounter of two planets: HBVM (fixed step, :class:`hbvm_md.HBVMIntegrator` when
    available) against REBOUND's IAS15 (reference), WHFast and leapfrog at the same step.

    Facts: per method label, energy error, finished; ``min_distance`` of the reference run and
    the Hill radius.
    """
    t_end = (40.0 if quick else 200.0) if t_end is None else float(t_end)
    nb = encounter_scene()
    y0 = nb.initial_state()
    rep = CaseReport("close-encounter", f"two planets (1e-3 M_star) at a=1, 1.15, T={t_end:g} (G=1, P=2pi)")
    samples = 400

    def run_rebound(integrator, dt=None):
        sim = nb.to_rebound(y0)
        sim.integrator = integrator
        if dt is not None:
            sim.dt = dt
        es, ys, clock = [sim.energy()], [y0], [0.0]
        _sample(sim, nb, t_end, samples, es, ys, clock)
        return Run(integrator, np.linspace(0, t_end, samples + 1), np.array(ys), np.array(es),
                   int(sim.steps_done), int(sim.steps_done), clock[0])

    ref = run_rebound("ias15")
    yref = ref.y[-1]
    rep.facts["min_distance"] = _nbody_min_distance(nb, ref.y)
    rep.facts["hill_radius"] = (1e-3 / 3) ** (1 / 3)
    rep.outcomes.append(_outcome(ref, "adaptive (reference)", yref,
                                 f"min distance {rep.facts['min_distance']:.3g}"))
    rep.facts["ias15"] = ref.max_energy_error
    for spo in steps_per_orbit:
        dt = 2 * np.pi / spo
        setting = f"dt=P/{spo}"
        try:
            hb = _hbvm_nbody_run(nb, y0, dt, t_end, s, samples)
        except StepError as err:
            hb = Run(f"HBVM(k, {s})", np.zeros(1), y0[None], np.zeros(1), 0, 0, 0.0, False,
                     f"{type(err).__name__} at t={err.t:.4g}")
        rep.outcomes.append(_outcome(hb, setting, yref, hb.message or hb.extra.get("how", "")))
        rep.facts[f"hbvm {spo}"] = hb.max_energy_error if hb.finished else float("inf")
        for name in ("whfast", "leapfrog"):
            pr = run_rebound(name, dt)
            rep.outcomes.append(_outcome(pr, setting, yref))
            rep.facts[f"{name} {spo}"] = pr.max_energy_error
    return rep


def _sim_state(sim, nb):
    x = np.array([[p.x, p.y, p.z] for p in sim.particles])
    v = np.array([[p.vx, p.vy, p.vz] for p in sim.particles])
    return nb.state(x, v)


def _sample(sim, nb, t_end, samples, es, ys, clock) -> None:
    """Integrate ``sim`` to t_end in ``samples`` equal pieces, appending H and the state after
    each to ``es`` and ``ys``; ``clock[0]`` adds up the wall time of the integrate calls.  What was
    sampled stays in the lists when a step raises."""
    for tt in np.linspace(0, t_end, samples + 1)[1:]:
        t0 = time.perf_counter()
        try:
            sim.integrate(tt)
        finally:
            clock[0] += time.perf_counter() - t0
        es.append(sim.energy())
        ys.append(_sim_state(sim, nb))


def _hbvm_nbody_run(nb, y0, dt, t_end, s, samples) -> Run:
    """HBVM on the N-body scene through REBOUND (:class:`hbvm_md.HBVMIntegrator`)."""
    from ..rebound import HBVMIntegrator
    sim = nb.to_rebound(y0)
    drv = HBVMIntegrator(sim, s=s, dt=dt)
    label = f"HBVM{(drv.method.k, drv.method.s)}"
    es, ys, clock = [sim.energy()], [y0], [0.0]
    try:
        _sample(sim, nb, t_end, samples, es, ys, clock)
    except StepError as err:
        return Run(label, np.zeros(len(es)), np.array(ys), np.array(es), drv.nsteps, drv.nfev,
                   clock[0], False, f"{type(err).__name__} at t={err.t:.6g}")
    return Run(label, np.linspace(0, t_end, samples + 1), np.array(ys), np.array(es), drv.nsteps,
               drv.nfev, clock[0], extra={"how": "HBVMIntegrator"})


# -- chaotic Henon-Heiles ------------------------------------------------------------------
def henon_heiles_start(energy: float = 0.1666, angle: float = 0.3) -> np.ndarray:
    """A state at the origin with |p| = sqrt(2 energy) at ``angle``: H = energy exactly."""
    v = math.sqrt(2 * energy)
    return np.array([0.0, 0.0, v * math.cos(angle), v * math.sin(angle)])


def chaotic_henon_heiles(quick: bool = False, t_end: float | None = None, energy: float = 0.1666,
                         s: int = 2, h: float = 0.1) -> CaseReport:
    """Henon-Heiles at H = 0.1666, just below the escape energy 1/6 (chaotic).

    HBVM(ceil(3s/2), s) conserves the cubic H exactly; Verlet at the same step and DOP853 at
    rtol 1e-10 are the peers.  The reference is HBVM(8, 6) at h / 10; in a chaotic orbit the
    solution error grows exponentially whatever the method, so it is measured at T.

    Facts: ``hbvm_energy``, ``verlet_energy``, ``dop853_energy``, ``escaped`` (max |q| > 2 in the
    HBVM run).
    """
    t_end = (100.0 if quick else 1000.0) if t_end is None else float(t_end)
    y0 = henon_heiles_start(energy)
    hh = HenonHeiles(y0)
    n = int(round(t_end / h))
    hstep = t_end / n
    rep = CaseReport("chaotic-henon-heiles", f"Henon-Heiles H={energy} (escape 1/6), T={t_end:g}, h={hstep:.3g}")
    nref = n * 10
    ref = integrate(HBVM(8, 6), hh, y0, t_end / nref, nref, sample_every=nref).y[-1]
    m = HBVM.for_polynomial_degree(3, s)
    r = integrate(m, hh, y0, hstep, n, sample_every=sample_interval(n, 500))
    run = from_integration(f"HBVM{(m.k, m.s)}", r)
    rep.outcomes.append(_outcome(run, f"h={hstep:.3g}", ref))
    rep.facts["hbvm_energy"] = run.max_energy_error
    rep.facts["escaped"] = bool(np.max(np.abs(r.y[:, :2])) > 2)
    g = HBVM(s, s)
    rg = integrate(g, hh, y0, hstep, n, sample_every=sample_interval(n, 500))
    rep.outcomes.append(_outcome(from_integration(f"Gauss{(s, s)}", rg), f"h={hstep:.3g}", ref))
    rep.facts["gauss_energy"] = rg.max_energy_error
    vv = stormer_verlet(hh, y0, hstep, n, sample_every=sample_interval(n, 500))
    rep.outcomes.append(_outcome(vv, f"h={hstep:.3g}", ref))
    rep.facts["verlet_energy"] = vv.max_energy_error
    dp = dop853(hh, y0, t_end, rtol=1e-10, samples=500)
    rep.outcomes.append(_outcome(dp, "rtol=1e-10", ref))
    rep.facts["dop853_energy"] = dp.max_energy_error
    return rep


# -- steps too large -----------------------------------------------------------------------
def step_too_large(quick: bool = False, steps_sizes=(0.5, 1.0, 2.0, 3.0, 5.0), steps: int = 50) -> CaseReport:
    """Henon-Heiles near escape with growing h: each run either conserves H to round-off with
    steps that resolve the motion, or raises (ConvergenceError, or UnresolvedStepError from the
    step's own error estimate) with the state untouched; never a silently wrong answer.

    Facts: ``raised`` h -> bool, ``energy`` h -> max rel error (finished runs), ``state_untouched``
    (the Stepper's y, t, nsteps after a failed step equal those before it).
    """
    y0 = henon_heiles_start()
    hh = HenonHeiles(y0)
    m = HBVM.for_polynomial_degree(3, 2)
    rep = CaseReport("step-too-large", f"Henon-Heiles H=0.1666, {m!r}, {steps} steps per h, solver auto")
    rep.facts.update(raised={}, energy={}, state_untouched=True)
    for h in steps_sizes:
        st = Stepper(m, hh, y0)
        t0 = time.perf_counter()
        Hs = [hh.energy(y0)]
        before = (st.y.copy(), st.t, st.nsteps)
        try:
            for _ in range(steps):
                before = (st.y.copy(), st.t, st.nsteps)
                st.step(h)
                Hs.append(hh.energy(st.y))
            err = float(np.max(np.abs(np.array(Hs) - Hs[0])) / abs(Hs[0]))
            rep.outcomes.append(Outcome(repr(m), f"h={h:g}", True, st.nsteps, err, float("nan"),
                                        time.perf_counter() - t0, f"{st.newton_steps} Newton steps"))
            rep.facts["raised"][h] = False
            rep.facts["energy"][h] = err
        except StepError as e:
            same = np.array_equal(before[0], st.y) and before[1] == st.t and before[2] == st.nsteps
            rep.facts["state_untouched"] = rep.facts["state_untouched"] and same
            rep.outcomes.append(Outcome(repr(m), f"h={h:g}", False, st.nsteps, float("nan"), float("nan"),
                                        time.perf_counter() - t0,
                                        f"{type(e).__name__} ({e.solver}, t={e.t:.3g})"))
            rep.facts["raised"][h] = True
    return rep


CASES = {
    "stiff-fpu": stiff_fpu,
    "eccentric-kepler": eccentric_kepler,
    "close-encounter": close_encounter,
    "chaotic-henon-heiles": chaotic_henon_heiles,
    "step-too-large": step_too_large,
}


def run_all(quick: bool = False, names=None, progress=None) -> list[CaseReport]:
    """Run the named cases (default all) and return their reports."""
    from .names import scene_key
    names = list(CASES) if names is None else [scene_key(n) for n in names]
    bad = [n for n in names if n not in CASES]
    if bad:
        raise ValueError(f"unknown hard case(s) {bad}; choose from {list(CASES)}")
    out = []
    for n in names:
        out.append(CASES[n](quick=quick))
        if progress is not None:
            progress(n)
    return out
