"""compare_rebound: HBVM against REBOUND's integrators in one process."""
import numpy as np
import pytest

import hbvm_md
from systems import NBody, outer_solar_system, solar_system


def test_outer_solar_system_table():
    cmp = hbvm_md.compare_rebound("outer_solar_system", t_end=2e4, hbvm=((6, None, 100.0),),
                                  peers=("whfast", "saba(10,6,4)", "leapfrog", "ias15"), n_samples=40)
    assert [r["method"].split("(")[0] for r in cmp.rows] == ["HBVM", "whfast", "saba", "leapfrog", "ias15"]
    assert cmp.reference == "ias15" and cmp.row("ias15")["final_position_diff"] == 0.0
    h = cmp.rows[0]
    assert h["max_rel_energy_error"] < 1e-14 and h["final_position_diff"] < 1e-10   # one draw: loose
    assert cmp.row("whfast")["max_rel_energy_error"] > 1e3 * h["max_rel_energy_error"]
    assert h["steps"] == 200 and h["dt"] == 100.0
    t, e = cmp.series[h["method"]]
    assert t.shape == e.shape == (40,) and t[-1] == pytest.approx(2e4)
    table = cmp.table()
    assert table.count("\n") == 2 + len(cmp.rows) and "vs ias15" in table


def test_scene_from_astropy_and_errors():
    sc = solar_system("2000-01-01T12:00:00", bodies=("sun", "jupiter", "saturn"), include_inner_in_sun=True)
    cmp = hbvm_md.compare_rebound(sc, t_end=1e4, hbvm=((6, 8),), peers=("ias15",), n_samples=10)
    assert cmp.rows[0]["max_rel_energy_error"] < 1e-14          # one draw: loose
    with pytest.raises(ValueError, match="`scene` must be"):
        hbvm_md.compare_rebound("inner_solar_system", t_end=1.0)
    with pytest.raises(ValueError, match="`hbvm` entries must be"):
        hbvm_md.compare_rebound("outer_solar_system", t_end=1.0, hbvm=((6,),), peers=())


def test_hbvm_row_at_round_off_median_over_perturbed_starts():
    """The table's HBVM energy error is at round-off: a bound on the median of five starts moved
    by 1e-13 AU (a single draw is the maximum of a random walk)."""
    nb = outer_solar_system()
    errs = []
    for seed in range(5):
        moved = nb.positions + 1e-13 * np.random.default_rng(seed).standard_normal(nb.positions.shape)
        scene = NBody(nb.body_masses, G=nb.G, positions=moved, velocities=nb.velocities, names=nb.names)
        cmp = hbvm_md.compare_rebound(scene, t_end=2e4, hbvm=((6, None, 100.0),), peers=(), n_samples=40)
        errs.append(cmp.rows[0]["max_rel_energy_error"])
    assert np.median(errs) <= 3e-15, errs
