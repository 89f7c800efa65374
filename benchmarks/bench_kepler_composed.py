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
error: at most 0.8x heyoka's time; over 1e6 days at SABA(10,6,4)'s energy error or better,
and at its position error or better (equal accuracy in the solution too): at most SABA's
time); then a work-precision table on the outer solar system over 1e5 days (energy error
against wall time, each method over a range of its own accuracy knob).
Writes benchmarks/results/kepler_composed.md.

    python benchmarks/bench_kepler_composed.py [--repeat 5] [--quick | --wp-only | --plot-only]
    python benchmarks/bench_kepler_composed.py --rebound [--repeat 7]

The work-precision run also draws ``docs/figures/kepler_composed_wp.png`` (energy error and
position error against wall time, one line per method) and writes its data beside it
(``kepler_composed_wp.csv``); ``--plot-only`` redraws the figure from that file.
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
#: (Sun and 8 planets: higher orders at longer steps are faster at heyoka's errors; steps that
#: divide the 500-day output interval exactly in binary; k = s, Gauss(11), keeps the energy
#: to round-off there too: its order 22 leaves no error above it at these steps)
PLAIN = {0: ((8, None, 500.0),), 1: ((8, None, 500.0), (12, None, 1000.0)),
         2: ((8, None, 5.0), (8, None, 6.0), (10, None, 12.5), (11, None, 15.625), (11, 12, 15.625),
             (11, 11, 15.625))}
KEPLER = {0: ((6, 8, 500.0), (7, 8, 500.0), (8, 9, 500.0), (5, 7, 250.0), (4, 6, 250.0)),
          1: ((6, 8, 500.0), (8, 10, 500.0), (8, 12, 1000.0), (10, 13, 1000.0), (12, 14, 1000.0)),
          2: ((6, 8, 10.0), (8, 10, 16.0), (8, 10, 20.0), (10, 12, 25.0))}
#: the composed method run inside REBOUND (HBVMIntegrator(sim, kepler=True), issue 48 item 4),
#: beside the engine's rows of the same settings
KEPLER_REBOUND = {0: ((6, 8, 500.0), (8, 9, 500.0)), 1: ((6, 8, 500.0), (10, 13, 1000.0)),
                  2: ((8, 10, 16.0),)}
#: the work-precision sweep (outer solar system, 1e5 days): each method's knob, chosen so that
#: every line crosses energy errors from about 1e-8 to round-off where the method can (plain
#: HBVM keeps the energy to round-off at every resolved step: its knob moves only the position
#: error and the time)
WP_KEPLER = ((4, 5, 500.0), (4, 6, 500.0), (5, 7, 500.0), (6, 7, 500.0),
             (6, 8, 500.0), (8, 9, 500.0), (5, 7, 250.0))
WP_PLAIN = ((4, None, 500.0), (6, None, 500.0), (6, None, 250.0), (8, None, 500.0), (8, None, 250.0))
WP_PEERS = tuple(("whfast", 4332.6 / d) for d in (20, 50, 100, 200, 400, 800, 1600)) + \
    tuple(("saba(10,6,4)", 4332.6 / d) for d in (5, 10, 20, 40, 80)) + \
    tuple(("heyoka", t) for t in (1e-9, 1e-10, 1e-12, 1e-13, 1e-14, None)) + ("ias15",)
#: the figure's families (a row's method label -> the line it belongs to), in legend order
FAMILIES = ("WHFast", "SABA(10,6,4)", "IAS15", "heyoka", "HBVM", "HBVM composed (kepler)")
FIGURE = os.path.join(os.path.dirname(HERE), "docs", "figures", "kepler_composed_wp")


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


