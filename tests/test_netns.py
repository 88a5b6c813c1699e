"""One stack split across three "machines": Linux network namespaces joined by veth pairs.

    namespace A (router host)              namespace B (brain host)      namespace C (scorer host)
    router, simulator, noise, driver  <->  brain (explicit)
      10.<n>.1.1 ----- veth ----- 10.<n>.1.2
      10.<n>.2.1 ----------------------- veth ---------------------- 10.<n>.2.2    scorer

Every process gets only its router endpoint from the environment (``DRIVEBENCH_ROUTER``), as on real machines.
Only addresses inside the namespaces this test creates are used; they are deleted at the end. Needs root (CI runs
as root); skipped with the reason where namespaces cannot be made.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from needs import missing
from support.env import clean_env

pytestmark = [pytest.mark.integration, pytest.mark.slow]

ROOT = Path(__file__).resolve().parent.parent


def ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)


class Namespaces:
    """Three namespaces A, B, C; A linked to B and to C by veth pairs on two private /24 subnets."""

    def __init__(self, tag: str, subnet: int):
        self.names = {host: f"db{tag}{host}" for host in "ABC"}
        self.address = {
            ("A", "B"): f"10.{subnet}.1.1",
            ("B", "A"): f"10.{subnet}.1.2",
            ("A", "C"): f"10.{subnet}.2.1",
            ("C", "A"): f"10.{subnet}.2.2",
        }
        self.tag = tag

    def create(self) -> None:
        for name in self.names.values():
            self._check(ip("netns", "add", name))
            self._check(ip("-n", name, "link", "set", "lo", "up"))
        for far in "BC":
            near_dev, far_dev = f"v{self.tag}A{far}", f"v{self.tag}{far}A"
            self._check(
                ip(
                    "link",
                    "add",
                    near_dev,
                    "netns",
                    self.names["A"],
                    "type",
                    "veth",
                    "peer",
                    "name",
                    far_dev,
                    "netns",
                    self.names[far],
                )
            )
            for host, dev, other in (("A", near_dev, far), (far, far_dev, "A")):
                self._check(ip("-n", self.names[host], "addr", "add", f"{self.address[(host, other)]}/24", "dev", dev))
                self._check(ip("-n", self.names[host], "link", "set", dev, "up"))

    @staticmethod
    def _check(result: subprocess.CompletedProcess) -> None:
        if result.returncode != 0:
            raise RuntimeError(f"{' '.join(result.args)}: {result.stderr.strip()}")

    def delete(self) -> None:
        for name in self.names.values():
            ip("netns", "del", name)  # removes its end of every veth pair, and with it the pair

    def popen(self, host: str, argv: list[str], *, env: dict[str, str], log: Path) -> subprocess.Popen:
        base = clean_env()
        with open(log, "wb") as out:
            return subprocess.Popen(
                ["ip", "netns", "exec", self.names[host], *argv],
                stdout=out,
                stderr=subprocess.STDOUT,
                env=base | env | {"PYTHONUNBUFFERED": "1"},
                cwd=ROOT,
            )


def namespaces_or_skip() -> Namespaces:
    if shutil.which("ip") is None:
        missing("iproute2's `ip` is not installed: cannot make network namespaces")
    if os.geteuid() != 0:
        missing("network namespaces need root (CI runs as root)")
    tag = f"{os.getpid() % 100000:05d}"
    namespaces = Namespaces(tag, subnet=200 + os.getpid() % 50)
    try:
        namespaces.create()
    except RuntimeError as error:
        namespaces.delete()
        missing(f"this kernel or sandbox does not allow network namespaces with veth pairs: {error}")
    return namespaces


def test_an_episode_runs_with_router_brain_and_scorer_in_separate_namespaces(tmp_path):
    net = namespaces_or_skip()
    processes: list[subprocess.Popen] = []
    router_b = f"tcp/{net.address[('A', 'B')]}:7447"  # the router as the brain's machine reaches it
    router_c = f"tcp/{net.address[('A', 'C')]}:7447"  # ... and as the scorer's machine does
    run_id = f"netns{net.tag}"
    env_a = {"DRIVEBENCH_ROUTER": router_b, "DRIVEBENCH_RUN_ID": run_id}
    try:
        processes.append(
            net.popen(
                "A",
                [sys.executable, "-m", "services.router", "--listen", router_b, "--listen", router_c],
                env={},
                log=tmp_path / "router.log",
            )
        )
        for module in ("services.simulator", "services.noise"):
            processes.append(net.popen("A", [sys.executable, "-m", module], env=env_a, log=tmp_path / f"{module}.log"))
        # The brain's machine as docs/guides/deployment.md sets it up: a client, so only the router's port must be
        # reachable.
        # (As a peer it relies on a direct link to the simulator; twice in full-suite runs the simulator had not
        # seen the brain's token 5 s after the driver had.)
        processes.append(
            net.popen(
                "B",
                [sys.executable, "-m", "brains", "--brain", "explicit"],
                env={"DRIVEBENCH_ROUTER": router_b, "DRIVEBENCH_RUN_ID": run_id, "DRIVEBENCH_MODE": "client"},
                log=tmp_path / "brain.log",
            )
        )
        processes.append(
            net.popen(
                "C",
                [sys.executable, "-m", "services.scorer"],
                env={"DRIVEBENCH_ROUTER": router_c, "DRIVEBENCH_RUN_ID": run_id},
                log=tmp_path / "scorer.log",
            )
        )
        driver = net.popen(
            "A",
            [
                sys.executable,
                "-m",
                "orchestrator.cli",
                "run",
                "--attach",
                "--wait",
                "60",
                "--max-sim-seconds",
                "10",
                "--out",
                str(tmp_path / "run"),
                "--json",
            ],
            env=env_a,
            log=tmp_path / "driver.log",
        )
        processes.append(driver)
        code = driver.wait(timeout=150)
        logs = {path.name: path.read_text(errors="replace")[-1500:] for path in tmp_path.glob("*.log")}
        assert code == 0, logs
        score = json.loads((tmp_path / "run" / "score.json").read_text())
        assert score["brain"] == "explicit" and score["reason"] == "time_limit", score
        assert score["metrics"]["steps"] == 200 and score["metrics"]["progress_m"] > 40, score["metrics"]
        # Everything crossed a veth: the brain's and the scorer's only links are to addresses in namespace A.
        for name in "BC":
            links = subprocess.run(
                ["ip", "netns", "exec", net.names[name], "ss", "-tnH", "state", "established"],
                capture_output=True,
                text=True,
                timeout=10,
            ).stdout
            assert net.address[("A", name)] in links, (name, links)
    finally:
        for process in processes:
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 20
        for process in processes:
            try:
                process.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        net.delete()
    assert not any(name in ip("netns", "list").stdout for name in net.names.values())
