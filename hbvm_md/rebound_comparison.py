"""Energy conservation of HBVM(k, s) against REBOUND's own integrators, in one process.

>>> from hbvm_md import compare_rebound
>>> cmp = compare_rebound("outer_solar_system", t_end=1e5, verbose=True)   # doctest: +SKIP
>>> cmp.table()                                                            # doctest: +SKIP
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

#: Default step of each fixed-step method as a fraction of the scene's shortest two-body period
#: (for the outer solar system, Jupiter's: P_J / 20 is 217 days; HBVM at round-off k keeps the energy
#: error at IAS15's level there, see benchmarks/results/rebound.md).
DT_FRACTION = {"hbvm": 1 / 20, "whfast": 1 / 100, "saba(10,6,4)": 1 / 20, "leapfrog": 1 / 1000}
DEFAULT_PEERS = ("whfast", "saba(10,6,4)", "leapfrog", "ias15")
ADAPTIVE = ("ias15", "bs")


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
        error per unit time, least-squares line), final_position_diff (max over particles of
        |x - x_ref| at t_end, in the scene's length unit), wall_time_s.
    series : dict
        label -> (t (n,), relative energy error (n,)) for plotting.
    reference : str
        Label of the run the positions are compared with.
    t_end : float
    """

    rows: list
    series: dict
    reference: str
    t_end: float
    positions: dict = field(default_factory=dict, repr=False)

    def row(self, method: str) -> dict:
        for r in self.rows:
            if r["method"] == method:
                return r
        raise KeyError(f"no run labelled {method!r}; runs: {[r['method'] for r in self.rows]}")

    def table(self) -> str:
        """A markdown table of the rows."""
        head = ("| method | dt | steps | max rel. energy error | drift slope (1/time) | "
                f"final position diff vs {self.reference} | wall time (s) |\n"
                "|---|---|---|---|---|---|---|\n")
        lines = []
        for r in self.rows:
            dt = "adaptive" if r["dt"] is None else f"{r['dt']:.4g}"
            lines.append(f"| {r['method']} | {dt} | {r['steps']} | {r['max_rel_energy_error']:.2e} | "
                         f"{r['drift_slope']:.1e} | {r['final_position_diff']:.1e} | "
                         f"{r['wall_time_s']:.4f} |")
        return head + "\n".join(lines) + "\n"


def _run(make, label, setup, t_end, n_samples, exact):
    sim = make()
    drv = setup(sim)
    E0 = sim.energy()
    ts = np.linspace(0.0, t_end, n_samples + 1)[1:] + sim.t
    err = np.empty(n_samples)
    steps0 = sim.steps_done
    start = time.perf_counter()
    for i, t in enumerate(ts):
        sim.integrate(t, exact_finish_time=exact)
        err[i] = abs(sim.energy() - E0) / abs(E0)
    wall = time.perf_counter() - start
    N = sim.N
    xv = np.zeros(6 * N)
    sim.serialize_particle_data(xyzvxvyvz=xv)
    x = xv.reshape(N, 6)[:, :3].copy()
    if drv is not None:
        drv.detach()
    return dict(method=label, steps=int(sim.steps_done - steps0), wall_time_s=wall,
                max_rel_energy_error=float(err.max()),
                drift_slope=float(np.polyfit(ts - ts[0], err, 1)[0]) if n_samples > 2 else 0.0,
                final_t=sim.t), (ts, err), x


