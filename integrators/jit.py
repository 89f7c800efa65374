"""How the project compiles: numba's ``njit`` with an on-disk cache when one can be written.

A read-only installation (no writable ``__pycache__`` beside the sources and no writable user
cache directory) makes ``njit(cache=True)`` fail at import ("no locator available"); there the
functions are compiled in memory, with one warning.  Under ``NUMBA_DISABLE_JIT=1`` everything
runs as plain Python.
"""
from __future__ import annotations

import itertools
import secrets
import warnings

from numba import njit

_warned = False


def _distinct_symbol_ids() -> None:
    """Start numba's function-id counter at a random offset in this process.

    numba names every compilation of a function ``qualname$uid`` with uid from a counter that
    starts at 1 in each process, and cached code keeps the names it was compiled with.  Code
    cached by two processes can then carry one symbol for two compilations: ``core.carve``
    cached alone, and inlined into the generated step module.  Loaded into one process, the
    second binds to the first's environment, and boxing its result fails ("descr is NULL",
    "returned a result with an exception set"; measured in a dask worker that ran the REBOUND
    step and then the ASE step; numba issue #10486).  With a random 40-bit start, processes
    almost never share ids.  Ids already given in this process stay below the new start."""
    try:
        from numba.core.bytecode import FunctionIdentity
    except ImportError:              # another numba layout: keep its counter
        return
    if isinstance(getattr(FunctionIdentity, "_unique_ids", None), itertools.count):
        FunctionIdentity._unique_ids = itertools.count(2 ** 40 + secrets.randbits(40))


_distinct_symbol_ids()


def jit(fn=None, *, nogil: bool = False):
    """``njit(cache=True, error_model="numpy")(fn)``, or without the cache when none can be
    written.  numpy's error model makes a division by zero an inf or a nan, which the step
    reports as a clear error, instead of an exception raised inside compiled code.
    ``@jit(nogil=True)``: the compiled function releases the GIL while it runs (for one that
    calls into a C library, as ctypes would)."""
    global _warned
    if fn is None:
        return lambda f: jit(f, nogil=nogil)
    options = dict(error_model="numpy", nogil=True) if nogil else dict(error_model="numpy")
    try:
        return njit(cache=True, **options)(fn)
    except RuntimeError as exc:       # numba: "cannot cache function ...: no locator available"
        if "cache" not in str(exc):
            raise
        if not _warned:
            _warned = True
            warnings.warn(f"hbvm-md: compiled code cannot be cached on disk ({exc}); it is "
                          "compiled in memory in every process. Set NUMBA_CACHE_DIR to a writable "
                          "folder to cache it.", RuntimeWarning, stacklevel=2)
        return njit(**options)(fn)


def cjit(signature, cache: bool = True):
    """``numba.cfunc(signature, cache=True, error_model="numpy")``: a C callback (its
    ``.address`` goes where a C library expects a function pointer), compiled like :func:`jit`
    (in memory when no cache can be written, or when ``cache`` is False)."""
    from numba import cfunc

    def deco(fn):
        if not cache:
            return cfunc(signature, error_model="numpy")(fn)
        try:
            return cfunc(signature, cache=True, error_model="numpy")(fn)
        except RuntimeError as exc:
            if "cache" not in str(exc):
                raise
            return cfunc(signature, error_model="numpy")(fn)
    return deco


def entry_point(dispatcher):
    """The compiled entry point of a dispatcher's only signature (skips numba's argument
    typing, several microseconds a call with many arguments), or the dispatcher itself when it
    has none or several yet, or is a plain Python function (``NUMBA_DISABLE_JIT``)."""
    overloads = getattr(dispatcher, "overloads", None)
    if overloads is not None and len(overloads) == 1:
        return next(iter(overloads.values())).entry_point
    return dispatcher
