"""Ensembles of independent runs on dask.distributed: one record per parameter.

>>> from hbvm_md.ensemble import run_ensemble
>>> from hbvm_md.ensemble_tasks import solar_clone
>>> records = run_ensemble(solar_clone, range(16), store="clones")     # doctest: +SKIP

:func:`run_ensemble` sends ``task(param)`` for every ``param`` to the workers of a dask cluster
(a ``LocalCluster`` on this machine unless the caller passes a ``Client`` or a scheduler
address) and returns one record per parameter, in the order of the parameters.  A member that
raises is recorded as failed with its exception; the others go on.

The store
---------
``store=DIR`` journals each finished member as ``DIR/parts/member-<index>.parquet``, written to
a temporary name and renamed, so that a crash or Ctrl-C loses only the unfinished members; a
rerun with the same ``DIR`` loads the finished ones instead of running them again.  At the end
of every run (also an interrupted one) the parts are joined into ``DIR/ensemble.parquet``: one
row per finished member with the columns ``member`` (index into params), ``param`` (JSON text),
``status``, ``error``, ``wall_time_s`` and ``result.<key>`` per key of the task's dict.  Open it
with ``pandas.read_parquet`` (or polars, DuckDB, R's arrow).  Parquet through pyarrow: one wheel
with no dependencies of its own, float64 stored bit for bit, and read by every data-frame tool.
``DIR/meta.json`` names the task and its bound arguments; a rerun with a different task, or
a different parameter at a stored index, is refused rather than mixed in.
"""
from __future__ import annotations

import functools
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
from distributed.diagnostics.plugin import WorkerPlugin

__all__ = ["run_ensemble", "load_store"]

_STORE_TABLE = "ensemble.parquet"
_FIXED = ("member", "param", "status", "error", "wall_time_s")


# -- on the worker -------------------------------------------------------------------------
def _run_member(task: Callable, param: Any) -> dict:
    """``task(param)`` timed, with any exception turned into a failed record (runs on a worker)."""
    start = time.perf_counter()
    try:
        result = task(param)
        if not isinstance(result, dict):
            raise TypeError(f"the task must return a dict (got {type(result).__name__} for "
                            f"param={param!r})")
        status, error = "ok", None
    except Exception as exc:  # noqa: BLE001 - a failed member must not stop the others
        result, status, error = None, "failed", f"{type(exc).__name__}: {exc}"
    return {"status": status, "error": error, "result": result,
            "wall_time_s": time.perf_counter() - start}


class _Warmup(WorkerPlugin):
    """A worker plugin that calls ``warmup()`` once on every worker, present or joining later.

    ``idempotent``: registering it again under the same name (a second ensemble on the same
    client) is a no-op, so compiled code is loaded once per worker process."""

    idempotent = True

    def __init__(self, warmup: Callable[[], Any]):
        self.warmup = warmup

    def setup(self, worker=None):
        self.warmup()

    def teardown(self, worker=None):
        pass


def _task_warmup(task) -> Callable | None:
    """The ``warmup`` attribute of the task (or of the function a ``functools.partial`` wraps)."""
    while isinstance(task, functools.partial):
        task = task.func
    return getattr(task, "warmup", None)


def _name(fn) -> str:
    while isinstance(fn, functools.partial):
        fn = fn.func
    return f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', type(fn).__qualname__)}"


# -- checks ----------------------------------------------------------------------------------
def _check_picklable(obj, what: str, fix: str) -> None:
    import cloudpickle      # what dask sends functions with (by reference when importable)
    try:
        cloudpickle.dumps(obj)
    except Exception as exc:  # noqa: BLE001 - any pickling failure means the same to the user
        raise TypeError(f"`{what}` cannot be sent to the workers: it does not pickle "
                        f"({type(exc).__name__}: {exc}); {fix}") from None


def _check_params(params) -> list:
    if isinstance(params, (str, bytes, dict)) or not isinstance(params, Iterable):
        raise TypeError(f"`params` must be a sequence of parameters, one per member (got "
                        f"{type(params).__name__}: {params!r:.80}); wrap a single one in a list")
    params = list(params)
    if not params:
        raise ValueError("`params` is empty: an ensemble needs at least one parameter (got [])")
    return params


# -- the store -------------------------------------------------------------------------------
def _plain(x):
    """numpy scalars and arrays as Python numbers and lists (what JSON and Arrow hold)."""
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    return x


def _param_text(param) -> str:
    return json.dumps(_plain(param), sort_keys=True, default=repr)


def _task_text(task) -> str:
    if isinstance(task, functools.partial):
        args = [repr(a) for a in task.args] + [f"{k}={v!r}" for k, v in sorted(task.keywords.items())]
        return f"{_name(task)}({', '.join(args)})"
    return _name(task)


