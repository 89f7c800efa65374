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
    assert "| max rel. angular momentum error |" in table and table.splitlines()[2].count("|") == 9
    t, dL = cmp.angular_momentum_series[h["method"]]
    assert t.shape == dL.shape == (40,) and np.all(dL >= 0)
    assert cmp.row("ias15")["max_rel_angular_momentum_error"] < 1e-14          # round-off
    assert h["max_rel_angular_momentum_error"] == dL.max()


def test_angular_momentum_column_separates_energy_from_symplecticity():
    """The column measures L, not the energy: HBVM(8, 2) at P_J / 20 keeps the energy at
    round-off and loses L by 4e-6 over 2e4 days (not symplectic); WHFast loses the energy by
    8e-8 and keeps L at round-off (symplectic); IAS15 keeps both."""
    cmp = hbvm_md.compare_rebound("outer_solar_system", t_end=2e4, hbvm=((2, None, 4332.6 / 20),),
                                  peers=("whfast", "ias15"), n_samples=20)
    h, wh, ias = cmp.rows
    assert h["max_rel_energy_error"] < 1e-13 and 1e-7 < h["max_rel_angular_momentum_error"] < 1e-4
    assert wh["max_rel_energy_error"] > 1e-8 and wh["max_rel_angular_momentum_error"] < 1e-13
    assert ias["max_rel_energy_error"] < 1e-13 and ias["max_rel_angular_momentum_error"] < 1e-14


def test_angular_momentum_change_is_that_of_rebounds_own_diagnostic():
    """angular_momentum_change on REBOUND states is the change of sim.angular_momentum() (the
    scene has only sources), relative to |L0|."""
    from hbvm_md.reports.rebound_comparison import _state, angular_momentum_change
    nb = outer_solar_system()
    sim = nb.to_rebound()
    L0, xv0 = np.array(sim.angular_momentum()), _state(sim)
    sim.particles[2].vx *= 1 + 1e-6                     # Saturn's velocity nudged
    sim.particles[4].z += 1e-3
    L1, xv1 = np.array(sim.angular_momentum()), _state(sim)
    got = angular_momentum_change(nb, np.stack([xv0, xv1]))
    assert got[0] == 0.0
    assert got[1] == pytest.approx(np.linalg.norm(L1 - L0) / np.linalg.norm(L0), rel=1e-9)


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


def test_requested_step_is_kept_and_attach_is_timed():
    # 300 does not divide the output interval 500: REBOUND shortens one step per interval
    # (300 + 200), so 40 intervals take 80 steps and the run still ends at t_end
    cmp = hbvm_md.compare_rebound("outer_solar_system", t_end=2e4, hbvm=((6, None, 300.0),),
                                  peers=("ias15",), n_samples=40)
    h = cmp.rows[0]
    assert h["dt"] == 300.0 and h["steps"] == 80 and h["final_t"] == 2e4
    # attaching (which chooses k) is part of the timed run
    assert 0 < h["setup_time_s"] <= h["wall_time_s"]
    assert h["compile_time_s"] is None


def test_heyoka_missing_is_a_clear_error(monkeypatch):
    import sys
    monkeypatch.setitem(sys.modules, "heyoka", None)
    with pytest.raises(ImportError, match=r"heyoka is not installed.*pip install 'hbvm-md\[bench\]'"):
        hbvm_md.compare_rebound("outer_solar_system", t_end=1e3, hbvm=(), peers=("heyoka",), n_samples=4)


def test_heyoka_peer_energy_and_positions():
    pytest.importorskip("heyoka")
    import numpy as np
    from hbvm_md.reports.rebound_comparison import EXTENDED
    nb = outer_solar_system()
    errs, pos = [], []
    for r in range(3):
        def make(r=r):
            sim = nb.to_rebound()
            for p in sim.particles[1:]:
                p.x *= 1 + r * 1e-13
            return sim
        cmp = hbvm_md.compare_rebound(make, t_end=2e4, hbvm=(), peers=("heyoka(compact)",), n_samples=40,
                                      reference=EXTENDED)
        row = cmp.rows[0]
        assert row["final_t"] == 2e4 and row["steps"] > 0 and row["compile_time_s"] > 0
        errs.append(row["max_rel_energy_error"])
        pos.append(row["final_position_diff"])
    # heyoka at tol = eps: round-off energy error, and the extended-precision reference agrees
    assert np.median(errs) < 1e-14
    assert np.median(pos) < 1e-11


def test_wall_time_leaves_out_the_energy_samples(monkeypatch):
    """The wall time is the integration's (attach included), not the energy and the state read
    at each output time, which heyoka's runs do not pay either: with a clock that only the energy evaluation
    advances, every run reports zero wall time (it reported n_samples when the energy was
    inside the timed region)."""
    from types import SimpleNamespace

    import rebound

    from hbvm_md.reports import rebound_comparison as rc

    ticks = [0.0]
    energy = rebound.Simulation.energy

    def ticking_energy(sim):
        ticks[0] += 1.0
        return energy(sim)

    state = rc._state

    def ticking_state(sim):
        ticks[0] += 1.0
        return state(sim)

    monkeypatch.setattr(rc, "time", SimpleNamespace(perf_counter=lambda: ticks[0]))
    monkeypatch.setattr(rebound.Simulation, "energy", ticking_energy)
    monkeypatch.setattr(rc, "_state", ticking_state)
    cmp = hbvm_md.compare_rebound("outer_solar_system", t_end=2e3, hbvm=((6, 7, 100.0),),
                                  peers=("ias15",), n_samples=10)
    # the energy and the state (for the angular momentum) were read at every output
    assert ticks[0] >= 2 * 2 * 10
    assert [r["wall_time_s"] for r in cmp.rows] == [0.0, 0.0]


def test_heyoka_rows_get_the_same_angular_momentum_column_without_heyoka():
    """_run_heyoka measures L from the states the peer returns, as _run does: checked with a
    stand-in solver that returns IAS15's states (heyoka itself is optional)."""
    from types import SimpleNamespace

    from hbvm_md.reports.rebound_comparison import _run_heyoka, _state

    nb = outer_solar_system()

    def propagate(xv0, ts):
        sim = nb.to_rebound()
        states = []
        for t in ts:
            sim.integrate(t)
            states.append(_state(sim).copy())
        return np.array(states), 0.0, int(sim.steps_done)

    fake = SimpleNamespace(propagate=propagate, compile_time=0.0)
    row, (t, err), x, (tl, dL) = _run_heyoka(lambda: nb.to_rebound(), "stand-in", fake, 2e4, 20)
    assert t.shape == tl.shape == dL.shape == (20,) and np.array_equal(t, tl)
    assert row["max_rel_angular_momentum_error"] == dL.max() and 0 < dL.max() < 1e-14
    assert row["max_rel_energy_error"] < 1e-14
