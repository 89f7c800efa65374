"""Energy and angular-momentum conservation of HBVM(k, s) against REBOUND's own integrators,
in one process.

The angular momentum is that of the sources about the origin (:meth:`systems.NBody.
angular_momentum`, REBOUND's ``sim.angular_momentum()`` for sources and massless test
particles), computed by one function from the states every method reached at the output times;
its change is measured as :mod:`hbvm_md.reports.invariants` defines.

>>> from hbvm_md import compare_rebound
>>> cmp = compare_rebound("outer_solar_system", t_end=1e5, verbose=True)   # doctest: +SKIP
>>> cmp.table()                                                            # doctest: +SKIP
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

#: Default step of each fixed-step peer as a fraction of the scene's shortest two-body period
#: (for the outer solar system, Jupiter's: P_J / 20 is 217 days).
DT_FRACTION = {"whfast": 1 / 100, "saba(10,6,4)": 1 / 20, "leapfrog": 1 / 1000}
DEFAULT_PEERS = ("whfast", "saba(10,6,4)", "leapfrog", "ias15")
ADAPTIVE = ("ias15", "bs")
HEYOKA_PEERS = ("heyoka", "heyoka(compact)")


def _scene_factory(scene) -> Callable:
    import rebound

    from systems import NBody, outer_solar_system

    from .names import scene_key

    if isinstance(scene, str):
        key = scene_key(scene)
        if key == "outer-solar-system":
            nb = outer_solar_system()
            return lambda: nb.to_rebound()
        if key == "rebound-outer-solar-system":
            def make():
                sim = rebound.Simulation()
                sim.add("outer solar system")
                return sim
            return make
        raise ValueError(f"`scene` must be 'outer-solar-system', 'rebound-outer-solar-system' ('_' "
                         f"or '-' alike), an "
                         f"NBody or a function returning a rebound.Simulation (got {scene!r})")
    if isinstance(scene, NBody):
        return lambda: scene.to_rebound()
    if callable(scene):
        return scene
    raise TypeError(f"`scene` must be a name, an NBody or a callable (got {type(scene).__name__})")


@dataclass
class ReboundComparison:
    """Result of :func:`compare_rebound`.

    Attributes
    ----------
    rows : list of dict
        One per run: method, dt, steps, max_rel_energy_error, drift_slope (relative energy
        error per unit time, least-squares line), max_rel_angular_momentum_error (max over the
        output times of |L - L0| / |L0|, :mod:`hbvm_md.reports.invariants`),
        final_position_diff (max over particles of |x - x_ref| at t_end, in the scene's length
        unit), wall_time_s.
    series : dict
        label -> (t (n,), relative energy error (n,)) for plotting.
    angular_momentum_series : dict
        label -> (t (n,), |L - L0| / |L0| (n,)) for plotting.
    reference : str
        Label of the run the positions are compared with.
    t_end : float
    """

    rows: list
    series: dict
    reference: str
    t_end: float
    positions: dict = field(default_factory=dict, repr=False)
    angular_momentum_series: dict = field(default_factory=dict, repr=False)

    def row(self, method: str) -> dict:
        for r in self.rows:
            if r["method"] == method:
                return r
        raise KeyError(f"no run labelled {method!r}; runs: {[r['method'] for r in self.rows]}")

    def table(self) -> str:
        """A markdown table of the rows."""
        head = ("| method | dt | steps | max rel. energy error | drift slope (1/time) | "
                f"max rel. angular momentum error | final position diff vs {self.reference} | "
                "wall time (s) |\n"
                "|---|---|---|---|---|---|---|---|\n")
        lines = []
        for r in self.rows:
            dt = "adaptive" if r["dt"] is None else f"{r['dt']:.4g}"
            lines.append(f"| {r['method']} | {dt} | {r['steps']} | {r['max_rel_energy_error']:.2e} | "
                         f"{r['drift_slope']:.1e} | {r['max_rel_angular_momentum_error']:.2e} | "
                         f"{r['final_position_diff']:.1e} | "
                         f"{r['wall_time_s']:.4f} |")
        return head + "\n".join(lines) + "\n"


def _state(sim) -> np.ndarray:
    """Positions and velocities of every particle, shape (N, 6) (REBOUND's xyzvxvyvz)."""
    xv = np.zeros(6 * sim.N)
    sim.serialize_particle_data(xyzvxvyvz=xv)
    return xv.reshape(sim.N, 6)


def angular_momentum_change(nb, xv) -> np.ndarray:
    """|L(t) - L(0)| / |L(0)| of the sources of ``nb`` (:class:`systems.NBody`) at states
    ``xv`` of shape (n, N, 6) (REBOUND's or heyoka's positions and velocities, the first the
    start); shape (n,).  One function for every method of a comparison."""
    from .invariants import change_series
    xv = np.asarray(xv, dtype=float).reshape(len(xv), nb.N, 6)
    y = np.concatenate([xv[..., :3].reshape(len(xv), -1),
                        xv[..., 3:].reshape(len(xv), -1) * nb.masses], axis=1)
    return change_series(nb.angular_momentum(y), nb.angular_momentum_scale(y))


def _slope(ts, err) -> float:
    """The slope of a linear fit of ``err`` against ``ts`` (0 for fewer than three samples).
    Fitted in time scaled to [0, 1]: times of a very short run (1e-300 days) would otherwise
    underflow inside the least-squares solve (numpy's LinAlgError)."""
    ts = np.asarray(ts, dtype=float)
    span = ts[-1] - ts[0] if len(ts) else 0.0
    if len(ts) <= 2 or not span > 0:
        return 0.0
    return float(np.polyfit((ts - ts[0]) / span, err, 1)[0] / span)


def _summary(label, steps, wall, ts, err, final_t, setup_time=0.0, compile_time=None, dL=None) -> dict:
    return dict(method=label, steps=int(steps), wall_time_s=float(wall), setup_time_s=float(setup_time),
                compile_time_s=compile_time, max_rel_energy_error=float(err.max()),
                drift_slope=_slope(ts, err),
                max_rel_angular_momentum_error=float(dL.max()) if dL is not None else float("nan"),
                final_t=float(final_t))


def _run(make, label, setup, t_end, n_samples):
    """One REBOUND-driven run: ``setup(sim)`` (attaching HBVM chooses k there) is inside the
    timed region, because the user pays for it; then ``sim.integrate(t_i)`` at each output time
    (exact_finish_time=1: REBOUND shortens the step that would overshoot an output time).  The
    energy and the state (for the angular momentum) at each output time are read outside the
    timed region, as they are for heyoka (:func:`_run_heyoka`): the wall time is what the
    integration costs, the same work for every method (``sim.energy()`` cost 1-1.5 us an
    output here, 3 % of HBVM's time over 1e5 days)."""
    from systems import NBody
    sim = make()
    nb = NBody.from_rebound(sim)
    E0 = sim.energy()
    ts = np.linspace(0.0, t_end, n_samples + 1)[1:] + sim.t
    err = np.empty(n_samples)
    xv = np.empty((n_samples + 1, sim.N, 6))
    xv[0] = _state(sim)
    steps0 = sim.steps_done
    clock = time.perf_counter
    start = clock()
    drv = setup(sim)
    setup_time = wall = clock() - start
    for i, t in enumerate(ts):
        start = clock()
        sim.integrate(t, exact_finish_time=1)
        wall += clock() - start
        err[i] = abs(sim.energy() - E0) / abs(E0)
        xv[i + 1] = _state(sim)
    x = xv[-1, :, :3].copy()
    dL = angular_momentum_change(nb, xv)[1:]
    return (_summary(label, sim.steps_done - steps0, wall, ts, err, sim.t, setup_time, dL=dL), (ts, err), x,
            drv, (ts, dL))


#: heyoka integrators already built in this process, by (masses, G, tol, precision, compact):
#: heyoka compiles once per scene shape, and a benchmark should not pay that once per run.
_HEYOKA = {}


def heyoka_solver(sim, tol: float | None = None, fp_type=float, compact_mode: bool = False):
    """The (cached) :class:`hbvm_md.reports.peers.HeyokaNBody` for the bodies of ``sim``."""
    from .peers import HeyokaNBody, import_heyoka
    import_heyoka()              # the message on a missing heyoka, even when a solver is cached
    m = np.zeros(sim.N)
    sim.serialize_particle_data(m=m)
    key = (tuple(m), float(sim.G), tol, np.dtype(fp_type).name, bool(compact_mode))
    if key not in _HEYOKA:
        _HEYOKA[key] = HeyokaNBody(m, sim.G, tol=tol, fp_type=fp_type, compact_mode=compact_mode)
    return _HEYOKA[key]


def _run_heyoka(make, label, solver, t_end, n_samples):
    """heyoka over the same output times (``propagate_grid``); energies evaluated by REBOUND's
    ``sim.energy()`` on the output states and the angular momentum by
    :func:`angular_momentum_change`, as for the REBOUND-driven runs (untimed)."""
    from systems import NBody
    sim = make()
    nb = NBody.from_rebound(sim)
    E0 = sim.energy()
    xv = np.zeros(6 * sim.N)
    sim.serialize_particle_data(xyzvxvyvz=xv)
    ts = np.linspace(0.0, t_end, n_samples + 1) + sim.t
    states, wall, steps = solver.propagate(xv, ts)
    err = np.empty(n_samples)
    for i in range(n_samples):
        sim.set_serialized_particle_data(xyzvxvyvz=np.ascontiguousarray(states[i + 1], dtype=float).reshape(-1))
        err[i] = abs(sim.energy() - E0) / abs(E0)
    x = np.asarray(states[-1, :, :3], dtype=float)
    dL = angular_momentum_change(nb, np.asarray(states, dtype=float))[1:]
    return (_summary(label, steps, wall, ts[1:], err, ts[-1], compile_time=solver.compile_time, dL=dL),
            (ts[1:], err), x, (ts[1:], dL))


def _run_composed(make, s: int, k: int, dt: float, t_end: float, n_samples: int):
    """HBVM(k, s) composed with the Keplerian flows (:class:`systems.flow_composed.FlowComposed`,
    issue 48), run by the engine over the same output times (not yet inside REBOUND): what the
    user pays is timed, the conversion of REBOUND's particles into the transformed variables,
    the steps (``dt`` shortened to divide each output interval, as REBOUND shortens a step
    that would overshoot) and the physical state at each output time; the energies and angular
    momenta are read from those states by REBOUND and :func:`angular_momentum_change`, untimed,
    as for every other method."""
    from integrators import HBVM, Stepper
    from systems import NBody
    from systems.flow_composed import FlowComposed
    sim = make()
    nb = NBody.from_rebound(sim)
    E0 = sim.energy()
    interval = t_end / n_samples
    per = max(1, int(np.ceil(interval / dt - 1e-9)))
    h = interval / per
    xv = np.empty((n_samples + 1, sim.N, 6))
    xv[0] = _state(sim)
    clock = time.perf_counter
    start = clock()
    fc = FlowComposed.from_nbody(nb, h)
    st = Stepper(HBVM(k, s), fc, fc.extend(nb.state(xv[0, :, :3], xv[0, :, 3:])), form="full")
    setup_time = clock() - start
    # one run with a sample at every output time, converted back in one pass: what a user
    # of the engine writes (a call per output costs tens of microseconds in Python)
    res = st.run(h, per * n_samples, sample_every=per)
    ys = fc.physical(res.y[1:], interval * np.arange(1, n_samples + 1))
    wall = clock() - start
    err = np.empty(n_samples)
    for i in range(n_samples):
        x = ys[i, :3 * sim.N].reshape(sim.N, 3)
        v = nb.velocities_from_momenta(ys[i, 3 * sim.N:])
        xv[i + 1] = np.hstack([x, v])
        sim.set_serialized_particle_data(xyzvxvyvz=np.ascontiguousarray(xv[i + 1]).reshape(-1))
        err[i] = abs(sim.energy() - E0) / abs(E0)
    ts = np.linspace(0.0, t_end, n_samples + 1)[1:] + sim.t
    dL = angular_momentum_change(nb, xv)[1:]
    label = f"HBVM({k},{s}) kepler"
    row = _summary(label, st.nsteps, wall, ts, err, ts[-1], setup_time, dL=dL)
    row["iterations_per_step"] = st.niter / max(st.nsteps, 1)
    return row, (ts, err), xv[-1, :, :3].copy(), (ts, dL)


#: ``reference=EXTENDED``: heyoka in 80-bit extended precision at tol 1e-18 (compact mode).
EXTENDED = "heyoka-extended"


def compare_rebound(scene="outer_solar_system", t_end: float = 1e5,
                    hbvm: Sequence = ((6, None),), peers: Sequence = DEFAULT_PEERS,
                    n_samples: int = 200, reference: str | None = None,
                    verbose: bool = False, kepler: Sequence = (),
                    kepler_rebound: Sequence = ()) -> ReboundComparison:
    """Integrate one scene with HBVM(k, s) through REBOUND, with REBOUND's integrators and
    (optionally) heyoka, over the same output times.

    Parameters
    ----------
    scene : str, NBody or callable
        "outer-solar-system" (HLW, :func:`systems.outer_solar_system`),
        "rebound-outer-solar-system" (REBOUND's ``sim.add("outer solar system")``) (names as
        everywhere in hbvm_md: "outer_solar_system" is the same scene), an
        :class:`systems.NBody` (e.g. :func:`systems.solar_system`) or a function returning a
        fresh ``rebound.Simulation`` (called once per run).
    t_end : float
        Length of each run, in the scene's time unit.
    hbvm : sequence of (s, k) or (s, k, dt)
        HBVM variants; k None chooses k on the scene when HBVM attaches
        (:func:`integrators.kchoice.choose_k`, timed as part of the run); dt None (the
        default) uses HBVMIntegrator's adaptive steps, as a user who gives no step gets.
    peers : sequence of str or (str, dt)
        REBOUND integrators ("whfast", "saba(10,6,4)", "leapfrog", "ias15", ...); a fixed step
        defaults to :data:`DT_FRACTION` times P; IAS15 and BS are adaptive.  "heyoka" and
        "heyoka(compact)" run heyoka's Taylor integrator (:class:`hbvm_md.reports.peers.HeyokaNBody`,
        heyoka's default or compact mode), the second element being its tolerance (default
        machine epsilon); its compile time is reported in ``compile_time_s``, not in the wall
        time.  ImportError with a message when heyoka is not installed.
    n_samples : int
        Output times t_end / n_samples apart, the same for every method: REBOUND-driven methods
        call ``sim.integrate(t_i)`` (exact_finish_time=1), heyoka uses ``propagate_grid``.  A
        requested step is used as given; when it does not divide the interval, REBOUND shortens
        the step that would overshoot an output time (``steps`` counts every step taken).
    reference : str, optional
        What the final positions are compared with: the label of a run, or :data:`EXTENDED`
        (heyoka in extended precision at tol 1e-18: needs heyoka); default "ias15" when it
        ran, else the run with the smallest maximum energy error.
    verbose : bool
        Print the table.
    kepler : sequence of (s, k, dt)
        HBVM(k, s) composed with the Keplerian flows (:mod:`systems.flow_composed`, the first
        body the star), run by the engine at steps of about dt (:func:`_run_composed`); rows
        "HBVM(k,s) kepler".
    kepler_rebound : sequence of (s, k, dt)
        The same method run inside REBOUND, as a user writes it:
        ``HBVMIntegrator(sim, s=s, k=k, dt=dt, kepler=True)`` and ``sim.integrate(t_i)`` at each
        output time (timed as the plain HBVM rows); rows "HBVM(k,s) kepler in REBOUND".

    Returns
    -------
    ReboundComparison
        Rows also carry ``setup_time_s`` (inside the wall time: attaching HBVM and choosing k)
        and ``compile_time_s`` (heyoka's one-off compile, outside the wall time; None for the
        others).
    """
    from ..rebound import HBVMIntegrator, shortest_period

    if not (np.isfinite(t_end) and t_end > 0):
        raise ValueError(f"`t_end` must be a positive number (got t_end={t_end!r})")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 1:
        raise ValueError(f"`n_samples` must be a positive integer (got n_samples={n_samples!r})")
    make = _scene_factory(scene)
    period = shortest_period(make())
    interval = t_end / n_samples

    runs = []
    for v in hbvm:
        v = tuple(v)
        if len(v) not in (2, 3):
            raise ValueError(f"`hbvm` entries must be (s, k) or (s, k, dt) (got {v!r})")
        s, k = int(v[0]), v[1]
        # no dt: HBVMIntegrator's own default, adaptive steps (what a user gets)
        dt = float(v[2]) if len(v) == 3 and v[2] is not None else None

        def setup(sim, s=s, k=k, dt=dt):
            return HBVMIntegrator(sim, s=s, k=k, dt=dt)
        runs.append(("hbvm", (s, k), setup, dt))
    for p in peers:
        name, arg = (p, None) if isinstance(p, str) else (p[0], p[1])
        if name in HEYOKA_PEERS:
            runs.append(("heyoka", name, heyoka_solver(make(), tol=arg, compact_mode=name != "heyoka"), None))
            continue
        dt = None if name in ADAPTIVE else float(arg if arg is not None else DT_FRACTION.get(name, 1 / 100) * period)

        def setup(sim, name=name, dt=dt):
            # REBOUND spells SABA(10,6,4) "saba10,6,4"
            sim.integrator = name.replace("(", "").replace(")", "") if name.startswith("saba") else name
            if dt is not None:
                sim.dt = dt
            return None
        runs.append(("rebound", name, setup, dt))
    for v in kepler:
        s_, k_, dt_ = (int(v[0]), int(v[1]), float(v[2]))
        runs.append(("kepler", (s_, k_), None, dt_))
    for v in kepler_rebound:
        s_, k_, dt_ = (int(v[0]), int(v[1]), float(v[2]))

        def setup(sim, s=s_, k=k_, dt=dt_):
            return HBVMIntegrator(sim, s=s, k=k, dt=dt, kepler=True)
        runs.append(("kepler_rebound", (s_, k_), setup, dt_))

    rows, series, positions, l_series = [], {}, {}, {}
    for kind, label, setup, dt in runs:
        if kind == "hbvm":
            # untimed warm-up over one sample interval: the first call of the compiled step in
            # a process loads it from numba's cache (or compiles it), which is not integration
            _run(make, "hbvm", setup, interval, 1)
            row, ser, x, drv, lser = _run(make, "hbvm", setup, t_end, n_samples)
            label = row["method"] = f"HBVM({drv.method.k},{label[0]})"
        elif kind == "kepler_rebound":
            _run(make, "hbvm", setup, interval, 1)              # (warm-up, as for HBVM)
            row, ser, x, drv, lser = _run(make, "hbvm", setup, t_end, n_samples)
            label = row["method"] = f"HBVM({label[1]},{label[0]}) kepler in REBOUND"
            row["iterations_per_step"] = drv.niter / max(drv.nsteps, 1)
        elif kind == "kepler":
            _run_composed(make, *label, dt, interval, 1)          # (warm-up, as for HBVM)
            row, ser, x, lser = _run_composed(make, *label, dt, t_end, n_samples)
            label = row["method"]
        elif kind == "heyoka":
            row, ser, x, lser = _run_heyoka(make, label, setup, t_end, n_samples)
            row["tol"], row["order"] = setup.tol, setup.order
        else:
            row, ser, x, _, lser = _run(make, label, setup, t_end, n_samples)
        row["dt"] = dt
        if label in series:          # e.g. two HBVM variants that chose the same k
            label = row["method"] = f"{label} dt={dt:.4g}" if dt else f"{label} #{len(rows)}"
        rows.append(row)
        series[label] = ser
        l_series[label] = lser
        positions[label] = x
    if reference == EXTENDED:
        sim = make()
        ref = heyoka_solver(sim, tol=1e-18, fp_type=np.longdouble, compact_mode=True)
        xv = np.zeros(6 * sim.N)
        sim.serialize_particle_data(xyzvxvyvz=xv)
        states, _, _ = ref.propagate(xv, np.array([sim.t, sim.t + t_end]))
        xr = np.asarray(states[-1, :, :3], dtype=float)
    else:
        if reference is None:
            reference = "ias15" if "ias15" in positions else min(rows, key=lambda r: r["max_rel_energy_error"])["method"]
        if reference not in positions:
            raise ValueError(f"`reference` must be {EXTENDED!r} or one of the runs {list(positions)} "
                             f"(got {reference!r})")
        xr = positions[reference]
    for r in rows:
        r["final_position_diff"] = float(np.max(np.linalg.norm(positions[r["method"]] - xr, axis=1)))
    out = ReboundComparison(rows, series, reference, float(t_end), positions, l_series)
    if verbose:
        print(out.table())
    return out
