"""No import cycles among torchtrack's modules and the experiment scripts.

A static check over ``ast``: every ``import`` and ``from ... import`` in a module (at module level or inside a
function, where a cycle is only deferred; ``if TYPE_CHECKING:`` blocks excepted) is an edge to the module it names
(``from pkg import name`` names ``pkg.name`` when that is a module, else ``pkg``); a strongly connected component of
more than one module is a cycle. The experiment scripts are top-level modules (a script's own folder,
``experiments/<paper|eval|bench>/``, is on the path when it runs); the evaluation scripts share helpers through
``experiments/eval/common.py``, never through one another.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Known cycles, each one's set of modules: none (learn/dataset <-> learn/record was broken by moving the record
# command into learn/record_app.py). A new cycle fails the test; so does a known one that is gone.
KNOWN: set[frozenset[str]] = set()


def modules() -> dict[str, Path]:
    """{dotted name: file} for torchtrack's modules and the experiment scripts."""
    out = {}
    for path in sorted((ROOT / "torchtrack").rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    for path in sorted((ROOT / "experiments").rglob("*.py")):
        assert path.stem not in out, f"two experiment scripts named {path.stem}: {out[path.stem]} and {path}"
        out[path.stem] = path
    return out


def _type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The known modules that ``name`` imports."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    stack = [ast.parse(path.read_text())]
    while stack:
        node = stack.pop()
        if _type_checking(node):
            continue
        stack.extend(ast.iter_child_nodes(node))
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package, up level - 1
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*up, *([base] if base else [])])
            out |= {f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names}
    return {m for m in out if m in known and m != name}


def cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on, stack, out = set(), [], []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = set()
                while True:
                    w = stack.pop()
                    on.discard(w)
                    component.add(w)
                    if w == v:
                        break
                if len(component) > 1:
                    out.append(frozenset(component))
    return out


def graph() -> dict[str, set[str]]:
    mods = modules()
    return {name: imports(name, path, set(mods)) for name, path in mods.items()}


def test_the_cycle_finder_finds_a_cycle_and_only_cycles():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [frozenset("abc")]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_import_graph_is_read():
    g = graph()
    assert "torchtrack.config" in g["torchtrack.cli"] and "torchtrack.geometry" in g["torchtrack.image.select"]
    assert "common" in g["evaluate"] and "common" in g["eval_weighting"]


def test_no_import_cycles():
    found = set(cycles(graph()))
    new = found - KNOWN
    assert not new, f"import cycles: {[sorted(c) for c in new]}"
    gone = KNOWN - found
    assert not gone, f"known cycles gone, remove them from KNOWN: {[sorted(c) for c in gone]}"


def test_no_import_cycles_among_torchtrack_packages():
    """Nor among the packages (torchtrack.learn, .pipeline, .filter, ...; top-level modules count as their own): the
    tracker computes the cues (filter/cues.py) that learn/ trains on, and learn/ records through the tracker."""
    package = {m: ".".join(m.split(".")[:2]) for m in graph() if m.startswith("torchtrack.")}
    g: dict[str, set[str]] = {p: set() for p in package.values()}
    for m, deps in graph().items():
        if m in package:
            g[package[m]] |= {package[d] for d in deps if d in package and package[d] != package[m]}
    assert not cycles(g), f"package import cycles: {[sorted(c) for c in cycles(g)]}"


def test_no_script_imports_the_evaluation_scripts():
    """evaluate.py and eval_weighting.py are scripts, not libraries: their shared helpers live in common.py."""
    g = graph()
    users = {name for name, deps in g.items() if deps & {"evaluate", "eval_weighting"}}
    assert not users, f"import a script: {sorted(users)}"


def test_experiment_scripts_import_only_from_their_own_folder():
    """``python experiments/<sub>/<script>.py`` puts only ``experiments/<sub>/`` on the path: an import of a script
    in another folder works under pytest (all three are on its pythonpath) and fails when the script is run."""
    mods = modules()
    scripts = {name: path for name, path in mods.items() if not name.startswith("torchtrack")}
    assert {p.parent.name for p in scripts.values()} == {"paper", "eval", "bench"}
    g = graph()
    crossing = {
        (name, dep)
        for name, path in scripts.items()
        for dep in g[name]
        if dep in scripts and scripts[dep].parent != path.parent
    }
    assert not crossing, f"imports across experiments/ folders: {sorted(crossing)}"
