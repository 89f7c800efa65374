"""Benchmark (not a test): the per-step cost of the engine's default energy check.

The same fixed-step runs with ``energy_tol=None`` (no check), a strict tolerance (one potential
evaluation a step) and the default ``"auto"`` (:func:`integrators.engine.energy_check`: strict
for a method exact for the polynomial H, the energy-flow check otherwise), interleaved, the
best process time of ``--repeat`` runs each (the machine is shared).  The final states are
compared bit for bit: the check only refuses steps, it never changes one.

``--scenes``: no false alarm on the project's benchmark scenes.  Every fixed-step HBVM/Gauss
setting of the benchmarks, reports, examples and hard cases on which the check of a method not
exact for H (the energy-flow rule, ``integrators.core.FLOW_FRACTION``) examines steps -- those
whose energy error is above round-off: Gauss(s) = HBVM(s, s) and coarse steps -- is run at its
recorded setting with the default check (refused or not, the max relative energy error), and
the same steps again with the check off, step by step, to measure its margin: the largest
|H(y1) - H(y0)| / (FLOW_FRACTION x the energy the step moved between T and V) over the steps
whose change is above ``NOT_A_SOLUTION`` (a step is refused above 1).  Writes
benchmarks/results/energy_check.md.  The other benchmark runs are not examined by this rule:
REBOUND with k chosen at attach and methods exact for a polynomial H have the strict check;
s = 1 keeps its rule; the rest change H by round-off, below ``NOT_A_SOLUTION``.

    python benchmarks/bench_energy_check.py [--repeat 15]
    python benchmarks/bench_energy_check.py --scenes [--no-ase]
"""
from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time
import warnings

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from integrators import (HBVM, AccumulatedErrorWarning, StepError, Stepper,  # noqa: E402
                         integrate)
from integrators.core import FLOW_FRACTION, energy_flow, weighted_kinetic  # noqa: E402
from integrators.engine import NOT_A_SOLUTION, NOT_A_SOLUTION_S1, method_arrays  # noqa: E402
from systems import FPU, HenonHeiles, Kepler, outer_solar_system         # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "energy_check.md"


def flow_margin(method, system, y0, h, steps, **options) -> dict:
    """The energy-flow rule's margin over ``steps`` steps of h from y0 (separable form).

    The steps are taken by :class:`integrators.Stepper` with the check off (the same steps:
    the check only refuses), and for each the rule's two tests are evaluated as
    :func:`integrators.loop.run` does: rel = |dH| / (|T1| + |V1|) above NOT_A_SOLUTION (s = 1:
    NOT_A_SOLUTION_S1) and ratio = |dH| / (FLOW_FRACTION x :func:`integrators.core.
    energy_flow`) above 1.  Returns the largest ratio over the steps with rel above the floor
    (``worst``; 0 when the rule examined none), their number (``examined``) and the largest
    rel (``largest_change``)."""
    # (all checks off: the same steps a checked run takes until it would refuse, measured)
    st = Stepper(method, system, np.asarray(y0, dtype=float), energy_tol=None, error_bound=None,
                 **options)
    kin_w = st.binding.kin_w
    m = kin_w.shape[0]
    (_, _), (Wp, Cp) = method_arrays(method)
    W, I = Wp[0], Cp[2]
    frac = FLOW_FRACTION[min(method.s, 3) - 1]
    floor = NOT_A_SOLUTION if method.s > 1 else NOT_A_SOLUTION_S1
    y = st.y.copy()
    H0 = float(system.energy(y))
    H_start = H0
    worst, examined, largest, drift = 0.0, 0, 0.0, 0.0
    tmean, tmax, nT = 0.0, 0.0, 0
    for _ in range(steps):
        y1 = st.step(h)
        gamma = st.save_state()[2]
        T1 = weighted_kinetic(y1[m:], kin_w)
        H1 = float(system.energy(y1))
        change = abs(H1 - H0)
        rel = change / (abs(T1) + abs(H1 - T1))
        largest = max(largest, rel)
        # the run's drift (integrators.core.DRIFT_BOUND): H against its start, over the run's
        # kinetic scale max(T, <T> sqrt(<T> / Tmax)), <T> and Tmax the mean and the largest of
        # T at the steps' ends so far
        nT += 1
        tmean += (abs(T1) - tmean) / nT
        tmax = max(tmax, abs(T1))
        drift = max(drift, abs(H1 - H_start) / max(abs(T1), tmean * np.sqrt(tmean / tmax)))
        if rel > floor:
            examined += 1
            flow = energy_flow(False, y, kin_w, h, gamma, W, I, np.zeros((0, 0)))
            worst = max(worst, change / (frac * flow) if flow > 0 else np.inf)
        y, H0 = y1, H1
    return dict(worst=worst, examined=examined, largest_change=largest, drift=drift)


