"""Messages and small defects of issue 58, item 6: each case takes the way out it names."""
import re

import numpy as np
import pytest
from ase import units
from ase.calculators.calculator import Calculator, all_changes
from ase.cluster import Icosahedron

from hbvm_md.ase import HBVMDynamics
from integrators import NonFiniteError


class NanForces(Calculator):
    """A harmonic well whose force on atom 0 is nan: everywhere (``where="everywhere"``), or
    everywhere but at the positions it was built with (``where="off_start"``)."""
    implemented_properties = ["energy", "forces"]

    def __init__(self, start, where="everywhere"):
        super().__init__()
        self.start, self.where, self.calls = np.array(start), where, 0

    def calculate(self, atoms=None, properties=("energy",), system_changes=all_changes):
        super().calculate(atoms, properties, system_changes)
        self.calls += 1
        x = atoms.get_positions() - self.start
        f = -x
        if self.where == "everywhere" or np.any(x != 0.0):
            f[0, 0] = np.nan
        self.results = {"energy": 0.5 * float(np.sum(x * x)), "forces": f}


def _cluster(where):
    atoms = Icosahedron("Cu", noshells=2)
    atoms.calc = NanForces(atoms.get_positions(), where)
    atoms.set_momenta(np.random.default_rng(1).normal(size=(13, 3)))
    return atoms


def test_adaptive_steps_stop_at_once_on_a_calculator_that_returns_nan():
    """Not ~1075 halvings and a StepSizeError advising a smaller min_dt: the forces at the
    step's start are not finite, so no shorter step helps; the calculator is named."""
    atoms = _cluster("everywhere")
    pos0 = atoms.get_positions()
    dyn = HBVMDynamics(atoms, timestep=2 * units.fs, adaptive=True)
    with pytest.raises(NonFiniteError, match=r"at t=0 fs .*the calculator NanForces returned a "
                       r"force that is not finite \(nan or inf\) on atom 0 at the positions the "
                       r"step starts from, so no smaller timestep helps; check the calculator"):
        dyn.run(1)
    assert atoms.calc.calls < 200
    assert np.array_equal(atoms.get_positions(), pos0)


@pytest.mark.parametrize("where", ["everywhere", "off_start"])
def test_nonfinite_error_of_a_calculator_names_the_calculator(where):
    """Fixed steps: the calculator, not "coincident particles"; at the start or at a stage."""
    atoms = _cluster(where)
    dyn = HBVMDynamics(atoms, timestep=2 * units.fs)
    with pytest.raises(NonFiniteError) as info:
        dyn.run(1)
    text = str(info.value)
    assert "coincident particles" not in text
    assert "the calculator NanForces returned a force that is not finite (nan or inf) on atom 0" in text
    if where == "everywhere":
        assert "at the positions the step starts from, so no smaller timestep helps" in text
    else:
        assert "at a stage of the step" in text and "a smaller timestep" in text


def test_linear_triatomic_not_in_a_line_is_named_and_the_ways_out_run():
    """Not a silent straightening (nor "a bond length is off"): the atom off the axis, by how
    much, the angle; the atom put on the axis runs, and so does FixBondLengths on the bent one."""
    from ase import Atoms
    from ase.calculators.lj import LennardJones
    from ase.constraints import FixBondLengths, FixLinearTriatomic
    bent = [[0, 0, 0], [1.16, 0.3, 0], [2.32, 0, 0]]
    atoms = Atoms("OCO", positions=bent)
    atoms.set_constraint(FixLinearTriatomic(triples=[(0, 1, 2)]))
    atoms.calc = LennardJones(sigma=1.0, rc=5.0)
    with pytest.raises(ValueError, match=r"FixLinearTriatomic\(0, 1, 2\): the three atoms are not "
                       r"in a line \(atom 1 is 0\.3 A off the axis through atoms 0 and 2; the "
                       r"angle 0-1-2 is 151 degrees, not 180\); .*put atom 1 on that axis, or "
                       r"hold a bent molecule with FixBondLengths on its three pairs"):
        HBVMDynamics(atoms, timestep=0.5 * units.fs).run(1)
    assert np.array_equal(atoms.get_positions(), bent)
    straight = Atoms("OCO", positions=[[0, 0, 0], [1.16, 0, 0], [2.32, 0, 0]])
    straight.set_constraint(FixLinearTriatomic(triples=[(0, 1, 2)]))
    straight.calc = LennardJones(sigma=1.0, rc=5.0)
    HBVMDynamics(straight, timestep=0.5 * units.fs).run(2)
    rigid = Atoms("OCO", positions=bent)
    rigid.set_constraint(FixBondLengths([(0, 1), (1, 2), (0, 2)]))
    rigid.calc = LennardJones(sigma=1.0, rc=5.0)
    d0 = rigid.get_all_distances()
    HBVMDynamics(rigid, timestep=0.5 * units.fs).run(2)
    assert np.allclose(rigid.get_all_distances(), d0, atol=1e-12)


