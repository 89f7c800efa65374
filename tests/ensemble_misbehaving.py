"""Ensemble members that stop their process, hang or sleep (tasks of tests/test_ensemble.py).

Apart from the test module so that a member process started for them imports only this (the
tests' timed members run in fresh processes, several times when killed)."""
import os
import signal
import time
from pathlib import Path


def misbehave(x, *, log: str = ""):
    """Members that stop their process or hang; a number returns normally."""
    if log:
        with open(log, "a") as f:
            f.write(f"{x}\n")
    if x == "exit":
        raise SystemExit(3)
    if x == "interrupt":
        raise KeyboardInterrupt("stop")
    if x == "die":
        os._exit(7)
    # one marker per member: members run in parallel, and "sigkill" must not mark "sigkill-once"
    # as killed (nor "hang" mark "hang-once" as hung)
    if x == "sigkill" or (x == "sigkill-once" and not Path(f"{log}.{x}.killed").exists()):
        Path(f"{log}.{x}.killed").touch()
        os.kill(os.getpid(), signal.SIGKILL)        # as the out-of-memory killer would
    if x == "hang" or (x == "hang-once" and not Path(f"{log}.{x}.hung").exists()):
        Path(f"{log}.{x}.hung").touch()
        while True:             # holds the GIL: no thread could stop this
            pass
    return {"x": x}


def sleepy(x, *, log: str):
    """Writes "param worker-pid member-pid"; member 0's first run then waits (up to 120 s) to be
    killed from outside, every other run returns at once (no race between a kill and a sleep)."""
    with open(log, "a") as f:
        f.write(f"{x} {os.getppid()} {os.getpid()}\n")
    marker = Path(f"{log}.{x}.started")
    if x == 0 and not marker.exists():
        marker.touch()
        time.sleep(120.0)
    return {"x": x}
