"""Every import on every code path is a declared dependency: core imports of the core dependencies, the optional
extras (train, scale, camera, view) imported only inside functions outside their own room, and every module
importable with the locked core environment (what `make test` installs from requirements.lock)."""

from __future__ import annotations

import ast
import importlib
import pkgutil
import re
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "normpos_grasp"
EXCLUDED = ("robot_models",)  # generated data and its generator script

# import name -> distribution name, where they differ
DISTRIBUTION_OF = {
    "cv2": "opencv-python-headless",
    "fcl": "python-fcl",
    "pinocchio": "pin",
    "rtde_control": "ur-rtde",
    "rtde_receive": "ur-rtde",
    "rtde_io": "ur-rtde",
    "dashboard_client": "ur-rtde",
    "yaml": "pyyaml",
}
# the rooms that exist for an extra and may import it at module level
EXTRA_ROOMS = {"train": ("normpos_grasp.training",)}


def _requirement_name(spec: str) -> str:
    return re.split(r"[\s<>=!~;\[]", spec, maxsplit=1)[0].lower().replace("_", "-")


def _declared() -> tuple[set[str], dict[str, set[str]]]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = {_requirement_name(s) for s in project["dependencies"]}
    extras = {k: {_requirement_name(s) for s in v} for k, v in project["optional-dependencies"].items() if k != "test"}
    return core, extras


def _third_party_imports() -> list[tuple[str, str, int, bool]]:
    """(module, imported top-level name, line, at module level) for every non-stdlib, non-project import."""
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        if any(part in EXCLUDED for part in rel.parts):
            continue
        module = ".".join(rel.parts).removesuffix(".__init__")
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top in sys.stdlib_module_names or top == "normpos_grasp" or top == "__future__":
                    continue
                out.append((module, top, node.lineno, _runs_at_import(tree, node)))
    return out


def _runs_at_import(tree: ast.Module, target: ast.AST) -> bool:
    """True when `target` is not inside a function (so it runs when the module is imported)."""
    stack: list[tuple[ast.AST, bool]] = [(tree, False)]
    while stack:
        node, in_function = stack.pop()
        if node is target:
            return not in_function
        inside = in_function or isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
        stack.extend((child, inside) for child in ast.iter_child_nodes(node))
    return False


def _type_checking_only(module: str, line: int) -> bool:
    path = PACKAGE.parent / (module.replace(".", "/") + ".py")
    if not path.exists():
        path = PACKAGE.parent / module.replace(".", "/") / "__init__.py"
    tree = ast.parse(path.read_text())
    return any(
        isinstance(node, ast.If)
        and "TYPE_CHECKING" in ast.unparse(node.test)
        and any(getattr(n, "lineno", -1) == line for n in ast.walk(node))
        for node in ast.walk(tree)
    )


def test_every_import_is_a_declared_dependency() -> None:
    core, extras = _declared()
    declared_anywhere = core | set().union(*extras.values())
    problems = []
    for module, top, line, at_import in _third_party_imports():
        dist = DISTRIBUTION_OF.get(top, top.lower().replace("_", "-"))
        if dist not in declared_anywhere:
            problems.append(f"{module}:{line} imports {top!r} ({dist}), declared nowhere in pyproject.toml")
            continue
        if dist in core or not at_import or _type_checking_only(module, line):
            continue
        extra = next(k for k, v in extras.items() if dist in v)
        if not module.startswith(EXTRA_ROOMS.get(extra, ("-",))):
            problems.append(f"{module}:{line} imports {top!r} of the [{extra}] extra when the module is imported")
    assert problems == [], "\n".join(problems)


def _modules() -> list[str]:
    names = []
    for info in pkgutil.walk_packages([str(PACKAGE)], "normpos_grasp."):
        if any(f".{part}" in info.name for part in EXCLUDED) or info.name.endswith("__main__"):
            continue
        names.append(info.name)
    return names


@pytest.mark.parametrize("module", _modules())
def test_every_module_imports_with_the_core_dependencies(module: str) -> None:
    _, extras = _declared()
    try:
        importlib.import_module(module)
    except ModuleNotFoundError as exc:  # allowed only in an extra's own room, for that extra's packages
        rooms = [k for k, v in EXTRA_ROOMS.items() if module.startswith(v)]
        missing = DISTRIBUTION_OF.get(str(exc.name), str(exc.name)).lower()
        assert rooms and missing in extras[rooms[0]], f"{module}: {exc}"
