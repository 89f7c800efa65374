"""The ``hbvm-md`` command line: demo, bench, spectrum, hard-cases, ensemble, compile, audit.

``hbvm-md demo`` is the quick start: the outer solar system through REBOUND and a
polynomial-pair cluster through ASE, each with HBVM and with the host's own integrators; it
prints comparison tables (energy and angular momentum) and writes plots of both errors against
time into an output folder.

Bad arguments print one line to stderr and exit with status 2.

:mod:`~hbvm_md.cli.commands` holds the parser, :func:`main` and every subcommand but
``ensemble`` (:mod:`~hbvm_md.cli.ensemble`); both take what they share from
:mod:`~hbvm_md.cli.common`.
"""
from .commands import build_parser, main

__all__ = ["build_parser", "main"]
