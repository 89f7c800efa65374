"""The adversarial sweep of issue 37, items 2-4, 7 and 8: ensemble stores that must know their
members by content and lose no work, and the mistakes whose message named nothing the user did.

Built from tables: a new case is one line of ``MESSAGES`` or ``STORES``.
"""
from __future__ import annotations

import errno
import functools
import os
import subprocess
import sys
import threading
import warnings

import numpy as np
import pytest

from integrators import HBVM, NonFiniteError, Stepper, integrate
from systems import Kepler, NBody
from systems.base import SeparableSystem

KEP = Kepler(0.6)
Y0 = KEP.initial_state()


# -- 1. messages that name the argument and the fix (item 8) ------------------------------------
class ZeroMass(SeparableSystem):
    """Kepler's problem with a zero mass on its first coordinate."""
    dim = 2

    def __init__(self):
        self.masses = np.array([0.0, 1.0])

    def potential(self, q):
        return KEP.potential(q)

    def forces(self, q):
        return KEP.forces(q)


class NoDim(ZeroMass):
    dim = 0

    def __init__(self):
        self.masses = np.ones(2)


class WordDegree(Kepler):
    polynomial_degree = "four"


def _bodies(masses, positions):
    nb = NBody(masses, positions=positions, velocities=np.zeros((len(masses), 3)))
    return nb, nb.initial_state()


def _run(model, y0=Y0, method=HBVM(4, 2), **kw):
    kw = {"h": 0.01, "steps": 5, **kw}
    return lambda: integrate(method, model, y0, **kw)


def _ase_extra_row():
    from ase import Atoms
    from ase.calculators.calculator import Calculator, all_changes

    from hbvm_md.ase import HBVMDynamics

    class OneRowTooMany(Calculator):
        implemented_properties = ["energy", "forces"]

        def calculate(self, atoms=None, properties=("energy",), system_changes=all_changes):
            super().calculate(atoms, properties, system_changes)
            self.results = {"energy": 0.0, "forces": np.zeros((len(atoms) + 1, 3))}

    atoms = Atoms("H2", positions=[[0, 0, 0], [0, 0, 1.0]])
    atoms.calc = OneRowTooMany()
    return lambda: HBVMDynamics(atoms, 0.5).run(2)


PAIR = _bodies([1.0, 1.0], [[1, 2, 3], [1, 2, 3]])      # two gravitating bodies at one place
COINCIDENT = r"HBVM step .* produced non-finite values .* check the state for coincident particles"
# id, the call, the exception, what the message must say
MESSAGES = [
    ("coincident bodies", _run(*PAIR), NonFiniteError, COINCIDENT),        # (was LinAlgError)
    ("coincident bodies, newton", _run(*PAIR, solver="newton"), NonFiniteError, COINCIDENT),
    # (issue 58: at once, not after halving to the smallest step and a StepSizeError)
    ("coincident bodies, adaptive", _run(*PAIR, steps=None, adaptive=True, t_end=1.0),
     NonFiniteError, r"the forces at the state the step starts from are not finite \(nan or "
                     r"inf\), so no shorter step helps; .*two bodies on top of each other"),
    ("zero mass", _run(ZeroMass()), ValueError,
     r"`masses` of ZeroMass must be nonzero and finite, .*\(got masses\[0\]=0.0\)"),
    ("fast='no'", _run(KEP, fast="no"), ValueError,
     r"`fast` must be True .*, False .* or None .* \(got fast='no'\)"),
    ("dim = 0", _run(NoDim()), ValueError, r"`dim` of NoDim must be a positive integer.*\(got dim=0\)"),
    ("polynomial_degree = 'four'", _run(WordDegree(0.6)), ValueError,
     r"`polynomial_degree` of WordDegree must be None .* or a non-negative integer.*'four'"),
    ("method as a string", _run(KEP, method="HBVM(4, 2)"), TypeError,
     r"`method` must be a method object such as integrators.HBVM\(4, 2\) .*got str 'HBVM\(4, 2\)'"),
    ("method as a string, adaptive", _run(KEP, method="hbvm", steps=None, adaptive=True, t_end=1.0),
     TypeError, r"`method` must be a method object .*got str 'hbvm'"),
    ("method as the class", _run(KEP, method=HBVM), TypeError, r"`method` must be .*got the class HBVM"),
    ("steps = 10**12", _run(KEP, steps=10**12), ValueError,
     r"`steps`=1000000000000 with sample_every=1 keeps .* GiB.*raise sample_every"),
    ("ASE forces (N + 1, 3)", _ase_extra_row(), ValueError,
     r"calculator OneRowTooMany returned forces of shape \(3, 3\) .* for 2 atoms \(shape \(2, 3\) expected\)"),
]


