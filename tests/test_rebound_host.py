"""HBVM registered with REBOUND ("hbvm"): REBOUND steps, saves, archives, copies and resolves
collisions; the patterns of REBOUND's own notebooks (Simulationarchive, restarting, collisions,
test particles) with HBVM swapped in."""
import math
import os
import pickle
import re
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
import rebound

import hbvm_md
from hbvm_md import HBVMIntegrator
from integrators import EQUIP, HBVM, StepSizeError
from integrators.engine import DEFAULT_EPSILON
from integrators.kchoice import adaptive_k
from systems import outer_solar_system

ROOT = Path(__file__).resolve().parents[1]


def _xv(sim):
    return np.array([[p.x, p.y, p.z, p.vx, p.vy, p.vz] for p in sim.particles])


def _outer(kind):
    sim = outer_solar_system().to_rebound()
    if kind == "fixed":
        HBVMIntegrator(sim, s=6, k=8, dt=100.0)
    elif kind == "equip-fixed":
        HBVMIntegrator(sim, s=4, k=6, dt=100.0, method="equip")
    elif kind == "equip-adaptive":
        HBVMIntegrator(sim, method="equip")
    else:
        sim.integrator = "hbvm"          # HBVM's defaults: adaptive steps
        sim.dt = 50.0
    return sim


def _max_energy_error(sim, t_end=1e5, n=200):
    E0, err = sim.energy(), 0.0
    for t in np.linspace(0, t_end, n + 1)[1:]:
        sim.integrate(t)
        err = max(err, abs(sim.energy() / E0 - 1))
    return err


# -- registration ------------------------------------------------------------------------------
def test_registered_once_with_defaults_as_fields():
    hbvm_md.rebound.register()                  # a second call does nothing (REBOUND would hang)
    sim = outer_solar_system().to_rebound()
    sim.integrator = "hbvm"
    cfg = sim.integrator
    assert cfg == "hbvm" and (cfg.s, str(cfg.nodes), cfg.adaptive) == (6, "gauss", 1)
    assert cfg.k == adaptive_k(6, DEFAULT_EPSILON) and cfg.epsilon == DEFAULT_EPSILON
    assert cfg.energy_tol == 1e-10 and cfg.max_iter == 60
    assert "HBVM(k, s)" in cfg.__doc__ and "Degree of the method" in cfg.__doc__
    cfg.nodes = "lobatto"                       # REBOUND's enum mapping of the field
    assert HBVMIntegrator.of(sim).method.nodes == "lobatto"
    d = HBVMIntegrator(sim, s=4, k=5, dt=10.0)
    assert sim.integrator == "hbvm" and d.method.k == 5 and not d.adaptive


def test_sim_integrator_hbvm_conserves_energy_like_hbvmintegrator():
    """``sim.integrator = "hbvm"`` on the outer solar system over 1e5 days (200 outputs):
    round-off energy like HBVMIntegrator(sim), and IAS15's positions to 1e-10 AU."""
    a = outer_solar_system().to_rebound()
    a.integrator = "hbvm"
    b = outer_solar_system().to_rebound()
    HBVMIntegrator(b)
    ref = outer_solar_system().to_rebound()
    ref.integrate(1e5)
    ea, eb = _max_energy_error(a), _max_energy_error(b)
    assert ea <= 1e-14 and eb <= 1e-14
    assert np.max(np.abs(_xv(a)[:, :3] - _xv(ref)[:, :3])) < 1e-10
    assert HBVMIntegrator.of(a).nsteps == a.steps_done          # no step failed
    assert HBVMIntegrator.of(a).adaptive and a.dt != 50.0


