"""The process graph as data: every process role of a stack, one row each.

A row says what a role runs (module), how it joins the bus, which keys it publishes, subscribes to, serves and
queries, the liveliness token it declares when ready, the identity it has in a secure stack, and the compose
service(s) that run it. Everything that used to spell the graph out by hand reads this table instead:

* ``orchestrator.stack.launcher`` starts a local stack's services from it;
* ``protocol.deploy.security`` derives the router's access rules from it (a role may put only what it publishes,
  serve only what it serves, query only what it queries, declare only its own token);
* ``orchestrator.compose_files`` generates ``compose.yaml``, ``compose.secure.yaml`` and ``deploy/secure/router.yaml``
  from it, and the process table of docs/architecture.md (tests fail when the committed files differ);
* ``drivebench health ROLE`` takes its roles from it.

Adding a process role is one row here (then ``python -m orchestrator.compose_files --write``).

Key templates are made by the ``protocol.keys`` functions with the placeholders :data:`RUN` and :data:`NAME`;
:func:`wildcard` turns one into a key expression (each placeholder chunk becomes ``*``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from protocol import keys

RUN, NAME = "__run__", "__name__"  # placeholders in key templates: the run id, a process's own name


def wildcard(template: str) -> str:
    """The key expression of a key template: each placeholder chunk becomes ``*``."""
    return "/".join("*" if chunk in (RUN, NAME) else chunk for chunk in template.split("/"))


@dataclass(frozen=True, kw_only=True)
class ComposeService:
    """One compose service that runs a role. ``command`` may use compose's ``${VAR:-default}`` interpolation."""

    name: str
    command: tuple[str, ...]
    comment: str = ""  # lines written above the service in compose.yaml
    profiles: tuple[str, ...] = ()
    healthcheck: tuple[str, ...] | None = None  # arguments after ``drivebench health``; None: no healthcheck
    depends_on: dict[str, str] = field(default_factory=lambda: {"router": "service_healthy"})
    extra: dict[str, Any] = field(default_factory=dict)  # further compose keys, written as they are
    secure: bool = True  # compose.secure.yaml gives it its role's certificate (False: it runs its own local stacks)
    secure_command: tuple[str, ...] = ()  # its command in compose.secure.yaml, where that differs


@dataclass(frozen=True, kw_only=True)
class Role:
    """One process role of the graph."""

    name: str  # the role in access rules and in ``drivebench health``
    summary: str  # what it is, for the process table of docs/architecture.md
    module: str  # ``python -m MODULE`` runs it ("" for a role only ``drivebench`` subcommands play)
    source: str  # where its code lives, for that table
    consumes: str  # what it takes, in words, for that table
    produces: str  # what it gives, in words, for that table
    alive_as: str = ""  # the role in its liveliness token (default: ``name``); "" with ``token=None``: none
    token: str | None = ""  # the name in its liveliness token: fixed ("sim") or "" for its own ``--name``
    publishes: tuple[str, ...] = ()
    subscribes: tuple[str, ...] = ()
    serves: tuple[str, ...] = ()  # queryables it declares (and answers)
    queries: tuple[str, ...] = ()  # queryables of others it may ask, beyond every role's status query
    claims: tuple[str, ...] = ()  # liveliness tokens it may declare besides its own (a swap's brain-name claims)
    bus_mode: str = "peer"  # how a local stack's instance joins: peer (the driving loop) or client (observers)
    identity: str = ""  # the certificate common name of its process in a secure stack ("": no certificate)
    group: str = ""  # a group role of the access rules that has every grant of its members ("service")
    local_stack: bool = False  # a local stack (``drivebench run``, each matrix episode) always starts it
    http_health: bool = False  # healthy when its HTTP server answers (``drivebench health ROLE --url URL``)
    on_bus: bool = True  # False: it never joins a stack's bus itself, so it has no access-control role
    compose: tuple[ComposeService, ...] = ()

    @property
    def token_role(self) -> str:
        return self.alive_as or self.name

    def token_key(self, run_id: str, name: str = "") -> str:
        """The liveliness key this role's process declares once ready."""
        return keys.alive(run_id, self.token_role, self.token or name)


_HEALTH = ("health",)

