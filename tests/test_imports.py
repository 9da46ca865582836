"""The packages' modules import each other without cycles, function-level imports included
(issue 32): a cycle means two modules that cannot be understood, tested or loaded apart. And the
libraries they import on first use do not make compiled programs compile again."""

import ast
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("lvenv", "optim", "fe_oracle")


def _modules() -> dict[str, pathlib.Path]:
    out = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = path
    return out


def _graph(modules: dict[str, pathlib.Path]) -> dict[str, set[str]]:
    """Module → the modules it imports anywhere in its code (a name imported from a package
    resolves to its submodule where there is one; a package is not an edge of its own submodules)."""
    graph = {name: set() for name in modules}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            else:
                continue
            for target in targets:
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target and target != name and not name.startswith(target + "."):
                    graph[name].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm)."""
    index, low, stack, on, found, counter = {}, {}, [], set(), [], [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_cycle_finder_finds_a_cycle_through_a_function_level_import():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


@pytest.mark.parametrize("package", PACKAGES)
def test_no_module_imports_itself_through_others(package):
    graph = _graph(_modules())
    assert len(graph) > 30
    found = [c for c in cycles(graph) if any(m.split(".")[0] == package for m in c)]
    assert not found, f"import cycles: {found}"


#: Libraries that lvenv and optim import when a function first needs them (the posteriors' flows,
#: samplers and diagnostics), not when lvenv is imported.
LAZY_JAX_LIBRARIES = ("equinox", "flowjax.flows", "paramax", "optax", "blackjax", "emcee", "arviz_stats.base")


def test_a_library_imported_later_does_not_make_compiled_programs_compile_again():
    """Equinox imports ``jax.extend``, which adds settings to every jitted function's cache key
    (lvenv/__init__.py): imported after a program compiled, it would make that program compile
    again. In a fresh process, as a user's: a jitted function traces once across the imports."""
    code = ("import jax, jax.numpy as jnp, lvenv\n"
            "traced = []\n"
            "double = jax.jit(lambda x: traced.append(x.shape) or 2 * x)\n"
            "double(jnp.ones(3))\n"
            f"import {', '.join(LAZY_JAX_LIBRARIES)}\n"
            "double(jnp.ones(3))\n"
            "print(len(traced))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[-1] == "1", "the jitted function traced again after the imports"
