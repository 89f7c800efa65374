"""run_ensemble on dask.distributed: records, failures, the store, bad arguments, a real cluster."""
from __future__ import annotations

import decimal
import enum
import functools
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")
pytest.importorskip("pyarrow")

from distributed import Client, LocalCluster  # noqa: E402

from hbvm_md.ensemble import EnsembleStoreWarning, load_store, run_ensemble  # noqa: E402
from hbvm_md.ensemble.tasks import md_replica, solar_clone, stability_member, stability_table  # noqa: E402

from ensemble_misbehaving import misbehave, sleepy  # noqa: E402

CLONE = functools.partial(solar_clone, t_end=5000.0, n_samples=4)


@pytest.fixture(scope="module")
def client():
    import logging
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.CRITICAL) as cluster, Client(cluster) as c:
        yield c


# tasks of these tests: module-level so that they pickle by reference (the LocalCluster's
# spawned workers inherit sys.path, so they import this module)
def counted(x, *, log: str):
    """x squared; appends a line to ``log`` per call (counts calls across processes)."""
    with open(log, "a") as f:
        f.write(f"{x}\n")
    if x == 3:
        raise ArithmeticError(f"member {x} fails on purpose")
    return {"x": x, "square": x * x, "values": [x / 3, x / 7]}


def warm_count(log: str):
    with open(log, "a") as f:
        f.write(f"{os.getpid()}\n")


# results no single Arrow column holds: mixed types across members, big ints, nested values
VARIED = [{"v": 1.5, "w": 1, "flag": True},
          {"v": "text", "w": 0.5, "flag": False},
          {"v": [1, 2], "w": 2, "flag": True, "arr": np.arange(3.0)},
          {"v": True, "w": -3, "flag": False},
          {"v": 2**70, "w": 0.25, "flag": True, "nested": {"a": [1, "x"], "b": (2, 3.5), 7: None}},
          {"v": {"deep": [[1.0], "y"]}, "w": 4, "flag": False, "arr": np.arange(2, dtype=np.int32)}]


class Half(float):
    """A float subclass (Arrow takes no subclass as a float)."""


class Colour(enum.IntEnum):
    RED = 1


LOOP = [1.0]
LOOP.append(LOOP)           # a list that contains itself: no JSON, no Arrow type
ODD = [{"v": np.longdouble(1) / 3}, {"v": Half(0.5)}, {"v": Colour.RED}, {"v": 1 + 2j},
       {"v": decimal.Decimal("0.1")}, {"v": LOOP}, {"v": np.uint64(2**64 - 1)}]


def odd(i):
    return ODD[i]


def varied(i, *, log: str):
    with open(log, "a") as f:
        f.write(f"{i}\n")
    return VARIED[i]


