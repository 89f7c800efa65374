"""One ensemble member, called and recorded; and the process that runs members under a timeout.

:func:`call` runs ``task(param)`` and turns whatever it raises into a record, ``SystemExit``
and ``KeyboardInterrupt`` included (a dask worker thread that lets them through kills its
worker, and dask then retries the member on the next worker until four are dead).

:class:`MemberProcess` is how ``run_ensemble(..., timeout=seconds)`` stops a member that runs
too long.  A dask worker runs tasks in threads, and a thread cannot be stopped from outside
(dask has no task timeout, dask/distributed#391; restarting the worker through its nanny kills
every task on it, and ``dask worker --no-nanny`` has none).  So each worker thread hands its
members to a child process of its own, started with :mod:`subprocess` (``multiprocessing``
refuses to start children of a daemonic nanny worker, dask/distributed#2142), and waits on a
pipe for at most ``timeout`` seconds; past that, the child's whole process group is
SIGKILLed, whatever it is doing (a compiled loop holding the GIL, a C call, a sleep), and the
next member gets a fresh child.  The child dies with its worker: on Linux it asks the kernel
for SIGKILL when the thread that started it exits (``PR_SET_PDEATHSIG``; that thread is a
dedicated one living as long as the worker process), elsewhere a watchdog thread checks its
parent every second.  Run as ``python -m hbvm_md.ensemble.member READ_FD WRITE_FD PARENT_PID``.
"""
from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from multiprocessing.connection import Connection

__all__ = ["call", "MemberProcess", "member_process"]


def describe(exc: BaseException) -> str:
    """``"Type: message"`` (``"Type"`` when the message is empty), as a record's ``error``."""
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def call(task, param) -> dict:
    """``task(param)`` timed; any exception, also ``SystemExit``/``KeyboardInterrupt``, recorded.

    Returns
    -------
    dict
        ``status`` ("ok" or "failed"), ``error`` (None or "Type: message"), ``result`` (the
        task's dict, None when failed) and ``wall_time_s``.
    """
    start = time.perf_counter()
    try:
        result = task(param)
        if not isinstance(result, dict):
            raise TypeError(f"the task must return a dict (got {type(result).__name__} for "
                            f"param={param!r})")
        status, error = "ok", None
    except BaseException as exc:  # noqa: BLE001 - SystemExit/KeyboardInterrupt of a member are its failure
        result, status, error = None, "failed", describe(exc)
    return {"status": status, "error": error, "result": result,
            "wall_time_s": time.perf_counter() - start}


# -- in the worker ---------------------------------------------------------------------------
# One long-lived thread starts every child: PR_SET_PDEATHSIG fires when the *thread* that
# forked the child exits, and dask's executor threads may be retired (secede/rejoin).
_SPAWNER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="hbvm-md-member-spawner")
_PER_THREAD = threading.local()


def _signal_name(code: int) -> str:
    try:
        return signal.Signals(code).name
    except ValueError:
        return str(code)


class MemberProcess:
    """A child process that runs members one at a time for one worker thread.

    Messages (pickles over two pipes): ``("prepare", sys_path, task_bytes, warmup_bytes)``
    loads the task (and calls the warmup once per child), ``("run", param_bytes)`` runs one
    member and answers its record with the result pickled (the worker never unpickles it).
    """

    def __init__(self):
        if os.name != "posix":
            raise OSError(f"run_ensemble(timeout=...) needs POSIX workers (process groups, "
                          f"inherited pipes); this worker runs on {sys.platform!r}: pass timeout=None")
        parent_r, child_w = os.pipe()
        child_r, parent_w = os.pipe()
        cmd = [sys.executable, "-m", "hbvm_md.ensemble.member", str(child_r), str(child_w),
               str(os.getpid())]
        try:
            # a session of its own: a Ctrl-C at the terminal goes to the client (which cancels),
            # and a timeout kills the member's own children with it
            self.proc = _SPAWNER.submit(subprocess.Popen, cmd, pass_fds=(child_r, child_w),
                                        start_new_session=True).result()
        finally:
            os.close(child_r)
            os.close(child_w)
        self.conn_in = Connection(parent_r, writable=False)
        self.conn_out = Connection(parent_w, readable=False)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> None:
        """SIGKILL the child and everything it started; reap it; close the pipes."""
        if self.proc.returncode is None:    # not reaped: its pid (its group's id) is still its own
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        self.proc.wait()
        self.conn_in.close()
        self.conn_out.close()

    def _death(self) -> str:
        code = self.proc.wait()
        how = (f"was killed by signal {-code} ({_signal_name(-code)})" if code < 0
               else f"exited with code {code}")
        return f"MemberProcessDied: the member's process {how}"

    def prepare(self, task_bytes: bytes, warmup_bytes: bytes | None) -> str | None:
        """Load the task (and warm up) in the child; None, or the error text of a failure."""
        try:
            self.conn_out.send(("prepare", list(sys.path), task_bytes, warmup_bytes))
            answer = self.conn_in.recv()
        except (EOFError, OSError):
            return self._death()
        return answer

    def run(self, param_bytes: bytes, timeout: float) -> dict:
        """One member's record; ``status="timeout"`` (the child killed) past ``timeout`` s."""
        start = time.perf_counter()
        try:
            self.conn_out.send(("run", param_bytes))
            if not self.conn_in.poll(timeout):
                self.stop()
                return {"status": "timeout", "result_pickle": None,
                        "error": (f"TimeoutError: the member ran longer than timeout={timeout:g} s; "
                                  "its process was stopped"),
                        "wall_time_s": time.perf_counter() - start}
            return self.conn_in.recv()
        except (EOFError, OSError):
            return {"status": "failed", "error": self._death(), "result_pickle": None,
                    "wall_time_s": time.perf_counter() - start}


