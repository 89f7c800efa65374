"""Benchmark (not a test): adaptive steps against the fewest fixed steps that reach the same
error, at every s (issue 58, item 3).

For each scene and s = 1..8 the adaptive run (the one controller, ``core.adapt_step``, at one
epsilon for every s) is measured by the error it reaches; the fixed-step run of the same
HBVM(k, s) that reaches that error with the fewest steps is then found by bisection over the
number of steps (the fixed runs with both checks off, ``error_bound=None, energy_tol=None``:
the method's own error, whatever a check would say).  Reported: the adaptive run's attempted
steps (accepted + rejected) and its error, the fewest fixed steps N reaching it, and the ratio
(the issue's bar: at most 2).

Scenes of the engine (``integrators.integrate``; error: the largest coordinate error of the
positions at the end):

* Kepler e = 0.6 and e = 0.9, one period from pericentre (exact: back at the start);
* Henon-Heiles from q = p = (0.18, 0.18), 20 time units (reference: HBVM(16, 8), 20000 steps);
* the outer solar system of HLW, 1e5 days (reference: HBVM(16, 8), 20000 steps), AU.

Scenes of ASE (``HBVMDynamics``, EMT copper; error: the largest |E - E0| per atom over the
run's 8 fs marks, eV; cost: calculator calls): Cu13 (icosahedron) at 300 K and the hot Cu55
icosahedron at 2400 K (it melts), 200 fs, the adaptive run at an 8 fs timestep, the fixed runs
at 8/m fs (m inner steps a timestep, bisected over m, the energy read at the same 8 fs marks).

    python benchmarks/bench_adaptive_steps.py [--scenes kepler0.6,...] [--s 1,2,...]
        [--epsilon 1e-9] [--md-epsilon ...] [--no-write]

Writes benchmarks/results/adaptive_steps.md (only when run with every scene and s).
"""
from __future__ import annotations

import argparse
import math
import os
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from integrators import HBVM, integrate                                 # noqa: E402
from integrators.kchoice import adaptive_k                              # noqa: E402
from systems import HenonHeiles, Kepler, outer_solar_system            # noqa: E402
from hbvm_md.ase.dynamics import MD_ADAPTIVE_EPSILON                   # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "adaptive_steps.md"
ENGINE_SCENES = ("kepler0.6", "kepler0.9", "henon-heiles", "outer")
MD_SCENES = ("cu13", "cu55")


def engine_scene(name):
    """(system, y0, T, exact final positions or None, k at least, first h)."""
    if name.startswith("kepler"):
        kep = Kepler(float(name[6:]))
        y0 = kep.initial_state()
        return kep, y0, 2 * math.pi, y0[:2].copy(), 1, 0.01
    if name == "henon-heiles":
        hh = HenonHeiles()
        return hh, hh.initial_state(), 20.0, None, 0, 0.1
    if name == "outer":
        nb = outer_solar_system()
        return nb, nb.initial_state(), 1e5, None, 1, 10.0
    raise ValueError(name)


def k_for(system, s, epsilon):
    k = adaptive_k(s, epsilon)
    nu = getattr(system, "polynomial_degree", None)
    if nu is not None:      # (Henon-Heiles: exact for k >= 3 s / 2)
        k = max(k, HBVM.for_polynomial_degree(nu, s).k)
    return k


def final_positions(res, m):
    return np.asarray(res.y[-1][:m], dtype=float)


def fixed_run(method, system, y0, T, n):
    h = T / n
    res = integrate(method, system, y0, h, steps=n, sample_every=n, error_bound=None,
                    energy_tol=None)
    return res


