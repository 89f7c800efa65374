"""The run of an ensemble and its store (exported by :mod:`hbvm_md.ensemble`).

:func:`run_ensemble` sends ``task(param)`` for every ``param`` to the workers of a dask cluster
(a ``LocalCluster`` on this machine unless the caller passes a ``Client`` or a scheduler
address) and returns one record per parameter, in the order of the parameters.  A member that
raises is recorded as failed with its exception; the others go on.

The store
---------
``store=DIR`` journals each finished member as ``DIR/parts/member-<index>.parquet``, written to
a temporary name and renamed, so that a crash or Ctrl-C loses only the unfinished members; a
rerun with the same ``DIR`` loads the finished ones instead of running them again (a member
that timed out runs again).  A part holds the member's index, its param (JSON text), the task,
status, error, wall time and the result pickled (cloudpickle), so that any picklable result is
kept exactly: mixed types across members, big integers, nested dicts, arrays and objects.

A member is known by content, not by ``repr``: each part carries the SHA-256 of the task and
of its param in a canonical form (:mod:`hbvm_md.ensemble.identity`: arrays by their bytes,
sets and dicts sorted, objects through the pickle protocol), so that ``partial(task,
w=other_array)`` or an ``Atoms`` with other positions is refused on a rerun rather than handed
the old records, and an object with the default ``repr`` or a set of strings (another text in
every process) resumes.  A param without such a form (a lambda, a lock) is refused by name
before any member runs.  Parts written by an earlier hbvm-md (without these digests) are set
aside with a warning and their members run again.

When the store cannot be written (a full or read-only disk), the run goes on: every record is
kept in memory and returned, and one :class:`EnsembleStoreWarning` names the store, the first
error and the members not stored; a rerun with the same store, once there is room, loads the
stored members and runs the others.  A
part or ``meta.json`` that cannot be read (truncated, corrupt, of another format) is named in
an :class:`EnsembleStoreWarning`; the part is renamed ``*.corrupt`` and its member runs again
(``meta.json`` is rewritten: each part names its task, so no member is lost with it).

At the end of every run (also an interrupted one) the records are joined into
``DIR/ensemble.parquet``: one row per finished member with the columns ``member`` (index into
params), ``param`` (JSON text), ``status``, ``error``, ``wall_time_s``, ``result.<key>`` per key
of the task's dicts (``result.<repr(key)>`` for keys whose ``str`` collide, e.g. ``result.1``
and ``result.'1'`` for 1 and "1") and ``result_pickle``.  A ``result.<key>`` column is typed when every
member's value fits one Arrow type without loss (bool, int64, float64, string, or a list of
one of them; ints beside floats as float64 when exact); otherwise (mixed types, integers
beyond int64, nested values) it holds each value as JSON text and is listed in the schema
metadata ``hbvm_md.json_columns``.  Open it with ``pandas.read_parquet`` (or polars, DuckDB,
R's arrow); :func:`load_store` gives the rows with the exact values.  Parquet through
pyarrow: one wheel with no dependencies of its own, float64 bit for bit, page checksums that
catch a corrupt file, read by every data-frame tool.  ``DIR/meta.json`` names the task and its
bound arguments; a rerun with a different task, or a different parameter at a stored index,
is refused rather than mixed in.

Stopping members
----------------
``timeout=seconds`` runs each member in a child process of its worker thread that is killed
when the member is late (see :mod:`hbvm_md.ensemble.member`); the member is recorded with
``status="timeout"``.  A member that raises ``SystemExit`` or ``KeyboardInterrupt`` is recorded
as failed with that exception, and its worker lives on.  A worker that dies (SIGKILL, the
out-of-memory killer) loses nothing: dask runs its member again on another worker, up to
three times, after which the member is recorded as failed (``KilledWorker``) but not stored,
so that a rerun tries it again.  Under a timeout a member's process SIGKILLed from outside is
treated alike (three attempts, then failed and not stored); one that crashes by itself (an
exit code, SIGSEGV) is recorded as failed with the cause.
"""
from __future__ import annotations

