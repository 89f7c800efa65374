"""HBVM's state in REBOUND and its step's context block, in memory: the host's one
record of each state (:class:`Record`), the views of a state (:func:`slots`), its arrays and
its context block (:func:`array`, :func:`context`), and whether the model it was prepared for
changed (:func:`model_changed`).  A module of its own so that both REBOUND steps' preparations,
the plain one (:mod:`hbvm_md.rebound.host`) and the composed one
(:mod:`hbvm_md.rebound.composed`), build on it without importing each other.  The layouts are
the named structs of ``csrc/hbvm_state.h`` (:mod:`hbvm_md.rebound.layout`).
"""
from __future__ import annotations

import ctypes
import hashlib
import os

import numpy as np

from hbvm_md.rebound import layout as L
from hbvm_md.rebound.masses import same_model
from hbvm_md.rebound.memory import doubles, int64s
from integrators import EQUIP
from integrators.engine import Extrapolation
from integrators.tangent import tangent_sizes

#: this package's folder (user_stacklevel: a warning points at the first frame outside it)
HERE = os.path.dirname(os.path.abspath(__file__))
#: what REBOUND's registration of HBVM keeps (host.register fills it): REBOUND's offsets, the
#: callbacks' addresses, the state's offset in reb_simulation
REG: dict = {}

LIBC = ctypes.CDLL(None)
LIBC.malloc.restype = LIBC.calloc.restype = LIBC.realloc.restype = ctypes.c_void_p
LIBC.calloc.argtypes = [ctypes.c_size_t, ctypes.c_size_t]
LIBC.realloc.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
LIBC.free.argtypes = [ctypes.c_void_p]

class Record:
    """What the host keeps for one HBVM state (one simulation's ``r->integrator.state``),
    beside the state itself: made by ``create`` (a new, copied or loaded simulation), dropped
    by REBOUND's ``free`` of the state (its ``forget`` callback), so that nothing outlives the
    simulation nor is inherited by another at a reused address.

    forces: the REBOUNDx forces (name, address) the step was last prepared with (None: not
    prepared; :func:`_recheck_forces`); kepler_terms: the REBOUNDx force terms the composed step
    (kepler = 1) was last prepared with (:func:`hbvm_md.rebound.composed.force_terms`); odes:
    the attached ODEs (:func:`hbvm_md.rebound.forces.ode_signature`) likewise; host_path: the
    step was last prepared on REBOUND's own accelerations; python_step: the glue's step as
    Python (``NUMBA_DISABLE_JIT``); kepler_seen_dt: the step HBVMIntegrator attached the
    composed method with (its short-step warning is not given again for it)."""

    __slots__ = ("forces", "kepler_terms", "odes", "host_path", "python_step",
                 "kepler_seen_dt")

    def __init__(self):
        self.forces = self.kepler_terms = self.odes = self.python_step = None
        self.kepler_seen_dt = None
        self.host_path = False


#: state address -> its record (:class:`Record`)
RECORDS: dict[int, Record] = {}
NO_RECORD = Record()     # (what a simulation without a record reads: all unset; never written)


def record_of_state(p: int) -> Record:
    """The record of the live HBVM state at address p (made if it has none: a state created
    before this module registered, which cannot happen but costs nothing to survive)."""
    rec = RECORDS.get(p)
    if rec is None:
        rec = RECORDS[p] = Record()
    return rec


def record(addr: int) -> Record:
    """The record of the simulation at address addr's HBVM state."""
    return RECORDS.get(ctypes.c_void_p.from_address(addr + REG["state_at"]).value,
                        NO_RECORD)
def slots(p: int) -> tuple[np.ndarray, np.ndarray]:
    """HBVM's state at address p as int64 and float64 arrays (the same memory)."""
    buf = (ctypes.c_int64 * L.N_SLOTS).from_address(p)
    return np.frombuffer(buf, np.int64), np.frombuffer(buf, np.float64)


def model_changed(st: np.ndarray, sim, host: bool) -> bool:
    """Has the model changed since the step was last prepared for this state (G, N_active, a
    setting HBVM checks, the choice of REBOUND's own accelerations, or on them a mass)?  Then the previous
    coefficients and the reference energy belong to another system: a continued run starts
    them afresh from the particles, as IAS15 continues after ``sim.G`` was changed.  A state
    without a context (new, loaded, copied) keeps what it carries."""
    if not st[L.SL_CTX]:
        return False
    ctx = int64s(int(st[L.SL_CTX]), L.N_HEADER)
    if not same_model(ctx, int64s(ctypes.addressof(sim), int(ctx[L.R_HEAD]))):
        return True
    if bool(ctx[L.D_HOST]) != host:
        return True
    # (a state of velocities does not see a mass changed)
    return host and masses_changed(st, sim)


