"""How the project compiles: numba's ``njit`` with an on-disk cache when one can be written.

A read-only installation (no writable ``__pycache__`` beside the sources and no writable user
cache directory) makes ``njit(cache=True)`` fail at import ("no locator available"); there the
functions are compiled in memory, with one warning.  Under ``NUMBA_DISABLE_JIT=1`` everything
runs as plain Python.
"""
from __future__ import annotations

import contextlib
import itertools
import secrets
import warnings

from numba import njit
from numba.core import sigutils, types
from numba.core.registry import CPUDispatcher

_warned = False


class _Ids:
    """numba issue #10486, scoped to this project's compilations.

    numba names every compilation of a function ``qualname$uid`` with uid from a counter that
    starts at 1 in each process (``FunctionIdentity._unique_ids``), and cached code keeps the
    names it was compiled with.  Code cached by two processes can then carry one symbol for two
    compilations: ``core.carve`` cached alone, and inlined into the generated step module.
    Loaded into one process, the second binds to the first's environment, and boxing its
    result fails ("descr is NULL", "returned a result with an exception set"; measured in a
    dask worker that ran the REBOUND step and then the ASE step).

    So the project's own compilations (:func:`jit`'s dispatchers, :func:`cjit`'s callbacks,
    and whatever numba compiles inside them) draw their ids from a counter of this process
    that starts at a random 40-bit offset above 2**40: processes almost never share ids, and
    numba's own counter is swapped back after each compile, untouched (importing hbvm-md, or
    compiling with it, changes nothing for the other libraries a user has loaded).  When
    numba's layout has changed and the counter cannot be scoped, the first compile says so
    once (a RuntimeWarning) and numba's counter is left as it is."""

    counter = itertools.count(2 ** 40 + secrets.randbits(40))
    warned = False

    @classmethod
    def identity(cls):
        """numba's ``FunctionIdentity`` class when its counter can be scoped, else None."""
        try:
            from numba.core.bytecode import FunctionIdentity
        except ImportError:
            FunctionIdentity = None
        if FunctionIdentity is None or not isinstance(getattr(FunctionIdentity, "_unique_ids",
                                                              None), itertools.count):
            if not cls.warned:
                cls.warned = True
                warnings.warn("hbvm-md: numba's function ids (numba.core.bytecode."
                              "FunctionIdentity._unique_ids) are not where this version expects "
                              "them, so compiled code cached by two processes may share symbol "
                              "names (numba issue #10486): if a process that loads both the "
                              "REBOUND and the ASE step fails with 'descr is NULL', clear "
                              "HBVM_MD_CACHE_DIR and NUMBA_CACHE_DIR", RuntimeWarning,
                              stacklevel=4)
            return None
        return FunctionIdentity

    @classmethod
    @contextlib.contextmanager
    def scoped(cls):
        """numba compiles with the project's counter inside this block (under numba's compiler
        lock: compilations of other threads wait, as they would for numba's own)."""
        from numba.core.compiler_lock import global_compiler_lock
        fid = cls.identity()
        if fid is None:
            yield
            return
        with global_compiler_lock:
            saved = fid._unique_ids
            fid._unique_ids = cls.counter
            try:
                yield
            finally:
                fid._unique_ids = saved


class Dispatcher(CPUDispatcher):
    """numba's dispatcher, compiling with the project's function ids (:class:`_Ids`), each
    function once per argument *types*: numba would also compile a copy for each constant a
    compiled caller passes (``exact=True``, and ``polish``'s first value False while it types
    the loop), a second or two each on a cold cache; a constant argument selects the compiled
    function of its type instead (the same code: no function here branches on its argument's
    type being a constant)."""

    def compile(self, sig):
        args, return_type = sigutils.normalize_signature(sig)
        plain = tuple(types.unliteral(a) for a in args)
        if plain != tuple(args):
            sig = plain if return_type is None else return_type(*plain)
        with _Ids.scoped():
            return super().compile(sig)


def _own(dispatcher):
    """The dispatcher numba made, as a :class:`Dispatcher` (the same object: numba's options,
    cache and typing unchanged)."""
    if type(dispatcher) is CPUDispatcher:
        dispatcher.__class__ = Dispatcher
    return dispatcher


def jit(fn=None, *, nogil: bool = False, inline: bool = False):
    """``njit(cache=True, error_model="numpy")(fn)``, or without the cache when none can be
    written.  numpy's error model makes a division by zero an inf or a nan, which the step
    reports as a clear error, instead of an exception raised inside compiled code.
    ``@jit(nogil=True)``: the compiled function releases the GIL while it runs (for one that
    calls into a C library, as ctypes would).  ``inline=True``: a compiled caller takes the
    function's code into its own (numba's ``inline="always"``) instead of linking a separately
    compiled copy; called from Python it is compiled as usual (see
    :mod:`integrators.specialise`, "Compile time")."""
    global _warned
    if fn is None:
        return lambda f: jit(f, nogil=nogil, inline=inline)
    options = dict(error_model="numpy", nogil=True) if nogil else dict(error_model="numpy")
    if inline:
        options["inline"] = "always"
    try:
        return _own(njit(cache=True, **options)(fn))
    except RuntimeError as exc:       # numba: "cannot cache function ...: no locator available"
        if "cache" not in str(exc):
            raise
        if not _warned:
            _warned = True
            warnings.warn(f"hbvm-md: compiled code cannot be cached on disk ({exc}); it is "
                          "compiled in memory in every process. Set NUMBA_CACHE_DIR to a writable "
                          "folder to cache it.", RuntimeWarning, stacklevel=2)
        return _own(njit(**options)(fn))


def cjit(signature, cache: bool = True):
    """``numba.cfunc(signature, cache=True, error_model="numpy")``: a C callback (its
    ``.address`` goes where a C library expects a function pointer), compiled like :func:`jit`
    (in memory when no cache can be written, or when ``cache`` is False)."""
    from numba import cfunc

    def deco(fn):
        with _Ids.scoped():           # (a cfunc compiles when it is made)
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
