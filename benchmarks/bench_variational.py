"""The cost of the tangent map against the step it differentiates (integrators.variational),
and MEGNO over long runs of two-planet systems.

Runs the same fixed-step integration with and without tangent vectors (``integrate(...,
variational=V0)``, one tangent, and as many as the state has components) in the same process,
interleaved, the fastest of ``--repeat`` rounds each, and prints the time per step and the
ratio.  Scenes: Kepler (e = 0.6, 100 steps a period) and the outer solar system (HLW, 10-day
steps), HBVM(k, s) as given.

Then (unless ``--no-megno``) the MEGNO <Y> of two regular two-planet systems (G = 1, a star of
mass 1, inner planet at a = 1 on a circular orbit, 60 steps of HBVM(6, 3) a period, a random
first tangent) at ten times over the run: masses 1e-4 and 1e-4 with a2 = 2 (period ratio 2.83)
over 1e4 inner orbits, and a Jupiter-Saturn-like pair (1e-3, 3e-4, a2 = 1.84, e2 = 0.05) over
2000.

    python benchmarks/bench_variational.py [--steps 20000] [--repeat 5] [--no-megno]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from integrators import HBVM, integrate
from systems import Kepler, NBody
from systems.solar import outer_solar_system


def scenes():
    kep = Kepler(0.6)
    yield "Kepler e=0.6", kep, kep.initial_state(), 2 * np.pi / 100
    oss = outer_solar_system()
    yield "outer solar system", oss, oss.initial_state(), 10.0


def per_step(method, system, y0, h, steps, V0):
    t = time.perf_counter()
    res = integrate(method, system, y0, h, steps, sample_every=steps, variational=V0)
    wall = time.perf_counter() - t
    return wall / steps, res


def two_planets(a2, m1, m2, e2=0.0):
    """Star (1), planet 1 at (1, 0, 0) on a circular orbit, planet 2 at apocentre of an orbit
    with semi-major axis a2 and eccentricity e2, 0.01 out of the plane; G = 1, centre of mass
    at rest."""
    x, v = np.zeros((3, 3)), np.zeros((3, 3))
    x[1], v[1] = [1.0, 0, 0], [0, 1.0, 0]
    r2 = a2 * (1 + e2)
    x[2], v[2] = [-r2, 0, 0.01], [0, -np.sqrt((1 - e2) / r2), 0]
    ms = np.array([1.0, m1, m2])
    x -= (ms[:, None] * x).sum(0) / ms.sum()
    v -= (ms[:, None] * v).sum(0) / ms.sum()
    return NBody(ms, positions=x, velocities=v)


def megno_runs():
    rng = np.random.default_rng(1)
    print("\n| system | orbits | <Y> at 10 %, 20 %, ... 100 % of the run | energy error | wall (s) |")
    print("|---|---|---|---|---|")
    for label, a2, m1, m2, e2, orbits in [("m = 1e-4, 1e-4, a2 = 2", 2.0, 1e-4, 1e-4, 0.0, 10000),
                                          ("Jupiter-Saturn-like", 1.84, 1e-3, 3e-4, 0.05, 2000)]:
        system = two_planets(a2, m1, m2, e2)
        y0 = system.initial_state()
        V0 = rng.normal(size=y0.size)
        integrate(HBVM(6, 3), system, y0, 0.1, 2, variational=V0)       # compile first
        t = time.perf_counter()
        res = integrate(HBVM(6, 3), system, y0, 2 * np.pi / 60, orbits * 60,
                        sample_every=6 * orbits, variational=V0)
        wall = time.perf_counter() - t
        mg = ", ".join(f"{x:.3f}" for x in res.extra["megno"][1:])
        print(f"| {label} | {orbits} | {mg} | {res.max_energy_error:.1e} | {wall:.1f} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--k", type=int, default=6)
    ap.add_argument("--s", type=int, default=3)
    ap.add_argument("--no-megno", action="store_true")
    args = ap.parse_args(argv)
    method = HBVM(args.k, args.s)
    rng = np.random.default_rng(0)
    print(f"HBVM({args.k}, {args.s}), {args.steps} steps, fastest of {args.repeat}")
    print("| scene | step (us) | + 1 tangent (us) | ratio | + d tangents (us) | ratio | "
          "tangent iterations / step iterations |")
    print("|---|---|---|---|---|---|---|")
    for name, system, y0, h in scenes():
        d = y0.size
        cases = {"plain": None, "one": rng.normal(size=d), "all": np.eye(d)}
        for V0 in cases.values():          # compile (or load) every path before timing
            per_step(method, system, y0, h, 10, V0)
        best = {key: np.inf for key in cases}
        res = {}
        for _ in range(args.repeat):
            for key, V0 in cases.items():
                t, res[key] = per_step(method, system, y0, h, args.steps, V0)
                best[key] = min(best[key], t)
        it_ratio = res["one"].extra["tangent_iterations"] / res["one"].iterations
        print(f"| {name} | {1e6 * best['plain']:.2f} | {1e6 * best['one']:.2f} | "
              f"{best['one'] / best['plain']:.2f} | {1e6 * best['all']:.2f} | "
              f"{best['all'] / best['plain']:.2f} | {it_ratio:.2f} |")
    if not args.no_megno:
        megno_runs()


if __name__ == "__main__":
    main()
