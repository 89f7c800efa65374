"""Benchmark (not a test): adaptive HBVM through REBOUND against IAS15 and fixed-step HBVM.

Scenes (each run from ``--starts`` starts (default 21; the disk from 5), one planet's position
scaled by 1 + r 1e-13; medians: at round-off the max energy error of one run is one draw of a
random walk, and medians of 5 draws still differ by 30 % from run to run):

* one planet (m = 1e-3) around m = 1, G = 1, at e = 0.9 and e = 0.99, 1000 orbits;
* the outer solar system of HLW over 1e5 and 1e6 days: adaptive defaults, the best fixed step of
  bench_rebound (HBVM(7,6), dt = 250) and IAS15;
* the close encounter of two Jupiters (``hbvm_md.reports.hard_cases.encounter_scene``), T = 200,
  also with epsilon = 1e-17 beside the defaults;
* the planetesimal disk: Sun, Jupiter and ``--disk-n`` bodies of 1e-8 solar masses (a in [1, 3]
  AU, e < 0.02, inc < 0.01, random angles from numpy ``default_rng(12345)``), 25 years.

Every method has the same ``--samples`` output times (``sim.integrate(t_i)``, exact finish); the
energy error is the max over them of |E - E0| / |E0|, the angular-momentum error the max of
|L - L0| / |L0| with L the bodies' total angular momentum about the origin
(``systems.NBody.angular_momentum``, REBOUND's ``sim.angular_momentum()`` here), both read
between the timed ``sim.integrate`` calls (until 2026-11-24 the energy read was inside the
timed region).  HBVM's time includes attaching.  Methods run once per start in turn, so that
load on the machine hits all of them alike.

Run:  python benchmarks/bench_adaptive.py [--starts 21] [--disk-n 300] [--quick]
"""
from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np
import rebound

from hbvm_md import HBVMIntegrator
from hbvm_md.reports.hard_cases import encounter_scene
from hbvm_md.reports.rebound_comparison import _state, angular_momentum_change
from integrators import StepError
from integrators.engine import DEFAULT_EPSILON
from integrators.kchoice import adaptive_k
from systems import NBody, outer_solar_system

HERE = os.path.dirname(os.path.abspath(__file__))


def kepler(e: float):
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, e=e)
    sim.move_to_com()
    return sim


def disk(n: int):
    """The planetesimal disk of the issue (AU, days, solar masses, G in those units)."""
    sim = rebound.Simulation()
    sim.units = ("day", "AU", "Msun")
    sim.add(m=1.0)
    sim.add(m=9.547919e-4, a=5.2026, e=0.0484, inc=0.0227, Omega=1.75, omega=4.78, M=0.35)
    rng = np.random.default_rng(12345)
    for _ in range(n):
        a, e, inc = rng.uniform(1, 3), rng.uniform(0, 0.02), rng.uniform(0, 0.01)
        Om, om, M = rng.uniform(0, 2 * np.pi, size=3)
        sim.add(m=1e-8, a=a, e=e, inc=inc, Omega=Om, omega=om, M=M)
    sim.move_to_com()
    return sim


def run(make, t_end: float, samples: int, method: str, r: int):
    sim = make()
    sim.particles[1].x *= 1 + r * 1e-13
    nb = NBody.from_rebound(sim)
    xv = [_state(sim)]
    e0 = sim.energy()
    t0 = time.perf_counter()
    drv = None
    if method == "ias15":
        sim.integrator = "ias15"
    elif method == "hbvm adaptive":
        drv = HBVMIntegrator(sim)
    elif method.startswith("hbvm epsilon="):           # adaptive, a tighter tolerance
        drv = HBVMIntegrator(sim, epsilon=float(method.split("=")[1]))
    else:                                   # "hbvm dt=X"
        drv = HBVMIntegrator(sim, s=6, dt=float(method.split("=")[1]))
    wall = time.perf_counter() - t0
    worst, ok = 0.0, "yes"
    try:
        for t in np.linspace(0, t_end, samples + 1)[1:]:
            t0 = time.perf_counter()
            try:
                sim.integrate(t)
            finally:
                wall += time.perf_counter() - t0
            worst = max(worst, abs((sim.energy() - e0) / e0))
            xv.append(_state(sim))
    except StepError as err:
        ok = f"stopped: {type(err).__name__} at t={err.t:.4g}"
    steps = drv.nsteps if drv is not None else sim.steps_done
    label = (f"HBVM({drv.method.k},{drv.method.s})" if drv is not None else "IAS15")
    return dict(worst=worst, wall=wall, steps=steps, ok=ok, label=label,
                rejected=getattr(drv, "rejected", 0), dL=float(np.max(angular_momentum_change(nb, np.array(xv)))))