@pytest.mark.parametrize("call,exc,match", [row[1:] for row in MESSAGES], ids=[row[0] for row in MESSAGES])
def test_mistakes_are_named_with_their_fix(call, exc, match):
    with pytest.raises(exc, match=match):
        call()


def test_the_checks_refuse_nothing_right():
    """Controls: test particles on top of each other (they do not feel each other), a source
    beside them, a long run with sparse samples, fast=np.True_ and an integer degree run."""
    nb = NBody([1.0, 0.0, 0.0], positions=[[0, 0, 0], [1, 0, 0], [1, 0, 0]],
               velocities=[[0, 0, 0], [0, 1, 0], [0, 1, 0]])
    res = integrate(HBVM(4, 2), nb, nb.initial_state(), 0.01, steps=20)
    assert res.status == "finished" and np.array_equal(res.y[-1, 3:6], res.y[-1, 6:9])
    assert integrate(HBVM(4, 2), KEP, Y0, 0.01, steps=10**5, sample_every=10**5).y.shape == (2, 4)
    assert integrate(HBVM(4, 2), KEP, Y0, 0.01, steps=3, fast=np.True_).status == "finished"


#: how long a gated thread waits for the other (the gate is always opened in a finally): long
#: enough that no load on the machine lets a step finish before the other thread has tried
WAIT = 600.0


class _Gate(SeparableSystem):
    """Kepler's problem (Python path) whose forces, once armed, wait in the thread that armed
    them until released: another thread then finds the Stepper mid-step."""
    dim = 2

    def __init__(self):
        self.masses = np.ones(2)
        self.inside, self.release, self.owner = threading.Event(), threading.Event(), None

    def potential(self, q):
        return KEP.potential(q)

    def forces(self, q):
        if threading.get_ident() == self.owner:
            self.inside.set()
            self.release.wait(WAIT)
        return KEP.forces(q)


def test_a_stepper_used_from_two_threads_is_refused_by_name():
    model = _Gate()
    st = Stepper(HBVM(4, 2), model, Y0, fast=False)
    st.step(0.01)
    ref = Stepper(HBVM(4, 2), _Gate(), Y0, fast=False)
    ref.step(0.01)
    ref.step(0.01)
    done = []

    def first():
        model.owner = threading.get_ident()
        st.step(0.01)
        done.append(True)

    t = threading.Thread(target=first)
    t.start()
    try:
        assert model.inside.wait(WAIT)
        with pytest.raises(RuntimeError, match=r"this Stepper is already running `step` in another "
                                               r"thread.*give each thread its own Stepper"):
            st.step(0.01)
    finally:
        model.release.set()
        t.join()
    # the first thread's step is whole, and the Stepper steps on in one thread
    assert done == [True] and st.nsteps == 2 and np.array_equal(st.y, ref.y)
    model.owner = None
    st.step(0.01)
    assert st.nsteps == 3


def test_a_rebound_simulation_integrated_from_two_threads_is_refused_by_name():
    rebound = pytest.importorskip("rebound")
    import hbvm_md.rebound  # noqa: F401 - registers "hbvm"
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, e=0.1)
    sim.integrator = "hbvm"
    sim.dt = 0.01
    inside, release = threading.Event(), threading.Event()
    owner = []

    def heartbeat(sim_pointer):
        if owner and threading.get_ident() == owner[0]:
            inside.set()
            release.wait(WAIT)

    sim.heartbeat = heartbeat
    errors = []

    def first():
        owner.append(threading.get_ident())
        try:
            sim.integrate(0.5)
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    t = threading.Thread(target=first)
    t.start()
    try:
        assert inside.wait(WAIT)
        with pytest.raises(RuntimeError, match=r"this REBOUND simulation is being integrated by "
                                               r"another thread .*sim.copy\(\)"):
            sim.integrate(1.0)
    finally:
        release.set()
        t.join()
    assert errors == [] and sim.t == 0.5
    owner.clear()
    sim.integrate(1.0)          # and again from this thread, once the other has finished
    assert sim.t == 1.0


