"""The house rules, checked on the source: no import cycle between the package's modules (imports
inside functions count: hiding a cycle in a function does not remove it), no private name
imported from another module, the catalogue package free of ucad_cl. (``ruff check`` and ``mypy``
with pyproject.toml's settings run in scripts/test.sh before the suite.)"""
from __future__ import annotations

import ast
import sys
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("ucad_cl", "ucad_catalog")


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(f.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = f
    return mods


def _imports(name: str, path: Path, mods: dict[str, Path]):
    """(module imported, names imported from it, line) for every import of a package module,
    function-level ones included; ``if TYPE_CHECKING:`` blocks are skipped."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for n in ast.walk(node))
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] in PACKAGES:
                    yield a.name, [], node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                target = ".".join(base[:len(base) - node.level + 1] + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] not in PACKAGES:
                continue
            names = [a.name for a in node.names]
            # "from . import x" / "from pkg import submodule": the submodule is the import
            subs = [f"{target}.{n}" for n in names if f"{target}.{n}" in mods]
            for s in subs:
                yield s, [], node.lineno
            rest = [n for n in names if f"{target}.{n}" not in mods]
            if rest or not subs:
                yield target, rest, node.lineno


def _graph():
    mods = _modules()
    graph = {m: set() for m in mods}
    private = []
    for m, path in mods.items():
        for target, names, line in _imports(m, path, mods):
            while target not in mods and "." in target:
                target = target.rsplit(".", 1)[0]
            if target in mods and target != m:
                graph[m].add(target)
                for n in names:
                    if n.startswith("_") and not n.startswith("__"):
                        private.append(f"{path.relative_to(ROOT)}:{line}: {n} from {target}")
    return graph, private


def _cycles(graph) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), sorted."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]
    sys.setrecursionlimit(10000)

    def visit(v):
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
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def test_no_import_cycles():
    graph, _ = _graph()
    # a package __init__ re-exporting its submodules is not a cycle of design
    for m in graph:
        graph[m] = {t for t in graph[m] if not (t.startswith(m + ".") or m.startswith(t + "."))}
    assert _cycles(graph) == []


def test_the_cycle_finder_finds_cycles():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_private_names_imported_across_modules():
    _, private = _graph()
    assert private == []


def test_catalogue_package_does_not_import_ucad_cl():
    graph, _ = _graph()
    bad = sorted(f"{m} -> {t}" for m in graph if m.startswith("ucad_catalog")
                 for t in graph[m] if t.startswith("ucad_cl"))
    assert bad == []


MAX_LINES = 800


def test_long_modules_say_why():
    """A module over MAX_LINES lines says why it is one module: its docstring has a sentence
    with '800 lines' (CONTRIBUTING.md, 'The layout'). Otherwise split it by concern."""
    long = []
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            text = f.read_text(encoding="utf-8")
            n = len(text.splitlines())
            doc = ast.get_docstring(ast.parse(text)) or ""
            if n > MAX_LINES and f"{MAX_LINES} lines" not in doc:
                long.append(f"{f.relative_to(ROOT)}: {n} lines")
    assert long == [], ("split these modules by concern, or say in their docstring why they "
                        f"are one module of over {MAX_LINES} lines: {long}")
