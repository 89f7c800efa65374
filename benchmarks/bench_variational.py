"""The cost of the tangent map against the step it differentiates (integrators.variational).

Runs the same fixed-step integration with and without tangent vectors (``integrate(...,
variational=V0)``, one tangent, and as many as the state has components) in the same process,
interleaved, the fastest of ``--repeat`` rounds each, and prints the time per step and the
ratio.  Scenes: Kepler (e = 0.6, 100 steps a period) and the outer solar system (HLW, 10-day
steps), HBVM(k, s) as given.

    python benchmarks/bench_variational.py [--steps 20000] [--repeat 5]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from integrators import HBVM, integrate
from systems import Kepler
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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--k", type=int, default=6)
    ap.add_argument("--s", type=int, default=3)
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


if __name__ == "__main__":
    main()
