"""Binding force kernels to the one step of :mod:`integrators.loop`.

How a kernel plugs in, and why this way (measured on the first version): passing a compiled
kernel to a compiled step as an argument either costs about 5 microseconds a call to unbox (a
``cfunc``) or makes the step uncachable (an ``njit`` function is embedded by address), and a
copy of the step per kernel written by hand drifts from the original.  So the step is written
once (``integrators/loop.py``) with the kernels as two module globals, and:

* **compiled kernels** (numba ``njit`` functions that can be imported by module and name):
  the loop's source text plus two import lines binding ``_force`` and ``_potential`` is
  written, once, to a module named by a hash of every source it depends on (the loop, the
  compiled pieces, the kernels' modules) and the numba and Python versions, in a writable cache
  folder (``HBVM_MD_CACHE_DIR``, else numba's ``NUMBA_CACHE_DIR``, else ``~/.cache/hbvm-md``,
  else a temporary folder).  numba caches that module's compiled code beside it.  Changing any
  of those sources changes the hash, so compiled code is never stale;
* **compiled kernels that cannot be imported** (defined in ``__main__``, closures): the same
  text is executed in memory and compiled without a disk cache;
* **anything else** (a user's Python ``gradient``, an ASE calculator): the same text is
  executed as Python, the kernels bound to Python callables; it calls the compiled pieces of
  :mod:`integrators.core`.  Under ``NUMBA_DISABLE_JIT=1`` every path is this one.

Compile time.  A generated module is compiled once per scene *variant* and cached: the
followers only for a system with test particles, the full or the separable form only as the
binding uses it, EQUIP only for EQUIP, the tangent map only when a ``jvp`` is bound (REBOUND:
variational particles), the simplified Newton iteration only for a host that can hand the step
Newton matrices (REBOUND's glue declares ``GLUE_NEWTON = False``: it only iterates to a fixed
point).  The variant is declared by the generated module's globals ``_FULL``, ``_EQUIP``,
``_FOLLOWERS``, ``_NEWTON`` (:mod:`integrators.loop`) and ``_TANGENTS`` (the REBOUND glue):
numba reads a global as a constant and prunes the branches it decides before typing them, so
what a variant leaves out is not compiled; its names stay bound to the stand-ins of
:mod:`integrators.absent`, guards never reached (the variant is part of the module's name).  numba
optimises and translates a caller together with every compiled function it calls, so a chain
of calls compiles the callee's code once per level: the wrappers around :func:`loop.run`
(``advance``, ``attempt``, the glue's ``step_arrays``; :data:`INLINED`) are inlined into their
compiled callers instead (:func:`integrators.jit.jit`, ``inline=True``; the same
floating-point operations in the same order, so the same numbers bit for bit), and ``run``
itself is not (numba copies an inlined function's IR once per level: measured dearer).  Measured on REBOUND's three-body scene with
empty caches: see ``benchmarks/results/cold_start.md`` (``benchmarks/bench_cold_start.py``).
A compile that is about to run logs one line (logger ``hbvm_md``) saying so;
:func:`hbvm_md.precompile` (``hbvm-md compile``) compiles the usual variants ahead.
"""
from __future__ import annotations

import functools
import hashlib
import importlib.util
import logging
import os
import sys
import tempfile
import threading
import types
import warnings
from pathlib import Path

import numba

from . import (absent, ccore, core, equip_core, followers, jit as _jitmod, loop, pointers as _pointersmod,
               records as _recordsmod, tangent)

# the step's features, each a function of its own (integrators.loop.run's docstring), inlined
STEP_PARTS = ("first_guess", "stage_field", "coefficient_update", "polish_coefficients",
              "equip_energy_condition", "sources_block", "gather_sources", "solve_followers",
              "resolution_check", "energy_check")
LOOP_FUNCTIONS = ("tableau", "evaluate", "energy_parts") + STEP_PARTS + ("run", "advance",
                                                                          "attempt")
# the followers' step (integrators.followers), appended for a system with followers
FOLLOWER_FUNCTIONS = ("follower_stages", "gather_followers", "follow")
_FOLLOWERS_PATH = Path(followers.__file__)
# the followers hooks of a system without followers (integrators.loop, "Followers")
NO_FOLLOWERS = (("integrators.core", "no_followers"), ("integrators.core", "no_field"))
_LOOP_PATH = Path(loop.__file__)
# the tangent map of the step (integrators.tangent), appended when a jvp kernel is bound
TANGENT_FUNCTIONS = ("evaluate_jvp", "tangent_converged", "tangent_sizes", "stages", "tangent_map",
                     "megno_step", "run_variational")
