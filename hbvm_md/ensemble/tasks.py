"""Ready-made ensemble members for :func:`hbvm_md.ensemble.run_ensemble`.

Each task is a module-level function ``task(param, **settings) -> dict`` (bind the settings with
``functools.partial``; both pickle by reference) with a ``warmup`` attribute that loads its
compiled code once per worker.

* :func:`solar_clone` -- the outer solar system (HLW) perturbed at 1e-13 by a seed, through
  :class:`hbvm_md.HBVMIntegrator`: energy-error statistics and the divergence of a nearby
  shadow clone (a chaos indicator).
* :func:`stability_member` -- a test planet at (a, e) added to the outer solar system: whether it
  survives, its chaos indicator (MEGNO by default, or the divergence of a shadow clone) and
  the energy error; :func:`stability_grid` makes the parameters of a map and
  :func:`plot_stability_map` draws it.
* :func:`md_replica` -- an ASE scene (the polynomial-pair cluster of
  :func:`hbvm_md.reports.md_comparison.default_cluster`) with seeded Maxwell-Boltzmann velocities
  through :class:`hbvm_md.HBVMDynamics`.

The divergence of two clones started ``delta`` apart (relative, in position) is the classic
two-particle chaos indicator: it grows about linearly in time on a regular orbit and
exponentially on a chaotic one, until it saturates at the size of the orbit (Benettin, Galgani,
Strelcyn, *Phys. Rev. A* 14 (1976)).  The field's indicator is MEGNO (Cincotta and Simo,
*Simple tools to study global dynamics in non-axisymmetric galactic potentials - I*, A&AS 147,
2000), computed by REBOUND from its first-order variational particles, which HBVM integrates by
the tangent map of its own step (:mod:`hbvm_md.rebound`): <Y> tends to 2 on a regular orbit and
grows like lambda t / 2 on a chaotic one; a map calls a point chaotic when <Y> exceeds
:data:`MEGNO_CHAOTIC`.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from integrators import StepError

__all__ = ["solar_clone", "stability_member", "stability_grid", "stability_table",
           "plot_stability_map", "md_replica", "MEGNO_CHAOTIC"]

#: Distance from the Sun (AU) beyond which a planet of a stability map counts as escaped.
_R_MAX = 100.0
#: Default mass of a stability map's planet (solar masses): about one Earth mass.
PLANET_MASS = 3.0e-6
#: A map's threshold: a point whose MEGNO <Y> exceeds it is called chaotic (a regular orbit's
#: <Y> tends to 2; over a run of a few hundred orbits a regular one stays well below this).
MEGNO_CHAOTIC = 4.0
#: The chaos indicators of :func:`stability_member`.
INDICATORS = ("megno", "clone")


def _perturbed(y: np.ndarray, scale: float, rng: np.random.Generator, mask=None) -> np.ndarray:
    """y (1 + scale N(0, 1)) on the entries of ``mask`` (default all)."""
    z = scale * rng.standard_normal(y.shape)
    if mask is not None:
        z = np.where(mask, z, 0.0)
    return y * (1.0 + z)


def _clone_pair(nb, y_a: np.ndarray, y_b: np.ndarray, *, t_end: float, dt: float, s: int,
                k: int | None, n_samples: int, watch, r_max: float | None = None) -> dict:
    """Integrate the scene ``nb`` from y_a and from its shadow y_b with HBVMIntegrator.

    ``watch``: indices of the bodies whose clone distance (max |x_a - x_b| in position) is
    followed and, with ``r_max``, whose distance from body 0 ends the run when above ``r_max``.
    An integration error (a close encounter the step cannot resolve) ends the run too: the
    record says when and why, the member does not fail.
    """
    from ..rebound import HBVMIntegrator

    _check_run(t_end, dt, n_samples)
    sims = [nb.to_rebound(y_a), nb.to_rebound(y_b)]
    drv_a = HBVMIntegrator(sims[0], s=s, k=k, dt=dt)
    HBVMIntegrator(sims[1], s=s, k=drv_a.method.k, dt=dt)     # the same method for both
    watch = np.asarray(watch)
    N = nb.N

    def positions(sim):
        xv = np.zeros(6 * N)
        sim.serialize_particle_data(xyzvxvyvz=xv)
        return xv.reshape(N, 6)[:, :3]

    def distance():
        return float(np.max(np.linalg.norm(positions(sims[0])[watch] - positions(sims[1])[watch], axis=1)))

    E0 = sims[0].energy()
    d0 = distance()
    ts = np.linspace(0.0, t_end, n_samples + 1)[1:]
    t_done, errs, logd = [], [], []
    stop_reason = None
    for t in ts:
        try:
            for sim in sims:
                sim.integrate(t)
        except StepError as exc:
            stop_reason = f"{type(exc).__name__}: {exc}"
            break
        t_done.append(t)
        errs.append(abs(sims[0].energy() - E0) / abs(E0))
        logd.append(math.log10(distance() / d0) if d0 > 0 else math.nan)
        if r_max is not None:
            stop_reason = _escaped(positions(sims[0]), watch, r_max)
            if stop_reason:
                break
    steps = drv_a.nsteps
    dd = np.array(logd)
    return {
        **_run_summary(t_end, t_done, errs, stop_reason),
        # log10 of the largest clone distance over the initial one: ~ log10(t / period) on a
        # regular orbit, up to log10(orbit size / d0) on a chaotic one
        "log10_divergence": float(np.nanmax(dd)) if np.isfinite(dd).any() else math.nan,
        "k": int(drv_a.method.k), "s": int(s), "dt": float(dt), "steps": int(steps),
    }


def _megno_run(nb, y: np.ndarray, *, t_end: float, dt: float, s: int, k: int | None,
               n_samples: int, watch, r_max: float | None = None) -> dict:
    """Integrate the scene ``nb`` from y with HBVMIntegrator and REBOUND's MEGNO
    (``sim.init_megno(seed=0)``: one tangent of the whole system, random and seeded).

    ``watch`` and ``r_max`` as for :func:`_clone_pair`: an escape or a step HBVM refuses ends
    the run, and the record says when and why."""
    from ..rebound import HBVMIntegrator

    _check_run(t_end, dt, n_samples)
    sim = nb.to_rebound(y)
    drv = HBVMIntegrator(sim, s=s, k=k, dt=dt)
    sim.init_megno(seed=0)
    watch = np.asarray(watch)
    N = nb.N
    xv = np.zeros(6 * N)
    E0 = sim.energy()
    ts = np.linspace(0.0, t_end, n_samples + 1)[1:]
    t_done, errs = [], []
    stop_reason = None
    megno = lyapunov = math.nan
    for t in ts:
        try:
            sim.integrate(t)
        except StepError as exc:
            stop_reason = f"{type(exc).__name__}: {exc}"
            break
        t_done.append(t)
        errs.append(abs(sim.energy() - E0) / abs(E0))
        megno, lyapunov = float(sim.megno()), float(sim.lyapunov())
        if r_max is not None:
            sim.serialize_particle_data(xyzvxvyvz=xv)
            stop_reason = _escaped(xv.reshape(N, 6)[:, :3], watch, r_max)
            if stop_reason:
                break
    return {
        **_run_summary(t_end, t_done, errs, stop_reason),
        "megno": megno, "lyapunov": lyapunov,
        "k": int(drv.method.k), "s": int(s), "dt": float(dt), "steps": int(drv.nsteps),
    }


def _escaped(x: np.ndarray, watch, r_max: float) -> str | None:
    """The stop reason when a watched body (positions x (N, 3)) is beyond r_max from body 0."""
    r = float(np.max(np.linalg.norm(x[watch] - x[0], axis=1)))
    return f"escaped: distance {r:.4g} > r_max={r_max:g} from body 0" if r > r_max else None


def _run_summary(t_end: float, t_done: list, errs: list, stop_reason: str | None) -> dict:
    """The fields every run of a map records: how far it went, why it stopped, its energy."""
    tt, ee = np.array(t_done), np.array(errs)
    return {
        "t_end": float(t_end), "t_stop": float(tt[-1]) if tt.size else 0.0,
        "survived": stop_reason is None, "stop_reason": stop_reason or "",
        "max_rel_energy_error": float(ee.max()) if ee.size else math.nan,
        "final_rel_energy_error": float(ee[-1]) if ee.size else math.nan,
        "energy_drift_slope": float(np.polyfit(tt, ee, 1)[0]) if tt.size > 2 else math.nan,
    }


def _check_run(t_end, dt, n_samples) -> None:
    if not (np.isfinite(t_end) and t_end > 0):
        raise ValueError(f"`t_end` must be a positive number (got t_end={t_end!r})")
    if not (np.isfinite(dt) and 0 < dt <= t_end):
        raise ValueError(f"`dt` must be in (0, t_end={t_end!r}] (got dt={dt!r})")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 2:
        raise ValueError(f"`n_samples` must be an integer >= 2 (got n_samples={n_samples!r})")


def _warm_rebound() -> None:
    """Load the compiled HBVMIntegrator step (numba cache) with a few steps of the outer solar system."""
    from systems import outer_solar_system
    nb = outer_solar_system()
    _clone_pair(nb, nb.initial_state(), nb.initial_state(), t_end=1000.0, dt=250.0, s=6, k=None,
                n_samples=2, watch=[1])


# -- perturbed clones of a scene -----------------------------------------------------------
def solar_clone(seed: int, *, t_end: float = 1e6, dt: float = 250.0, s: int = 6,
                k: int | None = None, scale: float = 1e-13, delta: float = 1e-13,
                n_samples: int = 100) -> dict:
    """The outer solar system (HLW) perturbed by ``seed``, integrated with HBVM(k, s).

    Parameters
    ----------
    seed : int
        Member number: every coordinate and momentum is multiplied by 1 + scale N(0, 1) drawn
        from ``numpy.random.default_rng(seed)``.
    t_end, dt : float
        Days.  dt = 250 with s = 6 keeps the energy error at round-off (P_Jupiter / 17).
    s, k : int
        The method; k None chooses the round-off k on the scene.
    scale : float
        Relative size of the member's perturbation.
    delta : float
        Relative size of the shadow clone's further perturbation of all positions.
    n_samples : int
        Samples of the energy error and the clone distance, equally spaced.

    Returns
    -------
    dict
        seed, max/final relative energy error, drift slope (per day), log10_divergence (all
        bodies), survived, t_stop, stop_reason, k, s, dt, steps and the final positions of
        the clone, flattened (``final_positions``, AU).
    """
    from systems import outer_solar_system
    nb = outer_solar_system()
    rng = np.random.default_rng(seed)
    y_a = _perturbed(nb.initial_state(), scale, rng)
    pos = np.arange(y_a.size) < nb.dim
    y_b = _perturbed(y_a, delta, rng, mask=pos)
    out = _clone_pair(nb, y_a, y_b, t_end=t_end, dt=dt, s=s, k=k, n_samples=n_samples,
                      watch=np.arange(nb.N))
    return {"seed": int(seed), **out}


solar_clone.warmup = _warm_rebound


# -- a stability map -------------------------------------------------------------------------
def _with_planet(a: float, e: float, mass: float):
    """The outer solar system with a planet of ``mass`` (solar masses) at (a, e) about the Sun,
    in Jupiter's orbital plane, its perihelion 90 degrees ahead of Jupiter's and its mean
    longitude opposite Jupiter's (so that it does not start next to Jupiter)."""
    from systems import NBody, outer_solar_system
    base = outer_solar_system()
    sim = base.to_rebound()
    jup = sim.particles[1].orbit(primary=sim.particles[0])
    sim.add(primary=sim.particles[0], m=mass, a=a, e=e, inc=jup.inc, Omega=jup.Omega,
            pomega=jup.pomega + math.pi / 2, l=jup.l + math.pi)
    return NBody.from_rebound(sim, names=base.names + ["planet"])