# -- REBOUND's Simulationarchive notebook ----------------------------------------------------------
@pytest.mark.parametrize("kind", ["fixed", "adaptive", "equip-fixed", "equip-adaptive"])
def test_simulationarchive_three_modes_and_restart_pattern(tmp_path, kind):
    """An archive written during an HBVM run: every snapshot is the run's state at its time bit
    for bit; "close" and "exact" are the uninterrupted run to the same time bit for bit; the
    notebook's restart (``sim = rebound.Simulation(archive)``, save again, integrate) continues
    like the uninterrupted run, bit for bit."""
    fn = str(tmp_path / "archive.bin")
    sim = _outer(kind)
    states = {}
    sim.heartbeat = lambda p: states.__setitem__(p.contents.t, _xv(sim))
    sim.save_to_file(fn, interval=1000.0, delete_file=True)
    sim.integrate(1e4)
    sa = rebound.Simulationarchive(fn)
    assert len(sa) >= 10
    for i in (1, len(sa) // 2, len(sa) - 1):
        snap = sa[i]
        assert snap.integrator == "hbvm" and np.array_equal(_xv(snap), states[snap.t])
    for t, mode, eft in ((4321.0, "exact", 1), (4321.0, "close", 0)):
        got = sa.getSimulation(t, mode=mode)
        ref = _outer(kind)
        ref.integrate(t, exact_finish_time=eft)
        assert got.t == ref.t and np.array_equal(_xv(got), _xv(ref)), mode
    got = sa.getSimulation(4321.0, mode="snapshot")
    assert got.t <= 4321.0 and np.array_equal(_xv(got), states[got.t])
    restart = rebound.Simulation(fn)
    assert str(restart.integrator.method) == ("equip" if "equip" in kind else "hbvm")
    assert HBVMIntegrator.of(restart).method == HBVMIntegrator.of(sim).method
    restart.save_to_file(fn, interval=1000.0)
    restart.integrate(2e4)
    sim.integrate(2e4)
    assert restart.t == sim.t and np.array_equal(_xv(restart), _xv(sim))
    assert len(rebound.Simulationarchive(fn)) >= 20
    assert sorted(p.name for p in tmp_path.iterdir()) == ["archive.bin"]


@pytest.mark.parametrize("kind", ["fixed", "adaptive", "equip-fixed", "equip-adaptive"])
def test_copy_and_pickle_continue_bit_for_bit(kind):
    sim = _outer(kind)
    sim.integrate(2345.0)
    twin, thawed = sim.copy(), pickle.loads(pickle.dumps(sim))
    for s in (sim, twin, thawed):
        s.integrate(2e4)
    assert np.array_equal(_xv(twin), _xv(sim)) and np.array_equal(_xv(thawed), _xv(sim))
    assert HBVMIntegrator.of(twin).resyncs == 1


def test_fresh_process_continues_a_pickled_run_bit_for_bit(tmp_path):
    """A spawned process that imports hbvm_md (a dask worker does) continues a pickled run."""
    sim = _outer("adaptive")
    sim.integrate(3000.0)
    path = tmp_path / "sim.pkl"
    path.write_bytes(pickle.dumps(sim))
    code = textwrap.dedent(f'''
        import pickle, hbvm_md
        sim = pickle.loads(open({str(path)!r}, "rb").read())
        sim.integrate(1e4)
        print(repr([p.x for p in sim.particles]))
    ''')
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    sim.integrate(1e4)
    assert eval(out.stdout.strip()) == [p.x for p in sim.particles]


def test_file_opened_without_hbvm_md_is_refused_not_frozen(tmp_path):
    """REBOUND's own refusal where hbvm_md was not imported: a warning at load and
    "Integrator not found." at the first integrate (never particles that do not move)."""
    fn = str(tmp_path / "run.bin")
    sim = _outer("fixed")
    sim.integrate(500.0)
    sim.save_to_file(fn, delete_file=True)
    code = textwrap.dedent(f'''
        import warnings, rebound
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            sim = rebound.Simulation({fn!r})
        print("WARN", [str(x.message) for x in w])
        try:
            sim.integrate(1000.0)
        except RuntimeError as e:
            print("ERROR", e)
    ''')
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "corrupted" in out.stdout and "ERROR Integrator not found." in out.stdout


# -- collisions (REBOUND's collisions notebook) ---------------------------------------------------
def _colliding(resolve):
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, r=0.05)
    sim.add(m=2e-3, a=1.2, e=0.3, f=2.0, r=0.05)       # crosses the first planet's orbit
    sim.collision = "direct"
    sim.collision_resolve = resolve
    sim.integrator = "hbvm"
    sim.dt = 0.01
    return sim


def _momentum(sim):
    return sum(np.array([p.m * p.vx, p.m * p.vy, p.m * p.vz]) for p in sim.particles)


def test_colliding_planets_merge_with_mass_and_momentum_conserved():
    sim = _colliding("merge")
    M0, P0 = sum(p.m for p in sim.particles), _momentum(sim)
    sim.integrate(100.0)
    assert sim.N == 2 and sum(p.m for p in sim.particles) == M0
    assert np.max(np.abs(_momentum(sim) - P0)) < 1e-17
    assert HBVMIntegrator.of(sim).resyncs == 2        # read afresh once after the merger
    assert sim.t == 100.0