import functools
import hashlib
import json
import logging
import math
import os
import pickle
import warnings
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
from distributed.diagnostics.plugin import WorkerPlugin

from .identity import code_identity, identity

__all__ = ["run_ensemble", "load_store", "EnsembleStoreWarning"]

_STORE_TABLE = "ensemble.parquet"


# -- on the worker -------------------------------------------------------------------------
# In the worker thread (no timeout): member.call.  Under a timeout: a child process per worker
# thread (member.run_in_process), which can be killed.


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
def _check_picklable(obj, what: str, fix: str) -> bytes:
    import cloudpickle      # what dask sends functions with (by reference when importable)
    try:
        return cloudpickle.dumps(obj)
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
class EnsembleStoreWarning(UserWarning):
    """A store file could not be read: named in the message, set aside, its members run again."""


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


def _json_text(x) -> str:
    return json.dumps(_plain(x), sort_keys=True, default=repr)


def _task_text(task) -> str:
    if isinstance(task, functools.partial):
        args = [repr(a) for a in task.args] + [f"{k}={v!r}" for k, v in sorted(task.keywords.items())]
        return f"{_name(task)}({', '.join(args)})"
    return _name(task)


_INT64 = (-2**63, 2**63)
_FLOAT_INTS = 2**53          # integers of at most this size are exact in float64


def _scalar_kind(v) -> str | None:
    """"bool", "int", "float", "str" when ``v`` fits that Arrow type without loss; None for
    None; "other" for anything else (an int beyond int64, a long double, a list, an object)."""
    if v is None:
        return None
    if isinstance(v, (bool, np.bool_)):
        return "bool"
    if isinstance(v, (int, np.integer)):
        return "int" if _INT64[0] <= v < _INT64[1] else "other"
    if isinstance(v, float) or (isinstance(v, np.floating) and v.dtype.itemsize <= 8):
        return "float"
    if isinstance(v, str):
        return "str"
    return "other"


def _kind(v) -> str | None:
    """The Arrow type a value fits without loss: a scalar kind, "list<kind>" for a flat list,
    tuple or 1-d array of one scalar kind, "list" when empty, None (null) or "other"."""
    if isinstance(v, (list, tuple)) or (isinstance(v, np.ndarray) and v.ndim == 1):
        if len(v) == 0:
            return "list"
        inner = _common({_scalar_kind(e) for e in v}, v)
        return f"list<{inner}>" if inner in ("bool", "int", "float", "str") else "other"
    return _scalar_kind(v)


def _exact_in_float64(values) -> bool:
    return all(abs(int(e)) <= _FLOAT_INTS for e in values if _scalar_kind(e) == "int")


def _common(kinds: set, values) -> str:
    """The one kind all ``values`` (of ``kinds``, nulls allowed) share without loss, or "other"."""
    kinds = kinds - {None}
    if not kinds:
        return "null"
    if all(k.startswith("list") for k in kinds):
        inner = {k[5:-1] for k in kinds if k != "list"}
        if len(inner) <= 1:
            return f"list<{inner.pop() if inner else 'float'}>"
        elems = [e for v in values if v is not None for e in v]
        return "list<float>" if inner == {"int", "float"} and _exact_in_float64(elems) else "other"
    if len(kinds) == 1:
        return next(iter(kinds))
    # ints beside floats: a float64 column when every int is exact in it
    return "float" if kinds == {"int", "float"} and _exact_in_float64(values) else "other"


def _arrow_type(kind: str):
    import pyarrow as pa
    scalar = {"bool": pa.bool_(), "int": pa.int64(), "float": pa.float64(), "str": pa.string(),
              "null": pa.null()}
    if kind.startswith("list<"):
        return pa.list_(scalar[kind[5:-1]])
    return scalar[kind]


def _cell_text(v) -> str:
    """A value as JSON text (its repr inside when JSON has no form for it)."""
    try:
        return _json_text(v)
    except (ValueError, TypeError, RecursionError):     # e.g. a list that contains itself
        try:
            return json.dumps(repr(v))
        except Exception:  # noqa: BLE001 - a broken __repr__ must not fail the table
            return json.dumps(f"<{type(v).__name__}>")


