"""The hbvm-md command line: every subcommand in --quick mode, --help, bad arguments."""
import re
import subprocess
import sys

import numpy as np
import pytest

from hbvm_md.cli import main
from hbvm_md.reports.progress import _Quiet, progress


@pytest.mark.parametrize("cmd", [[], ["demo"], ["bench"], ["spectrum"], ["hard-cases"]])
def test_help_on_every_subcommand(cmd, capsys):
    with pytest.raises(SystemExit) as ex:
        main(cmd + ["--help"])
    assert ex.value.code == 0
    assert "usage: hbvm-md" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["frobnicate"], r"invalid choice: 'frobnicate'"),
    (["spectrum", "x", "3"], r"argument K: expected a positive integer, got 'x'"),
    (["spectrum", "4", "0"], r"argument S: expected a positive integer, got '0'"),
    (["bench", "--scenes", "mars"], r"invalid choice: 'mars'"),
    (["hard-cases", "--case", "nope"], r"invalid choice: 'nope'"),
    (["demo", "--t-end", "-5"], r"argument --t-end: expected a positive number"),
])
def test_bad_arguments_exit_2_with_one_line(argv, message, capsys):
    with pytest.raises(SystemExit) as ex:
        main(argv)
    assert ex.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and re.search(message, err)


def test_spectrum_k_below_s_is_a_usage_error(capsys):
    assert main(["spectrum", "2", "3"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == ("hbvm-md spectrum: error: K must be >= S (got K=2, S=3); "
                           "HBVM(K, S) needs at least S nodes")


def test_spectrum_prints_tableau_and_isospectral_difference(capsys):
    assert main(["spectrum", "6", "3", "--quick"]) == 0
    out = capsys.readouterr().out
    assert "Butcher tableau" in out and "HBVM(6, 3)" in out
    diff = float(re.search(r"largest difference: (\S+)", out).group(1))
    assert diff < 1e-13
    assert main(["spectrum", "12", "2"]) == 0      # large K: tableau not printed, spectrum is
    out = capsys.readouterr().out
    assert "not printed" in out and float(re.search(r"largest difference: (\S+)", out).group(1)) < 1e-12


def test_hard_cases_quick(capsys):
    assert main(["hard-cases", "--quick", "--case", "step-too-large", "chaotic-henon-heiles"]) == 0
    out = capsys.readouterr().out
    assert "ConvergenceError" in out and "== chaotic-henon-heiles" in out


def test_bench_quick_writes_csv_png_markdown(tmp_path, capsys):
    out = tmp_path / "bench"
    assert main(["bench", "--quick", "--scenes", "henon-heiles", "kepler", "--out", str(out)]) == 0
    for name in ("workprecision.csv", "workprecision.md", "wp_henon-heiles.png", "wp_kepler.png"):
        assert (out / name).stat().st_size > 0
    csv = (out / "workprecision.csv").read_text().splitlines()
    assert csv[0].startswith("scene,method,family,param")
    md = (out / "workprecision.md").read_text()
    assert "HBVM s=2 (auto k)" in md and "DOP853" in md and "IAS15" in md and "what a larger k would have cost" in md
    assert "| max rel dL |" in md
    assert str(out / "workprecision.csv") in capsys.readouterr().out
    import csv as csvmod
    rows = list(csvmod.DictReader((out / "workprecision.csv").read_text().splitlines()))
    dL = {(r["scene"], r["method"], r["param"]): float(r["max_rel_angular_momentum_error"]) for r in rows}
    # Kepler e = 0.6 over 4 periods: the symplectic methods keep L at round-off, HBVM(k, 2)
    # (energy at round-off) loses it by ~5e-6 at 100 steps a period (h = 2 pi / 100)
    for (scene, method, _), v in dL.items():
        if scene == "kepler" and method.split("(")[0] in ("Gauss", "WHFast", "SABA", "leapfrog", "IAS15"):
            assert v < 1e-14, (method, v)
    assert 1e-6 < dL[("kepler", "HBVM s=2 (auto k)", "h=0.06283")] < 1e-4
    # Henon-Heiles has no angular momentum: the column is empty (nan), not a number
    assert all(np.isnan(v) for (scene, _, _), v in dL.items() if scene == "henon-heiles")


def test_demo_quick_writes_plots(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert str(out.resolve()) in text
    assert (out / "energy_outer_solar_system.png").stat().st_size > 0
    assert (out / "energy_md_cluster.png").stat().st_size > 0
    assert "ias15" in text.lower() and "VelocityVerlet" in text
    assert "max rel. angular momentum error" in text and "max abs(L-L0)/abs(L0)" in text
    # the MD section's cost beside VelocityVerlet's, and when VelocityVerlet is the better choice
    flat = " ".join(text.split())
    assert re.search(r"Cost: HBVM\(4, 2\) took [\d.]+x VelocityVerlet's force evaluations and "
                     r"[\d.]+x its wall time at the same timestep", flat), flat[-1500:]
    assert "HBVM's best case" in flat and "VelocityVerlet is the better choice" in flat


def test_python_dash_m_runs():
    r = subprocess.run([sys.executable, "-m", "hbvm_md", "spectrum", "3", "2"], capture_output=True, text=True)
    assert r.returncode == 0 and "largest difference" in r.stdout
    r = subprocess.run([sys.executable, "-m", "hbvm_md", "spectrum", "1"], capture_output=True, text=True)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1


def test_progress_is_quiet_off_a_terminal():
    assert isinstance(progress(range(3)), _Quiet)          # pytest captures stderr: not a TTY
    assert list(progress(range(3))) == [0, 1, 2]
    bar = progress(total=5, enabled=True)
    assert not isinstance(bar, _Quiet)
    bar.close()


def test_spectrum_says_when_conditioning_limits_the_check(capsys):
    # HBVM(60, 50): eigenvalue condition numbers ~1e17, the difference 2.6e-2 proves nothing
    assert main(["spectrum", "60", "50"]) == 0
    out = capsys.readouterr().out
    assert "isospectral check limited by conditioning" in out and "passed" not in out
    assert main(["spectrum", "6", "3"]) == 0
    assert "isospectral check passed" in capsys.readouterr().out


def test_spectrum_reports_a_failed_check(monkeypatch, capsys):
    import integrators
    true = integrators.gauss_spectrum
    monkeypatch.setattr(integrators, "gauss_spectrum", lambda s: true(s) + 1e-6)
    assert main(["spectrum", "6", "3"]) == 1
    assert "isospectral check FAILED" in capsys.readouterr().out


def test_demo_refuses_one_atom_before_running_anything(capsys, monkeypatch):
    import hbvm_md.reports.rebound_comparison as rc
    monkeypatch.setattr(rc, "compare_rebound", lambda *a, **k: pytest.fail("ran the solar system"))
    with pytest.raises(SystemExit) as ex:
        main(["demo", "--atoms", "1", "--quick"])
    assert ex.value.code == 2
    assert "argument --atoms: expected an integer >= 2, got '1'" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["outer_solar_system", "outer-solar-system", "Outer Solar System"])
def test_scene_names_accept_underscores_and_hyphens(name):
    from hbvm_md.reports.names import scene_key
    from hbvm_md.reports.rebound_comparison import _scene_factory
    from hbvm_md.reports.workprecision import SCENES
    assert scene_key(name) == "outer-solar-system" and scene_key(name) in SCENES
    assert _scene_factory(name)().N == 6
    with pytest.raises(ValueError, match="'_' or '-' alike"):
        _scene_factory("inner_solar_system")


def test_case_names_accept_underscores(capsys):
    assert main(["hard-cases", "--quick", "--case", "step_too_large"]) == 0
    assert "== step-too-large" in capsys.readouterr().out


def test_energy_plot_draws_magnitudes_of_signed_errors():
    from hbvm_md.reports.plots import plotted_error
    got = plotted_error([0.0, -5.6e-8, 3e-16, float("nan")])
    assert got[0] == 1e-17 and got[1] == 5.6e-8 and got[2] == 3e-16 and np.isnan(got[3])


def test_plots_put_the_angular_momentum_beside_the_energy(tmp_path, monkeypatch):
    """The work-precision figure gets a middle panel for the angular momentum on scenes where
    it is an invariant (a finite value in some row), and the energy-against-time figure one
    beside the energy when its series are given."""
    from hbvm_md.reports import plots
    panels = []
    save = plots._save
    monkeypatch.setattr(plots, "_save", lambda fig, path: (panels.append([a.get_ylabel() for a in fig.axes]),
                                                           save(fig, path))[1])
    row = dict(method="m", finished=True, wall_time_s=1.0, max_rel_energy_error=1e-15, solution_error=1e-9,
               max_rel_angular_momentum_error=float("nan"))
    plots.work_precision_plot([row], tmp_path / "a.png", "no L")
    plots.work_precision_plot([dict(row, max_rel_angular_momentum_error=3e-6)], tmp_path / "b.png", "L")
    series = {"m": (np.arange(3.0), np.array([0.0, 1e-15, 2e-15]))}
    plots.energy_error_plot(series, tmp_path / "c.png", "E")
    plots.energy_error_plot(series, tmp_path / "d.png", "E and L", angular_momentum=series)
    assert panels == [["max relative energy error", "final solution error (vs reference)"],
                      ["max relative energy error", "max relative angular momentum error",
                       "final solution error (vs reference)"],
                      ["|H - H0| / |H0|"], ["|H - H0| / |H0|", "|L - L0| / |L0|"]]
