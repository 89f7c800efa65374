"""compare_md: same start for every run, the table's numbers, default_cluster stability."""
import numpy as np
import pytest
from ase import units

from hbvm_md import MDComparison, compare_md
from hbvm_md.reports.md_comparison import default_cluster, maxwell_boltzmann


def test_compare_md_rows_series_and_table(capsys):
    atoms, calc = default_cluster(13)
    res = compare_md(atoms, calc, timesteps_fs=(4.0, 8.0),
                     methods=("VelocityVerlet", ("HBVM", 2), ("HBVM", 1, 3)), steps=200,
                     temperature_K=300.0, seed=3)
    assert isinstance(res, MDComparison) and len(res.rows) == 6
    assert len({r["E0_eV"] for r in res.rows}) == 1           # one initial state for all runs
    for dt in (4.0, 8.0):
        vv, h42, h31 = res.row("VelocityVerlet", dt), res.row("HBVM(4, 2)", dt), res.row("HBVM(3, 1)", dt)
        assert vv["force_evals"] == 201                          # one per step + the initial one
        assert h42["force_evals"] > 4 * 200 and (h42["k"], h42["s"]) == (4, 2)
        assert h42["max_rel_dE"] <= 1e-13 and h31["max_rel_dE"] <= 1e-13
        assert vv["max_rel_dE"] > 1e3 * h42["max_rel_dE"]
        assert vv["max_abs_dE_per_atom_eV"] == pytest.approx(vv["max_rel_dE"] * abs(vv["E0_eV"]) / 13)
        t, err = res.series[f"HBVM(4, 2) dt={dt:g} fs"]
        assert t.shape == err.shape == (201,) and t[-1] == pytest.approx(200 * dt / 1000)
        assert err[0] == 0.0
        # the angular momentum about the centre of mass: Verlet keeps it at round-off, HBVM
        # with k > s (not symplectic) does not, and HBVM(3, 1) at order 2 loses it the most
        assert vv["max_rel_dL"] < 1e-13
        assert 1e-12 < h42["max_rel_dL"] < 1e-8 and h31["max_rel_dL"] > 1e2 * h42["max_rel_dL"]
        t, dL = res.angular_momentum_series[f"HBVM(4, 2) dt={dt:g} fs"]
        assert t.shape == dL.shape == (201,) and dL[0] == 0.0 and dL.max() == h42["max_rel_dL"]
    # the Verlet error grows like dt^2
    ratio = res.row("VelocityVerlet", 8.0)["max_rel_dE"] / res.row("VelocityVerlet", 4.0)["max_rel_dE"]
    assert 2.5 < ratio < 6.0
    out = capsys.readouterr().out
    assert out.strip() == res.table()
    assert res.table().count("\n") == 7 and "| HBVM(3, 1) | 8 | 200 |" in res.table()
    assert "| max abs(L-L0)/abs(L0) |" in res.table()


def test_compare_md_keeps_momenta_when_no_temperature_and_leaves_atoms_alone():
    atoms, calc = default_cluster(8)
    maxwell_boltzmann(atoms, 200.0, seed=5)
    pos, mom = atoms.get_positions(), atoms.get_momenta()
    res = compare_md(atoms, timesteps_fs=(5.0,), methods=("VelocityVerlet",), steps=20,
                     temperature_K=None, verbose=False)
    assert np.array_equal(atoms.get_positions(), pos) and np.array_equal(atoms.get_momenta(), mom)
    assert res.rows[0]["E0_eV"] == pytest.approx(atoms.get_potential_energy() + atoms.get_kinetic_energy(),
                                                 rel=1e-14)


@pytest.mark.parametrize("kwargs, match", [
    (dict(methods=("Leapfrog",)), "`methods` entries must be"),
    (dict(methods=(("HBVM", 3, 2),)), "`k` must be >= `s`"),
    (dict(steps=0), "`steps` must be an integer >= 1"),
    (dict(timesteps_fs=(-1.0,)), "`timesteps_fs` must be positive"),
    (dict(temperature_K=-5.0), "`temperature_K` must be >= 0"),
])
def test_compare_md_bad_input(kwargs, match):
    atoms, calc = default_cluster(4)
    with pytest.raises(ValueError, match=match):
        compare_md(atoms, calc, verbose=False, **kwargs)


def test_default_cluster_neither_collapses_nor_explodes():
    from hbvm_md import HBVMDynamics
    atoms, calc = default_cluster(38)
    assert len(atoms) == 38 and calc.polynomial_degree == 4
    maxwell_boltzmann(atoms, 300.0, seed=0)

    def rg():
        x = atoms.positions - atoms.positions.mean(axis=0)
        return np.sqrt(np.mean(np.sum(x * x, axis=1)))
    r0 = rg()
    sizes = []
    dyn = HBVMDynamics(atoms, 20 * units.fs)
    dyn.attach(lambda: sizes.append(rg()), interval=10)
    dyn.run(500)                         # 10 ps
    assert 0.7 * r0 < min(sizes) and max(sizes) < 1.4 * r0
    # nearest neighbours stay apart on average (no collapse onto one point)
    d = np.linalg.norm(atoms.positions[:, None] - atoms.positions[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    assert np.mean(d.min(axis=1)) > 1.0


def test_wall_time_leaves_out_the_observer(monkeypatch):
    """The wall time is the integration's, not the observer that records the energy and the
    state after every step: with a clock that only the observer's energy read advances, every
    run reports zero wall time (it reported one tick per step when the observer was timed)."""
    from types import SimpleNamespace

    from ase import Atoms

    from hbvm_md.reports import md_comparison as mc

    ticks = [0.0]
    kinetic = Atoms.get_kinetic_energy

    def ticking(self):
        ticks[0] += 1.0
        return kinetic(self)

    monkeypatch.setattr(mc, "time", SimpleNamespace(perf_counter=lambda: ticks[0]))
    monkeypatch.setattr(Atoms, "get_kinetic_energy", ticking)
    atoms, calc = default_cluster(6)
    res = compare_md(atoms, calc, timesteps_fs=(4.0,), methods=("VelocityVerlet", ("HBVM", 2)), steps=10,
                     verbose=False)
    assert ticks[0] >= 2 * 11
    assert [r["wall_time_s"] for r in res.rows] == [0.0, 0.0]


def test_angular_momentum_column_is_empty_where_L_is_no_invariant_and_a_start_at_rest_works():
    """A periodic cell exerts torques through its images: L is no invariant there, and the
    column says so (nan, printed "-") instead of a figure; a cluster starting at rest (L0 = 0,
    no scale at t = 0) gets a number, not an error."""
    from ase.build import bulk
    from ase.calculators.emt import EMT
    cu = bulk("Cu", cubic=True)
    res = compare_md(cu, EMT(), timesteps_fs=(5.0,), methods=("VelocityVerlet",), steps=5,
                     temperature_K=300.0, verbose=False)
    assert np.isnan(res.rows[0]["max_rel_dL"]) and "| - |" in res.table()
    atoms, calc = default_cluster(6)
    res = compare_md(atoms, calc, timesteps_fs=(5.0,), methods=("VelocityVerlet", ("HBVM", 2)), steps=20,
                     temperature_K=0.0, verbose=False)
    assert all(0.0 <= r["max_rel_dL"] < 1e-13 for r in res.rows)
