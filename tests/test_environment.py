"""One home for the ``DRIVEBENCH_*`` environment variables (protocol/environment.py): no other module reads one, every
name the project uses is in its table, the docs' table is the generated one, and each command's ``--help`` states the
renderer default the table gives it."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from orchestrator.collect import COLLECT_RENDERER
from orchestrator.matrix.load import MATRIX_RENDERER
from protocol import environment

ROOT = Path(__file__).resolve().parent.parent
# The table, and the record type whose value() is the one read (on the ground floor, with circuits/ own variable).
HOMES = (ROOT / "protocol" / "environment.py", ROOT / "circuits" / "variables.py")
SOURCE_FOLDERS = ("circuits", "protocol", "services", "brains", "recorder", "orchestrator", "benchmarks", "tests")
DRIVEBENCH = "DRIVEBENCH_"
CLI_PATH = Path(sys.executable).parent / "drivebench"


def python_files() -> list[Path]:
    return [
        path
        for folder in SOURCE_FOLDERS
        for path in sorted((ROOT / folder).rglob("*.py"))
        if "__pycache__" not in path.parts and path not in HOMES
    ]


def _is_environ(node: ast.expr) -> bool:
    """``os.environ`` or a bare ``environ`` (from os import environ)."""
    return (isinstance(node, ast.Attribute) and node.attr == "environ") or (
        isinstance(node, ast.Name) and node.id == "environ"
    )


def _may_name_ours(key: ast.expr) -> bool:
    """Whether a key read from the environment may be a DRIVEBENCH_* variable: a literal that is one, or a name made
    elsewhere (ROUTER_ENV, environment.ROUTER.name) that the reader cannot see through."""
    if isinstance(key, ast.Constant):
        return isinstance(key.value, str) and key.value.startswith(DRIVEBENCH)
    return True


def _is_environ_as_mapping(node: ast.AST, parent: ast.AST | None) -> bool:
    """``os.environ`` itself kept or handed on for lookups (``env = os.environ``, ``os.environ if env is None else
    env``, ``resolve(env=os.environ)``), where the lookups elsewhere read variables by name. A copy for a child
    (``dict(os.environ)``, ``{**os.environ}``, ``os.environ | {...}``, ``.items()``) is none."""
    if not (isinstance(node, ast.expr) and _is_environ(node)):
        return False
    if isinstance(parent, (ast.Assign, ast.AnnAssign, ast.IfExp, ast.Return, ast.keyword)):
        return True
    return isinstance(parent, ast.Call) and node in parent.args and not _names(parent.func, "dict")


def _names(func: ast.expr, name: str) -> bool:
    return isinstance(func, ast.Name) and func.id == name


def environment_reads(path: Path, *, root: Path = ROOT) -> list[str]:
    """``file:line`` of every read of one variable whose name may be DRIVEBENCH_*: os.environ.get(K),
    os.environ[K], os.getenv(K), and os.environ handed on as a mapping to read from. Writes (os.environ[K] = v,
    del) and copies of the whole environment for a child are not reads of a variable."""
    found = []
    tree = ast.parse(path.read_text(), str(path))
    parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    for node in ast.walk(tree):
        if _is_environ_as_mapping(node, parents.get(node)):
            found.append(f"{path.relative_to(root)}:{node.lineno}")  # type: ignore[attr-defined]
            continue
        key = None
        if isinstance(node, ast.Call) and node.args and isinstance(node.func, ast.Attribute):
            if (node.func.attr == "get" and _is_environ(node.func.value)) or node.func.attr == "getenv":
                key = node.args[0]
        elif isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Load) and _is_environ(node.value):
            key = node.slice
        if key is not None and _may_name_ours(key):
            found.append(f"{path.relative_to(root)}:{node.lineno}")
    return found


def test_no_module_but_the_table_reads_a_drivebench_variable():
    reads = [where for path in python_files() for where in environment_reads(path)]
    assert not reads, "read these through protocol.environment: " + ", ".join(reads)


def test_the_reader_sees_reads_written_every_way(tmp_path):
    # The scan above passes on a clean tree; this is the proof that it would see a read if one came back.
    sample = tmp_path / "sample.py"
    sample.write_text(
        "import os\nfrom os import environ\nROUTER_ENV = 'DRIVEBENCH_ROUTER'\n"
        "a = os.environ.get('DRIVEBENCH_LOG', 'INFO')\nb = os.environ[ROUTER_ENV]\nc = os.getenv('DRIVEBENCH_MODE')\n"
        "d = environ.get(ROUTER_ENV)\nos.environ['DRIVEBENCH_TRACE_DIR'] = 'x'\ne = os.environ.get('CI')\n"
        "f = os.environ if e is None else {}\ng = dict(os.environ)\nh = {**os.environ}\n"
        "i = [k for k, v in os.environ.items()]\nresolve(env=os.environ)\nresolve(os.environ)\n"
    )
    reads = sorted(int(where.split(":")[1]) for where in environment_reads(sample, root=tmp_path))
    assert reads == [4, 5, 6, 7, 10, 14, 15]


def test_every_variable_the_project_names_is_in_the_table():
    names = {variable.name for variable in environment.VARIABLES}
    assert len(names) == len(environment.VARIABLES), "a variable is declared twice"
    pattern = re.compile(r"\bDRIVEBENCH_[A-Z][A-Z0-9_]*[A-Z0-9]\b")
    files = [*python_files(), *(ROOT / "scripts").glob("*.sh"), *ROOT.glob("*.md"), *ROOT.glob("*.yaml")]
    files += [*ROOT.glob("Dockerfile*"), *(ROOT / "docs").rglob("*.md")]
    used = {name for path in files if path.is_file() for name in pattern.findall(path.read_text(errors="replace"))}
    # DRIVEBENCH_TLS_ is the prefix the docs use for the three TLS variables together, not a variable.
    assert used - names - {"DRIVEBENCH_TLS"} == set(), "declare these in protocol/environment.py"


def test_the_docs_table_is_the_generated_one():
    assert environment.DOC_PATH.read_text() == environment.markdown(), "run: python -m protocol.environment --write"
    check = subprocess.run(
        [sys.executable, "-P", "-m", "protocol.environment"], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert check.returncode == 0, check.stdout + check.stderr
    for variable in environment.VARIABLES:
        assert f"| `{variable.name}` |" in environment.DOC_PATH.read_text()


def test_the_renderer_defaults_by_command_are_the_commands_own():
    assert environment.RENDERER_BY_COMMAND["matrix"] == MATRIX_RENDERER
    assert environment.RENDERER_BY_COMMAND["dataset collect"] == COLLECT_RENDERER
    for command, renderer in environment.RENDERER_BY_COMMAND.items():
        assert f"`{command}` {renderer}" in environment.RENDERER.default


@pytest.mark.parametrize("command", sorted(environment.RENDERER_BY_COMMAND))
def test_each_commands_help_states_its_renderer_default(command):
    shown = subprocess.run(
        [str(CLI_PATH), *command.split(), "--help"], capture_output=True, text=True, timeout=120, check=True
    ).stdout
    option = " ".join(shown.split("\n  --renderer", 1)[1].split("\n  -", 1)[0].split())  # its help, unwrapped
    assert environment.RENDERER.name in option and f"else {environment.RENDERER_BY_COMMAND[command]}" in option, option


@pytest.mark.parametrize(
    ("argv", "who"),
    [
        ([sys.executable, "-P", "-m", "services.scorer", "--run-id", "loud"], "scorer"),  # every service
        ([str(CLI_PATH), "view", "--router", "tcp/127.0.0.1:9"], "drivebench"),  # the command that logs
    ],
)
def test_a_bad_log_level_is_one_line_naming_the_variable(argv, who):
    env = {k: v for k, v in os.environ.items() if not k.startswith(DRIVEBENCH)} | {environment.LOG.name: "loud"}
    done = subprocess.run(argv, env=env, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [
        f"{who}: error: DRIVEBENCH_LOG must be one of DEBUG, INFO, WARNING, ERROR, CRITICAL, got 'LOUD'"
    ]