def test_python_resolve_halt_and_hardsphere():
    calls = []

    def resolve(simp, collision):
        calls.append((simp.contents.t, collision.p1, collision.p2))
        return 2                                      # remove p2
    sim = _colliding(resolve)
    sim.integrate(100.0)
    assert calls and sim.N == 2 and sim.t == 100.0
    halt = _colliding("halt")
    with pytest.raises(rebound.Collision):
        halt.integrate(100.0)
    assert halt.t < 100.0 and halt.N == 3
    hard = _colliding("hardsphere")
    E0 = hard.energy()
    hard.integrate(30.0)
    assert hard.N == 3 and abs(hard.energy() / E0 - 1) < 1e-3


# -- test particles, move_to_com, units (REBOUND's test particles notebook) -----------------------
def test_test_particles_move_to_com_and_units_as_with_ias15():
    def scene(integrator):
        sim = rebound.Simulation()
        sim.units = ("yr", "AU", "Msun")
        sim.add(m=1.0)
        sim.add(m=9.5e-4, a=5.2, e=0.05)
        sim.add(m=2.9e-4, a=9.5, e=0.05, inc=0.02)
        sim.N_active = sim.N
        for i in range(5):
            sim.add(a=2.5 + 0.3 * i, e=0.1, f=i)       # massless test particles
        sim.move_to_com()
        sim.integrator = integrator
        sim.dt = 0.05
        return sim
    a, b = scene("hbvm"), scene("ias15")
    for s in (a, b):
        s.integrate(30.0)
        s.move_to_com()
        s.remove(5)
        s.integrate(60.0)
    assert a.N == b.N == 7 and np.max(np.abs(_xv(a)[:, :3] - _xv(b)[:, :3])) < 1e-9
    assert HBVMIntegrator.of(a).resyncs >= 2         # the first step, the removal


def test_a_variation_of_a_particle_past_the_last_is_refused_at_the_first_step():
    sim = outer_solar_system().to_rebound()
    before = _xv(sim)
    sim.integrator = "hbvm"
    sim.add_variation(testparticle=sim.N)      # (REBOUND accepts an index past the last)
    with pytest.raises(ValueError, match=rf"add_variation\(testparticle={sim.N}\)\) but the "
                                         rf"simulation has {sim.N} particles; add the variation "
                                         "after the particle"):
        sim.integrate(100.0)
    assert sim.t == 0.0 and np.array_equal(_xv(sim), before)


def test_warnings_point_at_the_users_line_and_nothing_is_printed(capsys):
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=0.0, a=1.0, e=0.3)
    sim.N_active = 1
    HBVMIntegrator(sim, s=6, dt=2 * math.pi / 50)
    with pytest.warns(RuntimeWarning, match="no energy") as record:
        sim.integrate(1.0)
    assert record[0].filename == __file__
    assert capsys.readouterr().out == ""


def test_no_hard_coded_rebound_offset_outside_the_layout_module():
    """REBOUND's offsets are read from its ctypes structures in hbvm_md/rebound/layout.py only:
    no other module adds a number to an address, or names the old offset constants."""
    files = [p for d in ("hbvm_md", "integrators", "systems") for p in (ROOT / d).rglob("*.py")]
    layout = ROOT / "hbvm_md" / "rebound" / "layout.py"
    pattern = re.compile(r"from_address\([^)]*\+\s*\d|\b(T_AT|G_AT|STATUS_BYTES|EXTRAS_BYTES|"
                         r"PARTICLE_DOUBLES|SIM_HEAD)\b|\.offset\s*==\s*\d")
    bad = [f"{p.relative_to(ROOT)}:{i + 1}" for p in files if p != layout
           for i, line in enumerate(p.read_text().splitlines()) if pattern.search(line)]
    assert bad == []
    text = layout.read_text()
    assert "offset" in text and not re.search(r"offset\s*[=!]=\s*\d", text)


