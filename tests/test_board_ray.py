"""``drivebench board serve --ray ADDRESS``: a real Ray cluster on this machine (a head that runs no episode and one
worker node with an episode slot, all on 127.0.0.1), a real server that sends its evaluations' episodes there, brain
hosts sandboxed on the node. The scores are the ones the same server gives without Ray, to the bit.

Ray is the optional extra ``cluster``: skipped without it on a developer's machine, a failure in CI.
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
from pathlib import Path

# Only loopback may be used here: Ray must believe it runs single-machine (read when ray is imported, so before it;
# the server and its evaluations inherit it).
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"

import needs  # noqa: E402
import pytest  # noqa: E402

ray = needs.require("ray")

from ray.cluster_utils import Cluster  # noqa: E402
from test_board import GOOD_BRAIN, LOADED_S, TINY_CONDITIONS, Server, brain_file, last_json, submit  # noqa: E402

from orchestrator.matrix.ray_options import EPISODE_SLOT  # noqa: E402
from orchestrator.matrix.results import ResultStore  # noqa: E402

pytestmark = [pytest.mark.integration, pytest.mark.slow]

LOOPBACK = "127.0.0.1"


@pytest.fixture
def cluster():  # one test uses it; the refusal test starts its own, never beside it
    cluster = Cluster(initialize_head=True, connect=False, head_node_args={"num_cpus": 0, "node_ip_address": LOOPBACK})
    cluster.add_node(num_cpus=1, resources={EPISODE_SLOT: 1}, node_ip_address=LOOPBACK)
    cluster.wait_for_nodes()
    yield cluster
    cluster.shutdown()


def peeking_brain(seed_file: Path) -> str:
    """The good brain, but it tries to read the secret seed in every reset and raises (so would be rejected) if it
    ever can: scored only where its host is sandboxed."""
    return GOOD_BRAIN.replace(
        "    def reset(self, *, seed: int) -> None:\n        pass\n",
        "    def reset(self, *, seed: int) -> None:\n"
        "        try:\n"
        f"            secret = open({str(seed_file)!r}).read()\n"
        "        except OSError:\n"
        "            return\n"
        "        raise RuntimeError('read the secret seed: ' + secret)\n",
    )


def nodes_of(server: Server, submission_id: str) -> set[str]:
    """The node column of every episode row of a submission's (first) evaluation."""
    with ResultStore(server.data / "submissions" / submission_id / "attempt-1" / "matrix", create=False) as store:
        return {result.node for result in store.results()}


@pytest.mark.timeout(3 * LOADED_S)
def test_a_submission_scored_through_ray_has_the_numbers_of_a_local_evaluation(cluster, tmp_path):
    needs.require("starlette")
    needs.require_bubblewrap()
    conditions = tmp_path / "tiny.yaml"
    conditions.write_text(TINY_CONDITIONS)
    data = tmp_path / "data"
    peek = brain_file(tmp_path, "peek.py", peeking_brain(data / "secret_seed"))
    on_ray = Server(data, conditions, sandboxed=True, ray=cluster.address).start()
    try:
        through_ray = last_json(submit(on_ray, peek, name="through-ray", wait=True))
        log = on_ray.get(f"/api/submissions/{through_ray['id']}/log")
    finally:
        on_ray.stop()
    assert through_ray["state"] == "scored", through_ray  # sandboxed on the node: the seed was out of its reach
    assert "== episode simple" in log  # the public episode's brain log came back from the node
    ray_nodes = nodes_of(on_ray, through_ray["id"])
    assert ray_nodes and all(re.fullmatch(r"127\.0\.0\.1/[0-9a-f]{8}", node) for node in ray_nodes), ray_nodes

    local = Server(data, conditions, sandboxed=True).start()  # the same data folder: the same secret seed
    try:
        here = last_json(submit(local, peek, name="here", wait=True))
    finally:
        local.stop()
    assert nodes_of(local, here["id"]) == {socket.gethostname()}
    assert here["state"] == "scored" and here["scores"] == through_ray["scores"], (here, through_ray)
    assert here["config_sha256"] == through_ray["config_sha256"]


def serve(*args: str, data: Path) -> subprocess.CompletedProcess:
    argv = [sys.executable, "-m", "orchestrator.cli", "board", "serve", "--data", str(data), "--port", "1", *args]
    return subprocess.run(argv, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--ray", "auto", "--workers", "2"], "--workers and --ray: one or the other"),
        (["--ray", "127.0.0.1:1"], "nothing answers there"),
    ],
    ids=["with-workers", "no-cluster"],
)
def test_serve_with_ray_refuses_what_it_cannot_run_in_one_line(tmp_path, args, expected):
    needs.require("starlette")
    result = serve(*args, "--unsafe-no-sandbox", data=tmp_path / "d")
    assert result.returncode == 2 and expected in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr


def test_serve_with_ray_refuses_a_cluster_whose_node_cannot_sandbox(tmp_path, monkeypatch):
    """A node started where bubblewrap is not on its PATH: the server names it and does not start."""
    needs.require("starlette")
    needs.require_bubblewrap()  # here, on the server's machine
    empty = tmp_path / "no-bwrap"
    empty.mkdir()
    head = Cluster(initialize_head=True, connect=False, head_node_args={"num_cpus": 0, "node_ip_address": LOOPBACK})
    try:
        with monkeypatch.context() as patch:
            patch.setenv("PATH", f"{empty}:{Path(sys.executable).parent}")  # python, but no bwrap, on this node
            head.add_node(num_cpus=1, resources={EPISODE_SLOT: 1}, node_ip_address=LOOPBACK)
        head.wait_for_nodes()
        result = serve("--ray", head.address, data=tmp_path / "d")
    finally:
        head.shutdown()
    assert result.returncode == 2 and "cannot sandbox brains on every node" in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr
