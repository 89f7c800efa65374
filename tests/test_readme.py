"""The README's quick start and .ci/run must not drift apart, and every python block of the README
and of the documentation's pages runs as written."""
import pathlib
import re
import textwrap

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _doc_pages():
    """README.md and the documentation's Markdown pages (not the build or the generated gallery)."""
    skip = {"_build", "auto_tutorials", "_generated", "figures"}
    pages = [p for p in DOCS.rglob("*.md") if not skip.intersection(p.relative_to(DOCS).parts)]
    return [ROOT / "README.md", *sorted(pages)]


def _quick_start_commands(path=ROOT / "README.md"):
    text = path.read_text()
    block = re.search(r"# Quick start.*?```bash\n(.*?)```", text, re.S)
    assert block, f"{path.name} has no quick-start bash block"
    return [line for line in block.group(1).splitlines() if line.strip()]


def test_quick_start_has_two_commands():
    cmds = _quick_start_commands()
    assert len(cmds) == 2
    assert "hbvm-md demo" in cmds[0]
    assert "pytest" in cmds[1]


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    assert _quick_start_commands()[1] in ci


def test_docs_quick_start_is_the_readme_s():
    assert _quick_start_commands(DOCS / "quickstart.md") == _quick_start_commands()


def test_readme_is_short():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 200


def _docs_build_command():
    text = (ROOT / "README.md").read_text()
    block = re.search(r"## Documentation.*?```bash\n(.*?)```", text, re.S)
    assert block, "README.md has no documentation build block"
    return [line for line in block.group(1).splitlines() if line.strip()]


def test_ci_builds_the_docs_as_the_readme_says():
    """CI builds the site with warnings as errors, with the README's command and the docs extra."""
    cmds = _docs_build_command()
    assert '-e ".[docs]"' in cmds[0] and "-W --keep-going" in cmds[1]
    ci = (ROOT / ".ci" / "run").read_text()
    assert ".[docs]" in ci and cmds[1] in ci
    assert "docs = [" in (ROOT / "pyproject.toml").read_text()


def test_results_page_includes_every_results_file():
    raw = (DOCS / "results" / "raw.md").read_text()
    for f in sorted((ROOT / "benchmarks" / "results").glob("*.md")):
        assert f"../../benchmarks/results/{f.name}" in raw, f"docs/results/raw.md misses {f.name}"


def test_every_tutorial_makes_a_figure():
    tutorials = sorted((DOCS / "tutorials").glob("plot_*.py"))
    assert len(tutorials) >= 5
    for t in tutorials:
        assert "plt.show()" in t.read_text(), t.name


def _python_blocks():
    """Every python block of the README and of the docs pages (indented ones, inside a list item,
    dedented), each once: a block repeated on a page (the README's examples) runs once."""
    blocks = []
    for page in _doc_pages():
        for b in re.findall(r"```python\n(.*?)```", page.read_text(), re.S):
            b = textwrap.dedent(b)
            if b not in blocks:
                blocks.append(b)
    return blocks


# -- every python block of the README and the docs runs here as written -------------------------
# Each block is found by a phrase it contains and runs in a fresh folder; `subs` are the only
# changes (each must still match the page, so that the two cannot drift apart), and are made
# where the block as written takes minutes:
#   - the ensemble block runs 4 members of 1e4 days instead of 16 of 1e7 (the records[3] it reads
#     exists either way);
#   - the comparison block runs 2e3 days and 20 MD steps instead of 2e4 and 100, the ASE block
#     30 steps of EMT instead of 100;
# `setup` gives a fragment the names it uses; `check` asserts what the block claims.
def _check_api(ns, out):
    # each printed energy error is at round-off, as the README says (the REBOUND run prints its
    # final error, which can be exactly 0.0)
    errors = [float(x) for x in re.findall(r"(?:=|:|error) (\d\.\d+e-\d+|0\.0)\b", out)]
    assert len(errors) == 4 and max(errors) < 1e-12, out


def _failing_run():
    """The names the StepError fragment uses: a run whose 4th step cannot converge."""
    from integrators import HBVM, StepError, integrate
    from systems import Kepler

    kep = Kepler(0.6)
    return dict(integrate=integrate, StepError=StepError, method=HBVM(4, 2), system=kep,
                y0=kep.initial_state(), h=1.0, steps=10)


