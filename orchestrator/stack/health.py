"""Is this process of a running stack up? (compose healthchecks, scripts).

The router is healthy when its TCP port accepts connections; a role served over HTTP (the challenge server) when
``--url`` answers 200; any other role when its liveliness token is on the bus
(``drivebench/alive/<run>/<role>/<name>``), which it declares only once it is ready to serve. Exit code 0 when
healthy, 1 otherwise, with one line saying why.

Compose runs it as ``python -m orchestrator.stack.health ROLE`` rather than ``drivebench health ROLE``: the full CLI
imports every subcommand (about three times the CPU), and during start-up seven services are checked each second.
"""

from __future__ import annotations

import argparse
import sys
import urllib.error
import urllib.request

from protocol import environment, keys
from protocol.bus import ROUTER_ENV, Bus, BusConfig, BusError, probe_router
from protocol.deploy import graph
from protocol.deploy.runtime import RUN_ID_ENV

ROLES = graph.health_roles()  # "driver": the orchestrator driving an episode
CONNECT_TIMEOUT_S = 2.0
HTTP_TIMEOUT_S = 5.0
HTTP_ROLES = tuple(row.name for row in graph.ROLES if row.http_health)


def check_http(url: str) -> str | None:
    """None when ``url`` answers 200 within :data:`HTTP_TIMEOUT_S`, else why not (one line)."""
    direct = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # a proxy of the environment would answer
    try:
        with direct.open(url, timeout=HTTP_TIMEOUT_S) as response:
            status = response.status
    except urllib.error.HTTPError as error:
        status = error.code
    except (urllib.error.URLError, OSError) as error:
        return f"{url}: {getattr(error, 'reason', error)}"
    return None if status == 200 else f"{url} answered {status}"


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
    return (
        f"no {role}{f' {name!r}' if name else ''} alive on run {run_id!r} (alive: "
        f"{', '.join(f'{r}/{n}' for _, r, n in alive) or 'nothing'})"
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The arguments of ``drivebench health`` and of ``python -m orchestrator.stack.health``."""
    parser.add_argument("role", choices=ROLES, help="which process")
    parser.add_argument(
        "--name",
        help="its name on the bus, or the brain it runs (my_pkg.brain:MyBrain is MyBrain on "
        "the bus; default: any process of that role)",
    )
    parser.add_argument("--run", help=f"run id (default: ${RUN_ID_ENV})")
    parser.add_argument("--router", metavar="ENDPOINT", help=f"the router (default: ${ROUTER_ENV})")
    parser.add_argument("--url", help=f"the address a role served over HTTP answers on ({', '.join(HTTP_ROLES)})")


def check_health_args(args: argparse.Namespace) -> int:
    """Exit code 0 when healthy; else 1, with one line on stderr (exit code 2: ``--url`` missing or misplaced)."""
    if (args.role in HTTP_ROLES) != (args.url is not None):
        print(f"drivebench health: --url goes with {' or '.join(HTTP_ROLES)}, and only with it", file=sys.stderr)
        return 2
    if args.url is not None:
        return _report(check_http(args.url))
    endpoint = args.router or environment.ROUTER.value() or "tcp/127.0.0.1:7447"
    run_id = args.run or environment.RUN_ID.value() or "default"
    return _report(check_health(args.role, endpoint=endpoint, run_id=run_id, name=args.name))


def _report(problem: str | None) -> int:
    if problem is not None:
        print(f"drivebench health: {problem}", file=sys.stderr)
        return 1
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``python -m orchestrator.stack.health`` (compose's healthchecks)."""
    parser = argparse.ArgumentParser(prog="drivebench health", description="exit 0 when a process of a stack is up")
    add_arguments(parser)
    return parser


if __name__ == "__main__":
    sys.exit(check_health_args(build_parser().parse_args()))