def same(a, b) -> bool:
    """Equal values of the same types, all the way down (arrays: dtype and elements)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and bool(np.all(a == b))
    if isinstance(a, dict):
        return list(a) == list(b) and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return a == b




def test_records_equal_serial_runs_bit_for_bit(client):
    seeds = [0, 1, 2, 3]
    recs = run_ensemble(CLONE, seeds, client=client)
    assert [r["param"] for r in recs] == seeds
    for seed, r in zip(seeds, recs):
        assert r["status"] == "ok" and r["error"] is None
        assert r["result"] == CLONE(seed)          # every float equal, not close
        assert r["wall_time_s"] > 0
    # different seeds really are different members
    assert recs[0]["result"]["max_rel_energy_error"] != recs[1]["result"]["max_rel_energy_error"]


def test_md_replicas_equal_serial_runs(client):
    task = functools.partial(md_replica, n_atoms=6, steps=10)
    recs = run_ensemble(task, [5, 6], client=client)
    assert [r["result"] for r in recs] == [task(5), task(6)]
    assert recs[0]["result"]["max_rel_dE"] < 1e-12


def test_failed_member_is_recorded_and_the_others_finish(client, tmp_path):
    grid = [(7.0, 0.05), (25.0, 1.5), (26.0, 0.0)]     # e = 1.5 is no planet
    task = functools.partial(stability_member, t_end=3000.0, n_samples=3)
    recs = run_ensemble(task, grid, client=client)
    assert [r["status"] for r in recs] == ["ok", "failed", "ok"]
    assert recs[1]["error"].startswith("ValueError: a planet needs a > 0 and 0 <= e < 1 (got a=25.0, e=1.5)")
    assert recs[1]["result"] is None
    assert recs[2]["result"] == task((26.0, 0.0))
    rows = stability_table(recs)
    assert rows[1]["survived"] is False and "e=1.5" in rows[1]["stop_reason"]


def test_rerun_with_the_same_store_skips_finished_members(client, tmp_path):
    log = tmp_path / "calls.txt"
    task = functools.partial(counted, log=str(log))
    store = tmp_path / "store"
    params = list(range(6))
    # a first run that stopped after three members (as after Ctrl-C) ...
    first = run_ensemble(task, params[:3], client=client, store=store)
    assert sorted(log.read_text().split()) == ["0", "1", "2"]
    # ... then the full ensemble: only members 3, 4, 5 run
    recs = run_ensemble(task, params, client=client, store=store)
    assert sorted(log.read_text().split()) == ["0", "1", "2", "3", "4", "5"]
    assert recs[:3] == first
    assert recs[3]["status"] == "failed" and "ArithmeticError: member 3 fails on purpose" == recs[3]["error"]
    assert recs[5]["result"] == {"x": 5, "square": 25, "values": [5 / 3, 5 / 7]}
    # a third run calls nothing (the failed member is finished too) and returns the same
    again = run_ensemble(task, params, client=client, store=store)
    assert len(log.read_text().split()) == 6
    assert again == recs
    # the joined table a scientist opens
    rows = load_store(store)
    assert [r["member"] for r in rows] == params
    assert rows[4]["result.square"] == 16 and rows[3]["result.square"] is None
    assert rows[3]["status"] == "failed"


def test_mixed_and_big_results_are_stored_exactly_and_reread(client, tmp_path):
    log = tmp_path / "calls.txt"
    task = functools.partial(varied, log=str(log))
    store = tmp_path / "store"
    first = run_ensemble(task, range(3), client=client, store=store)
    recs = run_ensemble(task, range(6), client=client, store=store)     # 3 loaded, 3 run
    assert sorted(log.read_text().split()) == ["0", "1", "2", "3", "4", "5"]
    again = run_ensemble(task, range(6), client=client, store=store)    # all loaded
    assert len(log.read_text().split()) == 6
    for runs in (first, recs, again):
        for i, r in enumerate(runs):
            assert r["status"] == "ok", r
            assert same(r["result"], VARIED[i]), (i, r["result"])
    # the joined table: lossless columns typed, the others JSON text, exact values from load_store
    import pyarrow.parquet as pq
    table = pq.read_table(store / "ensemble.parquet")
    types = {n: str(table.schema.field(n).type) for n in table.column_names}
    assert types["result.w"] == "double" and types["result.flag"] == "bool"
    assert types["result.v"] == types["result.nested"] == "string"
    assert types["result.arr"] == "list<element: double>"     # int32 beside float64: exact
    assert json.loads(table.schema.metadata[b"hbvm_md.json_columns"]) == ["result.v", "result.nested"]
    assert table.column("result.w").to_pylist() == [1.0, 0.5, 2.0, -3.0, 0.25, 4.0]
    assert table.column("result.v").to_pylist()[4] == "1180591620717411303424"
    rows = load_store(store)
    for i, row in enumerate(rows):
        got = {k[len("result."):]: v for k, v in row.items() if k.startswith("result.") and v is not None}
        assert same(got, {str(k): v for k, v in VARIED[i].items() if v is not None})


def test_odd_results_never_fail_the_store(client, tmp_path):
    store = tmp_path / "store"
    recs = run_ensemble(odd, range(len(ODD)), client=client, store=store)
    rows = load_store(store)
    again = run_ensemble(odd, range(len(ODD)), client=client, store=store)     # read from the parts
    for i, expected in enumerate(ODD):
        for got in (recs[i]["result"]["v"], rows[i]["result.v"], again[i]["result"]["v"]):
            assert type(got) is type(expected["v"])
            if expected["v"] is LOOP:
                assert got[0] == 1.0 and got[1] is got
            else:
                assert got == expected["v"]
    import pyarrow.parquet as pq
    column = pq.read_table(store / "ensemble.parquet").column("result.v").to_pylist()
    assert column[5] == '"[1.0, [...]]"' and column[6] == "18446744073709551615"


def test_corrupt_part_and_meta_are_named_and_their_members_rerun(client, tmp_path):
    log = tmp_path / "calls.txt"
    task = functools.partial(varied, log=str(log))
    store = tmp_path / "store"
    run_ensemble(task, range(4), client=client, store=store)
    part1, part2 = store / "parts" / "member-0000001.parquet", store / "parts" / "member-0000002.parquet"
    part1.write_bytes(part1.read_bytes()[:-40])                   # truncated (a full disk)
    blob = bytearray(part2.read_bytes())
    blob[blob.find(b"varied")] ^= 0xFF                             # one flipped byte in the data
    part2.write_bytes(bytes(blob))
    (store / "meta.json").write_text('{"task": "hbvm_md')          # half written
    with pytest.warns(EnsembleStoreWarning) as caught:
        recs = run_ensemble(task, range(4), client=client, store=store)
    messages = "\n".join(str(w.message) for w in caught)
    assert f"{store / 'meta.json'}' cannot be read (JSONDecodeError" in messages
    assert f"{part1}' cannot be read" in messages and f"{part2}' cannot be read" in messages
    assert "moved to member-0000001.parquet.corrupt; its member runs again" in messages
    assert sorted(log.read_text().split()) == ["0", "1", "1", "2", "2", "3"]   # 1 and 2 ran again
    assert all(same(r["result"], VARIED[i]) for i, r in enumerate(recs))
    assert (store / "parts" / "member-0000001.parquet.corrupt").exists()
    meta = json.loads((store / "meta.json").read_text())
    assert meta["task"] == f"{__name__}.varied(log={str(log)!r})"
    # the store is whole again: a rerun runs nothing and warns nothing
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        run_ensemble(task, range(4), client=client, store=store)
    assert len(log.read_text().split()) == 6
    # a corrupt joined table is named too
    table = store / "ensemble.parquet"
    table.write_bytes(table.read_bytes()[:100])
    with pytest.raises(ValueError, match=rf"the store table '{table}' cannot be read .* run "
                       "run_ensemble with the same task, params and store again"):
        load_store(store)


@pytest.mark.parametrize("timeout", [None, 60.0], ids=["in-thread", "member-process"])
def test_system_exit_and_keyboard_interrupt_are_recorded_with_their_cause(client, timeout):
    workers = client.run(os.getpid)
    recs = run_ensemble(misbehave, ["exit", 1, "interrupt", 2], client=client, timeout=timeout)
    assert [(r["status"], r["error"]) for r in recs] == [
        ("failed", "SystemExit: 3"), ("ok", None), ("failed", "KeyboardInterrupt: stop"), ("ok", None)]
    assert recs[1]["result"] == {"x": 1} and recs[0]["result"] is None
    assert client.run(os.getpid) == workers            # no worker died


def test_timeout_stops_a_hung_member_and_keeps_the_others(client, tmp_path):
    log = str(tmp_path / "calls.txt")
    task = functools.partial(misbehave, log=log)
    store = tmp_path / "store"
    params = [1, "hang-once", 2, "die", 3, "sigkill-once", "sigkill", 4]
    recs = run_ensemble(task, params, client=client, store=store, timeout=1.5)
    assert [r["status"] for r in recs] == ["ok", "timeout", "ok", "failed", "ok", "ok", "failed", "ok"]
    assert recs[1]["error"] == ("TimeoutError: the member ran longer than timeout=1.5 s; its "
                                "process was stopped")
    assert recs[1]["result"] is None and recs[1]["wall_time_s"] >= 1.5
    assert recs[3]["error"] == "MemberProcessDied: the member's process exited with code 7"
    # SIGKILLed from outside: tried again in a new process, as dask does when a worker dies
    assert recs[6]["error"] == ("MemberProcessDied: the member's process was killed by signal 9 "
                                "(SIGKILL) in each of 3 attempts")
    assert [r["result"] for r in recs if r["status"] == "ok"] == [
        {"x": x} for x in (1, 2, 3, "sigkill-once", 4)]
    calls = Path(log).read_text().split()
    assert (calls.count("sigkill-once"), calls.count("sigkill")) == (2, 3)
    assert [r["status"] for r in load_store(store)] == ["ok", "timeout", "ok", "failed", "ok", "ok", "ok"]
    # a rerun runs the timed-out member and the lost one only (the first finishes this time)
    again = run_ensemble(task, params, client=client, store=store, timeout=1.5)
    calls = Path(log).read_text().split()
    assert [calls.count(p) for p in ("hang-once", "die", "sigkill-once", "sigkill")] == [2, 1, 2, 6]
    assert again[1] == {"param": "hang-once", "status": "ok", "error": None,
                        "result": {"x": "hang-once"}, "wall_time_s": again[1]["wall_time_s"]}
    assert again[3] == recs[3] and again[5] == recs[5]


def _running(pid: int) -> bool:
    """The process exists and is not a zombie (a dead child not reaped yet)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            return not any(line.startswith("State:") and "Z" in line for line in f)
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("timeout", [None, 60.0], ids=["in-thread", "member-process"])
def test_sigkilled_worker_loses_nothing(client, tmp_path, timeout):
    log = tmp_path / "pids.txt"
    log.touch()
    killed = []

    def kill_first_member_worker():
        # member 0's first run waits to be killed: kill it once its line is written
        while not (first := [ln for ln in log.read_text().splitlines() if ln.startswith("0 ")]):
            time.sleep(0.02)
        worker, member = map(int, first[0].split()[1:3])
        if timeout is None:
            worker = member                 # in-thread: the member runs in the worker
        os.kill(worker, signal.SIGKILL)
        killed.append((worker, member))

    killer = threading.Thread(target=kill_first_member_worker)
    killer.start()
    recs = run_ensemble(functools.partial(sleepy, log=str(log)), range(4), client=client,
                        timeout=timeout)
    killer.join()
    assert [r["status"] for r in recs] == ["ok"] * 4
    assert [r["result"] for r in recs] == [{"x": x} for x in range(4)]
    assert len(log.read_text().splitlines()) == 5          # the killed member ran twice
    worker, member = killed[0]
    assert not _running(worker) and not _running(member)    # the member died with its worker
    client.wait_for_workers(2, timeout=300)


