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
    if x == "sigkill" or (x == "sigkill-once" and not Path(log + ".killed").exists()):
        Path(log + ".killed").touch()
        os.kill(os.getpid(), signal.SIGKILL)        # as the out-of-memory killer would
    if x == "hang" or (x == "hang-once" and not Path(log + ".hung").exists()):
        Path(log + ".hung").touch()
        while True:             # holds the GIL: no thread could stop this
            pass
    return {"x": x}


def sleepy(x, *, log: str):
    """Writes "worker-pid member-pid" then sleeps 1 s (a member long enough to be killed in)."""
    with open(log, "a") as f:
        f.write(f"{os.getppid()} {os.getpid()}\n")
    time.sleep(1.0)
    return {"x": x}