#: the issue's must-show verdicts, one table row each, filled by run_scene
VERDICTS = []


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
            VERDICTS.append(f"| {title} | {name} | at heyoka's energy (x1.5) and position errors: "
                            f"at most 0.8x heyoka's time | {b['wall'] / hy['wall']:.2f}x ({b['method']} "
                            f"{_settings(b)}) | {'met' if b['wall'] <= 0.8 * hy['wall'] else '**not met**'} |")
        else:
            lines.append(f"- {name}: **no setting reaches heyoka's errors** (energy {1.5 * hy['err']:.2e}, "
                         f"position {hy['pos']:.1e} AU).")
            VERDICTS.append(f"| {title} | {name} | at heyoka's energy (x1.5) and position errors: "
                            f"at most 0.8x heyoka's time | no setting reaches them | **not met** |")
        # (and at SABA's position error or better: equal accuracy in the solution too, so that a
        # setting too coarse to follow the planets cannot pass on its energy alone)
        ok = [r for r in group if r["err"] <= saba["err"] and r["pos"] <= saba["pos"]]
        if ok:
            b = min(ok, key=lambda r: r["wall"])
            lines.append(f"- {name}, fastest at SABA(10,6,4)'s energy error ({saba['err']:.2e}) and position "
                         f"error ({saba['pos']:.1e} AU) or better: "
                         f"{b['method']} {_settings(b)}, **{b['wall'] / saba['wall']:.2f}x SABA's time**.")
        if t_end >= 1e6:        # (the SABA bar is over 1e6 days)
            verdict = (f"{ok and min(r['wall'] for r in ok) / saba['wall']:.2f}x" if ok else
                       "no setting reaches it")
            VERDICTS.append(f"| {title} | {name} | at SABA(10,6,4)'s energy and position errors or better: at most "
                            f"SABA's time | {verdict} | "
                            f"{'met' if ok and min(r['wall'] for r in ok) <= saba['wall'] else '**not met**'} |")
    its = [f"{r['method']} {_settings(r)}: {r['it']:.2f}" for r in comp if r.get("it")]
    lines += ["", "Fixed-point sweeps a step of the composed method: " + "; ".join(its) + ".", ""]
    return lines


def family(method):
    """The figure's line of a row (:data:`FAMILIES`)."""
    if method.startswith("whfast"):
        return "WHFast"
    if method.startswith("saba"):
        return "SABA(10,6,4)"
    if method.startswith("heyoka"):
        return "heyoka"
    if method.startswith("ias15"):
        return "IAS15"
    return "HBVM composed (kepler)" if "kepler" in method else "HBVM"


def work_precision(repeat, command="python benchmarks/bench_kepler_composed.py"):
    title, scene, t_end, _, _ = SCENES[0]
    nb = scene()
    runs = [compare_rebound(_perturbed_scene(nb, r), t_end, hbvm=WP_PLAIN, peers=WP_PEERS,
                            kepler=WP_KEPLER, n_samples=200, reference=EXTENDED)
            for r in range(repeat)]
    rows = sorted(_medians(runs), key=lambda r: r["err"])
    for r in rows:
        r["settings"] = _settings(r)
    write_csv(rows, FIGURE + ".csv")
    plot(rows, FIGURE + ".png", f"{title}, medians of {repeat} perturbed starts, 200 outputs", command)
    lines = [f"## Work-precision: {title}", "",
             "Every method over a range of its own accuracy knob (steps; heyoka's tolerance; IAS15 at "
             "its default epsilon), sorted by energy error. The same rows are the figure "
             "`docs/figures/kepler_composed_wp.png` (and `.csv`), drawn by this script from this run.", "",
             "| max rel. energy error (median) | method | settings | position error (AU) | wall (s) |",
             "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['err']:.2e} | {r['method']} | {_settings(r)} | {r['pos']:.1e} | {r['wall']:.4f} |")
    return lines + [""]


def write_csv(rows, path):
    """The work-precision medians, one row a setting (what :func:`plot` draws)."""
    import csv
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(("family", "method", "settings", "max_rel_energy_error", "position_error_au", "wall_s"))
        for r in rows:
            w.writerow((family(r["method"]), r["method"], _settings(r), repr(r["err"]), repr(r["pos"]),
                        repr(r["wall"])))


def read_csv(path):
    import csv
    with open(path) as f:
        return [dict(method=r["method"], settings=r["settings"], err=float(r["max_rel_energy_error"]),
                     pos=float(r["position_error_au"]), wall=float(r["wall_s"]))
                for r in csv.DictReader(f)]


def _front(points):
    """The points no other point beats in both time and error (the line drawn), by time."""
    pts = sorted(points)
    out, best = [], np.inf
    for w, e in pts:
        if e < best:
            out.append((w, e))
            best = e
    return out