def _column(values: list):
    """(Arrow array, exact) of one result key over the members (None where a member lacks it).

    Typed when every value fits one Arrow type without loss (ints with floats as float64 when
    exact); otherwise JSON text per value (``exact`` False), the exact values staying in the
    ``result_pickle`` column."""
    import pyarrow as pa
    try:
        kind = _common({_kind(v) for v in values}, values)
        if kind != "other":
            if kind == "float":
                values = [None if v is None else float(v) for v in values]
            elif kind == "list<float>":
                values = [None if v is None else [float(e) for e in v] for v in values]
            return pa.array([_plain(v) for v in values], _arrow_type(kind)), True
    except (pa.ArrowException, TypeError, ValueError, OverflowError):
        pass        # a subclass Arrow does not take: the column as text (the pickle is exact)
    return pa.array([None if v is None else _cell_text(v) for v in values], pa.string()), False


_PART_FIELDS = ("member", "param", "task", "status", "error", "wall_time_s", "result_pickle",
                "task_sha256", "param_sha256")
_IDENTITY_FIX = ("the store knows each member by the content of the task and its param; pass "
                 "picklable values (numbers, strings, tuples, dicts, arrays, objects of "
                 "module-level classes), or run without `store`")


def _digest(row: dict) -> str:
    """SHA-256 of a part's fields as read back: Parquet checksums only its data pages, and a
    flipped byte in its footer can change a column's type or a value unnoticed."""
    return hashlib.sha256(pickle.dumps(tuple(row[k] for k in _PART_FIELDS), protocol=4)).hexdigest()


