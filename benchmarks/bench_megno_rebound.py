"""MEGNO through REBOUND with HBVM as the registered integrator against IAS15, on a grid of a
Jupiter-Saturn-like system (scanning Saturn's semi-major axis and eccentricity).

Each grid point is one REBOUND simulation (G = 1, years / 2 pi as the time unit): the Sun, Jupiter
(m = 9.54e-4, a = 5.204, e = 0.048, M = 0.600, omega = 0.257) and Saturn (m = 2.85e-4, a and
e from the grid, M = 0.871, omega = 1.616), centre of mass at rest, ``sim.init_megno(seed=1)``,
``exit_max_distance = 20``, integrated to ``--orbits`` Jupiter periods with
``sim.integrator = "hbvm"`` (its defaults: adaptive, s = 6) and with ``"ias15"`` (its defaults),
the two interleaved point by point in one process.  A point is chaotic when <Y> > ``--threshold``
(or when the run stopped: an escape, or HBVM refusing an unresolved close encounter); the table
gives <Y> of both, whether the classes agree, and |<Y>_HBVM - <Y>_IAS15| on points both call
regular; the wall times are summed over the grid (what the user pays per map).

    python benchmarks/bench_megno_rebound.py [--na 8] [--ne 5] [--orbits 1000] [--threshold 4]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import rebound

import hbvm_md  # noqa: F401  (registers "hbvm")


def jupiter_saturn(a: float, e: float, integrator: str):
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=9.54e-4, a=5.204, M=0.600, omega=0.257, e=0.048)
    sim.add(m=2.85e-4, a=a, M=0.871, omega=1.616, e=e)
    sim.move_to_com()
    sim.integrator = integrator
    if integrator == "hbvm":
        sim.dt = 0.05 * 2 * np.pi * 5.204 ** 1.5     # the first trial step; adaptive after it
    sim.exit_max_distance = 20.0
    sim.init_megno(seed=1)
    return sim


def megno_point(a: float, e: float, integrator: str, t_end: float):
    """(<Y> or inf when the run stopped, wall seconds, steps)."""
    sim = jupiter_saturn(a, e, integrator)
    t = time.perf_counter()
    try:
        sim.integrate(t_end, exact_finish_time=0)
        y = sim.megno()
    except Exception:               # an escape, or a step HBVM refuses: unstable
        y = np.inf
    return y, time.perf_counter() - t, sim.steps_done


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--na", type=int, default=8)
    ap.add_argument("--ne", type=int, default=5)
    ap.add_argument("--a", type=float, nargs=2, default=(7.0, 10.0))
    ap.add_argument("--e", type=float, nargs=2, default=(0.0, 0.4))
    ap.add_argument("--orbits", type=float, default=1000.0, help="Jupiter periods")
    ap.add_argument("--threshold", type=float, default=4.0)
    args = ap.parse_args()
    t_end = args.orbits * 2 * np.pi * 5.204 ** 1.5
    megno_point(8.0, 0.1, "hbvm", 10.0)     # compile / load the step once, outside the timing
    rows, wall = [], {"hbvm": 0.0, "ias15": 0.0}
    print(f"| a | e | <Y> HBVM | <Y> IAS15 | same class | steps HBVM | steps IAS15 |")
    print("|---|---|---|---|---|---|---|")
    for a in np.linspace(*args.a, args.na):
        for e in np.linspace(*args.e, args.ne):
            res = {}
            for integ in ("hbvm", "ias15"):
                y, w, n = megno_point(a, e, integ, t_end)
                res[integ] = (y, n)
                wall[integ] += w
            (yh, nh), (yi, ni) = res["hbvm"], res["ias15"]
            same = (yh > args.threshold) == (yi > args.threshold)
            rows.append((a, e, yh, yi, same))
            print(f"| {a:.3f} | {e:.2f} | {yh:.3f} | {yi:.3f} | {'yes' if same else 'NO'} | "
                  f"{nh} | {ni} |", flush=True)
    regular = [abs(r[2] - r[3]) for r in rows if r[2] <= args.threshold and r[3] <= args.threshold]
    print()
    print(f"points: {len(rows)}; classified alike (<Y> > {args.threshold} chaotic): "
          f"{sum(r[4] for r in rows)}/{len(rows)}; regular by both: {len(regular)}, "
          f"max |<Y>_HBVM - <Y>_IAS15| there: {max(regular, default=np.nan):.4f}")
    print(f"wall time over the grid: HBVM {wall['hbvm']:.2f} s, IAS15 {wall['ias15']:.2f} s, "
          f"ratio IAS15 / HBVM {wall['ias15'] / wall['hbvm']:.2f}")


if __name__ == "__main__":
    main()