# -- REBOUND ----------------------------------------------------------------------------------
def _planet(**kw):
    rebound = pytest.importorskip("rebound")
    import hbvm_md  # noqa: F401
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0, e=0.1)
    sim.integrator = "hbvm"
    for key, value in kw.items():
        setattr(sim.integrator, key, value)
    return sim


def test_integrate_to_nan_is_refused_not_run_forever():
    sim = _planet()
    xs = [tuple(p.xyz) for p in sim.particles]
    for bad in (float("nan"), np.nan):
        with pytest.raises(ValueError, match=r"sim.integrate\(tmax\) needs a number for tmax "
                           r"\(got tmax=nan, which no time reaches: the run would never end\); "
                           r"pass the time to integrate to, or inf"):
            sim.integrate(bad)
    assert sim.t == 0.0 and [tuple(p.xyz) for p in sim.particles] == xs
    sim.integrate(0.5)          # the way out
    assert sim.t == 0.5


def test_a_force_that_writes_velocities_is_warned_about():
    """A "force" that kicks the velocities: the stages drop what it writes (warned, with the
    ways out); the way out, the same effect as an acceleration, runs without the warning."""
    import warnings
    sim = _planet()

    def kick(reb_sim):
        ps = reb_sim.contents.particles
        ps[1].vx *= 0.999

    sim.additional_forces = kick
    with pytest.warns(RuntimeWarning, match=r"sim.additional_forces \('.*kick'\) writes the "
                      r"particles' velocities: HBVM's stages take only the accelerations it "
                      r"writes .* Write the effect as an acceleration"):
        sim.integrate(0.5)
    sim2 = _planet()

    def drag(reb_sim):
        ps = reb_sim.contents.particles
        ps[1].ax -= 1e-3 * ps[1].vx

    sim2.additional_forces = drag
    sim2.force_is_velocity_dependent = 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sim2.integrate(0.5)
    assert sim2.t == 0.5


def _with_ode(kind):
    sim = _planet()
    ode = sim.create_ode(length=2, needs_nbody=False)

    def rhs(ode, yDot, y, t):
        if kind == "nan":
            yDot[0], yDot[1] = float("nan"), 0.0
        elif kind == "unwritten":
            yDot[0] = -y[1]
        else:
            yDot[0], yDot[1] = -y[1], 0.0

    ode.derivatives = rhs
    ode.y[0], ode.y[1] = 1.0, 0.5
    return sim, ode


@pytest.mark.parametrize("kind, match", [
    ("nan", r"the attached ODE sim._odes\[0\] \(length 2\) returns yDot\[0\] = nan from its "
            r"derivatives at the step's start \(t=0.0, y\[0\] = 1.0\): no step size helps; check "
            r"the ODE's derivatives function"),
    ("unwritten", r"the attached ODE sim._odes\[0\] \(length 2\) leaves yDot\[1\] unwritten in "
                  r"its derivatives .* write every component, yDot\[1\] = 0.0 for a constant one"),
])
def test_an_attached_ode_that_returns_nan_or_leaves_ydot_unwritten_is_named(kind, match):
    """Not "the closest encounter" and a smaller min_dt: the ODE, the component, the way out."""
    from integrators import NonFiniteError
    sim, ode = _with_ode(kind)
    with pytest.raises(NonFiniteError, match=match) as info:
        sim.integrate(1.0)
    assert "closest encounter" not in str(info.value) and "min_dt" not in str(info.value)
    assert sim.t == 0.0 and (ode.y[0], ode.y[1]) == (1.0, 0.5)
    fixed, fode = _with_ode("written")            # the way out: every component written
    fixed.integrate(1.0)
    assert fode.y[0] == pytest.approx(0.5, rel=1e-12) and fode.y[1] == 0.5


def test_odes_without_particles_are_refused_with_the_way_out():
    """REBOUND's test_bs scene (a harmonic oscillator as the only ODE, no particles)."""
    rebound = pytest.importorskip("rebound")
    import math

    def derivatives_ho(ode, yDot, y, t):
        yDot[0], yDot[1] = y[1], -y[0]

    def scene(integrator):
        sim = rebound.Simulation()
        sim.integrator = integrator
        ode = sim.create_ode(length=2, needs_nbody=False)
        ode.derivatives = derivatives_ho
        ode.y[0], ode.y[1] = 1.0, 0.0
        return sim, ode

    sim, ode = scene("hbvm")
    with pytest.raises(ValueError, match=r"the simulation has no particles, only 1 attached ODE: "
                       r"HBVM integrates attached ODEs together with the particles .* integrate "
                       r"ODEs alone with sim.integrator = 'BS'"):
        sim.integrate(math.pi)
    assert sim.t == 0.0 and (ode.y[0], ode.y[1]) == (1.0, 0.0)
    sim, ode = scene("BS")                          # the way out
    sim.integrate(math.pi)
    assert ode.y[0] == pytest.approx(-1.0, abs=1e-8)


