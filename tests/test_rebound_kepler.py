"""``sim.integrator.kepler = 1`` / ``HBVMIntegrator(sim, kepler=True)``: HBVM composed with
the Keplerian flows in REBOUND (issue 48, item 4), through the engine's FlowComposed (the same
state bit for bit), against IAS15, restarted from copies and archives, and its refusals."""
import numpy as np
import pytest
import rebound

from hbvm_md import HBVMIntegrator
from hbvm_md.rebound import layout as L
from hbvm_md.rebound.memory import doubles
from integrators import HBVM, StepError, integrate
from systems import NBody, outer_solar_system
from systems.flow_composed import FlowComposed

H = 500.0          # days: the composed method's step of benchmarks/results/kepler_composed.md


def _xv(sim):
    N = sim.N
    xv = np.zeros(6 * N)
    sim.serialize_particle_data(xyzvxvyvz=xv)
    return xv.reshape(N, 6)


def _state(sim, m):
    """The composed state y (2m,) HBVM keeps in REBOUND (hbvm_md.rebound.kepler_glue)."""
    st, _ = HBVMIntegrator.of(sim)._slots()
    return doubles(int(st[L.SL_Y]), 2 * m).copy()


def _outer(**kw):
    sim = outer_solar_system().to_rebound()
    HBVMIntegrator(sim, kepler=True, dt=H, **kw)
    return sim


def test_outer_solar_system_is_the_engines_run_and_ias15s():
    sim = outer_solar_system().to_rebound()
    nb = NBody.from_rebound(sim)
    E0 = sim.energy()
    hb = HBVMIntegrator(sim, kepler=True, dt=H)
    assert repr(hb).startswith("HBVMIntegrator(HBVM(8, 6), kepler=True")
    assert "kepler=1" in repr(sim.integrator) and sim.integrator.kepler == 1
    n = 40
    sim.steps(n)
    # one implementation: the engine's FlowComposed run by integrators.integrate, bit for bit
    fc = FlowComposed.from_nbody(nb, H)
    r = integrate(HBVM(8, 6), fc, fc.extend(nb.initial_state()), H, n, sample_every=n,
                  form="full")
    assert np.array_equal(_state(sim, fc.dim), r.y[-1])
    phys = fc.physical(r.y[-1], H * n)[:3 * sim.N].reshape(sim.N, 3)
    assert np.abs(_xv(sim)[:, :3] - phys).max() < 1e-13
    # against IAS15 (55 years): positions and energy
    ref = outer_solar_system().to_rebound()
    ref.integrator = "ias15"
    ref.integrate(sim.t)
    assert np.abs(_xv(sim)[:, :3] - _xv(ref)[:, :3]).max() < 1e-11
    assert abs(sim.energy() / E0 - 1) < 1e-14
    assert hb.nsteps == n and sim.t == H * n


def _with_test_particles(sim):
    sim.add(m=0.0, a=7.0, e=0.1, inc=0.05, primary=sim.particles[0])
    sim.add(m=0.0, a=40.0, e=0.2, inc=0.1, Omega=1.0, primary=sim.particles[0])
    sim.N_active = 6
    return sim


def test_test_particles_follow_and_pull_nothing():
    sim = _with_test_particles(outer_solar_system().to_rebound())
    nb = NBody.from_rebound(sim)
    HBVMIntegrator(sim, kepler=True, dt=H / 2)
    n = 80
    sim.steps(n)
    fc = FlowComposed.from_nbody(nb, H / 2)
    r = integrate(HBVM(8, 6), fc, fc.extend(nb.initial_state()), H / 2, n, sample_every=n,
                  form="full")
    assert np.array_equal(_state(sim, fc.dim), r.y[-1])
    ref = _with_test_particles(outer_solar_system().to_rebound())
    ref.integrator = "ias15"
    ref.integrate(sim.t)
    assert np.abs(_xv(sim)[:, :3] - _xv(ref)[:, :3]).max() < 1e-12
    # the gravitating bodies' run is the one without test particles
    alone = outer_solar_system().to_rebound()
    HBVMIntegrator(alone, kepler=True, dt=H / 2)
    alone.steps(n)
    assert np.array_equal(_xv(alone), _xv(sim)[:6])
    # a test particle sent through Jupiter is refused, naming it
    sim = _with_test_particles(outer_solar_system().to_rebound())
    jup = sim.particles[1]
    sim.particles[7].xyz = (jup.x + 0.01, jup.y, jup.z)
    sim.particles[7].vxyz = jup.vxyz
    HBVMIntegrator(sim, kepler=True, dt=H / 2)
    with pytest.raises(StepError, match="particle 7"):
        sim.steps(4)
    assert sim.t == 0.0


def test_a_star_with_test_particles_only_is_exact():
    # REBOUND's test_whfast_testparticles scene: every orbit is Keplerian, so the composed
    # step is the exact flow; N_active set or not is the same model
    def scene():
        sim = rebound.Simulation()
        sim.add(m=1)
        for i in range(5):
            sim.add(m=0, P=1, e=0.1, f=i)
        return sim
    a, b = scene(), scene()
    b.N_active = 1
    for sim in (a, b):
        HBVMIntegrator(sim, kepler=True, dt=0.1)
        sim.integrate(1.0)
    assert np.array_equal(_xv(a), _xv(b))
    # one period later, back where it started (REBOUND's bound for WHFast here: 2e-14)
    assert np.abs(_xv(a) - _xv(scene())).max() < 2e-14


def test_the_field_is_the_same_method():
    a = _outer(k=8, s=6)
    b = outer_solar_system().to_rebound()
    b.integrator = "hbvm"
    b.integrator.kepler = 1
    b.integrator.epsilon = 0            # fixed steps of sim.dt (IAS15's idiom)
    b.dt = H
    a.steps(8)
    b.steps(8)
    assert np.array_equal(_xv(a), _xv(b))


def test_copy_and_archive_continue_bit_for_bit(tmp_path):
    sim = _outer()
    sim.integrate(10 * H)
    path = str(tmp_path / "kepler.bin")
    sim.save_to_file(path, delete_file=True)
    copy = sim.copy()
    sim.integrate(20 * H)
    copy.integrate(20 * H)
    loaded = rebound.Simulation(path)
    assert loaded.integrator.kepler == 1
    loaded.integrate(20 * H)
    arch = rebound.Simulationarchive(path)[-1]
    arch.integrate(20 * H)
    for other in (copy, loaded, arch):
        assert np.array_equal(_xv(other), _xv(sim))
        assert HBVMIntegrator.of(other).resyncs == HBVMIntegrator.of(sim).resyncs


def test_moved_particles_start_afresh_and_switching_back_is_plain_hbvm():
    sim = _outer()
    sim.steps(4)
    sim.particles[1].x += 1e-3            # a user's change between runs: read afresh
    sim.steps(2)
    assert HBVMIntegrator.of(sim).resyncs == 2 and np.all(np.isfinite(_xv(sim)))
    sim.integrator.kepler = 0             # plain HBVM from here (its own fixed step)
    sim.steps(2)
    assert HBVMIntegrator.of(sim).method == HBVM(8, 6) and sim.t == 8 * H


