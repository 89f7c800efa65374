"""The named records the step passes around, instead of its arrays one by one.

Every record is a :func:`collections.namedtuple`: numba compiles a named tuple of arrays as a
struct of them (a field read is a struct access, free once compiled), Python reads the same
fields by name, and a record built once by a host (its system, method, work) is passed whole.
The step's signatures (:mod:`integrators.loop`, :mod:`integrators.tangent`,
:mod:`hbvm_md.rebound.glue`) are written in these records; what each field holds:

* :class:`System` -- the scene's side: the form (``full``: y is the state and the kernel is
  grad H; else y = (q, p) and the kernel the forces), 1 / m of each coordinate (empty in the
  full form; a state of REBOUND's own accelerations carries them for the velocities too), the
  kinetic energy's weights, and the kernel's parameters;
* :class:`State` -- what a step reads and, when it succeeds, writes: the double-double state
  (y, cy) (2m,), the last step's coefficients gamma (s, u), ``eref`` (the energy between steps;
  EQUIP's alpha and dE/dalpha after it, :data:`integrators.equip_core.EREF_EQUIP`) and the
  compensated clock (t, its low part);
* :class:`Method` -- the method's arrays packed as they are stored and passed (four arrays:
  one argument unboxed or one address kept by a host, whatever s and k are): ``tn`` (2, k) the
  nodes tau and their rounding remainders, ``ts`` (2+, s) X_s's first row, ``Wp`` (2+, s, K)
  the projection W = P_s^T Omega and its remainders, ``Cp`` (4+, K, s) C2 = I_s X_s and I_s with
  their remainders; EQUIP adds planes (:mod:`integrators.equip_core`).
  :func:`integrators.loop.tableau` names them at their natural shapes (:class:`Tableau`)
  inside the step (where a compiled step never returns it to Python: boxing a named tuple
  runs Python code, which a signal handler could interrupt);
* :class:`Newton` -- the simplified-Newton matrices of :mod:`integrators.core` (``NM`` of shape
  (0, u, u): the fixed-point iteration);
* :class:`Options` -- the iteration cap, its tolerance (0: to round-off), the energy check's
  tolerance, the bound on the step's own error estimate (0: no check) and the coordinates of
  one body (0: the state is one block) (:func:`integrators.loop.run`,
  :func:`integrators.core.resolution_error`);
* :class:`Work` -- the step's two work buffers (:func:`integrators.core.carve`) and its float
  counters (:data:`integrators.core.N_COUNTERS`, the committed steps' work);
* :class:`Samples` -- how many steps :func:`integrators.loop.run` takes and where it writes
  its samples (``every`` = 0: none);
* :class:`Extrapolation` -- the arrays of the initial guess's extrapolation
  (:func:`integrators.core.select_extrapolation`);
* :class:`Adaptive` -- the adaptive control of :func:`integrators.loop.attempt` (epsilon = 0: a
  fixed step) and its result record ``res``;
* :class:`StepConstants` -- h, h tau (exact pairs) and h^2 (an exact pair), computed once a
  step (:func:`integrators.core.step_constants`);
* :class:`Tableau`, :class:`Block` -- views inside a step (the method named; a group of
  followers' arrays);
* :class:`Tangents`, :class:`Variational` -- the tangent map's arrays and the variational
  run's scratch and samples (:mod:`integrators.tangent`).

A record is a view of arrays its builder owns: it does not copy them.
"""
from __future__ import annotations

from collections import namedtuple


System = namedtuple("System", ["full", "minv", "kin_w", "params"])
State = namedtuple("State", ["y", "cy", "gamma", "eref", "clock"])
Method = namedtuple("Method", ["tn", "ts", "Wp", "Cp"])
Tableau = namedtuple("Tableau", ["tau", "tau_lo", "X0", "X0_lo", "W", "W_lo", "C2", "C2_lo",
                                 "I", "I_lo"])
Newton = namedtuple("Newton", ["NV", "NVinv", "NM"])
Options = namedtuple("Options", ["max_iter", "tol", "etol", "ebound", "group"])
Work = namedtuple("Work", ["work", "cwork", "counters"])
Samples = namedtuple("Samples", ["nsteps", "every", "t", "y", "e"])
Extrapolation = namedtuple("Extrapolation", ["E1", "t", "w", "buf", "zero"])
Adaptive = namedtuple("Adaptive", ["epsilon", "min_dt", "res"])
StepConstants = namedtuple("StepConstants", ["h", "ht", "ht_lo", "h2", "h2_lo"])
Block = namedtuple("Block", ["y", "cy", "minv", "a", "X", "F"])
#: P (nv, p): each tangent's own params for the jvp kernel (p = 0: the system's), e.g. the N-body
#: params followed by a variation of the masses (:func:`systems.nbody.nbody_force_jvp`); O (nv, 3):
#: each tangent's order and, for a second-order one (order 2), the indices of its two
#: first-order tangents, earlier in V (order 0 or 1: a first-order tangent)
Tangents = namedtuple("Tangents", ["V", "DG", "Vt", "DGt", "tw", "tcw", "tcount", "P", "O"])
Variational = namedtuple("Variational", ["max_iter", "y0", "cy0", "gsave", "snap", "mg", "wv",
                                         "out_v", "out_m"])

__all__ = ["System", "State", "Method", "Tableau", "Newton", "Options", "Work", "Samples",
           "Extrapolation", "Adaptive", "StepConstants", "Block", "Tangents", "Variational"]