_TANGENT_PATH = Path(tangent.__file__)
# inlined into their compiled callers (module docstring, "Compile time"): a REBOUND step is
# then one compiled function (glue.core_step), an engine's step one (advance, run or
# run_variational); each also compiles as its own entry point when called from Python (the
# engine's Stepper calls run, for one step too, so that advance is not a second one)
INLINED = ("tableau", "advance", "attempt", "step_arrays") + STEP_PARTS
# the full form's pieces of integrators.core, bound to integrators.absent in a separable step
FULL_FUNCTIONS = ("full_stages", "full_stages_narrow", "symplectic", "commit_full")
# what a host's glue calls for variational particles, bound to integrators.absent without
TANGENT_GLUE = ("tangent_map", "read_tangents", "write_tangents", "delta2")
_log = logging.getLogger("hbvm_md")
_CACHE: dict = {}
_LOCK = threading.Lock()
_cache_dir: Path | None = None


def _is_compiled(kernel) -> bool:
    return isinstance(kernel, numba.core.registry.CPUDispatcher)


def _import_ref(kernel) -> tuple[str, str] | None:
    """(module, name) from which ``kernel`` can be imported again, or None."""
    fn = getattr(kernel, "py_func", None)
    mod, name = getattr(fn, "__module__", None), getattr(fn, "__qualname__", "")
    module = sys.modules.get(mod or "")
    if module is None or mod == "__main__" or "<" in name or "." in name:
        return None
    if getattr(module, name, None) is not kernel or not getattr(module, "__file__", None):
        return None
    return mod, name


def cache_dir() -> Path:
    """The folder of the generated, hash-named step modules (see the module docstring)."""
    global _cache_dir
    if _cache_dir is not None:
        return _cache_dir
    candidates = [os.environ.get("HBVM_MD_CACHE_DIR"), numba.config.CACHE_DIR or None,
                  os.path.join(os.path.expanduser("~"), ".cache", "hbvm-md")]
    for c in candidates:
        if not c:
            continue
        p = Path(c)
        try:
            p.mkdir(parents=True, exist_ok=True)
            probe = p / f".probe-{os.getpid()}"
            probe.write_text("")
            probe.unlink()
        except OSError:
            continue
        _cache_dir = p
        return p
    _cache_dir = Path(tempfile.mkdtemp(prefix="hbvm-md-"))
    warnings.warn(f"hbvm-md: no writable cache folder (tried {[c for c in candidates if c]}); "
                  f"compiled steps are cached in {_cache_dir} for this process only. Set "
                  "HBVM_MD_CACHE_DIR to a writable folder.", RuntimeWarning, stacklevel=3)
    return _cache_dir


def _glue(glue):
    """(path, functions, cfuncs, paths it depends on, whether it hands the step Newton
    matrices) of a host's glue module (see :func:`specialise`), or None."""
    if glue is None:
        return None
    module = importlib.import_module(glue)
    depends = []
    for d in getattr(module, "GLUE_DEPENDS", ()):
        dep = importlib.import_module(d)
        # (and the files a module reads its numbers from: a C header, for the layout)
        depends += [Path(dep.__file__), *map(Path, getattr(dep, "SOURCE_FILES", ()))]
    depends = tuple(depends)
    return (Path(module.__file__), tuple(module.GLUE_FUNCTIONS),
            dict(getattr(module, "GLUE_CFUNCS", {})), depends,
            bool(getattr(module, "GLUE_NEWTON", True)))


def _source_hash(refs, glue=None, frefs=NO_FOLLOWERS, variant=(None, None, False),
                 rref=None) -> str:
    h = hashlib.sha256()
    paths = [_LOOP_PATH, _FOLLOWERS_PATH, Path(_recordsmod.__file__), Path(core.__file__),
             Path(equip_core.__file__), Path(_jitmod.__file__),
             Path(_pointersmod.__file__), Path(absent.__file__), Path(__file__)]
    if glue is not None:
        paths += [glue[0], *glue[3]]
    if len(refs) > 2:                  # a jvp kernel: the tangent map is compiled with the step
        paths.append(_TANGENT_PATH)
    for path in paths:
        h.update(path.read_bytes())
    for mod, name in list(refs) + list(frefs):
        h.update(f"{mod}:{name}".encode())
        h.update(Path(sys.modules[mod].__file__).read_bytes())
        _hash_kernel_depends(h, mod)
    h.update(f"{numba.__version__} {sys.version} full={variant[0]} equip={variant[1]}".encode())
    if variant[2]:           # (the stage-velocity variant: the plain variants keep their names)
        h.update(b" stage velocities")
    if rref is not None:     # (a recentring hook: the plain variants keep their names)
        h.update(f" recentre {rref[0]}:{rref[1]}".encode())
        h.update(Path(sys.modules[rref[0]].__file__).read_bytes())
        _hash_kernel_depends(h, rref[0])
    return h.hexdigest()[:24]


