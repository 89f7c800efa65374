"""The two C functions registered with REBOUND that do not depend on the force kernel: the
step REBOUND calls (:func:`dispatch`) and the state's ``free`` (:func:`release`).

They are compiled once (numba ``cfunc``, cached on disk) when ``hbvm_md`` registers HBVM, so
that registering does not compile the step itself.  :func:`dispatch` calls, through the
addresses in HBVM's state (slots in :mod:`hbvm_md.rebound.layout`):

* the compiled step (``SL_CORE``, :func:`hbvm_md.rebound.glue.core_step`), which returns OK, a
  failure status (nothing changed), or RESYNC when the particles are not what it wrote last;
* the host's ``prepare`` (a Python callback, ``SL_PREPARE``) when there is no compiled step for
  this state yet (a new, loaded or copied simulation) or after RESYNC: it builds the model, the
  compiled step and the context block from the particles, then the step is called again;
* the host's ``fail`` (a Python callback, ``SL_FAIL``) when the step failed: it records the
  exception and sets REBOUND's status and error message.

Python runs only in those rare events; a normal step is two compiled calls.  These two serve
only where REBOUND's compiled glue (:mod:`hbvm_md.rebound.cglue`, the same two functions in C)
is not built or not usable.
"""
from __future__ import annotations

from numba import carray

from integrators.jit import cjit
from integrators.pointers import address_of, int64_pointer
from hbvm_md.rebound import layout as _layout
from hbvm_md.rebound.intrinsics import call_status, call_void
from hbvm_md.rebound.layout import (OK, RESYNC, N_SLOTS, SL_CORE, SL_CTX, SL_COUNTERS, SL_FAIL,
                                    SL_FORGET, SL_FREE, SL_GAMMA, SL_PREPARE, SL_STATUS, SL_Y)

#: layout.DIGEST (the first 16 hex digits of the SHA-256 of ``layout.py`` and of the C header
#: ``csrc/hbvm_state.h`` it reads the slots from) these functions were written for.  numba's disk
#: cache compiles the slot numbers in and is invalidated only when *this* file changes, so a
#: layout edited alone (a ``git pull`` over an editable install) would load code that indexes
#: the state with the old slots: a crash at the first ``free`` (measured: ``import hbvm_md``
#: segfaulted after a layout change).  When the layout is not the one named here, the two
#: functions are compiled in memory instead of loaded from the cache;
#: ``tests/test_rebound_host.py`` keeps the digest current, so edit it with the layout.
LAYOUT_DIGEST = "e1008eefe6ce66b8"
_CACHE = _layout.DIGEST == LAYOUT_DIGEST


@cjit("void(voidptr, voidptr)", cache=_CACHE)
def dispatch(r, p):
    """REBOUND's step: the compiled step, prepared first when needed; a failure reported."""
    st = carray(int64_pointer(address_of(p)), N_SLOTS)
    status = RESYNC
    if st[SL_CORE] != 0:
        status = call_status(st[SL_CORE], r, p)
    if status == RESYNC:
        status = call_status(st[SL_PREPARE], r, p)
        if status == OK:
            status = call_status(st[SL_CORE], r, p)
    if status != OK:
        st[SL_STATUS] = status
        call_status(st[SL_FAIL], r, p)


@cjit("void(voidptr)", cache=_CACHE)
def release(p):
    """REBOUND's ``free``: the arrays REBOUND or the host allocated, then the state."""
    st = carray(int64_pointer(address_of(p)), N_SLOTS)
    if st[SL_FORGET] != 0:                  # (the host's record of this state)
        call_status(st[SL_FORGET], p, p)
    free = st[SL_FREE]
    for slot in (SL_Y, SL_GAMMA, SL_COUNTERS, SL_CTX):
        if st[slot] != 0:
            call_void(free, st[slot])
    call_void(free, address_of(p))
