"""Benchmark (not a test): REBOUNDx's and REBOUND's own example notebooks run as written, with
HBVM swapped in for the integrator they use, against IAS15.

The notebooks are not part of this repository (REBOUNDx and REBOUND are GPL-3 projects of
their own); fetch them and give their ``ipython_examples`` folders on the command line::

    git clone --depth 1 https://github.com/dtamayo/reboundx
    git clone --depth 1 https://github.com/hannorein/rebound
    python benchmarks/bench_reboundx_notebooks.py \\
        --reboundx reboundx/ipython_examples --rebound rebound/ipython_examples

(``--only NAME`` runs the notebooks whose file name contains NAME and prints the table without
writing it.)  Each notebook runs three times, each in a fresh Python process (headless:
matplotlib's Agg backend; its code cells in order, IPython ``%`` and ``!`` lines dropped):

* ``hbvm``: every simulation the notebook creates starts with ``sim.integrator = "hbvm"``, and
  every ``sim.integrator = NAME`` in the notebook's own code sets ``"hbvm"`` instead (NAME =
  ``"none"``, a notebook that steps with operators only, is kept);
* ``ias15``: the same with IAS15 (REBOUND's default), the peer;
* ``ias15 tight``: IAS15 at ``epsilon = 1e-11``: IAS15's own distance from the truth, so that a
  notebook whose quantity is chaotic or stochastic is judged against IAS15's own error.

NumPy's and Python's random generators and every simulation's ``rand_seed`` are seeded alike
in the three runs.  Notebooks that run for long run to a shorter end (the substitutions in
:data:`SHORTEN`, listed in the table); notebooks that need the network or that only read
saved files of another integrator are left out (:data:`SKIP`, with the reason).

What is compared: every array the notebook plots (the data arguments of matplotlib's plot,
scatter, semilogx/y, loglog, errorbar, hist, imshow, pcolormesh and contour calls), and the
final positions of every ``rebound.Simulation`` left in the notebook's namespace.  The
difference of two runs is the largest over those arrays of max |a - b| / max |b| (relative to
the array's scale).  Time: the notebook's code cells (the process start, the imports and the
loading of HBVM's compiled code excluded: a warm-up integration runs first), HBVM / IAS15, on a
loaded machine.  Writes benchmarks/results/reboundx_notebooks.md.

``--operators`` (REBOUNDx's operator notebooks, :data:`OPERATOR_NOTEBOOKS`, or those given with
``--only``): each notebook runs a fourth time, ``hbvm max_dt``: HBVM with
``sim.integrator.max_dt`` set, for each simulation the notebook creates, to IAS15's mean step
on that simulation in the ``ias15`` run (its time advanced over its steps, summed over its
``integrate`` calls; simulations are matched by the order the notebook creates them), and a
fifth with half that bound.  The table gives each run's distance from two references: ``ias15
tight`` (IAS15 at epsilon 1e-11: IAS15's own distance from it is the yardstick), and ``ias15
fixed``, IAS15 at fixed steps of 1/FINE of its mean step on each simulation (an operator's
splitting error follows the step, and at epsilon 1e-11 IAS15's steps are only about twice
shorter than at its default, so that reference carries half of IAS15's splitting error; at
1/FINE of the step it carries 1/FINE of it), and the times of HBVM with the bounds over IAS15's.
Writes benchmarks/results/reboundx_operator_notebooks.md.
"""
from __future__ import annotations

import argparse
import json
import os
import pickle
import re
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

#: REBOUND's notebooks that touch REBOUND's own forces at the stages (the rest of REBOUND's
#: notebooks run plain gravity, tested elsewhere)
REBOUND_NOTEBOOKS = ("Forces", "PoincareMap", "Holmberg", "PrimordialEarth", "EccentricComets",
                     "IntegratingArbitraryODEs",
                     "Testparticles")

#: notebook -> why it is left out
SKIP: dict[str, str] = {}

