"""Memory layouts shared by the Python host and the compiled step: HBVM's state in REBOUND,
the step's context block, and REBOUND's own offsets (read from its ctypes structures).

HBVM's state
------------
``struct reb_integrator``'s ``create`` returns the state REBOUND keeps per simulation
(``r->integrator.state``) and passes to the step: ``struct hbvm_rb_state`` of
``csrc/hbvm_state.h``, whose members the C glue reads by name.  This module reads that header
(:func:`read_struct`) and names each member's 8-byte slot ``SL_<MEMBER>`` for the Python host
and the numba step (and the context block's words, ``struct hbvm_rb_context``, by their
members' names upper-cased: ``A_YT``, ``D_S``, ``R_T`` ...), so that one table, the header,
places every field for C, numba and Python; :mod:`hbvm_md.rebound.cglue` checks at import that
the glue's ``offsetof`` of every member is the slot read here.  The members in :data:`SAVED`
are described to REBOUND by field descriptors (``integrator.hbvm.<name>`` in its binary format)
at those offsets: settings (the method among them: HBVM or EQUIP), the proposed next step lives
in ``sim.dt``, the previous step size, the reference energy (and EQUIP's alpha and slope, its
warm starts), the counts, and three arrays REBOUND allocates, saves and restores itself
(the double-double state, the last step's coefficients gamma, the core's counters).  The other
members hold this process's function addresses, the context block and a failed step's record;
REBOUND neither saves nor copies them (a loaded or copied state starts with them zero, and the
step rebuilds them).

REBOUND's layout
----------------
The compiled step reads a handful of ``struct reb_simulation`` and ``struct reb_particle``
fields.  Their offsets are taken at run time from REBOUND's own ctypes structures
(``rebound.Simulation``, ``rebound.Particle``, ``rebound.integrator.Integrator``,
``BinarydataFieldDescriptor``), which REBOUND checks against its C library when it is
imported, and written into each context block: no REBOUND offset is a literal anywhere in this
project.  :func:`rebound_offsets` checks that every field the step reads is an aligned 8-byte
value, and :func:`check_version` that the REBOUND is one whose plug-in interface this host was
written and tested for.
"""
from __future__ import annotations

import ctypes
import hashlib
import re
from pathlib import Path

#: REBOUND versions with the plug-in interface (``reb_integrator_register``, the step called
#: with the integrator's state) that this host was written for and tested with
SUPPORTED = "REBOUND >= 5.2, < 6 (tested with 5.2.2)"

OK = 0
RESYNC = -1           # the particles are not what the last step wrote: the host prepares again
PREPARE_FAILED = -2   # the host refused the simulation (its exception is pending)
BAD_DT = -3           # sim.dt is zero or not finite
BAD_SETTINGS = -4     # a setting in sim.integrator is out of its range (host.check_settings)
TEST_PARTICLE = -5    # a fixed step converged, but a test particle's own error estimate is
                      # above its bound (glue.TP_FLOOR, TP_FACTOR): nothing committed
OUT_OF_MEMORY = -6    # the compiled step could not allocate its work: nothing committed

# ---- the two structs of csrc/hbvm_state.h, read from that file --------------------------------
#: the C header that defines HBVM's state in REBOUND and the step's context block
STATE_HEADER = Path(__file__).resolve().parent / "csrc" / "hbvm_state.h"
_MEMBER = re.compile(r"^\s*(int64_t|double|double\s*\*|void\s*\*|hbvm_rb_fn)\s*(\w+)(?:\[(\d+)\])?;\s*$")


def read_struct(text: str, name: str) -> dict[str, int]:
    """The members of ``struct name`` in the header's text, by name, at their positions in
    8-byte words (the header's rule: one member a line, every member 8 bytes; an array
    ``TYPE name[N];`` spans N words); the struct's size under the key "".  A line inside the
    struct that is neither a member, a comment nor blank is an error (the rule would then
    misplace what follows it)."""
    start = text.index("struct " + name + " {")
    end = text.index("\n};", start)
    slots, at, comment = {}, 0, False
    for line in text[text.index("\n", start) + 1:end].splitlines():
        code = line
        if comment:
            if "*/" not in code:
                continue
            code, comment = code.split("*/", 1)[1], False
        code = re.sub(r"/\*.*?\*/", "", code)
        if "/*" in code:
            code, comment = code.split("/*", 1)[0], True
        if not code.strip():
            continue
        m = _MEMBER.match(code)
        if m is None:
            raise RuntimeError(f"{STATE_HEADER.name}: cannot read the member line {line!r} of "
                               f"struct {name} (one member of 8 bytes a line)")
        slots[m.group(2)] = at
        at += int(m.group(3) or 1)
    slots[""] = at
    return slots


