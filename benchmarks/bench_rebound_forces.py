"""Benchmark (not a test): HBVM on REBOUND's own forces against IAS15, scene by scene.

Scenes beyond plain Newtonian point masses (:mod:`hbvm_md.rebound.forces`): REBOUNDx ``gr``
(velocity dependent) and ``gr_potential`` on a Mercury-like planet over 100 years, a softened
cluster, ``modify_orbits_forces`` migration, a Python drag force, semi-active planetesimals
(``testparticle_type = 1``), a change of ``sim.G`` between runs, and the eccentricity-damping
operator added after ``sim.integrator = "hbvm"``.  Each scene is built and integrated by HBVM
(``sim.integrator = "hbvm"``: the defaults, and where given a second setting) and by IAS15
(defaults), interleaved, from ``--repeat`` runs; the time is the median wall time of building
the scene and integrating it (what the user pays), and the ratio HBVM / IAS15 is taken in this
one process.  Error measures, per scene:

* precession: |advance_HBVM / advance_IAS15 - 1| of the perihelion longitude;
* H: max over 20 output times of |H / H0 - 1|, H of :func:`hbvm_md.rebound.forces.scene_energy`
  (kinetic + softened pair potential of the pairs REBOUND computes + REBOUNDx's potentials),
  median over 5 starts (the scene's own and 4 perturbed: Mercury's omega and anomaly, the
  cluster's and the disk's random draws);
* state: max |x, v (HBVM) - x, v (IAS15)| at the end;
* e: the final eccentricity (damping operator; 0.1 exp(-10) = 4.5e-6 by the damping law).

Writes benchmarks/results/rebound_forces.md.

    python benchmarks/bench_rebound_forces.py [--repeat 3]
"""
from __future__ import annotations

import argparse
import os
import time
import warnings

import numpy as np
import rebound
import reboundx

import hbvm_md  # noqa: F401  (registers "hbvm")
from hbvm_md import HBVMIntegrator
from hbvm_md.rebound.forces import scene_energy
from hbvm_md.reports.machine import machine

HERE = os.path.dirname(os.path.abspath(__file__))
C_AU_YR = 63241.077
_KEEP = []          # REBOUNDx objects live as long as the run (a Simulation takes no attributes)


def _attach(sim, integ):
    if isinstance(integ, dict):
        HBVMIntegrator(sim, **integ)
    else:
        sim.integrator = integ


def mercury(integ, force, seed=0):
    r = np.random.default_rng(seed)
    dw, f = (r.uniform(-1, 1), r.uniform(0, 2 * np.pi)) if seed else (0.0, 0.0)
    sim = rebound.Simulation()
    sim.units = ("yr", "AU", "Msun")
    sim.add(m=1.0)
    sim.add(m=1.66e-7, a=0.387098, e=0.205630, omega=0.5 + dw, inc=0.1, f=f)
    sim.move_to_com()
    rebx = reboundx.Extras(sim)
    f = rebx.load_force(force)
    rebx.add_force(f)
    f.params["c"] = C_AU_YR
    _attach(sim, integ)
    _KEEP.append((rebx, f))
    return sim


def planets(integ, softening=0.0):
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, e=0.1)
    sim.add(m=1e-3, a=1.6, e=0.05, inc=0.1)
    sim.softening = softening
    sim.move_to_com()
    _attach(sim, integ)
    return sim


def cluster(integ, seed=0):
    sim = rebound.Simulation()
    r = np.random.default_rng(3 + seed)
    for _ in range(12):
        x, v = r.normal(size=3), 0.3 * r.normal(size=3)
        sim.add(m=1.0 / 12, x=x[0], y=x[1], z=x[2], vx=v[0], vy=v[1], vz=v[2])
    sim.softening = 0.1
    sim.move_to_com()
    _attach(sim, integ)
    return sim


def migration(integ):
    sim = planets("ias15")
    rebx = reboundx.Extras(sim)
    mof = rebx.load_force("modify_orbits_forces")
    rebx.add_force(mof)
    sim.particles[2].params["tau_a"] = -2000.0
    sim.particles[2].params["tau_e"] = -500.0
    _attach(sim, integ)
    _KEEP.append((rebx, mof))
    return sim


def drag(integ):
    sim = planets("ias15")

    def force(reb_sim):
        ps = sim.particles
        for i in (1, 2):
            ps[i].ax -= 1e-3 * ps[i].vx
            ps[i].ay -= 1e-3 * ps[i].vy
            ps[i].az -= 1e-3 * ps[i].vz

    sim.additional_forces = force
    sim.force_is_velocity_dependent = 1
    _attach(sim, integ)
    return sim


def disk(integ, seed=0):
    sim = planets("ias15")
    r = np.random.default_rng(7 + seed)
    for _ in range(50):
        sim.add(m=1e-7, a=r.uniform(1.25, 1.35), e=r.uniform(0, 0.01), f=r.uniform(0, 6.28))
    sim.N_active = 3
    sim.testparticle_type = 1
    _attach(sim, integ)
    return sim


def damping(integ):
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, e=0.1)
    sim.move_to_com()
    _attach(sim, integ)               # REBOUNDx's usual order: the integrator first
    rebx = reboundx.Extras(sim)
    op = rebx.load_operator("modify_orbits_direct")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rebx.add_operator(op)
    sim.particles[1].params["tau_e"] = -10.0
    _KEEP.append((rebx, op))
    return sim


def run_plain(sim, t_end):
    sim.integrate(t_end)


def run_g_change(sim, t_end):
    sim.integrate(t_end / 2)
    sim.G = 1.2
    sim.integrate(t_end)