#: notebook -> [(text in a code cell, replacement)]: shorter ends for notebooks that run long
#: (IAS15 over a minute as written on a loaded two-core machine, or likely to)
SHORTEN: dict[str, list[tuple[str, str]]] = {
    "GasDampingTimescale": [("tmax = 500", "tmax = 50")],
    "InnerDiskEdge": [("np.linspace(0, 3e3, 1000)", "np.linspace(0, 1e2, 1000)")],
    "IntegrateForce": [("1e4*sim.particles[1].P", "1e3*sim.particles[1].P")],
    "J2": [("np.linspace(0, 5e3, Nout)", "np.linspace(0, 5e2, Nout)")],
    "LenseThirring": [("tmax = 5e3", "tmax = 5e2")],
    "ModifyMass": [("np.linspace(0., 1.e4, Nout)", "np.linspace(0., 1.e3, Nout)")],
    "OperatorsOverview": [("np.linspace(0., 1.e4, Nout)", "np.linspace(0., 1.e3, Nout)")],
    "ObliquityEvolution": [("tmax = 2.e4", "tmax = 2.e3")],
    "ParameterInterpolation": [("np.linspace(0., 4.e6, Nout)", "np.linspace(0., 4.e5, Nout)")],
    "Radiation_Forces_Circumplanetary_Dust": [("np.linspace(0,100.*yr, Noutput)",
                                               "np.linspace(0,10.*yr, Noutput)")],
    "Simulationarchive": [("integrate(1.e6)", "integrate(1.e4)"), ("interval=1e3", "interval=10")],
    "SpinsIntro": [("tmax = 4e4*ps[1].P", "tmax = 4e3*ps[1].P")],
    "StochasticForcesCartesian": [("np.linspace(0.,100, 1000)", "np.linspace(0.,10, 1000)")],
    "StochasticForces": [("1e4*np.pi*2., 1000", "1e3*np.pi*2., 1000"),
                         ("np.logspace(0.,5, 1000)", "np.logspace(0.,4, 1000)")],
    "TidesConstantTimeLag": [("tmax = 2.5e5", "tmax = 2.5e4")],
    "TidesSpinEarthMoon": [("tmax = 1e6", "tmax = 1e5")],
    "TidesSpinPseudoSynchronization": [("tmax = 2 * np.pi * 1e4", "tmax = 2 * np.pi * 1e3")],
    "TypeIMigration": [("np.linspace(0, 4e3, 1000)", "np.linspace(0, 4e2, 1000)")],
    "YarkovskyEffect": [("tmax=100000", "tmax=10000")],
    "PoincareMap": [("N_points_max = 2000", "N_points_max = 200"), ("Nsim = 10", "Nsim = 4"),
                    # (the standard library's Pool: the multiprocess package is not a dependency)
                    ("from multiprocess import Pool", "from multiprocessing import Pool")],
    "PrimordialEarth": [("N_pl = 8500", "N_pl = 300"),
                        ("np.linspace(0.,1000.,1000)", "np.linspace(0.,100.,1000)")],
    "EccentricComets": [("tmax = 1e4", "tmax = 1e3")],
    "Testparticles": [("N_testparticle = 1000", "N_testparticle = 200")],
    # (not a shortening: the notebook tightens its BS integrator's own tolerances, fields that
    # neither HBVM nor IAS15 has; both keep their defaults)
    "IntegratingArbitraryODEs": [("sim.integrator.eps_rel = 1e-8", "pass"),
                                 ("sim.integrator.eps_abs = 1e-8", "pass")],
}

TIMEOUT = 900.0

#: REBOUNDx's notebooks whose effects are operators (applied once per step, after it)
OPERATOR_NOTEBOOKS = ("EccAndIncDamping", "ModifyMass", "GeneralRelativity", "IntegrateForce")
#: the fine reference of ``--operators``: IAS15 at fixed steps of 1/FINE of its mean step
FINE = 16


# -- the child: one notebook, one integrator ------------------------------------------------------
def _cells(path: str) -> list[str]:
    with open(path) as fh:
        nb = json.load(fh)
    out = []
    for c in nb["cells"]:
        if c["cell_type"] != "code":
            continue
        src = "".join(c["source"])
        keep = [ln for ln in src.splitlines() if not ln.lstrip().startswith(("%", "!"))]
        out.append("\n".join(keep))
    return out


