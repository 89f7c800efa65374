"""REBOUND's step on the compiled core (hbvm_md/rebound/csrc, hbvm_md.rebound.cglue): the
plain N-body case runs in C with nothing compiled at run time, and gives the numba step's
numbers bit for bit; every other case still goes to the numba step."""
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import rebound

import hbvm_md
from hbvm_md import HBVMIntegrator
from hbvm_md.rebound import cglue, layout as L
from hbvm_md.rebound.host import _slots
from integrators import EnergyDriftError

pytestmark = pytest.mark.skipif(not cglue.available(),
                                reason="the compiled REBOUND glue is not built")
ROOT = Path(__file__).resolve().parents[1]


def _oss():
    sim = rebound.Simulation()
    sim.add(m=1.00000597682)
    for m, a, e, inc in ((1 / 1047.355, 5.2, 0.048, 0.02), (1 / 3501.6, 9.55, 0.056, 0.04),
                         (1 / 22869.0, 19.2, 0.047, 0.01), (1 / 19314.0, 30.1, 0.009, 0.03)):
        sim.add(m=m, a=a, e=e, inc=inc, primary=sim.particles[0])
    sim.move_to_com()
    sim.dt = 0.5
    return sim


def _eccentric():
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, e=0.6)
    sim.add(m=3e-4, a=1.6, e=0.03, inc=0.02, Omega=0.3)
    sim.move_to_com()
    sim.dt = 0.01
    return sim


def _asteroids():
    """A star, two giant planets and 40 test particles in the asteroid belt (N_active = 3)."""
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=5.2, e=0.05)
    sim.add(m=3e-4, a=9.5, e=0.05, inc=0.02)
    rng = np.random.default_rng(1)
    for _ in range(40):
        sim.add(a=rng.uniform(2.2, 3.3), e=rng.uniform(0, 0.2), inc=rng.uniform(0, 0.1),
                f=rng.uniform(0, 2 * np.pi))
    sim.N_active = 3
    sim.move_to_com()
    sim.dt = 0.3
    return sim


def _core_of(sim) -> int:
    return int(_slots(sim.integrator.state)[0][L.SL_CORE])


def _run(make, how, c: bool, monkeypatch):
    """The scene run as ``how`` says, on the C step (c) or the numba glue; returns what a user
    sees and what the state keeps."""
    with monkeypatch.context() as mp:
        if not c:
            mp.setattr(cglue, "plain_step", lambda *a: False)
        sim = make()
        sim.integrator = "hbvm"
        if "fixed" in how:
            HBVMIntegrator(sim, adaptive=False)
        sign = -1.0 if "backwards" in how else 1.0
        if "backwards" in how:
            sim.dt = -sim.dt
        if "moved" in how:      # (particles changed after each step: the step rereads them)
            def nudge(p):
                p.contents.particles[1].vx *= 1.0 + 1e-9
            sim.post_timestep_modifications = nudge
        times = sign * np.array([0.7, 3.3, 10.0, 24.1, 40.0])
        for i, t in enumerate(times):
            if "copied" in how and i == 2:
                sim = sim.copy()
                sim.integrator = "hbvm"
            sim.integrate(t)
        if c:
            assert _core_of(sim) == cglue.addresses()[2]
        else:
            assert _core_of(sim) != cglue.addresses()[2]
        st, sd = _slots(sim.integrator.state)
        x = np.array([[p.x, p.y, p.z, p.vx, p.vy, p.vz] for p in sim.particles])
        return dict(x=x, t=sim.t, dt=sim.dt, last=sim.dt_last_done, steps=sim.steps_done,
                    repr=repr(sim.integrator), counters=np.array(HBVMIntegrator.of(sim).counters),
                    eref=sd[L.SL_EREF:L.SL_EREF + L.N_EREF].copy(),
                    saved=[sd[L.SL_H_PREV], sd[L.SL_T_COMP], sd[L.SL_RUN_ERR],
                           int(st[L.SL_NSTEPS]), int(st[L.SL_REJECTED]),
                           int(st[L.SL_RESYNCS])])


