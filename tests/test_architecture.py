"""The folders' rules (ARCHITECTURE.md), held by reading every import of every module (lazy ones included).

* Which top-level package may import which: nothing imports upward (protocol/ is the floor every process stands on,
  orchestrator/ the roof of the processes, drivebench/ the library face above it).
* No cycle between packages: the subpackages (orchestrator/stack, matrix, report; protocol/deploy, mapping; ...) form
  a graph without loops, so each can be read knowing only what it imports.
* Only protocol/ imports zenoh; no package folder holds more than 15 modules.
* No function outside tests/ is over 80 lines (CODE_STYLE.md: a longer one splits by what it does), and no module of
  the packages is over 700 lines (a longer one splits by responsibility, as protocol/messages.py did: issue 41).
"""

from __future__ import annotations

import ast
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TOP_LEVEL = ("circuits", "protocol", "services", "brains", "recorder", "orchestrator", "drivebench")
# What each top-level package may import besides itself. brains/ renders the checker's frames with the simulator's
# scene (services/simulator) and trains from recordings (recorder/, from brains/training only); the Behavior Metrics
# adapter's handler perturbs frames with the noise injector's own models (transform_image = --noise rain, ...).
MAY_IMPORT = {
    "circuits": set(),
    "protocol": {"circuits"},
    "services": {"protocol", "circuits"},
    "recorder": {"protocol", "circuits"},
    "brains": {"protocol", "circuits", "services", "recorder"},
    "orchestrator": {"protocol", "circuits", "services", "brains", "recorder"},
    # The library face above the CLI: the Gymnasium environment drives stacks the orchestrator's launcher starts.
    "drivebench": {"protocol", "circuits", "services", "brains", "recorder", "orchestrator"},
}
ONLY_FROM = {
    ("brains", "recorder"): ("brains.training",),
    ("brains", "services"): ("brains.checker", "brains.behavior_metrics"),
}
# The ground floor's record of an environment variable (and the circuit library's own variable): standard library
# only, so that protocol.environment's table lists it without circuits/ importing upward (issue 41).
GROUND_VARIABLES = "circuits.variables"
MAX_MODULES_PER_FOLDER = 15
MAX_FUNCTION_LINES = 80
MAX_MODULE_LINES = 700
# Every folder of Python code but tests/ (test functions may read as one long scenario).
CODE_FOLDERS = (*TOP_LEVEL, "benchmarks", "examples", "scripts")


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def package_of(module: str) -> str:
    """The package a module belongs to: its folder (``orchestrator.matrix.runner`` -> ``orchestrator.matrix``)."""
    parts = module.split(".")
    for length in range(len(parts), 0, -1):
        if (ROOT.joinpath(*parts[:length]) / "__init__.py").is_file():
            return ".".join(parts[:length])
    return parts[0]


def imported_modules(path: Path) -> set[str]:
    """Every absolute import of ``path``, at any depth (a ``from a import b`` names ``a.b`` when b is a module)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            folder = ROOT.joinpath(*node.module.split("."))
            found.update(
                f"{node.module}.{alias.name}"
                for alias in node.names
                if (folder / alias.name).is_dir() or (folder / f"{alias.name}.py").is_file()
            )
    return found


def project_modules() -> dict[str, set[str]]:
    return {
        module_name(path): imported_modules(path)
        for top in TOP_LEVEL
        for path in sorted((ROOT / top).rglob("*.py"))
        if "__pycache__" not in path.parts
    }


def test_no_package_imports_upward():
    wrong = []
    for module, imports in project_modules().items():
        top = module.split(".")[0]
        for imported in imports:
            target = imported.split(".")[0]
            if target not in TOP_LEVEL or target == top:
                continue
            only = ONLY_FROM.get((top, target), ())
            if target not in MAY_IMPORT[top] or (
                only and not any(module == o or module.startswith(o + ".") for o in only)
            ):
                wrong.append(f"{module} imports {imported}")
    assert not wrong, "\n".join(sorted(wrong))


def test_packages_form_no_cycle():
    edges: dict[str, set[str]] = defaultdict(set)
    for module, imports in project_modules().items():
        source = package_of(module)
        for imported in imports:
            if imported.split(".")[0] in TOP_LEVEL and (target := package_of(imported)) != source:
                # A package reaching into its own subpackages is downward (a registry naming its brains' folders).
                if not target.startswith(source + "."):
                    edges[source].add(target)
    cycle = find_cycle(edges)
    assert cycle is None, " -> ".join(cycle or [])


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, str] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = "open"
        stack.append(node)
        for target in sorted(edges.get(node, ())):
            if state.get(target) == "open":
                return stack[stack.index(target) :] + [target]
            if target not in state and (found := visit(target)):
                return found
        state[node] = "done"
        stack.pop()
        return None

    for node in sorted(edges):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_only_protocol_imports_zenoh():
    users = [
        module
        for module, imports in project_modules().items()
        if any(name.split(".")[0] == "zenoh" for name in imports) and not module.startswith("protocol")
    ]
    assert not users, users


def test_no_folder_holds_more_than_fifteen_modules():
    crowded = {}
    for top in TOP_LEVEL:
        for folder in [ROOT / top, *(p for p in (ROOT / top).rglob("*") if p.is_dir())]:
            modules = [p for p in folder.glob("*.py") if p.name not in ("__init__.py", "__main__.py")]
            if len(modules) > MAX_MODULES_PER_FOLDER:
                crowded[str(folder.relative_to(ROOT))] = len(modules)
    assert not crowded, crowded


def test_no_function_outside_tests_is_over_eighty_lines():
    long = []
    for folder in CODE_FOLDERS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                    lines = node.end_lineno - node.lineno + 1 if node.end_lineno else 0
                    if lines > MAX_FUNCTION_LINES:
                        long.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.name} is {lines} lines")
    assert not long, "\n".join(long)


def test_no_module_of_the_packages_is_over_seven_hundred_lines():
    long = [
        f"{path.relative_to(ROOT)} is {lines} lines"
        for top in TOP_LEVEL
        for path in sorted((ROOT / top).rglob("*.py"))
        if "__pycache__" not in path.parts
        and (lines := len(path.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES
    ]
    assert not long, "\n".join(long)


def test_the_ground_floors_variables_import_nothing_of_ours():
    imports = project_modules()[GROUND_VARIABLES]
    ours = sorted(name for name in imports if name.split(".")[0] in TOP_LEVEL)
    assert not ours, f"{GROUND_VARIABLES} must stay below every package: it imports {ours}"
    assert imports <= set(sys.stdlib_module_names) | {"__future__", "collections.abc"}, imports


def module_of(imported: str, modules: set[str]) -> str | None:
    """The project module an import names (``a.b.Name`` -> ``a.b``), or None for one outside the project."""
    parts = imported.split(".")
    for length in range(len(parts), 0, -1):
        if ".".join(parts[:length]) in modules:
            return ".".join(parts[:length])
    return None


def test_modules_form_no_cycle():
    """No two modules import each other, at any depth and lazily or not (issue 41: orchestrator.seeds and
    seeds_ray, services.simulator.gl_scene and gl_gazebo did): a pair that needs each other is one module, or the
    part both need moves below them. A package's ``__init__`` re-exporting its modules is no edge back."""
    graph = project_modules()
    modules = set(graph)
    edges: dict[str, set[str]] = defaultdict(set)
    for module, imports in graph.items():
        for imported in imports:
            target = module_of(imported, modules)
            # A package's __init__ is its front door: a module of the package importing a sibling through it, or
            # the __init__ importing its modules, is not an arrow between two modules.
            if target is None or target == module or module.startswith(target + ".") or target.startswith(module + "."):
                continue
            edges[module].add(target)
    cycle = find_cycle(edges)
    assert cycle is None, " -> ".join(cycle or [])


