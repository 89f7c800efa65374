"""Benchmark (not a test): the per-step cost of the engine's default energy check.

The same fixed-step runs with ``energy_tol=None`` (no check), a strict tolerance (one potential
evaluation a step) and the default ``"auto"`` (:func:`integrators.engine.energy_check`: strict
for a method exact for the polynomial H, the energy-flow check otherwise), interleaved, the
best process time of ``--repeat`` runs each (the machine is shared).  The final states are
compared bit for bit: the check only refuses steps, it never changes one.

    python benchmarks/bench_energy_check.py [--repeat 15]
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from integrators import HBVM, integrate                                  # noqa: E402
from systems import HenonHeiles, Kepler, outer_solar_system              # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=15)
    args = ap.parse_args(argv)
    kep, hh, oss = Kepler(0.6), HenonHeiles(), outer_solar_system()
    cases = [("Kepler e=0.6, HBVM(6, 3), h = P/50", HBVM(6, 3), kep, kep.initial_state(),
              2 * np.pi / 50, 20000, 1e-10),
             ("Kepler e=0.6, HBVM(2, 2), h = P/100", HBVM(2, 2), kep, kep.initial_state(),
              2 * np.pi / 100, 20000, 1.0),
             ("Henon-Heiles, HBVM(3, 2) (exact), h = 0.5", HBVM(3, 2), hh, np.full(4, 0.18),
              0.5, 20000, 1e-10),
             ("outer solar system, HBVM(12, 6), h = 200 d", HBVM(12, 6), oss,
              oss.initial_state(), 200.0, 2000, 1e-10)]
    print("| run | no check [ns / step] | strict | default ('auto') | same states |")
    print("|---|---|---|---|---|")
    for name, method, system, y0, h, n, strict in cases:
        opts = (None, strict, "auto")
        best = {o: np.inf for o in opts}
        final = {}
        for o in opts:                       # compile and warm every variant first
            integrate(method, system, y0, h, 10, energy_tol=o)
        for _ in range(args.repeat):
            for o in opts:
                t0 = time.process_time()
                res = integrate(method, system, y0, h, n, sample_every=n, energy_tol=o)
                best[o] = min(best[o], time.process_time() - t0)
                final[o] = res.y[-1]
        base = best[None]
        same = all(np.array_equal(final[None], final[o]) for o in opts)
        print(f"| {name} | {base / n * 1e9:.0f} | {100 * (best[strict] / base - 1):+.1f} % "
              f"(tol {strict:g}) | {100 * (best['auto'] / base - 1):+.1f} % | {same} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
