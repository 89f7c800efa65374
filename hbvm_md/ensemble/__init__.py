"""Ensembles of independent runs on dask.distributed: one record per parameter.

>>> from hbvm_md.ensemble import run_ensemble
>>> from hbvm_md.ensemble.tasks import solar_clone
>>> records = run_ensemble(solar_clone, range(16), store="clones")     # doctest: +SKIP

* :mod:`~hbvm_md.ensemble.run`: :func:`run_ensemble`, its store and :func:`load_store`;
* :mod:`~hbvm_md.ensemble.identity`: the digest a store knows a task and a parameter by;
* :mod:`~hbvm_md.ensemble.member`: one member called and recorded, and the child process that
  runs members under a timeout (``python -m hbvm_md.ensemble.member``);
* :mod:`~hbvm_md.ensemble.tasks`: ready-made members (:func:`~hbvm_md.ensemble.tasks.solar_clone`,
  :func:`~hbvm_md.ensemble.tasks.stability_member`, :func:`~hbvm_md.ensemble.tasks.md_replica`).

The names are imported lazily, so that a member's child process (``hbvm_md.ensemble.member``
and the task's module) does not import dask.distributed, which it does not use.
"""
from importlib import import_module

_LAZY = {
    "run_ensemble": "hbvm_md.ensemble.run",
    "load_store": "hbvm_md.ensemble.run",
    "EnsembleStoreWarning": "hbvm_md.ensemble.run",
}

__all__ = [*_LAZY]


def __getattr__(name):
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'hbvm_md.ensemble' has no attribute {name!r}")
