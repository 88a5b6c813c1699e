"""``drivebench health ROLE``: exit 0 when a process of a running stack is up (compose healthchecks, scripts).

One line on stderr and exit 1 when it is not (``orchestrator.stack.health`` says how each role is checked).
"""

from __future__ import annotations

import argparse
import sys

from orchestrator.cli.errors import EXIT_FAILED, EXIT_OK
from orchestrator.stack.health import ROLES, check_health
from protocol import environment
from protocol.bus import ROUTER_ENV
from protocol.deploy.runtime import RUN_ID_ENV


def add(commands: argparse._SubParsersAction) -> None:
    health = commands.add_parser("health", help="exit 0 when a process of a running stack is up (healthchecks)")
    health.add_argument("role", choices=ROLES, help="which process")
    health.add_argument(
        "--name",
        help="its name on the bus, or the brain it runs (my_pkg.brain:MyBrain is MyBrain on "
        "the bus; default: any process of that role)",
    )
    health.add_argument("--run", help=f"run id (default: ${RUN_ID_ENV})")
    health.add_argument("--router", metavar="ENDPOINT", help=f"the router (default: ${ROUTER_ENV})")
    health.set_defaults(func=run_health_command)


def run_health_command(args: argparse.Namespace) -> int:
    endpoint = args.router or environment.ROUTER.value() or "tcp/127.0.0.1:7447"
    run_id = args.run or environment.RUN_ID.value() or "default"
    problem = check_health(args.role, endpoint=endpoint, run_id=run_id, name=args.name)
    if problem is not None:
        print(f"drivebench health: {problem}", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK
