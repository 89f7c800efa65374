"""HBVMIntegrator in everyday REBOUND workflows: copies, restarts, interruptions by signals,
restricted problems, and what attaching accepts."""
import logging
import math
import re
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import rebound

from hbvm_md import HBVMIntegrator
from systems import outer_solar_system

ROOT = Path(__file__).resolve().parents[1]


def _xv(sim):
    return np.array([[p.x, p.y, p.z, p.vx, p.vy, p.vz] for p in sim.particles])


def _driven(**kw):
    sim = outer_solar_system().to_rebound()
    kw = {"s": 6, "k": 8, "dt": 100.0, **kw}
    return sim, HBVMIntegrator(sim, **kw)


# -- 1. sim.copy() --------------------------------------------------------------------------
def test_copy_carries_hbvm_and_continues_bit_for_bit():
    sim, drv = _driven(energy_tol=1e-9, max_iter=50)
    sim.integrate(2345.0)                   # a shrunken last step: h_prev and gamma matter
    twin = sim.copy()
    d2 = HBVMIntegrator.of(twin)
    assert d2 is not None and d2 is not drv and d2.sim is twin
    assert (d2.method, d2.energy_tol, d2.max_iter, d2.nsteps) == (drv.method, 1e-9, 50, drv.nsteps)
    sim.integrate(2e4)
    twin.integrate(2e4)
    assert twin.t == sim.t == 2e4
    assert np.array_equal(_xv(twin), _xv(sim))
    assert d2.resyncs == drv.resyncs == 1   # the copy kept the compensated state


def test_copy_before_any_step_and_detach_of_the_copy():
    sim = outer_solar_system().to_rebound()
    sim.integrator = "whfast"
    HBVMIntegrator(sim, s=6, k=8, dt=100.0)
    twin = sim.copy()
    assert HBVMIntegrator.of(twin).nsteps == 0
    twin.integrate(1000.0)
    sim.integrate(1000.0)
    assert np.array_equal(_xv(twin), _xv(sim))
    assert type(twin) is rebound.Simulation and twin.integrator == "hbvm"


# -- 2. restart --------------------------------------------------------------------------------
@pytest.mark.parametrize("adaptive", [False, True])
def test_save_and_load_continue_bit_for_bit(tmp_path, adaptive):
    kw = {"dt": None, "k": None, "adaptive": True} if adaptive else {}
    ref, dref = _driven(**kw)
    ref.integrate(4321.0)                   # the same steps, uninterrupted
    ref.integrate(1e4)
    sim, drv = _driven(**kw)
    sim.integrate(4321.0)
    path = tmp_path / "run.bin"
    sim.save_to_file(str(path), delete_file=True)
    del sim, drv
    sim = rebound.Simulation(str(path))
    drv2 = HBVMIntegrator.of(sim)
    assert sim.t == 4321.0 and drv2.method == dref.method and drv2.adaptive == adaptive
    sim.integrate(1e4)
    assert sim.t == ref.t and np.array_equal(_xv(sim), _xv(ref))
    assert drv2.nsteps == dref.nsteps and drv2.nfev == dref.nfev
    assert drv2.resyncs == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.bin"]    # no side file


def _readme_block(title):
    """The python block after `title` in the user guide's REBOUND page (once the README's)."""
    text = (ROOT / "docs" / "guide" / "rebound.md").read_text()
    m = re.search(rf"{re.escape(title)}.*?```python\n(.*?)```", text, re.S)
    assert m, f"docs/guide/rebound.md has no python block after {title!r}"
    return m.group(1)


