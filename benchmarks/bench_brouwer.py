"""Brouwer's law for HBVM on Kepler: the round-off energy error grows like sqrt(n).

An ensemble of Kepler orbits (e = 0.6, the same orbit rotated by random angles, so the
rounding errors differ while the exact energy is the same) is integrated for 1e7 steps with
HBVM(k, s) on the compiled fast path, with k chosen at round-off by
:func:`integrators.kchoice.choose_k` over one period.  The root-mean-square relative energy error over the ensemble
is fitted against the step count on a log-log scale; Brouwer's law predicts slope 1/2
(a random walk of rounding errors; Kahan-compensated sums keep the systematic part out).

Usage::

    python benchmarks/bench_brouwer.py [--steps 1e7] [--members 24] [--out docs/figures]

Writes brouwer.png and brouwer.json into the output folder and prints the fitted slope.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from integrators import HBVM, integrate
from integrators.kchoice import choose_k, period_steps
from systems import Kepler


def rotated(y, angle):
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, -s], [s, c]])
    return np.concatenate([R @ y[:2], R @ y[2:]])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=float, default=1e7)
    ap.add_argument("--members", type=int, default=24)
    ap.add_argument("--s", type=int, default=2)
    ap.add_argument("--per-period", type=int, default=200)
    ap.add_argument("--samples", type=int, default=4000)
    ap.add_argument("--out", default="docs/figures")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    steps = int(a.steps)
    kep = Kepler(0.6)
    y0 = kep.initial_state()
    h = 2 * np.pi / a.per_period
    kc = choose_k(kep, y0, a.s, h, period_steps(2 * np.pi, h))
    m = HBVM(kc.k, a.s)
    every = max(1, steps // a.samples)
    rng = np.random.default_rng(a.seed)
    errs = []
    wall = 0.0
    t0 = time.perf_counter()
    for i in range(a.members):
        yi = rotated(y0, rng.uniform(0, 2 * np.pi))
        r = integrate(m, kep, yi, h, steps, sample_every=every)
        wall += r.wall_time
        errs.append((r.energy - r.energy[0]) / abs(r.energy[0]))
        print(f"member {i + 1}/{a.members}: {r.path}, {1e6 * r.wall_time / steps:.3f} us/step, "
              f"final rel dE {errs[-1][-1]:.2e}", flush=True)
    E = np.array(errs)
    n = np.arange(E.shape[1]) * every
    rms = np.sqrt(np.mean(E ** 2, axis=0))
    # the energy evaluation itself has a rounding noise of a few ulps: fit where the walk is
    # above it, from 1e-3 of the run on
    sel = n >= max(every, steps // 1000)
    slope, icpt = np.polyfit(np.log10(n[sel]), np.log10(rms[sel]), 1)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    res = dict(method=repr(m), k_reason=kc.reason, h=h, steps=steps, members=a.members, slope=float(slope),
               intercept=float(icpt), rms_final=float(rms[-1]), max_final=float(np.max(np.abs(E[:, -1]))),
               us_per_step=1e6 * wall / (steps * a.members), total_seconds=time.perf_counter() - t0,
               command=f"python benchmarks/bench_brouwer.py --steps {a.steps:g} --members {a.members}")
    (out / "brouwer.json").write_text(json.dumps(res, indent=2))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.5, 4.2), dpi=120)
    for e in E[:6]:
        ax.loglog(n[1:], np.abs(e[1:]) + 1e-18, lw=0.4, alpha=0.5, color="grey")
    ax.loglog(n[1:], rms[1:], lw=1.5, label=f"RMS over {a.members} orbits")
    ax.loglog(n[sel], 10 ** (icpt + slope * np.log10(n[sel])), "--", label=f"fit: slope {slope:.3f}")
    ax.set_xlabel("steps n")
    ax.set_ylabel("relative energy error")
    ax.set_title(f"Brouwer's law: {m!r} on Kepler e=0.6, h=P/{a.per_period}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "brouwer.png")
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
