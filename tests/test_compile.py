"""How the project compiles (integrators.jit, integrators.specialise, hbvm_md.precompile):
numba's function ids left alone outside the project's own compilations, each scene's step
compiled without the parts it does not use, the line a cold compile logs, the ahead-of-time
compile."""
import logging
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numba
import numpy as np
import pytest

from integrators import ccore

from integrators import absent, specialise as sp
from integrators.jit import Dispatcher, _own
from integrators.records import Method, Newton, Options, StepConstants, System, Tableau, Tangents

ROOT = Path(__file__).resolve().parents[1]
JIT_OFF = os.environ.get("NUMBA_DISABLE_JIT") == "1"


def _python(code: str, timeout=600) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, env=env, timeout=timeout)


def test_importing_hbvm_md_leaves_numbas_function_ids_alone():
    r = _python("""
        import sys
        from numba.core.bytecode import FunctionIdentity
        ids = FunctionIdentity._unique_ids
        first = next(ids)
        hook = sys.unraisablehook
        import hbvm_md, hbvm_md.rebound, hbvm_md.ase, integrators.specialise
        assert FunctionIdentity._unique_ids is ids
        assert sys.unraisablehook is hook   # (the REBOUND host chains its hook at a run)
        print(next(ids) - first)
        """)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "1"          # nothing drew an id from numba's counter


@pytest.mark.skipif(JIT_OFF, reason="nothing is compiled under NUMBA_DISABLE_JIT")
def test_project_compiles_with_its_own_ids_and_gives_numbas_counter_back():
    from numba.core.bytecode import FunctionIdentity
    ids = FunctionIdentity._unique_ids
    ours = _own(numba.njit(lambda x: x * 3.0 + 1.0))
    theirs = numba.njit(lambda x: x * 5.0 - 1.0)
    assert isinstance(ours, Dispatcher)
    assert ours(2.0) == 7.0 and theirs(2.0) == 9.0
    assert FunctionIdentity._unique_ids is ids
    uid_ours = next(iter(ours.overloads.values())).fndesc.uid
    uid_theirs = next(iter(theirs.overloads.values())).fndesc.uid
    assert uid_ours > 2 ** 40 > uid_theirs


@pytest.mark.slow
@pytest.mark.skipif(JIT_OFF, reason="nothing is cached under NUMBA_DISABLE_JIT")
def test_rebound_step_then_ase_step_loaded_from_cache_in_one_process():
    """numba issue #10486's scene (integrators.jit._Ids): the REBOUND step and the ASE step
    compiled (or loaded) by two processes, then both loaded from the cache by a third."""
    rebound_run = """
        import rebound, hbvm_md
        sim = rebound.Simulation()
        sim.add(m=1.0); sim.add(m=1e-3, a=1.0, e=0.05); sim.add(m=1e-3, a=1.6, e=0.02)
        sim.integrator = "hbvm"; sim.dt = 0.05; sim.integrate(2.0)
        print("rebound", repr(sim.particles[1].x))
        """
    ase_run = """
        import numpy as np
        from ase import Atoms
        from ase.calculators.emt import EMT
        from hbvm_md import HBVMDynamics
        atoms = Atoms("Cu3", positions=[[0, 0, 0], [2.5, 0, 0], [1.2, 2.2, 0]])
        atoms.calc = EMT()
        HBVMDynamics(atoms, 0.2).run(5)                     # (2 fs)
        print("ase", repr(atoms.positions[0, 0]))
        """
    a, b = _python(rebound_run), _python(ase_run)
    assert a.returncode == 0 and b.returncode == 0, a.stderr + b.stderr
    both = _python(rebound_run + ase_run)
    assert both.returncode == 0, both.stderr
    assert both.stdout.split() == a.stdout.split() + b.stdout.split()   # and the same numbers