def test_readme_restart_recipe(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    ns = {}
    exec(_readme_block("### Restarting a run"), ns)
    ref, _ = _driven(dt=250.0)
    ref.integrate(ns["sim"].t)
    assert ns["sim"].t == 1e5
    assert np.array_equal(_xv(ns["sim"]), _xv(ref))


# -- 3. signals --------------------------------------------------------------------------------
class _Alarm(Exception):
    pass


def test_signal_interrupts_leave_whole_committed_steps():
    """An exception raised by a signal handler lands between any two bytecodes of Python: when
    REBOUND returns, or inside the host's prepare callback (the first step).  Particles and
    sim.t must stay at a whole number of steps of the uninterrupted run, the exception must
    reach the caller, and the run must go on bit for bit."""
    n, dt = 600, 100.0
    ref, _ = _driven(dt=dt)
    states = {0.0: _xv(ref)}
    for _ in range(n):
        ref.steps(1)
        states[ref.t] = _xv(ref)
    end = ref.t
    rng = np.random.default_rng(12)
    probe, _ = _driven(dt=dt)
    probe.integrate(end)                    # compile and warm up before timing the alarms
    wall = time.perf_counter()
    probe2, _ = _driven(dt=dt)
    probe2.integrate(end)
    wall = time.perf_counter() - wall       # alarms drawn within a run's length
    kinds = [_Alarm, SystemExit]
    interrupted = 0
    old = signal.getsignal(signal.SIGALRM)
    try:
        # until 30 alarms have landed inside a run (a loaded machine lets some fire after the
        # run ended: those trials only check the run; at most 200 trials)
        for trial in range(200):
            if interrupted >= 30:
                break
            kind = kinds[trial % 2]

            def handler(signum, frame, kind=kind):
                raise kind("alarm")

            signal.signal(signal.SIGALRM, handler)
            sim, drv = _driven(dt=dt)
            try:
                delay = float(rng.uniform(1e-4, max(2e-4, 0.8 * wall)))
                signal.setitimer(signal.ITIMER_REAL, delay)
                sim.integrate(end)
                signal.setitimer(signal.ITIMER_REAL, 0.0)
            except (_Alarm, SystemExit):
                interrupted += 1
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0.0)
            assert sim.t in states, f"trial {trial}: t={sim.t} is not a whole step"
            assert np.array_equal(_xv(sim), states[sim.t]), f"trial {trial} at t={sim.t}"
            sim.integrate(end)
            assert np.array_equal(_xv(sim), states[end])
    finally:
        signal.signal(signal.SIGALRM, old)
    assert interrupted >= 30


# -- 4. restricted problem and duplicated particles ----------------------------------------
def _restricted():
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=0.0, a=1.0, e=0.3)
    sim.add(m=0.0, a=1.7, e=0.1, inc=0.2)
    sim.N_active = 1
    return sim


def test_restricted_problem_runs_and_says_the_energy_check_is_off():
    sim, ref = _restricted(), _restricted()
    ref.integrator = "ias15"
    HBVMIntegrator(sim, s=6, dt=2 * math.pi / 50)
    with pytest.warns(RuntimeWarning, match="no energy.*test particles are checked by their own error"):
        sim.integrate(20 * math.pi)
    ref.integrate(20 * math.pi)
    assert np.max(np.abs(_xv(sim) - _xv(ref))) < 1e-11


def test_duplicated_particle_is_named():
    sim, drv = _driven()
    sim.integrate(500.0)
    sim.add(sim.particles[3])
    before, t = _xv(sim), sim.t
    with pytest.raises(ValueError, match=r"particles 3, 6 are at the same position .*infinite"):
        sim.integrate(1000.0)
    assert sim.t == t and np.array_equal(_xv(sim), before)
    dup = outer_solar_system().to_rebound()
    dup.add(dup.particles[0])
    dt = dup.dt
    with pytest.raises(ValueError, match=r"particles 0, 6 are at the same position"):
        HBVMIntegrator(dup, s=6, dt=100.0)       # k = None: checked before the k probe
    assert dup.dt == dt and str(dup.integrator) == "ias15"


def test_test_particles_may_share_a_position():
    sim = _restricted()
    sim.add(sim.particles[2])
    HBVMIntegrator(sim, s=6, k=8, dt=0.1, energy_tol=None)
    sim.integrate(1.0)
    assert np.array_equal(_xv(sim)[2], _xv(sim)[3])


