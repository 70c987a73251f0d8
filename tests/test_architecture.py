"""The import graph of `normpos_grasp` runs one way: no package cycles and no import upward in the layer order.

Every module is parsed with `ast` (imports at any depth, inside functions and `TYPE_CHECKING` blocks included,
relative forms resolved); an import counts for the top-level package ("unit") it lands in. Generated and data
folders (robot_models/, examples/) are not code of the library and are skipped.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import pkgutil
from collections import defaultdict
from functools import lru_cache
from pathlib import Path

PACKAGE = "normpos_grasp"
ROOT = Path(__file__).resolve().parents[1] / PACKAGE
EXCLUDED = ("robot_models", "examples")

# Bottom first: a unit may import only units listed before it (and itself).
LAYERS: tuple[str, ...] = (
    # foundation: no normpos_grasp imports but each other
    "errors",
    "models",  # the bundled ONNX model files (no code)
    "hosts",  # loopback address checks (standard library only)
    "atomic",  # files replaced only when completely written (standard library only)
    "interrupts",  # SIGINT/SIGTERM as exceptions, worker start-up (standard library and errors only)
    "typing",
    "validation",
    "geometry",
    # the records every stage hands the next (Instance, NormPosition, Template, TemplateFit, GraspCandidate,
    # Target, PickPlan, ToolModel)
    "records",
    # sensors and files
    "camera",
    "io",
    # engines, and the cell they work in
    "kinematics",  # also the planner's ArmModel
    "collision",
    "cell",
    "sim",  # scene synthesis, rendering, physics judge, UR controller emulator
    # stages
    "measure",
    "templates",
    "perception",  # above templates: the cad detector finds templates in the whole scene (perception.cad_detector)
    "grasp",
    "planning",
    "execution",
    "watch",  # zone watch during motion, per-frame drift check (uses a driver only through request_stop)
    # one frame, then the applications around it
    "pipeline",
    "realsense_source",
    "report",
    "replay",  # replay bundles: one loop cycle saved, re-run offline and compared
    "simulate",
    "loop",
    "training",
    "demo",
    "teach",  # CAD to a ready part: symmetry, resting poses, grasps validated in physics, report
    "warmup",  # install-time compilation of every stage's kernels
    "cli",
    # the package's own __init__ (version only)
    PACKAGE,
)

Edges = dict[tuple[str, str], list[str]]


def module_name(path: Path, root: Path) -> tuple[str, bool]:
    """Dotted name of the module at `path` and whether it is a package `__init__`."""
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    is_package = parts[-1] == "__init__"
    if is_package:
        parts = parts[:-1]
    return ".".join(parts), is_package


def imported_modules(tree: ast.AST, module: str, is_package: bool) -> list[tuple[str, int]]:
    """(absolute target, line) of every import in `tree`; `from a import b` yields `a.b` (b may be a name)."""
    package = module if is_package else module.rpartition(".")[0]
    out: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((alias.name, node.lineno) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")
                if node.level - 1 >= len(base_parts):
                    raise ValueError(f"{module}:{node.lineno}: relative import beyond the top package")
                base = ".".join(base_parts[: len(base_parts) - (node.level - 1)])
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module or ""
            out.extend((f"{base}.{alias.name}", node.lineno) for alias in node.names)
    return out


def unit_of(module: str) -> str:
    """The top-level package (or module) of `module` inside PACKAGE; PACKAGE itself for the root."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def import_graph(root: Path = ROOT) -> tuple[set[str], Edges]:
    """(units, edges between different units with 'module:line -> target' evidence)."""
    units: set[str] = set()
    edges: Edges = defaultdict(list)
    for path in sorted(root.rglob("*.py")):
        if path.relative_to(root).parts[0] in EXCLUDED:
            continue
        module, is_package = module_name(path, root)
        source = unit_of(module)
        units.add(source)
        for target, line in imported_modules(ast.parse(path.read_text(encoding="utf-8")), module, is_package):
            if target != PACKAGE and not target.startswith(PACKAGE + "."):
                continue
            dest = unit_of(target.removesuffix(".*"))
            if dest != source:
                edges[(source, dest)].append(f"{module}:{line} -> {target}")
    return units, dict(edges)


