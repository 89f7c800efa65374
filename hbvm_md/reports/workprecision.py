"""Work-precision diagrams: error against wall time for HBVM and its peers, per scene.

Each scene sweeps step sizes (tolerances for adaptive peers) and measures, for every run, the
largest relative energy error, the largest relative change of the angular momentum where it is
an invariant (Kepler, the outer solar system, the free MD cluster; ``nan`` on FPU and
Henon-Heiles; measured as :mod:`hbvm_md.reports.invariants` defines, from the same samples for
every method, never inside a timed region) and the final position error against a reference
run of higher accuracy (``solution_error`` = max |q - q_ref| / max |q_ref|).  :func:`bench`
writes a CSV, one PNG per scene and a markdown table.

Scenes (``SCENES``):

* ``kepler`` - Kepler e = 0.6 (HLW I.2.3); reference: the exact solution.  Peers: DOP853 and
  REBOUND's WHFast, SABA(10,6,4), leapfrog, IAS15 (a planetary scene).
* ``fpu`` - stiff FPU chain, omega = 50; peers: Velocity Verlet, DOP853.
* ``henon-heiles`` - Henon-Heiles from q = p = (0.18, 0.18); peers: Verlet, DOP853.
* ``outer-solar-system`` - HLW's outer solar system (:func:`systems.outer_solar_system`);
  HBVM on :class:`systems.NBody`, peers through REBOUND, DOP853 and (when installed) heyoka;
  reference: IAS15.
* ``md-cluster`` - the polynomial-pair cluster of :func:`hbvm_md.compare_md.default_cluster`
  through ASE (:class:`hbvm_md.HBVMDynamics` against ASE's VelocityVerlet); reference: HBVM at
  a quarter of the smallest step.

HBVM(k, s) runs for several s with k chosen by :func:`integrators.kchoice.choose_k` over one
period of the scene's fastest motion; Gauss-Legendre is HBVM(s, s).
"""
from __future__ import annotations

import csv
import logging
import math
import time
from pathlib import Path

import numpy as np

from integrators import HBVM, StepError, integrate
from integrators.kchoice import choose_k, period_steps
from systems import FPU, HenonHeiles, Kepler

from .autok import k_cost
from .hard_cases import kepler_exact
from .invariants import atoms_angular_momentum, relative_change
from .names import scene_key
from .peers import dop853, rebound_kepler, sample_interval, stormer_verlet
from .progress import progress

FIELDS = ["scene", "method", "family", "param", "steps", "nfev", "wall_time_s",
          "max_rel_energy_error", "max_rel_angular_momentum_error", "solution_error", "finished", "note"]


def _pos_error(q, q_ref) -> float:
    q, q_ref = np.asarray(q, float), np.asarray(q_ref, float)
    return float(np.max(np.abs(q - q_ref)) / np.max(np.abs(q_ref)))


def _row(scene, method, family, param, steps, nfev, wall, energy_err, sol_err, finished=True, note="",
         dL=float("nan")):
    return dict(scene=scene, method=method, family=family, param=param, steps=int(steps), nfev=int(nfev),
                wall_time_s=float(wall), max_rel_energy_error=float(energy_err),
                max_rel_angular_momentum_error=float(dL),
                solution_error=float(sol_err), finished=bool(finished), note=note)


def _dL(system, Y) -> float:
    """Max relative change of the angular momentum over the samples Y (n, 2m) of a run, by the
    model's own ``angular_momentum`` (Kepler, NBody); nan for a model without one (the
    invariant does not exist there)."""
    if not hasattr(system, "angular_momentum"):
        return float("nan")
    Y = np.asarray(Y, dtype=float)
    return relative_change(system.angular_momentum(Y), system.angular_momentum_scale(Y))


def _rel_energy(E) -> float:
    E = np.asarray(E, dtype=float)
    err = np.abs(E - E[0]) / (abs(E[0]) if E[0] != 0 else 1.0)
    return float(np.max(err)) if np.all(np.isfinite(err)) else float("inf")


