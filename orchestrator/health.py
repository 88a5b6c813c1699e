"""``drivebench health ROLE``: is this process of a running stack up? (compose healthchecks, scripts).

The router is healthy when its TCP port accepts connections; any other role when its liveliness token is on the
bus (``drivebench/alive/<run>/<role>/<name>``), which it declares only once it is ready to serve. Exit code 0 when
healthy, 1 otherwise, with one line saying why.
"""

from __future__ import annotations

import argparse
import os
import sys

from protocol import graph, keys
from protocol.bus import ROUTER_ENV, Bus, BusConfig, BusError, probe_router
from protocol.runtime import RUN_ID_ENV

ROLES = graph.health_roles()  # "driver": the orchestrator driving an episode
CONNECT_TIMEOUT_S = 2.0


def add_health_command(commands: argparse._SubParsersAction) -> None:
    health = commands.add_parser("health", help="exit 0 when a process of a running stack is up (healthchecks)")
    health.add_argument("role", choices=ROLES, help="which process")
    health.add_argument("--name", help="its name on the bus, or the brain it runs (my_pkg.brain:MyBrain is MyBrain on "
                                       "the bus; default: any process of that role)")
    health.add_argument("--run", help=f"run id (default: ${RUN_ID_ENV})")
    health.add_argument("--router", metavar="ENDPOINT", help=f"the router (default: ${ROUTER_ENV})")


def check_health(role: str, *, endpoint: str, run_id: str, name: str | None = None) -> str | None:
    """None when healthy, else why not (one line)."""
    try:
        probe_router(endpoint.split(",")[0], timeout_s=CONNECT_TIMEOUT_S)
    except BusError as error:
        return str(error)
    if role == "router":
        return None
    try:
        with Bus(BusConfig(mode="client", connect=endpoint.split(",")), name=f"health-{role}") as bus:
            alive = [keys.parse_alive(key) for key in bus.alive_now(keys.alive_all(run_id))]
    except BusError as error:
        return str(error)
    names = sorted(n for _, r, n in alive if r == role)
    if name is not None and role == "brain":
        from brains.registry import bus_name

        name = bus_name(name)  # compose passes the BRAIN it started, which may be a module path or a file
    if (name is None and names) or name in names:
        return None
    return f"no {role}{f' {name!r}' if name else ''} alive on run {run_id!r} (alive: " \
           f"{', '.join(f'{r}/{n}' for _, r, n in alive) or 'nothing'})"


def run_health_command(args: argparse.Namespace) -> int:
    endpoint = args.router or os.environ.get(ROUTER_ENV, "tcp/127.0.0.1:7447")
    run_id = args.run or os.environ.get(RUN_ID_ENV, "default")
    problem = check_health(args.role, endpoint=endpoint, run_id=run_id, name=args.name)
    if problem is not None:
        print(f"drivebench health: {problem}", file=sys.stderr)
        return 1
    return 0
