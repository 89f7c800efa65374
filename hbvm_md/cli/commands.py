"""The ``hbvm-md`` parser, its entry point :func:`main` and the subcommands demo, bench,
spectrum, hard-cases and compile (ensemble: :mod:`hbvm_md.cli.ensemble`; audit:
:mod:`hbvm_md.cli.audit`).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from .common import (DEFAULT_OUT, _fail, _int_at_least, _Parser, _positive_float, _positive_int,
                     _say, _UsageError)
from .audit import add_audit_parser, cmd_audit
from .ensemble import add_ensemble_parser, cmd_ensemble


def _at_least_a_day(text: str) -> float:
    """--t-end of the demo: the solar system's energy behaviour needs at least a day (Jupiter's
    period is 4333 days; a shorter run is a fraction of one step and shows round-off only)."""
    v = _positive_float(text)
    if v < 1.0:
        raise argparse.ArgumentTypeError(f"expected a run of at least 1 day, got {text!r}; the "
                                         "demo compares energy behaviour over orbits (Jupiter's "
                                         "period: 4333 days), e.g. --t-end 2e4")
    return v


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    from ..reports.names import scene_key
    p = _Parser(prog="hbvm-md", description="Energy-conserving HBVM(k, s) integrators for ASE and "
                "REBOUND: demos, work-precision benchmarks, spectra and hard cases.")
    p.add_argument("--version", action="version", version=f"hbvm-md {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    d = sub.add_parser("demo", help="outer solar system (REBOUND) and a pair-potential cluster (ASE): "
                       "HBVM against the hosts' integrators, table and energy plots",
                       description="Integrate the outer solar system through REBOUND and a "
                       "polynomial-pair cluster through ASE with HBVM and the hosts' own integrators; "
                       "print comparison tables and write PNG plots of the relative energy and angular-momentum errors.")
    d.add_argument("--out", default=DEFAULT_OUT, help=f"output folder (default ./{DEFAULT_OUT})")
    d.add_argument("--quick", action="store_true", help="shorter runs (for CI)")
    d.add_argument("--t-end", type=_at_least_a_day, default=None,
                   help="length of the solar-system run in days, at least 1 (default 1e5, 2e4 "
                        "with --quick)")
    # a cluster needs a pair: checked here, before the solar-system half runs
    d.add_argument("--atoms", type=_int_at_least(2), default=None,
                   help="atoms in the cluster, at least 2 (default 38, 13 with --quick)")
    d.add_argument("--md-steps", type=_positive_int, default=None,
                   help="MD steps per method (default 2000, 100 with --quick)")

    b = sub.add_parser("bench", help="work-precision diagrams (error against wall time) per scene",
                       description="Sweep step sizes (tolerances for adaptive peers) per scene and "
                       "plot energy and solution error against wall time; writes CSV, PNG, markdown.")
    from ..reports.workprecision import SCENES
    b.add_argument("--out", default=f"{DEFAULT_OUT}/bench", help=f"output folder (default ./{DEFAULT_OUT}/bench)")
    b.add_argument("--scenes", nargs="+", type=scene_key, choices=list(SCENES), default=None, metavar="SCENE",
                   help=f"scenes to run (default all: {', '.join(SCENES)})")
    b.add_argument("--quick", action="store_true", help="fewer and shorter runs (for CI)")

    s = sub.add_parser("spectrum", help="HBVM(K, S) tableau and its isospectral check against Gauss",
                       description="Print the Butcher tableau of HBVM(K, S), the S nonzero eigenvalues of "
                       "A next to those of the S-stage Gauss-Legendre method, and the largest difference.")
    s.add_argument("K", type=_positive_int, help="quadrature nodes k (k >= s)")
    s.add_argument("S", type=_positive_int, help="degree s of the method (order 2s)")
    s.add_argument("--nodes", choices=("gauss", "lobatto"), default="gauss", help="quadrature abscissae")
    s.add_argument("--quick", action="store_true", help="accepted for uniformity (spectra are instant)")

    h = sub.add_parser("hard-cases", help="run the hard-case suite (stiff FPU, eccentric Kepler, close "
                       "encounter, chaotic Henon-Heiles, steps too large)",
                       description="Run each hard case and print, per method, whether it finished, "
                       "its energy error, solution error and wall time.")
    from ..reports.hard_cases import CASES
    h.add_argument("--case", nargs="+", type=scene_key, choices=list(CASES), default=None, metavar="CASE",
                   help=f"cases to run (default all: {', '.join(CASES)})")
    h.add_argument("--quick", action="store_true", help="small sizes (for CI)")

    add_ensemble_parser(sub)
    add_audit_parser(sub)

    from ..compile_ahead import DEFAULT_SCENES, SCENES
    c = sub.add_parser("compile", help="compile and cache HBVM's steps ahead (CI, containers, "
                       "dask workers)", description="Run a tiny scene of each kind so that numba "
                       "compiles and caches HBVM's step for it (HBVM_MD_CACHE_DIR and "
                       "NUMBA_CACHE_DIR say where); later processes using the same folders start "
                       "without compiling.")
    c.add_argument("scenes", nargs="*", choices=[*SCENES, "all"], default=list(DEFAULT_SCENES),
                   metavar="SCENE", help=f"scenes to compile: {', '.join(SCENES)} or all "
                   f"(default: {' '.join(DEFAULT_SCENES)})")
    return p


# -- demo ----------------------------------------------------------------------------------
def _show(title: str, t0: float, result, path, plot_title: str, xlabel: str):
    """Print one comparison of the demo (its title, the time since t0, its table) and plot its
    energy (and angular momentum) errors into ``path``; returns the plot's path."""
    from ..reports.plots import energy_error_plot
    _say(f"\n== {title} ({time.perf_counter() - t0:.1f} s)\n")
    _say(result.table())
    return energy_error_plot(result.series, path, plot_title, xlabel,
                             angular_momentum=result.angular_momentum_series)