class _Store:
    """The journal of one ensemble (see the module docstring)."""

    def __init__(self, path, task, params: list):
        import importlib
        importlib.import_module("pyarrow")   # fail before any member runs when it is missing
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise ValueError(f"`store` must be a folder (got the file {str(self.path)!r}); pass a "
                             "folder path, it is created when missing")
        # the members' identities first: a param the store cannot identify is refused on the
        # first run, before anything is written (not on the rerun, with the work done)
        self.task_id = identity(task, "task", _IDENTITY_FIX)
        self.ids = [identity(p, f"params[{i}]", _IDENTITY_FIX) for i, p in enumerate(params)]
        self.parts = self.path / "parts"
        try:
            self.parts.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OSError(exc.errno, f"`store` {str(self.path)!r} cannot be created "
                          f"({type(exc).__name__}: {exc}); pass a folder you can write to") from None
        self.texts = [_json_text(p) for p in params]
        self.task = _task_text(task)
        self.saved: dict[int, dict] = {}       # index -> stored record (what consolidate joins)
        self.write_error: tuple[Path, BaseException] | None = None     # the first failed write
        self.code_id = code_identity(task)
        meta = {"task": self.task, "task_sha256": self.task_id, "task_code_sha256": self.code_id,
                "n_members": len(params)}
        mfile = self.path / "meta.json"
        if mfile.exists():
            try:
                old = json.loads(mfile.read_text())
                if not isinstance(old, dict):
                    raise ValueError(f"a JSON object expected, got {type(old).__name__}")
            except (ValueError, UnicodeDecodeError) as exc:
                # each part names its task too, so no finished member is lost with meta.json
                self._warn(mfile, exc, "rewritten; each part is checked against the task it names")
                old = {}
            if old.get("task", self.task) != self.task:
                raise ValueError(f"`store` {str(self.path)!r} holds the ensemble of task "
                                 f"{old.get('task')!r}, not {self.task!r}; pass another store "
                                 "folder or delete this one")
            if old.get("task_code_sha256", self.code_id) != self.code_id:
                raise ValueError(f"`store` {str(self.path)!r} holds the ensemble of task "
                                 f"{self.task}, whose code has been edited since (its source, or "
                                 "that of a function of its module it calls, differs): its "
                                 "records are the old code's. Delete the store to compute them "
                                 "again with the new code, or pass another store folder (or "
                                 "put the old code back to use these records)")
            if "task_sha256" in old and "task_code_sha256" not in old:
                raise ValueError(f"`store` {str(self.path)!r} was written by an earlier hbvm-md, "
                                 "which did not identify the task by its code (an edited task "
                                 "got the old records); delete it to compute the ensemble "
                                 "again, or pass another store folder")
            if old.get("task_sha256", self.task_id) != self.task_id:
                raise ValueError(self._same_text_message("the ensemble of task", self.task))
            if old == meta:
                return          # (nothing to write: a finished store on a read-only disk loads)
        tmp = mfile.with_suffix(".tmp")
        try:
            tmp.write_text(json.dumps(meta, indent=1))
            os.replace(tmp, mfile)
        except OSError as exc:      # nothing has run yet: say so before any member does
            raise OSError(exc.errno, f"`store` {str(self.path)!r} cannot be written "
                          f"({type(exc).__name__}: {exc}); free space, make the folder "
                          "writable or pass another one") from None

    def _same_text_message(self, what: str, text: str) -> str:
        return (f"`store` {str(self.path)!r} holds {what} {text}, written the same but with "
                "other content (an argument that repr() shortens or leaves out: a long array, "
                "the positions of an Atoms, an object's attributes); pass another store folder "
                "for this ensemble, or delete this one to compute it again")

    def _file(self, i: int) -> Path:
        return self.parts / f"member-{i:07d}.parquet"

    @staticmethod
    def _warn(f: Path, exc: BaseException, what: str) -> None:
        warnings.warn(f"ensemble store file {str(f)!r} cannot be read ({type(exc).__name__}: "
                      f"{exc}); {what}", EnsembleStoreWarning, stacklevel=4)

    def _read_part(self, f: Path) -> dict:
        """The record in part ``f``; raises when the file is truncated, corrupt or foreign."""
        import pyarrow.parquet as pq
        table = pq.read_table(f, page_checksum_verification=True)
        missing = [c for c in _PART_FIELDS if c not in table.column_names]
        if set(missing) == {"task_sha256", "param_sha256"}:
            raise ValueError("written by an earlier hbvm-md, which identified a member by "
                             "repr() (and could mistake another task's or param's records for "
                             "its own)")
        if missing or table.num_rows != 1:
            raise ValueError(f"not a part of this store's format (columns {table.column_names}, "
                             f"{table.num_rows} rows)")
        row = table.to_pylist()[0]
        digest = (table.schema.metadata or {}).get(b"hbvm_md.sha256", b"").decode()
        if digest != _digest(row):
            raise ValueError("its content does not match its checksum")
        if f.name != self._file(row["member"]).name:
            raise ValueError(f"it holds member {row['member']}")
        blob = row["result_pickle"]
        row["result"] = pickle.loads(blob) if blob is not None else None
        return row

    def finished(self) -> dict[int, dict]:
        """index -> record fields (status, error, result, wall_time_s) of the stored members.

        A part that cannot be read is renamed ``*.corrupt`` with a warning naming it, and its
        member runs again; a timed-out member runs again too."""
        done = {}
        for f in sorted(self.parts.glob("member-*.parquet")):
            try:
                row = self._read_part(f)
            except Exception as exc:  # noqa: BLE001 - any unreadable part: the member runs again
                os.replace(f, f.with_name(f.name + ".corrupt"))
                self._warn(f, exc, f"moved to {f.name}.corrupt; its member runs again")
                continue
            i = row["member"]
            if row["task"] != self.task:
                raise ValueError(f"`store` {str(self.path)!r} holds member {i} of task "
                                 f"{row['task']!r}, not {self.task!r}; pass another store folder "
                                 "or delete this one")
            if row["task_sha256"] != self.task_id:
                raise ValueError(self._same_text_message(f"member {i} of task", self.task))
            if i >= len(self.texts) or (row["param"] != self.texts[i]
                                        and row["param_sha256"] != self.ids[i]):
                have = self.texts[i] if i < len(self.texts) else "no member"
                raise ValueError(f"`store` {str(self.path)!r} holds member {i} with param "
                                 f"{row['param']}, but this ensemble has {have} there; pass "
                                 "another store folder or delete this one")
            if row["param_sha256"] != self.ids[i]:
                raise ValueError(self._same_text_message(f"member {i} with param", row["param"]))
            self.saved[i] = row
            if row["status"] != "timeout":
                done[i] = {k: row[k] for k in ("status", "error", "result", "wall_time_s")}
        return done

    def save(self, i: int, rec: dict) -> None:
        """Journal member ``i``.  A write that fails (a full or read-only disk) is kept in
        ``write_error`` (the first one) and ends the journaling: the caller keeps the records
        in memory and :meth:`warn_unwritten` names the store and that error at the end."""
        import cloudpickle
        import pyarrow as pa
        import pyarrow.parquet as pq
        if self.write_error is not None:
            return
        blob = None if rec["result"] is None else cloudpickle.dumps(rec["result"])
        row = {"member": i, "param": self.texts[i], "task": self.task, "status": rec["status"],
               "error": rec["error"], "wall_time_s": float(rec["wall_time_s"]),
               "result": rec["result"], "result_pickle": blob}
        table = pa.table({"member": pa.array([i], pa.int64()), "param": [row["param"]],
                          "task": [self.task], "status": [row["status"]],
                          "error": pa.array([row["error"]], pa.string()),
                          "wall_time_s": pa.array([row["wall_time_s"]], pa.float64()),
                          "result_pickle": pa.array([blob], pa.binary()),
                          "task_sha256": [self.task_id], "param_sha256": [self.ids[i]]})
        table = table.replace_schema_metadata({"hbvm_md.sha256": _digest(table.to_pylist()[0])})
        tmp = self._file(i).with_suffix(".tmp")
        try:
            pq.write_table(table, tmp, write_page_checksum=True)
            os.replace(tmp, self._file(i))      # a crash leaves the old part or the new, never half
        except OSError as exc:
            self._write_failed(tmp, exc)
            return
        self.saved[i] = row

    def _write_failed(self, f: Path, exc: OSError) -> None:
        if self.write_error is None:
            self.write_error = (f, exc)
        try:
            f.unlink(missing_ok=True)       # no half-written temporary left behind
        except OSError:
            pass

    def warn_unwritten(self, records: list, lost: set) -> None:
        """After a run whose store could not be written: one warning naming the store, the
        first error and the members computed but not stored (returned all the same; ``lost``:
        members a rerun tries again anyway, see the module docstring)."""
        if self.write_error is None:
            return
        f, exc = self.write_error
        unstored = [i for i, r in enumerate(records)
                    if r is not None and i not in self.saved and i not in lost]
        warnings.warn(f"ensemble store {str(self.path)!r} could not be written ({type(exc).__name__}: "
                      f"{exc}, writing {f.name}); the {sum(r is not None for r in records)} records "
                      f"computed are returned, {len(unstored)} of them not stored (members "
                      f"{_ranges(unstored)}): free space or make the folder writable and run again "
                      "with the same store to journal them (the stored members are loaded, the "
                      "others run again), or pass another store folder",
                      EnsembleStoreWarning, stacklevel=3)

    def consolidate(self) -> Path | None:
        """Join the stored records into one table (see the module docstring)."""
        import pyarrow as pa
        import pyarrow.parquet as pq
        if not self.saved:
            return None
        rows = [self.saved[i] for i in sorted(self.saved)]
        keys = _result_columns(r["result"] for r in rows)
        cols = {"member": pa.array([r["member"] for r in rows], pa.int64()),
                "param": pa.array([r["param"] for r in rows], pa.string()),
                "status": pa.array([r["status"] for r in rows], pa.string()),
                "error": pa.array([r["error"] for r in rows], pa.string()),
                "wall_time_s": pa.array([r["wall_time_s"] for r in rows], pa.float64())}
        text_columns = []
        for name, k in keys.items():
            cols[name], exact = _column([(r["result"] or {}).get(k) for r in rows])
            if not exact:
                text_columns.append(name)
        cols["result_pickle"] = pa.array([r["result_pickle"] for r in rows], pa.binary())
        table = pa.table(cols).replace_schema_metadata(
            {"hbvm_md.json_columns": json.dumps(text_columns), "hbvm_md.task": self.task})
        out = self.path / _STORE_TABLE
        tmp = out.with_suffix(".tmp")
        try:
            pq.write_table(table, tmp, write_page_checksum=True)
            os.replace(tmp, out)
        except OSError as exc:
            self._write_failed(tmp, exc)
            return None
        return out


