"""A calculator's own energy discontinuity does not stop HBVMDynamics (issue 46, item 4): EMT's
energy jumps by 1.6e-5 eV when a Cu2 pair crosses its neighbour list's cutoff, 5.8768 A; the
step's energy change then does not shrink with the step, so the step is accepted with one
CalculatorDiscontinuityWarning and the run goes on, on the true path."""
import warnings

import numpy as np
import pytest
from ase import units
from ase.md.verlet import VelocityVerlet

from hbvm_md import HBVMDynamics, UnresolvedStepError
from hbvm_md.ase.discontinuity import CalculatorDiscontinuityWarning, change_persists
from hbvm_md.reports.audit_scenes import EMT_CU_CUTOFF, cu2_pair

cu2 = cu2_pair


def test_cu2_collision_through_emts_cutoff_finishes_with_one_warning_a_crossing():
    """Before: UnresolvedStepError at the crossing, at any timestep.  Now: in and out through
    the cutoff, one warning each, naming the time, the pair and the jump; positions within
    1e-3 A of VelocityVerlet at 0.1 fs (bench_audit.py: 0.01 fs, and 0.5 fs too)."""
    atoms = cu2()
    dyn = HBVMDynamics(atoms, 1 * units.fs)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        dyn.run(200)
    ours = [w for w in seen if issubclass(w.category, CalculatorDiscontinuityWarning)]
    assert len(ours) == 2 and len(dyn.jumps) == 2
    assert atoms.get_distance(0, 1) > EMT_CU_CUTOFF               # collided and separated
    first = str(ours[0].message)
    assert "atoms 0 and 1 crossed the calculator's cutoff 5.8768 A" in first
    assert "the energy stepped by -1.590e-05 eV" in first and "t=2.053" in first
    assert "no integrator can conserve an energy that jumps" in first
    for jump, sign in zip(dyn.jumps, (-1, 1)):
        assert jump.atoms == (0, 1) and jump.distance == pytest.approx(EMT_CU_CUTOFF, abs=1e-4)
        assert sign * jump.energy == pytest.approx(1.59e-5, rel=0.01)
    ref = cu2()
    VelocityVerlet(ref, 0.1 * units.fs).run(2000)
    assert np.max(np.abs(atoms.positions - ref.positions)) < 1e-3


def test_the_warning_made_an_error_leaves_the_step_untaken():
    atoms = cu2(distance=5.95)
    dyn = HBVMDynamics(atoms, 1 * units.fs)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CalculatorDiscontinuityWarning)
        with pytest.raises(CalculatorDiscontinuityWarning, match="atoms 0 and 1"):
            dyn.run(10)
    assert atoms.get_distance(0, 1) > EMT_CU_CUTOFF and dyn.nsteps == 1
    assert dyn.jumps == []


def test_a_change_that_shrinks_with_the_step_is_still_refused():
    """The integrator's own error falls with the step: a strict energy_tol still refuses it
    (the jump test does not swallow it)."""
    atoms = cu2(distance=2.6, speed=0.02)
    dyn = HBVMDynamics(atoms, 5 * units.fs, s=1, k=1, energy_tol=1e-13)
    with pytest.raises(UnresolvedStepError, match=r"at t=0 fs changed the energy by \S+ "
                                                  r"\(relative, about \S+ eV\), more than "
                                                  r"energy_tol=1.0e-13"):
        dyn.run(5)


def test_energy_tol_is_an_argument_checked_by_name():
    atoms = cu2()
    assert HBVMDynamics(atoms, units.fs, energy_tol=1e-8).todict()["energy_tol"] == 1e-8
    with pytest.raises(ValueError, match="`energy_tol` must be 'auto', a positive number or None"):
        HBVMDynamics(atoms, units.fs, energy_tol=-1.0)


def test_change_persists_tells_a_jump_from_an_order_two_error():
    assert change_persists([1.6e-5, 1.6e-5, 1.59e-5])
    assert change_persists([2.6e-5, 2.1e-5, 1.8e-5])       # a jump and the kink's error
    assert not change_persists([1e-6, 1e-6 / 4, 1e-6 / 16])
    assert not change_persists([0.0, 0.0, 0.0])