#: on ASE's MD tutorial (EMT copper, 108 atoms) HBVM is cheaper in force evaluations than
#: VelocityVerlet below this energy error per atom (benchmarks/bench_md_cost.py; the README)
MD_COST_CROSSOVER = 7e-6


def md_cost_note(mdc) -> str:
    """The demo's MD cost, HBVM's against VelocityVerlet's, and when VelocityVerlet is the
    better choice (the demo's cluster is HBVM's best case: a polynomial potential)."""
    vv = next((r for r in mdc.rows if r["method"] == "VelocityVerlet"), None)
    hb = next((r for r in mdc.rows if r["method"] != "VelocityVerlet"), None)
    if vv is None or hb is None:
        return ""
    e_vv, e_hb = vv["max_abs_dE_per_atom_eV"], hb["max_abs_dE_per_atom_eV"]
    better = (f"an energy error {e_vv / e_hb:.2g}x smaller" if e_hb > 0 else
              "an energy error at round-off")
    wall = (f" and {hb['wall_time_s'] / vv['wall_time_s']:.2g}x its wall time"
            if vv["wall_time_s"] > 0 else "")
    return (f"Cost: {hb['method']} took {hb['force_evals'] / vv['force_evals']:.3g}x "
            f"VelocityVerlet's force evaluations{wall} at the same timestep, for {better} "
            f"({e_hb:.1e} against {e_vv:.1e} eV per atom). This cluster's pair potential is a "
            "polynomial (a quartic well), on which HBVM(2s, s) keeps the energy exactly: HBVM's "
            "best case. With a general calculator (EMT, a machine-learned potential) "
            "VelocityVerlet is the better choice at the usual 1-5 fs accuracy: on ASE's EMT "
            "copper tutorial it is cheaper for energy errors above about "
            f"{MD_COST_CROSSOVER:g} eV per atom (benchmarks/bench_md_cost.py), HBVM below that "
            "and for long constant-energy runs.")