#: (name, builder, t_end, run, error measures, HBVM settings besides the defaults: None, a dict
#: or a tuple of dicts)
SCENES = (
    # (k = s for gr: the scene has no H, and HBVM's k > s nodes serve only the energy)
    ("REBOUNDx gr, Mercury, 100 yr", lambda i, seed=0: mercury(i, "gr", seed), 100.0, run_plain,
     ("precession",), (dict(s=8), dict(s=8, k=8))),
    ("REBOUNDx gr_potential, Mercury, 100 yr",
     lambda i, seed=0: mercury(i, "gr_potential", seed), 100.0,
     run_plain, ("precession", "H"), dict(s=8)),
    ("softened cluster, 12 bodies, b = 0.1, t = 10", cluster, 10.0, run_plain, ("H", "state"),
     None),
    ("modify_orbits_forces migration, t = 100", migration, 100.0, run_plain, ("state",), None),
    ("Python drag (additional_forces), t = 100", drag, 100.0, run_plain, ("state",), None),
    ("testparticle_type = 1, 2 planets + 50 planetesimals, t = 20", disk, 20.0, run_plain,
     ("H", "state"), None),
    ("plain 2 planets, sim.G 1 -> 1.2 at t = 50, t = 100", planets, 100.0, run_g_change,
     ("state",), None),
    ("modify_orbits_direct damping operator added after the integrator, t = 100", damping,
     100.0, run_plain, ("e",), None),
)


def one(builder, integ, t_end, run, measures):
    """(wall time, sim, H series) of one build-and-run (H read outside the timed region is not
    possible without splitting the run; the H column is from a separate untimed run)."""
    t0 = time.perf_counter()
    sim = builder(integ)
    run(sim, t_end)
    return time.perf_counter() - t0, sim


#: perturbed starts of the H column (the scene's own start and four perturbed ones)
STARTS = 5


def h_error(builder, integ, t_end):
    """Median over STARTS starts of max over 20 output times of |H / H0 - 1| (a bound on one
    draw at round-off says little: the error is a random walk of ulps)."""
    out = []
    for seed in range(STARTS):
        sim = builder(integ, seed=seed)
        e0 = scene_energy(sim)
        worst = 0.0
        for t in np.linspace(t_end / 20, t_end, 20):
            sim.integrate(t)
            worst = max(worst, abs(scene_energy(sim) / e0 - 1))
        out.append(worst)
    return float(np.median(out))


def _xv(sim):
    xv = np.zeros(6 * sim.N)
    sim.serialize_particle_data(xyzvxvyvz=xv)
    return xv


def _settings(best) -> tuple:
    """A scene's HBVM settings besides the defaults, as a tuple of dicts."""
    return () if not best else (best,) if isinstance(best, dict) else tuple(best)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    load = os.getloadavg()
    for _, builder, _, run, _, best in SCENES:       # compile / load every step once, untimed
        for integ in ("hbvm", "ias15") + _settings(best):
            run(builder(integ), 1e-3)
    rows = []
    for name, builder, t_end, run, measures, best in SCENES:
        variants = ["ias15", "hbvm"] + list(_settings(best))
        times = {str(v): [] for v in variants}
        sims = {}
        for _ in range(args.repeat):
            for v in variants:
                dt, sim = one(builder, v, t_end, run, measures)
                times[str(v)].append(dt)
                sims[str(v)] = sim
        ref = sims["ias15"]
        for v in variants[1:]:
            sim = sims[str(v)]
            errs = []
            for m in measures:
                if m == "precession":
                    p0 = builder(v).particles[1].pomega
                    adv, adv_ref = sim.particles[1].pomega - p0, ref.particles[1].pomega - p0
                    errs.append(f"precession {abs(adv / adv_ref - 1):.1e} "
                                f"({adv_ref * 206264.806:.2f}\" / century by IAS15)")
                elif m == "H":
                    errs.append(f"H: {h_error(builder, v, t_end):.1e} "
                                f"(IAS15 {h_error(builder, 'ias15', t_end):.1e})")
                elif m == "state":
                    errs.append(f"state {np.max(np.abs(_xv(sim) - _xv(ref))):.1e}")
                elif m == "e":
                    errs.append(f"e {sim.particles[1].e:.2e} (IAS15 {ref.particles[1].e:.2e})")
            label = "defaults" if v == "hbvm" else ", ".join(f"{k}={x}" for k, x in v.items())
            ratio = np.median(times[str(v)]) / np.median(times["ias15"])
            rows.append(f"| {name} | {label} | {ratio:.2f} | {'; '.join(errs)} |")
            print(rows[-1], flush=True)
    out = ["# HBVM on REBOUND's own forces vs IAS15", "",
           f"{machine()}, one process; load average at the start {load[0]:.1f}, {load[1]:.1f}, "
           f"{load[2]:.1f} (1, 5, 15 min). Generated by "
           f"`python benchmarks/bench_rebound_forces.py --repeat {args.repeat}` on "
           f"{time.strftime('%Y-%m-%d')}. Time: median over {args.repeat} interleaved runs of "
           "building the scene and integrating it, HBVM / IAS15 (both at their defaults unless "
           "the setting says otherwise). H: median over 5 starts. Every scene here runs on REBOUND's accelerations at "
           "HBVM's stages (separable form; gr, the migration and the Python drag with the stage "
           "velocities), except the change of G and the damping operator (plain "
           "gravity: the compiled N-body kernel).", "",
           "| scene | HBVM | time HBVM / IAS15 | errors (HBVM, against IAS15) |",
           "|---|---|---|---|", *rows, ""]
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    path = os.path.join(HERE, "results", "rebound_forces.md")
    with open(path, "w") as fh:
        fh.write("\n".join(out))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