def test_refusals_name_the_way_out():
    sim = outer_solar_system().to_rebound()
    with pytest.raises(ValueError, match="fixed steps only.*dt="):
        HBVMIntegrator(sim, kepler=True, adaptive=True)
    with pytest.raises(ValueError, match="method='hbvm' or kepler=False"):
        HBVMIntegrator(sim, kepler=True, dt=H, method="equip")
    with pytest.raises(TypeError, match="`kepler`"):
        HBVMIntegrator(sim, kepler="yes", dt=H)
    # REBOUND's default sim.dt (0.001 days here) without dt=: a warning naming dt=
    with pytest.warns(RuntimeWarning, match=r"for long steps.*pass dt="):
        HBVMIntegrator(sim.copy(), kepler=True)
    assert sim.integrator == "ias15"                     # nothing changed by a refused attach
    # the field with HBVM's default adaptive steps
    sim.integrator = "hbvm"
    sim.integrator.kepler = 1
    with pytest.raises(ValueError, match=r"fixed steps of sim.dt only.*epsilon = 0"):
        sim.integrate(1000.0)
    # a force beyond Newtonian gravity would be left out of the perturbation
    sim = outer_solar_system().to_rebound()
    sim.additional_forces = lambda reb_sim: None
    with pytest.raises(ValueError, match=r"additional_forces.*kepler = 0"):
        HBVMIntegrator(sim, kepler=True, dt=H)
    # a body not bound to particle 0, a central body that does not dominate
    sim = outer_solar_system().to_rebound()
    sim.particles[4].vx *= 3.0
    with pytest.raises(ValueError, match=r"particle 4 is not .*kepler = 0"):
        HBVMIntegrator(sim, kepler=True, dt=H)
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1.0, a=1.0)
    with pytest.raises(ValueError, match="dominant mass"):
        HBVMIntegrator(sim, kepler=True, dt=0.01)
    # a massive body past N_active (REBOUND's bodies that pull nothing) is not modelled
    sim = outer_solar_system().to_rebound()
    sim.N_active = 4
    with pytest.raises(ValueError, match=r"particle 4 is past N_active=4.*kepler = 0"):
        HBVMIntegrator(sim, kepler=True, dt=H)


def test_close_encounter_is_refused_before_it_is_stepped():
    # systems.flow_composed's test scene: two planets on crossing orbits meet near t ~ pi/2
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, x=1.0, vy=1.0)
    sim.add(m=1e-3, x=-1.02, vy=1 / np.sqrt(1.02))
    HBVMIntegrator(sim, kepler=True, dt=0.1)
    with pytest.raises(StepError, match=r"does not resolve the motion of (particle|the pert)"
                       r".*kepler = 0 with adaptive steps") as err:
        sim.integrate(4.0)
    assert 0.9 < sim.t < 1.6                      # at the encounter, not before
    before = _xv(sim)
    assert err.value.encounter["distance"] < 0.2
    with pytest.raises(StepError):
        sim.integrate(4.0)
    assert np.array_equal(_xv(sim), before)       # a refused step changes nothing


def test_collisions_merge_and_the_run_goes_on():
    # the encounter scene with radii: the planets merge (REBOUND's collision search after the
    # step), the particles change, and the next step starts afresh from them
    def scene(integrator):
        sim = rebound.Simulation()
        sim.add(m=1.0, r=0.005)
        sim.add(m=1e-3, x=1.0, vy=1.0, r=0.05)
        sim.add(m=1e-3, x=-1.02, vy=1 / np.sqrt(1.02), r=0.05)
        sim.collision, sim.collision_resolve = "direct", "merge"
        if integrator == "kepler":
            HBVMIntegrator(sim, kepler=True, dt=0.01)
        else:
            sim.integrator = integrator
        return sim
    sim, ref = scene("kepler"), scene("ias15")
    sim.integrate(2.0)
    ref.integrate(2.0)
    assert sim.N == ref.N == 2 and sim.particles[1].m == 2e-3
    assert np.abs(_xv(sim) - _xv(ref)).max() < 1e-4        # (merged at slightly other times)
    # the merged body falls onto the star: the last planet is gone, and kepler = 1 says so
    with pytest.raises(ValueError, match=r"at least one more \(got 1 particles\).*kepler = 0"):
        sim.integrate(4.0)


def test_a_mass_changed_between_runs_starts_afresh():
    a = _outer()
    a.steps(4)
    a.particles[1].m *= 1.001
    b = a.copy()
    HBVMIntegrator(b, kepler=True, dt=H)       # a new attach from the same particles
    a.steps(4)
    b.steps(4)
    assert np.array_equal(_xv(a), _xv(b))


def test_variational_particles_are_refused():
    sim = outer_solar_system().to_rebound()
    sim.add_variation()
    with pytest.raises(ValueError, match=r"variational particles.*kepler = 0"):
        HBVMIntegrator(sim, kepler=True, dt=H)


