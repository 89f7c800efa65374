"""An ensemble store knows a task by its code and a calculator by its settings, and names rows
that are not its own (issue 47, item 6).  No cluster: the store is driven directly."""
from __future__ import annotations

import functools
import importlib
import shutil
import sys
import textwrap

import numpy as np
import pytest

pytest.importorskip("pyarrow")
pytest.importorskip("distributed")

from hbvm_md.ensemble import EnsembleStoreWarning, load_store  # noqa: E402
from hbvm_md.ensemble.identity import identity  # noqa: E402
from hbvm_md.ensemble.run import _Store  # noqa: E402


def _journal(store, task, params):
    """What run_ensemble does with a store, without the cluster: run, save, consolidate."""
    st = _Store(store, task, params)
    done = st.finished()
    for i, p in enumerate(params):
        if i not in done:
            st.save(i, {"status": "ok", "error": None, "result": task(p), "wall_time_s": 0.0})
    st.consolidate()
    return done


@pytest.fixture
def task_module(tmp_path, monkeypatch):
    """A module of the user's (task and helper) that the test edits between two runs."""
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    path = tmp_path / "user_tasks_h47.py"

    def write(scale: int, offset: int = 0):
        path.write_text(textwrap.dedent(f"""
            def helper(x):
                return x + {offset}

            def task(x):
                return {{"y": {scale} * helper(x)}}
        """))
        sys.modules.pop("user_tasks_h47", None)
        importlib.invalidate_caches()
        return importlib.import_module("user_tasks_h47")

    yield write
    sys.modules.pop("user_tasks_h47", None)


def test_an_edited_task_is_refused_not_handed_the_old_records(tmp_path, task_module):
    store = tmp_path / "store"
    mod = task_module(scale=1)
    _journal(store, mod.task, [1, 2])
    assert len(_journal(store, mod.task, [1, 2])) == 2          # unchanged: resumed
    mod = task_module(scale=2)                                   # the task edited
    with pytest.raises(ValueError, match=r"code has been edited since.*Delete the store"):
        _Store(store, mod.task, [1, 2])
    mod = task_module(scale=1, offset=5)                         # a helper it calls edited
    with pytest.raises(ValueError, match=r"code has been edited"):
        _Store(store, mod.task, [1, 2])
    shutil.rmtree(store)                                         # the way out: recompute
    assert _journal(store, mod.task, [1, 2]) == {}
    assert [r["result.y"] for r in load_store(store)] == [6, 7]


def test_a_calculator_that_has_computed_is_known_by_its_settings():
    from ase.build import bulk
    from ase.calculators.emt import EMT

    from hbvm_md.ensemble.tasks import md_replica
    atoms = bulk("Cu", cubic=True)
    atoms.calc = EMT()
    before = identity(functools.partial(md_replica, atoms=atoms), "task")
    atoms.get_potential_energy()            # EMT now holds a dict with a lambda inside
    assert identity(functools.partial(md_replica, atoms=atoms), "task") == before
    other = atoms.copy()
    other.calc = EMT(asap_cutoff=True)      # other settings: another task
    assert identity(functools.partial(md_replica, atoms=other), "task") != before
    moved = atoms.copy()
    moved.calc = EMT()
    moved.positions[0, 0] += 1e-9           # other positions: another task
    assert identity(functools.partial(md_replica, atoms=moved), "task") != before


def square(x):
    return {"x2": x * x}


def test_load_store_names_rows_copied_in_from_another_store(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    _journal(a, square, [1, 2, 3])
    _journal(b, square, [4, 5])
    with np.errstate():
        assert [r["result.x2"] for r in load_store(b)] == [16, 25]     # its own: no warning
    shutil.copy(a / "ensemble.parquet", b / "ensemble.parquet")
    with pytest.warns(EnsembleStoreWarning, match=r"members 0-2 \(of 3\) are not this store's"):
        rows = load_store(b)
    assert [r["result.x2"] for r in rows] == [1, 4, 9]