@pytest.mark.parametrize("make, how", [
    (_oss, "adaptive"), (_oss, "fixed"), (_eccentric, "adaptive"), (_eccentric, "fixed"),
    (_eccentric, "adaptive backwards"), (_oss, "adaptive copied"), (_eccentric, "fixed moved"),
    (_eccentric, "adaptive moved"), (_asteroids, "adaptive"), (_asteroids, "fixed")])
def test_the_c_step_is_the_numba_step_bit_for_bit(make, how, monkeypatch):
    a, b = _run(make, how, True, monkeypatch), _run(make, how, False, monkeypatch)
    assert np.array_equal(a["x"], b["x"])
    for key in ("t", "dt", "last", "steps"):
        assert a[key] == b[key], key
    assert np.array_equal(a["counters"], b["counters"])
    assert np.array_equal(a["eref"], b["eref"], equal_nan=True)
    assert np.array_equal(a["saved"], b["saved"], equal_nan=True)
    assert a["steps"] > 10 and a["saved"][2] > 0.0          # (steps taken, an estimate kept)
    if "adaptive" in how and "moved" not in how:
        assert a["saved"][4] >= 0


def _refused(c: bool, monkeypatch):
    with monkeypatch.context() as mp:
        if not c:
            mp.setattr(cglue, "plain_step", lambda *a: False)
        sim = rebound.Simulation()
        sim.add(m=1.0)
        sim.add(m=1e-3, a=1.0, e=0.9)
        sim.move_to_com()
        P = 2 * np.pi
        HBVMIntegrator(sim, s=1, k=1, adaptive=False)
        sim.dt = P / 3000
        with pytest.raises(EnergyDriftError) as err:
            sim.integrate(P)
        before = np.array([[p.x, p.y, p.z, p.vx, p.vy, p.vz] for p in sim.particles])
        t = sim.t
        with pytest.raises(EnergyDriftError):   # (refused again: the failed step left no trace)
            sim.integrate(P)
        after = np.array([[p.x, p.y, p.z, p.vx, p.vy, p.vz] for p in sim.particles])
        assert np.array_equal(before, after) and sim.t == t
        return str(err.value), t, before


def test_a_refused_step_is_refused_as_numba_refuses_it_and_changes_nothing(monkeypatch):
    a, b = _refused(True, monkeypatch), _refused(False, monkeypatch)
    assert a[0] == b[0] and a[1] == b[1] and np.array_equal(a[2], b[2])


def test_what_the_c_step_does_not_cover_goes_to_numba():
    sim = _eccentric()
    sim.integrator = "hbvm"
    sim.integrate(0.1)
    assert _core_of(sim) == cglue.addresses()[2]
    sim.integrator.method = "equip"             # (EQUIP: the numba step)
    sim.integrate(0.2)
    assert _core_of(sim) not in (0, cglue.addresses()[2])
    tp = _eccentric()
    tp.add(a=2.5, e=0.1)                        # (a test particle: on the C step too)
    tp.N_active = 3
    tp.integrator = "hbvm"
    tp.integrate(0.1)
    assert _core_of(tp) == cglue.addresses()[2]
    var = _eccentric()
    var.add_variation()                         # (variational particles: the numba step)
    var.integrator = "hbvm"
    var.integrate(0.1)
    assert _core_of(var) not in (0, cglue.addresses()[2])


def test_a_glue_built_for_another_rebound_is_refused_by_name(monkeypatch):
    class Old:
        LAYOUT = dict(cglue._glue.LAYOUT, _status=cglue._glue.LAYOUT["_status"] + 8)
        SOURCE_DIGEST = cglue._glue.SOURCE_DIGEST
        REBOUND_VERSION = "5.9.0"
    monkeypatch.setattr(cglue, "_glue", Old)
    why = cglue._why_not()
    assert "_status" in why and "5.9.0" in why and "reinstall" in why