def engine_scenes():
    """(source, setting, method, system, y0, h, steps, margin steps): the recorded fixed-step
    settings whose energy error is above round-off (the flow rule examines their steps)."""
    kep, oss, fpu = Kepler(0.6), outer_solar_system(), FPU(3, 50.0)
    hh_wp, hh_ex = HenonHeiles(), HenonHeiles(y0=[0.0, 0.1, 0.5, 0.1])
    v = (2 * 0.1666) ** 0.5
    y_chaos = np.array([0.0, 0.0, v * np.cos(0.3), v * np.sin(0.3)])
    P = 2 * np.pi
    out = []
    for s_, per in ((2, 25), (2, 50), (2, 100), (2, 200), (4, 25), (4, 50), (6, 25)):
        out.append(("work-precision (`hbvm-md bench`)", f"Kepler e=0.6, Gauss({s_}), h = P/{per}, "
                    "100 periods", HBVM(s_, s_), kep, kep.initial_state(), P / per, 100 * per,
                    100 * per))
    for s_, n in ((2, 231), (2, 462), (4, 231)):
        out.append(("work-precision", f"outer solar system, Gauss({s_}), h = {1e5 / n:.4g} d, "
                    "1e5 d", HBVM(s_, s_), oss, oss.initial_state(), 1e5 / n, n, n))
    for s_, n in ((2, 500), (2, 1000), (4, 500)):
        out.append(("work-precision", f"FPU m=3 omega=50, Gauss({s_}), h = {20 / n:g}, T = 20",
                    HBVM(s_, s_), fpu, fpu.initial_state(), 20 / n, n, n))
    for s_, n in ((2, 250), (2, 500), (4, 250)):
        out.append(("work-precision", f"Henon-Heiles, Gauss({s_}), h = {200 / n:g}, T = 200",
                    HBVM(s_, s_), hh_wp, hh_wp.initial_state(), 200 / n, n, n))
    for s_ in (2, 3, 4, 5, 6, 7, 8):
        out.append(("bench_kepler", f"Kepler e=0.6, Gauss({s_}), h = P/100, 1000 periods",
                    HBVM(s_, s_), kep, kep.initial_state(), P / 100, 100000, 1000))
    out.append(("bench_energy_check", "Kepler e=0.6, HBVM(2, 2), h = P/100", HBVM(2, 2), kep,
                kep.initial_state(), P / 100, 20000, 20000))
    for s_ in (2, 3):
        out.append(("examples/hbvm_vs_gauss.py", f"Henon-Heiles, Gauss({s_}), h = 0.5",
                    HBVM(s_, s_), hh_ex, hh_ex.initial_state(), 0.5, 20000, 20000))
        out.append(("examples/hbvm_vs_gauss.py", f"FPU m=3 omega=50, Gauss({s_}), h omega = 1",
                    HBVM(s_, s_), fpu, fpu.initial_state(), 1 / 50, 20000, 20000))
    out.append(("hard case chaotic-henon-heiles", "Henon-Heiles H=0.1666, Gauss(2), h = 0.1",
                HBVM(2, 2), HenonHeiles(y_chaos), y_chaos, 0.1, 10000, 10000))
    for e, n in ((0.9, 2000), (0.99, 20000)):
        ke = Kepler(e)
        out.append(("hard case eccentric-kepler", f"Kepler e={e}, HBVM(10, 3), h = P/{n}, "
                    "1000 periods", HBVM(10, 3), ke, ke.initial_state(), P / n, 1000 * n, 2 * n))
    return out


