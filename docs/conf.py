"""Sphinx configuration of the lvenv documentation (``make docs``; warnings are errors).

The results pages are written here, before Sphinx reads the sources, by the sections of
``lvenv report`` (:func:`optim.report.build_pages`), from the results under ``out/``, into
``_generated/`` (git-ignored), which is cleared first so that no page of an earlier build lingers.
The tutorial (``tutorial.md``, a MyST-NB text notebook) is executed at every build; an error in
it fails the build.
"""

import pathlib
import shutil
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
GENERATED = pathlib.Path(__file__).resolve().parent / "_generated"
sys.path.insert(0, str(ROOT))

from optim.report import build_pages  # noqa: E402  (needs the repository on sys.path)

shutil.rmtree(GENERATED, ignore_errors=True)
build_pages(ROOT / "out", GENERATED / "results")

project = "lvenv"
author = "the lvenv developers"
copyright = "the lvenv developers"  # noqa: A001  (Sphinx's name)

extensions = [
    "myst_nb",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx.ext.napoleon",
]
source_suffix = {".rst": "restructuredtext", ".md": "myst-nb"}  # .rst first: autosummary writes its stubs with the first
root_doc = "index"
exclude_patterns = ["_build"]
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3

# The tutorial runs at every build, in the build's Python (ipykernel's native kernel).
nb_execution_mode = "force"
nb_execution_raise_on_error = True
nb_execution_timeout = 300  # s per cell: a stuck cell fails the build instead of hanging it
nb_merge_streams = True

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