def _hash_kernel_depends(h, mod):
    """Hash the sources a kernel's module names in ``KERNEL_DEPENDS`` (modules whose compiled
    functions its kernels call): numba's cache checks only the cached function's own file, so
    a change there must rename the generated step.  (A module without it: nothing hashed, the
    names of its variants unchanged.)"""
    for dep in getattr(sys.modules[mod], "KERNEL_DEPENDS", ()):
        h.update(Path(importlib.import_module(dep).__file__).read_bytes())


def _variant_lines(refs, glue, frefs, variant) -> str:
    """The generated module's lines binding what this variant leaves out to the stand-ins of
    :mod:`integrators.absent` (module docstring, "Compile time"); variant: (full, equip, stage
    velocities)."""
    full, equip, velocities = variant
    lines = ["from integrators import absent as _absent  # noqa: E402"]
    if velocities:
        lines.append("_STAGE_VELOCITIES = True")
    if frefs == NO_FOLLOWERS:
        lines += ["_FOLLOWERS = False", "follow = _absent.follow"]
    if full is not None:
        lines.append(f"_FULL = {bool(full)}")
    if full is False:
        lines += [f"{f} = _absent.{f}" for f in FULL_FUNCTIONS]
    if equip is not None:
        lines.append(f"_EQUIP = {bool(equip)}")
    if equip is False:
        lines.append("eq = _absent")
    if glue is not None and not glue[4]:      # a host that never hands the step Newton matrices
        lines += ["_NEWTON = False", "newton_update = _absent.newton_update"]
    if glue is not None and len(refs) <= 2:
        lines += ["_TANGENTS = False"] + [f"{f} = _absent.{f}" for f in TANGENT_GLUE
                                          if hasattr(absent, f)]
    return "\n".join(lines) + "\n"


def _is_cached(name: str, path: Path) -> bool | None:
    """Has numba cached compiled code of the generated module ``name`` (at ``path``)?  Looks
    where numba's own cache locators would put it; None when that cannot be told."""
    try:
        from numba.core import caching
        impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl")
        for cls in impl._locator_classes:
            loc = cls.from_function(_announce, str(path))    # (any function: its line)
            if loc is None:
                continue
            try:
                loc.ensure_cache_path()
            except OSError:
                continue
            return any(Path(loc.get_cache_path()).glob(f"{name}.*.nbi"))
    except Exception:                # numba's private layout changed: say nothing
        return None
    return None


def _announce(name: str, path: Path, refs, glue, frefs, variant) -> None:
    """One line before a compile that takes tens of seconds (a cold cache)."""
    if _is_cached(name, path) is not False:
        return
    parts = [f"kernel {refs[0][0]}.{refs[0][1]}", "separable form" if variant[0] is False
             else "full form" if variant[0] else "both forms",
             "EQUIP" if variant[1] else "HBVM" if variant[1] is False else "HBVM and EQUIP"]
    if frefs != NO_FOLLOWERS:
        parts.append("test particles")
    if variant[2]:
        parts.append("stage velocities")
    if len(refs) > 2:
        parts.append("tangent map")
    if glue is not None:
        parts.append(f"host {glue[0].stem}")
    _log.warning("hbvm-md: compiling HBVM's step for this scene, once: %s (tens of seconds at "
                 "most; cached in %s for every later run; `hbvm-md compile` compiles ahead)",
                 ", ".join(parts), path.parent)