def stability_member(param, *, t_end: float = 1e6, dt: float = 250.0, s: int = 6,
                     k: int | None = None, mass: float = PLANET_MASS, delta: float = 1e-10,
                     n_samples: int = 100, r_max: float = _R_MAX,
                     indicator: str = "megno") -> dict:
    """One point of a stability map: a planet at (a, e) in the outer solar system.

    Parameters
    ----------
    param : dict or tuple
        ``{"a": AU, "e": eccentricity}`` or ``(a, e)``.
    t_end, dt : float
        Days.
    mass : float
        The planet's mass in solar masses (default about one Earth mass: it enters the energy,
        so an unresolved close encounter shows as an energy error).  0 makes it a test particle.
    delta : float
        Relative displacement of the shadow clone's planet (position only; indicator "clone").
    r_max : float
        The planet has escaped when farther than this from the Sun (AU).
    indicator : {"megno", "clone"}
        "megno": REBOUND's MEGNO <Y> and Lyapunov estimate from HBVM's variational particles
        (``sim.init_megno(seed=0)``); "clone": the divergence of a shadow clone ``delta``
        apart (two runs).

    Returns
    -------
    dict
        a, e, the indicator and the fields of the run: survived, t_stop, stop_reason,
        max_rel_energy_error, megno and lyapunov (MEGNO) or log10_divergence (of the planet;
        clone), ...
    """
    if indicator not in INDICATORS:
        raise ValueError(f"`indicator` must be one of {INDICATORS} (got {indicator!r})")
    a, e = (param["a"], param["e"]) if isinstance(param, dict) else param
    a, e = float(a), float(e)
    if not (np.isfinite(a) and a > 0 and 0 <= e < 1):
        raise ValueError(f"a planet needs a > 0 and 0 <= e < 1 (got a={a!r}, e={e!r})")
    nb = _with_planet(a, e, mass)
    y_a = nb.initial_state()
    if indicator == "megno":
        out = _megno_run(nb, y_a, t_end=t_end, dt=dt, s=s, k=k, n_samples=n_samples,
                         watch=[nb.N - 1], r_max=r_max)
        return {"a": a, "e": e, "indicator": indicator, **out}
    mask = np.zeros(y_a.size, bool)
    mask[3 * (nb.N - 1):3 * nb.N] = True
    y_b = _perturbed(y_a, delta, np.random.default_rng(0), mask=mask)
    out = _clone_pair(nb, y_a, y_b, t_end=t_end, dt=dt, s=s, k=k, n_samples=n_samples,
                      watch=[nb.N - 1], r_max=r_max)
    return {"a": a, "e": e, "indicator": indicator, **out}