def scene(name, make, t_end, methods, starts, samples, lines):
    rows = {m: [] for m in methods}
    for r in range(starts):
        for m in methods:
            rows[m].append(run(make, t_end, samples, m, r))
    ref = np.median([x["wall"] for x in rows["ias15"]])
    lines += [f"## {name}", "",
              "| method | steps | rejected | max rel. energy error, median | max rel. angular momentum error, "
              "median | wall (s), median | / IAS15 | finished |",
              "|---|---|---|---|---|---|---|---|"]
    for m in methods:
        xs = rows[m]
        wall = float(np.median([x["wall"] for x in xs]))
        lines.append(f"| {xs[0]['label']} {m if m != 'ias15' else ''} | {xs[0]['steps']} | "
                     f"{xs[0]['rejected']} | {np.median([x['worst'] for x in xs]):.2e} | "
                     f"{np.median([x['dL'] for x in xs]):.2e} | {wall:.4f} | "
                     f"{wall / ref:.2f} | {xs[0]['ok']} |")
    lines.append("")
    print("\n".join(lines[-len(methods) - 4:]), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--starts", type=int, default=21,
                    help="perturbed starts per scene (the disk: at most 5)")
    ap.add_argument("--samples", type=int, default=200)
    ap.add_argument("--disk-n", type=int, default=300)
    ap.add_argument("--quick", action="store_true", help="fewer orbits, a 30-body disk")
    a = ap.parse_args(argv)
    orbits = 100 if a.quick else 1000
    load = os.getloadavg()
    lines = ["# Adaptive HBVM through REBOUND", "",
             f"Generated by `python benchmarks/bench_adaptive.py{' --quick' if a.quick else ''}`: "
             f"medians over {a.starts} starts (the disk: {min(a.starts, 5)}), {a.samples} output times for every "
             f"method (the disk: 100), HBVM "
             f"attach included, defaults (`HBVMIntegrator(sim)`: adaptive, s = 6, "
             f"k = {adaptive_k(6, DEFAULT_EPSILON)}, epsilon = {DEFAULT_EPSILON:g}). "
             f"Load average at the start: {load[0]:.1f}, {load[1]:.1f}, "
             f"{load[2]:.1f} on {os.cpu_count()} cores.", ""]
    run(lambda: kepler(0.9), 1.0, 2, "hbvm adaptive", 0)           # compile outside the timings
    for e in (0.9, 0.99):
        scene(f"One planet at e = {e}, {orbits} orbits", lambda e=e: kepler(e), 2 * math.pi * orbits,
              ["hbvm adaptive", "ias15"], a.starts, a.samples, lines)
    for t_end in ((1e5,) if a.quick else (1e5, 1e6)):
        scene(f"Outer solar system, {t_end:.0e} days", lambda: outer_solar_system().to_rebound(),
              t_end, ["hbvm adaptive", "hbvm dt=250", "ias15"], a.starts, a.samples, lines)
    scene("Close encounter of two Jupiters (hard case), T = 200",
          lambda: encounter_scene().to_rebound(), 200.0,
          ["hbvm adaptive", "hbvm epsilon=1e-17", "hbvm dt=0.0314159", "ias15"], a.starts,
          a.samples, lines)
    n = 30 if a.quick else a.disk_n
    scene(f"Planetesimal disk, Sun + Jupiter + {n} bodies, 25 years", lambda: disk(n), 25 * 365.25,
          ["hbvm adaptive", "hbvm dt=9", "ias15"], min(a.starts, 5), 100, lines)
    out = os.path.join(HERE, "results", "adaptive.md")
    with open(out, "w") as f:
        f.write("\n".join(lines) + "\n")
    print("written to", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
