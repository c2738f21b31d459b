"""Sphinx configuration: the user guide (MyST Markdown), the API reference from the numpydoc
docstrings, and the examples as a sphinx-gallery, run at build time so that they cannot rot.

Build: ``pip install -e ".[docs]" && sphinx-build -W -b html docs docs/_build/html``.
"""
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
# the examples run at build time in their quick mode (coarse grids: the build stays under a few minutes
# on 2 cores); their outputs go to a scratch folder, not into the source tree
os.environ.setdefault("CILIA_EXAMPLE_QUICK", "1")
os.environ.setdefault("CILIA_EXAMPLE_OUT", str(ROOT / "docs" / "_build" / "example_out"))
os.environ.setdefault("MPLBACKEND", "Agg")

import single_cilium  # noqa: E402

project = "cilia-flow"
author = "the cilia-flow developers"
copyright = "2026, the cilia-flow developers"
release = single_cilium.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "numpydoc",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "auto_examples/*.ipynb", "auto_examples/*.py", "auto_examples/*.zip",
                    "auto_examples/*.json", "auto_examples/*.md5"]
myst_heading_anchors = 3
myst_enable_extensions = ["dollarmath"]

autosummary_generate = True
autodoc_default_options = {"members": True, "undoc-members": False, "show-inheritance": True}
autodoc_typehints = "none"          # numpydoc lists the types
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False

sphinx_gallery_conf = {
    "examples_dirs": str(ROOT / "examples"),
    "gallery_dirs": "auto_examples",
    "filename_pattern": r".*\.py",   # run every example, not only plot_*.py
    "download_all_examples": False,
    "remove_config_comments": True,
    "within_subsection_order": "FileNameSortKey",
    "abort_on_example_error": True,
}

html_theme = "alabaster"
html_title = "cilia-flow"
html_static_path = []


# ------------------------------------------------------------------------------ docstrings
# The docstrings write absolute values and norms as plain text, |x|, which reStructuredText reads as
# a substitution reference. Escape the bars outside inline literals and outside grid tables.
import re  # noqa: E402

_LITERAL = re.compile(r"(``.+?``)")


def _escape_bars(line: str) -> str:
    row = line.strip()
    if row.startswith("+") or (len(row) > 1 and row[0] == row[-1] == "|"):  # a grid table's border or row
        return line
    return "".join(part if part.startswith("``") else part.replace("|", r"\|") for part in _LITERAL.split(line))


def _plain_text_docstrings(app, what, name, obj, options, lines):
    for i, line in enumerate(lines):
        lines[i] = _escape_bars(line)


def setup(app):
    app.connect("autodoc-process-docstring", _plain_text_docstrings, priority=100)  # before numpydoc (500)