def test_kepler_field_at_a_short_step_warns_as_hbvmintegrator_does():
    """sim.integrator.kepler = 1 with REBOUND's default sim.dt (1/6283 of the period) warns as
    HBVMIntegrator(sim, kepler=True) does; a step given (dt=...) or long enough does not."""
    import warnings
    rebound = pytest.importorskip("rebound")
    from hbvm_md import HBVMIntegrator

    def scene():
        sim = rebound.Simulation()
        sim.add(m=1.0)
        sim.add(m=1e-3, a=1.0)
        sim.add(m=1e-3, a=1.6)
        return sim

    sim = scene()
    sim.integrator = "hbvm"
    sim.integrator.epsilon = 0
    sim.integrator.kepler = 1
    with pytest.warns(RuntimeWarning, match=r"sim.integrator.kepler = 1 steps sim.dt=0.001, "
                      r"1/6.28e\+03 of the shortest orbital period \(6.28\): the composed method "
                      r"is for long steps \(1/25 to 1/50 of it\); set sim.dt, e.g. sim.dt=0.126"):
        sim.integrate(0.003)
    with pytest.warns(RuntimeWarning, match=r"kepler=True steps sim.dt=0.001, .*pass dt=\.\.\., "
                                            r"e.g. dt=0.126") as caught:
        HBVMIntegrator(scene(), kepler=True)
    assert len(caught) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        chosen = scene()
        HBVMIntegrator(chosen, kepler=True, dt=0.001)
        chosen.integrate(0.003)
        long = scene()
        long.integrator = "hbvm"
        long.integrator.epsilon = 0
        long.integrator.kepler = 1
        long.dt = 0.1
        long.integrate(0.3)


def test_repr_of_a_fixed_step_run_does_not_say_adaptive():
    sim = _planet()
    assert re.search(r", adaptive=1, epsilon=[0-9.e+-]+,", repr(sim.integrator))
    sim.integrator.epsilon = 0          # IAS15's idiom: fixed steps of sim.dt
    text = repr(sim.integrator)
    assert "adaptive=1" not in text and ", adaptive=0 (epsilon=0: fixed steps of sim.dt)," in text
    sim.dt = 0.05
    sim.integrate(0.1)
    assert "adaptive=1" not in repr(sim.integrator)
    sim.integrator.epsilon = 1e-6       # adaptive again, as IAS15
    assert ", adaptive=1, epsilon=1e-06," in repr(sim.integrator)


def test_import_hbvm_md_loads_rebound_only_when_rebound_is_imported():
    """An ASE user's ``import hbvm_md`` does not import REBOUND; ``import rebound`` afterwards
    (or unpickling a simulation) registers "hbvm", as the README's order (rebound first) does."""
    import os
    import subprocess
    import sys
    import textwrap
    from pathlib import Path
    pytest.importorskip("rebound")
    root = str(Path(__file__).resolve().parents[1])
    code = textwrap.dedent('''
        import sys
        import hbvm_md
        from hbvm_md import HBVMDynamics
        assert "rebound" not in sys.modules, "import hbvm_md imported REBOUND"
        import rebound
        sim = rebound.Simulation()
        sim.add(m=1.0)
        sim.add(m=1e-3, a=1.0)
        sim.integrator = "hbvm"
        sim.integrate(0.5)
        print("OK", sim.t, sim.integrator)
    ''')
    env = dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["OK", "0.5", "hbvm"]


def test_nonfinite_error_of_a_calculator_is_named_with_rigid_bonds_too():
    from ase import Atoms
    from ase.constraints import FixLinearTriatomic
    atoms = Atoms("OCO", positions=[[0, 0, 0], [1.16, 0, 0], [2.32, 0, 0]])
    atoms.set_constraint(FixLinearTriatomic(triples=[(0, 1, 2)]))
    atoms.calc = NanForces(atoms.get_positions())
    atoms.set_momenta([[0, 0.1, 0], [0, 0, 0], [0, -0.1, 0]])
    pos0 = atoms.get_positions()
    with pytest.raises(NonFiniteError, match=r"the calculator NanForces returned a force that is "
                       r"not finite \(nan or inf\) on atom 0 at the positions the step starts "
                       r"from, so no smaller timestep helps") as info:
        HBVMDynamics(atoms, timestep=1 * units.fs).run(1)
    assert "coincident particles" not in str(info.value)
    assert np.array_equal(atoms.get_positions(), pos0)
