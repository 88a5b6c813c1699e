"""``drivebench run --attach`` and ``drivebench health``: user mistakes and missing processes are one line each.

The successful paths run in tests/test_compose.py (the compose services, started as processes) and
tests/test_netns.py (the same stack split across network namespaces).
"""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
from support.env import clean_env

from orchestrator.stack.launcher import free_loopback_port
from protocol.bus import router_address


def drivebench(*args: str, env: dict[str, str] | None = None, timeout: float = 60) -> subprocess.CompletedProcess:
    base = clean_env()
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *args],
        capture_output=True,
        text=True,
        env=base | (env or {}),
        timeout=timeout,
    )


def one_line(result: subprocess.CompletedProcess) -> str:
    lines = result.stderr.strip().splitlines()
    assert "Traceback" not in result.stderr and len(lines) == 1, result.stderr
    return lines[0]


@pytest.mark.parametrize(
    "args, code, message",
    [
        (["run", "--router", "tcp/127.0.0.1:7447"], 2, "--router needs --attach"),
        (["run", "--attach", "--run-id", "r1", "--weights", "x.ckpt"], 2, "--weights cannot be used with --attach"),
        (["run", "--attach", "--run-id", "r1", "--shadow", "explicit"], 2, "--shadow cannot be used with --attach"),
        (["run", "--attach"], 2, "no router to attach to: give --router ENDPOINT or set DRIVEBENCH_ROUTER"),
        (["run", "--attach", "--run-id", "r1"], 2, "no router to attach to"),
    ],
)
def test_attach_mistakes_are_one_line(args, code, message):
    result = drivebench(*args)
    assert result.returncode == code, result.stderr
    assert message in one_line(result)


@pytest.fixture
def router():
    port = free_loopback_port()
    process = subprocess.Popen(
        [sys.executable, "-m", "services.router", "--listen", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        assert _wait_router(port), "the router did not listen"
        yield f"tcp/127.0.0.1:{port}"
    finally:
        process.terminate()
        process.wait(timeout=20)


def _wait_router(port: int) -> bool:
    import socket
    import time

    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return True
        except OSError:
            time.sleep(0.2)
    return False


@pytest.mark.integration
def test_attach_names_what_is_not_alive(router):
    result = drivebench("run", "--attach", "--router", router, "--run-id", "nobody", "--wait", "1")
    assert result.returncode == 1
    line = one_line(result)
    assert "run 'nobody'" in line and "not alive after 1 s: noise/noise, scorer/scorer, simulator/sim" in line
    result = drivebench("run", "--attach", "--router", router, "--wait", "1")
    assert result.returncode == 2
    assert f"no run alive on {router}: choose one with --run-id or DRIVEBENCH_RUN_ID" in one_line(result)


def test_an_endpoint_without_a_port_is_refused_at_once_not_after_the_wait():
    started = time.monotonic()
    result = drivebench("run", "--attach", "--router", "tcp/localhost", "--run-id", "r1", "--wait", "60")
    assert result.returncode == 1
    assert "not a tcp/tls endpoint with a port: 'tcp/localhost'" in one_line(result)
    assert time.monotonic() - started < 30  # not the 60 s --wait: no wait gives an endpoint a port


def test_attach_to_a_router_that_is_not_there_fails_in_one_line_after_the_wait():
    dead = f"tcp/127.0.0.1:{free_loopback_port()}"
    result = drivebench("run", "--attach", "--router", dead, "--run-id", "r1", "--wait", "1")
    assert result.returncode == 1
    line = one_line(result)
    assert line.startswith(f"drivebench: the stack could not run: router {dead} not reachable") and "waited 1 s" in line


@pytest.mark.integration
def test_health_says_what_is_missing(router):
    result = drivebench("health", "simulator", "--router", router, "--run", "r1")
    assert result.returncode == 1
    assert one_line(result) == "drivebench health: no simulator alive on run 'r1' (alive: nothing)"
    dead = f"tcp/127.0.0.1:{free_loopback_port()}"
    result = drivebench("health", "router", "--router", dead)
    assert result.returncode == 1 and one_line(result).startswith(f"drivebench health: router {dead} not reachable")


@pytest.mark.parametrize(
    "endpoint, address",
    [
        ("tcp/10.0.0.5:7447", ("10.0.0.5", 7447)),
        ("tls/localhost:7447", ("localhost", 7447)),
        ("tcp/[::]:7447", ("::1", 7447)),
        ("tcp/0.0.0.0:7447", ("127.0.0.1", 7447)),
        ("tcp/[::1]:9", ("::1", 9)),
    ],
)
def test_router_address_of_endpoints(endpoint, address):
    assert router_address(endpoint) == address


def test_router_address_rejects_an_endpoint_without_port():
    with pytest.raises(ValueError, match="not a tcp/tls endpoint with a port"):
        router_address("tcp/localhost")
