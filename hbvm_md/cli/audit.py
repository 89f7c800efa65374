"""``hbvm-md audit STRUCTURE --calculator module:Class``: the conservation audit of an ASE
calculator (:func:`hbvm_md.audit`) on a structure file, from the command line."""
from __future__ import annotations

import importlib
import json

from .common import _fail, _positive_float, _positive_int, _say


def add_audit_parser(sub) -> None:
    a = sub.add_parser("audit", help="conservation audit of an ASE calculator: its energy jumps, "
                       "non-conservative work and the integrator's share",
                       description="Run constant-energy HBVM on the structure with the named ASE "
                       "calculator and report the calculator's energy jumps (time, atoms, "
                       "distance, size), the work of its forces that its energy does not account "
                       "for, and the integrator's share (hbvm_md.audit).")
    a.add_argument("structure", help="a structure file ASE reads (ase.io.read); momenta from the "
                   "file when it has them")
    a.add_argument("--calculator", required=True, metavar="MODULE:CLASS",
                   help="the calculator's import path, e.g. ase.calculators.emt:EMT")
    a.add_argument("--calculator-args", default="{}", metavar="JSON",
                   help="keyword arguments of the calculator, as a JSON object (default {})")
    a.add_argument("--steps", type=_positive_int, default=100, help="steps (default 100)")
    a.add_argument("--timestep", type=_positive_float, default=1.0, metavar="FS",
                   help="the step in fs (default 1)")
    a.add_argument("--temperature", type=_positive_float, default=None, metavar="K",
                   help="draw Maxwell-Boltzmann momenta at this temperature (default: the file's "
                   "momenta, zero if it has none)")
    a.add_argument("--seed", type=int, default=0, help="seed of the momenta drawn (default 0)")
    a.add_argument("-s", type=_positive_int, default=2, help="HBVM's s (order 2s; default 2)")
    a.add_argument("-k", type=_positive_int, default=None,
                   help="HBVM's k (default s + 4: four quadrature nodes beyond s make the "
                   "quadrature's error round-off for a smooth calculator, so what remains is "
                   "the calculator's; the audit measures its k's own share with k + 4 more)")
    a.add_argument("--plot", default=None, metavar="PATH",
                   help="write the energy's parts against time to this image")
    a.add_argument("--quick", action="store_true", help="10 steps (for CI)")


def _calculator(path: str, kwargs: str):
    module, sep, name = path.partition(":")
    if not sep or not module or not name:
        _fail(f"--calculator must be MODULE:CLASS, e.g. ase.calculators.emt:EMT (got {path!r})")
    try:
        cls = getattr(importlib.import_module(module), name)
    except ImportError as err:
        _fail(f"--calculator {path}: cannot import {module} ({err})")
    except AttributeError:
        _fail(f"--calculator {path}: {module} has no {name}")
    try:
        args = json.loads(kwargs)
    except json.JSONDecodeError as err:
        _fail(f"--calculator-args must be a JSON object, e.g. '{{\"rc\": 10}}' ({err})")
    if not isinstance(args, dict):
        _fail(f"--calculator-args must be a JSON object, e.g. '{{\"rc\": 10}}' (got {kwargs!r})")
    try:
        return cls(**args)
    except (TypeError, ValueError) as err:
        _fail(f"--calculator {path} with --calculator-args {kwargs}: {err}")


def cmd_audit(args) -> int:
    from ase import units
    from ase.io import read
    from ..reports.audit import audit
    calc = _calculator(args.calculator, args.calculator_args)
    try:
        atoms = read(args.structure)
    except (OSError, ValueError, StopIteration) as err:
        _fail(f"cannot read the structure {args.structure!r}: {err}")
    if args.temperature is not None:
        import numpy as np
        from ase.md.velocitydistribution import thermalize_momenta
        thermalize_momenta(atoms, temperature_K=args.temperature,
                           rng=np.random.default_rng(args.seed))
    atoms.calc = calc
    steps = 10 if args.quick else args.steps
    try:
        report = audit(atoms, args.timestep * units.fs, steps, s=args.s, k=args.k)
    except ValueError as err:       # k < s, masses, positions: the message names the fix
        _fail(str(err))
    _say(report)
    if args.plot:
        report.plot(args.plot)
        _say(f"plot: {args.plot}")
    return 0
