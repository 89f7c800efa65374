"""Every script in examples/ runs (in its quick mode where it has one) and prints its tables."""
import pathlib
import runpy
import sys

import pytest

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"

QUICK_ARGS = {
    "hbvm_vs_gauss.py": [],
    "md_cluster_and_copper.py": ["--quick"],
    "solar_system_rebound.py": ["--t-end", "2000"],
}


def test_every_example_is_covered():
    assert sorted(p.name for p in EXAMPLES.glob("*.py")) == sorted(QUICK_ARGS)


@pytest.mark.parametrize("name", sorted(QUICK_ARGS))
def test_example_runs(name, monkeypatch, capsys, tmp_path):
    pytest.importorskip("ase")
    pytest.importorskip("rebound")
    argv = QUICK_ARGS[name]
    if name != "hbvm_vs_gauss.py":
        argv = argv + ["--plot", str(tmp_path / "energy.png")]
    monkeypatch.setattr(sys, "argv", [name, *argv])
    runpy.run_path(str(EXAMPLES / name), run_name="__main__")
    out = capsys.readouterr().out
    assert "HBVM" in out
    if name != "hbvm_vs_gauss.py":
        assert (tmp_path / "energy.png").stat().st_size > 1000
