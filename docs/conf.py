"""Sphinx configuration of the lvenv documentation (``make docs``; warnings are errors).

The results page is written here, before Sphinx reads the sources, by the same function as
``lvenv report`` (:func:`optim.report.build_report`), from the results under ``out/``.
"""

import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from optim.report import build_report  # noqa: E402  (needs the repository on sys.path)

build_report(ROOT / "out", pathlib.Path(__file__).resolve().parent / "_generated" / "results.md")

project = "lvenv"
author = "the lvenv developers"
copyright = "the lvenv developers"  # noqa: A001  (Sphinx's name)

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx.ext.napoleon",
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build"]
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3

napoleon_numpy_docstring = False
autosummary_generate = True
autodoc_typehints = "none"
autodoc_inherit_docstrings = False
autodoc_member_order = "bysource"
autodoc_default_options = {"members": True, "show-inheritance": False}
autodoc_mock_imports = ["dolfinx", "basix", "ufl", "petsc4py", "mpi4py", "gmsh"]

# Broken references to our own code fail the build; names of other libraries are not looked up.
nitpicky = True
nitpick_ignore_regex = [(r"py:.*", r"(?!(lvenv|optim|fe_oracle)\b).*")]

templates_path = ["_templates"]
html_theme = "furo"
html_title = "lvenv"