def _compiled_from_file(refs, glue=None, frefs=NO_FOLLOWERS,
                        variant=(None, None, False), rref=None) -> types.ModuleType:
    digest = _source_hash(refs, glue, frefs, variant, rref)
    name = f"_hbvm_md_step_{digest}"
    if name in sys.modules:
        return sys.modules[name]
    text = _LOOP_PATH.read_text()
    functions, cfuncs = LOOP_FUNCTIONS, {}
    if frefs != NO_FOLLOWERS:
        text += "\n\n# ---- generated by integrators.specialise: the followers (followers.py) ----\n"
        text += _FOLLOWERS_PATH.read_text()
        functions = functions + FOLLOWER_FUNCTIONS
    if len(refs) > 2:
        text += "\n\n# ---- generated by integrators.specialise: the tangent map (tangent.py) ----\n"
        text += _TANGENT_PATH.read_text()
        functions = functions + TANGENT_FUNCTIONS
    if glue is not None:
        text += f"\n\n# ---- generated by integrators.specialise: the host glue ({glue[0].name}) ----\n"
        text += glue[0].read_text()
        functions, cfuncs = functions + glue[1], glue[2]
    text += ("\n\n# ---- generated by integrators.specialise: the kernels and compilation ----\n"
             f"from {refs[0][0]} import {refs[0][1]} as _force  # noqa: E402\n"
             f"from {refs[1][0]} import {refs[1][1]} as _potential  # noqa: E402\n"
             + (f"from {refs[2][0]} import {refs[2][1]} as _force_jvp  # noqa: E402\n"
                if len(refs) > 2 else "")
             + f"from {frefs[0][0]} import {frefs[0][1]} as _followers  # noqa: E402\n"
             + f"from {frefs[1][0]} import {frefs[1][1]} as _field  # noqa: E402\n"
             + "from integrators.jit import cjit as _cjit, jit as _jit  # noqa: E402\n"
             + "".join(f"{f} = _jit({f}{', inline=True' if f in INLINED else ''})\n"
                       for f in functions)
             + _variant_lines(refs, glue, frefs, variant)
             + (f"from {rref[0]} import {rref[1]} as _recentre  # noqa: E402\n_RECENTRE = True\n"
                if rref is not None else "_recentre = _absent.recentre\n")
             + "".join(f"{f} = _cjit({sig!r})({f})\n" for f, sig in cfuncs.items()))
    folder = cache_dir()
    path = folder / f"{name}.py"
    if not path.exists() or path.read_text() != text:
        tmp = folder / f".{name}.{os.getpid()}.tmp"
        tmp.write_text(text)
        os.replace(tmp, path)          # atomic: parallel workers never see half a file
    _announce(name, path, refs, glue, frefs, variant)    # (numba's locators need the file)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def _executed(force, potential, compile_: bool, glue=None, jvp=None,
              follow=None, equip=None, velocities=False, recentre=None) -> types.SimpleNamespace:
    ns = {"__name__": "integrators.loop_bound", "__file__": str(_LOOP_PATH)}
    exec(compile(_LOOP_PATH.read_text(), str(_LOOP_PATH), "exec"), ns)
    functions = LOOP_FUNCTIONS
    if follow is not None:
        exec(compile(_FOLLOWERS_PATH.read_text(), str(_FOLLOWERS_PATH), "exec"), ns)
        functions = functions + FOLLOWER_FUNCTIONS
    else:
        ns["follow"] = absent.follow           # (never reached: no followers)
    if jvp is not None:
        exec(compile(_TANGENT_PATH.read_text(), str(_TANGENT_PATH), "exec"), ns)
        ns["_force_jvp"] = jvp
        functions = functions + TANGENT_FUNCTIONS
    if glue is not None:
        exec(compile(glue[0].read_text(), str(glue[0]), "exec"), ns)
        functions = functions + glue[1]
    ns["_force"], ns["_potential"] = force, potential
    ns["_EQUIP"] = None if equip is None else bool(equip)
    ns["_FOLLOWERS"] = follow is not None
    ns["_TANGENTS"] = jvp is not None
    ns["_STAGE_VELOCITIES"] = bool(velocities)
    ns["_RECENTRE"] = recentre is not None
    ns["_recentre"] = recentre if recentre is not None else absent.recentre
    ns["_followers"], ns["_field"] = follow if follow is not None else (core.no_followers,
                                                                        core.no_field)
    if compile_:
        for f in functions:
            ns[f] = _jitmod._own(numba.njit(error_model="numpy")(ns[f]))
        if glue is not None:
            for f, sig in glue[2].items():
                with _jitmod._Ids.scoped():
                    ns[f] = numba.cfunc(sig, error_model="numpy")(ns[f])
                functions = functions + (f,)
    return types.SimpleNamespace(**{f: ns[f] for f in functions + ("follow",)})