#: the files besides this one that the numbers here come from (integrators.specialise hashes
#: them with this module into the name of a compiled step that uses them)
SOURCE_FILES = (STATE_HEADER,)
_TEXT = STATE_HEADER.read_text()
#: HBVM's state (struct hbvm_rb_state): member -> its slot
STATE = read_struct(_TEXT, "hbvm_rb_state")
#: the context block's header (struct hbvm_rb_context): member -> its word
CONTEXT = read_struct(_TEXT, "hbvm_rb_context")
#: the first 16 hex digits of the SHA-256 of this file and the header: what the numba modules
#: that compile these numbers in are keyed on (cabi.LAYOUT_DIGEST)
DIGEST = hashlib.sha256(Path(__file__).read_bytes() + _TEXT.encode()).hexdigest()[:16]
N_SLOTS = STATE.pop("")
N_HEADER = CONTEXT.pop("")
globals().update({"SL_" + k.upper(): v for k, v in STATE.items()})
globals().update({k.upper(): v for k, v in CONTEXT.items()})
N_RES = 5             # loop.attempt's res: h taken, next h, rejections, cause, its status
assert SL_MAX_DT - SL_RES == N_RES   # noqa: F821  (defined from the header above)
#: 1 runs HBVM composed with the Keplerian flows (kepler); CONTROL: epsilon's meaning
#: (SL_CONTROL, "controller": each step's own local error estimate relative to its motion,
#: core.adapt_step, hbvm-md since 2026-12-08; a file saved before the field existed loads
#: ``create``'s 0 and holds an epsilon of the former step control, default 1e-3, which
#: host._adopt_old_epsilon converts or warns about)
CONTROL = 1
#: the former controller's default epsilon (before 2026-12-08)
OLD_DEFAULT_EPSILON = 1e-3
#: the step's eref (integrators.core.N_EREF): the energy, EQUIP's alpha and dE/dalpha (its warm
#: starts), the energy at the run's start, T's time mean over the run, the run's time and T's
#: largest (the anchor and the scale of core.DRIFT_BOUND's rule), in the consecutive slots
#: SL_EREF, SL_ALPHA, SL_SLOPE, SL_EREF_RUN, SL_TMEAN_RUN, SL_TIME_RUN, SL_TMAX_RUN.  Saved fields are found by name
#: in REBOUND's binary format, so a slot added here leaves older archives readable (a field
#: they lack keeps the value ``create`` gave it: nan for these)
N_EREF = 7
assert (SL_ALPHA, SL_SLOPE, SL_EREF_RUN, SL_TMEAN_RUN, SL_TIME_RUN, SL_TMAX_RUN) == tuple(
    SL_EREF + i for i in range(1, N_EREF))

NODES = ("gauss", "lobatto")
#: the integrators' family (``sim.integrator.method``): integrators.HBVM, integrators.EQUIP
METHODS = ("hbvm", "equip")

# REBOUND's dtype ids (enum REB_BINARYDATA_DTYPE; rebound.binarydata_field_descriptor maps them)
_DOUBLE, _INT64, _POINTER = 1, 5, 10