def fewest_fixed(err_of, target, n0, n_max=2 ** 22):
    """The smallest n with err_of(n) <= target, by doubling from n0 then bisection; None
    when even n_max does not reach it."""
    lo, hi = None, max(1, n0)
    while True:
        e = err_of(hi)
        if e <= target:
            break
        lo = hi
        if hi >= n_max:
            return None
        hi = min(n_max, 2 * hi)
    if lo is None:       # n0 reaches it: go down
        while hi > 1:
            trial = max(1, hi // 2)
            if err_of(trial) <= target:
                hi = trial
            else:
                lo = trial
                break
        if lo is None:
            return hi
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if err_of(mid) <= target:
            hi = mid
        else:
            lo = mid
    return hi


def engine_row(name, s, epsilon):
    system, y0, T, exact, _, h0 = engine_scene(name)
    m = y0.size // 2
    k = k_for(system, s, epsilon)
    method = HBVM(k, s)
    if exact is None:
        ref = fixed_run(HBVM(16, 8), system, y0, T, 20000)
        exact = final_positions(ref, m)

    def err_of(n):
        r = fixed_run(method, system, y0, T, n)
        q = final_positions(r, m)
        return float(np.max(np.abs(q - exact))) if np.all(np.isfinite(q)) else math.inf

    res = integrate(method, system, y0, h0, adaptive=True, t_end=T, epsilon=epsilon,
                    sample_every=10 ** 9)
    err = float(np.max(np.abs(final_positions(res, m) - exact)))
    tried = res.steps + res.extra["rejected"]
    n = fewest_fixed(err_of, err, res.steps)
    return dict(scene=name, s=s, k=k, epsilon=epsilon, steps=res.steps,
                rejected=res.extra["rejected"], err=err, fixed=n,
                ratio=tried / n if n else float("nan"))


# -- ASE ------------------------------------------------------------------------------------
def md_atoms(name):
    from ase.cluster import Icosahedron
    from ase.md.velocitydistribution import Stationary, ZeroRotation, thermalize_momenta
    shells, T = {"cu13": (2, 300), "cu55": (3, 2400)}[name]
    atoms = Icosahedron("Cu", noshells=shells)
    atoms.calc = _CountingEMT()
    thermalize_momenta(atoms, temperature_K=T, rng=np.random.default_rng(3))
    Stationary(atoms)
    ZeroRotation(atoms)
    return atoms


def _counting_emt():
    from ase.calculators.emt import EMT

    class CountingEMT(EMT):
        calls = 0

        def calculate(self, *args, **kwargs):
            type(self).calls += 1
            super().calculate(*args, **kwargs)
    return CountingEMT


_CountingEMT = None


def md_run(name, t_end, outer_fs, inner, s, **kw):
    """(max |E - E0| per atom at the 8 fs marks, calculator calls, inner steps, rejected)."""
    from ase import units
    from hbvm_md import HBVMDynamics
    atoms = md_atoms(name)
    n = len(atoms)
    e0 = atoms.get_total_energy()
    dt = outer_fs / inner
    dyn = HBVMDynamics(atoms, dt * units.fs, s=s, **kw)
    worst = [0.0]

    def look():
        worst[0] = max(worst[0], abs(atoms.get_total_energy() - e0) / n)
    dyn.attach(look, interval=inner)
    c0 = _CountingEMT.calls
    dyn.run(int(round(t_end / dt)))
    calls = _CountingEMT.calls - c0
    steps = dyn.inner_steps if dyn.adaptive else dyn.nsteps
    rejected = dyn.inner_rejections if dyn.adaptive else 0
    return worst[0], calls, steps, rejected


def md_row(name, s, epsilon, t_end=200.0, outer=8.0):
    global _CountingEMT
    if _CountingEMT is None:
        _CountingEMT = _counting_emt()
    kw = {} if epsilon is None else {"epsilon": epsilon}
    err, calls, steps, rejected = md_run(name, t_end, outer, 1, s, adaptive=True, **kw)
    costs = {}

    def err_of(m):
        e, c, _, _ = md_run(name, t_end, outer, m, s, error_bound=None, energy_tol=None)
        costs[m] = c
        return e
    m = fewest_fixed(err_of, err, max(1, steps // int(round(t_end / outer))), n_max=32)
    return dict(scene=name, s=s, k=s + 1, epsilon=epsilon, steps=steps, rejected=rejected,
                err=err, fixed=None if m is None else m * int(round(t_end / outer)),
                ratio=(steps + rejected) / (m * int(round(t_end / outer))) if m else float("nan"),
                calls=calls, fixed_calls=costs.get(m),
                call_ratio=calls / costs[m] if m else float("nan"))


def fmt(row):
    fixed = "none (round-off)" if row["fixed"] is None else str(row["fixed"])
    eps = "default" if row["epsilon"] is None else f"{row['epsilon']:g}"
    out = (f"| {row['scene']} | {row['s']} | {row['k']} | {eps} | {row['steps']} "
           f"({row['rejected']}) | {row['err']:.2e} | {fixed} | "
           f"{'< 1' if row['fixed'] is None else format(row['ratio'], '.2f')} |")
    if "calls" in row:
        fc = "-" if row["fixed_calls"] is None else str(row["fixed_calls"])
        out += f" {row['calls']} / {fc} = {row['call_ratio']:.2f} |"
    else:
        out += " |"
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=",".join(ENGINE_SCENES + MD_SCENES))
    ap.add_argument("--s", default="1,2,3,4,5,6,7,8")
    ap.add_argument("--epsilon", type=float, default=1e-9)
    ap.add_argument("--md-epsilon", type=float, default=None,
                    help="ASE's epsilon (default: HBVMDynamics' own)")
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args(argv)
    scenes = a.scenes.split(",")
    ss = [int(x) for x in a.s.split(",")]
    head = ["| scene | s | k | epsilon | adaptive steps (rejected) | error reached | fewest fixed "
            "steps reaching it | ratio (attempted / fixed) | calculator calls adaptive / fixed |",
            "|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(head), flush=True)
    rows = []
    for name in scenes:
        for s in ss:
            row = (md_row(name, s, a.md_epsilon) if name in MD_SCENES
                   else engine_row(name, s, a.epsilon))
            rows.append(row)
            print(fmt(row), flush=True)
    if not a.no_write and set(scenes) == set(ENGINE_SCENES + MD_SCENES) and len(ss) == 8:
        load = os.getloadavg()
        worst = max(r["ratio"] for r in rows if not math.isnan(r["ratio"]))
        text = ["# Adaptive steps against the fewest fixed steps", "",
                f"Generated by `python benchmarks/bench_adaptive_steps.py` (load average "
                f"{load[0]:.1f} on {os.cpu_count()} cores). Engine scenes at epsilon = "
                f"{a.epsilon:g} for every s, error: the largest position error at the end; ASE "
                f"scenes (EMT copper, 8 fs timestep, 200 fs) at "
                f"{'epsilon = %g' % a.md_epsilon if a.md_epsilon else 'HBVMDynamics default epsilon (%g)' % MD_ADAPTIVE_EPSILON}, "
                f"error: the largest energy error per atom (eV) at the 8 fs marks. The fixed "
                f"runs have both checks off. Largest ratio: {worst:.2f} (bar: 2).", ""]
        text += head + [fmt(r) for r in rows]
        RESULTS.write_text("\n".join(text) + "\n")
        print("written to", RESULTS)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
