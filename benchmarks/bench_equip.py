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
"""
from __future__ import annotations

import argparse
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--starts", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="a tenth of the steps")
    a = ap.parse_args()
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