def masses_digest(sim) -> float:
    """The particles' masses (and their number) as one double, saved with the run's start
    (layout.SL_EREF_MASSES): 52 bits of their SHA-256, so that a loaded or copied run tells
    whether its drift check's anchor was taken with the masses it now has."""
    m = np.zeros(sim.N)
    sim.serialize_particle_data(m=m)
    d = hashlib.sha256(np.ascontiguousarray(m, dtype=float).tobytes()).digest()
    return float(int.from_bytes(d[:8], "little") >> 12)


def masses_changed(st: np.ndarray, sim) -> bool:
    """Are the simulation's masses other than those the last step wrote (its context's copy of
    the particles)?  False without a context or with another N."""
    if not st[L.SL_CTX]:
        return False
    ctx = int64s(int(st[L.SL_CTX]), L.N_HEADER)
    N = int(ctx[L.D_N])
    if N != sim.N:
        return False
    written = doubles(int(ctx[L.A_WRITTEN]), 7 * N).reshape(N, 7)
    m = np.zeros(N)
    sim.serialize_particle_data(m=m)
    return not np.array_equal(written[:, 6], m)


def array(st: np.ndarray, slot: int, slot_n: int, n: int) -> np.ndarray:
    """The state's array at ``slot`` with n doubles (reallocated with the C library, as REBOUND
    allocates it when it loads a simulation, so that either may free it)."""
    if int(st[slot_n]) != n or not st[slot]:
        addr = LIBC.realloc(ctypes.c_void_p(int(st[slot]) or None), 8 * max(n, 1))
        if not addr:
            raise MemoryError("HBVM: could not allocate its state")
        st[slot], st[slot_n] = addr, n
    return doubles(int(st[slot]), n)