# -- generic runners on a core system ------------------------------------------------------
def _hbvm_rows(scene, system, y0, T, ns, svals, q_ref, gauss=(), k_info=None, bar=None, period=math.inf):
    """HBVM(k, s) with k chosen on the scene (over one ``period`` of its fastest motion,
    :func:`integrators.kchoice.period_steps`; polynomial scenes run nothing) and Gauss."""
    rows = []
    d = system.dim
    for s in svals:
        for n in ns:
            h = T / n
            # when even the reference k fails on the test steps, choose_k returns it and the
            # run below reports its own failure
            kc = choose_k(system, y0, s, h, period_steps(period, h))
            rows.append(_core_run(scene, f"HBVM s={s} (auto k)", "HBVM", HBVM(kc.k, s), system, y0, h, n, q_ref, d,
                                  note=f"k={kc.k}"))
            if k_info is not None and n == ns[len(ns) // 2]:
                k_info.append(dict(scene=scene, s=s, h=h, reason=kc.reason, trials=kc.trial_errors,
                                   **k_cost(s, kc.k, system, y0, h)))
            if bar is not None:
                bar.update(1)
    for s in gauss:
        for n in ns:
            rows.append(_core_run(scene, f"Gauss({s})", "Gauss", HBVM(s, s), system, y0, T / n, n, q_ref, d))
    return rows


def _core_run(scene, label, family, method, system, y0, h, n, q_ref, d, note=""):
    try:
        # the diagram measures each run's error against its reference, the coarse steps' too:
        # the step's own error check (which refuses steps that miss a thousandth of their
        # motion, e.g. Gauss(2) at h = P/25) and the run's drift (a Gauss run whose energy
        # stands 1e-3 of its kinetic scale off its start, integrators.core.DRIFT_BOUND) would leave
        # those points out
        r = integrate(method, system, y0, h, n, sample_every=sample_interval(n, 200),
                      error_bound=None, energy_tol=None)
    except StepError as err:
        return _row(scene, label, family, f"h={h:.4g}", 0, 0, 0, np.inf, np.inf, False, f"ConvergenceError: {err.solver}",
                    dL=np.inf if hasattr(system, "angular_momentum") else np.nan)
    return _row(scene, label, family, f"h={h:.4g}", r.steps, r.nfev, r.wall_time, r.max_energy_error,
                _pos_error(r.y[-1, :d], q_ref), True, note or f"k={method.k}", dL=_dL(system, r.y))


def _verlet_rows(scene, system, y0, T, ns, q_ref):
    rows = []
    for n in ns:
        vv = stormer_verlet(system, y0, T / n, n, sample_every=sample_interval(n, 200))
        sol = _pos_error(vv.y[-1, : system.dim], q_ref) if vv.finished else np.inf
        rows.append(_row(scene, "VelocityVerlet", "Verlet", f"h={T / n:.4g}", vv.steps, vv.nfev, vv.wall_time,
                         vv.max_energy_error if vv.finished else np.inf, sol, vv.finished, vv.message,
                         dL=_dL(system, vv.y) if vv.finished else np.inf))
    return rows


def _dop_rows(scene, system, y0, T, rtols, q_ref):
    rows = []
    for rtol in rtols:
        r = dop853(system, y0, T, rtol=rtol, samples=200)
        sol = _pos_error(r.y[-1, : system.dim], q_ref) if r.finished else np.inf
        rows.append(_row(scene, "DOP853", "DOP853", f"rtol={rtol:.0e}", r.steps, r.nfev, r.wall_time,
                         r.max_energy_error, sol, r.finished, r.message, dL=_dL(system, r.y)))
    return rows


# -- scenes --------------------------------------------------------------------------------
def scene_kepler(quick=False, k_info=None, bar=None):
    kep = Kepler(0.6)
    y0 = kep.initial_state()
    periods = 4 if quick else 100
    T = 2 * np.pi * periods
    q_ref = kepler_exact(0.6, T)[:2]
    per = (25, 100) if quick else (25, 50, 100, 200, 400)
    ns = [periods * p for p in per]
    rows = _hbvm_rows("kepler", kep, y0, T, ns, (2, 4) if quick else (2, 3, 4, 6), q_ref,
                      gauss=(2, 4) if quick else (2, 4, 6), k_info=k_info, bar=bar, period=2 * np.pi)
    rows += _dop_rows("kepler", kep, y0, T, (1e-6, 1e-10) if quick else (1e-6, 1e-8, 1e-10, 1e-12, 1e-13), q_ref)
    for name, label in (("whfast", "WHFast"), ("saba10_6_4", "SABA(10,6,4)"), ("leapfrog", "leapfrog")):
        for n in ns:
            r = _rebound_kepler_fixed(0.6, T, name, n)
            rows.append(_row("kepler", label, "REBOUND", f"h=T/{n}", r.steps, r.nfev, r.wall_time,
                             r.max_energy_error, _pos_error(r.y[-1, :2], q_ref), dL=_dL(kep, r.y)))
    for eps in ((1e-6,) if quick else (1e-3, 1e-5, 1e-7, 1e-9)):
        r = rebound_kepler(0.6, T, "ias15", epsilon=eps, samples=100)
        rows.append(_row("kepler", "IAS15", "REBOUND", f"eps={eps:.0e}", r.steps, r.nfev, r.wall_time,
                         r.max_energy_error, _pos_error(r.y[-1, :2], q_ref), dL=_dL(kep, r.y)))
    return rows, f"Kepler e=0.6, {periods} periods (reference: exact solution)"


def _rebound_kepler_fixed(e, T, name, n, samples=100):
    from .peers import Run, kepler_simulation
    sim = kepler_simulation(e, name, T / n)
    ys, wall = [], 0.0
    pl = sim.particles[1]
    ys.append([pl.x, pl.y, pl.vx, pl.vy])
    chunks = np.diff(np.linspace(0, n, samples + 1).round().astype(int))
    for c in chunks:
        t0 = time.perf_counter()
        sim.steps(int(c))
        wall += time.perf_counter() - t0
        pl = sim.particles[1]
        ys.append([pl.x, pl.y, pl.vx, pl.vy])
    Y = np.array(ys)
    E = 0.5 * (Y[:, 2] ** 2 + Y[:, 3] ** 2) - 1.0 / np.hypot(Y[:, 0], Y[:, 1])
    return Run(name, np.linspace(0, T, samples + 1), Y, E, n, n, wall)


def scene_fpu(quick=False, k_info=None, bar=None):
    fpu = FPU(3, 50.0)
    y0 = fpu.initial_state()
    T = 2.0 if quick else 20.0
    nref = int(T * 50 / 0.01)
    q_ref = integrate(HBVM(8, 4), fpu, y0, T / nref, nref, sample_every=nref).y[-1, :6]
    hws = (1.0, 0.25) if quick else (2.0, 1.0, 0.5, 0.25, 0.1, 0.05)
    ns = [int(round(T * 50 / hw)) for hw in hws]
    rows = _hbvm_rows("fpu", fpu, y0, T, ns, (2, 4) if quick else (1, 2, 3, 4), q_ref,
                      gauss=(2,) if quick else (2, 4), k_info=k_info, bar=bar)
    vns = ns + ([] if quick else [int(round(T * 50 / hw)) for hw in (0.02, 0.01, 0.005)])
    rows += _verlet_rows("fpu", fpu, y0, T, vns, q_ref)
    rows += _dop_rows("fpu", fpu, y0, T, (1e-6, 1e-10) if quick else (1e-6, 1e-8, 1e-10, 1e-12), q_ref)
    return rows, f"stiff FPU m=3, omega=50, T={T:g} (reference: HBVM(8,4), h*omega=0.01)"


def scene_henon_heiles(quick=False, k_info=None, bar=None):
    hh = HenonHeiles()
    y0 = hh.initial_state()
    T = 20.0 if quick else 200.0
    nref = int(T / 0.005)
    q_ref = integrate(HBVM(9, 6), hh, y0, T / nref, nref, sample_every=nref).y[-1, :2]
    hs = (0.4, 0.1) if quick else (0.8, 0.4, 0.2, 0.1, 0.05, 0.025)
    ns = [int(round(T / h)) for h in hs]
    rows = _hbvm_rows("henon-heiles", hh, y0, T, ns, (2, 4) if quick else (1, 2, 3, 4), q_ref,
                      gauss=(2,) if quick else (2, 4), k_info=k_info, bar=bar)
    rows += _verlet_rows("henon-heiles", hh, y0, T, ns + ([] if quick else [int(T / 0.01), int(T / 0.005)]), q_ref)
    rows += _dop_rows("henon-heiles", hh, y0, T, (1e-6, 1e-10) if quick else (1e-6, 1e-8, 1e-10, 1e-12), q_ref)
    return rows, f"Henon-Heiles q=p=(0.18,0.18), T={T:g} (reference: HBVM(9,6), h=0.005)"


def _sim_positions(sim):
    return np.array([[p.x, p.y, p.z] for p in sim.particles]).reshape(-1)


def scene_outer_solar_system(quick=False, k_info=None, bar=None):
    from systems import outer_solar_system
    nb = outer_solar_system()
    y0 = nb.initial_state()
    PJ = 4332.6
    T = 2e4 if quick else 1e5
    sim = nb.to_rebound(y0)
    sim.integrator = "ias15"
    sim.integrate(T)
    q_ref = _sim_positions(sim)
    per = (20, 100) if quick else (10, 20, 50, 100, 200)
    ns = [int(round(T / PJ * p)) for p in per]
    rows = _hbvm_rows("outer-solar-system", nb, y0, T, ns, (2, 4) if quick else (2, 3, 4, 6), q_ref,
                      gauss=(4,) if quick else (2, 4, 6), k_info=k_info, bar=bar, period=PJ)
    for name, label in (("whfast", "WHFast"), ("saba10_6_4", "SABA(10,6,4)"), ("leapfrog", "leapfrog")):
        lns = ns if name != "leapfrog" else [n * 10 for n in ns]
        for n in lns:
            rows.append(_rebound_nbody("outer-solar-system", label, nb, y0, T, name, n=n, q_ref=q_ref))
    for eps in ((1e-5,) if quick else (1e-3, 1e-5, 1e-7)):
        rows.append(_rebound_nbody("outer-solar-system", "IAS15", nb, y0, T, "ias15", eps=eps, q_ref=q_ref))
    rows += _dop_rows("outer-solar-system", nb, y0, T, (1e-8,) if quick else (1e-6, 1e-8, 1e-10, 1e-12), q_ref)
    rows += _heyoka_rows("outer-solar-system", nb, y0, T, (1e-12, None) if quick else (1e-9, 1e-12, 1e-14, None), q_ref)
    return rows, f"outer solar system (HLW), T={T:g} days (reference: IAS15, default epsilon)"


def _heyoka_rows(scene, nb, y0, T, tols, q_ref, samples=100):
    """heyoka (an optional peer) at each tolerance (None: machine epsilon); no rows, and a
    note in the log, when heyoka is not installed.  Compile time is outside the wall time."""
    from .peers import HEYOKA_MISSING, import_heyoka
    from .rebound_comparison import _run_heyoka, heyoka_solver
    try:
        import_heyoka()
    except ImportError:
        logging.getLogger(__name__).warning("scene %s: %s", scene, HEYOKA_MISSING)
        return []
    rows = []
    for tol in tols:
        solver = heyoka_solver(nb.to_rebound(y0), tol=tol)
        r, _, x, _ = _run_heyoka(lambda: nb.to_rebound(y0), "heyoka", solver, T, samples)
        rows.append(_row(scene, "heyoka", "heyoka", f"tol={solver.tol:.0e}", r["steps"], 0, r["wall_time_s"],
                         r["max_rel_energy_error"], _pos_error(x.reshape(-1), q_ref),
                         note=f"Taylor order {solver.order} (nfev: not applicable); compile {solver.compile_time:.2f} s not timed",
                         dL=r["max_rel_angular_momentum_error"]))
    return rows


def _rebound_nbody(scene, label, nb, y0, T, name, n=None, eps=None, q_ref=None, samples=100):
    """One REBOUND run of the N-body scene: ``sim.steps`` (fixed step) or ``sim.integrate``
    (IAS15) timed, the energy and the state at each output read between the timed calls."""
    from .rebound_comparison import _state, angular_momentum_change
    sim = nb.to_rebound(y0)
    sim.integrator = name
    es = [sim.energy()]
    xv = [_state(sim)]
    wall = 0.0
    if n is not None:
        sim.dt = T / n
        chunks = np.diff(np.linspace(0, n, samples + 1).round().astype(int))
        for c in chunks:
            t0 = time.perf_counter()
            sim.steps(int(c))
            wall += time.perf_counter() - t0
            es.append(sim.energy())
            xv.append(_state(sim))
        param = f"h=T/{n}"
    else:
        sim.integrator.epsilon = eps
        for tt in np.linspace(0, T, samples + 1)[1:]:
            t0 = time.perf_counter()
            sim.integrate(tt)
            wall += time.perf_counter() - t0
            es.append(sim.energy())
            xv.append(_state(sim))
        param = f"eps={eps:.0e}"
    return _row(scene, label, "REBOUND", param, sim.steps_done, sim.steps_done, wall, _rel_energy(es),
                _pos_error(_sim_positions(sim), q_ref), dL=float(np.max(angular_momentum_change(nb, np.array(xv)))))


def scene_md_cluster(quick=False, k_info=None, bar=None):
    """The ASE cluster at 300 K: HBVMDynamics (s = 1, 2, 3 with the ASE helper's own k rule) and
    VelocityVerlet over the same time, positions against HBVM(.., 3) at a quarter step."""
    from ase.md.verlet import VelocityVerlet
    from ase import units

    from ..ase import HBVMDynamics
    from .md_comparison import default_cluster
    from ase.md.velocitydistribution import MaxwellBoltzmannDistribution, Stationary
    atoms0, calc = default_cluster(20 if quick else 38)
    # 300 K, fixed seed: every method starts from the same state
    MaxwellBoltzmannDistribution(atoms0, temperature_K=300.0, rng=np.random.default_rng(0))
    Stationary(atoms0)
    T_fs = 96.0 if quick else 480.0          # a multiple of every step below
    dts = (4.0, 2.0) if quick else (8.0, 4.0, 2.0, 1.0)

    def fresh():
        a = atoms0.copy()
        a.calc = calc
        return a

    def run(make_dyn, dt):
        """(atoms, steps, wall, energies, dL): the energy, positions and momenta read between
        the timed ``dyn.run`` calls; dL the max relative change of the angular momentum about
        the centre of mass (:func:`hbvm_md.reports.invariants.atoms_angular_momentum`)."""
        a = fresh()
        dyn = make_dyn(a, dt * units.fs)
        n = int(round(T_fs / dt))
        es = [a.get_total_energy()]
        xs, ps = [a.get_positions()], [a.get_momenta()]
        every = sample_interval(n, 100)
        wall = 0.0
        for _ in range(n // every):
            t0 = time.perf_counter()
            dyn.run(every)
            wall += time.perf_counter() - t0
            es.append(a.get_total_energy())
            xs.append(a.get_positions())
            ps.append(a.get_momenta())
        L, scale = atoms_angular_momentum(np.array(xs), np.array(ps), a.get_masses())
        return a, n, wall, np.array(es), relative_change(L, scale)

    ref_atoms, *_ = run(lambda a, dt: HBVMDynamics(a, dt, s=3), min(dts) / 4)
    q_ref = ref_atoms.get_positions().reshape(-1)
    rows = []
    for s in ((1, 2) if quick else (1, 2, 3)):
        for dt in dts:
            try:
                # (each point's error measured against the reference: the checks that
                # refuse coarse steps, the step's own and the run's drift, are off)
                a, n, wall, es, dL = run(lambda a, dt_: HBVMDynamics(a, dt_, s=s, error_bound=None,
                                                                   energy_tol=None), dt)
            except StepError:
                rows.append(_row("md-cluster", f"HBVMDynamics(s={s})", "HBVM", f"dt={dt}fs", 0, 0, 0, np.inf,
                                 np.inf, False, "ConvergenceError", dL=np.inf))
                continue
            rows.append(_row("md-cluster", f"HBVMDynamics(s={s})", "HBVM", f"dt={dt}fs", n, 0, wall,
                             _rel_energy(es), _pos_error(a.get_positions().reshape(-1), q_ref), dL=dL))
    for dt in dts + ((0.5, 0.25) if not quick else (1.0,)):
        a, n, wall, es, dL = run(lambda a, dt_: VelocityVerlet(a, timestep=dt_), dt)
        rows.append(_row("md-cluster", "VelocityVerlet (ASE)", "Verlet", f"dt={dt}fs", n, n, wall,
                         _rel_energy(es), _pos_error(a.get_positions().reshape(-1), q_ref), dL=dL))
    return rows, f"polynomial-pair cluster through ASE, {T_fs:g} fs (reference: HBVMDynamics s=3, dt/4)"


SCENES = {
    "kepler": scene_kepler,
    "fpu": scene_fpu,
    "henon-heiles": scene_henon_heiles,
    "outer-solar-system": scene_outer_solar_system,
    "md-cluster": scene_md_cluster,
}


def sweep(scene: str, quick: bool = False, k_info: list | None = None, bar=None) -> tuple[list, str]:
    """Run one scene's sweep; returns (rows, title).  Rows are dicts with keys ``FIELDS``."""
    key = scene_key(scene)
    if key not in SCENES:
        raise ValueError(f"unknown scene {scene!r}; choose from {list(SCENES)} ('_' or '-' alike)")
    return SCENES[key](quick=quick, k_info=k_info, bar=bar)


def markdown(rows: list, titles: dict, k_info: list) -> str:
    """The bench report as markdown: one table per scene, then the k choices and their cost."""
    out = ["# Work-precision benchmark", ""]
    for scene, title in titles.items():
        out += [f"## {scene}: {title}", "",
                "| method | param | steps | wall s | max rel dE | max rel dL | solution error | note |",
                "|---|---|---:|---:|---:|---:|---:|---|"]
        for r in rows:
            if r["scene"] != scene:
                continue
            fin = "" if r["finished"] else "NOT FINISHED "
            dL = r["max_rel_angular_momentum_error"]
            out.append(f"| {r['method']} | {r['param']} | {r['steps']} | {r['wall_time_s']:.3g} | "
                       f"{r['max_rel_energy_error']:.2e} | {'-' if np.isnan(dL) else f'{dL:.2e}'} | "
                       f"{r['solution_error']:.2e} | {fin}{r['note']} |")
        out.append("")
    if k_info:
        out += ["## k chosen and what a larger k would have cost", "",
                "| scene | s | h | k | why | us/step at k | k+4 | us/step at k+4 | ratio |",
                "|---|---:|---:|---:|---|---:|---:|---:|---:|"]
        for ki in k_info:
            out.append(f"| {ki['scene']} | {ki['s']} | {ki['h']:.4g} | {ki['k']} | {ki['reason']} | "
                       f"{ki['us_per_step']:.3g} | {ki['k_larger']} | {ki['us_per_step_larger']:.3g} | "
                       f"{ki['ratio']:.2f} |")
        out.append("")
    return "\n".join(out)


def bench(outdir, scenes=None, quick: bool = False, log=print) -> dict:
    """Run the sweeps and write ``workprecision.csv``, ``workprecision.md`` and
    ``wp_<scene>.png`` into ``outdir``.  Returns {"csv", "markdown", "pngs", "rows", "skipped"}.

    A scene whose host module is missing (ImportError) is skipped and listed in ``skipped``.
    """
    from .plots import work_precision_plot
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    scenes = list(SCENES) if scenes is None else [scene_key(s) for s in scenes]
    for s in scenes:
        if s not in SCENES:
            raise ValueError(f"unknown scene {s!r}; choose from {list(SCENES)}")
    rows, titles, k_info, pngs, skipped = [], {}, [], [], {}
    bar = progress(total=len(scenes), desc="bench")
    for sc in scenes:
        t0 = time.perf_counter()
        try:
            r, title = sweep(sc, quick=quick, k_info=k_info)
        except ImportError as err:
            skipped[sc] = str(err)
            log(f"skipped scene {sc}: {err}")
            bar.update(1)
            continue
        rows += r
        titles[sc] = title
        pngs.append(work_precision_plot(r, outdir / f"wp_{sc}.png", title))
        log(f"scene {sc}: {len(r)} runs in {time.perf_counter() - t0:.1f} s")
        bar.update(1)
    bar.close()
    csv_path = outdir / "workprecision.csv"
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow(r)
    md_path = outdir / "workprecision.md"
    md_path.write_text(markdown(rows, titles, k_info))
    return {"csv": csv_path, "markdown": md_path, "pngs": pngs, "rows": rows, "skipped": skipped}
