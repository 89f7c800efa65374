"""Sphinx configuration of hbvm-md's documentation.

Build (from the repository root, after ``pip install -e ".[docs]"``)::

    python -m sphinx -W --keep-going -b html docs docs/_build/html

The tutorials in ``docs/tutorials/`` are run by sphinx-gallery during the build (their figures
are made then); the results pages quote ``benchmarks/results/`` (``python docs/update_results.py``
pastes the tables between their markers).
"""
from __future__ import annotations

import os
import pathlib
import re
import sys

DOCS = pathlib.Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("MPLBACKEND", "Agg")

project = "hbvm-md"
author = "the hbvm-md developers"
copyright = "2026, the hbvm-md developers"
release = version = "0.1.0"

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "sphinx_gallery.gen_gallery",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "_generated", "figures/*.md", "tutorials", "auto_tutorials/*.ipynb",
                    "auto_tutorials/*.py", "auto_tutorials/*.zip", "**/*.md5",
                    "update_results.py"]
myst_enable_extensions = ["colon_fence", "dollarmath"]
myst_heading_anchors = 3

# The API pages document the public names (``hbvm_md.HBVMDynamics``, not the module that defines
# it); napoleon reads the numpydoc sections of the docstrings.
autodoc_member_order = "bysource"
autodoc_typehints = "description"
# (no "show-inheritance" key: Sphinx shows the bases whenever the key is present, False
# included, and HBVMIntegrator's page then named the engine's internal Counted; the classes
# whose base a reader needs ask for it: HBVMDynamics is an ASE MolecularDynamics)
autodoc_default_options = {"members": True}
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False

sphinx_gallery_conf = {
    "examples_dirs": ["tutorials"],
    "gallery_dirs": ["auto_tutorials"],
    "filename_pattern": r"/plot_",
    "within_subsection_order": "FileNameSortKey",
    "download_all_examples": False,
    "remove_config_comments": True,
    "plot_gallery": "True",
    "abort_on_example_error": True,
    "matplotlib_animations": False,
    "show_memory": False,
}

html_theme = "furo"
html_title = "hbvm-md"
html_static_path: list[str] = []
# the benchmarks' raw results are included into the results pages, not pages of their own
suppress_warnings: list[str] = []


def _write_cli_help(app) -> None:
    """Write each subcommand's ``--help`` into ``_generated/`` for the command-line page: the
    page shows what the installed parser says, never a copy that can drift."""
    from hbvm_md.cli import build_parser

    os.environ["COLUMNS"] = "100"         # argparse wraps its help to the terminal width
    out = DOCS / "_generated"
    out.mkdir(exist_ok=True)
    parser = build_parser()
    texts = {"hbvm-md": parser.format_help()}
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    for name, p in sub.choices.items():
        texts[f"hbvm-md {name}"] = p.format_help()
        for a in p._actions:      # nested subcommands (hbvm-md ensemble stability-map)
            if a.__class__.__name__ == "_SubParsersAction":
                for name2, p2 in a.choices.items():
                    texts[f"hbvm-md {name} {name2}"] = p2.format_help()
    for name, text in texts.items():
        (out / (name.replace(" ", "_") + ".txt")).write_text(text)


def _plain_bars(app, what, name, obj, options, lines) -> None:
    """The docstrings write absolute values and norms as in the papers, |T| + |V|; to
    reStructuredText a ``|...|`` is a substitution.  Escape every bar (the docstrings hold no
    reStructuredText tables or line blocks)."""
    for i, line in enumerate(lines):
        if "|" in line:        # not inside ``literals`` (the odd pieces of a split on ``)
            parts = line.split("``")
            lines[i] = "``".join(re.sub(r"(?<!\\)\|", r"\\|", part) if j % 2 == 0 else part
                                 for j, part in enumerate(parts))


def setup(app):
    app.connect("builder-inited", _write_cli_help)
    app.connect("autodoc-process-docstring", _plain_bars)