@pytest.mark.parametrize("field, value, match", [
    ("epsilon", 2.0, r"`epsilon` must be a number in \(0, 1\)"),
    ("max_iter", 0, r"`sim.integrator.max_iter` must be a positive integer \(got 0\)"),
    ("energy_tol", -1.0, r"`sim.integrator.energy_tol` must be a finite number >= 0"),
    ("k", 3, r"`k` must be >= `s`"),
    ("method", 7, r"`sim.integrator.method` must be one of \('hbvm', 'equip'\) \(got 7\)"),
])
def test_settings_changed_in_sim_integrator_are_checked(field, value, match):
    sim = outer_solar_system().to_rebound()
    sim.integrator = "hbvm"
    sim.integrate(1000.0)
    before, t = _xv(sim), sim.t
    setattr(sim.integrator, field, value)
    with pytest.raises(ValueError, match=match):
        sim.integrate(2000.0)
    assert sim.t == t and np.array_equal(_xv(sim), before)


def test_particles_changed_inside_a_run_by_callbacks_are_honoured():
    """A heartbeat that adds a planet and a pre-timestep kick change the particles between two
    steps of one sim.integrate: HBVM reads them afresh, and the run is the one where the same
    changes are made between two integrate calls, bit for bit."""
    def planet(s):
        s.add(m=3e-6, x=0.0, y=40.0, z=0.0, vx=-0.00272, vy=0.0, vz=0.0)

    def beat(simp):
        s = simp.contents
        if s.t >= 5000.0 and s.N == 6:
            planet(s)

    def kick(simp):
        s = simp.contents
        if s.t >= 1000.0 and not kicked:
            kicked.append(s.t)
            s.particles[1].vx *= 1.0001
    kicked = []
    a, b = (outer_solar_system().to_rebound() for _ in range(2))
    for s in (a, b):
        HBVMIntegrator(s, s=6, k=8, dt=100.0)
    a.heartbeat, a.pre_timestep_modifications = beat, kick
    a.integrate(8000.0)
    b.integrate(1000.0)
    b.particles[1].vx *= 1.0001
    b.integrate(5000.0)
    planet(b)
    b.integrate(8000.0)
    assert kicked == [1000.0] and a.N == b.N == 7 and np.array_equal(_xv(a), _xv(b))
    assert HBVMIntegrator.of(a).resyncs == HBVMIntegrator.of(b).resyncs == 3


def test_adaptive_step_size_error_leaves_the_state():
    """An adaptive step that cannot be resolved above min_dt raises StepSizeError naming it,
    with the particles, t and dt as before (the first step, 87 d, is refused)."""
    sim = outer_solar_system().to_rebound()
    HBVMIntegrator(sim, epsilon=1e-24, min_dt=80.0)
    before, dt = _xv(sim), sim.dt
    with pytest.raises(StepSizeError, match="min_dt=80"):
        sim.integrate(1e4)
    assert sim.t == 0.0 and sim.dt == dt and np.array_equal(_xv(sim), before)


def test_a_stop_from_a_heartbeat_and_arguments_are_rebounds():
    """sim.stop() in a heartbeat ends the run without an exception, at a whole step, as with
    IAS15; integrate's arguments are converted and refused as REBOUND's own method does."""
    sim = _outer("fixed")
    stop_at = [1000.0]
    sim.heartbeat = lambda p: p.contents.t >= stop_at[0] and sim.stop()
    sim.integrate(5000.0)
    assert sim.t == 1000.0
    ref = _outer("fixed")
    ref.integrate(1000.0)
    assert np.array_equal(_xv(sim), _xv(ref))
    stop_at[0] = math.inf
    sim.integrate(2000)                                # an int tmax, as REBOUND takes it
    with pytest.raises(TypeError):
        sim.integrate(3000.0, exact_finish_time="yes")
    with pytest.raises(TypeError):
        sim.integrate("4000")
    assert sim.t == 2000.0


# -- EQUIP through REBOUND (issue 26) ---------------------------------------------------------------
def _outer_perturbed(r):
    """The outer solar system with the planets' positions scaled by 1 + r 1e-13."""
    nb = outer_solar_system()
    sim = nb.to_rebound()
    for p in sim.particles[1:]:
        p.x, p.y, p.z = (c * (1 + r * 1e-13) for c in (p.x, p.y, p.z))
    sim.move_to_com()
    return sim


def _invariant_errors(sim, t_end, n=100):
    """Largest relative change of the energy and of |L - L0| / |L0| over n outputs."""
    E0, L0 = sim.energy(), np.array(sim.angular_momentum())
    e = l = 0.0
    for t in np.linspace(0.0, t_end, n + 1)[1:]:
        sim.integrate(t)
        e = max(e, abs(sim.energy() / E0 - 1))
        l = max(l, np.linalg.norm(np.array(sim.angular_momentum()) - L0) / np.linalg.norm(L0))
    return e, l


