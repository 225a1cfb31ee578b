"""The package's layout: no import cycle among jaxfit's modules, and the layers import
one way (shapes <- engine <- decomposition, detect, evaluation <- cli)."""

import ast
import importlib
from pathlib import Path

import jaxfit

ROOT = Path(jaxfit.__file__).resolve().parent


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, lazy: bool) -> set[str]:
    """The jaxfit modules ``path`` imports at module level (and inside its functions,
    with ``lazy``)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    tree = ast.parse(path.read_text())
    for node in (ast.walk(tree) if lazy else tree.body):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("jaxfit")}
        elif isinstance(node, ast.ImportFrom):
            base = importlib.util.resolve_name("." * node.level + (node.module or ""),
                                               package) if node.level else node.module
            if not base.startswith("jaxfit"):
                continue
            for alias in node.names:  # `from . import x` may name a submodule
                sub = f"{base}.{alias.name}"
                found.add(sub if (ROOT.parent / (sub.replace(".", "/") + ".py")).exists()
                          else base)
    return {m for m in found if m != name}


#: module -> the modules it imports, anywhere in it (a lazy import inside a function
#: still ties the two modules together) / at module level.
GRAPH = {module_name(p): imports(p, lazy=True) for p in ROOT.rglob("*.py")}
TOP = {module_name(p): imports(p, lazy=False) for p in ROOT.rglob("*.py")}


def test_no_import_cycle():
    done, path = set(), []

    def visit(node):
        if node in path:
            raise AssertionError("import cycle: " + " -> ".join(path[path.index(node):] + [node]))
        if node in done or node not in GRAPH:
            return
        path.append(node)
        for child in sorted(GRAPH[node]):
            visit(child)
        path.pop()
        done.add(node)

    for node in sorted(GRAPH):
        visit(node)


def test_layers_import_one_way():
    below = {  # a layer may not import these at module level
        "jaxfit.shapes": ("jaxfit.engine", "jaxfit.decomposition", "jaxfit.evaluation",
                          "jaxfit.io", "jaxfit.detect", "jaxfit.cli"),
        "jaxfit.engine": ("jaxfit.decomposition", "jaxfit.evaluation", "jaxfit.io",
                          "jaxfit.detect", "jaxfit.cli"),
        "jaxfit.io": ("jaxfit.engine", "jaxfit.decomposition", "jaxfit.evaluation",
                      "jaxfit.detect", "jaxfit.cli"),
    }
    # The one io module the engine reads: fit_batch converts its callers' sources (meshes,
    # paths, Open3D clouds) with it before any work.
    allowed = {"jaxfit.engine": {"jaxfit.io.inputs"}}
    for module, found in GRAPH.items():
        for layer, forbidden in below.items():
            if module == layer or module.startswith(layer + "."):
                bad = sorted(m for m in found if m.startswith(forbidden)
                             and m not in allowed.get(layer, ()))
                assert not bad, f"{module} imports {bad}"


def test_the_graph_is_read():
    # The check above must see real edges: the engine's fit imports its loop and options.
    assert {"jaxfit.engine.loop", "jaxfit.engine.options"} <= GRAPH["jaxfit.engine.fit"]
    assert "jaxfit.shapes" in GRAPH["jaxfit.engine.kernel"]
    assert "jaxfit.normals" in GRAPH["jaxfit.engine.cloud"] - TOP["jaxfit.engine.cloud"]
