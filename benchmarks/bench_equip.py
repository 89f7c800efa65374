"""Benchmark (not a test): EQUIP(k, s) against HBVM(k, s), both invariants and the time a step.

Three scenes, both methods run in turn from each perturbed start (the state scaled by
1 + 1e-3 r, r standard normal; start 0 unperturbed) so that load on the machine hits both alike;
medians over the starts:

* Kepler e = 0.6, h = 2 pi / 100, 1e4 steps: EQUIP(6, 2) against HBVM(6, 2), EQUIP(12, 4)
  against HBVM(12, 4) (the engine's compiled path);
* HLW's outer solar system (:func:`systems.outer_solar_system`), h = 500 days, 1e6 days:
  EQUIP(9, 8) against HBVM(9, 8);
* a free 13-atom quartic cluster through ASE (:class:`hbvm_md.HBVMDynamics`, method="hbvm"
  or "equip", k and s the defaults), 5 fs, 200 steps, spun about its centre of mass so that
  its angular momentum has a scale.

Columns: the largest relative change of the energy and of the total angular momentum over
the samples (every 50 steps; every step for ASE), and the time a step (the integration loop's
wall time, or ``dyn.run``'s for ASE); the ratio is EQUIP's median time over HBVM's.

Run:  python benchmarks/bench_equip.py [--starts 5] [--quick]

``--rebound``: instead, EQUIP through REBOUND (``HBVMIntegrator(sim, method="equip", ...)``)
against IAS15 and HBVM on the outer solar system, HLW's (:func:`systems.outer_solar_system`,
days) and REBOUND's own (``sim.add("outer solar system")``, G = 1, time in years / 2 pi),
over 1e5 and 1e6 days, as :mod:`benchmarks.bench_rebound` measures: 200 output times
``sim.integrate(t_i)``, the attach (which chooses k) and the integrate calls timed, energy and
angular momentum (``sim.energy()``, ``sim.angular_momentum()``) read outside the timing, the
largest relative changes over the outputs; medians over ``--starts`` starts (planet positions
scaled by 1 + r 1e-13), every setting once per start in turn.  The EQUIP settings: its
defaults (HBVMIntegrator's for method="equip": adaptive, s = 8, epsilon = 1e-17, k =
adaptive_k; HBVM beside it at its own, s = 6, epsilon = 3e-15), HBVM's defaults (s = 6,
epsilon = 3e-15), adaptive with a smaller epsilon, and fixed steps (HLW's days, scaled by Jupiter's period on REBOUND's
scene), each beside HBVM at the same setting (the cost ratio).  Writes
benchmarks/results/equip_rebound.md.

    python benchmarks/bench_equip.py --rebound [--starts 9]
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from integrators import EQUIP, HBVM, integrate
from systems import outer_solar_system
from systems.kepler import Kepler


def _starts(y0, n, seed=1):
    rng = np.random.default_rng(seed)
    return [y0] + [y0 * (1 + 1e-3 * rng.standard_normal(y0.shape)) for _ in range(n - 1)]


def _engine(method, system, y0, h, steps, momentum):
    integrate(method, system, y0, h, 2, sample_every=1)          # compile outside the timing
    r = integrate(method, system, y0, h, steps, sample_every=50)
    L = np.array([momentum(y) for y in r.y]).reshape(len(r.y), -1)
    dL = np.max(np.linalg.norm(L - L[0], axis=1)) / np.linalg.norm(L[0])
    return r.max_energy_error, dL, r.wall_time / steps


def _ase(method, seed, steps):
    from ase import units

    from hbvm_md import HBVMDynamics
    from hbvm_md.reports.md_comparison import default_cluster, maxwell_boltzmann
    atoms, _ = default_cluster(13)
    maxwell_boltzmann(atoms, 300.0, seed)
    p = atoms.get_momenta()
    r = atoms.get_positions() - atoms.get_center_of_mass()
    atoms.set_momenta(p + atoms.get_masses()[:, None] * np.cross([0.0, 0.0, 0.02], r))
    dyn = HBVMDynamics(atoms, 5 * units.fs, method=method)
    E, L = [], []

    def observe():
        E.append(atoms.get_potential_energy() + atoms.get_kinetic_energy())
        L.append(np.cross(atoms.get_positions(), atoms.get_momenta()).sum(axis=0))
    dyn.run(2)
    dyn.attach(observe)
    t = time.perf_counter()
    dyn.run(steps)
    dt = (time.perf_counter() - t) / steps
    E, L = np.array(E), np.array(L)
    return (np.max(np.abs(E - E[0])) / abs(E[0]),
            np.max(np.linalg.norm(L - L[0], axis=1)) / np.linalg.norm(L[0]), dt, dyn.method)


# -- through REBOUND ------------------------------------------------------------------------
HLW_PJ = 4332.6                      # Jupiter's period in HLW's days (dt below scale with it)
#: (label, method, s or None (the default), dt in HLW days or None (adaptive), epsilon or
#: None (the default)); "defaults": each method at its own (HBVM s = 6, epsilon 3e-15; EQUIP
#: s = 8, epsilon 1e-17: issue 58's controller, about the steps of the earlier 1e-3 and 1e-4)
REBOUND_VARIANTS = (
    ("defaults", "equip", None, None, None),
    ("adaptive, s 6, epsilon 3e-15", "equip", 6, None, 3e-15),
    ("adaptive, epsilon 1e-17", "equip", 6, None, 1e-17),
    ("adaptive, s 8, epsilon 1e-17", "equip", 8, None, 1e-17),
    ("fixed", "equip", 6, 150.0, None),
    ("fixed", "equip", 6, 200.0, None),
    ("fixed", "equip", 6, 250.0, None),
    ("fixed", "equip", 8, 350.0, None),
    ("fixed", "equip", 8, 400.0, None),
)


def _rebound_scenes():
    import rebound

    nb = outer_solar_system()

    def own():
        sim = rebound.Simulation()
        sim.add("outer solar system")
        return sim
    days = 2 * np.pi / 365.25        # REBOUND's scene: time unit = 1 year / 2 pi
    return (("outer solar system (HLW), 1e5 days", nb.to_rebound, 1e5, 1.0),
            ("outer solar system (HLW), 1e6 days", nb.to_rebound, 1e6, 1.0),
            ('REBOUND\'s sim.add("outer solar system"), 1e5 days', own, 1e5 * days, None),
            ('REBOUND\'s sim.add("outer solar system"), 1e6 days', own, 1e6 * days, None))


def _rebound_run(make, r, setting, t_end, n=200):
    """(energy error, angular-momentum error, wall time, steps) of one run from start r."""
    from hbvm_md import HBVMIntegrator
    sim = make()
    for p in sim.particles[1:]:
        p.x, p.y, p.z = p.x * (1 + r * 1e-13), p.y * (1 + r * 1e-13), p.z * (1 + r * 1e-13)
    E0, L0 = sim.energy(), np.array(sim.angular_momentum())
    t = time.perf_counter()
    if setting is None:
        sim.integrator = "ias15"
    else:
        HBVMIntegrator(sim, **setting)
    wall = time.perf_counter() - t
    dE = dL = 0.0
    for ti in np.linspace(0.0, t_end, n + 1)[1:]:
        t = time.perf_counter()
        sim.integrate(ti)
        wall += time.perf_counter() - t
        dE = max(dE, abs(sim.energy() / E0 - 1))
        dL = max(dL, np.linalg.norm(np.array(sim.angular_momentum()) - L0) / np.linalg.norm(L0))
    return dE, dL, wall, sim.steps_done


def rebound_section(starts: int) -> list[str]:
    """The tables of ``--rebound`` (markdown lines)."""
    from hbvm_md.reports.machine import machine
    half_ulp = 0.5 * np.finfo(float).eps
    out = ["# EQUIP through REBOUND against IAS15 and HBVM (outer solar system)", "",
           f"{machine()}. Generated by `python benchmarks/bench_equip.py --rebound --starts "
           f"{starts}` on {time.strftime('%Y-%m-%d')}. 200 output times `sim.integrate(t_i)`; "
           "wall: the attach (`HBVMIntegrator(sim, method=..., ...)`, which chooses k) and the "
           "integrate calls; energy and angular momentum: largest relative change over the "
           "outputs (`sim.energy()`, `sim.angular_momentum()`, not timed). Medians over "
           f"{starts} starts (planet positions scaled by 1 + r 1e-13), every setting once per "
           "start in turn. Load average at the start (1, 5, 15 min): "
           + ", ".join(f"{x:.1f}" for x in os.getloadavg()) + " on "
           f"{os.cpu_count()} cores shared with other work: ratios are taken within one run. "
           "EQUIP / HBVM: EQUIP's time over HBVM's at the same setting. Bars: *strict*, energy "
           "and angular momentum at or below IAS15's median (to half an ulp); *1e-14*, both at "
           "or below max(IAS15's, 1e-14).", ""]
    _rebound_run(outer_solar_system().to_rebound, 0, dict(method="equip", s=6, dt=250.0), 1e3,
                 n=2)                                  # numba's cache, once, outside the timing
    for title, make, t_end, scale in _rebound_scenes():
        t_scene = time.perf_counter()
        sim0 = make()
        pj = sim0.particles[1].P if scale is None else HLW_PJ
        settings = {"ias15": None}
        for label, method, s, dt, eps in REBOUND_VARIANTS:
            for m in (method, "hbvm"):
                kw = dict(method=m)
                if s is not None:
                    kw["s"] = s
                if dt is not None:
                    kw["dt"] = dt * pj / HLW_PJ
                if eps is not None:
                    kw["epsilon"] = eps
                settings[(label, m, s, dt, eps)] = kw
        runs = {key: [] for key in settings}
        for r in range(starts):
            for key, kw in settings.items():
                runs[key].append(_rebound_run(make, r, kw, t_end))
        med = {key: np.median(np.array(v), axis=0) for key, v in runs.items()}
        ias = med["ias15"]
        out += [f"## {title}", "",
                "| method | setting | steps | energy | ang. mom. | wall (s) | / IAS15 | EQUIP / HBVM |",
                "|---|---|---|---|---|---|---|---|",
                f"| IAS15 | adaptive (REBOUND's default epsilon) | {ias[3]:.0f} | {ias[0]:.2e} | "
                f"{ias[1]:.2e} | {ias[2]:.4f} | 1.00 | |"]
        rows = []
        for key in settings:
            if key == "ias15":
                continue
            label, m, s, dt, eps = key
            e, l, w, steps = med[key]
            k, s_, e_ = _k_of(make, settings[key])
            step = ("adaptive, epsilon " + f"{e_:g}" if dt is None
                    else f"dt = {dt * pj / HLW_PJ:.4g}" + ("" if scale else f" (HLW's {dt:g} d)"))
            name = f"{'EQUIP' if m == 'equip' else 'HBVM'}({k}, {s_})"
            ratio = (f"{w / med[(label, 'hbvm', s, dt, eps)][2]:.2f}" if m == "equip" else "")
            rows.append((name, label, step, steps, e, l, w, m))
            out.append(f"| {name} | {step}{' (defaults)' if label == 'defaults' else ''} | "
                       f"{steps:.0f} | {e:.2e} | {l:.2e} | {w:.4f} | {w / ias[2]:.2f} | {ratio} |")
        eq = [r for r in rows if r[7] == "equip"]
        strict = [r for r in eq if r[4] <= ias[0] + half_ulp and r[5] <= ias[1] + half_ulp]
        loose = [r for r in eq if r[4] <= max(ias[0], 1e-14) and r[5] <= max(ias[1], 1e-14)]
        out.append("")
        for bar, ok in (("strict", strict), ("1e-14", loose)):
            if ok:
                b = min(ok, key=lambda r: r[6])
                out.append(f"Fastest EQUIP within the {bar} bar: {b[0]}, {b[2]}: energy {b[4]:.2e}, "
                           f"angular momentum {b[5]:.2e} (IAS15 {ias[0]:.2e}, {ias[1]:.2e}), "
                           f"**{b[6] / ias[2]:.2f}x IAS15's time**.")
            else:
                out.append(f"No EQUIP setting within the {bar} bar.")
        d = eq[0]
        out += ["", f"EQUIP defaults ({d[0]}, adaptive): energy {d[4]:.2e}, angular momentum "
                f"{d[5]:.2e}, {d[6] / ias[2]:.2f}x IAS15's time. (scene done in "
                f"{time.perf_counter() - t_scene:.0f} s)", ""]
        print("\n".join(out[-len(rows) - 9:]), flush=True)
    return out


def _k_of(make, setting) -> tuple[int, int, float]:
    """(k, s, epsilon) HBVMIntegrator chooses for ``setting`` on the scene (deterministic)."""
    from hbvm_md import HBVMIntegrator
    sim = make()
    m = HBVMIntegrator(sim, **setting).method
    return m.k, m.s, float(sim.integrator.epsilon)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--starts", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="a tenth of the steps")
    ap.add_argument("--rebound", action="store_true",
                    help="EQUIP through REBOUND against IAS15 (writes results/equip_rebound.md)")
    a = ap.parse_args()
    if a.rebound:
        out = rebound_section(a.starts)
        here = os.path.dirname(os.path.abspath(__file__))
        os.makedirs(os.path.join(here, "results"), exist_ok=True)
        with open(os.path.join(here, "results", "equip_rebound.md"), "w") as f:
            f.write("\n".join(out))
        return
    div = 10 if a.quick else 1
    kepler = Kepler(0.6)
    solar = outer_solar_system()
    kepler_L = lambda y: y[0] * y[3] - y[1] * y[2]          # noqa: E731
    scenes = [("Kepler e=0.6, 1e4 steps", kepler, kepler_L, 2 * np.pi / 100, 10_000 // div,
               [(EQUIP(6, 2), HBVM(6, 2)), (EQUIP(12, 4), HBVM(12, 4))]),
              ("outer solar system, 500 d, 1e6 d", solar, solar.angular_momentum, 500.0,
               2000 // div, [(EQUIP(9, 8), HBVM(9, 8))])]
    print(f"{'scene':34s} {'method':13s} {'energy':>9s} {'ang. mom.':>9s} {'us/step':>9s} "
          f"{'ratio':>6s}")
    for name, system, momentum, h, steps, pairs in scenes:
        for pair in pairs:
            rows = {m: [] for m in pair}
            for y0 in _starts(system.initial_state(), a.starts):
                for m in pair:
                    rows[m].append(_engine(m, system, y0, h, steps, momentum))
            t_hbvm = np.median([r[2] for r in rows[pair[1]]])
            for m in pair:
                dE, dL, t = np.median(np.array(rows[m]), axis=0)
                print(f"{name:34s} {m!r:13s} {dE:9.1e} {dL:9.1e} {1e6 * t:9.2f} "
                      f"{t / t_hbvm:6.2f}")
    rows = {"hbvm": [], "equip": []}
    names = {}
    for seed in range(a.starts):
        for method in rows:
            dE, dL, t, m = _ase(method, seed, 200 // div)
            rows[method].append((dE, dL, t))
            names[method] = m
    t_hbvm = np.median([r[2] for r in rows["hbvm"]])
    for method in ("equip", "hbvm"):
        dE, dL, t = np.median(np.array(rows[method]), axis=0)
        print(f"{'ASE 13-atom cluster, 5 fs':34s} {names[method]!r:13s} {dE:9.1e} {dL:9.1e} "
              f"{1e6 * t:9.1f} {t / t_hbvm:6.2f}")


if __name__ == "__main__":
    main()
