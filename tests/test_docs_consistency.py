"""What the documentation says agrees with what the code does (issue 47, item 9): the ASE
guide's constraint table, HBVMDynamics' docstring, the REBOUND guide's advice, test markers a
reader can read."""
import ast
import pathlib
import re

from ase import constraints as ase_constraints

from hbvm_md.ase import HBVMDynamics
from hbvm_md.ase.constraints import UNSUPPORTED, classify

ROOT = pathlib.Path(__file__).resolve().parents[1]
ASE_GUIDE = (ROOT / "docs" / "guide" / "ase.md").read_text()


def _constraint(name: str):
    """An instance of ASE's constraint class ``name`` with small valid arguments."""
    cls = getattr(ase_constraints, name)
    args = {"FixAtoms": ([0],), "FixCom": (), "FixSubsetCom": ([0, 1],),
            "FixedPlane": (0, [0, 0, 1]), "FixedLine": (0, [0, 0, 1]), "FixCartesian": ([0],),
            "Hookean": (0, 1, 1.0, 1.0), "ExternalForce": (0, 1, 1.0),
            "FixBondLength": (0, 1), "FixBondLengths": ([(0, 1)],),
            "FixLinearTriatomic": ([(0, 1, 2)],)}[name]
    return cls(*args)


def test_ase_guide_lists_as_supported_only_what_runs_and_refuses_nothing_it_lists():
    rows = [line for line in ASE_GUIDE.splitlines() if line.startswith("| `")]
    supported = [r for r in rows if "refused" not in r.split("|")[2]]
    names = {n for r in supported for n in re.findall(r"`(\w+)`", r.split("|")[1])
             if hasattr(ase_constraints, n)}
    assert {"FixAtoms", "FixBondLengths", "FixLinearTriatomic", "Hookean"} <= names
    assert [n for n in sorted(names) if classify(_constraint(n)) == UNSUPPORTED] == []
    # (the guide once said "FixAtoms; other constraints are refused" above that table)
    assert "other constraints are refused" not in ASE_GUIDE


def test_ase_guide_advises_on_the_timestep_with_measured_numbers():
    section = ASE_GUIDE.split("## Choosing the timestep and s")[1].split("\n## ")[0]
    assert "{doc}`../results/md`" in section and "fs" in section and "eV per atom" in section


def test_hbvmdynamics_docstring_does_not_refuse_the_rigid_bonds_it_runs():
    doc = " ".join(HBVMDynamics.__doc__.split())
    assert not re.search(r"FixBondLength\(s\)[^.]*raise ``ValueError``", doc)
    assert "FixLinearTriatomic" in doc and "NotImplementedError" in doc


def test_rebound_guide_says_when_not_to_use_hbvm_with_the_results():
    guide = (ROOT / "docs" / "guide" / "rebound.md").read_text()
    section = guide.split("## When not to use HBVM")[1].split("\n## ")[0]
    assert "{doc}`../results/rebound`" in section
    assert all(word in section for word in ("WHFast", "heyoka", "IAS15"))


def test_skip_and_xfail_reasons_are_short():
    """A reason is printed on every run (-ra): a line, not a paragraph (the detail belongs in a
    comment beside the test)."""
    long = []
    for path in sorted((ROOT / "tests").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.keyword) and node.arg == "reason" and isinstance(
                    node.value, ast.Constant) and isinstance(node.value.value, str):
                if len(node.value.value) > 200:
                    long.append(f"{path.name}:{node.value.lineno} ({len(node.value.value)} chars)")
    assert long == []


def test_api_pages_do_not_show_internal_base_classes():
    """Sphinx shows a class's bases whenever ``show-inheritance`` is among autodoc's default
    options, set to False included: HBVMIntegrator's page named the engine's internal
    ``Counted``.  The option is asked for where a reader needs the base."""
    conf = (ROOT / "docs" / "conf.py").read_text()
    defaults = re.search(r"^autodoc_default_options = (\{.*?\})", conf, re.M | re.S).group(1)
    assert "show-inheritance" not in defaults
    api = (ROOT / "docs" / "api" / "hbvm_md.rst").read_text()
    integrator = api.split(".. autoclass:: HBVMIntegrator")[1].split(".. auto")[0]
    assert ":show-inheritance:" not in integrator


# -- issue 58, item 8 ---------------------------------------------------------------------------
def test_ase_guide_gives_hbvmdynamics_signature_in_its_order():
    import inspect
    params = [p for p in inspect.signature(HBVMDynamics.__init__).parameters.values()
              if p.name != "self" and p.kind is not p.VAR_KEYWORD]
    wanted = ", ".join(p.name if p.default is p.empty else f"{p.name}={p.default!r}"
                       for p in params).replace("'", '"')
    flat = " ".join(ASE_GUIDE.split())
    assert f"`HBVMDynamics({wanted})`" in flat, wanted


def test_quickstart_says_which_subcommands_take_quick():
    from hbvm_md.cli import build_parser
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")

    def has_quick(p):
        if any("--quick" in a.option_strings for a in p._actions):
            return True
        inner = [a for a in p._actions if a.__class__.__name__ == "_SubParsersAction"]
        return bool(inner) and all(has_quick(q) for q in inner[0].choices.values())

    without = sorted(name for name, p in sub.choices.items() if not has_quick(p))
    text = " ".join((ROOT / "docs" / "quickstart.md").read_text().split())
    assert without == ["compile"]
    assert "all but `compile` (which compiles what it is asked) take `--quick`" in text
    assert "each has `--help` and `--quick`" not in text


def test_rebound_guide_quotes_the_readmes_time_against_ias15():
    readme = (ROOT / "README.md").read_text()
    guide = " ".join((ROOT / "docs" / "guide" / "rebound.md").read_text().split())
    ratio = re.search(r"IAS15's energy error \([^)]*\) in ([\d.]+)x IAS15's time", readme).group(1)
    assert f"({ratio}x on REBOUND's outer solar system over 1000 Jupiter years" in guide
    assert "about half of IAS15's time" not in guide


def test_api_page_documents_the_ensemble_names_where_run_ensemble_is():
    """Sphinx's viewcode links a module's objects under the first one's module: run_ensemble,
    load_store and EnsembleStoreWarning (one source module) are all documented as hbvm_md.*,
    so the source page's back-links land (they were #hbvm_md.load_store on an anchor
    hbvm_md.ensemble.load_store)."""
    import hbvm_md
    from hbvm_md import ensemble
    api = (ROOT / "docs" / "api" / "hbvm_md.rst").read_text()
    part = api.split("Ensembles\n---------")[1].split("\n---")[0]
    for directive in (".. autofunction:: run_ensemble", ".. autofunction:: load_store",
                      ".. autoclass:: EnsembleStoreWarning"):
        assert directive in part
    assert "currentmodule" not in part and "hbvm_md.ensemble.load_store" not in part
    assert hbvm_md.load_store is ensemble.load_store
    assert hbvm_md.EnsembleStoreWarning is ensemble.EnsembleStoreWarning


def test_no_section_title_carries_an_issue_number():
    pages = [*(ROOT / "docs").rglob("*.md"), *(ROOT / "benchmarks" / "results").glob("*.md")]
    bad = [f"{p.relative_to(ROOT)}: {line}" for p in pages if "_build" not in p.parts
           for line in p.read_text().splitlines()
           if line.startswith("#") and re.search(r"\bissues? \d+", line)]
    assert bad == []
