"""What an ensemble store knows a task and a parameter by: a digest of their content.

``repr()`` cannot identify a member: numpy shortens a long array to "[0. 0. ... 0.]", an ASE
``Atoms`` leaves its positions out, an object of a class without ``__repr__`` shows its memory
address (another in every process).  A store that matched members by ``repr`` handed back the
records of ``partial(task, w=a)`` to ``partial(task, w=b)``, and refused its own members on a
rerun.  So :func:`identity` reduces an object to a canonical tree, the way pickle sees it, and
hashes that (SHA-256):

* numbers, strings, bytes, None: their type and exact value (a float by its round-trip repr);
* lists and tuples in order; dicts, sets and frozensets sorted by their items' canonical bytes
  (a set of strings iterates in another order in every process: hash randomisation);
* numpy arrays and scalars: dtype, shape and the bytes of the values (object arrays element by
  element);
* functions and classes by module and qualified name, when that name finds them again (a
  lambda or a function defined inside another cannot be found by name: refused); a function
  also by its code: the source text of it and of the functions of its own module it calls by
  name, recursively (the bytecode where the source cannot be read), so that a task edited
  between two runs of one store is not handed the records of its earlier code.  Functions of
  other modules count by name only (a library is identified by its version, not its code);
* an ASE calculator by its class and its ``calc.todict()`` (ASE's record of the parameters
  that define it, what its trajectories store), not its caches: a calculator that has
  computed holds results, the atoms it last saw and derived tables (EMT keeps a dict with a
  lambda inside) that say nothing of what it computes.  A calculator of your own that keeps
  its settings outside ``parameters`` must return them from ``todict`` (as
  :class:`systems.PolynomialPairPotential` does), or two of its settings look alike here;
* any other object through the protocol pickle uses (``__reduce_ex__``): its constructor, its
  arguments and its state (``__dict__``), recursively: a ``functools.partial``, a dataclass, an
  ``Atoms`` (positions, numbers, cell, ...), an object with the default ``repr``.

What cannot be reduced so (a lock, an open file, a generator, a lambda) raises a ``TypeError``
naming the parameter and the fix, before any member runs.  The digest is the same in every
process and on every machine with the same library versions (an array's bytes are in its own
byte order, part of its dtype).
"""
from __future__ import annotations

import copyreg
import functools
import hashlib
import importlib
import inspect
import pickle
import sys
import types
import weakref
from typing import Any

import numpy as np

__all__ = ["identity", "code_identity", "IdentityError"]

_PROTOCOL = 4            # fixed: the digest must not change with Python's default protocol
_ATOMS = (type(None), bool, int, float, complex, str, bytes)


class IdentityError(TypeError):
    """An object has no content the store can identify across processes."""


def identity(obj: Any, what: str, fix: str = "") -> str:
    """SHA-256 hex digest of the canonical form of ``obj`` (see the module docstring).

    Parameters
    ----------
    obj : object
        A task or a parameter of :func:`hbvm_md.ensemble.run_ensemble`.
    what : str
        How the message names it (e.g. "params[3]", "task").
    fix : str
        What to do instead, appended to the message.

    Raises
    ------
    IdentityError (a TypeError)
        Some part of ``obj`` has no stable content (named in the message).
    """
    try:
        tree = _canon(obj, [], what)
    except RecursionError:
        raise IdentityError(f"`{what}` cannot be identified in the store: it nests too deeply; "
                            f"{fix}") from None
    except _Unstable as exc:
        raise IdentityError(f"`{what}` cannot be identified in the store: {exc}; "
                            f"{fix or 'use numbers, strings, tuples, dicts or arrays'}") from None
    return hashlib.sha256(pickle.dumps(tree, protocol=_PROTOCOL)).hexdigest()


def code_identity(task) -> str | None:
    """SHA-256 of the code of ``task`` (the function a ``functools.partial`` wraps): its
    source and that of the functions of its module it calls (see the module docstring); None
    for a callable that is not a Python function."""
    while isinstance(task, functools.partial):
        task = task.func
    if not isinstance(task, types.FunctionType):
        return None
    return _function_digest(task)


class _Unstable(Exception):
    """Raised inside the walk with the part that has no stable content."""


def _ref(obj) -> tuple:
    """A function or class by name, when its module finds the same object under that name."""
    module, qualname = getattr(obj, "__module__", None), getattr(obj, "__qualname__", None)
    if module is None or qualname is None or "<" in qualname:
        raise _Unstable(f"it holds {obj!r}, which cannot be found again by its name (a lambda, "
                        "or a function or class defined inside a function); define it at module "
                        "level")
    try:
        found = importlib.import_module(module)
        for part in qualname.split("."):
            found = getattr(found, part)
    except (ImportError, AttributeError):
        found = None
    if found is not obj:
        raise _Unstable(f"it holds {qualname} of module {module}, which that module does not "
                        "hold under that name; define it at module level")
    if isinstance(obj, types.FunctionType):
        return ("ref", module, qualname, _function_digest(obj))
    return ("ref", module, qualname)


