"""Benchmark (not a test): Mercury's perihelion precession with REBOUNDx's ``gr_potential``,
HBVM composed with the Keplerian flows inside REBOUND (``HBVMIntegrator(sim, kepler=True)``,
the potential a term of the perturbation: ``FlowComposed(gr_c=...)``) against IAS15 with the
same REBOUNDx force.

Two scenes in years, AU and solar masses (c = 63241.077 AU/yr), over 1000 years:
"Sun + Mercury" (the precession is GR's alone: the potential's 6 pi G M / (c^2 a (1 - e^2)) an
orbit, 42.98 arcsec a century) and "Sun + Mercury .. Saturn" (the planets' pull adds about
530).  Each integrator runs alone to the same 101 output times (the composed step's multiples of
its dt; IAS15 integrates to them exactly); the precession is the slope of a least-squares line
through Mercury's unwrapped heliocentric longitude of pericentre.  Columns: the precession,
the longitude of pericentre at the end against IAS15's at epsilon 1e-11 (arcsec), Mercury's
position there against it (AU), the largest relative error of REBOUNDx's energy
(``sim.energy() + rebx.gr_potential_potential(force)``) over the outputs, wall time (median of
``--repeat`` runs, each in turn) and its ratio to IAS15 at REBOUND's default epsilon (1e-9).
Writes benchmarks/results/kepler_gr.md.

    python benchmarks/bench_kepler_gr.py [--repeat 3] [--years 1000]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

import rebound  # noqa: E402
import reboundx  # noqa: E402

from hbvm_md import HBVMIntegrator  # noqa: E402
from hbvm_md.reports.machine import machine  # noqa: E402

C = 63241.077                       # AU / yr
ARCSEC_PER_CENTURY = 100 * 180 * 3600 / np.pi
#: (name, mass, a, e, inc, Omega, omega, M) of the planets (J2000-like elements, degrees)
PLANETS = [("Mercury", 1.6601e-7, 0.387098, 0.205630, 7.005, 48.331, 29.124, 174.796),
           ("Venus", 2.4478e-6, 0.723332, 0.006772, 3.3947, 76.680, 54.884, 50.115),
           ("Earth", 3.0404e-6, 1.000001, 0.016709, 0.0, -11.261, 114.208, 358.617),
           ("Mars", 3.2272e-7, 1.523679, 0.093405, 1.850, 49.558, 286.502, 19.412),
           ("Jupiter", 9.5479e-4, 5.2044, 0.0489, 1.303, 100.464, 273.867, 20.020),
           ("Saturn", 2.8589e-4, 9.5826, 0.0565, 2.485, 113.665, 339.392, 317.020)]
SCENES = {"Sun + Mercury": 1, "Sun + Mercury .. Saturn": 6}
#: the composed method's settings (s, k, dt in years: Mercury's period is 0.2408 yr, so P/24,
#: P/12 and P/6; a sweep over 100 years put HBVM(7,5) and HBVM(8,6) at dt = 0.02 and HBVM(10,8)
#: at dt = 0.04 within 4e-11 AU of IAS15 at epsilon 1e-11, HBVM(8,6) at 0.04 at 2e-10)
KEPLER = ((6, 8, 0.01), (6, 8, 0.02), (8, 10, 0.04))
IAS15 = (1e-9, 1e-11)


def scene(n_planets: int, gr: bool = True):
    sim = rebound.Simulation()
    sim.units = ("yr", "AU", "Msun")
    sim.add(m=1.0)
    d = np.pi / 180
    for name, m, a, e, inc, Om, om, M in PLANETS[:n_planets]:
        sim.add(m=m, a=a, e=e, inc=inc * d, Omega=Om * d, omega=om * d, M=M * d)
    sim.move_to_com()
    rebx = reboundx.Extras(sim)
    force = rebx.load_force("gr_potential")
    rebx.add_force(force)
    force.params["c"] = C
    return sim, rebx, force


def run(n_planets: int, how, times):
    """(seconds, pomega (n,), Mercury's xyz at the end, max rel. energy error) of one run to
    ``times``: how = ("kepler", s, k, dt) or ("ias15", epsilon)."""
    sim, rebx, force = scene(n_planets)
    if how[0] == "kepler":
        HBVMIntegrator(sim, kepler=True, s=how[1], k=how[2], dt=how[3])
    else:
        sim.integrator = "ias15"
        sim.integrator.epsilon = how[1]
    E0 = sim.energy() + rebx.gr_potential_potential(force)
    pom, err = [], 0.0
    wall = 0.0
    for t in times:
        a = time.perf_counter()
        if how[0] == "kepler":
            sim.steps(int(round((t - sim.t) / how[3])))
        else:
            sim.integrate(t)
        wall += time.perf_counter() - a
        pom.append(sim.particles[1].orbit(primary=sim.particles[0]).pomega)
        err = max(err, abs((sim.energy() + rebx.gr_potential_potential(force)) / E0 - 1))
    return wall, np.unwrap(pom), np.array(sim.particles[1].xyz), err


def output_times(n_steps: int, dt: float) -> np.ndarray:
    """101 output times, multiples k dt of the composed step dt (the coarsest) for k = 0, n / 100,
    ..., n: where sim.t is after k steps of HBVM's compensated clock (k dt rounded once; a
    finer step's run reaches them to about 1e-13 of t), and where IAS15 integrates to."""
    per = n_steps // 100
    return dt * np.arange(0, per * 100 + 1, per, dtype=float)


def interleaved(run, key, settings, times, repeat: int):
    """Every setting of one scene run ``repeat`` times, the settings in turn (a slow spell of a
    shared machine falls on all of them): (median wall time by setting, the last run's results
    by setting: pomega, positions, max energy error), ``run(key, setting, times)`` returning
    (wall, pomega, positions, energy error)."""
    walls = {h: [] for h in settings}
    res = {}
    for _ in range(repeat):
        for h in settings:
            w, pom, xyz, err = run(key, h, times)
            walls[h].append(w)
            res[h] = (pom, xyz, err)
    return {h: float(np.median(w)) for h, w in walls.items()}, res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3, help="runs per setting (median wall time)")
    ap.add_argument("--years", type=float, default=1000.0)
    args = ap.parse_args()
    # warm-up: numba's caches of the composed step (not timed)
    run(1, ("kepler",) + KEPLER[0], output_times(int(round(1.0 / KEPLER[0][2])), KEPLER[0][2]))
    out = ["# Mercury's perihelion precession with REBOUNDx gr_potential: HBVM composed with the "
           "Keplerian flows vs IAS15", "",
           f"{machine()}, one process. Generated by `python benchmarks/bench_kepler_gr.py --repeat "
           f"{args.repeat} --years {args.years:g}` on {time.strftime('%Y-%m-%d')}. Load average at "
           f"the start: {', '.join(f'{x:.1f}' for x in os.getloadavg())} on {os.cpu_count()} cores. "
           f"The GR precession of the potential: 6 pi G M / (c^2 a (1 - e^2)) an orbit.", ""]
    for name, n in SCENES.items():
        dt = max(k[2] for k in KEPLER)
        times = output_times(int(round(args.years / dt)), dt)
        settings = [("kepler",) + k for k in KEPLER] + [("ias15", e) for e in IAS15]
        walls, res = interleaved(run, n, settings, times, args.repeat)
        ref = res[("ias15", 1e-11)]
        base = walls[("ias15", 1e-9)]
        lines = [f"## {name}, {args.years:g} years", "",
                 "| method | settings | precession (arcsec/century) | pomega vs IAS15 1e-11 (arcsec) "
                 "| Mercury vs IAS15 1e-11 (AU) | max rel. energy error | wall (s) | / IAS15 1e-9 |",
                 "|---|---|---|---|---|---|---|---|"]
        for h in settings:
            pom, xyz, err = res[h]
            rate = np.polyfit(times, pom, 1)[0] * ARCSEC_PER_CENTURY
            dpom = (pom[-1] - ref[0][-1]) * 180 * 3600 / np.pi
            dx = np.abs(xyz - ref[1]).max()
            w = walls[h]
            label = (f"HBVM({h[2]},{h[1]}) kepler in REBOUND", f"dt={h[3]:g} yr") if h[0] == "kepler" \
                else ("ias15", f"epsilon={h[1]:g}")
            lines.append(f"| {label[0]} | {label[1]} | {rate:.4f} | {dpom:.1e} | {dx:.1e} | {err:.1e} "
                         f"| {w:.2f} | {w / base:.2f} |")
        if n == 1:
            mu = 4 * np.pi ** 2
            a, e = PLANETS[0][2], PLANETS[0][3]
            P = 2 * np.pi * np.sqrt(a ** 3 / mu)
            theory = 6 * np.pi * mu / (C ** 2 * a * (1 - e * e)) / P * ARCSEC_PER_CENTURY
            lines += ["", f"The potential's precession in closed form: {theory:.4f} arcsec/century "
                          f"(the fit's slope over {args.years:g} years also holds the short-period "
                          f"wobble of the osculating pericentre)."]
        lines.append("")
        print("\n".join(lines), flush=True)
        out += lines
    with open(os.path.join(HERE, "results", "kepler_gr.md"), "w") as f:
        f.write("\n".join(out))


if __name__ == "__main__":
    main()