def test_a_run_nested_in_a_heartbeat_releases_both_simulations():
    """A heartbeat of one HBVM simulation that integrates another (a run inside a run, in one
    thread): both runs end normally, and afterwards each simulation can be integrated from
    another thread (neither is left marked as running)."""
    import threading

    rebound = pytest.importorskip("rebound")
    import hbvm_md.rebound  # noqa: F401 - registers "hbvm"

    def two_body():
        s = rebound.Simulation()
        s.add(m=1.0)
        s.add(m=1e-3, a=1.0, e=0.1)
        s.integrator = "hbvm"
        s.dt = 0.01
        return s

    outer, inner = two_body(), two_body()
    calls = []

    def heartbeat(sim_pointer):
        if len(calls) < 3:
            calls.append(inner.t)
            inner.integrate(inner.t + 0.05)

    outer.heartbeat = heartbeat
    outer.integrate(0.2)
    assert len(calls) == 3 and inner.t == pytest.approx(0.15) and outer.t == 0.2
    errors = []

    def other():
        try:
            outer.integrate(0.3)
            inner.integrate(0.3)
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    t = threading.Thread(target=other)
    t.start()
    t.join()
    assert errors == [] and outer.t == 0.3 and inner.t == 0.3


# -- 2. ensemble stores (items 2, 3, 4, 7) -------------------------------------------------------
distributed = pytest.importorskip("distributed")
pytest.importorskip("pyarrow")

from hbvm_md.ensemble import EnsembleStoreWarning, load_store, run_ensemble  # noqa: E402


@pytest.fixture(scope="module")
def client():
    import logging
    # threads of this process: the store is the driver's, the members' place does not matter
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=None, silence_logs=logging.CRITICAL) as cl, \
            distributed.Client(cl) as c:
        yield c


def weighted(x, *, w, log: str):
    """sum(w) * x; one line in ``log`` per call."""
    with open(log, "a") as f:
        f.write(f"{x!r}\n")
    return {"value": float(np.sum(w)) * (x if isinstance(x, (int, float)) else 1.0)}


def positions_sum(atoms, *, log: str):
    with open(log, "a") as f:
        f.write("call\n")
    return {"value": float(atoms.positions.sum())}


def keyed(i):
    return {1: "the int", "1": "the str", "x": i}


class Plain:
    """An object with the default repr (its address: another in every process)."""

    def __init__(self, v):
        self.v = v

    def __eq__(self, other):
        return type(other) is Plain and other.v == self.v


def plain_value(p, *, log: str):
    with open(log, "a") as f:
        f.write("call\n")
    return {"value": p.v if isinstance(p, Plain) else sorted(p)}


def _one_at(i, n=2000):
    w = np.zeros(n)
    w[i] = 1.0          # (numpy's repr shows neither: "[0. 0. 0. ... 0. 0. 0.]")
    return w


def _atoms(shift):
    from ase import Atoms
    return Atoms("H2", positions=[[0, 0, 0], [0, 0, 0.74 + shift]])


def _calls(log):
    return len(open(log).read().split("\n")) - 1 if os.path.exists(log) else 0


# id, task of (log), params of the first run, of the second, what the second run must do:
# "refused" (a ValueError naming the store), "resumed" (no member runs again)
STORES = [
    ("task with another long array", lambda log: functools.partial(weighted, w=np.zeros(2000), log=log),
     [1.0, 2.0], lambda log: functools.partial(weighted, w=_one_at(1000), log=log), [1.0, 2.0],
     "refused"),
    ("Atoms with other positions", lambda log: functools.partial(positions_sum, log=log),
     [_atoms(0.0)], None, [_atoms(1e-9)], "refused"),
    ("objects with the default repr", lambda log: functools.partial(plain_value, log=log),
     [Plain(1), Plain(2)], None, [Plain(1), Plain(2)], "resumed"),
    ("sets of strings", lambda log: functools.partial(plain_value, log=log),
     [{"a", "b", "c"}, frozenset({"x", "y"})], None, [{"c", "b", "a"}, frozenset({"y", "x"})],
     "resumed"),
]


@pytest.mark.parametrize("make,first,make2,second,outcome", [row[1:] for row in STORES],
                         ids=[row[0] for row in STORES])
