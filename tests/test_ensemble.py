"""run_ensemble on dask.distributed: records, failures, the store, bad arguments, a real cluster."""
from __future__ import annotations

import functools
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("distributed")
pytest.importorskip("pyarrow")

from distributed import Client, LocalCluster  # noqa: E402

from hbvm_md.ensemble import load_store, run_ensemble  # noqa: E402
from hbvm_md.ensemble_tasks import md_replica, solar_clone, stability_member, stability_table  # noqa: E402

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
        with Client(addr, timeout=30) as c:
            c.wait_for_workers(2, timeout=60)
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
    args = ["ensemble", "stability-map", "--grid", "2x2", "--a-range", "7", "25", "--t-end", "3000",
            "--scheduler", client.scheduler.address, "--out", str(out)]
    assert main(args) == 0
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
