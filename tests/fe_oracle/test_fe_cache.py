"""The oracle cache's code version: documentation edits keep it, code edits change it."""

from fe_oracle import cache

SOURCE = '''"""Module doc."""
import math


def f(x):
    """Doc of f."""
    # a comment
    return math.sqrt(x) * 2.0


class A:
    """Doc of A."""

    def g(self):
        """Only a docstring."""
'''


def test_code_version_ignores_docstrings_comments_and_layout_but_not_code():
    documented = SOURCE.replace("Doc of f.", "Square root, doubled (mm).").replace("# a comment", "# another comment\n\n")
    assert cache.code_text(documented) == cache.code_text(SOURCE)
    assert cache.code_text(SOURCE.replace("* 2.0", "* 2.5")) != cache.code_text(SOURCE)
    assert cache.code_text(SOURCE.replace("math.sqrt(x)", "math.sqrt(x + 0)")) != cache.code_text(SOURCE)
    # a docstring that is a function's whole body leaves a body that still parses and differs from an empty one
    assert "Pass" in cache.code_text(SOURCE)
    assert len(cache.code_version("dolfinx")) == 16
