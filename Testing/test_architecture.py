"""The house: data flows one way between the rooms, no import circles, light leaves.

Stages, upstream first: the leaves (config, errors, progress, cluster, parallel, memory, version),
geometry (rigid alignment, for every stage below it), prepare, correspondence, model, the build
folder (folders: its files read and written), analysis, report, the commands (build, outputs,
analyze, fit, compare), the faces (cli and its options, vtkfilters, vtkmodel, demo, and the
package front door, whose heavy names load on first use). A module may import its own stage and
the stages upstream of it, never one downstream.
"""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import mdlshapemodel

PACKAGE = Path(mdlshapemodel.__file__).parent
STAGES = [
    {"config", "errors", "progress", "cluster", "parallel", "memory", "version"},
    {"geometry"},
    {"prepare"},
    {"correspondence"},
    {"model"},
    {"folders"},
    {"analysis"},
    {"report"},
    {"build", "outputs", "analyze", "fit", "compare", "kernels"},
    {"cli", "options", "vtkfilters", "vtkmodel", "demo", "__init__"},
]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    return ".".join(parts)


def stage_of(module: str) -> int:
    room = module.split(".")[0]
    for k, rooms in enumerate(STAGES):
        if room in rooms:
            return k
    raise AssertionError(f"module {module} is in no stage of the architecture")


def package_imports(path: Path) -> set:
    """The package modules a file imports (relative imports resolved; every import, also those
    inside functions)."""
    module = module_name(path)
    package = module.split(".")[:-1] if path.name != "__init__.py" else module.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level == 0:
                if node.module and node.module.startswith("mdlshapemodel."):
                    base = node.module.split(".")[1:]
                else:
                    continue
            else:
                base = package[:len(package) - (node.level - 1)] + (
                    node.module.split(".") if node.module else [])
            for alias in node.names:
                candidate = base + [alias.name]
                if resolve(candidate):
                    found.add(".".join(candidate))
                elif base:
                    found.add(".".join(base))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("mdlshapemodel."):
                    found.add(alias.name.split(".", 1)[1])
    return {name for name in found if resolve(name.split("."))}


def resolve(parts) -> Path | None:
    target = PACKAGE.joinpath(*parts)
    if target.with_suffix(".py").is_file():
        return target.with_suffix(".py")
    if (target / "__init__.py").is_file():
        return target / "__init__.py"
    return None


def graph() -> dict:
    modules = {}
    for path in PACKAGE.rglob("*.py"):
        name = module_name(path)
        modules[name] = {m if not m.endswith("__init__") else m for m in package_imports(path)}
    return modules


def test_no_room_imports_one_downstream_of_it():
    upward = []
    for module, imports in graph().items():
        for imported in imports:
            if stage_of(imported) > stage_of(module):
                upward.append(f"{module} -> {imported}")
    assert not upward, "imports against the data flow: " + ", ".join(sorted(upward))


def test_the_package_has_no_import_circle():
    edges = graph()

    def canonical(name):
        return name[: -len(".__init__")] if name.endswith(".__init__") else name

    adjacency = {canonical(m): {canonical(i) for i in imports} - {canonical(m)}
                 for m, imports in edges.items()}
    # a package's __init__ importing its own submodules is not a circle
    for module in adjacency:
        adjacency[module] = {i for i in adjacency[module] if not i.startswith(module + ".")}
    state = {}
    path = []

    def visit(node):
        state[node] = "open"
        path.append(node)
        for nxt in sorted(adjacency.get(node, ())):
            if state.get(nxt) == "open":
                cycle = path[path.index(nxt):] + [nxt]
                raise AssertionError("import circle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt)
        path.pop()
        state[node] = "done"

    for node in sorted(adjacency):
        if node not in state:
            visit(node)


def private_imports(module: str, source: str) -> list:
    """The names private to another package module (a leading underscore, dunders aside) that
    the source of ``module`` (e.g. "prepare.case") imports or reads from such a module:
    ``from .x import _y``, ``x._y``."""
    package = module.split(".")[:-1]
    tree = ast.parse(source)
    modules, found = {}, []   # modules: local name -> the package module it is
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level == 0:
                if not (node.module or "").startswith("mdlshapemodel"):
                    continue
                base = node.module.split(".")[1:]
            else:
                base = package[:len(package) - (node.level - 1)] + (
                    node.module.split(".") if node.module else [])
            for alias in node.names:
                if resolve(base + [alias.name]):
                    modules[alias.asname or alias.name] = base + [alias.name]
                elif alias.name.startswith("_") and not alias.name.startswith("__"):
                    found.append(f"line {node.lineno}: from {'.'.join(base)} import {alias.name}")
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("mdlshapemodel.") and alias.asname:
                    modules[alias.asname] = alias.name.split(".")[1:]
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in modules and node.attr.startswith("_")
                and not node.attr.startswith("__")):
            found.append(f"line {node.lineno}: {node.value.id}.{node.attr}")
    return found