def test_every_noqa_names_a_rule_ruff_runs():
    """A noqa comment for a rule ruff does not run silences nothing and tells a reader a check exists that does
    not (issue 41: BLE001, N802, SIM115, ... were named while ruff ran E, F, W, I)."""
    import re
    import tomllib

    selected = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["ruff"]["lint"]["select"]
    stray = []
    for folder in (*TOP_LEVEL, "tests", "benchmarks", "scripts", "tools", "examples", "experiments"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                for codes in re.findall(r"#\s*noqa:\s*([A-Z0-9, ]+)", line):
                    for code in filter(None, (c.strip() for c in codes.split(","))):
                        if not any(code.startswith(prefix) for prefix in selected):
                            stray.append(f"{path.relative_to(ROOT)}:{number}: {code}")
    assert not stray, f"noqa for rules ruff does not run ({', '.join(selected)}): {stray}"


def test_no_module_imports_another_modules_private_name():
    """A name with a leading underscore is its module's own: a second module that needs it gets it made public or
    moved to where both read it (issue 41: the report's modules imported 13 of cells' and trajectories' names)."""
    wrong = []
    for top in CODE_FOLDERS:
        for path in sorted((ROOT / top).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in TOP_LEVEL:
                    private = [a.name for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
                    wrong += [f"{path.relative_to(ROOT)}:{node.lineno}: {node.module}.{name}" for name in private]
    assert not wrong, "\n".join(wrong)


def stack_classes() -> set[str]:
    """The classes of orchestrator/stack/ that start or join a stack's processes (``LocalStack``,
    ``AttachedStack``, ...): by name, as the package defines them."""
    return {
        node.name
        for path in sorted((ROOT / "orchestrator" / "stack").glob("*.py"))
        for node in ast.walk(ast.parse(path.read_text(), str(path)))
        if isinstance(node, ast.ClassDef) and node.name.endswith("Stack")
    }


def test_the_cli_parses_and_prints_and_makes_no_stack():
    """A command hands its parsed options to a pipeline object (LocalRun, AttachedRun, the matrix's run) and
    prints what it returns: no module of orchestrator/cli/ imports a stack class or drives an episode itself
    (issue 41: `run --attach` drove an AttachedStack in the CLI)."""
    stacks = stack_classes()
    assert {"LocalStack", "AttachedStack"} <= stacks, "the stack classes moved: update stack_classes()"
    wrong = []
    for path in sorted((ROOT / "orchestrator" / "cli").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            where = f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 0)}"
            if isinstance(node, ast.ImportFrom):
                wrong += [f"{where}: imports {a.name}" for a in node.names if a.name in stacks]
            elif isinstance(node, ast.Attribute) and node.attr == "run_episode":
                wrong.append(f"{where}: calls run_episode")
    assert not wrong, "\n".join(wrong)
