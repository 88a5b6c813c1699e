"""An episode's wall-clock guard is one rule (``orchestrator.stack.launcher.wall_guard_s``), used by ``drivebench
run``, the matrix runner and the Ray runner alike; no other module computes its own guard from ``max_sim_seconds``."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from orchestrator.stack.launcher import wall_guard_s

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("circuits", "protocol", "services", "brains", "recorder", "orchestrator")


@pytest.mark.parametrize("max_sim_seconds", [0.5, 4.0, 60.0, 300.0, 3600.0])
def test_the_guard_is_never_tighter_than_either_rule_it_replaced(max_sim_seconds):
    # run used 20x + 60 s, the matrix 10x + 120 s: a run that finished under either must not time out now
    assert wall_guard_s(max_sim_seconds=max_sim_seconds) >= max(max_sim_seconds * 20 + 60, max_sim_seconds * 10 + 120)


def test_a_longer_episode_gets_a_longer_guard():
    assert wall_guard_s(max_sim_seconds=10.0) < wall_guard_s(max_sim_seconds=100.0)


def _scales_sim_seconds(node: ast.AST) -> bool:
    """``... max_sim_seconds * k`` or ``k * ... max_sim_seconds``: a wall time derived from the episode's limit."""

    def names_limit(operand: ast.AST) -> bool:
        return (isinstance(operand, ast.Attribute) and operand.attr == "max_sim_seconds") or (
            isinstance(operand, ast.Name) and operand.id == "max_sim_seconds"
        )

    if not (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult)):
        return False
    return names_limit(node.left) or names_limit(node.right)


def test_only_the_launcher_rule_scales_max_sim_seconds_into_a_guard():
    found = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            tree = ast.parse(path.read_text(), str(path))
            for function in ast.walk(tree):
                if isinstance(function, ast.FunctionDef | ast.AsyncFunctionDef):
                    if any(_scales_sim_seconds(node) for node in ast.walk(function)):
                        found.append(f"{path.relative_to(ROOT)}:{function.name}")
    assert sorted(set(found)) == ["orchestrator/stack/launcher.py:wall_guard_s"]


def test_the_matrix_runner_leaves_the_guard_to_the_launcher():
    for module in ("runner.py", "executor.py"):  # the executor is where a matrix episode runs on its stack
        source = (ROOT / "orchestrator" / "matrix" / module).read_text()
        assert "wall_timeout_s=" not in source, module
