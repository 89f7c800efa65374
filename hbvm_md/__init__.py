"""hbvm-md: the backend facade.

HBVM(k, s) as an ASE ``MolecularDynamics`` class (:class:`HBVMDynamics`), as an integrator
driven by REBOUND (:class:`HBVMIntegrator`), conservation checks against the hosts' own
integrators (:func:`compare_md`, :func:`compare_rebound`), the conservation audit of an ASE
calculator (:func:`audit`) and the ``hbvm-md`` command line.

Names are imported lazily so that ``import hbvm_md`` does not pull in ASE.  When REBOUND is
installed, ``import hbvm_md`` registers HBVM with it under the name "hbvm" (once per process,
:mod:`hbvm_md.rebound`), so that a simulation saved with HBVM loads and continues in any process
that imported ``hbvm_md``.
"""
from importlib import import_module

from integrators import HBVM, ConvergenceError, UnresolvedStepError, integrate

__version__ = "0.1.0"

_LAZY = {
    "HBVMDynamics": "hbvm_md.ase",
    "compare_md": "hbvm_md.reports.md_comparison",
    "MDComparison": "hbvm_md.reports.md_comparison",
    "HBVMIntegrator": "hbvm_md.rebound",
    "compare_rebound": "hbvm_md.reports.rebound_comparison",
    "ReboundComparison": "hbvm_md.reports.rebound_comparison",
    "run_ensemble": "hbvm_md.ensemble",
    "precompile": "hbvm_md.compile_ahead",
    "audit": "hbvm_md.reports.audit",
    "AuditReport": "hbvm_md.reports.audit",
}

__all__ = ["HBVM", "ConvergenceError", "UnresolvedStepError", "integrate", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'hbvm_md' has no attribute {name!r}")


def _register_with_rebound() -> None:
    try:
        import_module("rebound")
    except ImportError:          # REBOUND is optional
        return
    from hbvm_md.rebound import register
    try:
        register()
    except RuntimeError as exc:  # an unsupported REBOUND: the ASE host and the engine still work
        import warnings
        warnings.warn(f"hbvm_md: HBVM is not registered with REBOUND ({exc})", RuntimeWarning,
                      stacklevel=3)


_register_with_rebound()