def test_store_of_another_ensemble_is_refused(client, tmp_path):
    log = str(tmp_path / "calls.txt")
    store = tmp_path / "store"
    run_ensemble(functools.partial(counted, log=log), [1, 2], client=client, store=store)
    with pytest.raises(ValueError, match=r"holds member 1 with param 2, but this ensemble has 5"):
        run_ensemble(functools.partial(counted, log=log), [1, 5], client=client, store=store)
    with pytest.raises(ValueError, match=r"holds the ensemble of task .*counted\(log="):
        run_ensemble(CLONE, [1, 2], client=client, store=store)


def test_warmup_runs_once_per_worker_not_per_member(client, tmp_path):
    log = tmp_path / "warm.txt"
    task = functools.partial(counted, log=str(tmp_path / "calls.txt"))
    warm = functools.partial(warm_count, str(log))
    run_ensemble(task, [0, 1, 2, 4, 5, 6], client=client, warmup=warm)
    run_ensemble(task, [7, 8], client=client, warmup=warm)
    pids = log.read_text().split()
    assert len(pids) == 2 and len(set(pids)) == 2


def test_bad_arguments_fail_fast():
    with pytest.raises(TypeError, match=r"`task` cannot be sent to the workers: it does not pickle"):
        run_ensemble(functools.partial(counted, log=threading.Lock()), [1])
    with pytest.raises(ValueError, match=r"`params` is empty"):
        run_ensemble(CLONE, [])
    with pytest.raises(TypeError, match=r"`params` must be a sequence of parameters"):
        run_ensemble(CLONE, "0123")
    with pytest.raises(TypeError, match=r"`params` cannot be sent to the workers"):
        run_ensemble(CLONE, [threading.Lock()])
    with pytest.raises(ValueError, match=r"`workers` must be a positive integer"):
        run_ensemble(CLONE, [1], workers=0)
    with pytest.raises(TypeError, match=r"`client` must be None, a distributed.Client or a scheduler"):
        run_ensemble(CLONE, [1], client=42)
    for bad in (0, -1.0, float("nan"), True, "1"):
        with pytest.raises(ValueError, match=r"`timeout` must be None or a positive number of "
                           rf"seconds a member may run \(got timeout={bad!r}\)"):
            run_ensemble(CLONE, [1], timeout=bad)