def plot(rows, path, subtitle, command="python benchmarks/bench_kepler_composed.py --plot-only"):
    """Two panels against wall time, log-log: the max relative energy error over the run and
    the final position error (a method can keep the energy and still drift along the orbit).
    Every setting is a marker; each method's line joins its settings that no other of its
    settings beats in both time and error."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12.4, 4.8))
    styles = dict(zip(FAMILIES, ("C0-o", "C1-s", "C2-D", "C3-^", "C4-v", "C5-*")))
    floor = 1e-16                       # (an error of 0 would leave the log axis)
    for ax, key, label in ((axes[0], "err", "max relative energy error over the run"),
                           (axes[1], "pos", "position error at t_end [AU] (vs heyoka, 80-bit)")):
        for fam in FAMILIES:
            pts = [(r["wall"], max(r[key], floor)) for r in rows if family(r["method"]) == fam]
            if not pts:
                continue
            st = styles[fam]
            ax.loglog([p[0] for p in pts], [p[1] for p in pts], st[:2] + st[3:], linestyle="none",
                      alpha=0.45, markersize=5)
            fr = _front(pts)
            ax.loglog([p[0] for p in fr], [p[1] for p in fr], st, label=fam, markersize=6)
            # (HBVM's knob is (k, s) and the step: say which, where the points spread apart)
            if fam.startswith("HBVM") and key == "pos":
                for r in rows:
                    if family(r["method"]) == fam:
                        ax.annotate(r["method"].split(" ")[0][4:] + " " + r["settings"].replace("dt=", "h="),
                                    (r["wall"], max(r[key], floor)), textcoords="offset points",
                                    xytext=(4, -3), fontsize=5.5, color=st[:2], alpha=0.8)
        ax.set_xlabel("wall time [s] (setup included)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        if key == "err":
            lo, hi = ax.get_ylim()
            ax.set_ylim(min(lo, 1e-16), max(hi, 1e-7))
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Work-precision: {subtitle}\n({command})", fontsize=10)
    fig.tight_layout()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fig.savefig(path, dpi=110)


def _timers():
    """Compiled loops that time the composed kernel's parts on the same rows (numba; built on
    first use): the Keplerian flows alone, the pull-backs alone (from the scalars one flow
    kept), the interactions alone, the whole kernel, plain HBVM's N-body force, the recentring
    hook and the energy (the step's energy check calls it once a step)."""
    from numba import njit
    from integrators.kepler_flow import SAVED, kepler_pullback, kepler_step_saved
    from systems.flow_composed import (_header, _interaction_gradient, _massive, composed_energy,
                                       composed_gradient, composed_recentre)
    from systems.nbody import nbody_forces

    @njit
    def flows(Y, params, reps):
        N, G, m0, ms, mu, m = _header(params)
        sv = np.empty((N, SAVED))
        acc = 0.0
        its = 0
        for _ in range(reps):
            for r in range(Y.shape[0]):
                for i in range(N):
                    mi = ms[i]
                    a, b, c, d, e, f, it = kepler_step_saved(
                        Y[r, 3 * i], Y[r, 3 * i + 1], Y[r, 3 * i + 2], Y[r, m + 3 * i] / mi,
                        Y[r, m + 3 * i + 1] / mi, Y[r, m + 3 * i + 2] / mi, mu, Y[r, m - 1], sv, i)
                    acc += a
                    its += it
        return acc, its

    @njit
    def pullbacks(Y, params, reps):
        N, G, m0, ms, mu, m = _header(params)
        sv = np.empty((Y.shape[0], N, SAVED))
        for r in range(Y.shape[0]):
            for i in range(N):
                mi = ms[i]
                kepler_step_saved(Y[r, 3 * i], Y[r, 3 * i + 1], Y[r, 3 * i + 2], Y[r, m + 3 * i] / mi,
                                  Y[r, m + 3 * i + 1] / mi, Y[r, m + 3 * i + 2] / mi, mu, Y[r, m - 1],
                                  sv[r], i)
        acc = 0.0
        for _ in range(reps):
            for r in range(Y.shape[0]):
                for i in range(N):
                    mi = ms[i]
                    acc += kepler_pullback(Y[r, 3 * i], Y[r, 3 * i + 1], Y[r, 3 * i + 2],
                                           Y[r, m + 3 * i] / mi, Y[r, m + 3 * i + 1] / mi,
                                           Y[r, m + 3 * i + 2] / mi, sv[r], i, 1e-9, 2e-9, 3e-9,
                                           1e-12, acc * 1e-300, 1e-12)[0]
        return acc

    @njit
    def interactions(Y, params, reps):
        N, G, m0, ms, mu, m = _header(params)
        x = np.empty((N, 3))
        v = np.empty((N, 3))
        gx = np.empty((N, 3))
        gp = np.empty(3)
        massive = _massive(params)
        for i in range(N):
            for a in range(3):
                x[i, a] = Y[0, 3 * i + a]
                v[i, a] = Y[0, m + 3 * i + a] / ms[i]
        acc = 0.0
        for _ in range(reps):
            for r in range(Y.shape[0]):
                x[0, 0] += acc * 1e-300
                acc += _interaction_gradient(x, v, ms, G, m0, gx, gp, massive)
        return acc

    @njit
    def kernel(Y, params, out, reps):
        for _ in range(reps):
            composed_gradient(Y, params, out)

    @njit
    def force(q, params, f, reps):
        for _ in range(reps):
            nbody_forces(q, params, f)

    @njit
    def recentre(y, cy, gamma, h, params, reps):
        m = y.shape[0] // 2
        for _ in range(reps):
            y[m - 1] = 0.5 * h          # (the end of a step: a flow over h each time)
            composed_recentre(y, cy, gamma, h, params)

    @njit
    def energy(y, params, reps):
        acc = 0.0
        for _ in range(reps):
            acc += composed_energy(y, params)
        return acc

    return flows, pullbacks, interactions, kernel, force, recentre, energy


def _best(fn, *args, runs=5):
    fn(*args[:-1], 1)                   # (compile)
    best = np.inf
    for _ in range(runs):
        t0 = time.perf_counter()
        res = fn(*args)
        best = min(best, time.perf_counter() - t0)
    return best, res


def where_the_time_goes(s=6, k=8, h=500.0, steps=2000):
    """The composed step's time split, measured in this process on the outer solar system
    (:func:`_timers`, best of 5, compiled loops: no Python call in the figures), and the
    sweeps a step against the scene's unit of time (the stop rule's scale, below)."""
    from integrators import HBVM, Stepper
    from systems import NBody, outer_solar_system
    from systems.flow_composed import FlowComposed
    flows, pullbacks, interactions, kernel, force, recentre, energy = _timers()
    nb = outer_solar_system()
    fc = FlowComposed.from_nbody(nb, h)
    st = Stepper(HBVM(k, s), fc, fc.extend(nb.initial_state()), form="full")
    st.run(h, 10, sample_every=10)
    n0, i0, s0 = st.nfev, st.niter, st.nsteps
    t0 = time.perf_counter()
    st.run(h, steps, sample_every=steps)
    step = (time.perf_counter() - t0) / steps
    rows = (st.nfev - n0) / (st.nsteps - s0)
    sweeps = (st.niter - i0) / (st.nsteps - s0)
    Y = np.tile(st.y, (k, 1))
    Y[:, fc.dim - 1] = np.linspace(-h / 2, h / 2, k)
    P = fc._params
    reps = 20000
    per_row = {}
    t, (_, its) = _best(flows, Y, P, reps)
    per_row["flows"] = t / reps / k
    per_row["pullbacks"] = _best(pullbacks, Y, P, reps)[0] / reps / k
    per_row["interactions"] = _best(interactions, Y, P, reps)[0] / reps / k
    out = np.empty_like(Y)
    kern = _best(kernel, Y, P, out, reps)[0] / reps / k
    q = np.tile(nb.initial_state()[:3 * nb.N], (k, 1))
    fq = np.empty_like(q)
    frc = _best(force, q, nb.separable_kernels()[2], fq, reps)[0] / reps / k
    y = st.y.copy()
    gamma = np.random.default_rng(0).standard_normal((s, y.size)) * 1e-9
    rec = _best(recentre, y, np.zeros_like(y), gamma, h, P, reps // 10)[0] / (reps // 10)
    en = _best(energy, st.y.copy(), P, reps // 10)[0] / (reps // 10)
    parts = ", ".join(f"{name} {v * 1e9:.0f} ns" for name, v in per_row.items())
    lines = [f"## Where the time goes (outer solar system, HBVM({k},{s}) composed, h = {h:g} days)", "",
             f"A step: {step * 1e6:.1f} us, {sweeps:.2f} sweeps ({rows:.1f} stage rows evaluated, the "
             f"polish included). A stage row of {fc.N} planets costs {kern * 1e9:.0f} ns in the kernel "
             f"({kern / frc:.1f}x plain HBVM's N-body force, {frc * 1e9:.0f} ns a row): {parts} a row, "
             f"each measured alone as a chain of dependent calls (sum {sum(per_row.values()) * 1e9:.0f} ns; "
             f"{its / (reps * k * fc.N):.2f} Laguerre iterations a flow). "
             f"The kernel is {rows * kern / step:.0%} of the step; once a step, the recentring "
             f"hook {rec * 1e6:.2f} us ({rec / step:.0%}) and the energy check's energy {en * 1e6:.2f} us "
             f"({en / step:.0%}); the rest is the step's own sums (stages, projections, stop rule).", ""]
    # the stop rule's scale: max |gamma| over the whole state, whose largest entry is the clock's
    # rate 1 (tau' = 1); the planets' coefficients are in length / time, so the same scene in
    # another unit of time stops the iteration at another place
    x = nb.initial_state()[:3 * nb.N].reshape(-1, 3)
    v = nb.initial_state()[3 * nb.N:].reshape(-1, 3) / nb.body_masses[:, None]
    res, ref = [], None
    for unit, c in (("days", 1.0), ("hours", 24.0), ("seconds", 86400.0), ("1e-3 days", 1e-3)):
        nbu = NBody(nb.body_masses, nb.G / c ** 2, positions=x, velocities=v / c)
        fu = FlowComposed.from_nbody(nbu, h * c)
        y0 = fu.extend(nbu.initial_state())
        su = Stepper(HBVM(k, s), fu, y0, form="full")
        su.run(h * c, 200, sample_every=200)
        X = fu.physical(su.y, 200 * h * c)[:3 * nb.N]
        ref = X if ref is None else ref
        dE = abs(fu.physical_energy(su.y) / fu.physical_energy(y0) - 1.0)
        res.append(f"{unit} {su.niter / su.nsteps:.2f} sweeps (energy error {dE:.1e}, positions "
                   f"{np.abs(X - ref).max():.1e} AU from the days run)")
    lines += ["The same run (1e5 days) in other units of time: " + "; ".join(res) + ". The "
              "iteration's stop rule (`integrators.core.stop_action`) compares the increment with "
              "max |gamma| over the whole state, which is the clock's rate 1 here, so the sweeps "
              "depend on the unit of time; the results agree to the spread of round-off.", ""]
    return lines + clock_rates()


def clock_rates(runs=3):
    """``FlowComposed(clock_rate=c)`` (c tau in the state, a power of 2: only the stop rule sees
    it) against c = 1, in the engine, best of ``runs``: sweeps, time, energy error (max over
    100 outputs) and the final positions against plain HBVM(12, 8) at a tenth of the step."""
    from integrators import HBVM, Stepper, integrate
    from systems import outer_solar_system, solar_system
    from systems.flow_composed import FlowComposed
    cases = (("outer solar system, 1e5 days", outer_solar_system(), (6, 8, 500.0), 1e5, 50.0),
             ("outer solar system, 1e5 days", outer_solar_system(), (10, 13, 1000.0), 1e5, 50.0),
             ("Sun and 8 planets, 2e4 days", solar_system(), (8, 10, 16.0), 2e4, 1.0))
    lines = ["### The clock's rate (`FlowComposed(clock_rate=c)`, opt-in)", "",
             "| scene | HBVM(k,s) composed, h | c | sweeps a step | time / c = 1's | max rel. energy "
             "error | position error (AU, vs plain HBVM(12,8) at h/10 or less) |",
             "|---|---|---|---|---|---|---|"]
    for title, nb, (s, k, h), T, href in cases:
        n = int(round(T / h))
        ref = integrate(HBVM(12, 8), nb, nb.initial_state(), href, int(round(T / href)),
                        sample_every=int(round(T / href))).y[-1][:3 * nb.N]
        base = None
        for c in (1.0, 2.0 ** 10, 2.0 ** 16, 2.0 ** 24):
            best = np.inf
            for _ in range(runs + 1):           # (the first: the compile)
                fc = FlowComposed.from_nbody(nb, h, clock_rate=c)
                y0 = fc.extend(nb.initial_state())
                st = Stepper(HBVM(k, s), fc, y0, form="full")
                t0 = time.perf_counter()
                r = st.run(h, n, sample_every=n // 100)
                best = min(best, time.perf_counter() - t0)
            base = base or best
            E0 = fc.physical_energy(y0)
            dE = max(abs(fc.physical_energy(y) / E0 - 1.0) for y in r.y)
            pos = np.abs(fc.physical(st.y, n * h)[:3 * nb.N] - ref).max()
            lines.append(f"| {title} | HBVM({k},{s}), {h:g} | 2^{int(np.log2(c))} | "
                         f"{st.niter / st.nsteps:.2f} | {best / base:.2f} | {dE:.1e} | {pos:.1e} |")
    return lines + ["", "A larger c stops the iteration earlier (as a longer unit of time does); "
                    "too large a c leaves it short of its fixed point, which shows in the energy and "
                    "position errors: the safe c depends on the iteration's contraction, so c = 1 "
                    "stays the default.", ""]


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
    ap.add_argument("--wp-only", action="store_true",
                    help="only the work-precision run and its figure (docs/figures/kepler_composed_wp.*; "
                         "no results file)")
    ap.add_argument("--plot-only", action="store_true",
                    help="redraw the figure from docs/figures/kepler_composed_wp.csv (no run)")
    args = ap.parse_args()
    if args.rebound:
        compare_rebound("outer_solar_system", 1e4, hbvm=((8, None, 500.0),), peers=("ias15",),
                        kepler=((6, 8, 500.0),), kepler_rebound=((6, 8, 500.0),), n_samples=10)
        lines = rebound_rows(args.repeat) + eccentric_rows()
        text = ["# HBVM composed with the Keplerian flows inside REBOUND", "",
                f"{machine()}, one process. Generated by `python benchmarks/bench_kepler_composed.py "
                f"--rebound --repeat {args.repeat}` on {time.strftime('%Y-%m-%d')}: 200 output times, "
                f"`sim.integrate(t_i)` for the REBOUND-driven rows (HBVM, 'kepler in REBOUND', IAS15), "
                f"the engine's Stepper for the 'kepler' rows. Load average at the start: "
                f"{', '.join(f'{x:.1f}' for x in os.getloadavg())} on {os.cpu_count()} cores.", ""] + lines
        print("\n".join(text), flush=True)
        with open(os.path.join(HERE, "results", "kepler_rebound.md"), "w") as f:
            f.write("\n".join(text))
        return
    if args.plot_only:
        plot(read_csv(FIGURE + ".csv"), FIGURE + ".png", SCENES[0][0] + ", from the last run's CSV")
        return
    import_heyoka()            # (the comparison is against heyoka: refuse without it)
    repeat = 2 if args.quick else args.repeat
    command = "python benchmarks/bench_kepler_composed.py" + (" --quick" if args.quick else f" --repeat {repeat}")
    out = ["# HBVM composed with the Keplerian flows vs heyoka, SABA(10,6,4), WHFast, IAS15, plain HBVM",
           "", f"{machine()}, one process. Generated by `{command}` on {time.strftime('%Y-%m-%d')}. Medians over {repeat} starts "
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
    if args.wp_only:
        print("\n".join(work_precision(repeat, command + " --wp-only")), flush=True)
        return
    for i in ((0,) if args.quick else range(len(SCENES))):
        t0 = time.perf_counter()
        lines = run_scene(i, repeat)
        print("\n".join(lines) + f"(scene done in {time.perf_counter() - t0:.0f} s)\n", flush=True)
        out += lines
    lines = ["## The issue's speed bars (ratios in this run, medians over the starts)", "",
             "| scene | method | bar | measured | verdict |", "|---|---|---|---|---|"] + VERDICTS + [""]
    print("\n".join(lines), flush=True)
    out += lines
    lines = where_the_time_goes()
    print("\n".join(lines), flush=True)
    out += lines
    if not args.quick:
        lines = work_precision(repeat, command)
        print("\n".join(lines), flush=True)
        out += lines
    name = "kepler_composed_quick.md" if args.quick else "kepler_composed.md"
    with open(os.path.join(HERE, "results", name), "w") as f:
        f.write("\n".join(out))


if __name__ == "__main__":
    main()