def specialise(force, potential, python: bool = False, glue: str | None = None, jvp=None,
               follow=None, *, full: bool | None = None, equip: bool | None = None,
               velocities: bool = False, recentre=None):
    """The step bound to these kernels: an object with ``advance``, ``run``, ``attempt`` (see
    :mod:`integrators.loop`) and ``kind`` ("compiled" or "python"); ``python=True`` executes
    the step as Python even when the kernels are compiled.

    ``glue``: the name of a host's module whose text is compiled in the same module, after the
    step (its functions see the step's and the kernels' names and call them statically): its
    ``GLUE_FUNCTIONS`` are compiled like the step and become attributes of the result, and its
    ``GLUE_CFUNCS`` (name: signature) become C callbacks (compiled only: a Python step has
    none).  The hash of the generated module covers the glue's source.

    ``jvp``: a kernel ``jvp(X, dX, params, out)`` (the derivative of ``force`` along dX, row by
    row; see :mod:`integrators.variational`): the tangent map of :mod:`integrators.tangent` is
    then bound too (``evaluate_jvp``, ``tangent_map``, ``megno_step``, ``run_variational``),
    compiled when all three kernels are, else executed as Python.

    ``follow``: the followers hooks ``(followers(params), field(Xt, Xs, params, out))`` of a
    separable system whose unknowns split into sources and followers (test particles, see
    :mod:`integrators.loop`), bound like the force kernel (Python ones make the step Python);
    None: none.

    ``full``, ``equip``: the form the step will be called with (True: full, False: separable)
    and whether the method is EQUIP; a compiled step then leaves the other form (EQUIP) out
    (module docstring, "Compile time").  None: both, as a step called either way needs.

    ``velocities``: the separable HBVM step hands the force kernel the stage velocities too
    (``_force(X, params, out)`` with X (n, 2m): positions, then velocities; out (n, m)), for a
    force that reads them (:func:`integrators.core.stage_velocities`).  A variant of its own.

    ``recentre``: a kernel ``recentre(y, cy, gamma, h, params)`` run after each committed step
    (the loop's ``_recentre``: a system whose variables are re-expressed between steps, such
    as :class:`systems.flow_composed.FlowComposed`'s recentring of the Keplerian flows); bound
    like the force kernel (a Python one makes the step Python).  A variant of its own."""
    if recentre is not None and not _is_compiled(recentre):
        python = True
    if jvp is not None and not _is_compiled(jvp):
        python = True
    if follow is not None and not all(_is_compiled(f) for f in follow):
        python = True
    if python:
        out = _executed(force, potential, False, _glue(glue), jvp, follow, equip, velocities,
                        recentre)
        out.kind = "python"
        return out
    # the compiled core (integrators.ccore) for the kernels and the variant it covers: compiled
    # kernels it has in C, or Python kernels it calls back
    compiled = _is_compiled(force) and _is_compiled(potential)
    if compiled or not (_is_compiled(force) or _is_compiled(potential)):
        refs = (_import_ref(force), _import_ref(potential)) if compiled else None
        stepper = ccore.core_step(
            force, potential, refs, full=full, equip=equip, velocities=velocities, glue=glue,
            jvp=jvp, follow=follow, recentre=recentre,
            fallback=functools.partial(_numba_step, force, potential, glue, jvp, follow, full,
                                       equip, velocities, recentre))
        if stepper is not None:
            return stepper
    return _numba_step(force, potential, glue, jvp, follow, full, equip, velocities, recentre)


def _numba_step(force, potential, glue, jvp, follow, full, equip, velocities, recentre):
    """:func:`specialise`'s numba step (compiled kernels) or Python step (anything else)."""
    variant = (None if full is None else bool(full), None if equip is None else bool(equip),
               bool(velocities))
    key = (force, potential, glue, jvp, follow, variant, recentre)
    try:
        hit = _CACHE.get(key)
    except TypeError:            # unhashable callables: no cache
        hit, key = None, None
    if hit is not None:          # (before the glue's paths are looked up: 15 us a Binding)
        return hit
    glue_ = _glue(glue)
    with _LOCK:
        if _is_compiled(force) and _is_compiled(potential):
            refs = [_import_ref(force), _import_ref(potential)]
            if jvp is not None:
                refs.append(_import_ref(jvp))
            frefs = NO_FOLLOWERS if follow is None else tuple(_import_ref(f) for f in follow)
            rref = None if recentre is None else _import_ref(recentre)
            if None not in refs and None not in frefs and (recentre is None) == (rref is None):
                mod = _compiled_from_file(refs, glue_, frefs, variant, rref)
                names = (LOOP_FUNCTIONS + ("follow",) + (TANGENT_FUNCTIONS if jvp is not None else ())
                         + (glue_[1] + tuple(glue_[2]) if glue_ else ()))
                out = types.SimpleNamespace(**{f: getattr(mod, f) for f in names})
            else:
                out = _executed(force, potential, True, glue_, jvp, follow, equip, velocities,
                                recentre)
            out.kind = "compiled"
        else:
            out = _executed(force, potential, False, glue_, jvp, follow, equip, velocities,
                            recentre)
            out.kind = "python"
        if key is not None and out.kind == "compiled":
            _CACHE[key] = out
    return out