def test_unreachable_scheduler_is_a_clear_error():
    port = _free_port()           # nothing listens there
    with pytest.raises(ConnectionError, match=rf"no dask scheduler answered at .*127.0.0.1:{port}.* within 1 s"):
        run_ensemble(CLONE, [1], client=f"tcp://127.0.0.1:{port}", connect_timeout=1.0)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ensemble_through_a_scheduler_and_two_worker_processes(tmp_path):
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    dask = [sys.executable, "-m", "dask"]
    procs = []
    logs = []
    try:
        def start(args, name):
            f = open(tmp_path / f"{name}.log", "w")
            logs.append(f)
            procs.append(subprocess.Popen(dask + args, stdout=f, stderr=subprocess.STDOUT))
        start(["scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"], "scheduler")
        for i in range(2):
            start(["worker", addr, "--nthreads", "1", "--no-dashboard", "--name", f"w{i}"], f"worker{i}")
        # (generous: on a loaded machine starting a scheduler and two workers can take a while;
        # a healthy start takes seconds)
        with Client(addr, timeout=300) as c:
            c.wait_for_workers(2, timeout=300)
            assert len(c.scheduler_info()["workers"]) == 2
        recs = run_ensemble(CLONE, [4, 5, 6], client=addr)
        assert [r["result"] for r in recs] == [CLONE(4), CLONE(5), CLONE(6)]
    finally:
        for p in procs:
            p.terminate()
        deadline = time.monotonic() + 10
        for p in procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for f in logs:
            f.close()


