"""Committed files cite papers and books, not paths on a developer's machine; the REBOUND range
that pyproject declares is the one the adapter accepts."""
import pathlib
import re
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
# spelled in pieces so that this file does not match itself
MACHINE_PATHS = re.compile("|".join(["shared" + "/seed", "shared" + "/reference", "/tmp" + "/",
                                     "/ho" + "me/", "/wo" + "rk/", "/ro" + "ot/"]))


def _tracked_text_files():
    try:
        names = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                               check=True).stdout.split()
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    return [ROOT / n for n in names if n.endswith((".py", ".md", ".toml", ".cfg", ".txt"))]


def test_no_machine_specific_paths_in_committed_files():
    bad = [f"{p.relative_to(ROOT)}:{i + 1}" for p in _tracked_text_files() if p.exists()
           for i, line in enumerate(p.read_text(errors="replace").splitlines())
           if MACHINE_PATHS.search(line)]
    assert bad == []


def test_pyproject_declares_the_tested_rebound_range():
    """pyproject accepts exactly the REBOUND versions the adapter accepts (layout.SUPPORTED)."""
    import re
    from hbvm_md.rebound.layout import SUPPORTED
    low, high = re.match(r"REBOUND >= ([\d.]+), < ([\d.]+)", SUPPORTED).groups()
    text = (ROOT / "pyproject.toml").read_text()
    assert f'"rebound>={low},<{high}"' in text
    assert (low, high) == ("5.2", "6")


def test_other_rebound_major_versions_are_refused(monkeypatch):
    rebound = pytest.importorskip("rebound")
    from hbvm_md import HBVMIntegrator
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=1e-3, a=1.0)
    monkeypatch.setattr(rebound, "__version__", "4.4.3")
    with pytest.raises(RuntimeError, match=r"supports REBOUND >= 5\.2, < 6 .*got rebound 4\.4\.3: "
                                           r"pip install 'rebound>=5\.2,<6'"):
        HBVMIntegrator(sim, s=2, k=2, dt=0.01)
    assert sim.integrator == "ias15"     # nothing was attached
