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


def test_the_shipped_runs_are_read_when_the_cache_lacks_them(tmp_path, monkeypatch):
    """Each file the package ships (`scripts/ship_fe_runs.py`) is one run of the current oracle
    code under its own key, and `fe_oracle.run` answers a built-in heart's training beat from
    them when the cache is empty: from the cache, without computing or writing anything."""
    import fe_oracle
    from lvenv import presets

    shipped = sorted(cache.SHIPPED.glob("*.npz"))
    assert len(shipped) >= 40  # N and HF: passive curve, beats 1-3, 8 unseen scenarios and their 8 interior points each
    for path in shipped:
        meta = cache.load(cache.SHIPPED, path.stem).metadata
        assert meta["key"] == path.stem
        assert meta["code_version"] == cache.code_version(meta["backend"]), f"{path.name} is of older oracle code: run scripts/ship_fe_runs.py"
    monkeypatch.setenv("LVENV_FE_CACHE", str(tmp_path))
    heart = presets.normal()
    run = fe_oracle.run(heart.geometry, presets.training_circulation(2), cell=heart.cell, progress=False)
    assert run.from_cache and run.metadata["key"] in {p.stem for p in shipped} and run.log == []
    assert run.traces["V"].shape == run.traces["t"].shape and run.traces["t"][-1] > 0.9
    assert not list(tmp_path.iterdir())