def test_equip_keeps_energy_and_angular_momentum_where_hbvm_loses_it():
    """Outer solar system, s = 2, k = 8, dt = 50 d over 1e5 days (medians of 3 starts): HBVM(8,
    2) keeps the energy and loses L at its order (1.3e-8); EQUIP(8, 2) keeps both at round-off,
    and its adaptive defaults too."""
    runs = {}
    for r in range(3):
        for name, kw in (("hbvm", dict(s=2, k=8, dt=50.0)), ("equip", dict(s=2, k=8, dt=50.0)),
                         ("equip-defaults", {})):
            sim = _outer_perturbed(r)
            d = HBVMIntegrator(sim, method=name.split("-")[0], **kw)
            runs.setdefault(name, []).append(_invariant_errors(sim, 1e5))
            assert d.nsteps == sim.steps_done                 # no step failed
    med = {k: np.median(np.array(v), axis=0) for k, v in runs.items()}
    assert med["hbvm"][0] <= 1e-14 and med["hbvm"][1] > 1e-10
    for name in ("equip", "equip-defaults"):
        assert med[name][0] <= 1e-14 and med[name][1] <= 1e-14, (name, med[name])


def test_equip_is_a_setting_saved_with_the_run_and_k_is_hbvms():
    """``method="equip"`` selects EQUIP(k, s) with the k HBVM would take (the energy
    condition is HBVM's line integral): adaptive_k for adaptive steps, choose_k's for a fixed
    step; ``sim.integrator.method`` shows it, and switching it between runs switches the
    method (the run continues from the same particles, L kept from then on)."""
    sim = outer_solar_system().to_rebound()
    d = HBVMIntegrator(sim, method="equip")
    # EQUIP's own adaptive defaults (s = 8, epsilon = 1e-17 since issue 58's controller, 1e-4
    # before: integrators.equip; they were HBVM's, s = 6 and 1e-3, before issue 38)
    assert d.method == EQUIP(adaptive_k(8, 1e-17), 8) == EQUIP(9, 8)
    assert str(sim.integrator.method) == "equip"
    a, b = outer_solar_system().to_rebound(), outer_solar_system().to_rebound()
    ka = HBVMIntegrator(a, s=4, dt=200.0).method
    kb = HBVMIntegrator(b, s=4, dt=200.0, method="equip").method
    assert isinstance(ka, HBVM) and kb == EQUIP(ka.k, 4)
    sim = outer_solar_system().to_rebound()
    HBVMIntegrator(sim, s=2, k=8, dt=50.0)
    sim.integrate(2e4)
    L0 = np.array(sim.angular_momentum())
    sim.integrator.method = "equip"
    sim.integrate(6e4)
    assert HBVMIntegrator.of(sim).method == EQUIP(8, 2)
    assert np.linalg.norm(np.array(sim.angular_momentum()) - L0) / np.linalg.norm(L0) < 1e-14


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(method="gauss"), ValueError,
     r"`method` must be one of \('hbvm', 'equip'\) \(got method='gauss'\)"),
    (dict(method=None), ValueError, r"`method` must be one of .* \(got method=None\)"),
    (dict(method="equip", nodes="lobatto"), ValueError,
     r"`nodes` must be 'gauss' with method='equip' \(got nodes='lobatto'\)"),
    (dict(method="equip", s=1, k=2), ValueError, r"`s` must be >= 2 for EQUIP \(got s=1\)"),
    (dict(method="equip", s=4, k=3), ValueError, r"`k` must be >= `s` \(got k=3, s=4\)"),
])
def test_bad_method_is_refused_naming_it_and_leaves_the_simulation(kwargs, error, match):
    sim = outer_solar_system().to_rebound()
    with pytest.raises(error, match=match):
        HBVMIntegrator(sim, **kwargs)
    assert str(sim.integrator) == "ias15"
    sim.integrator = "hbvm"
    with pytest.raises(AttributeError, match="hbvm, equip"):      # REBOUND's enum refusal
        sim.integrator.method = "gauss"