class _Store:
    """The journal of one ensemble (see the module docstring)."""

    def __init__(self, path, task, params: list):
        import pyarrow  # noqa: F401 - fail before any member runs when pyarrow is missing
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise ValueError(f"`store` must be a folder (got the file {str(self.path)!r}); pass a "
                             "folder path, it is created when missing")
        self.parts = self.path / "parts"
        self.parts.mkdir(parents=True, exist_ok=True)
        self.texts = [_param_text(p) for p in params]
        meta = {"task": _task_text(task), "n_members": len(params)}
        mfile = self.path / "meta.json"
        if mfile.exists():
            old = json.loads(mfile.read_text())
            if old.get("task") != meta["task"]:
                raise ValueError(f"`store` {str(self.path)!r} holds the ensemble of task "
                                 f"{old.get('task')!r}, not {meta['task']!r}; pass another store "
                                 "folder or delete this one")
        mfile.write_text(json.dumps(meta, indent=1))

    def _file(self, i: int) -> Path:
        return self.parts / f"member-{i:07d}.parquet"

    def finished(self) -> dict[int, dict]:
        """index -> record fields (status, error, result, wall_time_s) of the stored members."""
        import pyarrow.parquet as pq
        done = {}
        for f in sorted(self.parts.glob("member-*.parquet")):
            row = pq.read_table(f).to_pylist()[0]
            i = row["member"]
            if i >= len(self.texts) or row["param"] != self.texts[i]:
                have = self.texts[i] if i < len(self.texts) else "no member"
                raise ValueError(f"`store` {str(self.path)!r} holds member {i} with param "
                                 f"{row['param']}, but this ensemble has {have} there; pass "
                                 "another store folder or delete this one")
            result = None
            if row["status"] == "ok":
                result = {k[len("result."):]: v for k, v in row.items() if k.startswith("result.")}
            done[i] = {"status": row["status"], "error": row["error"], "result": result,
                       "wall_time_s": row["wall_time_s"]}
        return done

    def save(self, i: int, rec: dict) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq
        row = {"member": i, "param": self.texts[i], "status": rec["status"], "error": rec["error"],
               "wall_time_s": rec["wall_time_s"]}
        for k, v in (rec["result"] or {}).items():
            row[f"result.{k}"] = _plain(v)
        try:
            table = pa.Table.from_pylist([row])
            # typed even when empty, so that the parts of ok and failed members join
            table = table.set_column(table.schema.get_field_index("error"), "error",
                                     pa.array([rec["error"]], pa.string()))
        except (pa.ArrowException, TypeError, ValueError) as exc:
            raise TypeError(f"member {i}: the task's result cannot be stored ({exc}); return "
                            "numbers, strings, booleans, None or lists and arrays of numbers") from None
        tmp = self._file(i).with_suffix(".tmp")
        pq.write_table(table, tmp)
        os.replace(tmp, self._file(i))      # a crash leaves the old part or the new, never half

    def consolidate(self) -> Path | None:
        """Join the parts into one table (columns unified; a missing value is null)."""
        import pyarrow as pa
        import pyarrow.parquet as pq
        files = sorted(self.parts.glob("member-*.parquet"))
        if not files:
            return None
        tables = [pq.read_table(f) for f in files]
        table = pa.concat_tables(tables, promote_options="permissive")
        out = self.path / _STORE_TABLE
        tmp = out.with_suffix(".tmp")
        pq.write_table(table, tmp)
        os.replace(tmp, out)
        return out


def load_store(path) -> list[dict]:
    """The rows of a store's ``ensemble.parquet`` as dicts (``pandas.read_parquet`` gives a frame)."""
    import pyarrow.parquet as pq
    f = Path(path) / _STORE_TABLE
    if not f.exists():
        raise ValueError(f"`path` {str(path)!r} holds no {_STORE_TABLE}; pass the `store` folder "
                         "of a run_ensemble call")
    return pq.read_table(f).to_pylist()


# -- the driver ------------------------------------------------------------------------------
def _connect(client, workers: int | None, connect_timeout: float):
    """(client, owned cluster or None); a string is a scheduler address."""
    from distributed import Client, LocalCluster
    if client is None:
        n = workers or os.cpu_count() or 1
        # one single-threaded process per core: the members are compiled, GIL-holding loops
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=logging.ERROR)
        return Client(cluster), cluster
    if workers is not None:
        raise ValueError(f"`workers` applies only to the LocalCluster started when client=None "
                         f"(got workers={workers!r} with a client); size your cluster instead")
    if isinstance(client, (str, os.PathLike)):
        try:
            return Client(str(client), timeout=connect_timeout), None
        except (OSError, TimeoutError) as exc:
            raise ConnectionError(f"no dask scheduler answered at `client`={str(client)!r} within "
                                  f"{connect_timeout:g} s ({type(exc).__name__}: {exc}); start one "
                                  "(`dask scheduler`) or check the address, e.g. "
                                  "'tcp://127.0.0.1:8786'") from None
    if isinstance(client, Client):
        return client, None
    raise TypeError(f"`client` must be None, a distributed.Client or a scheduler address string "
                    f"(got {type(client).__name__})")