def test_cli_stability_map_writes_csv_and_png(client, tmp_path, capsys):
    import csv

    from hbvm_md.cli import main
    out = tmp_path / "map"
    # --timeout: the members run in the workers' member processes (and well within it)
    args = ["ensemble", "stability-map", "--grid", "2x2", "--a-range", "7", "25", "--t-end", "3000",
            "--scheduler", client.scheduler.address, "--out", str(out), "--timeout", "600"]
    assert main(args) == 0
    assert "4 survived, 0 unstable, 0 failed, 0 timed out" in capsys.readouterr().out
    rows = list(csv.DictReader(open(out / "stability_map.csv")))
    assert [(float(r["a"]), float(r["e"])) for r in rows] == [(7.0, 0.0), (7.0, 0.5), (25.0, 0.0), (25.0, 0.5)]
    assert all(r["status"] == "ok" and float(r["max_rel_energy_error"]) < 1e-12 for r in rows)
    assert (out / "stability_map.png").stat().st_size > 10_000
    # a changed run length is refused instead of mixing in the stored members
    assert main([a if a != "3000" else "6000" for a in args]) == 2
    assert "holds the ensemble of task" in capsys.readouterr().err


def test_cli_rejects_workers_with_scheduler(capsys):
    from hbvm_md.cli import main
    assert main(["ensemble", "stability-map", "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"]) == 2
    assert "not both" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["ensemble", "stability-map", "--timeout", "0"])
    assert "--timeout: expected a positive number, got '0'" in capsys.readouterr().err


def test_stability_member_uses_megno_by_default_and_keeps_the_clone_indicator():
    """A regular point (a planet at 26 AU, circular): REBOUND's MEGNO from HBVM's variational
    particles by default, near 2 once it has settled; the shadow clone on request; a bad
    indicator is refused by name."""
    megno = stability_member((26.0, 0.0), t_end=2e5, n_samples=4)
    assert megno["indicator"] == "megno" and megno["survived"]
    assert 1.5 < megno["megno"] < 2.5 and abs(megno["lyapunov"]) < 1e-5
    assert "log10_divergence" not in megno
    clone = stability_member((26.0, 0.0), t_end=3000.0, n_samples=3, indicator="clone")
    assert clone["indicator"] == "clone" and np.isfinite(clone["log10_divergence"])
    with pytest.raises(ValueError, match=r"`indicator` must be one of \('megno', 'clone'\) "
                                         r"\(got 'fli'\)"):
        stability_member((26.0, 0.0), indicator="fli")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX signals")
def test_sigkill_members_do_not_share_a_marker(tmp_path):
    """"sigkill" run first must not mark "sigkill-once" as killed (they shared one marker file,
    and in parallel the run order decided whether "sigkill-once" was ever killed)."""
    log = str(tmp_path / "calls.txt")
    here = str(Path(__file__).resolve().parent)

    def member(x):
        code = (f"import sys; sys.path.insert(0, {here!r}); "
                f"from ensemble_misbehaving import misbehave; misbehave({x!r}, log={log!r})")
        return subprocess.run([sys.executable, "-c", code], timeout=120).returncode

    assert member("sigkill") == -signal.SIGKILL
    assert member("sigkill-once") == -signal.SIGKILL        # its own first run, killed
    assert member("sigkill-once") == 0                      # its second, through