#: (name, slot, dtype, slot of the element count or None, documentation) of every saved slot
SAVED = (
    ("method", SL_METHOD, _INT64, None, "'hbvm': HBVM(k, s), energy conserving; 'equip': "
     "EQUIP(k, s), energy and every quadratic invariant (angular momentum) conserving."),
    ("kepler", SL_KEPLER, _INT64, None, "1: HBVM composed with the Keplerian flows about "
     "particle 0 (democratic heliocentric coordinates; fixed steps of sim.dt only, every other "
     "body bound to particle 0, Newtonian gravity only); 0: plain HBVM."),
    ("s", SL_S, _INT64, None, "Degree of the method: HBVM(k, s) and EQUIP(k, s) have order 2s."),
    ("k", SL_K, _INT64, None, "Quadrature nodes of the line integral (k >= s; EQUIP: of its "
     "energy condition)."),
    ("nodes", SL_NODES, _INT64, None, "Quadrature: 'gauss' or 'lobatto' (EQUIP: 'gauss')."),
    ("max_iter", SL_MAX_ITER, _INT64, None, "Fixed-point iterations allowed per step."),
    ("adaptive", SL_ADAPTIVE, _INT64, None, "1: adaptive steps (sim.dt shows the next step "
     "proposed); 0: fixed steps of sim.dt."),
    ("epsilon", SL_EPSILON, _DOUBLE, None, "Precision of the adaptive step control."),
    ("min_dt", SL_MIN_DT, _DOUBLE, None, "Smallest adaptive step; below it a step that cannot "
     "be resolved raises StepSizeError."),
    ("max_dt", SL_MAX_DT, _DOUBLE, None, "Largest adaptive step (0: no bound), e.g. to bound the "
     "splitting error of REBOUNDx operators, which are applied once per step."),
    ("tol", SL_TOL, _DOUBLE, None, "Relative tolerance of the iteration (0: round-off)."),
    ("energy_tol", SL_ETOL, _DOUBLE, None, "A step changing the energy by more than this "
     "(relative) is refused with UnresolvedStepError (0: no check; negative: the engine's "
     "not-a-solution rule with |energy_tol|); also switches on the fixed step's check of its "
     "test particles."),
    ("h_prev", SL_H_PREV, _DOUBLE, None, ""),
    ("eref", SL_EREF, _DOUBLE, None, ""),
    ("alpha", SL_ALPHA, _DOUBLE, None, ""),
    ("slope", SL_SLOPE, _DOUBLE, None, ""),
    ("eref_run", SL_EREF_RUN, _DOUBLE, None, ""),
    ("tmean_run", SL_TMEAN_RUN, _DOUBLE, None, ""),
    ("time_run", SL_TIME_RUN, _DOUBLE, None, ""),
    ("tmax_run", SL_TMAX_RUN, _DOUBLE, None, ""),
    ("eref_masses", SL_EREF_MASSES, _DOUBLE, None, ""),
    ("error_estimate", SL_RUN_ERR, _DOUBLE, None, "The run's accumulated error estimate: the "
     "sum over its steps of each step's own error estimate (and the phase its energy drift "
     "makes, when k does not keep H) times the share of its motion the step turns, relative to "
     "the motion's scale (an orbit's radius); HBVM warns (AccumulatedErrorWarning) when it "
     "passes 1e-2."),
    ("t_comp", SL_T_COMP, _DOUBLE, None, "Compensation of sim.t's sum of steps (the exact "
     "time is sim.t - t_comp); 0 after the user sets sim.t."),
    ("t_written", SL_T_WRITTEN, _DOUBLE, None, ""),
    ("controller", SL_CONTROL, _INT64, None, "The meaning of epsilon this state was saved "
     "with: 1, each step's own local error estimate relative to its motion; 0 in a file "
     "saved by hbvm-md before 2026-12-08, whose epsilon meant the former controller's (a "
     "warning then says what it became)."),
    ("nsteps", SL_NSTEPS, _INT64, None, "Steps committed."),
    ("rejected", SL_REJECTED, _INT64, None, "Adaptive trial steps rejected and retried smaller."),
    ("resyncs", SL_RESYNCS, _INT64, None, "Times the state was read afresh from the particles."),
    ("state", SL_Y, _POINTER, SL_NY, ""),
    ("gamma", SL_GAMMA, _POINTER, SL_NGAMMA, ""),
    ("counters", SL_COUNTERS, _POINTER, SL_NCOUNTERS, ""),
)
INT_SLOTS = frozenset(slot for _, slot, dtype, _, _ in SAVED if dtype == _INT64)
#: the saved fields REBOUND shows by name (its enum descriptors): field -> names by value
ENUMS = {"method": METHODS, "nodes": NODES}

#: settings HBVM checks (host.check_simulation): the 8-byte words of reb_simulation holding
#: them (context C_WORDS), and their values when the step was prepared (C_VALUES); a changed
#: word makes the step answer RESYNC, and the host checks the settings again
CONFIG_FIELDS = ("softening", "N_var", "testparticle_type", "_gravity", "_boundary",
                 "_N_odes", "_additional_forces", "force_is_velocity_dependent")
