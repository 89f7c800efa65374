"""Benchmark (not a test): HBVM composed with the Keplerian flows (issue 48) against heyoka,
SABA(10,6,4), WHFast, IAS15 and plain HBVM, on bench_rebound's scenes.

The composed method (``systems.flow_composed.FlowComposed``: the planets' Keplerian motion in
closed form, HBVM(k, s) on the transformed system, the flows recentred after each step) runs
through the engine and inside REBOUND (``HBVMIntegrator(sim, kepler=True)``: rows "kepler in
REBOUND", what a REBOUND user pays), over the same 200 output times as every peer;
``hbvm_md.reports.rebound_comparison._run_composed`` times what the user pays: the conversion
into the transformed variables, the steps, and the physical state at every output time.  The
scenes, the perturbed starts, the peers and how they are timed are bench_rebound's
(``SCENES``, ``_perturbed_scene``, ``compare_rebound``); position errors against heyoka in
80-bit extended precision at tol 1e-18.

Tables: per scene, medians over ``--repeat`` starts, with each row's ratio to heyoka and the
issue's verdicts (the fastest composed setting at heyoka's energy error x 1.5 and position
error: at most 0.8x heyoka's time; over 1e6 days at SABA(10,6,4)'s energy error or better: at
most SABA's time); then a work-precision table on the outer solar system over 1e5 days
(energy error against wall time, each method over a range of its own accuracy knob).
Writes benchmarks/results/kepler_composed.md.

    python benchmarks/bench_kepler_composed.py [--repeat 5] [--quick]
    python benchmarks/bench_kepler_composed.py --rebound [--repeat 7]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from bench_rebound import SCENES, _perturbed_scene  # noqa: E402

from hbvm_md import compare_rebound  # noqa: E402
from hbvm_md.reports.machine import machine  # noqa: E402
from hbvm_md.reports.peers import import_heyoka  # noqa: E402
from hbvm_md.reports.rebound_comparison import EXTENDED  # noqa: E402

#: per scene of bench_rebound.SCENES: the plain HBVM settings kept as the peer (s, k, dt), the
#: composed settings (s, k, dt), and the REBOUND peers' steps
PLAIN = {0: ((8, None, 500.0),), 1: ((8, None, 500.0), (12, None, 1000.0)), 2: ((8, None, 5.0), (8, None, 6.0))}
KEPLER = {0: ((6, 8, 500.0), (7, 8, 500.0), (8, 9, 500.0), (5, 7, 250.0), (4, 6, 250.0)),
          1: ((6, 8, 500.0), (8, 10, 500.0), (8, 12, 1000.0), (10, 13, 1000.0), (12, 14, 1000.0)),
          2: ((6, 8, 10.0), (8, 10, 16.0), (8, 10, 20.0), (10, 12, 25.0))}
#: the composed method run inside REBOUND (HBVMIntegrator(sim, kepler=True), issue 48 item 4),
#: beside the engine's rows of the same settings
KEPLER_REBOUND = {0: ((6, 8, 500.0), (8, 9, 500.0)), 1: ((6, 8, 500.0), (10, 13, 1000.0)),
                  2: ((8, 10, 16.0),)}
#: the work-precision sweep (outer solar system, 1e5 days): each method's knob
WP_KEPLER = ((4, 5, 500.0), (4, 6, 500.0), (6, 7, 500.0), (6, 8, 500.0), (8, 9, 500.0), (5, 7, 250.0))
WP_PLAIN = ((6, None, 500.0), (6, None, 250.0), (8, None, 500.0), (8, None, 250.0))
WP_PEERS = tuple(("whfast", 4332.6 / d) for d in (20, 50, 100, 200, 400)) + \
    tuple(("saba(10,6,4)", 4332.6 / d) for d in (5, 10, 20, 40)) + \
    tuple(("heyoka", t) for t in (1e-9, 1e-12, 1e-14, None)) + ("ias15",)


def _medians(runs):
    rows = []
    for i, r0 in enumerate(runs[0].rows):
        col = {key: [c.rows[i][key] for c in runs]
               for key in ("max_rel_energy_error", "final_position_diff", "wall_time_s", "steps")}
        rows.append(dict(method=r0["method"], dt=r0["dt"], tol=r0.get("tol"),
                         err=float(np.median(col["max_rel_energy_error"])),
                         pos=float(np.median(col["final_position_diff"])),
                         wall=float(np.median(col["wall_time_s"])),
                         steps=int(np.median(col["steps"])),
                         it=r0.get("iterations_per_step")))
    return rows


def _settings(r):
    if r["method"].startswith("heyoka"):
        return f"tol={r['tol']:.2g}"
    return "dt=adaptive" if r["dt"] is None else f"dt={r['dt']:.4g}"


def run_scene(i, repeat):
    title, scene, t_end, _, peers = SCENES[i]
    nb = scene()
    all_peers = ("ias15", "heyoka") + peers
    runs = [compare_rebound(_perturbed_scene(nb, r), t_end, hbvm=PLAIN[i], peers=all_peers,
                            kepler=KEPLER[i], kepler_rebound=KEPLER_REBOUND[i], n_samples=200,
                            reference=EXTENDED)
            for r in range(repeat)]
    rows = _medians(runs)
    hy = next(r for r in rows if r["method"] == "heyoka")
    saba = next(r for r in rows if r["method"].startswith("saba"))
    lines = [f"## {title}", "",
             "| method | settings | steps | max rel. energy error (median) | position error (AU) | "
             "wall (s) | / heyoka | / SABA(10,6,4) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['method']} | {_settings(r)} | {r['steps']} | {r['err']:.2e} | {r['pos']:.1e} | "
                     f"{r['wall']:.4f} | {r['wall'] / hy['wall']:.2f} | {r['wall'] / saba['wall']:.2f} |")
    # ("kepler" anywhere: two settings of one (k, s) get " dt=..." appended to the label)
    comp = [r for r in rows if "kepler" in r["method"]]
    plain = [r for r in rows if r["method"].startswith("HBVM") and "kepler" not in r["method"]]
    lines.append("")
    for name, group in (("HBVM composed with the Keplerian flows", comp), ("plain HBVM", plain)):
        ok = [r for r in group if r["err"] <= 1.5 * hy["err"] and r["pos"] <= hy["pos"]]
        if ok:
            b = min(ok, key=lambda r: r["wall"])
            lines.append(f"- {name}, fastest at heyoka's errors (energy {1.5 * hy['err']:.2e}, position "
                         f"{hy['pos']:.1e} AU): {b['method']} {_settings(b)}, **{b['wall'] / hy['wall']:.2f}x "
                         f"heyoka's time** (issue's bar: 0.8x).")
        else:
            lines.append(f"- {name}: **no setting reaches heyoka's errors** (energy {1.5 * hy['err']:.2e}, "
                         f"position {hy['pos']:.1e} AU).")
        ok = [r for r in group if r["err"] <= saba["err"]]
        if ok:
            b = min(ok, key=lambda r: r["wall"])
            lines.append(f"- {name}, fastest at SABA(10,6,4)'s energy error ({saba['err']:.2e}) or better: "
                         f"{b['method']} {_settings(b)}, **{b['wall'] / saba['wall']:.2f}x SABA's time**.")
    its = [f"{r['method']} {_settings(r)}: {r['it']:.2f}" for r in comp if r.get("it")]
    lines += ["", "Fixed-point sweeps a step of the composed method: " + "; ".join(its) + ".", ""]
    return lines


def work_precision(repeat):
    title, scene, t_end, _, _ = SCENES[0]
    nb = scene()
    runs = [compare_rebound(_perturbed_scene(nb, r), t_end, hbvm=WP_PLAIN, peers=WP_PEERS,
                            kepler=WP_KEPLER, n_samples=200, reference=EXTENDED)
            for r in range(repeat)]
    rows = sorted(_medians(runs), key=lambda r: r["err"])
    lines = [f"## Work-precision: {title}", "",
             "Every method over a range of its own accuracy knob (steps; heyoka's tolerance; IAS15 at "
             "its default epsilon), sorted by energy error.", "",
             "| max rel. energy error (median) | method | settings | position error (AU) | wall (s) |",
             "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['err']:.2e} | {r['method']} | {_settings(r)} | {r['pos']:.1e} | {r['wall']:.4f} |")
    return lines + [""]


def where_the_time_goes(s=6, k=8, h=500.0, steps=2000):
    """The composed step's time split, measured in this process on the outer solar system:
    the kernel (the Keplerian flows, the interactions, the pull-back by Phi^T) against the
    whole step, and the kernel against plain HBVM's N-body force, per stage row."""
    from integrators import HBVM, Stepper
    from systems import outer_solar_system
    from systems.flow_composed import FlowComposed, composed_gradient
    from systems.nbody import nbody_forces
    nb = outer_solar_system()
    fc = FlowComposed.from_nbody(nb, h)
    st = Stepper(HBVM(k, s), fc, fc.extend(nb.initial_state()), form="full")
    st.run(h, 10, sample_every=10)
    n0 = st.nfev
    t0 = time.perf_counter()
    st.run(h, steps, sample_every=steps)
    step = (time.perf_counter() - t0) / steps
    rows = (st.nfev - n0) / steps
    Y = np.tile(st.y, (k, 1))
    Y[:, fc.dim - 1] = np.linspace(-h / 2, h / 2, k)
    out = np.empty_like(Y)
    q = np.tile(nb.initial_state()[:3 * nb.N], (k, 1))
    f = np.empty_like(q)
    params = nb.separable_kernels()[2]
    composed_gradient(Y, fc._params, out)
    nbody_forces(q, params, f)
    reps = 20000
    t0 = time.perf_counter()
    for _ in range(reps):
        composed_gradient(Y, fc._params, out)
    kern = (time.perf_counter() - t0) / reps / k
    t0 = time.perf_counter()
    for _ in range(reps):
        nbody_forces(q, params, f)
    force = (time.perf_counter() - t0) / reps / k
    return [f"## Where the time goes (outer solar system, HBVM({k},{s}) composed, h = {h:g} days)", "",
            f"A step: {step * 1e6:.1f} us, {rows:.1f} stage rows evaluated ({st.niter / st.nsteps:.2f} "
            f"sweeps); the kernel {kern * 1e9:.0f} ns a row ({kern * 1e9 / fc.N:.0f} ns a planet: flow, "
            f"interactions, pull-back), so {rows * kern / step:.0%} of the step is the kernel. Plain "
            f"HBVM's N-body force: {force * 1e9:.0f} ns a row (the composed kernel {kern / force:.1f}x dearer). (Python "
            "calls of the kernels: each includes numba's dispatch, about 0.3 us a call over "
            f"{k} rows.)", ""]