def test_time_set_between_runs_moves_no_body():
    # a barycentre in motion: the bodies are written from its uniform motion since the start,
    # so a sim.t set by the user must not move them (read afresh at the new time instead)
    sim = outer_solar_system().to_rebound()
    for p in sim.particles:
        p.vx += 1e-3
    HBVMIntegrator(sim, kepler=True, dt=H)
    sim.steps(4)
    sim.t = 0.0
    fresh = sim.copy()
    HBVMIntegrator(fresh, kepler=True, dt=H)
    sim.steps(4)
    fresh.steps(4)
    assert np.array_equal(_xv(sim), _xv(fresh))


def test_a_reboundx_force_is_refused_by_name_also_when_added_later():
    reboundx = pytest.importorskip("reboundx")
    sim = _outer()
    sim.steps(2)
    rebx = reboundx.Extras(sim)
    gr = rebx.load_force("gr")
    rebx.add_force(gr)
    gr.params["c"] = 1e4
    before = _xv(sim)
    with pytest.raises(ValueError, match=r"REBOUNDx.*gr.*kepler = 0"):
        sim.steps(2)
    assert np.array_equal(_xv(sim), before) and sim.t == 2 * H
    sim = outer_solar_system().to_rebound()
    rebx = reboundx.Extras(sim)
    rebx.add_force(rebx.load_force("gr"))
    with pytest.raises(ValueError, match=r"REBOUNDx.*gr.*kepler = 0"):
        HBVMIntegrator(sim, kepler=True, dt=H)


C_AU_YR = 63241.077        # the speed of light in AU/yr (REBOUNDx's GR examples)


def _mercury(integrator="kepler", c=C_AU_YR, dt=0.01, rebx_attached=True):
    """The inner planets, Jupiter and a test particle inside Mercury's orbit (yr, AU, Msun), with
    REBOUNDx's gr_potential: the composed step (dt) or IAS15 at a tight epsilon."""
    reboundx = pytest.importorskip("reboundx")
    sim = rebound.Simulation()
    sim.units = ("yr", "AU", "Msun")
    sim.add(m=1.0)
    sim.add(m=1.66e-7, a=0.387098, e=0.2056, inc=0.12)
    sim.add(m=2.45e-6, a=0.723, e=0.0068, inc=0.06, Omega=1.0)
    sim.add(m=3.0e-6, a=1.0, e=0.0167, f=2.0)
    sim.add(m=9.5e-4, a=5.2, e=0.048, inc=0.02, f=4.0)
    sim.add(m=0.0, a=0.3, e=0.3, inc=0.2, f=1.0)
    sim.N_active = 5
    sim.move_to_com()
    rebx = gr = None
    if rebx_attached:
        rebx = reboundx.Extras(sim)
        gr = rebx.load_force("gr_potential")
        rebx.add_force(gr)
        gr.params["c"] = c
    if integrator == "kepler":
        HBVMIntegrator(sim, kepler=True, dt=dt)
    else:
        sim.integrator = integrator
        sim.integrator.epsilon = 1e-11
    return sim, rebx, gr


def test_gr_potential_is_a_term_of_the_perturbation():
    """REBOUNDx's gr_potential with kepler = 1: FlowComposed's gr_c term (the engine's run bit
    for bit), against IAS15 with the same force, and REBOUNDx's energy kept."""
    sim, rebx, gr = _mercury()
    nb = NBody.from_rebound(sim)
    E0 = sim.energy() + rebx.gr_potential_potential(gr)
    n = 500
    sim.steps(n)
    fc = FlowComposed.from_nbody(nb, 0.01, gr_c=C_AU_YR)
    r = integrate(HBVM(8, 6), fc, fc.extend(nb.initial_state()), 0.01, n, sample_every=n,
                  form="full")
    assert np.array_equal(_state(sim, fc.dim), r.y[-1])
    E1 = sim.energy() + rebx.gr_potential_potential(gr)
    assert abs(E1 / E0 - 1) < 2e-14
    assert fc.physical_energy(r.y[-1]) == pytest.approx(E1, rel=1e-14)
    ref, _, _ = _mercury("ias15")
    ref.integrate(sim.t)
    assert np.abs(_xv(sim)[:, :3] - _xv(ref)[:, :3]).max() < 5e-12
    # the term matters at this tolerance (measured: Newton alone is 4e-5 AU away after 5 years;
    # the run is 9e-13 from IAS15, its energy error 4e-15)
    newton, _, _ = _mercury(rebx_attached=False)
    newton.steps(n)
    assert np.abs(_xv(sim)[:, :3] - _xv(newton)[:, :3]).max() > 1e-6


