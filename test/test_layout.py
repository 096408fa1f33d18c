"""The package's layout rules, checked on the source (ast; nothing is imported except for the
block check):

- the package is a stack of layer folders (LAYERS, low to high); a module imports nothing from a
  higher layer, and the imports between the package's modules have no cycle. Both count every
  import: at module level, inside functions and under `if TYPE_CHECKING:`;
- at most a handful of modules at the package root, and no source file over 500 lines;
- only perception_config/ros/ imports rclpy, perception_config_interfaces or perception_config.ros
  at module level (imports inside functions are how the higher layers reach ROS lazily);
- perception_config/blocks/ holds block modules (each defines a Block subclass) plus base.py,
  pipeline.py, features.py and __init__.py, and a block module imports no other block module:
  shared algorithms live in perception_config/vision/.

Module-level means executed on import: the module body, including `try`/`if` blocks and class
bodies, but not function bodies and not `if TYPE_CHECKING:` blocks. An import of a.b.c counts as
an edge to a.b.c only (not to the packages a and a.b that Python initialises first: a
submodule's own package is always being initialised already, so that edge is no cycle).
"""
from __future__ import annotations

import ast
import importlib
import inspect
from pathlib import Path

import pytest

PACKAGE = "perception_config"
ROOT = Path(__file__).resolve().parents[1] / PACKAGE

ROS_ONLY = ("rclpy", "perception_config_interfaces", f"{PACKAGE}.ros")
# The layer folders, low to high (docs/concepts/layout.md says what lives in each). `config` holds
# only data files; the package root's own modules (__init__, __main__) sit below everything.
LAYERS = ("config", "util", "core", "datasets", "vision", "blocks", "rl", "bench", "agents", "store", "learning",
          "online", "launcher", "ros", "cli")
MAX_ROOT_MODULES = 8
MAX_LINES = 500
BLOCKS_INFRASTRUCTURE = ("__init__", "base", "pipeline", "features", "verified")


def module_files() -> dict[str, Path]:
    """Dotted module name -> source file, for every module of the package."""
    out = {}
    for path in sorted(ROOT.rglob("*.py")):
        parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