def _child(path: str, integ: str, out: str, shorten: list, bounds: list | None = None) -> None:
    """Run the notebook at ``path`` with ``integ`` ("hbvm", "ias15", "ias15 tight") and pickle
    what it plotted, its simulations' final positions, the forces and operators it loaded, its
    time, its status and each simulation's mean step (``mean_dt``, in the order the notebook
    created them) to ``out``.  ``bounds``: with "hbvm", the ``max_dt`` of each simulation in
    that order (NaN: none), set before each of its ``integrate`` calls; with "ias15 fixed",
    IAS15's fixed step (``epsilon = 0``, ``sim.dt``) of each simulation."""
    import random
    import warnings

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.axes
    import matplotlib.pyplot as plt
    import rebound
    restarts = integ == "hbvm restarts"
    if integ in ("hbvm", "hbvm restarts"):
        import hbvm_md  # noqa: F401  (registers "hbvm")
    name = "hbvm" if integ in ("hbvm", "hbvm restarts") else "ias15"
    eps = 1e-11 if integ == "ias15 tight" else None
    result = dict(plots=[], sims={}, uses=[], status="ok", message="", time=np.nan, mean_dt=[],
                  restarts=[])
    extras = {}                     # id(sim) -> the REBOUNDx Extras the notebook attached
    calls = {}                      # id(sim) -> its integrate calls so far
    created = []                    # the notebook's simulations, in the order it creates them
    advanced = {}                   # id -> [time advanced, steps] over its integrate calls

    def from_notebook() -> bool:
        f = sys._getframe(2)
        return f.f_code.co_filename.startswith("<cell")

    S = rebound.Simulation
    reb_setattr, reb_init = S.__setattr__, S.__init__

    def setattr_(self, key, value):
        if key == "integrator" and isinstance(value, str) and from_notebook():
            if value.lower() != "none":
                value = name
        if key in ("additional_forces", "softening", "testparticle_type", "gravity") \
                and from_notebook():
            what = f"{key}={value!r}" if key != "additional_forces" else "additional_forces"
            if key != "softening" or value:
                result["uses"].append(what)
        reb_setattr(self, key, value)
        if key == "integrator" and eps is not None and str(self.integrator) == "ias15":
            self.integrator.epsilon = eps

    def init_(self, *args, **kw):
        reb_init(self, *args, **kw)
        created.append(self)
        if not args and not kw:
            reb_setattr(self, "rand_seed", 1234)
            reb_setattr(self, "integrator", name)
            if eps is not None:
                self.integrator.epsilon = eps

    reb_integrate = S.integrate

    def integrate(self, *args, **kw):
        i = next((j for j, c in enumerate(created) if c is self), -1)
        if bounds is not None and 0 <= i < len(bounds) and np.isfinite(bounds[i]):
            if str(self.integrator) == "hbvm":
                self.integrator.max_dt = bounds[i]
            elif integ == "ias15 fixed" and str(self.integrator) == "ias15":
                self.integrator.epsilon = 0.0          # (IAS15's fixed steps of sim.dt)
                self.dt = bounds[i]
        t0, n0 = self.t, self.steps_done
        calls[id(self)] = calls.get(id(self), 0) + 1
        saved = None
        if restarts and calls[id(self)] in RESTART_CALLS and str(self.integrator) == "hbvm" \
                and id(self) in extras:
            saved = _save_for_restart(self, extras[id(self)])
        try:
            return reb_integrate(self, *args, **kw)
        finally:
            if saved is not None:
                result["restarts"] += _restarted(self, saved, args, kw, reboundx_extras)
            acc = advanced.setdefault(id(self), [0.0, 0])
            acc[0] += abs(self.t - t0)
            acc[1] += self.steps_done - n0

    integrate.__wrapped__ = reb_integrate      # (a restart's run, not counted)
    S.__setattr__, S.__init__, S.integrate = setattr_, init_, integrate
    try:
        import reboundx
        E = reboundx.extras.Extras
        lf, lo, io = E.load_force, E.load_operator, E.add_operator

        def load_force(self, n):
            result["uses"].append(f"force {n}")
            return lf(self, n)

        def load_operator(self, n):
            result["uses"].append(f"operator {n}")
            return lo(self, n)

        cf, co = E.create_force, E.create_operator

        def create_force(self, n):
            result["uses"].append(f"Python force {n}")
            return cf(self, n)

        def create_operator(self, n):
            result["uses"].append(f"Python operator {n}")
            return co(self, n)

        E.load_force, E.load_operator = load_force, load_operator
        e_init = E.__init__

        def extras_init(self, sim, *args, **kw):
            e_init(self, sim, *args, **kw)
            if not args and not kw:                   # (the notebook's, not a restart's)
                extras.setdefault(id(sim), self)
        E.__init__ = extras_init
        reboundx_extras = E
        E.create_force, E.create_operator = create_force, create_operator
        del io
    except ImportError:
        pass

    def capture(meth):
        orig = getattr(matplotlib.axes.Axes, meth)

        def wrapped(self, *args, **kw):
            arrs = []
            for a in args:
                if isinstance(a, str):
                    continue
                try:
                    x = np.asarray(a, dtype=float)
                except (TypeError, ValueError):
                    continue
                if x.size:
                    arrs.append(x.copy())
            result["plots"].append((meth, arrs))
            return orig(self, *args, **kw)
        setattr(matplotlib.axes.Axes, meth, wrapped)

    for meth in ("plot", "scatter", "semilogx", "semilogy", "loglog", "errorbar", "hist",
                 "imshow", "pcolormesh", "contour", "contourf"):
        capture(meth)

    # warm-up, untimed: the compiled step loaded from disk (both of HBVM's paths, with and
    # without test particles: each a compiled variant of its own)
    for soft, tp in ((0.0, False), (0.01, False), (0.0, True), (0.01, True)):
        w = rebound.Simulation()
        w.add(m=1.0)
        w.add(m=1e-3, a=1.0)
        if tp:
            w.add(m=0.0, a=2.0)
        w.softening = soft
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            w.integrate(1.0)
    result["uses"].clear()
    created.clear()
    advanced.clear()

    import __main__                     # (a notebook's Pool pickles its functions by name)
    ns = __main__.__dict__
    np.random.seed(0)
    random.seed(0)
    cells = _cells(path)
    for old, new in shorten:
        hits = [i for i, c in enumerate(cells) if old in c]
        if not hits:
            raise SystemExit(f"{path}: the shortening {old!r} matches no code cell")
        for i in hits:
            cells[i] = cells[i].replace(old, new)
    os.chdir(os.path.dirname(out))
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for j, src in enumerate(cells):
            try:
                exec(compile(src, f"<cell {j}>", "exec"), ns)
            except Exception as e:          # (report it, keep what was computed)
                result["status"] = "failed"
                result["message"] = f"cell {j}: {type(e).__name__}: {e}"
                break
            plt.close("all")
    result["time"] = time.perf_counter() - t0
    for k, v in list(ns.items()):
        if isinstance(v, rebound.Simulation) and v.N > 0:
            xyz = np.zeros(3 * v.N)
            v.serialize_particle_data(xyz=xyz)
            result["sims"][k] = xyz
    result["uses"] = sorted(set(result["uses"]))
    result["mean_dt"] = [advanced[id(c)][0] / advanced[id(c)][1]
                         if advanced.get(id(c), [0, 0])[1] > 0 else np.nan for c in created]
    with open(out, "wb") as fh:
        pickle.dump(result, fh)