def test_a_new_user_s_first_rebound_run_compiles_nothing(tmp_path):
    """The README's REBOUND scene in a fresh process with empty caches: no numba compilation
    (its caches stay empty) and the same numbers as in this process."""
    code = textwrap.dedent("""
        import numpy as np, rebound, hbvm_md
        sim = rebound.Simulation()
        sim.add("outer solar system") if False else None
        sim.add(m=1.0); sim.add(m=1e-3, a=1.0, e=0.6); sim.add(m=3e-4, a=1.6, e=0.03, inc=0.02)
        sim.move_to_com(); sim.integrator = "hbvm"; sim.dt = 0.01
        sim.integrate(20.0)
        print(repr(sim.particles[1].x), sim.steps_done)
    """)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"),
               HBVM_MD_CACHE_DIR=str(tmp_path / "hbvm"), PYTHONPATH=str(ROOT))
    env.pop("HBVM_MD_CORE", None)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert "compiling" not in out.stderr
    cached = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert cached == []
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, e=0.6)
    sim.add(m=3e-4, a=1.6, e=0.03, inc=0.02)
    sim.move_to_com()
    sim.integrator = "hbvm"
    sim.dt = 0.01
    sim.integrate(20.0)
    assert out.stdout.split() == [repr(sim.particles[1].x), str(sim.steps_done)]


def test_the_layout_is_read_from_the_c_header_and_refuses_what_it_cannot_read():
    """layout.py's slots are the members of csrc/hbvm_state.h at 8 bytes each (the build checks
    each against offsetof); a member line the rule cannot place is an error, not a silent
    shift of every slot after it."""
    assert L.SL_EPSILON == L.STATE["epsilon"] and L.SL_RES + L.N_RES == L.SL_MAX_DT
    assert L.C_WORDS + L.N_CFG == L.C_VALUES and L.N_HEADER == len(L.CONTEXT) + 2 * (L.N_CFG - 1)
    text = "struct t {\n    int64_t a;\n    double b[3]; /* three */\n    /* a\n comment */\n    double *c;\n};\n"
    assert L.read_struct(text, "t") == {"a": 0, "b": 1, "c": 4, "": 5}
    with pytest.raises(RuntimeError, match="cannot read the member line"):
        L.read_struct("struct t {\n    int32_t a;\n};\n", "t")
    with pytest.raises(RuntimeError, match="cannot read the member line"):
        L.read_struct("struct t {\n    double a, b;\n};\n", "t")


def test_the_host_s_record_of_a_simulation_lives_as_long_as_its_state():
    """One record per HBVM state, made by REBOUND's create and dropped by its free (a
    simulation collected, or one whose integrator is changed): nothing outlives a simulation
    or is inherited by the next one at a reused address."""
    import gc

    from hbvm_md.rebound import host

    sim = _eccentric()
    sim.integrator = "hbvm"
    sim.integrate(0.1)
    p = int(sim.integrator.state)
    assert p in host._RECORDS and host._RECORDS[p].forces == ()
    copy = sim.copy()
    q = int(copy.integrator.state)
    assert q != p and q in host._RECORDS and host._RECORDS[q].forces is None
    copy.integrator = "ias15"                 # (REBOUND frees the HBVM state)
    assert q not in host._RECORDS
    del sim
    gc.collect()
    assert p not in host._RECORDS


def _comet(c: bool, monkeypatch):
    with monkeypatch.context() as mp:
        if not c:
            mp.setattr(cglue, "plain_step", lambda *a: False)
        sim = rebound.Simulation()
        sim.add(m=1.0)
        sim.add(m=1e-3, a=5.2, e=0.05)
        sim.add(a=3.0, e=0.97, f=-0.5)          # (a comet falling to its perihelion)
        sim.N_active = 2
        sim.move_to_com()
        HBVMIntegrator(sim, adaptive=False, dt=0.5)
        with pytest.raises(Exception) as err:
            sim.integrate(20.0)
        assert _core_of(sim) == cglue.addresses()[2] if c else True
        return type(err.value).__name__, str(err.value), sim.t, [(p.x, p.vx) for p in sim.particles]


def test_a_test_particle_refused_by_the_c_step_is_refused_as_by_numba(monkeypatch):
    """A fixed step that resolves the planets but not a comet at its perihelion: refused by the
    test particles' own check (glue.TP_FLOOR, TP_FACTOR), naming the comet, with the same
    message, time and particles as the numba step's."""
    a, b = _comet(True, monkeypatch), _comet(False, monkeypatch)
    assert a == b
    assert "particle 2" in a[1]