ROLES: tuple[Role, ...] = (
    Role(
        name="router",
        summary="router",
        module="services.router",
        source="`services/router`",
        consumes="–",
        produces="a Zenoh router (discovery; peers exchange data directly)",
        token=None,
        bus_mode="router",
        identity="router",
        compose=(
            ComposeService(
                name="router",
                comment="Loopback unless asked: anyone who reaches the router may start episodes and publish commands. "
                "For several\nmachines set DRIVEBENCH_LISTEN=tcp/[::]:7447 on the router's host, and prefer "
                "compose.secure.yaml (TLS).",
                command=("python", "-m", "services.router", "--listen", "${DRIVEBENCH_LISTEN:-tcp/127.0.0.1:7447}"),
                healthcheck=("router",),
                depends_on={},
                secure_command=(
                    "python",
                    "-m",
                    "services.router",
                    "--config",
                    "deploy/secure/router.yaml",
                    "--listen",
                    "tls/[::]:7447",
                ),
            ),
        ),
    ),
    Role(
        name="simulator",
        summary="simulator",
        module="services.simulator",
        source="`services/simulator`",
        consumes="run control (queryable), the active brain's commands",
        produces="camera frames, ground-truth poses, episode events (and the brains' copy, without the conditions)",
        token="sim",
        publishes=(keys.camera_raw(RUN), keys.pose(RUN), keys.events(RUN), keys.brain_events(RUN)),
        subscribes=(keys.commands_all(RUN),),
        serves=(keys.sim_control(RUN), keys.sim_status(RUN)),
        identity="sim",
        group="service",
        local_stack=True,
        compose=(
            ComposeService(
                name="simulator", command=("python", "-m", "services.simulator"), healthcheck=("simulator",)
            ),
        ),
    ),
    Role(
        name="noise",
        summary="noise injector",
        module="services.noise",
        source="`services/noise`",
        consumes="ground-truth camera frames",
        produces="perturbed frames (seeded per episode; identity forwards bytes)",
        token="noise",
        publishes=(keys.camera_perturbed(RUN),),
        subscribes=(keys.camera_raw(RUN),),
        identity="noise",
        group="service",
        local_stack=True,
        compose=(ComposeService(name="noise", command=("python", "-m", "services.noise"), healthcheck=("noise",)),),
    ),
    Role(
        name="brain",
        summary="brain host",
        module="brains",
        source="`brains/` (`python -m brains --brain NAME`)",
        consumes="camera frames: the noise injector's, or the simulator's in an episode without noise",
        produces="commands stamped with the frame they answer",
        publishes=(keys.command(RUN, NAME),),
        subscribes=(keys.camera_perturbed(RUN), keys.camera_raw(RUN), keys.brain_events(RUN), keys.pose(RUN)),
        serves=(keys.brain_control(RUN, NAME),),
        identity="brain",
        compose=(
            ComposeService(
                name="brain",
                comment="BRAIN: any brain name (built-in, installed entry point, package.module:Class, or a Behavior "
                "Metrics brain file\nsuch as /results/brain_f1.py: whatever is under ./results is seen as "
                "/results); neural ones take BRAIN_WEIGHTS\n(a checkpoint under ./results, seen as "
                "/results/...) or, without it, the weights drivebench ships.",
                command=("python", "-m", "brains", "--brain", "${BRAIN:-explicit}", "--weights", "${BRAIN_WEIGHTS:-}"),
                healthcheck=("brain", "--name", "${BRAIN:-explicit}"),
            ),
            ComposeService(
                name="brain-gpu",
                profiles=("gpu",),
                command=(
                    "python",
                    "-m",
                    "brains",
                    "--brain",
                    "${GPU_BRAIN:-deepest_lstm_tiny_pilotnet}",
                    "--weights",
                    "${GPU_WEIGHTS:-}",
                    "--set",
                    "options.backend=torch",
                    "--set",
                    "options.device=cuda",
                ),
                healthcheck=("brain", "--name", "${GPU_BRAIN:-deepest_lstm_tiny_pilotnet}"),
                extra={
                    "deploy": {
                        "resources": {
                            "reservations": {"devices": [{"driver": "nvidia", "count": 1, "capabilities": ["gpu"]}]}
                        }
                    }
                },
            ),
        ),
    ),
    Role(
        name="scorer",
        summary="metric scorer",
        module="services.scorer",
        source="`services/scorer`",
        consumes="poses, commands, episode events",
        produces="live metrics, one final score per episode",
        token="scorer",
        publishes=(keys.live_metrics(RUN), keys.score(RUN)),
        subscribes=(keys.pose(RUN), keys.commands_all(RUN), keys.events(RUN)),
        bus_mode="client",
        identity="scorer",
        group="service",
        local_stack=True,
        compose=(ComposeService(name="scorer", command=("python", "-m", "services.scorer"), healthcheck=("scorer",)),),
    ),
    Role(
        name="orchestrator",
        summary="launcher / orchestrator",
        module="",
        source="`orchestrator/` (`drivebench run`, `matrix`, `swap`)",
        consumes="liveliness, live metrics, scores, poses",
        produces="run control (as the episode's driver: a liveliness token the simulator watches), run folder, "
        "failure records, matrix results and reports",
        alive_as="driver",
        queries=(keys.sim_control(RUN), keys.brain_control(RUN, NAME), keys.recorder_control(RUN)),
        claims=(keys.name_claims(RUN),),
        subscribes=(keys.live_metrics(RUN), keys.score(RUN)),
        identity="orchestrator",
        compose=(
            ComposeService(
                name="run",
                comment="Drives one episode on the services above, writes "
                "./results/runs/<time>-<run>/{config.yaml,score.json} and exits.",
                command=(
                    "drivebench",
                    "run",
                    "--attach",
                    "--runs-dir",
                    "/results/runs",
                    "--circuit",
                    "${CIRCUIT:-simple}",
                    "--direction",
                    "${DIRECTION:-forward}",
                    "--laps",
                    "${LAPS:-1}",
                    "--max-sim-seconds",
                    "${MAX_SIM_SECONDS:-300}",
                ),
                depends_on={
                    "simulator": "service_healthy",
                    "noise": "service_healthy",
                    "scorer": "service_healthy",
                    "brain": "service_healthy",
                },
                extra={"restart": "no"},
            ),
            ComposeService(
                name="orchestrator",
                profiles=("matrix",),
                comment="Runs a whole test matrix on its own local stacks (its own embedded router) and writes its "
                "tables and report.",
                command=(
                    "drivebench",
                    "matrix",
                    "${MATRIX:-experiments/smoke.yaml}",
                    "-o",
                    "/results/matrix",
                    "--workers",
                    "${WORKERS:-1}",
                    "--resume",
                ),
                depends_on={},
                extra={"restart": "no"},
                secure=False,
            ),
        ),
    ),
    Role(
        name="recorder",
        summary="recorder",
        module="recorder",
        source="`recorder/` (`python -m recorder`)",
        consumes="every key of one run",
        produces="an MCAP file (also: repair, replay, datasets)",
        subscribes=(keys.run_all(RUN),),
        serves=(keys.recorder_control(RUN),),
        token="recorder",
        bus_mode="client",
        identity="recorder",
        group="service",
        compose=(
            ComposeService(
                name="recorder",
                profiles=("record",),
                command=(
                    "python",
                    "-m",
                    "recorder",
                    "--set",
                    "output=/results/recordings/{run_id}-{time}.mcap",
                    "--set",
                    "image_format=${RECORD_IMAGES:-jpeg}",
                ),
                healthcheck=("recorder",),
                extra={"stop_grace_period": "60s"},
                comment="stop_grace_period: finishing a recording (drain, summary, fsync) must not be cut short by "
                "SIGKILL",
            ),
        ),
    ),
    Role(
        name="viz",
        summary="live view",
        module="services.viz",
        source="`services/viz` (`drivebench view`)",
        consumes="every key of one run",
        produces="Foxglove WebSocket channels (JPEG camera, pose, track, commands, metrics)",
        subscribes=(keys.run_all(RUN),),
        token="viz",
        bus_mode="client",
        identity="viz",
        group="service",
        compose=(
            ComposeService(
                name="viz",
                profiles=("viz",),
                command=(
                    "python",
                    "-m",
                    "services.viz",
                    "--set",
                    "host=${VIZ_HOST:-0.0.0.0}",
                    "--set",
                    "port=${VIZ_PORT:-8765}",
                ),
                healthcheck=("viz",),
            ),
        ),
    ),
    Role(
        name="ros2_bridge",
        summary="ROS 2 bridge",
        module="services.ros2_bridge",
        source="`services/ros2_bridge` (`drivebench run --ros2`)",
        consumes="camera frames, poses, commands, episode events, live metrics, scores",
        produces="the same as ROS 2 messages on rmw_zenoh's keys, with its node's liveliness tokens",
        subscribes=(
            keys.camera_raw(RUN),
            keys.pose(RUN),
            keys.commands_all(RUN),
            keys.events(RUN),
            keys.live_metrics(RUN),
            keys.score(RUN),
        ),
        token="ros2_bridge",
        bus_mode="client",
        compose=(
            ComposeService(
                name="ros2-bridge",
                profiles=("ros2",),
                comment="ROS 2 tools (RMW_IMPLEMENTATION=rmw_zenoh_cpp) on this router see the run: "
                "docs/guides/ros2.md.\nIts keys are ROS 2's, outside drivebench's access rules: not in "
                "compose.secure.yaml.",
                command=(
                    "python",
                    "-m",
                    "services.ros2_bridge",
                    "--set",
                    "domain_id=${ROS_DOMAIN_ID:-0}",
                ),
                healthcheck=("ros2_bridge",),
                secure=False,
            ),
        ),
    ),
    Role(
        name="board",
        summary="challenge server",
        module="",
        source="`orchestrator/board/` (`drivebench board serve`)",
        consumes="uploaded brains (HTTP)",
        produces="a leaderboard page and API; each submission's evaluation on local stacks of its own, its brains in "
        "bubblewrap",
        token=None,
        http_health=True,
        on_bus=False,  # each evaluation starts local stacks of its own, with their own routers
        compose=(
            ComposeService(
                name="board",
                profiles=("board",),
                comment=(
                    "The challenge server (docs/guides/challenge.md): its state in ./results/board "
                    "(keep it private: it holds the\nsecret seed). "
                    "Loopback unless asked (BOARD_HOST=0.0.0.0). "
                    "Each evaluation runs its own local stack; every\n"
                    "submitted brain runs in bubblewrap, which needs namespaces that Docker's defaults refuse: "
                    "security_opt\nlets them in (what each option grants: docs/guides/deployment.md)."
                ),
                command=(
                    "drivebench",
                    "board",
                    "serve",
                    "--data",
                    "/results/board",
                    "--host",
                    "${BOARD_HOST:-127.0.0.1}",
                    "--port",
                    "${BOARD_PORT:-8000}",
                    "--conditions",
                    "${BOARD_CONDITIONS:-}",
                    "--workers",
                    "${BOARD_WORKERS:-1}",
                ),
                depends_on={},
                healthcheck=("board", "--url", "http://${BOARD_HOST:-127.0.0.1}:${BOARD_PORT:-8000}/api/leaderboard"),
                extra={
                    "security_opt": [
                        "no-new-privileges:true",
                        "seccomp=deploy/board/seccomp.json",
                        "systempaths=unconfined",
                    ],
                    "stop_grace_period": "60s",
                },
                secure=False,
            ),
        ),
    ),
    Role(
        name="replay",
        summary="replay of a recording",
        module="",
        source="`recorder/` (`drivebench recorder replay`)",
        consumes="an MCAP file",
        produces="every key of the recorded run, on the bus again (commands included)",
        token=None,
        publishes=(keys.run_all(RUN),),
        identity="",
    ),
)