#: the integrate calls (1-based, of each simulation with REBOUNDx attached) before which "hbvm
#: restarts" saves the run, to continue it restarted next to the notebook's own
RESTART_CALLS = (2, 10, 50)


def _save_for_restart(sim, rebx) -> tuple:
    """The run before an integrate call: saved to a file with its REBOUNDx effects (REBOUNDx's
    ``save``), and a ``sim.copy()``."""
    d = tempfile.mkdtemp()
    sim.save_to_file(os.path.join(d, "s.bin"), delete_file=True)
    rebx.save(os.path.join(d, "x.bin"))
    return d, sim.copy()


def _restarted(sim, saved, args, kw, E) -> list:
    """Continue the saved run (from the file; from the copy, its effects loaded from the file)
    with the integrate call the notebook made, and compare with the notebook's own, which went
    on uninterrupted: [(how, t, bit for bit?, largest |difference|)]."""
    import rebound
    d, copy = saved
    out = []
    for how in ("file", "copy"):
        back = rebound.Simulation(os.path.join(d, "s.bin")) if how == "file" else copy
        keep = E(back, os.path.join(d, "x.bin"))
        rebound.Simulation.integrate.__wrapped__(back, *args, **kw)
        a, b = np.zeros(7 * sim.N), np.zeros(7 * back.N)
        for arr, s in ((a, sim), (b, back)):
            xyz, vxvyvz, m = np.zeros(3 * s.N), np.zeros(3 * s.N), np.zeros(s.N)
            s.serialize_particle_data(xyz=xyz, vxvyvz=vxvyvz, m=m)
            arr[:] = np.concatenate([xyz, vxvyvz, m]) if s.N == sim.N else np.nan
        same = back.t == sim.t and np.array_equal(a, b)
        out.append((how, sim.t, bool(same), float(np.max(np.abs(a - b)))))
        del keep
    return out