def _kepler_run():
    """The names the MEGNO fragment uses: Kepler e = 0.3 over 100 periods (regular)."""
    import numpy as np

    from integrators import HBVM, integrate
    from systems import Kepler

    kep = Kepler(0.3)
    return dict(np=np, integrate=integrate, method=HBVM(6, 3), system=kep,
                y0=kep.initial_state(), h=kep.period / 100, steps=100 * 100)


def _check_megno(ns, out):
    res = ns["res"]
    assert res.extra["variational"].shape == (len(res.t), 1, 4)
    assert abs(res.extra["megno"][-1] - 2.0) < 0.1      # a regular orbit


def _check_failure(ns, out):
    res = ns["res"]
    assert res.status == "failed" and "did not converge" in res.message
    assert len(res.t) == res.steps + 1 and res.steps < 10


def _check_oscillator(ns, out):
    assert out.startswith("oscillator, 1000 steps: max |H-H0|/|H0| =")
    assert float(out.split("=")[-1]) < 1e-13


def _check_ensemble(ns, out):
    records = ns["records"]
    assert [r["status"] for r in records] == ["ok"] * 4
    assert records[3]["result"]["max_rel_energy_error"] < 1e-13
    assert (pathlib.Path("clones") / "ensemble.parquet").exists()


def _check_restart(ns, out):
    assert ns["sim"].t == 1e5 and ns["sim"].integrator == "hbvm"
    assert sorted(p.name for p in pathlib.Path(".").iterdir()) == ["run.bin"]   # no side file


def _check_readme_rebound(ns, out):
    assert ns["sim"].t == 1e5 and ns["sim"].integrator == "hbvm"
    assert float(out.split(":")[-1]) < 1e-13, out


def _check_readme_ase(ns, out):
    assert out.startswith("HBVM(") and len(ns["atoms"]) == 13
    assert float(out.split(":")[-1]) < 1e-8, out          # EMT: round-off and its cutoff's floor


def _check_notebook_pattern(ns, out):
    assert ns["sim"].t == 1000.0 and ns["sim"].integrator == "hbvm"
    assert out.split() == ["6", "8", "3e-15"], out         # the defaults the comment names


def _check_comparison(ns, out):
    assert "| HBVM(8,6) | adaptive |" in out and "| ias15 |" in out and "| whfast |" in out, out
    assert "| VelocityVerlet | 2 |" in out and "| HBVM(4, 2) | 2 |" in out, out


def _check_kepler_flow(ns, out):
    assert ns["status"] == -1 and ns["phi"].shape == (2, 6, 6)


def _check_audit(ns, out):
    assert "1 jump" in out and "crossed the calculator's cutoff 5.8768 A" in out, out
    assert pathlib.Path("audit.png").stat().st_size > 0


def _check_flow_composed(ns, out):
    err = float(out.split("relative energy error:")[1].split()[0])
    assert err < 1e-13, out
    assert ns["res"].y.shape[0] == 2


def _check_rebound_kepler(ns, out):
    assert ns["sim"].t == 1e5 and "kepler=True" in out, out
    assert float(out.split("energy error:")[1]) < 1e-13, out


def _mercury():
    """The gr_potential block's scene: the Sun and Mercury in years, AU and solar masses."""
    import rebound

    from hbvm_md import HBVMIntegrator
    sim = rebound.Simulation()
    sim.units = ("yr", "AU", "Msun")
    sim.add(m=1.0)
    sim.add(m=1.66e-7, a=0.387, e=0.2056)
    sim.move_to_com()
    return {"sim": sim, "HBVMIntegrator": HBVMIntegrator}


def _check_rebound_gr(ns, out):
    sim = ns["sim"]
    e0 = sim.energy() + ns["rebx"].gr_potential_potential(ns["gr"])
    sim.integrate(2.0)                              # eight orbits of Mercury, the force on
    e1 = sim.energy() + ns["rebx"].gr_potential_potential(ns["gr"])
    assert "kepler=1" in repr(sim.integrator) and abs(e1 - e0) < 1e-12 * abs(e0)


def _j2_example():
    """The harmonics block's scene: REBOUNDx's J2 example, a star and a planet at a = 0.1
    (G = 1), REBOUNDx imported."""
    import rebound
    import reboundx

    from hbvm_md import HBVMIntegrator
    sim = rebound.Simulation()
    sim.add(m=1.0)
    sim.add(m=3e-6, a=0.1, e=0.01, inc=0.5236)
    sim.move_to_com()
    return {"sim": sim, "HBVMIntegrator": HBVMIntegrator, "reboundx": reboundx}