def test_no_room_uses_a_name_private_to_another():
    """What two rooms share is public in the room that owns it: no ``from .x import _y``, no
    ``x._y`` on a package module."""
    found = {module_name(path): private_imports(module_name(path), path.read_text())
             for path in PACKAGE.rglob("*.py")}
    assert not {m: names for m, names in found.items() if names}


def test_the_private_name_checker_sees_both_forms():
    # the checker must see both forms, or the test above would pass vacuously
    code = ("from .io import _hidden, read_polydata\nfrom . import nearest\n"
            "from ..version import __version__\nvalue = nearest._grid, nearest.TriangleGrid\n")
    assert private_imports("prepare.probe", code) == ["line 1: from prepare.io import _hidden",
                                                      "line 4: nearest._grid"]


def bare_value_errors(source: str) -> list:
    """The lines of ``source`` that raise ``ValueError`` itself (not one of its subclasses)."""
    return sorted(node.lineno for node in ast.walk(ast.parse(source))
                  if isinstance(node, ast.Raise) and node.exc is not None
                  and getattr(node.exc.func if isinstance(node.exc, ast.Call) else node.exc,
                              "id", None) == "ValueError")


def test_errors_are_of_the_package_hierarchy():
    """A rejected input raises an error of mdlshapemodel.errors, a bad argument its
    ArgumentError (a ValueError, as numpy's are), a bug InternalError: no bare ValueError."""
    found = {module_name(path): bare_value_errors(path.read_text())
             for path in PACKAGE.rglob("*.py")}
    assert not {m: lines for m, lines in found.items() if lines}
    assert bare_value_errors("if x:\n    raise ValueError('a')\nraise ValueError\n"
                             "raise ArgumentError('b')\n") == [2, 3]


def test_the_checker_sees_an_upward_import(tmp_path):
    # the parser must resolve relative imports, or the two tests above would pass vacuously
    imports = package_imports(PACKAGE / "build.py")
    assert "outputs" in imports and "prepare" in imports
    assert any(name.startswith("correspondence.strategies") for name in imports)
    assert stage_of("cli") > stage_of("build") > stage_of("model.evaluation")


@pytest.mark.parametrize("module", ["mdlshapemodel.config", "mdlshapemodel.progress",
                                    "mdlshapemodel.errors"])
def test_leaves_import_neither_numba_nor_vtk_nor_the_optimiser(module):
    code = (f"import sys, {module}, mdlshapemodel; mdlshapemodel.BuildConfig().validate(); "
            "heavy = [m for m in ('numba', 'vtk', 'vtkmodules', 'scipy', 'SimpleITK', "
            "'mdlshapemodel.correspondence', 'mdlshapemodel.prepare') if m in sys.modules]; "
            "print(','.join(heavy))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            check=True, timeout=120)
    assert result.stdout.strip() == ""


def test_every_strategy_name_has_a_registered_phase():
    from mdlshapemodel.config import STRATEGIES
    from mdlshapemodel.correspondence.strategies import KEEP_INITIAL, PHASES

    assert set(PHASES) | {KEEP_INITIAL} == set(STRATEGIES)
    assert KEEP_INITIAL not in PHASES


def test_the_library_never_imports_slicer_or_qt():
    """The Slicer module imports the library, never the reverse: the library runs without Slicer."""
    faces_only = {"slicer", "qt", "ctk", "MDLShapeModel"}
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([alias.name for alias in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0
                     else [])
            assert not {n.split(".")[0] for n in names} & faces_only, path