# -- the parent: three runs per notebook, the table -----------------------------------------------
def _run(path: str, integ: str, shorten: list, bounds: list | None = None) -> dict:
    with tempfile.TemporaryDirectory() as d:
        for f in os.listdir(os.path.dirname(path)):           # (data files the notebook reads)
            if f.endswith((".txt", ".bin", ".csv", ".dat")):
                os.symlink(os.path.abspath(os.path.join(os.path.dirname(path), f)),
                           os.path.join(d, f))
        out = os.path.join(d, "result.pkl")
        env = dict(os.environ, MPLBACKEND="Agg",
                   PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]))
        code = ("import sys, json; sys.path.insert(0, %r); import bench_reboundx_notebooks as b; "
                "b._child(%r, %r, %r, json.loads(%r), json.loads(%r))" % (
                    HERE, os.path.abspath(path), integ, out, json.dumps(shorten),
                    json.dumps(bounds)))
        try:
            p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                               text=True, timeout=TIMEOUT)
        except subprocess.TimeoutExpired:
            return dict(status="timeout", message=f"over {TIMEOUT:.0f} s", plots=[], sims={},
                        uses=[], time=np.nan)
        if not os.path.exists(out):
            return dict(status="crashed", message=p.stderr.strip().splitlines()[-1:] or "",
                        plots=[], sims={}, uses=[], time=np.nan)
        with open(out, "rb") as fh:
            return pickle.load(fh)


#: a plotted array whose largest entry is below this (in IAS15's run) is an error measure the
#: notebook plots (an energy error): compared by its size, not entry by entry
SMALL = 1e-6