def member_process() -> MemberProcess:
    """The calling thread's child (a new one when there is none or it died)."""
    mp = getattr(_PER_THREAD, "process", None)
    if mp is None or not mp.alive():
        if mp is not None:
            mp.stop()
        mp = _PER_THREAD.process = MemberProcess()
    return mp


# A child SIGKILLed from outside (the out-of-memory killer picks the biggest process: the
# member's, not its worker) is tried again, as dask retries a member whose worker died
# (``distributed.scheduler.allowed-failures``, 3); a crash of the member's own (SIGSEGV, exit
# code) is its result and is not.
ATTEMPTS = 3


def run_in_process(task_bytes: bytes, param_bytes: bytes, warmup_bytes: bytes | None,
                   timeout: float) -> dict:
    """A member run in the worker thread's child, stopped after ``timeout`` s (runs on a worker).

    Returns the record of :func:`call` with ``result_pickle`` (the result, pickled in the
    child) instead of ``result``; ``status`` "ok", "failed" or "timeout"; ``lost`` True when
    its child was SIGKILLed from outside in every one of ``ATTEMPTS`` tries (a store does not
    keep such a member: a rerun tries it again, as after dask's ``KilledWorker``).
    """
    for _ in range(ATTEMPTS):
        mp = member_process()
        failure = mp.prepare(task_bytes, warmup_bytes)
        if failure is not None:
            rec = {"status": "failed", "error": failure, "result_pickle": None, "wall_time_s": 0.0}
        else:
            rec = mp.run(param_bytes, timeout)
        if mp.alive():
            return rec
        mp.stop()
        _PER_THREAD.process = None
        if rec["status"] == "timeout" or mp.proc.returncode != -signal.SIGKILL:
            return rec
    rec["error"] += f" in each of {ATTEMPTS} attempts"
    rec["lost"] = True
    return rec


# -- in the child ----------------------------------------------------------------------------
def _die_with_parent(parent_pid: int) -> None:
    if sys.platform.startswith("linux"):
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_PDEATHSIG = 1
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0:
            if os.getppid() != parent_pid:        # the parent died before prctl
                os._exit(1)
            return

    def watch():         # needs the GIL: a member holding it delays this check
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(1)
    threading.Thread(target=watch, daemon=True).start()


def _serve(conn_in: Connection, conn_out: Connection) -> None:
    import cloudpickle
    task_bytes = task = None
    warmed = set()
    while True:
        try:
            msg = conn_in.recv()
        except EOFError:
            return
        if msg[0] == "prepare":
            _, path, t_bytes, w_bytes = msg
            sys.path[:] = path
            answer = None
            try:
                if t_bytes != task_bytes:
                    task, task_bytes = pickle.loads(t_bytes), t_bytes
                if w_bytes is not None and w_bytes not in warmed:
                    pickle.loads(w_bytes)()
                    warmed.add(w_bytes)
            except BaseException as exc:  # noqa: BLE001 - reported to the worker as the member's failure
                task_bytes = task = None
                answer = f"the task or its warmup failed to load in the member's process ({describe(exc)})"
            conn_out.send(answer)
        elif msg[0] == "run":
            rec = call(task, pickle.loads(msg[1]))
            try:
                rec["result_pickle"] = cloudpickle.dumps(rec.pop("result"))
            except Exception as exc:  # noqa: BLE001 - an unpicklable result fails this member only
                rec.update(status="failed", result_pickle=None,
                           error=f"TypeError: the task's result does not pickle ({describe(exc)})")
            conn_out.send(rec)


def main(argv=None) -> None:
    read_fd, write_fd, parent_pid = (int(a) for a in (argv or sys.argv[1:]))
    _die_with_parent(parent_pid)
    _serve(Connection(read_fd, writable=False), Connection(write_fd, readable=False))


if __name__ == "__main__":
    main()