@pytest.mark.skipif(JIT_OFF, reason="the stand-ins are bound in compiled steps only")
def test_a_step_compiles_only_the_parts_its_scene_uses():
    from systems import NBody
    from integrators import HBVM, EQUIP
    from integrators.engine import Binding
    masses = np.array([1.0, 1e-3, 1e-3])
    plain = Binding(HBVM(6, 6), NBody(masses), form="separable")
    assert plain.kind == "compiled"
    # the plain N-body step runs on the compiled core (integrators.ccore); its numba step,
    # built for the Newton iteration, leaves out what the scene does not use
    assert isinstance(plain.step_code, ccore.CoreStep)
    numba_plain = plain.step_code.numba_step()
    assert numba_plain.follow is absent.follow
    assert numba_plain.run.py_func.__globals__["eq"] is absent
    assert numba_plain.run.py_func.__globals__["full_stages"] is absent.full_stages
    tp = Binding(HBVM(6, 6), NBody(np.array([1.0, 1e-3, 0.0])), form="separable")
    assert tp.step_code.follow is not absent.follow
    eq = Binding(EQUIP(6, 6), NBody(masses), form="separable")
    assert eq.step_code.run.py_func.__globals__["eq"] is not absent


@pytest.mark.skipif(JIT_OFF, reason="the stand-ins are bound in compiled steps only")
def test_rebound_binds_the_tangent_map_only_with_variational_particles(monkeypatch):
    import rebound
    import hbvm_md  # noqa: F401  (registers "hbvm")
    from hbvm_md.rebound import cglue
    # (the plain scene's numba step: point masses run the C step of hbvm_md.rebound.csrc)
    monkeypatch.setattr(cglue, "plain_step", lambda *a: False)

    def glue_steps(variational):
        sim = rebound.Simulation()
        sim.add(m=1.0)
        sim.add(m=1e-3, a=1.0)
        if variational:
            sim.add_variation()
        sim.integrator = "hbvm"
        sim.dt = 0.05
        sim.steps(1)
        return {k[3] is not None: v for k, v in sp._CACHE.items()
                if k[2] == "hbvm_md.rebound.glue"}

    def bound(step):
        return step.step_arrays.py_func.__globals__["tangent_map"]

    assert bound(glue_steps(False)[False]) is absent.tangent_map
    assert bound(glue_steps(True)[True]) is not absent.tangent_map
    # REBOUND's step only iterates to a fixed point: built without the simplified Newton update
    # (the engine's steps keep it: solver="auto" may switch to Newton)
    for step in glue_steps(True).values():
        assert step.run.py_func.__globals__["newton_update"] is absent.newton_update
        assert step.run.py_func.__globals__["_NEWTON"] is False
    from systems import NBody
    from integrators import HBVM
    from integrators.engine import Binding
    engine = Binding(HBVM(6, 6), NBody(np.array([1.0, 1e-3, 1e-3])), form="separable")
    assert (engine.step_code.numba_step().run.py_func.__globals__["newton_update"]
            is not absent.newton_update)


def test_the_stand_ins_refuse_to_be_reached():
    with pytest.raises(RuntimeError, match="compiled without this part"):
        absent.follow(*([np.zeros(1)] * 6), 0, StepConstants(0.1, *([np.zeros(1)] * 2), 0.0, 0.0),
                      Tableau(*([np.zeros(1)] * 10)), Options(1, 0.0, 0.0, 0.0, 0), np.zeros(1),
                      np.zeros(1))
    with pytest.raises(RuntimeError, match="compiled without this part"):
        absent.start(np.zeros(6), np.zeros(3))
    with pytest.raises(RuntimeError, match="compiled without this part"):
        absent.newton_update(*([np.zeros((1, 1))] * 2), *([np.zeros((1, 1), complex)] * 2),
                             np.zeros((0, 1, 1), complex), np.zeros((2, 1)),
                             np.zeros((1, 1), complex))
    # no tangents: nothing to map, and OK
    assert absent.tangent_map(System(False, np.zeros(1), np.zeros(1), np.zeros(1)),
                              np.zeros(1), np.zeros(1), np.zeros((1, 1)), 0.1, np.zeros((1, 1)),
                              Method(np.zeros((2, 1)), np.zeros((2, 1)), np.zeros((2, 1, 1)),
                                     np.zeros((4, 1, 1))),
                              Newton(np.zeros((1, 1), complex), np.zeros((1, 1), complex),
                                     np.zeros((0, 1, 1), complex)), 1,
                              Tangents(np.zeros((0, 2)), np.zeros((0, 1, 1)), np.zeros((0, 2)),
                                       np.zeros((0, 1, 1)), np.zeros(1), np.zeros(1, complex),
                                       np.zeros(3), np.zeros((0, 0)), np.zeros((0, 3)))) == 0