def rebound_rows(repeat: int) -> list[str]:
    """``--rebound``: the composed method inside REBOUND (``HBVMIntegrator(sim, kepler=True)``)
    beside the engine's run of the same settings, plain HBVM at the same steps and IAS15, on the
    outer solar system over 1e5 days (200 outputs): medians of ``repeat`` runs, all methods
    once per run in turn, positions against IAS15 (no heyoka needed)."""
    settings = ((6, 8, 500.0), (8, 9, 500.0))
    runs = [compare_rebound("outer_solar_system", 1e5, hbvm=((6, 8, 500.0), (8, 9, 500.0)),
                            peers=("ias15",), kepler=settings, kepler_rebound=settings,
                            n_samples=200, reference="ias15") for _ in range(repeat)]
    ias = float(np.median([next(r["wall_time_s"] for r in c.rows if r["method"] == "ias15")
                           for c in runs]))
    lines = ["## The composed method inside REBOUND (outer solar system, 1e5 days)", "",
             "| method | settings | max rel. energy error (median) | position vs IAS15 (AU) | "
             "wall (ms) | / IAS15 |", "|---|---|---|---|---|---|"]
    for i, r0 in enumerate(runs[0].rows):
        w = float(np.median([c.rows[i]["wall_time_s"] for c in runs]))
        e = float(np.median([c.rows[i]["max_rel_energy_error"] for c in runs]))
        x = float(np.median([c.rows[i]["final_position_diff"] for c in runs]))
        lines.append(f"| {r0['method']} | {_settings(r0)} | {e:.2e} | {x:.1e} | {w * 1e3:.1f} | "
                     f"{w / ias:.2f} |")
    return lines + [""]