def _check_rebound_harmonics(ns, out):
    sim, rebx = ns["sim"], ns["rebx"]
    e0 = sim.energy() + rebx.gravitational_harmonics_potential()
    sim.integrate(2.0)                              # ten orbits, the star's J2 on
    e1 = sim.energy() + rebx.gravitational_harmonics_potential()
    assert "kepler=1" in repr(sim.integrator) and abs(e1 - e0) < 1e-12 * abs(e0)
    assert rebx.gravitational_harmonics_potential() != 0.0


README_BLOCKS = {   # phrase: (substitutions, setup, check)
    "# 1. The core engine": ((), None, _check_api),
    "except StepError as err": ((), _failing_run, _check_failure),
    "variational=V0": ((), _kepler_run, _check_megno),
    "class Oscillator": ((), None, _check_oscillator),
    "run_ensemble(task": ((("t_end=1e7", "t_end=1e4"), ("range(16)", "range(4)")), None,
                          _check_ensemble),
    'rebound.Simulation("run.bin")': ((), None, _check_restart),
    'sim.units = ("day", "AU", "Msun")': ((), None, _check_readme_rebound),
    'Icosahedron("Cu", noshells=2)': ((("dyn.run(100)", "dyn.run(30)"),), None, _check_readme_ase),
    '# was: "ias15"': ((), None, _check_notebook_pattern),
    "kepler_flow_into(x, v, mu, 0.3, x, v)": ((), None, _check_kepler_flow),
    "FlowComposed.from_nbody(nb, h)": ((), None, _check_flow_composed),
    "HBVMIntegrator(sim, kepler=True, dt=500.0)": ((), None, _check_rebound_kepler),
    'rebx.load_force("gr_potential")': ((), _mercury, _check_rebound_gr),
    'load_force("gravitational_harmonics")': ((), _j2_example, _check_rebound_harmonics),
    "hbvm_md.audit(atoms": ((), None, _check_audit),
    "compare_rebound(": ((("t_end=2e4", "t_end=2e3"), ("steps=100", "steps=20")), None,
                         _check_comparison),
}


def test_every_readme_block_has_one_entry():
    blocks = _python_blocks()
    for block in blocks:
        hits = [p for p in README_BLOCKS if p in block]
        assert len(hits) == 1, f"python block without one entry in README_BLOCKS ({hits}):\n{block}"
    for phrase in README_BLOCKS:
        assert sum(phrase in b for b in blocks) == 1, f"no single python block contains {phrase!r}"


@pytest.mark.parametrize("phrase", list(README_BLOCKS))
def test_readme_block_runs_as_written(phrase, tmp_path, monkeypatch, capsys):
    subs, setup, check = README_BLOCKS[phrase]
    block = next(b for b in _python_blocks() if phrase in b)
    for old, new in subs:
        assert old in block, f"the block no longer has {old!r}: update README_BLOCKS"
        block = block.replace(old, new)
    monkeypatch.chdir(tmp_path)
    ns = setup() if setup else {}
    exec(compile(block, f"docs block ({phrase})", "exec"), ns)
    check(ns, capsys.readouterr().out)


def _inline_calls():
    """The calls the pages write inline (`method.integrate(...)`, `method.step(...)`)."""
    text = "\n".join(p.read_text() for p in _doc_pages())
    return [" ".join(c.split()) for c in re.findall(r"`(method\.(?:integrate|step)\(.*?\))`", text, re.S)]


def test_readme_inline_calls_run_as_written():
    """The signatures the README gives in prose run with the names they use (the adaptive one,
    `method.integrate(system, y0, h, t_end=T, adaptive=True, ...)`, raised "missing 1 required
    positional argument: 'steps'")."""
    import numpy as np

    from integrators import HBVM
    from systems import Kepler

    calls = _inline_calls()
    assert any("adaptive=True" in c for c in calls) and any("steps" in c for c in calls), calls
    kep = Kepler(0.6)
    names = dict(method=HBVM(6, 3), system=kep, y0=kep.initial_state(), y=kep.initial_state(),
                 h=0.1, T=2.0, steps=20)
    for call in calls:
        out = eval(call, {}, names)
        if "adaptive=True" in call:
            assert out.t[-1] == 2.0 and out.status == "finished", call
        elif "integrate" in call:
            assert out.steps == 20, call
        else:
            assert np.shape(out) == (4,), call
