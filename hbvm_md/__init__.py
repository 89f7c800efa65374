"""hbvm-md: the backend facade.

HBVM(k, s) as an ASE ``MolecularDynamics`` class (:class:`HBVMDynamics`), as an integrator
driven by REBOUND (:class:`HBVMIntegrator`), conservation checks against the hosts' own
integrators (:func:`compare_md`, :func:`compare_rebound`), the conservation audit of an ASE
calculator (:func:`audit`) and the ``hbvm-md`` command line.

Names are imported lazily so that ``import hbvm_md`` pulls in neither ASE nor REBOUND.  HBVM is
registered with REBOUND under the name "hbvm" (once per process, :mod:`hbvm_md.rebound`) at
``import hbvm_md`` when REBOUND is imported already, else when REBOUND is imported (an import
hook, :class:`_RegisterOnImport`): ``sim.integrator = "hbvm"`` works, and a simulation saved with
HBVM loads and continues, in any process that imported ``hbvm_md``, while a process that never
imports REBOUND does not pay for it.
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
    "load_store": "hbvm_md.ensemble",
    "EnsembleStoreWarning": "hbvm_md.ensemble",
    "precompile": "hbvm_md.compile_ahead",
    "audit": "hbvm_md.reports.audit",
    "AuditReport": "hbvm_md.reports.audit",
}

__all__ = ["HBVM", "ConvergenceError", "UnresolvedStepError", "integrate", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'hbvm_md' has no attribute {name!r}")


def _register_now() -> None:
    """Register HBVM with REBOUND (REBOUND is imported)."""
    from hbvm_md.rebound import register
    try:
        register()
    except RuntimeError as exc:  # an unsupported REBOUND: the ASE host and the engine still work
        import warnings
        warnings.warn(f"hbvm_md: HBVM is not registered with REBOUND ({exc})", RuntimeWarning,
                      stacklevel=3)


class _RegisterOnImport:
    """A finder on ``sys.meta_path`` that lets REBOUND's own finder find it and, once the
    ``rebound`` package has run, registers HBVM with it; it then leaves ``sys.meta_path``.
    So ``import hbvm_md`` does not import REBOUND (an ASE user's import pays nothing for it),
    and ``sim.integrator = "hbvm"`` works in any process that imported both, in either order
    (a pickled or saved simulation too: unpickling imports ``rebound`` first)."""

    def find_spec(self, name, path=None, target=None):
        if name != "rebound":
            return None
        _remove_hook()
        import importlib.util
        spec = importlib.util.find_spec(name)     # REBOUND's own finder (this one is gone)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        spec.loader = _RegisteringLoader(spec.loader)
        return spec


class _RegisteringLoader:
    """REBOUND's loader, then the registration (a failure of it never fails ``import
    rebound``: it is a warning)."""

    def __init__(self, loader):
        self._loader = loader

    def __getattr__(self, name):            # (resources, get_filename, ... as REBOUND's)
        return getattr(self._loader, name)

    def create_module(self, spec):
        return self._loader.create_module(spec)

    def exec_module(self, module):
        self._loader.exec_module(module)
        try:
            _register_now()
        except Exception as exc:  # noqa: BLE001 - REBOUND itself must still import
            import warnings
            warnings.warn(f"hbvm_md: HBVM is not registered with REBOUND ({type(exc).__name__}: "
                          f"{exc})", RuntimeWarning, stacklevel=2)


_HOOK = _RegisterOnImport()


def _remove_hook() -> None:
    import sys
    try:
        sys.meta_path.remove(_HOOK)
    except ValueError:
        pass


def _register_with_rebound() -> None:
    """Register now when REBOUND is imported already, else when it is (an import hook)."""
    import sys
    if "rebound" in sys.modules:
        _register_now()
    elif _HOOK not in sys.meta_path:
        sys.meta_path.insert(0, _HOOK)


_register_with_rebound()
