"""The conservation audit of an ASE calculator (issue 50): jumps, non-conservative work and the
integrator's share, told apart by HBVM's own line integral."""
import pytest
from ase import units
from ase.calculators.lj import LennardJones

import hbvm_md
from hbvm_md.cli import main
from hbvm_md.reports.audit_scenes import EMT_CU_CUTOFF, ScaledForcesLJ, cu2_pair, lj_cluster

SCALE = 1.03


def cu2(distance=5.95, speed=0.02):
    return cu2_pair(distance, speed)


def test_emt_cu2_crossing_the_cutoff_is_one_jump_at_the_pair():
    atoms = cu2()
    report = hbvm_md.audit(atoms, 1 * units.fs, 8)
    assert len(report.jumps) == 1
    jump = report.jumps[0]
    assert jump.atoms == (0, 1) and jump.step == 1
    assert jump.distance == pytest.approx(EMT_CU_CUTOFF, abs=0.01)
    assert abs(jump.energy) == pytest.approx(1.6e-5, rel=0.2)
    assert 1.0 < jump.t < 2.0
    # the rest: no non-conservative work; the step's quadrature at the force's jump, measured
    assert abs(report.nonconservative_work) < 1e-12
    assert 0 < report.kink_error < 0.1 * abs(jump.energy)
    assert report.energy_change == pytest.approx(jump.energy + report.nonconservative_work,
                                                 abs=report.kink_error + 1e-12)
    assert report.meaningful
    assert atoms.get_distance(0, 1) < EMT_CU_CUTOFF                 # advanced as a run would
    text = str(report)
    assert "1 jump" in text and "crossed the calculator's cutoff 5.8768 A" in text


def test_scaled_forces_give_their_nonconservative_work_and_a_small_integrator_share():
    """F = 1.03 (-grad V): the work is -1.03 dV, so H changes by -0.03 dV."""
    atoms = lj_cluster(ScaledForcesLJ(SCALE, rc=10.0))
    v0 = atoms.get_potential_energy()
    report = hbvm_md.audit(atoms, 2 * units.fs, 12, sample=4)
    expected = -(SCALE - 1) * (atoms.get_potential_energy() - v0)
    assert abs(expected) > 1e-3
    assert report.jumps == []
    assert report.nonconservative_work == pytest.approx(expected, rel=1e-6)
    assert report.integrator_error < 1e-3 * abs(report.nonconservative_work)
    assert report.meaningful and "far below the calculator's own defects" in str(report)


def test_smooth_lennard_jones_cluster_has_no_jump_and_no_work():
    """ASE's LennardJones with smooth=True, the pairs in and beyond the smoothing shell
    (1.45 to 2.8 A) none of which crosses its ends on this path."""
    atoms = lj_cluster(LennardJones(smooth=True, rc=2.8, ro=1.45))
    report = hbvm_md.audit(atoms, 2 * units.fs, 12, sample=4)
    assert report.jumps == []
    assert abs(report.nonconservative_work) < 1e-10
    assert "conserves its energy on this path" in str(report) and report.meaningful


def test_plot_and_arguments(tmp_path):
    pytest.importorskip("matplotlib")
    report = hbvm_md.audit(cu2(), 1 * units.fs, 4, sample=2)
    report.plot(tmp_path / "audit.png")
    assert (tmp_path / "audit.png").stat().st_size > 0
    with pytest.raises(ValueError, match="`steps` must be a positive integer"):
        hbvm_md.audit(cu2(), units.fs, 0)
    with pytest.raises(ValueError, match="`timestep` must be a positive number"):
        hbvm_md.audit(cu2(), -1.0, 3)
    with pytest.raises(TypeError, match="do not pass energy_tol"):
        hbvm_md.audit(cu2(), units.fs, 3, energy_tol=None)


def test_cli_audit_on_a_structure_file(tmp_path, capsys):
    from ase.io import write
    path = tmp_path / "cu2.traj"
    write(path, cu2())
    assert main(["audit", str(path), "--calculator", "ase.calculators.emt:EMT",
                 "--steps", "8", "--timestep", "1"]) == 0
    out = capsys.readouterr().out
    assert "1 jump" in out and "atoms 0 and 1 crossed" in out
    assert main(["audit", str(path), "--calculator", "ase.calculators.emt:Nope"]) == 2
    assert "Nope" in capsys.readouterr().err


def test_tip3p_rigid_water_conserves_its_energy():
    """TIP3P (smooth switching before rc) on a rigid water dimer (FixBondLengths, held in the
    step): no jump, non-conservative work and the integrator's share at round-off."""
    from ase import Atoms
    from ase.calculators.tip3p import TIP3P, angleHOH, rOH
    from ase.constraints import FixBondLengths
    import numpy as np
    x = angleHOH * np.pi / 180 / 2
    water = Atoms("OH2", positions=[[0, 0, 0], [0, rOH * np.cos(x), rOH * np.sin(x)],
                                    [0, rOH * np.cos(x), -rOH * np.sin(x)]])
    atoms = water + water.copy()
    atoms.positions[3:] += [3.0, 0.2, 0.1]
    atoms.center(vacuum=6)
    atoms.calc = TIP3P(rc=5.0)
    atoms.set_constraint(FixBondLengths([(3 * i + j, 3 * i + (j + 1) % 3)
                                         for i in range(2) for j in range(3)]))
    atoms.set_momenta(np.random.default_rng(1).standard_normal((6, 3)) * 0.5)
    report = hbvm_md.audit(atoms, units.fs, 30)
    assert report.jumps == []
    assert abs(report.nonconservative_work) < 1e-12 and abs(report.integrator_error) < 1e-11


def test_a_structure_that_does_not_move_is_said_not_audited(tmp_path, capsys):
    """A perfect crystal with no momenta and no --temperature stays where it is: not "conserves
    its energy" but "did not move ... nothing was audited", with the way out, which moves it;
    --help gives the default k and why."""
    from ase.build import bulk
    from ase.io import write
    path = tmp_path / "cu.traj"
    write(path, bulk("Cu", cubic=True))
    assert main(["audit", str(path), "--calculator", "ase.calculators.emt:EMT", "--steps", "3"]) == 0
    out = capsys.readouterr().out
    assert "conserves its energy" not in out
    assert "The atoms did not move (largest displacement " in out
    assert "nothing was audited" in out and "--temperature K" in out
    assert "a sum of magnitudes" in out
    assert main(["audit", str(path), "--calculator", "ase.calculators.emt:EMT", "--steps", "3",
                 "--temperature", "300"]) == 0
    out = capsys.readouterr().out
    assert "did not move" not in out
    with pytest.raises(SystemExit):
        main(["audit", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default s + 4: four quadrature nodes beyond s make the quadrature's error " in text
