"""``hbvm-md ensemble ...``: ensembles from the command line (see :mod:`hbvm_md.ensemble`).

``hbvm-md ensemble stability-map --grid 20x20 --t-end 2e6 --workers 2 --out DIR`` writes
``DIR/stability_map.csv`` and ``DIR/stability_map.png``; its store ``DIR/stability_map_store``
lets an interrupted map resume.  ``--scheduler ADDRESS`` runs on an existing dask cluster;
``--timeout SECONDS`` stops a member that runs longer (recorded as ``timeout``).
"""
from __future__ import annotations

import argparse
import csv
import functools
import time
from pathlib import Path

from .common import DEFAULT_OUT, _fail, _positive_float, _positive_int, _say


def _grid(text: str) -> tuple[int, int]:
    try:
        na, ne = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected NAxNE such as 20x20, got {text!r}") from None
    if na < 1 or ne < 1:
        raise argparse.ArgumentTypeError(f"expected two positive integers NAxNE, got {text!r}")
    return na, ne


def add_ensemble_parser(sub) -> None:
    """Add ``ensemble`` and its subcommands to the ``hbvm-md`` subparsers ``sub``."""
    ens = sub.add_parser("ensemble", help="many independent runs on a dask cluster (local or remote)",
                         description="Run an ensemble of simulations on dask.distributed: a local "
                         "cluster with one worker per core, or an existing one (--scheduler).")
    esub = ens.add_subparsers(dest="ensemble_command", metavar="ENSEMBLE", parser_class=sub._parser_class)
    esub.required = True
    m = esub.add_parser("stability-map", help="a test planet over a grid of (a, e) in the outer solar system",
                        description="Add a planet (about one Earth mass) at each (a, e) of a grid to the "
                        "outer solar system, integrate it with HBVMIntegrator, and map its chaos "
                        "indicator (REBOUND's MEGNO from HBVM's variational particles, or the "
                        "divergence of a shadow clone 1e-10 apart), the maximum energy error and "
                        "the survival; writes a CSV and a PNG.")
    m.add_argument("--grid", type=_grid, default=None, metavar="NAxNE",
                   help="grid points in a and e (default 20x20, 6x4 with --quick)")
    m.add_argument("--a-range", type=_positive_float, nargs=2, default=(6.0, 36.0), metavar=("AMIN", "AMAX"),
                   help="semi-major axes in AU (default 6 36)")
    m.add_argument("--e-range", type=float, nargs=2, default=(0.0, 0.5), metavar=("EMIN", "EMAX"),
                   help="eccentricities (default 0 0.5)")
    m.add_argument("--t-end", type=_positive_float, default=None,
                   help="days per run (default 1e6, 2e4 with --quick)")
    m.add_argument("--dt", type=_positive_float, default=250.0, help="step in days (default 250)")
    m.add_argument("--workers", type=_positive_int, default=None,
                   help="worker processes of the local cluster (default: one per core)")
    m.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="address of a running dask scheduler, e.g. tcp://10.0.0.5:8786 (instead of a "
                   "local cluster)")
    m.add_argument("--out", default=f"{DEFAULT_OUT}/ensemble", help=f"output folder (default "
                   f"./{DEFAULT_OUT}/ensemble); its stability_map_store resumes an interrupted map")
    m.add_argument("--timeout", type=_positive_float, default=None, metavar="SECONDS",
                   help="stop a member that runs longer and record it as 'timeout' (each worker "
                   "then runs its members in a child process it can kill; default: no limit)")
    m.add_argument("--indicator", choices=("megno", "clone"), default="megno",
                   help="chaos indicator: MEGNO <Y> (default; chaotic above 4) or the "
                   "divergence of a shadow clone (two runs a point)")
    m.add_argument("--quick", action="store_true", help="a small, short map (for CI)")


def cmd_ensemble(args) -> int:
    """Run ``hbvm-md ensemble <subcommand>``."""
    from ..ensemble import run_ensemble
    from ..ensemble.tasks import (PLANET_MASS, plot_stability_map, stability_grid,
                                  stability_member, stability_table)
    if args.workers is not None and args.scheduler is not None:
        _fail("give --workers (a local cluster) or --scheduler (an existing one), not both")
    shape = args.grid or ((6, 4) if args.quick else (20, 20))
    t_end = args.t_end or (2e4 if args.quick else 1e6)
    try:
        params = stability_grid(tuple(args.a_range), tuple(args.e_range), shape)
    except ValueError as err:
        _fail(str(err))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    task = functools.partial(stability_member, t_end=t_end, dt=args.dt,
                             indicator=args.indicator)
    where = args.scheduler or f"a local cluster of {args.workers or 'one worker per core'}"
    _say(f"hbvm-md ensemble stability-map: {len(params)} members, {t_end:g} days each, on {where}; "
         f"writing into {out.resolve()}")
    t0 = time.perf_counter()
    try:
        records = run_ensemble(task, params, client=args.scheduler, store=out / "stability_map_store",
                               workers=args.workers, timeout=args.timeout)
    except (ValueError, ConnectionError) as err:
        _fail(f"{err} (or pass another --out)" if "store" in str(err) else str(err))
    wall = time.perf_counter() - t0
    rows = stability_table(records)
    csv_path = out / "stability_map.csv"
    with open(csv_path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    png = plot_stability_map(rows, out / "stability_map.png",
                             f"Planet of {PLANET_MASS:g} M_sun in the outer solar system, HBVM, "
                             f"{'MEGNO' if args.indicator == 'megno' else 'shadow clone'}, "
                             f"{t_end:g} days ({shape[0]}x{shape[1]} grid)")
    failed = sum(r["status"] != "ok" for r in records)
    timed_out = sum(r["status"] == "timeout" for r in records)
    survived = sum(r["survived"] is True for r in rows)
    _say(f"{len(rows)} members in {wall:.1f} s: {survived} survived, {len(rows) - survived - failed} "
         f"unstable, {failed - timed_out} failed, {timed_out} timed out")
    for r in records:
        if r["status"] != "ok":
            _say(f"  {r['status']} {r['param']}: {r['error']}")
    _say(f"wrote {csv_path}\nwrote {png}")
    return 0 if failed == 0 else 1