def ase_scenes():
    """(source, setting, atoms factory, s, k, dt in fs, steps) of HBVMDynamics (s, k None: its
    defaults): the EMT copper rows of bench_md_cost at its longest step for each s >= 2 (0.2 ps;
    its other rows err less, below NOT_A_SOLUTION a step) and of
    examples/md_cluster_and_copper.py (32 atoms, 600 K, 5 fs, 100 steps), and
    bench_ase_constraints' quartic cluster with Hookean terms (a kink in H where the pair's
    spring engages: not a polynomial)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_ase_constraints
    import bench_md_cost
    from ase.build import bulk
    from ase.calculators.emt import EMT

    from hbvm_md.reports.md_comparison import maxwell_boltzmann

    def example_copper():
        atoms = bulk("Cu", cubic=True) * (2, 2, 2)
        maxwell_boltzmann(atoms, 600.0, seed=0)
        atoms.calc = EMT()
        return atoms
    out = [("bench_md_cost", f"EMT copper 108 atoms, HBVM({k}, {s_}), {dt:g} fs, 0.2 ps",
            bench_md_cost.copper, s_, k, dt, int(round(200 / dt)))
           for s_, k, dt in ((2, 2, 10.0), (2, 3, 10.0), (3, 4, 20.0))]
    out.append(("examples/md_cluster_and_copper.py", "EMT copper 32 atoms 600 K, HBVM(3, 2), 5 fs",
                example_copper, 2, 3, 5.0, 100))

    def hookean_cluster():
        atoms, _ = bench_ase_constraints.quartic()
        atoms.calc = type(atoms.calc)(atoms.calc.coefficients)
        atoms.set_constraint(bench_ase_constraints.CONSTRAINTS["Hookean (pair + tether)"](atoms))
        return atoms
    out.append(("bench_ase_constraints", "quartic cluster 147 atoms + Hookean (pair + tether), "
                "defaults (HBVM(3, 2)), 10 fs", hookean_cluster, None, None, 10.0, 80))
    return out


def _ase_run(make, s, k, dt_fs, steps):
    """(refused message or None, max relative energy error, its max |dE| per atom in eV,
    margin) of HBVMDynamics."""
    from ase import units

    from hbvm_md import HBVMDynamics
    kw = {} if s is None else dict(s=s, k=k)
    atoms = make()
    dyn = HBVMDynamics(atoms, dt_fs * units.fs, **kw)
    energies = [atoms.get_total_energy()]
    dyn.attach(lambda: energies.append(atoms.get_total_energy()))
    refused = None
    try:
        dyn.run(steps)
    except StepError as err:
        refused = f"{type(err).__name__} at step {dyn.nsteps}"
    E = np.array(energies)
    scale = abs(atoms.get_kinetic_energy()) + abs(atoms.get_potential_energy())
    # the same steps by the engine, on the system the dynamics built (its separable form)
    atoms = make()
    dyn = HBVMDynamics(atoms, dt_fs * units.fs, **kw)
    dyn._ensure_stepper(dyn._constraints(atoms))
    mg = flow_margin(dyn.method, dyn._system, dyn._stepper.y, dt_fs * units.fs, steps,
                     form="separable")
    dE = float(np.max(np.abs(E - E[0])))
    return refused, dE / scale, dE / len(atoms), mg


def scenes_main(ase: bool) -> int:
    load = os.getloadavg()
    lines = ["# The energy check on the benchmark scenes: no false alarm", "",
             f"Generated by `python benchmarks/bench_energy_check.py --scenes"
             f"{'' if ase else ' --no-ase'}` ({time.strftime('%Y-%m-%d')}; load average "
             f"{load[0]:.1f} on {os.cpu_count()} cores).  Every fixed-step setting of the "
             "benchmarks, reports, examples and hard cases whose energy error is above round-off "
             "(the steps the rule of a method not exact for H examines), at its recorded setting "
             "with the default checks (`energy_tol=\"auto\"`, and the step's own error estimate: "
             "the coarse Gauss points the diagrams measure with the checks off are refused by it).  "
             "*largest drift*: the run's energy against its start over max(T, <T> sqrt(<T> / Tmax)), the checks off "
             "(integrators.core.DRIFT_BOUND refuses above 1e-3).  *margin*: the largest "
             "|dH| / (FLOW_FRACTION x the energy the step moved between T and V) over the steps "
             f"whose |dH| / (|T| + |V|) exceeds NOT_A_SOLUTION = {NOT_A_SOLUTION:g}, the check off "
             "(a step is refused above 1; 0: the rule examined no step), over the first *margin "
             f"steps* of the run.  FLOW_FRACTION (s = 1, 2, >= 3) = {FLOW_FRACTION}.", "",
             "| from | setting | steps | refused | max rel. energy error | margin | examined steps "
             "| margin steps | largest drift |", "|---|---|---|---|---|---|---|---|---|"]
    refusals = 0
    for src, setting, method, system, y0, h, steps, msteps in engine_scenes():
        try:
            # the energy sampled about as its source samples it (a Gauss method's error
            # oscillates within a period): 200 samples a run, at least every 10 steps;
            # once a period on the hard case's 2e6 and 2e7 steps
            every = max(1, min(10, steps // 200)) if steps <= 200000 else steps // 1000
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", AccumulatedErrorWarning)
                res = integrate(method, system, y0, h, steps, sample_every=every)
            warned = [w for w in caught if w.category is AccumulatedErrorWarning]
            refused, err = "no", f"{res.max_energy_error:.2e}"
            if warned:
                refused = f"**warned**: accumulated estimate {res.error_estimate:.2g}"
                refusals += 1
        except StepError as exc:
            refused, err = f"**yes**: {type(exc).__name__} at t={exc.t:.4g}", "-"
            refusals += 1
        mg = flow_margin(method, system, y0, h, msteps)
        lines.append(f"| {src} | {setting} | {steps} | {refused} | {err} | {mg['worst']:.3g} | "
                     f"{mg['examined']} | {msteps} | {mg['drift']:.2g} |")
        print(lines[-1], flush=True)
    if ase:
        for src, setting, make, s, k, dt, steps in ase_scenes():
            refused, err, per_atom, mg = _ase_run(make, s, k, dt, steps)
            refusals += refused is not None
            lines.append(f"| {src} | {setting} | {steps} | {'no' if refused is None else '**yes**: ' + refused} "
                         f"| {err:.2e} ({per_atom:.1e} eV/atom) | {mg['worst']:.3g} | "
                         f"{mg['examined']} | {steps} | {mg['drift']:.2g} |")
            print(lines[-1], flush=True)
    lines += ["", f"Refused or warned (AccumulatedErrorWarning): {refusals}."]
    RESULTS.write_text("\n".join(lines) + "\n")
    print(f"Refused or warned: {refusals}; written to {RESULTS.relative_to(ROOT)}")
    return 1 if refusals else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--scenes", action="store_true",
                    help="the benchmark scenes' settings under the default check (no timing)")
    ap.add_argument("--no-ase", action="store_true", help="with --scenes: skip the EMT copper runs")
    args = ap.parse_args(argv)
    if args.scenes:
        return scenes_main(not args.no_ase)
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
