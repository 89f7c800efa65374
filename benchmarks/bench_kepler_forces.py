"""Benchmark (not a test): REBOUNDx's ``gravitational_harmonics`` and ``central_force`` of the
star with HBVM composed with the Keplerian flows inside REBOUND (``HBVMIntegrator(sim,
kepler=True)``, each force a term of the perturbation: ``FlowComposed(harmonics=...,
central=...)``) against IAS15 with the same REBOUNDx forces.

Scenes (G = 1), from REBOUNDx's examples with one dominant star:
"J2 example" (``ipython_examples/J2.ipynb``: a star with J2 = 0.01, R_eq = 1/200 and its spin
axis tilted by pi/3, a planet of 3e-6 at a = 0.1, e = 0.01, inclined by pi/6); "J2 + J4, two
planets" (the same star with J4 = -1e-3 and a second planet of 1e-5 at a = 0.17); "central
force example" (``ipython_examples/CentralForce.ipynb``: a planet of 1e-3 at a = 1, e = 0.2, the
star's gamma = -1 and Acentral set from a pericentre precession of 1e-3 per unit time with
REBOUNDx's ``central_force_Acentral``); "all three" (the two-planet J2 + J4 scene with that
central force's gamma and A = 1e-4, and gr_potential at c = 300).  Each run goes to 101 output
times (multiples of the coarsest composed step); columns: the largest distance of the bodies
from IAS15 at epsilon 1e-11 at the end, the largest relative error of REBOUNDx's energy
(``sim.energy()`` plus the attached forces' potentials) over the outputs, the fitted slope of
planet 1's longitude of pericentre (the central force example predicts 1e-3), wall time (median
of ``--repeat`` runs, in turn) and its ratio to IAS15 at REBOUND's default epsilon (1e-9).
Writes benchmarks/results/kepler_forces.md.

    python benchmarks/bench_kepler_forces.py [--repeat 3] [--orbits 2000]
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

sys.path.insert(0, HERE)
from bench_kepler_gr import interleaved, output_times  # noqa: E402

OBLIQUITY = np.pi / 3


def scene(name: str):
    """(sim, rebx, the innermost planet's period) of a scene (module docstring)."""
    sim = rebound.Simulation()
    sim.add(m=1.0)
    if name == "central force example":
        sim.add(m=1e-3, a=1.0, e=0.2)
    else:
        sim.add(m=3e-6, a=0.1, e=0.01, inc=np.pi / 6)
        if name != "J2 example":
            sim.add(m=1e-5, a=0.17, e=0.05, inc=0.1, f=2.0)
    sim.move_to_com()
    rebx = reboundx.Extras(sim)
    p0 = sim.particles[0]
    if name != "central force example":
        rebx.add_force(rebx.load_force("gravitational_harmonics"))
        p0.params["J2"], p0.params["R_eq"] = 0.01, 1 / 200
        p0.params["Omega"] = [0.0, -np.sin(OBLIQUITY), np.cos(OBLIQUITY)]
        if name != "J2 example":
            p0.params["J4"] = -1e-3
    if name in ("central force example", "all three"):
        rebx.add_force(rebx.load_force("central_force"))
        p0.params["gammacentral"] = -1.0
        p0.params["Acentral"] = (1e-4 if name == "all three" else rebx.central_force_Acentral(
            sim.particles[1], p0, 1e-3, -1.0))
    if name == "all three":
        gr = rebx.load_force("gr_potential")
        rebx.add_force(gr)
        gr.params["c"] = 300.0
    return sim, rebx, sim.particles[1].P


def energy(sim, rebx) -> float:
    """REBOUND's energy plus REBOUNDx's potentials (those of the harmonics and the central force
    are sums over the particles carrying their parameters: 0 in a scene without)."""
    e = sim.energy() + rebx.gravitational_harmonics_potential() + rebx.central_force_potential()
    try:
        gr = rebx.get_force("gr_potential")
    except AttributeError:
        return e
    return e + rebx.gr_potential_potential(gr)


SCENES = ("J2 example", "J2 + J4, two planets", "central force example", "all three")
#: (s, k, steps per orbit of the innermost planet)
KEPLER = ((6, 8, 24), (6, 8, 12), (8, 10, 6))
IAS15 = (1e-9, 1e-11)


def run(name, how, times):
    sim, rebx, P = scene(name)
    if how[0] == "kepler":
        HBVMIntegrator(sim, kepler=True, s=how[1], k=how[2], dt=P / how[3])
    else:
        sim.integrator = "ias15"
        sim.integrator.epsilon = how[1]
    E0 = energy(sim, rebx)
    pom, err, wall = [], 0.0, 0.0
    for t in times:
        a = time.perf_counter()
        if how[0] == "kepler":
            sim.steps(int(round((t - sim.t) / sim.dt)))
        else:
            sim.integrate(t)
        wall += time.perf_counter() - a
        pom.append(sim.particles[1].orbit(primary=sim.particles[0]).pomega)
        err = max(err, abs(energy(sim, rebx) / E0 - 1))
    xyz = np.array([p.xyz for p in sim.particles])
    return wall, np.unwrap(pom), xyz, err


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3, help="runs per setting (median wall time)")
    ap.add_argument("--orbits", type=float, default=2000.0,
                    help="of the innermost planet")
    args = ap.parse_args()
    run("all three", ("kepler",) + KEPLER[0], [0.0, 1.0])      # numba's caches (not timed)
    out = ["# REBOUNDx gravitational_harmonics and central_force: HBVM composed with the "
           "Keplerian flows vs IAS15", "",
           f"{machine()}, one process. Generated by `python benchmarks/bench_kepler_forces.py "
           f"--repeat {args.repeat} --orbits {args.orbits:g}` on {time.strftime('%Y-%m-%d')}. "
           f"Load average at the start: {', '.join(f'{x:.1f}' for x in os.getloadavg())} on "
           f"{os.cpu_count()} cores.", ""]
    for name in SCENES:
        P = scene(name)[2]
        coarsest = min(k[2] for k in KEPLER)
        times = output_times(int(args.orbits * coarsest), P / coarsest)
        settings = [("kepler",) + k for k in KEPLER] + [("ias15", e) for e in IAS15]
        walls, res = interleaved(run, name, settings, times, args.repeat)
        ref = res[("ias15", 1e-11)]
        base = walls[("ias15", 1e-9)]
        lines = [f"## {name}, {args.orbits:g} orbits of planet 1 (t = {times[-1]:.6g})", "",
                 "| method | settings | bodies vs IAS15 1e-11 | max rel. energy error "
                 "| pomega rate of planet 1 | wall (s) | / IAS15 1e-9 |",
                 "|---|---|---|---|---|---|---|"]
        for h in settings:
            pom, xyz, err = res[h]
            rate = np.polyfit(times, pom, 1)[0]
            dx = np.abs(xyz - ref[1]).max()
            w = walls[h]
            label = ((f"HBVM({h[2]},{h[1]}) kepler in REBOUND", f"dt=P/{h[3]}")
                     if h[0] == "kepler" else ("ias15", f"epsilon={h[1]:g}"))
            lines.append(f"| {label[0]} | {label[1]} | {dx:.1e} | {err:.1e} | {rate:.6e} "
                         f"| {w:.2f} | {w / base:.2f} |")
        lines.append("")
        print("\n".join(lines), flush=True)
        out += lines
    out += ["The pomega rate is the slope of a least-squares line through planet 1's unwrapped "
            "longitude of pericentre (about particle 0, in the scene's frame). In the central "
            "force example the example sets Acentral for a rate of 1e-3 with REBOUNDx's "
            "central_force_Acentral, an estimate from the osculating orbit: IAS15 measures the "
            "same rate as the composed method there.", ""]
    with open(os.path.join(HERE, "results", "kepler_forces.md"), "w") as f:
        f.write("\n".join(out))


if __name__ == "__main__":
    main()