def test_equip_with_test_particles_conserves_the_sources_energy():
    """Test particles (N_active) are outside H: EQUIP's energy condition leaves them out (with
    them alpha conserved H plus their own energies, and the sources' energy drifted to 1.9e-11
    over 1e5 days); they still move as under HBVM."""
    sims = []
    for method in ("equip", "hbvm"):
        sim = outer_solar_system().to_rebound()
        sim.N_active = sim.N
        sim.add(m=0.0, a=7.0, e=0.1, primary=sim.particles[0])
        sim.add(m=0.0, a=12.0, e=0.05, inc=0.1, primary=sim.particles[0])
        HBVMIntegrator(sim, s=4, k=6, dt=100.0, method=method)
        sims.append(sim)
    sim, ref = sims
    e, l = _invariant_errors(sim, 1e5, n=50)
    ref.integrate(1e5)
    assert e <= 1e-14 and l <= 1e-14, (e, l)
    assert np.max(np.abs(_xv(sim)[-2:, :3] - _xv(ref)[-2:, :3])) < 1e-8


def test_the_registered_c_functions_name_the_layout_they_were_compiled_for():
    # numba caches cabi's functions with layout's slot numbers compiled in, keyed on cabi.py
    # alone: a layout change must change cabi.LAYOUT_DIGEST too (else they compile in memory)
    from hbvm_md.rebound import cabi, layout
    digest = layout.DIGEST          # (layout.py and the C header it reads the slots from)
    assert cabi.LAYOUT_DIGEST == digest, f"set LAYOUT_DIGEST = {digest!r} in hbvm_md/rebound/cabi.py"
    assert cabi._CACHE
    # (so do the compiled helpers of particles.py and masses.py, cached on their own files)
    from hbvm_md.rebound import masses, particles
    for mod in (particles, masses):
        assert mod.LAYOUT_DIGEST == digest, f"set LAYOUT_DIGEST = {digest!r} in {mod.__file__}"


def test_a_file_saved_before_the_step_control_changed_keeps_its_accuracy(tmp_path):
    """A simulation saved by hbvm-md before 2026-12-08 (no ``controller`` field: it loads as
    0) holds an epsilon of the former step control: its default 1e-3 becomes today's default
    with a warning (the continued run keeps round-off energy), another value is kept with a
    warning saying what to set; a file of today's version loads silently."""
    from hbvm_md.rebound import layout as L
    from hbvm_md.rebound.host import _slots

    def saved(eps, old):
        sim = rebound.Simulation()
        sim.add(m=1.0)
        sim.add(m=1e-3, a=1.0, e=0.3)
        sim.move_to_com()
        sim.integrator = "hbvm"
        sim.integrate(2.0)
        st, sd = _slots(sim.integrator.state)
        sd[L.SL_EPSILON] = eps
        if old:
            st[L.SL_CONTROL] = 0
        path = tmp_path / f"old{eps}{old}.bin"
        sim.save_to_file(str(path))
        return path

    for eps, old, want in ((1e-3, True, DEFAULT_EPSILON), (1e-6, True, 1e-6),
                           (1e-3, False, 1e-3), (DEFAULT_EPSILON, False, DEFAULT_EPSILON)):
        sim = rebound.Simulation(str(saved(eps, old)))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            sim.integrate(4.0)
        ours = [w for w in caught if "before 2026-12-08" in str(w.message)]
        assert len(ours) == (1 if old else 0), (eps, old)
        assert sim.integrator.epsilon == want
        if old and eps != 1e-3:
            assert "Set sim.integrator.epsilon again" in str(ours[0].message)
        assert sim.integrator.controller == 1


def test_rebound_is_changed_only_at_the_first_hbvm_simulation():
    """Importing hbvm_md and REBOUND registers "hbvm" and changes nothing else: REBOUND's
    Simulation.integrate stays its own and REBOUNDx is not imported until a simulation selects
    HBVM (its state's create), and then failed steps raise HBVM's own exceptions."""
    code = textwrap.dedent("""
        import sys, rebound, hbvm_md
        before = (getattr(rebound.Simulation.integrate, "_hbvm_md", False),
                  "reboundx" in sys.modules)
        sim = rebound.Simulation(); sim.add(m=1.0); sim.add(m=1e-3, a=1.0)
        sim.integrator = "hbvm"
        after = getattr(rebound.Simulation.integrate, "_hbvm_md", False)
        sim.dt = 0.0
        try:
            sim.integrate(1.0)
        except ValueError as err:
            raised = "sim.dt" in str(err)
        print(before, after, raised)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, env=dict(os.environ, PYTHONPATH=str(Path(__file__).parents[1])))
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["(False,", "False)", "True", "True"]