# Identities that play no process role: a read-only viewer (what every identity may do, and nothing more).
OBSERVER_IDENTITY = "viewer"


def role(name: str) -> Role:
    """The row of one role (KeyError names the known ones)."""
    for row in ROLES:
        if row.name == name:
            return row
    raise KeyError(f"no process role {name!r} (known: {', '.join(r.name for r in ROLES)})")


def local_stack_roles() -> tuple[Role, ...]:
    """The services every local stack starts (brains and the optional recorder come from the caller)."""
    return tuple(row for row in ROLES if row.local_stack)


def health_roles() -> tuple[str, ...]:
    """The roles ``drivebench health`` can check: the router, every role with a liveliness token, and every role
    served over HTTP."""
    return tuple(row.token_role for row in ROLES if row.name == "router" or row.token is not None or row.http_health)


def key_matches(expression: str, key: str) -> bool:
    """Whether a concrete key lies in a key expression of ``*`` (one chunk) and a final ``**`` (the rest)."""
    pattern, chunks = expression.split("/"), key.split("/")
    if pattern and pattern[-1] == "**":
        return len(chunks) >= len(pattern) and key_matches("/".join(pattern[:-1]), "/".join(chunks[: len(pattern) - 1]))
    return len(pattern) == len(chunks) and all(p in ("*", c) for p, c in zip(pattern, chunks))


def publishers_of(key: str) -> tuple[Role, ...]:
    """The roles whose rows say they publish ``key`` (replay, which republishes a whole run, is not counted)."""
    return tuple(
        row
        for row in ROLES
        if row.name != "replay" and any(key_matches(wildcard(template), key) for template in row.publishes)
    )