def cmd_demo(args) -> int:
    from ..reports.progress import progress
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    _say(f"hbvm-md demo: writing into {out.resolve()}")
    t_end = args.t_end or (2e4 if args.quick else 1e5)
    written, missing = [], []
    bar = progress(total=2, desc="demo")
    # the outer solar system through REBOUND; its numba step compiled first, and said so, so
    # that the section's time is the work it shows (once per machine: cached)
    try:
        import rebound  # noqa: F401
        from ..compile_ahead import precompile
        tc = time.perf_counter()
        precompile(["rebound"])
        took = time.perf_counter() - tc
        if took > 0.5:
            _say(f"(compiled REBOUND's HBVM step, once on this machine: {took:.1f} s)")
    except ImportError:
        pass
    t0 = time.perf_counter()
    try:
        from ..reports.rebound_comparison import compare_rebound
        cmp = compare_rebound("outer-solar-system", t_end=t_end, n_samples=200)
        written.append(_show(f"Outer solar system (HLW), {t_end:g} days, through REBOUND", t0,
                             cmp, out / "energy_outer_solar_system.png",
                             f"Outer solar system, {t_end:g} days", "t [days]"))
    except ImportError as err:
        missing.append(f"REBOUND comparison not available ({err})")
    bar.update(1)
    # the polynomial-pair cluster through ASE
    t0 = time.perf_counter()
    n_atoms = args.atoms or (13 if args.quick else 38)
    md_steps = args.md_steps or (100 if args.quick else 2000)
    try:
        from ..reports.md_comparison import compare_md, default_cluster
        atoms, calc = default_cluster(n_atoms=n_atoms)
        mdc = compare_md(atoms, calculator=calc, steps=md_steps,
                         verbose=False)      # (the demo prints the table itself)
        written.append(_show(f"Polynomial-pair cluster, {len(atoms)} atoms, {md_steps} steps, "
                             "through ASE", t0, mdc, out / "energy_md_cluster.png",
                             f"Polynomial-pair cluster, {len(atoms)} atoms", "t [ps]"))
        _say("\n" + md_cost_note(mdc))
    except ImportError as err:
        missing.append(f"ASE comparison not available ({err})")
    bar.update(1)
    bar.close()
    for m in missing:
        _say(f"skipped: {m}")
    _say("\nwrote:")
    for w in written:
        _say(f"  {w}")
    return 0 if written else 1


# -- bench ---------------------------------------------------------------------------------
def cmd_bench(args) -> int:
    from ..reports.workprecision import bench
    out = Path(args.out)
    _say(f"hbvm-md bench: writing into {out.resolve()}")
    res = bench(out, scenes=args.scenes, quick=args.quick, log=_say)
    _say(f"wrote {res['csv']}\nwrote {res['markdown']}")
    for p in res["pngs"]:
        _say(f"wrote {p}")
    for sc, why in res["skipped"].items():
        _say(f"skipped {sc}: {why}")
    return 0 if res["rows"] else 1


# -- spectrum ------------------------------------------------------------------------------
def cmd_spectrum(args) -> int:
    from integrators import HBVM, gauss_spectrum
    if args.K < args.S:
        _fail(f"K must be >= S (got K={args.K}, S={args.S}); HBVM(K, S) needs at least S nodes")
    if args.K > 64:
        _fail(f"K must be <= 64 for a printed tableau (got K={args.K})")
    m = HBVM(args.K, args.S, nodes=args.nodes)
    A, b, c = m.butcher_tableau()
    np.set_printoptions(linewidth=160, precision=6, suppress=False)
    _say(f"{m!r}: {m.n_stages} stages, order {m.order}, exact for polynomial H of degree <= "
         f"{m.polynomial_degree_exact}, symplecticity defect {m.symplecticity_defect():.2e}")
    if m.n_stages <= 10:
        _say("\nButcher tableau (c | A, then b):")
        for i in range(m.n_stages):
            _say(f"  {c[i]: .6f} | " + " ".join(f"{a: .6f}" for a in A[i]))
        _say("  " + " " * 9 + "| " + " ".join(f"{x: .6f}" for x in b))
    else:
        _say(f"\nA is {m.n_stages} x {m.n_stages} (not printed); c and b:")
        _say("  c = " + " ".join(f"{x:.6f}" for x in c))
        _say("  b = " + " ".join(f"{x:.6f}" for x in b))
    ev = m.essential_spectrum()
    g = gauss_spectrum(args.S)
    _say(f"\nNonzero eigenvalues of A (HBVM({args.K},{args.S})) and of the {args.S}-stage Gauss method:")
    for i, (x, y) in enumerate(zip(ev, g)):
        _say(f"  {i + 1:2d}  {x.real: .15f} {x.imag:+.15f}i    {y.real: .15f} {y.imag:+.15f}i")
    diff, bound = isospectral_check(m)
    _say(f"\nlargest difference: {np.max(diff):.3e} (round-off bound of the two eigenvalue "
         f"computations, eps * cond * norm: {np.max(bound):.3e})")
    if np.any(diff > bound):
        _say("isospectral check FAILED: a difference exceeds its round-off bound")
        return 1
    if np.max(bound) > _PASS_LEVEL:
        _say("isospectral check limited by conditioning: every difference is within its round-off "
             "bound, but the eigenvalues are too ill-conditioned in double precision for the "
             "difference to confirm the property")
        return 0
    _say("isospectral check passed: A and the Gauss matrix share their nonzero eigenvalues to "
         "round-off")
    return 0