def test_gr_potential_restarts_bit_for_bit(tmp_path):
    reboundx = pytest.importorskip("reboundx")
    whole, _, _ = _mercury()
    whole.steps(40)
    half, rebx, gr = _mercury()
    half.steps(20)
    half.save_to_file(str(tmp_path / "s.bin"), delete_file=True)
    rebx.save(str(tmp_path / "x.rebx"))
    copy = half.copy()                       # (REBOUND's copy leaves REBOUNDx behind)
    crebx = reboundx.Extras(copy)
    cgr = crebx.load_force("gr_potential")
    crebx.add_force(cgr)
    cgr.params["c"] = C_AU_YR
    loaded = rebound.Simulation(str(tmp_path / "s.bin"))
    lrebx = reboundx.Extras(loaded, str(tmp_path / "x.rebx"))
    assert loaded.integrator.kepler == 1
    for other in (half, copy, loaded):
        other.steps(20)
        assert np.array_equal(_xv(other), _xv(whole))
        assert HBVMIntegrator.of(other).resyncs == HBVMIntegrator.of(whole).resyncs
    del lrebx


def test_gr_potential_changed_or_dropped_between_runs_is_followed():
    # c changed between runs (a number of REBOUNDx's, no word of REBOUND's): the step is
    # prepared again from the particles and follows IAS15 with the new c
    c2 = C_AU_YR / 30
    sim, rebx, gr = _mercury()
    ref, rrebx, rgr = _mercury("ias15")
    for s in (sim, ref):
        s.integrate(1.0)
    gr.params["c"] = rgr.params["c"] = c2
    before = HBVMIntegrator.of(sim).resyncs
    for s in (sim, ref):
        s.integrate(3.0)
    assert HBVMIntegrator.of(sim).resyncs == before + 1
    assert np.abs(_xv(sim)[:, :3] - _xv(ref)[:, :3]).max() < 1e-11
    # a copy without REBOUNDx is Newton's scene: it starts afresh, and follows IAS15 on it
    copy = sim.copy()
    plain = sim.copy()
    plain.integrator = "ias15"
    plain.integrator.epsilon = 1e-11
    copy.integrate(4.0)
    plain.integrate(4.0)
    assert HBVMIntegrator.of(copy).resyncs == HBVMIntegrator.of(sim).resyncs + 1
    assert np.abs(_xv(copy)[:, :3] - _xv(plain)[:, :3]).max() < 1e-11


def test_other_reboundx_forces_beside_gr_potential_are_refused():
    sim, rebx, gr = _mercury()
    sim.steps(2)
    for name in ("gr", "gr_potential"):
        other = rebx.load_force(name)
        rebx.add_force(other)
        other.params["c"] = C_AU_YR
        before = _xv(sim)
        with pytest.raises(ValueError, match=(r"REBOUNDx 'gr'.*kepler = 0" if name == "gr" else
                                              r"one REBOUNDx 'gr_potential' force \(got 2\)")):
            sim.steps(2)
        assert np.array_equal(_xv(sim), before)
        rebx.remove_force(other)
    sim.steps(2)                                   # (gr_potential alone again: it runs)
    assert sim.t == pytest.approx(0.04)
    # gr_potential without its c
    sim, rebx, gr = _mercury(rebx_attached=False, integrator="ias15")
    reboundx = pytest.importorskip("reboundx")
    rebx = reboundx.Extras(sim)
    rebx.add_force(rebx.load_force("gr_potential"))
    with pytest.raises(ValueError, match=r"set force.params\['c'\]"):
        HBVMIntegrator(sim, kepler=True, dt=0.01)