def eccentric_rows() -> list[str]:
    """``--rebound``: where the exact Keplerian part pays: a Jupiter-mass planet at e = 0.9
    (starting at pericentre) and a second planet (1e-4, a = 3, e = 0.3), G = 1, 100 inner
    orbits at fixed steps of P/f, composed and plain HBVM(8, 6) inside REBOUND, against IAS15
    at epsilon 1e-11 (accuracy only: these runs are not timed)."""
    import rebound
    from hbvm_md import HBVMIntegrator

    def scene():
        sim = rebound.Simulation()
        sim.add(m=1.0)
        sim.add(m=1e-3, a=1.0, e=0.9)
        sim.add(m=1e-4, a=3.0, e=0.3, inc=0.1)
        sim.move_to_com()
        return sim
    T = 100 * 2 * np.pi
    ref = scene()
    ref.integrator, ref.integrator.epsilon = "ias15", 1e-11
    ref.integrate(T)
    lines = ["## An eccentric planet (e = 0.9, Jupiter's mass), 100 orbits, inside REBOUND", "",
             "| method | step | max rel. energy error at the end | position vs IAS15 (epsilon 1e-11) |",
             "|---|---|---|---|"]
    for f in (50, 200, 1000):
        for kepler in (True, False):
            sim = scene()
            E0 = sim.energy()
            HBVMIntegrator(sim, s=6, k=8, dt=2 * np.pi / f, kepler=kepler)
            name = "HBVM(8,6) kepler in REBOUND" if kepler else "HBVM(8,6)"
            try:
                sim.integrate(T)
            except Exception as exc:  # noqa: BLE001 - a refused step is a result here
                lines.append(f"| {name} | P/{f} | refused at t = {sim.t:.3g}: {type(exc).__name__} | - |")
                continue
            x = max(abs(p.x - q.x) + abs(p.y - q.y) + abs(p.z - q.z)
                    for p, q in zip(sim.particles, ref.particles))
            lines.append(f"| {name} | P/{f} | {abs(sim.energy() / E0 - 1):.1e} | {x:.1e} |")
    return lines + [""]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5, help="perturbed starts per method")
    ap.add_argument("--quick", action="store_true", help="the first scene only, 2 starts, no work-precision")
    ap.add_argument("--rebound", action="store_true",
                    help="only the composed method inside REBOUND against the engine, plain HBVM and "
                         "IAS15 (outer solar system, 1e5 days; writes results/kepler_rebound.md)")
    args = ap.parse_args()
    if args.rebound:
        compare_rebound("outer_solar_system", 1e4, hbvm=((8, None, 500.0),), peers=("ias15",),
                        kepler=((6, 8, 500.0),), kepler_rebound=((6, 8, 500.0),), n_samples=10)
        lines = rebound_rows(args.repeat) + eccentric_rows()
        text = ["# HBVM composed with the Keplerian flows inside REBOUND (issue 48, item 4)", "",
                f"{machine()}, one process. Generated by `python benchmarks/bench_kepler_composed.py "
                f"--rebound --repeat {args.repeat}` on {time.strftime('%Y-%m-%d')}: 200 output times, "
                f"`sim.integrate(t_i)` for the REBOUND-driven rows (HBVM, 'kepler in REBOUND', IAS15), "
                f"the engine's Stepper for the 'kepler' rows. Load average at the start: "
                f"{', '.join(f'{x:.1f}' for x in os.getloadavg())} on {os.cpu_count()} cores.", ""] + lines
        print("\n".join(text), flush=True)
        with open(os.path.join(HERE, "results", "kepler_rebound.md"), "w") as f:
            f.write("\n".join(text))
        return
    import_heyoka()            # (the comparison is against heyoka: refuse without it)
    repeat = 2 if args.quick else args.repeat
    out = ["# HBVM composed with the Keplerian flows (issue 48) vs heyoka, SABA(10,6,4), WHFast, IAS15, plain HBVM",
           "", f"{machine()}, one process. Generated by `python benchmarks/bench_kepler_composed.py"
           f"{' --quick' if args.quick else ''}` on {time.strftime('%Y-%m-%d')}. Medians over {repeat} starts "
           f"(bench_rebound's perturbed starts), all methods once per start in turn; the same 200 output "
           f"times for every method; position error against heyoka in 80-bit extended precision. The "
           f"composed method ('kepler' rows) runs through the engine: its wall time includes the "
           f"conversion into its variables and the physical state at every output time; 'kepler in "
           f"REBOUND' rows run it inside REBOUND (HBVMIntegrator(sim, kepler=True), "
           f"sim.integrate at each output time, timed as plain HBVM's). Load average "
           f"at the start: {', '.join(f'{x:.1f}' for x in os.getloadavg())} on {os.cpu_count()} cores.", ""]
    # warm-up: numba's caches of both steps (not integration)
    compare_rebound("outer_solar_system", 1e4, hbvm=((8, None, 500.0),), peers=("ias15",),
                    kepler=((6, 8, 500.0),), kepler_rebound=((6, 8, 500.0),), n_samples=10)
    for i in ((0,) if args.quick else range(len(SCENES))):
        t0 = time.perf_counter()
        lines = run_scene(i, repeat)
        print("\n".join(lines) + f"(scene done in {time.perf_counter() - t0:.0f} s)\n", flush=True)
        out += lines
    lines = where_the_time_goes()
    print("\n".join(lines), flush=True)
    out += lines
    if not args.quick:
        lines = work_precision(repeat)
        print("\n".join(lines), flush=True)
        out += lines
    name = "kepler_composed_quick.md" if args.quick else "kepler_composed.md"
    with open(os.path.join(HERE, "results", name), "w") as f:
        f.write("\n".join(out))


if __name__ == "__main__":
    main()