def test_a_cold_compile_says_so_in_one_line(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path / "numba"))
    name = "_hbvm_md_step_0123456789abcdef01234567"
    path = tmp_path / f"{name}.py"
    path.write_text("")
    refs = [("systems.nbody", "nbody_forces"), ("systems.nbody", "nbody_potential")]
    with caplog.at_level(logging.INFO, logger="hbvm_md"):
        sp._announce(name, path, refs, None, sp.NO_FOLLOWERS, (False, False, False))
    [line] = [r.getMessage() for r in caplog.records]
    assert line.startswith("hbvm-md: compiling HBVM's step for this scene, once: kernel "
                           "systems.nbody.nbody_forces, separable form, HBVM (")
    assert "hbvm-md compile" in line
    # once numba has cached it: nothing
    from numba.core import caching
    for cls in (getattr(caching, "CacheImpl", None) or caching._CacheImpl)._locator_classes:
        loc = cls.from_function(sp._announce, str(path))
        if loc is not None:
            loc.ensure_cache_path()
            Path(loc.get_cache_path(), f"{name}.run-93.py311.nbi").write_text("")
            break
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="hbvm_md"):
        sp._announce(name, path, refs, None, sp.NO_FOLLOWERS, (False, False, False))
    assert caplog.records == []


def test_precompile_names_the_scenes_it_knows():
    from hbvm_md import precompile
    with pytest.raises(ValueError, match=r"`scenes` must name scenes among .*'rebound'.* "
                                         r"or 'all' \(got 'mars'\)"):
        precompile(["mars"])


def test_hbvm_md_compile_compiles_the_rebound_step(capsys):
    from hbvm_md.cli import main
    assert main(["compile", "rebound"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("rebound: ") and "cached in" in out


def test_precompile_covers_the_scenes_on_rebounds_own_forces(caplog):
    """``hbvm-md compile rebound-forces rebound-forces-velocities`` compiles the variants that a
    scene on REBOUND's accelerations uses (softening; a force of the velocities): the scenes
    that follow compile nothing (no "compiling" line: a scene whose variant differed from the
    precompiled one would build a module of another name and announce it)."""
    import rebound

    from hbvm_md import precompile
    precompile(["rebound-forces", "rebound-forces-velocities"])
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="hbvm_md"):
        for velocities in (False, True):
            sim = rebound.Simulation()
            sim.add(m=1.0)
            sim.add(m=1e-3, a=1.0, e=0.1)
            sim.add(m=1e-4, a=1.9, e=0.05)
            if velocities:
                def drag(reb_sim, sim=sim):
                    for p in sim.particles:
                        p.ax -= 1e-5 * p.vx
                sim.additional_forces = drag
                sim.force_is_velocity_dependent = 1
            else:
                sim.softening = 1e-3
            sim.integrator = "hbvm"
            sim.integrate(1.0)
            assert sim.t == 1.0
    assert [r.getMessage() for r in caplog.records if "compiling" in r.getMessage()] == []


def test_precompile_covers_the_composed_kepler_step(caplog):
    """``hbvm-md compile kepler`` (and ``all``) compiles the step of ``sim.integrator.kepler =
    1``, its own kernels and glue: the runs that follow, with and without test particles,
    compile nothing (before, ``all`` left it out and the first composed run compiled for about
    20 s after it)."""
    import rebound

    from hbvm_md import precompile
    precompile(["kepler"])
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="hbvm_md"):
        for test_particle in (False, True):
            sim = rebound.Simulation()
            sim.add(m=1.0)
            sim.add(m=1e-3, a=1.0, e=0.1)
            sim.add(m=1e-4, a=1.9, e=0.05)
            if test_particle:
                sim.add(a=3.0, e=0.2)
            sim.integrator = "hbvm"
            sim.integrator.kepler = 1
            sim.integrator.epsilon = 0.0
            sim.dt = 0.05
            sim.integrate(1.0)
            assert sim.t == 1.0
    assert [r.getMessage() for r in caplog.records if "compiling" in r.getMessage()] == []