def _j2_scene(integrator="kepler", dt=0.004, forces=("gravitational_harmonics", "central_force",
                                                    "gr_potential")):
    """REBOUNDx's J2 example (G = 1: a star with J2, J4 and R_eq about a tilted spin axis, a
    planet at a = 0.1 inclined by pi/6), with a second planet, a test particle, the star's
    central force (CentralForce example's gamma = -1) and gr_potential: the composed step (dt),
    plain HBVM (kepler=False, dt) or IAS15 at a tight epsilon."""
    reboundx = pytest.importorskip("reboundx")
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=3e-6, a=0.1, e=0.01, inc=np.pi / 6)
    sim.add(m=1e-5, a=0.17, e=0.05, inc=0.1, f=2.0)
    sim.add(m=0.0, a=0.13, e=0.1, inc=0.3, f=4.0)
    sim.N_active = 3
    sim.move_to_com()
    rebx = reboundx.Extras(sim)
    p0 = sim.particles[0]
    for name in forces:
        force = rebx.load_force(name)
        rebx.add_force(force)
        if name == "gr_potential":
            force.params["c"] = 300.0
    if "gravitational_harmonics" in forces:
        p0.params["J2"], p0.params["J4"], p0.params["R_eq"] = 0.01, -1e-3, 1 / 200
        p0.params["Omega"] = [0.0, -np.sin(np.pi / 3), np.cos(np.pi / 3)]
    if "central_force" in forces:
        p0.params["gammacentral"], p0.params["Acentral"] = -1.0, 1e-4
    if integrator == "ias15":
        sim.integrator = "ias15"
        sim.integrator.epsilon = 1e-11
    else:
        HBVMIntegrator(sim, kepler=integrator == "kepler", dt=dt)
    return sim, rebx


def _rebx_energy(sim, rebx):
    """REBOUND's energy plus the potentials of the REBOUNDx forces attached."""
    e = sim.energy() + rebx.gravitational_harmonics_potential() + rebx.central_force_potential()
    return e + rebx.gr_potential_potential(rebx.get_force("gr_potential"))


def test_harmonics_and_central_force_are_terms_of_the_perturbation():
    """REBOUNDx's gravitational_harmonics and central_force of the star, with gr_potential,
    under kepler = 1: plain HBVM's run on REBOUNDx's own accelerations and IAS15's to round-off,
    REBOUNDx's energy kept, and the engine's energy is REBOUNDx's potentials'."""
    from hbvm_md.rebound.composed import force_terms
    sim, rebx = _j2_scene()
    E0 = _rebx_energy(sim, rebx)
    nb = NBody.from_rebound(sim)
    gr_c, harmonics, central = force_terms(sim)
    assert (gr_c, central) == (300.0, (1e-4, -1.0)) and harmonics[:3] == (0.01, -1e-3, 1 / 200)
    sim.integrate(1.0)
    fc = FlowComposed.from_nbody(nb, 0.004, gr_c=gr_c, harmonics=harmonics, central=central)
    E1 = _rebx_energy(sim, rebx)
    assert fc.physical_energy(_state(sim, fc.dim)) == pytest.approx(E1, rel=1e-13)
    assert abs(E1 / E0 - 1) < 1e-14
    plain, _ = _j2_scene("plain", dt=0.002)
    ias, _ = _j2_scene("ias15")
    newton, _ = _j2_scene(forces=())
    for other in (plain, ias, newton):
        other.integrate(1.0)
    # (measured: 6.9e-15 from plain HBVM, 8.2e-15 from IAS15; Newton alone is 3.7e-3 away)
    assert np.abs(_xv(sim)[:, :3] - _xv(plain)[:, :3]).max() < 5e-14
    assert np.abs(_xv(sim)[:, :3] - _xv(ias)[:, :3]).max() < 5e-14
    assert np.abs(_xv(sim)[:, :3] - _xv(newton)[:, :3]).max() > 1e-4