_DIGESTS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _function_digest(fn: types.FunctionType) -> str:
    """:func:`_code_digest` once per function object (a param list that names one function
    ten thousand times reads its source once; an edited and reloaded function is a new
    object)."""
    d = _DIGESTS.get(fn)
    if d is None:
        d = _DIGESTS[fn] = _code_digest(fn, set())
    return d


def _code_text(code: types.CodeType) -> tuple:
    """A code object as plain values (no source at hand): bytecode, constants, names."""
    consts = tuple(_code_text(c) if isinstance(c, types.CodeType) else repr(c)
                   for c in code.co_consts)
    return (code.co_code, consts, code.co_names, code.co_varnames)


def _called_names(code: types.CodeType) -> set:
    names = set(code.co_names)
    for c in code.co_consts:
        if isinstance(c, types.CodeType):
            names |= _called_names(c)
    return names


def _code_digest(fn: types.FunctionType, seen: set) -> str:
    """SHA-256 of the source of ``fn`` and of the module-level functions of its own module it
    names (recursively): an edited task, or an edited helper beside it, changes the digest.
    Why source and not bytecode: bytecode changes with the Python version, source only with
    an edit."""
    seen.add(id(fn))
    try:
        text = inspect.getsource(fn).encode()
    except (OSError, TypeError):            # no source file (an interactive definition)
        text = pickle.dumps(_code_text(fn.__code__), protocol=_PROTOCOL)
    parts = [text]
    glb = getattr(fn, "__globals__", {})
    for n in sorted(_called_names(fn.__code__)):
        g = glb.get(n)
        if (isinstance(g, types.FunctionType) and id(g) not in seen
                and getattr(g, "__module__", None) == fn.__module__):
            parts.append(n.encode() + b"=" + _code_digest(g, seen).encode())
    return hashlib.sha256(b"\0".join(parts)).hexdigest()


def _calculator_class():
    """ASE's BaseCalculator when ASE is imported (an object can only be one if it is)."""
    mod = sys.modules.get("ase.calculators.calculator")
    return getattr(mod, "BaseCalculator", None)


def _sorted(items: list) -> list:
    """Canonical trees in the order of their pickled bytes (an order every process agrees on)."""
    return sorted(items, key=lambda t: pickle.dumps(t, protocol=_PROTOCOL))


def _canon(obj, path: list, what: str):
    t = type(obj)
    if t in _ATOMS:
        return (t.__name__, repr(obj) if t in (float, complex) else obj)
    if isinstance(obj, np.ndarray):
        if obj.dtype.hasobject:
            return ("ndarray-object", obj.shape, [_canon(v, path, what) for v in obj.ravel()])
        return ("ndarray", obj.dtype.str, obj.shape, np.ascontiguousarray(obj).tobytes())
    if isinstance(obj, np.generic):
        return ("numpy", obj.dtype.str, obj.tobytes())
    if isinstance(obj, (types.FunctionType, types.BuiltinFunctionType, type)):
        return _ref(obj)
    if any(obj is p for p in path):          # a cycle: name the ancestor by its depth
        return ("cycle", next(i for i, p in enumerate(path) if p is obj))
    path.append(obj)
    try:
        calc = _calculator_class()
        if calc is not None and isinstance(obj, calc):
            try:
                settings = obj.todict()
            except Exception as exc:  # noqa: BLE001 - whatever a calculator raises
                raise _Unstable(f"its calculator {t.__qualname__} fails in todict() "
                                f"({type(exc).__name__}: {exc})") from None
            return ("calculator", _ref(t), _canon(dict(settings), path, what))
        if t in (list, tuple):
            return (t.__name__, [_canon(v, path, what) for v in obj])
        if t is dict:
            return ("dict", _sorted([(_canon(k, path, what), _canon(v, path, what))
                                     for k, v in obj.items()]))
        if t in (set, frozenset):
            return (t.__name__, _sorted([_canon(v, path, what) for v in obj]))
        return _reduced(obj, path, what)
    finally:
        path.pop()


def _reduced(obj, path: list, what: str):
    """An object through the pickle protocol: (constructor, args, state, items)."""
    reducer = copyreg.dispatch_table.get(type(obj))
    try:
        rv = reducer(obj) if reducer is not None else obj.__reduce_ex__(_PROTOCOL)
    except Exception as exc:  # noqa: BLE001 - whatever a class raises: it does not pickle
        raise _Unstable(f"it holds a {type(obj).__module__}.{type(obj).__qualname__}, which "
                        f"does not pickle ({type(exc).__name__}: {exc})") from None
    if isinstance(rv, str):                  # a global: pickled by name
        return ("global", type(obj).__module__, rv)
    rv = tuple(rv) + (None,) * (6 - len(rv))
    func, args, state, listitems, dictitems = rv[:5]
    if isinstance(func, functools.partial):
        func = func.func
    return ("object", _canon(func, path, what), _canon(tuple(args or ()), path, what),
            _canon(state, path, what),
            None if listitems is None else _canon(list(listitems), path, what),
            None if dictitems is None else _canon(dict(dictitems), path, what))