def context(st, binding, method, nb, view, ptr, sim, ix, ivx, im, host_forces=False,
             kepler=False, work=None, follow=False) -> None:
    """The context block (:mod:`hbvm_md.rebound.layout`): the header, then the step's arrays,
    allocated with the C library (the state's ``free`` releases it with the state).  work: the
    compiled core's scratch (the C step, :mod:`hbvm_md.rebound.cglue`) in place of the numba
    step's work array.  kepler:
    the composed step's (:mod:`hbvm_md.rebound.kepler_glue`: the full form, coefficients of
    width 2m)."""
    ex = Extrapolation(method)
    (tn, ts), (Wp, Cp) = binding.c1, binding.c2
    NV, NVinv, NM = binding.no_newton
    s, N = method.s, view.shape[0]
    if binding.full:
        m = int(binding.system.dim)
        u = 2 * m                             # the coefficients' width (full form: 2m)
    else:
        u = m = binding.minv.shape[0]         # the coefficients' width (separable: m)
    written = np.empty((N, 7))
    written[:, :3], written[:, 3:6] = view[:, ix:ix + 3], view[:, ivx:ivx + 3]
    written[:, 6] = view[:, im]
    host = np.array([sim.G, float(np.uint64(sim.N_active).astype(np.int64))])  # as the step reads
    arrays = {L.A_YT: np.zeros(2 * m), L.A_CYT: np.zeros(2 * m), L.A_GAMMAT: np.zeros((s, u)),
              L.A_EREFT: np.zeros(L.N_EREF), L.A_WRITTEN: written, L.A_MINV: binding.minv,
              L.A_KINW: binding.kin_w, L.A_PARAMS: binding.params, L.A_HOST: host, L.A_TN: tn,
              L.A_TS: ts, L.A_WP: Wp, L.A_CP: Cp, L.A_NV: NV, L.A_NVINV: NVinv, L.A_NM: NM,
              L.A_WORK: binding.work if work is None else work, L.A_CWORK: binding.cwork, L.A_CLOCK: np.zeros(2),
              L.A_E1: ex.E1, L.A_ET: ex.t, L.A_EW: ex.w, L.A_EBUF: ex.buf, L.A_EZERO: ex.zero}
    # the tangents of REBOUND's first-order variational particles (checks.check_simulation
    # refused any other kind): one per set, its first row var_config[j].index and its particle
    # (testparticle: -1 for the whole system's N rows, i for one row of particle i's variation)
    nv = int(sim.N_var_config) if sim.N_var > 0 else 0
    vidx = np.array([[float(sim.var_config[j].index), float(sim.var_config[j].testparticle)]
                     for j in range(nv)]).reshape(nv, 2)
    nf, nc = tangent_sizes(method.n_stages, s, m, m, 2 * m) if nv else (0, 0)
    arrays.update({L.A_V: np.zeros((nv, 2 * m)), L.A_VT: np.zeros((nv, 2 * m)),
                   L.A_DG: np.zeros((nv, s, m)), L.A_DGT: np.zeros((nv, s, m)),
                   L.A_DGS: np.zeros((nv, s, m)), L.A_TW: np.zeros(nf),
                   L.A_TCW: np.zeros(nc, complex), L.A_TCOUNT: np.zeros(3), L.A_VIDX: vidx,
                   L.A_TP: np.zeros((nv, 6 * N + 3)), L.A_TO: orders(sim, nv)})
    sizes = {k: (a.nbytes + 15) // 16 * 16 for k, a in arrays.items()}
    head = 8 * L.N_HEADER
    total = head + sum(sizes.values())
    if st[L.SL_CTX]:
        LIBC.free(ctypes.c_void_p(int(st[L.SL_CTX])))
        st[L.SL_CTX] = st[L.SL_CORE] = 0
    base = LIBC.malloc(total + 16)
    if not base:
        raise MemoryError("HBVM: could not allocate its step's context")
    header = int64s(base, L.N_HEADER)
    at = base + head
    for k, a in arrays.items():
        header[k] = at
        if a.nbytes:
            dst = np.frombuffer((ctypes.c_char * a.nbytes).from_address(at), a.dtype)
            dst[:] = np.ascontiguousarray(a).reshape(-1)
        at += sizes[k]
    header[[L.D_S, L.D_K, L.D_NODES, L.D_M, L.D_N, L.D_P, L.D_NF, L.D_NC, L.D_PTR]] = (
        s, method.k, L.NODES.index(method.nodes), m, N, binding.params.shape[0],
        arrays[L.A_WORK].shape[0],
        binding.cwork.shape[0], ptr)
    header[L.D_METHOD] = L.METHODS.index("equip" if isinstance(method, EQUIP) else "hbvm")
    header[L.D_HOST] = int(host_forces)
    header[L.D_KEPLER] = int(kepler)
    header[L.D_FOLLOW] = int(follow)          # (the C step's test particles)
    # the packed arrays' shapes (HBVM's and EQUIP's differ: integrators.engine.method_arrays)
    header[[L.D_TNC, L.D_TSR, L.D_WPP, L.D_CPP, L.D_KK]] = (
        tn.shape[1], ts.shape[0], Wp.shape[0], Cp.shape[0], Cp.shape[1])
    header[L.R_T:L.R_M + 1] = REG["offsets"]
    pvar_at, megno_at, t0_at = REG["variational"]
    pvar = ctypes.c_void_p.from_address(ctypes.addressof(sim) + 8 * pvar_at).value or 0
    header[[L.D_NV, L.D_TGF, L.D_TGC, L.D_PVAR, L.D_MEGNO_FN, L.R_PVAR, L.R_MEGNO_ON,
            L.R_MEGNO_T0]] = (nv, nf, nc, pvar, REG["megno_update"], pvar_at,
                              megno_at, t0_at)
    header[L.R_STATUS] = REG["status_at"]
    header[L.R_HEAD] = max(int(header[L.R_HEAD]), pvar_at + 1, megno_at // 8 + 1, t0_at + 1,
                           type(sim)._N_odes.offset // 8 + 1,   # (the step hides the ODEs)
                           REG["status_at"] // 8 + 1)
    words = REG["config_words"]
    header[L.C_WORDS:L.C_VALUES] = words
    sim_words = int64s(ctypes.addressof(sim), max(words) + 1)
    header[L.C_VALUES:L.C_VALUES + L.N_CFG] = sim_words[words]
    st[L.SL_CTX] = base


def orders(sim, nv: int) -> np.ndarray:
    """Each variational set's order and, for a second-order set, the sets of its two first-order
    variations (REBOUND names their first rows in ``particles_var``: index_1st_order_a/b)."""
    first = {int(sim.var_config[j].index): j for j in range(nv)}
    out = np.zeros((nv, 3))
    for j in range(nv):
        vc = sim.var_config[j]
        out[j] = (vc.order, -1, -1)
        if vc.order == 2:
            out[j, 1:] = first[int(vc.index_1st_order_a)], first[int(vc.index_1st_order_b)]
    return out


def user_stacklevel() -> int:
    """The stacklevel of the first frame outside hbvm_md.rebound (the user's line)."""
    import sys
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.dirname(os.path.abspath(frame.f_code.co_filename)) == HERE:
        frame, level = frame.f_back, level + 1
    return level