def run_ensemble(task: Callable[[Any], dict], params: Iterable, client=None, store=None, *,
                 workers: int | None = None, warmup: Callable[[], Any] | None = None,
                 progress: bool | None = None, connect_timeout: float = 5.0) -> list[dict]:
    """Run ``task(param)`` for every param on a dask cluster; one record per param, in order.

    Parameters
    ----------
    task : callable
        ``task(param) -> dict``, picklable: a module-level function (or a ``functools.partial``
        of one) in a module the workers can import.  Its dict should hold numbers, strings,
        booleans, None or lists of numbers when a ``store`` is used.
    params : sequence
        One picklable parameter per member (a seed, a tuple, a dict ...).
    client : None, distributed.Client or str
        None starts a ``LocalCluster`` with one single-threaded worker process per core (or
        ``workers``) and closes it afterwards.  A ``Client`` of any cluster (dask-jobqueue,
        Kubernetes, ``dask scheduler`` + ``dask worker``) is used as it is and left open; a
        string is a scheduler address ("tcp://host:8786") to connect to.
    store : path, optional
        A folder journaling the records as they finish (see the module docstring); a rerun
        with the same folder skips the members finished there.
    workers : int, optional
        Worker processes of the LocalCluster (default: the number of cores).
    warmup : callable, optional
        Called once on each worker before its first member (e.g. to load compiled numba code);
        default the task's ``warmup`` attribute, which the ready-made tasks of
        :mod:`hbvm_md.ensemble_tasks` carry.
    progress : bool, optional
        Show a progress bar (default: when stderr is a terminal).
    connect_timeout : float
        Seconds to wait for a scheduler given by address.

    Returns
    -------
    list of dict
        Per param: ``param`` (the object given), ``status`` ("ok" or "failed"), ``error``
        ("ExceptionType: message" of a failed member, else None), ``result`` (the task's dict;
        None when failed) and ``wall_time_s`` (the member's own time on its worker).  Members
        loaded from the store have ``result`` as stored (arrays become lists).

    Raises
    ------
    TypeError
        The task or a parameter does not pickle, or an argument has the wrong type.
    ValueError
        Empty ``params``; a store that holds another ensemble.
    ConnectionError
        No scheduler answers at the address given within ``connect_timeout``.
    """
    from distributed import as_completed

    from .reports.progress import progress as progress_bar

    if not callable(task):
        raise TypeError(f"`task` must be a callable task(param) -> dict (got {type(task).__name__})")
    params = _check_params(params)
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, (int, np.integer))
                                or workers < 1):
        raise ValueError(f"`workers` must be a positive integer or None (got workers={workers!r})")
    if not (isinstance(connect_timeout, (int, float)) and math.isfinite(connect_timeout)
            and connect_timeout > 0):
        raise ValueError(f"`connect_timeout` must be a positive number of seconds (got "
                         f"{connect_timeout!r})")
    _check_picklable(task, "task", "define it at module level in a module the workers can "
                     "import (not a lambda or a function holding locks, files or open simulations)")
    _check_picklable(params, "params", "use numbers, tuples, dicts, arrays or other picklable values")
    warmup = warmup if warmup is not None else _task_warmup(task)
    if warmup is not None:
        _check_picklable(warmup, "warmup", "define it at module level")

    journal = _Store(store, task, params) if store is not None else None
    records: list[dict | None] = [None] * len(params)
    if journal is not None:
        for i, rec in journal.finished().items():
            records[i] = {"param": params[i], **rec}
    todo = [i for i, r in enumerate(records) if r is None]
    if not todo:
        if journal is not None:
            journal.consolidate()
        return records

    cl, cluster = _connect(client, workers, connect_timeout)
    futures = []
    bar = progress_bar(total=len(params), desc="ensemble", enabled=progress)
    bar.update(len(params) - len(todo))
    try:
        if warmup is not None:
            try:
                cl.register_plugin(_Warmup(warmup), name=f"hbvm-md-warmup-{_task_text(warmup)}")
            except Exception as exc:
                raise RuntimeError(f"`warmup` {_task_text(warmup)} failed on a worker "
                                   f"({type(exc).__name__}: {exc}); fix it or pass another "
                                   "warmup") from exc
        index = {}
        for i in todo:
            f = cl.submit(_run_member, task, params[i], pure=False)
            index[f.key] = i
            futures.append(f)
        for f in as_completed(futures):
            i = index[f.key]
            try:
                rec = f.result()
                lost = False
            except Exception as exc:  # noqa: BLE001 - the worker died (KilledWorker) or similar
                rec = {"status": "failed", "error": f"{type(exc).__name__}: {exc}", "result": None,
                       "wall_time_s": math.nan}
                lost = True
            f.release()
            if journal is not None and not lost:     # a lost member is retried by a rerun
                journal.save(i, rec)
            records[i] = {"param": params[i], **rec}
            bar.update(1)
            bar.set_postfix_str(f"{sum(r is not None and r['status'] == 'failed' for r in records)} failed")
    finally:
        bar.close()
        unfinished = [f for f in futures if not f.done()]
        if unfinished:          # Ctrl-C or an error here: do not leave work running on a cluster
            cl.cancel(unfinished)
        if journal is not None:
            journal.consolidate()
        if cluster is not None:
            cl.close()
            cluster.close()
        elif isinstance(client, (str, os.PathLike)):
            cl.close()
    return records
