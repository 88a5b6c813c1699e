"""``drivebench matrix --ray`` option mistakes, the capacity arithmetic, and the results columns Ray runs added
(read back from a results file written before them). No Ray needed: nothing here joins a cluster."""

from __future__ import annotations

import dataclasses
import json
import os
import sqlite3
import subprocess
import sys

import pytest

from orchestrator.matrix.ray_options import EPISODE_SLOT, slots_of
from orchestrator.matrix.results import LostAttempt, ResultStore


def run_matrix(tmp_path, *args: str) -> subprocess.CompletedProcess:
    path = tmp_path / "m.yaml"
    path.write_text("name: options\nbrains: [explicit]\ncircuits: [simple]\n")
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "matrix", str(path), "-o", str(tmp_path / "out"), *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--ray", "auto", "--record"), "--record with --ray needs --artifacts DIR"),
        (("--ray", "auto", "--ray-resource", "GPU"), "--ray-resource 'GPU': expected NAME=AMOUNT with AMOUNT > 0"),
        (("--ray", "auto", "--ray-resource", "GPU=-1"), "--ray-resource 'GPU=-1': expected NAME=AMOUNT"),
        (("--ray", "auto", "--node-retries", "-1"), "--node-retries must be >= 0, got -1"),
        (("--artifacts", "/tmp"), "--artifacts and --ray-resource go with --ray ADDRESS"),
        (("--ray", " "), "--ray needs an address: auto, HOST:PORT or ray://HOST:10001"),
        (("--ray", "auto", "--workers", "4"), "--workers is for a local run: on Ray, the nodes' episode_slot"),
    ],
)
def test_a_ray_option_mistake_is_one_line_and_nothing_starts(tmp_path, args, message):
    run = run_matrix(tmp_path, *args)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("drivebench: error: ") and message in lines[0], run.stderr
    assert not (tmp_path / "out" / "results.sqlite").exists()


def test_slots_of_a_node_are_what_its_scarcest_resource_allows():
    node = {"Resources": {EPISODE_SLOT: 4.0, "GPU": 1.0, "CPU": 8.0}}
    assert slots_of(node, {EPISODE_SLOT: 1.0}) == 4
    assert slots_of(node, {EPISODE_SLOT: 1.0, "GPU": 0.25}) == 4
    assert slots_of(node, {EPISODE_SLOT: 1.0, "GPU": 0.5}) == 2
    assert slots_of(node, {EPISODE_SLOT: 1.0, "TPU": 1.0}) == 0
    assert slots_of({"Resources": {"CPU": 8.0}}, {EPISODE_SLOT: 1.0}) == 0  # a head that runs no episode
    assert slots_of({"Resources": {EPISODE_SLOT: 0.3 * 10}}, {EPISODE_SLOT: 0.3}) == 10  # float sums: no off-by-one


OLD_SCHEMA = """
CREATE TABLE matrix (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE episodes (key TEXT PRIMARY KEY, idx INTEGER NOT NULL, brain TEXT NOT NULL, circuit TEXT NOT NULL,
    variation TEXT NOT NULL, perturbation TEXT NOT NULL, repetition INTEGER NOT NULL, spec_json TEXT NOT NULL,
    brain_json TEXT NOT NULL, status TEXT NOT NULL CHECK (status IN ('done', 'failed')), reason TEXT, failure TEXT,
    score_json TEXT, run_id TEXT NOT NULL, started_at REAL NOT NULL, ended_at REAL NOT NULL, recording TEXT,
    trajectory TEXT, logs TEXT);
INSERT INTO episodes VALUES ('explicit/simple/default/none/r0', 0, 'explicit', 'simple', 'default', 'none', 0,
    '{"circuit": "simple"}', '{"brain": "explicit"}', 'failed', NULL, 'start_failed: x', NULL, 'm0000-abcdef', 1.0,
    2.0, NULL, NULL, NULL);
"""


def test_a_results_file_from_before_the_node_column_reads_and_takes_new_rows(tmp_path):
    with sqlite3.connect(tmp_path / "results.sqlite") as db:
        db.executescript(OLD_SCHEMA)
    with ResultStore(tmp_path, create=False) as store:
        (old,) = store.results()
        assert (old.key, old.node, old.lost_attempts) == ("explicit/simple/default/none/r0", None, ())
        lost = (LostAttempt(node="10.0.0.7/abcdef12", error="NodeDiedError: gone"),)
        store.record(dataclasses.replace(old, key="k2", index=1, node="10.0.0.8/12345678", lost_attempts=lost))
        new = store.results()[1]
    assert (new.node, new.lost_attempts) == ("10.0.0.8/12345678", lost)
    with sqlite3.connect(tmp_path / "results.sqlite") as db:  # the row keeps the file's format: {node, error}
        (stored,) = db.execute("SELECT lost_attempts FROM episodes WHERE key = 'k2'").fetchone()
    assert json.loads(stored) == [{"node": "10.0.0.7/abcdef12", "error": "NodeDiedError: gone"}]


def test_compose_ray_file_resolves_and_its_worker_declares_episode_slots(tmp_path):
    from support.compose import compose
    from support.processes import ROOT

    result = compose("config", "--format", "json", file=ROOT / "compose.ray.yaml", profiles=())
    assert result.returncode == 0, result.stderr
    services = json.loads(result.stdout)["services"]
    assert services["ray-head"]["command"][:3] == ["ray", "start", "--head"] and "0" in services["ray-head"]["command"]
    shell, flag, script = services["ray-worker"]["command"]
    assert (shell, flag) == ("sh", "-c") and script.startswith("exec ray start ")
    # The worker's own shell line, run for real with `ray` swapped for a printer of its arguments: the resources
    # argument is the JSON Ray wants, one slot per core by default.
    printer = tmp_path / "ray"
    printer.write_text('#!/bin/sh\nfor arg in "$@"; do printf \'%s\\n\' "$arg"; done\n')
    printer.chmod(0o755)
    for slots, expected in (("3", 3), ("", len(os.sched_getaffinity(0)))):
        env = {"PATH": f"{tmp_path}:{os.environ['PATH']}", "EPISODE_SLOTS": slots, "RAY_HEAD": "10.0.0.1:6379"}
        run = subprocess.run(
            ["sh", "-c", script.replace("$$", "$")], capture_output=True, text=True, env=env, timeout=10
        )
        args = run.stdout.splitlines()
        assert args[args.index("--address") + 1] == "10.0.0.1:6379"
        assert json.loads(args[args.index("--resources") + 1]) == {EPISODE_SLOT: expected}


def test_without_ray_installed_ray_says_how_to_install_it(tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text("name: plain\nbrains: [explicit]\ncircuits: [simple]\n")
    # A Python where `import ray` fails, as on an install without the extra.
    code = (
        "import sys; sys.modules['ray'] = None; from orchestrator.cli import main; "
        f"sys.exit(main(['matrix', {str(path)!r}, '-o', {str(tmp_path / 'out')!r}, '--ray', 'auto']))"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 1
    assert run.stderr.strip().splitlines() == [
        "drivebench: the stack could not run: --ray needs Ray: pip install 'drivebench[cluster]' "
        "(or: pip install 'ray>=2.50')"
    ]