def _result_columns(results) -> dict[str, Any]:
    """column name -> key of the task's dicts, in the order first met: ``result.<key>``, or
    ``result.<repr(key)>`` for keys whose ``str`` collide (1 and "1" are ``result.1`` and
    ``result.'1'``): every key keeps a column of its own (``#n`` appended when even the reprs
    collide)."""
    seen: dict = {}                  # (type, key) -> key: 1 and 1.0 are two keys here
    for res in results:
        for k in (res if isinstance(res, dict) else {}):
            seen.setdefault((type(k), k), k)
    by_str: dict[str, list] = {}
    for k in seen.values():
        by_str.setdefault(f"result.{k}", []).append(k)
    out: dict[str, Any] = {}
    for name, ks in by_str.items():
        for k in ks:
            col, n = (name if len(ks) == 1 else f"result.{k!r}"), 1
            while col in out or (col != name and col in by_str):
                n += 1
                col = f"result.{k!r}#{n}"
            out[col] = k
    return out


def _ranges(indices: list[int]) -> str:
    """[0, 1, 2, 5, 7, 8] -> "0-2, 5, 7-8"."""
    out, start = [], None
    for k, i in enumerate(indices):
        if start is None:
            start = i
        if k + 1 == len(indices) or indices[k + 1] != i + 1:
            out.append(f"{start}" if start == i else f"{start}-{i}")
            start = None
    return ", ".join(out) or "none"