MODULES = module_files()


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def module_level_imports(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    """The import statements executed when the module is imported (see the module docstring)."""
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                continue
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                found.append(child)
            elif isinstance(child, ast.If) and _is_type_checking(child.test):
                for other in child.orelse:
                    visit_node(other)
            else:
                visit(child)

    def visit_node(node: ast.AST) -> None:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found.append(node)
        elif not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            visit(node)

    visit(tree)
    return found


def imported_modules(name: str, path: Path, module_level: bool = True) -> set[str]:
    """Absolute names of everything `name` imports at module level (`module_level=False`: anywhere)
    (packages and modules of any distribution; `from X import y` names X.y when that is a module
    of this package, else X)."""
    is_package = path.name == "__init__.py"
    tree = ast.parse(path.read_text(), str(path))
    nodes = module_level_imports(tree) if module_level else [
        n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
    out: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
            continue
        if node.level:
            base = name.split(".") if is_package else name.split(".")[:-1]
            base = base[: len(base) - (node.level - 1)]
            target = ".".join(base + ([node.module] if node.module else []))
        else:
            target = node.module or ""
        for alias in node.names:
            sub = f"{target}.{alias.name}"
            out.add(sub if sub in MODULES else target)
    return out


def import_graph(module_level: bool = False) -> dict[str, set[str]]:
    """Import edges between the package's own modules: every import (`module_level=True`: only
    those executed on import)."""
    return {name: {m for m in imported_modules(name, path, module_level) if m in MODULES and m != name}
            for name, path in MODULES.items()}


def layer(module: str) -> int:
    """The index of `module`'s layer in LAYERS; -1 for the package root's own modules."""
    parts = module.split(".")
    if len(parts) == 1 or (len(parts) == 2 and f"{PACKAGE}.{parts[1]}" in MODULES
                           and not (ROOT / parts[1]).is_dir()):
        return -1
    assert parts[1] in LAYERS, f"{module}: not in a layer folder ({', '.join(LAYERS)})"
    return LAYERS.index(parts[1])


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle (as a path that returns to its start) of a directed graph, or None."""
    WHITE, GREY, BLACK = 0, 1, 2
    colour = dict.fromkeys(graph, WHITE)
    stack: list[str] = []

    def dfs(u: str) -> list[str] | None:
        colour[u] = GREY
        stack.append(u)
        for v in sorted(graph.get(u, ())):
            if colour.get(v, BLACK) == GREY:
                return stack[stack.index(v):] + [v]
            if colour.get(v) == WHITE:
                cycle = dfs(v)
                if cycle:
                    return cycle
        stack.pop()
        colour[u] = BLACK
        return None

    for node in sorted(graph):
        if colour[node] == WHITE:
            cycle = dfs(node)
            if cycle:
                return cycle
    return None


def test_the_graph_sees_relative_and_absolute_imports():
    graph = import_graph()
    assert f"{PACKAGE}.blocks.base" in graph[f"{PACKAGE}.blocks"]  # from .base import ...
    assert f"{PACKAGE}.vision.edges" in graph[f"{PACKAGE}.blocks.d2co"]  # from ..vision.edges import ...
    assert f"{PACKAGE}.datasets.bag.writer" in graph[f"{PACKAGE}.datasets.bag"]
    assert f"{PACKAGE}.core.geometry" in graph[f"{PACKAGE}.datasets.bag.frames"]  # from ...core.geometry import ...
    # an import inside a function counts, and one under TYPE_CHECKING
    assert f"{PACKAGE}.ros.cell_sim_run" in graph[f"{PACKAGE}.cli"] or any(
        m.startswith(f"{PACKAGE}.ros") for name, deps in graph.items() if name.startswith(f"{PACKAGE}.cli")
        for m in deps)
    assert f"{PACKAGE}.ros.cell_sim_run" not in import_graph(module_level=True).get(f"{PACKAGE}.cli", set())


def test_find_cycle_reports_the_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_imports_have_no_cycle():
    cycle = find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_no_module_imports_a_higher_layer():
    upward = [f"{name} imports {m}" for name, deps in import_graph().items() for m in sorted(deps)
              if layer(m) > layer(name)]
    assert not upward, "imports from a lower layer to a higher one: " + "; ".join(upward)


def test_layer_check_catches_an_upward_import():
    assert layer(f"{PACKAGE}.core.geometry") < layer(f"{PACKAGE}.blocks.icp") < layer(f"{PACKAGE}.ros.pick_node")
    assert layer(PACKAGE) == -1
    with pytest.raises(AssertionError, match="layer folder"):
        layer(f"{PACKAGE}.nowhere.module")


def test_a_handful_of_modules_at_the_root():
    root = sorted(p.name for p in ROOT.glob("*.py"))
    assert len(root) <= MAX_ROOT_MODULES, f"{len(root)} modules at the package root: {root}"
    folders = {p.name for p in ROOT.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert folders <= set(LAYERS), f"folders outside the layers: {sorted(folders - set(LAYERS))}"


def test_no_source_file_over_500_lines():
    long = [f"{p.relative_to(ROOT.parent)} ({n} lines)" for p in sorted(ROOT.rglob("*.py"))
            if (n := len(p.read_text().splitlines())) > MAX_LINES]
    assert not long, "split along their seams: " + "; ".join(long)


def test_only_ros_imports_ros_at_module_level():
    offenders = []
    for name, path in MODULES.items():
        if name == f"{PACKAGE}.ros" or name.startswith(f"{PACKAGE}.ros."):
            continue
        for m in sorted(imported_modules(name, path)):
            if any(m == r or m.startswith(r + ".") for r in ROS_ONLY):
                offenders.append(f"{name} imports {m}")
    assert not offenders, "module-level ROS imports outside perception_config/ros/: " + "; ".join(offenders)


BLOCK_MODULES = sorted(p.stem for p in (ROOT / "blocks").glob("*.py") if p.stem not in BLOCKS_INFRASTRUCTURE)


@pytest.mark.parametrize("module", BLOCK_MODULES)
def test_every_module_in_blocks_defines_a_block(module):
    from perception_config.blocks import Block

    mod = importlib.import_module(f"{PACKAGE}.blocks.{module}")
    blocks = [obj for _, obj in inspect.getmembers(mod, inspect.isclass)
              if issubclass(obj, Block) and obj is not Block and obj.__module__ == mod.__name__]
    assert blocks, f"blocks/{module}.py defines no Block subclass: non-block code belongs in vision/ or elsewhere"


def test_block_modules_do_not_import_each_other():
    allowed = {f"{PACKAGE}.blocks.{m}" for m in BLOCKS_INFRASTRUCTURE if m != "__init__"}
    offenders = []
    for module in BLOCK_MODULES:
        name = f"{PACKAGE}.blocks.{module}"
        for m in sorted(imported_modules(name, MODULES[name], module_level=False)):
            if (m == f"{PACKAGE}.blocks" or m.startswith(f"{PACKAGE}.blocks.")) and m not in allowed:
                offenders.append(f"{name} imports {m}")
    assert not offenders, "; ".join(offenders)