def test_a_store_knows_its_members_by_content(client, tmp_path, make, first, make2, second, outcome):
    log = str(tmp_path / "calls.txt")
    store = tmp_path / "store"
    recs = run_ensemble(make(log), first, client=client, store=store)
    assert [r["status"] for r in recs] == ["ok"] * len(first) and _calls(log) == len(first)
    task2 = (make2 or make)(log)
    if outcome == "refused":
        with pytest.raises(ValueError, match=rf"`store` '{store}' holds .* written the same but with "
                                             r"other content \(.*\); pass another store folder"):
            run_ensemble(task2, second, client=client, store=store)
        assert _calls(log) == len(first)           # nothing ran, nothing was handed back
    else:
        again = run_ensemble(task2, second, client=client, store=store)
        assert _calls(log) == len(first)           # every member loaded
        assert [r["result"] for r in again] == [r["result"] for r in recs]


def test_set_params_have_one_identity_in_every_process():
    """Hash randomisation orders a set of strings differently in every process: the digest
    does not follow it (each process here has another PYTHONHASHSEED)."""
    code = ("from hbvm_md.ensemble.identity import identity; "
            "print(identity([{'alpha', 'beta', 'gamma', 'delta'}, frozenset({'x', 'y', 'z'})], 'p'))")
    digests = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                              env={**os.environ, "PYTHONHASHSEED": seed}).stdout for seed in "123"}
    assert len(digests) == 1 and len(digests.pop().strip()) == 64


def test_params_the_store_cannot_identify_are_refused_on_the_first_run(client, tmp_path):
    log = str(tmp_path / "calls.txt")
    task = functools.partial(plain_value, log=log)
    with pytest.raises(TypeError, match=r"`params\[1\]` cannot be identified in the store: it holds "
                                        r"<function .*<lambda> at .* define it at module level"):
        run_ensemble(task, [Plain(1), Plain(lambda: 2)], client=client, store=tmp_path / "store")
    assert _calls(log) == 0 and not (tmp_path / "store").exists()


@pytest.mark.parametrize("fail_from", [1, 3], ids=["read-only from the start", "full mid-run"])
def test_a_failing_disk_loses_no_member(client, tmp_path, monkeypatch, fail_from):
    import pyarrow.parquet as pq
    log = str(tmp_path / "calls.txt")
    store = tmp_path / "store"
    task = functools.partial(weighted, w=np.ones(3), log=log)
    params = list(range(12))
    real, calls = pq.write_table, []

    def write_table(table, where, **kw):
        calls.append(where)
        if len(calls) >= fail_from:
            raise OSError(errno.ENOSPC, "No space left on device", str(where))
        return real(table, where, **kw)

    monkeypatch.setattr(pq, "write_table", write_table)
    with pytest.warns(EnsembleStoreWarning) as caught:
        recs = run_ensemble(task, params, client=client, store=store)
    assert [r["result"] for r in recs] == [{"value": 3.0 * x} for x in params]   # none lost
    stored = fail_from - 1
    message = str(caught[0].message)
    assert f"ensemble store '{store}' could not be written (OSError: [Errno 28] No space left " in message
    assert f"the 12 records computed are returned, {12 - stored} of them not stored" in message
    assert len(list((store / "parts").glob("member-*.parquet"))) == stored
    assert not list((store / "parts").glob("*.tmp"))
    # room again: the rerun loads the stored members and runs the others only
    monkeypatch.setattr(pq, "write_table", real)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = run_ensemble(task, params, client=client, store=store)
    assert again == recs or [r["result"] for r in again] == [r["result"] for r in recs]
    assert _calls(log) == 12 + 12 - stored
    assert len(load_store(store)) == 12


def test_result_keys_that_collide_after_str_keep_a_column_each(client, tmp_path):
    store = tmp_path / "store"
    run_ensemble(keyed, [0, 1], client=client, store=store)
    rows = load_store(store)
    assert [(r["result.1"], r["result.'1'"], r["result.x"]) for r in rows] == [
        ("the int", "the str", 0), ("the int", "the str", 1)]
    import pyarrow.parquet as pq
    table = pq.read_table(store / "ensemble.parquet")
    assert table.column("result.1").to_pylist() == ["the int"] * 2
    assert table.column("result.'1'").to_pylist() == ["the str"] * 2