def compare_rebound(scene="outer_solar_system", t_end: float = 1e5,
                    hbvm: Sequence = ((6, None),), peers: Sequence = DEFAULT_PEERS,
                    n_samples: int = 200, reference: str | None = None,
                    verbose: bool = False) -> ReboundComparison:
    """Integrate one scene with HBVM(k, s) through REBOUND and with REBOUND's integrators.

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
        HBVM variants; k None chooses k on the scene (:func:`hbvm_md.rebound_driver.choose_k`);
        dt defaults to P / 35, P the shortest two-body period of the scene.
    peers : sequence of str or (str, dt)
        REBOUND integrators ("whfast", "saba(10,6,4)", "leapfrog", "ias15", ...); a fixed step
        defaults to :data:`DT_FRACTION` times P; IAS15 and BS are adaptive.
    n_samples : int
        Energy samples (equally spaced, t_end / n_samples apart).  Fixed steps are rounded down
        so that they divide that interval: every run ends exactly at t_end without a shrunken
        step.
    reference : str, optional
        Label of the run the final positions are compared with; default "ias15" when it ran,
        else the run with the smallest maximum energy error.
    verbose : bool
        Print the table.

    Returns
    -------
    ReboundComparison
    """
    from .rebound_driver import HBVMIntegrator, shortest_period

    if not (np.isfinite(t_end) and t_end > 0):
        raise ValueError(f"`t_end` must be a positive number (got t_end={t_end!r})")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 1:
        raise ValueError(f"`n_samples` must be a positive integer (got n_samples={n_samples!r})")
    make = _scene_factory(scene)
    period = shortest_period(make())
    interval = t_end / n_samples

    def fit(dt):
        return interval / math.ceil(interval / dt - 1e-9)

    runs = []
    for v in hbvm:
        v = tuple(v)
        if len(v) not in (2, 3):
            raise ValueError(f"`hbvm` entries must be (s, k) or (s, k, dt) (got {v!r})")
        s, k = int(v[0]), v[1]
        dt = fit(v[2] if len(v) == 3 and v[2] is not None else DT_FRACTION["hbvm"] * period)
        drvs = {}

        def setup(sim, s=s, k=k, dt=dt):
            return HBVMIntegrator(sim, s=s, k=k, dt=dt)
        runs.append((None, setup, dt, 1, drvs, (s, k)))
    for p in peers:
        name, dt = (p, None) if isinstance(p, str) else (p[0], p[1])
        if name in ADAPTIVE:
            dt = None
        else:
            dt = fit(dt if dt is not None else DT_FRACTION.get(name, 1 / 100) * period)

        def setup(sim, name=name, dt=dt):
            # REBOUND spells SABA(10,6,4) "saba10,6,4"
            sim.integrator = name.replace("(", "").replace(")", "") if name.startswith("saba") else name
            if dt is not None:
                sim.dt = dt
            return None
        runs.append((name, setup, dt, 1, None, None))

    rows, series, positions = [], {}, {}
    for label, setup, dt, exact, _, sk in runs:
        if sk is not None:
            holder = {}

            def setup_h(sim, setup=setup, holder=holder):
                d = setup(sim)
                holder["k"] = d.method.k
                return d
            # untimed warm-up over one sample interval: the first call of the compiled step in
            # a process loads it from numba's cache (or compiles it), which is not integration
            _run(make, "hbvm", setup_h, interval, 1, exact)
            row, ser, x = _run(make, "hbvm", setup_h, t_end, n_samples, exact)
            label = f"HBVM({holder['k']},{sk[0]})"
            row["method"] = label
        else:
            row, ser, x = _run(make, label, setup, t_end, n_samples, exact)
        row["dt"] = dt
        if label in series:          # e.g. two HBVM variants whose steps were fitted alike
            label = row["method"] = f"{label} dt={dt:.4g}" if dt else f"{label} #{len(rows)}"
        rows.append(row)
        series[label] = ser
        positions[label] = x
    if reference is None:
        reference = "ias15" if "ias15" in positions else min(rows, key=lambda r: r["max_rel_energy_error"])["method"]
    if reference not in positions:
        raise ValueError(f"`reference` must be one of the runs {list(positions)} (got {reference!r})")
    xr = positions[reference]
    for r in rows:
        r["final_position_diff"] = float(np.max(np.linalg.norm(positions[r["method"]] - xr, axis=1)))
    out = ReboundComparison(rows, series, reference, float(t_end), positions)
    if verbose:
        print(out.table())
    return out