# a check whose round-off bound is above this no longer confirms equality of the spectra
_PASS_LEVEL = 1e-10


def isospectral_check(method) -> tuple[np.ndarray, np.ndarray]:
    """Per nonzero eigenvalue of A: |lambda_A - lambda_Gauss| and the first-order round-off bound
    eps (kappa_A ||A|| + kappa_X ||X_s||) of computing both, kappa the eigenvalue condition
    number 1 / |y^H x| (unit left and right eigenvectors; Golub-Van Loan, Sec. 7.2.2).

    For s >~ 25 the kappas exceed 1e10 and the difference says nothing either way.
    """
    import scipy.linalg as sl

    from integrators import gauss_matrix, gauss_spectrum

    def conditioned(M, wanted):
        w, vl, vr = sl.eig(M, left=True, right=True)
        idx = [int(np.argmin(np.abs(w - lam))) for lam in wanted]
        x = vr[:, idx] / np.linalg.norm(vr[:, idx], axis=0)
        y = vl[:, idx] / np.linalg.norm(vl[:, idx], axis=0)
        return np.linalg.norm(M, 2) / np.abs(np.sum(np.conj(y) * x, axis=0))

    A = method.butcher_tableau()[0]
    ev, g = method.essential_spectrum(), gauss_spectrum(method.s)
    eps = np.finfo(float).eps
    bound = eps * (conditioned(A, ev) + conditioned(gauss_matrix(method.s), g))
    return np.abs(ev - g), bound


# -- hard cases ----------------------------------------------------------------------------
def cmd_hard_cases(args) -> int:
    from ..reports.hard_cases import CASES
    from ..reports.progress import progress
    names = args.case or list(CASES)
    bar = progress(total=len(names), desc="hard cases")
    for n in names:
        t0 = time.perf_counter()
        rep = CASES[n](quick=args.quick)
        _say(rep.table())
        _say(f"({n}: {time.perf_counter() - t0:.1f} s)\n")
        bar.update(1)
    bar.close()
    return 0


# -- compile (hbvm_md/compile_ahead.py) ------------------------------------------------------
def cmd_compile(args) -> int:
    from integrators.specialise import cache_dir
    from ..compile_ahead import precompile
    for name, took in precompile(args.scenes).items():
        _say(f"{name}: {took:.1f} s")
    _say(f"cached in {cache_dir()} (steps) and numba's cache folder")
    return 0


COMMANDS = {"demo": cmd_demo, "bench": cmd_bench, "spectrum": cmd_spectrum, "hard-cases": cmd_hard_cases,
            "ensemble": cmd_ensemble, "compile": cmd_compile, "audit": cmd_audit}


def main(argv=None) -> int:
    """Entry point of ``hbvm-md`` and ``python -m hbvm_md``; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except _UsageError as err:
        sys.stderr.write(f"hbvm-md {args.command}: error: {err}\n")
        return 2
    except OSError as err:
        # e.g. an output folder that cannot be created
        sys.stderr.write(f"hbvm-md {args.command}: error: {err}\n")
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