def test_adaptive_steps_go_through_the_cutoff_with_the_same_warning():
    """Issue 58, item 4: adaptive steps shrank to h = 3.5e-16 at EMT's cutoff and raised
    StepSizeError; an inner step the energy check refuses is now tested for the calculator's
    jump as a fixed step is, and taken through it with one warning a crossing, at the same
    times as the fixed steps' (2.053 fs in, 141.752 fs out)."""
    atoms = cu2()
    dyn = HBVMDynamics(atoms, 1 * units.fs, adaptive=True)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        dyn.run(200)
    ours = [w for w in seen if issubclass(w.category, CalculatorDiscontinuityWarning)]
    assert len(ours) == 2 and len(dyn.jumps) == 2
    assert "t=2.053" in str(ours[0].message) and "t=141.75" in str(ours[1].message)
    assert "atoms 0 and 1 crossed the calculator's cutoff 5.8768 A" in str(ours[0].message)
    for jump, sign in zip(dyn.jumps, (-1, 1)):
        assert sign * jump.energy == pytest.approx(1.59e-5, rel=0.01)
    assert atoms.get_distance(0, 1) > EMT_CU_CUTOFF and dyn.inner_steps < 250
    ref = cu2()
    VelocityVerlet(ref, 0.1 * units.fs).run(2000)
    assert np.max(np.abs(atoms.positions - ref.positions)) < 1e-3


def test_adaptive_jump_made_an_error_leaves_the_atoms_as_they_were():
    atoms = cu2(distance=5.95)
    dyn = HBVMDynamics(atoms, 2 * units.fs, adaptive=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CalculatorDiscontinuityWarning)
        with pytest.raises(CalculatorDiscontinuityWarning, match="atoms 0 and 1"):
            for _ in range(10):
                pos, mom, n = atoms.get_positions(), atoms.get_momenta(), dyn.nsteps
                dyn.run(1)
    assert np.array_equal(atoms.get_positions(), pos) and np.array_equal(atoms.get_momenta(), mom)
    assert dyn.nsteps == n and dyn.jumps == []


def test_ase_messages_give_the_steps_own_time_in_fs_and_no_advice_of_adaptive_steps():
    """A refusal after the engine was rebuilt (the momenta rescaled from outside at 20 fs)
    names the step's own time, 20 fs (the fresh engine's clock says 0); an adaptive run's
    StepSizeError is in fs throughout, its quoted cause too, and advises neither adaptive
    steps nor HBVMDynamics' absent min_dt."""
    from ase.calculators.emt import EMT
    from ase.cluster import Icosahedron
    from ase.md.velocitydistribution import thermalize_momenta

    from integrators import StepSizeError
    atoms = Icosahedron("Cu", noshells=2)
    atoms.calc = EMT()
    thermalize_momenta(atoms, temperature_K=3000, rng=np.random.default_rng(1))
    dyn = HBVMDynamics(atoms, 1 * units.fs, s=2, k=3)
    dyn.run(20)
    atoms.set_momenta(atoms.get_momenta() * 1.01)            # a fresh engine, t = 0 there
    dyn.dt = 25 * units.fs
    pos = atoms.get_positions()
    with pytest.raises(UnresolvedStepError, match=r"size h=25 fs at t=20 fs does not resolve"):
        dyn.run(1)
    assert np.array_equal(atoms.get_positions(), pos) and dyn.nsteps == 20
    ad = HBVMDynamics(cu2(), 1 * units.fs, adaptive=True)
    cause = ("UnresolvedStepError: HBVM step of size h=2.18108e-17 at t=0.2016954 changed the "
             "energy by 1.228e-06 (relative), more than energy_tol=1.0e-06; use a smaller step "
             "(one that resolves the encounter: several steps over its closest approach), or "
             "adaptive steps")
    ad._clock0 = (20 * units.fs, 0.0)
    msg = str(ad._in_fs(StepSizeError(2.18108e-17, 0.0, 0.2016954, cause), ad._run_time))
    assert "h=2.18108e-17" not in msg and "t=0.2016954" not in msg
    assert msg.count(" fs") >= 4 and msg.count("at t=22.0534 fs") == 2, msg
    assert "adaptive steps" not in msg and "min_dt" not in msg, msg