# -- 5. attaching ----------------------------------------------------------------------------
def test_k_probe_survives_an_encounter_ahead(caplog, capsys):
    from hbvm_md.reports.hard_cases import encounter_scene
    nb = encounter_scene()
    sim = nb.to_rebound(nb.initial_state())
    with caplog.at_level(logging.WARNING, logger="integrators.kchoice"):
        drv = HBVMIntegrator(sim, s=6, dt=2 * math.pi / 200)
    assert re.search(r"k probe: HBVM\(14, 6\) failed after \d+ steps", caplog.text)
    assert capsys.readouterr().out == ""          # logged, never printed
    # on the steps before the encounter HBVM(14, 6) still shows 7.9e-15 (HBVM(17, 6) 7e-16):
    # the reference grows onto the plateau, at most to 3 s + 12
    assert 6 <= drv.method.k <= 3 * 6 + 12 and sim.dt == 2 * math.pi / 200
    with pytest.raises(Exception, match="smaller sim.dt") as info:
        sim.integrate(3.0)
    assert "newton" not in str(info.value)


@pytest.mark.parametrize("kw, error, match", [
    ({"s": 2.5}, ValueError, r"`s` must be an integer.*s=2\.5"),
    ({"s": True}, ValueError, r"`s` must be an integer.*s=True"),
    # (s=None is the method's own default since EQUIP got its own: 6 for HBVM, 8 for EQUIP)
    ({"s": "6"}, ValueError, r"`s` must be an integer.*s='6'"),
    ({"k": 6.5}, ValueError, r"`k` must be an integer.*k=6\.5"),
    ({"k": "8"}, ValueError, r"`k` must be an integer.*k='8'"),
    ({"k": 5}, ValueError, r"`k` must be >= `s`"),
    ({"dt": True}, TypeError, r"`dt` must be a real number \(got dt=True\)"),
    ({"dt": "100"}, TypeError, r"`dt` must be a real number \(got dt='100'\)"),
    ({"dt": float("nan")}, ValueError, r"`dt` must be a nonzero finite step size"),
    ({"dt": 0.0}, ValueError, r"`dt` must be a nonzero finite step size"),
    ({"tol": "small"}, TypeError, r"`tol` must be a real number"),
    ({"energy_tol": "1e-10"}, TypeError, r"`energy_tol` must be a real number"),
    ({"energy_tol": True}, TypeError, r"`energy_tol` must be a real number"),
    ({"max_iter": 2.5}, ValueError, r"`max_iter` must be a positive integer"),
    ({"nodes": "radau"}, ValueError, r"`nodes` must be one of"),
])
def test_bad_arguments_are_named_and_change_nothing(kw, error, match):
    sim = outer_solar_system().to_rebound()
    dt, integrator = sim.dt, str(sim.integrator)
    args = {"s": 6, "dt": 250.0, **kw}
    with pytest.raises(error, match=match):
        HBVMIntegrator(sim, **args)
    assert sim.dt == dt and str(sim.integrator) == integrator and type(sim) is rebound.Simulation
    assert HBVMIntegrator.of(sim) is None


def test_nan_step_between_calls_is_refused_before_integrating():
    sim, _ = _driven()
    sim.integrate(500.0)
    before = _xv(sim)
    sim.dt = float("nan")
    with pytest.raises(ValueError, match=r"`sim.dt` must be a nonzero finite step size \(got sim.dt=nan\)"):
        sim.integrate(1000.0)
    assert sim.t == 500.0 and np.array_equal(_xv(sim), before)
    sim.dt = 100.0
    sim.integrate(1000.0)
    assert sim.t == 1000.0


def test_changing_the_integrator_gives_a_short_message():
    sim, drv = _driven()
    sim.integrator = "whfast"
    sim.integrate(500.0)             # REBOUND's to change: WHFast runs
    with pytest.raises(ValueError) as info:
        drv.nsteps
    msg = str(info.value)
    assert re.fullmatch(r"sim\.integrator is 'whfast', not HBVM .*", msg)
    assert len(msg) < 160 and "IntegratorConfiguration" not in msg


@pytest.mark.parametrize("method", ["hbvm", "equip"])
def test_a_failed_step_names_the_method_it_ran(method):
    """A fixed step far too long for the orbit fails, and REBOUND's message names the method
    the simulation runs (EQUIP's said "HBVM step" before), with the particles unchanged."""
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, e=0.9)
    sim.move_to_com()
    HBVMIntegrator(sim, method=method, s=4, dt=50.0)
    before = [(p.x, p.vx) for p in sim.particles]
    with pytest.raises(Exception, match=rf"^{method.upper()} step of size h=50"):
        sim.integrate(100.0)
    assert [(p.x, p.vx) for p in sim.particles] == before and sim.t == 0.0