def _warn_foreign(folder: Path, table: Path, rows: list[dict]) -> None:
    """Warn naming the rows of ``table`` that this store's journal does not hold: no part of
    that member, or a part of other param, result or task (a table copied in from another
    store, or a part of another ensemble copied in)."""
    import pyarrow.parquet as pq
    try:
        task_id = json.loads((folder / "meta.json").read_text()).get("task_sha256")
    except (OSError, ValueError, AttributeError):
        task_id = None
    foreign = []
    for row in rows:
        part = folder / "parts" / f"member-{row['member']:07d}.parquet"
        try:
            p = pq.read_table(part, columns=["param", "task_sha256", "result_pickle"]).to_pylist()[0]
        except Exception:  # noqa: BLE001 - missing or unreadable: not this store's record
            foreign.append(row["member"])
            continue
        if (p["param"] != row["param"] or p["result_pickle"] != row.get("result_pickle")
                or (task_id is not None and p["task_sha256"] != task_id)):
            foreign.append(row["member"])
    if foreign:
        warnings.warn(f"{str(table)!r}: the rows of members {_ranges(sorted(foreign))} (of "
                      f"{len(rows)}) are not this store's records: its journal ({folder}/parts, "
                      "meta.json) holds no such member, or one of other param, result or task "
                      "(a table copied in from another store?); they are returned as read. "
                      "Run run_ensemble with this store's task and params to rebuild the table "
                      "from its parts", EnsembleStoreWarning, stacklevel=3)


