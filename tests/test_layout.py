"""The package's imports flow one way: every module's `scenegen_jax` imports (at module level
or inside functions) are read with `ast`, grouped by part (a subpackage, or a top-level
module), and checked for cycles and for the layer rules below."""

from __future__ import annotations

import ast
import os

from conftest import REPO

PACKAGE = os.path.join(REPO, "scenegen_jax")
# The package's layers, bottom up (README.md, "Library layout"): a part imports only parts of
# lower layers. So the training code (`train`) is imported by the CLI alone: a scene's
# likelihood, sampling and evaluation only need parameters.
LAYERS = (
    ("jsonfile", "files", "config_fields", "locks", "signals"),
    ("config", "allocator", "backend", "recipes"),
    ("scene", "vector_map"),
    ("frame", "geometry"),
    ("checkpoint", "raster"),
    ("data", "distributions"),
    ("model",),
    ("workdir", "likelihood"),
    ("sampling",),
    ("pretrained",),
    ("train", "eval", "viz"),
    ("api",),
    ("cli",),
)


def _part(module: str) -> str:
    """'scenegen_jax.train.loop' -> 'train'; 'scenegen_jax.scene' -> 'scene'."""
    return module.split(".")[1]


def _is_part(name: str) -> bool:
    return os.path.isdir(os.path.join(PACKAGE, name)) or os.path.isfile(
        os.path.join(PACKAGE, name + ".py"))


def part_imports() -> dict[str, set[str]]:
    """{part: parts it imports}, over every module of the package."""
    out: dict[str, set[str]] = {}
    for root, _, files in os.walk(PACKAGE):
        for name in files:
            if not name.endswith(".py"):
                continue
            path = os.path.join(root, name)
            rel = os.path.relpath(path, REPO)[: -len(".py")].replace(os.sep, ".")
            rel = rel.removesuffix(".__init__")
            me = _part(rel) if rel != "scenegen_jax" else "scenegen_jax"
            with open(path) as f:
                tree = ast.parse(f.read(), path)
            for node in ast.walk(tree):
                names = []
                if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    names = [node.module]
                    if node.module == "scenegen_jax":  # modules only, not e.g. __version__
                        names = [f"scenegen_jax.{a.name}" for a in node.names
                                 if _is_part(a.name)]
                elif isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                for m in names:
                    if m.startswith("scenegen_jax.") and _part(m) != me:
                        out.setdefault(me, set()).add(_part(m))
    return out


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of the directed graph as a list of nodes, or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(node, path):
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt, path + [nxt])
                if found:
                    return found
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node, [node])
            if found:
                return found
    return None


def test_find_cycle_on_hand_made_graphs():
    assert find_cycle({"a": {"b"}, "b": {"c"}}) is None
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_no_import_cycle_between_parts():
    graph = part_imports()
    assert "train" in graph and "likelihood" in graph["train"]  # the walk sees real imports
    assert find_cycle(graph) is None, find_cycle(graph)


def layer_breaks(graph: dict[str, set[str]], layers) -> list[str]:
    """'a -> b' for each import of a part `b` from a part `a` of the same or a lower layer."""
    level = {part: i for i, parts in enumerate(layers) for part in parts}
    return sorted(f"{a} -> {b}" for a, deps in graph.items() for b in deps
                  if level[b] >= level[a])


def test_layer_breaks_on_hand_made_graphs():
    layers = (("a",), ("b", "c"))
    assert layer_breaks({"b": {"a"}, "c": {"a"}}, layers) == []
    assert layer_breaks({"a": {"b"}, "b": {"c"}}, layers) == ["a -> b", "b -> c"]


def test_every_part_has_a_layer():
    names = [name.removesuffix(".py") for name in os.listdir(PACKAGE)]
    parts = {n for n in names if n.isidentifier() and not n.startswith("__") and _is_part(n)}
    placed = {p for layer in LAYERS for p in layer}
    assert parts == placed, f"not in LAYERS: {parts - placed}; gone: {placed - parts}"


def test_imports_flow_down_the_layers():
    graph = part_imports()
    graph.pop("scenegen_jax", None)  # the package's own __init__ (imports no part)
    assert "cli" in graph and "train" in graph["cli"]  # the walk sees real imports
    assert not layer_breaks(graph, LAYERS), layer_breaks(graph, LAYERS)
