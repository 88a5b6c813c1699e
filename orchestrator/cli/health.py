"""``drivebench health ROLE``: exit 0 when a process of a running stack is up (compose healthchecks, scripts).

One line on stderr and exit 1 when it is not (``orchestrator.stack.health`` says how each role is checked).
"""

from __future__ import annotations

import argparse

from orchestrator.stack.health import add_arguments, check_health_args


def add(commands: argparse._SubParsersAction) -> None:
    health = commands.add_parser("health", help="exit 0 when a process of a running stack is up (healthchecks)")
    add_arguments(health)
    health.set_defaults(func=check_health_args)
