"""Benchmark (not a test): the flow-composed method's recentring in double-double against the
double one it replaced (issue 48, item 1: the physical energy's error at IAS15's level).

The composed method (``systems.flow_composed.FlowComposed``) on the outer solar system, each
setting run with both recentrings in turn (:func:`systems.flow_composed.composed_recentre`,
double-double; :func:`systems.flow_composed.composed_recentre_double`, the double flow), over
``--starts`` perturbed starts (the planets' positions scaled by 1 + rep 1e-13, as
bench_rebound's: at round-off one run's error is one draw of a random walk).  Columns: the
median over the starts of the max relative physical energy error over 200 samples, of the
final position error against a reference (the double-double composed HBVM(13,10) at
h = 250 days, whose truncation error is 2^-20 of the h = 1000 days rows'), and the time of
a run (the steps and the samples, median over the starts; both recentrings in turn in one
process, so their ratio is the comparison) and of one recentring (best of 5 x 2000 calls, the
state after one step of HBVM(8,6)).

A last table follows the max energy error of HBVM(10,8) at 500 days over 1e5 .. 1e8 days
(``--growth``): the double recentring's Brouwer's law, eps sqrt(steps), against the
double-double one.

    python benchmarks/bench_kepler_recentre.py [--starts 5] [--days 1e5 1e6] [--growth 1e5 .. 1e8]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
LOAD = ", ".join(f"{x:.1f}" for x in os.getloadavg())

from hbvm_md.reports.machine import machine  # noqa: E402
from integrators import HBVM, Stepper  # noqa: E402
from systems import outer_solar_system  # noqa: E402
from systems.flow_composed import (FlowComposed, composed_recentre,  # noqa: E402
                                   composed_recentre_double)

SETTINGS = ((6, 8, 500.0), (8, 10, 500.0), (10, 13, 1000.0))


class DoubleRecentring(FlowComposed):
    """The composed system with the double recentring (the baseline)."""

    def recentre_kernel(self):
        return composed_recentre_double


def start(rep):
    nb = outer_solar_system()
    y0 = nb.initial_state().copy()
    n = nb.body_masses.size
    y0[3:3 * n] *= 1 + rep * 1e-13           # the planets' positions (the Sun's first)
    return nb, y0


def run(cls, nb, y0, s, k, h, days):
    fc = cls.from_nbody(nb, h)
    Y = fc.extend(y0)
    steps = int(round(days / h))
    every = max(1, steps // 200)
    st = Stepper(HBVM(k, s), fc, Y, form="full")
    t = time.perf_counter()
    r = st.run(h, steps, sample_every=every)
    wall = time.perf_counter() - t
    e0 = fc.physical_energy(r.y[0])
    err = max(abs(fc.physical_energy(y) / e0 - 1.0) for y in r.y)
    return err, fc.physical(r.y[-1], r.t[-1]), wall


def recentre_time(cls):
    nb, y0 = start(0)
    fc = cls.from_nbody(nb, 500.0)
    st = Stepper(HBVM(8, 6), fc, fc.extend(y0), form="full")
    st.run(500.0, 1, sample_every=1)
    fn = fc.recentre_kernel()
    _, _, params = fc.full_kernels()
    best = np.inf
    for _ in range(5):
        y, cy, gamma = st.y.copy(), np.zeros_like(st.y), np.zeros((6, st.y.size))
        y[fc.dim - 1] = 0.5 * 500.0
        fn(y, cy, gamma, 500.0, params)
        t = time.perf_counter()
        for _ in range(2000):
            y[fc.dim - 1] = 0.5 * 500.0
            cy[fc.dim - 1] = 0.0
            fn(y, cy, gamma, 500.0, params)
        best = min(best, (time.perf_counter() - t) / 2000)
    return best


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--starts", type=int, default=5)
    ap.add_argument("--days", type=float, nargs="+", default=[1e5, 1e6])
    ap.add_argument("--growth", type=float, nargs="*", default=[1e5, 1e6, 1e7, 1e8],
                    help="t_end of the growth table (max energy error against the steps)")
    a = ap.parse_args()
    n = 3 * (outer_solar_system().body_masses.size)
    lines = []
    for days in a.days:
        lines += [f"## outer solar system, t_end = {days:.0e} days, medians over {a.starts} starts",
                  "", "| method | h (days) | recentring | max rel. energy error "
                  "| position error (AU) | wall (s) |", "|---|---|---|---|---|---|"]
        res = {}
        refs = []
        for rep in range(a.starts):
            nb, y0 = start(rep)
            refs.append(run(FlowComposed, nb, y0, 10, 13, 250.0, days)[1])
            for s, k, h in SETTINGS:
                for name, cls in (("double", DoubleRecentring), ("double-double", FlowComposed)):
                    err, y, wall = run(cls, nb, y0, s, k, h, days)
                    pos = np.abs(y[:n] - refs[-1][:n]).max()
                    res.setdefault((s, k, h, name), []).append((err, pos, wall))
        for (s, k, h, name), v in res.items():
            v = np.array(v)
            lines.append(f"| HBVM({k},{s}) kepler | {h:g} | {name} | {np.median(v[:, 0]):.2e} | "
                         f"{np.median(v[:, 1]):.1e} | {np.median(v[:, 2]):.3f} |")
        lines.append("")
        print("\n".join(lines[-len(res) - 5:]), flush=True)
    if a.growth:
        lines += [f"## Growth with the number of steps: HBVM(10,8) kepler, h = 500 days, medians "
                  f"over {a.starts} starts", "",
                  "| t_end (days) | steps | double | double-double |", "|---|---|---|---|"]
        for days in a.growth:
            errs = {"double": [], "double-double": []}
            for rep in range(a.starts):
                nb, y0 = start(rep)
                for name, cls in (("double", DoubleRecentring), ("double-double", FlowComposed)):
                    errs[name].append(run(cls, nb, y0, 8, 10, 500.0, days)[0])
            lines.append(f"| {days:.0e} | {int(round(days / 500))} | "
                         f"{np.median(errs['double']):.2e} | {np.median(errs['double-double']):.2e} |")
            print(lines[-1], flush=True)
        lines.append("")
    t_old, t_new = recentre_time(DoubleRecentring), recentre_time(FlowComposed)
    lines.append(f"One recentring (5 planets): double {1e6 * t_old:.2f} us, double-double "
                 f"{1e6 * t_new:.2f} us ({t_new / t_old:.2f}x).")
    print(lines[-1])
    cmd = "python benchmarks/bench_kepler_recentre.py " + " ".join(sys.argv[1:])
    head = ["# The composed method's recentring: double-double flow vs double flow", "",
            f"{machine()}, one process. Generated by `{cmd.strip()}` on "
            f"{time.strftime('%Y-%m-%d')}. Load average at the start: {LOAD}. Both recentrings "
            "run on the same starts in turn; position error against the double-double "
            "HBVM(13,10) kepler at h = 250 days of the same start.", ""]
    with open(os.path.join(HERE, "results", "kepler_recentre.md"), "w") as f:
        f.write("\n".join(head + lines) + "\n")


if __name__ == "__main__":
    main()