stability_member.warmup = _warm_rebound


def stability_grid(a_range=(6.0, 36.0), e_range=(0.0, 0.5), shape=(20, 20)) -> list[dict]:
    """Parameters of a stability map: ``shape = (n_a, n_e)`` points, e varying fastest."""
    n_a, n_e = (int(n) for n in shape)
    if n_a < 1 or n_e < 1:
        raise ValueError(f"`shape` must be two positive integers (got {shape!r})")
    (a0, a1), (e0, e1) = a_range, e_range
    if not (0 < a0 <= a1 and 0 <= e0 <= e1 < 1):
        raise ValueError(f"need 0 < a_min <= a_max and 0 <= e_min <= e_max < 1 (got "
                         f"a_range={a_range!r}, e_range={e_range!r})")
    return [{"a": float(a), "e": float(e)} for a in np.linspace(a0, a1, n_a)
            for e in np.linspace(e0, e1, n_e)]


_MAP_COLUMNS = ("a", "e", "indicator", "survived", "t_stop", "megno", "lyapunov",
                "log10_divergence", "max_rel_energy_error", "k", "steps", "wall_time_s", "status",
                "stop_reason")


def stability_table(records: list[dict]) -> list[dict]:
    """One flat row per grid point from the records of :func:`stability_member` (failed members
    keep a and e, NaN values and their error as the stop reason)."""
    rows = []
    for r in records:
        p = r["param"]
        a, e = (p["a"], p["e"]) if isinstance(p, dict) else p
        res = r["result"] or {}
        row = {c: res.get(c, math.nan) for c in _MAP_COLUMNS}
        row.update(a=float(a), e=float(e), wall_time_s=r["wall_time_s"], status=r["status"])
        if r["status"] != "ok":
            row["survived"], row["stop_reason"] = False, r["error"]
        rows.append(row)
    return rows