N_CFG = len(CONFIG_FIELDS)
assert C_VALUES - C_WORDS == N_CFG and A_V - C_VALUES == N_CFG   # noqa: F821  (the header's)
N_HOST = 2            # the block's float64 host array: G and N_active the step was built for
#: the simulation fields the step reads or writes (R_T ...), and the particle's
SIM_FIELDS = ("t", "G", "dt", "dt_last_done", "N", "_particles", "N_active")
PARTICLE_FIELDS = ("x", "vx", "m")


def _offset8(structure, name: str) -> int:
    field = getattr(structure, name)
    if field.offset % 8 or field.size != 8:
        raise RuntimeError(f"HBVM's REBOUND host needs {structure.__name__}.{name} as an aligned "
                           f"8-byte field (offset {field.offset}, size {field.size}); it supports "
                           f"{SUPPORTED}")
    return field.offset // 8


def rebound_offsets(rebound) -> list[int]:
    """REBOUND's offsets for the header slots R_T .. R_M (in doubles), from its ctypes
    structures: the simulation's fields, the number of doubles viewed from its start (up to
    the last of them or of the settings' words), the particle's size in doubles and its x, vx
    and m."""
    sim = [_offset8(rebound.Simulation, f) for f in SIM_FIELDS]
    P = rebound.Particle
    if ctypes.sizeof(P) % 8:
        raise RuntimeError(f"sizeof(reb_particle) = {ctypes.sizeof(P)} is not a multiple of 8; "
                           f"HBVM's REBOUND host supports {SUPPORTED}")
    words = [getattr(rebound.Simulation, f).offset // 8 for f in CONFIG_FIELDS]
    x, vx, m = (_offset8(P, f) for f in PARTICLE_FIELDS)
    if [_offset8(P, f) for f in ("y", "z", "vy", "vz")] != [x + 1, x + 2, vx + 1, vx + 2]:
        raise RuntimeError(f"reb_particle's x, y, z and vx, vy, vz are not consecutive; HBVM's "
                           f"REBOUND host supports {SUPPORTED}")
    return sim + [max(sim + words) + 1, ctypes.sizeof(P) // 8, x, vx, m]


def variational_offsets(rebound) -> tuple[int, int, int]:
    """REBOUND's offsets of ``_particles_var`` (doubles), ``_calculate_megno`` (bytes; a C int)
    and ``_megno_initial_t`` (doubles), the fields the variational step reads."""
    S = rebound.Simulation
    flag = S._calculate_megno
    if flag.size != 4:
        raise RuntimeError(f"HBVM's REBOUND host needs reb_simulation.calculate_megno as a C int "
                           f"(size {flag.size}); it supports {SUPPORTED}")
    return _offset8(S, "_particles_var"), flag.offset, _offset8(S, "_megno_initial_t")


def config_words(rebound) -> list[int]:
    """The 8-byte words of ``struct reb_simulation`` that hold :data:`CONFIG_FIELDS`."""
    return [getattr(rebound.Simulation, f).offset // 8 for f in CONFIG_FIELDS]


def check_version(rebound) -> None:
    """Raise RuntimeError unless ``rebound`` is a version this host supports."""
    version = getattr(rebound, "__version__", "?")
    try:
        major, minor = (int(v) for v in version.split(".")[:2])
    except ValueError:
        major, minor = 0, 0
    if major != 5 or minor < 2 or not hasattr(rebound.clibrebound, "reb_integrator_register"):
        raise RuntimeError(f"HBVM's REBOUND host supports {SUPPORTED}; got rebound {version}: "
                           "pip install 'rebound>=5.2,<6'")


def run_offsets(rebound) -> dict:
    """Byte offsets in ``struct reb_simulation`` of the fields the host's ``integrate`` and
    ``fail`` touch: exact_finish_time, status, messages."""
    S = rebound.Simulation
    return dict(eft_at=S.exact_finish_time.offset, status_at=S._status.offset,
                messages_at=S.messages.offset)


def state_offset(rebound) -> tuple[int, int]:
    """Byte offsets in ``struct reb_simulation`` of the integrator's step function pointer and
    of its state pointer (``r->integrator.callbacks.step``, ``r->integrator.state``)."""
    from rebound.integrator import Integrator, IntegratorConfiguration
    base = rebound.Simulation.integrator.offset
    return (base + IntegratorConfiguration.callbacks.offset + Integrator.step.offset,
            base + IntegratorConfiguration.state.offset)