def load_store(path) -> list[dict]:
    """The rows of a store's ``ensemble.parquet`` as dicts, ``result.<key>`` exactly as returned.

    Each row has ``member``, ``param`` (JSON text), ``status``, ``error``, ``wall_time_s`` and
    ``result.<key>`` for every key any member returned (None where a member lacks it), with
    the values unpickled from the ``result_pickle`` column: the task's own objects, types
    included (a big integer, a nested dict, an array).  Unpickling runs code named in the
    file: load stores you wrote.  A member whose pickle no longer loads (its class is gone)
    keeps the column values, with a warning.  Rows the store's own journal does not hold (a
    table copied in from another store) are named in an :class:`EnsembleStoreWarning`.  ``pandas.read_parquet`` gives the columns as a
    frame (the columns listed in the schema metadata ``hbvm_md.json_columns`` as JSON text).
    """
    import pyarrow.parquet as pq
    f = Path(path) / _STORE_TABLE
    if not f.exists():
        raise ValueError(f"`path` {str(path)!r} holds no {_STORE_TABLE}; pass the `store` folder "
                         "of a run_ensemble call")
    try:
        rows = pq.read_table(f, page_checksum_verification=True).to_pylist()
    except Exception as exc:  # noqa: BLE001 - any unreadable file: say which and how to rebuild it
        raise ValueError(f"the store table {str(f)!r} cannot be read ({type(exc).__name__}: {exc}); "
                         "run run_ensemble with the same task, params and store again to rebuild it "
                         "from the parts") from None
    _warn_foreign(Path(path), f, rows)
    results = {}
    for n, row in enumerate(rows):
        blob = row.pop("result_pickle", None)
        if blob is None:
            continue
        try:
            results[n] = pickle.loads(blob)
        except Exception as exc:  # noqa: BLE001 - keep the columns rather than fail the read
            warnings.warn(f"{str(f)!r}: the result of member {row['member']} does not unpickle "
                          f"({type(exc).__name__}: {exc}); its row keeps the column values",
                          EnsembleStoreWarning, stacklevel=2)
    # the columns consolidate named: keys whose str() collide keep one each
    columns = {(type(k), k): name for name, k in _result_columns(results.values()).items()}
    for n, result in results.items():
        for k, v in result.items():
            rows[n][columns.get((type(k), k), f"result.{k}")] = v
    return rows


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
                 progress: bool | None = None, connect_timeout: float = 5.0,
                 timeout: float | None = None) -> list[dict]:
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
        :mod:`hbvm_md.ensemble.tasks` carry.
    progress : bool, optional
        Show a progress bar (default: when stderr is a terminal).
    connect_timeout : float
        Seconds to wait for a scheduler given by address.
    timeout : float, optional
        Seconds a member may run; a longer one is stopped and recorded with
        ``status="timeout"``, the others go on.  With a timeout each worker thread runs its
        members in a child process of its own, killed (with whatever it started) when its
        member is late, and replaced for the next member; ``warmup`` then runs once per child,
        and the timeout counts the task call only (not the child's start or the warmup).
        A child that dies is recorded as failed with the cause ("MemberProcessDied: ...");
        one SIGKILLed from outside is first tried again (see the module docstring).
        Without one, members run in the worker threads and a hung member blocks its worker.

    Returns
    -------
    list of dict
        Per param: ``param`` (the object given), ``status`` ("ok"; "failed" when the member
        raised, ``SystemExit`` and ``KeyboardInterrupt`` included, when its process died or
        its worker was lost; "timeout"), ``error`` ("ExceptionType: message" of a member not
        ok, else None), ``result`` (the task's dict; None when not ok) and ``wall_time_s``
        (the member's own time on its worker).  Members loaded from the store have ``result``
        exactly as returned (pickled in the store), types included.

    Raises
    ------
    TypeError
        The task or a parameter does not pickle, or an argument has the wrong type; with a
        ``store``, a task or parameter that has no content the store can identify (a lambda,
        a lock: :mod:`hbvm_md.ensemble.identity`), before any member runs.
    ValueError
        Empty ``params``; a store that holds another ensemble (another task, or a param of
        other content at a stored index, whatever their repr); a bad ``timeout``.

    Warns
    -----
    EnsembleStoreWarning
        A store file (a part, ``meta.json``) cannot be read: the message names it; a part is
        renamed ``*.corrupt`` and its member runs again.  Or the store could not be written
        (a full or read-only disk): the records are all returned, the message names the store,
        the first error and the members not stored.
    ConnectionError
        No scheduler answers at the address given within ``connect_timeout``.
    """
    import cloudpickle
    from distributed import as_completed

    from ..reports.progress import progress as progress_bar
    from .member import call, run_in_process

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
    if timeout is not None and (isinstance(timeout, bool) or not isinstance(timeout, (int, float))
                                or not math.isfinite(timeout) or timeout <= 0):
        raise ValueError(f"`timeout` must be None or a positive number of seconds a member may "
                         f"run (got timeout={timeout!r})")
    task_bytes = _check_picklable(task, "task", "define it at module level in a module the "
                                  "workers can import (not a lambda or a function holding locks, "
                                  "files or open simulations)")
    _check_picklable(params, "params", "use numbers, tuples, dicts, arrays or other picklable values")
    warmup = warmup if warmup is not None else _task_warmup(task)
    warmup_bytes = None
    if warmup is not None:
        warmup_bytes = _check_picklable(warmup, "warmup", "define it at module level")

    journal = _Store(store, task, params) if store is not None else None
    records: list[dict | None] = [None] * len(params)
    if journal is not None:
        for i, rec in journal.finished().items():
            records[i] = {"param": params[i], **rec}
    todo = [i for i, r in enumerate(records) if r is None]
    if not todo:
        if journal is not None:
            journal.consolidate()
            journal.warn_unwritten(records, set())
        return records

    cl, cluster = _connect(client, workers, connect_timeout)
    futures = []
    lost_members = set()
    bar = progress_bar(total=len(params), desc="ensemble", enabled=progress)
    bar.update(len(params) - len(todo))
    try:
        if warmup is not None and timeout is None:      # under a timeout: in each child
            try:
                cl.register_plugin(_Warmup(warmup), name=f"hbvm-md-warmup-{_task_text(warmup)}")
            except Exception as exc:
                raise RuntimeError(f"`warmup` {_task_text(warmup)} failed on a worker "
                                   f"({type(exc).__name__}: {exc}); fix it or pass another "
                                   "warmup") from exc
        index = {}
        for i in todo:
            if timeout is None:
                f = cl.submit(call, task, params[i], pure=False)
            else:           # pickled here: the worker passes them on without importing the task
                f = cl.submit(run_in_process, task_bytes, cloudpickle.dumps(params[i]),
                              warmup_bytes, timeout, pure=False)
            index[f.key] = i
            futures.append(f)
        for f in as_completed(futures):
            i = index[f.key]
            try:
                rec = f.result()
                lost = rec.get("lost", False)
                if "result_pickle" in rec:      # from a member's process: unpickled here only
                    blob = rec["result_pickle"]
                    rec = {"status": rec["status"], "error": rec["error"],
                           "result": pickle.loads(blob) if rec["status"] == "ok" else None,
                           "wall_time_s": rec["wall_time_s"]}
            except Exception as exc:  # noqa: BLE001 - the worker died (KilledWorker) or similar
                rec = {"status": "failed", "error": f"{type(exc).__name__}: {exc}", "result": None,
                       "wall_time_s": math.nan}
                lost = True
            f.release()
            records[i] = {"param": params[i], **rec}      # (kept whatever the disk does)
            if lost:
                lost_members.add(i)
            elif journal is not None:     # a lost member is tried again by a rerun
                journal.save(i, rec)
            bar.update(1)
            bar.set_postfix_str(f"{sum(r is not None and r['status'] != 'ok' for r in records)} not ok")
    finally:
        bar.close()
        unfinished = [f for f in futures if not f.done()]
        if unfinished:          # Ctrl-C or an error here: do not leave work running on a cluster
            cl.cancel(unfinished)
        if journal is not None:
            journal.consolidate()
            journal.warn_unwritten(records, lost_members)
        if cluster is not None:
            cl.close()
            cluster.close()
        elif isinstance(client, (str, os.PathLike)):
            cl.close()
    return records