def _gap(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """|u - v|, modulo 2 pi when both arrays lie within [-2 pi, 2 pi] (angles: a wrap is no
    difference), NaN where both are NaN counted as 0."""
    d = np.abs(u - v)
    lim = 2 * np.pi + 1e-9
    if np.nanmax(np.abs(u)) <= lim and np.nanmax(np.abs(v)) <= lim:
        d = np.minimum(d, np.abs(np.remainder(u - v + np.pi, 2 * np.pi) - np.pi))
    return np.where(np.isnan(u) & np.isnan(v), 0.0, d)


def difference(a: dict, b: dict) -> tuple[float, str, tuple[float, float]]:
    """(largest relative difference, a note, (largest error measure of a, of b)) of run ``a``
    against run ``b``: the plotted arrays (an error measure, below :data:`SMALL`, by its size)
    and the final positions of the simulations both runs left."""
    worst, n, why = 0.0, 0, ""
    small = [0.0, 0.0]
    pa, pb = a["plots"], b["plots"]
    if len(pa) != len(pb):
        why = f"plot calls differ ({len(pa)} vs {len(pb)})"
    else:
        for (ma, xa), (mb, xb) in zip(pa, pb):
            if ma != mb or len(xa) != len(xb) or any(u.shape != v.shape for u, v in zip(xa, xb)):
                why = "plotted shapes differ"
                continue
            for u, v in zip(xa, xb):
                if not np.isfinite(v).any() or np.array_equal(u, v, equal_nan=True):
                    n += 1
                    continue
                scale = float(np.nanmax(np.abs(v)))
                if scale < SMALL:
                    small = [max(small[0], float(np.nanmax(np.abs(u)))), max(small[1], scale)]
                    continue
                d = _gap(u, v)
                worst = max(worst, float(np.max(d)) / scale if np.isfinite(d).all() else np.inf)
                n += 1
    for k in set(a["sims"]) & set(b["sims"]):
        u, v = a["sims"][k], b["sims"][k]
        if u.shape != v.shape:
            why = why or f"{k}: N differs"
            continue
        scale = np.max(np.abs(v))
        if scale > 0:
            worst = max(worst, float(np.max(np.abs(u - v)) / scale))
            n += 1
    return (worst if n else np.nan), why, tuple(small)


def notebooks(args) -> list[tuple[str, str]]:
    out = []
    if args.reboundx:
        for f in sorted(os.listdir(args.reboundx)):
            if f.endswith(".ipynb"):
                out.append(("REBOUNDx", os.path.join(args.reboundx, f)))
    if args.rebound:
        for n in REBOUND_NOTEBOOKS:
            out.append(("REBOUND", os.path.join(args.rebound, n + ".ipynb")))
    if args.only:
        out = [(w, p) for w, p in out if any(o in os.path.basename(p) for o in args.only)]
    return out


def _fmt(x: float) -> str:
    return "-" if not np.isfinite(x) else ("0" if x == 0 else f"{x:.1e}")


def operators(args) -> None:
    """The ``--operators`` mode (module docstring): six runs per notebook, the distances from
    the two references, the table."""
    if not args.reboundx:
        raise SystemExit("--operators needs --reboundx (REBOUNDx's ipython_examples folder)")
    names = args.only or list(OPERATOR_NOTEBOOKS)
    rows = []
    load = os.getloadavg()
    compared = {"ias15 tight": ("hbvm max_dt", "hbvm max_dt/2", "ias15", "hbvm"),
                "ias15 fixed": ("hbvm max_dt", "hbvm max_dt/2", "ias15", "ias15 tight", "hbvm")}
    for nb in names:
        path = os.path.join(args.reboundx, nb + ".ipynb")
        sh = SHORTEN.get(nb, [])
        runs = {}
        for integ in ("ias15", "ias15 tight", "hbvm"):
            runs[integ] = _run(path, integ, sh)
        mean = np.array(runs["ias15"]["mean_dt"], dtype=float)
        runs["hbvm max_dt"] = _run(path, "hbvm", sh, list(mean))
        runs["hbvm max_dt/2"] = _run(path, "hbvm", sh, list(mean / 2))
        runs["ias15 fixed"] = _run(path, "ias15 fixed", sh, list(mean / FINE))
        runs["hbvm restarts"] = _run(path, "hbvm restarts", sh, list(mean))
        for k, r in runs.items():
            print(f"  {nb} {k}: {r['status']} {r['time']:.2f} s {r['message']}",
                  file=sys.stderr, flush=True)
        ok = all(r["status"] == "ok" for r in runs.values())
        cells = []
        for ref, of in compared.items():
            d = {k: difference(runs[k], runs[ref]) for k in of}
            cells += [_fmt(d[k][0]) + (f" ({d[k][1]})" if d[k][1] else "") for k in of]
            within = "yes" if d["hbvm max_dt"][0] <= d["ias15"][0] else "no"
            within += ("; /2: " + ("yes" if d["hbvm max_dt/2"][0] <= d["ias15"][0] else "no"))
            cells.append(within)
        t = {k: runs[k]["time"] / runs["ias15"]["time"] if ok else np.nan
             for k in ("hbvm max_dt", "hbvm max_dt/2")}
        rs = runs["hbvm restarts"].get("restarts", [])
        same = sum(r[2] for r in rs)
        cells.append(f"{same} of {len(rs)}" + ("" if same == len(rs) else " (largest "
                     + _fmt(max(r[3] for r in rs)) + ")"))
        used = "; ".join(_fmt(b) for b in mean if np.isfinite(b))
        uses = ", ".join(runs["ias15"]["uses"]) or "gravity only"
        if sh:
            uses += "; shortened: " + "; ".join(f"`{o}` -> `{n}`" for o, n in sh)
        note = "" if ok else " (" + "; ".join(f"{k}: {r['status']} {r['message']}"
                                              for k, r in runs.items() if r["status"] != "ok") + ")"
        rows.append(f"| {nb} | {uses} | {used} | " + " | ".join(cells) + " | "
                    + " / ".join(f"{x:.2f}" if np.isfinite(x) else "-" for x in t.values())
                    + " |" + note)
        print(rows[-1], flush=True)
    import rebound
    import reboundx
    from hbvm_md.reports.machine import machine
    out = ["# REBOUNDx's operator notebooks: HBVM with `max_dt` against IAS15", "",
           f"{machine()}, load average at the start {load[0]:.1f}, {load[1]:.1f}, "
           f"{load[2]:.1f} (1, 5, 15 min); REBOUND {rebound.__version__}, REBOUNDx "
           f"{reboundx.__version__}. Generated by `python benchmarks/bench_reboundx_notebooks.py "
           "--reboundx REBOUNDX/ipython_examples --operators` on "
           f"{time.strftime('%Y-%m-%d')}. Each notebook runs as written (shortened as listed) "
           "in a fresh process, six times: IAS15 at its defaults; IAS15 at epsilon 1e-11 and "
           f"IAS15 at fixed steps of 1/{FINE} of its mean step on each simulation (the two "
           "references); HBVM at its defaults; HBVM with `sim.integrator.max_dt` set for each "
           "simulation to IAS15's mean step on it (its time advanced over its steps in the "
           "first run: the column max_dt), and to half of it. Distance: the largest over the "
           "arrays the notebook plots and the final positions of its simulations of "
           "max |a - ref| / max |ref|. An operator's splitting error follows the step; IAS15's "
           "steps at 1e-11 are only about twice shorter than at its default, so that reference "
           "carries about half of IAS15's own splitting error, the fixed-step one 1/"
           f"{FINE} of it. Restarts: a seventh run, HBVM with `max_dt`, saves each simulation "
           "with REBOUNDx attached before its integrate calls number "
           f"{', '.join(map(str, RESTART_CALLS))} (`save_to_file` and REBOUNDx's `save`, and "
           "`sim.copy()`), continues the saved run (loaded from the files; the copy with its "
           "effects loaded) with the same call, and compares it with the notebook's own run, "
           "which went on uninterrupted: positions, velocities and masses. Time: the notebook's code cells, HBVM with `max_dt` (and with half of "
           "it) / IAS15 at its defaults, one run each.", "",
           "| notebook | what it uses | max_dt (each simulation) | to IAS15 at 1e-11: HBVM + "
           "max_dt | HBVM + max_dt/2 | IAS15 | HBVM defaults | HBVM + max_dt within IAS15's? | "
           f"to IAS15 fixed at 1/{FINE}: HBVM + max_dt | HBVM + max_dt/2 | IAS15 | "
           "IAS15 at 1e-11 | HBVM defaults | HBVM + max_dt within IAS15's? | restarts bit for "
           "bit | time HBVM + max_dt / IAS15 (max_dt/2) |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|", *rows, ""]
    path = os.path.join(HERE, "results", "reboundx_operator_notebooks.md")
    with open(path, "w") as fh:
        fh.write("\n".join(out))
    print(f"wrote {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reboundx", help="REBOUNDx's ipython_examples folder")
    ap.add_argument("--rebound", help="REBOUND's ipython_examples folder")
    ap.add_argument("--only", nargs="*", help="only notebooks whose name contains one of these")
    ap.add_argument("--save", help="also pickle every run's raw results to this file")
    ap.add_argument("--load", help="compare the runs pickled by --save instead of running")
    ap.add_argument("--no-run", action="store_true",
                    help="with --load: list the notebooks not loaded as not run")
    ap.add_argument("--timeout", type=float, default=TIMEOUT, help="seconds a run may take")
    ap.add_argument("--operators", action="store_true",
                    help="REBOUNDx's operator notebooks: HBVM with max_dt at IAS15's mean step, "
                         "HBVM and IAS15, each against IAS15 at 1e-11 (module docstring)")
    args = ap.parse_args()
    globals()["TIMEOUT"] = args.timeout
    if args.operators:
        operators(args)
        return
    if not (args.reboundx or args.rebound):
        ap.error("give --reboundx and/or --rebound (see the module docstring)")
    rows = []
    saved = {}
    if args.load:
        with open(args.load, "rb") as fh:
            saved = pickle.load(fh)
    for who, path in notebooks(args):
        nb = os.path.basename(path)[:-len(".ipynb")]
        if nb in SKIP:
            rows.append(f"| {who} {nb} | - | skipped: {SKIP[nb]} | - | - | - |")
            print(rows[-1], flush=True)
            continue
        sh = SHORTEN.get(nb, [])
        runs = saved.get(nb, {}) if args.load else {}
        if args.no_run and len(runs) < 3:
            rows.append(f"| {who} {nb} | - | not run in this session | - | - | - | - |")
            continue
        for integ in ("ias15", "hbvm", "ias15 tight"):
            if integ in runs:
                continue
            runs[integ] = _run(path, integ, sh)
            print(f"  {nb} {integ}: {runs[integ]['status']} {runs[integ]['time']:.2f} s "
                  f"{runs[integ]['message']}", file=sys.stderr, flush=True)
        saved[nb] = runs
        if args.save and not args.no_run:
            with open(args.save, "wb") as fh:
                pickle.dump(saved, fh)
        h, i, it = runs["hbvm"], runs["ias15"], runs["ias15 tight"]
        uses = ", ".join(h["uses"] or i["uses"]) or "gravity only"
        if sh:
            uses += "; shortened: " + "; ".join(f"`{o}` -> `{n}`" for o, n in sh)
        if h["status"] == "ok":
            ran = "yes"
        else:
            ran = f"{h['status']}: {h['message']}"
        if i["status"] != "ok":
            ran += f" (IAS15 too: {i['message']})"
        d, why, small = difference(h, i)
        dt, _, small_t = difference(it, i)
        agree = _fmt(d) + (f" ({why})" if why else "")
        errs = (f"{_fmt(small[0])} / {_fmt(small[1])} / {_fmt(small_t[0])}" if small[1] > 0
                else "-")
        ratio = h["time"] / i["time"] if h["status"] == i["status"] == "ok" else np.nan
        rows.append(f"| {who} {nb} | {uses} | {ran} | {agree} | {_fmt(dt)} | {errs} | "
                    + (f"{ratio:.2f} |" if np.isfinite(ratio) else "- |"))
        print(rows[-1], flush=True)
    if args.only:
        return
    incomplete = sum("not run in this session" in r for r in rows)
    import rebound
    import reboundx
    from hbvm_md.reports.machine import machine
    out = ["# REBOUNDx's and REBOUND's notebooks with HBVM swapped in, against IAS15", "",
           f"{machine()}, on a loaded machine; REBOUND {rebound.__version__}, REBOUNDx "
           f"{reboundx.__version__}. Generated by `python benchmarks/bench_reboundx_notebooks.py "
           "--reboundx REBOUNDX/ipython_examples --rebound REBOUND/ipython_examples` on "
           f"{time.strftime('%Y-%m-%d')} (the notebooks fetched from the two projects' "
           "repositories; see the script's docstring). Each notebook runs as written in a fresh "
           "process with every integrator it sets (and REBOUND's default) replaced by HBVM's "
           "defaults, then by IAS15's defaults, then by IAS15 at epsilon 1e-11. Difference: the "
           "largest over the arrays the notebook plots and the final positions of its "
           "simulations of max |a - b| / max |b|. Time: the notebook's code cells, HBVM / "
           "IAS15, one run each, taken back to back (with --load, notebooks run in several "
           "sessions at different loads: a ratio compares two runs of one session)." + (f" {incomplete} notebooks were not run in the session that "
                                     "wrote this file (time)." if incomplete else ""), "",
           "| notebook | what it uses | runs with HBVM? | HBVM vs IAS15 | IAS15 vs IAS15 at "
           "1e-11 (IAS15's own error) | error measures it plots (largest): HBVM / IAS15 / "
           "IAS15 at 1e-11 | time HBVM / IAS15 |",
           "|---|---|---|---|---|---|---|", *rows, ""]
    path = os.path.join(HERE, "results", "reboundx_notebooks.md")
    with open(path, "w") as fh:
        fh.write("\n".join(out))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