def test_harmonics_and_central_force_restart_bit_for_bit(tmp_path):
    reboundx = pytest.importorskip("reboundx")
    whole, _ = _j2_scene()
    whole.steps(40)
    half, rebx = _j2_scene()
    half.steps(20)
    half.save_to_file(str(tmp_path / "s.bin"), delete_file=True)
    rebx.save(str(tmp_path / "x.rebx"))
    loaded = rebound.Simulation(str(tmp_path / "s.bin"))
    lrebx = reboundx.Extras(loaded, str(tmp_path / "x.rebx"))
    assert loaded.integrator.kepler == 1
    for other in (half, loaded):
        other.steps(20)
        assert np.array_equal(_xv(other), _xv(whole))
        assert HBVMIntegrator.of(other).resyncs == HBVMIntegrator.of(whole).resyncs
    del lrebx


@pytest.mark.parametrize("param, value", [("J2", 0.02), ("Omega", [0.0, 0.0, 1.0]),
                                          ("Acentral", 3e-4), ("gammacentral", 0.5)])
def test_harmonics_or_central_force_changed_between_runs_is_followed(param, value):
    sim, _ = _j2_scene()
    ref, _ = _j2_scene("ias15")
    for s in (sim, ref):
        s.integrate(0.5)
        s.particles[0].params[param] = value
    before = HBVMIntegrator.of(sim).resyncs
    for s in (sim, ref):
        s.integrate(1.0)
    assert HBVMIntegrator.of(sim).resyncs == before + 1
    assert np.abs(_xv(sim)[:, :3] - _xv(ref)[:, :3]).max() < 5e-14
    # a copy without REBOUNDx is Newton's scene: it starts afresh
    copy = sim.copy()
    copy.integrate(1.2)
    assert HBVMIntegrator.of(copy).resyncs == HBVMIntegrator.of(sim).resyncs + 1


def test_harmonics_or_central_force_of_a_planet_are_refused_by_name():
    sim, rebx = _j2_scene()
    sim.steps(2)
    p1 = sim.particles[1]
    for param, value, match in (
            ("J2", 1e-3, r"'gravitational_harmonics' of particle 0 only; particle 1 has J2"),
            ("Acentral", 1e-3, r"'central_force' from particle 0 only; particle 1 has Acentral")):
        p1.params[param] = value
        if param == "J2":
            p1.params["R_eq"] = 1e-4
        else:
            p1.params["gammacentral"] = -2.0
        before = _xv(sim)
        with pytest.raises(ValueError, match=match + r".*kepler = 0"):
            sim.steps(2)
        assert np.array_equal(_xv(sim), before)
        p1.params[param] = 0.0            # (J2 = 0, A = 0: REBOUNDx applies nothing)
    sim.steps(2)
    assert sim.t == pytest.approx(0.016)
    # a planet's J2 (REBOUNDx's own example sets J4 on a planet without J2: no force, accepted)
    # with the way out: plain HBVM runs it on REBOUNDx's accelerations
    p1.params["J2"] = 1e-3
    sim.integrator.kepler = 0
    sim.steps(2)
    # two of a kind, and a parameter that is not a finite number
    sim, rebx = _j2_scene()
    rebx.add_force(rebx.load_force("central_force"))
    with pytest.raises(ValueError, match=r"one REBOUNDx 'central_force' force \(got 2\)"):
        sim.steps(1)
    sim, rebx = _j2_scene()
    sim.particles[0].params["R_eq"] = -1.0
    with pytest.raises(ValueError, match=r"R_eq of particle 0 must be > 0"):
        sim.steps(1)
    sim.particles[0].params["R_eq"] = float("nan")
    with pytest.raises(ValueError, match=r"R_eq of particle 0 must be a finite number"):
        sim.steps(1)