def plot_stability_map(rows: list[dict], path, title: str = "") -> Path:
    """Three panels over (a, e): the chaos indicator (MEGNO <Y>, with the contour <Y> =
    :data:`MEGNO_CHAOTIC` and the indicator and threshold in its label; or the log10 clone
    divergence), log10 max energy error, survival time.  A MEGNO run that stopped (an
    escape, an unresolved encounter) is drawn as the top of the colour scale: unstable.

    Grey cells: no sample (the run stopped before its first sample, or the member failed)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a = np.array(sorted({r["a"] for r in rows}))
    e = np.array(sorted({r["e"] for r in rows}))
    grids = {name: np.full((e.size, a.size), np.nan) for name in ("div", "err", "surv")}
    kinds = {r.get("indicator") for r in rows if r.get("status", "ok") == "ok"} - {None, ""}
    megno = kinds != {"clone"} and any(np.isfinite(r.get("megno", math.nan)) for r in rows)
    for r in rows:
        i, j = int(np.searchsorted(e, r["e"])), int(np.searchsorted(a, r["a"]))
        grids["div"][i, j] = r["log10_divergence"] if not megno else (
            # a run that stopped (escape, unresolved encounter) is unstable: drawn as the
            # colour bar's top, whatever <Y> it had reached
            1e3 if r["survived"] is not True and r["t_stop"] > 0 else r["megno"])
        grids["err"][i, j] = np.log10(max(r["max_rel_energy_error"], 1e-17))   # nan stays nan
        t_end = r.get("t_end") or max(x["t_stop"] for x in rows) or 1.0
        grids["surv"][i, j] = r["t_stop"] / t_end if r["survived"] is not True else 1.0

    def edges(v):
        if v.size == 1:
            return np.array([v[0] - 0.5, v[0] + 0.5])
        m = 0.5 * (v[1:] + v[:-1])
        return np.concatenate([[2 * v[0] - m[0]], m, [2 * v[-1] - m[-1]]])

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4), constrained_layout=True)
    indicator = "MEGNO <Y>" if megno else "log10 shadow-clone divergence"
    panels = (("div", indicator, "magma"),
              ("err", "log10 max relative energy error", "viridis"),
              ("surv", "survived fraction of the run", "RdYlGn"))
    for ax, (key, label, cmap) in zip(axes, panels):
        # grey: stopped before the first sample, or failed
        cmap = matplotlib.colormaps[cmap].with_extremes(bad="0.75")
        limits = ({"vmin": 0.0, "vmax": 1.0} if key == "surv" else
                  {"vmin": 1.5, "vmax": 3 * MEGNO_CHAOTIC} if key == "div" and megno else {})
        pc = ax.pcolormesh(edges(a), edges(e), grids[key], cmap=cmap, shading="flat", **limits)
        bar = fig.colorbar(pc, ax=ax, label=label)
        if key == "div":
            ax.set_title(f"chaos indicator: MEGNO <Y> (REBOUND, HBVM's tangents)\nchaotic: "
                         f"<Y> > {MEGNO_CHAOTIC:g} (cyan contour)" if megno else
                         "chaos indicator: shadow clone 1e-10 apart\n(no threshold)",
                         fontsize=9, pad=14)
        if key == "div" and megno:
            bar.ax.axhline(MEGNO_CHAOTIC, color="c", lw=1.5)
            if a.size > 1 and e.size > 1 and np.isfinite(grids[key]).sum() > 3:
                shown = np.nan_to_num(grids[key], nan=0.0)
                ax.contour(a, e, shown, levels=[MEGNO_CHAOTIC],
                           colors="c", linewidths=1.0)
        for x, name in ((5.2, "J"), (9.55, "S"), (19.2, "U"), (30.1, "N")):
            if edges(a)[0] <= x <= edges(a)[-1]:
                ax.axvline(x, color="w", lw=0.8, ls=":")
                ax.text(x, edges(e)[-1], name, ha="center", va="bottom", fontsize=8)
        ax.set_xlabel("a [AU]")
        ax.set_ylabel("e")
    if title:
        fig.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# -- MD replicas -----------------------------------------------------------------------------
def md_replica(seed: int, *, atoms=None, n_atoms: int = 13, steps: int = 200, dt_fs: float = 2.0,
               temperature_K: float = 300.0, s: int = 2, k: int | None = None) -> dict:
    """One MD replica through :class:`hbvm_md.HBVMDynamics`: the same atoms, velocities drawn
    with ``seed`` (Maxwell-Boltzmann at ``temperature_K``, then zero total momentum).

    Parameters
    ----------
    seed : int
    atoms : ase.Atoms, optional
        The scene, with its calculator (both must pickle); default the polynomial-pair cluster
        of ``n_atoms`` atoms (:func:`hbvm_md.reports.md_comparison.default_cluster`).
    steps, dt_fs, temperature_K, s, k
        As in :func:`hbvm_md.compare_md`.

    Returns
    -------
    dict
        seed and the HBVM row of :func:`hbvm_md.compare_md` (max_rel_dE, drift_slope, ...)
        without its wall time.
    """
    from ..reports.md_comparison import compare_md, default_cluster
    if atoms is None:
        atoms, _ = default_cluster(n_atoms=n_atoms)
    cmp = compare_md(atoms, timesteps_fs=(dt_fs,), methods=(("HBVM", s) if k is None else ("HBVM", s, k),),
                     steps=steps, temperature_K=temperature_K, seed=int(seed), verbose=False)
    row = dict(cmp.rows[0])
    row.pop("wall_time_s")       # the ensemble's record times the member
    return {"seed": int(seed), **row}


def _warm_md() -> None:
    md_replica(0, n_atoms=4, steps=2)


md_replica.warmup = _warm_md