@lru_cache(maxsize=1)
def package_graph() -> tuple[set[str], Edges]:
    """`import_graph` of the package, parsed once per test session."""
    return import_graph()


def package_cycles(edges: Edges) -> list[list[str]]:
    """Strongly connected components with more than one unit (Tarjan)."""
    graph: dict[str, set[str]] = defaultdict(set)
    for a, b in edges:
        graph[a].add(b)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def upward_imports(edges: Edges, layers: tuple[str, ...] = LAYERS) -> list[str]:
    """Evidence lines of every import from a unit to one listed after it in `layers`."""
    rank = {name: i for i, name in enumerate(layers)}
    out = []
    for (a, b), evidence in sorted(edges.items()):
        if a in rank and b in rank and rank[b] > rank[a]:
            out.extend(f"{a} -> {b}: {e}" for e in evidence)
    return out


def test_every_unit_has_a_layer() -> None:
    units, _ = package_graph()
    assert sorted(units - set(LAYERS)) == [], "new package: place it in LAYERS"
    assert len(set(LAYERS)) == len(LAYERS)


def test_no_package_cycles() -> None:
    _, edges = package_graph()
    cycles = package_cycles(edges)
    detail = []
    for cycle in cycles:
        detail.append("cycle: " + ", ".join(cycle))
        detail.extend(f"  {a} -> {b}: {e}" for (a, b), ev in sorted(edges.items()) if {a, b} <= set(cycle) for e in ev)
    assert cycles == [], "package cycles:\n" + "\n".join(detail)


def test_no_upward_imports() -> None:
    _, edges = package_graph()
    upward = upward_imports(edges)
    assert upward == [], (
        "imports going up the layer order (bottom first: " + ", ".join(LAYERS) + "):\n" + "\n".join(upward)
    )


def test_records_are_frozen_dataclasses() -> None:
    import normpos_grasp.records as records

    classes = {}
    for info in pkgutil.iter_modules(records.__path__):
        module = importlib.import_module(f"{records.__name__}.{info.name}")
        own = {name: obj for name, obj in vars(module).items() if inspect.isclass(obj)}
        classes.update({name: obj for name, obj in own.items() if obj.__module__ == module.__name__})
    expected = {"Instance", "NormPosition", "Template", "TemplateFit", "GraspCandidate", "Target", "PickPlan"}
    expected |= {"ToolModel", "ToolShape", "Evaluation", "Waypoint", "Trajectory", "OrientedBox", "Symmetry"}
    assert expected <= set(classes)
    not_frozen = [n for n, c in classes.items() if not (dataclasses.is_dataclass(c) and c.__dataclass_params__.frozen)]
    assert not_frozen == []


def test_checker_sees_what_it_must(tmp_path: Path) -> None:
    """The checker itself: relative and function-level imports resolve; a planted cycle and upward import show."""
    pkg = tmp_path / PACKAGE
    for folder in ("low", "high", "low/sub"):
        (pkg / folder).mkdir(parents=True)
        (pkg / folder / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "low" / "sub" / "deep.py").write_text("def f():\n    from ...high import thing\n")
    (pkg / "high" / "mod.py").write_text("from ..low.sub import deep\nimport normpos_grasp.low as low\n")
    (pkg / "examples").mkdir()
    (pkg / "examples" / "x.py").write_text("from normpos_grasp import high\n")
    units, edges = import_graph(pkg)
    assert units == {PACKAGE, "low", "high"}
    assert edges[("low", "high")] == [f"{PACKAGE}.low.sub.deep:2 -> {PACKAGE}.high.thing"]
    assert len(edges[("high", "low")]) == 2
    assert package_cycles(edges) == [["high", "low"]]
    assert upward_imports(edges, ("low", "high")) == [f"low -> high: {PACKAGE}.low.sub.deep:2 -> {PACKAGE}.high.thing"]
    assert upward_imports(edges, ("high", "low")) == [
        f"high -> low: {PACKAGE}.high.mod:1 -> {PACKAGE}.low.sub.deep",
        f"high -> low: {PACKAGE}.high.mod:2 -> {PACKAGE}.low",
    ]
